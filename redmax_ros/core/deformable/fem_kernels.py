"""Compiled co-rotated linear FEM of linear tetrahedra: the one implementation of fem.py's formulas (Sifakis &
Barbic, "FEM Simulation of 3D Deformable Solids", SIGGRAPH 2012 course, §3.4-§4; fem.py's docstring has the
equations). Units: positions [m], Lamé parameters mu, lambda [Pa], volumes [m^3], forces [N], stiffness
[N/m], energy [J].

Per tetrahedron t with vertices tet (4,) and shape gradients b_a = B[t, a] (4,3) [1/m]:

* F = sum_a x_a b_a^T (``deformation_gradient``);
* F = R S, R the proper rotation with the reflection of an inverted F moved to the smallest singular value
  (``polar3``; the convention of Irving, Teran & Fedkiw, "Invertible finite elements for robust simulation
  of large deformation", SCA 2004): Newton's polar iteration where F is neither inverted nor near flat
  (``newton_polar3``, there the polar factor is that rotation), else the SVD F = U Sigma V^T from a cyclic
  Jacobi eigen-decomposition of F^T F with U's last column u_1 x u_2, so that det U = det V = +1;
* P = 2 mu (F - R) + lambda tr(R^T F - I) R, Psi = mu |F - R|^2 + lambda/2 tr^2(R^T F - I), f_a = -V P b_a
  (``lane_stress``);
* the exact K_e = -df_e/dx_e (``tet_blocks_lanes``), written in the rotated frame with c_a = R b_a and
  Sh = R S R^T = F R^T: the block of vertex rows p and vertex columns q is

      K_pq = V [2 mu (b_p . b_q) I + lambda c_p c_q^T + (lambda tr(S - I) - 2 mu) [c_p]_x^T Ah [c_q]_x],

  Ah = (tr S I - Sh)^-1. It is fem.py's K[(p,d),(q,c)] = V [... + coef (R (w_qc x b_p))_d] with
  w_qc = (tr S I - S)^-1 (b_q x r_c): (R (w x b_p))_d = (b_q x r_c)^T (tr S I - S)^-1 (b_p x r_d) and
  b x r_c = R^T (c x e_c).
"""
from __future__ import annotations

import numpy as np

from redmax_ros.core.deformable.sparsity import add_block_strided
from redmax_ros.core.jit import drop_stale_caches, njit, njit_inline

# the kernels below inline sparsity.add_block_strided: an edit of sparsity.py recompiles them
drop_stale_caches("deformable/fem_kernels.py", ("deformable/fem_kernels.py", "deformable/sparsity.py", "jit.py"))


@njit_inline
def deformation_gradient(x, tet, Bt, F):
    """F (3,3) = sum_a x_a b_a^T of one tetrahedron: x (n,3) [m], tet (4,) vertex indices, Bt (4,3) [1/m]."""
    for i in range(3):
        for k in range(3):
            s = 0.0
            for a in range(4):
                s += x[tet[a], i] * Bt[a, k]
            F[i, k] = s


@njit_inline
def jacobi_rotate(A, V, p, q, r):
    """One Jacobi rotation zeroing A[p, q] of the symmetric 3 x 3 A (r the third index), accumulated into V
    (Golub & Van Loan, Matrix Computations, 4th ed. 2013, §8.5.2; Rutishauser's stable tangent)."""
    apq = A[p, q]
    if apq == 0.0:
        return
    theta = (A[q, q] - A[p, p]) / (2.0 * apq)
    at = abs(theta)
    t = 0.5 / at if at > 1e150 else 1.0 / (at + np.sqrt(at * at + 1.0))
    if theta < 0.0:
        t = -t
    c = 1.0 / np.sqrt(t * t + 1.0)
    s = t * c
    A[p, p] -= t * apq
    A[q, q] += t * apq
    A[p, q] = 0.0
    A[q, p] = 0.0
    arp, arq = A[r, p], A[r, q]
    A[r, p] = A[p, r] = c * arp - s * arq
    A[r, q] = A[q, r] = s * arp + c * arq
    for k in range(3):
        vkp, vkq = V[k, p], V[k, q]
        V[k, p] = c * vkp - s * vkq
        V[k, q] = s * vkp + c * vkq


@njit_inline
def sym_eigen3(A, V):
    """Cyclic Jacobi of a symmetric 3 x 3 A in place: A's diagonal becomes the eigenvalues, V's columns the
    eigenvectors (A_in = V diag(A) V^T, V orthogonal); sweeps until the off-diagonal is below 1e-17 of the
    diagonal (quadratic convergence: 2-4 sweeps)."""
    for i in range(3):
        for j in range(3):
            V[i, j] = 1.0 if i == j else 0.0
    for _ in range(40):
        off = A[0, 1] * A[0, 1] + A[0, 2] * A[0, 2] + A[1, 2] * A[1, 2]
        if off <= 1e-34 * (A[0, 0] * A[0, 0] + A[1, 1] * A[1, 1] + A[2, 2] * A[2, 2]):
            return
        jacobi_rotate(A, V, 0, 1, 2)
        jacobi_rotate(A, V, 0, 2, 1)
        jacobi_rotate(A, V, 1, 2, 0)


