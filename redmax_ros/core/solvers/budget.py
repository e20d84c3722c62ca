"""Bounded work per step: the step budget (CPU time of the iterative solvers and QP iteration caps), the
per-step Deadline the iterative solvers check between their iterations, and ProxSuite solves held to it.

A step runs a few iterative solvers: the joint-limit QP of Eq. (5) (ProxSuite, solvers/direct.py, and
its fixed point for the implicit Coriolis term), the Staggered Projections / BISP iterations of Alg. 2/3
(friction/staggered.py: a Python loop with ProxSuite inner solves, or a compiled loop with PGS ones),
the lockstep PCG solves of Eq. (4) and the joint-limit active set (solvers/lockstep_pcg.py). Each has an
iteration cap, but ProxSuite's (10000 outer iterations of up to 1500 inner ones, ~10 us each on the
hand) is far beyond a real-time step: an input whose scale puts the QP's absolute tolerance below
round-off (a prescribed velocity of 1e12 rad/s, a torque of 1e12 N m) ran for 2-124 s, and the
walker's compiled loop at its caps (50 iterations of two 500-sweep PGS solves) takes ~50 ms of CPU.
With a :class:`StepBudget` every ProxSuite solve is capped (``qp_max_iter`` outer iterations in slices,
``qp_max_iter_in`` inner ones per outer iteration) and the time of the step's iterative solvers is
checked between iterations (QP slices, loop iterations, pieces of the compiled loop); past either the
step raises StepError("step budget exceeded: ...") and, as every StepError, leaves the state as it was.
Inputs whose step must diverge are rejected before any solve (step/state.py), so the budget is the
backstop for what gets past those tests.

The clock: the CPU time of the stepping thread (time.thread_time) from the start of the step's first
iterative solver, minus the time numba spends meanwhile in its compiler lock (compiling or loading cached
kernels: 0.1-2 s in the first step of a process or of a new code path, which is not the step's work) and
minus the time the thread spends in Python's cyclic garbage collector (a full collection traverses every
object of the process, whoever made them: up to 264 ms measured in a pytest process of test/core, 4446
collections; the walker's first step under CI failed its 50 ms budget "after 1 iterations / 238.5 ms").
CPU time, not wall time, so that a loaded machine does not fail normal steps (measured here, load average
10 on 2 cores: a 5-10 ms umbrella PCG step took 10-120 ms of wall time, and a first step 3.7 s of wall time
for 0.3 s of CPU); the non-iterative stages before the first solver (kinematics, assembly, factorisations)
cost a fixed amount for a given mechanism (hand: ~0.1 ms) and are not counted. The fast path of a check is
one time.perf_counter comparison (a thread's CPU time never exceeds the wall time); thread_time (1.5-3 us
here) is read once when the first solver starts and again only when the wall clock has passed the limit.
Only the iterative solvers check (between iterations or QP slices), so a step that has finished its work is
never failed for its time.

The caps are far above what the solvers use on normal steps (over the 218,000 steps of test/core: at most
10 outer and 17 inner iterations in one QP, 3 ms of iterative-solver CPU time in one step; the walker's
compiled loop at most ~1e6 work units, half its first piece), so with the default budget the result of
every normal step is bitwise that of an unlimited one. ``budget=None`` (and 0 or None for one field)
means unlimited: ProxSuite's own caps and no clock.
"""
from __future__ import annotations

import gc
import math
import numbers
import threading
import time
from dataclasses import dataclass

import proxsuite

from redmax_ros.core.errors import StepError

try:  # numba reports the time it holds its compiler lock (JIT compilation and cache loading)
    from numba.core import event as _numba_event
except ImportError:  # pragma: no cover - numba missing: kernels are plain Python (core/jit.py)
    _numba_event = None

PROXSUITE_MAX_ITER = 10000  # ProxSuite's default outer iterations (used when qp_max_iter is None/0)
QP_SLICE = 25  # outer iterations per ProxSuite call under a budget (normal QPs: <= 10); checked between
_MAX_ITER_REACHED = proxsuite.proxqp.QPSolverOutput.PROXQP_MAX_ITER_REACHED
_CONTINUE = proxsuite.proxqp.InitialGuess.WARM_START_WITH_PREVIOUS_RESULT


