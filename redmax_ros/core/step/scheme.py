"""The time-integration scheme of a step: BDF1 (the paper's Eq. 2, the default, ``integrator.scheme: euler``)
or a linearly implicit BDF2 (``integrator.scheme: bdf2``); the derivation is docs/bdf2.md.

BDF2 (Sueda's notes §3.4.2, Eq. 3.76-3.81: u+ = 4/3 u_k - 1/3 u_k-1 + 2/3 h f(u+)) applied to the RedMax
equations of motion, velocity form, with hat h = 2h/3:

    q+ = q^ (+) hat h qdot+,         q^ = q_k (+) 1/3 (q_k (-) q_k-1)                (3.77b)
    M (qdot+ - v^) = hat h f(q+, qdot+),   v^ = 4/3 qdot_k - 1/3 qdot_k-1             (3.77a)

The notes solve (3.80) by Newton iterations; here it is linearly implicit (one solve per step, like Eq. 2):
the forces are linearised about the predicted state v* = 2 qdot_k - qdot_k-1 (v* - qdot+ = O(h^2)) and
q* = q^ (+) hat h v* (so q* - q+ = hat h (v* - qdot+) = O(h^3)): M(q*), the explicit terms and the
constraint rows G(q*) err by O(h^3) per step (an implicit-explicit BDF2 with extrapolated explicit terms,
as Ascher, Ruuth & Wetton 1995's SBDF2). Extrapolating only to O(h^2), q_k (+) (q_k (-) q_k-1), is not
enough with configuration-dependent rows: G(q*) qdot+ = 0 then misses the velocity of the exact solution
by O(h^2) every step (measured on the four-bar: local velocity error O(h^2), global order 1). The elastic
forces act at q^, f(q+) ~ f(q^) - K hat h qdot+ (exact for joint springs, which are linear in q).
So a BDF2 step is the step of Eq. (2) with

    * kinematics, mass matrix, bias forces, Jacobians and constraint rows at (q*, v*), at time t_k+1;
    * step size hat h in the LHS, (M + hat h D + hat h^2 K) qdot+ (the notes' Eq. 3.81 Hessian);
    * RHS M v^ + hat h (f(q*, v*) - nle(q*, v*)), joint springs at q^, and maximal springs linearised about
      q*: f(q+) ~ f(q*) + K' (q* (-) q^) - K hat h qdot+ (dynamics/springs.spring_shift; K' = K, the LHS's
      stiffness, unless a compressed spring's negative transverse stiffness, which the LHS leaves out, is stiff
      at this step, then the exact Jacobian), plus the turn of their lever arms, B (q* (-) q^). Linearising
      about q^ instead, f(q^) - K hat h qdot+, misses 1/2 f'' (hat h qdot+)^2, which for a stiff spring on a
      swinging body is k/l (hat h v)^2 along the spring every step: on the issue-14 slow kick (k = 1e6) that
      was 60-95x the error of the linearisation about q* (docs/bdf2.md, "Stiff maximal springs");
    * q+ = q^ (+) hat h qdot+, joint limits lower <= q^ + hat h qdot+ <= upper, trajectories aiming from q^;
    * required torques -*G^T lam / hat h (the constraint force at t_k+1 of the discrete equation above).

The start-up step (no history: after load, reset or set_state, or when the step size changed) is a BDF1
step (:func:`startup_point`): Eq. (2) linearised, like the BDF2 step, about a predicted point, here the
explicit Euler predictor q* = q_k (+) h qdot_k (v* = v^ = qdot_k, q^ = q_k, step size h). For every term but
the maximal springs that is Eq. (2) with its kinematics, M, bias forces and rows at q* instead of q_k (the
same to O(h)); the springs are linearised about q*, f(q+) ~ f(q*) + K' (q* (-) q_k) - K h qdot+, as in the
BDF2 step, which leaves out 1/2 f'' (h (qdot+ - qdot_k))^2 instead of Eq. (2)'s 1/2 f'' (h qdot+)^2. On the
kicked stiff springs of docs/bdf2.md (k = 1e6, 0.5 m/s) at h = 2e-2, Eq. (2)'s start-up put 0.055 J into the
springs (the chord stretch), which the extrapolating BDF2 steps carried on ringing, with steps rejected by the
order control and a run error of 2.7e-2; from this start-up, 7.9e-5 J and 4.5e-4. One first-order step
contributes O(h^2) to the global error, so the order stays 2 (observed on the four-bar and the slider-crank;
the notes start with SDIRK2, Eq. 3.66-3.75, which measured the same here, at two solves and without an exact
replay of the required torques of its first step). A
velocity that violates the bilateral rows (a loop's v0 given on one joint only) is projected by the first
step in any scheme with an O(h) error (the rows at the step's point, not at t_0): from such a state the
global error is O(h); start from a consistent velocity for second order. The history (q_k-1, qdot_k-1, h)
is part of the State.

Order control (:func:`accepts`). A linearly implicit BDF2 is only as stable as its linearisation is good: the
terms taken at the predicted point (M, bias forces, Jacobians, rows at q*, v*) and the part of the elastic
forces the LHS stiffness misses are, in effect, explicit and extrapolated, and an extrapolated explicit term
makes BDF2 grow on oscillatory modes where BDF1 only loses energy (for f = -K q with a linearised stiffness
alpha K the amplification of the step exceeds 1 for alpha < ~0.8 at omega h > 1, and for alpha = 0 at any
omega h; BDF1 stays below 1 for alpha > 1/2). Where the prediction is poor, so is the linearisation: the step
is accepted as BDF2 only when the predictor-corrector difference (Milne's device, the local-error and
order-selection estimate of variable-order BDF codes: Hairer & Wanner, Solving ODEs II, §III.7; Brenan,
Campbell & Petzold's DASSL) is small against the step's own motion,

    max_i |(q+ (-) q*)_i| <= ORDER_RATIO max_i |(q+ (-) q_k)_i| + ORDER_FLOOR        (radians and metres),

and when the maximal springs' linearisation about q* missed no more than that at q+ either
(dynamics/springs.linearisation_miss: hat h^2 k |l+ - l* - u*.(dx_a - dx_b)| / m, the spring force the linear
step left out as the displacement it causes in one step; a few millimetres of miss across a stiff spring are
tens of newtons, which the joint-coordinate miss does not show: on kicked k = 1e6 springs at h = 0.05 it let
the energy rise to +2338 J, docs/bdf2.md). Else the step is redone from the same state as the BDF1 step of
Eq. (2) itself, linearised at q_k (the history is kept: the next step tries BDF2 again): the fallback is the
paper's step, stable wherever it is. For smooth motion the left side is O(h^3) and the right O(h), so in the asymptotic range
no step falls back and the order stays 2 (measured ratio maxima: chain-5 0.12 at h = 1e-2, 0.0012 at 1e-3;
pendulum 0.006; four-bar and hand only on their first BDF2 step, 0.56 and 0.51). It falls back on violent
transients: 4-11 of 500-1000 steps on mass_springs with corner springs (k = 1e4, 1e6 at h = 1e-2, 5e-3),
which diverged without it, and on most steps of an under-resolved run (chain-3 with 0.1 N m/rad joint
springs at h = 0.1), which also diverged.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

ORDER_RATIO = 0.5  # a BDF2 step is kept while its predictor misses q+ by at most this fraction of the step
ORDER_FLOOR = 1e-12  # [rad, m] ... or by at most this much (a body at rest: both sides at round-off)


@dataclass(frozen=True)
class History:
    """What BDF2 needs of the step before: its start configuration and velocity and its size."""
    q: np.ndarray  # (nq,) q_k-1
    v: np.ndarray  # (ndof,) hyper-reduced qdot_k-1
    h: float  # s, the step from q_k-1 to q_k


@dataclass(frozen=True)
class Bdf2Point:
    """Where a step of the bdf2 scheme is linearised and from where it advances (module docstring): a BDF2 step
    (``order`` 2) or its start-up BDF1 step (``order`` 1, :func:`startup_point`: q^ = q_k, v* = v^ = qdot_k,
    hat h = h)."""
    q_lin: np.ndarray  # (nq,) q* = q^ (+) hat h v*: kinematics, M, nle, Jacobians, rows
    v_lin: np.ndarray  # (ndof,) v* = 2 qdot_k - qdot_k-1, hyper-reduced
    q_base: np.ndarray  # (nq,) q^ = q_k (+) (q_k (-) q_k-1) / 3: q+ = q^ (+) hat h qdot+
    v_mom: np.ndarray  # (nv,) v^ = 4/3 qdot_k - 1/3 qdot_k-1, reduced: RHS M v^
    back: np.ndarray  # (nv,) q* (-) q^ = hat h v*, reduced tangent [rad, m]
    h: float  # s, hat h = 2 h / 3
    order: int = 2  # 2: BDF2, checked by the order control; 1: the start-up step


def continues(history: History | None, h: float) -> bool:
    """Whether a step of h can be a BDF2 step from ``history``: one exists and was made with the same h (else
    the step starts up with BDF1)."""
    return history is not None and history.h == h


def next_history(scheme: str, q, v, h: float) -> History | None:
    """The history a step of h from (q, v) leaves in its State: (q, v, h) under BDF2, None under BDF1."""
    return History(q, v, h) if scheme == "bdf2" else None


def startup_point(model, to_reduced, q, v, h: float) -> Bdf2Point:
    """The point of the start-up BDF1 step of h from (q, v) (module docstring): q* = q (+) h T v, v* = v, q^ = q,
    v^ = T v, hat h = h; ``order`` 1."""
    v_r = to_reduced(v)
    back = h * v_r
    return Bdf2Point(pin.integrate(model, q, back), v, q, v_r, back, h, order=1)


def bdf2_point(model, to_reduced, q, v, history: History | None, h: float) -> Bdf2Point:
    """The Bdf2Point of the step of h from (q, v) with ``history``: BDF2's, or when the step must start up (no
    history, or it was made with another step size) :func:`startup_point`'s. ``model``: the pin.Model of the
    configuration space; ``to_reduced``: hyper-reduced -> reduced velocities (T = J_rR)."""
    if not continues(history, h):
        return startup_point(model, to_reduced, q, v, h)
    hh = 2.0 * h / 3.0
    d = pin.difference(model, history.q, q)  # q_k (-) q_k-1, tangent [rad, m]
    q_base = pin.integrate(model, q, d / 3.0)
    v_lin = 2.0 * v - history.v
    back = hh * to_reduced(v_lin)
    v_mom = to_reduced((4.0 * v - history.v) / 3.0)
    return Bdf2Point(pin.integrate(model, q_base, back), v_lin, q_base, v_mom, back, hh)


def accepts(model, q, q_lin, q_new, spring_miss: float = 0.0) -> bool:
    """Order control (module docstring): whether the BDF2 step from q = q_k that predicted q* = ``q_lin`` and
    reached ``q_new`` is kept; False: redo it as the BDF1 step of Eq. (2). ``spring_miss`` [m]: what the
    linearisation of the stiff maximal springs about q* missed at q_new, as a displacement
    (dynamics/springs.linearisation_miss), held to the same bound."""
    miss = np.abs(pin.difference(model, q_lin, q_new)).max(initial=0.0)
    motion = np.abs(pin.difference(model, q, q_new)).max(initial=0.0)
    bound = ORDER_RATIO * motion + ORDER_FLOOR
    return bool(miss <= bound and spring_miss <= bound)
