"""redmax_bench friction: Fig. 5c (crank torque of the Klann walker vs time for joint mu 0 ... 0.8),
staggered iterations per step, walker steps/s and real-time factor at h = 1 ms with floor contact and
joint friction (best-of-3 CPU time, with the load average, and the CPU time of each stage of a step), and
BISP (reduced coordinates) vs Staggered Projections in maximal coordinates with
Baumgarte (redmax_bench/sp_maximal.py) on friction_chain and a frictional four-bar, in one run.
Writes friction.json and friction_fig5c.png into --out (default bench/results under the current
directory).

    redmax_bench friction [--quick] [--duration S] [--dt H] [--no-chart] [--out DIR]
"""
from __future__ import annotations

import argparse
import math
import os
import time

import numpy as np
import pinocchio as pin

from redmax_ros.core import Simulator
from redmax_ros.core.friction import staggered
from redmax_ros.core.step import pipeline as stepper
from redmax_bench.common import add_out_argument, results_dir, write_json
from redmax_bench.sp_maximal import MaximalSP

MUS = (0.0, 0.2, 0.4, 0.6, 0.8)
FOURBAR_FRICTION = ["joints.crank_joint.friction={mu: 0.3, radius: 0.01, length: 0.02}",
                    "joints.coupler_joint.friction={mu: 0.3, radius: 0.01, length: 0.02}",
                    "joints.rocker_joint.friction={mu: 0.3, radius: 0.01, length: 0.02}",
                    "loops.close.axis=y", "loops.close.friction={mu: 0.3, radius: 0.01, length: 0.02}"]


def walker(mu, dt, duration):
    sim = Simulator.load("klann", overrides=[f"friction.joint_mu={mu}", f"dt={dt}"])
    m = sim.mech
    cf = m.joint_index["crank_fwd"].idx_v
    n = int(round(duration / dt))
    t, tau, its, nc, pen, viol = [], [], [], 0, 0.0, 0.0
    x0 = sim.state.q[0]
    w0, c0 = time.perf_counter(), time.process_time()
    for _ in range(n):
        r = sim.step()
        d = r.diagnostics
        t.append(r.t)
        tau.append(r.effort[cf] * np.sign(r.v[cf]))  # torque the motor delivers along its rotation
        its.append(d.friction.iterations)
        nc += not d.friction.converged
        pen = max(pen, d.friction.max_penetration)
        viol = max(viol, d.violation_pos)
    wall, cpu = time.perf_counter() - w0, time.process_time() - c0
    s = int(0.2 / dt)
    return dict(mu=mu, t=t, tau=tau, tau_mean=float(np.mean(tau[s:])), iterations_mean=float(np.mean(its)),
                iterations_max=int(max(its)), nonconverged_steps=nc, steps=n, wall_s=wall, steps_per_s=n / wall,
                real_time_factor=duration / wall, cpu_s=cpu, steps_per_cpu_s=n / cpu,
                real_time_factor_cpu=duration / cpu, distance_m=float(sim.state.q[0] - x0),
                speed_m_s=float((sim.state.q[0] - x0) / duration), max_penetration_m=pen, max_loop_violation_m=viol)


_STAGES = (  # (module, function, label): the stages of a walker step, timed from inside the step
    (stepper, "kinematics.compute", "kinematics"),
    (stepper, "forces.assemble", "forces"),
    (stepper, "constraints.build", "constraints"),
    (stepper, "staggered.solve", "staggered solve (total)"),
    (staggered, "bisp.body_frames", "  body frames (FK, inertias, twists, Jdot qdot)"),
    (staggered, "staggered_rows", "  contact detection + rows"),
    (staggered, "condense", "  condensation (P, Delassus blocks, lambda map)"),
    (staggered, "bisp.wrench_map", "  BISP joint wrenches, constant part (Eq. 15-17)"),
    (staggered, "staggered_kernel", "  staggered iterations (compiled loop)"),
    (staggered, "finish", "  outputs"),
    (stepper, "stabilization.project_chord", "loop post-stabilization"),
    (stepper, "energies", "energies"),
)


