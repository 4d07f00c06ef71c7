"""Replay a recorded run: redo localization and fusion from the recorded inputs and compare.

The app records every input of the fusion with a sequence number in the order the core consumed
it: the initial pose, each odometry and gyro sample, and for each localization the frame, the coarse pose
and covariance it started from and the method. Replay feeds a fresh ``ControllerCore`` the same
calls in the same order; the localizer is deterministic for a given frame and coarse pose (its
RNG is seeded by the frame number), so the fused poses must agree with the recorded ones to
rounding. A difference means the code or the config changed since the recording, which is what
a desk investigation of a field problem wants to see.

A frame the recorder skipped (over its depth bandwidth budget) cannot be localized again; its
recorded plane measurements are fused instead, so the fusion still replays exactly and the
report counts how many localizations were redone (``relocalized``) and how many were taken
from the record (``from_recorded_planes``).

The robot config and the map come from the recording itself unless overridden: the effective
config the run used (defaults as they were then), or for an older recording the YAML text it
loaded, read with today's defaults.
"""

from __future__ import annotations

import math
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np

from drivers.chassis.encoders import quantisation_variance
from robot.base.errors import InputError
from robot.base.samples import DepthFrame, WheelOdometry
from robot.config import RobotConfig, load_robot_config
from robot.config.calibration import calibrated_frame
from robot.control.core import ControllerCore
from robot.localization.localizer import LocalizationResult, Localizer
from robot.maps.plane_map import PlaneMap, load_plane_map
from robot.recording import schema as ms
from robot.recording.reader import RecordingReader


@dataclass
class ReplayReport:
    localizations: int = 0
    poses_compared: int = 0
    max_position_diff: float = 0.0  # m, replayed vs recorded fused pose
    max_heading_diff: float = 0.0  # rad
    fit_mismatches: List[str] = field(default_factory=list)  # localizations whose accepted planes differ
    missing_frames: int = 0  # localized frames with neither the frame nor its plane measurements recorded
    relocalized: int = 0  # localizations redone from the recorded frame
    from_recorded_planes: int = 0  # frames not recorded: their recorded plane measurements fused
    odometry: int = 0
    truncated: List[str] = field(default_factory=list)

    def ok(self, tol_position: float = 1e-6, tol_heading: float = 1e-6) -> bool:
        return (self.poses_compared > 0 and self.max_position_diff <= tol_position
                and self.max_heading_diff <= tol_heading and not self.fit_mismatches and self.missing_frames == 0)

    def to_json(self) -> Dict[str, object]:
        return {"localizations": self.localizations, "odometry": self.odometry, "poses_compared": self.poses_compared,
                "max_position_diff_m": self.max_position_diff, "max_heading_diff_rad": self.max_heading_diff,
                "fit_mismatches": self.fit_mismatches, "missing_frames": self.missing_frames,
                "relocalized": self.relocalized, "from_recorded_planes": self.from_recorded_planes,
                "truncated_segments": self.truncated, "identical": self.ok()}


def _config_from_recording(reader: RecordingReader) -> Tuple[RobotConfig, PlaneMap]:
    cfg = reader.config()
    if cfg is None:
        raise InputError(f"{reader.paths[0]}: the recording has no /config message; give --robot and --map")
    robot = reader.robot_config()
    with tempfile.TemporaryDirectory() as d:
        robot_path, map_path = Path(d) / "robot.yaml", Path(d) / "map.yaml"
        if robot is None:
            robot_path.write_text(cfg["robot_config_yaml"], encoding="utf-8")
            robot = load_robot_config(robot_path)
        map_path.write_text(cfg["map_yaml"], encoding="utf-8")
        return robot, load_plane_map(map_path)


def _recorded_result(path, msg: dict) -> LocalizationResult:
    """The fusion's input of a localization whose frame was not recorded: its recorded measurements."""
    try:
        measurements = [ms.measurement_from_json(m) for m in msg["measurements"]]
    except (TypeError, ValueError) as e:
        raise InputError(f"{path}: /planes of {msg.get('camera')} frame {msg.get('frame_number')}: {e}") from None
    return LocalizationResult(x=math.nan, y=math.nan, phi=math.nan, cov=np.full((3, 3), np.nan),
                              status=str(msg.get("status", "")), unobservable=[], planes=[], measurements=measurements)


