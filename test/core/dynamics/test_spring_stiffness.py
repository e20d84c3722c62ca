"""The full maximal stiffness of springs (issue 13 item 1): K_m with the lever-arm blocks, notes Eq. (1.32),
(1.44), symmetrised (springs.geometric_blocks_kernel), against central finite differences of the generalized
spring force.

The maximal coordinates of a body are its centre-of-mass position and its rotation (world axes, notes §1.9
body-centred frames). On free bodies whose frame is at the centre of mass the generalized force in those
coordinates is (sum f, sum r x f), and the LHS stiffness of Eq. (2) must equal T^T H T, with H the symmetric part
of -d(force, torque)/d(c, theta) (theta: a world rotation exp([theta]) R about the centre of mass; the symmetric
part of that right-hand derivative of a gradient is the Hessian of the energy along the exponential) and
T = blkdiag(R, R) per body, the map from the FreeFlyer's body twist to (c dot, omega world). The Gauss-Newton form
(J^T K J of the 3x3 point stiffness) misses the lever-arm terms and differs by O(|f| |r|).
"""
from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from redmax_ros.core import SceneError, Simulator
from redmax_ros.core.dynamics import kinematics
from redmax_ros.core.dynamics.forces import assemble
from redmax_ros.core.dynamics.springs import clamp_lever_blocks, geometric_blocks_kernel, spring_terms
from redmax_ros.core.step.backends import DataFreeBackend, DirectBackend

SCENE = "catalogue/lever_springs"  # two free boxes on off-centre springs (stretched, zero rest length, a tie)
DIRECTION = ("forces=[{name: dir, type: direction_spring, a: b1, b: w1, direction: [1, 2, 0.5], stiffness: 120.0, "
             "rest_length: -0.2}]")


def _load(direction=False, form=None, dt=0.01):
    overrides = [f"dt={dt}"] + ([DIRECTION] if direction else [])
    if form is not None:
        overrides.append(f"integrator.spring_stiffness={form}")
    return Simulator.load(SCENE, overrides, solver="reference")


def _spring_force(sim, ws, q):
    """Generalized force of the springs (and direction springs) at q, velocity 0: RHS of Eq. (2) at h = 1 minus
    the gravity/Coriolis part (-nle)."""
    mech = sim.mech
    kin = kinematics.compute(mech, ws, q, np.zeros(mech.nv))
    f = np.zeros(mech.nv)
    if len(mech.spring_ab):
        fs, _, _, Jd, _ = spring_terms(mech, kin.X, kin.J)
        f += Jd.reshape(-1, mech.nv).T @ fs.reshape(-1)
    if ws.extras is not None:
        A = np.zeros((mech.nv, mech.nv))
        ws.extras.forces(mech, ws, kin, q, np.zeros(mech.nv), 1.0, A, f)
    return f


def _lhs_stiffness(sim, ws, q, h=1e-3):
    """K_r of Eq. (2)'s LHS, (A - M) / h^2 (no damping in the scene), at a step h small enough for the lever
    clamp (springs.clamp_lever_blocks) to be idle: K_r is then what the step uses."""
    mech = sim.mech
    kin = kinematics.compute(mech, ws, q, np.zeros(mech.nv))
    M = kin.M.copy()
    sys = assemble(mech, ws, kin, q, np.zeros(mech.nv), np.zeros(mech.nv), h)
    return (sys.A - M) / (h * h)


def _chart_force(sim, ws, q):
    """Per free body (FreeFlyer, frame at the centre of mass): world force and torque about the centre of mass of
    the springs (and direction springs) at q, stacked (6 per body)."""
    mech = sim.mech
    f = _spring_force(sim, ws, q)  # body-twist coordinates: (force, torque) in the body frame at the body origin
    out = np.empty(mech.nv)
    for j in range(1, mech.model.njoints):
        R = pin.Quaternion(q[7 * (j - 1) + 3:7 * j]).normalized().matrix()
        i = 6 * (j - 1)
        out[i:i + 3] = R @ f[i:i + 3]
        out[i + 3:i + 6] = R @ f[i + 3:i + 6]
    return out


def _chart_perturb(q, j, d):
    """q with body j's centre moved by d[:3] (world) and its rotation turned by exp([d[3:]]) (world axes)."""
    q = q.copy()
    k = 7 * (j - 1)
    R = pin.Quaternion(q[k + 3:k + 7]).normalized().matrix()
    q[k:k + 3] += d[:3]
    q[k + 3:k + 7] = pin.Quaternion(pin.exp3(d[3:]) @ R).coeffs()
    return q


def _fd_chart_hessian(sim, ws, q, eps=1e-6):
    """T^T H T: H = -sym(d chart force / d (c, theta)) by central differences, T = blkdiag(R, R) per body."""
    nv = sim.mech.nv
    Jfd = np.empty((nv, nv))
    for col in range(nv):
        j, c = col // 6 + 1, col % 6
        d = np.zeros(6)
        d[c] = eps
        Jfd[:, col] = (_chart_force(sim, ws, _chart_perturb(q, j, d))
                       - _chart_force(sim, ws, _chart_perturb(q, j, -d))) / (2 * eps)
    H = -0.5 * (Jfd + Jfd.T)
    T = np.zeros((nv, nv))
    for j in range(1, sim.mech.model.njoints):
        R = pin.Quaternion(q[7 * (j - 1) + 3:7 * j]).normalized().matrix()
        i = 6 * (j - 1)
        T[i:i + 3, i:i + 3] = R
        T[i + 3:i + 6, i + 3:i + 6] = R
    return T.T @ H @ T


