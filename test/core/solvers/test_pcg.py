"""Projected Block Jacobi Preconditioner (Alg. 1), matrix-free LHS of Eq. (2), PCG and the
loop-closure path of §3.1 Eq. (4), checked against dense Pinocchio matrices."""
import numpy as np
import pinocchio as pin
import pytest

from recursive_models import MODELS, chain, dense_mass, random_state
from redmax_ros.core.solvers import recursive as rc
from redmax_ros.core.solvers.pcg import MatrixFreeSystem, PointSprings, pcg, solve_loop_closure
from redmax_ros.core.solvers.preconditioner import ProjectedBlockJacobi

H = 1e-2  # time step [s]


def setup(model, seed=0):
    rng = np.random.default_rng(seed)
    q, v = random_state(model, rng)
    data = model.createData()
    topo = rc.build_topology(model)
    ws = rc.update_kinematics(topo, rc.make_workspace(topo), q, v)
    pin.computeJointJacobians(model, data, q)
    M = dense_mass(model, data, q)
    return data, topo, ws, q, M, rng


def spd(rng, n, scale=1.0):
    A = rng.normal(size=(n, n))
    return scale * (A @ A.T)


def dense_inverse_of(P, nv):
    return np.column_stack([P.apply(e) for e in np.eye(nv)])


def site_jacobian(model, data, joint, offset):
    """World-frame point Jacobian (3 x nv) of a site; zero for the world."""
    if joint == 0:
        return np.zeros((3, model.nv))
    return pin.getFrameJacobian(model, data, int(joint), pin.SE3(np.eye(3), offset), pin.LOCAL_WORLD_ALIGNED)[:3]


def random_springs(model, rng, m, world_only=False, same_body=0):
    ja = rng.integers(1, model.njoints, size=m)
    jb = np.zeros(m, dtype=int) if world_only else rng.integers(0, model.njoints, size=m)
    jb[:same_body] = ja[:same_body]
    return PointSprings(ja, 0.1 * rng.normal(size=(m, 3)), jb, 0.1 * rng.normal(size=(m, 3)),
                        stiffness=np.array([spd(rng, 3, 1e3) for _ in range(m)]),
                        damping=np.array([spd(rng, 3, 1.0) for _ in range(m)]))


def dense_lhs(model, data, M, springs, h, reduced, body_blocks=None):
    """A = M (with armature) + diag(reduced) + J^T B J + sum_s J_s^T (h D + h^2 K) J_s, densely."""
    A = M + np.diag(reduced)
    if body_blocks is not None:
        for j in range(1, model.njoints):
            J = pin.getJointJacobian(model, data, j, pin.WORLD)
            A += J.T @ body_blocks[j] @ J
    for s in range(springs.m):
        Js = (site_jacobian(model, data, springs.joint_a[s], springs.offset_a[s])
              - site_jacobian(model, data, springs.joint_b[s], springs.offset_b[s]))
        A += Js.T @ (h * springs.damping[s] + h * h * springs.stiffness[s]) @ Js
    return A


@pytest.mark.parametrize("name", list(MODELS))
def test_preconditioner_without_maximal_terms_is_inverse_mass(name):
    """Alg. 1 with A^m = 0: P^{-1} = (M + diag(armature + reduced))^{-1}; pin.crba includes the armature."""
    model = MODELS[name]()
    data, topo, ws, q, M, rng = setup(model)
    reduced = rng.uniform(0.0, 1.0, size=model.nv)
    P = ProjectedBlockJacobi(topo).factor(ws, reduced_diag=reduced)
    ref = np.linalg.inv(M + np.diag(reduced))
    assert np.max(np.abs(dense_inverse_of(P, model.nv) - ref)) < 1e-10 * np.max(np.abs(ref))
    # plain M^{-1} (reduced terms and armature off) against Pinocchio's computeMinverse
    m0 = model.copy()
    m0.armature = np.zeros(model.nv)
    Minv = pin.computeMinverse(m0, m0.createData(), q)
    Minv = np.triu(Minv) + np.triu(Minv, 1).T
    P.factor(ws, include_armature=False)
    assert np.max(np.abs(dense_inverse_of(P, model.nv) - Minv)) < 1e-10 * np.max(np.abs(Minv))


