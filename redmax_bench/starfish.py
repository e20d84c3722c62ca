"""redmax_bench starfish: the paper's STARFISH (Fig. 1c, §4; scenes/starfish.yaml, docs/deformables.md), a
skeleton of 20 joints fully two-way coupled to a tetrahedral FEM mesh. Per-step CPU time split into the
skeleton stages (kinematics, Eq. 2, rows), the mesh assembly (co-rotated FEM forces and stiffness, A_d, b_d)
and the coupled sparse solve; CPU per step against the vertex count at three mesh resolutions with the fitted
log-log slope; the real-time factor at h = 1e-3 (with the shipped floor friction and without; ``rtf`` on the
wall clock, ``rtf_cpu`` = h / CPU per step, what the machine's load leaves out); and the
measurement behind the solver choice (our LDL^T of the reduced system against SuperLU on it and against the
sparse KKT LU of the unreduced system). Writes starfish.json into --out.

    redmax_bench starfish [--steps N] [--out DIR]
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from redmax_ros.core import Simulator
from redmax_ros.core.deformable import attach
from redmax_ros.core.solvers import sparse_ldl
from redmax_ros.core.step import deformable_stages
from redmax_bench.common import add_out_argument, write_json

CELLS = (0.028, 0.02, 0.014)  # mesh cell sizes [m] of the three resolutions (0.028: the shipped scene)
SPLIT = ("skeleton", "mesh_assembly", "reduction", "coupled_solve")  # backend.timing keys [s] (thread CPU time)


def run_one(cell: float, steps: int, warm: int = 20, overrides=()) -> dict:
    sim = Simulator.load("starfish", [f"params.cell={cell}", *overrides])
    sim.step(warm)
    tm = sim.backend.timing
    for k in SPLIT:
        tm[k] = 0.0
    iters = facts = 0
    c0, w0 = time.process_time(), time.perf_counter()
    for _ in range(steps):
        sim.step(1)
        iters += tm.get("contact_iterations", 0)
        facts += tm.get("contact_factorisations", 0)
    cpu, wall = (time.process_time() - c0) / steps, (time.perf_counter() - w0) / steps
    dm = sim.deformables
    return {"cell": cell, "vertices": dm.n_vertices, "tets": dm.elements[0].n_elements,
            "attached": int(len(dm.attach.vertex)), "nv": sim.mech.nv, "floor_mu": float(dm.floor_mu),
            "cpu_per_step_ms": 1e3 * cpu, "wall_per_step_ms": 1e3 * wall, "rtf": sim.dt / wall, "rtf_cpu": sim.dt / cpu,
            "split_ms": {k: 1e3 * tm[k] / steps for k in SPLIT},
            "rest_ms": 1e3 * (cpu - sum(tm[k] for k in SPLIT) / steps),
            "contact_subsolves_per_step": iters / steps, "factorisations_per_step": facts / steps, "_sim": sim}


def solver_choice(sim, repeats: int = 20) -> dict:
    """The reduced system of the starfish's last step (attached vertices eliminated, deformable/reduction.py)
    factorised and solved by our supernodal LDL^T (solvers/sparse_ldl.py, pattern analysed once) against
    SuperLU (scipy splu) on the same matrix, and against the sparse KKT LU of the unreduced system with its
    attachment rows (the first design): CPU ms per factorisation + one solve, best of ``repeats``."""
    ws, dm = sim.backend.workspace, sim.deformables
    red, cws, buf = ws.cache["deformable_reduction"]
    n = red.n
    data = buf["data"].copy()
    A = sp.csr_matrix((data, red.indices, red.indptr), shape=(n, n)).tocsc()
    b = buf["b"].copy()

    def best(f):
        ts = []
        for _ in range(repeats):
            t0 = time.process_time()
            f()
            ts.append(time.process_time() - t0)
        return 1e3 * min(ts)

    ldl = best(lambda: sparse_ldl.solve(cws.sym, sparse_ldl.factor(cws.sym, data, out=cws.num), b))
    superlu = best(lambda: splu(A).solve(b))
    ds = deformable_stages.deform_state(dm, sim.state)
    A_d, _ = dm.assemble(ds.x, ds.v, sim.dt)
    n_r = sim.mech.nv
    _, Js = deformable_stages.attachment_points(sim.mech, ws.data, dm, deformable_stages.attachment_support(sim.mech, dm))
    Ga_r, Ga_d = attach.rows(n_r, dm.n_vertices, dm.attach.vertex, Js.reshape(-1, 3, n_r))
    K = sp.bmat([[sp.block_diag([sp.csr_matrix(np.eye(n_r)), A_d]), sp.hstack([sp.csr_matrix(Ga_r), Ga_d]).T],
                 [sp.hstack([sp.csr_matrix(Ga_r), Ga_d]), None]], format="csc")
    kkt = best(lambda: splu(K))
    return {"reduced_size": n, "reduced_nnz": int(len(red.indices)), "nnz_L": int(cws.sym.nnz_l),
            "ldl_factor_solve_ms": ldl, "superlu_reduced_factor_solve_ms": superlu, "kkt_size": int(K.shape[0]),
            "kkt_superlu_factor_ms": kkt}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="redmax_bench starfish", description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=300)
    add_out_argument(ap)
    a = ap.parse_args(argv)
    rows = [run_one(c, a.steps) for c in CELLS]
    frictionless = run_one(CELLS[0], a.steps, overrides=["params.mu=0"])
    choice = solver_choice(rows[0]["_sim"])
    for r in rows + [frictionless]:
        r.pop("_sim")
    v = np.log([r["vertices"] for r in rows])
    c = np.log([r["cpu_per_step_ms"] for r in rows])
    slope = float(np.polyfit(v, c, 1)[0])
    out = {"resolutions": rows, "cpu_vs_vertices_slope": slope, "shipped": rows[0], "frictionless": frictionless,
           "solver_choice": choice, "h": 1e-3, "steps": a.steps}
    for r in rows + [frictionless]:
        print(f"{r['vertices']:5d} vertices {r['tets']:5d} tets, floor mu {r['floor_mu']:.1f}: "
              f"{r['cpu_per_step_ms']:.2f} ms CPU/step, RTF {r['rtf']:.3f} (CPU: {r['rtf_cpu']:.3f}), "
              f"split {', '.join(f'{k} {x:.2f}' for k, x in r['split_ms'].items())} ms, "
              f"{r['contact_subsolves_per_step']:.2f} contact sub-solves and {r['factorisations_per_step']:.2f} "
              f"factorisations per step")
    print(f"slope of log CPU vs log vertices: {slope:.2f}")
    print(f"solver choice: {choice}")
    write_json(a.out, "starfish", out)
    return 0