def _states(sim, n=3, seed=4):
    rng = np.random.default_rng(seed)
    model = sim.mech.model
    qs = [sim.state.q.copy()]
    for _ in range(n - 1):
        qs.append(pin.integrate(model, sim.state.q, rng.normal(scale=0.4, size=sim.mech.nv)))
    return qs


@pytest.mark.parametrize("direction", [False, True])
def test_full_stiffness_is_the_symmetrised_derivative_of_the_spring_force(direction):
    """K_r = T^T H T to 1e-7 relative on free bodies (point-to-point springs stretched, at zero rest length and as
    a tie; with a direction spring); no spring is compressed, so the transverse clamp is idle."""
    sim = _load(direction)
    ws = DirectBackend(sim.mech).workspace
    for q in _states(sim):
        kin = kinematics.compute(sim.mech, ws, q, np.zeros(sim.mech.nv))
        fs, _, _, _, l = spring_terms(sim.mech, kin.X, kin.J)
        assert (l >= sim.mech.spring_rest).all()
        K = _lhs_stiffness(sim, ws, q)
        want = _fd_chart_hessian(sim, ws, q)
        err = np.abs(K - want).max() / np.abs(want).max()
        assert err <= 1e-7, err
        assert np.abs(K - K.T).max() <= 1e-9 * np.abs(K).max()


def test_gauss_newton_form_misses_the_lever_arm_terms():
    """integrator.spring_stiffness: gauss_newton keeps J^T K J only: off by O(|f| |r|), here > 1 % of |K|."""
    sim = _load(True, "gauss_newton")
    ws = DirectBackend(sim.mech).workspace
    q = sim.state.q
    K = _lhs_stiffness(sim, ws, q)
    want = _fd_chart_hessian(sim, ws, q)
    assert np.abs(K - want).max() / np.abs(want).max() > 1e-2


def test_data_free_and_compiled_paths_take_the_same_stiffness():
    """The compiled step (geometric_blocks_kernel and clamp_lever_blocks inside the kernel) equals the Pinocchio
    pipeline over 100 steps of the tumbling boxes at h = 5 ms; from the state reached, one data-free direct step
    and one PCG step (tree_forces.maximal_blocks) equal the pipeline's."""
    ref = Simulator.load(SCENE, solver="reference")
    sim = Simulator.load(SCENE, solver="direct")  # the compiled step
    ref.step(100)
    sim.step(100)
    assert np.abs(sim.state.q - ref.state.q).max() <= 1e-9
    assert np.abs(sim.state.v - ref.state.v).max() <= 1e-7 * np.abs(ref.state.v).max()
    _, rr = DirectBackend(ref.mech).step(ref.state, ref.commands, ref.dt)
    _, rd = DataFreeBackend(ref.mech, "direct").step(ref.state, ref.commands, ref.dt)
    _, rp = DataFreeBackend(ref.mech, "pcg", rtol=1e-12).step(ref.state, ref.commands, ref.dt)
    scale = np.abs(rr.v).max()
    assert np.abs(rd.v - rr.v).max() <= 1e-10 * scale
    assert np.abs(rp.v - rr.v).max() <= 1e-8 * scale


def test_spring_stiffness_option_is_validated():
    with pytest.raises(SceneError, match="integrator.spring_stiffness"):
        _load(False, "exact")


def test_lever_clamp_keeps_the_lhs_positive_definite_and_is_idle_at_small_steps():
    """Along 0.3 s of the tumbling boxes (h = 1 ms), the LHS of Eq. (2) with the lever-arm blocks is assembled
    at h = 1 ms, 10 ms and 50 ms. Unclamped, the springs that pull a lever arm inwards make it indefinite at the
    larger steps; with springs.clamp_lever_blocks the smallest eigenvalue of M^-1 A stays >= 1/2 at every h,
    and at h = 1 ms the clamp changes nothing."""
    sim = _load(dt=1e-3)
    mech = sim.mech
    ws = DirectBackend(mech).workspace
    changed = {1e-3: 0, 1e-2: 0, 5e-2: 0}
    for k in range(300):
        if k % 10 == 0:
            q, v = sim.state.q, sim.state.v
            for h in changed:
                kin = kinematics.compute(mech, ws, q, v)
                M = kin.M.copy()
                A = assemble(mech, ws, kin, q, v, np.zeros(mech.nv), h).A
                lam = np.linalg.eigvals(np.linalg.solve(M, A)).real.min()
                assert lam >= 0.5 - 1e-9, (h, k, lam)
                fs, *_ = spring_terms(mech, kin.X, kin.J)
                blocks = np.zeros((mech.model.njoints, 6, 6))
                rows = mech.spring_rows
                inertia = np.array([np.zeros((6, 6))] + [ws.data.oMi[j].act(mech.model.inertias[j]).matrix()
                                                         for j in range(1, mech.model.njoints)])
                geometric_blocks_kernel(ws.tree.spring_ja, kin.X[rows[:, 0]], ws.tree.spring_jb, kin.X[rows[:, 1]],
                                        fs, np.zeros(len(fs), np.int64), h * h, inertia, blocks)
                changed[h] += clamp_lever_blocks(inertia, blocks)
        sim.step()
    assert changed[1e-3] == 0 and changed[5e-2] > 0, changed
