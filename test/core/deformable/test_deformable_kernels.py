"""The compiled deformable assembly (issue 15, RTF at h = 1e-3): fem_kernels.py's co-rotated FEM and the fixed
CSR pattern of A_d (sparsity.py, Deformables.csr_pattern / fill). Physics only, no timing (the kernel's
stiffness against central differences of its forces, and its forces against the energy's gradient, are
test_deformable_elements.py's FD tests): the kernel's element stiffness against the numpy closed form; the
polar decomposition's convention (the proper rotation, the reflection of an inverted F moved to the smallest
singular value; Irving, Teran & Fedkiw 2004) on inverted, near-flat and ordinary F against numpy's SVD; the
pattern; and the filled A_d, b_d against a numpy reference of the former vectorised assembly (SVD polar,
Sifakis & Barbic 2012's element stiffness with the rotation's differential, COO -> CSR) on the starfish mesh."""
import numpy as np
import pytest
import scipy.sparse as sp
from scipy.spatial.transform import Rotation

from redmax_ros.core import Simulator
from redmax_ros.core.deformable import fem_kernels, meshes
from redmax_ros.core.deformable.fem import TetFEM, polar
from redmax_ros.core.deformable.string import String
from redmax_ros.core.deformable.system import Attachments, Deformables


def _rot(axis, ang):
    return Rotation.from_rotvec(ang * np.asarray(axis, float) / np.linalg.norm(axis)).as_matrix()


def svd_polar(F):
    """Reference (R, S) of a batch F: numpy's SVD, U's last column flipped where det U det V < 0."""
    U, s, Vt = np.linalg.svd(F)
    flip = np.linalg.det(U) * np.linalg.det(Vt) < 0
    U = U.copy()
    U[flip, :, 2] *= -1.0
    R = U @ Vt
    S = np.swapaxes(R, 1, 2) @ F
    return R, 0.5 * (S + np.swapaxes(S, 1, 2))


def reference_element_stiffness(fem, x):
    """(T,12,12) K_e of fem.py's closed form in batched numpy (the former TetFEM.element_stiffness)."""
    F = np.einsum("tai,tak->tik", x[fem.tets], fem.B)
    R, S = svd_polar(F)
    B, T = fem.B, len(F)
    trS = np.trace(S, axis1=1, axis2=2)
    RT = np.swapaxes(R, 1, 2)
    BB = B @ np.swapaxes(B, 1, 2)
    RB = B @ RT
    axial = np.cross(B[:, :, None, :], R[:, None, :, :])
    Ainv = np.linalg.inv(trS[:, None, None] * np.eye(3) - S)
    w = axial @ np.swapaxes(Ainv, 1, 2)[:, None]
    RwB = np.cross(w[:, :, :, None, :], B[:, None, None, :, :]) @ RT[:, None, None]
    K = (fem.lam * (trS - 3.0) - 2.0 * fem.mu)[:, None, None, None, None] * RwB
    K += fem.lam * RB[:, :, :, None, None] * RB[:, None, None, :, :]
    K += 2.0 * fem.mu * BB[:, :, None, :, None] * np.eye(3)[None, None, :, None, :]
    K *= fem.vol[:, None, None, None, None]
    return np.ascontiguousarray(K.transpose(0, 3, 4, 1, 2)).reshape(T, 12, 12)


def reference_system(fem, x, v, h, gravity):
    """(A_d dense, b_d) of one FEM by the former route: numpy forces and element stiffness, COO -> CSR."""
    F = np.einsum("tai,tak->tik", x[fem.tets], fem.B)
    R, S = svd_polar(F)
    P = 2.0 * fem.mu * (F - R) + (fem.lam * (np.trace(S, axis1=1, axis2=2) - 3.0))[:, None, None] * R
    f = np.zeros((fem.n, 3))
    np.add.at(f, fem.tets.ravel(), (-fem.vol[:, None, None] * np.einsum("tik,tak->tai", P, fem.B)).reshape(-1, 3))
    Ke = reference_element_stiffness(fem, x)
    dofs = (3 * fem.tets[:, :, None] + np.arange(3)).reshape(-1, 12)
    rows = np.repeat(dofs, 12, axis=1).ravel()
    cols = np.tile(dofs, (1, 12)).ravel()
    K = sp.coo_matrix((Ke.ravel(), (rows, cols)), shape=(3 * fem.n, 3 * fem.n)).tocsr()
    m3 = np.repeat(fem.mass, 3)
    A = sp.diags(m3 * (1.0 + h * fem.alpha)) + (h * fem.beta + h * h) * K
    return A.toarray(), m3 * v.ravel() + h * (f + fem.mass[:, None] * gravity).ravel()


