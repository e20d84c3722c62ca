"""redmax_bench node: the ROS node's latency, per-step service overhead, real-time factor, the
cost of MCAP logging, the real-time factor under command floods and query latency.

The machine is shared (2 cores here), so every section interleaves what it compares, repeats it
and reports medians with the 1-minute load average at the time. Clients are this process (rclpy
over Fast DDS, private domain unless ROS_DOMAIN_ID is set, localhost discovery), spun by rclpy's
EventsExecutor when available; joint_states are taken raw (no Python deserialization per
message) so the client measures the node rather than its own decoding.

(a) command-to-state latency: node subprocess in free-run at h = 1 ms, real-time factor 1,
    joint_states every step; publish an elbow velocity command with a fresh value and time until
    the first joint_states carrying that velocity arrives.
(b) lockstep step_simulation(steps=1) round trip, in blocks interleaved with the same number of
    in-process core steps (same scene) and of calls to do-nothing servers of the same service type
    (the floor: one spun by rclpy's MultiThreadedExecutor, one by its EventsExecutor, one served
    like the node's step_simulation by node/step_server.py's StepServer): overhead per step =
    round trip - core step; node - StepServer floor = what the node adds to serving the call
    (the step itself, run in the node process between calls, included).
(c) real-time factor in free-run as fast as possible (real_time_factor 0), joint_states every
    step with a subscriber attached, node subprocess per run, logging off/on alternated, for each
    scene; RTF from the node's /diagnostics (median over 1 s windows, start-up window dropped).
(d) logging cost in one process: one in-process node (hand, free-run as fast as possible,
    joint_states every step, a raw subscriber in another process), switched per window between:
    off; logging with the writer process (the default); logging with the same MCAP writer on a
    thread of this interpreter (writer='thread'); off but solver_stats built every step as if
    subscribed (logging records solver_stats, whose KKT residual is computed for it, so this
    separates the writer's cost from the cost of producing what it records). Order rotated each
    round; medians of steps/s, of per-round ratios, of process CPU per step and of the writer
    process's CPU per step.
(e) free-run real-time factor under a flood of commands: node subprocess (hand, h = 1 ms,
    joint_states every step) at real_time_factor 0 and then 1 (set through the parameter service);
    a flooder subprocess (its own GIL) publishes joint_commands at 10 kHz for 5 s: valid (the wrist's
    two DOFs, a small velocity of zero mean, period 0.5 s of wall time, so that the wrist stays
    within its limits at any real-time factor) or invalid (an unknown joint), interleaved with
    unflooded windows per round (none, valid, invalid). RTF = sim-time advance / wall time over the
    window from the raw joint_states stamps (and, as a check, the mean of the node's /diagnostics
    windows), in the flood, in its last 2 s and in the 3 s after it, per 0.5 s bins, and the longest
    stall; ratio flooded / unflooded per round (issue 17: >= 0.8); commands_received/coalesced and
    command_errors from /diagnostics; CPU % of the node (and of its busiest threads), of the flooder
    and of this process from /proc.
(f) query latency: get_simulation_state, describe_scene and a parameter get (GetParameters on
    <ns>/redmax/get_parameters), each called from this process (spinning its own executor until the
    answer), in lockstep idle, while a long step_simulation(20000) request runs (queries sent while
    it runs count there, answered before it ended or not), and in free-run as fast as possible; the
    conditions interleaved per round; median/p95/max (issue 17: <= 50 ms, measured, not asserted).

Writes node.json into --out (default bench/results under the current directory).

The ROS parts (rclpy, the message packages and redmax_ros.node, which needs rclpy) are imported
inside the functions that use them: they are optional for the benchmark package (every other
subcommand runs without ROS).
"""
from __future__ import annotations

import argparse
import bisect
import json
import math
import os
import resource
import signal
import statistics
import struct
import subprocess
import sys
import tempfile
import threading
import time

from redmax_ros.core import Simulator
from redmax_ros.logging.mcap_log import McapLogger
from redmax_bench.common import add_out_argument, results_dir, write_json

os.environ.setdefault("ROS_DOMAIN_ID", str(101 - os.getpid() % 20))
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")


def _load():
    return round(os.getloadavg()[0], 2)


def _median(xs):
    xs = [x for x in xs if x is not None]
    return statistics.median(xs) if xs else None


def _f(x, digits=2):
    return "n/a" if x is None else f"{x:.{digits}f}"


def _start_node(ns, params: dict):
    cmd = [sys.executable, "-m", "redmax_ros.node.main", "--ros-args", "-r", f"__ns:={ns}"]
    for k, v in params.items():
        cmd += ["-p", f"{k}:={v}"]
    err = tempfile.TemporaryFile(mode="w+")  # a pipe nobody reads could fill up and stall the node
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err, text=True)
    proc.err_file = err
    return proc


def _stderr_tail(proc, n=2000):
    try:
        proc.err_file.seek(0)
        return proc.err_file.read()[-n:]
    except (AttributeError, OSError, ValueError):
        return ""


def _stop(proc):
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _executor():
    try:
        from rclpy.experimental import EventsExecutor  # optional: rclpy
        return EventsExecutor()
    except ImportError:
        from rclpy.executors import SingleThreadedExecutor  # optional: rclpy
        return SingleThreadedExecutor()


class _JointStates:
    """Raw joint_states subscription: counts messages and reads one velocity straight from the CDR
    bytes (offsets from our encoder's layout for the names of the first message)."""

    def __init__(self, node, topic, joint=None, on_message=None):
        from rclpy.qos import QoSProfile, ReliabilityPolicy  # optional: rclpy
        from sensor_msgs.msg import JointState  # optional: sensor_msgs (ROS)

        self.count = 0
        self.joint = joint
        self.offset = None
        self.on_message = on_message
        self._JointState = JointState
        node.create_subscription(JointState, topic, self._cb,
                                 QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE), raw=True)

    def _cb(self, data):
        now = time.perf_counter()
        self.count += 1
        if self.joint is None or self.on_message is None:
            return
        if self.offset is None:
            from rclpy.serialization import deserialize_message  # optional: rclpy
            from redmax_ros.node.cdr import JointStateEncoder  # optional: rclpy (redmax_ros.node)
            names = list(deserialize_message(data, self._JointState).name)
            self.offset = JointStateEncoder(names).off[1] + 8 * names.index(self.joint)
        self.on_message(now, struct.unpack_from("<d", data, self.offset)[0])


class _Spinner:
    def __init__(self, node):
        self.ex = _executor()
        self.ex.add_node(node)
        self._stop = False
        self.th = threading.Thread(target=self._spin, daemon=True)
        self.th.start()

    def _spin(self):
        while not self._stop:
            try:
                self.ex.spin_once(timeout_sec=0.05)
            except Exception:
                break

    def close(self):
        self._stop = True
        self.th.join(5)
        try:
            self.ex.shutdown()
        except Exception:
            pass


def _wait_for(pred, timeout, what):
    end = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > end:
            raise TimeoutError(f"timed out waiting for {what}")
        time.sleep(0.01)


# ------------------------------------------------------------------------------------------------
# (a) latency

