"""What a step takes and gives: State (immutable), Commands, Diagnostics, StepResult; the input checks and
the divergence limit shared by every backend (SI units: m, rad, s, N, N m, J)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from redmax_ros.core.errors import StepError

MAX_SPEED = 1e6  # |qdot| above this (rad/s or m/s) is reported as divergence


@dataclass(frozen=True)
class State:
    t: float  # s
    q: np.ndarray  # (nq,) Pinocchio configuration
    v: np.ndarray  # (ndof,) hyper-reduced velocity qdot_R (= qdot_r without couplings)
    friction_cache: np.ndarray | None = None  # warm start of the friction impulses (staggered.py)


@dataclass
class Commands:
    joint_velocities: dict = field(default_factory=dict)  # prescribed joint -> (nv_j,) [rad/s, m/s]
    site_velocities: dict = field(default_factory=dict)  # prescribed site -> (3,) world [m/s]
    site_axes: dict = field(default_factory=dict)  # prescribed site -> (k,3) world directions (default: x, y, z)
    joint_torques: np.ndarray | None = None  # (nv,) explicit applied joint torques [N m, N]
    site_forces: dict = field(default_factory=dict)  # site -> (3,) explicit world force [N]


@dataclass
class Diagnostics:
    E_kin: float  # J
    E_pot: float  # J (gravity)
    E_spring: float  # J (maximal springs + joint springs)
    E_total: float
    violation_pos: float  # max loop-closure residual after the step [m]
    violation_vel: float  # max |G qdot - g| of the bilateral rows
    iterations: int
    solver: str
    wall_time: float  # s
    solution: object = field(default=None, repr=False)
    friction: object = None  # staggered.FrictionReport when the scene has contact or joint friction

    @property
    def residual(self) -> float:
        """Relative KKT residual of the solve (computed on first access)."""
        return 0.0 if self.solution is None else self.solution.residual


@dataclass
class StepResult:
    t: float
    q: np.ndarray  # (nq,)
    v: np.ndarray  # (nv,) reduced velocities
    effort: np.ndarray  # (nv,) applied torque + required torque of prescribed DOFs [N m, N]
    site_forces: dict  # prescribed site -> required force (3,) world frame [N]
    diagnostics: Diagnostics


def _finite(name, x):
    if not np.all(np.isfinite(x)):
        raise StepError(f"non-finite {name}")


def check_inputs(state, tau, cmd):
    """Name the first non-finite input (slow path, only after the cheap check failed)."""
    _finite("configuration q", state.q)
    _finite("velocity", state.v)
    _finite("joint torques", tau)
    for name, v in cmd.joint_velocities.items():
        _finite(f"prescribed velocity of joint '{name}'", v)
    for name, v in cmd.site_velocities.items():
        _finite(f"prescribed velocity of site '{name}'", v)
    for n, f in cmd.site_forces.items():
        _finite(f"force on site '{n}'", f)


def applied_torques(mech, state, cmd, h) -> np.ndarray:
    """tau = constant joint torques + commanded ones (nv,); StepError on a bad step size or a non-finite
    input (named)."""
    if not (h > 0 and math.isfinite(h)):
        raise StepError(f"time step must be positive and finite, got {h}")
    tau = mech.torque0 if cmd.joint_torques is None else mech.torque0 + cmd.joint_torques
    if not math.isfinite(state.q @ state.q + state.v @ state.v + tau @ tau):  # cheap test; names it below
        check_inputs(state, tau, cmd)
    for f in cmd.site_forces.values():
        if not np.all(np.isfinite(f)):
            check_inputs(state, tau, cmd)
    return tau


def check_speed(v) -> None:
    """StepError when max |qdot| exceeds MAX_SPEED (or is not finite): the step diverged."""
    if not v @ v <= MAX_SPEED * MAX_SPEED:  # cheap test (also catches NaN), then the exact one
        vmax = float(np.abs(v).max())
        if not vmax <= MAX_SPEED:
            raise StepError(f"step diverged: max |qdot| = {vmax:.3g} (limit {MAX_SPEED:g})")
