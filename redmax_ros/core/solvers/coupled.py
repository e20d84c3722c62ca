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
system with one solve per changed DOF (_HeldSystem), refactorised only past MAX_CHANGES changes (with mu > 0;
a frictionless floor refactorises on each change, as before, which keeps restarts bit for bit).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from redmax_ros.core.errors import StepError
from redmax_ros.core.jit import njit
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


@dataclass
class CoupledSolution:
    z: np.ndarray  # (n,) reduced velocities (v_f, qdot_r)
    lam: np.ndarray  # (m,) multipliers of the skeleton's bilateral rows
    mu: np.ndarray  # (p,) multipliers of the joint-limit rows (0 when inactive)
    iterations: int
    violation: float  # max |G qdot_r - g|
    residual: float  # stationarity |A z + G^T lam + C^T mu - b - F - R| / |b|
    contact_impulse: np.ndarray  # (k,3) floor impulses on the contact vertices (beta_x, beta_y, alpha) [N s]
    # vertex in contact -> (stick_x, stick_y, sign_x, sign_y, alpha, the last step's alpha or NaN) (1/0, signs, N s)
    contact_state: dict = field(default_factory=dict)
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


class CSR:
    """A square matrix with values ``data`` in a CSR pattern (indptr, indices): ``A @ x`` by one compiled loop.
    (scipy.sparse.csr_matrix costs ~35 us to construct and ~25 us a product on the starfish's reduced system,
    this ~8 us a product and nothing to construct.)"""

    __slots__ = ("indptr", "indices", "data")

    def __init__(self, indptr, indices, data):
        self.indptr, self.indices, self.data = indptr, indices, data

    def __matmul__(self, x):
        out = np.empty(len(self.indptr) - 1)
        csr_matvec(self.indptr, self.indices, self.data, np.ascontiguousarray(x, dtype=float), out)
        return out


@njit
def csr_matvec(indptr, indices, data, x, out):
    for i in range(len(indptr) - 1):
        acc = 0.0
        for e in range(indptr[i], indptr[i + 1]):
            acc += data[e] * x[indices[e]]
        out[i] = acc


class Workspace:
    """Per-pattern state of the coupled solve: the reduced CSR pattern, its symbolic LDL^T analysis (minimum
    degree, once), the diagonal and transpose maps used to hold DOFs, and the numeric factor's storage."""

    def __init__(self, indptr, indices, n):
        self.indptr, self.indices, self.n = indptr, indices, n
        self.diag, self.tpos = _pattern_maps(indptr, indices, n)
        self.held = np.empty(len(indices))  # _held's output
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
    """data with the rows and columns of ``fixed_dofs`` replaced by the identity (in ws.held, reused: a Factor
    reads it into its own storage)."""
    if not len(fixed_dofs):
        return data
    held_kernel(ws.indptr, ws.tpos, ws.diag, data, np.asarray(fixed_dofs, dtype=np.int64), ws.held)
    return ws.held


@njit
def held_kernel(indptr, tpos, diag, data, dofs, out):
    out[:] = data
    for j in dofs:
        for e in range(indptr[j], indptr[j + 1]):
            out[e] = 0.0
            out[tpos[e]] = 0.0
    for j in dofs:
        out[diag[j]] = 1.0


