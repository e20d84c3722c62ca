"""The chart of a sweep: one metric against a swept parameter (PNG, matplotlib).

x: the first swept key (or ``x``); one line per value of the other keys (grid), or a scatter (random
samples). Runs whose metric is missing (failed or errored) are counted in the title, not drawn.
"""
from __future__ import annotations

from collections import defaultdict
from pathlib import Path

from redmax_ros.sweep.table import number

LABELS = {  # axis labels of the metric columns (redmax_ros/sweep/run.py), with units
    "body_vx": "mean forward speed of the body, x [m/s]", "body_speed": "mean speed of the body [m/s]",
    "body_dx": "body displacement x [m]", "body_path": "path length of the body [m]",
    "effort_mean": "mean required torque / force [N m, N]", "effort_mean_abs": "mean |required torque| [N m, N]",
    "effort_rms": "RMS required torque / force [N m, N]", "effort_max_abs": "max |required torque| [N m, N]",
    "E_drift": "energy drift E_end - E_start [J]", "E_total_end": "final total energy [J]",
    "violation_max": "max loop-closure violation [m]", "wall_s": "wall time of the run [s]",
    "cpu_s": "CPU time of the run [s]", "steps": "steps completed", "t_end": "simulated time reached [s]",
}


def chart(path, rows, keys, metric: str, x: str | None = None, title: str = "", labels=None):
    """Write ``path`` (PNG): ``metric`` of the ok rows against parameter ``x`` (default: the first of ``keys``),
    a line per combination of the other keys. ``labels``: {column: axis label}. Returns the path, or None
    when matplotlib is missing or nothing can be drawn."""
    try:
        import matplotlib  # optional: matplotlib (the bench extra)
    except ImportError:
        return None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # optional: matplotlib
    labels = {**LABELS, **(labels or {})}
    if not keys:
        return None
    x = x or keys[0]
    others = [k for k in keys if k != x]
    series = defaultdict(list)
    missing = 0
    for r in rows:
        xv, yv = number(str(r.get(x))), r.get(metric)
        yv = number(str(yv)) if yv is not None else None
        if xv is None or yv is None:
            missing += 1
            continue
        series[tuple(str(r.get(k)) for k in others)].append((xv, yv))
    if not series:
        return None
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    scatter = any(len(pts) != len({p[0] for p in pts}) for pts in series.values()) or len(series) > 12
    for key in sorted(series, key=lambda k: [number(v) if number(v) is not None else v for v in k]):
        pts = sorted(series[key])
        name = ", ".join(f"{labels.get(k, k)} = {v}" for k, v in zip(others, key)) or None
        xs, ys = [p[0] for p in pts], [p[1] for p in pts]
        if scatter:
            ax.scatter(xs, ys, s=14, label=None if len(series) > 12 else name)
        else:
            ax.plot(xs, ys, marker="o", ms=4, label=name)
    ax.set_xlabel(labels.get(x, x))
    ax.set_ylabel(labels.get(metric, metric))
    ax.grid(True, lw=0.3, alpha=0.5)
    if any(k for k in series) and len(series) <= 12:
        ax.legend(fontsize=8)
    t = title + (f" ({missing} runs without a value)" if missing else "")
    if t:
        ax.set_title(t, fontsize=9)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
