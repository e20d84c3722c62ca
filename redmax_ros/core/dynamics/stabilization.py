"""Loop-closure drift: post-stabilization by projection (Gauss-Newton, least-norm correction).

The velocity-level constraint G qdot = 0 (Eq. 5/6) leaves O(h^2) position drift per step. After
each configuration update we project q back onto the loop manifold phi(q) = 0 with least-norm
Newton steps in hyper-reduced coordinates, dq = -G^+ phi, keeping prescribed joints fixed, until
max |phi| < ``tol`` (default 1e-10 m) or ``max_iter`` iterations (default 5). Velocities are not
projected (the next step's velocity constraint acts on them). This replaces Baumgarte's
stabilization [Baumgarte 1972], which the paper uses, because it needs no tuning and removes the
drift to solver precision; see docs/architecture.md.
"""
from __future__ import annotations

import numpy as np
import pinocchio as pin

from redmax_ros.core.dynamics.constraints import loop_rows
from redmax_ros.core.errors import SceneError
from redmax_ros.core.dynamics.kinematics import site_jacobians, site_positions

TOL = 1e-10


def loop_residual(mech, data, q):
    """phi (rows,) [m] and G_R (rows, ndof) of the loop closures at configuration q."""
    pin.computeJointJacobians(mech.model, data, q)
    X, J = site_jacobians(mech, data, mech.jac_sites)
    G, phi = loop_rows(mech, X, J)
    return phi, (G if mech.T is None else G @ mech.T)


def loop_violation(mech, data) -> float:
    """max |phi| [m] at the configuration of data (forward kinematics done)."""
    if not len(mech.loop_ab):
        return 0.0
    return float(np.abs(loop_phi(mech, data)).max())


def project(mech, data, q, hold_dofs=(), tol=TOL, max_iter=5):
    """Project q onto phi(q) = 0. ``hold_dofs``: hyper-reduced DOFs that must not move. Returns (q, max|phi|)."""
    if not len(mech.loop_ab):
        return q, 0.0
    hold = np.zeros((len(hold_dofs), mech.ndof))
    hold[np.arange(len(hold_dofs)), list(hold_dofs)] = 1.0
    phi, G = loop_residual(mech, data, q)
    for _ in range(max_iter):
        err = float(np.abs(phi).max())
        if err < tol:
            return q, err
        Gh = np.vstack([G, hold])
        rhs = np.concatenate([-phi, np.zeros(len(hold))])
        dq, *_ = np.linalg.lstsq(Gh, rhs, rcond=None)
        q = pin.integrate(mech.model, q, mech.to_reduced(dq))
        phi, G = loop_residual(mech, data, q)
    return q, float(np.abs(phi).max())


def project_chord(mech, data, q, G, hold_dofs=(), tol=TOL, max_iter=8):
    """Chord-Newton projection onto phi(q) = 0 reusing the step's loop rows G (hyper-reduced, at q_k):
    each iteration costs forward kinematics and the loop sites only. The chord converges at a rate
    O(h |qdot|) (the change of G over one step); if it has not converged in ``max_iter`` iterations the
    full Newton projection takes over. Returns (q, max|phi|) at the returned q.

    One implementation serves both pipelines: data_free.project_chord, whose forward kinematics and
    site positions are compiled O(n) passes (recursive.py) instead of a Pinocchio forwardKinematics
    and one frame update per loop site per iteration. ``data`` is not used (kept for the signature)."""
    from redmax_ros.core.dynamics.data_free import context, project_chord as chord  # data_free imports this module
    return chord(context(mech), q, G, hold_dofs, tol, max_iter)


def loop_phi(mech, data) -> np.ndarray:
    """Loop-closure residuals phi (rows,) [m] at the forward kinematics in data."""
    X = site_positions(mech, data, mech.jac_sites)
    A, B = mech.loop_rows_ab[:, 0], mech.loop_rows_ab[:, 1]
    return mech.loop_select @ (X[A] - X[B]).reshape(-1)


def assemble_loops(mech, q):
    """Close the loops at the initial configuration; reject redundant loop rows (SceneError)."""
    if not len(mech.loop_ab):
        return q
    data = mech.model.createData()
    src = mech.spec.source
    q, err = project(mech, data, q, tol=1e-12, max_iter=100)
    if err > 1e-9:
        raise SceneError(src, "loops", f"cannot close the loops from the initial configuration "
                                       f"(residual {err:.3g} m after 100 Newton steps); check q0 and the loop sites")
    _, G = loop_residual(mech, data, q)
    check_loop_rank(mech, G)
    return q


def check_loop_rank(mech, G) -> None:
    """Reject loops whose rows are redundant with the joints (SceneError naming the first such loop).
    G: the loop rows (hyper-reduced) at the assembled configuration, loop by loop in mech order."""
    r0 = 0
    for name, P in zip(mech.loop_names, mech.loop_axes):
        r1 = r0 + len(P)
        sv = np.linalg.svd(G[:r1], compute_uv=False)
        rank = int(np.sum(sv > 1e-9 * max(sv[0], 1e-300)))
        if rank < r1:
            raise SceneError(mech.spec.source, f"loops '{name}'",
                             f"over-constrains the mechanism: its rows are redundant with the joints "
                             f"(rank {rank} < {r1} rows); keep only the rows the mechanism needs (e.g. rows: [x, y] "
                             f"for a planar loop)")
        r0 = r1
