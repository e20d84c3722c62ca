"""Body damping (issue 13 item 2): the maximal damping matrix D_m of Eq. (2) per body, implicit
(notes §1.9.1: f = -D phi, D = -df/dphi; Eq. 2's LHS term J^T h D_m J), in two forms:

* ``mass`` (default): D_m = c diag(m I3, I_com) at the COM;
* ``twist`` (the reference's): the wrench -c phi on all six components of the body twist
  phi = (omega, nu) at the COM (body frame), D_m = c I6.

Checked: the damping force computed independently from Pinocchio's body-frame COM twists against
central finite differences and against the D used in the step's LHS; the energy dissipation rate
against -phi^T D phi (analytic, exactly per step on an isotropic free body, and on a chain as h -> 0);
the per-step decay of the catalogue scene; SceneErrors. The PCG / data-free paths are compared with the
direct path in test/core/step/test_matrix_free.py (EXTRA: a chain with both forms).
"""
import numpy as np
import pinocchio as pin
import pytest

from redmax_ros.core import SceneError, Simulator
from redmax_ros.core.dynamics import forces, kinematics

LOCAL = pin.ReferenceFrame.LOCAL
CHAIN = ["params.n=4", "params.length=0.5", "params.width=0.1", "gravity=[0, 0, 0]", "joints.j0.q0=0.4", "joints.j0.v0=3.0", "joints.j2.v0=-5.0", "bodies.link0.damping={c: 0.5, form: twist}",
         "bodies.link1.damping={c: 2.0, form: mass}", "bodies.link3.damping={c: 0.2, form: twist}"]


def body_twists(mech, q, v):
    """{body: (phi (6,) = (nu, omega) at the COM in the COM frame, J_local (6, nv))} from Pinocchio."""
    model = mech.model
    data = model.createData()
    pin.forwardKinematics(model, data, q, v)
    pin.computeJointJacobians(model, data, q)
    pin.updateFramePlacements(model, data)
    out = {}
    for bi in range(len(mech.bodies)):
        fid = mech.body_com_fid[bi]
        out[bi] = (pin.getFrameVelocity(model, data, fid, LOCAL).vector.copy(),
                   pin.getFrameJacobian(model, data, fid, LOCAL).copy())
    return out


def body_D(sim, bi):
    """D_m of body bi in its COM frame (linear first, Pinocchio's order), from the scene's BodySpec."""
    b = sim.spec.bodies[bi]
    D = np.zeros((6, 6))
    if b.damping_form == "twist":
        return b.damping * np.eye(6)
    D[:3, :3] = b.damping * b.mass * np.eye(3)
    D[3:, 3:] = b.damping * sim.mech.body_inertia[bi]  # I_com in the joint (= COM-frame) axes
    return D


def damping_force(sim, q, v):
    """Generalized damping force sum_b J_b^T (-D_b phi_b) and dissipated power sum_b phi_b^T D_b phi_b."""
    f, P = np.zeros(sim.mech.nv), 0.0
    for bi, (phi, J) in body_twists(sim.mech, q, v).items():
        D = body_D(sim, bi)
        f -= J.T @ (D @ phi)
        P += phi @ D @ phi
    return f, P


def lhs(sim, q, v, h):
    ws = sim.workspace
    kin = kinematics.compute(sim.mech, ws, q, v, [])
    return forces.assemble(sim.mech, ws, kin, q, v, sim.mech.torque0.copy(), h).A


def test_damping_force_fd_equals_lhs_damping_matrix():
    """(A_damped - A_undamped)/h of Eq. (2) = -d f_damp / d qdot by central differences (1e-7 rel),
    with f_damp from Pinocchio's body-frame COM twists (not the code under test), for both forms."""
    sim = Simulator.load("chain", CHAIN)
    sim0 = Simulator.load("chain", CHAIN[:7])
    rng = np.random.default_rng(3)
    q = sim.state.q + 0.3 * rng.standard_normal(sim.mech.nq)
    v = rng.standard_normal(sim.mech.nv)
    h = 1e-2
    Dr = (lhs(sim, q, v, h) - lhs(sim0, q, v, h)) / h
    eps = 1e-6
    Dfd = np.zeros_like(Dr)
    for i in range(len(v)):
        e = np.zeros_like(v)
        e[i] = eps
        Dfd[:, i] = -(damping_force(sim, q, v + e)[0] - damping_force(sim, q, v - e)[0]) / (2 * eps)
    rel = np.abs(Dr - Dfd).max() / np.abs(Dfd).max()
    assert rel < 1e-7, rel
    f, P = damping_force(sim, q, v)
    assert np.allclose(Dr @ v, -f, rtol=1e-12, atol=1e-12 * np.abs(f).max())
    assert abs(v @ Dr @ v - P) <= 1e-12 * P  # qdot^T J^T D J qdot = sum phi^T D phi
    # the twist form differs from the mass form (c I6 vs c diag(m I3, I)): not the same matrix
    sim_m = Simulator.load("chain", CHAIN[:7] + [c.replace("twist", "mass") for c in CHAIN[7:]])
    assert np.abs((lhs(sim_m, q, v, h) - lhs(sim0, q, v, h)) / h - Dr).max() > 1e-2 * np.abs(Dr).max()


