"""redmax_bench node: the ROS node's latency, per-step service overhead, real-time factor and the
cost of MCAP logging.

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

Writes node.json into --out (default bench/results under the current directory).

The ROS parts (rclpy, the message packages and redmax_ros.node, which needs rclpy) are imported
inside the functions that use them: they are optional for the benchmark package (every other
subcommand runs without ROS).
"""
from __future__ import annotations

import argparse
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
from redmax_bench.common import add_out_argument, write_json

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

def _diag_listener(node, ns):
    from diagnostic_msgs.msg import DiagnosticArray  # optional: diagnostic_msgs (ROS)

    out = []

    def cb(m):
        if m.status and m.status[0].name.startswith(ns + "/"):  # not another simulation on this graph
            out.append({kv.key: kv.value for kv in m.status[0].values})
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
    ap.add_argument("--only", nargs="+", choices=["latency", "service", "rtf", "logging"],
                    help="run only these sections")
    ap.add_argument("--quick", action="store_true", help="small sample counts (smoke run)")
    ap.add_argument("--no-write", action="store_true", help="do not write node.json")
    add_out_argument(ap)
    a = ap.parse_args(argv)
    if a.quick:
        a.latency_samples, a.service_steps, a.service_rounds = 30, 50, 2
        a.seconds, a.rtf_rounds, a.log_rounds, a.log_window = 3.0, 1, 2, 1.0
    want = set(a.only or ["latency", "service", "rtf", "logging"])

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
    finally:
        rclpy.shutdown()
    out["load_at_end"] = list(os.getloadavg())
    if not a.no_write:
        p = write_json(a.out, "node", {"args": {**vars(a), "out": None if a.out is None else str(a.out)}, **out})
        print(f"wrote {p}")
    return 0


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "_floor_server":
        sys.exit(_floor_server(sys.argv[2], sys.argv[3]))
    if len(sys.argv) > 1 and sys.argv[1] == "_raw_subscriber":
        sys.exit(_raw_subscriber(sys.argv[2]))
    sys.exit(main())
