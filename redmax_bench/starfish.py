"""redmax_bench starfish: the paper's STARFISH (Fig. 1c, §4; scenes/starfish.yaml, docs/deformables.md), a
skeleton of 20 joints fully two-way coupled to a tetrahedral FEM mesh. Per-step CPU time split into the
skeleton stages (kinematics, Eq. 2, rows), the mesh assembly (co-rotated FEM forces and stiffness, A_d, b_d)
and the coupled sparse solve; CPU per step against the vertex count at three mesh resolutions with the fitted
log-log slope; the real-time factor at h = 1e-3; and the measurement behind the solver choice (one sparse KKT
LU against a Schur complement of the attachment rows onto the reduced DOFs). Writes starfish.json into --out.

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
from redmax_ros.core.step import deformable_stages
from redmax_bench.common import add_out_argument, write_json

CELLS = (0.028, 0.02, 0.014)  # mesh cell sizes [m] of the three resolutions (0.028: the shipped scene)


def run_one(cell: float, steps: int, warm: int = 20) -> dict:
    sim = Simulator.load("starfish", [f"params.cell={cell}"])
    sim.step(warm)
    tm = sim.backend.timing
    for k in ("skeleton", "mesh_assembly", "coupled_solve"):
        tm[k] = 0.0
    c0, w0 = time.process_time(), time.perf_counter()
    sim.step(steps)
    cpu, wall = (time.process_time() - c0) / steps, (time.perf_counter() - w0) / steps
    dm = sim.deformables
    return {"cell": cell, "vertices": dm.n_vertices, "tets": dm.elements[0].n_elements,
            "attached": int(len(dm.attach.vertex)), "nv": sim.mech.nv,
            "cpu_per_step_ms": 1e3 * cpu, "wall_per_step_ms": 1e3 * wall, "rtf": sim.dt / wall,
            "split_ms": {k: 1e3 * tm[k] / steps for k in ("skeleton", "mesh_assembly", "coupled_solve")},
            "rest_ms": 1e3 * (wall - sum(tm[k] for k in ("skeleton", "mesh_assembly", "coupled_solve")) / steps),
            "_sim": sim}


def solver_choice(sim, repeats: int = 20) -> dict:
    """Time one sparse KKT LU of the coupled system against the Schur complement route (LU of A_d, A_d^-1 G_d^T
    for the attachment rows, dense Schur complement with the skeleton's block) on the starfish's step."""
    mech, ws, dm = sim.mech, sim.backend.workspace, sim.deformables
    ds = deformable_stages.deform_state(dm, sim.state)
    h = sim.dt
    A_d, b_d = dm.assemble(ds.x, ds.v, h)
    n_r = mech.nv
    _, Js = deformable_stages.attachment_points(mech, ws.data, dm)
    Ga_r, Ga_d = attach.rows(n_r, dm.n_vertices, dm.attach.vertex, Js)
    A_r = np.eye(n_r)  # the skeleton's block is small and dense: its cost is the same on both routes
    A = sp.block_diag([sp.csr_matrix(A_r), A_d], format="csr")
    G = sp.hstack([sp.csr_matrix(Ga_r), Ga_d], format="csr")
    K = sp.bmat([[A, G.T], [G, None]], format="csc")
    t0 = time.process_time()
    for _ in range(repeats):
        splu(K)
    kkt = (time.process_time() - t0) / repeats
    t0 = time.process_time()
    for _ in range(repeats):
        lu = splu(A_d.tocsc())
        Y = lu.solve(Ga_d.T.toarray())
        S = Ga_r @ np.linalg.solve(A_r, Ga_r.T) + Ga_d @ Y
        np.linalg.cholesky(S)
    schur = (time.process_time() - t0) / repeats
    return {"kkt_lu_ms": 1e3 * kkt, "schur_ms": 1e3 * schur, "attachment_rows": int(G.shape[0]),
            "kkt_size": int(K.shape[0])}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="redmax_bench starfish", description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=300)
    add_out_argument(ap)
    a = ap.parse_args(argv)
    rows = [run_one(c, a.steps) for c in CELLS]
    choice = solver_choice(rows[0]["_sim"])
    for r in rows:
        r.pop("_sim")
    v = np.log([r["vertices"] for r in rows])
    c = np.log([r["cpu_per_step_ms"] for r in rows])
    slope = float(np.polyfit(v, c, 1)[0])
    out = {"resolutions": rows, "cpu_vs_vertices_slope": slope, "shipped": rows[0], "solver_choice": choice,
           "h": 1e-3}
    for r in rows:
        print(f"{r['vertices']:5d} vertices {r['tets']:5d} tets: {r['cpu_per_step_ms']:.2f} ms CPU/step, "
              f"RTF {r['rtf']:.3f}, split {', '.join(f'{k} {x:.2f}' for k, x in r['split_ms'].items())} ms")
    print(f"slope of log CPU vs log vertices: {slope:.2f}")
    print(f"solver choice: {choice}")
    write_json(a.out, "starfish", out)
    return 0
