"""The coupled velocity solve of articulated and deformable DOFs (Wang et al. 2019 §4, the equation after Eq. 5),
on the reduced system of deformable/reduction.py (attached vertices eliminated): unknowns z = (v_f, qdot_r),

    A z = b + F + R,     G qdot_r = g (multipliers lam),     lo <= C qdot_r <= hi (joint limits, Eq. 5),

A the reduced symmetric matrix (one sparse LDL^T factorisation per step, solvers/sparse_ldl.py, on a
pattern analysed once), G the skeleton's bilateral rows
(loops, prescriptions; sign convention of solvers/problem.py: A z + G^T lam = b), F the friction impulses of
sliding floor contacts, R the reactions on the DOFs held fixed (floor contacts). The bilateral and the active
limit rows are taken by the Schur complement S = G A^-1 G^T (one A solve per row; the skeleton has few), in the
same bordered system as the held-set changes below.

Floor contact of the free vertices: Staggered Projections (paper Alg. 2, Eq. 11-12; Kaufman et al. 2008), with
the rigid ground contact's four-sided pyramid |beta_x|, |beta_y| <= mu alpha on the world tangents x, y
(friction/staggered.py). A vertex's contact rows are unit rows on its own DOFs, so both projections are primal
active sets on vertex DOFs (Nocedal & Wright §16.5), alternated with the other's impulses fixed:
  * normal stage (Alg. 2 line 9, Eq. 11): v_z >= lo (lo = (floor - z)/h, speculative); a held row v_z = lo has
    the impulse alpha = (A z - b - F)_z >= 0; a row whose alpha pulls (< 0) is released, a violated one held
    (sliding along its tangential velocity, or stuck if it is below STICK_V). The working set is carried into
    the friction stage (the normal velocities stay held there), so one factorisation serves both stages.
  * friction stage (Eq. 12 with alpha fixed): the convex piecewise-quadratic problem
        min_z 1/2 z^T A z - b^T z + sum_j mu alpha_j |z_j|     (j over the contact tangents)
    by a primal active set with descent: a state (stuck set S with z_S = 0, the signs s of the sliding impulses
    F_j = s_j mu alpha_j) gives a linear sub-problem with solution zs; from the current z (in the state's
    face) an exact line search along zs - z stops at the first sliding tangent whose velocity reaches 0, which
    sticks; when zs is sign-consistent, the one stuck tangent whose reaction most exceeds mu alpha slides
    (with the sign of its reaction). The objective never increases, so the state cannot cycle.
  * convergence (Alg. 2 line 12): no working-set change and max mu |delta alpha| / A_jj <= TOL_V [m/s] over
    the sliding contacts; the bound's fixed point is accelerated by Anderson(1), and the warm alpha of a
    contact is extrapolated from its last two steps. Not converged within MAX_ITER sub-problem solves is a
    StepError (the step leaves the state as it was). The reported friction impulses lie in the pyramid to
    ``contact_tol`` = TOL_V A_jj (a sliding impulse uses the bound of the last normal stage).
Held DOFs are imposed by overwriting their rows and columns with the identity (the pattern, hence the symbolic
analysis, is unchanged). Per step the held set of the warm start is factorised once; later changes of the held
set (a contact sticks, slides, lands or lifts off) are solved on that factor by a bordered (capacitance)
system with one solve per changed DOF (coupled_kernel.staggered), refactorised only past MAX_CHANGES changes (with mu > 0;
a frictionless floor refactorises on each change, as before, which keeps restarts bit for bit).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from redmax_ros.core.errors import StepError
from redmax_ros.core.solvers import coupled_kernel as ck
from redmax_ros.core.solvers import sparse_ldl

MAX_ITER = 200  # cap of sub-problem solves per step (friction and normal stages together)
TOL_V = 1e-6  # [m/s] the staggered loop's tolerance on the velocity change of a friction bound update (as friction.tol)
STICK_V = 1e-9  # [m/s] a new contact slower than this along a tangent starts stuck on it
MAX_CHANGES = 12  # held-set changes solved on the step's factorisation (bordered system) before refactorising


@dataclass(frozen=True)
class VertexContacts:
    """Free vertices near the floor: ``dof`` (k,) the reduced index of each one's x DOF (y, z follow), ``lo``
    (k,) the lower bound of v_z [m/s], ``mu`` the friction coefficient, ``vertex`` (k,) their global indices
    (the warm-start key)."""
    dof: np.ndarray
    lo: np.ndarray
    mu: float
    vertex: np.ndarray


@dataclass(frozen=True)
class ContactStates:
    """The floor contacts' states a solve ends with, the next step's warm start: ``vertex`` (c,) the contact
    vertices (ascending), ``rows`` (c, 6) their (stick_x, stick_y (1/0), sign_x, sign_y, alpha [N s], the step
    before's alpha or NaN)."""
    vertex: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    rows: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))

    def __len__(self):
        return len(self.vertex)


