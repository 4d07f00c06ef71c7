"""``robotctl relocalize``: where the robot is, from depth snapshots and the map alone (no coarse pose)."""

from __future__ import annotations

import math

from robot.cli.common import add_robot_map_args, load_robot_and_map, print_json


def register(sub) -> None:
    p = sub.add_parser("relocalize", help="global relocalization from depth snapshots (.npz), no coarse pose")
    add_robot_map_args(p)
    p.add_argument("--region", nargs=4, type=float, metavar=("X0", "Y0", "X1", "Y1"),
                   help="only consider poses inside this box of the map (m)")
    p.add_argument("--json", action="store_true")
    p.add_argument("snapshots", nargs="+", help="one .npz per camera, taken at the same instant")
    p.set_defaults(func=cmd_relocalize)


def cmd_relocalize(args) -> int:
    from robot.base.errors import InputError
    from robot.localization.relocalize import AMBIGUOUS, NONE, Relocalizer
    from robot.localization.viewpoint import ViewpointPlanner, no_move_reason
    from robot.recording.snapshot import load_snapshot

    robot, plane_map = load_robot_and_map(args)
    frames = [load_snapshot(s) for s in args.snapshots]
    cams = [f.camera for f in frames]
    if len(set(cams)) != len(cams):
        raise InputError(f"two snapshots from the same camera ({', '.join(cams)}): give one per camera")
    if args.region is not None and not all(math.isfinite(v) for v in args.region):
        raise InputError("--region: the four values must be finite numbers")
    relocalizer = Relocalizer(robot, plane_map)
    res = relocalizer.relocalize(frames, region=args.region)
    move = None
    if res.verdict == AMBIGUOUS:
        # Where the robot could look from next so that the views tell the places apart, planned as
        # the recovery would (its distance, clearance and moves; a path of two where none alone does).
        rc = robot.recovery
        move = ViewpointPlanner(robot, plane_map, relocalizer.index).plan(
            [(h.x, h.y, h.phi) for h in res.hypotheses if h.refined], rc.move_max_distance, rc.move_clearance,
            moves=min(2, rc.max_moves))
    if args.json:
        print_json({**res.to_json(), "move": None if move is None else move.to_json()})
    else:
        print(f"verdict: {res.verdict}" + (f" ({res.reason})" if res.reason else "") + f"  [{res.ms:.0f} ms, "
              f"{res.walls_seen} walls in view]")
        for i, h in enumerate(res.hypotheses):
            sx, sy, sp = (math.sqrt(max(h.cov[k][k], 0.0)) for k in range(3))
            print(f"  {i + 1}. x={h.x:.4f} y={h.y:.4f} phi={h.phi:.4f} rad  std {sx * 1e3:.1f}/{sy * 1e3:.1f} mm "
                  f"{math.degrees(sp):.2f} deg  score {h.score:.1f}  support {h.support:.0%}  walls: "
                  + ", ".join(h.planes[:6]))
            for hw in h.hidden_walls:  # a panel standing in front of this wall would put the robot farther along
                print(f"     {hw['plane']} may be hidden by a panel: the robot may then be up to {hw['up_to_m']:.2f} m "
                      f"farther along ({hw['direction'][0]:.2f}, {hw['direction'][1]:.2f})")
            if h.unbuilt is not None:
                print(f"     only if wall {h.unbuilt} is not built yet (this place needs it missing)")
        if move is not None:
            print(f"  a move that would tell {move.places} places apart ({move.alike} pairs alike after it, "
                  f"{move.alike_here} here): turn {math.degrees(move.dphi):+.0f} deg on the spot, then drive "
                  f"{move.distance:.2f} m straight ahead; then relocalize there")
            if move.then is not None:
                print(f"    (that alone does not: then turn {math.degrees(move.then[2]):+.0f} deg and drive "
                      f"{math.hypot(move.then[0], move.then[1]):.2f} m, and relocalize again)")
        elif res.verdict == AMBIGUOUS:
            print(f"  {no_move_reason(rc.move_max_distance, rc.max_moves)}")
    return 1 if res.verdict == NONE else 0