def walker_profile(mu, dt, steps):
    """CPU time per step of each stage of the walker step on the reference pipeline (wrappers around its stage
    functions; each adds ~0.3 us), and the whole step. The compiled step is one native call whose stages are not
    Python functions (docs/benchmarks.md gives its split, measured inside the kernel). Returns {label: us per step}."""
    acc, patched = {}, []
    for obj, attr, label in _STAGES:
        *path, name = attr.split(".")
        try:
            for p_ in path:
                obj = getattr(obj, p_)
            f = getattr(obj, name)
        except AttributeError:  # the stage moved: not timed
            continue

        def wrap(*a, _f=f, _l=label, **k):
            t0 = time.process_time()
            try:
                return _f(*a, **k)
            finally:
                acc[_l] = acc.get(_l, 0.0) + time.process_time() - t0
        setattr(obj, name, wrap)
        patched.append((obj, name, f))
    try:
        sim = Simulator.load("klann", overrides=[f"friction.joint_mu={mu}", f"dt={dt}"], solver="reference")
        sim.step(20)
        acc.clear()
        c0 = time.process_time()
        sim.step(steps)
        total = time.process_time() - c0
    finally:
        for obj, name, f in reversed(patched):
            setattr(obj, name, f)
    out = {"step (total)": 1e6 * total / steps}
    out.update({label: 1e6 * acc.get(label, 0.0) / steps for _, _, label in _STAGES})
    return out


def walker_speed(mu, dt, steps, repeats=3):
    """Best-of-``repeats`` CPU time of ``steps`` walker steps (after a warm-up run that loads the compiled
    kernels): steps per CPU second and the real-time factor; the load average before and after."""
    Simulator.load("klann", overrides=[f"friction.joint_mu={mu}", f"dt={dt}"]).step(20)
    load0 = os.getloadavg()[0]
    best = math.inf
    for _ in range(repeats):
        sim = Simulator.load("klann", overrides=[f"friction.joint_mu={mu}", f"dt={dt}"])
        c0 = time.process_time()
        sim.step(steps)
        best = min(best, time.process_time() - c0)
    return dict(mu=mu, dt=dt, steps=steps, repeats=repeats, cpu_ms_per_step=1e3 * best / steps,
                steps_per_cpu_s=steps / best, real_time_factor_cpu=steps * dt / best,
                load_before=load0, load_after=os.getloadavg()[0])


def _reduced_coms(sim):
    m = sim.mech
    data = m.model.createData()
    pin.forwardKinematics(m.model, data, sim.state.q)
    return np.array([data.oMi[i].act(m.model.inertias[i].lever) for i in range(1, m.model.njoints)])


