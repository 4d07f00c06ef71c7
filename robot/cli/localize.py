"""``robotctl visible | localize | render | demo``: the localizer from the command line."""

from __future__ import annotations

import math
import time

import numpy as np

from robot.base.errors import InputError
from robot.base.files import check_writable_file
from robot.cli.common import add_robot_map_args, float_in, int_in, load_robot_and_map, pose_arg, print_json
from robot.config import load_robot_config
from robot.config.calibration import calibrated_frame
from robot.localization.localizer import DEFAULT_COARSE_STD, METHODS, Localizer, coarse_covariance
from robot.localization.visible_planes import visible_planes
from robot.maps.plane_map import load_plane_map
from robot.recording.snapshot import load_snapshot, save_snapshot


def register(sub) -> None:
    p = sub.add_parser("visible", help="which map planes each camera sees from a pose")
    add_robot_map_args(p)
    p.add_argument("--pose", nargs=3, required=True, metavar=("X", "Y", "PHI"))
    p.add_argument("--camera", help="only this camera")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_visible)

    p = sub.add_parser("localize", help="refine a coarse pose from depth snapshots (.npz)")
    add_robot_map_args(p)
    p.add_argument("--init", nargs=3, required=True, metavar=("X", "Y", "PHI"), help="coarse pose (m, m, rad)")
    p.add_argument("--init-std", nargs=2, type=float_in(0.0, 180.0, lo_open=True), metavar=("XY_M", "PHI_DEG"),
                   default=(DEFAULT_COARSE_STD[0], math.degrees(DEFAULT_COARSE_STD[2])),
                   help="how far off the coarse pose may be (default: %(default)s)")
    p.add_argument("--method", choices=METHODS, default="joint")
    p.add_argument("--json", action="store_true")
    p.add_argument("--repeat", type=int_in(1, 100000), metavar="N",
                   help="time N repetitions of the same localization after one warm-up call, and report the CPU and "
                        "wall time per call ('timing' in --json)")
    p.add_argument("--calibration", metavar="FILE", help="calibration file (docs/calibration.md), instead of the "
                   "robot config's `calibration:`")
    p.add_argument("snapshots", nargs="+", help="one .npz per camera, taken at the same instant")
    p.set_defaults(func=cmd_localize)

    p = sub.add_parser("render", help="simulate a D435i depth frame to a .npz snapshot")
    add_robot_map_args(p)
    p.add_argument("--pose", nargs=3, required=True, metavar=("X", "Y", "PHI"))
    p.add_argument("--camera", required=True)
    p.add_argument("--out", required=True)
    p.add_argument("--seed", type=int_in(0, 2**32 - 1), default=0)
    p.add_argument("--noise", choices=("realistic", "simple", "none"), default="realistic",
                   help="depth error model (docs/simulator.md; default: %(default)s)")
    p.add_argument("--depth-scale-error", type=float_in(-0.2, 0.2), default=0.0, metavar="E",
                   help="the camera reads depth (1 + E) times too long, e.g. 0.01 (default: 0)")
    p.add_argument("--clutter", type=int_in(0, 200), default=0, help="number of random boxes the map does not know")
    p.add_argument("--site", type=int_in(0, 1000), default=0, metavar="N",
                   help="N random construction-site items: people, pallets, boards, doors, panels, shelving")
    p.add_argument("--as-built", action="store_true",
                   help="render the walls as built (offset, bowed, out of plumb), not as in the map")
    p.set_defaults(func=cmd_render)

    p = sub.add_parser("demo", help="render example scenes, localize them and print errors against truth")
    add_robot_map_args(p)
    p.add_argument("--seed", type=int_in(0, 2**32 - 1), default=1)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_demo)


def cmd_visible(args) -> int:
    robot, plane_map = load_robot_and_map(args)
    pose = pose_arg(args.pose, "--pose")
    cams = [robot.camera(args.camera)] if args.camera else list(robot.cameras)
    out = {"cameras": [{"name": c.name, "planes": visible_planes(plane_map, c, pose)} for c in cams]}
    if args.json:
        print_json(out)
    else:
        for c in out["cameras"]:
            print(f"{c['name']}: " + (", ".join(f"{p['id']} ({p['pixels']} px)" for p in c["planes"]) or "no planes"))
    return 0


