"""redmax_run: run a scene offline (no ROS) and write a CSV of the trajectory.

    redmax_run SCENE [--dt H] [--duration T] [--solver direct|reference|compiled|pcg|auto] [--set key=value ...] [--out FILE.csv]

CSV columns: t; q:<joint> and v:<joint> (``[i]`` per component of multi-DOF joints); E_kin, E_pot,
E_spring, E_total [J]; violation (max loop-closure residual [m]); tau:<joint> for prescribed joints
(required torque [N m] or force [N]), f:<site>[i] for prescribed sites (required force [N], world) and
w:<body>[i], i = 0..5, for prescribed body twists (required wrench [torque N m; force N] in the
prescription's frame); with deformables E_def_kin, E_def_elastic [J] (their share, included in E_kin and
E_spring) and attach_violation (the attachment drift before the post-stabilization [m], docs/deformables.md).
Prescriptions, joint trajectories included, are scene values: ``--set 'prescribed={joints: {hinge: {position:
{type: sine, amplitude: 0.4, frequency: 0.5}, b: 5}}}'`` (docs/scenes.md, Constraints).
``--controller module:function`` (or ``path/to/file.py:function``) calls ``function(t, state)`` before every
step and applies the commands it returns (``apply_commands``); redmax_sweep (redmax_ros/sweep/) runs this
module's loop (``run``) over grids of scene overrides.
"""
from __future__ import annotations

import argparse
import hashlib
import importlib
import importlib.util
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from redmax_ros.core import SOLVERS, CommandError, SceneError, Simulator, StepBudget, StepError


