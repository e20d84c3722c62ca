"""Coulomb floor friction of the free vertices of deformables (solvers/coupled.py: Staggered Projections,
Wang et al. 2019 Alg. 2 / Eq. 11-12, four-sided pyramid |beta_x|, |beta_y| <= mu alpha on world x, y), against
the analytic rigid-block values: a stiff FEM block sliding on the floor decelerates at mu g and stops after
v0^2 / (2 mu g); on an incline (emulated by tilted gravity) it sticks for tan(theta) < mu and slides with
acceleration g (sin(theta) - mu cos(theta)) for tan(theta) > mu. Every step's contact solve converges, its
impulses lie in the pyramid, a failed solve leaves the state as it was, and bad floor_mu values are named."""
import copy
import math

import numpy as np
import pinocchio as pin
import pytest

from redmax_ros.core import SceneError, Simulator, StepError
from redmax_ros.core.deformable import meshes
from redmax_ros.core.deformable.system import DeformState
from redmax_ros.core.scene.loader import scene_from_dict
from redmax_ros.core.solvers import coupled
from redmax_ros.core.step.state import State

G = 9.81  # m/s^2


def block_scene(mu, gravity=(0.0, 0.0, -G), young=1e7, size=0.1, cells=(2, 2, 2), dt=1e-3, beta=0.0):
    """A stiff FEM cube (edge ``size`` m, E = ``young`` Pa, 1000 kg/m^3) resting on the floor z = 0 with
    friction ``mu``; the skeleton is one unrelated hinge body far from it."""
    x, t = meshes.box_tets([-size / 2, -size / 2, 0.0], [size] * 3, cells)
    return {"name": "block", "gravity": list(gravity), "dt": dt,
            "bodies": [{"name": "b", "shape": {"type": "box", "size": [0.1, 0.1, 0.1]}, "density": 100}],
            "joints": [{"name": "j", "type": "revolute", "parent": "world", "child": "b", "axis": "y",
                        "placement": {"pos": [0, 5, 1]}}],
            "deformables": [{"name": "block", "type": "fem", "mesh": {"vertices": x.tolist(), "tets": t.tolist()},
                             "young": young, "poisson": 0.3, "density": 1000.0,
                             "rayleigh": {"alpha": 0.0, "beta": beta}, "floor": 0.0, "floor_mu": mu}]}


def block_sim(mu, v0=(0.0, 0.0, 0.0), **kw):
    sim = Simulator(scene_from_dict(block_scene(mu, **kw), "<block>"))
    ds = sim.deformables.initial()
    sim.set_state(State(0.0, np.zeros(1), np.zeros(1),
                        deform=DeformState.of(ds.x, np.tile(np.asarray(v0, float), (len(ds.x), 1)))))
    return sim


def run(sim, steps, impulses=None):
    """(t, centre-of-mass x, centre-of-mass v_x) at the start and after each of ``steps`` steps; asserts every
    contact solve converged."""
    m = sim.deformables.mass
    ds = sim.state.deform
    out = [(sim.state.t, m @ ds.x[:, 0] / m.sum(), m @ ds.v[:, 0] / m.sum())]
    for _ in range(steps):
        sim.step()
        assert sim.backend.timing["contact_converged"]
        ds = sim.state.deform
        out.append((sim.state.t, m @ ds.x[:, 0] / m.sum(), m @ ds.v[:, 0] / m.sum()))
    return np.array(out).T


@pytest.fixture
def recorded(monkeypatch):
    """Every coupled solve's (contact impulses (k, 3) [N s], mu) while the fixture is in use."""
    log = []
    solve = coupled.solve

    def recording(*args, **kw):
        sol = solve(*args, **kw)
        contacts = args[9] if len(args) > 9 else kw.get("contacts")
        if contacts is not None:
            log.append((sol.contact_impulse.copy(), contacts.mu, sol.contact_tol))
        return sol

    monkeypatch.setattr(coupled, "solve", recording)
    return log