def replay(path, robot: Optional[RobotConfig] = None, plane_map: Optional[PlaneMap] = None) -> ReplayReport:
    reader = RecordingReader(path)
    if robot is None or plane_map is None:
        rec_robot, rec_map = _config_from_recording(reader)
        robot, plane_map = robot or rec_robot, plane_map or rec_map
    # Pass 1: the fusion inputs and outputs, in the order the app made them.
    events: List[Tuple[int, str, dict]] = []
    needed = set()
    for m in reader.messages([ms.TOPIC_ODOMETRY, ms.TOPIC_PLANES, ms.TOPIC_POSE, ms.TOPIC_STATUS]):
        seq = m.message.get("seq") if isinstance(m.message, dict) else None
        if seq is None:
            continue
        if m.topic == ms.TOPIC_STATUS and m.message.get("event") != "set_pose":
            continue
        events.append((int(seq), m.topic, m.message))
        if m.topic == ms.TOPIC_PLANES:
            needed.add((m.message["camera"], int(m.message["frame_number"])))
    events.sort(key=lambda e: e[0])
    # Pass 2: only the depth frames that were localized.
    frames: Dict[Tuple[str, int], DepthFrame] = {}
    for m in reader.messages([ms.DEPTH_PREFIX]):
        f = m.message
        if (f.camera, int(f.frame_number)) in needed:
            frames[(f.camera, int(f.frame_number))] = f
    report = ReplayReport(truncated=[str(p) for p in reader.truncated])
    core = ControllerCore(robot, vision=True)
    localizer = Localizer(robot, plane_map)
    ticks = robot.chassis.ticks_per_rev
    skip = 0
    for i, (_, topic, msg) in enumerate(events):
        if skip:  # fused with the message before it (one fusion step of the app)
            skip -= 1
            continue
        if topic == ms.TOPIC_STATUS:
            try:
                hidden = ms.hidden_walls_from_json(msg.get("hidden_walls"))
            except ValueError as e:
                raise InputError(f"{path}: /status set_pose at t={msg.get('t')}: {e}") from None
            core.set_pose(msg["t"], msg["x"], msg["y"], msg["phi"], np.array(msg["cov"], float).reshape(3, 3),
                          hidden_walls=hidden)
        elif topic == ms.TOPIC_ODOMETRY and "gyro_wz" in msg:
            core.on_gyro(msg["t"], msg["gyro_wz"], msg["variance"])
        elif topic == ms.TOPIC_ODOMETRY:
            odo = WheelOdometry(t=msg["t"], angles=tuple(msg["angles"]), speeds=tuple(msg["wheel_speeds"]), dt=msg["dt"],
                                t_board=msg.get("t_board", msg["t"]))
            core.on_odometry(odo, quantisation_variance(ticks, odo.dt))
            report.odometry += 1
        elif topic == ms.TOPIC_PLANES:
            group = [msg] + [m for _, _, m in _same_fusion_step(events, i, msg)]
            results = []
            for m in group:
                result = _replayed_result(reader, frames, robot, localizer, m, report)
                if result is not None:
                    results.append((m, result))
            fused = core.on_localizations([(result, m["t"], m["camera"]) for m, result in results])
            report.localizations += len(results)
            for (m, _), rep in zip(results, fused):
                if sorted(rep.accepted) != sorted(m.get("accepted", [])):
                    report.fit_mismatches.append(f"{m['camera']} frame {m['frame_number']}: accepted "
                                                 f"{sorted(rep.accepted)} now, {sorted(m.get('accepted', []))} recorded")
            skip = len(group) - 1
        elif topic == ms.TOPIC_POSE and core.initialized:
            (x, y, phi), _ = core.pose(msg["t"])
            report.poses_compared += 1
            report.max_position_diff = max(report.max_position_diff, math.hypot(x - msg["x"], y - msg["y"]))
            report.max_heading_diff = max(report.max_heading_diff, abs(math.remainder(phi - msg["phi"], 2 * math.pi)))
    return report


def _same_fusion_step(events, i: int, msg) -> list:
    """The /planes events right after ``events[i]`` that the app fused in the same step as ``msg``
    (recordings before fusion steps were recorded fused every frame alone)."""
    step = msg.get("fusion_step")
    out = []
    if step is None:
        return out
    for e in events[i + 1:]:
        if e[1] != ms.TOPIC_PLANES or e[2].get("fusion_step") != step:
            break
        out.append(e)
    return out


def _replayed_result(reader, frames, robot, localizer, msg, report):
    """The localization of one /planes message: redone on its recorded frame, else the recorded
    measurements; None (counted) when neither was recorded."""
    frame = frames.get((msg["camera"], int(msg["frame_number"])))
    if frame is not None:
        cov = np.array(msg["coarse_cov"], float).reshape(3, 3)
        frame = calibrated_frame(frame, robot.camera(frame.camera).depth_scale)  # as the app did
        report.relocalized += 1
        return localizer.localize([frame], tuple(msg["coarse"]), cov, msg.get("method", "joint"))
    if "measurements" in msg:
        report.from_recorded_planes += 1
        return _recorded_result(reader.paths[0], msg)
    report.missing_frames += 1
    return None