@njit_inline
def cross_into(a0, a1, a2, b0, b1, b2, out):
    """out (3,) = a x b."""
    out[0] = a1 * b2 - a2 * b1
    out[1] = a2 * b0 - a0 * b2
    out[2] = a0 * b1 - a1 * b0


@njit_inline
def newton_polar3(F, R):
    """R := the orthogonal polar factor of F by Newton's iteration R <- (R + R^-T) / 2 (Higham, "Computing
    the polar decomposition - with applications", SIAM J. Sci. Stat. Comput. 7, 1986, §3), R^-T = cof(R) /
    det R, in registers. Stops when a step is below 1e-8 in the Frobenius norm (quadratic convergence: the
    error is then ~ step^2 / 2 < 1e-16). Returns False, R untouched, unless det F > 1e-2 (|F|_F^2 / 3)^(3/2)
    (F neither inverted, where the proper rotation is not the polar factor, nor near flat; the ratio is 1 for
    a rotation) and the iteration converged in 30 steps (about 14 from the worst accepted F, 3-4 at strains
    of 1e-2 without scaling); ``polar3`` then takes the SVD route."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = (F[0, 0], F[0, 1], F[0, 2], F[1, 0], F[1, 1], F[1, 2],
                                                   F[2, 0], F[2, 1], F[2, 2])
    n2 = r00 * r00 + r01 * r01 + r02 * r02 + r10 * r10 + r11 * r11 + r12 * r12 + r20 * r20 + r21 * r21 + r22 * r22
    det = r00 * (r11 * r22 - r12 * r21) + r01 * (r12 * r20 - r10 * r22) + r02 * (r10 * r21 - r11 * r20)
    if not (det > 0.0 and det * det > 1e-4 * (n2 / 3.0) ** 3):
        return False
    for _ in range(30):
        c00, c01, c02 = r11 * r22 - r12 * r21, r12 * r20 - r10 * r22, r10 * r21 - r11 * r20
        c10, c11, c12 = r02 * r21 - r01 * r22, r00 * r22 - r02 * r20, r01 * r20 - r00 * r21
        c20, c21, c22 = r01 * r12 - r02 * r11, r02 * r10 - r00 * r12, r00 * r11 - r01 * r10
        b = 0.5 / (r00 * c00 + r01 * c01 + r02 * c02)
        s00, s01, s02 = 0.5 * r00 + b * c00, 0.5 * r01 + b * c01, 0.5 * r02 + b * c02
        s10, s11, s12 = 0.5 * r10 + b * c10, 0.5 * r11 + b * c11, 0.5 * r12 + b * c12
        s20, s21, s22 = 0.5 * r20 + b * c20, 0.5 * r21 + b * c21, 0.5 * r22 + b * c22
        step2 = ((s00 - r00) ** 2 + (s01 - r01) ** 2 + (s02 - r02) ** 2 + (s10 - r10) ** 2 + (s11 - r11) ** 2
                 + (s12 - r12) ** 2 + (s20 - r20) ** 2 + (s21 - r21) ** 2 + (s22 - r22) ** 2)
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = s00, s01, s02, s10, s11, s12, s20, s21, s22
        if step2 <= 1e-16:
            R[0, 0], R[0, 1], R[0, 2] = r00, r01, r02
            R[1, 0], R[1, 1], R[1, 2] = r10, r11, r12
            R[2, 0], R[2, 1], R[2, 2] = r20, r21, r22
            return True
    return False


@njit_inline
def polar3(F, R, C, V):
    """R (3,3): the proper rotation of F = R S (det R = +1; for det F < 0 the reflection is moved to the
    smallest singular value, S then has one negative eigenvalue). C, V (3,3) scratch. Route: V Lambda V^T =
    F^T F (``sym_eigen3``), u_1 = F v_1 / |F v_1|, u_2 = F v_2 orthogonalised against u_1 and normalised,
    u_3 = u_1 x u_2, v_3 = v_1 x v_2 (v_1, v_2 the eigenvectors of the two largest eigenvalues), R = U V^T.
    Only v_1, v_2, u_1, u_2 enter, so a near-flat F (sigma_3 -> 0) keeps full accuracy; F = 0 gives R = I,
    a rank-1 F (sigma_2 <= 1e-15 sigma_1) a proper R with R v_1 = u_1. Well-conditioned, non-inverted F
    (nearly every element of a simulation) take ``newton_polar3`` first: on the starfish's 372 tetrahedra
    32 us against 137 us for this route (CPU, measured)."""
    if newton_polar3(F, R):
        return
    for i in range(3):
        for j in range(i, 3):
            s = F[0, i] * F[0, j] + F[1, i] * F[1, j] + F[2, i] * F[2, j]
            C[i, j] = s
            C[j, i] = s
    sym_eigen3(C, V)
    o0, o1, o2 = 0, 1, 2
    if C[o1, o1] > C[o0, o0]:
        o0, o1 = o1, o0
    if C[o2, o2] > C[o1, o1]:
        o1, o2 = o2, o1
    if C[o1, o1] > C[o0, o0]:
        o0, o1 = o1, o0
    # C's rows 0-1 now hold u_1, u_2; R's rows v_1, v_2, v_3 (V's columns o0, o1 and their cross product)
    for k in range(3):
        R[0, k] = V[k, o0]
        R[1, k] = V[k, o1]
    cross_into(R[0, 0], R[0, 1], R[0, 2], R[1, 0], R[1, 1], R[1, 2], R[2])
    for m in range(2):
        for i in range(3):
            C[m, i] = F[i, 0] * R[m, 0] + F[i, 1] * R[m, 1] + F[i, 2] * R[m, 2]
    n1 = np.sqrt(C[0, 0] ** 2 + C[0, 1] ** 2 + C[0, 2] ** 2)
    if n1 == 0.0:  # F = 0
        for i in range(3):
            for j in range(3):
                R[i, j] = 1.0 if i == j else 0.0
        return
    for i in range(3):
        C[0, i] /= n1
    for _ in range(2):  # Gram-Schmidt, twice ("twice is enough": Parlett, The Symmetric Eigenvalue Problem, §6-9)
        d = C[0, 0] * C[1, 0] + C[0, 1] * C[1, 1] + C[0, 2] * C[1, 2]
        for i in range(3):
            C[1, i] -= d * C[0, i]
    n2 = np.sqrt(C[1, 0] ** 2 + C[1, 1] ** 2 + C[1, 2] ** 2)
    if n2 <= 1e-15 * n1:  # rank 1 to round-off: any unit vector normal to u_1 (u_1 x its smallest axis)
        k = 0
        for i in range(1, 3):
            if abs(C[0, i]) < abs(C[0, k]):
                k = i
        e0, e1, e2 = 1.0 if k == 0 else 0.0, 1.0 if k == 1 else 0.0, 1.0 if k == 2 else 0.0
        cross_into(C[0, 0], C[0, 1], C[0, 2], e0, e1, e2, C[1])
        n2 = np.sqrt(C[1, 0] ** 2 + C[1, 1] ** 2 + C[1, 2] ** 2)
    for i in range(3):
        C[1, i] /= n2
    cross_into(C[0, 0], C[0, 1], C[0, 2], C[1, 0], C[1, 1], C[1, 2], C[2])
    for i in range(3):  # R = U V^T = sum_m u_m v_m^T (V^T's rows sit in R: read them before overwriting)
        for j in range(3):
            V[i, j] = C[0, i] * R[0, j] + C[1, i] * R[1, j] + C[2, i] * R[2, j]
    for i in range(3):
        for j in range(3):
            R[i, j] = V[i, j]


# Stress, energy, forces and stiffness of LANES tetrahedra at a time (``stress_lanes``, ``tet_blocks_lanes``) in
# one flat scratch array S, row r of lane l at S[r * LANES + l]: every access an offset from one base known at
# compile time, so the compiler sees the rows do not overlap and vectorises the loops over the lanes (rows of
# separate arrays: it did not). Each number is the same expression, in the same order, as in the
# tetrahedron-by-tetrahedron code these replace (tet_stress, tet_energy_density, add_tet_forces, tet_blocks),
# so the same bits: fem_add on the starfish's 372 tetrahedra 108.8 -> 70.6 us (CPU, alternating blocks of 25
# calls in one process, medians of 200).
LANES = 16
S_F, S_R, S_B, S_VOL = 0, 9, 18, 30  # inputs: F, R (row-major), b_0..b_3 (S_B + 3 a + k), the volume
S_TRS, S_P, S_EN, S_FA = 31, 32, 41, 42  # tr S; P (row-major); V Psi; scale V (P b_a)_i at S_FA + 3 a + i
S_AH, S_CR, S_N = 54, 60, 69  # Ah's (00, 01, 02, 11, 12, 22); c_a (S_CR + 3 (a - 1) + i); N_a (S_N + 9 (a - 1) + ...)
S_K = 96  # the blocks: entry (i, j) of block (p, q) at row S_K + 36 p + 9 q + 3 i + j
S_ROWS = S_K + 144


@njit_inline
def load_lanes(Fb, Rb, B, vol, t0, nl, S):
    """S's input rows for the tetrahedra t0 .. t0 + nl - 1 (nl <= LANES): F, R from Fb, Rb (9, T) (row-major
    entries per column t), the shape gradients b_0..b_3 from B (T, 4, 3), the volumes (T,)."""
    for l in range(nl):
        t = t0 + l
        for k in range(9):
            S[(S_F + k) * LANES + l] = Fb[k, t]
            S[(S_R + k) * LANES + l] = Rb[k, t]
        for a in range(4):
            for k in range(3):
                S[(S_B + 3 * a + k) * LANES + l] = B[t, a, k]
        S[S_VOL * LANES + l] = vol[t]


@njit_inline
def row(S, r, l):
    """S's row r, lane l (l unsigned: no wrap-around test)."""
    return S[np.uint64(r * LANES) + l]


