"""``robotctl teleop``: drive with the keyboard, in simulation (``--sim``) or on the robot.

WASD or the arrows translate, Q/E turn, space stops, +/- change the speed step, X or Esc
quits. A key keeps the robot moving only while the terminal repeats it (deadman); the fused
pose and its quality are shown on one line while driving. The same health rules as path
following apply: without localization the robot slows down, then stops.
"""

from __future__ import annotations

import argparse
import asyncio
import time

from robot.app.assemble import build_rig
from robot.app.controller import AppOptions, RobotApp
from robot.app.pose_store import PoseStore
from robot.cli.common import float_in
from robot.cli.run import add_app_args, load_app_inputs, make_live_view, make_recorder


def register(sub) -> None:
    p = sub.add_parser("teleop", help="drive with the keyboard (simulation or hardware)", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    add_app_args(p)
    p.set_defaults(config="config/robot.yaml")
    p.add_argument("--sim", action="store_true", help="drive the simulated robot (emulated board, fake cameras)")
    p.add_argument("--fps", type=float_in(1.0, 90.0, "Hz"), default=15.0, help="simulated camera rate (default: %(default)s)")
    p.add_argument("--deadman", type=float_in(0.05, 5.0, "s"), default=0.6,
                   help="s a key holds its motion without a repeat, 0.05 to 5 (default: %(default)s)")
    p.set_defaults(func=cmd_teleop)


async def _drive(app: RobotApp, robot, deadman: float) -> int:
    from robot.app.teleop_terminal import TerminalKeyboard, format_status
    from robot.control.teleop_keys import TeleopState

    state = TeleopState.from_control(robot.control, deadman=deadman)
    app.teleop = state
    async with TerminalKeyboard(lambda: app.request_stop("operator quit"), state=state) as kb:
        async def display() -> None:
            while True:
                await asyncio.sleep(0.1)
                t = time.monotonic()
                s = app.status(t)
                pose = (s["x"], s["y"], s["phi"]) if "x" in s else None
                kb.show(format_status(pose, s.get("cov"), str(s["quality"]), str(s.get("command_reason") or s.get("reason", "")),
                                      state.twist(t), str(s["chassis"]), speed_fraction=state.speed_fraction))

        shown = asyncio.get_running_loop().create_task(display())
        try:
            return await app.run()
        finally:
            shown.cancel()


def cmd_teleop(args) -> int:
    robot, plane_map, _, init = load_app_inputs(args)
    options = AppOptions(vision=not args.odometry_only, method=args.method, stop_when_done=False,
                         install_signal_handlers=True)
    store = PoseStore(args.state_dir) if args.state_dir else None
    recorder = make_recorder(args.record)
    live = make_live_view(args.live)
    if args.sim and init is None:  # the simulated robot starts in the middle of its map
        lo, hi = plane_map.bounds()
        init = (float(lo[0] + hi[0]) / 2.0, float(lo[1] + hi[1]) / 2.0, 0.0)
    rig = build_rig("sim" if args.sim else "hardware", robot, plane_map, init, fps=args.fps)
    try:
        app = RobotApp(robot, plane_map, rig.cameras, rig.chassis, options, teleop=True, initial_pose=init,
                       pose_store=store, recorder=recorder, live_view=live)
        rc = asyncio.run(_drive(app, robot, args.deadman))
    finally:
        rig.close()
    print()
    return rc
