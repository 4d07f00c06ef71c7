"""The calibration file (``calibration.yaml``): measured values that replace hand-typed ones.

What it may hold (every key optional; ``docs/calibration.md``)::

    cameras:
      front:
        depth_scale: 0.990099          # multiplies the depth the camera reports (reads 1 % long: 1 / 1.01)
        depth_scale_std: 0.0004        # its 1-sigma uncertainty (a fraction), as the calibration measured it
        mount: {xyz: [0.11, 0.0175, 0.12], rpy_deg: [0.0, 0.0, 0.5],    # replaces the robot config's mount
                rpy_std_deg: [0.01, 0.02, 0.01]}                       # 1-sigma of each angle, measured
    odometry:
      wheel_radius: 0.0303             # m, the effective rolling radius
      lx_plus_ly: 0.160                # m, the Mecanum L = lx + ly the turn rate is computed with

``robotctl calibrate`` writes it; other tools may too, so reading is as strict as for the robot
config: unknown keys, values outside their ranges and cameras the robot does not have are one
``ConfigError`` naming the file, the key and the range. The robot config names the file with
``calibration: FILE`` (relative to the config), ``--calibration FILE`` replaces that on the
commands that drive or localize, and :func:`apply_calibration` is the one place where the values
enter a ``RobotConfig``: mounts and depth scales go into the cameras' sections, the radius and
L into the chassis section (lx and ly scaled together, since only their sum is measured), so
everything downstream (localizer, kinematics, filter) sees calibrated values and none of it
knows there was a file.

A calibrated camera is also a better known one. Once the file gives every camera's depth scale,
the localizer's error model takes ``localizer.calibrated_depth_scale_std`` (0.25 %, or the
file's ``depth_scale_std`` where that is larger) for the uncalibrated ``depth_scale_std`` (1 %);
likewise the mount angles with ``rpy_std_deg``. The floor is there because a scale measured to
0.04 % today is not known that well next week (temperature, knocks); the online calibration
warns when its estimate leaves three of those standard deviations.

A calibration also has to stay near the config it corrects: a radius 10 % off, or a mount
moved by more than 0.1 m or 10 degrees, is another robot's file or a typo, not a calibration.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Dict, List, Optional, Tuple

from robot.base.errors import ConfigError
from robot.base.files import CALIBRATION, atomic_write_text
from robot.base.samples import DepthFrame
from robot.config.ranges import Range
from robot.config.schema import Section, load_yaml_file
from robot.config.sections import MAX_MOUNT_OFFSET, LocalizerConfig

if TYPE_CHECKING:  # the loader imports this module: no import of it at run time
    from robot.config.loader import RobotConfig

DEPTH_SCALE_RANGE = Range(0.9, 1.1, "x")  # a D435i is 0.5 to 2 % off; 10 % is a broken or foreign camera
MOUNT_XYZ_RANGE = Range(-MAX_MOUNT_OFFSET, MAX_MOUNT_OFFSET, "m")
MOUNT_RPY_RANGE = Range(-360.0, 360.0, "deg")
DEPTH_SCALE_STD_RANGE = Range(0.0, 0.1, "")
MOUNT_RPY_STD_RANGE = Range(0.0, 10.0, "deg")
WHEEL_RADIUS_RANGE = Range(0.005, 0.5, "m")
LX_PLUS_LY_RANGE = Range(0.02, 4.0, "m")
# How far a calibration may move a value from the robot config it corrects.
MAX_RADIUS_CHANGE = 0.10  # relative
MAX_L_CHANGE = 0.20  # relative
MAX_MOUNT_SHIFT = 0.10  # m per axis
MAX_MOUNT_TURN_DEG = 10.0  # per angle


@dataclass(frozen=True)
class CameraCalibration:
    depth_scale: Optional[float] = None
    mount_xyz: Optional[Tuple[float, float, float]] = None
    mount_rpy_deg: Optional[Tuple[float, float, float]] = None
    depth_scale_std: Optional[float] = None  # 1-sigma of depth_scale as measured (a fraction)
    mount_rpy_std_deg: Optional[Tuple[float, float, float]] = None  # 1-sigma of each mount angle as measured

    @property
    def empty(self) -> bool:
        return all(v is None for v in dataclasses.astuple(self))


@dataclass(frozen=True)
class OdometryCalibration:
    wheel_radius: Optional[float] = None
    lx_plus_ly: Optional[float] = None


@dataclass(frozen=True)
class Calibration:
    cameras: Dict[str, CameraCalibration] = field(default_factory=dict)
    odometry: OdometryCalibration = field(default_factory=OdometryCalibration)
    source: str = "<calibration>"

    @property
    def empty(self) -> bool:
        return all(c.empty for c in self.cameras.values()) and self.odometry == OdometryCalibration()


def _ranged_vector(sec: Section, key: str, rng: Range) -> Optional[Tuple[float, float, float]]:
    if not sec.has(key):
        return None
    return sec.vector(key, 3, rng=rng)


def parse_calibration(data, source: str = "<calibration>") -> Calibration:
    """The calibration in ``data`` (a parsed YAML document); ConfigError naming ``source`` and the key."""
    top = Section(data, "", source)
    cameras: Dict[str, CameraCalibration] = {}
    raw = top.raw("cameras", None)
    if raw is None:
        raw = {}
    if not isinstance(raw, dict):
        top.fail(f"'cameras' must be a mapping of camera name to its calibration, got {type(raw).__name__}")
    for name, entry in raw.items():
        if not isinstance(name, str) or not name or len(name) > 64:
            top.fail(f"cameras: names must be non-empty strings of up to 64 characters, got {name!r}")
        sec = Section(entry, f"cameras.{name}", source)
        scale = sec.ranged("depth_scale", DEPTH_SCALE_RANGE) if sec.has("depth_scale") else None
        scale_std = sec.ranged("depth_scale_std", DEPTH_SCALE_STD_RANGE) if sec.has("depth_scale_std") else None
        if scale_std is not None and scale is None:
            sec.fail("'depth_scale_std' without 'depth_scale': the uncertainty of a scale the file does not give")
        xyz = rpy = rpy_std = None
        if sec.has("mount"):
            mount = sec.sub("mount")
            xyz = _ranged_vector(mount, "xyz", MOUNT_XYZ_RANGE)
            rpy = _ranged_vector(mount, "rpy_deg", MOUNT_RPY_RANGE)
            rpy_std = _ranged_vector(mount, "rpy_std_deg", MOUNT_RPY_STD_RANGE)
            if rpy_std is not None and rpy is None:
                mount.fail("'rpy_std_deg' without 'rpy_deg': the uncertainty of angles the file does not give")
            mount.done()
        sec.done()
        cameras[name] = CameraCalibration(scale, xyz, rpy, scale_std, rpy_std)
    odo = top.sub("odometry")
    radius = odo.ranged("wheel_radius", WHEEL_RADIUS_RANGE) if odo.has("wheel_radius") else None
    length = odo.ranged("lx_plus_ly", LX_PLUS_LY_RANGE) if odo.has("lx_plus_ly") else None
    odo.done()
    top.done()
    return Calibration(cameras, OdometryCalibration(radius, length), source)


def load_calibration(path) -> Calibration:
    return parse_calibration(load_yaml_file(path, CALIBRATION), source=str(path))


def _near(cal: Calibration, where: str, value: float, nominal: float, limit: float, unit: str) -> None:
    if abs(value - nominal) > limit:
        raise ConfigError(f"{cal.source}: {where}: {value:g} {unit} is more than {limit:g} {unit} from the robot "
                          f"config's {nominal:g} {unit} (allowed: [{nominal - limit:g}, {nominal + limit:g}] {unit}): "
                          "a calibration of another robot, or a typo")


def apply_calibration(robot: RobotConfig, cal: Optional[Calibration]) -> RobotConfig:
    """``robot`` with the calibration's values in place of the config's; ConfigError naming the
    calibration file when it names a camera the robot lacks or moves a value implausibly far."""
    if cal is None or cal.empty:
        return robot
    names = [c.name for c in robot.cameras]
    unknown = sorted(set(cal.cameras) - set(names))
    if unknown:
        raise ConfigError(f"{cal.source}: cameras: unknown camera(s) {', '.join(unknown)} "
                          f"(the robot config {robot.source} has {', '.join(names)})")
    cams = []
    for cam in robot.cameras:
        c = cal.cameras.get(cam.name)
        if c is None:
            cams.append(cam)
            continue
        changes: Dict[str, object] = {}
        if c.depth_scale is not None:
            changes["depth_scale"] = float(c.depth_scale)
        if c.mount_xyz is not None:
            for axis, v, v0 in zip("xyz", c.mount_xyz, cam.mount_xyz):
                _near(cal, f"cameras.{cam.name}.mount.xyz ({axis})", v, v0, MAX_MOUNT_SHIFT, "m")
            changes["mount_xyz"] = tuple(float(v) for v in c.mount_xyz)
        if c.mount_rpy_deg is not None:
            for axis, v, v0 in zip(("roll", "pitch", "yaw"), c.mount_rpy_deg, cam.mount_rpy_deg):
                if abs(math.remainder(v - v0, 360.0)) > MAX_MOUNT_TURN_DEG:  # 359 deg and -1 deg are one angle
                    _near(cal, f"cameras.{cam.name}.mount.rpy_deg ({axis})", v, v0, MAX_MOUNT_TURN_DEG, "deg")
            changes["mount_rpy_deg"] = tuple(float(v) for v in c.mount_rpy_deg)
        try:
            cams.append(dataclasses.replace(cam, **changes))
        except ConfigError as e:
            raise ConfigError(f"{cal.source}: cameras.{cam.name}: {e}") from None
    chassis = robot.chassis
    localizer = calibrated_error_model(robot.localizer, [cal.cameras.get(name) for name in names])
    o = cal.odometry
    ch: Dict[str, float] = {}
    if o.wheel_radius is not None:
        _near(cal, "odometry.wheel_radius", o.wheel_radius, chassis.wheel_radius,
              MAX_RADIUS_CHANGE * chassis.wheel_radius, "m")
        ch["wheel_radius"] = float(o.wheel_radius)
    if o.lx_plus_ly is not None:
        L0 = chassis.half_wheelbase + chassis.half_track
        _near(cal, "odometry.lx_plus_ly", o.lx_plus_ly, L0, MAX_L_CHANGE * L0, "m")
        # Only the sum is measured (the turn rate): lx and ly keep their ratio.
        k = float(o.lx_plus_ly) / L0
        ch["half_wheelbase"] = chassis.half_wheelbase * k
        ch["half_track"] = chassis.half_track * k
    if ch:
        try:
            chassis = dataclasses.replace(chassis, **ch)
        except ConfigError as e:
            raise ConfigError(f"{cal.source}: odometry: {e}") from None
    return dataclasses.replace(robot, cameras=tuple(cams), chassis=chassis, localizer=localizer)


def calibrated_error_model(localizer: LocalizerConfig, cams: List[Optional[CameraCalibration]]) -> LocalizerConfig:
    """The localizer section with the error model of calibrated cameras (``cams``: each camera's
    calibration, None for none): the depth scale std once every camera's scale is calibrated, the
    mount angle std once every camera's angles are; each the configured floor for a calibrated
    camera, or the largest std the file gives where that is larger. Otherwise as configured: one
    camera still off by its uncalibrated 1 % is what the shared model must cover."""
    changes: Dict[str, float] = {}
    if cams and all(c is not None and c.depth_scale is not None for c in cams):
        stds = [c.depth_scale_std for c in cams if c is not None and c.depth_scale_std is not None]
        changes["depth_scale_std"] = max([localizer.calibrated_depth_scale_std] + stds)
    if cams and all(c is not None and c.mount_rpy_deg is not None for c in cams):
        stds = [max(c.mount_rpy_std_deg) for c in cams if c is not None and c.mount_rpy_std_deg is not None]
        changes["mount_angle_std_deg"] = max([localizer.calibrated_mount_angle_std_deg] + stds)
    return dataclasses.replace(localizer, **changes) if changes else localizer


def error_model_note(loc: LocalizerConfig) -> str:
    """What the localizer assumes of the cameras' systematic errors: the controller logs it at start-up,
    ``robotctl calibrate`` prints it for the file it writes."""
    calibrated = (loc.depth_scale_std <= loc.calibrated_depth_scale_std
                  and loc.mount_angle_std_deg <= loc.calibrated_mount_angle_std_deg)
    return (f"localizer error model: depth scale std {loc.depth_scale_std * 100:.2f} %, mount angle std "
            f"{loc.mount_angle_std_deg:.2f} deg" + ("" if calibrated else
                                                  " (a calibration file of every camera's scale and mount lowers them)"))


def calibrated_frame(frame: DepthFrame, depth_scale: float) -> DepthFrame:
    """The frame with its metres per depth unit multiplied by the camera's calibrated ``depth_scale``
    (the pixels are shared, not copied). What every shell hands the localizer."""
    if depth_scale == 1.0:
        return frame
    return dataclasses.replace(frame, depth_scale=float(frame.depth_scale) * float(depth_scale))


# -- writing ---------------------------------------------------------------------------------------


def _num(v: float, digits: int) -> str:
    text = f"{v:.{digits}f}".rstrip("0")
    return text + "0" if text.endswith(".") else text


def calibration_yaml(cal: Calibration, comments: Optional[Dict[str, List[str]]] = None) -> str:
    """The YAML text of ``cal`` in the documented format. ``comments``: lines written above the
    cameras' and the odometry's entries (key: camera name or ``odometry``; ``""``: the file's head)."""
    comments = comments or {}
    out = [f"# {line}" for line in comments.get("", [])]
    cams = [(n, c) for n, c in cal.cameras.items() if not c.empty]
    if cams:
        out.append("cameras:")
        for name, c in cams:
            out += [f"  # {line}" for line in comments.get(name, [])]
            out.append(f"  {name}:")
            if c.depth_scale is not None:
                out.append(f"    depth_scale: {_num(c.depth_scale, 7)}")
            if c.depth_scale_std is not None:
                out.append(f"    depth_scale_std: {_num(c.depth_scale_std, 7)}")
            parts = []
            if c.mount_xyz is not None:
                parts.append("xyz: [" + ", ".join(_num(v, 5) for v in c.mount_xyz) + "]")
            if c.mount_rpy_deg is not None:
                parts.append("rpy_deg: [" + ", ".join(_num(v, 4) for v in c.mount_rpy_deg) + "]")
            if c.mount_rpy_std_deg is not None:
                parts.append("rpy_std_deg: [" + ", ".join(_num(v, 5) for v in c.mount_rpy_std_deg) + "]")
            if parts:
                out.append("    mount: {" + ", ".join(parts) + "}")
    o = cal.odometry
    if o.wheel_radius is not None or o.lx_plus_ly is not None:
        out += [f"# {line}" for line in comments.get("odometry", [])]
        out.append("odometry:")
        if o.wheel_radius is not None:
            out.append(f"  wheel_radius: {_num(o.wheel_radius, 7)}")
        if o.lx_plus_ly is not None:
            out.append(f"  lx_plus_ly: {_num(o.lx_plus_ly, 6)}")
    if not cams and o == OdometryCalibration():
        out.append("{}")
    return "\n".join(out) + "\n"


def write_calibration(path, text: str) -> Path:
    """Write ``text`` to ``path`` atomically (a temporary file beside it, then a rename)."""
    p = Path(path)
    atomic_write_text(p, text)
    return p


__all__ = ["Calibration", "CameraCalibration", "OdometryCalibration", "apply_calibration", "calibrated_frame",
           "calibration_yaml", "load_calibration", "parse_calibration", "write_calibration"]
