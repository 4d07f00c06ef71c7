"""``robotctl run``: the controller on the real robot (RealSense cameras, serial motor board).

The same app as the simulation with the real drivers. Under systemd (Type=notify) it sends
READY=1 once the motor board, the cameras and the map are up, STATUS= lines with the
localization quality, and WATCHDOG=1 from the control loop. Without a path it holds still,
localizing, until stopped.
"""

from __future__ import annotations

import argparse
import asyncio
from pathlib import Path

from robot.app.assemble import build_rig
from robot.app.calibration_store import CalibrationStore
from robot.app.controller import AppOptions, RobotApp
from robot.app.pose_store import PoseStore
from robot.base.errors import ConfigError
from robot.base.files import check_writable_directory
from robot.cli.common import int_in, pose_arg
from robot.config import load_robot_config
from robot.control.path_file import check_path_in_bounds, load_path
from robot.maps.plane_map import load_plane_map


def register(sub) -> None:
    p = sub.add_parser("run", help="run the controller on the robot's hardware", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    add_app_args(p)
    p.add_argument("--online-calibration", action="store_true",
                   help="estimate depth scales, mounts and wheel radii while running (kept in --state-dir)")
    p.set_defaults(func=cmd_run)


def add_app_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", default="/etc/robot-controller/robot.yaml", help="robot config YAML (default: %(default)s)")
    p.add_argument("--map", help="plane map YAML (default: the config's `map:`)")
    p.add_argument("--path", help="path file to follow; without it the robot holds still")
    p.add_argument("--init", nargs=3, metavar=("X", "Y", "PHI"), help="initial pose (m, m, rad); default: the "
                   "path's start, else the last saved pose")
    p.add_argument("--state-dir", default=None, help="where the last pose is kept (e.g. /var/lib/robot-controller)")
    p.add_argument("--record", metavar="DIR", help="record runs as MCAP files in DIR (off by default)")
    p.add_argument("--live", nargs="?", const=8765, type=int_in(1, 65535), metavar="PORT",
                   help="serve a Foxglove live view on 127.0.0.1:PORT (default port 8765; needs the 'live' extra)")
    p.add_argument("--odometry-only", action="store_true", help="drive without vision (experiments; not for sites)")
    p.add_argument("--method", choices=("joint", "paper"), default="joint")
    p.add_argument("--calibration", metavar="FILE", help="calibration file (docs/calibration.md), instead of the "
                   "config's `calibration:`")


def load_app_inputs(args):
    robot = load_robot_config(args.config, calibration=getattr(args, "calibration", None))
    map_path = args.map or robot.map_path
    if not map_path:
        raise ConfigError(f"{args.config}: no map: give --map or a `map:` key in the robot config")
    plane_map = load_plane_map(map_path)
    plan = load_path(args.path) if args.path else None  # refused here, before anything moves
    if plan is not None:
        lo, hi = plane_map.bounds()
        check_path_in_bounds(plan, lo[:2], hi[:2])
    init = pose_arg(args.init, "--init") if args.init else None
    return robot, plane_map, plan, init


def make_recorder(directory):
    if not directory:
        return None
    from robot.recording.recorder import BackgroundRecorder, Recorder

    d = Path(directory)
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ConfigError(f"--record {d}: {e}") from None
    check_writable_directory(d, "--record")  # read-only or full: refused now, not found out while driving
    return BackgroundRecorder(Recorder(str(d / "run-{start}.mcap"), compression="none"))


def make_live_view(port):
    if port is None:
        return None
    from robot.recording.live_view import make_live_view as _make

    return _make(port)


def cmd_run(args) -> int:
    robot, plane_map, plan, init = load_app_inputs(args)
    rig = build_rig("hardware", robot)
    store = PoseStore(args.state_dir) if args.state_dir else None
    # remote: the control socket and (when enabled) the fleet link, as the robot config says
    options = AppOptions(vision=not args.odometry_only, method=args.method, stop_when_done=False, remote=True,
                         online_calibration=args.online_calibration)
    calibration_store = CalibrationStore(args.state_dir) if args.state_dir and args.online_calibration else None
    app = RobotApp(robot, plane_map, rig.cameras, rig.chassis, options, plan=plan, initial_pose=init, pose_store=store,
                   recorder=make_recorder(args.record), live_view=make_live_view(args.live),
                   calibration_store=calibration_store)
    rc = asyncio.run(app.run())
    if rc != 0:
        raise ConfigError(app.exit_reason or "the controller failed to start")
    return 0
