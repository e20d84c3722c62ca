"""integrator.coriolis: implicit (docs/scenes.md, "Integrator"): the Coriolis/gyroscopic force of Eq. (2)
linearised about the step's start velocity, (M + h K_v) qdot+ = M qdot + h (tau - nle) + h K_v qdot with
K_v = d nle / d qdot; its Jacobian, the non-symmetric solves (LU kernel, numpy LU, limit QP fixed point),
validation, and that the default is the unchanged explicit step. The energy behaviour per catalogue scene
is in test_catalogue.py."""
import numpy as np
import pinocchio as pin
import pytest

from redmax_ros.core import SceneError, Simulator
from redmax_ros.core.solvers.problem import Constraints
from redmax_ros.core.dynamics.forces import coriolis_jacobian
from redmax_ros.core.solvers.problem import LinearSystem
from redmax_ros.core.solvers.direct import solve_direct

IMPLICIT = "integrator={coriolis: implicit}"


def energies_of(sim, n):
    return np.array([sim.step().diagnostics.E_total for _ in range(n)])


@pytest.mark.parametrize("name", ["catalogue/spherical", "catalogue/universal", "catalogue/composite",
                                  "catalogue/free3d", "hand", "branching"])
def test_coriolis_jacobian_matches_finite_differences(name):
    """K_v from exact central differences of the quadratic RNEA term agrees with finite differences of
    Pinocchio's nle (step 1e-6: truncation-free since nle is quadratic in qdot, round-off ~1e-10)."""
    sim = Simulator.load(name)
    m = sim.mech
    rng = np.random.default_rng(3)
    q = pin.randomConfiguration(m.model, -np.ones(m.nq), np.ones(m.nq)) if name == "hand" else m.q0.copy()
    v = rng.standard_normal(m.nv)
    K = coriolis_jacobian(m, sim.workspace, q, v)
    d, e, fd = m.model.createData(), 1e-6, np.zeros((m.nv, m.nv))
    for i in range(m.nv):
        dv = np.zeros(m.nv)
        dv[i] = e
        fd[:, i] = (pin.nonLinearEffects(m.model, d, q, v + dv).copy() - pin.nonLinearEffects(m.model, d, q, v - dv)) / (2 * e)
    assert np.abs(K - fd).max() < 1e-8 * max(1.0, np.abs(fd).max()), np.abs(K - fd).max()
    assert np.abs(K @ v - 2 * (pin.nonLinearEffects(m.model, d, q, v) - pin.computeGeneralizedGravity(m.model, d, q))).max() < 1e-12


def test_default_is_the_explicit_step_bit_for_bit():
    """No key, coriolis: explicit: the same trajectory bit for bit (the option is opt-in)."""
    for name in ("hand", "catalogue/mesh_wedge"):
        a, b = Simulator.load(name), Simulator.load(name, ["integrator={coriolis: explicit}"])
        for _ in range(50):
            ra, rb = a.step(), b.step()
            assert np.array_equal(ra.q, rb.q) and np.array_equal(ra.v, rb.v)
    assert not Simulator.load("catalogue/revolute").mech.coriolis_implicit


@pytest.mark.parametrize("h", [1e-2, 1e-3])
def test_free_body_never_gains_energy(h):
    """Tumbling box in zero gravity, no momentum projection: explicit, E+ - E = 1/2 h^2 |I w x w|^2_(I^-1) > 0
    every step (test_catalogue); implicit: E+ <= E every step, a first-order loss (measured E(5 s)/E0 =
    0.98789 at h = 1e-2, 0.99866 at h = 1e-3; explicit 1.01529, 1.00137)."""
    sim = Simulator.load("catalogue/free3d", ["joints.free.conserve_momentum=false", f"dt={h}", IMPLICIT])
    E = np.concatenate([[_energy(sim)], energies_of(sim, int(round(5.0 / h)))])
    assert np.all(np.diff(E) <= 1e-13 * E[0]), np.diff(E).max()
    assert 0.95 < E[-1] / E[0] < 1.0, E[-1] / E[0]


def _energy(sim):
    return sum(sim.energies())


def test_loops_and_couplings_with_the_lu_kernel():
    """gear_loop (loop rows, a coupling, post-stabilization) with the option: the non-symmetric KKT system is
    solved by the LU Schur complement; velocity-level residual at round-off, loop closed to 1e-10 m,
    stationarity residual at round-off."""
    sim = Simulator.load("catalogue/gear_loop", [IMPLICIT])
    for _ in range(500):
        d = sim.step().diagnostics
        assert d.violation_vel < 1e-10 and d.violation_pos <= 1e-10
    assert d.residual < 1e-12


