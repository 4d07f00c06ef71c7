"""``robotctl cameras`` (what RealSense devices are connected, and are they fit for the robot) and
``robotctl record-bag`` (a librealsense recording of a simulated run, for the real driver's
playback or Intel's RealSense Viewer).

pyrealsense2 is imported only when a command runs, so ``robotctl`` works without it.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Dict, List

from robot.base.errors import DriverError, InputError
from robot.base.files import check_writable_file
from robot.cli.common import add_robot_map_args, float_in, int_in, print_json

RECOMMENDED_FIRMWARE = "5.16.0.1"  # what librealsense 2.55.1 ships with and recommends for D400


def _version_tuple(v: str):
    out = []
    for part in str(v).split("."):
        if not part.isdigit():
            return None
        out.append(int(part))
    return tuple(out)


def describe_device(rs, device) -> Dict:
    """A device's identity, its streams and its depth intrinsics, as JSON-ready data."""
    from drivers.camera.realsense import describe_device_info

    info = describe_device_info(rs, device)
    sensors = []
    depth_intrinsics = []
    for sensor in device.query_sensors():
        name = sensor.get_info(rs.camera_info.name) if sensor.supports(rs.camera_info.name) else "?"
        streams: Dict[str, set] = {}
        for p in sensor.get_stream_profiles():
            st = str(p.stream_type()).rsplit(".", 1)[-1]
            fmt = str(p.format()).rsplit(".", 1)[-1]
            if p.is_video_stream_profile():
                vp = p.as_video_stream_profile()
                mode = f"{vp.width()}x{vp.height()} {fmt} @{p.fps()}"
                if p.stream_type() == rs.stream.depth:
                    intr = vp.get_intrinsics()
                    depth_intrinsics.append({
                        "width": vp.width(), "height": vp.height(), "fps": p.fps(),
                        "fx": round(intr.fx, 3), "fy": round(intr.fy, 3),
                        "ppx": round(intr.ppx, 3), "ppy": round(intr.ppy, 3),
                        "hfov_deg": round(math.degrees(2 * math.atan(vp.width() / (2 * intr.fx))), 2),
                        "vfov_deg": round(math.degrees(2 * math.atan(vp.height() / (2 * intr.fy))), 2),
                        "model": str(intr.model).rsplit(".", 1)[-1],
                    })
            else:
                mode = f"{fmt} @{p.fps()}"
            streams.setdefault(st, set()).add(mode)
        entry = {"name": name, "streams": {k: sorted(v) for k, v in sorted(streams.items())}}
        if sensor.is_depth_sensor():
            try:
                entry["depth_scale"] = sensor.as_depth_sensor().get_depth_scale()
            except RuntimeError:
                pass
        sensors.append(entry)
    unique = {(d["width"], d["height"]): d for d in depth_intrinsics}  # same K at every fps
    return {**info, "sensors": sensors, "depth_intrinsics": [unique[k] for k in sorted(unique)]}


def device_warnings(desc: Dict) -> List[str]:
    """USB 2 links and old firmware: the two things that most often cripple a D435i."""
    out = []
    who = f"{desc.get('name', 'RealSense')} {desc.get('serial', '')}".strip()
    usb = desc.get("usb_type")
    if usb and usb.startswith("2"):
        out.append(f"{who}: connected over USB {usb}: depth at 848x480/30 fps needs USB 3 "
                   f"(use a USB 3 port and cable)")
    fw = _version_tuple(desc.get("firmware", ""))
    rec_str = desc.get("recommended_firmware") or RECOMMENDED_FIRMWARE
    rec = _version_tuple(rec_str)
    if fw is not None and rec is not None and fw < rec:
        out.append(f"{who}: firmware {desc['firmware']} is older than the recommended {rec_str} "
                   f"(update with rs-fw-update or the RealSense Viewer)")
    return out


def _config_warnings(robot, descs: List[Dict]) -> List[str]:
    out = []
    serials = {d.get("serial") for d in descs}
    for cam in robot.cameras:
        if cam.serial is None:
            if not descs:
                out.append(f"camera '{cam.name}' is not connected")
            elif len(descs) > 1:
                out.append(f"camera '{cam.name}' has no serial in {robot.source} and {len(descs)} devices are "
                           f"connected: set 'serial'")
            continue
        if cam.serial not in serials:
            out.append(f"camera '{cam.name}' (serial {cam.serial}) is not connected")
            continue
        desc = next(d for d in descs if d.get("serial") == cam.serial)
        modes = {(d["width"], d["height"]) for d in desc["depth_intrinsics"]}
        if (cam.width, cam.height) not in modes:
            out.append(f"camera '{cam.name}': depth {cam.width}x{cam.height} is not offered by {cam.serial}")
    return out