class _JitClock:
    """CPU time [s] each thread has spent holding numba's compiler lock (outermost acquisitions only); a
    numba event listener on "numba:compiler_lock" when numba is there."""

    def __init__(self):
        self.total = {}  # thread id -> s
        self._open = {}  # thread id -> (depth, start)

    def on_start(self, event):
        tid = threading.get_ident()
        depth, t0 = self._open.get(tid, (0, 0.0))
        self._open[tid] = (depth + 1, time.thread_time() if depth == 0 else t0)

    def on_end(self, event):
        tid = threading.get_ident()
        depth, t0 = self._open.get(tid, (1, time.thread_time()))
        if depth <= 1:
            self._open.pop(tid, None)
            self.total[tid] = self.total.get(tid, 0.0) + time.thread_time() - t0
        else:
            self._open[tid] = (depth - 1, t0)


if _numba_event is not None:
    class _JitListener(_JitClock, _numba_event.Listener):
        pass

    _JIT = _JitListener()
    _numba_event.register("numba:compiler_lock", _JIT)
else:  # pragma: no cover
    _JIT = _JitClock()


def jit_seconds() -> float:
    """CPU time [s] this thread has spent so far in numba's compiler lock (compiling or loading kernels)."""
    return _JIT.total.get(threading.get_ident(), 0.0)


class _GcClock:
    """CPU time [s] each thread has spent in Python's cyclic garbage collector (a ``gc.callbacks`` entry).
    Collections run while the thread holds numba's compiler lock are left out: that time is already in
    jit_seconds."""

    def __init__(self):
        self.total = {}  # thread id -> s
        self._start = {}  # thread id -> thread_time at the collection's start

    def __call__(self, phase, info):
        tid = threading.get_ident()
        if phase == "start":
            if tid not in _JIT._open:
                self._start[tid] = time.thread_time()
        else:
            t0 = self._start.pop(tid, None)
            if t0 is not None:
                self.total[tid] = self.total.get(tid, 0.0) + time.thread_time() - t0


_GC = _GcClock()
gc.callbacks.append(_GC)


def pause_seconds() -> float:
    """CPU time [s] this thread has spent so far on work that is not any step's: numba's compiler lock
    (jit_seconds) and the garbage collector."""
    tid = threading.get_ident()
    return _JIT.total.get(tid, 0.0) + _GC.total.get(tid, 0.0)


@dataclass(frozen=True)
class StepBudget:
    """The work one step may do; past it the step fails with StepError("step budget exceeded: ...").

    ``cpu_time`` [s]: CPU time of the step's iterative solvers (from the first one's start, JIT compilation
    and garbage collection excluded), checked between their iterations (QP slices, staggered iterations
    with ProxSuite inner solves, PCG iterations, active-set and QP fixed-point iterations). ``qp_max_iter``: ProxSuite outer
    iterations of one QP (run in slices of QP_SLICE); ``qp_max_iter_in``: ProxSuite inner iterations per
    outer one. None or 0 switches a limit off (ProxSuite's own caps: 10000 and 1500)."""

    cpu_time: float | None = 0.05  # s
    qp_max_iter: int | None = 1000
    qp_max_iter_in: int | None = 50

    def __post_init__(self):
        t = self.cpu_time
        if t is not None and not (isinstance(t, (int, float)) and not isinstance(t, bool) and math.isfinite(t)
                                  and t >= 0):
            raise ValueError(f"StepBudget.cpu_time must be a finite number of seconds >= 0 or None, got {t!r}")
        for name in ("qp_max_iter", "qp_max_iter_in"):
            n = getattr(self, name)
            if n is not None and not (isinstance(n, int) and not isinstance(n, bool) and n >= 0):
                raise ValueError(f"StepBudget.{name} must be an integer >= 0 or None, got {n!r}")

    @classmethod
    def from_ms(cls, ms: float | None, **caps) -> "StepBudget | None":
        """The budget of a ``step_budget_ms`` parameter [ms of CPU time]: ``cpu_time = ms / 1000`` s with the
        default QP caps (or ``caps``); None (unlimited) when ``ms`` is None or <= 0; ValueError when it is
        not a finite number (NaN would otherwise read as "unlimited")."""
        if ms is None:
            return None
        if isinstance(ms, bool) or not isinstance(ms, numbers.Real) or not math.isfinite(ms):
            raise ValueError(f"step budget must be a finite number of milliseconds or None, got {ms!r}")
        return cls(cpu_time=float(ms) * 1e-3, **caps) if ms > 0 else None

    def start(self) -> "Deadline":
        """The Deadline of a step starting now (its clock starts with the step's first iterative solver)."""
        return Deadline(self)


