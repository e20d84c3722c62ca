#!/usr/bin/env python3
"""Compare ``redmax_run`` CSVs of every shipped scene between a base revision and the work tree.

    python scripts/compare_runs.py [--base REV] [--duration T] [--scenes a,b] [--keep DIR]

The base revision is checked out with ``git worktree`` into a temporary folder and run with that
folder first on PYTHONPATH (same interpreter, same packages), the work tree likewise; every scene of
``scenes/`` runs for ``--duration`` seconds (default 0.5 s, or the scene's own duration if shorter)
with its own solver, and the large ones (bridge, umbrella, chain) also with ``--solver pcg`` and
``--solver direct`` so that every step implementation is exercised. The CSVs (``%.17g``) are compared
byte for byte; a difference is reported with the largest absolute difference per column. Exit code 0
when every pair is identical, 1 otherwise. Used for the "no physics change" point of the re-housing
(docs/architecture.md).
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SOLVER_VARIANTS = {"bridge": ("pcg", "direct"), "umbrella": ("pcg", "direct"), "chain": ("pcg", "direct")}


def scene_names(tree: Path) -> list:
    base = tree / "scenes"
    return sorted(str(p.relative_to(base).with_suffix("")) for p in base.rglob("*.yaml"))


def run(tree: Path, scene: str, solver: str | None, duration: float, out: Path) -> tuple:
    cmd = [sys.executable, "-m", "redmax_ros.runner", scene, "--duration", str(duration), "--quiet",
           "--out", str(out)]
    if solver:
        cmd += ["--solver", solver]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tree), os.environ.get("PYTHONPATH", "")]))
    p = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True)
    return p.returncode, (p.stdout + p.stderr).strip().splitlines()[-1:] if p.returncode else []


def diff_columns(a: Path, b: Path) -> str:
    """Largest absolute difference of the state columns (q:, v:) and, separately, of the worst other
    columns (energies, violation, required torques/forces); NaN in both files counts as equal."""
    ha, hb = a.read_text().splitlines()[0], b.read_text().splitlines()[0]
    if ha != hb:
        return "headers differ"
    A = np.loadtxt(a, delimiter=",", skiprows=1, ndmin=2)
    B = np.loadtxt(b, delimiter=",", skiprows=1, ndmin=2)
    if A.shape != B.shape:
        return f"shapes differ {A.shape} vs {B.shape}"
    both_nan = np.isnan(A) & np.isnan(B)
    d = np.where(both_nan, 0.0, np.nan_to_num(np.abs(A - B), nan=np.inf))
    cols = ha.split(",")
    state = [i for i, c in enumerate(cols) if c.startswith(("q:", "v:"))]
    other = [i for i in range(len(cols)) if i not in state and cols[i] != "t"]
    parts = [f"state (q, v) max |diff| {d[:, state].max():.3g}" if state else "no state columns"]
    worst = sorted(other, key=lambda i: -d[:, i].max())[:3]
    parts += [f"{cols[i]} {d[:, i].max():.3g}" for i in worst if d[:, i].max() > 0]
    if not d.any():
        parts = ["equal values, different text (e.g. -0 vs 0)"]
    return "; ".join(parts)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--base", default="HEAD", help="git revision to compare against (default HEAD)")
    ap.add_argument("--duration", type=float, default=0.5, help="simulated seconds per scene")
    ap.add_argument("--scenes", help="comma-separated subset of scene names")
    ap.add_argument("--keep", type=Path, help="write the CSVs here instead of a temporary folder")
    a = ap.parse_args(argv)
    work = Path(a.keep or tempfile.mkdtemp(prefix="redmax_cmp_"))
    base_tree = work / "base_tree"
    if not base_tree.exists():
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(base_tree), a.base],
                       check=True, capture_output=True)
    scenes = a.scenes.split(",") if a.scenes else scene_names(ROOT)
    same = differ = 0
    try:
        for scene in scenes:
            for solver in (None,) + SOLVER_VARIANTS.get(scene, ()):
                tag = scene.replace("/", "_") + (f"_{solver}" if solver else "")
                outs = []
                for label, tree in (("base", base_tree), ("work", ROOT)):
                    out = work / label / f"{tag}.csv"
                    out.parent.mkdir(parents=True, exist_ok=True)
                    rc, msg = run(tree, scene, solver, a.duration, out)
                    outs.append((rc, msg, out))
                (rc0, m0, o0), (rc1, m1, o1) = outs
                if rc0 != rc1:
                    print(f"DIFF  {tag}: exit codes {rc0} (base) vs {rc1} (work) {m0} {m1}")
                    differ += 1
                elif not o0.exists() and not o1.exists():
                    print(f"same  {tag}: both failed the same way {m0}")
                    same += 1
                elif o0.read_bytes() == o1.read_bytes():
                    n = len(o0.read_text().splitlines()) - 1
                    print(f"same  {tag}: {n} rows bitwise identical" + (f" (both exit {rc0})" if rc0 else ""))
                    same += 1
                else:
                    print(f"DIFF  {tag}: {diff_columns(o0, o1)}")
                    differ += 1
    finally:
        if a.keep is None:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(base_tree)],
                           capture_output=True)
    print(f"{same} identical, {differ} different (base {a.base}, {a.duration:g} s per scene)")
    return 0 if differ == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
