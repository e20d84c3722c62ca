"""``run_tasks``: independent tasks on a local process pool or on Ray, behind one entry point.

    for index, result, attempts in run_tasks(fn, tasks, workers=2):           # this machine
    for index, result, attempts in run_tasks(fn, tasks, ray_address="auto"):  # a Ray cluster

``fn`` is a module-level function (pickled by reference), ``tasks`` a list of picklable arguments; results
come back as tasks finish (any order), each with its index in ``tasks`` and the number of attempts it took.
Results do not depend on the backend or the worker count: every task runs alone in a worker with the same
environment (BLAS single-threaded, as redmax_ros sets on import), and nothing is shared between tasks.

Failures: an exception raised by ``fn`` is returned as a TaskFailure (not retried: it would raise again).
A worker process that dies (killed, segfault, ``os._exit``) fails only the task it was running: that task is
run again once on a fresh worker (``retries``), then returned as a TaskFailure("worker died ...").

Local backend: ``workers`` processes ``python -m redmax_ros.sweep.worker`` (redmax_ros/sweep/worker.py) with
this process's sys.path, each importing ``preload`` (by default the sweep's run module and with it the core)
once, then running one task at a time: the task goes in on its stdin, the result comes back on its stdout
(pickled frames); EOF on a worker's stdout while it holds a task means it died. No multiprocessing start
method is involved, so the caller's main module is never re-imported (scripts need no ``__main__`` guard).
``workers=0`` runs the tasks in this process, one after the other (no isolation: debugging, profiling).

Ray backend (``pip install .[cluster]``): ``ray_address`` "auto" (the cluster of ``ray start``), an address
``host:port`` / ``ray://host:10001``, or "local" (start a Ray instance on this machine with ``workers``
CPUs, or all of them); a Ray already initialised in this process is used as it is. One Ray task per task
(num_cpus=1), retried here once after a WorkerCrashedError, like the local pool.
"""
from __future__ import annotations

import os
import pickle
import struct
import subprocess
import sys
import traceback
from collections import deque
from dataclasses import dataclass
from multiprocessing.connection import wait

from redmax_ros.runner import progress_bar

DEFAULT_PRELOAD = ("redmax_ros.sweep.run",)
NEW_SESSION = True  # start each local worker in a session of its own (see _Worker)


@dataclass
class TaskFailure:
    """A task without a result: ``reason`` (the exception and its traceback, or how the worker died)."""
    reason: str
    killed: bool = False  # the worker process died (on every attempt)
    detail: str = ""  # how it died (exit code, Ray's error): differs between backends, unlike ``reason``


def default_workers() -> int:
    """The CPUs this process may run on (os.sched_getaffinity where available)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


def call_task(fn, arg):
    """fn(arg), or a TaskFailure carrying the exception's traceback."""
    try:
        return fn(arg)
    except Exception:  # noqa: BLE001 - reported in the result
        return TaskFailure(traceback.format_exc())


def read_frame(f):
    """One frame (8-byte little-endian length, then that many bytes) from the binary stream ``f``; None at EOF."""
    head = f.read(8)
    if len(head) < 8:
        return None
    n = struct.unpack("<Q", head)[0]
    data = f.read(n)
    return data if len(data) == n else None


def write_frame(f, data: bytes) -> None:
    """Write one frame (see read_frame) and flush."""
    f.write(struct.pack("<Q", len(data)) + data)
    f.flush()


class _Worker:
    """``python -m redmax_ros.sweep.worker`` with this process's sys.path; tasks in on stdin, results out."""

    def __init__(self, preload):
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(p for p in sys.path if p)
        # a session of its own per worker: with the kernel's autogroup scheduling (CONFIG_SCHED_AUTOGROUP) each
        # session shares the CPUs with the others as one, so N workers in the caller's session would get one
        # session's share on a busy machine (Ray's workers have their own sessions too); and Ctrl-C reaches the
        # parent only, which then ends the workers (run_tasks' finally)
        self.proc = subprocess.Popen([sys.executable, "-m", "redmax_ros.sweep.worker", *preload],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env,
                                     start_new_session=NEW_SESSION)
        self.task = None  # index of the task it is running

    def send(self, fn, arg):
        write_frame(self.proc.stdin, pickle.dumps((fn, arg), protocol=pickle.HIGHEST_PROTOCOL))

    def stop(self, timeout=10.0, kill=False):
        """End the worker: EOF on its stdin (it exits between tasks), killed after ``timeout`` [s] or at once
        with ``kill`` (an interrupted sweep: its run would otherwise go on)."""
        if kill:
            self.proc.kill()
        try:
            self.proc.stdin.close()
        except OSError:
            pass
        try:
            self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self.proc.stdout.close()


