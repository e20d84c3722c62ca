"""Loop stabilization (issue 13 item 5): post-stabilization (default: the step's loop rows at velocity
level, then q+ projected onto phi = 0) or Baumgarte at velocity level, G qdot+ = -b phi(q_k)
(``stabilization: {method: baumgarte, b: 5}``). With no other motion phi then decays exactly as
(1 - b h)^k; the rows hold to round-off every step; both solver paths give the same step; the
drift ordering on moving mechanisms is post << Baumgarte, and a larger b drifts less."""
import numpy as np
import pinocchio as pin
import pytest

from redmax_ros.core import SceneError, State
from redmax_ros.core.dynamics.stabilization import loop_residual, loop_violation, project_chord


def baumgarte(b):
    return f"stabilization={{method: baumgarte, b: {b}}}"


@pytest.mark.parametrize("scene,solver", [("fourbar", "direct"), ("fourbar", "pcg"), ("slider_crank", "direct")])
@pytest.mark.parametrize("b", [5.0, 50.0])
def test_violation_decays_as_one_minus_bh_to_the_k(load_sim, scene, solver, b):
    """Zero gravity, at rest, loop opened by 1e-3 rad on every joint: the only motion is the correction,
    so phi_k = (1 - b h)^k phi_0 (velocity-level law integrated by q+ = q + h qdot+, to first order in
    the 7e-4 m violation)."""
    sim = load_sim(scene, ["gravity=[0,0,0]", baumgarte(b)], solver=solver)
    m, h = sim.mech, sim.dt
    q = pin.integrate(m.model, m.q0, 1e-3 * np.ones(m.nv))
    sim.state = State(0.0, q, np.zeros_like(sim.state.v))
    v0 = loop_violation(sim.backend.workspace.tree, q)
    assert v0 > 1e-4
    for k in range(1, 101):
        r = sim.step()
        assert r.diagnostics.violation_pos == pytest.approx(v0 * (1 - b * h) ** k, rel=2e-3, abs=1e-12), k
        assert r.diagnostics.violation_vel < 1e-9  # G qdot+ = -b phi(q_k) holds to round-off


def test_default_post_stabilization_closes_to_round_off(load_sim):
    for scene in ("fourbar", "slider_crank", "klann_leg"):
        sim = load_sim(scene)
        viol = [sim.step().diagnostics.violation_pos for _ in range(300)]
        assert max(viol) < 1e-9, scene


def test_catalogue_scene_is_the_slider_crank_with_baumgarte(load_sim):
    """catalogue/baumgarte_loop is slider_crank with stabilization {method: baumgarte, b: 5}: the same steps."""
    a = load_sim("catalogue/baumgarte_loop")
    b = load_sim("slider_crank", [baumgarte(5.0)])
    assert a.mech.loop_baumgarte == 5.0
    for _ in range(200):
        ra, rb = a.step(), b.step()
    assert np.array_equal(ra.q, rb.q) and 1e-6 < ra.diagnostics.violation_pos < 1e-2


@pytest.mark.parametrize("scene", ["fourbar", "slider_crank"])
def test_drift_ordering_on_a_moving_mechanism(load_sim, scene):
    """Swinging under gravity for 1 s: Baumgarte settles where b h phi balances the O(h^2 |qdot|^2) drift
    of each step, so post-stabilization (1e-10 m) << Baumgarte with b = 50 < Baumgarte with b = 5."""
    out = {}
    for label, ov in (("post", []), ("b5", [baumgarte(5.0)]), ("b50", [baumgarte(50.0)])):
        sim = load_sim(scene, ov)
        out[label] = max(sim.step().diagnostics.violation_pos for _ in range(1000))
    assert out["post"] < 1e-9 < 1e-5 < out["b50"] < out["b5"] < 1e-2, out


def test_pcg_and_direct_paths_take_the_same_baumgarte_step(load_sim):
    ref = load_sim("fourbar", [baumgarte(20.0)], solver="direct")
    it = load_sim("fourbar", [baumgarte(20.0)], solver="pcg")
    q = pin.integrate(ref.mech.model, ref.mech.q0, 2e-3 * np.ones(ref.mech.nv))
    for s in (ref, it):
        s.state = State(0.0, q.copy(), np.zeros_like(s.state.v))
    a, b = ref.step(), it.step()
    assert np.abs(a.v - b.v).max() < 1e-6 * max(1.0, np.abs(a.v).max())
    assert abs(a.diagnostics.violation_pos - b.diagnostics.violation_pos) < 1e-10


@pytest.mark.parametrize("value,where", [("{method: magic}", "stabilization.method"),
                                         ("{method: baumgarte, b: -1}", "stabilization.b"),
                                         ("{method: post, b: 5}", "stabilization.b"),
                                         ("{method: baumgarte, gain: 5}", "stabilization"),
                                         ("baumgarte", "stabilization")])
def test_bad_stabilization_values_name_the_entry(load_sim, value, where):
    with pytest.raises(SceneError, match=where.replace(".", r"\.")):
        load_sim("fourbar", [f"stabilization={value}"])


@pytest.mark.parametrize("scene,overrides,held", [("fourbar", [], ()), ("bridge", [], ()), ("bridge", [], (0,)),
                                                  ("umbrella", ["params.ribs=2"], ())])
def test_compiled_chord_projection_equals_the_python_iterations(load_sim, scene, overrides, held):
    """stabilization.chord_project_kernel (vector-space configurations, Context.additive) against project_chord's
    Python iterations (loop_phi_at, chord_step, pin.integrate) from a configuration off the loop manifold: the same
    q and max|phi|, bit for bit, and the same placements left in the workspace."""
    sim = load_sim(scene, overrides, solver="pcg")
    sim.step(3)
    ctx, m = sim.backend.workspace.tree, sim.mech
    assert ctx.additive
    q0 = sim.state.q
    _, G = loop_residual(ctx, q0)
    q = pin.integrate(m.model, q0, 1e-3 * np.sin(np.arange(m.nv)))  # loops opened by ~1e-3 rad a joint
    out = {}
    for additive in (True, False):
        ctx.additive = additive
        qp, err = project_chord(ctx, q, G, held)
        out[additive] = (qp, err, ctx.ws.R.copy(), ctx.ws.St.copy())
    assert 0.0 < out[True][1] < 1e-10 and not np.array_equal(out[True][0], q)
    for a, b in zip(out[True], out[False]):
        assert np.asarray(a).tobytes() == np.asarray(b).tobytes()