@pytest.mark.parametrize("name", list(MODELS))
def test_preconditioner_with_body_blocks_is_exact(name):
    """Maximal terms restricted to each body's own 6x6 block: P = J^T blkdiag J + M + diag exactly."""
    model = MODELS[name]()
    data, topo, ws, q, M, rng = setup(model, seed=1)
    reduced = rng.uniform(0.0, 1.0, size=model.nv)
    blocks = np.zeros((model.njoints, 6, 6))
    for j in range(1, model.njoints):
        blocks[j] = spd(rng, 6, 0.5)
    A = M + np.diag(reduced)
    for j in range(1, model.njoints):
        J = pin.getJointJacobian(model, data, j, pin.WORLD)
        A += J.T @ blocks[j] @ J
    P = ProjectedBlockJacobi(topo).factor(ws, blocks, reduced)
    ref = np.linalg.inv(A)
    assert np.max(np.abs(dense_inverse_of(P, model.nv) - ref)) < 1e-10 * np.max(np.abs(ref))


def test_preconditioner_single_body_block():
    model = chain(n=10, seed=7)
    data, topo, ws, q, M, rng = setup(model, seed=2)
    j = 4
    blocks = np.zeros((model.njoints, 6, 6))
    blocks[j] = spd(rng, 6, 10.0)
    J = pin.getJointJacobian(model, data, j, pin.WORLD)
    ref = np.linalg.inv(M + J.T @ blocks[j] @ J)
    P = ProjectedBlockJacobi(topo).factor(ws, blocks)
    assert np.max(np.abs(dense_inverse_of(P, model.nv) - ref)) < 1e-10 * np.max(np.abs(ref))


def test_preconditioner_rejects_indefinite_joint_term():
    model = chain(n=5)
    data, topo, ws, q, M, rng = setup(model)
    reduced = np.zeros(model.nv)
    reduced[2] = -1e6
    with pytest.raises(ValueError, match="line 6"):
        ProjectedBlockJacobi(topo).factor(ws, reduced_diag=reduced)


@pytest.mark.parametrize("name", ["chain", "tree", "floating_spherical", "humanoid"])
def test_matrix_free_lhs_matches_dense(name):
    model = MODELS[name]()
    data, topo, ws, q, M, rng = setup(model, seed=3)
    springs = random_springs(model, rng, 12, same_body=2)
    reduced = rng.uniform(0.0, 1.0, size=model.nv)
    blocks = np.zeros((model.njoints, 6, 6))
    blocks[1:] = [spd(rng, 6, 0.1) for _ in range(model.njoints - 1)]
    sys = MatrixFreeSystem(topo, ws, H, reduced, springs, body_blocks=blocks)
    A = dense_lhs(model, data, M, springs, H, reduced, blocks)
    for trial in range(3):
        x = rng.normal(size=model.nv)
        assert np.max(np.abs(sys.apply(x) - A @ x)) < 1e-11 * np.max(np.abs(A @ x))


def test_pcg_matches_dense_solve_on_chain_with_many_springs():
    model = chain(n=40, seed=11)
    data, topo, ws, q, M, rng = setup(model, seed=4)
    springs = random_springs(model, rng, 80)
    reduced = H * 0.5 + H * H * rng.uniform(0.0, 50.0, size=model.nv)
    sys = MatrixFreeSystem(topo, ws, H, reduced, springs)
    A = dense_lhs(model, data, M, springs, H, reduced)
    b = rng.normal(size=model.nv)
    x_ref = np.linalg.solve(A, b)
    res = sys.solve(b, rtol=1e-10)
    assert res.converged and res.residual <= 1e-10
    assert np.linalg.norm(res.x - x_ref) <= 1e-6 * np.linalg.norm(x_ref)
    assert np.linalg.norm(A @ res.x - b) <= 1e-9 * np.linalg.norm(b)  # the reported residual is true
    # the preconditioner pays off against unpreconditioned CG
    plain = pcg(sys.apply, lambda r: r.copy(), b, rtol=1e-10, max_iter=10 * model.nv)
    assert res.iterations < plain.iterations
    # default tolerance: relative residual 1e-6
    res6 = sys.solve(b)
    assert res6.converged and np.linalg.norm(A @ res6.x - b) <= 1.01e-6 * np.linalg.norm(b)
    # warm start from the solution: nothing to do
    assert sys.solve(b, x0=x_ref, rtol=1e-8).iterations == 0


