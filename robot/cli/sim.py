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
from typing import Dict, Union

from drivers.sim.render import resolve_noise
from drivers.sim.world import WorldSettings
from robot.base.errors import ConfigError
from robot.base.files import check_writable_file
from robot.cli.common import add_robot_map_args, float_in, int_in, print_json
from robot.config import load_robot_config
from robot.control.path_file import check_path_in_bounds, load_path
from robot.maps.plane_map import load_plane_map
from robot.sim.runner import RunSettings


def register(sub) -> None:
    p = sub.add_parser("sim", help="simulate the robot following a path (the paper's Section 4.3 experiment)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_robot_map_args(p)
    p.add_argument("--path", required=True, help="path file YAML (start pose and waypoints)")
    p.add_argument("--runs", type=int_in(1, 1000), default=15, help="runs per mode, 1 to 1000 (default: %(default)s)")
    p.add_argument("--modes", default="vision,odometry", help="comma-separated: vision, odometry (default: both)")
    p.add_argument("--workers", type=int_in(1, 64), default=None,
                   help="worker processes, 1 to 64 (default: the number of CPU cores, at most 4)")
    p.add_argument("--vision-rate", type=float_in(0.1, 90.0, "Hz"), default=5.0,
                   help="frames per second per camera, 0.1 to 90 (default: %(default)s)")
    p.add_argument("--decimation", type=int_in(1, 8), default=4,
                   help="render frames at 1/N resolution, like the D435i decimation filter (default: %(default)s)")
    p.add_argument("--method", choices=("joint", "paper"), default="joint")
    p.add_argument("--clutter", type=int_in(0, 200), default=0, help="random boxes on the floor, up to 200 (default: none)")
    p.add_argument("--noise", choices=("realistic", "simple", "none"), default="realistic",
                   help="depth error model of the simulated cameras (docs/simulator.md; default: %(default)s)")
    p.add_argument("--depth-scale-error", default="0", metavar="E|CAM=E,...",
                   help="cameras read depth (1 + E) times too long: one value, or per camera, e.g. front=0.01,left=-0.005")
    p.add_argument("--site", type=int_in(0, 1000), default=0, metavar="N", help="N random construction-site items (default: none)")
    p.add_argument("--as-built", action="store_true", help="walls rendered as built (offset, bowed, out of plumb)")
    p.add_argument("--mount-error", action="append", default=[], metavar="CAM=DX,DY,DZ,DROLL,DPITCH,DYAW",
                   help="a camera's true mount minus its configured one (mm and deg; repeatable)")
    p.add_argument("--wheel-radius-error", type=float_in(-0.1, 0.1), default=0.0, metavar="E",
                   help="the wheels are (1 + E) times their configured radius (default: 0)")
    p.add_argument("--online-calibration", action="store_true",
                   help="the controller estimates depth scales, mounts and wheel radii while it drives")
    p.add_argument("--calibration", metavar="FILE",
                   help="calibration file the controller runs with (docs/calibration.md), instead of the config's "
                        "`calibration:`; the simulated robot stays as configured, plus the errors given above")
    p.add_argument("--out-dir", default="sim_out", help="where the PNG figures go (default: %(default)s)")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG figures")
    p.add_argument("--json", action="store_true", help="print the results as JSON instead of the table")
    p.add_argument("--realtime", action="store_true", help="run the asyncio app once in real time instead")
    p.add_argument("--kidnap-at", nargs=4, type=float, metavar=("T", "X", "Y", "PHI"),
                   help="with --realtime: at T s carry the robot to (X, Y, PHI) without its wheels turning")
    p.add_argument("--record", metavar="RUN.mcap", help="record the run (depth, odometry, poses, planes, commands)")
    p.set_defaults(func=cmd_sim)


def cmd_sim(args) -> int:
    # The controller runs with the calibration, if any (--calibration, else the config's); the
    # simulated robot is the configured one plus the errors given (what calibration has to find).
    robot = load_robot_config(args.robot, calibration=args.calibration)
    world_robot = load_robot_config(args.robot, calibration="")
    plane_map = load_plane_map(args.map)
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
    if args.kidnap_at is not None:
        if not args.realtime:
            raise ConfigError("--kidnap-at carries the robot of one real-time run: use it with --realtime")
        t_k, x_k, y_k, phi_k = args.kidnap_at
        if not all(math.isfinite(v) for v in args.kidnap_at) or not 0.0 < t_k <= 3600.0:
            raise ConfigError(f"--kidnap-at: T must be in (0, 3600] s and X Y PHI finite, got {args.kidnap_at}")
        if not (lo[0] <= x_k <= hi[0] and lo[1] <= y_k <= hi[1]):
            raise ConfigError(f"--kidnap-at: ({x_k}, {y_k}) is outside the map")
    if args.record:
        check_writable_file(args.record, "--record")  # a directory or a read-only place: refused before the run
    scale_error = _scale_errors(args.depth_scale_error, [c.name for c in robot.cameras])
    if args.clutter < 0 or args.site < 0:
        raise ConfigError("--clutter and --site must not be negative")
    if args.realtime and (args.noise != "realistic" or scale_error or args.site or args.as_built or args.mount_error
                          or args.wheel_radius_error or args.online_calibration or args.calibration is not None):
        raise ConfigError("--noise, --depth-scale-error, --site, --as-built, --mount-error, --wheel-radius-error, "
                          "--online-calibration and --calibration apply to the simulated-clock experiment, not to "
                          "--realtime")
    if args.realtime:
        from robot.sim.realtime import run_realtime

        return run_realtime(robot, plane_map, plan, args)

    from robot.cli.calibrate import parse_mount_errors
    from robot.sim.experiment import format_table, run_experiment

    settings = RunSettings(vision_rate=args.vision_rate, method=args.method, online_calibration=args.online_calibration,
                           world_robot=world_robot,
                           world=replace(WorldSettings(), decimation=args.decimation, clutter=args.clutter,
                                         depth_noise=resolve_noise(args.noise, scale_error or None), site=args.site,
                                         as_built=args.as_built, wheel_radius_error=args.wheel_radius_error,
                                         mount_errors=parse_mount_errors(args.mount_error, [c.name for c in robot.cameras])))
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
                           "latency_s": settings.latency, "clutter": args.clutter, "noise": args.noise,
                           "depth_scale_error": scale_error, "site": args.site, "as_built": args.as_built,
                           "calibration": args.calibration}
        print_json(doc)
    else:
        print(f"Path tracking, {plan.source}: {args.runs} runs per mode, vision at {args.vision_rate:g} Hz per camera "
              f"(frames decimated x{args.decimation}, {args.noise} camera model), {args.method} estimator")
        print(format_table(exp))
        for f in figures:
            print(f"wrote {f}")
    failed = [r for rs in exp.runs.values() for r in rs if not r.finished]
    return 1 if failed else 0


def _scale_errors(text: str, cameras) -> Union[float, Dict[str, float]]:
    """``--depth-scale-error``: one value for every camera, or ``CAM=E,...`` (others 0)."""
    def number(v: str, what: str) -> float:
        try:
            e = float(v)
        except ValueError:
            e = math.nan
        if not (math.isfinite(e) and -0.2 <= e <= 0.2):
            raise ConfigError(f"--depth-scale-error: {what} must be a number between -0.2 and 0.2 "
                              f"(0.01 reads 1 % long), got {v!r}")
        return e

    if "=" not in text:
        return number(text, "the value")
    out: Dict[str, float] = {}
    for item in text.split(","):
        name, _, v = item.partition("=")
        name = name.strip()
        if name not in cameras:
            raise ConfigError(f"--depth-scale-error: no camera {name!r} (cameras: {', '.join(cameras)})")
        out[name] = number(v.strip(), f"the value for {name}")
    return out
