"""Pacing and rate helpers for the simulation thread (no ROS)."""
from __future__ import annotations

import time


class Pacer:
    """Maps simulated time to wall time at a real-time factor.

    ``rtf`` > 0: step k+1 is due at ``wall0 + (t_k+1 - t0) / rtf``; ``rtf`` == 0: always due.
    If the simulation falls more than ``max_lag`` wall seconds behind, the anchor moves so it
    does not race to catch up (no bursts after a slow step or a long service call).
    """

    def __init__(self, rtf: float = 1.0, max_lag: float = 0.05, clock=time.monotonic):
        self.rtf = float(rtf)
        self.max_lag = float(max_lag)
        self.clock = clock
        self.anchor(0.0)

    def anchor(self, sim_t: float):
        self.wall0 = self.clock()
        self.sim0 = float(sim_t)

    def set_rtf(self, rtf: float, sim_t: float):
        self.rtf = float(rtf)
        self.anchor(sim_t)

    def steps_due(self, sim_t: float, dt: float, most: int) -> int:
        """Steps of dt from ``sim_t`` that are due now (at least 1: called once the next one is due; at
        most ``most``; rtf 0: ``most``)."""
        if self.rtf <= 0:
            return int(most)
        ahead = (self.clock() - self.wall0) * self.rtf - (sim_t - self.sim0)  # sim seconds due beyond sim_t
        return int(min(most, max(1.0, ahead // dt)))

    def wait_time(self, next_sim_t: float) -> float:
        """Wall seconds until the step that reaches ``next_sim_t`` is due (<= 0: due now)."""
        if self.rtf <= 0:
            return 0.0
        now = self.clock()
        due = self.wall0 + (next_sim_t - self.sim0) / self.rtf
        if now - due > self.max_lag:
            self.wall0 += (now - due) - self.max_lag
            due = self.wall0 + (next_sim_t - self.sim0) / self.rtf
        return due - now


def decimation(rate_hz: float, dt: float) -> int:
    """Publish every n-th step for a publish rate in Hz of simulated time (0 = every step)."""
    if rate_hz <= 0:
        return 1
    return max(1, int(round(1.0 / (rate_hz * dt))))


class RateMeter:
    """Steps per wall second and real-time factor over the last reporting window."""

    def __init__(self, clock=time.monotonic):
        self.clock = clock
        self.reset(0.0)

    def reset(self, sim_t: float):
        self.w0 = self.clock()
        self.t0 = float(sim_t)
        self.steps = 0
        self.iterations = 0
        self.step_wall = 0.0

    def add(self, iterations: int, step_wall: float, steps: int = 1):
        """``steps`` steps (a run) that took ``step_wall`` seconds and ``iterations`` solver iterations in all."""
        self.steps += int(steps)
        self.iterations += int(iterations)
        self.step_wall += float(step_wall)

    def elapsed(self) -> float:
        return self.clock() - self.w0

    def report(self, sim_t: float) -> dict:
        dw = max(self.elapsed(), 1e-9)
        out = {
            "steps_per_second": self.steps / dw,
            "real_time_factor": (sim_t - self.t0) / dw,
            "mean_solver_iterations": (self.iterations / self.steps) if self.steps else 0.0,
            "mean_step_wall_time": (self.step_wall / self.steps) if self.steps else 0.0,
        }
        self.reset(sim_t)
        return out
