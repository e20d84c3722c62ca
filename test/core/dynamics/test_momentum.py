"""dynamics/momentum.py: the locked inertia maps a rigid twist to its momentum, the skeleton's momentum equals
a per-body sum, and the momentum balance of an isolated system under uniform gravity (momentum.target) is
the exact one of free fall."""
import numpy as np
import pinocchio as pin

from redmax_ros.core import Simulator
from redmax_ros.core.dynamics import momentum


def _string():
    """The string scene's Deformables (n point masses) and random positions and velocities for them."""
    dm = Simulator.load("catalogue/string").backend.deformables
    rng = np.random.default_rng(3)
    return dm, rng.standard_normal((dm.n_vertices, 3)), rng.standard_normal((dm.n_vertices, 3))


def test_locked_inertia_of_points_maps_a_rigid_twist_to_its_momentum():
    dm, x, _ = _string()
    m = dm.mass
    twist = np.array([0.3, -0.2, 0.5, 1.1, -0.7, 0.4])  # (v_O, w)
    v = twist[:3] + np.cross(twist[3:], x)
    np.testing.assert_allclose(dm.locked_inertia(x) @ twist, np.concatenate(dm.momentum(x, v)), rtol=1e-13,
                               atol=1e-13)
    np.testing.assert_allclose(momentum.com_of(dm.locked_inertia(x)), m @ x / m.sum(), rtol=1e-13)


def test_skeleton_momentum_is_the_sum_over_bodies():
    sim = Simulator.load("hand")
    model = sim.mech.model
    rng = np.random.default_rng(0)
    q = pin.integrate(model, sim.state.q, 0.2 * rng.standard_normal(model.nv))
    v = rng.standard_normal(model.nv)
    h, inertia = momentum.skeleton_momentum(model, model.createData(), q, v)
    d = model.createData()
    pin.forwardKinematics(model, d, q, v)
    h_sum = sum(d.oMi[k].act(model.inertias[k] * d.v[k]).vector for k in range(1, model.njoints))
    I_sum = sum(d.oMi[k].act(model.inertias[k]).matrix() for k in range(1, model.njoints))
    np.testing.assert_allclose(h, h_sum, atol=1e-13)
    np.testing.assert_allclose(inertia, I_sum, atol=1e-13)


def test_target_is_the_exact_momentum_of_free_fall():
    """Point masses falling freely (x(t) = x0 + v0 t + g t^2 / 2): target(h(0), I(0), g, t) equals the momentum
    at t to round-off, for any t; in zero gravity it is h(0)."""
    dm, x0, v0 = _string()
    g = np.array([0.0, 0.0, -9.81])
    h0 = np.concatenate(dm.momentum(x0, v0))
    for t in (1e-3, 0.1, 0.7):
        x, v = x0 + v0 * t + 0.5 * g * t * t, v0 + g * t
        np.testing.assert_allclose(momentum.target(h0, dm.locked_inertia(x0), g, t),
                                   np.concatenate(dm.momentum(x, v)), rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(momentum.target(h0, dm.locked_inertia(x0), np.zeros(3), 0.1), h0)