@njit_inline
def set_row(S, r, l, value):
    S[np.uint64(r * LANES) + l] = value


@njit_inline
def sym_fr(fi0, fi1, fi2, ri0, ri1, ri2, fj0, fj1, fj2, rj0, rj1, rj2):
    """sum_k F_ik R_jk + F_jk R_ik (from 0, k ascending): twice the entry (i, j) of sym(F R^T)."""
    return 0.0 + (fi0 * rj0 + fj0 * ri0) + (fi1 * rj1 + fj1 * ri1) + (fi2 * rj2 + fj2 * ri2)


@njit_inline
def lane_stress(S, l, mu, lam, scale):
    """Lane l's tr S = tr(R^T F), P = 2 mu (F - R) + lambda (tr S - 3) R [Pa], V Psi [J] with Psi = mu |F - R|_F^2
    + lambda/2 (tr S - 3)^2, and scale * f_a = -scale V P b_a [N] (the nodal elastic forces, as the terms
    subtracted: S_FA + 3 a + i holds scale V (P b_a)_i) into S."""
    ts = 0.0
    for i in range(3):
        r0, r1, r2 = row(S, S_R + i, l), row(S, S_R + 3 + i, l), row(S, S_R + 6 + i, l)  # column i of R and F
        ts += r0 * row(S, S_F + i, l) + r1 * row(S, S_F + 3 + i, l) + r2 * row(S, S_F + 6 + i, l)
    set_row(S, S_TRS, l, ts)
    g = lam * (ts - 3.0)
    sq = 0.0
    for k in range(9):
        fk, rk = row(S, S_F + k, l), row(S, S_R + k, l)
        set_row(S, S_P + k, l, 2.0 * mu * (fk - rk) + g * rk)
        sq += (fk - rk) ** 2
    vol = row(S, S_VOL, l)
    set_row(S, S_EN, l, vol * (mu * sq + 0.5 * lam * (ts - 3.0) ** 2))
    for a in range(4):
        b0, b1, b2 = row(S, S_B + 3 * a, l), row(S, S_B + 3 * a + 1, l), row(S, S_B + 3 * a + 2, l)
        for i in range(3):
            set_row(S, S_FA + 3 * a + i, l, scale * vol * (row(S, S_P + 3 * i, l) * b0 + row(S, S_P + 3 * i + 1, l) * b1
                                                            + row(S, S_P + 3 * i + 2, l) * b2))


