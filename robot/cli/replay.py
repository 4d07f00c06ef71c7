"""``robotctl replay RUN.mcap``: redo localization and fusion on a recording and compare.

Exit 0 when the replayed fused poses match the recorded ones (the same code and config give the
same result), 1 when they differ (the report says where), 2 on a bad file.
"""

from __future__ import annotations

import argparse
import logging
import math

from robot.base.errors import InputError, RobotError
from robot.cli.common import print_json
from robot.config import load_robot_config
from robot.maps.plane_map import load_plane_map
from robot.sim.replay import replay


def register(sub) -> None:
    p = sub.add_parser("replay", help="re-run localization and fusion on a recorded run and compare",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("recording", help="an MCAP file written by --record (other segments of the run are found)")
    p.add_argument("--robot", help="robot config to replay with (default: the one recorded)")
    p.add_argument("--map", help="plane map to replay with (default: the one recorded)")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_replay)


def cmd_replay(args) -> int:
    robot = load_robot_config(args.robot) if args.robot else None
    plane_map = load_plane_map(args.map) if args.map else None
    try:
        report = replay(args.recording, robot, plane_map)
    except RobotError:
        raise
    except (KeyError, IndexError, TypeError, ValueError, OverflowError, ZeroDivisionError) as e:
        # The replay trusts each message's fields (a recording is our own file); one that was
        # edited, or written by another tool, is a bad file, not a crash. -v logs the traceback.
        logging.getLogger(__name__).debug("replay of %s failed", args.recording, exc_info=True)
        raise InputError(f"{args.recording}: a recorded message does not hold what the replay needs "
                         f"({type(e).__name__}: {str(e)[:120]})") from None
    if args.json:
        print_json(report.to_json())
    else:
        print(f"{args.recording}: {report.odometry} odometry samples, {report.localizations} localizations redone, "
              f"{report.poses_compared} fused poses compared")
        print(f"largest difference to the recording: {report.max_position_diff * 1e3:.6f} mm, "
              f"{math.degrees(report.max_heading_diff):.6f} deg")
        for m in report.fit_mismatches[:10]:
            print(f"  differs: {m}")
        if report.missing_frames:
            print(f"  {report.missing_frames} localized frames are missing from the recording (dropped while recording?)")
        for p in report.truncated:
            print(f"  segment cut short (read up to its last complete chunk): {p}")
        print("identical" if report.ok() else "DIFFERENT")
    return 0 if report.ok() else 1
