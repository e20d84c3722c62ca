"""Maximal point-to-point springs and joint springs: forces, 3x3 stiffness/damping and energy, one
formula for every pipeline (forces.py, tree_forces.py, energy.py, friction/bisp.py)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from redmax_ros.core.jit import njit
from redmax_ros.core.solvers.recursive import site_pos_kernel


def spring_forces(mech, X: np.ndarray, V: np.ndarray | None = None, arrays: SpringArrays | None = None):
    """Per spring, from the positions X (rows in mech.spring_rows): force on end a (P,3), 3x3 stiffness
    K (P,3,3), 3x3 damping D (P,3,3), lengths (P,). Shared by every pipeline (the compiled step calls
    :func:`spring_kernel` itself). ``arrays``: :func:`spring_arrays` of mech, when the caller keeps them.

    f_a = -k (l - L0) u,  K = k [u u^T + max(0, 1 - L0/l) (I - u u^T)],  D = c u u^T
    (notes §1.9.5 point-to-point force, §1.9.9 spring damper).
    The transverse (geometric) term is clamped at zero for compressed springs so that the LHS of
    Eq. (2) stays positive definite (a compressed spring's negative transverse stiffness would
    otherwise make the linear system indefinite).

    Springs with ``implicit: false`` (mech.spring_explicit) are explicit (notes §1.9: "for explicit
    integration we only need f and not K and D"): K = D = 0, so nothing of theirs enters the LHS of
    Eq. (2), and their whole force is evaluated at step k, f_a = -k (l - L0) u - c (u . (v_a - v_b)) u
    with the site velocities V (rows as X; needed only when such a spring has damping).
    """
    sa = spring_arrays(mech) if arrays is None else arrays
    P = len(sa.k)
    if V is None:
        if sa.needs_velocities:
            raise ValueError("explicit spring dampers need the site velocities V")
        V = _NO_V
    f, K, D, l = np.empty((P, 3)), np.empty((P, 3, 3)), np.empty((P, 3, 3)), np.empty(P)
    spring_kernel(np.ascontiguousarray(X, dtype=float), sa.a, sa.b, sa.k, sa.d, sa.rest, sa.explicit,
                  np.ascontiguousarray(V, dtype=float), f, K, D, l)
    return f, K, D, l


@dataclass(frozen=True, eq=False)
class SpringArrays:
    """The per-spring constants of :func:`spring_kernel` for a Mechanism (made once by :func:`spring_arrays`)."""
    a: np.ndarray  # (P,) int64 rows of end a in mech.jac_sites (contiguous)
    b: np.ndarray  # (P,) int64 rows of end b
    k: np.ndarray  # (P,) stiffness [N/m]
    d: np.ndarray  # (P,) damping [N s/m]
    rest: np.ndarray  # (P,) rest length [m]
    explicit: np.ndarray  # (P,) int64, 1 for implicit: false
    needs_velocities: bool  # :func:`needs_velocities`


def spring_arrays(mech) -> SpringArrays:
    """:class:`SpringArrays` of mech's maximal springs."""
    P = len(mech.spring_k)
    ex = getattr(mech, "spring_explicit", None)  # None: all implicit (also for stand-ins)
    ex = np.zeros(P, dtype=np.int64) if ex is None else np.asarray(ex, dtype=np.int64)
    rows = np.asarray(mech.spring_rows, dtype=np.int64).reshape(P, 2)
    return SpringArrays(rows[:, 0].copy(), rows[:, 1].copy(), np.asarray(mech.spring_k, float),
                        np.asarray(mech.spring_d, float), np.asarray(mech.spring_rest, float), ex,
                        needs_velocities(mech))


_NO_V = np.zeros((0, 3))


@njit
def spring_kernel(X, a, b, k, c, L0, explicit, V, f, K, D, l):
    """spring_forces' formulas for springs between rows a[s] and b[s] of X (P,): f (P,3), K and D (P,3,3),
    l (P,) written in place. V: site velocities (rows as X) for explicit dampers, or (0,3) when none is."""
    for s in range(a.shape[0]):
        d0 = X[a[s], 0] - X[b[s], 0]
        d1 = X[a[s], 1] - X[b[s], 1]
        d2 = X[a[s], 2] - X[b[s], 2]
        ls = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        l[s] = ls
        tiny = ls <= 1e-12
        safe = 1.0 if tiny else ls
        u0, u1, u2 = d0 / safe, d1 / safe, d2 / safe
        fk = -(k[s] * (ls - L0[s]))
        f[s, 0], f[s, 1], f[s, 2] = fk * u0, fk * u1, fk * u2
        if explicit[s]:
            K[s] = 0.0
            D[s] = 0.0
            if c[s] != 0.0:
                dv0 = V[a[s], 0] - V[b[s], 0]
                dv1 = V[a[s], 1] - V[b[s], 1]
                dv2 = V[a[s], 2] - V[b[s], 2]
                fd = c[s] * (u0 * dv0 + u1 * dv1 + u2 * dv2)
                f[s, 0] -= fd * u0
                f[s, 1] -= fd * u1
                f[s, 2] -= fd * u2
            continue
        trans = 1.0 if tiny else max(1.0 - L0[s] / safe, 0.0)
        u = (u0, u1, u2)
        for r in range(3):
            for q in range(3):
                uu = u[r] * u[q]
                K[s, r, q] = k[s] * (uu + trans * ((1.0 if r == q else 0.0) - uu))
                D[s, r, q] = c[s] * uu


@njit
def spring_state_kernel(R, p, jid, local, a, b, k, c, L0, explicit, V, h, X, f, K, D, l, pa, pb, C):
    """What the data-free step needs of its springs at the placements (R, p) in one call: the positions X of
    the sites (joint ``jid``, offset ``local``: mech.jac_sites, recursive.site_pos_kernel), :func:`spring_kernel`'s
    f, K, D, l, the end points pa = X[a], pb = X[b] [m] and the springs' LHS matrices C = h D + h^2 K of Eq. (2)
    (as solvers.pcg.MatrixFreeSystem.refresh forms them from K and D: the same products and sums)."""
    site_pos_kernel(R, p, jid, local, X)
    spring_kernel(X, a, b, k, c, L0, explicit, V, f, K, D, l)
    hh = h * h
    for s in range(a.shape[0]):
        for r in range(3):
            pa[s, r] = X[a[s], r]
            pb[s, r] = X[b[s], r]
            for q in range(3):
                C[s, r, q] = h * D[s, r, q] + hh * K[s, r, q]


SHIFT_SOFT = 0.1  # spring_shift: a compressed spring's negative transverse stiffness counts as soft below this


@njit
def spring_shift(X, a, b, k, L0, explicit, dX, ma, mb, hh, s, out):
    """BDF2 (step/scheme.py): out (3,) = K'_s (dX[a[s]] - dX[b[s]]), the change of spring s's force on end a
    from the site positions X - dX to X, to first order, so that f(x^) ~ f(x*) + K' (x* - x^) with
    dX = x* - x^ = J (q* (-) q^) (x* = X of q*). K' is the stiffness the LHS of the step has, spring_kernel's
    K = k [u u^T + max(0, 1 - L0/l) (I - u u^T)], when what the LHS misses of the exact Jacobian (a compressed
    spring's negative transverse stiffness k (1 - L0/l) < 0) is soft at this step, hh k (L0/l - 1) <=
    SHIFT_SOFT min(ma, mb) (hh = hat h^2; ma, mb the masses of the ends' bodies, inf for the world): then the
    step's spring force is f(x*) - K (x+ - x*), the linearisation about the predicted point, which errs by
    O(|x+ - x*|^2) = O(h^6) and by the missed stiffness times x+ - x* = O(h^3). Otherwise K' is the exact
    Jacobian k [u u^T + (1 - L0/l) (I - u u^T)] (and for explicit springs, which have no LHS stiffness, always):
    the force is then f(x^) to second order and the missed stiffness acts at q^ as in the linearisation about q^,
    which stays stable where treating a stiff missed part at the extrapolated q* does not (mass_springs
    k = 1e8: the ties compressed by 7 %)."""
    d0 = X[a[s], 0] - X[b[s], 0]
    d1 = X[a[s], 1] - X[b[s], 1]
    d2 = X[a[s], 2] - X[b[s], 2]
    e0 = dX[a[s], 0] - dX[b[s], 0]
    e1 = dX[a[s], 1] - dX[b[s], 1]
    e2 = dX[a[s], 2] - dX[b[s], 2]
    ls = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    if ls <= 1e-12:  # spring_kernel: K = k I
        out[0], out[1], out[2] = k[s] * e0, k[s] * e1, k[s] * e2
        return
    u0, u1, u2 = d0 / ls, d1 / ls, d2 / ls
    trans = 1.0 - L0[s] / ls
    if trans < 0.0 and not explicit[s] and hh * k[s] * (-trans) <= SHIFT_SOFT * min(ma, mb):
        trans = 0.0
    ue = u0 * e0 + u1 * e1 + u2 * e2
    out[0] = k[s] * (ue * u0 + trans * (e0 - ue * u0))
    out[1] = k[s] * (ue * u1 + trans * (e1 - ue * u1))
    out[2] = k[s] * (ue * u2 + trans * (e2 - ue * u2))


@njit
def spring_shift_kernel(X, a, b, k, L0, explicit, dX, ja, jb, mass, hh, out):
    """:func:`spring_shift` for every spring into out (P,3); ``mass`` (njoints,) the body mass per joint (the world,
    joint 0, counts as infinitely heavy), ``ja``, ``jb`` the joints of the spring ends."""
    for s in range(a.shape[0]):
        ma = np.inf if ja[s] == 0 else mass[ja[s]]
        mb = np.inf if jb[s] == 0 else mass[jb[s]]
        spring_shift(X, a, b, k, L0, explicit, dX, ma, mb, hh, s, out[s])


@njit
def linearisation_miss(pa, pb, X, a, b, k, explicit, ja, jb, mass, hh):
    """BDF2's order control for stiff maximal springs (step/scheme.accepts): how far the step's linearisation of
    the springs about the predicted q* misses at the result q+, as a displacement [m]: the largest over implicit
    springs s of hh k_s |l+ - l* - u* . (dx_a - dx_b)| / min(m_a, m_b). l*, u* the spring's length and direction
    at q* (its ends ``pa``, ``pb`` (P,3)), l+ its length at q+ (the sites ``X`` at q+, rows a[s], b[s]), dx the
    ends' displacements from q* to q+: the spring force the linear step left out, k times the length's error
    beyond first order (~ k |dx_perp|^2 / 2l for a miss dx_perp across the spring), turned into the displacement
    it causes in a step of hat h = sqrt(hh) on the lighter end's body (``mass`` per joint; the world, joint 0,
    is infinitely heavy). A miss of a few millimetres across a 1e6 N/m spring is a force error of tens of
    newtons, which the predictor's own miss in joint coordinates does not show (docs/bdf2.md)."""
    worst = 0.0
    for s in range(a.shape[0]):
        if explicit[s]:
            continue
        d0, d1, d2 = pa[s, 0] - pb[s, 0], pa[s, 1] - pb[s, 1], pa[s, 2] - pb[s, 2]
        ls = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        if ls <= 1e-12:
            continue
        n0, n1, n2 = X[a[s], 0] - X[b[s], 0], X[a[s], 1] - X[b[s], 1], X[a[s], 2] - X[b[s], 2]
        ln = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
        err = abs(ln - ls - ((n0 - d0) * d0 + (n1 - d1) * d1 + (n2 - d2) * d2) / ls)
        ma = np.inf if ja[s] == 0 else mass[ja[s]]
        mb = np.inf if jb[s] == 0 else mass[jb[s]]
        m = min(ma, mb)
        if m > 0.0 and m < np.inf:
            worst = max(worst, hh * k[s] * err / m)
    return worst


@njit
def geometric_blocks_kernel(ja, pa, jb, pb, f, explicit, scale, I, blocks):
    """The lever-arm (geometric) part of the full maximal spring stiffness K_m, added as per-body 6x6 blocks:
    blocks[j] += scale * B_j for each end of each implicit spring (end a: force f[s] at pa[s] on joint ja[s];
    end b: -f[s] at pb[s] on jb[s]; joint 0, the world, and massless joint bodies get nothing).

    A spring end is a world force f at a point x of a body; its wrench on the body depends on the body's
    rotation even at fixed f, through the lever arm r = x - c from the body's centre of mass c: the torque
    r x f turns with the body. Notes Eq. (1.32) and (1.44) give that derivative, the block [x][R^T f] of the
    rotational DOFs (Eq. 1.33, 1.43), non-symmetric; symmetrised (K = (K + K^T)/2, Baraff and Witkin 1998, as
    the notes do) it is the Hessian of the end's energy -f . x in the body's rotation about its centre of mass,
    -d^2(-f . x)/d theta^2 = sym([r][f]) = 1/2 (f r^T + r f^T) - (r . f) I. The rest of K_m, the change of the
    force with the end's position, is the Gauss-Newton part J_a^T K J_a of :func:`spring_kernel`'s 3x3 K.

    The maximal coordinates are the body's centre-of-mass velocity and angular velocity, both in world axes
    (notes §1.9: body-centred frames): in them the translational block of the lever term is zero. (With the
    translation in the rotating body frame, Eq. 1.44's literal reading, the symmetrised matrix would also couple
    translation to rotation by 1/2 [R^T f], a term of the frame, not of the spring, which is as large as the
    spring force: with stiff springs it makes the LHS indefinite at any practical step, docs/scenes.md.)
    Written at the world origin, twists (v_o, w), linear first, the coordinates of every 6x6 block of the
    pipelines (solvers/pcg.py), the block keeps that form (the centre-of-mass velocity is v_o + w x c and the
    translational rows are zero). In the positive-stiffness convention of Eq. (2)'s LHS (B = -d f_m / d q_m):

        B_j = sum over the ends on j of [[0, 0], [0, (r . f) I - 1/2 (f r^T + r f^T)]],   r = x - c_j

    ``I`` (njoints, 6, 6): the bodies' spatial inertias in the same coordinates (c_j = (I_53, I_32, I_40) / I_00);
    ``scale``: h^2 (Eq. 2) or 1 (K itself). Explicit springs (``explicit[s]``) add nothing, their K being 0."""
    for s in range(ja.shape[0]):
        if explicit[s]:
            continue
        for end in range(2):
            j = ja[s] if end == 0 else jb[s]
            if j == 0:
                continue
            m = I[j, 0, 0]
            if not m > 0.0:
                continue
            sg = scale if end == 0 else -scale
            x = pa[s] if end == 0 else pb[s]
            r0 = x[0] - I[j, 5, 1] / m
            r1 = x[1] - I[j, 3, 2] / m
            r2 = x[2] - I[j, 4, 0] / m
            f0, f1, f2 = sg * f[s, 0], sg * f[s, 1], sg * f[s, 2]
            rf = r0 * f0 + r1 * f1 + r2 * f2
            rs = (r0, r1, r2)
            fs = (f0, f1, f2)
            for a in range(3):
                for b in range(3):
                    blocks[j, 3 + a, 3 + b] += (rf if a == b else 0.0) - 0.5 * (fs[a] * rs[b] + rs[a] * fs[b])


LEVER_FLOOR = 0.5  # clamp_lever_blocks: each body's lever-arm block B_j >= -LEVER_FLOOR * (its spatial inertia)


@njit
def clamp_lever_blocks_into(I, B, T):
    """Keep the LHS of Eq. (2) positive definite under the lever-arm blocks: per joint j with a nonzero block,
    B_j (h^2-scaled, world frame, :func:`geometric_blocks_kernel`) is replaced by the nearest matrix with
    B_j >= -LEVER_FLOOR I_j in the metric of the body's spatial inertia I_j (world frame, same coordinates):
    with I_j = L L^T and L^-1 B_j L^-T = V diag(w) V^T, B_j <- L V diag(max(w, -LEVER_FLOOR)) V^T L^T.

    The lever-arm terms are the Hessian of a spring end's energy in its body's rotation, (r . f) I - sym(f r^T)
    (r from the body's centre of mass to the end): a force that pulls a lever arm inwards (r . f < 0) is a
    physical instability with negative stiffness, and once h^2 times that stiffness reaches the body's own
    inertia the linearly implicit step would divide by a vanishing or negative "mass" (an indefinite LHS, the
    step's velocity flipping sign). This clamp, like spring_kernel's clamp of the transverse term of compressed
    springs, leaves such a mode with at least half of its inertia: since every other term of the LHS is positive
    semi-definite, A >= J^T (I + B) J >= 1/2 M. It is idle (B_j unchanged, checked by one 6x6 Cholesky of
    I_j + B_j / LEVER_FLOOR) whenever the step resolves the lever instabilities, which covers every shipped scene
    (docs/scenes.md, "Full maximal spring stiffness"). Returns the number of blocks changed. ``T``: (6, 6) scratch (the
    compiled step's, so that it allocates nothing while the clamp is idle)."""
    nj = I.shape[0]
    changed = 0
    for j in range(1, nj):
        nz = False
        for a in range(6):
            for b in range(6):
                if B[j, a, b] != 0.0:
                    nz = True
        if not nz:
            continue
        for a in range(6):
            for b in range(6):
                T[a, b] = I[j, a, b] + B[j, a, b] / LEVER_FLOOR
        ok = True
        for c in range(6):  # Cholesky of T in place (lower), just to test positive definiteness
            s = T[c, c]
            for k in range(c):
                s -= T[c, k] * T[c, k]
            if not s > 0.0:
                ok = False
                break
            T[c, c] = np.sqrt(s)
            for r in range(c + 1, 6):
                t = T[r, c]
                for k in range(c):
                    t -= T[r, k] * T[c, k]
                T[r, c] = t / T[c, c]
        if ok:
            continue
        Ij = np.ascontiguousarray(I[j])
        w0 = np.linalg.eigvalsh(Ij)
        if not w0[0] > 0.0:  # a massless joint body: no metric to clamp in; drop its lever block
            B[j] = 0.0
            changed += 1
            continue
        L = np.linalg.cholesky(Ij)
        Li = np.linalg.inv(L)
        C = Li @ np.ascontiguousarray(B[j]) @ Li.T
        C = 0.5 * (C + C.T)
        w, V = np.linalg.eigh(C)
        for k in range(6):
            if w[k] < -LEVER_FLOOR:
                w[k] = -LEVER_FLOOR
        LV = L @ V
        B[j] = (LV * w) @ LV.T
        changed += 1
    return changed



@njit
def clamp_lever_blocks(I, B):
    """:func:`clamp_lever_blocks_into` with a scratch of its own."""
    return clamp_lever_blocks_into(I, B, np.empty((6, 6)))


def needs_velocities(mech) -> bool:
    """True when some spring is explicit (implicit: false) and has damping (spring_forces needs V)."""
    ex = getattr(mech, "spring_explicit", None)  # None: all implicit (also for stand-ins)
    return ex is not None and bool((ex & (mech.spring_d != 0.0)).any())


def spring_terms(mech, X: np.ndarray, J: np.ndarray, v: np.ndarray | None = None):
    """:func:`spring_forces` plus the Jacobian of the end difference (P,3,nv) from J (K,3,nv):
    returns (f_a, K, D, J_a - J_b, lengths). ``v`` (nv,) the reduced velocity at step k (site
    velocities V = J v, for explicit spring dampers)."""
    V = np.einsum("kin,n->ki", J, v) if v is not None and needs_velocities(mech) else None
    f, K, D, l = spring_forces(mech, X, V)
    return f, K, D, J[mech.spring_rows[:, 0]] - J[mech.spring_rows[:, 1]], l




def joint_displacement(mech, q: np.ndarray) -> np.ndarray:
    """q - q_rest on the configuration manifold (pin.difference), per velocity DOF."""
    return pin.difference(mech.model, mech.q_rest, q)


def spring_energy(mech, X, q) -> float:
    """E_spring [J]: maximal springs (ends at X, rows of mech.jac_sites) + joint springs at q, on pin.Data's
    site positions (the Context's path: :func:`point_spring_energy_kernel` + :func:`joint_spring_energy`)."""
    es = 0.0
    if len(mech.spring_ab):
        d = X[mech.spring_rows[:, 0]] - X[mech.spring_rows[:, 1]]
        l = np.sqrt(np.einsum("pi,pi->p", d, d))
        es += 0.5 * float(mech.spring_k @ (l - mech.spring_rest) ** 2)
    return es + joint_spring_energy(mech, q)


def joint_spring_energy(mech, q: np.ndarray, additive: bool = False) -> float:
    """1/2 sum_i k_i (q (-) q_rest)_i^2 [J] of the joint springs at q (0 without); ``additive``: every joint a
    vector space (tree_kinematics.Context.additive), where q (-) q_rest is q - q_rest (one compiled call)."""
    if not mech.has_stiffness:
        return 0.0
    if additive:
        return joint_energy_kernel(mech.stiffness, q, mech.q_rest)
    dq = joint_displacement(mech, q)
    return 0.5 * float(mech.stiffness @ (dq * dq))


@njit
def joint_energy_kernel(k, q, q_rest):
    """1/2 sum_i k_i (q_i - q_rest_i)^2 [J]: the joint springs' energy where every joint is a vector space."""
    e = 0.0
    for i in range(k.shape[0]):
        d = q[i] - q_rest[i]
        e += k[i] * (d * d)
    return 0.5 * e


@njit
def point_spring_energy_kernel(R, p, ja, oa, jb, ob, k, rest):
    """1/2 sum_s k_s (|x_a - x_b| - rest_s)^2 [J] of the maximal springs from the world placements (R, p) of
    their bodies: end points x = R[j] o + p[j] (o the site's offset in its joint's frame, joint 0 the world) as
    recursive.site_pos_kernel, no site array gathered."""
    e = 0.0
    for s in range(ja.shape[0]):
        i, j = ja[s], jb[s]
        dd = 0.0
        for a in range(3):
            xa = p[i, a] + R[i, a, 0] * oa[s, 0] + R[i, a, 1] * oa[s, 1] + R[i, a, 2] * oa[s, 2]
            xb = p[j, a] + R[j, a, 0] * ob[s, 0] + R[j, a, 1] * ob[s, 1] + R[j, a, 2] * ob[s, 2]
            dd += (xa - xb) * (xa - xb)
        x = np.sqrt(dd) - rest[s]
        e += k[s] * (x * x)
    return 0.5 * e