def cmd_cameras(args) -> int:
    from drivers.camera.realsense import load_pyrealsense2, pyrealsense2_version

    rs = load_pyrealsense2()
    ctx = rs.context()
    if args.file:
        p = Path(args.file)
        if not p.is_file():
            raise InputError(f"{p}: recording not found")
        try:
            devices = [ctx.load_device(str(p))]
        except RuntimeError as e:
            raise InputError(f"{p}: not a readable librealsense recording ({e})") from None
    else:
        devices = list(ctx.query_devices())
    descs = []
    for dev in devices:
        try:
            descs.append(describe_device(rs, dev))
        except RuntimeError as e:  # a device that vanished or is being reset while we looked
            raise DriverError(f"cannot query a RealSense device: {e}") from None
    warnings = [w for d in descs for w in device_warnings(d)]
    if args.robot:
        from robot.config import load_robot_config

        warnings += _config_warnings(load_robot_config(args.robot), descs)
    if args.json:
        print_json({"pyrealsense2": pyrealsense2_version(), "devices": descs, "warnings": warnings})
    else:
        _print_human(descs, warnings)
    if not descs:
        sys.stderr.write("robotctl cameras: no RealSense device connected\n")
        return 1
    return 0


def _print_human(descs: List[Dict], warnings: List[str]) -> None:
    w = sys.stdout.write
    for d in descs:
        w(f"{d.get('name', '?')}  serial {d.get('serial', '?')}  firmware {d.get('firmware', '?')}  "
          f"USB {d.get('usb_type', '?')}\n")
        for s in d["sensors"]:
            scale = f"  (depth scale {s['depth_scale']:g} m)" if "depth_scale" in s else ""
            w(f"  {s['name']}{scale}\n")
            for st, modes in s["streams"].items():
                shown = ", ".join(modes[:6]) + (f", ... ({len(modes)} modes)" if len(modes) > 6 else "")
                w(f"    {st}: {shown}\n")
        for k in d["depth_intrinsics"]:
            w(f"  depth {k['width']}x{k['height']}: fx {k['fx']} fy {k['fy']} ppx {k['ppx']} ppy {k['ppy']} "
              f"(hfov {k['hfov_deg']} deg, vfov {k['vfov_deg']} deg)\n")
    for msg in warnings:
        w(f"warning: {msg}\n")


def cmd_record_bag(args) -> int:
    import numpy as np

    from drivers.camera.bag import write_recording
    from drivers.sim.drive import simulate_run
    from drivers.sim.render import SimScene
    from robot.config import load_robot_config
    from robot.maps.plane_map import load_plane_map

    out = Path(args.out)
    if out.suffix != ".bag":
        raise InputError(f"{out}: the output must end in .bag (librealsense 2.55 writes ROS1 bags)")
    check_writable_file(out, "--out")
    if args.frames < 1:
        raise InputError(f"--frames must be >= 1, got {args.frames}")
    if not all(math.isfinite(v) for v in list(args.pose) + list(args.velocity)):
        raise InputError("--pose and --velocity must be finite numbers")
    robot = load_robot_config(args.robot)
    cam = robot.camera(args.camera)
    scene = SimScene(load_plane_map(args.map))
    frames, imu = simulate_run(robot, scene, cam.name, args.pose, args.velocity, frames=args.frames,
                               imu_rate=args.imu_rate, noise=None if args.no_noise else "default",
                               rng=np.random.default_rng(args.seed))
    rec = write_recording(out, frames, imu, fps=cam.fps, serial=cam.serial or f"SIM-{cam.name}")
    msg = {"out": str(out), "camera": cam.name, "frames": len(rec.frames), "imu_samples": len(imu),
           "width": rec.width, "height": rec.height, "fps": rec.fps, "bytes": out.stat().st_size}
    if args.json:
        print_json(msg)
    else:
        sys.stdout.write(f"wrote {out}: {msg['frames']} depth frames {rec.width}x{rec.height} at {rec.fps} fps"
                         f"{f', {len(imu)} IMU samples' if imu else ''} ({msg['bytes'] / 1e6:.1f} MB)\n")
    return 0


def register(sub) -> None:

    p = sub.add_parser("cameras", help="list connected RealSense devices, their streams and intrinsics")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.add_argument("--robot", help="robot config: also check its cameras' serials and resolutions")
    p.add_argument("--file", help="describe the device in a librealsense recording instead")
    p.set_defaults(func=cmd_cameras)

    r = sub.add_parser("record-bag", help="write a librealsense .bag of a simulated run (depth, optional IMU)")
    add_robot_map_args(r)
    r.add_argument("--pose", nargs=3, type=float, required=True, metavar=("X", "Y", "PHI"),
                   help="start pose (m, m, rad)")
    r.add_argument("--velocity", nargs=3, type=float, default=(0.0, 0.0, 0.0), metavar=("VX", "VY", "OMEGA"),
                   help="constant ground-frame velocity (m/s, m/s, rad/s); default still")
    r.add_argument("--camera", required=True, help="camera name in the robot config")
    r.add_argument("--frames", type=int_in(1, 10000), default=30, help="number of depth frames, 1 to 10000 (default 30)")
    r.add_argument("--imu-rate", type=float_in(0.0, 1000.0, "Hz"), default=0.0,
                   help="IMU samples per second (0 = no IMU; D435i: 200)")
    r.add_argument("--no-noise", action="store_true", help="exact depth, no stereo noise")
    r.add_argument("--seed", type=int_in(0, 2**32 - 1), default=0, help="noise seed")
    r.add_argument("--out", required=True, help="output .bag")
    r.add_argument("--json", action="store_true", help="print JSON")
    r.set_defaults(func=cmd_record_bag)
