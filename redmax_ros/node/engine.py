"""The simulation thread: owns the core Simulator, orders commands and requests, paces free-run.

No ROS here. Everything that touches the Simulator runs on one thread, in the order requests
were handed in (a FIFO job queue), so

* a command received before a step request is applied in that step;
* the state handed to the sink after step k is exactly the core's StepResult of step k;
* in lockstep the same sequence of commands and step requests gives bitwise-identical states.

Jobs that arrive while a multi-step request runs wait until it finishes (they are applied at a
deterministic step).

Commands (joint_commands, joint_trajectory, point_commands, body_commands) are validated in the thread that
receives them, against the scene description, and coalesced: the latest value per joint, torque, site and
body waits in a pending table, and one queued job (never more) applies the whole table before the next step
or request. A flood of commands therefore costs the stepping thread one table per step, whatever the rate;
invalid ones never reach it. The counts are in /diagnostics (commands_received, commands_coalesced,
command_errors). The node (``main.py``) translates ROS messages into calls on this class and
implements the ``sink`` that publishes and logs what the engine produces.

Simulation states follow ROS 2 ``simulation_interfaces``: STOPPED (paused and reset), PLAYING
(free-run paced at ``real_time_factor``, 0 = as fast as possible), PAUSED (steps only on request).
"""
from __future__ import annotations

import collections
import threading
import time
from concurrent.futures import Future
from dataclasses import dataclass, field, replace

import numpy as np

from redmax_ros.core import CommandError, SceneError, SceneNotFound, Simulator, StepBudget, StepError

from .convert import (CommandRejected, SceneInfo, TrajectoryCommand, body_command, joint_command, joint_trajectory,
                      point_command)
from .pacing import Pacer, RateMeter, decimation

# simulation_interfaces/msg/Result codes
FEATURE_UNSUPPORTED, OK, NOT_FOUND, INCORRECT_STATE, OPERATION_FAILED = 0, 1, 2, 3, 4
# SetSimulationState extended codes
ALREADY_IN_TARGET_STATE, STATE_TRANSITION_ERROR, INCORRECT_TRANSITION = 101, 102, 103
# LoadScene extended code
INVALID_SCENE = 101
# simulation_interfaces/msg/SimulationState
STOPPED, PLAYING, PAUSED, QUITTING = 0, 1, 2, 3
STATE_NAMES = {STOPPED: "stopped", PLAYING: "playing", PAUSED: "paused", QUITTING: "quitting"}
# ResetSimulation scopes
SCOPE_DEFAULT, SCOPE_TIME, SCOPE_STATE, SCOPE_SPAWNED, SCOPE_ALL = 0, 1, 2, 4, 255


@dataclass
class Outcome:
    code: int = OK
    message: str = ""
    steps: int = 0
    t: float = 0.0
    extra: dict = field(default_factory=dict)

    @property
    def ok(self):
        return self.code == OK


class NullSink:
    """What the engine reports to; the node overrides every method."""

    def scene_loaded(self, info: SceneInfo): ...
    def state(self, t, q, v, effort, site_forces, diag, step_index, body_wrenches): ...

    def run_states(self, results, first_index, body_wrenches):
        """The StepResults of a recorded run, step indices from ``first_index``: ``state`` for each
        (``body_wrenches(result)`` its last argument); the node overrides it to do its per-call work once
        a run."""
        for i, r in enumerate(results, first_index):
            self.state(r.t, r.q, r.v, r.effort, r.site_forces, r.diagnostics, i, body_wrenches(r))

    def markers(self, t, poses, springs, meshes=None, contacts=None, shapes=None): ...
    def vertices(self, t, positions): ...
    def frames(self, t, sim): ...
    def robot_model(self, sim): ...
    def status(self, text: str): ...
    def diagnostics(self, values: dict, ok: bool, message: str): ...
    def sim_state(self, state: int): ...
    def prescriptions(self, t, joints: dict, sites: dict, bodies: dict): ...
    def command_error(self, text: str): ...
    def warn(self, text: str): ...
    def quit(self): ...


RUN_WALL = 0.01  # [s wall] a run of steps in _advance aims at about this long (cancel and shutdown latency)
RUN_CAP_MAX = 4096  # steps in one run at most


