"""Springs with ``implicit: false`` (issue 13 item 6): explicit force only (notes §1.9: "for explicit
integration we only need f and not K and D"), nothing of the spring in the LHS of Eq. (2).

Checked: the LHS of the step equals the LHS without the spring (and the implicit spring's LHS minus
J^T (h D + h^2 K) J); one step equals an explicit-force step computed by hand from Pinocchio's site
positions/velocities; the catalogue scene is exactly symplectic Euler (analytic period, no amplitude
decay); direction springs the same; the PCG / data-free paths equal the direct path
(test/core/step/test_matrix_free.py, EXTRA); SceneErrors.
"""
import numpy as np
import pinocchio as pin
import pytest

from redmax_ros.core import SceneError, Simulator
from redmax_ros.core.dynamics import forces, kinematics
from redmax_ros.core.dynamics.springs import spring_forces

LWA = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
BASE = ["params.n=4", "params.springs=2", "params.spring_k=300", "params.spring_d=0.8",
        "params.spring_rest=0.15", "joints.j0.q0=0.6", "joints.j1.q0=0.5", "joints.j1.v0=2.0", "joints.j3.v0=-1.5"]


def assemble(sim, q, v, h):
    ws = sim.workspace
    kin = kinematics.compute(sim.mech, ws, q, v, [])
    return forces.assemble(sim.mech, ws, kin, q, v, sim.mech.torque0.copy(), h), kin


def site_state(sim, q, v, name):
    """World position and velocity of a site, from Pinocchio frames (not the code under test)."""
    m = sim.mech
    data = m.model.createData()
    pin.forwardKinematics(m.model, data, q, v)
    pin.updateFramePlacements(m.model, data)
    fid = m.site_fid[m.site_index[name]]
    if fid < 0:  # world site
        return np.asarray(sim.spec.sites[m.site_index[name]].pos, float), np.zeros(3)
    return data.oMf[fid].translation.copy(), pin.getFrameVelocity(m.model, data, fid, LWA).linear.copy()


def site_jacobian(sim, q, name):
    m = sim.mech
    data = m.model.createData()
    pin.computeJointJacobians(m.model, data, q)
    pin.updateFramePlacements(m.model, data)
    fid = m.site_fid[m.site_index[name]]
    return np.zeros((3, m.nv)) if fid < 0 else pin.getFrameJacobian(m.model, data, fid, LWA)[:3].copy()


def test_lhs_lacks_the_explicit_spring_and_one_step_is_explicit_by_hand():
    # the Gauss-Newton form (integrator.spring_stiffness) for the term by term check of the implicit spring's
    # LHS below; with the default full form the explicit spring adds nothing to the LHS either (last check)
    gn = ["integrator.spring_stiffness=gauss_newton"]
    sim_e = Simulator.load("chain", BASE + gn + ["springs.brace0.implicit=false"])
    sim_i = Simulator.load("chain", BASE + gn)
    sim_0 = Simulator.load("chain", BASE + gn + ["springs.brace0.stiffness=0", "springs.brace0.damping=0"])
    sim_e.step(50)  # a moving, bent state; every LHS below is assembled at this one (q, v)
    q, v, h = sim_e.state.q.copy(), sim_e.joint_velocities().copy(), sim_e.dt
    (se, _), (si, kin), (s0, _) = (assemble(s, q, v, h) for s in (sim_e, sim_i, sim_0))
    Ae, be, Ai, A0, b0 = se.A, se.b, si.A, s0.A, s0.b
    assert np.array_equal(Ae, A0)  # no K/D of brace0 in the LHS
    full_e, full_0 = (assemble(Simulator.load("chain", BASE + o), q, v, h)[0].A
                      for o in (["springs.brace0.implicit=false"], ["springs.brace0.stiffness=0", "springs.brace0.damping=0"]))
    assert np.array_equal(full_e, full_0)  # nor any lever-arm block of brace0 in the full form
    # the implicit spring's LHS term is J^T (h D + h^2 K) J of brace0 (3x3 K, D from springs.spring_forces)
    sp = sim_i.spec.springs[0]
    _, K, D, _ = spring_forces(sim_i.mech, kin.X)
    Jd = site_jacobian(sim_i, q, sp.a) - site_jacobian(sim_i, q, sp.b)
    term = Jd.T @ (h * D[0] + h * h * K[0]) @ Jd
    assert np.abs(Ai - A0 - term).max() <= 1e-10 * np.abs(term).max()
    assert np.abs(term).max() > 1e-3 * np.abs(A0).max()  # the stiffness is not negligible here
    # one step of the explicit scene = A0^-1 (b0 + h Jd^T f(q, v)) with f computed by hand at step k
    xa, va = site_state(sim_e, q, v, sp.a)
    xb, vb = site_state(sim_e, q, v, sp.b)
    d = xa - xb
    l = np.linalg.norm(d)
    u = d / l
    L0 = sim_e.mech.spring_rest[0]
    f = -sp.stiffness * (l - L0) * u - sp.damping * (u @ (va - vb)) * u
    v_hand = np.linalg.solve(A0, b0 + h * Jd.T @ f)
    assert np.allclose(be, b0 + h * Jd.T @ f, rtol=0, atol=1e-12 * np.abs(be).max())
    sim_e.step()
    err = np.abs(sim_e.joint_velocities() - v_hand).max()
    assert err < 1e-12 * max(np.abs(v_hand).max(), 1.0), err
    assert np.abs(sim_e.state.q - pin.integrate(sim_e.mech.model, q, h * v_hand)).max() < 1e-13


