"""Micro-benchmark of the O(n) passes (not a test): per-joint cost of the Projected Block Jacobi
Preconditioner (Alg. 1) and of the J / J^T / Jdot products, on chains of revolute joints.

    redmax_bench passes [--sizes 100 300 1000] [--seconds 0.2] [--out DIR]
    python -m redmax_bench.passes [...]

Prints microseconds per call and nanoseconds per joint and writes them to passes.json in --out
(default bench/results under the current directory). The first run JIT-compiles the numba
kernels (cached afterwards in __pycache__); compilation is excluded from the timings.
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import pinocchio as pin

from redmax_ros.core.solvers import recursive as rc
from redmax_ros.core.solvers.pcg import MatrixFreeSystem, PointSprings
from redmax_ros.core.solvers.preconditioner import ProjectedBlockJacobi
from redmax_bench.common import add_out_argument, write_json

H = 1e-3  # time step [s]


def revolute_chain(n: int) -> pin.Model:
    """n links of 0.1 m, 0.1 kg, alternating y / x revolute axes; no pin.Data is ever created
    (pin 4.1's Data is O(nv^3) in memory)."""
    model = pin.Model()
    parent = 0
    for k in range(n):
        jm = pin.JointModelRY() if k % 2 == 0 else pin.JointModelRX()
        offset = pin.SE3(np.eye(3), np.array([0.0, 0.0, -0.1 if k else 0.0]))
        parent = model.addJoint(parent, jm, offset, f"j{k}")
        model.appendBodyToJoint(parent, pin.Inertia(0.1, np.array([0.0, 0.0, -0.05]),
                                                    np.diag([1e-4, 1e-4, 1e-5])), pin.SE3.Identity())
    model.armature = np.full(model.nv, 1e-4)
    return model


def per_call(fn, seconds: float) -> float:
    """Median seconds per call of ``fn`` over ~5 batches lasting ``seconds`` in total."""
    fn()  # warm-up / compile
    t0 = time.perf_counter()
    fn()
    once = max(time.perf_counter() - t0, 1e-7)
    reps = max(1, int(seconds / 5 / once))
    batches = []
    for _ in range(5):
        t0 = time.perf_counter()
        for _ in range(reps):
            fn()
        batches.append((time.perf_counter() - t0) / reps)
    return float(np.median(batches))


def python_loop_jv(topo, ws, x):
    """Reference: Alg. 5 as a per-joint interpreted loop (what numba avoids)."""
    Y = np.zeros((topo.njoints, 6))
    for j in range(1, topo.njoints):
        i0, n = topo.idx_v[j], topo.nv_j[j]
        Y[j] = Y[topo.parents[j]] + ws.S[:, i0:i0 + n] @ x[i0:i0 + n]
    return Y


def bench(n: int, seconds: float, rng) -> dict:
    model = revolute_chain(n)
    topo = rc.build_topology(model)
    ws = rc.make_workspace(topo)
    q = rng.uniform(-0.5, 0.5, size=model.nq)
    v = rng.normal(size=model.nv)
    rc.update_kinematics(topo, ws, q, v)
    # n springs between random pairs of bodies (one in four to the world), 3x3 SPD matrices
    m = n
    ja = rng.integers(1, topo.njoints, size=m)
    jb = np.where(rng.random(m) < 0.25, 0, rng.integers(1, topo.njoints, size=m))
    K = np.array([np.eye(3) * 1e3 for _ in range(m)])
    springs = PointSprings(ja, rng.normal(scale=0.02, size=(m, 3)), jb,
                           rng.normal(scale=0.02, size=(m, 3)), K, 0.1 * K / 1e3)
    system = MatrixFreeSystem(topo, ws, H, reduced_diag=np.full(model.nv, H * 1e-3 + H * H * 0.1),
                              springs=springs)
    P = ProjectedBlockJacobi(topo)
    blocks = system.preconditioner_blocks()
    P.factor(ws, blocks, system.reduced_diag)
    x = rng.normal(size=model.nv)
    W = rng.normal(size=(topo.njoints, 6))
    y = np.empty(model.nv)
    Y = np.empty((topo.njoints, 6))
    b = system.apply(rng.normal(size=model.nv))
    res = system.solve(b, P=P)
    timings = {
        "P^-1 x   (Alg. 1 lines 10-18)": per_call(lambda: P.apply(x, y), seconds),
        "P factor (Alg. 1 lines 1-8)": per_call(lambda: P.factor(ws, blocks, system.reduced_diag), seconds),
        "J x      (Alg. 5)": per_call(lambda: rc.jv(topo, ws, x, Y), seconds),
        "J^T w    (Alg. 6)": per_call(lambda: rc.jtw(topo, ws, W, y), seconds),
        "Jdot x   (Alg. 5)": per_call(lambda: rc.jdot_v(topo, ws, x, Y), seconds),
        f"A x      (Eq. 2 LHS, m={m} springs)": per_call(lambda: system.apply(x, y), seconds),
        "update_kinematics (FK, S, inertias)": per_call(lambda: rc.update_kinematics(topo, ws, q, v), seconds),
        f"PCG solve rtol 1e-6 ({res.iterations} it)": per_call(lambda: system.solve(b, P=P), seconds),
        "J x per-joint Python loop (baseline)": per_call(lambda: python_loop_jv(topo, ws, x), seconds),
    }
    return timings


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[100, 300, 1000])
    ap.add_argument("--seconds", type=float, default=0.2, help="time budget per measurement [s]")
    add_out_argument(ap)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(0)
    print(f"numba: {rc.HAVE_NUMBA}; chain of revolute joints; times are medians of 5 batches")
    rows = []
    for n in args.sizes:
        t = bench(n, args.seconds, rng)
        rows.append({"n": n, "us_per_call": {name: sec * 1e6 for name, sec in t.items()},
                     "ns_per_joint": {name: sec * 1e9 / n for name, sec in t.items()}})
        print(f"\nn = {n}")
        print(f"  {'pass':44s} {'us/call':>10s} {'ns/joint':>10s}")
        for name, sec in t.items():
            print(f"  {name:44s} {sec * 1e6:10.2f} {sec * 1e9 / n:10.1f}")
    p = write_json(args.out, "passes", {"numba": bool(rc.HAVE_NUMBA), "seconds": args.seconds,
                                        "timer": "wall (median of 5 batches)", "sizes": rows})
    print(f"\nwrote {p}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