def cmd_localize(args) -> int:
    robot, plane_map = load_robot_config(args.robot, calibration=args.calibration), load_plane_map(args.map)
    coarse = pose_arg(args.init, "--init")
    frames = [load_snapshot(p) for p in args.snapshots]
    seen = set()
    for path, f in zip(args.snapshots, frames):
        robot.camera(f.camera)  # unknown camera -> ConfigError naming it
        if f.camera in seen:
            raise InputError(f"{path}: a second snapshot of camera '{f.camera}' (give one per camera)")
        seen.add(f.camera)
    frames = [calibrated_frame(f, robot.camera(f.camera).depth_scale) for f in frames]
    std_xy, std_phi_deg = args.init_std
    if not (std_xy > 0 and std_phi_deg > 0 and math.isfinite(std_xy) and math.isfinite(std_phi_deg)):
        raise InputError("--init-std: both values must be positive and finite")
    loc = Localizer(robot, plane_map)
    prior = coarse_covariance(std_xy, math.radians(std_phi_deg))
    res = loc.localize(frames, coarse, prior, method=args.method)
    timing = None
    if args.repeat:
        # The first call above fills the localizer's caches: it is the warm-up, never timed.
        cpu, wall = [], []
        for _ in range(args.repeat):
            c0, w0 = time.thread_time(), time.perf_counter()
            loc.localize(frames, coarse, prior, method=args.method)
            cpu.append(time.thread_time() - c0)
            wall.append(time.perf_counter() - w0)
        timing = {"cpu_median_ms": round(1e3 * float(np.median(cpu)), 4),
                  "cpu_p95_ms": round(1e3 * float(np.percentile(cpu, 95)), 4),
                  "wall_median_ms": round(1e3 * float(np.median(wall)), 4), "repeats": args.repeat}
    if args.json:
        out = res.to_json()
        if timing is not None:
            out["timing"] = timing
        print_json(out)
    else:
        sd = np.sqrt(np.diag(res.cov))
        print(f"pose x={res.x:.4f} m y={res.y:.4f} m phi={res.phi:.5f} rad  status={res.status}  ({res.ms:.1f} ms)")
        print(f"std  x={sd[0] * 1000:.2f} mm y={sd[1] * 1000:.2f} mm phi={math.degrees(sd[2]):.3f} deg")
        if math.isfinite(res.horizontal_pl) and math.isfinite(res.heading_pl):
            print(f"protection  horizontal={res.horizontal_pl * 1000:.1f} mm heading={math.degrees(res.heading_pl):.2f} deg "
                  f"(risk {res.risk:g})")
        else:
            print(f"protection  none: {res.integrity.get('reason') or 'no bound'}")
        for u in res.unobservable:
            print(f"unobservable: {u['label']}")
        for p in res.planes:
            print(f"  {p.camera:>6} {p.id:<16} inliers={p.inliers:<7} {'used' if p.used else 'dropped'}: {p.reason}")
        if timing is not None:
            print(f"timing: CPU median {timing['cpu_median_ms']:.3f} ms, p95 {timing['cpu_p95_ms']:.3f} ms, wall median "
                  f"{timing['wall_median_ms']:.3f} ms per call over {args.repeat} calls after one warm-up")
    return 0


def cmd_render(args) -> int:
    from drivers.sim.clutter import as_built, random_site_clutter
    from drivers.sim.render import SimScene, random_clutter, render_depth_frame, resolve_noise

    robot, plane_map = load_robot_and_map(args)
    pose = pose_arg(args.pose, "--pose")
    robot.camera(args.camera)
    e = args.depth_scale_error
    if not (math.isfinite(e) and -0.2 <= e <= 0.2):
        raise InputError(f"--depth-scale-error must be between -0.2 and 0.2 (0.01 reads 1 % long), got {e}")
    if args.clutter < 0 or args.site < 0:
        raise InputError("--clutter and --site must not be negative")
    noise = resolve_noise(args.noise, e)
    rng = np.random.default_rng(args.seed)
    clutter = list(random_clutter(plane_map, args.clutter, rng, keep_clear=[pose[:2]])) if args.clutter else []
    if args.site:
        clutter += random_site_clutter(plane_map, rng, args.site, keep_clear=[pose[:2]])
    walls = as_built(plane_map, rng) if args.as_built else None
    frame = render_depth_frame(robot, SimScene(plane_map, clutter, walls=walls), args.camera, pose, rng=rng,
                               noise=noise)
    out = check_writable_file(args.out, "--out")
    save_snapshot(out, frame)
    print(f"wrote {out} ({args.camera} at x={pose[0]} y={pose[1]} phi={pose[2]})")
    return 0


DEMO_POSES = [(0.5, 0.5, math.pi), (0.5, 0.5, 5 * math.pi / 6), (0.2, 0.9, 0.3), (0.9, 0.2, -2.0),
              (0.0, 1.0, -0.8), (1.0, 0.0, 2.4), (0.6, 0.8, 1.2), (0.3, 0.3, -2.7)]


def cmd_demo(args) -> int:
    from drivers.sim.render import SimScene, render_depth_frame
    robot, plane_map = load_robot_and_map(args)
    rng = np.random.default_rng(args.seed)
    scene = SimScene(plane_map)
    loc = Localizer(robot, plane_map)
    rows = []
    for truth in DEMO_POSES:
        frames = [render_depth_frame(robot, scene, c.name, truth, rng=rng) for c in robot.cameras]
        off = rng.uniform(-1, 1, 3) * (0.1 / math.sqrt(2), 0.1 / math.sqrt(2), math.radians(10))
        coarse = tuple(np.add(truth, off))
        for method in METHODS:
            r = loc.localize(frames, coarse, method=method)
            rows.append({"truth": truth, "coarse": coarse, "method": method, "status": r.status,
                         "err_mm": 1000 * math.hypot(r.x - truth[0], r.y - truth[1]),
                         "err_deg": abs(math.degrees(math.remainder(r.phi - truth[2], 2 * math.pi))),
                         "planes": sum(p.used for p in r.planes), "ms": r.ms})
    if args.json:
        print_json({"rows": rows})
        return 0
    print("Paper arena, both cameras, realistic D435i noise, coarse pose up to 0.1 m and 10 deg off\n")
    print(f"{'truth x, y, phi':<24} {'method':<6} {'status':<10} {'planes':>6} {'pos err mm':>10} {'head err deg':>12} {'ms':>6}")
    for r in rows:
        t = r["truth"]
        print(f"{t[0]:5.2f} {t[1]:5.2f} {t[2]:+6.3f}        {r['method']:<6} {r['status']:<10} {r['planes']:>6} "
              f"{r['err_mm']:>10.3f} {r['err_deg']:>12.4f} {r['ms']:>6.1f}")
    return 0
