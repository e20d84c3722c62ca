"""The coupled velocity solve of articulated and deformable DOFs (Wang et al. 2019 §4, the equation after Eq. 5),
on the reduced system of deformable/reduction.py (attached vertices eliminated): unknowns z = (v_f, qdot_r),

    A z = b + F + R,     G qdot_r = g (multipliers lam),     lo <= C qdot_r <= hi (joint limits, Eq. 5),

A the reduced symmetric matrix (one sparse LDL^T factorisation per working set, solvers/sparse_ldl.py, on a
pattern analysed once), G the skeleton's bilateral rows
(loops, prescriptions; sign convention of solvers/problem.py: A z + G^T lam = b), F the friction impulses of
sliding floor contacts, R the reactions on the DOFs held fixed (floor contacts). The bilateral and the active
limit rows are taken by the Schur complement S = G A^-1 G^T (one A solve per row; the skeleton has few).

Floor contact of the free vertices (Staggered Projections, paper Alg. 2 / Eq. 11-12, Kaufman et al. 2008, as
the rigid ground contact of friction/staggered.py, with the same four-sided pyramid |beta_x|, |beta_y| <= mu alpha
on the world tangents x, y): a vertex's contact rows are unit rows on its own DOFs, so each projection is a primal
active set on the vertex DOFs (Nocedal & Wright §16.5):
  * normal (Alg. 2 line 9): v_z >= lo (lo = (floor - z)/h, speculative); an active row holds v_z = lo and its
    impulse is alpha = (A z - b - F)_z >= 0; a row whose alpha pulls (< 0) is released, a violated one held;
  * friction (Eq. 12, bound mu alpha from the current normal impulse): a tangent DOF sticks (v = 0, reaction
    beta = (A z - b - F)_c, kept while |beta| <= mu alpha) or slides (impulse F_c = s mu alpha, s the sign of the
    reaction that failed to hold it; back to sticking when the velocity turns along F).
A held DOF is imposed by overwriting its row and column with the identity (the pattern, hence the symbolic
factorisation, is unchanged) and moving its known velocity to the right-hand side. The staggered fixed point
(the sliding impulses follow alpha) reuses the factorisation; the loop ends when no state changes and the
sliding impulses move the velocity by less than ``tol_v`` (Alg. 2 line 12), and reports non-convergence.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from redmax_ros.core.errors import StepError
from redmax_ros.core.solvers import sparse_ldl

MAX_ITER = 100  # cap of working-set / staggered iterations per step
TOL_V = 1e-9  # [m/s] the staggered loop's tolerance on the velocity change of a sliding impulse update


@dataclass(frozen=True)
class VertexContacts:
    """Free vertices near the floor: ``dof`` (k,) the reduced index of each one's x DOF (y, z follow), ``lo``
    (k,) the lower bound of v_z [m/s], ``mu`` the friction coefficient, ``vertex`` (k,) their global indices
    (the warm-start key)."""
    dof: np.ndarray
    lo: np.ndarray
    mu: float
    vertex: np.ndarray


@dataclass
class CoupledSolution:
    z: np.ndarray  # (n,) reduced velocities (v_f, qdot_r)
    lam: np.ndarray  # (m,) multipliers of the skeleton's bilateral rows
    mu: np.ndarray  # (p,) multipliers of the joint-limit rows (0 when inactive)
    iterations: int
    violation: float  # max |G qdot_r - g|
    residual: float  # stationarity |A z + G^T lam + C^T mu - b - F - R| / |b|
    contact_impulse: np.ndarray  # (k,3) floor impulses on the contact vertices (beta_x, beta_y, alpha) [N s]
    contact_state: dict = field(default_factory=dict)  # vertex -> (normal, stick_x, stick_y, sign_x, sign_y)
    converged: bool = True


def _pattern_maps(indptr, indices, n):
    """(diag position (n,), transpose position (nnz,)) of a symmetric CSR pattern."""
    rows = np.repeat(np.arange(n), np.diff(indptr))
    key = rows * n + indices
    order = np.argsort(key)
    tkey = indices * n + rows
    tpos = order[np.searchsorted(key[order], tkey)]
    diag = order[np.searchsorted(key[order], np.arange(n) * (n + 1))]
    return diag, tpos


class Workspace:
    """Per-pattern state of the coupled solve: the reduced CSR pattern, its symbolic LDL^T analysis (minimum
    degree, once), the diagonal and transpose maps used to hold DOFs, and the numeric factor's storage."""

    def __init__(self, indptr, indices, n):
        self.indptr, self.indices, self.n = indptr, indices, n
        self.diag, self.tpos = _pattern_maps(indptr, indices, n)
        self.rowlen = np.diff(indptr)
        self.sym = sparse_ldl.analyse(indptr, indices, n)
        self.num = sparse_ldl.LDLNumeric.empty(self.sym)


