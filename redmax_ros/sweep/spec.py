"""Expansion of ``--grid`` and ``--random`` into the runs of a sweep.

    --grid KEY=V1,V2,...            values as YAML text (commas inside [..] / {..} do not split)
    --grid KEY=lin:A:B:N            N values from A to B, evenly spaced
    --grid KEY=log:A:B:N            N values from A to B, evenly spaced in log (A, B > 0)
    --random KEY=uniform:A:B        U(A, B)
    --random KEY=normal:MU:SIGMA    N(MU, SIGMA^2)
    --random KEY=loguniform:A:B     exp(U(ln A, ln B)), A, B > 0

The grid is the cartesian product of its keys (the first key varies slowest); ``--samples N`` random points
are drawn with numpy's default_rng(seed), key after key for each sample, so a seed gives the same points on
every machine. With both, every grid point is combined with every random sample. Each point becomes a
RunSpec whose overrides are the base ``--set`` list followed by ``KEY=VALUE`` for each swept key.
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np


def yaml_float(x: float) -> str:
    """``x`` as YAML text that reads back as the same float64 (positional notation: YAML 1.1 reads '1e3' as a
    string, '1000.' as a number)."""
    return np.format_float_positional(float(x))


def split_values(text: str) -> list:
    """Split ``v1,v2,...`` at the commas outside brackets and braces: '[0,0,1],[0,1,0]' -> 2 values."""
    out, depth, cur = [], 0, []
    for ch in text:
        if ch in "[{":
            depth += 1
        elif ch in "]}":
            depth -= 1
        if ch == "," and depth == 0:
            out.append("".join(cur).strip())
            cur = []
        else:
            cur.append(ch)
    out.append("".join(cur).strip())
    if any(v == "" for v in out):
        raise ValueError(f"empty value in {text!r}")
    return out


def _key_value(text: str, what: str):
    key, sep, val = text.partition("=")
    if not sep or not key.strip() or not val.strip():
        raise ValueError(f"{what} {text!r}: expected KEY=VALUES")
    return key.strip(), val.strip()


def _numbers(text: str, kind: str, n_expected: int, what: str) -> list:
    parts = text.split(":")[1:]
    if len(parts) != n_expected:
        raise ValueError(f"{what}: '{kind}' takes {n_expected} numbers separated by ':'")
    try:
        return [float(p) for p in parts]
    except ValueError:
        raise ValueError(f"{what}: '{kind}' needs numbers, got {text!r}") from None


def grid_values(text: str) -> tuple:
    """(key, [value texts]) of one ``--grid KEY=...`` argument (see the module docstring)."""
    key, val = _key_value(text, "--grid")
    kind = val.split(":", 1)[0]
    if kind in ("lin", "log") and ":" in val:
        a, b, n = _numbers(val, kind, 3, f"--grid {text!r}")
        if n < 1 or n != int(n):
            raise ValueError(f"--grid {text!r}: the count must be a positive integer")
        if kind == "log":
            if a <= 0 or b <= 0:
                raise ValueError(f"--grid {text!r}: log spacing needs positive ends")
            xs = np.geomspace(a, b, int(n))
        else:
            xs = np.linspace(a, b, int(n))
        return key, [yaml_float(x) for x in xs]
    return key, split_values(val)


DISTRIBUTIONS = ("uniform", "normal", "loguniform")


def random_spec(text: str) -> tuple:
    """(key, distribution, (p1, p2)) of one ``--random KEY=DIST:P1:P2`` argument."""
    key, val = _key_value(text, "--random")
    kind = val.split(":", 1)[0]
    if kind not in DISTRIBUTIONS:
        raise ValueError(f"--random {text!r}: unknown distribution '{kind}' (known: {', '.join(DISTRIBUTIONS)})")
    p1, p2 = _numbers(val, kind, 2, f"--random {text!r}")
    if kind == "loguniform" and (p1 <= 0 or p2 <= 0):
        raise ValueError(f"--random {text!r}: loguniform needs positive bounds")
    if kind == "normal" and p2 < 0:
        raise ValueError(f"--random {text!r}: the standard deviation must be >= 0")
    return key, kind, (p1, p2)


def draw(rng, kind: str, p) -> float:
    """One sample of distribution ``kind`` with parameters ``p`` from the numpy Generator ``rng``."""
    if kind == "uniform":
        return float(rng.uniform(p[0], p[1]))
    if kind == "normal":
        return float(rng.normal(p[0], p[1]))
    return float(np.exp(rng.uniform(np.log(p[0]), np.log(p[1]))))


def expand(grid=(), random=(), samples: int = 0, seed: int = 0) -> tuple:
    """(keys, points): the swept keys in order and one tuple of value texts per run (grid product x random
    samples; a single empty point when nothing is swept)."""
    g = [grid_values(t) for t in grid]
    r = [random_spec(t) for t in random]
    keys = [k for k, _ in g] + [k for k, _, _ in r]
    if len(set(keys)) != len(keys):
        raise ValueError(f"a key is swept twice: {keys}")
    if r and samples < 1:
        raise ValueError("--random needs --samples N >= 1")
    rng = np.random.default_rng(seed)
    rand = [tuple(yaml_float(draw(rng, kind, p)) for _, kind, p in r) for _ in range(samples if r else 1)]
    points = [tuple(gp) + rp for gp in itertools.product(*[v for _, v in g]) for rp in rand]
    return keys, points


@dataclass(frozen=True)
class RunSpec:
    """One run of a sweep: everything a worker needs (picklable)."""
    index: int
    scene: str
    overrides: tuple  # ("key=value", ...): base --set, --dt/--solver, then the swept keys
    params: tuple  # ((key, value text), ...): the swept keys of this run
    duration: float | None = None  # simulated time [s]; None: the scene's
    controller: str | None = None  # "module:function" or "file.py:function"
    body: str | None = None  # body whose distance travelled is measured
    step_budget_ms: float | None = None
    csv_path: str | None = None  # per-run trajectory CSV (redmax_run's format), or None
    extra: dict = field(default_factory=dict, compare=False)


def build_runs(scene: str, keys, points, base_overrides=(), **kw) -> list:
    """One RunSpec per point, numbered 0.. in order; ``kw``: the RunSpec fields shared by every run (with
    ``csv_dir`` [str] instead of csv_path: run_<index>.csv in that folder)."""
    csv_dir = kw.pop("csv_dir", None)
    runs = []
    for i, pt in enumerate(points):
        ov = tuple(base_overrides) + tuple(f"{k}={v}" for k, v in zip(keys, pt))
        csv = f"{csv_dir}/run_{i:05d}.csv" if csv_dir else None
        runs.append(RunSpec(i, scene, ov, tuple(zip(keys, pt)), csv_path=csv, **kw))
    return runs
