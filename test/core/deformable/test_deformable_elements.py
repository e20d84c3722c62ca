"""Element physics of redmax_ros/core/deformable (issue 15 point 5): the co-rotated linear FEM of Sifakis &
Barbic 2012 (patch test, co-rotation, stiffness against central differences of the force, force against the
energy) and the mass-spring string (force/stiffness FD, hanging sag against Irvine's elastic catenary)."""
import numpy as np
import pytest
from scipy.optimize import brentq
from scipy.sparse.linalg import spsolve

from redmax_ros.core.deformable import meshes
from redmax_ros.core.deformable.fem import TetFEM, lame, polar
from redmax_ros.core.deformable.string import String


def _block(nx=3, ny=2, nz=2, size=(0.3, 0.2, 0.2)):
    x, tets = meshes.box_tets(np.zeros(3), np.asarray(size), (nx, ny, nz))
    return TetFEM(x, tets, young=1e5, poisson=0.3, density=1000.0)


def _rot(axis, ang):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(ang) * K + (1 - np.cos(ang)) * K @ K


def _interior(fem):
    surf = np.unique(fem.surface())
    return np.setdiff1d(np.arange(fem.n), surf)


def test_zero_force_at_rest():
    fem = _block()
    assert np.abs(fem.force(fem.x0)).max() < 1e-9
    assert abs(fem.energy(fem.x0)) < 1e-20


def test_patch_test_affine_gives_exact_constant_stress():
    fem = _block(4, 3, 3)
    A = np.array([[1.05, 0.02, -0.01], [0.03, 0.97, 0.04], [-0.02, 0.01, 1.02]])
    x = fem.x0 @ A.T + np.array([0.1, -0.2, 0.3])
    P = fem.stress(x)
    R, S = polar(A[None])
    mu, lam = lame(fem.young, fem.poisson)
    P_exact = 2 * mu * (A - R[0]) + lam * (np.trace(S[0]) - 3) * R[0]
    assert np.abs(P - P_exact).max() <= 1e-9 * np.abs(P_exact).max()
    inner = _interior(fem)
    assert len(inner) > 0
    f = fem.force(x)
    assert np.abs(f[inner]).max() <= 1e-10 * np.abs(f).max()  # interior nodes in equilibrium
    assert np.abs(f.sum(axis=0)).max() <= 1e-10 * np.abs(f).max()


def test_rigid_rotation_gives_zero_elastic_force():
    fem = _block()
    R = _rot([1, 2, 3], 1.1)
    x = fem.x0 @ R.T + np.array([1.0, 2.0, -0.5])
    f = fem.force(x)
    assert np.abs(f).max() < 1e-9
    assert abs(fem.energy(x)) < 1e-12
    # and a stretched + rotated configuration has the rotated forces of the stretch alone
    A = np.diag([1.1, 0.95, 1.0])
    f0 = fem.force(fem.x0 @ A.T)
    f1 = fem.force(fem.x0 @ (R @ A).T)
    assert np.abs(f1 - f0 @ R.T).max() <= 1e-10 * np.abs(f0).max()


def central_differences(fn, x, eps=1e-6):
    """d fn(x).ravel() / dx.ravel() by central differences: (m, 3n) for an array-valued fn, (1, 3n) for a
    scalar one."""
    cols = []
    for j in range(x.size):
        d = np.zeros(x.size)
        d[j] = eps
        d = d.reshape(x.shape)
        cols.append(np.ravel(fn(x + d) - fn(x - d)) / (2 * eps))
    return np.array(cols).T


@pytest.mark.parametrize("seed", [0, 1])
def test_fem_stiffness_matches_central_differences(seed):
    """The compiled kernel's stiffness (fem_kernels.tet_blocks_lanes, scattered into the CSR pattern) against central
    differences of its forces, and the forces against the energy's gradient (round-off at eps = 1e-6: ~1e-11)."""
    rng = np.random.default_rng(seed)
    fem = _block(2, 2, 2)
    x = fem.x0 @ _rot([0.3, 1, 0.2], 0.7).T + 0.03 * rng.standard_normal(fem.x0.shape)
    K = fem.stiffness(x).toarray()
    assert np.abs(K - K.T).max() <= 1e-12 * np.abs(K).max()
    err = np.abs(K + central_differences(fem.force, x)).max() / np.abs(K).max()
    assert err < 1e-8, err
    f = fem.force(x).ravel()
    assert np.abs(f + central_differences(fem.energy, x).ravel()).max() <= 1e-8 * np.abs(f).max()


def test_lumped_mass_is_total_mass():
    fem = _block()
    assert fem.mass.sum() == pytest.approx(1000.0 * 0.3 * 0.2 * 0.2, rel=1e-12)


def test_string_force_and_stiffness_match_central_differences():
    rng = np.random.default_rng(3)
    x0 = np.stack([np.linspace(0, 1, 6), np.zeros(6), np.zeros(6)], 1)
    s = String(x0, mass=0.5, stiffness=200.0)
    x = x0 + 0.05 * rng.standard_normal(x0.shape)
    K = s.stiffness(x).toarray()
    assert np.abs(K + central_differences(s.force, x)).max() / np.abs(K).max() < 1e-8
    f = s.force(x).ravel()
    assert np.abs(f + central_differences(s.energy, x).ravel()).max() <= 1e-8 * np.abs(f).max()
    assert s.mass.sum() == pytest.approx(0.5)


def irvine_sag(span, L0, W, EA):
    """Mid-span sag of an elastic catenary (Irvine, Cable Structures, 1981, §2.3): supports at one height
    ``span`` apart, unstretched length L0, total weight W, axial stiffness EA; H from the span condition."""
    V = W / 2.0

    def x_end(H):
        return H * L0 / EA + H * L0 / W * (np.arcsinh(V / H) - np.arcsinh((V - W) / H)) - span

    H = brentq(x_end, 1e-9 * W, 1e6 * W)
    s = L0 / 2
    return W * s / EA * (V / W - s / (2 * L0)) + H * L0 / W * (np.sqrt(1 + (V / H) ** 2) - np.sqrt(1 + ((V - W * s / L0) / H) ** 2))


def string_static(n, span, L0, mass, EA, g=9.81):
    """Static equilibrium of the discrete string (ends fixed at the supports) by Newton on its
    force and stiffness."""
    xs = np.linspace(0, span, n)
    x0 = np.stack([xs * L0 / span, np.zeros(n), np.zeros(n)], 1)  # rest spacing L0/(n-1)
    s = String(x0, mass=mass, stiffness=EA)
    x = np.stack([xs, np.zeros(n), -0.3 * L0 * np.sin(np.pi * xs / span)], 1)
    free = np.arange(3, 3 * n - 3)
    fg = np.zeros((n, 3))
    fg[:, 2] = -g * s.mass
    for _ in range(100):
        r = (s.force(x) + fg).ravel()[free]
        if np.abs(r).max() < 1e-10 * mass * g:
            break
        K = s.stiffness(x).tocsc()[free][:, free]
        dx = spsolve(K, r)
        x.reshape(-1)[free] += dx
    return -x[n // 2, 2]


def test_hanging_string_sag_matches_elastic_catenary():
    span, L0, mass, EA = 1.0, 1.2, 0.3, 50.0
    exact = irvine_sag(span, L0, mass * 9.81, EA)
    sag = string_static(201, span, L0, mass, EA)
    assert abs(sag - exact) <= 0.01 * exact
    assert abs(sag - exact) <= 1e-3 * exact  # O(1/n^2): far inside 1 % at n = 201
