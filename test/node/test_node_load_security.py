"""load_scene is confined (issue 17; docs/node.md "Security"): a remote caller loads scenes from the
package's scenes/ and the ``scene_dirs`` parameter only; anything else is refused with a result code,
the node keeps running and its state is unchanged. The start scene (the operator's ``scene``
parameter) is not restricted.

Real rclpy over Fast DDS (private ROS_DOMAIN_ID, localhost discovery: see test/conftest.py), the node
in this process (node_fixtures.run_node_in_thread), a namespace of our own.
"""
import os
import shutil

import pytest

from node_fixtures import Client, run_node_in_thread  # noqa: F401  (first: skips without ROS)

from rcl_interfaces.srv import SetParameters  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402

from redmax_msgs.msg import Result, SimulationState  # noqa: E402
from redmax_msgs.srv import LoadScene  # noqa: E402
from redmax_ros.core.scene.loader import SCENES_DIR  # noqa: E402

NS = f"/loadsec{os.getpid()}"
MARKER = "MARKER_5d1e0b_SECRET"
INVALID_SCENE = LoadScene.Response.INVALID_SCENE
PENDULUM = (SCENES_DIR / "pendulum.yaml").read_text()


@pytest.fixture(scope="module")
def dirs(tmp_path_factory):
    root = tmp_path_factory.mktemp("load_security")
    extra, outside = root / "extra", root / "outside"
    extra.mkdir()
    outside.mkdir()
    (extra / "extra_pendulum.yaml").write_text(PENDULUM.replace("name: pendulum", "name: extra_pendulum"))
    (extra / "escape.yaml").symlink_to(outside / "secret.yaml")
    (extra / "mesh_up.yaml").write_text(
        (SCENES_DIR / "catalogue" / "mesh_cube.yaml").read_text().replace("meshes/cube.obj", "../outside/cube.obj"))
    shutil.copy(SCENES_DIR / "catalogue" / "meshes" / "cube.obj", outside / "cube.obj")
    (extra / "meshes").mkdir()
    shutil.copy(SCENES_DIR / "catalogue" / "meshes" / "cube.obj", extra / "meshes" / "cube.obj")
    shutil.copy(SCENES_DIR / "catalogue" / "mesh_cube.yaml", extra / "mesh_cube.yaml")
    (extra / "bomb.yaml").write_text(
        "name: bomb\ndescription:\n  - &l0 [lol, lol, lol, lol, lol, lol, lol, lol, lol, lol]\n"
        + "".join(f"  - &l{i} [" + ", ".join([f"*l{i - 1}"] * 10) + "]\n" for i in range(1, 10)))
    (extra / "marker.yaml").write_text(f"{MARKER}: [unclosed\n")
    (outside / "secret.yaml").write_text(f"name: {MARKER}\n{MARKER}: [\n")
    (outside / "valid.yaml").write_text(PENDULUM.replace("name: pendulum", "name: outside_pendulum"))
    (outside / "start.yaml").write_text(PENDULUM.replace("name: pendulum", "name: operator_scene"))
    return extra, outside


@pytest.fixture(scope="module")
def client(ros, dirs):
    extra, outside = dirs
    # the operator starts the node on a scene outside scenes/ and scene_dirs: allowed (trusted)
    params = {"scene": str(outside / "start.yaml"), "mode": "lockstep", "marker_rate": 0.0,
              "command_timeout": 0.0, "scene_dirs": [str(extra)]}
    node, shutdown = run_node_in_thread(params, namespace=NS)
    c = Client(ns=NS)
    c.wait_ready()
    yield c
    c.close()
    shutdown()


def _stamp(c):
    m = c.last_state()
    return m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec


def _assert_unchanged(c, name, t_ns):
    """The node answers, its scene and simulation state are as before, and the simulation goes on
    from where it was (a load would have reset the time to 0)."""
    r = c.call("get_state")
    assert r.result.result == Result.OK and r.state.state == SimulationState.PAUSED
    assert c.describe().name == name
    n = len(c.joint_states)
    assert c.step(1).result.result == Result.OK
    c.wait_for(lambda: len(c.joint_states) > n, what="joint_states after the step")
    assert _stamp(c) == t_ns + 1_000_000