class Factor:
    """The LDL^T factorisation (solvers/sparse_ldl.py, no pivoting) of the reduced matrix with values ``data``
    in ``ws``'s pattern, into ws's storage; a zero pivot is a StepError naming the rows involved."""

    def __init__(self, ws: Workspace, data, labels=()):
        self.ws = ws
        try:
            sparse_ldl.factor(ws.sym, data, out=ws.num)
        except StepError as e:
            raise StepError("the coupled system of the skeleton and the deformables is singular "
                            f"(among: {', '.join(sorted(set(labels))[:6]) or 'the mesh'}): {e}") from None

    def solve(self, B):
        return sparse_ldl.solve(self.ws.sym, self.ws.num, B)


def _held(ws, data, fixed_dofs):
    """data with the rows and columns of ``fixed_dofs`` replaced by the identity."""
    if not len(fixed_dofs):
        return data
    d = data.copy()
    starts = ws.indptr[fixed_dofs]
    lens = ws.rowlen[fixed_dofs]
    idx = np.repeat(starts - np.cumsum(np.concatenate([[0], lens[:-1]])), lens) + np.arange(lens.sum())
    d[idx] = 0.0
    d[ws.tpos[idx]] = 0.0
    d[ws.diag[fixed_dofs]] = 1.0
    return d


def solve(ws: Workspace, data, b, n_r, G, g, C=None, lo=None, hi=None, contacts: VertexContacts | None = None,
          warm=None, labels=(), tol=1e-12) -> CoupledSolution:
    """The coupled solve on the reduced system (values ``data`` in ws's CSR pattern, right-hand side b (n,)):
    G (m, n_r) dense with g (m,), joint-limit rows C (p, n_r) with lo, hi (+-inf where open) or None, the
    floor ``contacts`` of free vertices or None, ``warm`` the last step's contact states (vertex -> state)."""
    n = ws.n
    A = sp.csr_matrix((data, ws.indices, ws.indptr), shape=(n, n))
    nf = n - n_r
    m = len(g)
    p = 0 if C is None else len(lo)
    k = 0 if contacts is None else len(contacts.dof)
    scale = 1.0 + float(np.abs(b).max()) if n else 1.0
    tol_imp = tol * scale
    # contact state: normal held, stick x / y, sliding sign x / y
    normal = np.zeros(k, dtype=bool)
    stick = np.zeros((k, 2), dtype=bool)
    sign = np.zeros((k, 2))
    if k and warm:
        for i, vtx in enumerate(contacts.vertex):
            st = warm.get(int(vtx))
            if st is not None:
                normal[i], stick[i, 0], stick[i, 1], sign[i, 0], sign[i, 1] = st
    F = np.zeros(n)
    active = {}  # limit row -> bound it is held at
    factor, key = None, None
    mu = np.zeros(p)
    alpha = np.zeros(k)
    z = lam = r = None
    converged = False
    it = 0
    for it in range(1, MAX_ITER + 1):
        fixed, vals = _fixed(contacts, normal, stick) if k else (np.zeros(0, np.int64), np.zeros(0))
        if k:  # sliding impulses from the current normal impulses (Eq. 12's bound mu alpha)
            F[:] = 0.0
            for c in range(2):
                sl = normal & ~stick[:, c] & (contacts.mu > 0)
                F[contacts.dof[sl] + c] = sign[sl, c] * contacts.mu * alpha[sl]
        new_key = fixed.tobytes()
        if factor is None or new_key != key:
            factor, key = Factor(ws, _held(ws, data, fixed), labels), new_key
        rhs = b + F
        if len(fixed):
            w = np.zeros(n)
            w[fixed] = vals
            rhs = rhs - A @ w
            rhs[fixed] = vals
        idx = np.fromiter(active, dtype=np.int64, count=len(active))
        z, lam, muW = _schur(factor, rhs, n, n_r, G, g, C[idx] if len(idx) else None,
                             np.array([active[i] for i in idx]), labels)
        r = A @ z - b - F  # reactions on the held DOFs (elsewhere the skeleton rows' G^T lam, C^T mu or 0)
        changed = False
        mu = np.zeros(p)
        mu[idx] = muW
        for j, i in enumerate(idx):  # limits: release rows whose multiplier pulls, hold violated ones
            lower = active[i] == lo[i]
            if (lower and muW[j] > tol_imp) or (not lower and muW[j] < -tol_imp):
                del active[i]
                mu[i] = 0.0
                changed = True
        if p:
            Cv = C @ z[nf:]
            for i in np.nonzero((Cv < lo - 1e-12) | (Cv > hi + 1e-12))[0]:
                if i not in active:
                    active[int(i)] = lo[i] if Cv[i] < lo[i] else hi[i]
                    changed = True
        moved = 0.0
        if k:
            ch, moved = _update_contacts(contacts, z, r, normal, stick, sign, alpha, data[ws.diag], tol_imp)
            changed |= ch
        if not changed and moved <= TOL_V:
            converged = True
            break
    imp = np.zeros((k, 3))
    if k:
        for c in range(3):
            imp[:, c] = np.where(normal, r[contacts.dof + c], 0.0)
        for c in range(2):
            imp[:, c] = np.where(normal & ~stick[:, c], F[contacts.dof + c], imp[:, c])
    res = r.copy()
    if k:
        held = _fixed(contacts, normal, stick)[0]
        res[held] = 0.0
    if m:
        res[nf:] += G.T @ lam
    if p:
        res[nf:] += C.T @ mu
    state = {int(v): (bool(normal[i]), bool(stick[i, 0]), bool(stick[i, 1]), float(sign[i, 0]), float(sign[i, 1]))
             for i, v in enumerate(contacts.vertex) if normal[i]} if k else {}
    viol = float(np.abs(G @ z[nf:] - g).max()) if m else 0.0
    return CoupledSolution(z, lam, mu, it, viol, float(np.linalg.norm(res) / max(np.linalg.norm(b), 1e-300)), imp,
                           state, converged)