@njit_inline
def stress_lanes(S, nl, mu, lam, scale):
    """``lane_stress`` of the nl <= LANES tetrahedra ``load_lanes`` put in S, in one vectorised loop."""
    for ll in range(nl):
        lane_stress(S, np.uint64(ll), mu, lam, scale)


@njit_inline
def lane_ah(S, l):
    """Ah = (tr S I - sym(F R^T))^-1 (cofactors / determinant; np.divide: IEEE division without numba's
    zero-divisor branch, the same quotient) of lane l into S (tr S from ``lane_stress``)."""
    F00, F01, F02, F10, F11, F12, F20, F21, F22 = (row(S, S_F, l), row(S, S_F + 1, l), row(S, S_F + 2, l),
                                                   row(S, S_F + 3, l), row(S, S_F + 4, l), row(S, S_F + 5, l),
                                                   row(S, S_F + 6, l), row(S, S_F + 7, l), row(S, S_F + 8, l))
    R00, R01, R02, R10, R11, R12, R20, R21, R22 = (row(S, S_R, l), row(S, S_R + 1, l), row(S, S_R + 2, l),
                                                   row(S, S_R + 3, l), row(S, S_R + 4, l), row(S, S_R + 5, l),
                                                   row(S, S_R + 6, l), row(S, S_R + 7, l), row(S, S_R + 8, l))
    ts = row(S, S_TRS, l)
    a = -0.5 * sym_fr(F00, F01, F02, R00, R01, R02, F00, F01, F02, R00, R01, R02) + ts
    b = -0.5 * sym_fr(F00, F01, F02, R00, R01, R02, F10, F11, F12, R10, R11, R12)
    c = -0.5 * sym_fr(F00, F01, F02, R00, R01, R02, F20, F21, F22, R20, R21, R22)
    d = -0.5 * sym_fr(F10, F11, F12, R10, R11, R12, F10, F11, F12, R10, R11, R12) + ts
    e = -0.5 * sym_fr(F10, F11, F12, R10, R11, R12, F20, F21, F22, R20, R21, R22)
    f = -0.5 * sym_fr(F20, F21, F22, R20, R21, R22, F20, F21, F22, R20, R21, R22) + ts
    i00, i01, i02 = d * f - e * e, c * e - b * f, b * e - c * d
    i11, i12, i22 = a * f - c * c, b * c - a * e, a * d - b * b
    r = np.divide(1.0, a * i00 + b * i01 + c * i02)
    set_row(S, S_AH, l, i00 * r)
    set_row(S, S_AH + 1, l, i01 * r)
    set_row(S, S_AH + 2, l, i02 * r)
    set_row(S, S_AH + 3, l, i11 * r)
    set_row(S, S_AH + 4, l, i12 * r)
    set_row(S, S_AH + 5, l, i22 * r)