def assert_in_pyramid(log):
    """|beta_x|, |beta_y| <= mu alpha + tol, tol the staggered loop's (a sliding impulse uses the bound of the
    last normal stage, mu |delta alpha| <= coupled.TOL_V A_jj: CoupledSolution.contact_tol); returns the
    largest excess over mu alpha relative to tol."""
    worst = 0.0
    for imp, mu, tol in log:
        alpha = imp[:, 2]
        assert np.all(alpha >= -1e-12)
        excess = np.abs(imp[:, :2]) - mu * alpha[:, None]
        assert np.all(excess <= tol[:, None] + 1e-15), excess.max()
        worst = max(worst, float((excess / tol[:, None]).max(initial=0.0)))
    return worst


def test_sliding_block_decelerates_at_mu_g_and_stops_after_v0_squared_over_2_mu_g(recorded):
    mu, v0 = 0.5, 1.0
    sim = block_sim(mu, v0=(v0, 0.0, 0.0))
    t, x, v = run(sim, 300)
    # deceleration: fit of the centre of mass velocity while it slides (after the first elastic transient)
    sel = (t >= 0.02) & (v > 0.05)
    a = -np.polyfit(t[sel], v[sel], 1)[0]
    assert abs(a - mu * G) <= 0.01 * mu * G, a
    stop = t[np.argmax(v <= 1e-3)]
    assert abs(stop - v0 / (mu * G)) <= 0.02 * v0 / (mu * G), stop
    dist = x[-1] - x[0]
    assert abs(dist - v0 ** 2 / (2 * mu * G)) <= 0.02 * v0 ** 2 / (2 * mu * G), dist
    assert abs(v[-1]) <= 1e-5  # at rest, held by static friction
    worst = assert_in_pyramid(recorded)
    print(f"deceleration {a:.5f} m/s^2 (mu g {mu * G:.5f}); stop at {stop:.4f} s (v0/(mu g) {v0 / (mu * G):.4f}); "
          f"distance {dist:.5f} m (v0^2/(2 mu g) {v0 ** 2 / (2 * mu * G):.5f}); pyramid excess {worst:.2e} of tol")


def test_diagonal_slide_follows_the_four_sided_pyramid(recorded):
    """Sliding along (0.6, -0.8) m/s: with the pyramid |beta_x|, |beta_y| <= mu alpha (the rigid ground
    contact's law) each component decelerates at mu g while it slides, so x stops first (0.6 / (mu g)) and y
    later (0.8 / (mu g)); a circular cone would decelerate along the velocity and stop both together."""
    mu = 0.5
    sim = block_sim(mu, v0=(0.6, -0.8, 0.0))
    m = sim.deformables.mass
    t, vx, vy = [0.0], [0.6], [-0.8]
    for _ in range(250):
        sim.step()
        assert sim.backend.timing["contact_converged"]
        v = m @ sim.state.deform.v / m.sum()
        t.append(sim.state.t), vx.append(v[0]), vy.append(v[1])
    t, vx, vy = np.array(t), np.array(vx), np.array(vy)
    for comp, v0 in ((vx, 0.6), (vy, -0.8)):
        sel = (t >= 0.02) & (np.abs(comp) > 0.05)
        a = -np.sign(v0) * np.polyfit(t[sel], comp[sel], 1)[0]
        assert abs(a - mu * G) <= 0.01 * mu * G, a
        stop = t[np.argmax(np.sign(v0) * comp <= 1e-3)]  # (then the block rings elastically about 0)
        assert abs(stop - abs(v0) / (mu * G)) <= 0.02 * abs(v0) / (mu * G), stop
        print(f"v0 {v0}: deceleration {a:.5f} m/s^2, stop at {stop:.4f} s (|v0|/(mu g) {abs(v0) / (mu * G):.4f})")
    assert_in_pyramid(recorded)


@pytest.mark.parametrize("tan_theta", [0.3, 0.7])
def test_block_on_incline_sticks_below_and_slides_above_the_friction_angle(tan_theta, recorded):
    mu = 0.5
    th = math.atan(tan_theta)
    sim = block_sim(mu, gravity=(G * math.sin(th), 0.0, -G * math.cos(th)), beta=1e-3)
    t, x, v = run(sim, 400)
    if tan_theta < mu:  # static friction holds it: only the elastic settling moves the centre of mass
        bottom = sim.deformables.initial().x[:, 2] <= 1e-12
        assert np.abs(sim.state.deform.v[bottom, 0]).max() <= 1e-9
        assert abs(x[-1] - x[0]) <= 1e-5 and abs(v[-100:]).max() <= 1e-4
        print(f"tan {tan_theta}: sticks, centre of mass moved {x[-1] - x[0]:.2e} m, |v| <= {abs(v[-100:]).max():.2e} m/s")
    else:
        sel = t >= 0.05
        a = np.polyfit(t[sel], v[sel], 1)[0]
        expected = G * (math.sin(th) - mu * math.cos(th))
        assert abs(a - expected) <= 0.01 * expected, a
        print(f"tan {tan_theta}: slides at {a:.5f} m/s^2 (g (sin - mu cos) {expected:.5f})")
    assert_in_pyramid(recorded)