@pytest.mark.parametrize("name", ["chain", "tree", "humanoid"])
def test_world_springs_make_preconditioner_exact(name):
    """Springs attached to the world (or with both ends on one body) only produce body-diagonal
    maximal blocks: P = A and PCG converges in one iteration (BRIDGE scene remark, §3)."""
    model = MODELS[name]()
    data, topo, ws, q, M, rng = setup(model, seed=5)
    springs = random_springs(model, rng, 10, world_only=True, same_body=3)
    reduced = rng.uniform(0.0, 1.0, size=model.nv)
    blocks = np.zeros((model.njoints, 6, 6))
    blocks[2] = spd(rng, 6, 1.0)
    sys = MatrixFreeSystem(topo, ws, H, reduced, springs, body_blocks=blocks)
    A = dense_lhs(model, data, M, springs, H, reduced, blocks)
    P = sys.preconditioner()
    Ainv = np.linalg.inv(A)
    assert np.max(np.abs(dense_inverse_of(P, model.nv) - Ainv)) < 1e-9 * np.max(np.abs(Ainv))
    res = sys.solve(rng.normal(size=model.nv), P=P)
    assert res.converged and res.iterations <= 2


def test_pcg_generic_spd_and_edge_cases():
    rng = np.random.default_rng(0)
    n = 30
    A = spd(rng, n) + n * np.eye(n)
    b = rng.normal(size=n)
    d = np.diag(A).copy()
    res = pcg(lambda x: A @ x, lambda r: r / d, b, rtol=1e-12)
    assert res.converged and np.allclose(res.x, np.linalg.solve(A, b), rtol=1e-10, atol=1e-12)
    zero = pcg(lambda x: A @ x, lambda r: r, np.zeros(n))
    assert zero.converged and zero.iterations == 0 and not np.any(zero.x)
    capped = pcg(lambda x: A @ x, lambda r: r, b, rtol=1e-14, max_iter=2)
    assert not capped.converged and capped.iterations == 2
    indefinite = pcg(lambda x: -x, lambda r: r, b)
    assert not indefinite.converged


def test_loop_closure_matches_dense_kkt():
    """§3.1 Eq. (4): tip of a chain pinned to a world point (3 rows) plus one joint velocity
    prescribed (a reduced row), with springs; compare with the dense KKT solve."""
    model = chain(n=20, seed=12)
    data, topo, ws, q, M, rng = setup(model, seed=6)
    springs = random_springs(model, rng, 25)
    reduced = rng.uniform(0.0, 1.0, size=model.nv)
    sys = MatrixFreeSystem(topo, ws, H, reduced, springs)
    A = dense_lhs(model, data, M, springs, H, reduced)
    tip = model.njoints - 1
    G = np.vstack([site_jacobian(model, data, tip, np.array([0.0, 0.0, 0.2])), np.eye(model.nv)[3]])
    g = np.array([0.0, 0.0, 0.0, 0.7])
    b = rng.normal(size=model.nv)
    l = G.shape[0]
    K = np.block([[A, G.T], [G, np.zeros((l, l))]])
    sol = np.linalg.solve(K, np.concatenate([b, g]))
    P = sys.preconditioner()
    res = solve_loop_closure(sys.apply, P.apply, b, G, g, rtol=1e-10)
    assert res.converged and len(res.iterations) == l + 1
    assert np.linalg.norm(res.x - sol[:model.nv]) <= 1e-6 * np.linalg.norm(sol[:model.nv])
    assert np.linalg.norm(res.lam - sol[model.nv:]) <= 1e-6 * np.linalg.norm(sol[model.nv:])
    assert res.constraint_residual < 1e-8


