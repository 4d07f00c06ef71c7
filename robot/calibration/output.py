"""From a solve to a calibration file: only what the data observed, in the config's units.

The standard deviations of a depth scale and of a mount's three angles are written as data (the
localizer's error model takes them, with a floor: ``apply_calibration``); those of the mount
position and of the odometry go into comments.

A mount is written as a whole (``xyz`` and ``rpy_deg`` are triples in the file format); its
components the data did not observe keep the configured value, and the file says which, in a
comment. A depth scale, a wheel radius or lx + ly that was not observed is not written at all.
The differences between the wheels are estimated (they would otherwise bias the mount yaw) but
the file format has no place for them: they are reported, not written.
"""

from __future__ import annotations

import math
from typing import Dict, List, Tuple

from robot.calibration.solver import CalibrationResult
from robot.config import RobotConfig
from robot.config.calibration import Calibration, CameraCalibration, OdometryCalibration


def _fmt_std(kind: str, std: float) -> str:
    if kind in ("roll", "pitch", "yaw"):
        return f"{math.degrees(std):.3f} deg"
    if kind == "depth_scale":
        return f"{std * 100:.3f} %"
    return f"{std * 1000:.2f} mm"


def to_calibration(result: CalibrationResult, robot: RobotConfig, source: str = "<calibration>"
                   ) -> Tuple[Calibration, Dict[str, List[str]]]:
    """The calibration to write and the comments that go with it (``calibration_yaml``)."""
    by_name = {r.name: r for r in result.reports}
    cameras: Dict[str, CameraCalibration] = {}
    comments: Dict[str, List[str]] = {}
    for cam in robot.cameras:
        notes: List[str] = []
        s = by_name[f"{cam.name}.depth_scale"]
        scale = s.value if s.observable else None
        scale_std = s.std if s.observable else None  # written as data: the error model uses it (apply_calibration)
        xyz = rpy = rpy_std = None
        pos = [by_name[f"{cam.name}.{k}"] for k in ("x", "y", "z")]
        ang = [by_name[f"{cam.name}.{k}"] for k in ("roll", "pitch", "yaw")]
        if any(r.observable for r in pos):
            xyz = tuple(r.value if r.observable else v for r, v in zip(pos, cam.mount_xyz))
        if any(r.observable for r in ang):
            rpy = tuple(math.degrees(r.value) if r.observable else v for r, v in zip(ang, cam.mount_rpy_deg))
        if all(r.observable for r in ang):
            rpy_std = tuple(math.degrees(r.std) for r in ang)
        for r in pos + (ang if rpy_std is None else []):
            kind = r.name.rsplit(".", 1)[1]
            if r.observable:
                notes.append(f"{kind} std {_fmt_std(kind, r.std)}")
        held = [r.name.rsplit(".", 1)[1] for r in pos + ang if not r.observable]
        if held and (xyz is not None or rpy is not None):
            notes.append(f"not observed, kept as configured: {', '.join(held)}")
        if scale is not None or xyz is not None or rpy is not None:
            cameras[cam.name] = CameraCalibration(scale, xyz, rpy, scale_std, rpy_std)  # type: ignore[arg-type]
            comments[cam.name] = ["; ".join(notes)] if notes else []
    r = by_name["odometry.wheel_radius"]
    L = by_name["odometry.lx_plus_ly"]
    odo = OdometryCalibration(r.value if r.observable else None, L.value if L.observable else None)
    notes = [f"{x.name.rsplit('.', 1)[1]} std {x.std * 1000:.3f} mm" for x in (r, L) if x.observable]
    diffs = [by_name[f"odometry.wheel_diff_{k}"] for k in ("crab", "turn", "axle")]
    if any(d.observable for d in diffs):
        notes.append("wheel differences (reported, not part of the format): " + ", ".join(
            f"{d.name.rsplit('_', 1)[1]} {d.value * 1000:+.3f} mm" for d in diffs if d.observable))
    comments["odometry"] = ["; ".join(notes)] if notes else []
    return Calibration(cameras, odo, source), comments