def _mesh(cells=(2, 2, 1), young=1e5, alpha=0.0, beta=0.0):
    x, tets = meshes.box_tets(np.zeros(3), np.array([0.2, 0.2, 0.1]), cells)
    return TetFEM(x, tets, young=young, poisson=0.3, density=1000.0, alpha=alpha, beta=beta)


def _deformed(fem, seed, noise=0.03):
    rng = np.random.default_rng(seed)
    return fem.x0 @ _rot([0.3, 1, 0.2], 0.7).T + noise * rng.standard_normal(fem.x0.shape)


def test_kernel_element_stiffness_equals_the_numpy_closed_form():
    fem = _mesh()
    x = _deformed(fem, 2)
    K = fem.element_stiffness(x)
    K_ref = reference_element_stiffness(fem, x)
    assert np.abs(K - K_ref).max() <= 1e-12 * np.abs(K_ref).max()


def _from_singular_values(s, seed):
    rng = np.random.default_rng(seed)
    U, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    V, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    return U @ np.diag(s) @ V.T


@pytest.mark.parametrize("s, newton", [
    ((1.2, 0.9, -0.3), False),  # inverted: the reflection on the smallest singular value
    ((1.1, -0.8, 0.95), False),  # inverted through another axis
    ((1.0, 1.0, -0.5), False),  # inverted, two equal singular values
    ((1.2, 0.9, 1e-3), False), ((1.2, 0.9, 1e-8), False), ((1.2, 0.9, 1e-14), False),  # near flat
    ((1.2, 0.9, 0.0), False), ((1.2, 0.9, -1e-8), False),  # flat; near flat and inverted
    ((1.05, 0.98, 1.01), True), ((1.3, 0.7, 1.0), True), ((1.0, 1.0, 1.0), True),  # ordinary
])
def test_polar_is_the_svd_convention(s, newton):
    """Both routes of fem_kernels.polar3: Newton's iteration for ordinary F, the SVD route otherwise."""
    for seed in range(4):
        F = _from_singular_values(s, seed)[None]
        assert fem_kernels.newton_polar3(F[0], np.empty((3, 3))) == newton
        R, S = polar(F)
        R_ref, S_ref = svd_polar(F)
        assert np.abs(R - R_ref).max() <= 1e-13
        assert np.linalg.det(R[0]) == pytest.approx(1.0, abs=1e-14)
        assert np.abs(S - S_ref).max() <= 1e-13 * max(1.0, np.abs(S_ref).max())
        assert np.abs(R[0] @ S[0] - F[0]).max() <= 1e-14 * max(1.0, np.abs(F).max())


def test_polar_of_strained_rotations_and_random_matrices():
    rng = np.random.default_rng(5)
    n = 400
    F = np.array([_rot(rng.standard_normal(3), rng.uniform(0, np.pi)) for _ in range(n)])
    F = F @ (np.eye(3) + 0.2 * rng.standard_normal((n, 3, 3)))  # strained rotations (mostly the Newton route)
    F = np.concatenate([F, rng.standard_normal((n, 3, 3))])  # half of these inverted
    R, _ = polar(F)
    R_ref, _ = svd_polar(F)
    s = np.linalg.svd(F, compute_uv=False)
    gap = np.minimum(s[:, 1] + np.sign(np.linalg.det(F)) * s[:, 2], 1.0)  # the conditioning of R
    assert np.all(np.abs(R - R_ref).max(axis=(1, 2)) <= 1e-14 / gap)


