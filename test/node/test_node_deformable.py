"""The node with a deformable (issue 15, docs/deformables.md, docs/node.md Topics): each step's vertex
positions are published on deformable_vertices (sensor_msgs/PointCloud2, FLOAT64 x, y, z and the
deformable's index) and the surface as a marker (LINE_LIST for a string), both equal to the core's
positions after the same steps. Real rclpy over Fast DDS (the private domain of test/conftest.py)."""
import numpy as np
import pytest

from node_fixtures import Client, run_node_in_thread  # noqa: F401  (first: skips without ROS)

from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402
from visualization_msgs.msg import Marker, MarkerArray  # noqa: E402

from redmax_msgs.msg import Result  # noqa: E402
from redmax_ros.core import Simulator  # noqa: E402

NS = "/deformable"
SCENE = "catalogue/string"


@pytest.fixture(scope="module")
def node(ros):
    n, shutdown = run_node_in_thread({"scene": SCENE, "mode": "lockstep", "marker_rate": 1000.0}, namespace=NS)
    yield n
    shutdown()


@pytest.fixture(scope="module")
def client(node):
    c = Client("redmax_deformable_client", ns=NS)
    c.clouds, c.markers = [], []
    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    c.node.create_subscription(PointCloud2, f"{NS}/deformable_vertices", c._store(c.clouds), qos)
    c.node.create_subscription(MarkerArray, f"{NS}/markers", c._store(c.markers), qos)
    c.wait_ready()
    yield c
    c.close()


def _cloud_xyz(msg):
    rec = np.frombuffer(bytes(msg.data), dtype=np.dtype([("xyz", "<f8", 3), ("deformable", "<u4"), ("pad", "<u4")]))
    return rec["xyz"], rec["deformable"]


def test_vertices_and_surface_follow_the_core(client):
    core = Simulator.load(SCENE)
    n_vertices = core.describe().deformables[0][2]
    assert client.reset().result.result == Result.OK
    r = client.step(25)
    assert r.result.result == Result.OK, r.result.error_message
    core.step(25)
    want = core.deformable_positions()["rope"]
    stamp = (r.sim_time.sec, r.sim_time.nanosec)

    def newest_cloud():
        with client.lock:
            return next((m for m in reversed(client.clouds) if (m.header.stamp.sec, m.header.stamp.nanosec) == stamp), None)

    client.wait_for(lambda: newest_cloud() is not None, what="the cloud of the last step")
    msg = newest_cloud()
    assert [f.name for f in msg.fields] == ["x", "y", "z", "deformable"]
    assert msg.width == n_vertices == len(want) and msg.point_step == 32 and msg.row_step == 32 * msg.width
    xyz, which = _cloud_xyz(msg)
    assert np.array_equal(which, np.zeros(n_vertices))
    assert np.array_equal(xyz, want)  # bitwise: the same steps as the in-process core
    assert np.abs(want - core.deformables.initial().x).max() > 1e-4  # the string moved

    def surface():
        with client.lock:
            for arr in reversed(client.markers):
                ms = [m for m in arr.markers if m.ns == "deformable/rope"]
                if ms and (ms[0].header.stamp.sec, ms[0].header.stamp.nanosec) == stamp:
                    return ms[0]
        return None

    client.wait_for(lambda: surface() is not None, what="the string's marker of the last step")
    m = surface()
    assert m.type == Marker.LINE_LIST and len(m.points) == 2 * (n_vertices - 1)
    seg = core.deformable_surfaces()["rope"]
    pts = np.array([[p.x, p.y, p.z] for p in m.points])
    assert np.array_equal(pts, want[seg.ravel()])



def test_logged_vertices_decode_with_both_readers(ros, tmp_path):
    """A logging node on the string scene: every deformable_vertices record decodes with mcap_ros2 and with
    rosbags (Jazzy typestore) to the positions the core computes for the same steps."""
    from pathlib import Path

    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    ns = "/deformable_log"
    n, shutdown = run_node_in_thread({"scene": SCENE, "mode": "lockstep", "marker_rate": 1000.0,
                                      "log_path": str(tmp_path)}, namespace=ns)
    c = Client("redmax_deformable_log_client", ns=ns)
    try:
        c.wait_ready()
        assert c.step(10).result.result == Result.OK
    finally:
        c.close()
        shutdown()
    core = Simulator.load(SCENE)
    want = {}
    for k in range(1, 11):
        core.step(1)
        want[k * 1_000_000] = core.deformable_positions()["rope"]  # stamp [ns] of step k at h = 1 ms
    path = sorted(Path(tmp_path).rglob("*.mcap"))[0]
    topic = f"{ns}/deformable_vertices"
    with open(path, "rb") as f:
        got_a = [m for _, _, _, m in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages(
            topics=[topic])]
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        conns = [x for x in reader.connections if x.topic == topic]
        got_b = [reader.deserialize(raw, x.msgtype) for x, _, raw in reader.messages(connections=conns)]
    for got in (got_a, got_b):
        stepped = [m for m in got if m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec in want]
        assert len(stepped) == 10
        for m in stepped:
            xyz, _ = _cloud_xyz(m)
            assert np.array_equal(xyz, want[m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec])