def parse_args(argv=None):
    ap = argparse.ArgumentParser(prog="redmax_run", description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", help="scene name (scenes/) or path to a scene YAML")
    ap.add_argument("--dt", type=float, help="time step h [s] (default: the scene's)")
    ap.add_argument("--duration", type=float, help="simulated time [s] (default: the scene's)")
    ap.add_argument("--solver", choices=list(SOLVERS), default=None,
                    help="linear solver (default: the scene's; see docs/solvers.md)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a scene value or builder parameter, e.g. params.n=20, joints.elbow.q0=0.3")
    ap.add_argument("--out", type=Path, help="CSV file to write (default: runs/<scene>.csv)")
    ap.add_argument("--every", type=int, default=1, metavar="K",
                    help="write every K-th step's row (and the last step's); the steps between are taken but not "
                         "recorded (default 1: every step)")
    ap.add_argument("--quiet", action="store_true", help="no progress bar")
    ap.add_argument("--step-budget-ms", type=float, default=None, metavar="MS",
                    help="CPU time a step's iterative solvers may take before the step fails (default: the "
                         "core's StepBudget, 50 ms; 0: unlimited, ProxSuite's own iteration caps)")
    ap.add_argument("--controller", default=None, metavar="MODULE:FUNCTION",
                    help="a Python callable (t [s], State) -> commands (a dict, see apply_commands) called before "
                         "every step; MODULE is a dotted module name or a path to a .py file")
    return ap.parse_args(argv)


def scene_overrides(sets=(), dt=None, solver=None) -> list:
    """The override list ["key=value", ...] for Simulator.load: ``sets``, then ``dt=`` (time step h [s]) and
    ``solver=`` when given (what --set, --dt and --solver mean)."""
    out = list(sets)
    if dt is not None:
        out.append(f"dt={dt}")
    if solver is not None:
        out.append(f"solver={solver}")
    return out


def load_simulator(scene: str, overrides=(), step_budget_ms=None) -> Simulator:
    """Simulator.load(scene, overrides) held to the step budget of --step-budget-ms (CPU ms per step; 0:
    unlimited; None: the core's default). Raises SceneError / CommandError."""
    sim = Simulator.load(scene, list(overrides))
    if step_budget_ms is not None:
        sim.budget = StepBudget.from_ms(step_budget_ms)
    return sim


def step_count(sim: Simulator, duration=None) -> int:
    """Number of steps of h = sim.dt that cover ``duration`` [s] (None: the scene's); ValueError unless positive."""
    duration = duration if duration is not None else sim.spec.duration
    if not duration > 0:
        raise ValueError("--duration must be positive")
    return max(1, int(round(duration / sim.dt)))


def load_controller(text: str):
    """The callable named by ``module:function`` (module: a dotted name on sys.path, or a path to a .py file;
    function: a dotted attribute path). Raises ValueError naming what is missing."""
    mod_name, sep, attr = text.rpartition(":")
    if not sep or not mod_name or not attr:
        raise ValueError(f"controller {text!r}: expected module:function")
    try:
        if mod_name.endswith(".py") or "/" in mod_name:
            path = Path(mod_name).expanduser().resolve()
            if not path.is_file():
                raise ValueError(f"controller {text!r}: no such file {path}")
            key = "redmax_controller_" + hashlib.sha1(str(path).encode()).hexdigest()[:12]
            mod = sys.modules.get(key)
            if mod is None:
                spec = importlib.util.spec_from_file_location(key, path)
                mod = importlib.util.module_from_spec(spec)
                sys.modules[key] = mod
                try:
                    spec.loader.exec_module(mod)
                except BaseException:
                    sys.modules.pop(key, None)
                    raise
        else:
            mod = importlib.import_module(mod_name)
    except ImportError as e:
        raise ValueError(f"controller {text!r}: cannot import {mod_name}: {e}") from None
    fn = mod
    for part in attr.split("."):
        fn = getattr(fn, part, None)
        if fn is None:
            raise ValueError(f"controller {text!r}: {mod_name} has no attribute {attr}")
    if not callable(fn):
        raise ValueError(f"controller {text!r}: {attr} is not callable")
    return fn


COMMANDS = ("joint_torques", "joint_velocities", "site_velocities", "site_axes", "site_forces", "release_joints",
            "release_sites")


def apply_commands(sim: Simulator, cmd) -> None:
    """Apply a controller's commands through the Simulator API (each is held until changed):

    * ``joint_torques`` {joint: torque [N m] or force [N], nv values}: ``set_joint_torques``;
    * ``joint_velocities`` {joint: velocity [rad/s, m/s] or a trajectory dict}: ``prescribe_joints``;
    * ``site_velocities`` {site: [vx, vy, vz] m/s, world}, optional ``site_axes`` {site: axes}: ``prescribe_sites``;
    * ``site_forces`` {site: [fx, fy, fz] N, world}: ``set_site_forces``;
    * ``release_joints`` / ``release_sites`` [names]: back to passive dynamics.

    ``None`` or {} changes nothing. CommandError for unknown keys, names or malformed values."""
    if not cmd:
        return
    if not isinstance(cmd, dict):
        raise CommandError(f"a controller must return a dict of commands or None, got {type(cmd).__name__}")
    unknown = set(cmd) - set(COMMANDS)
    if unknown:
        raise CommandError(f"unknown controller command(s) {sorted(unknown)} (known: {', '.join(COMMANDS)})")
    if cmd.get("release_joints"):
        sim.release_joints(list(cmd["release_joints"]))
    if cmd.get("release_sites"):
        sim.release_sites(list(cmd["release_sites"]))
    if cmd.get("joint_torques"):
        sim.set_joint_torques(cmd["joint_torques"])
    if cmd.get("joint_velocities"):
        sim.prescribe_joints(cmd["joint_velocities"])
    if cmd.get("site_velocities"):
        sim.prescribe_sites(cmd["site_velocities"], cmd.get("site_axes"))
    if cmd.get("site_forces") is not None:
        sim.set_site_forces(cmd["site_forces"])


def csv_header(sim: Simulator) -> list:
    d = sim.describe()
    cols = ["t"] + [f"q:{n}" for n in d.position_names] + [f"v:{n}" for n in d.velocity_names]
    cols += ["E_kin", "E_pot", "E_spring", "E_total", "violation"]
    if d.deformables:  # docs/deformables.md: the deformables' share of the energies, the attachment drift
        cols += ["E_def_kin", "E_def_elastic", "attach_violation"]
    for name in sim.prescribed_joints():
        j = sim.mech.joint_index[name]
        cols += [f"tau:{name}"] if j.nv == 1 else [f"tau:{name}[{i}]" for i in range(j.nv)]
    for name in sim.prescribed_sites():
        cols += [f"f:{name}[{i}]" for i in range(3)]
    for name in sim.prescribed_bodies():
        cols += [f"w:{name}[{i}]" for i in range(6)]
    return cols


def csv_row(sim: Simulator, res) -> np.ndarray:
    dg = res.diagnostics
    parts = [[res.t], res.q, res.v, [dg.E_kin, dg.E_pot, dg.E_spring, dg.E_total, dg.violation_pos]]
    rep = sim.deformable_report()
    if rep is not None:
        parts.append([rep["E_kin"], rep["E_elastic"], rep["attachment_drift"]])
    parts += prescribed_columns(sim, res.effort, res.site_forces, res.body_wrenches)
    return np.concatenate([np.atleast_1d(np.asarray(p, float)) for p in parts])


def prescribed_columns(sim: Simulator, effort, site_forces: dict, body_wrenches: dict) -> list:
    """The required torques, site forces and body wrenches of the prescribed joints, sites and bodies, in the
    CSV's column order (csv_header): arrays whose last axis is the columns (one step's, or a Rollout's rows)."""
    parts = []
    for name in sim.prescribed_joints():
        j = sim.mech.joint_index[name]
        parts.append(effort[..., j.idx_v:j.idx_v + j.nv])
    parts += [site_forces[name] for name in sim.prescribed_sites()]
    parts += [body_wrenches[name] for name in sim.prescribed_bodies()]
    return parts


CHUNK = 64  # rows per Simulator.rollout call of ``run`` (and steps per progress-bar update when stepping singly)


def progress_bar(total: int, quiet: bool, unit: str = "step", desc: str | None = None):
    """A tqdm bar on stderr, shown only once the work has lasted 2 s of wall time (never when ``quiet``)."""
    return tqdm(total=total, disable=quiet, delay=2.0, mininterval=0.25, unit=unit, desc=desc, leave=False,
                dynamic_ncols=True)


def run(sim: Simulator, n_steps: int, quiet=False, controller=None, on_step=None, every: int = 1):
    """Step n times; returns (header, rows incl. the initial state, StepError or None, wall time of the stepping
    [s]): a row after every ``every``-th step and after the last one, stopping at the last recorded step before a
    failure. ``controller(t, state) -> commands`` is called before each step and its commands applied
    (``apply_commands``; its exceptions propagate); ``on_step(sim, res)`` after each successful step."""
    header = csv_header(sim)
    full, rem = divmod(n_steps, every)  # rows after every ``every`` steps, then one after the last ``rem``
    n_rows = full + (rem > 0)
    rows = np.empty((n_rows + 1, len(header)))
    r0 = initial_row(sim)
    rows[0, :len(r0)] = r0
    rows[0, len(r0):] = np.nan  # no required forces before the first step
    err = None
    t0 = time.perf_counter()
    r = 0  # rows written after the initial one
    # without a controller, a callback or deformables (whose CSV columns are read from the simulator's state),
    # steps go in runs: Simulator.rollout records the rows' steps in one kernel call per run
    chunked = controller is None and on_step is None and sim.deformables is None
    with progress_bar(n_steps, quiet) as bar:
        k = 0  # steps taken (single steps)
        while r < n_rows and err is None:
            if chunked:
                stride, n = (every, min(CHUNK, full - r)) if r < full else (rem, 1)
                try:
                    ro = sim.rollout(n, stride)
                except StepError as e:
                    err = e
                    ro = e.rollout
                got = 0 if ro is None else len(ro)
                if got:
                    rows[r + 1:r + 1 + got] = rollout_rows(sim, ro)
                r += got
                bar.update(got * stride)
                continue
            if controller is not None:
                apply_commands(sim, controller(sim.time, sim.state))
            try:
                res = sim.step()
            except StepError as e:
                err = e
                break
            k += 1
            if on_step is not None:
                on_step(sim, res)
            if k % every == 0 or k == n_steps:
                r += 1
                rows[r] = csv_row(sim, res)
            if k % CHUNK == 0:
                bar.update(CHUNK)
    wall = time.perf_counter() - t0
    return header, rows[:r + 1], err, wall


def rollout_rows(sim: Simulator, ro) -> np.ndarray:
    """The CSV rows (csv_row's columns and numbers) of a Rollout's steps."""
    parts = [ro.t[:, None], ro.q, ro.v, np.stack([ro.E_kin, ro.E_pot, ro.E_spring, ro.E_total, ro.violation_pos], 1)]
    parts += prescribed_columns(sim, ro.effort, ro.site_forces, ro.body_wrenches)
    return np.concatenate(parts, axis=1)


def write_csv(path: Path, header, rows) -> None:
    """Write the trajectory CSV: the ``header`` line, then the rows at %.17g (float64 round-trips exactly)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savetxt(path, rows, delimiter=",", header=",".join(header), comments="", fmt="%.17g")


def initial_row(sim: Simulator) -> np.ndarray:
    v = sim.joint_velocities()
    ek, ep, es = sim.energies()
    return np.concatenate([[sim.time], sim.state.q, v, [ek, ep, es, ek + ep + es, 0.0]])


def summary(sim, header, rows, wall, err) -> str:
    n = int(round((rows[-1, 0] - rows[0, 0]) / sim.dt))  # steps up to the last row (rows may be every K-th step)
    E = rows[:, header.index("E_total")]
    viol = rows[:, header.index("violation")]
    drift = E[-1] - E[0]
    lines = [
        f"scene {sim.scene_name}: {n} steps of h = {sim.dt:g} s ({n * sim.dt:g} s simulated, "
        f"{sim.describe().ndof} DOF)",
        f"  wall time {wall:.3f} s: {n / max(wall, 1e-12):.0f} steps/s, real-time factor {n * sim.dt / max(wall, 1e-12):.2f}",
        f"  energy: start {E[0]:.6g} J, end {E[-1]:.6g} J, drift {drift:+.3e} J"
        + (f" ({drift / abs(E[0]):+.2e} relative)" if abs(E[0]) > 1e-12 else ""),
        f"  max loop-closure violation {np.nanmax(viol):.3e} m",
    ]
    if err is not None:
        lines.append(f"  STOPPED: {err}")
    return "\n".join(lines)


def main(argv=None) -> int:
    a = parse_args(argv)
    try:
        sim = load_simulator(a.scene, scene_overrides(a.set, a.dt, a.solver), a.step_budget_ms)
        n = step_count(sim, a.duration)
        if a.every < 1:
            raise CommandError(f"--every must be a positive integer (a row every K steps), got {a.every}")
        controller = load_controller(a.controller) if a.controller else None
    except (SceneError, CommandError, ValueError) as e:
        print(f"redmax_run: {e}", file=sys.stderr)
        return 2
    try:
        header, rows, err, wall = run(sim, n, a.quiet, controller, every=a.every)
    except CommandError as e:
        print(f"redmax_run: controller: {e}", file=sys.stderr)
        return 2
    out = a.out or Path("runs") / f"{sim.scene_name}.csv"
    write_csv(out, header, rows)
    print(summary(sim, header, rows, wall, err))
    print(f"  wrote {out} ({len(rows)} rows x {len(header)} columns)")
    return 1 if err is not None else 0


if __name__ == "__main__":
    sys.exit(main())
