"""``robotctl sim``: the whole robot in simulation.

Default: the paper's path-tracking experiment on a simulated clock (``--runs`` runs with vision
and as many with odometry only), a per-target error table, PNG figures and optional JSON.
``--realtime``: one run of the asyncio app itself in real time (threads, pty emulator, fake
cameras), as on the robot.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from dataclasses import replace
from pathlib import Path

from drivers.sim.world import WorldSettings
from robot.base.errors import ConfigError
from robot.cli.common import add_robot_map_args, load_robot_and_map, print_json
from robot.control.path_file import check_path_in_bounds, load_path
from robot.sim.runner import RunSettings


def register(sub) -> None:
    p = sub.add_parser("sim", help="simulate the robot following a path (the paper's Section 4.3 experiment)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_robot_map_args(p)
    p.add_argument("--path", required=True, help="path file YAML (start pose and waypoints)")
    p.add_argument("--runs", type=int, default=15, help="runs per mode (default: %(default)s)")
    p.add_argument("--modes", default="vision,odometry", help="comma-separated: vision, odometry (default: both)")
    p.add_argument("--workers", type=int, default=0, help="worker processes (default: the number of CPU cores)")
    p.add_argument("--vision-rate", type=float, default=5.0, help="frames per second per camera (default: %(default)s)")
    p.add_argument("--decimation", type=int, default=4,
                   help="render frames at 1/N resolution, like the D435i decimation filter (default: %(default)s)")
    p.add_argument("--method", choices=("joint", "paper"), default="joint")
    p.add_argument("--clutter", type=int, default=0, help="random boxes on the floor (default: none)")
    p.add_argument("--out-dir", default="sim_out", help="where the PNG figures go (default: %(default)s)")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG figures")
    p.add_argument("--json", action="store_true", help="print the results as JSON instead of the table")
    p.add_argument("--realtime", action="store_true", help="run the asyncio app once in real time instead")
    p.add_argument("--record", metavar="RUN.mcap", help="record the run (depth, odometry, poses, planes, commands)")
    p.set_defaults(func=cmd_sim)


def cmd_sim(args) -> int:
    robot, plane_map = load_robot_and_map(args)
    plan = load_path(args.path)  # a malformed path file stops here, before anything moves
    lo, hi = plane_map.bounds()
    check_path_in_bounds(plan, lo[:2], hi[:2])
    if plan.start is None:
        raise ConfigError(f"{args.path}: the simulation needs a 'start' pose")
    if args.runs < 1:
        raise ConfigError(f"--runs must be at least 1, got {args.runs}")
    if not (math.isfinite(args.vision_rate) and 0.1 <= args.vision_rate <= 90.0):
        raise ConfigError(f"--vision-rate must be between 0.1 and 90 Hz, got {args.vision_rate}")
    if args.decimation not in (1, 2, 3, 4, 5, 6, 7, 8):
        raise ConfigError(f"--decimation must be 1 to 8, got {args.decimation}")
    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    bad = [m for m in modes if m not in ("vision", "odometry")]
    if bad or not modes:
        raise ConfigError(f"--modes: unknown mode(s) {', '.join(bad) or '(none)'} (choose from vision, odometry)")
    if args.record and not args.realtime:
        raise ConfigError("--record records one run of the app: use it with --realtime")
    if args.realtime:
        from robot.sim.realtime import run_realtime

        return run_realtime(robot, plane_map, plan, args)

    from robot.sim.experiment import format_table, run_experiment

    settings = RunSettings(vision_rate=args.vision_rate, method=args.method,
                           world=replace(WorldSettings(), decimation=args.decimation, clutter=args.clutter))
    workers = args.workers or min(os.cpu_count() or 1, 4)
    done = {"n": 0}
    total = args.runs * len(modes)

    def progress(mode, res) -> None:
        done["n"] += 1
        if not args.json:
            worst = max((t.error for t in res.targets), default=math.nan)
            sys.stderr.write(f"\r  run {done['n']}/{total}: {mode:8s} seed {res.seed:2d} "
                             f"{'ok ' if res.finished else 'FAILED'} worst {worst * 1e3:6.1f} mm   ")
            sys.stderr.flush()

    exp = run_experiment(robot, plane_map, plan, args.runs, settings, workers=workers, modes=modes, progress=progress)
    if not args.json:
        sys.stderr.write("\n")
    figures = []
    if not args.no_plots:
        from robot.sim.plots import save_error_plot, save_trajectory_plot

        out = Path(args.out_dir)
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise ConfigError(f"--out-dir {out}: {e}") from None
        figures = [str(save_error_plot(exp, out / "errors_per_target.png")),
                   str(save_trajectory_plot(exp, plane_map, out / "trajectories.png"))]
    if args.json:
        doc = exp.to_json()
        doc["figures"] = figures
        doc["settings"] = {"vision_rate_hz": args.vision_rate, "decimation": args.decimation, "method": args.method,
                           "latency_s": settings.latency, "clutter": args.clutter}
        print_json(doc)
    else:
        print(f"Path tracking, {plan.source}: {args.runs} runs per mode, vision at {args.vision_rate:g} Hz per camera "
              f"(frames decimated x{args.decimation}), {args.method} estimator")
        print(format_table(exp))
        for f in figures:
            print(f"wrote {f}")
    failed = [r for rs in exp.runs.values() for r in rs if not r.finished]
    return 1 if failed else 0