@njit_inline
def lane_rotated_gradient(S, l, a):
    """c_a = R b_a and N_a = Ah [c_a]_x (row i, column j at S_N + 9 (a - 1) + 3 i + j) of lane l into S."""
    b0, b1, b2 = row(S, S_B + 3 * a, l), row(S, S_B + 3 * a + 1, l), row(S, S_B + 3 * a + 2, l)
    c0 = row(S, S_R, l) * b0 + row(S, S_R + 1, l) * b1 + row(S, S_R + 2, l) * b2
    c1 = row(S, S_R + 3, l) * b0 + row(S, S_R + 4, l) * b1 + row(S, S_R + 5, l) * b2
    c2 = row(S, S_R + 6, l) * b0 + row(S, S_R + 7, l) * b1 + row(S, S_R + 8, l) * b2
    ca = S_CR + 3 * (a - 1)
    set_row(S, ca, l, c0)
    set_row(S, ca + 1, l, c1)
    set_row(S, ca + 2, l, c2)
    h00, h01, h02 = row(S, S_AH, l), row(S, S_AH + 1, l), row(S, S_AH + 2, l)
    h11, h12, h22 = row(S, S_AH + 3, l), row(S, S_AH + 4, l), row(S, S_AH + 5, l)
    na = S_N + 9 * (a - 1)
    for i in range(3):  # Ah's row i: (i, 0), (i, 1), (i, 2) of the symmetric Ah
        h0 = h00 if i == 0 else (h01 if i == 1 else h02)
        h1 = h01 if i == 0 else (h11 if i == 1 else h12)
        h2 = h02 if i == 0 else (h12 if i == 1 else h22)
        set_row(S, na + 3 * i, l, h1 * c2 - h2 * c1)
        set_row(S, na + 3 * i + 1, l, h2 * c0 - h0 * c2)
        set_row(S, na + 3 * i + 2, l, h0 * c1 - h1 * c0)


@njit_inline
def lane_pair_block(S, l, p, q, mu, lam):
    """The block (p, q), 1 <= p <= q, of lane l into S, with its mirror (q, p) = (p, q)^T written after each of
    its columns (on a diagonal block the mirror overwrites the entries below the diagonal with those above):
    K_pq = V [2 mu (b_p . b_q) I + lambda c_p c_q^T + (lambda tr(S - I) - 2 mu) [c_p]_x^T Ah [c_q]_x]."""
    c0, c1, c2 = row(S, S_CR + 3 * (p - 1), l), row(S, S_CR + 3 * (p - 1) + 1, l), row(S, S_CR + 3 * (p - 1) + 2, l)
    bp, bq = S_B + 3 * p, S_B + 3 * q
    bb = 2.0 * mu * (row(S, bp, l) * row(S, bq, l) + row(S, bp + 1, l) * row(S, bq + 1, l)
                     + row(S, bp + 2, l) * row(S, bq + 2, l))
    coef = lam * (row(S, S_TRS, l) - 3.0) - 2.0 * mu
    vol = row(S, S_VOL, l)
    nq = S_N + 9 * (q - 1)
    for j in range(3):
        n0, n1, n2 = row(S, nq + j, l), row(S, nq + 3 + j, l), row(S, nq + 6 + j, l)  # ([c_p]_x^T n)_i = (n x c_p)_i
        rot0, rot1, rot2 = n1 * c2 - n2 * c1, n2 * c0 - n0 * c2, n0 * c1 - n1 * c0
        cq = lam * row(S, S_CR + 3 * (q - 1) + j, l)
        k0 = vol * (c0 * cq + coef * rot0 + (bb if j == 0 else 0.0))
        k1 = vol * (c1 * cq + coef * rot1 + (bb if j == 1 else 0.0))
        k2 = vol * (c2 * cq + coef * rot2 + (bb if j == 2 else 0.0))
        pq, qp = S_K + 36 * p + 9 * q, S_K + 36 * q + 9 * p
        set_row(S, pq + j, l, k0)
        set_row(S, pq + 3 + j, l, k1)
        set_row(S, pq + 6 + j, l, k2)
        set_row(S, qp + 3 * j, l, k0)
        set_row(S, qp + 3 * j + 1, l, k1)
        set_row(S, qp + 3 * j + 2, l, k2)


