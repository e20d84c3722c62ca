"""Self-collision as unilateral rows of the QP of Eq. (5) (docs/collisions.md): two capsules meeting
head-on (scenes/capsules.yaml, no gravity) conserve momentum, do not penetrate beyond
margin + O(h), and separate; bad collision entries are SceneErrors naming the entry."""
import numpy as np
import pinocchio as pin
import pytest

from redmax_ros.core import SceneError, Simulator, load_scene, scene_from_dict
from redmax_ros.core.step.backends import make_backend
from redmax_ros.core import compile_scene


def momentum(sim):
    """(linear (3,), angular about the system COM (3,)) world momentum [kg m/s, kg m^2/s]."""
    mech = sim.mech
    data = mech.model.createData()
    h = pin.computeCentroidalMomentum(mech.model, data, sim.state.q, sim.workspace.to_reduced(sim.state.v))
    return np.array(h.linear), np.array(h.angular)


def test_capsules_head_on_conserve_momentum_and_separate():
    sim = Simulator.load("capsules")
    p0, L0 = momentum(sim)
    h = sim.spec.dt
    margin = sim.mech.collision.margin
    dmin, rows_seen, active_seen = np.inf, 0, 0
    for _ in range(300):
        res = sim.step()
        c = res.diagnostics.solution.contacts
        rows_seen = max(rows_seen, c.rows)
        active_seen = max(active_seen, c.active)
        dmin = min(dmin, c.min_distance)
        p, L = momentum(sim)
        assert np.allclose(p, p0, atol=1e-9), (p, p0)
        assert np.allclose(L, L0, atol=1e-9), (L, L0)
    assert rows_seen >= 1 and active_seen >= 1
    # penetration at most margin + O(h) (here the speculative rows keep it positive)
    assert dmin > -(margin + 2.0 * h * 1.0)
    assert dmin > -1e-6
    # separated: moving apart along x at the restitution speed 0.5 m/s, and no contact row left
    P = sim.body_poses()
    xl = np.asarray(P["left"].translation if hasattr(P["left"], "translation") else P["left"][0])[0]
    xr = np.asarray(P["right"].translation if hasattr(P["right"], "translation") else P["right"][0])[0]
    assert xr - xl > 0.3 + margin
    assert c.rows == 0
    v = sim.workspace.to_reduced(sim.state.v)
    assert abs(abs(v[2]) - 0.5) < 1e-6 and abs(abs(v[8]) - 0.5) < 1e-6


def test_collision_scenes_use_the_reference_pipeline():
    mech = compile_scene(load_scene("capsules"))
    assert type(make_backend(mech, "direct")).__name__ == "DirectBackend"
    with pytest.raises(SceneError, match="pcg"):
        make_backend(mech, "pcg")
    with pytest.raises(SceneError, match="compiled"):
        make_backend(mech, "compiled")


def _scene(collision, **extra):
    d = {"gravity": [0, 0, 0], "bodies": [
        {"name": "a", "shape": {"type": "capsule", "radius": 0.05, "length": 0.2}, "mass": 1.0},
        {"name": "b", "shape": {"type": "sphere", "radius": 0.05}, "mass": 1.0}],
        "joints": [{"name": "fa", "type": "free", "parent": "world", "child": "a"},
                   {"name": "fb", "type": "free", "parent": "world", "child": "b", "q0": [0.5, 0, 0, 0, 0, 0]}],
        "collision": collision}
    d.update(extra)
    return scene_from_dict(d)


@pytest.mark.parametrize("coll, entry", [
    ({"margin": -1.0}, "collision.margin"),
    ({"margin": 0.01, "offset": 0.02}, "collision.offset"),
    ({"restitution": 2.0}, "collision.restitution"),
    ({"exclude": [["a", "nope"]]}, "collision.exclude[0]"),
    ({"bodies": ["zz"]}, "collision.bodies"),
    ({"shapes": {"a": {"type": "blob"}}}, "collision.shapes.a"),
    ({"shapes": {"a": {"type": "capsule", "radius": 0.1}}}, "collision.shapes.a"),
    ({"obstacles": [{"name": "floor", "type": "plane"}]}, "collision.obstacles[0] 'floor'"),
    ({"obstacles": [{"name": "jar", "type": "shell", "radius": 0.1, "length": 0.1, "thickness": 0.01,
                     "segments": 2}]}, "collision.obstacles[0] 'jar'"),
    ({"unknown": 1}, "collision"),
])
def test_bad_collision_entries_name_the_entry(coll, entry):
    with pytest.raises(SceneError) as e:
        _scene(coll)
    assert entry in str(e.value)


def test_bdf2_is_rejected_with_collision():
    with pytest.raises(SceneError, match="integrator.scheme"):
        _scene({"margin": 0.01}, integrator={"scheme": "bdf2"})


def test_floor_plane_and_sphere_rest_without_penetration():
    """A sphere dropped on a floor obstacle (half-space) comes to rest on it (d >= -1 % of its radius)."""
    spec = scene_from_dict({"gravity": [0, 0, -9.81], "bodies": [
        {"name": "ball", "shape": {"type": "sphere", "radius": 0.05}, "mass": 1.0}],
        "joints": [{"name": "f", "type": "free", "parent": "world", "child": "ball", "q0": [0, 0, 0.2, 0, 0, 0]}],
        "collision": {"margin": 0.01, "obstacles": [{"name": "floor", "type": "plane", "normal": [0, 0, 1]}]}})
    sim = Simulator(spec)
    for _ in range(600):
        res = sim.step()
    z = sim.state.q[2]
    assert abs(z - 0.05) < 0.01 * 0.05
    assert res.diagnostics.solution.contacts.active == 1


def test_collision_shapes_for_display_follow_the_bodies():
    """Simulator.collision_shapes: one capsule per body at the body frame (zero shape offset), its axis (local
    z) along world x as the scene's pitch of pi/2 puts it, sizes from the scene; they move with the bodies."""
    sim = Simulator.load("capsules")
    for _ in range(2):
        shapes = sim.collision_shapes()
        poses = sim.body_poses()
        assert [(s.owner, s.kind) for s in shapes] == [("left", "capsule"), ("right", "capsule")]
        for s in shapes:
            p, quat = poses[s.owner]
            assert np.allclose(s.position, p, atol=1e-12) and np.allclose(np.abs(s.quaternion), np.abs(quat), atol=1e-12)
            assert s.size == pytest.approx((0.1, 0.1, 0.2))
            x, y, z, w = s.quaternion
            assert np.allclose([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], [1, 0, 0], atol=1e-9)
        for _ in range(20):
            sim.step()
    assert shapes[0].position[0] > -0.225 + 0.019  # moved 20 mm toward the other in 20 ms
