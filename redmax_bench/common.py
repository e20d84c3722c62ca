"""Shared helpers for the benchmarks: output directory (``--out``), JSON writing, timing.

Results go to the directory given by ``--out`` (every subcommand has it), by default
``bench/results`` under the current directory; never next to this package's files (which, after a
normal ``pip install``, are inside site-packages).
"""
from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path


def default_out() -> Path:
    """``bench/results`` under the current directory (the default of ``--out``)."""
    return Path.cwd() / "bench" / "results"


def add_out_argument(ap: argparse.ArgumentParser) -> None:
    """The ``--out DIR`` option shared by every subcommand (parsed into ``args.out``, a Path)."""
    ap.add_argument("--out", type=Path, default=None, metavar="DIR",
                    help="directory for the JSON/PNG results, created if missing "
                         "(default: bench/results under the current directory)")


def results_dir(out: str | Path | None) -> Path:
    """The output directory ``out`` (``None``: :func:`default_out`), created if missing."""
    d = default_out() if out is None else Path(out).expanduser()
    d.mkdir(parents=True, exist_ok=True)
    return d


def write_json(out: str | Path | None, name: str, payload: dict) -> Path:
    """Write ``payload`` (with machine and date) to ``<out>/<name>.json``; returns the path."""
    payload = {"machine": {"python": platform.python_version(), "processor": platform.processor(),
                           "node": platform.node()}, "date": time.strftime("%Y-%m-%d %H:%M:%S"), **payload}
    p = results_dir(out) / f"{name}.json"
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