def _local(fn, tasks, workers, retries, preload):
    pending = deque(range(len(tasks)))
    attempts = [0] * len(tasks)
    pool = [_Worker(preload) for _ in range(max(1, min(workers, len(tasks))))]
    finished = False
    try:
        while pending or any(w.task is not None for w in pool):
            for w in pool:
                if w.task is None and pending:
                    i = pending.popleft()
                    attempts[i] += 1
                    w.task = i
                    try:
                        w.send(fn, tasks[i])
                    except OSError:
                        pass  # a dead worker: its EOF is seen below
            busy = [w for w in pool if w.task is not None]
            ready = wait([w.proc.stdout for w in busy])
            for k, w in enumerate(pool):
                if w.task is None or w.proc.stdout not in ready:
                    continue
                i, w.task = w.task, None
                data = read_frame(w.proc.stdout)
                if data is not None:
                    yield i, pickle.loads(data), attempts[i]
                    continue
                # EOF: the worker died while running task i
                w.stop()
                code = w.proc.returncode
                pool[k] = _Worker(preload)
                if attempts[i] <= retries:
                    pending.appendleft(i)
                else:
                    yield i, TaskFailure(f"worker died on each of {attempts[i]} attempts", killed=True,
                                         detail=f"exit code {code}"), attempts[i]
        finished = True
    finally:  # also on Ctrl-C or when the caller stops iterating: then the workers are killed
        for w in pool:
            w.stop(kill=not finished)


def _inline(fn, tasks):
    for i, arg in enumerate(tasks):
        yield i, call_task(fn, arg), 1


def ray_call(fn, arg):
    """The body of a Ray task: fn(arg) or a TaskFailure (as a local worker)."""
    return call_task(fn, arg)


def _ray(fn, tasks, address, workers, retries):
    import ray  # optional: pip install .[cluster]
    own = not ray.is_initialized()
    if own:
        if address == "local":
            ray.init(num_cpus=workers or None, include_dashboard=False, log_to_driver=False)
        else:
            ray.init(address=address, log_to_driver=False)
    remote = ray.remote(num_cpus=1, max_retries=0)(ray_call)
    try:
        refs = {}
        attempts = [0] * len(tasks)

        def submit(i):
            attempts[i] += 1
            refs[remote.remote(fn, tasks[i])] = i

        for i in range(len(tasks)):
            submit(i)
        while refs:
            done, _ = ray.wait(list(refs), num_returns=1)
            for ref in done:
                i = refs.pop(ref)
                try:
                    result = ray.get(ref)
                except (ray.exceptions.WorkerCrashedError, ray.exceptions.NodeDiedError,
                        ray.exceptions.LocalRayletDiedError) as e:
                    if attempts[i] <= retries:
                        submit(i)
                        continue
                    result = TaskFailure(f"worker died on each of {attempts[i]} attempts", killed=True,
                                         detail=type(e).__name__)
                except ray.exceptions.RayError as e:
                    result = TaskFailure(f"{type(e).__name__}: {e}")
                yield i, result, attempts[i]
    finally:
        if own:
            ray.shutdown()


def run_tasks(fn, tasks, workers: int | None = None, ray_address: str | None = None, retries: int = 1,
              preload=DEFAULT_PRELOAD, progress: bool = False, desc: str | None = None):
    """Run fn(task) for every task; yields (index, result or TaskFailure, attempts) as tasks finish.
    ``workers``: local processes (None: this machine's CPUs; 0: in this process); ``ray_address``: run on
    Ray instead (see the module docstring); ``progress``: a tqdm bar over the tasks."""
    tasks = list(tasks)
    if not tasks:
        return
    if ray_address:
        it = _ray(fn, tasks, ray_address, workers, retries)
    elif workers == 0:
        it = _inline(fn, tasks)
    else:
        it = _local(fn, tasks, default_workers() if workers is None else workers, retries, preload)
    with progress_bar(len(tasks), not progress, unit="task", desc=desc) as bar:
        for item in it:
            bar.update(1)
            yield item


def run_all(fn, tasks, **kw) -> list:
    """run_tasks' results in task order; a TaskFailure raises RuntimeError (for callers whose tasks must all
    succeed, e.g. the benchmarks)."""
    tasks = list(tasks)
    out = [None] * len(tasks)
    for i, res, _ in run_tasks(fn, tasks, **kw):
        if isinstance(res, TaskFailure):
            raise RuntimeError(f"task {i} failed: {res.reason}")
        out[i] = res
    return out