@njit_inline
def tet_blocks_lanes(S, nl, mu, lam):
    """The exact element stiffness K_e = -df_e/dx_e [N/m] (module docstring) of the nl <= LANES tetrahedra
    whose F, R, b_0..b_3 and volumes ``load_lanes`` and tr S ``stress_lanes`` put in S: the blocks (rows:
    vertex p's x, y, z; columns: vertex q's) into S's rows S_K + ... . The blocks of vertices 1-3 from c_a =
    R b_a and Ah = (tr S I - sym(F R^T))^-1 (``lane_pair_block``); those of vertex 0 from the others' (b_0 is
    -(b_1 + b_2 + b_3), fem.TetFEM.B, and K_pq is linear in b_p). One loop over the lanes, which the compiler
    vectorises (AVX2). The same bits as the tetrahedron-by-tetrahedron tet_blocks, unless Ah is singular: 1/0
    raised ZeroDivisionError there and gives inf here."""
    for ll in range(nl):
        l = np.uint64(ll)
        lane_ah(S, l)
        lane_rotated_gradient(S, l, 1)
        lane_rotated_gradient(S, l, 2)
        lane_rotated_gradient(S, l, 3)
        lane_pair_block(S, l, 1, 1, mu, lam)
        lane_pair_block(S, l, 1, 2, mu, lam)
        lane_pair_block(S, l, 1, 3, mu, lam)
        lane_pair_block(S, l, 2, 2, mu, lam)
        lane_pair_block(S, l, 2, 3, mu, lam)
        lane_pair_block(S, l, 3, 3, mu, lam)
        for q in range(1, 4):  # K_0q = -sum_p K_pq, K_q0 = K_0q^T
            for i in range(3):
                for j in range(3):
                    k = -(row(S, S_K + 36 + 9 * q + 3 * i + j, l) + row(S, S_K + 72 + 9 * q + 3 * i + j, l)
                          + row(S, S_K + 108 + 9 * q + 3 * i + j, l))
                    set_row(S, S_K + 9 * q + 3 * i + j, l, k)
                    set_row(S, S_K + 36 * q + 3 * j + i, l, k)
        for i in range(3):
            for j in range(3):
                set_row(S, S_K + 3 * i + j, l, -(row(S, S_K + 9 + 3 * i + j, l) + row(S, S_K + 18 + 3 * i + j, l)
                                                 + row(S, S_K + 27 + 3 * i + j, l)))


