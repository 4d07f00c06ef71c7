"""``robotctl calibrate``: depth scales, camera mounts and wheel odometry from the walls of a mapped room.

The robot plans a short motion from where it stands (a turn in place, then squares of short
drives; under a minute), drives it with its ordinary controller, and solves all frames at once
for each camera's depth scale and mount and the wheels' radius and lx + ly. It prints every
parameter with its standard deviation and whether the data observed it, and writes only the
observed ones to the calibration file (docs/calibration.md).

Data: on the robot (default: drives it, recording to --record-dir); ``--sim``: the same motion in
the simulated world, whose robot differs from its config as the --*-error options say;
``--from RUN.mcap``: the frames of a recorded run. ``--check``: compare the calibration in effect
(the config's ``calibration:`` or --calibration) with fresh data; exit 0 while it holds, 1 when not.
"""

from __future__ import annotations

import argparse
import math
import sys
from typing import Dict, List, Tuple

from robot.base.errors import ConfigError, InputError
from robot.base.files import check_writable_file
from robot.cli.common import add_robot_map_args, confirm_motion, float_in, int_in, pose_arg, print_json


def register(sub) -> None:
    p = sub.add_parser("calibrate", help="calibrate depth scales, camera mounts and wheel odometry against the map",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_robot_map_args(p)
    p.add_argument("--calibration", metavar="FILE", help="the calibration in effect (default: the config's "
                   "`calibration:`); the solve starts from it and --check compares against it")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--sim", action="store_true", help="drive the motion in the simulated world")
    src.add_argument("--from", dest="recording", metavar="RUN.mcap", help="calibrate from a recorded run")
    p.add_argument("--init", nargs=3, metavar=("X", "Y", "PHI"),
                   help="where the robot stands (m, m, rad); default: the saved pose (--state-dir), "
                        "with --sim the middle of the map")
    p.add_argument("--out", default="calibration.yaml", help="calibration file to write (default: %(default)s)")
    p.add_argument("--check", action="store_true", help="compare the calibration in effect with fresh data "
                   "(exit 0: it holds, 1: it does not); writes nothing")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.add_argument("--state-dir", default=None, help="where the robot's saved pose is (on the robot)")
    p.add_argument("--record-dir", default=".", help="where the robot's calibration drive is recorded "
                   "(default: the current directory)")
    p.add_argument("--yes", action="store_true", help="do not ask before the robot drives")
    g = p.add_argument_group("simulation (--sim)")
    g.add_argument("--seed", type=int_in(0, 2**31 - 1), default=1)
    g.add_argument("--depth-scale-error", default=None, metavar="E|CAM=E,...",
                   help="cameras read depth (1 + E) times too long (default: front=0.01,left=-0.01)")
    g.add_argument("--mount-error", action="append", default=None, metavar="CAM=DX,DY,DZ,DROLL,DPITCH,DYAW",
                   help="a camera's true mount minus its configured one (mm and deg; repeatable; default: "
                        "front=10,0,0,0,0,0.5 and left=0,0,0,0,0,-0.5)")
    g.add_argument("--wheel-radius-error", type=float_in(-0.1, 0.1), default=0.01, metavar="E",
                   help="the wheels are (1 + E) times their configured radius (default: %(default)s)")
    g.add_argument("--noise", choices=("realistic", "simple", "none"), default="realistic")
    p.set_defaults(func=cmd_calibrate)


def parse_mount_errors(items, cameras) -> Tuple[Tuple[str, Tuple[float, ...]], ...]:
    """``--mount-error`` values (mm and deg) as ``WorldSettings.mount_errors`` (m and deg); None: the
    shipped robot's default errors (front 10 mm forward and 0.5 deg left, left 0.5 deg right)."""
    if items is None:
        items = ["front=10,0,0,0,0,0.5", "left=0,0,0,0,0,-0.5"]
        items = [i for i in items if i.split("=")[0] in cameras]
    out: Dict[str, Tuple[float, ...]] = {}
    for item in items:
        name, _, values = item.partition("=")
        if name not in cameras:
            raise ConfigError(f"--mount-error: no camera {name!r} (cameras: {', '.join(cameras)})")
        try:
            v = [float(x) for x in values.split(",")]
        except ValueError:
            v = []
        if len(v) != 6 or not all(math.isfinite(x) for x in v):
            raise ConfigError(f"--mount-error {item!r}: give CAM=DX,DY,DZ,DROLL,DPITCH,DYAW (mm and deg)")
        if any(abs(x) > 50.0 for x in v[:3]) or any(abs(x) > 5.0 for x in v[3:]):
            raise ConfigError(f"--mount-error {item!r}: at most 50 mm and 5 deg")
        out[name] = tuple([x / 1000.0 for x in v[:3]] + v[3:])
    return tuple(sorted(out.items()))


def _load(args):
    from robot.config import load_robot_config
    from robot.maps.plane_map import load_plane_map

    robot = load_robot_config(args.robot, calibration=args.calibration)
    return robot, load_plane_map(args.map)


def _start_pose(args, plane_map) -> Tuple[float, float, float]:
    if args.init:
        return pose_arg(args.init, "--init")  # type: ignore[return-value]
    if args.sim:
        lo, hi = plane_map.bounds()
        return (float(lo[0] + hi[0]) / 2.0, float(lo[1] + hi[1]) / 2.0, 0.0)
    if args.state_dir:
        from robot.app.pose_store import PoseStore

        stored, why = PoseStore(args.state_dir).load(plane_map.source)
        if stored is None:
            raise ConfigError(f"no start pose: {why}; give --init X Y PHI")
        return (stored.x, stored.y, stored.phi)
    raise ConfigError("where does the robot stand? give --init X Y PHI (or --state-dir with a saved pose)")


def _collect(args, robot, plane_map):
    """(dataset, truth or None, what was driven)."""
    from robot.control.calibration_path import clearance_for, plan_calibration_motion
    from robot.sim.calibration_run import collect_recording

    if args.recording:
        return collect_recording(args.recording, robot, plane_map), None, f"recording {args.recording}"
    start = _start_pose(args, plane_map)
    plan = plan_calibration_motion(plane_map, start, speed=min(0.30, robot.control.max_speed),
                                   clearance=clearance_for(robot))
    if args.sim:
        from drivers.sim.render import resolve_noise
        from drivers.sim.world import WorldSettings
        from robot.cli.sim import _scale_errors
        from robot.sim.calibration_run import collect_sim
        from robot.sim.runner import RunSettings

        names = [c.name for c in robot.cameras]
        if args.depth_scale_error is None:  # the default: the shipped robot's two cameras, 1 % each way
            scale = {k: v for k, v in {"front": 0.01, "left": -0.01}.items() if k in names}
        else:
            scale = _scale_errors(args.depth_scale_error, names)
        world = WorldSettings(seed=args.seed, depth_noise=resolve_noise(args.noise, scale or None),
                              wheel_radius_error=args.wheel_radius_error,
                              mount_errors=parse_mount_errors(args.mount_error, names))
        # the simulated robot is the uncalibrated one with the injected errors; the controller runs with
        # the calibration in effect (which --check then tests)
        from robot.config import load_robot_config

        bare = load_robot_config(args.robot, calibration="")
        col = collect_sim(robot, plane_map, start, RunSettings(world=world, max_time=180.0, world_robot=bare), plan)
        if not col.run.finished:
            raise InputError(f"the simulated calibration drive did not complete: {col.run.reason}")
        return col.data, col.truth, f"simulated drive, {col.run.sim_time:.0f} s of motion"
    why = confirm_motion(args.yes, "robotctl calibrate")
    if why is not None:
        raise ConfigError(why.replace("ON BLOCKS with every wheel free", "free to drive about 0.5 m around"))
    from robot.app.calibration_drive import record_calibration_drive

    files = record_calibration_drive(robot, plane_map, plan, args.record_dir, start=start)
    if not files:
        raise InputError("the calibration drive left no recording")
    return collect_recording(files[0], robot, plane_map), None, f"drive recorded in {files[0]}"


def _value(name: str, v: float) -> Tuple[float, str]:
    kind = name.rsplit(".", 1)[1]
    if kind in ("roll", "pitch", "yaw"):
        return math.degrees(v), "deg"
    if kind == "depth_scale":
        return v, ""
    return v * 1000.0, "mm"


def _table(result, truth) -> List[str]:
    layout = result.solution.layout
    head = f"{'parameter':<28} {'configured':>11} {'estimate':>11} {'std':>9} {'unit':<4}  observable"
    if truth is not None:
        head = head.replace("  observable", f" {'truth':>11} {'error':>9}  observable")
    lines = [head, "-" * len(head)]
    for r in result.reports:
        nom, unit = _value(r.name, r.nominal)
        est, _ = _value(r.name, r.value)
        std = _value(r.name, r.std)[0] if math.isfinite(r.std) else math.nan
        row = f"{r.name:<28} {nom:>11.5f} {est:>11.5f} {std:>9.5f} {unit:<4}"
        if truth is not None:
            tv, _ = _value(r.name, float(truth[layout.index(r.name)]))
            row += f" {tv:>11.5f} {est - tv:>+9.5f}"
        row += "  " + ("yes" if r.observable else f"NO: {r.reason}")
        lines.append(row)
    return lines


def cmd_calibrate(args) -> int:
    from robot.calibration.output import to_calibration
    from robot.calibration.solver import calibrate, check_calibration
    from robot.config.calibration import calibrated_error_model, calibration_yaml, error_model_note, write_calibration

    robot, plane_map = _load(args)
    out = None if args.check else check_writable_file(args.out, "--out")  # refused before the robot moves
    data, truth, what = _collect(args, robot, plane_map)
    if not data.keyframes:
        raise InputError(f"{what}: no wall was fitted: nothing to calibrate from")
    result = calibrate(data, plane_map=plane_map)
    sol = result.solution
    doc: Dict[str, object] = {
        "source": what, "keyframes": sol.counts["keyframes"], "plane_observations": sol.counts["plane_observations"],
        "odometry_intervals": sol.counts["odometry_intervals"],
        "parameters": [{"name": r.name, "configured": r.nominal, "estimate": r.value,
                        "std": r.std if math.isfinite(r.std) else None, "observable": r.observable,
                        "reason": r.reason} for r in result.reports],
        "noise_factors": sol.group_sigma}
    if truth is not None:
        doc["truth"] = {r.name: float(truth[sol.layout.index(r.name)]) for r in result.reports}
    text: List[str] = [f"Calibration from {what}: {sol.counts['keyframes']} keyframes, "
                       f"{sol.counts['plane_observations']} wall fits, {sol.counts['odometry_intervals']} wheel intervals"]
    text += _table(result, truth)
    rc = 0
    if args.check:
        holds, rows = check_calibration(result)
        doc["check"] = {"holds": holds, "rows": [row.__dict__ for row in rows]}
        if not rows:
            text.append("check: the fresh data observes none of the parameters: cannot say the calibration holds")
        for row in rows:
            cur, unit = _value(row.name, row.current)
            est, _ = _value(row.name, row.estimate)
            text.append(f"  {row.name:<28} {'holds' if row.holds else 'CHANGED'}: {cur:.5f} -> {est:.5f} {unit}")
        text.append("the calibration holds" if holds else "the calibration does not hold: run robotctl calibrate")
        rc = 0 if holds else 1
    else:
        cal, comments = to_calibration(result, robot, str(out))
        if cal.empty:
            text.append("nothing was observable well enough to write: no calibration file written")
            rc = 1
        else:
            comments[""] = [f"robotctl calibrate: {what}", "only observed parameters are written (docs/calibration.md)"]
            write_calibration(out, calibration_yaml(cal, comments))
            doc["written"] = str(out)
            text.append(f"wrote {out} (use it with `calibration: {out}` in the robot config or --calibration)")
            # What the file does to the protection levels (docs/calibration.md, 'What a calibration file buys').
            loc = calibrated_error_model(robot.localizer, [cal.cameras.get(c.name) for c in robot.cameras])
            doc["error_model"] = {"depth_scale_std": loc.depth_scale_std, "mount_angle_std_deg": loc.mount_angle_std_deg}
            text.append(f"with it, the {error_model_note(loc)}")
        not_written = [r.name for r in result.reports if not r.observable]
        if not_written:
            text.append("not written (not observable): " + ", ".join(not_written))
    if args.json:
        print_json(doc)
    else:
        sys.stdout.write("\n".join(text) + "\n")
    return rc
