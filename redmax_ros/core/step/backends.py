"""The stepping backends and the solver selection (``solver: direct | reference | compiled | pcg | auto``,
docs/solvers.md).

A backend owns a Workspace (step/workspace.py) made from the frozen Mechanism and steps with
step.pipeline.step and its velocity stages (the compiled step, step/compiled/backend.CompiledBackend, is one
native call per step with the Pinocchio pipeline as its reference): :class:`DirectBackend` with the Pinocchio stages
(pipeline.pinocchio_velocity, pin.Data), :class:`DataFreeBackend` with the data-free ones
(data_free_stages.data_free_velocity: PCG with Alg. 1, or the dense data-free direct solver), and
:class:`AutoBackend` choosing between them by a cost model after a short PCG probe. ``step(state, cmd,
h, budget=None)``: ``budget`` a solvers/budget.StepBudget bounding the step's work, None for unlimited.
"""
from __future__ import annotations

import numpy as np

from redmax_ros.core.dynamics.tree_kinematics import PIN_DATA_MAX_NV
from redmax_ros.core.errors import SceneError
from redmax_ros.core.scene.spec import SOLVERS
from redmax_ros.core.solvers.lockstep_pcg import DEFAULT_RTOL
from redmax_ros.core.step.compiled.backend import CompiledBackend
from redmax_ros.core.step.compiled.model import unsupported as compiled_unsupported
from redmax_ros.core.step.data_free_stages import data_free_velocity
from redmax_ros.core.step.deformable_stages import DeformableBackend
from redmax_ros.core.step.deformable_stages import build as build_deformables
from redmax_ros.core.step.pipeline import pinocchio_velocity, step
from redmax_ros.core.step.workspace import Workspace


class DirectBackend:
    """The Pinocchio pipeline with its pin.Data (small models only: pin.Data grows as nv^3)."""

    name = "direct"

    def __init__(self, mech):
        self.mech = mech
        self.workspace = Workspace(mech, pin_data=True)

    def step(self, state, cmd, h, budget=None):
        return step(self.mech, self.workspace, state, cmd, h, pinocchio_velocity, budget)

    def at_state(self, q, t):
        self.workspace.at_state(q, t)


class DataFreeBackend:
    """The data-free stages with solver 'pcg' or 'direct' (dense, data-free); no pin.Data."""

    def __init__(self, mech, solver, rtol=DEFAULT_RTOL, max_iter=None):
        if solver not in ("pcg", "direct"):
            raise ValueError(f"solver must be 'pcg' or 'direct', got {solver!r}")
        self.mech, self.solver, self.rtol, self.max_iter = mech, solver, rtol, max_iter
        self.name = solver if solver == "pcg" else "direct (data-free)"
        self.workspace = Workspace(mech, pin_data=False)

    def velocity(self, mech, ws, state, cmd, tau, h):
        """The data-free velocity stages with this backend's solver, tolerance and iteration cap."""
        return data_free_velocity(mech, ws, state, cmd, tau, h, self.solver, self.rtol, self.max_iter)

    def step(self, state, cmd, h, budget=None):
        return step(self.mech, self.workspace, state, cmd, h, self.velocity, budget)

    def at_state(self, q, t):
        self.workspace.at_state(q, t)


# The auto rule (docs/solvers.md). Per-step cost models [s], fitted to redmax_bench scaling on the
# project's 2-core benchmark machine (CPU time, single-threaded BLAS); only their ratio matters.
DENSE_MAX_NV = 4096  # above: no dense solver (its nv x nv matrices: 134 MB each, ~8 s a step at 4096 DOF)
AUTO_DIRECT_NV = 48  # at or below: direct without probing (PCG's fixed per-step Python cost dominates)
AUTO_PROBE_STEPS = 5
PCG_S_PER_STEP = 1.0e-3  # fixed: numpy/Python work of a step (rows, small solves, stabilization)
PCG_S_PER_JOINT_STEP = 1.5e-6  # kinematics, RHS, factorisation, stabilization, energies, per DOF
PCG_S_PER_JOINT_ITER = 1.2e-7  # one LHS product + one P^-1 application, per DOF and iteration
PCG_S_PER_ITER = 3.0e-5  # fixed per-iteration overhead
DENSE_S_PER_STEP = 6.0e-4
DENSE_S_PER_N3 = 2.5e-11  # dense Cholesky (Eigen LLT) + KKT, per nv^3
DENSE_S_PER_N2 = 4.0e-8  # dense assembly per nv^2 (deep chains; less on bushy trees)


