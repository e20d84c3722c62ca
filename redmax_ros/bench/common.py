"""Shared helpers for the benchmarks: results directory, JSON writing, timing."""
from __future__ import annotations

import json
import platform
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parents[2] / "bench" / "results"


def results_dir() -> Path:
    RESULTS.mkdir(parents=True, exist_ok=True)
    return RESULTS


def write_json(name: str, payload: dict) -> Path:
    payload = {"machine": {"python": platform.python_version(), "processor": platform.processor(),
                           "node": platform.node()}, "date": time.strftime("%Y-%m-%d %H:%M:%S"), **payload}
    p = results_dir() / f"{name}.json"
    p.write_text(json.dumps(payload, indent=2))
    return p


def best_rate(fn, n: int, repeats: int = 3) -> float:
    """Best-of-``repeats`` calls per CPU second of this process of ``fn`` called ``n`` times (fn(n)
    does n calls). CPU time, not wall time: the work is single-threaded (BLAS threads pinned to 1),
    so on a quiet machine the two agree, and on the shared 2-core machine CPU time is much less
    distorted by other processes."""
    best = 0.0
    for _ in range(repeats):
        t0 = time.process_time()
        fn(n)
        dt = max(time.process_time() - t0, 1e-9)
        best = max(best, n / dt)
    return best
