"""PNG figures of the path-tracking experiment: error per target (like the paper's Fig 18) and the
trajectories on the map. Needs matplotlib (the ``viz`` extra)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from robot.maps.plane_map import PlaneMap
from robot.maps.plot import _pyplot, save_figure
from robot.sim.experiment import ExperimentResult

_COLOURS = {"vision": "tab:blue", "odometry": "tab:red"}


def save_error_plot(exp: ExperimentResult, path) -> Path:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 4))
    idx = np.arange(1, len(exp.plan.waypoints) + 1)
    for k, (mode, stats) in enumerate(exp.stats.items()):
        mean = np.array([s.mean for s in stats]) * 1e3
        mx = np.array([s.max for s in stats]) * 1e3
        off = (k - 0.5) * 0.18
        ax.plot(idx + off, mean, "o-", color=_COLOURS.get(mode), label=f"{mode}: mean of {len(exp.runs[mode])} runs")
        ax.vlines(idx + off, mean, mx, color=_COLOURS.get(mode), lw=1.0, alpha=0.7)
        ax.plot(idx + off, mx, "_", color=_COLOURS.get(mode), ms=10, label=f"{mode}: max")
    ax.set_xticks(idx)
    ax.set_xlabel("target along the path")
    ax.set_ylabel("position error at the target [mm]")
    ax.set_yscale("log")
    ax.axhline(10.0, color="0.5", lw=0.8, ls="--")
    ax.grid(True, lw=0.3, alpha=0.5)
    ax.legend(fontsize=8)
    ax.set_title("Path tracking in the paper arena: error at each target", fontsize=10)
    fig.tight_layout()
    return save_figure(plt, fig, path)


def save_trajectory_plot(exp: ExperimentResult, plane_map: PlaneMap, path) -> Path:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6, 6))
    for p in plane_map.planes:
        for poly in p.polygons:
            lo = poly[:, 2] <= poly[:, 2].min() + 1e-6
            pts = poly[lo]
            if len(pts) >= 2:
                ax.plot(pts[:, 0], pts[:, 1], color="k", lw=2)
    for mode, runs in exp.runs.items():
        for i, r in enumerate(runs):
            if len(r.truth_trace):
                ax.plot(r.truth_trace[:, 1], r.truth_trace[:, 2], color=_COLOURS.get(mode), lw=0.6, alpha=0.6,
                        label=f"{mode} (true paths)" if i == 0 else None)
    wps = np.array([[w.x, w.y] for w in exp.plan.waypoints])
    ax.plot(wps[:, 0], wps[:, 1], "k+", ms=10, label="targets")
    for i, (x, y) in enumerate(wps):
        ax.annotate(str(i + 1), (x, y), textcoords="offset points", xytext=(5, 5), fontsize=8)
    if exp.plan.start is not None:
        ax.plot([exp.plan.start.x], [exp.plan.start.y], "ks", ms=6, label="start")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(True, lw=0.3, alpha=0.5)
    ax.legend(fontsize=8, loc="center")
    ax.set_title("True trajectories, all runs", fontsize=10)
    fig.tight_layout()
    return save_figure(plt, fig, path)