def predicted_costs(nv: int, iters_per_step: float) -> tuple:
    """(PCG, direct) predicted seconds per step for nv DOFs and the measured PCG iterations per step
    (summed over the l + 1 solves of Eq. 4)."""
    pcg_t = PCG_S_PER_STEP + PCG_S_PER_JOINT_STEP * nv + iters_per_step * (PCG_S_PER_JOINT_ITER * nv + PCG_S_PER_ITER)
    direct_t = DENSE_S_PER_STEP + PCG_S_PER_JOINT_STEP * nv + DENSE_S_PER_N3 * nv ** 3 + DENSE_S_PER_N2 * nv ** 2
    return pcg_t, direct_t


def check_dense_size(source: str, solver: str, nv: int) -> None:
    """SceneError when ``solver`` (direct, compiled, reference: dense nv x nv matrices) is asked for more than
    DENSE_MAX_NV DOFs; the Simulator calls it before compiling the scene too (from the scene's joint DOFs), so a
    huge chain is refused in milliseconds, not after its model is built."""
    if solver in ("direct", "compiled", "reference") and nv > DENSE_MAX_NV:
        raise SceneError(source, "solver",
                         f"solver '{solver}' factors dense {nv} x {nv} matrices ({8 * nv ** 2 / 2 ** 30:.1f} GiB each, "
                         f"O(nv^3) a step); above {DENSE_MAX_NV} DOFs use solver pcg or auto")


class AutoBackend:
    """``solver: auto``: direct for nv <= AUTO_DIRECT_NV; otherwise PCG for AUTO_PROBE_STEPS steps,
    then PCG if its predicted cost with the measured iterations per step is below the direct
    solver's (dense Cholesky ~ nv^3), else direct (Pinocchio pipeline when nv <= PIN_DATA_MAX_NV,
    data-free dense otherwise). A PCG fallback during the probe chooses direct."""

    def __init__(self, mech, rtol=DEFAULT_RTOL, max_iter=None):
        self.mech = mech
        self.pcg = DataFreeBackend(mech, "pcg", rtol, max_iter)
        self.choice = None
        self.iters = []
        self.impl = self.pcg
        self.reason = ""
        if mech.nv <= AUTO_DIRECT_NV:
            self._choose("direct", f"nv = {mech.nv} <= {AUTO_DIRECT_NV}")

    @property
    def name(self):
        return "auto:" + (self.choice if self.choice else "probing")

    @property
    def workspace(self):
        """The workspace of the backend that steps now (the PCG probe's until the choice is made)."""
        return self.impl.workspace

    def at_state(self, q, t):
        self.pcg.at_state(q, t)
        if self.impl is not self.pcg:
            self.impl.at_state(q, t)

    def _choose(self, what, reason):
        self.reason = reason
        if what == "direct" and self.mech.nv > DENSE_MAX_NV:  # no dense solver at this size: PCG stays
            what, self.reason = "pcg", f"{reason}; nv = {self.mech.nv} > {DENSE_MAX_NV}, no dense solver"
        if what == "pcg":
            self.choice, self.impl = "pcg", self.pcg
            return
        self.choice = "direct"
        self.impl = make_backend(self.mech, "direct")

    def step(self, state, cmd, h, budget=None):
        if self.choice is not None:
            return self.impl.step(state, cmd, h, budget)
        new, res = self.pcg.step(state, cmd, h, budget)
        d = res.diagnostics
        if d.solver != "pcg":
            self._choose("direct", f"PCG fell back during the probe ({d.solver})")
            return new, res
        self.iters.append(d.iterations)
        if len(self.iters) >= AUTO_PROBE_STEPS:
            k = float(np.mean(self.iters))
            tp, td = predicted_costs(self.mech.nv, k)
            self._choose("pcg" if tp < td else "direct",
                         f"{k:.1f} PCG iterations/step: predicted {tp * 1e3:.2f} ms (PCG) vs {td * 1e3:.2f} ms (direct)")
        return new, res


