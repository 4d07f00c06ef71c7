"""``robotctl status | set-pose | go | goto | pause | resume | abort | relocalize-live | recover | limits``: talk to
the running controller over its control socket (docs/control-api.md).

Each prints the controller's answer (``--json``: the reply's result as one JSON line) and exits
0; a refusal or an unreachable controller is one line on stderr and exit status 2. ``go`` reads
the path file here, with the same strict parser the controller uses, and sends its text: the
controller never opens a file a client names. (``robotctl relocalize`` stays the offline search
over snapshot files; ``relocalize-live`` asks the running controller.)
"""

from __future__ import annotations

import argparse
import math
from typing import Any, Dict

from robot.app.control_client import SOCKET_ENV, ControlClient, default_socket
from robot.base.files import PATH_FILE, read_text
from robot.cli.common import float_in, pose_arg, print_json
from robot.config.schema import parse_yaml
from robot.control.path_file import parse_path

RELOCALIZE_TIMEOUT = 120.0  # s the client waits for a relocalization (the controller has its own bound)


def register(sub) -> None:
    def add(name: str, help_text: str, func, timeout: float = 20.0) -> argparse.ArgumentParser:
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.add_argument("--socket", default=None, help=f"control socket (default: ${SOCKET_ENV} or {default_socket()})")
        p.add_argument("--timeout", type=float_in(0.1, 3600.0, "s"), default=timeout,
                       help="s to wait for the answer (default: %(default)s)")
        p.add_argument("--json", action="store_true", help="print the controller's answer as JSON")
        p.set_defaults(func=func)
        return p

    add("status", "the running controller's pose, quality, mission, chassis and battery", cmd_status)
    p = add("set-pose", "set the running controller's pose (checked against what the cameras see)", cmd_set_pose)
    p.add_argument("pose", nargs=3, metavar=("X", "Y", "PHI"), help="m, m, rad in the map frame")
    p.add_argument("--std", nargs=2, type=float_in(0.0, 10.0, lo_open=True), metavar=("XY", "PHI"),
                   help="its uncertainty: std in m and rad (default: the controller's)")
    p.add_argument("--force", action="store_true", help="skip the checks (inside the map, standing still, cameras)")
    p = add("go", "follow a path file (refused while a mission runs, unless --replace)", cmd_go)
    p.add_argument("path", help="path file (YAML)")
    p.add_argument("--replace", action="store_true", help="brake the running mission to rest, then follow this one")
    p = add("goto", "drive to one target pose", cmd_goto)
    p.add_argument("pose", nargs=3, metavar=("X", "Y", "PHI"), help="m, m, rad in the map frame")
    p.add_argument("--speed", type=float_in(0.0, 2.0, "m/s", lo_open=True), help="cruise speed (m/s)")
    p.add_argument("--tolerance", type=float_in(0.0, 1.0, "m", lo_open=True), help="arrival radius (m)")
    p.add_argument("--replace", action="store_true", help="brake the running mission to rest, then drive there")
    add("pause", "brake within the limits and hold", cmd_simple("pause"))
    add("resume", "continue after pause", cmd_simple("resume"))
    p = add("abort", "brake within the limits and end the mission", cmd_abort)
    p.add_argument("--reason", help="recorded with the abort")
    p = add("relocalize-live", "global relocalization by the running controller from its newest frames",
            cmd_relocalize, timeout=RELOCALIZE_TIMEOUT)
    p.add_argument("--no-apply", action="store_true", help="only report; do not set the pose even when unique")
    p.add_argument("--region", nargs=4, type=float, metavar=("X0", "Y0", "X1", "Y1"),
                   help="only consider poses inside this box of the map (m)")
    add("recover", "restart recovery: relocalize, then turn in place and move to tell places apart as the "
        "config allows (after a stopped turn or move, the robot tries again only when asked)", cmd_recover)
    p = add("limits", "show or lower the speed limit (never above the configured control.max_speed)", cmd_limits)
    g = p.add_mutually_exclusive_group()
    g.add_argument("--speed", type=float_in(0.0, 2.0, "m/s", lo_open=True), help="new cruise speed limit (m/s)")
    g.add_argument("--reset", action="store_true", help="back to the configured control.max_speed")


def _call(args, cmd: str, payload: Dict[str, Any]) -> Any:
    with ControlClient(args.socket, timeout=args.timeout) as client:
        result = client.request(cmd, payload)
    if args.json:
        print_json(result)
    return result