class _HeldSystem:
    """The reduced system with a set H of DOFs held at given velocities and the skeleton rows W = [G; active
    limit rows] W z_r = w by multipliers. One LDL^T per *base* held set H0 (identity rows, ``_held``;
    ``factorisations`` counts them); a held set H that differs from H0 by a few DOFs (added: held now, free in
    H0; released: free now, held in H0) is solved on the base factor by a small capacitance system instead of a
    new factorisation (Woodbury / bordered system, Golub & Van Loan §2.1.4): with A~0 the base matrix,

        z = z0 - Y0 lam + sum_a w_a mu_a + sum_j u_j y_j,    z0 = A~0^-1 f0,  Y0 = A~0^-1 W^T,
        w_a = A~0^-1 e_a (a added, mu_a its reaction),    u_j = e_j - A~0^-1 P0 A e_j (j released, y_j = z_j - v_j),

    P0 the projection off H0, and the multipliers from W z_r = w, z_a = v_a, (A z)_j = rhs_j: one base solve per
    changed DOF (kept while the base stands). The base is refactorised when more than ``max_changes`` DOFs
    differ (0: on every change, so the solution is that of the final held set's own factorisation whatever the
    path, as on a frictionless floor, where a restarted run then equals a continuing one bit for bit)."""

    def __init__(self, ws, data, n_r, G, g, labels, max_changes=MAX_CHANGES):
        self.max_changes = max_changes
        self.ws, self.data, self.n, self.nf = ws, data, ws.n, ws.n - n_r
        self.G, self.g, self.labels = G, g, labels
        self.A = CSR(ws.indptr, ws.indices, data)
        self.factor = None
        self.factorisations = 0
        self.rows = np.zeros((0, n_r))

    def _rebase(self, fixed, vals):
        self.factor = Factor(self.ws, _held(self.ws, self.data, fixed), self.labels)
        self.factorisations += 1
        self.H0, self.v0 = fixed, vals
        self.in_h0 = np.zeros(self.n, dtype=bool)
        self.in_h0[fixed] = True
        u = np.zeros(self.n)
        u[fixed] = vals
        self.Au = self.A @ u if len(fixed) else None
        self.cols = {}  # ("add" | "rel", dof) -> column of the bordered system on this base
        self.key = None
        self.rows_a = {}  # dof -> dense row of A
        self.schur_key = None

    def _row(self, j):
        r = self.rows_a.get(j)
        if r is None:
            a, e = self.ws.indptr[j], self.ws.indptr[j + 1]
            r = np.zeros(self.n)
            r[self.ws.indices[a:e]] = self.data[a:e]
            self.rows_a[j] = r
        return r

    def _col(self, kind, j):
        c = self.cols.get((kind, j))
        if c is None:
            if kind == "add":
                e = np.zeros(self.n)
                e[j] = 1.0
                c = self.factor.solve(e)
            else:
                a = self._row(j).copy()  # A e_j (A symmetric), off H0
                a[self.in_h0] = 0.0
                c = -self.factor.solve(a)
                c[j] += 1.0
            self.cols[(kind, j)] = c
        return c

    def solve(self, fixed, vals, rhs, W, w, wkey):
        """(z, lam, mu_W): A z + [0; G^T lam + W^T mu_W] = rhs on the DOFs off ``fixed``, z[fixed] = vals,
        G z_r = g, W z_r = w. The bordered system is kept while ``fixed`` and ``wkey`` (the limit rows) stand."""
        key = (fixed.tobytes(), wkey)
        if self.factor is None:
            self._rebase(fixed, vals)
        if key != self.key:
            in_h = np.zeros(self.n, dtype=bool)
            in_h[fixed] = True
            sel = ~self.in_h0[fixed]
            add, v_add = fixed[sel], vals[sel]
            rel = self.H0[~in_h[self.H0]]
            if len(add) + len(rel) > self.max_changes:
                self._rebase(fixed, vals)
                add, v_add, rel = fixed[:0], vals[:0], fixed[:0]
            nw = len(self.g) + (0 if W is None else len(W))
            if self.schur_key != wkey:
                self.rows = self.G if W is None else np.vstack([self.G, W])
                Gt = np.zeros((self.n, nw))
                Gt[self.nf:] = self.rows.T
                self.Y = self.factor.solve(Gt) if nw else np.zeros((self.n, 0))
                self.schur_key = wkey
            self.add, self.v_add, self.rel, self.nw = add, v_add, rel, nw
            if nw or len(add) or len(rel):
                self.Z = np.column_stack([-self.Y] + [self._col("add", int(a)) for a in add]
                                         + [self._col("rel", int(j)) for j in rel])
                self.R = np.array([self._row(int(j)) for j in rel]).reshape(len(rel), self.n)
                try:
                    self.Kinv = np.linalg.inv(self._border(self.Z))
                except np.linalg.LinAlgError:
                    raise StepError("the skeleton's rows (or held contact DOFs) are redundant or conflicting in "
                                    f"the coupled solve (among: {', '.join(sorted(set(self.labels))[:6])})") from None
            self.key = key
        f0 = rhs
        if self.Au is not None:
            f0 = rhs - self.Au
            f0[self.H0] = self.v0
        z0 = self.factor.solve(f0)
        m = len(self.g)
        if not self.nw and not len(self.add) and not len(self.rel):
            return z0, np.zeros(0), np.zeros(0)
        beta = np.concatenate([self.g if W is None else np.concatenate([self.g, w]), self.v_add, rhs[self.rel]])
        c = self.Kinv @ (beta - self._border(z0))
        return z0 + self.Z @ c, c[:m], c[m:self.nw]

    def _border(self, X):
        """The bordered rows applied to X: W X_r, X on the added DOFs, A X on the released ones."""
        return np.concatenate([self.rows @ X[self.nf:], X[self.add], self.R @ X])