def bench_latency(scene, n, dt):
    from rclpy.node import Node  # optional: rclpy
    from sensor_msgs.msg import JointState  # optional: sensor_msgs (ROS)

    ns = f"/bench_lat{os.getpid()}"
    proc = _start_node(ns, {"scene": scene, "mode": "free_run", "real_time_factor": 1.0, "dt": dt,
                            "publish_rate": 0.0, "marker_rate": 0.0, "command_timeout": 100.0})
    node = Node("redmax_bench_latency", namespace=ns)
    state = {"want": None, "hit": None}
    cond = threading.Condition()

    def on_velocity(now, v):
        w = state["want"]
        if w is not None and state["hit"] is None and abs(v - w) < 1e-12:
            with cond:
                state["hit"] = now
                cond.notify_all()

    js = _JointStates(node, "joint_states", joint="elbow", on_message=on_velocity)
    pub = node.create_publisher(JointState, "joint_commands", 10)
    spin = _Spinner(node)
    lat, load = [], []
    try:
        _wait_for(lambda: pub.get_subscription_count() > 0 and js.count > 0, 30, "the node")
        time.sleep(1.0)
        for i in range(n):
            v = 0.001 * (i + 1) * (1 if i % 2 else -1)
            state["hit"], state["want"] = None, v
            t0 = time.perf_counter()
            pub.publish(JointState(name=["elbow"], velocity=[v]))
            with cond:
                cond.wait_for(lambda: state["hit"] is not None, timeout=2.0)
            if state["hit"] is not None:
                lat.append(state["hit"] - t0)
            if i % 20 == 0:
                load.append(_load())
            time.sleep(0.02)
    finally:
        spin.close()
        node.destroy_node()
        _stop(proc)
    lat.sort()
    return {"scene": scene, "dt": dt, "samples": len(lat), "requested": n,
            "median_ms": 1e3 * statistics.median(lat) if lat else None,
            "p95_ms": 1e3 * lat[int(0.95 * (len(lat) - 1))] if lat else None,
            "max_ms": 1e3 * lat[-1] if lat else None, "load": _median(load)}


# ------------------------------------------------------------------------------------------------
# (b) step service vs the core and the rclpy floor

def _floor_server(kind, ns):
    """A do-nothing step_simulation server (run as a subprocess)."""
    import rclpy  # optional: rclpy
    from rclpy.node import Node  # optional: rclpy
    from redmax_msgs.srv import StepSimulation  # optional: redmax_msgs (ROS)

    rclpy.init()
    node = Node("redmax_bench_floor", namespace=ns)

    def cb(req, resp):
        resp.result.result = 1
        resp.completed_steps = req.steps
        return resp

    if kind == "raw":  # the node's own way of serving step_simulation (node/step_server.py)
        from redmax_ros.node.step_server import StepServer  # optional: rclpy (redmax_ros.node)
        srv = StepServer(node, "step_simulation", lambda steps: (1, "", steps, 0.0))
        srv.start()
        try:
            while rclpy.ok():
                time.sleep(0.2)
        except BaseException:
            pass
        srv.close()
        return 0
    if kind == "mte":
        from rclpy.callback_groups import ReentrantCallbackGroup  # optional: rclpy
        from rclpy.executors import MultiThreadedExecutor  # optional: rclpy
        node.create_service(StepSimulation, "step_simulation", cb, callback_group=ReentrantCallbackGroup())
        ex = MultiThreadedExecutor(num_threads=4)
    else:
        ex = _executor()
        node.create_service(StepSimulation, "step_simulation", cb)
    ex.add_node(node)
    try:
        while rclpy.ok():
            ex.spin_once(timeout_sec=0.2)
    except BaseException:
        pass
    return 0


class _StepClient:
    """Calls step_simulation and spins its own executor until the answer (no thread hop)."""

    def __init__(self, ns, name):
        from rclpy.node import Node  # optional: rclpy
        from redmax_msgs.srv import StepSimulation  # optional: redmax_msgs (ROS)

        self.node = Node(name, namespace=ns)
        self.cli = self.node.create_client(StepSimulation, "step_simulation")
        self.ex = _executor()
        self.ex.add_node(self.node)
        self.req = StepSimulation.Request(steps=1)

    def call(self, timeout=5.0):
        fut = self.cli.call_async(self.req)
        self.ex.spin_until_future_complete(fut, timeout_sec=timeout)
        if not fut.done():
            raise TimeoutError("step_simulation did not answer")
        return fut.result()

    def ready(self, warmup=30):
        assert self.cli.wait_for_service(timeout_sec=30), "server did not come up"
        done = 0
        end = time.monotonic() + 60
        while done < warmup:
            try:
                r = self.call(timeout=2.0)
                assert r.result.result == 1, r.result.error_message
                done += 1
            except TimeoutError:  # a request sent before the server matched us is lost: resend
                assert time.monotonic() < end, "server does not answer"

    def time_calls(self, n):
        t0 = time.perf_counter()
        for _ in range(n):
            self.call()
        return (time.perf_counter() - t0) / n

    def close(self):
        try:
            self.ex.remove_node(self.node)
            self.ex.shutdown()
        except Exception:
            pass
        self.node.destroy_node()