@pytest.mark.parametrize("form", ["twist", "mass"])
def test_isotropic_free_body_decay_and_energy_exact(form):
    """Catalogue body_damping (a cube, zero gravity, free3d: COM velocity + body angular velocity, M
    constant, no gyroscopic torque): each step M phi+ = M phi - h D phi+, so the COM velocity is divided
    by exactly 1 + h c/m (twist) or 1 + h c (mass) and omega by 1 + h c/i or 1 + h c, and
    E+ - E = -h phi+^T D phi+ - h^2/2 |D phi+|^2_(M^-1) (round-off): the rate -phi^T D phi to O(h)."""
    sim = Simulator.load("catalogue/body_damping", [f"bodies.cube.damping={{c: 0.4, form: {form}}}"])
    b = sim.spec.bodies[0]
    m, i, c, h = b.mass, b.inertia[0, 0], b.damping, sim.dt
    M = np.diag([m] * 3 + [i] * 3)
    D = c * (np.eye(6) if form == "twist" else M)
    rl, ra = (1 + h * c / m, 1 + h * c / i) if form == "twist" else (1 + h * c, 1 + h * c)
    phi = sim.joint_velocities().copy()
    E = sim.energies()[0]
    err_v = err_e = 0.0
    for _ in range(2000):
        E1 = sim.step().diagnostics.E_total
        phi1 = sim.joint_velocities().copy()
        err_v = max(err_v, np.abs(phi1 - np.r_[phi[:3] / rl, phi[3:] / ra]).max())
        Dp = D @ phi1
        err_e = max(err_e, abs((E1 - E) - (-h * phi1 @ Dp - 0.5 * h * h * Dp @ np.linalg.solve(M, Dp))))
        phi, E = phi1, E1
    assert err_v < 1e-14 and err_e < 1e-14 * E, (err_v, err_e)
    t = 2000 * h  # continuous decay exp(-c t / m) and exp(-c t / i) for twist, exp(-c t) for mass
    v0 = np.array(sim.spec.joints[0].v0)
    kl, ka = (c / m, c / i) if form == "twist" else (c, c)
    assert np.allclose(phi[:3], v0[:3] * np.exp(-kl * t), rtol=1e-2 * kl * t + 1e-12)
    assert np.allclose(phi[3:], v0[3:] * np.exp(-ka * t), rtol=ka * ka * t * h)


def dissipation_mismatch(h, T=0.2):
    """max over steps of |(E_k+1 - E_k)/h + (P_k + P_k+1)/2| / max P on the damped chain, P = phi^T D phi."""
    sim = Simulator.load("chain", CHAIN + [f"dt={h}", "integrator={coriolis: implicit}"])
    P = damping_force(sim, sim.state.q, sim.joint_velocities())[1]
    E = sum(sim.energies())
    err, Pmax = 0.0, P
    for _ in range(int(round(T / h))):
        E1 = sim.step().diagnostics.E_total
        P1 = damping_force(sim, sim.state.q, sim.joint_velocities())[1]
        err, Pmax = max(err, abs((E1 - E) / h + 0.5 * (P + P1))), max(Pmax, P1)
        E, P = E1, P1
    return err / Pmax


def test_chain_dissipation_rate_is_minus_phi_D_phi():
    """Articulated chain (zero gravity, both forms on different links): the energy rate of the step
    equals -sum_b phi_b^T D_b phi_b up to the integrator's O(h) error (first order: halving h halves it)."""
    e1, e2 = dissipation_mismatch(2e-4), dissipation_mismatch(1e-4)
    assert e2 < 2e-3, e2  # measured 1.4e-3 (h = 2e-4), 7.1e-4 (h = 1e-4)
    assert e2 < 0.6 * e1, (e1, e2)


@pytest.mark.parametrize("value,msg", [
    ("{c: 0.4, form: foo}", r"bodies\[0\] 'cube'.*'damping.form' must be one of \['mass', 'twist'\]"),
    ("{c: -1, form: twist}", r"bodies\[0\] 'cube'.*'damping.c' must be non-negative"),
    ("{form: twist}", r"bodies\[0\] 'cube' damping: missing 'c'"),
    ("{c: 1, kind: twist}", r"bodies\[0\] 'cube' damping: unknown key"),
    ("{c: .nan, form: twist}", r"bodies\[0\] 'cube'.*'damping.c' must be finite"),
])
def test_bad_body_damping_raises_scene_error(value, msg):
    with pytest.raises(SceneError, match=msg):
        Simulator.load("catalogue/body_damping", [f"bodies.cube.damping={value}"])


def test_composite_body_takes_damping_form():
    """Composite/mesh bodies (scene/bodies.validate_body) take the same entry: D_m = c I6 for 'twist'."""
    sim = Simulator.load("catalogue/composite_body", ["bodies.hammer.damping={c: 0.2, form: twist}"])
    bi = sim.mech.bodies.index("hammer")
    assert sim.spec.bodies[bi].damping_form == "twist" and sim.mech.body_damping_mass[bi] == 1.0
    assert np.array_equal(sim.mech.body_damping_inertia[bi], np.eye(3))
    assert Simulator.load("catalogue/composite_body").mech.body_damping_mass[bi] == sim.mech.body_mass[bi]