def test_the_operators_start_scene_is_not_restricted(client):
    assert client.describe().name == "operator_scene"
    assert client.step(5).result.result == Result.OK
    client.wait_for(lambda: client.last_state() is not None and _stamp(client) == 5_000_000, what="step 5")


@pytest.mark.parametrize("which", ["absolute_outside", "start_scene_again", "traversal", "passwd", "symlink_out"])
def test_paths_outside_the_allowed_directories_are_refused(client, dirs, which):
    extra, outside = dirs
    scene = {"absolute_outside": str(outside / "valid.yaml"), "start_scene_again": str(outside / "start.yaml"),
             "traversal": "../outside/secret", "passwd": "../../../../../../../../etc/passwd",
             "symlink_out": "escape"}[which]
    t = _stamp(client)
    r = client.load(scene)
    assert r.result.result == Result.NOT_FOUND, r.result.error_message
    msg = r.result.error_message
    assert "outside the allowed scene directories" in msg and str(extra) in msg and MARKER not in msg
    assert "'operator_scene' kept" in msg and r.description.name == "operator_scene"
    _assert_unchanged(client, "operator_scene", t)
    # the refusal is logged, without file content
    client.wait_for(lambda: any("outside the allowed scene directories" in e for e in client.errors()),
                    what="the refusal on /rosout")
    assert not any(MARKER in e for e in client.errors())


@pytest.mark.parametrize("which, problem", [
    ("mesh_up", "must lie inside the scene file's directory"),
    ("bomb", "nodes with its aliases expanded"),
    ("marker", "not valid YAML"),
])
def test_malformed_scenes_inside_are_refused_as_invalid(client, which, problem):
    t = _stamp(client)
    r = client.load(which)
    assert r.result.result == INVALID_SCENE and problem in r.result.error_message, r.result.error_message
    assert MARKER not in r.result.error_message and "lol" not in r.result.error_message
    _assert_unchanged(client, "operator_scene", t)


def test_overrides_cannot_point_a_mesh_outside(client, dirs):
    _, outside = dirs
    t = _stamp(client)
    for ov in [f"bodies.brick.shape.file={outside / 'cube.obj'}", "bodies.brick.shape.file=../outside/cube.obj"]:
        r = client.load("mesh_cube", [ov])
        assert r.result.result == INVALID_SCENE and "bodies[0] 'brick'" in r.result.error_message, r.result.error_message
    _assert_unchanged(client, "operator_scene", t)


def test_scene_dirs_is_read_only(client):
    cli = client.node.create_client(SetParameters, f"{NS}/redmax/set_parameters")
    assert cli.wait_for_service(timeout_sec=10)
    req = SetParameters.Request(parameters=[Parameter("scene_dirs", value=["/"]).to_parameter_msg()])
    fut = cli.call_async(req)
    client.wait_for(fut.done, what="set_parameters answer")
    assert not fut.result().results[0].successful
    client.node.destroy_client(cli)
    assert client.load("/etc/hostname").result.result == Result.NOT_FOUND


def test_scenes_in_scene_dirs_and_in_scenes_load(client, dirs):
    extra, _ = dirs
    r = client.load("extra_pendulum")
    assert r.result.result == Result.OK, r.result.error_message
    assert r.description.name == "extra_pendulum" and client.describe().name == "extra_pendulum"
    r = client.load(str(extra / "extra_pendulum.yaml"), ["dt=0.002"])
    assert r.result.result == Result.OK and r.description.dt == 0.002
    assert client.load("mesh_cube").result.result == Result.OK  # its mesh in its own directory
    assert client.load("pendulum").result.result == Result.OK
    assert client.describe().name == "pendulum"
    assert client.call("get_state").state.state == SimulationState.PAUSED


def test_a_missing_scene_dir_stops_the_node_at_start(ros, dirs):
    from redmax_ros.node.main import RedmaxNode
    _, outside = dirs
    with pytest.raises(ValueError, match="scene_dirs: every entry must be an existing directory"):
        RedmaxNode("redmax_bad", namespace=NS + "_bad",
                   parameter_overrides=[Parameter("scene", value="pendulum"),
                                        Parameter("scene_dirs", value=[str(outside / "nope")])])
