"""The compiled stepping backend (``solver: compiled``): one native call per step (kernel.step_n_kernel, a run of one) for every
Mechanism model.unsupported accepts, with the Pinocchio pipeline as the reference beside it.

Per step, Python only checks the inputs (step/state.applied_torques, trajectory prescriptions resolved by
step/trajectory.py), stacks the prescribed velocities, calls the kernel and wraps its outputs in a State and
a StepResult. The Data of each set of prescribed joints and sites is built once and cached. Steps the kernel
hands back (kernel.py: a joint-limit active set that does not settle, a loop projection that needs the full
Newton, a rejected or rank-deficient input) and steps with commands it does not take (body-twist prescriptions, explicit site
forces) are taken by the reference backend, so their outcome (result or StepError) is the reference's;
``handoffs`` counts them by reason.
"""
from __future__ import annotations

import math
import os
import time
from concurrent.futures import ThreadPoolExecutor
from collections import Counter
from dataclasses import dataclass

import numpy as np

from redmax_ros.core.errors import SceneError, StepError
from redmax_ros.core.step import trajectory
from redmax_ros.core.step.compiled.data import (OUT_ITERS, OUT_E_KIN, OUT_E_POT, OUT_E_SPRING, OUT_ORDER, OUT_RESIDUAL, OUT_STAGE,
                                                OUT_VIOL_POS, OUT_VIOL_VEL, build_data)
from redmax_ros.core.friction import staggered
from redmax_ros.core.step.compiled.friction import (N_REP, REP_ACTIVE, REP_CONTACTS, REP_CONVERGED, REP_ITERS,
                                                    REP_PENETRATION, REP_RESIDUAL, REP_STICKING, build_friction)
from redmax_ros.core.step.compiled.kernel import STAGE_NAMES, friction_step_n_kernel, step_n_kernel
from redmax_ros.core.step.compiled.model import build_model, unsupported
from redmax_ros.core.step.pipeline import pinocchio_velocity, step as pipeline_step
from redmax_ros.core.step.scheme import bdf2_point, continues, next_history
from redmax_ros.core.step.state import BatchResult, Diagnostics, Rollout, StepResult, step_each
from redmax_ros.core.step.workspace import Workspace

_NO_V = np.zeros(0)
_NO_S = np.zeros((0, 3))
_NO_REC = np.zeros((0, 0))  # the kernels' ``rec`` when nothing is recorded
RECORD_FIELDS = ("q_new", "v_hyper", "v_new", "effort", "site_force", "out", "lam", "mu")  # kernel.record_step


def record_layout(d, friction_joints=None) -> dict:
    """name -> slice of a run's record row (kernel.record_step: RECORD_FIELDS of the Data ``d``, then, with
    friction (``friction_joints``: the names of the joint normal impulses), the friction report ``rep``
    (N_REP) and those impulses ``jn``); "width" -> the row length."""
    out, j = {}, 0
    sizes = [(n, d[n].size) for n in RECORD_FIELDS]
    if friction_joints is not None:
        sizes += [("rep", N_REP), ("jn", len(friction_joints))]
    for name, size in sizes:
        out[name] = slice(j, j + size)
        j += size
    out["width"] = j
    return out


def _order(out_order: float) -> int:
    """Diagnostics.order from the kernel's d.out[OUT_ORDER]: 2.0 a BDF2 step, else 1 (Eq. 2; the frictional
    kernel, BDF1 only, leaves the entry unset)."""
    return 2 if out_order == 2.0 else 1


@dataclass
class CompiledSolution:
    """The Solution interface (solvers/direct.py) of a compiled step: hyper-reduced qdot+, multipliers."""
    v: np.ndarray
    lam: np.ndarray
    mu: np.ndarray
    residual: float  # relative KKT residual |A v - b + G^T lam| / |b|
    iterations: int = 1
    solver: str = "compiled"