def solve(ws: Workspace, data, b, n_r, G, g, C=None, lo=None, hi=None, contacts: VertexContacts | None = None,
          warm=None, labels=(), tol=1e-12, stats=None) -> CoupledSolution:
    """The coupled solve on the reduced system (values ``data`` in ws's CSR pattern, right-hand side b (n,)):
    G (m, n_r) dense with g (m,), joint-limit rows C (p, n_r) with lo, hi (+-inf where open) or None, the
    floor ``contacts`` of free vertices or None, ``warm`` the last step's contact states (vertex -> state, as
    CoupledSolution.contact_state). ``stats`` (a dict or None) receives ``contact_iterations`` (sub-problem
    solves), ``contact_factorisations`` and ``contact_converged``. Raises StepError when the contact iteration
    does not converge within MAX_ITER sub-problem solves (the caller's state is then left as it was)."""
    n = ws.n
    nf = n - n_r
    p = 0 if C is None else len(lo)
    k = 0 if contacts is None else len(contacts.dof)
    scale = 1.0 + float(np.abs(b).max()) if n else 1.0
    tol_imp = tol * scale
    fric = 0.0 if contacts is None else float(contacts.mu)
    hs = _HeldSystem(ws, data, n_r, G, g, labels, MAX_CHANGES if fric > 0 else 0)
    A = hs.A
    # contact state; the tangents are flat, slot 2 i + c for vertex i, world axis c (x, y)
    normal = np.zeros(k, dtype=bool)  # v_z = lo held (alpha >= 0)
    stick = np.zeros(2 * k, dtype=bool)  # tangent held at 0 (|beta| <= mu alpha)
    sign = np.zeros(2 * k)  # sign of a sliding tangent's friction impulse (its velocity has the other sign)
    alpha = np.zeros(k)  # the normal impulse the friction bound mu alpha uses [N s]
    known = np.zeros(k, dtype=bool)  # alpha computed (this step or the last): stuck tangents may be released
    prev = np.full(k, np.nan)  # the last step's normal impulse of the contacts it had
    if k:
        ndof = contacts.dof + 2
        tdof = (contacts.dof[:, None] + np.arange(2)).ravel()
        cdof = (contacts.dof[:, None] + np.arange(3)).ravel()  # the contact vertices' DOFs (x, y, z)
        a0, a1 = ws.indptr[cdof], ws.indptr[cdof + 1]  # their CSR rows, gathered once: the reactions there
        lens = a1 - a0
        c_start = np.concatenate([[0], np.cumsum(lens)[:-1]])
        pos = np.repeat(a0 - c_start, lens) + np.arange(lens.sum())
        c_val, c_col = data[pos], ws.indices[pos]
        diag = data[ws.diag][contacts.dof]  # A_xx of each contact vertex: impulse -> velocity
        if warm:
            hit = [(i, warm[v]) for i, v in enumerate(contacts.vertex.tolist()) if v in warm]
            if hit:
                ii = np.array([h[0] for h in hit])
                W = np.array([h[1] for h in hit], dtype=float)  # rows (stick_x, stick_y, sign_x, sign_y, alpha, prev)
                normal[ii] = known[ii] = True
                stick[2 * ii], stick[2 * ii + 1] = W[:, 0] > 0, W[:, 1] > 0
                sign[2 * ii], sign[2 * ii + 1] = W[:, 2], W[:, 3]
                # alpha extrapolated from the last two steps' (when both had the contact)
                alpha[ii] = np.where(np.isnan(W[:, 5]), W[:, 4], np.maximum(2.0 * W[:, 4] - W[:, 5], 0.0))
                prev[ii] = W[:, 4]
            if fric <= 0:
                stick[:] = False

    def reactions(z, F):  # (k, 3) A z - b - F on the contact vertices' DOFs
        return (np.add.reduceat(c_val * z[c_col], c_start) - b[cdof] - F[cdof]).reshape(k, 3)

    F = np.zeros(n)
    active = {}  # limit row -> bound it is held at
    idx, wvals, wkey = np.zeros(0, np.int64), np.zeros(0), b""
    mu_lim = np.zeros(p)
    z = lam = muW = rc = None
    fixed, vals = np.zeros(0, np.int64), np.zeros(0)
    slide = n2 = np.zeros(2 * k, dtype=bool)
    dirty = True
    face = 0  # counts the friction stage's state changes (the Anderson history below is per state)
    hist = None
    converged = False
    it = 0
    while it < MAX_ITER:
        # friction stage (Eq. 12 with alpha fixed; normal working set and limit rows held): primal active set
        # with descent on min 1/2 z^T A z - (b + N^T alpha)^T z + sum_j mu alpha_j |z_j| over the tangents
        bound = np.repeat(fric * alpha, 2)
        releasable = np.repeat(normal & known, 2)  # stuck tangents whose bound is known (normal, known change below)
        done = False
        while it < MAX_ITER:
            it += 1
            if k:
                if dirty:
                    fixed, vals = _fixed(contacts, normal, stick)
                    n2 = np.repeat(normal, 2)
                    if fric > 0:
                        slide = n2 & ~stick
                    dirty = False
                F[tdof] = np.where(slide, sign * bound, 0.0)  # the sub-problem's linear term
            zs, lam, muW = hs.solve(fixed, vals, b + F, C[idx] if len(idx) else None, wvals, wkey)
            if not k:
                z = zs
                done = True
                break
            zt_s = zs[tdof]
            wrong = slide & (zt_s * sign > 0)  # moving along its friction impulse in the sub-problem
            if z is None:  # first solve: the warm state's face; a wrong-way slider sticks (z_j = 0)
                z = zs
                if wrong.any():
                    stick |= wrong
                    z[tdof[wrong]] = 0.0
                    dirty = True
                    face += 1
                    continue
            elif wrong.any():  # exact line search to zs, stopping at the first slider that reaches 0
                zt = z[tdof]
                tj = np.full(2 * k, np.inf)
                tj[wrong] = np.clip(zt[wrong] / (zt[wrong] - zt_s[wrong]), 0.0, 1.0)  # zt sign <= 0 < zt_s sign
                tb = float(tj.min())
                z += tb * (zs - z)
                hit = wrong & ((tj <= tb) | (np.abs(z[tdof]) <= STICK_V))
                stick |= hit
                z[tdof[hit]] = 0.0
                dirty = True
                face += 1
                continue
            else:
                z = zs
            rc = reactions(z, F)
            if fric > 0:
                held_t = stick & releasable
                if held_t.any():  # the stuck tangent whose reaction most exceeds its bound slides
                    rt = rc[:, :2].ravel()
                    excess = np.where(held_t, np.abs(rt) - bound, -np.inf)
                    j = int(np.argmax(excess))
                    if excess[j] > tol_imp:
                        stick[j] = False
                        sign[j] = np.sign(rt[j])
                        dirty = True
                        face += 1
                        continue
            done = True
            break
        if not done:
            break
        # normal stage (Alg. 2 line 9, the friction impulses fixed): v_z >= lo with alpha >= 0; joint limits
        changed = False
        if p:
            mu_lim = np.zeros(p)
            mu_lim[idx] = muW
            for j, i in enumerate(idx):  # limits: release rows whose multiplier pulls, hold violated ones
                lower = active[i] == lo[i]
                if (lower and muW[j] > tol_imp) or (not lower and muW[j] < -tol_imp):
                    del active[i]
                    mu_lim[i] = 0.0
                    changed = True
            Cv = C @ z[nf:]
            for i in np.nonzero((Cv < lo - 1e-12) | (Cv > hi + 1e-12))[0]:
                if i not in active:
                    active[int(i)] = lo[i] if Cv[i] < lo[i] else hi[i]
                    changed = True
            if changed:
                idx = np.fromiter(active, dtype=np.int64, count=len(active))
                wvals, wkey = np.array([active[i] for i in idx]), idx.tobytes()
        moved = 0.0
        if k:
            a_new = rc[:, 2]
            off = normal & (a_new < -tol_imp)  # the floor would pull: released
            on = ~normal & (z[ndof] < contacts.lo - 1e-12)  # below the floor's bound: held
            keep = normal & ~off
            a_new = np.maximum(a_new, 0.0)
            if fric > 0:  # Alg. 2 line 12: the velocity change the bound's change makes on the sliding tangents
                sl = keep & ~(stick[0::2] & stick[1::2])
                if sl.any():
                    moved = float((fric * np.abs(a_new[sl] - alpha[sl]) / diag[sl]).max())
                # a stuck tangent is unaffected by its bound unless the new bound no longer holds it
                held_t = stick & np.repeat(keep, 2)
                if held_t.any() and (np.abs(rc[:, :2].ravel()) - np.repeat(fric * a_new, 2))[held_t].max() > tol_imp:
                    changed = True
            nxt = a_new.copy()
            if fric > 0 and not off.any() and not on.any():  # Anderson(1) on the fixed point alpha = G(alpha)
                res_k = fric * (a_new - alpha) / diag  # its residual as velocities [m/s]
                if hist is not None and hist[2] == face and hist[3] == keep.tobytes():
                    dr = res_k - hist[1]
                    dd = float(dr @ dr)
                    if dd > 0.0:
                        nxt = np.maximum(a_new - (float(res_k @ dr) / dd) * (a_new - hist[0]), 0.0)
                hist = (a_new, res_k, face, keep.tobytes())
            else:
                hist = None
            alpha[keep] = nxt[keep]
            known[keep] = True
            if off.any():
                normal[off] = False
                off2 = np.repeat(off, 2)
                stick[off2] = False
                sign[off2] = 0.0
                alpha[off] = 0.0
                known[off] = False
                changed = True
            if on.any():  # new contacts slide along their tangential velocity (stick if it is ~0)
                normal[on] = True
                z[ndof[on]] = contacts.lo[on]
                on2 = np.repeat(on, 2)
                zt = z[tdof[on2]]
                st = (np.abs(zt) <= STICK_V) & (fric > 0)
                stick[on2] = st
                sign[on2] = np.where(st, 0.0, -np.sign(zt))
                z[tdof[on2]] = np.where(st, 0.0, zt)
                alpha[on] = 0.0
                known[on] = False
                changed = True
            dirty |= changed
        if not changed and moved <= TOL_V:
            converged = True
            break
    if stats is not None:
        stats["contact_iterations"] = it
        stats["contact_factorisations"] = hs.factorisations
        stats["contact_converged"] = converged
    if not converged:
        raise StepError(f"the floor contact solve of the deformables did not converge in {MAX_ITER} sub-problem "
                        f"solves ({int(normal.sum())} vertices in contact, {int(stick.sum())} tangents stuck, "
                        f"{hs.factorisations} factorisations)")
    r = A @ z - b - F
    imp = np.zeros((k, 3))
    if k:
        stick2 = stick.reshape(k, 2)
        imp[:, 2] = np.where(normal, r[ndof], 0.0)
        rt, Ft = r[tdof].reshape(k, 2), F[tdof].reshape(k, 2)
        imp[:, :2] = np.where(normal[:, None] & stick2, rt, np.where(normal[:, None], Ft, 0.0))
    res = r.copy()
    if k:
        res[(fixed if not dirty else _fixed(contacts, normal, stick)[0])] = 0.0
    m = len(g)
    if m:
        res[nf:] += G.T @ lam
    if p:
        res[nf:] += C.T @ mu_lim
    state = {}
    if k and normal.any():
        rows = np.column_stack([stick[0::2], stick[1::2], sign[0::2], sign[1::2], np.maximum(imp[:, 2], 0.0),
                                prev])[normal]
        state = dict(zip(contacts.vertex[normal].tolist(), map(tuple, rows.tolist())))
    viol = float(np.abs(G @ z[nf:] - g).max()) if m else 0.0
    return CoupledSolution(z, lam, mu_lim, it, viol, float(np.linalg.norm(res) / max(np.linalg.norm(b), 1e-300)),
                           imp, state, converged, hs.factorisations, TOL_V * diag if k else np.zeros(0))


def _fixed(contacts, normal, stick):
    """(held DOFs (sorted), their velocities): v_z = lo for a held normal, v_x / v_y = 0 for a sticking tangent
    (``stick`` flat, slot 2 i + c)."""
    st = stick & np.repeat(normal, 2)
    d = np.concatenate([contacts.dof[normal] + 2, (contacts.dof[:, None] + np.arange(2)).ravel()[st]])
    v = np.concatenate([contacts.lo[normal], np.zeros(int(st.sum()))])
    o = np.argsort(d)
    return d[o].astype(np.int64), v[o]