def bisp_vs_sp(scene, overrides, dt, duration):
    warm = Simulator.load(scene, overrides=list(overrides) + [f"dt={dt}"])  # numba kernels loaded/compiled
    warm.step(5)
    MaximalSP(warm.mech).step(dt)
    sim = Simulator.load(scene, overrides=list(overrides) + [f"dt={dt}"])
    n = int(round(duration / dt))
    its = []
    w0 = time.process_time()  # CPU time: robust to the shared machine's load
    for _ in range(n):
        its.append(sim.step().diagnostics.friction.iterations)
    w_red = time.process_time() - w0
    sp = MaximalSP(sim.mech)
    w0 = time.process_time()
    for _ in range(n):
        sp.step(dt)
    w_max = time.process_time() - w0
    diff = float(np.abs(_reduced_coms(sim) - sp.com_positions()).max())
    return dict(scene=scene, dt=dt, duration=duration, bisp_wall_per_sim_s=w_red / duration,
                sp_maximal_wall_per_sim_s=w_max / duration, sp_over_bisp=w_max / w_red,
                bisp_iterations_mean=float(np.mean(its)), sp_iterations_mean=float(np.mean(sp.iterations)),
                final_com_difference_m=diff, dof_reduced=sim.mech.ndof, dof_maximal=6 * sp.nb)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="redmax_bench friction")
    ap.add_argument("--quick", action="store_true", help="h = 2 ms, 0.6 s walker runs, 1 s comparisons")
    ap.add_argument("--duration", type=float, default=None, help="walker run length [s] (default 2)")
    ap.add_argument("--dt", type=float, default=1e-3, help="walker time step [s] (default 1 ms)")
    ap.add_argument("--no-chart", action="store_true")
    add_out_argument(ap)
    a = ap.parse_args(argv)
    dt = 2e-3 if a.quick else a.dt
    dur = a.duration or (0.6 if a.quick else 2.0)
    Simulator.load("klann", overrides=["friction.joint_mu=0.2", f"dt={dt}"]).step(5)  # load compiled kernels
    speed = [walker_speed(mu, 1e-3, 300 if a.quick else 1000) for mu in (0.4, 0.0)]
    for r in speed:
        print(f"klann joint mu {r['mu']:.1f}, h = 1 ms: {r['cpu_ms_per_step']:.3f} ms CPU per step (best of "
              f"{r['repeats']} x {r['steps']}) = {r['steps_per_cpu_s']:.0f} steps/s, RTF {r['real_time_factor_cpu']:.2f} "
              f"(load {r['load_before']:.2f} -> {r['load_after']:.2f})", flush=True)
    runs = []
    for mu in MUS:
        r = walker(mu, dt, dur)
        runs.append(r)
        print(f"klann joint mu {mu:.1f}: mean crank torque {r['tau_mean']:7.3f} N m, staggered iterations "
              f"{r['iterations_mean']:.1f} (max {r['iterations_max']}, {r['nonconverged_steps']} capped), "
              f"{r['steps_per_s']:.0f} steps/s = RTF {r['real_time_factor']:.3f} (CPU time: {r['steps_per_cpu_s']:.0f} "
              f"steps/s, RTF {r['real_time_factor_cpu']:.3f}), walked {r['distance_m']:.3f} m, "
              f"max sink {1e3 * r['max_penetration_m']:.3f} mm", flush=True)
    prof = walker_profile(0.4, dt, 500 if a.quick else 2000)
    print(f"klann joint mu 0.4, reference pipeline, where the CPU time of a step goes [us/step, best-of-1 with "
          f"timing wrappers]:")
    for k, v in prof.items():
        print(f"  {k:50s} {v:8.1f}")
    taus = [r["tau_mean"] for r in runs]
    mono = all(b > a_ for a_, b in zip(taus, taus[1:]))
    cmp_dur = 1.0 if a.quick else 2.0
    comps = [bisp_vs_sp("friction_chain", [], 1e-3, cmp_dur), bisp_vs_sp("fourbar", FOURBAR_FRICTION, 1e-3, cmp_dur)]
    for c in comps:
        print(f"{c['scene']}: CPU time BISP {c['bisp_wall_per_sim_s']:.3f} s/sim-s ({c['bisp_iterations_mean']:.1f} it), "
              f"SP maximal+Baumgarte {c['sp_maximal_wall_per_sim_s']:.3f} s/sim-s ({c['sp_iterations_mean']:.1f} it): "
              f"SP/BISP = {c['sp_over_bisp']:.2f}; final COM difference {c['final_com_difference_m']:.2e} m", flush=True)
    payload = {
        "walker": [{k: v for k, v in r.items() if k not in ("t", "tau")} for r in runs],
        "fig5c_monotonic": mono, "fig5c_tau_mean": dict(zip([str(m) for m in MUS], taus)),
        "walker_dt": dt, "walker_duration": dur, "walker_speed_h1ms": speed, "walker_stage_us_per_step_mu_0.4_reference": prof,
        "iterations_mean_all": float(np.mean([r["iterations_mean"] for r in runs])),
        "bisp_vs_sp": comps,
    }
    p = write_json(a.out, "friction", payload)
    print(f"Fig. 5c monotonic in joint mu: {mono}; wrote {p}")
    if not a.no_chart:
        import matplotlib  # optional: matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt  # optional: matplotlib
        fig, axs = plt.subplots(2, 1, figsize=(8, 7), sharex=True)
        k = max(1, int(round(0.05 / dt)))  # 50 ms moving average
        hi = 0.0
        for r in runs:
            tau = np.asarray(r["tau"])
            hi = max(hi, float(np.percentile(tau, 98)))
            axs[0].plot(r["t"], tau, lw=0.7, label=f"joint mu = {r['mu']:.1f}")
            axs[1].plot(r["t"][k - 1:], np.convolve(tau, np.ones(k) / k, mode="valid"), lw=1.2,
                        label=f"joint mu = {r['mu']:.1f} (mean {r['tau_mean']:.1f} N m)")
        axs[0].set_ylim(-0.3 * hi, 1.5 * hi)
        axs[0].set_title(f"KLANN walker, floor mu = 0.8, crank 1 rev/s, h = {dt * 1e3:g} ms (paper Fig. 5c)\n"
                         "crank torque along its rotation; spikes (clipped) = foot touchdowns (inelastic impacts)",
                         fontsize=9)
        axs[1].set_title("50 ms moving average", fontsize=9)
        for ax in axs:
            ax.set_ylabel("torque [N m]")
            ax.grid(alpha=0.3)
        axs[1].set_xlabel("time [s]")
        axs[1].legend(fontsize=8)
        fig.tight_layout()
        png = results_dir(a.out) / "friction_fig5c.png"
        fig.savefig(png, dpi=120)
        print(f"wrote {png}")
    return 0