def bench_step_service(scene, n, dt, rounds):
    sim = Simulator.load(scene, overrides=[f"dt={dt}"])
    sim.step(20)
    pid = os.getpid()
    ns_node, ns_mte, ns_ev, ns_raw = (f"/bench_step{pid}", f"/bench_floor_mte{pid}", f"/bench_floor_ev{pid}",
                                      f"/bench_floor_raw{pid}")
    procs = [_start_node(ns_node, {"scene": scene, "mode": "lockstep", "dt": dt, "publish_rate": 0.0,
                                   "marker_rate": 0.0, "command_timeout": 0.0})]
    floor = [("floor_mte", ns_mte, "mte"), ("floor_events", ns_ev, "events"), ("floor_raw", ns_raw, "raw")]
    for _, ns, kind in floor:
        procs.append(subprocess.Popen([sys.executable, "-m", "redmax_bench.node", "_floor_server", kind, ns],
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
    clients = {"node": _StepClient(ns_node, "redmax_bench_step")}
    for key, ns, _ in floor:
        clients[key] = _StepClient(ns, f"redmax_bench_{key}")
    keys = ("node", "floor_mte", "floor_events", "floor_raw")
    rows = {k: [] for k in ("core",) + keys + ("load",)}
    try:
        for c in clients.values():
            c.ready()
        for r in range(rounds):
            t0 = time.perf_counter()
            for _ in range(n):
                sim.step(1)
            rows["core"].append((time.perf_counter() - t0) / n)
            for key in keys if r % 2 == 0 else keys[::-1]:
                rows[key].append(clients[key].time_calls(n))
            rows["load"].append(_load())
    finally:
        for c in clients.values():
            c.close()
        for p in procs:
            _stop(p)
    core, rt = _median(rows["core"]), _median(rows["node"])
    overhead = _median([b - a for a, b in zip(rows["core"], rows["node"])])
    return {"scene": scene, "dt": dt, "calls_per_block": n, "rounds": rounds,
            "core_step_ms": 1e3 * core, "service_round_trip_ms": 1e3 * rt, "overhead_ms": 1e3 * overhead,
            "overhead_ratio": rt / core,
            "floor_round_trip_ms": {"multi_threaded_executor": 1e3 * _median(rows["floor_mte"]),
                                    "events_executor": 1e3 * _median(rows["floor_events"]),
                                    "step_server": 1e3 * _median(rows["floor_raw"])},
            "node_minus_step_server_floor_ms": 1e3 * _median([b - a for a, b in zip(rows["floor_raw"], rows["node"])]),
            # best blocks: the least disturbed by other work on the machine
            "best_ms": {k: 1e3 * min(v) for k, v in rows.items() if k != "load"},
            "overhead_best_ms": 1e3 * (min(rows["node"]) - min(rows["core"])),
            "blocks_ms": {k: [round(1e3 * x, 4) for x in v] for k, v in rows.items() if k != "load"},
            "load": _median(rows["load"])}


# ------------------------------------------------------------------------------------------------
# (c) free-run real-time factor, node subprocess, logging off/on alternated

def _diag_listener(node, ns, stamp=False):
    """The node's /diagnostics values (strings) per report; with stamp, "_t" = arrival (time.monotonic)."""
    from diagnostic_msgs.msg import DiagnosticArray  # optional: diagnostic_msgs (ROS)

    out = []

    def cb(m):
        if m.status and m.status[0].name.startswith(ns + "/"):  # not another simulation on this graph
            d = {kv.key: kv.value for kv in m.status[0].values}
            if stamp:
                d["_t"] = time.monotonic()
            out.append(d)
    node.create_subscription(DiagnosticArray, "/diagnostics", cb, 10)
    return out


def bench_rtf_once(scene, seconds, dt, logging):
    from rclpy.node import Node  # optional: rclpy

    ns = f"/bench_rtf{os.getpid()}"
    params = {"scene": scene, "mode": "free_run", "real_time_factor": 0.0, "dt": dt, "publish_rate": 0.0,
              "marker_rate": 0.0, "command_timeout": 0.0, "diagnostics_period": 1.0}
    tmp = None
    if logging:
        tmp = tempfile.mkdtemp(prefix="redmax_bench_logs_")
        params["log_path"] = tmp
    ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    proc = _start_node(ns, params)
    node = Node("redmax_bench_rtf", namespace=ns)
    js = _JointStates(node, "joint_states")
    diags = _diag_listener(node, ns)
    spin = _Spinner(node)
    try:
        _wait_for(lambda: len(diags) > 0, 60, "the node's diagnostics")
        n0 = len(diags)
        want = n0 + 1 + max(1, int(round(seconds)))  # the window that includes start-up is dropped
        try:
            _wait_for(lambda: len(diags) >= want, seconds + 30, "diagnostics windows")
        except TimeoutError:
            pass  # report what came (a window may be lost on a loaded machine)
        d = diags[n0 + 1:]
        load = _load()
        if proc.poll() is not None:
            raise RuntimeError(f"the node exited early: {_stderr_tail(proc)}")
    finally:
        spin.close()
        node.destroy_node()
        _stop(proc)
    ru1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    steps = int(float(diags[-1]["steps"])) if diags else 0
    size = 0
    if tmp:
        for root, _, files in os.walk(tmp):
            size += sum(os.path.getsize(os.path.join(root, f)) for f in files)
    return {"real_time_factor": _median([float(v["real_time_factor"]) for v in d]),
            "steps_per_second": _median([float(v["steps_per_second"]) for v in d]), "windows": len(d),
            "max_log_backlog": max([int(float(v.get("log_backlog", 0))) for v in d] or [0]),
            "cpu_ms_per_step_incl_startup": 1e3 * ((ru1.ru_utime + ru1.ru_stime) - (ru0.ru_utime + ru0.ru_stime))
            / max(steps, 1),
            "joint_states_received": js.count, "log_bytes": size, "load": load}


def bench_rtf(scene, seconds, dt, rounds):
    runs = {False: [], True: []}
    for r in range(rounds):
        for logging in (False, True) if r % 2 == 0 else (True, False):
            runs[logging].append(bench_rtf_once(scene, seconds, dt, logging))
    out = []
    for logging, rs in runs.items():
        out.append({"scene": scene, "dt": dt, "logging": logging, "runs": len(rs),
                    "real_time_factor": _median([x["real_time_factor"] for x in rs]),
                    "steps_per_second": _median([x["steps_per_second"] for x in rs]),
                    "max_log_backlog": max(x["max_log_backlog"] for x in rs),
                    "cpu_ms_per_step_incl_startup": _median([x["cpu_ms_per_step_incl_startup"] for x in rs]),
                    "load": _median([x["load"] for x in rs]),
                    "best_real_time_factor": max((x["real_time_factor"] for x in rs if x["real_time_factor"]),
                                                 default=None),
                    "per_run_rtf": [x["real_time_factor"] for x in rs], "per_run_load": [x["load"] for x in rs]})
    ratios = [b["real_time_factor"] / a["real_time_factor"] for a, b in zip(runs[False], runs[True])
              if a["real_time_factor"] and b["real_time_factor"]]
    slowdown = 1 - _median(ratios) if ratios else None
    if out[0]["best_real_time_factor"] and out[1]["best_real_time_factor"]:  # best run vs best run
        out[1]["slowdown_best_vs_best"] = 1 - out[1]["best_real_time_factor"] / out[0]["best_real_time_factor"]
    return out, slowdown


# ------------------------------------------------------------------------------------------------
# (d) logging cost inside one node process

def _raw_subscriber(ns):
    """A raw joint_states subscriber (run as a subprocess for section (d))."""
    import rclpy  # optional: rclpy
    from rclpy.node import Node  # optional: rclpy

    rclpy.init()
    node = Node("redmax_bench_sub", namespace=ns)
    _JointStates(node, "joint_states")
    ex = _executor()
    ex.add_node(node)
    try:
        while rclpy.ok():
            ex.spin_once(timeout_sec=0.2)
    except BaseException:
        pass
    return 0


def _cpu_seconds(path):
    with open(path) as f:
        s = f.read()
    fields = s[s.rindex(")") + 2:].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def bench_logging_inprocess(scene, dt, rounds, window, writers=("process", "thread")):
    from rclpy.executors import MultiThreadedExecutor  # optional: rclpy
    from rclpy.parameter import Parameter  # optional: rclpy

    from redmax_ros.node.main import RedmaxNode, qos_dict, type_name  # optional: rclpy (redmax_ros.node)

    ns = f"/bench_log{os.getpid()}"
    params = {"scene": scene, "mode": "free_run", "real_time_factor": 0.0, "dt": dt, "publish_rate": 0.0,
              "marker_rate": 0.0, "command_timeout": 0.0, "diagnostics_period": 1.0}
    switch = sys.getswitchinterval()
    sys.setswitchinterval(float(os.environ.get("REDMAX_SWITCH_INTERVAL", "0.0005")))  # as redmax_node does
    node = RedmaxNode("redmax", namespace=ns,
                      parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])
    tmp = tempfile.mkdtemp(prefix="redmax_bench_logab_")
    loggers = {"off": None}
    for w in writers:
        lg = McapLogger(os.path.join(tmp, w), scene, writer=w)
        for topic, (cls, qos, *_) in list(node._pubs.items()) + list(node._subs.items()):
            lg.add_topic(topic, type_name(cls), [qos_dict(qos)])
        loggers[w] = lg
    ex = MultiThreadedExecutor(num_threads=4)
    ex.add_node(node)
    stop = threading.Event()

    def spin():
        while not stop.is_set():
            ex.spin_once(timeout_sec=0.2)
    th = threading.Thread(target=spin, daemon=True)
    th.start()
    sub = subprocess.Popen([sys.executable, "-m", "redmax_bench.node", "_raw_subscriber", ns],
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    # "off+stats": not logging, but solver_stats built every step as if someone subscribed
    # (RedmaxNode._stats_forced). Logging records solver_stats, whose KKT residual is computed for
    # it; against this condition the writer's own cost shows, against "off" the whole price of
    # logging.
    loggers["off+stats"] = None
    conds = list(loggers)
    rows = {c: [] for c in conds}
    try:
        _wait_for(lambda: node.pub_js.get_subscription_count() > 0, 30, "the subscriber")
        time.sleep(1.0)
        e = node.engine
        child = loggers["process"]._proc.pid if "process" in loggers else None
        for r in range(rounds):
            order = conds[r % len(conds):] + conds[:r % len(conds)]
            for c in order:
                node.logger_mcap = loggers[c]
                node._stats_forced = c == "off+stats"
                time.sleep(0.3)
                k0, t0, p0 = e.step_index, time.perf_counter(), time.process_time()
                w0 = _cpu_seconds(f"/proc/{child}/stat") if child else 0.0
                time.sleep(window)
                k1, t1, p1 = e.step_index, time.perf_counter(), time.process_time()
                w1 = _cpu_seconds(f"/proc/{child}/stat") if child else 0.0
                n = max(k1 - k0, 1)
                rows[c].append({"steps_per_second": n / (t1 - t0), "process_cpu_us_per_step": 1e6 * (p1 - p0) / n,
                                "writer_process_cpu_us_per_step": 1e6 * (w1 - w0) / n if c == "process" else 0.0,
                                "load": _load()})
    finally:
        node.logger_mcap = None
        node._stats_forced = False
        stop.set()
        th.join(5)
        node.close()
        for lg in loggers.values():
            if lg is not None:
                lg.close()
        _stop(sub)
        node.destroy_node()
        sys.setswitchinterval(switch)
    out = {"scene": scene, "dt": dt, "rounds": rounds, "window_s": window, "conditions": {}}
    for c in conds:
        o = {k: _median([x[k] for x in rows[c]]) for k in rows[c][0]}
        if c != "off":
            ratios = [x["steps_per_second"] / y["steps_per_second"] for x, y in zip(rows[c], rows["off"])]
            o["slowdown"] = 1 - _median(ratios)
            o["slowdown_per_round"] = [round(1 - q, 4) for q in ratios]
            o["extra_process_cpu"] = o["process_cpu_us_per_step"] / out["conditions"]["off"]["process_cpu_us_per_step"] - 1
        if loggers[c] is not None:
            ratios = [x["steps_per_second"] / y["steps_per_second"] for x, y in zip(rows[c], rows["off+stats"])]
            o["slowdown_vs_off_with_stats"] = 1 - _median(ratios)
            o["messages_written"] = loggers[c].written
            o["messages_handed_over"] = loggers[c].handed_over
        o["steps_per_second_per_round"] = [round(x["steps_per_second"]) for x in rows[c]]
        out["conditions"][c] = o
    return out


# ------------------------------------------------------------------------------------------------
# (e) free-run real-time factor under a flood of commands

def _flooder(ns):
    """A joint_commands flooder (run as a subprocess for section (e), so that publishing does not
    compete with this process's clients, nor anything with the node's GIL). Waits for the node's
    subscription and prints 'ready'; then for each line 'valid|invalid RATE SECONDS' on stdin
    publishes at RATE Hz for SECONDS (reliable, keep last 10, as the node's subscription; paced on
    time.monotonic: each message is sent at most 0.2 ms before it is due, the loop sleeps otherwise
    (a pure busy wait took a whole core from the node on the 2-core machine: 100 % vs ~27 % CPU at
    10 kHz, no subscriber), and catches up at most 5 ms when it falls behind) and prints
    'SENT T0 T1' (time.monotonic: CLOCK_MONOTONIC, the same clock in every process)."""
    import rclpy  # optional: rclpy
    from rclpy.node import Node  # optional: rclpy
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy  # optional: rclpy
    from rclpy.serialization import serialize_message  # optional: rclpy
    from sensor_msgs.msg import JointState  # optional: sensor_msgs (ROS)

    rclpy.init()
    node = Node("redmax_bench_flooder", namespace=ns)
    pub = node.create_publisher(JointState, "joint_commands", QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE))
    # valid: the wrist's two DOFs, v = 0.05 sin(2 pi t / 0.5 s) [rad/s] at 10 kHz (pre-serialized, 500 levels); with a
    # 5 s period the wrist drifted 0.6 rad in sim time at RTF 5 and the prescription met its limit (QP infeasible)
    valid = [serialize_message(JointState(name=["wrist[0]", "wrist[1]"],
                                          velocity=[0.05 * math.sin(2 * math.pi * k / 500), 0.0]))
             for k in range(500)]
    invalid = serialize_message(JointState(name=["no_such_joint"], velocity=[1.0]))
    end = time.monotonic() + 60
    while pub.get_subscription_count() == 0 and time.monotonic() < end:
        time.sleep(0.01)
    print("ready", pub.get_subscription_count(), flush=True)
    for line in sys.stdin:
        parts = line.split()
        if not parts or parts[0] == "quit":
            break
        kind, rate, seconds = parts[0], float(parts[1]), float(parts[2])
        period, per_level, lead = 1.0 / rate, max(1, int(rate * 0.5 / 500)), 2e-4
        n = k = 0
        t0 = time.monotonic()
        stop = t0 + seconds
        due = t0
        while True:
            now = time.monotonic()
            if now >= stop:
                break
            if due > now + lead:  # ahead of schedule: sleep (a busy wait would take a core from the node)
                time.sleep(due - now - lead)
                continue
            pub.publish(invalid if kind == "invalid" else valid[(k // per_level) % 500])
            n += 1
            k += 1
            due += period
            if now - due > 5e-3:  # preempted: do not burst to catch up more than 5 ms
                due = now - 5e-3
        t1 = time.monotonic()
        print(n, t0, t1, flush=True)
    node.destroy_node()
    rclpy.shutdown()
    return 0


class _Stamps:
    """Raw joint_states subscription recording (time.monotonic when taken, header stamp [s]) per message:
    the sim time the node had reached at each wall instant, without deserializing. Read by the node's
    own burst reader (node/command_reader.CommandReader, a wait set in a thread, keep last 100) on a node
    of its own rather than by an executor callback per message: at RTF 10 that callback took ~40 % of a
    core of this process, which then competed with the node it measures; taken in bursts (<= 200 a
    second) the wall times are those of the drains, to within 5 ms."""

    def __init__(self, ns, topic):
        from rclpy.node import Node  # optional: rclpy
        from rclpy.qos import QoSProfile, ReliabilityPolicy  # optional: rclpy
        from sensor_msgs.msg import JointState  # optional: sensor_msgs (ROS)
        from redmax_ros.node.command_reader import CommandReader  # optional: rclpy

        self.wall, self.sim = [], []
        node = Node("redmax_bench_stamps", namespace=ns)
        sub = node.create_subscription(JointState, topic, self._cb,
                                       QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE), raw=True)
        self._reader = CommandReader(node, [sub], [self._cb])
        self._reader.start()

    def close(self):
        self._reader.close()

    def _cb(self, data):
        sec, nsec = struct.unpack_from("<iI", data, 4)  # CDR: 4-byte encapsulation, then header.stamp
        self.wall.append(time.monotonic())
        self.sim.append(sec + 1e-9 * nsec)

    def sim_at(self, t):
        """Sim time of the newest message received by wall time t (None before the first)."""
        i = bisect.bisect_right(self.wall, t) - 1
        return self.sim[i] if i >= 0 else None

    def rtf(self, a, b):
        s0, s1 = self.sim_at(a), self.sim_at(b)
        return None if s0 is None or s1 is None or b <= a else (s1 - s0) / (b - a)

    def max_gap(self, a, b):
        """Longest wall interval in [a, b] without a new state (a stall of the stepping)."""
        i, j = bisect.bisect_left(self.wall, a), bisect.bisect_right(self.wall, b)
        ts = [a] + self.wall[i:j] + [b]
        return max(y - x for x, y in zip(ts, ts[1:]))


def _threads_cpu(pid):
    """{tid: (comm, CPU seconds)} of every thread of process pid."""
    out = {}
    tck = os.sysconf("SC_CLK_TCK")
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return out
    for tid in tids:
        try:
            with open(f"/proc/{pid}/task/{tid}/stat") as f:
                s = f.read()
        except OSError:
            continue
        fields = s[s.rindex(")") + 2:].split()
        out[int(tid)] = (s[s.index("(") + 1:s.rindex(")")], (int(fields[11]) + int(fields[12])) / tck)
    return out


class _CpuWindow:
    """CPU % (of one core) of the node process, its threads, the flooder and this process over a window."""

    def __init__(self, node_pid, flooder_pid):
        self.pids = {"node": node_pid, "flooder": flooder_pid, "bench": os.getpid()}
        self.t0 = time.monotonic()
        self.c0 = {k: _cpu_seconds(f"/proc/{p}/stat") for k, p in self.pids.items()}
        self.th0 = _threads_cpu(node_pid)

    def close(self):
        dt = max(time.monotonic() - self.t0, 1e-9)
        c1 = {k: _cpu_seconds(f"/proc/{p}/stat") for k, p in self.pids.items()}
        th1 = _threads_cpu(self.pids["node"])
        out = {f"{k}_cpu_pct": round(100 * (c1[k] - self.c0[k]) / dt, 1) for k in self.pids}
        threads = sorted(((100 * (c - self.th0[t][1]) / dt, t, name) for t, (name, c) in th1.items() if t in self.th0),
                         reverse=True)
        out["node_threads_cpu_pct"] = [{"tid": t, "comm": name, "cpu_pct": round(p, 1)} for p, t, name in threads[:6]
                                       if p >= 0.5]
        return out


def _diag_delta(diags, a, b, key):
    """Increase of a cumulative /diagnostics counter between the last report received by a and the
    last received by b."""
    before = [d for d in diags if d["_t"] <= a]
    after = [d for d in diags if d["_t"] <= b]
    if not before or not after:
        return None
    return int(float(after[-1].get(key, 0))) - int(float(before[-1].get(key, 0)))


def _diag_mean(diags, a, b, key, period):
    """Mean of a per-window /diagnostics value over the reports whose window lies in [a, b]."""
    xs = [float(d[key]) for d in diags if a + period <= d["_t"] <= b and key in d]
    return statistics.fmean(xs) if xs else None


def _param_msg(name, value):
    from rclpy.parameter import Parameter  # optional: rclpy
    return Parameter(name, value=value).to_parameter_msg()


def _flood_window(stamps, diags, cpu, flooder, kind, rate, seconds, post, period):
    """One flood (kind 'valid'/'invalid') of `seconds` at `rate` Hz, then `post` s of quiet; or,
    kind 'none', `seconds` s of quiet (the unflooded reference)."""
    if kind == "none":
        a = time.monotonic()
        w = cpu()
        time.sleep(seconds)
        b = time.monotonic()
        r = {"kind": kind, "t0": a, "t1": b, "rtf": stamps.rtf(a, b), "max_stall_s": stamps.max_gap(a, b),
             "diag_rtf": _diag_mean(diags, a, b, "real_time_factor", period),
             "step_wall_ms": _ms(_diag_mean(diags, a, b, "mean_step_wall_time", period)), **w.close()}
        return r
    w = cpu()
    flooder.stdin.write(f"{kind} {rate} {seconds}\n")
    flooder.stdin.flush()
    line = flooder.stdout.readline().split()
    if len(line) != 3:
        raise RuntimeError(f"the flooder did not answer: {line}")
    sent, a, b = int(line[0]), float(line[1]), float(line[2])
    load = w.close()
    w2 = cpu()
    time.sleep(max(0.0, b + post - time.monotonic()) + 0.05)
    after = w2.close()
    bins = [stamps.rtf(a + 0.5 * i, a + 0.5 * (i + 1)) for i in range(int(round((b - a + post) / 0.5)))]
    return {"kind": kind, "t0": a, "t1": b, "sent": sent, "rate_hz": sent / (b - a),
            "rtf": stamps.rtf(a, b), "rtf_last_2s": stamps.rtf(b - 2.0, b), "rtf_post": stamps.rtf(b, b + post),
            "max_stall_s": stamps.max_gap(a, b + post),
            "diag_rtf": _diag_mean(diags, a, b, "real_time_factor", period),
            "diag_rtf_post": _diag_mean(diags, b, b + post, "real_time_factor", period),
            "step_wall_ms": _ms(_diag_mean(diags, a, b, "mean_step_wall_time", period)),
            "commands_received": _diag_delta(diags, a, b + post, "commands_received"),
            "commands_coalesced": _diag_delta(diags, a, b + post, "commands_coalesced"),
            "command_errors": _diag_delta(diags, a, b + post, "command_errors"),
            "rtf_bins_0.5s": [None if x is None else round(x, 3) for x in bins], **load,
            "post_cpu": after}


def _ms(x):
    return None if x is None else 1e3 * x


def bench_flood(scene, dt, rate, seconds, post, quiet, rounds_by_rtf):
    """Free-run RTF of one node subprocess under floods of valid and invalid joint_commands from a
    flooder process, interleaved with unflooded windows (none, valid, invalid per round), at each
    real_time_factor in rounds_by_rtf ({rtf: rounds}, set at run time through the parameter
    service)."""
    from rclpy.node import Node  # optional: rclpy
    from rcl_interfaces.srv import SetParameters  # optional: rcl_interfaces (ROS)

    ns = f"/bench_flood{os.getpid()}"
    period = 0.5
    t_start = time.monotonic()
    phases = {}
    first_rtf = next(iter(rounds_by_rtf))
    proc = _start_node(ns, {"scene": scene, "mode": "free_run", "real_time_factor": float(first_rtf), "dt": dt,
                            "publish_rate": 0.0, "marker_rate": 0.0, "diagnostics_period": period})
    flooder = subprocess.Popen([sys.executable, "-m", "redmax_bench.node", "_flooder", ns], stdin=subprocess.PIPE,
                               stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    node = Node("redmax_bench_flood", namespace=ns)
    stamps = _Stamps(ns, "joint_states")
    diags = _diag_listener(node, ns, stamp=True)
    setp = node.create_client(SetParameters, "redmax/set_parameters")
    spin = _Spinner(node)
    out = {"scene": scene, "dt": dt, "target_rate_hz": rate, "flood_s": seconds, "post_s": post, "quiet_s": quiet,
           "node_params": {"mode": "free_run", "publish_rate": 0.0, "command_timeout": "default (0.5 s sim)"},
           "by_rtf": []}
    try:
        _wait_for(lambda: len(diags) > 0 and len(stamps.wall) > 0, 60, "the node")
        ready = flooder.stdout.readline().split()
        if not ready or ready[0] != "ready":
            raise RuntimeError(f"the flooder did not start: {ready}")
        phases["start_up"] = time.monotonic() - t_start

        def cpu():
            return _CpuWindow(proc.pid, flooder.pid)

        for rtf, rounds in rounds_by_rtf.items():
            if rtf != first_rtf:
                assert setp.wait_for_service(timeout_sec=10), "no parameter service"
                fut = setp.call_async(SetParameters.Request(parameters=[_param_msg("real_time_factor", float(rtf))]))
                _wait_for(fut.done, 10, "set_parameters")
                assert fut.result().results[0].successful, fut.result().results[0].reason
            time.sleep(1.0 if rtf != first_rtf else 0.5)
            runs = []
            for r in range(rounds):
                for kind in ("none", "valid", "invalid"):
                    length = quiet if kind == "none" else seconds
                    runs.append(dict(_flood_window(stamps, diags, cpu, flooder, kind, rate, length, post, period),
                                     round=r, load=_load()))
                if proc.poll() is not None:
                    raise RuntimeError(f"the node exited: {_stderr_tail(proc)}")
            out["by_rtf"].append(_flood_summary(rtf, runs))
        phases["measuring"] = time.monotonic() - t_start - phases["start_up"]
    finally:
        try:
            flooder.stdin.write("quit\n")
            flooder.stdin.flush()
            flooder.wait(10)
        except (OSError, ValueError, subprocess.TimeoutExpired):
            flooder.kill()
        spin.close()
        stamps.close()
        node.destroy_node()
        _stop(proc)
    out["wall_s"] = {**{k: round(v, 2) for k, v in phases.items()}, "total": round(time.monotonic() - t_start, 2)}
    return out


def _flood_summary(rtf, runs):
    by = {k: [x for x in runs if x["kind"] == k] for k in ("none", "valid", "invalid")}
    none = by["none"]
    s = {"real_time_factor": rtf, "rounds": len(none), "conditions": {}, "runs": runs}
    for kind, rs in by.items():
        c = {"rtf": _median([x["rtf"] for x in rs]), "diag_rtf": _median([x["diag_rtf"] for x in rs]),
             "per_round_rtf": [None if x["rtf"] is None else round(x["rtf"], 3) for x in rs],
             "max_stall_s": max((x["max_stall_s"] for x in rs), default=None),
             "step_wall_ms": _median([x["step_wall_ms"] for x in rs]),
             "node_cpu_pct": _median([x["node_cpu_pct"] for x in rs]),
             "flooder_cpu_pct": _median([x["flooder_cpu_pct"] for x in rs]),
             "bench_cpu_pct": _median([x["bench_cpu_pct"] for x in rs]), "load": _median([x["load"] for x in rs])}
        if kind != "none":
            ratios = [x["rtf"] / n["rtf"] for x, n in zip(rs, none) if x["rtf"] is not None and n["rtf"]]
            post = [x["rtf_post"] / n["rtf"] for x, n in zip(rs, none) if x["rtf_post"] is not None and n["rtf"]]
            c.update({"ratio": _median(ratios), "per_round_ratio": [round(q, 3) for q in ratios],
                      "rtf_last_2s": _median([x["rtf_last_2s"] for x in rs]),
                      "rtf_post": _median([x["rtf_post"] for x in rs]), "post_ratio": _median(post),
                      "diag_rtf_post": _median([x["diag_rtf_post"] for x in rs]),
                      "rate_hz": _median([x["rate_hz"] for x in rs]),
                      "commands_received": _median([x["commands_received"] for x in rs]),
                      "commands_coalesced": _median([x["commands_coalesced"] for x in rs]),
                      "command_errors": _median([x["command_errors"] for x in rs]),
                      "sent": _median([x["sent"] for x in rs]),
                      "rtf_bins_0.5s_median": [_median([x["rtf_bins_0.5s"][i] for x in rs
                                                        if i < len(x["rtf_bins_0.5s"])])
                                               for i in range(max(len(x["rtf_bins_0.5s"]) for x in rs))]})
        threads = {}
        for x in rs:
            for t in x["node_threads_cpu_pct"]:
                threads.setdefault((t["tid"], t["comm"]), []).append(t["cpu_pct"])
        c["node_threads_cpu_pct"] = sorted(({"tid": t, "comm": n, "cpu_pct": _median(v)}
                                            for (t, n), v in threads.items()), key=lambda d: -d["cpu_pct"])[:5]
        s["conditions"][kind] = c
    # the simulation thread: the busiest one without a flood (Python threads are all named "python")
    busiest = s["conditions"]["none"]["node_threads_cpu_pct"]
    s["simulation_thread_tid"] = busiest[0]["tid"] if busiest else None
    return s


def _print_flood(res):
    print(f"    target {res['target_rate_hz']:g} Hz, {res['flood_s']:g} s floods, RTF also in the {res['post_s']:g} s "
          f"after each; unflooded windows {res['quiet_s']:g} s; RTF = sim-time advance / wall time from joint_states "
          "stamps (diag = mean of the node's /diagnostics windows); medians over rounds")
    head = (f"      {'condition':9s} {'sent/s':>7s} {'RTF':>6s} {'(diag)':>7s} {'ratio':>6s} {'last2s':>6s} "
            f"{'after':>6s} {'ratio':>6s} {'stall s':>7s} {'recv':>6s} {'coalesc':>7s} {'errors':>6s} "
            f"{'step ms':>7s} {'CPU% node/flooder/bench':>23s} {'load':>5s}")
    for b in res["by_rtf"]:
        paced = "paced" if b["real_time_factor"] else "as fast as possible"
        print(f"    real_time_factor {b['real_time_factor']:g} ({paced}), {b['rounds']} rounds:")
        print(head)
        for kind, c in b["conditions"].items():
            g = (lambda k, d=3: _f(c.get(k), d)) if kind != "none" else (lambda k, d=3: "-")
            cpu = f"{_f(c['node_cpu_pct'], 0)}/{_f(c['flooder_cpu_pct'], 0)}/{_f(c['bench_cpu_pct'], 0)}"
            print(f"      {kind:9s} {g('rate_hz', 0):>7s} {_f(c['rtf'], 3):>6s} {'(' + _f(c['diag_rtf'], 3) + ')':>7s} "
                  f"{g('ratio'):>6s} {g('rtf_last_2s'):>6s} {g('rtf_post'):>6s} {g('post_ratio'):>6s} "
                  f"{_f(c['max_stall_s'], 3):>7s} {g('commands_received', 0):>6s} {g('commands_coalesced', 0):>7s} "
                  f"{g('command_errors', 0):>6s} {_f(c['step_wall_ms'], 3):>7s} {cpu:>23s} {_f(c['load']):>5s}")
        for kind in ("valid", "invalid"):
            c = b["conditions"][kind]
            print(f"      {kind:7s}: per-round ratio {', '.join(_f(q, 3) for q in c['per_round_ratio'])}; RTF per 0.5 s "
                  f"from flood start: {' '.join(_f(x, 2) for x in c['rtf_bins_0.5s_median'])}")
        sim = b["simulation_thread_tid"]
        for kind, c in b["conditions"].items():
            print(f"      {kind:7s}: node threads CPU%: " + ", ".join(
                f"{'simulation' if t['tid'] == sim else t['comm']}[{t['tid']}] {t['cpu_pct']:.0f}"
                for t in c["node_threads_cpu_pct"]))
    print(f"    section wall time [s]: {res.get('wall_s')}")


# ------------------------------------------------------------------------------------------------
# (f) query latency: idle, during a long step request, in free-run

class _Caller:
    """Service clients of one node, called from this thread: it spins its own executor until the
    answer (as _StepClient)."""

    def __init__(self, ns, name):
        from rclpy.node import Node  # optional: rclpy

        self.node = Node(name, namespace=ns)
        self.ex = _executor()
        self.ex.add_node(self.node)

    def client(self, srv, name):
        return self.node.create_client(srv, name)

    def call(self, cli, req, timeout=10.0):
        """(response or None on timeout, seconds)."""
        t0 = time.perf_counter()
        fut = cli.call_async(req)
        self.ex.spin_until_future_complete(fut, timeout_sec=timeout)
        dt = time.perf_counter() - t0
        if not fut.done():
            cli.remove_pending_request(fut)
            return None, dt
        return fut.result(), dt

    def close(self):
        try:
            self.ex.remove_node(self.node)
            self.ex.shutdown()
        except Exception:
            pass
        self.node.destroy_node()


def _lat_stats(xs):
    xs = sorted(xs)
    if not xs:
        return {"n": 0, "median_ms": None, "p95_ms": None, "max_ms": None}
    return {"n": len(xs), "median_ms": 1e3 * statistics.median(xs), "p95_ms": 1e3 * xs[int(0.95 * (len(xs) - 1))],
            "max_ms": 1e3 * xs[-1]}


def bench_query(scene, dt, calls, rounds, long_steps, gap):
    """Latency of get_simulation_state, describe_scene and a parameter get on one node subprocess:
    (i) idle lockstep, (ii) while step_simulation(long_steps) runs (lockstep), (iii) free-run as fast
    as possible; `calls` calls per query and condition per round, round-robin over the queries,
    `gap` s apart, the conditions interleaved per round."""
    from rclpy.node import Node  # optional: rclpy
    from rcl_interfaces.srv import GetParameters  # optional: rcl_interfaces (ROS)
    from redmax_msgs.msg import SimulationState  # optional: redmax_msgs (ROS)
    from redmax_msgs.srv import DescribeScene, GetSimulationState  # optional: redmax_msgs (ROS)
    from redmax_msgs.srv import SetSimulationState, StepSimulation  # optional: redmax_msgs (ROS)

    ns = f"/bench_query{os.getpid()}"
    proc = _start_node(ns, {"scene": scene, "mode": "lockstep", "real_time_factor": 0.0, "dt": dt,
                            "publish_rate": 0.0, "marker_rate": 0.0, "command_timeout": 0.0})
    q = _Caller(ns, "redmax_bench_query")
    queries = {"get_simulation_state": (q.client(GetSimulationState, "get_simulation_state"),
                                        GetSimulationState.Request()),
               "describe_scene": (q.client(DescribeScene, "describe_scene"), DescribeScene.Request()),
               "get_parameters": (q.client(GetParameters, "redmax/get_parameters"),
                                  GetParameters.Request(names=["real_time_factor", "dt"]))}
    set_state = q.client(SetSimulationState, "set_simulation_state")
    step_node = Node("redmax_bench_long_step", namespace=ns)
    step_cli = step_node.create_client(StepSimulation, "step_simulation")
    spin = _Spinner(step_node)
    conds = ("idle_lockstep", "during_step", "free_run")
    lat = {c: {k: [] for k in queries} for c in conds}
    extra = {"timeouts": {c: 0 for c in conds}, "answered_while_step_ran": 0, "queries_during_step": 0,
             "long_steps": [], "wrong_results": 0}
    state = {"fut": None, "t0": None}

    def start_step():
        state["t0"] = time.monotonic()
        state["fut"] = step_cli.call_async(StepSimulation.Request(steps=long_steps))
        time.sleep(0.2)  # let it reach the node and start

    def finish_step(wait=True):
        fut = state["fut"]
        if fut is None:
            return
        if wait:
            _wait_for(fut.done, 300, "the long step request")
        if fut.done():
            r = fut.result()
            extra["long_steps"].append({"result": int(r.result.result), "completed_steps": int(r.completed_steps),
                                        "wall_s": round(state.get("t_done", time.monotonic()) - state["t0"], 3)})
        state["fut"] = None

    def on_done(_fut):
        state["t_done"] = time.monotonic()

    def set_sim_state(s):
        r, _ = q.call(set_state, SetSimulationState.Request(state=SimulationState(state=s)))
        assert r is not None and r.result.result in (1, 101), "set_simulation_state failed"

    try:
        for cli, _ in queries.values():
            assert cli.wait_for_service(timeout_sec=60), "the node did not come up"
        assert step_cli.wait_for_service(timeout_sec=30) and set_state.wait_for_service(timeout_sec=30)
        for cli, req in queries.values():  # warm-up (first-call costs, discovery)
            for _ in range(5):
                q.call(cli, req)
        for r in range(rounds):
            for c in (conds if r % 2 == 0 else conds[::-1]):
                if c == "free_run":
                    set_sim_state(1)  # PLAYING
                    time.sleep(0.5)
                for i in range(calls * len(queries)):
                    key = list(queries)[i % len(queries)]
                    cli, req = queries[key]
                    if c == "during_step":
                        if state["fut"] is None or state["fut"].done():
                            finish_step(wait=False)
                            state.pop("t_done", None)
                            start_step()
                            state["fut"].add_done_callback(on_done)
                    resp, t = q.call(cli, req)
                    if resp is None:
                        extra["timeouts"][c] += 1
                        continue
                    if c == "during_step":
                        extra["queries_during_step"] += 1
                        extra["answered_while_step_ran"] += not state["fut"].done()
                    if key != "get_parameters" and resp.result.result != 1:
                        extra["wrong_results"] += 1
                    lat[c][key].append(t)
                    time.sleep(gap)
                if c == "during_step":
                    finish_step()
                if c == "free_run":
                    set_sim_state(2)  # PAUSED
                    time.sleep(0.2)
            if proc.poll() is not None:
                raise RuntimeError(f"the node exited: {_stderr_tail(proc)}")
        load = _load()
    finally:
        spin.close()
        step_node.destroy_node()
        q.close()
        _stop(proc)
    return {"scene": scene, "dt": dt, "calls_per_round": calls, "rounds": rounds, "long_step_request": long_steps,
            "gap_s": gap, "latency": {c: {k: _lat_stats(v) for k, v in d.items()} for c, d in lat.items()},
            "all_ms": {c: {k: [round(1e3 * x, 3) for x in v] for k, v in d.items()} for c, d in lat.items()},
            **extra, "load": load}


def _print_query(r):
    print(f"    {'condition':14s} {'query':22s} {'n':>4s} {'median':>8s} {'p95':>8s} {'max':>8s}  [ms]")
    for c, d in r["latency"].items():
        for k, s in d.items():
            print(f"    {c:14s} {k:22s} {s['n']:4d} {_f(s['median_ms'], 2):>8s} {_f(s['p95_ms'], 2):>8s} "
                  f"{_f(s['max_ms'], 2):>8s}")
    ls = r["long_steps"]
    print(f"    long step_simulation({r['long_step_request']}) requests: {len(ls)}, wall "
          f"{', '.join(_f(x['wall_s'], 2) for x in ls)} s, results {sorted({x['result'] for x in ls})}; "
          f"{r['answered_while_step_ran']}/{r['queries_during_step']} queries answered while it ran; "
          f"timeouts {r['timeouts']}; load {r['load']}")


# ------------------------------------------------------------------------------------------------

def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="redmax_bench node", description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="+", default=["hand", "klann_leg"])
    ap.add_argument("--dt", type=float, default=0.001)
    ap.add_argument("--latency-samples", type=int, default=200)
    ap.add_argument("--service-steps", type=int, default=100, help="calls per block in (b)")
    ap.add_argument("--service-rounds", type=int, default=7, help="interleaved blocks in (b)")
    ap.add_argument("--seconds", type=float, default=5.0, help="free-run duration per RTF run in (c)")
    ap.add_argument("--rtf-rounds", type=int, default=5, help="runs per scene and logging setting in (c)")
    ap.add_argument("--log-rounds", type=int, default=12, help="rounds of windows in (d)")
    ap.add_argument("--log-window", type=float, default=1.5, help="window length [s] in (d)")
    ap.add_argument("--flood-rate", type=float, default=10000.0, help="commands/s of the flooder in (e)")
    ap.add_argument("--flood-seconds", type=float, default=5.0, help="length of each flood in (e)")
    ap.add_argument("--flood-post", type=float, default=3.0, help="seconds measured after each flood in (e)")
    ap.add_argument("--flood-quiet", type=float, default=1.5, help="length of each unflooded window in (e)")
    ap.add_argument("--flood-rounds", type=int, default=3,
                    help="rounds (none, valid, invalid) at real_time_factor 0 in (e)")
    ap.add_argument("--flood-paced-rounds", type=int, default=2,
                    help="rounds at real_time_factor 1 in (e) (0: skip; 2 keeps the section under ~90 s)")
    ap.add_argument("--query-calls", type=int, default=20, help="calls per query, condition and round in (f)")
    ap.add_argument("--query-rounds", type=int, default=3, help="interleaved rounds in (f)")
    ap.add_argument("--query-long-steps", type=int, default=20000, help="steps of the long request in (f)")
    ap.add_argument("--only", nargs="+", choices=["latency", "service", "rtf", "logging", "flood", "query"],
                    help="run only these sections (node.json then keeps the other sections of an earlier run)")
    ap.add_argument("--quick", action="store_true", help="small sample counts (smoke run)")
    ap.add_argument("--no-write", action="store_true", help="do not write node.json")
    add_out_argument(ap)
    a = ap.parse_args(argv)
    if a.quick:
        a.latency_samples, a.service_steps, a.service_rounds = 30, 50, 2
        a.seconds, a.rtf_rounds, a.log_rounds, a.log_window = 3.0, 1, 2, 1.0
        a.flood_seconds, a.flood_post, a.flood_quiet, a.flood_rounds, a.flood_paced_rounds = 2.0, 1.0, 1.0, 1, 1
        a.query_calls, a.query_rounds, a.query_long_steps = 10, 1, 5000
    want = set(a.only or ["latency", "service", "rtf", "logging", "flood", "query"])

    import rclpy  # optional: rclpy
    rclpy.init()
    out = {"load_at_start": list(os.getloadavg()), "cpus": os.cpu_count()}
    try:
        if "latency" in want:
            print(f"(a) command-to-state latency, free-run 1 kHz, {a.latency_samples} commands")
            r = bench_latency("hand", a.latency_samples, a.dt)
            out["latency"] = [r]
            print(f"    hand: median {r['median_ms']:.2f} ms, p95 {r['p95_ms']:.2f} ms, max {r['max_ms']:.2f} ms "
                  f"({r['samples']}/{r['requested']}), load {r['load']}")
        if "service" in want:
            print(f"(b) lockstep step_simulation(steps=1) round trip vs in-process core step and the rclpy floor, "
                  f"{a.service_rounds} x {a.service_steps} calls")
            out["step_service"] = []
            for sc in a.scenes:
                r = bench_step_service(sc, a.service_steps, a.dt, a.service_rounds)
                out["step_service"].append(r)
                f = r["floor_round_trip_ms"]
                print(f"    {sc}: core {r['core_step_ms']:.3f} ms, service {r['service_round_trip_ms']:.3f} ms, "
                      f"overhead {r['overhead_ms']:.3f} ms/step (x{r['overhead_ratio']:.2f}); do-nothing service "
                      f"{f['step_server']:.3f} ms (StepServer), {f['events_executor']:.3f} ms (EventsExecutor), "
                      f"{f['multi_threaded_executor']:.3f} ms (MultiThreadedExecutor); node - StepServer floor "
                      f"{r['node_minus_step_server_floor_ms']:.3f} ms; load {r['load']}")
                b = r["best_ms"]
                print(f"      best blocks: core {b['core']:.3f}, service {b['node']:.3f}, overhead "
                      f"{r['overhead_best_ms']:.3f} ms/step; StepServer floor {b['floor_raw']:.3f}, EventsExecutor "
                      f"{b['floor_events']:.3f} ms")
        if "rtf" in want:
            print(f"(c) free-run real-time factor (as fast as possible), h = {a.dt:g} s, joint_states every step, "
                  f"{a.rtf_rounds} runs each, logging off/on alternated")
            out["free_run"], out["logging_slowdown"] = [], {}
            for sc in a.scenes:
                rs, slow = bench_rtf(sc, a.seconds, a.dt, a.rtf_rounds)
                out["free_run"] += rs
                out["logging_slowdown"][sc] = slow
                for r in rs:
                    print(f"    {sc:10s} logging {'on ' if r['logging'] else 'off'}: RTF {_f(r['real_time_factor'])} "
                          f"({_f(r['steps_per_second'], 0)} steps/s; runs {', '.join(_f(x) for x in r['per_run_rtf'])}), "
                          f"max log backlog {r['max_log_backlog']}, load {r['load']}")
                if slow is not None:
                    best = rs[1].get("slowdown_best_vs_best")
                    print(f"    {sc}: logging slows free-run by {100 * slow:.1f} % (median of paired runs)"
                          + (f", {100 * best:.1f} % best run vs best run (RTF {rs[0]['best_real_time_factor']:.2f} / "
                             f"{rs[1]['best_real_time_factor']:.2f})" if best is not None else ""))
        if "logging" in want:
            print(f"(d) logging cost in one process (hand), {a.log_rounds} rounds of {a.log_window:g} s windows: "
                  "off / writer process / writer thread / off with solver_stats built")
            print("    (the MCAP writer is the same in both logging conditions; writer CPU = the writer process's)")
            r = bench_logging_inprocess("hand", a.dt, a.log_rounds, a.log_window)
            out["logging_inprocess"] = r
            off = r["conditions"]["off"]
            for c, o in r["conditions"].items():
                extra = "" if c == "off" else (f", slowdown {100 * o['slowdown']:.1f} %, process CPU "
                                               f"{100 * o['extra_process_cpu']:+.1f} %")
                if "slowdown_vs_off_with_stats" in o:
                    extra += f" (vs off+stats: slowdown {100 * o['slowdown_vs_off_with_stats']:.1f} %)"
                print(f"    {c:8s}: {o['steps_per_second']:.0f} steps/s, process CPU {o['process_cpu_us_per_step']:.0f} "
                      f"us/step (writer process {o['writer_process_cpu_us_per_step']:.0f}){extra}, load {o['load']}")
            del off
        if "flood" in want:
            print(f"(e) free-run real-time factor under a flood of joint_commands from another process (hand, "
                  f"h = {a.dt:g} s, joint_states every step): none / valid / invalid interleaved per round")
            rounds = {0.0: a.flood_rounds}
            if a.flood_paced_rounds:
                rounds[1.0] = a.flood_paced_rounds
            r = bench_flood("hand", a.dt, a.flood_rate, a.flood_seconds, a.flood_post, a.flood_quiet, rounds)
            out["flood"] = r
            _print_flood(r)
        if "query" in want:
            print(f"(f) query latency (hand, h = {a.dt:g} s): idle lockstep / during step_simulation("
                  f"{a.query_long_steps}) / free-run as fast as possible, {a.query_rounds} rounds x "
                  f"{a.query_calls} calls per query, interleaved")
            r = bench_query("hand", a.dt, a.query_calls, a.query_rounds, a.query_long_steps, 0.005)
            out["query"] = r
            _print_query(r)
    finally:
        rclpy.shutdown()
    out["load_at_end"] = list(os.getloadavg())
    if not a.no_write:
        payload = {"args": {**vars(a), "out": None if a.out is None else str(a.out)}, **out}
        if a.only:  # keep the sections of an earlier run that this one did not repeat
            try:
                old = json.loads((results_dir(a.out) / "node.json").read_text())
            except (OSError, ValueError):
                old = {}
            payload = {**{k: v for k, v in old.items() if k not in ("machine", "date")}, **payload}
        p = write_json(a.out, "node", payload)
        print(f"wrote {p}")
    return 0


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "_floor_server":
        sys.exit(_floor_server(sys.argv[2], sys.argv[3]))
    if len(sys.argv) > 1 and sys.argv[1] == "_raw_subscriber":
        sys.exit(_raw_subscriber(sys.argv[2]))
    if len(sys.argv) > 1 and sys.argv[1] == "_flooder":
        sys.exit(_flooder(sys.argv[2]))
    sys.exit(main())
