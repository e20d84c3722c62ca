"""step_server.StepServer (step_simulation with C structs through ctypes) against rclpy clients:
every response field, odd values, handler failures, order, close."""
from __future__ import annotations

import os
import threading

import node_fixtures  # noqa: F401  (first: skips this module without rclpy/redmax_msgs)

import pytest
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

from redmax_msgs.srv import StepSimulation
from redmax_ros.node import step_server

_RUNS = []
pytestmark = pytest.mark.skipif(not step_server.available(), reason="librcl not reachable through ctypes")


@pytest.fixture()
def served(ros):
    ns = f"/step_server_test{os.getpid()}_{len(_RUNS)}"
    _RUNS.append(ns)
    server_node = Node("server", namespace=ns)
    calls = []

    def handler(steps):
        calls.append((steps, threading.current_thread().name))
        if steps == 7:
            raise RuntimeError("boom")
        if steps == 3:
            return 4, "step 2 of 3 failed: non-finite velocity, état gardé", 1, 0.001
        return 1, "", steps, steps * 0.001  # OK

    srv = step_server.StepServer(server_node, "step_simulation", handler)
    srv.start()
    client = Node("client", namespace=ns)
    cli = client.create_client(StepSimulation, "step_simulation")
    ex = SingleThreadedExecutor()
    ex.add_node(client)
    assert cli.wait_for_service(timeout_sec=20)

    def call(steps):
        fut = cli.call_async(StepSimulation.Request(steps=steps))
        ex.spin_until_future_complete(fut, timeout_sec=20)
        assert fut.done(), "no answer"
        return fut.result()

    yield call, calls, srv
    srv.close()
    ex.shutdown()
    client.destroy_node()
    server_node.destroy_node()


def test_fields_order_and_failures(served):
    call, calls, srv = served
    r = call(25)
    assert r.result.result == 1 and r.result.error_message == ""
    assert r.completed_steps == 25 and r.sim_time.sec == 0 and r.sim_time.nanosec == 25_000_000
    r = call(3)
    assert r.result.result == 4 and r.result.error_message == "step 2 of 3 failed: non-finite velocity, état gardé"
    assert r.completed_steps == 1 and r.sim_time.nanosec == 1_000_000
    r = call(2**64 - 1)  # the full uint64 range reaches the handler
    assert r.completed_steps == 2**64 - 1 and r.result.error_message == ""
    r = call(7)  # an exception in the handler: OPERATION_FAILED with the reason, the server lives on
    assert r.result.result == 4 and "RuntimeError: boom" in r.result.error_message and r.completed_steps == 0
    for n in range(1, 21):
        assert call(1000 + n).completed_steps == 1000 + n
    assert [c[0] for c in calls] == [25, 3, 2**64 - 1, 7] + [1000 + n for n in range(1, 21)]
    assert {c[1] for c in calls} == {"redmax-step"}
    assert srv.served == len(calls)


def test_close_stops_the_thread(served):
    call, calls, srv = served
    call(1)
    srv.close()
    assert not srv._thread.is_alive()
    srv.close()  # idempotent