@njit_inline
def newton_polar_batch(x, tets, B, Fb, Rb, s2, ok):
    """The polar factors of every tetrahedron's F by Newton's iteration (``newton_polar3``'s) run on all of them
    at once: Fb, Rb (9, T) the entries of F and R (row-major 3 x 3 per column t), s2 (T,) scratch, ok (T,) True
    where Newton's R is taken (F neither inverted nor near flat, ``newton_polar3``'s test, and converged). The
    iterations run over all tetrahedra in lockstep, a loop over t without branches that the compiler
    vectorises (the per-tetrahedron iteration is a chain of dependent operations, a division among them, that
    left the core idle: 3.6 iterations at ~100 ns each on the starfish), until the largest step of the accepted
    ones is below 1e-8 (Frobenius; at most 30 iterations). A tetrahedron that converged earlier takes the extra
    iterations at its fixed point, which move R by round-off (~1e-16): R is the polar factor to the same
    accuracy as newton_polar3's, not bit for bit the same numbers. The iterates' determinants stay positive
    (each singular value s goes to (s + 1/s) / 2; a rejected F iterates from the identity), so the division
    needs no zero test. Returns the number of accepted tetrahedra."""
    T = len(tets)
    nok = 0
    for t in range(T):  # F = sum_a x_a b_a^T, each entry's four terms in vertex order (as deformation_gradient)
        v0, v1, v2, v3 = np.uint64(tets[t, 0]), np.uint64(tets[t, 1]), np.uint64(tets[t, 2]), np.uint64(tets[t, 3])
        for i in range(3):  # the vertices' coordinates read once, unsigned (no wrap-around test): 43 -> 33 us
            x0, x1, x2, x3 = x[v0, i], x[v1, i], x[v2, i], x[v3, i]
            for k in range(3):
                Fb[3 * i + k, t] = 0.0 + x0 * B[t, 0, k] + x1 * B[t, 1, k] + x2 * B[t, 2, k] + x3 * B[t, 3, k]
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = (Fb[0, t], Fb[1, t], Fb[2, t], Fb[3, t], Fb[4, t], Fb[5, t],
                                                       Fb[6, t], Fb[7, t], Fb[8, t])
        n2 = r00 * r00 + r01 * r01 + r02 * r02 + r10 * r10 + r11 * r11 + r12 * r12 + r20 * r20 + r21 * r21 + r22 * r22
        det = r00 * (r11 * r22 - r12 * r21) + r01 * (r12 * r20 - r10 * r22) + r02 * (r10 * r21 - r11 * r20)
        good = det > 0.0 and det * det > 1e-4 * (n2 / 3.0) ** 3
        ok[t] = good
        for i in range(9):  # a rejected F iterates from the identity (discarded; keeps the loop finite)
            Rb[i, t] = Fb[i, t] if good else (1.0 if i % 4 == 0 else 0.0)
        nok += 1 if good else 0
    if nok == 0:
        return 0
    G0, G1, G2, G3, G4, G5, G6, G7, G8 = Rb[0], Rb[1], Rb[2], Rb[3], Rb[4], Rb[5], Rb[6], Rb[7], Rb[8]
    for _ in range(30):
        for tt in range(T):  # unsigned indices: no wrap-around test, so the loop vectorises
            t = np.uint64(tt)
            r00, r01, r02, r10, r11, r12, r20, r21, r22 = G0[t], G1[t], G2[t], G3[t], G4[t], G5[t], G6[t], G7[t], G8[t]
            c00, c01, c02 = r11 * r22 - r12 * r21, r12 * r20 - r10 * r22, r10 * r21 - r11 * r20
            c10, c11, c12 = r02 * r21 - r01 * r22, r00 * r22 - r02 * r20, r01 * r20 - r00 * r21
            c20, c21, c22 = r01 * r12 - r02 * r11, r02 * r10 - r00 * r12, r00 * r11 - r01 * r10
            # np.divide: IEEE division without the zero-divisor test (ZeroDivisionError) numba puts on a float
            # '/', a branch that kept this loop from vectorising (the same quotient; 62 -> 41 us on the starfish)
            b = np.divide(0.5, r00 * c00 + r01 * c01 + r02 * c02)
            s00, s01, s02 = 0.5 * r00 + b * c00, 0.5 * r01 + b * c01, 0.5 * r02 + b * c02
            s10, s11, s12 = 0.5 * r10 + b * c10, 0.5 * r11 + b * c11, 0.5 * r12 + b * c12
            s20, s21, s22 = 0.5 * r20 + b * c20, 0.5 * r21 + b * c21, 0.5 * r22 + b * c22
            d00, d01, d02, d10, d11 = s00 - r00, s01 - r01, s02 - r02, s10 - r10, s11 - r11
            d12, d20, d21, d22 = s12 - r12, s20 - r20, s21 - r21, s22 - r22
            s2[t] = (d00 * d00 + d01 * d01 + d02 * d02 + d10 * d10 + d11 * d11 + d12 * d12 + d20 * d20 + d21 * d21
                     + d22 * d22)
            G0[t], G1[t], G2[t], G3[t], G4[t], G5[t], G6[t], G7[t], G8[t] = s00, s01, s02, s10, s11, s12, s20, s21, s22
        worst = 0.0
        for t in range(T):
            if ok[t] and s2[t] > worst:
                worst = s2[t]
        if worst <= 1e-16:
            return nok
    for t in range(T):  # not converged in 30: those take polar3's SVD route
        if ok[t] and not s2[t] <= 1e-16:
            ok[t] = False
            nok -= 1
    return nok


