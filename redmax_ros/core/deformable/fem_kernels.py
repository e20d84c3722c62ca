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
* P = 2 mu (F - R) + lambda tr(R^T F - I) R, Psi = mu |F - R|^2 + lambda/2 tr^2(R^T F - I), f_a = -V P b_a;
* the exact K_e = -df_e/dx_e (``tet_blocks``), written in the rotated frame with c_a = R b_a and
  Sh = R S R^T = F R^T: the block of vertex rows p and vertex columns q is

      K_pq = V [2 mu (b_p . b_q) I + lambda c_p c_q^T + (lambda tr(S - I) - 2 mu) [c_p]_x^T Ah [c_q]_x],

  Ah = (tr S I - Sh)^-1. It is fem.py's K[(p,d),(q,c)] = V [... + coef (R (w_qc x b_p))_d] with
  w_qc = (tr S I - S)^-1 (b_q x r_c): (R (w x b_p))_d = (b_q x r_c)^T (tr S I - S)^-1 (b_p x r_d) and
  b x r_c = R^T (c x e_c).
"""
from __future__ import annotations

import numpy as np

from redmax_ros.core.deformable.sparsity import add_block
from redmax_ros.core.jit import drop_stale_caches, njit, njit_inline

# the kernels below inline sparsity.add_block: an edit of sparsity.py recompiles them
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


@njit_inline
def tet_stress(F, R, mu, lam, P):
    """P (3,3) = 2 mu (F - R) + lambda tr(R^T F - I) R [Pa]; returns tr(R^T F) = tr S."""
    trS = 0.0
    for i in range(3):
        trS += R[0, i] * F[0, i] + R[1, i] * F[1, i] + R[2, i] * F[2, i]
    g = lam * (trS - 3.0)
    for i in range(3):
        for k in range(3):
            P[i, k] = 2.0 * mu * (F[i, k] - R[i, k]) + g * R[i, k]
    return trS


@njit_inline
def tet_energy_density(F, R, trS, mu, lam):
    """Psi = mu |F - R|_F^2 + lambda/2 (tr S - 3)^2 [J/m^3]."""
    s = 0.0
    for i in range(3):
        for k in range(3):
            s += (F[i, k] - R[i, k]) ** 2
    return mu * s + 0.5 * lam * (trS - 3.0) ** 2


@njit_inline
def tet_state(x, tet, Bt, mu, lam, F, R, P, C, V):
    """F, R (``polar3``, with scratch C, V) and P of one tetrahedron into F, R, P; returns tr S."""
    deformation_gradient(x, tet, Bt, F)
    polar3(F, R, C, V)
    return tet_stress(F, R, mu, lam, P)


@njit_inline
def inverse_sym3(M):
    """M (3,3) symmetric := M^-1 (cofactors / determinant)."""
    a, b, c, d, e, f = M[0, 0], M[0, 1], M[0, 2], M[1, 1], M[1, 2], M[2, 2]
    i00, i01, i02 = d * f - e * e, c * e - b * f, b * e - c * d
    i11, i12, i22 = a * f - c * c, b * c - a * e, a * d - b * b
    r = 1.0 / (a * i00 + b * i01 + c * i02)
    M[0, 0], M[1, 1], M[2, 2] = i00 * r, i11 * r, i22 * r
    M[0, 1] = M[1, 0] = i01 * r
    M[0, 2] = M[2, 0] = i02 * r
    M[1, 2] = M[2, 1] = i12 * r


@njit_inline
def tet_blocks(F, R, trS, Bt, vol, mu, lam, Ah, Cr, N, Kb):
    """Kb (4,4,3,3): Kb[p, q] the block (rows: vertex p's x, y, z; columns: vertex q's) of the exact element
    stiffness K_e = -df_e/dx_e [N/m] (module docstring); the blocks of vertex 0 from the others' (Bt[0] is
    -(Bt[1] + Bt[2] + Bt[3]), fem.TetFEM.B). Scratch: Ah (3,3), Cr (4,3) the c_a = R b_a, N (4,3,3) the
    Ah [c_a]_x (rows 1-3 used)."""
    for i in range(3):  # Ah = (tr S I - sym(F R^T))^-1
        for j in range(i, 3):
            s = 0.0
            for k in range(3):
                s += F[i, k] * R[j, k] + F[j, k] * R[i, k]
            Ah[i, j] = -0.5 * s
            Ah[j, i] = -0.5 * s
        Ah[i, i] += trS
    inverse_sym3(Ah)
    for a in range(1, 4):
        for i in range(3):
            Cr[a, i] = R[i, 0] * Bt[a, 0] + R[i, 1] * Bt[a, 1] + R[i, 2] * Bt[a, 2]
        c0, c1, c2 = Cr[a, 0], Cr[a, 1], Cr[a, 2]
        for i in range(3):
            N[a, i, 0] = Ah[i, 1] * c2 - Ah[i, 2] * c1
            N[a, i, 1] = Ah[i, 2] * c0 - Ah[i, 0] * c2
            N[a, i, 2] = Ah[i, 0] * c1 - Ah[i, 1] * c0
    coef = lam * (trS - 3.0) - 2.0 * mu
    for p in range(1, 4):
        c0, c1, c2 = Cr[p, 0], Cr[p, 1], Cr[p, 2]
        for q in range(p, 4):
            bb = 2.0 * mu * (Bt[p, 0] * Bt[q, 0] + Bt[p, 1] * Bt[q, 1] + Bt[p, 2] * Bt[q, 2])
            for j in range(3):
                n0, n1, n2 = N[q, 0, j], N[q, 1, j], N[q, 2, j]  # ([c_p]_x^T n)_i = (n x c_p)_i
                rot0, rot1, rot2 = n1 * c2 - n2 * c1, n2 * c0 - n0 * c2, n0 * c1 - n1 * c0
                cq = lam * Cr[q, j]
                k0 = vol * (c0 * cq + coef * rot0 + (bb if j == 0 else 0.0))
                k1 = vol * (c1 * cq + coef * rot1 + (bb if j == 1 else 0.0))
                k2 = vol * (c2 * cq + coef * rot2 + (bb if j == 2 else 0.0))
                Kb[p, q, 0, j], Kb[p, q, 1, j], Kb[p, q, 2, j] = k0, k1, k2
                Kb[q, p, j, 0], Kb[q, p, j, 1], Kb[q, p, j, 2] = k0, k1, k2
    for q in range(1, 4):  # K_0q = -sum_p K_pq, as b_0 = -(b_1 + b_2 + b_3) and K_pq is linear in b_p
        for i in range(3):
            for j in range(3):
                k = -(Kb[1, q, i, j] + Kb[2, q, i, j] + Kb[3, q, i, j])
                Kb[0, q, i, j] = k
                Kb[q, 0, j, i] = k
    for i in range(3):
        for j in range(3):
            Kb[0, 0, i, j] = -(Kb[0, 1, i, j] + Kb[0, 2, i, j] + Kb[0, 3, i, j])


@njit_inline
def add_tet_forces(P, Bt, vol, tet, scale, f):
    """f[tet[a]] += scale * f_a with f_a = -V P b_a [N] the nodal elastic forces; f (n,3)."""
    for a in range(4):
        for i in range(3):
            f[tet[a], i] -= scale * vol * (P[i, 0] * Bt[a, 0] + P[i, 1] * Bt[a, 1] + P[i, 2] * Bt[a, 2])


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
    factors first, for all tetrahedra at once (``newton_polar_batch``; ``polar3`` for those it does not take)."""
    F, R, P = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    C, V, Ah = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    Cr, N, Kb = np.empty((4, 3)), np.empty((4, 3, 3)), np.empty((4, 4, 3, 3))
    T = len(tets)
    Fb, Rb, s2, ok = np.empty((9, T)), np.empty((9, T)), np.empty(T), np.empty(T, np.bool_)
    newton_polar_batch(x, tets, B, Fb, Rb, s2, ok)
    energy = 0.0
    for t in range(T):
        tet, Bt = tets[t], B[t]
        for i in range(3):
            for k in range(3):
                F[i, k] = Fb[3 * i + k, t]
        if ok[t]:
            for i in range(3):
                for k in range(3):
                    R[i, k] = Rb[3 * i + k, t]
        else:
            polar3(F, R, C, V)
        trS = tet_stress(F, R, mu, lam, P)
        energy += vol[t] * tet_energy_density(F, R, trS, mu, lam)
        if hf != 0.0:
            add_tet_forces(P, Bt, vol[t], tet, hf, f)
        if ck != 0.0:
            tet_blocks(F, R, trS, Bt, vol[t], mu, lam, Ah, Cr, N, Kb)
            for p in range(4):
                for q in range(4):
                    add_block(data, blk[t, p, q], stride[tet[p]], ck, Kb[p, q])
    return energy


@njit
def fem_element_stiffness(x, tets, B, vol, mu, lam):
    """(T,4,4,3,3) per-tetrahedron stiffness blocks (``tet_blocks``) [N/m]."""
    F, R, P = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    C, V, Ah = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    Cr, N = np.empty((4, 3)), np.empty((4, 3, 3))
    K = np.empty((len(tets), 4, 4, 3, 3))
    for t in range(len(tets)):
        trS = tet_state(x, tets[t], B[t], mu, lam, F, R, P, C, V)
        tet_blocks(F, R, trS, B[t], vol[t], mu, lam, Ah, Cr, N, K[t])
    return K


@njit
def fem_stress(x, tets, B, mu, lam):
    """(T,3,3) first Piola-Kirchhoff stress P [Pa] per tetrahedron."""
    F, R, C, V = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    P = np.empty((len(tets), 3, 3))
    for t in range(len(tets)):
        tet_state(x, tets[t], B[t], mu, lam, F, R, P[t], C, V)
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