def _fixed(contacts, normal, stick):
    """(held DOFs (sorted), their velocities): v_z = lo for a held normal, v_x / v_y = 0 for a sticking tangent."""
    dofs = [contacts.dof[normal] + 2]
    vals = [contacts.lo[normal]]
    for c in range(2):
        s = normal & stick[:, c]
        dofs.append(contacts.dof[s] + c)
        vals.append(np.zeros(int(s.sum())))
    d = np.concatenate(dofs).astype(np.int64)
    v = np.concatenate(vals)
    o = np.argsort(d)
    return d[o], v[o]


def _update_contacts(contacts, z, r, normal, stick, sign, alpha, diag, tol_imp):
    """One projection of every contact vertex's state (module docstring); updates the arrays in place and
    returns (whether a held set changed, the largest velocity change |delta F| / A_pp of the sliding impulses)."""
    changed = False
    moved = 0.0
    mu = contacts.mu
    for i in range(len(contacts.dof)):
        d = contacts.dof[i]
        if not normal[i]:
            if z[d + 2] < contacts.lo[i] - 1e-12:
                normal[i] = True
                stick[i] = mu > 0
                alpha[i] = 0.0
                changed = True
            continue
        a = r[d + 2]
        if a < -tol_imp:  # the floor would pull: release the vertex
            normal[i] = False
            stick[i] = False
            sign[i] = 0.0
            alpha[i] = 0.0
            changed = True
            continue
        a = max(a, 0.0)
        if mu > 0:
            for c in range(2):
                if stick[i, c]:
                    beta = r[d + c]
                    if abs(beta) > mu * a + tol_imp:  # the cone cannot hold it: slide
                        stick[i, c] = False
                        sign[i, c] = np.sign(beta)
                        changed = True
                elif z[d + c] * sign[i, c] > 1e-12:  # moving along the friction impulse: it overshot, stick
                    stick[i, c] = True
                    changed = True
                else:
                    moved = max(moved, abs(mu * (a - alpha[i])) / diag[d + c])
        alpha[i] = a
    return changed, moved


def _schur(factor, rhs, n, n_r, G, g, W, w, labels):
    """z = A^-1 (rhs - [0; G^T lam] - [0; W^T mu]) with G z_r = g and W z_r = w (the Schur complement of the
    skeleton rows; A^-1 through ``factor``)."""
    z0 = factor.solve(rhs)
    rows = G if W is None else np.vstack([G, W])
    vals = g if W is None else np.concatenate([g, w])
    if not len(vals):
        return z0, np.zeros(len(g)), np.zeros(0 if W is None else len(w))
    nf = n - n_r
    Gt = np.zeros((n, len(vals)))
    Gt[nf:] = rows.T
    Y = factor.solve(Gt)
    S = rows @ Y[nf:]
    try:
        lm = np.linalg.solve(S, rows @ z0[nf:] - vals)
    except np.linalg.LinAlgError:
        raise StepError("the skeleton's rows are redundant or conflicting in the coupled solve "
                        f"(among: {', '.join(sorted(set(labels))[:6])})") from None
    z = z0 - Y @ lm
    return z, lm[:len(g)], lm[len(g):]
