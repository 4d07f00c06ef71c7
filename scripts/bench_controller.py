"""Controller benchmarks: the paper's path experiment, control-loop jitter and CPU.

- The path-tracking experiment: ``robotctl sim``'s 15 + 15 runs, per-target tables, and the
  wall time of the whole command.
- Jitter and CPU: the real-time app (asyncio loop, localization thread, serial driver on the pty
  emulator) with two fake cameras delivering full-resolution 848x480 frames at 30 Hz, every
  frame localized. The frames are pre-rendered (a cycle of noisy frames at the robot's pose,
  robot holding still) so the renderer's cost does not load the machine while we measure; it
  is reported apart. CPU is read per thread from /proc, so the simulator's own threads (the
  board emulator, the fake cameras) are reported apart from the controller's. The CPU budget
  (medians over alternating windows, the Nano estimate) is scripts/bench_cpu.py's.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import asyncio  # noqa: E402
import platform  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Dict  # noqa: E402

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from robot.app.controller import AppOptions  # noqa: E402
from robot.config import load_robot_config  # noqa: E402
from robot.maps.plane_map import load_plane_map  # noqa: E402
from robot.sim.realtime import RealtimeSimSettings, sim_rig  # noqa: E402

sys.path.insert(0, str(REPO / "scripts"))
from bench_cpu import GROUPS, group_of, thread_cpu, thread_names  # noqa: E402


def measure_realtime(seconds: float = 20.0, fps: float = 30.0) -> Dict[str, object]:
    robot = load_robot_config(REPO / "config/robot.yaml")
    arena = load_plane_map(REPO / "config/maps/paper_arena.yaml")
    pose = (0.5, 0.5, 0.3)
    settings = RealtimeSimSettings(fps=fps, decimation=1, frame_cache=8, radius_error_std=0.0, slip_noise=0.0)
    opts = AppOptions(install_signal_handlers=False, stop_when_done=False)
    result: Dict[str, object] = {}
    marks: Dict[str, object] = {}
    with sim_rig(robot, arena, pose, settings, opts, initial_pose=pose) as rig:
        app = rig.app

        async def window() -> None:
            loop = asyncio.get_running_loop()
            guard = loop.time() + 60.0  # hang guard only
            while app.stats.localizations < 10 and loop.time() < guard:  # start-up done, frames flowing
                await asyncio.sleep(0.05)
            cpu0, wall0 = thread_cpu(), loop.time()
            ticks0, loc0, frames0 = len(app.stats.tick_times), app.stats.localizations, dict(app.stats.frames)
            await asyncio.sleep(seconds)
            marks.update(cpu0=cpu0, cpu1=thread_cpu(), wall=loop.time() - wall0, names=thread_names(),
                         ticks=list(app.stats.tick_times[ticks0:]), loc=app.stats.localizations - loc0,
                         frames={k: v - frames0.get(k, 0) for k, v in app.stats.frames.items()})
            marks["ms"] = list(app.stats.localize_ms[-marks["loc"]:]) if marks["loc"] else []

        async def main():
            task = asyncio.ensure_future(app.run())
            try:
                await window()
            finally:
                app.request_stop("benchmark done")
            return await task

        asyncio.run(main())
        render_s = sum(c.render_seconds for c in rig.cameras)
        result["render_ms_per_frame"] = 1e3 * render_s / max(1, sum(c._cache_n for c in rig.cameras))
    wall = marks["wall"]
    cpu0, cpu1, names = marks["cpu0"], marks["cpu1"], marks["names"]
    # The same thread groups as scripts/bench_cpu.py; the simulator's threads are kept apart by name.
    groups = {g: 0.0 for g in GROUPS}
    groups.update({"simulator: board emulator": 0.0, "simulator: fake cameras": 0.0})
    main_tid = threading.main_thread().native_id
    for tid, cpu in cpu1.items():
        name = names.get(tid, "")
        g = group_of(tid, name, main_tid)
        if g is None:
            g = "simulator: fake cameras" if name.startswith("camera-") else "simulator: board emulator"
        groups[g] += cpu - cpu0.get(tid, 0.0)
    ticks = np.array(marks["ticks"])
    periods = np.diff(ticks) * 1e3
    jitter = np.abs(periods - 1e3 / robot.control.rate)
    result.update({
        "seconds": wall, "fps": fps, "localizations_per_s": marks["loc"] / wall,
        "frames_per_s": {k: v / wall for k, v in marks["frames"].items()},
        "period_p50": float(np.percentile(periods, 50)), "jitter_p50": float(np.percentile(jitter, 50)),
        "jitter_p99": float(np.percentile(jitter, 99)), "jitter_max": float(jitter.max()),
        "ticks": int(len(ticks)), "cpu": {k: v / wall for k, v in groups.items()},
        "localize_ms_p50": float(np.median(marks["ms"])) if marks["ms"] else float("nan"),
    })
    return result


def measure_experiment(quick: bool) -> str:
    runs = 3 if quick else 15
    t0 = time.monotonic()
    p = subprocess.run([sys.executable, "-m", "robot.cli.main", "sim", "--path", "config/paths/paper_4_3.yaml", "--runs",
                        str(runs), "--out-dir", "docs/bench"], cwd=REPO, capture_output=True, text=True)
    wall = time.monotonic() - t0
    if p.returncode != 0:
        return f"`robotctl sim` failed (exit {p.returncode}):\n\n```\n{p.stdout}\n{p.stderr}\n```\n"
    return (f"`robotctl sim --path config/paths/paper_4_3.yaml --runs {runs}` (README's run command) took "
            f"**{wall:.0f} s** wall time on {os.cpu_count()} cores (target: under 120 s for 15 runs).\n\n"
            f"```\n{p.stdout.strip()}\n```\n\n![error per target](docs/bench/errors_per_target.png)\n"
            "![trajectories](docs/bench/trajectories.png)\n")


def run(quick: bool = False) -> str:
    out = ["## Controller", ""]
    out.append("### The paper's path-tracking experiment (Section 4.3, Fig 18)")
    out.append("")
    out.append("Simulated clock; each run has its own wheel-radius errors (about 1 %, per wheel) and random slip, the "
               "same seeds in both modes. Error = distance from the true robot position to the target at the end of "
               "its dwell. Vision: both cameras at 5 Hz, frames decimated x4 (the renderer's cost; the localizer "
               "samples the same point density as on 848x480 frames).")
    out.append("")
    out.append(measure_experiment(quick))
    r = measure_realtime(seconds=8.0 if quick else 20.0)
    out.append("### Real time: control-loop jitter and CPU with two cameras at 30 Hz")
    out.append("")
    out.append(f"The asyncio app on the pty board emulator, two fake cameras at {r['fps']:.0f} Hz with 848x480 frames, "
               f"every frame localized ({r['localizations_per_s']:.1f} localizations/s over {r['seconds']:.0f} s, "
               f"{r['localize_ms_p50']:.1f} ms median each), control at 50 Hz ({r['ticks']} ticks).")
    out.append("")
    out.append("| control period | p50 | jitter p50 | jitter p99 | jitter max | target |")
    out.append("|---|---|---|---|---|---|")
    out.append(f"| 20 ms | {r['period_p50']:.2f} ms | {r['jitter_p50']:.2f} ms | {r['jitter_p99']:.2f} ms | "
               f"{r['jitter_max']:.2f} ms | p99 < 5 ms |")
    out.append("")
    out.append("| thread | CPU (share of one core) |")
    out.append("|---|---|")
    controller = 0.0
    for k, v in r["cpu"].items():
        out.append(f"| {k} | {v * 100:.1f} % |")
        if not k.startswith("simulator"):
            controller += v
    out.append(f"| **controller total** | **{controller * 100:.1f} %** |")
    out.append("")
    out.append(f"The renderer (simulator only) costs {r['render_ms_per_frame']:.0f} ms per 848x480 frame; the cycle of "
               "frames is rendered before the window and not counted above. One window of one run: the CPU budget "
               "section (scripts/bench_cpu.py) has medians over alternating runs and the Nano estimate.")
    out.append("")
    out.append(f"Machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
               "OPENBLAS_NUM_THREADS=1.")
    out.append("")
    return "\n".join(out)


if __name__ == "__main__":
    print(run(quick="--quick" in sys.argv))
