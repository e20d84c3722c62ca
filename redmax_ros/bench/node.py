"""redmax_bench node: the ROS node's latency, per-step service overhead and real-time factor.

The node runs as a subprocess (``python -m redmax_ros.node.main``), the client is this process
(rclpy over Fast DDS, private domain unless ROS_DOMAIN_ID is set, localhost discovery).

(a) command-to-state latency: free-run at h = 1 ms, real-time factor 1, joint_states every step;
    publish an elbow velocity command with a fresh value and time until the first joint_states
    carrying that velocity arrives.
(b) lockstep step-service round trip for one step vs the core stepping in-process (same scene):
    overhead per step = round trip - core step.
(c) real-time factor reached in free-run as fast as possible (real_time_factor 0), joint_states
    every step with a subscriber attached, with and without MCAP logging, for each scene.

Writes bench/results/node.json.
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time

os.environ.setdefault("ROS_DOMAIN_ID", str(101 - os.getpid() % 20))
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")


def _start_node(ns, params: dict):
    cmd = [sys.executable, "-m", "redmax_ros.node.main", "--ros-args", "-r", f"__ns:={ns}"]
    for k, v in params.items():
        cmd += ["-p", f"{k}:={v}"]
    return subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def _stop_node(proc):
    import signal
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()


class _Client:
    def __init__(self, ns, want_states=True):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from diagnostic_msgs.msg import DiagnosticArray
        from sensor_msgs.msg import JointState
        from redmax_msgs.srv import SetSimulationState, StepSimulation

        self.node = Node("redmax_bench_client", namespace=ns)
        self.cond = threading.Condition()
        self.last_js = None
        self.js_count = 0
        self.diag = []
        self.waiting_for = None
        self.hit_time = None
        if want_states:
            self.node.create_subscription(JointState, "joint_states", self._on_js,
                                          QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, 10)
        self.pub = self.node.create_publisher(JointState, "joint_commands", 10)
        self.step_cli = self.node.create_client(StepSimulation, "step_simulation")
        self.state_cli = self.node.create_client(SetSimulationState, "set_simulation_state")
        self.ex = SingleThreadedExecutor()
        self.ex.add_node(self.node)
        self._stop = False
        self.th = threading.Thread(target=self._spin, daemon=True)
        self.th.start()
        self._rclpy = rclpy

    def _spin(self):
        while not self._stop:
            try:
                self.ex.spin_once(timeout_sec=0.05)
            except Exception:
                break

    def _on_js(self, m):
        now = time.perf_counter()
        self.js_count += 1
        w = self.waiting_for
        if w is not None and self.hit_time is None and len(m.velocity) and abs(m.velocity[0] - w) < 1e-9:
            self.hit_time = now
            with self.cond:
                self.cond.notify_all()

    def _on_diag(self, m):
        if not m.status or not m.status[0].name.startswith(self.node.get_namespace() + "/"):
            return  # another simulation node on this ROS graph
        vals = {kv.key: kv.value for kv in m.status[0].values}
        self.diag.append((time.monotonic(), vals))

    def wait_ready(self, timeout=30):
        assert self.step_cli.wait_for_service(timeout_sec=timeout), "node did not come up"
        end = time.monotonic() + timeout
        while self.pub.get_subscription_count() == 0:
            assert time.monotonic() < end
            time.sleep(0.01)

    def call(self, cli, req, timeout=30):
        fut = cli.call_async(req)
        ev = threading.Event()
        fut.add_done_callback(lambda f: ev.set())
        if not ev.wait(timeout):
            raise TimeoutError("service call timed out")
        return fut.result()

    def close(self):
        self._stop = True
        self.th.join(5)
        self.node.destroy_node()


def bench_latency(scene, n, dt):
    from sensor_msgs.msg import JointState

    ns = "/bench_lat"
    proc = _start_node(ns, {"scene": scene, "mode": "free_run", "real_time_factor": 1.0, "dt": dt,
                            "publish_rate": 0.0, "marker_rate": 0.0, "command_timeout": 100.0})
    c = _Client(ns)
    lat = []
    try:
        c.wait_ready()
        time.sleep(1.0)
        for i in range(n):
            v = 0.001 * (i + 1) * (1 if i % 2 else -1)
            c.hit_time = None
            c.waiting_for = v
            t0 = time.perf_counter()
            c.pub.publish(JointState(name=["elbow"] if scene == "hand" else [], velocity=[v]))
            with c.cond:
                c.cond.wait_for(lambda: c.hit_time is not None, timeout=2.0)
            if c.hit_time is not None:
                lat.append(c.hit_time - t0)
            time.sleep(0.02)
    finally:
        c.close()
        _stop_node(proc)
    lat.sort()
    return {"scene": scene, "dt": dt, "samples": len(lat), "requested": n,
            "median_ms": 1e3 * statistics.median(lat) if lat else None,
            "p95_ms": 1e3 * lat[int(0.95 * (len(lat) - 1))] if lat else None,
            "max_ms": 1e3 * lat[-1] if lat else None}


def bench_step_service(scene, n, dt):
    from redmax_msgs.srv import StepSimulation
    from redmax_ros.core import Simulator

    sim = Simulator.load(scene, overrides=[f"dt={dt}"])
    sim.step(20)
    t0 = time.perf_counter()
    for _ in range(n):
        sim.step(1)
    core = (time.perf_counter() - t0) / n

    ns = "/bench_step"
    proc = _start_node(ns, {"scene": scene, "mode": "lockstep", "dt": dt, "publish_rate": 0.0,
                            "marker_rate": 0.0, "command_timeout": 0.0})
    c = _Client(ns, want_states=True)
    try:
        c.wait_ready()
        req = StepSimulation.Request(steps=1)
        for _ in range(20):
            c.call(c.step_cli, req)
        t0 = time.perf_counter()
        for _ in range(n):
            r = c.call(c.step_cli, req)
            assert r.result.result == 1, r.result.error_message
        rt = (time.perf_counter() - t0) / n
    finally:
        c.close()
        _stop_node(proc)
    return {"scene": scene, "dt": dt, "steps": n, "core_step_ms": core * 1e3, "service_round_trip_ms": rt * 1e3,
            "overhead_ms": (rt - core) * 1e3, "overhead_ratio": rt / core}


def bench_rtf(scene, seconds, dt, logging):
    ns = "/bench_rtf"
    params = {"scene": scene, "mode": "free_run", "real_time_factor": 0.0, "dt": dt, "publish_rate": 0.0,
              "marker_rate": 0.0, "command_timeout": 0.0, "diagnostics_period": 1.0}
    tmp = None
    if logging:
        tmp = tempfile.mkdtemp(prefix="redmax_bench_logs_")
        params["log_path"] = tmp
    proc = _start_node(ns, params)
    c = _Client(ns, want_states=True)
    try:
        c.wait_ready()
        end = time.monotonic() + seconds + 1.5
        while time.monotonic() < end:
            time.sleep(0.1)
        diags = [v for _, v in c.diag][1:]  # the first window includes start-up
    finally:
        c.close()
        _stop_node(proc)
    rtf = [float(v["real_time_factor"]) for v in diags if "real_time_factor" in v]
    sps = [float(v["steps_per_second"]) for v in diags if "steps_per_second" in v]
    backlog = [int(float(v.get("log_backlog", 0))) for v in diags]
    size = 0
    if tmp:
        for root, _, files in os.walk(tmp):
            size += sum(os.path.getsize(os.path.join(root, f)) for f in files)
    return {"scene": scene, "dt": dt, "logging": logging, "windows": len(rtf),
            "real_time_factor": statistics.median(rtf) if rtf else None,
            "steps_per_second": statistics.median(sps) if sps else None,
            "max_log_backlog": max(backlog) if backlog else 0, "log_bytes": size}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="redmax_bench node", description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="+", default=["hand", "klann_leg"])
    ap.add_argument("--dt", type=float, default=0.001)
    ap.add_argument("--latency-samples", type=int, default=200)
    ap.add_argument("--service-steps", type=int, default=500)
    ap.add_argument("--seconds", type=float, default=6.0, help="free-run duration per RTF measurement")
    ap.add_argument("--quick", action="store_true", help="small sample counts (smoke run)")
    ap.add_argument("--no-write", action="store_true", help="do not write bench/results/node.json")
    a = ap.parse_args(argv)
    if a.quick:
        a.latency_samples, a.service_steps, a.seconds = 30, 100, 3.0

    import rclpy
    rclpy.init()
    out = {"latency": [], "step_service": [], "free_run": []}
    try:
        print(f"(a) command-to-state latency, free-run 1 kHz, {a.latency_samples} commands")
        r = bench_latency("hand", a.latency_samples, a.dt)
        out["latency"].append(r)
        print(f"    hand: median {r['median_ms']:.2f} ms, p95 {r['p95_ms']:.2f} ms, max {r['max_ms']:.2f} ms "
              f"({r['samples']}/{r['requested']})")
        print(f"(b) lockstep step_simulation(steps=1) round trip vs in-process core step, {a.service_steps} calls")
        for sc in a.scenes:
            r = bench_step_service(sc, a.service_steps, a.dt)
            out["step_service"].append(r)
            print(f"    {sc}: core {r['core_step_ms']:.3f} ms, service {r['service_round_trip_ms']:.3f} ms, "
                  f"overhead {r['overhead_ms']:.3f} ms/step (x{r['overhead_ratio']:.2f})")
        print(f"(c) free-run real-time factor (as fast as possible), h = {a.dt:g} s, joint_states every step")
        for sc in a.scenes:
            for logging in (False, True):
                r = bench_rtf(sc, a.seconds, a.dt, logging)
                out["free_run"].append(r)
                print(f"    {sc:10s} logging {'on ' if logging else 'off'}: RTF {r['real_time_factor']:.2f} "
                      f"({r['steps_per_second']:.0f} steps/s), max log backlog {r['max_log_backlog']}")
        for sc in a.scenes:
            off = [r for r in out["free_run"] if r["scene"] == sc and not r["logging"]][0]
            on = [r for r in out["free_run"] if r["scene"] == sc and r["logging"]][0]
            if off["real_time_factor"] and on["real_time_factor"]:
                slow = 1 - on["real_time_factor"] / off["real_time_factor"]
                out.setdefault("logging_slowdown", {})[sc] = slow
                print(f"    {sc}: logging slows free-run by {100 * slow:.1f} %")
    finally:
        rclpy.shutdown()
    if not a.no_write:
        from .common import write_json
        p = write_json("node", {"args": vars(a), **out})
        print(f"wrote {p}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