def _next_cap(cap: int, k: int, wall: float) -> int:
    """The run cap after a run of k steps took ``wall`` seconds: doubled while runs at the cap stay under
    RUN_WALL / 2, halved when a run took over 2 RUN_WALL (a scene or state whose steps got dearer)."""
    if wall > 2 * RUN_WALL:
        return max(1, cap // 2)
    if k >= cap and wall < RUN_WALL / 2:
        return min(RUN_CAP_MAX, 2 * cap)
    return cap


class Engine:
    def __init__(self, sink, scene="hand", overrides=(), *, initial_state=PLAYING, real_time_factor=1.0,
                 publish_rate=0.0, marker_rate=0.0, command_timeout=0.0, diagnostics_period=1.0,
                 max_steps_per_request=1_000_000, publish_solver_stats=True, scene_dirs=(), step_budget_ms=50.0,
                 tf_rate=0.0, status_period=0.0, position_gain=5.0):
        self.sink = sink
        self.base_overrides = list(overrides)
        self.scene_dirs = [str(d) for d in scene_dirs]  # load requests: scenes/ and these only (_load_scene)
        self.rtf = float(real_time_factor)
        self.publish_rate = float(publish_rate)
        self.marker_rate = float(marker_rate)
        self.tf_rate = float(tf_rate)  # body frames (sink.frames: /tf, odom) in Hz of sim time; 0 = off
        self.status_period = float(status_period)  # wall seconds between free-run status lines; 0 = off
        self.position_gain = float(position_gain)  # b [1/s] of position targets and trajectories
        self.command_timeout = float(command_timeout)
        self.diagnostics_period = float(diagnostics_period)
        self.max_steps_per_request = int(max_steps_per_request)
        self.step_budget = StepBudget.from_ms(step_budget_ms)  # every scene's steps (_adopt); None: unlimited
        self.state = initial_state
        self.sim = self._load(scene, [])  # raises SceneError: the node refuses to start
        self._jobs = collections.deque()
        self._cv = threading.Condition()
        self._running = False
        self._busy = False  # a thread (simulation or caller) is using the Simulator
        self._sim_waiting = False  # the simulation thread waits for _busy to clear
        self._thread = None
        self.pacer = Pacer(self.rtf)
        self.meter = RateMeter()
        self._status_mark = None  # (wall time, sim time, step index, failures) of the last status line
        self.last_diag = None
        self.failures = 0
        self.command_errors = 0
        self.commands_received = 0
        self.commands_coalesced = 0
        self._pending_lock = threading.Lock()
        self._batch = None  # the open batch of pending commands: ("joint" | "torque" | "site" | "body", name) -> value
        self._batch_job = False  # a queued job will apply the open batch
        self._run_cap = 1  # steps a run may take (_advance, _next_cap)
        self._adopt(self.sim)

    # ------------------------------------------------------------------ thread and job queue
    def start(self):
        self._running = True
        self.pacer.anchor(self.sim.time)
        self.meter.reset(self.sim.time)
        self._thread = threading.Thread(target=self._loop, name="redmax-sim", daemon=True)
        self._thread.start()

    def stop(self, timeout=10.0):
        with self._cv:
            self._running = False
            self._cv.notify_all()
        if self._thread is not None:
            self._thread.join(timeout)

    def submit(self, fn, *args) -> Future:
        """Run ``fn(*args)`` after everything submitted before it, with exclusive use of the
        Simulator. If nothing is queued and the simulation is not busy (paused, or between two
        free-run steps), the calling thread runs it at once (no thread hop, lower latency);
        otherwise it is queued for the simulation thread. Either way requests keep their order."""
        if fn != self._apply_batch:
            self._close_batch()  # commands that arrive from now on are applied after this request
        fut = Future()
        with self._cv:
            if not self._running:
                fut.set_exception(RuntimeError("the simulation thread is not running"))
                return fut
            if self._jobs or self._busy:
                self._jobs.append((fut, fn, args))
                self._cv.notify_all()
                return fut
            self._busy = True
        try:
            self._run_job(fut, fn, args)
        finally:
            self._end_inline()
        return fut

    def _end_inline(self):
        """End of an inline request: wake the simulation thread only if it has something to do
        (it waits for the Simulator, is playing, or jobs are queued). A paused simulation thread
        sleeps on: waking it after every lockstep request costs a GIL hand-over each time."""
        with self._cv:
            self._busy = False
            if self._sim_waiting or self._jobs or self.state == PLAYING or not self._running:
                self._cv.notify_all()

    @staticmethod
    def _run_job(fut, fn, args):
        if fut.set_running_or_notify_cancel():
            try:
                fut.set_result(fn(*args))
            except BaseException as e:  # reported to the caller; the simulation lives on
                fut.set_exception(e)

    def call(self, fn, *args, timeout=None):
        """``submit(fn, *args).result(timeout)``; when it can run inline, without the Future."""
        self._close_batch()
        with self._cv:
            inline = self._running and not self._jobs and not self._busy
            if inline:
                self._busy = True
        if not inline:
            return self.submit(fn, *args).result(timeout)
        try:
            return fn(*args)
        finally:
            self._end_inline()

    def _loop(self):
        next_diag = time.monotonic() + self.diagnostics_period
        next_status = time.monotonic() + self.status_period
        while True:
            job, step_due = None, False
            with self._cv:
                while self._running and (self._busy or not self._jobs):
                    if self._busy:  # another thread runs a request inline
                        self._sim_waiting = True
                        try:
                            self._cv.wait(0.05)
                        finally:
                            self._sim_waiting = False
                        continue
                    if self.state == PLAYING:
                        wait = self.pacer.wait_time(self.sim.time + self.sim.dt)
                        if wait <= 0:
                            step_due = True
                            break
                    else:
                        wait = next_diag - time.monotonic()
                        if wait <= 0:
                            break
                    self._cv.wait(min(wait, max(0.0, next_diag - time.monotonic()) + 1e-4))
                    if time.monotonic() >= next_diag and not self._busy:
                        break
                if not self._running:
                    break
                if self._jobs:
                    job = self._jobs.popleft()
                self._busy = True
            try:
                if job is not None:
                    self._run_job(*job)
                elif step_due and self.state == PLAYING:
                    try:
                        self._apply_open_batch()
                        # the steps due (pacer), in runs, until a request waits or about RUN_WALL has passed
                        due = self.pacer.steps_due(self.sim.time, self.sim.dt, RUN_CAP_MAX)
                        out = self._advance(due, lockstep=False, free_run=True)
                    except Exception as e:  # a sink failure must not kill the simulation thread
                        out = Outcome(OPERATION_FAILED, f"{type(e).__name__}: {e}")
                    if not out.ok:
                        self.state = PAUSED
                        self._close_batch()  # commands received while playing: a job applies them now
                        self._safe(self.sink.sim_state, self.state)
                        self._safe(self.sink.warn, f"free-run stopped, simulation paused: {out.message}")
                now = time.monotonic()
                if self.status_period > 0 and now >= next_status:
                    next_status = now + self.status_period
                    self._status(now)
                if now >= next_diag:
                    next_diag = now + self.diagnostics_period
                    try:
                        self._report()
                    except Exception as e:  # diagnostics must never stop the simulation
                        self._safe(self.sink.warn, f"diagnostics failed: {type(e).__name__}: {e}")
            finally:
                with self._cv:
                    self._busy = False
                    self._cv.notify_all()
        # drain: fail whatever is still queued so no caller waits forever
        with self._cv:
            jobs, self._jobs = list(self._jobs), collections.deque()
        for fut, _, _ in jobs:
            if fut.set_running_or_notify_cancel():
                fut.set_exception(RuntimeError("the simulation thread stopped"))

    @staticmethod
    def _safe(fn, *args):
        try:
            fn(*args)
        except Exception:
            pass

    # ------------------------------------------------------------------ scene
    def _load(self, scene, overrides):
        return Simulator.load(scene, overrides=self.base_overrides + list(overrides))

    def _adopt(self, sim):
        self.sim = sim
        sim.budget = self.step_budget
        self.info = SceneInfo(sim.describe(), getattr(getattr(sim, "spec", None), "solver", ""))
        self.step_index = 0
        self.cmd_times = {}  # ("joint"|"torque"|"site"|"body", name) -> sim time of the command
        self.publish_every = decimation(self.publish_rate, sim.dt)
        self.marker_every = decimation(self.marker_rate, sim.dt) if self.marker_rate > 0 else 0
        self.tf_every = decimation(self.tf_rate, sim.dt) if self.tf_rate > 0 else 0
        if hasattr(self, "pacer"):
            self.pacer.anchor(sim.time)
        self.sink.scene_loaded(self.info)
        self.sink.robot_model(sim)

    def publish_current(self):
        """Hand the current (not stepped) state to the sink: after start, reset and load."""
        s = self.sim
        tau = getattr(getattr(s, "commands", None), "joint_torques", None)
        effort = np.zeros(self.info.d.nv) if tau is None else np.asarray(tau, float)
        self.sink.state(s.time, s.joint_positions(), s.joint_velocities(), effort, {}, None, self.step_index, {})
        self._publish_prescriptions()
        if self.marker_every:
            self._markers(s.time, None)
        if self.tf_every:
            self.sink.frames(s.time, s)

    def _markers(self, t, contacts):
        """Markers (bodies, springs, deformable surfaces, collision shapes, the step's active contacts) and, with deformables,
        their vertex positions (sink.vertices), at marker_rate."""
        sim = self.sim
        positions = sim.deformable_positions()
        meshes = None
        if positions:
            surfaces = sim.deformable_surfaces()
            meshes = {n: (positions[n], surfaces[n]) for n in positions}
            self.sink.vertices(t, positions)
        self.sink.markers(t, sim.body_poses(), sim.spring_segments(), meshes, contacts, sim.collision_shapes())

    def _publish_prescriptions(self):
        self.sink.prescriptions(self.sim.time, self.sim.prescribed_joints(), self.sim.prescribed_sites(),
                                self.sim.prescribed_bodies())

    # ------------------------------------------------------------------ stepping
    def _expire_commands(self):
        """Commands older than command_timeout (sim time) end: a commanded joint, site or body the
        scene prescribes itself (the walker's crank, the hand's held elbow, catalogue/body_twist's
        lower rod) goes back to the scene's prescription, any other one to passive dynamics; a
        commanded torque goes back to zero."""
        if self.command_timeout <= 0 or not self.cmd_times:
            return
        t = self.sim.time
        expired = [k for k, t0 in self.cmd_times.items() if t - t0 >= self.command_timeout - 1e-12]
        if not expired:
            return
        spec = self.sim.spec
        restored, released = [], []
        for kind, name in expired:
            del self.cmd_times[(kind, name)]
            if kind == "joint":
                self.sim.restore_prescriptions(joints=[name])
                (restored if name in spec.prescribed_joints else released).append(f"joint '{name}'")
            elif kind == "site":
                self.sim.restore_prescriptions(sites=[name])
                (restored if name in spec.prescribed_sites else released).append(f"site '{name}'")
            elif kind == "body":
                self.sim.restore_prescriptions(bodies=[name])
                (restored if name in spec.prescribed_bodies else released).append(f"body '{name}'")
            else:
                self.sim.set_joint_torques({name: np.zeros(self.info.joint_nv[name])})
                released.append(f"torque '{name}'")
        what = "; ".join(([f"released {', '.join(released)} to passive dynamics"] if released else [])
                         + ([f"returned {', '.join(restored)} to the scene's prescription"] if restored else []))
        self.sink.warn(f"command timeout ({self.command_timeout:g} s sim time) at t = {t:.6g} s: {what}")
        self._publish_prescriptions()

    def _advance(self, n, lockstep, feedback=None, cancelled=None, free_run=False) -> Outcome:
        """n steps, in runs (Simulator.step(k): one kernel call for k steps on the compiled path, issue 12
        point 2) that end wherever something has to happen between steps: a published state, markers or
        frames, the last step of a lockstep request, a command's timeout, and the feedback of an action
        (then every step is a run of one). Publishing every step (publish_every 1), a run records every
        step's result in its one kernel call (Simulator.step_results) and each is published (_records). A run
        is also kept under ~RUN_WALL wall seconds, so a cancel or shutdown is seen within about that time. A failed step reports the steps done before it
        (in its run too); the state is that after them.

        ``free_run``: n is what the pacer has due (_loop). Before every run after the first the open batch of
        commands is applied (as _loop does before the first), and the call ends early, after a run, once a
        request is queued, the node stops or RUN_WALL wall seconds have passed, so requests and commands wait for
        at most one run and diagnostics and status lines for about RUN_WALL (the Outcome then counts the steps
        done; stopping here is no failure: _loop ends).
        Publishing every step, this keeps _loop's per-iteration work (its lock, pacer, clocks) out of every
        step."""
        sim, sink = self.sim, self.sink
        each = feedback is None and self._records(lockstep)  # every step published: recorded runs
        single = (feedback is not None or 1 in (self.marker_every, self.tf_every)
                  or (self.publish_every == 1 and not each))
        end = time.perf_counter() + RUN_WALL if free_run else 0.0
        i = 0
        while i < n:
            if free_run and i:  # back to _loop: a request waits, the node stops, or RUN_WALL has passed
                if self._jobs or not self._running or time.perf_counter() >= end:
                    return Outcome(OK, "", steps=i, t=sim.time)
                if self._batch is not None:
                    self._apply_open_batch()
            if cancelled is not None and cancelled():
                return Outcome(OK, "canceled", steps=i, t=sim.time, extra={"canceled": True})
            if not self._running:  # the node is shutting down (SIGINT/SIGTERM): end a long request now
                return Outcome(OPERATION_FAILED, f"the node is shutting down: stopped after {i} of {n} steps",
                               steps=i, t=sim.time)
            if self.cmd_times:
                self._expire_commands()
            k = 1 if single else self._run_length(n - i, each)
            w0 = time.perf_counter()
            try:
                if each:
                    results = sim.step_results(k)
                    res = results[-1]
                else:
                    res = sim.step(k)
            except StepError as e:
                done = int(getattr(e, "steps_done", 0))
                if each:  # the run's steps before the failing one, published as single steps publish them
                    self._publish_each(getattr(e, "results", ())[:done])
                else:
                    self.step_index += done
                i += done
                self.failures += 1
                return Outcome(OPERATION_FAILED, f"step {i + 1} of {n} failed, state kept at t = {sim.time:.6g} s: "
                               f"{e.reason if hasattr(e, 'reason') else e}", steps=i, t=sim.time)
            wall = time.perf_counter() - w0
            i += k
            d = res.diagnostics
            self.last_diag = d
            if each:
                self.meter.add(sum(r.diagnostics.iterations for r in results), wall, k)
                self._publish_each(results)
                idx = self.step_index
                # the run's wall time with its publishing, which keeps a cancel or shutdown within ~RUN_WALL
                self._run_cap = _next_cap(self._run_cap, k, time.perf_counter() - w0)
            else:
                self._run_cap = _next_cap(self._run_cap, k, wall)
                self.meter.add(d.iterations * k, wall, k)
                self.step_index += k
                idx = self.step_index
                if idx % self.publish_every == 0 or (lockstep and i == n):
                    sink.state(res.t, res.q, res.v, res.effort, res.site_forces, d, idx, self._body_wrenches(res))
            if self.marker_every and idx % self.marker_every == 0:
                self._markers(res.t, getattr(d.solution, "contacts", None))
            if self.tf_every and (idx % self.tf_every == 0 or (lockstep and i == n)):
                sink.frames(res.t, sim)
            if feedback is not None:
                feedback(i, n, res.t)
        return Outcome(OK, "", steps=n, t=sim.time)

    def _publish_each(self, results):
        """Count the steps of a recorded run (Simulator.step_results) and publish their StepResults, one state
        per step, in one sink.run_states call (the engine publishes every step: publish_every 1)."""
        first = self.step_index + 1
        self.step_index += len(results)
        self.sink.run_states(results, first, self._body_wrenches)

    def _records(self, lockstep: bool) -> bool:
        """Whether runs record every step's result (Simulator.step_results) and publish them all: when every
        step is published (publish_every 1) in a step request or in free-run as fast as possible. Paced
        free-run (real_time_factor > 0) steps one at a time then, each published when it is due: a recorded
        run hands DDS its states back to back (~20 in 1 ms), and a reliable Python subscriber at 1 kHz lost
        up to 80 % of them that way on a loaded machine (test_node_freerun.py)."""
        return self.publish_every == 1 and (lockstep or self.rtf <= 0)

    def _run_length(self, left: int, record: bool = False) -> int:
        """Steps of the next run (at most ``left``): up to the next published state (unless ``record``: the
        run records them all, _advance), markers, frames or command timeout, and at most the current run cap
        (_next_cap)."""
        k = min(left, self._run_cap)
        idx = self.step_index
        for every in (0 if record else self.publish_every, self.marker_every, self.tf_every):
            if every and every > 1:
                k = min(k, every - idx % every)
            elif every == 1:
                return 1
        if self.command_timeout > 0 and self.cmd_times:
            # the run ends at least one step before the first timeout is due, so _expire_commands
            # sees it before the step it would have seen it before, stepping one at a time
            due = min(self.cmd_times.values()) + self.command_timeout - self.sim.time
            k = min(k, max(1, int(due / self.sim.dt) - 1))
        return max(1, k)

    def _body_wrenches(self, res) -> dict:
        """body -> (frame, required wrench (6,) [torque N m; force N]) of a StepResult; {} when no body
        is prescribed."""
        w = res.body_wrenches
        if not w:
            return {}
        frames = self.sim.prescribed_bodies()
        return {n: (frames[n]["frame"], f) for n, f in w.items()}

    def _status(self, now):
        """One console line while PLAYING (every status_period wall seconds): sim time, real-time
        factor and steps/s since the previous line, step failures."""
        mark = (now, self.sim.time, self.step_index, self.failures)
        last, self._status_mark = self._status_mark, mark
        if self.state != PLAYING or last is None or now <= last[0]:
            return
        dw = now - last[0]
        rtf = (mark[1] - last[1]) / dw
        sps = (mark[2] - last[2]) / dw
        self.sink.status(f"{self.info.name}: t = {mark[1]:.3f} s sim, RTF {rtf:.3g}, {sps:.4g} steps/s, "
                         f"{self.failures} step failure(s)" + (f", {self.command_errors} command error(s)"
                                                               if self.command_errors else ""))

    def _report(self):
        vals = self.meter.report(self.sim.time)
        d = self.last_diag
        vals.update({
            "state": STATE_NAMES.get(self.state, "?"), "scene": self.info.name, "sim_time": self.sim.time,
            "steps": self.step_index, "dt": self.sim.dt, "step_failures": self.failures,
            "command_errors": self.command_errors, "commands_received": self.commands_received,
            "commands_coalesced": self.commands_coalesced,
        })
        if d is not None:
            vals.update({"solver": d.solver, "solver_iterations": d.iterations, "residual": d.residual,
                         "violation_pos": d.violation_pos, "violation_vel": d.violation_vel,
                         "energy_total": d.E_total, "energy_kinetic": d.E_kin,
                         "energy_potential": d.E_pot, "energy_spring": d.E_spring, "integration_order": d.order})
            contacts = getattr(d.solution, "contacts", None)
            if contacts is not None:  # self-collision (docs/collisions.md): the last step's pairs and rows
                vals.update({"contact_candidates": contacts.candidates, "contact_rows": contacts.rows,
                             "contacts_active": contacts.active})
        self.sink.diagnostics(vals, self.failures == 0, STATE_NAMES.get(self.state, "?"))

    # ------------------------------------------------------------------ requests (any thread)
    def joint_command(self, msg):
        """sensor_msgs/JointState command (any thread): validated here, then coalesced into the pending
        table; errors go to sink.command_error (nothing changes)."""
        info = self.info
        self.commands_received += 1
        try:
            velocities, torques, positions = joint_command(msg, info)
            for j in velocities:
                if j not in info.prescribable_joints:
                    raise CommandRejected(f"joint command: joint '{j}' is not prescribable in scene '{info.name}' "
                                          f"(prescribable: {', '.join(info.prescribable_joints)})")
        except (CommandRejected, CommandError) as e:
            self._reject(str(e))
            return
        b = self.position_gain  # a position target: the core's trajectory with a constant q_p, held
        self._enqueue([(("joint", j), v) for j, v in velocities.items()]
                      + [(("joint", j), {"position": [float(x) for x in v], "b": b}) for j, v in positions.items()]
                      + [(("torque", j), v) for j, v in torques.items()])

    def command_superseded(self):
        """A command dropped unread because a newer one sets the same prescriptions (command_reader.py):
        counted as received and coalesced."""
        self.commands_received += 1
        self.commands_coalesced += 1

    def joint_trajectory(self, msg):
        """trajectory_msgs/JointTrajectory (any thread): validated here (convert.joint_trajectory), then
        coalesced with the joint commands (the latest prescription per joint wins); resolved against the
        state when applied (convert.TrajectoryCommand)."""
        self.commands_received += 1
        try:
            cmds = joint_trajectory(msg, self.info, self.position_gain)
        except (CommandRejected, CommandError) as e:
            self._reject(str(e))
            return
        self._enqueue([(("joint", j), c) for j, c in cmds.items()])

    def point_command(self, msg):
        """redmax_msgs/PointVelocityCommand (any thread): validated here, then coalesced."""
        self.commands_received += 1
        try:
            sites = point_command(msg, self.info)
        except (CommandRejected, CommandError) as e:
            self._reject(str(e))
            return
        self._enqueue([(("site", s), v) for s, v in sites.items()])

    def body_command(self, msg):
        """redmax_msgs/BodyTwistCommand (any thread): validated here (convert.body_command), then coalesced
        (the latest prescription per body wins). The core checks the step pipeline when the batch is
        applied (a data-free path rejects it with the core's message)."""
        self.commands_received += 1
        try:
            bodies = body_command(msg, self.info)
        except (CommandRejected, CommandError) as e:
            self._reject(str(e))
            return
        self._enqueue([(("body", b), v) for b, v in bodies.items()])

    def _enqueue(self, items):
        """Add validated commands to the open batch (the latest value per key wins). While PLAYING the
        simulation thread applies the batch before its next step (no job, no thread hop: a flood costs
        the stepping thread one batch per step); otherwise the batch gets one job, queued after every
        request submitted before it (in lockstep the command is applied, and acknowledged on
        prescribed_joints, before the next request)."""
        with self._pending_lock:
            batch = self._batch
            if batch is None:
                batch = self._batch = {}
            for key, value in items:
                if key in batch:
                    self.commands_coalesced += 1
                batch[key] = value
            schedule = self.state != PLAYING and not self._batch_job
            if schedule:
                self._batch_job = True
        if schedule:
            self.submit(self._apply_batch, batch)

    def _close_batch(self):
        """A request is being submitted: commands received before it are applied before it (the open
        batch gets its job now unless it has one), commands received after it go into a new batch."""
        with self._pending_lock:
            batch, self._batch = self._batch, None
            unscheduled = batch is not None and not self._batch_job
            self._batch_job = False
        if unscheduled:
            self.submit(self._apply_batch, batch)

    def _apply_open_batch(self):
        """Simulation thread, before a free-run step: apply the open batch unless a job has it."""
        if self._batch is not None and not self._batch_job:
            with self._pending_lock:
                batch = self._batch if not self._batch_job else None
            if batch is not None:
                self._apply_batch(batch)

    @property
    def queued_jobs(self) -> int:
        """Requests (and command batches) waiting for the simulation thread."""
        return len(self._jobs)

    def step(self, n, feedback=None, cancelled=None, timeout=None) -> Outcome:
        """Blocking: n steps while PAUSED, stays PAUSED."""
        return self.call(self._step, int(n), feedback, cancelled, timeout=timeout)

    def reset(self, scope=SCOPE_DEFAULT) -> Outcome:
        return self.call(self._reset, int(scope))

    def set_state(self, target) -> Outcome:
        return self.call(self._set_state, int(target))

    def load(self, scene, overrides=(), stop=False) -> Outcome:
        """Load a scene (by name or path, confined to scenes/ and scene_dirs); ``stop``: leave the
        simulation STOPPED afterwards (simulation_interfaces LoadWorld)."""
        return self.call(self._load_scene, str(scene), list(overrides), bool(stop))

    def query(self, fn):
        """``fn(sim)`` with exclusive use of the Simulator, after everything submitted before
        (entity states: body poses and twists of one state)."""
        return self.call(lambda: fn(self.sim))

    def release(self, joints=(), sites=(), bodies=()) -> Outcome:
        """Release named joints (prescription and torque), sites and bodies; all empty: everything prescribed."""
        return self.call(self._release, list(joints), list(sites), list(bodies))

    def configure(self, **kw) -> Outcome:
        return self.call(self._configure, kw)

    def configure_async(self, **kw) -> Future:
        """``configure`` without waiting for it: queued after everything submitted before (the
        node's parameter callback)."""
        return self.submit(self._configure, kw)

    # ------------------------------------------------------------------ job bodies (sim thread)
    def _reject(self, text):
        self.command_errors += 1
        self.sink.command_error(text)

    def _apply_batch(self, batch):
        """Apply a batch of commands (latest per joint, torque, site, body) at once: one prescription update
        and one prescribed_* publication, whatever number of messages it came in. Body twists the core
        refuses (the data-free step path) are rejected with its message; the rest of the batch applies."""
        with self._pending_lock:
            if self._batch is batch:
                self._batch = None
                self._batch_job = False
            pending = dict(batch)
        if not pending:
            return
        velocities = {n: v for (k, n), v in pending.items() if k == "joint"}
        torques = {n: v for (k, n), v in pending.items() if k == "torque"}
        sites = {n: v for (k, n), v in pending.items() if k == "site"}
        bodies = {n: v for (k, n), v in pending.items() if k == "body"}
        t = self.sim.time
        ends = {}  # joint -> end time of its trajectory: the command timeout counts from there
        trajectories = [n for n, v in velocities.items() if isinstance(v, TrajectoryCommand)]
        if trajectories:
            pos, vel = self.info.positions(self.sim.state.q), self.sim.joint_velocities()
            for n in trajectories:
                off = self.info.joint_offset.get(n)
                if off is None:  # validated against another scene (a load came in between)
                    self._reject(f"joint trajectory: unknown joint '{n}' in scene '{self.info.name}'")
                    return
                sl = slice(off, off + self.info.joint_nv[n])
                velocities[n], ends[n] = velocities[n].prescription(t, pos[sl], vel[sl])
        try:
            if velocities:
                self.sim.prescribe_joints(velocities)
            if torques:
                self.sim.set_joint_torques(torques)
            if sites:
                self.sim.prescribe_sites(sites)
        except CommandError as e:  # validated against another scene (a load came in between)
            self._reject(str(e))
            return
        if bodies:
            try:
                self.sim.prescribe_bodies(bodies)  # all or nothing
            except CommandError as e:  # the data-free path, or validated against another scene
                self._reject(str(e))
                pending = {k: v for k, v in pending.items() if k[0] != "body"}
                if not pending:
                    return
        for key in pending:
            self.cmd_times[key] = max(t, ends.get(key[1], t)) if key[0] == "joint" else t
        self._publish_prescriptions()

    def _step(self, n, feedback, cancelled):
        if self.state != PAUSED:
            return Outcome(INCORRECT_STATE, f"stepping needs the simulation paused; it is "
                           f"{STATE_NAMES.get(self.state)} (call set_simulation_state with PAUSED first)",
                           t=self.sim.time)
        if n < 1 or n > self.max_steps_per_request:
            return Outcome(OPERATION_FAILED, f"steps must be in [1, {self.max_steps_per_request}] "
                           f"(parameter max_steps_per_request), got {n}", t=self.sim.time)
        return self._advance(n, lockstep=True, feedback=feedback, cancelled=cancelled)

    def _reset(self, scope):
        sim = self.sim
        if scope in (SCOPE_DEFAULT, SCOPE_ALL):
            sim.reset()
            self.step_index = 0
            self.cmd_times.clear()
        elif scope & ~(SCOPE_TIME | SCOPE_STATE | SCOPE_SPAWNED):
            return Outcome(FEATURE_UNSUPPORTED, f"unknown reset scope {scope} (use 0, 1, 2, 4 or 255)",
                           t=sim.time)
        else:
            if scope & SCOPE_STATE:
                t = sim.time
                sim.reset()  # initial q, v, prescriptions and torques
                sim.set_state(replace(sim.state, t=t, k=0, t0=None, history=None))  # deformables kept
                self.cmd_times.clear()
            if scope & SCOPE_TIME:
                sim.set_state(replace(sim.state, t=0.0, k=0, t0=None, history=None))  # deformables kept
                self.step_index = 0
                self.cmd_times = {k: 0.0 for k in self.cmd_times}
        self.pacer.anchor(sim.time)
        self.meter.reset(sim.time)
        self.publish_current()
        return Outcome(OK, "", t=sim.time)

    def _set_state(self, target):
        cur = self.state
        if target not in STATE_NAMES:
            return Outcome(OPERATION_FAILED, f"unknown simulation state {target} (0 stopped, 1 playing, "
                           "2 paused, 3 quitting)")
        if cur == QUITTING:
            return Outcome(INCORRECT_TRANSITION, "the node is quitting")
        if target == cur:
            return Outcome(ALREADY_IN_TARGET_STATE, f"already {STATE_NAMES[cur]}")
        if target == STOPPED:
            self._reset(SCOPE_ALL)
        elif target == PLAYING:
            self.pacer.anchor(self.sim.time)
            self.meter.reset(self.sim.time)
        self.state = target
        self.sink.sim_state(target)
        if target == QUITTING:
            self.sink.quit()
        return Outcome(OK, f"{STATE_NAMES[cur]} -> {STATE_NAMES[target]}")

    def _load_scene(self, scene, overrides, stop=False):
        if not scene:
            return Outcome(NOT_FOUND, "no scene given")
        try:  # confined (docs/node.md, "Security"): the start scene (self._load) is the operator's choice
            sim = Simulator.load(scene, self.base_overrides + list(overrides), allowed_dirs=self.scene_dirs)
        except SceneError as e:  # SceneNotFound: no such scene, or outside scenes/ and scene_dirs
            code = NOT_FOUND if isinstance(e, SceneNotFound) else INVALID_SCENE
            return Outcome(code, f"scene not loaded, '{self.info.name}' kept: {e}")
        except Exception as e:  # anything else the core raises while building: keep the old scene
            return Outcome(INVALID_SCENE, f"scene not loaded, '{self.info.name}' kept: "
                           f"{type(e).__name__}: {e}")
        self._adopt(sim)
        self.meter.reset(sim.time)
        self.last_diag = None
        self.publish_current()
        if stop and self.state not in (STOPPED, QUITTING):
            self.state = STOPPED
            self.sink.sim_state(STOPPED)
        return Outcome(OK, f"loaded '{self.info.name}'")

    def _release(self, joints, sites, bodies=()):
        sim = self.sim
        if not joints and not sites and not bodies:
            joints = list(sim.prescribed_joints()) + [n for k, n in self.cmd_times if k == "torque"]
            sites = list(sim.prescribed_sites())
            bodies = list(sim.prescribed_bodies())
        names = []
        for j in joints:
            if j in self.info.joint_nv:
                names.append(j)
            elif j in self.info.dof_index:
                names.append(self.info.dof_index[j][0])
            else:
                return Outcome(NOT_FOUND, f"unknown joint '{j}' (known: {', '.join(self.info.joint_names)})")
        for s in sites:
            if s not in self.info.sites:
                return Outcome(NOT_FOUND, f"unknown site '{s}' (known: {', '.join(self.info.sites)})")
        for b in bodies:
            if b not in self.info.bodies:
                return Outcome(NOT_FOUND, f"unknown body '{b}' (known: {', '.join(self.info.bodies)})")
        names = list(dict.fromkeys(names))
        sim.release_joints(names)
        if names:
            sim.set_joint_torques({j: np.zeros(self.info.joint_nv[j]) for j in names})
        sim.release_sites(sites)
        sim.release_bodies(bodies)
        for j in names:
            self.cmd_times.pop(("joint", j), None)
            self.cmd_times.pop(("torque", j), None)
        for s in sites:
            self.cmd_times.pop(("site", s), None)
        for b in bodies:
            self.cmd_times.pop(("body", b), None)
        self._publish_prescriptions()
        return Outcome(OK, "")

    def _configure(self, kw):
        if "real_time_factor" in kw:
            self.rtf = float(kw["real_time_factor"])
            self.pacer.set_rtf(self.rtf, self.sim.time)
        if "publish_rate" in kw:
            self.publish_rate = float(kw["publish_rate"])
            self.publish_every = decimation(self.publish_rate, self.sim.dt)
        if "marker_rate" in kw:
            self.marker_rate = float(kw["marker_rate"])
            self.marker_every = decimation(self.marker_rate, self.sim.dt) if self.marker_rate > 0 else 0
        if "tf_rate" in kw:
            self.tf_rate = float(kw["tf_rate"])
            self.tf_every = decimation(self.tf_rate, self.sim.dt) if self.tf_rate > 0 else 0
        if "status_period" in kw:
            self.status_period = float(kw["status_period"])
        if "position_gain" in kw:
            self.position_gain = float(kw["position_gain"])
        if "command_timeout" in kw:
            self.command_timeout = float(kw["command_timeout"])
        if "max_steps_per_request" in kw:
            self.max_steps_per_request = int(kw["max_steps_per_request"])
        if "diagnostics_period" in kw:
            self.diagnostics_period = float(kw["diagnostics_period"])
        if "step_budget_ms" in kw:
            self.step_budget = self.sim.budget = StepBudget.from_ms(float(kw["step_budget_ms"]))
        return Outcome(OK, "")