def period_and_amplitude(sim, steps):
    xs = [sim.state.q[0]]
    for _ in range(steps):
        sim.step()
        xs.append(sim.state.q[0])
    xs = np.array(xs)
    up = np.flatnonzero((xs[:-1] < 0) & (xs[1:] >= 0))  # upward zero crossings, linearly interpolated
    tc = (up + (-xs[up]) / (xs[up + 1] - xs[up])) * sim.dt
    return np.diff(tc).mean(), np.abs(xs[-1000:]).max()


def test_catalogue_explicit_spring_is_symplectic_euler():
    """x'' = -w^2 x with the spring explicit is symplectic Euler: period 2 pi / theta, cos theta =
    1 - h^2 w^2 / 2, amplitude kept (< 1e-4 relative over 10 s; exact discrete invariant
    x^2 + v^2/w^2 - h x v); the implicit spring decays by (1 + h^2 w^2)^(-1/2) per step."""
    sim = Simulator.load("catalogue/explicit_spring")
    m, k, h = sim.spec.bodies[0].mass, sim.spec.springs[0].stiffness, sim.dt
    w2 = k / m
    T, amp = period_and_amplitude(sim, 10000)
    theta = np.arccos(1 - h * h * w2 / 2)
    assert abs(T - 2 * np.pi * h / theta) < 1e-6, (T, 2 * np.pi * h / theta)
    x0 = sim.spec.joints[0].q0[0]
    assert abs(amp - x0) < 1e-3 * x0, amp  # max over the last 1000 samples of a non-decaying oscillation
    x, v = sim.state.q[0], sim.joint_velocities()[0]
    inv = x * x + v * v / w2 - h * x * v  # conserved by symplectic Euler: x+ = x + h v+, v+ = v - h w^2 x
    assert abs(inv - x0 * x0) < 1e-12, inv - x0 * x0
    sim = Simulator.load("catalogue/explicit_spring", ["springs.pull.implicit=true"])
    _, amp_i = period_and_amplitude(sim, 10000)
    # (m + h^2 k) v+ = m v - h k x, x+ = x + h v+: the map's determinant is 1/(1 + h^2 w^2), |lambda| its root;
    # the envelope at the start of the last 1000 steps (the max over them, within one period of 628 steps)
    env = x0 * (1 + h * h * w2) ** (-9000 / 2)
    assert abs(amp_i / env - 1) < 0.05, (amp_i, env)


def test_direction_spring_implicit_false():
    """direction_spring with implicit: false: catalogue direction_spring (2 kg, k = 200, along x) is then
    symplectic Euler along x too (period 2 pi / theta), and the LHS has no d d^T term."""
    ov = ["forces=[{name: xs, type: direction_spring, a: centre, b: anchor, direction: x, stiffness: 200.0, "
          "damping: 0.0, rest_length: 0.0, implicit: false}]"]
    sim = Simulator.load("catalogue/direction_spring", ov)
    h, w2 = sim.dt, 200.0 / 2.0
    T, _ = period_and_amplitude(sim, 4000)
    assert abs(T - 2 * np.pi * h / np.arccos(1 - h * h * w2 / 2)) < 1e-6, T
    q, v = sim.state.q.copy(), sim.joint_velocities().copy()
    A = assemble(sim, q, v, h)[0].A
    assert np.allclose(A, np.diag([2.0] * 3), rtol=0, atol=1e-12)
    sim_d = Simulator.load("catalogue/direction_spring", [ov[0].replace("damping: 0.0", "damping: 3.0")])
    b = assemble(sim_d, q, v, h)[0].b  # M v + h (-k x - c xdot) along x
    assert abs(b[0] - (2.0 * v[0] + h * (-200.0 * q[0] - 3.0 * v[0]))) < 1e-12


@pytest.mark.parametrize("value", ["maybe", "1", "[true]"])
def test_bad_implicit_raises_scene_error(value):
    with pytest.raises(SceneError, match=r"springs\[0\] 'pull'.*'implicit' must be true or false"):
        Simulator.load("catalogue/explicit_spring", [f"springs.pull.implicit={value}"])
    with pytest.raises(SceneError, match=r"forces\[0\] 'xs'.*'implicit' must be true or false"):
        Simulator.load("catalogue/direction_spring", [
            f"forces=[{{name: xs, type: direction_spring, a: centre, b: anchor, direction: x, implicit: {value}}}]"])