class Deadline:
    """A step's budget and its clock; the iterative solvers call :meth:`begin` when they start and
    :meth:`check` between iterations.

    ``limit`` is the perf_counter value past which :meth:`check` reads the thread's CPU time: one
    comparison per check while within the budget."""

    __slots__ = ("budget", "limit", "c0", "j0")

    def __init__(self, budget: StepBudget):
        self.budget = budget
        self.limit = math.inf
        self.c0 = None  # thread CPU time when the first iterative solver started

    def begin(self) -> None:
        """Start the clock (once per step: later calls do nothing); called by every iterative solver."""
        if self.c0 is None:
            self.c0 = time.thread_time()
            self.j0 = pause_seconds()
            if self.budget.cpu_time:
                self.limit = time.perf_counter() + self.budget.cpu_time

    def used(self) -> float:
        """CPU time [s] of the step's iterative solvers so far, JIT compilation and garbage collection
        excluded (0 before they start)."""
        return 0.0 if self.c0 is None else time.thread_time() - self.c0 - (pause_seconds() - self.j0)

    def remaining(self) -> float:
        """Seconds left of the time budget (inf without one)."""
        t = self.budget.cpu_time
        return t - self.used() if t else math.inf

    def iterations_left(self, per_iteration: float, cap: int) -> int:
        """How many more iterations of ``per_iteration`` seconds fit before :attr:`limit`, between 1 and ``cap``
        (``cap`` without a time budget): a solver's next slice between two checks. ``per_iteration`` is the wall
        time of its iterations so far, an upper bound on their CPU time, and the CPU time left is at least the
        wall time to the limit, so a slice at that pace ends within the budget; no clock is read but
        time.perf_counter."""
        if self.limit == math.inf or not per_iteration > 0.0:
            return cap
        return max(1, min(cap, int((self.limit - time.perf_counter()) / per_iteration)))

    def check(self, what: str, iterations: int) -> None:
        """StepError when the step's iterative solvers have used up the time budget (``what``: the solver,
        ``iterations``: its iterations so far); else nothing."""
        now = time.perf_counter()
        if now <= self.limit:
            return
        t = self.budget.cpu_time
        spent = self.used()
        if spent <= t:  # the thread waited (machine load) or compiled meanwhile: not the step's work
            self.limit = now + (t - spent)
            return
        raise self.exceeded(what, iterations, f"{t * 1e3:g} ms", spent)

    def exceeded(self, what: str, iterations: int, budget: str, spent: float | None = None) -> StepError:
        """The budget's StepError: the solver, its iterations, the CPU time spent and the budget."""
        spent = self.used() if spent is None else spent
        return StepError(f"step budget exceeded: {what} after {iterations} iterations / {spent * 1e3:.1f} ms "
                         f"(budget {budget})")


def qp_solve(qp, deadline: Deadline | None, what: str, *guess) -> int:
    """``qp.solve(*guess)`` held to the step's budget; returns the inner iterations of all slices.

    Without a deadline (no budget): one call with the QP's settings, as before. With one: the settings get
    the budget's caps (``max_iter_in`` = qp_max_iter_in, ``max_iter`` = at most QP_SLICE outer iterations
    per call); while ProxSuite stops at the slice's cap the deadline is checked and the solve continues
    from its previous result (next slice sized to the time left), up to qp_max_iter outer iterations in
    all, past which it raises the budget's StepError. A QP that converges within the first slice (every
    normal one) runs exactly as without the budget. ``qp.results.info.status`` is the last slice's."""
    if deadline is None:
        qp.solve(*guess)
        return int(qp.results.info.iter)
    deadline.begin()
    b, s = deadline.budget, qp.settings
    cap = b.qp_max_iter or PROXSUITE_MAX_ITER
    if b.qp_max_iter_in:
        s.max_iter_in = b.qp_max_iter_in
    s.max_iter = min(QP_SLICE, cap)
    qp.solve(*guess)
    info = qp.results.info
    if info.status != _MAX_ITER_REACHED:  # every normal QP: converged in the first slice
        return int(info.iter)
    outer, inner = int(info.iter_ext), int(info.iter)
    while info.status == _MAX_ITER_REACHED:
        if outer >= cap:
            raise deadline.exceeded(what, inner, f"{cap} QP outer iterations")
        deadline.check(what, inner)
        per_outer = deadline.used() / max(outer, 1)  # s per outer iteration (an upper bound: includes earlier solvers)
        left = deadline.remaining()
        fit = QP_SLICE if not math.isfinite(left) else int(left / per_outer) if per_outer > 0 else QP_SLICE
        s.max_iter = max(1, min(QP_SLICE, cap - outer, fit))
        s.initial_guess = _CONTINUE
        qp.solve()
        info = qp.results.info
        outer += int(info.iter_ext)
        inner += int(info.iter)
    return inner