def cmd_status(args) -> int:
    s = _call(args, "status", {})
    if args.json:
        return 0
    pose = s.get("pose")
    if pose:
        cov = pose.get("cov") or [[0.0] * 3] * 3
        sx, sy, sp = (math.sqrt(max(cov[i][i] or 0.0, 0.0)) for i in range(3))
        print(f"pose      ({pose['x']:.3f}, {pose['y']:.3f}, {math.degrees(pose['phi']):.1f} deg)  std "
              f"{sx * 1e3:.1f}/{sy * 1e3:.1f} mm {math.degrees(sp):.2f} deg")
    else:
        print("pose      none (set-pose or relocalize-live)")
    q = s.get("quality", {})
    print(f"quality   {q.get('state')}" + (f" ({q.get('reason')})" if q.get("reason") else ""))
    rec = s.get("recovery") or {}
    if rec.get("state") not in (None, "tracking"):
        print(f"recovery  {rec['state']}" + (f" ({rec.get('reason')})" if rec.get("reason") else "")
              + (f"; {len(rec['hypotheses'])} hypotheses" if rec.get("hypotheses") else ""))
    if s.get("protection_levels"):
        print("protection " + ", ".join(f"{k} {v}" for k, v in s["protection_levels"].items()))
    m = s.get("mission", {})
    where = f", waypoint {m['waypoint'] + 1} of {m['waypoints']}" if m.get("waypoint") is not None else ""
    print(f"mission   {m.get('mode')} {m.get('state')}{where}" + (" [paused]" if m.get("paused") else "")
          + f"; speed limit {m.get('speed_limit'):.2f} of {m.get('max_speed'):.2f} m/s")
    c = s.get("chassis", {})
    volts = s.get("battery", {}).get("voltage")
    print(f"chassis   {c.get('link')}" + (" ESTOP" if c.get("estop") else "")
          + (f"; battery {volts:.2f} V" if volts is not None else ""))
    print("cameras   " + (", ".join(f"{k} {v}" for k, v in s.get("cameras", {}).items()) or "none"))
    return 0


def cmd_set_pose(args) -> int:
    x, y, phi = pose_arg(args.pose, "set-pose")
    payload: Dict[str, Any] = {"x": x, "y": y, "phi": phi, "force": bool(args.force)}
    if args.std:
        payload.update(std_xy=args.std[0], std_phi=args.std[1])
    r = _call(args, "set-pose", payload)
    if not args.json:
        check = r.get("check", {})
        how = (f"the cameras agree within {check['offset_m'] * 1e3:.0f} mm ({', '.join(check['walls'])})"
               if check.get("checked") else "not checked (forced)")
        print(f"pose set to ({x:.3f}, {y:.3f}, {math.degrees(phi):.1f} deg): {how}")
    return 0


def cmd_go(args) -> int:
    text = read_text(args.path, PATH_FILE)
    plan = parse_path(parse_yaml(text, args.path), source=args.path)  # the same errors, before anything is sent
    r = _call(args, "go", {"path": text, "name": str(args.path), "replace": bool(args.replace)})
    if not args.json:
        print(f"following {args.path}: {len(plan.waypoints)} waypoints" + (" (replacing the running mission)"
              if r.get("replaced") else "") + (" [paused: resume to drive]" if r.get("paused") else ""))
    return 0


def cmd_goto(args) -> int:
    x, y, phi = pose_arg(args.pose, "goto")
    payload: Dict[str, Any] = {"x": x, "y": y, "phi": phi, "replace": bool(args.replace)}
    if args.speed is not None:
        payload["speed"] = args.speed
    if args.tolerance is not None:
        payload["tolerance"] = args.tolerance
    r = _call(args, "goto", payload)
    if not args.json:
        print(f"driving to ({x:.3f}, {y:.3f}, {math.degrees(phi):.1f} deg)" + (" [paused: resume to drive]"
              if r.get("paused") else ""))
    return 0


def cmd_simple(name: str):
    def run(args) -> int:
        r = _call(args, name, {})
        if not args.json:
            print(f"{name}: ok" + ("" if r.get("mission") else " (no mission running)"))
        return 0
    return run


def cmd_abort(args) -> int:
    r = _call(args, "abort", {"reason": args.reason} if args.reason else {})
    if not args.json:
        print("abort: braking to rest" if r.get("aborted") else "abort: no mission was running")
    return 0


def cmd_relocalize(args) -> int:
    payload: Dict[str, Any] = {"apply": not args.no_apply}
    if args.region is not None:
        payload["region"] = list(args.region)
    r = _call(args, "relocalize", payload)
    if not args.json:
        print(f"verdict: {r['verdict']}" + (f" ({r['reason']})" if r.get("reason") else "")
              + ("; pose set" if r.get("applied") else "") + f"  [{r.get('ms', 0.0):.0f} ms]")
        for i, h in enumerate(r.get("hypotheses", [])):
            print(f"  {i + 1}. x={h['x']:.4f} y={h['y']:.4f} phi={h['phi']:.4f} rad  score {h['score']:.1f}  "
                  f"support {h['support']:.0%}")
    return 0 if r.get("verdict") != "none" else 1


def cmd_recover(args) -> int:
    r = _call(args, "recover", {})
    if not args.json:
        print(f"recovery: {r['state']}" + (f" ({r['reason']})" if r.get("reason") else ""))
    return 0


def cmd_limits(args) -> int:
    payload: Dict[str, Any] = {}
    if args.speed is not None:
        payload["speed"] = args.speed
    if args.reset:
        payload["reset"] = True
    r = _call(args, "limits", payload)
    if not args.json:
        print(f"speed limit {r['speed']:.3f} m/s (configured maximum {r['max_speed']:.3f} m/s)")
    return 0