def make_backend(mech, solver: str, rtol: float = DEFAULT_RTOL, max_iter: int | None = None):
    """The stepping backend for ``solver`` (scene.spec.SOLVERS, docs/solvers.md):

    * 'direct' (default): the compiled one-call step (step/compiled/, CompiledBackend) when the scene is within
      its set (compiled.model.unsupported is empty), else 'reference';
    * 'reference': the Pinocchio pipeline when nv <= PIN_DATA_MAX_NV (pin.Data fits), the data-free dense
      solver above;
    * 'compiled': the compiled step, or a SceneError naming what the scene uses that it does not take;
    * 'pcg', 'auto': the data-free PCG path and the rule choosing between it and 'direct'.
    Scenes with deformables (SceneSpec.deformables) step on deformable_stages.DeformableBackend (the Pinocchio
    pipeline with the coupled sparse solve) for 'direct', 'reference' and 'auto'; 'pcg' and 'compiled' are a
    SceneError.
    Scenes with contact or joint friction (Mechanism.friction, Staggered Projections / BISP) take the compiled
    step under 'direct' and 'compiled' where compiled.friction.friction_unsupported is empty. Those it does not
    take, catalogue joints and force elements (Mechanism.extras) and self-collision (Mechanism.collision) need
    the Pinocchio pipeline: 'direct', 'reference' and 'auto' use it at any size, 'pcg' is a SceneError."""
    if mech.scheme == "bdf2" and mech.extras is not None:
        raise SceneError(mech.spec.source, "integrator.scheme",
                         "'bdf2' is not supported with catalogue joints or force elements (spline, exponential and "
                         "Euler-chart joints, timed loads, linear joint constraints: their hooks are BDF1); use scheme: euler")
    if solver == "compiled" and mech.collision is not None:
        raise SceneError(mech.spec.source, "solver", "solver 'compiled' does not support self-collision (collision "
                         "section; the Pinocchio reference pipeline steps it: use direct or reference)")
    deformables = build_deformables(mech)
    if deformables is not None:  # deformables (docs/deformables.md): the Pinocchio pipeline + coupled sparse solve
        if solver in ("direct", "reference", "auto"):
            return DeformableBackend(mech, deformables)
        raise SceneError(mech.spec.source, "solver",
                         f"solver '{solver}' does not support deformables (the coupled sparse solve is on the "
                         "Pinocchio reference pipeline: use direct, reference or auto)")
    check_dense_size(mech.spec.source, solver, mech.nv)
    if solver == "compiled":
        return CompiledBackend(mech)
    if solver == "direct":
        if not compiled_unsupported(mech) and mech.collision is None:
            return CompiledBackend(mech)
        solver = "reference"
    unsupported = [what for what, attr in (("contact or joint friction", "friction"),
                                           ("catalogue joints/force elements", "extras"),
                                           ("self-collision", "collision"))
                   if getattr(mech, attr) is not None]
    if unsupported:
        if solver == "pcg":
            raise SceneError(mech.spec.source, "solver",
                             f"solver 'pcg' does not support {' and '.join(unsupported)} (use direct or auto)")
        if solver in ("reference", "auto"):
            return DirectBackend(mech)
    if mech.coriolis_implicit and (solver != "reference" or mech.nv > PIN_DATA_MAX_NV):
        raise SceneError(mech.spec.source, "integrator.coriolis",
                         f"'implicit' is implemented in the Pinocchio pipeline only (solver 'direct' with at most "
                         f"{PIN_DATA_MAX_NV} DOFs; here solver '{solver}', {mech.nv} DOFs); use coriolis: explicit")
    if solver == "reference":
        return DirectBackend(mech) if mech.nv <= PIN_DATA_MAX_NV else DataFreeBackend(mech, "direct")
    if solver == "pcg":
        return DataFreeBackend(mech, "pcg", rtol, max_iter)
    if solver == "auto":
        return AutoBackend(mech, rtol, max_iter)
    raise SceneError(mech.spec.source, "solver", f"unknown solver '{solver}' ({', '.join(SOLVERS)})")
