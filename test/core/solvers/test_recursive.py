"""O(n) Jacobian products (redmax_ros.core.recursive) against dense Pinocchio Jacobians."""
import numpy as np
import pinocchio as pin
import pytest

from recursive_models import MODELS, chain, dense_mass, fallback_joints, random_state
from redmax_ros.core.solvers import recursive as rc

TOL = 1e-12


def setup(name, seed=0):
    model = MODELS[name]()
    rng = np.random.default_rng(seed)
    q, v = random_state(model, rng)
    data = model.createData()
    topo = rc.build_topology(model)
    ws = rc.update_kinematics(topo, rc.make_workspace(topo), q, v)
    pin.computeJointJacobiansTimeVariation(model, data, q, v)  # oMi, data.J, data.dJ
    return model, data, topo, ws, q, v, rng


def rel(a, b):
    return np.max(np.abs(a - b)) / max(1.0, np.max(np.abs(b)))


@pytest.mark.parametrize("name", list(MODELS))
def test_kinematics_match_pinocchio(name):
    model, data, topo, ws, *_ = setup(name)
    for j in range(model.njoints):
        assert np.allclose(ws.R[j], data.oMi[j].rotation, rtol=0, atol=TOL)
        assert np.allclose(ws.p[j], data.oMi[j].translation, rtol=0, atol=TOL)
    assert rel(ws.S, data.J.reshape(6, -1)) < TOL
    for j in range(1, model.njoints):
        assert rel(ws.I[j], data.oMi[j].act(model.inertias[j]).matrix()) < TOL


@pytest.mark.parametrize("name", list(MODELS))
def test_jv_matches_dense_world_and_local(name):
    model, data, topo, ws, q, v, rng = setup(name)
    for trial in range(3):
        x = rng.normal(size=model.nv)
        Y = rc.jv(topo, ws, x)
        Yl = rc.twists_world_to_local(ws, Y)
        for j in range(model.njoints):
            assert rel(Y[j], pin.getJointJacobian(model, data, j, pin.WORLD) @ x) < TOL
            assert rel(Yl[j], pin.getJointJacobian(model, data, j, pin.LOCAL) @ x) < TOL
    # body twists at the state velocity
    assert rel(ws.ov, rc.jv(topo, ws, v)) < TOL


@pytest.mark.parametrize("name", list(MODELS))
def test_jtw_matches_dense(name):
    model, data, topo, ws, q, v, rng = setup(name)
    for trial in range(3):
        W = rng.normal(size=(model.njoints, 6))
        ref = sum(pin.getJointJacobian(model, data, j, pin.WORLD).T @ W[j] for j in range(1, model.njoints))
        assert rel(rc.jtw(topo, ws, W), ref) < TOL
        # local wrenches: J_local^T W_local == J_world^T (wrench mapped to the world)
        ref_l = sum(pin.getJointJacobian(model, data, j, pin.LOCAL).T @ W[j] for j in range(1, model.njoints))
        assert rel(rc.jtw(topo, ws, rc.wrenches_local_to_world(ws, W)), ref_l) < TOL
    # the universe row is ignored
    W = np.zeros((model.njoints, 6))
    W[0] = rng.normal(size=6)
    assert np.all(rc.jtw(topo, ws, W) == 0.0)


@pytest.mark.parametrize("name", list(MODELS))
def test_jt_is_adjoint_of_j(name):
    """<J x, W> == <x, J^T W> (power balance), an identity independent of Pinocchio."""
    model, data, topo, ws, q, v, rng = setup(name)
    x = rng.normal(size=model.nv)
    W = rng.normal(size=(model.njoints, 6))
    W[0] = 0.0
    lhs = np.sum(rc.jv(topo, ws, x) * W)
    assert abs(lhs - x @ rc.jtw(topo, ws, W)) < 1e-12 * max(1.0, abs(lhs))


@pytest.mark.parametrize("name", list(MODELS))
def test_jdot_matches_dense(name):
    model, data, topo, ws, q, v, rng = setup(name)
    for trial in range(3):
        x = rng.normal(size=model.nv)
        Z = rc.jdot_v(topo, ws, x)
        for j in range(model.njoints):
            assert rel(Z[j], pin.getJointJacobianTimeVariation(model, data, j, pin.WORLD) @ x) < TOL


@pytest.mark.parametrize("name", list(MODELS))
def test_bias_acceleration_matches_forward_kinematics(name):
    """Exact Jdot qdot = world spatial acceleration at zero joint acceleration (includes the
    joint bias c of configuration-dependent subspaces)."""
    model, data, topo, ws, q, v, rng = setup(name)
    pin.forwardKinematics(model, data, q, v, np.zeros(model.nv))
    Z = rc.bias_acceleration(topo, ws)
    for j in range(1, model.njoints):
        assert rel(Z[j], data.oMi[j].act(data.a[j]).vector) < TOL


def test_bias_acceleration_finite_difference():
    """d/dt (J(q) v) at fixed v by central differences along qdot = v, for joints whose motion
    subspace depends on q (Planar, SphericalZYX, Universal, Composite)."""
    model = fallback_joints()
    rng = np.random.default_rng(5)
    q, v = random_state(model, rng)
    topo = rc.build_topology(model)
    ws = rc.update_kinematics(topo, rc.make_workspace(topo), q, v)
    Z = rc.bias_acceleration(topo, ws)
    eps = 1e-6
    wp = rc.update_kinematics(topo, rc.make_workspace(topo), pin.integrate(model, q, eps * v))
    wm = rc.update_kinematics(topo, rc.make_workspace(topo), pin.integrate(model, q, -eps * v))
    fd = (rc.jv(topo, wp, v) - rc.jv(topo, wm, v)) / (2 * eps)
    assert np.max(np.abs(Z - fd)) < 1e-6 * max(1.0, np.max(np.abs(fd)))
    # jdot_v (Pinocchio's dJ convention) differs exactly by the joint bias terms there
    assert np.max(np.abs(rc.jdot_v(topo, ws, v) - Z)) > 1e-3