def centre_of_mass(sim):
    """The centre of mass of the skeleton and the deformables [m]."""
    mech = sim.backend.mech
    data = mech.model.createData()
    c = pin.centerOfMass(mech.model, data, sim.state.q)
    m = sim.deformables.mass
    return (data.mass[0] * c + m @ sim.state.deform.x) / (data.mass[0] + m.sum())


def test_starfish_with_friction_crawls_converging_every_step_in_the_pyramid(recorded):
    """The shipped starfish (floor_mu 0.8, lift and sweep gait) over one gait period (2 s): every contact solve
    converges with its impulses in the pyramid, and the core crawls along the heading (+x)."""
    sim = Simulator.load("starfish")
    assert sim.deformables.floor_mu == 0.8
    free = np.setdiff1d(sim.deformables.floor_vertices, sim.deformables.attach.vertex)
    q0 = sim.state.q.copy()
    for _ in range(2000):
        sim.step()
        assert sim.backend.timing["contact_converged"]
    assert sim.deformable_positions()["body"][free, 2].min() >= -1e-9
    assert len(recorded) == 2000 and max(len(rec[0]) for rec in recorded) > 0
    worst = assert_in_pyramid(recorded)
    dx, dy = sim.state.q[:2] - q0[:2]
    assert dx >= 0.015 and abs(dy) <= 0.5 * dx
    print(f"starfish 2 s: core moved ({dx:.4f}, {dy:.4f}) m; pyramid excess {worst:.2e} of tol")


def test_starfish_on_a_frictionless_floor_keeps_its_centre_of_mass():
    """No horizontal external impulse on a frictionless floor: the centre of mass stays where it is (but for
    the post-stabilization of the attached vertices, O(h^2) a step), so the gait cannot crawl."""
    sim = Simulator.load("starfish", overrides=["params.mu=0"])
    sim.step(1)
    c0, q0 = centre_of_mass(sim), sim.state.q.copy()
    sim.step(2000)
    drift = np.abs(centre_of_mass(sim)[:2] - c0[:2]).max()
    assert drift <= 1e-4
    assert np.abs(sim.state.q[:2] - q0[:2]).max() <= 2e-3
    print(f"frictionless starfish 2 s: centre of mass drift {drift:.2e} m, core moved {sim.state.q[:2] - q0[:2]} m")


def test_failed_contact_solve_leaves_the_state_as_it_was(monkeypatch):
    sim = block_sim(0.5, v0=(1.0, 0.0, 0.0))
    before = sim.state
    x0 = before.deform.x.copy()
    monkeypatch.setattr(coupled, "MAX_ITER", 1)  # the landing needs several sub-problem solves
    with pytest.raises(StepError, match="did not converge"):
        sim.step()
    assert sim.state is before and np.array_equal(sim.state.deform.x, x0)
    monkeypatch.setattr(coupled, "MAX_ITER", 200)
    sim.step()
    assert sim.state.t > before.t


@pytest.mark.parametrize("value, what", [(-0.1, "non-negative"), (float("nan"), "finite"), ("rough", "number")])
def test_bad_floor_mu_is_named(value, what):
    raw = block_scene(0.5)
    raw["deformables"][0]["floor_mu"] = value
    with pytest.raises(SceneError) as e:
        scene_from_dict(copy.deepcopy(raw), "<t>")
    assert "deformables.block.floor_mu" in str(e.value) and what in str(e.value)
    del raw["deformables"][0]["floor"]
    raw["deformables"][0]["floor_mu"] = 0.5
    with pytest.raises(SceneError, match="floor_mu.*needs a 'floor'"):
        scene_from_dict(raw, "<t>")