@dataclass
class CoupledSolution:
    z: np.ndarray  # (n,) reduced velocities (v_f, qdot_r)
    lam: np.ndarray  # (m,) multipliers of the skeleton's bilateral rows
    mu: np.ndarray  # (p,) multipliers of the joint-limit rows (0 when inactive)
    iterations: int
    violation: float  # max |G qdot_r - g|
    residual: float  # stationarity |A z + G^T lam + C^T mu - b - F - R| / |b|
    contact_impulse: np.ndarray  # (k,3) floor impulses on the contact vertices (beta_x, beta_y, alpha) [N s]
    contact_state: ContactStates = field(default_factory=ContactStates)  # the contacts' states (warm start)
    converged: bool = True
    factorisations: int = 0  # LDL^T factorisations of the reduced matrix this solve
    contact_tol: np.ndarray | None = None  # (k,) [N s] |beta| <= mu alpha + contact_tol: the loop's TOL_V A_jj


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
    degree, once), the diagonal and transpose maps used to hold DOFs, the numeric factor's storage, and the
    analysis' arrays as the compiled loop takes them."""

    def __init__(self, indptr, indices, n):
        self.indptr, self.indices, self.n = indptr, indices, n
        self.diag, self.tpos = _pattern_maps(indptr, indices, n)
        self.sym = sym = sparse_ldl.analyse(indptr, indices, n)
        self.data_map = sym.data_map  # each entry's position in the factor's values (coupled_kernel.held_factor)
        self.num = sparse_ldl.LDLNumeric.empty(sym)
        self.factor_arrays = (sym.sptr, sym.rptr, sym.voff, sym.diag, sym.assign_src, sym.assign_dst, sym.add_src,
                              sym.add_dst, sym.fill, sym.uptr, sym.usrc, sym.ua, sym.ub, sym.relptr, sym.rel,
                              sym.run_ptr, sym.run_row, sym.run_pos)
        self.solve_arrays = (sym.sptr, sym.rptr, sym.rows, sym.voff, sym.diag, sym.perm)


def solve(ws: Workspace, data, b, n_r, G, g, C=None, lo=None, hi=None, contacts: VertexContacts | None = None,
          warm=None, labels=(), tol=1e-12, stats=None) -> CoupledSolution:
    """The coupled solve on the reduced system (values ``data`` in ws's CSR pattern, right-hand side b (n,)):
    G (m, n_r) dense with g (m,), joint-limit rows C (p, n_r) with lo, hi (+-inf where open) or None, the
    floor ``contacts`` of free vertices or None, ``warm`` the last step's ContactStates
    (CoupledSolution.contact_state) or None. ``stats`` (a dict or None) receives ``contact_iterations`` (sub-problem
    solves), ``contact_factorisations`` and ``contact_converged``. Raises StepError when the contact iteration
    does not converge within MAX_ITER sub-problem solves (the caller's state is then left as it was). The loop
    itself, with its warm start and the contacts' states, is one compiled call (coupled_kernel.coupled_solve)."""
    n = ws.n
    nf = n - n_r
    k = 0 if contacts is None else len(contacts.dof)
    fric = 0.0 if contacts is None else float(contacts.mu)
    dof = np.zeros(0, np.int64) if not k else np.ascontiguousarray(contacts.dof, dtype=np.int64)
    clo = np.zeros(0) if not k else np.ascontiguousarray(contacts.lo, dtype=float)
    cvert = np.zeros(0, np.int64) if not k else np.ascontiguousarray(contacts.vertex, dtype=np.int64)
    if warm is None or not k:
        warm = ContactStates()
    G = np.ascontiguousarray(G, dtype=float).reshape(len(g), n_r)
    Cm = np.zeros((0, n_r)) if C is None else np.ascontiguousarray(C, dtype=float)
    lo_ = np.zeros(0) if C is None else np.ascontiguousarray(lo, dtype=float)
    hi_ = np.zeros(0) if C is None else np.ascontiguousarray(hi, dtype=float)
    m, p = len(g), len(lo_)
    z, F, lam, mu_lim = np.empty(n), np.empty(n), np.zeros(m), np.zeros(p)
    imp, svert, srows, ctol = np.zeros((k, 3)), np.empty(k, np.int64), np.empty((k, 6)), np.empty(k)
    info = np.zeros(ck.INFO_LEN, np.int64)
    finfo = np.zeros(ck.FINFO_LEN)
    ck.coupled_solve(ws.indptr, ws.indices, ws.diag, ws.tpos, data, b, ws.data_map, ws.factor_arrays, ws.solve_arrays,
                     ws.num.values, ws.num.buf, sparse_ldl.TINY, nf, G, np.ascontiguousarray(g, dtype=float), Cm, lo_,
                     hi_, dof, clo, cvert, warm.vertex, warm.rows, fric, tol, MAX_ITER, MAX_CHANGES if fric > 0 else 0,
                     TOL_V, STICK_V, z, F, lam, mu_lim, imp, svert, srows, ctol, info, finfo)
    it, facts = int(info[ck.INFO_ITER]), int(info[ck.INFO_FACTORS])
    if info[ck.INFO_STATUS] == ck.FACTOR_FAILED:
        e = sparse_ldl.pivot_error(ws.sym, ws.num, int(info[ck.INFO_PIVOT]), float(finfo[ck.FINFO_DMAX]))
        raise StepError("the coupled system of the skeleton and the deformables is singular "
                        f"(among: {', '.join(sorted(set(labels))[:6]) or 'the mesh'}): {e}")
    if info[ck.INFO_STATUS] == ck.BORDER_SINGULAR:
        raise StepError("the skeleton's rows (or held contact DOFs) are redundant or conflicting in "
                        f"the coupled solve (among: {', '.join(sorted(set(labels))[:6])})")
    converged = bool(info[ck.INFO_CONVERGED])
    if stats is not None:
        stats["contact_iterations"] = it
        stats["contact_factorisations"] = facts
        stats["contact_converged"] = converged
    if not converged:
        raise StepError(f"the floor contact solve of the deformables did not converge in {MAX_ITER} sub-problem "
                        f"solves ({int(info[ck.INFO_NORMAL])} vertices in contact, {int(info[ck.INFO_STUCK])} "
                        f"tangents stuck, {facts} factorisations)")
    c = int(info[ck.INFO_NSTATE])
    return CoupledSolution(z, lam, mu_lim, it, float(finfo[ck.FINFO_VIOLATION]), float(finfo[ck.FINFO_RESIDUAL]),
                           imp, ContactStates(svert[:c], srows[:c]), converged, facts, ctol)