@pytest.mark.parametrize("name", list(MODELS))
def test_site_products_match_frame_jacobians(name):
    model, data, topo, ws, q, v, rng = setup(name)
    m = 7
    joint = rng.integers(0, model.njoints, size=m)
    joint[0] = 0  # one site on the world
    offset = rng.normal(size=(m, 3))
    pos = rc.site_positions(ws, joint, offset)
    x = rng.normal(size=model.nv)
    f = rng.normal(size=(m, 3))
    u = rc.site_jv(topo, ws, joint, pos, x)
    Jt_f = np.zeros(model.nv)
    for s in range(m):
        Js = pin.getFrameJacobian(model, data, int(joint[s]), pin.SE3(np.eye(3), offset[s]),
                                  pin.LOCAL_WORLD_ALIGNED)[:3]
        ref_pos = data.oMi[int(joint[s])].act(offset[s])
        assert np.allclose(pos[s], ref_pos, rtol=0, atol=TOL)
        assert rel(u[s], Js @ x) < TOL
        Jt_f += Js.T @ f[s]
    assert rel(rc.site_jtf(topo, ws, joint, pos, f), Jt_f) < TOL


def test_point_block_projects_point_stiffness():
    """J_site^T K3 J_site == J_body^T (X^T K3 X) J_body for a site on the body."""
    model, data, topo, ws, q, v, rng = setup("humanoid")
    j = 7
    off = rng.normal(size=3)
    A = rng.normal(size=(3, 3))
    K3 = A @ A.T
    x = data.oMi[j].act(off)
    Js = pin.getFrameJacobian(model, data, j, pin.SE3(np.eye(3), off), pin.LOCAL_WORLD_ALIGNED)[:3]
    Jb = pin.getJointJacobian(model, data, j, pin.WORLD)
    lhs = Js.T @ K3 @ Js
    assert rel(Jb.T @ rc.point_block(x, K3) @ Jb, lhs) < 1e-12 * max(1.0, np.max(np.abs(lhs)))


def test_block_to_world_preserves_quadratic_form():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(6, 6))
    B = A @ A.T
    R, p = pin.exp3(rng.normal(size=3)), rng.normal(size=3)
    Y = rng.normal(size=6)  # world twist
    Yf = pin.SE3(R, p).inverse().action @ Y  # same twist in frame F
    assert abs(Y @ rc.block_to_world(R, p, B) @ Y - Yf @ B @ Yf) < 1e-10


@pytest.mark.parametrize("name", list(MODELS))
def test_mass_matrix_product(name):
    model, data, topo, ws, q, v, rng = setup(name)
    M = dense_mass(model, data, q)  # includes model.armature
    m0 = model.copy()
    m0.gravity.setZero()
    for trial in range(3):
        x = rng.normal(size=model.nv)
        Mx = rc.mass_matrix_product(topo, ws, x)
        assert rel(Mx, M @ x) < 1e-11
        assert rel(Mx, pin.rnea(m0, m0.createData(), q, np.zeros(model.nv), x)) < 1e-11


def test_workspace_without_pinocchio_data_scales():
    """update_kinematics + products need no pin.Data (whose size is O(nv^3) in pin 4.1)."""
    model = chain(n=400, seed=4, armature=False)
    topo = rc.build_topology(model)
    ws = rc.make_workspace(topo)
    rng = np.random.default_rng(0)
    q, v = random_state(model, rng)
    rc.update_kinematics(topo, ws, q, v)
    # chain: the tip twist equals the sum of all joint contributions
    x = rng.normal(size=model.nv)
    Y = rc.jv(topo, ws, x)
    assert np.allclose(Y[-1], ws.S @ x, rtol=0, atol=1e-10)
    W = np.zeros((model.njoints, 6))
    W[-1] = rng.normal(size=6)
    assert np.allclose(rc.jtw(topo, ws, W), ws.S.T @ W[-1], rtol=0, atol=1e-10)


def test_mimic_joint_rejected():
    if not hasattr(pin, "JointModelMimic"):
        pytest.skip("no mimic joints in this Pinocchio")
    m = pin.Model()
    j1 = m.addJoint(0, pin.JointModelRX(), pin.SE3.Identity(), "a")
    m.addJoint(j1, pin.JointModelMimic(m.joints[j1], 2.0, 0.0), pin.SE3.Identity(), "b")
    with pytest.raises(NotImplementedError):
        rc.build_topology(m)


@pytest.mark.parametrize("name", ["fallback_joints", "floating_spherical"])
def test_workspace_reuse_matches_fresh_workspace(name):
    model = MODELS[name]()
    topo = rc.build_topology(model)
    rng = np.random.default_rng(9)
    q1, v1 = random_state(model, rng)
    q2, v2 = random_state(model, rng)
    reused = rc.update_kinematics(topo, rc.make_workspace(topo), q1, v1)
    rc.update_kinematics(topo, reused, q2, v2)
    fresh = rc.update_kinematics(topo, rc.make_workspace(topo), q2, v2)
    for a in ("R", "p", "St", "I", "ov", "c_local"):
        assert np.array_equal(getattr(reused, a), getattr(fresh, a)), a
    rc.update_kinematics(topo, reused, q2)  # no velocity: velocity-dependent products refuse
    with pytest.raises(ValueError):
        rc.jdot_v(topo, reused, v2)
    with pytest.raises(ValueError):
        rc.bias_acceleration(topo, reused)
