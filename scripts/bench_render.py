"""Simulator figures for BENCHMARKS.md: what a rendered D435i frame costs under each depth error
model (docs/simulator.md), at full resolution and decimated as ``robotctl sim`` renders them, and
what the realistic model costs a simulated path run."""

from __future__ import annotations

import math
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import List

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from drivers.sim.building import free_space_poses, room_grid_map  # noqa: E402
from drivers.sim.clutter import as_built, random_site_clutter  # noqa: E402
from drivers.sim.render import SimScene, render_depth_frame  # noqa: E402
from robot.config import load_robot_config  # noqa: E402
from robot.maps.plane_map import load_plane_map  # noqa: E402

ROBOT = load_robot_config(ROOT / "config/robot.yaml")
ARENA = load_plane_map(ROOT / "config/maps/paper_arena.yaml")
MODELS = ("none", "simple", "realistic")


def frame_cost(scene: SimScene, poses, decimation: int, model: str, reps: int) -> float:
    """Median CPU milliseconds per rendered frame (front camera, one thread): CPU time, so other
    processes on a shared machine change it less than they change wall time."""
    rng = np.random.default_rng(0)
    render_depth_frame(ROBOT, scene, "front", poses[0], rng=rng, noise=model, decimation=decimation)  # warm caches
    ts: List[float] = []
    for _ in range(reps):
        for p in poses:
            t0 = time.thread_time()
            render_depth_frame(ROBOT, scene, "front", p, rng=rng, noise=model, decimation=decimation)
            ts.append((time.thread_time() - t0) * 1e3)
    return float(np.median(ts))


def render_costs(quick: bool) -> List[str]:
    reps = 2 if quick else 5
    arena_poses = [(0.5, 0.5, math.pi), (0.3, 0.8, 0.4), (1.0, 0.0, 2.4), (0.0, 0.5, 0.0)]
    site_map = room_grid_map(3, 3, seed=2)
    site = SimScene(site_map, random_site_clutter(site_map, np.random.default_rng(1), 25),
                    walls=as_built(site_map, np.random.default_rng(1)))
    site_poses = free_space_poses(site_map, 4, np.random.default_rng(3))
    scenes = (("paper arena", SimScene(ARENA), arena_poses),
              ("3x3 room grid, 25 site items, walls as built", site, site_poses))
    lines = ["### Time per rendered depth frame (one camera, one thread, median CPU ms)", "",
             "The scene is rasterized once per frame; the error model then runs on the frame's pixels. "
             "`robotctl sim` and `make run` render decimated frames (x4, 212x120); full frames are 848x480.", "",
             "| scene | frame | " + " | ".join(f"{m} ms" for m in MODELS) + " |",
             "|---|---|" + "---|" * len(MODELS)]
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)  # all the work on the measured thread
    try:
        for label, scene, poses in scenes:
            for d, size in ((1, "848x480"), (4, "212x120 (x4)")):
                costs = [frame_cost(scene, poses, d, m, reps) for m in MODELS]
                lines.append(f"| {label} | {size} | " + " | ".join(f"{c:.2f}" for c in costs) + " |")
    finally:
        cv2.setNumThreads(threads)
    return lines


def sim_run_costs(quick: bool) -> List[str]:
    """One simulated path run (vision mode) per model: wall time and its render share."""
    from drivers.sim.render import resolve_noise
    from drivers.sim.world import WorldSettings
    from robot.control.path_file import load_path
    from robot.sim.runner import RunSettings, run_path

    plan = load_path(ROOT / "config/paths/paper_4_3.yaml")
    lines = ["### One simulated path run (`robotctl sim`, vision mode, 5 Hz per camera, frames x4)", "",
             "| depth model | vision ticks | run CPU s | render ms per tick, both cameras (median, wall) | worst target error mm |",
             "|---|---|---|---|---|"]
    for model in ("simple", "realistic"):
        world = replace(WorldSettings(seed=1), depth_noise=resolve_noise(model))
        c0 = time.process_time()
        res = run_path(ROBOT, ARENA, plan, RunSettings(vision=True, world=world))
        cpu = time.process_time() - c0
        worst = max((t.error for t in res.targets), default=math.nan)
        lines.append(f"| {model} | {len(res.render_ms)} | {cpu:.1f} | {np.median(res.render_ms):.2f} | "
                     f"{worst * 1e3:.2f} |")
    return lines


def run(quick: bool = False) -> str:
    parts = ["## Simulator", ""]
    fns = (render_costs,) if quick else (render_costs, sim_run_costs)
    for fn in fns:
        t0 = time.perf_counter()
        parts += fn(quick)
        parts += ["", f"_({fn.__name__}: {time.perf_counter() - t0:.1f} s to measure)_", ""]
    return "\n".join(parts)


if __name__ == "__main__":
    print(run(quick="--quick" in sys.argv))