def test_loop_closure_redundant_rows():
    """A duplicated constraint row (rank-deficient G A^-1 G^T) still gives the constrained velocity."""
    model = chain(n=8, seed=13)
    data, topo, ws, q, M, rng = setup(model, seed=7)
    sys = MatrixFreeSystem(topo, ws, H, rng.uniform(0.0, 1.0, size=model.nv))
    Gs = site_jacobian(model, data, model.njoints - 1, np.zeros(3))
    G = np.vstack([Gs, Gs[:1]])
    b = rng.normal(size=model.nv)
    res = solve_loop_closure(sys.apply, sys.preconditioner().apply, b, G, rtol=1e-12)
    A = dense_lhs(model, data, M, sys.springs, H, sys.reduced_diag)
    K = np.block([[A, Gs.T], [Gs, np.zeros((3, 3))]])
    ref = np.linalg.solve(K, np.concatenate([b, np.zeros(3)]))[:model.nv]
    assert np.linalg.norm(res.x - ref) <= 1e-6 * np.linalg.norm(ref)
    assert res.constraint_residual < 1e-8


def test_dual_solve_matches_numpy_products():
    """lockstep_pcg.dual_solve (one compiled call) against the numpy products it replaced in the PCG step:
    y = (H Z)^-1 (H u - g) (symmetrised H Z), v = u - Z y; to round-off, and a redundant row is named."""
    from redmax_ros.core.errors import StepError
    from redmax_ros.core.solvers.lockstep_pcg import dual_solve
    rng = np.random.default_rng(5)
    n, l = 40, 7
    A = spd(rng, n) + n * np.eye(n)
    H = rng.normal(size=(l, n))
    b, g = rng.normal(size=n), rng.normal(size=l)
    X = np.vstack([np.linalg.solve(A, b), np.linalg.solve(A, H.T).T])
    u, Z = X[0], X[1:].T
    S = H @ Z
    y_ref = np.linalg.solve(0.5 * (S + S.T), H @ u - g)
    v_ref = u - Z @ y_ref
    y, v = dual_solve(H, X, g, [f"row {i}" for i in range(l)])
    assert np.max(np.abs(y - y_ref)) <= 1e-12 * np.max(np.abs(y_ref))
    assert np.max(np.abs(v - v_ref)) <= 1e-13 * np.max(np.abs(u))
    assert np.max(np.abs(H @ v - g)) <= 1e-12 * np.max(np.abs(g))  # the rows hold
    Hr = np.vstack([H, H[2]])  # a repeated row: S singular, named
    Xr = np.vstack([X, X[3]])
    with pytest.raises(StepError, match="row 2|row 7"):
        dual_solve(Hr, Xr, np.concatenate([g, g[2:3]]), [f"row {i}" for i in range(l + 1)])


@pytest.mark.parametrize("name", ["chain", "tree"])
def test_kkt_residual_kernel_matches_products(name):
    """lockstep_kernel.kkt_residual_kernel against MatrixFreeSystem.apply and numpy: r = A v - b + H^T y
    (+ mu on limited DOFs), r.r, b.b and max |H_i v - g_i| over the first m rows."""
    from redmax_ros.core.solvers.lockstep_kernel import kkt_residual_kernel
    model = MODELS[name]()
    data, topo, ws, q, M, rng = setup(model, seed=7)
    springs = random_springs(model, rng, 6, same_body=1)
    sys = MatrixFreeSystem(topo, ws, H, rng.uniform(0.0, 1.0, size=model.nv), springs)
    nv, l, m = model.nv, 4, 3
    v, b, Hr, y, g = (rng.normal(size=nv), rng.normal(size=nv), rng.normal(size=(l, nv)), rng.normal(size=l),
                      rng.normal(size=m))
    limited, mu = np.array([0, nv - 1], dtype=np.int64), np.array([0.3, -0.2])
    r_ref = sys.apply(v) - b + Hr.T @ y
    r_ref[limited] += mu
    r = np.empty(nv)
    rr, bb, viol = kkt_residual_kernel(*sys.lhs_args(), *sys.lhs_scratch(), v, b, Hr, y, limited, mu, m, g, r)
    scale = np.max(np.abs(sys.apply(v))) + np.max(np.abs(Hr.T @ y))
    assert np.max(np.abs(r - r_ref)) <= 1e-13 * scale
    assert rr == pytest.approx(r_ref @ r_ref, rel=1e-12) and bb == pytest.approx(b @ b, rel=1e-14)
    assert viol == pytest.approx(np.abs(Hr[:m] @ v - g).max(), rel=1e-12)
