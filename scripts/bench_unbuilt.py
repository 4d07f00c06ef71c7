"""Relocalization with a wall of the model not built yet, with the recovery's in-place turn.

    python scripts/benchmark.py --only bench_unbuilt

The first free-space poses of the one-view table of ``bench_relocalize`` (the same draws, clutter
and camera model) in the three building maps; the map wall the front camera sees most of is left
out of the scene. One view, then the in-place turn while the verdict is not unique (as
``bench_relocalize``'s turn table: a view every turn step, odometry heading 0.2 deg off per step),
relocalized with every view. Each pose is run twice on the same draws: with the relocalizer's
check for places that explain the views if one wall is missing (``relocalize.UNBUILT_*``) and
without it (``UNBUILT_CANDIDATES = 0``). The paper arena is left out: a square room is never
unique. Verdicts only; no timing.
"""

from __future__ import annotations

import math
import os
import sys
from pathlib import Path
from typing import Dict, List

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

import bench_relocalize as B  # noqa: E402
import numpy as np  # noqa: E402

import robot.localization.relocalize as relocalize_module  # noqa: E402
from drivers.sim.building import free_space_poses  # noqa: E402
from robot.control.recovery import views_from_latest  # noqa: E402
from robot.maps.plane_map import load_plane_map  # noqa: E402

MAPS = ["fzk_haus_ground", "institute_ground", "duplex_level1"]
POSES = 20  # per map


def _turn(rel, scene, rng, pose, noise) -> str:
    """The one-view draw of ``bench_relocalize.run_map`` (``rng``: the pose's stream after its
    clutter), then the turn; the verdict's class."""
    frames = B.frames_at(scene, pose, rng, noise)
    res = rel.relocalize(frames, seed=int(rng.integers(1 << 30)))
    step = math.radians(B.TURN_STEP_DEG)
    views = [(frames, (0.0, 0.0, 0.0))]
    odo_phi, k, last = 0.0, 1, pose
    while res.verdict != relocalize_module.UNIQUE and k * step < 2 * math.pi - 1e-9:
        last = (pose[0], pose[1], pose[2] + k * step)
        odo_phi += step + math.radians(rng.normal(0.0, 0.2))
        views.append((B.frames_at(scene, last, rng, noise), (0.0, 0.0, odo_phi)))
        first, more = views_from_latest(views)
        res = rel.relocalize(first, more_views=more, seed=int(rng.integers(1 << 30)))
        k += 1
    return B.classify(res, last)


def run(quick: bool = False) -> str:
    noise, noise_name = B._noise()
    n = 3 if quick else POSES
    lines = ["## Relocalization with a wall not built yet: the in-place turn", "",
             f"The first {n} free-space poses of each building map's one-view relocalization table (the same draws, "
             f"clutter and {noise_name} camera model); the map wall the front camera sees most of is left out of the "
             "scene, so the cameras see through it. One view, then the recovery's in-place turn while the verdict is "
             f"not unique (steps of {B.TURN_STEP_DEG:g} deg, odometry heading 0.2 deg off per step), relocalized with "
             "every view. Each pose twice on the same draws: with the relocalizer's check for places that explain the "
             "views if one wall is missing, and without it ('before'). The paper arena is left out (a square room is "
             "never unique).", "",
             "| map | poses | correct unique | WRONG unique | ambiguous, truth in list | ambiguous, truth missing | none "
             "| before: correct unique | before: WRONG unique |",
             "|---|---|---|---|---|---|---|---|---|"]
    total: Dict[str, int] = {}
    for name in MAPS:
        plane_map = load_plane_map(ROOT / "config" / "maps" / f"{name}.yaml")
        rel = relocalize_module.Relocalizer(B.ROBOT, plane_map)
        seed = 100 + B.MAPS.index(name)
        poses = free_space_poses(plane_map, 130, np.random.default_rng(seed), z=0.15)
        c: Dict[str, int] = {}
        for i_pose in range(n):
            pose = tuple(float(v) for v in poses[i_pose])
            site = B.unbuilt_site(plane_map, rel.index, seed, i_pose, pose)
            if site is None:
                continue
            c["poses"] = c.get("poses", 0) + 1
            k = _turn(rel, *site, pose, noise)
            c[k] = c.get(k, 0) + 1
            with B.unbuilt_check_off():  # the same scene and draws again: a fresh copy of the pose's stream
                k0 = _turn(rel, *B.unbuilt_site(plane_map, rel.index, seed, i_pose, pose), pose, noise)
            c["before_" + k0] = c.get("before_" + k0, 0) + 1
        lines.append(B.unbuilt_row(name, c, by_check=False))
        for key, v in c.items():
            total[key] = total.get(key, 0) + v
    lines += [B.unbuilt_row("**all**", total, by_check=False), ""]
    return "\n".join(lines)


def main(argv: List[str]) -> int:
    print(run(quick="--quick" in argv))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
