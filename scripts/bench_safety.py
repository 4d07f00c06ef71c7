"""The protective stop: clearance to a person in the path at the configured speeds, and false stops.

    python scripts/bench_safety.py [--quick]

Runs on the simulated clock (``robot.sim.safety_experiment``): the robot is sent 4 m straight
ahead in an empty 8 m room with a person standing 1.0 m ahead of its front edge (up to 0.1 m off
the centre line, turned at random); odometry-only pose, the realistic camera model, frames at
5 Hz per camera. False stops: control ticks held in the stop zone on the paper path (vision on),
where nothing stands in the way, and on a tour of the FZK house's large room among ten random
site items (people, pallets, shelving, boards and panels at walls, doors) kept 0.5 m clear of
the path, with the walls as built.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from drivers.sim.world import WorldSettings  # noqa: E402
from robot.config import load_robot_config  # noqa: E402
from robot.control.path_file import load_path  # noqa: E402
from robot.maps.plane_map import load_plane_map  # noqa: E402
from robot.sim.runner import RunSettings, run_path  # noqa: E402
from robot.sim.safety_experiment import cluttered_run, obstacle_run, stop_ticks  # noqa: E402

ROBOT = load_robot_config(ROOT / "config" / "robot.yaml")


def run(quick: bool = False) -> str:
    c = ROBOT.safety
    lines = ["## Protective stop (depth cameras)", "",
             f"Footprint {c.footprint_length:.2f} x {c.footprint_width:.2f} m, stop margin {c.stop_margin:.2f} m, "
             f"reaction time {c.reaction_time:.2f} s, braking {c.brake_decel:.2f} m/s^2, slow-down "
             f"{c.slowdown_speed:.2f} m/s within {c.slowdown_distance:.2f} m, blind creep {c.blind_creep_speed:.2f} m/s.",
             "", "| speed (m/s) | runs | touched | stopped short | clearance min (m) | median (m) | travelled median (m) |",
             "|---|---|---|---|---|---|---|"]
    n = 4 if quick else 100
    for speed in (0.15, 0.3):
        count = n if speed == 0.3 else max(2, n // 4)
        runs = [obstacle_run(ROBOT, 1000 + k, speed=speed, distance=1.0, vision=False) for k in range(count)]
        cl = np.array([r.min_clearance for r in runs])
        tr = np.array([r.travelled for r in runs])
        touched = int(np.count_nonzero(cl <= 0.0))
        stopped = sum(1 for r in runs if r.stopped)
        lines.append(f"| {speed:.2f} | {len(runs)} | {touched} | {stopped} | {cl.min():.3f} | {np.median(cl):.3f} | "
                     f"{np.median(tr):.3f} |")
    plan = load_path(ROOT / "config" / "paths" / "paper_4_3.yaml")
    arena = load_plane_map(ROOT / "config" / "maps" / "paper_arena.yaml")
    m = 3 if quick else 15
    stops, limited, finished = [], [], 0
    for k in range(m):
        res = run_path(ROBOT, arena, plan, RunSettings(vision=True, world=WorldSettings(seed=k)))
        stops.append(stop_ticks(res.counters))
        limited.append(int(res.counters.get("safety_limited", 0)))
        finished += int(res.finished)
    lines += ["", f"- Paper path, {m} runs with vision: {finished} finished; ticks held in the stop zone: "
              f"{sum(stops)} in all (false stops: {sum(1 for s in stops if s)} runs); ticks slowed or limited for any "
              f"reason (blind creep toward unseen directions, slow-down): median {int(np.median(limited))} per run."]
    lines += building_false_stops(2 if quick else 10)
    return "\n".join(lines)


def building_false_stops(n: int) -> list:
    fzk = load_plane_map(ROOT / "config" / "maps" / "fzk_haus_ground.yaml")
    tour = load_path(ROOT / "config" / "paths" / "fzk_house_room.yaml")
    runs = [cluttered_run(ROBOT, fzk, tour, seed) for seed in range(n)]
    false = [r for r in runs if r.stop_ticks]
    unfinished = [r for r in runs if not r.finished]
    out = [f"- FZK house room tour, {n} runs with vision among 10 random site items each (kept 0.5 m clear of the "
           f"path; walls as built): {n - len(unfinished)} finished; ticks held in the stop zone: "
           f"{sum(r.stop_ticks for r in runs)} in all (false stops: {len(false)} runs); ticks slowed or limited: "
           f"median {int(np.median([r.limited_ticks for r in runs]))} per run."]
    for r in unfinished + [r for r in false if r.finished]:
        out.append(f"  - seed {r.seed} ({', '.join(sorted(set(r.items)))}): "
                   + (f"not finished: {r.reason}" if not r.finished else "finished")
                   + (f"; {r.stop_ticks} ticks in the stop zone" if r.stop_ticks else ""))
    return out + [""]


if __name__ == "__main__":
    print(run(quick="--quick" in sys.argv))