def test_polar_of_zero_and_rank_one():
    R, _ = polar(np.zeros((1, 3, 3)))
    assert np.array_equal(R[0], np.eye(3))
    F = np.outer([1.0, 2.0, 0.5], [0.3, -1.0, 0.2])[None]
    R, _ = polar(F)
    assert np.abs(R[0] @ R[0].T - np.eye(3)).max() < 1e-14 and np.linalg.det(R[0]) == pytest.approx(1.0)
    v1 = np.array([0.3, -1.0, 0.2]) / np.linalg.norm([0.3, -1.0, 0.2])
    u1 = np.array([1.0, 2.0, 0.5]) / np.linalg.norm([1.0, 2.0, 0.5])
    assert np.abs(R[0] @ v1 - u1).max() < 1e-14


def _no_attachments():
    return Attachments(np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros((0, 3)), [])


def test_pattern_is_sorted_csr_with_every_diagonal_block():
    x0 = np.stack([np.linspace(0, 1, 5), np.zeros(5), np.zeros(5)], 1)
    els = [_mesh(), String(x0, mass=0.2, stiffness=50.0)]
    offsets = np.cumsum([0] + [e.n for e in els])
    dm = Deformables(["fem", "rope"], els, offsets, _no_attachments(), np.array([0.0, 0.0, -9.81]))
    indptr, indices = dm.csr_pattern()
    n = 3 * dm.n_vertices
    A = sp.csr_matrix((np.ones(len(indices)), indices, indptr), shape=(n, n))
    assert A.has_sorted_indices and A.nnz == len(indices)
    assert np.all(A.diagonal() == 1.0)
    B = A.toarray()
    assert np.array_equal(B, B.T)
    assert not B[:3 * els[0].n, 3 * els[0].n:].any()  # no coupling between deformables
    assert dm.csr_pattern()[1] is indices  # computed once


def test_filled_system_equals_the_former_assembly_on_the_starfish():
    dm = Simulator.load("starfish").deformables
    fem = dm.elements[0]
    assert isinstance(fem, TetFEM) and len(dm.elements) == 1
    rng = np.random.default_rng(7)
    x = fem.x0 @ _rot([1, -0.5, 0.3], 0.4).T + 0.004 * rng.standard_normal(fem.x0.shape)
    v = 0.1 * rng.standard_normal(x.shape)
    h = 1e-3
    indptr, indices = dm.csr_pattern()
    data, b = np.full(len(indices), np.nan), np.full(3 * dm.n_vertices, np.nan)
    dm.fill(x, v, h, data, b)
    n = 3 * dm.n_vertices
    A = sp.csr_matrix((data, indices, indptr), shape=(n, n)).toarray()
    A_ref, b_ref = reference_system(fem, x, v, h, dm.gravity)
    assert fem.beta > 0 and np.abs(A_ref - np.diag(np.diag(A_ref))).max() > 1e-3 * np.abs(A_ref).max()
    assert np.abs(A - A_ref).max() <= 1e-12 * np.abs(A_ref).max()
    assert np.abs(b - b_ref).max() <= 1e-12 * np.abs(b_ref).max()
    A2, b2 = dm.assemble(x, v, h)
    assert np.array_equal(A2.toarray(), A) and np.array_equal(b2, b)


def test_string_fill_has_mass_damping_and_stiffness():
    x0 = np.stack([np.linspace(0, 1, 6), np.zeros(6), np.zeros(6)], 1)
    s = String(x0, mass=0.3, stiffness=80.0, alpha=0.5, beta=0.01)
    dm = Deformables(["rope"], [s], np.array([0, 6]), _no_attachments(), np.array([0.0, 0.0, -9.81]))
    rng = np.random.default_rng(1)
    x, v, h = x0 + 0.05 * rng.standard_normal(x0.shape), rng.standard_normal(x0.shape), 2e-3
    A, b = dm.assemble(x, v, h)
    m3 = np.repeat(s.mass, 3)
    A_ref = np.diag(m3 * (1 + h * s.alpha)) + (h * s.beta + h * h) * s.stiffness(x).toarray()
    b_ref = m3 * v.ravel() + h * (s.force(x) + s.mass[:, None] * dm.gravity).ravel()
    assert np.abs(A.toarray() - A_ref).max() <= 1e-14 * np.abs(A_ref).max()
    assert np.abs(b - b_ref).max() <= 1e-14 * np.abs(b_ref).max()