def test_large_system_numpy_lu_path():
    """Above kkt.SMALL_N (64 DOFs) the numpy LU route: a 70-link chain with a prescribed base joint solves the
    KKT system to round-off (relative stationarity residual, prescribed rows) and agrees with a dense solve of
    the KKT matrix and with the kernel route (SMALL_N raised) to 1e-8 (the long chain's mass matrix is
    ill-conditioned: measured differences 2e-10)."""
    from redmax_ros.core.solvers import kkt
    from redmax_ros.core.solvers import direct as solve
    sim = Simulator.load("chain", ["params.n=70", IMPLICIT])
    sim.step(3)
    names = list(sim.mech.joint_index)
    sim.prescribe_joints({names[0]: [0.3]})
    r = sim.step()
    sol = r.diagnostics.solution
    A, b, G, g = sol.system.A, sol.system.b, sol.cons.G, sol.cons.g
    assert not sol.system.symmetric and np.abs(A - A.T).max() > 0
    n, m = len(b), len(g)
    K = np.block([[A, G.T], [G, np.zeros((m, m))]])
    x = np.linalg.solve(K, np.concatenate([b, g]))
    assert sol.residual < 1e-12 and r.diagnostics.violation_vel < 1e-12
    assert np.abs(sol.v - x[:n]).max() < 1e-8 * max(1.0, np.abs(x[:n]).max())
    old = solve.SMALL_N
    try:
        solve.SMALL_N = 1000
        s2 = solve.solve_direct(sol.system, sol.cons)
    finally:
        solve.SMALL_N = old
    assert np.abs(s2.v - sol.v).max() < 1e-8 * max(1.0, np.abs(sol.v).max())
    assert kkt.SMALL_N == 64


def _random_system(n, m, p, seed, asym=0.05):
    rng = np.random.default_rng(seed)
    B = rng.standard_normal((n, n))
    S = B @ B.T + n * np.eye(n)
    W = rng.standard_normal((n, n))
    A = S + asym * (W - W.T) * n
    G = rng.standard_normal((m, n))
    C = rng.standard_normal((p, n))
    return A, rng.standard_normal(n), G, rng.standard_normal(m), C


def _cons(G, g, C=None, lo=None, hi=None):
    return Constraints(G, g, [("row", len(g))], C=C, lo=lo, hi=hi)


def test_limit_qp_fixed_point_solves_the_nonsymmetric_complementarity_problem():
    """Joint limits with a non-symmetric A: the fixed point of symmetric QPs satisfies A v = b - G^T lam - C^T mu
    with lo <= C v <= hi and mu complementary (mu >= 0 only at active bounds, sign convention of solve.py)."""
    A, b, G, g, C = _random_system(8, 2, 3, 5)
    v_free = np.linalg.solve(np.block([[A, G.T], [G, np.zeros((2, 2))]]), np.concatenate([b, g]))[:8]
    Cv = C @ v_free
    lo, hi = np.full(3, -np.inf), Cv - 0.5 * np.abs(Cv) - 0.1  # upper bounds all violated by the free solution
    sol = solve_direct(LinearSystem(A, b, False), _cons(G, g, C, lo, hi))
    assert sol.solver == "qp"
    v, lam, mu = sol.v, sol.lam, sol.mu
    r = A @ v - b + G.T @ lam + C.T @ mu
    assert np.abs(r).max() < 1e-8 * np.abs(b).max(), np.abs(r).max()
    assert np.abs(G @ v - g).max() < 1e-9
    assert np.all(C @ v <= hi + 1e-9)
    active = C @ v > hi - 1e-8
    assert np.all(mu[~active] == pytest.approx(0, abs=1e-8)) and np.all(mu[active] >= -1e-9)


def test_limits_multi_with_the_option():
    """limits_multi (limit impacts on translational and Euler-angle joints) steps with the option, the QP
    route is taken, limits hold, and energy does not end above E0."""
    sim = Simulator.load("catalogue/limits_multi", [IMPLICIT])
    solvers, E = set(), []
    for _ in range(1500):
        d = sim.step().diagnostics
        solvers.add(d.solver)
        E.append(d.E_total)
    assert "qp" in solvers
    assert E[-1] < E[0]


@pytest.mark.parametrize("name, overrides, text", [
    ("catalogue/spherical", ["integrator=implicit"], "integrator: must be a mapping"),
    ("catalogue/spherical", ["integrator={coriolis: implicit, order: 2}"], "unknown key(s) ['order']"),
    ("catalogue/spherical", ["integrator={coriolis: semi}"], "integrator.coriolis: unknown value 'semi'"),
    ("catalogue/spherical", ["solver=pcg", IMPLICIT], "integrator.coriolis: 'implicit' needs solver: direct"),
    ("incline", [IMPLICIT], "integrator.coriolis: 'implicit' is not supported with contact or joint friction"),
    ("chain", ["params.n=120", IMPLICIT], "integrator.coriolis: 'implicit' is implemented in the Pinocchio pipeline only"),
])
def test_option_validation(name, overrides, text):
    with pytest.raises(SceneError) as ei:
        Simulator.load(name, overrides)
    assert text in str(ei.value), str(ei.value)


def test_simulator_solver_override_is_rejected():
    with pytest.raises(SceneError, match="integrator.coriolis"):
        Simulator.load("pendulum", [IMPLICIT], solver="auto")