@njit
def fem_add(x, tets, B, vol, mu, lam, blk, stride, ck, hf, data, f):
    """Over every tetrahedron: f (n,3) += hf * (elastic forces [N]) when hf != 0, the CSR ``data`` of a
    sparsity.BlockPattern += ck * (element stiffness blocks [N/m]) when ck != 0. Returns the elastic energy
    sum_t V_t Psi_t [J]. x (n,3) [m], tets (T,4), B (T,4,3) [1/m], vol (T,) [m^3], mu, lam [Pa]. The polar
    factors first, for all tetrahedra at once (``newton_polar_batch``; ``polar3`` for those it does not take),
    the stress, energy, forces and stiffness LANES tetrahedra at a time (``stress_lanes``,
    ``tet_blocks_lanes``); the sums into f, data and the energy tetrahedron by tetrahedron, in order."""
    F, R, C, V = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    T = len(tets)
    Fb, Rb, s2, ok = np.empty((9, T)), np.empty((9, T)), np.empty(T), np.empty(T, np.bool_)
    newton_polar_batch(x, tets, B, Fb, Rb, s2, ok)
    for t in range(T):  # polar3's route for the tetrahedra Newton's lockstep iteration does not take
        if not ok[t]:
            for i in range(3):
                for k in range(3):
                    F[i, k] = Fb[3 * i + k, t]
            polar3(F, R, C, V)
            for i in range(3):
                for k in range(3):
                    Rb[3 * i + k, t] = R[i, k]
    S = np.empty(S_ROWS * LANES)
    energy = 0.0
    for t0 in range(0, T, LANES):
        nl = min(LANES, T - t0)
        load_lanes(Fb, Rb, B, vol, t0, nl, S)
        stress_lanes(S, nl, mu, lam, hf)
        if ck != 0.0:
            tet_blocks_lanes(S, nl, mu, lam)
        for l in range(nl):
            t = t0 + l
            tet = tets[t]
            energy += S[S_EN * LANES + l]
            if hf != 0.0:
                for a in range(4):
                    for i in range(3):
                        f[tet[a], i] -= S[(S_FA + 3 * a + i) * LANES + l]
            if ck != 0.0:
                for p in range(4):
                    for q in range(4):
                        add_block_strided(data, blk[t, p, q], stride[tet[p]], ck, S, (S_K + 36 * p + 9 * q) * LANES + l,
                                          LANES)
    return energy


@njit_inline
def polar_factors(x, tets, B, Fb, Rb):
    """Fb, Rb (9, T) := every tetrahedron's F (``deformation_gradient``) and R (``polar3``), row-major."""
    F, R, C, V = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    for t in range(len(tets)):
        deformation_gradient(x, tets[t], B[t], F)
        polar3(F, R, C, V)
        for i in range(3):
            for k in range(3):
                Fb[3 * i + k, t] = F[i, k]
                Rb[3 * i + k, t] = R[i, k]


@njit
def fem_element_stiffness(x, tets, B, vol, mu, lam):
    """(T,4,4,3,3) per-tetrahedron stiffness blocks (``tet_blocks_lanes``) [N/m] at the polar factors of
    ``polar3``."""
    T = len(tets)
    Fb, Rb = np.empty((9, T)), np.empty((9, T))
    polar_factors(x, tets, B, Fb, Rb)
    S = np.empty(S_ROWS * LANES)
    out = np.empty((T, 4, 4, 3, 3))
    for t0 in range(0, T, LANES):
        nl = min(LANES, T - t0)
        load_lanes(Fb, Rb, B, vol, t0, nl, S)
        stress_lanes(S, nl, mu, lam, 0.0)
        tet_blocks_lanes(S, nl, mu, lam)
        for l in range(nl):
            for p in range(4):
                for q in range(4):
                    for i in range(3):
                        for j in range(3):
                            out[t0 + l, p, q, i, j] = S[(S_K + 36 * p + 9 * q + 3 * i + j) * LANES + l]
    return out


@njit
def fem_stress(x, tets, B, mu, lam):
    """(T,3,3) first Piola-Kirchhoff stress P [Pa] per tetrahedron (``lane_stress`` at the polar factors of
    ``polar3``)."""
    T = len(tets)
    Fb, Rb = np.empty((9, T)), np.empty((9, T))
    polar_factors(x, tets, B, Fb, Rb)
    S = np.empty(S_ROWS * LANES)
    P = np.empty((T, 3, 3))
    vol = np.ones(T)
    for t0 in range(0, T, LANES):
        nl = min(LANES, T - t0)
        load_lanes(Fb, Rb, B, vol, t0, nl, S)
        stress_lanes(S, nl, mu, lam, 0.0)
        for l in range(nl):
            for k in range(9):
                P[t0 + l, k // 3, k % 3] = S[(S_P + k) * LANES + l]
    return P


@njit
def polar_batch(F):
    """(R, S) (T,3,3) each with F = R S of a batch F (T,3,3): R from ``polar3``, S = sym(R^T F)."""
    T = len(F)
    R, S = np.empty((T, 3, 3)), np.empty((T, 3, 3))
    C, V = np.empty((3, 3)), np.empty((3, 3))
    for t in range(T):
        polar3(F[t], R[t], C, V)
        for i in range(3):
            for j in range(3):
                C[i, j] = R[t, 0, i] * F[t, 0, j] + R[t, 1, i] * F[t, 1, j] + R[t, 2, i] * F[t, 2, j]
        for i in range(3):
            for j in range(3):
                S[t, i, j] = 0.5 * (C[i, j] + C[j, i])
    return R, S
