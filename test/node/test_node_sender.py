"""node/sender.py: every publish mode keeps order; the publisher thread: drain, inline, back-pressure, shutdown."""
import os
import threading
import time

import pytest

import node_fixtures  # noqa: F401  (first: skips this module without rclpy/redmax_msgs)

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from rclpy.serialization import serialize_message  # noqa: E402
from rosgraph_msgs.msg import Clock  # noqa: E402
from std_msgs.msg import String  # noqa: E402

from redmax_ros.node.cdr import encode_clock  # noqa: E402
from redmax_ros.node.sender import Sender  # noqa: E402

NS = f"/sender{os.getpid()}"
QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)


@pytest.fixture(scope="module")
def nodes(ros):
    pub_node, sub_node = Node("sender_pub", namespace=NS), Node("sender_sub", namespace=NS)
    got, lock = [], threading.Lock()

    def store(kind):
        def cb(m):
            with lock:
                got.append((kind, m.data if kind == "s" else m.clock.sec))
        return cb
    sub_node.create_subscription(String, "a", store("s"), QOS)
    sub_node.create_subscription(Clock, "b", store("c"), QOS)
    pa, pb = pub_node.create_publisher(String, "a", QOS), pub_node.create_publisher(Clock, "b", QOS)
    ex = SingleThreadedExecutor()
    ex.add_node(sub_node)
    stop = threading.Event()
    th = threading.Thread(target=lambda: [ex.spin_once(timeout_sec=0.05) for _ in iter(stop.is_set, True)],
                          daemon=True)
    th.start()
    end = time.monotonic() + 20
    while pa.get_subscription_count() == 0 or pb.get_subscription_count() == 0:
        assert time.monotonic() < end, "no match"
        time.sleep(0.01)
    yield pa, pb, got, lock
    stop.set()
    th.join(5)
    pub_node.destroy_node()
    sub_node.destroy_node()


@pytest.mark.parametrize("mode", Sender.MODES)
def test_everything_published_in_order(nodes, mode):
    pa, pb, got, lock = nodes
    with lock:
        got.clear()
    s = Sender(mode=mode)
    assert s.mode == mode and s.threaded == (mode in ("thread", "auto"))
    for i in range(300):
        if mode == "auto" and i % 50 == 0:  # to the publisher thread and back every 50 (set_overlap drains)
            s.set_overlap(i % 100 == 0)
        s.send(pa, serialize_message(String(data=str(i))), wake=i % 3 == 2)
        s.send(pb, encode_clock(float(i)), wake=False)
    s.wake()
    assert s.drain()
    if mode == "thread":
        assert s.published == 600 and s.failed == 0
    end = time.monotonic() + 20
    while len(got) < 600 and time.monotonic() < end:
        time.sleep(0.01)
    s.close()
    with lock:
        strings = [int(v) for k, v in got if k == "s"]
        clocks = [v for k, v in got if k == "c"]
    assert strings == list(range(300)) and clocks == list(range(300))  # per topic in order, none lost


def test_close_publishes_what_is_queued_then_falls_back(nodes):
    pa, _, got, lock = nodes
    with lock:
        got.clear()
    s = Sender(threaded=True)
    for i in range(50):
        s.send(pa, serialize_message(String(data=f"x{i}")), wake=False)
    s.close()  # no wake before: close drains anyway
    assert s.published == 50
    s.send(pa, serialize_message(String(data="after")))  # after close: published in the caller
    end = time.monotonic() + 20
    while len(got) < 51 and time.monotonic() < end:
        time.sleep(0.01)
    with lock:
        assert [v for _, v in got] == [f"x{i}" for i in range(50)] + ["after"]


def test_inline_keeps_order_with_what_was_queued(nodes):
    pa, _, got, lock = nodes
    with lock:
        got.clear()
    s = Sender(threaded=True)
    for i in range(100):
        s.send(pa, serialize_message(String(data=f"q{i}")), wake=False)
    with s.inline():  # drains the queue, then publishes in this thread
        for i in range(20):
            s.send(pa, serialize_message(String(data=f"i{i}")))
    s.send(pa, serialize_message(String(data="after")))
    s.close()
    end = time.monotonic() + 20
    while len(got) < 121 and time.monotonic() < end:
        time.sleep(0.01)
    with lock:
        assert [v for _, v in got] == [f"q{i}" for i in range(100)] + [f"i{i}" for i in range(20)] + ["after"]


def test_back_pressure_bounds_the_queue():
    """A DDS write that blocks (slow reliable reader) must not let the queue grow without bound:
    the producer waits (GIL released) until it is half empty; nothing is lost, order is kept."""
    import ctypes

    out, longest = [], [0]

    class _Pub:  # stands in for an rclpy publisher: only handle.pointer is used
        class handle:
            pointer = 1234

    s = None

    def slow_publish(ptr, msg_ref, _):
        m = msg_ref._obj
        out.append(ctypes.string_at(m.buffer, m.buffer_length))
        longest[0] = max(longest[0], len(s._q))
        time.sleep(0.002)
        return 0

    s = Sender(threaded=True, max_queue=20, rcl=(slow_publish, slow_publish, None, None))
    for i in range(200):
        s.send(_Pub, f"m{i}".encode())
    assert s.drain(timeout=10)
    s.close()
    assert out == [f"m{i}".encode() for i in range(200)]
    assert longest[0] <= 21 and s.waits > 0