class CompiledBackend:
    name = "compiled"

    def __init__(self, mech):
        why = unsupported(mech)
        if why:
            raise SceneError(mech.spec.source, "solver",
                             f"solver 'compiled' does not support {', '.join(why)} (use direct or auto)")
        self.mech = mech
        self.workspace = Workspace(mech, pin_data=True)  # the reference's (queries, energies, hand-offs)
        self.model = build_model(mech)
        self.bdf2 = mech.scheme == "bdf2"  # integrator.scheme: the kernel keeps BDF2's history (step/scheme.py)
        self._data = {}
        self._free = None  # _free_inputs: the Data of a step without prescriptions
        self._no_q, self._no_v = mech.q0.copy(), np.zeros(mech.ndof)  # BDF1's history placeholders (never read)
        self._layouts = {}
        self.handoffs = Counter()
        fm = mech.friction  # contact / joint friction: the staggered solve in the kernel (friction.py)
        self.friction = None if fm is None else build_friction(mech)
        if fm is not None:
            self._cache_new = np.zeros(fm.n_slots)
            self._jn = np.zeros(len(fm.fj_names))
            self._rep = np.zeros(N_REP)
            self._no_cache = np.zeros(fm.n_slots)

    def at_state(self, q, t):
        self.workspace.at_state(q, t)

    def reference_step(self, state, cmd, h, budget=None):
        """The Pinocchio pipeline's step (step/pipeline.py) on this backend's workspace."""
        return pipeline_step(self.mech, self.workspace, state, cmd, h, pinocchio_velocity, budget)

    def _data_for(self, cmd):
        axes = cmd.site_axes
        key = (tuple(cmd.joint_velocities), tuple(cmd.site_velocities),
               tuple(None if axes.get(n) is None else np.asarray(axes[n]).tobytes() for n in cmd.site_velocities)
               if axes else None)
        d = self._data.get(key)
        if d is None:
            d = self._data[key] = build_data(self.mech, self.model, tuple(cmd.joint_velocities),
                                             tuple(cmd.site_velocities), axes, self.workspace.T)
        return d

    def _inputs(self, state, cmd, h):
        """(resolved commands, tau, Data, gj, sv) of a step the kernel can take, or None (the reference's)."""
        if not (cmd.joint_velocities or cmd.site_velocities or cmd.joint_trajectories or cmd.body_twists
                or cmd.site_forces) and h > 0 and math.isfinite(h):
            return self._free_inputs(cmd)  # nothing prescribed: the same Data every step
        if cmd.body_twists or cmd.site_forces:
            self.handoffs["body twists or site forces commanded"] += 1
            return None
        if self.friction is not None and cmd.site_velocities:  # their lambda in the joint reactions (bisp.py)
            self.handoffs["prescribed sites with contact or joint friction"] += 1
            return None
        if not (h > 0 and math.isfinite(h)):
            return None  # applied_torques names it
        q_base = None
        if cmd.joint_trajectories and self._history(state, h):  # BDF2: trajectories aim from q^ (step/scheme.py)
            q_base = bdf2_point(self.mech.model, self.workspace.to_reduced, state.q, state.v, state.history, h).q_base
        rcmd = trajectory.resolve(self.mech, state, cmd, h, q_base)
        tau = self.mech.torque0 if rcmd.joint_torques is None else self.mech.torque0 + rcmd.joint_torques
        d = self._data_for(rcmd)
        jv, sv = rcmd.joint_velocities, rcmd.site_velocities
        gj = _NO_V if not jv else np.concatenate([np.atleast_1d(np.asarray(x, float)) for x in jv.values()])
        s = _NO_S if not sv else np.array(list(sv.values()), dtype=float).reshape(len(sv), 3)
        return rcmd, np.asarray(tau, dtype=float), d, gj, s

    def _free_inputs(self, cmd):
        """_inputs without prescriptions: the Data of no prescriptions (built once), no rows, and the torques
        torque0 (+ the commanded joint torques), as _inputs computes them."""
        if self._free is None:
            self._free = self._data_for(cmd)
        jt = cmd.joint_torques
        tau = self.mech.torque0 if jt is None else np.asarray(self.mech.torque0 + jt, dtype=float)
        return cmd, tau, self._free, _NO_V, _NO_S

    def _history(self, state, h) -> bool:
        """Whether the step of h from ``state`` is a BDF2 step (integrator.scheme bdf2 and a history of h)."""
        return self.bdf2 and continues(state.history, h)

    def _history_args(self, state, h):
        """(q_k-1, qdot_k-1, hist) for the kernel: copies of the history and 1 (a BDF2 step), or under BDF1
        placeholders and 0 (the kernel never touches them: the backend's own), or for the bdf2 scheme's start-up
        step copies of the state and 2 (the kernel writes the new history into them)."""
        if self._history(state, h):
            return state.history.q.copy(), state.history.v.copy(), 1
        if not self.bdf2:
            return self._no_q, self._no_v, 0
        return state.q.copy(), state.v.copy(), 2

    def _advanced(self, state, h, q, v, qp, vp, steps=1):
        """The State after the kernel's steps, with BDF2's history (q_k-1, qdot_k-1, h) when the scheme keeps one."""
        return state.advanced(h, q, v, steps=steps, history=next_history(self.mech.scheme, qp, vp, h))

    def _handed_back(self, d):
        self.handoffs[STAGE_NAMES[int(d["out"][OUT_STAGE])]] += 1

    def step(self, state, cmd, h, budget=None):
        t0 = time.perf_counter()
        inp = self._inputs(state, cmd, h)
        if inp is None:
            return self.reference_step(state, cmd, h, budget)
        rcmd, tau, d, gj, sv = inp
        if self.friction is not None:
            return self._friction_step(state, cmd, h, budget, inp, t0)
        qp, vp, hist = self._history_args(state, h)
        q, v = state.q.copy(), state.v.copy()  # a run of one step: the kernel advances them in place
        if not step_n_kernel(*self.model.args, *d.args, q, v, tau, float(h), gj, sv, 1, qp, vp, hist, hist, _NO_REC, 1, 0,
                             1):
            self._handed_back(d)
            return self.reference_step(state, cmd, h, budget)
        if hist == 1 and cmd.joint_trajectories and d["out"][OUT_ORDER] == 1.0:
            # the order control redid the step as BDF1, whose trajectories aim from q_k, not q^ (resolved above)
            self.handoffs["BDF2 step redone as BDF1 with trajectories"] += 1
            return self.reference_step(state, cmd, h, budget)
        new = self._advanced(state, h, q, v, state.q, state.v)
        return new, self._result(new, d, q.copy(), rcmd, t0)

    def _friction_args(self, state, budget):
        """(cache, has_cache, cache_new, jn, rep, work_cap) of friction_step_n_kernel: a copy of the state's
        friction cache (the kernel advances it in place in a run of steps) and the loop's work budget (the
        reference's first piece under a step budget, staggered.KERNEL_FIRST_WORK: past it, the reference takes
        the step with its deadline checks)."""
        fc = state.friction_cache
        has = fc is not None and len(fc) == len(self._no_cache)
        cache = fc.copy() if has else self._no_cache.copy()
        cap = math.inf if budget is None else float(staggered.KERNEL_FIRST_WORK)
        return cache, int(has), self._cache_new, self._jn, self._rep, cap

    def _friction_step(self, state, cmd, h, budget, inp, t0):
        rcmd, tau, d, gj, sv = inp
        cache, has, cache_new, jn, rep, cap = self._friction_args(state, budget)
        q, v = state.q.copy(), state.v.copy()  # a run of one step: the kernel advances them and the cache in place
        if not friction_step_n_kernel(*self.model.args, *d.args, *self.friction.args, q, v, tau, float(h), gj, sv, 1,
                                      cache, has, cache_new, jn, rep, cap, _NO_REC, 1, 0):
            self._handed_back(d)
            return self.reference_step(state, cmd, h, budget)
        new = state.advanced(h, q, v, cache)
        return new, self._result(new, d, q.copy(), rcmd, t0)


    def friction_report(self):
        """The FrictionReport of the kernel's last frictional step (staggered.FrictionReport)."""
        return self._friction_report(self._rep, self._jn)

    def _friction_report(self, r, jn):
        """staggered.FrictionReport from a kernel's report ``r`` (N_REP) and joint normal impulses ``jn``."""
        rep = staggered.FrictionReport(int(r[REP_ITERS]), bool(r[REP_CONVERGED]), float(r[REP_RESIDUAL]), int(r[REP_CONTACTS]),
                             int(r[REP_ACTIVE]), float(r[REP_PENETRATION]), int(r[REP_STICKING]))
        if len(jn):
            rep._jn_names = self.mech.friction.fj_names
            rep._jn_values = jn.copy()
        return rep

    def step_run(self, state, cmd, h, n, budget=None, record=False):
        """Advance by k in [1, n] steps with the same commands: a run of up to n steps in one kernel call
        (kernel.step_n_kernel), or, when the kernel cannot take the next step (or trajectory prescriptions
        change the rows every step), one step by ``step``. Returns (State, last StepResult, k), with ``record``
        (State, the k steps' StepResults, k): the kernel records each step's outputs (kernel.record_step) and
        they are the results single steps give (diagnostics.wall_time: the run's wall time / k). A StepError
        comes only from a single step (the state before it is the input's)."""
        r = self._run(state, cmd, h, n, budget, n if record else 0, 1, 0, 1)
        if r[0] is None:  # one step by ``step``
            _, new, res = r
            return new, [res] if record else res, 1
        new, d, rec, k, rcmd, t0 = r
        if record:
            return new, self._recorded(state, h, d, rec, k, rcmd, time.perf_counter() - t0), k
        return new, self._result(new, d, new.q.copy(), rcmd, t0), k

    def rollout_run(self, state, cmd, h, n, every, phase, budget=None):
        """step_run recording only every ``every``-th step, counted from ``phase`` (< every) steps taken before
        this run: (State, a Rollout of the recorded steps or None, k). The kernel records those steps' outputs
        (and computes BDF2's energies for those steps only, kernel.tail_stages); their numbers are the ones
        step_results gives; the KKT residual, which a Rollout's rows do not carry, only for the run's last step
        (its ``last``)."""
        r = self._run(state, cmd, h, n, budget, (n + phase) // every, every, phase, 0)
        if r[0] is None:
            _, new, res = r
            return new, (Rollout.from_results([res]) if phase + 1 == every else None), 1
        new, d, rec, k, rcmd, t0 = r
        rows = (k + phase) // every
        if not rows:
            return new, None, k
        return new, self._rollout(state, h, d, rec[:rows], every, phase, rcmd, time.perf_counter() - t0, k), k

    def _run(self, state, cmd, h, n, budget, rows, every, phase, residuals):
        """One kernel call of up to n steps recording ``rows`` rows (kernel.record_row: every ``every``-th step
        from ``phase``; with ``residuals`` each with its KKT residual, else only the run's last step has it):
        (State, Data, record, k, resolved commands, start time), or (None, State, StepResult) when ``step`` took
        one step instead."""
        inp = None if cmd.joint_trajectories else self._inputs(state, cmd, h)
        if inp is None:
            return (None, *self.step(state, cmd, h, budget))
        t0 = time.perf_counter()
        rcmd, tau, d, gj, sv = inp
        q, v = state.q.copy(), state.v.copy()
        rec = np.empty((rows, self._layout(d)["width"])) if rows else _NO_REC
        if self.friction is not None:
            cache, has, cache_new, jn, rep, cap = self._friction_args(state, budget)
            k = friction_step_n_kernel(*self.model.args, *d.args, *self.friction.args, q, v, tau, float(h), gj, sv, n,
                                       cache, has, cache_new, jn, rep, cap, rec, every, phase)
            new = state.advanced(h, q, v, cache, steps=k) if k else None
        else:
            qp, vp, hist = self._history_args(state, h)
            k = step_n_kernel(*self.model.args, *d.args, q, v, tau, float(h), gj, sv, n, qp, vp, hist, int(self.bdf2),
                              rec, every, phase, residuals)
            new = self._advanced(state, h, q, v, qp, vp, steps=k) if k else None
        if k == 0:
            self._handed_back(d)
            return (None, *self.reference_step(state, cmd, h, budget))
        return new, d, rec, k, rcmd, t0

    def _layout(self, d) -> dict:
        """record_layout of the Data ``d`` (kept per Data)."""
        lay = self._layouts.get(id(d))
        if lay is None:
            fm = self.mech.friction
            lay = self._layouts[id(d)] = record_layout(d, None if fm is None else fm.fj_names)
        return lay

    def _rollout(self, state, h, d, rec, every, phase, rcmd, wall, k) -> Rollout:
        """The Rollout of the record rows ``rec`` of a run of k steps from ``state`` (row i: step (i + 1) every -
        phase of the run; t = t0 + (k0 + step) h as State.advanced computes it)."""
        lay = self._layout(d)
        steps = np.arange(1, len(rec) + 1, dtype=np.int64) * every - phase
        t0 = state.t if state.t0 is None else state.t0
        O = rec[:, lay["out"]]
        F = rec[:, lay["site_force"]]
        col = np.ascontiguousarray
        last = self._recorded(state, h, d, rec[-1:], 1, rcmd, wall / k, int(steps[-1]))[0]
        return Rollout(t0 + (state.k + steps) * h, col(rec[:, lay["q_new"]]), col(rec[:, lay["v_new"]]),
                       col(rec[:, lay["effort"]]),
                       {name: col(F[:, 3 * j:3 * j + 3]) for j, name in enumerate(rcmd.site_velocities)},
                       col(O[:, OUT_E_KIN]), col(O[:, OUT_E_POT]), col(O[:, OUT_E_SPRING]), col(O[:, OUT_VIOL_POS]),
                       col(O[:, OUT_VIOL_VEL]), O[:, OUT_ITERS].astype(np.int64), ["compiled"] * len(rec), last,
                       order=np.where(O[:, OUT_ORDER] == 2.0, 2, 1).astype(np.int64))

    def _recorded(self, state, h, d, rec, k, rcmd, wall, first=1) -> list:
        """The StepResults of the first k rows of a run's record ``rec`` from ``state`` (the numbers _result
        gives after each of those steps; row i is step first + i of the run, t = t0 + (k0 + first + i) h as
        State.advanced computes it)."""
        lay = self._layout(d)
        Q, H, V, E, F, _, L, M = (rec[:k, lay[n]] for n in RECORD_FIELDS)  # row i of each: step i's views
        O = rec[:k, lay["out"]].tolist()  # Python floats of the outputs, all rows at once
        names = list(rcmd.site_velocities)
        friction = self.friction is not None
        t0 = state.t if state.t0 is None else state.t0
        each = wall / k
        out = []
        for i in range(k):
            o = O[i]
            ek, ep, es = o[OUT_E_KIN], o[OUT_E_POT], o[OUT_E_SPRING]
            sol = CompiledSolution(H[i], L[i], M[i], o[OUT_RESIDUAL])
            diag = Diagnostics(ek, ep, es, ek + ep + es, o[OUT_VIOL_POS], o[OUT_VIOL_VEL], int(o[OUT_ITERS]),
                               "compiled", each, sol,
                               self._friction_report(rec[i, lay["rep"]], rec[i, lay["jn"]]) if friction else None,
                               order=_order(o[OUT_ORDER]))
            site_forces = {name: F[i, 3 * j:3 * j + 3] for j, name in enumerate(names)} if names else {}
            out.append(StepResult(t0 + (state.k + i + first) * h, Q[i], V[i], E[i], site_forces, diag, {}))
        return out

    def step_batch(self, states, cmd, h, n=1, budget=None) -> BatchResult:
        """n steps of each of the B states with the same commands (issue 12, point 4). Each instance runs
        kernel.step_n_kernel on its own Data in a thread pool: the kernel releases the GIL (nogil), so the
        instances run in parallel on the machine's cores, and each result is bitwise the single-instance one
        by construction (the same compiled code; a numba prange version of the loop differed by a few ulps in
        the velocity, its parfor code being compiled differently). Steps the kernel hands back are the
        reference's, one instance at a time; an instance whose step fails keeps its state from before it."""
        B = len(states)
        states = list(states)
        todo = np.full(B, int(n), dtype=np.int64)
        done = np.zeros(B, dtype=np.int64)
        errors = [None] * B
        inp = None if cmd.joint_trajectories or self.friction is not None else self._inputs(states[0], cmd, h)
        if inp is None:  # friction (a cache per instance), trajectories (rows depend on each instance's time) or commands the kernel does not take
            return step_each(self.step, states, cmd, h, n, budget)
        _, tau, d, gj, sv = inp
        DF = np.tile(d.f, (B, 1))  # each instance its own Data: floats and ints (the KKT solve's scratch, kkt_span)
        DI = np.tile(d.i, (B, 1))
        Q = np.array([s.q for s in states], dtype=float)
        V = np.array([s.v for s in states], dtype=float)
        hist_args = [self._history_args(s, h) for s in states]
        QP = np.array([a[0] for a in hist_args], dtype=float)
        VP = np.array([a[1] for a in hist_args], dtype=float)
        HIST = np.array([a[2] for a in hist_args], dtype=np.int64)
        bdf2 = int(self.bdf2)
        total = np.zeros(B, dtype=np.int64)
        stage = d.names.index("out")
        out_off = int(d.tab[stage, 1])
        workers = min(B, os.cpu_count() or 1)

        def run(b):
            return step_n_kernel(*self.model.args, DF[b], DI[b], d.tab, Q[b], V[b], tau, float(h), gj, sv, int(todo[b]),
                                 QP[b], VP[b], int(HIST[b]), bdf2, _NO_REC, 1, 0, 1)

        while todo.any():
            live = [int(b) for b in np.flatnonzero(todo)]
            if workers > 1 and len(live) > 1:
                with ThreadPoolExecutor(max_workers=workers) as ex:
                    done[live] = list(ex.map(run, live))
            else:
                done[live] = [run(b) for b in live]
            for b in np.flatnonzero(todo):
                if done[b]:
                    states[b] = self._advanced(states[b], h, Q[b].copy(), V[b].copy(), QP[b].copy(), VP[b].copy(),
                                               steps=int(done[b]))
                    HIST[b] = bdf2
                    total[b] += done[b]
                    todo[b] -= done[b]
                if not todo[b]:
                    continue
                self.handoffs[STAGE_NAMES[int(DF[b, out_off + OUT_STAGE])]] += 1
                try:
                    states[b], _ = self.reference_step(states[b], cmd, h, budget)
                    total[b] += 1
                    todo[b] -= 1
                    Q[b], V[b] = states[b].q, states[b].v
                    QP[b], VP[b], HIST[b] = self._history_args(states[b], h)
                except StepError as e:
                    errors[b] = e.reason
                    todo[b] = 0
        return BatchResult(states, total, errors)

    def _result(self, new, d, q_new, rcmd, t0):
        views = d.views
        o = views["out"].tolist()
        sv = rcmd.site_velocities
        site_forces = {name: views["site_force"][k].copy() for k, name in enumerate(sv)} if sv else {}
        ek, ep, es = o[OUT_E_KIN], o[OUT_E_POT], o[OUT_E_SPRING]
        sol = CompiledSolution(new.v, views["lam"].copy(), views["mu"].copy(), o[OUT_RESIDUAL])
        diag = Diagnostics(ek, ep, es, ek + ep + es, o[OUT_VIOL_POS], o[OUT_VIOL_VEL], int(o[OUT_ITERS]),
                           "compiled", time.perf_counter() - t0, sol,
                           None if self.friction is None else self.friction_report(), order=_order(o[OUT_ORDER]))
        return StepResult(new.t, q_new, views["v_new"].copy(), views["effort"].copy(), site_forces, diag, {})
