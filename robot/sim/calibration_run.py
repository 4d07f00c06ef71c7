"""Calibration data from a simulated drive or from a recorded run (``robotctl calibrate --sim | --from``).

``collect_sim`` drives the planned calibration motion (``robot.control.calibration_path``) on the
simulated-clock runner in a world whose robot differs from its config (``WorldSettings``:
depth scale errors, mount errors, wheel radius errors) and keeps what the core saw: every wheel
report and the planes of every localization that the pose filter accepted, with the true pose
of each frame for the evaluation. ``true_parameters`` says what a perfect calibration would find
in that world. ``collect_recording`` redoes the localizations of a recorded run (the frames it
localized, from the coarse poses it used, with the config it ran with) and reads its wheel reports.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Dict, Optional, Sequence, Tuple

import numpy as np

from drivers.sim.world import SimWorld
from robot.base.errors import InputError
from robot.base.samples import WheelOdometry
from robot.calibration.collect import Collector
from robot.calibration.model import Dataset, ParamLayout
from robot.config import RobotConfig
from robot.config.calibration import calibrated_frame
from robot.control.calibration_path import clearance_for, plan_calibration_motion
from robot.control.path_file import PathPlan
from robot.localization.localizer import Localizer
from robot.maps.plane_map import PlaneMap
from robot.sim.runner import RunResult, RunSettings, run_path


class _Tap:
    """What the runner's core sees, kept for the calibration."""

    def __init__(self, robot: RobotConfig):
        self.collector = Collector(robot)
        self._truth: Dict[float, Tuple[float, float, float]] = {}

    def on_odometry(self, odo: WheelOdometry) -> None:
        self.collector.add_odometry(odo)

    def on_capture(self, frames, result) -> None:
        if frames and frames[0].truth is not None:
            self._truth[float(frames[0].t_capture)] = tuple(frames[0].truth)  # type: ignore[assignment]

    def on_fused(self, result, t_capture: float, report) -> None:
        self.collector.add_localization(result, t_capture, accepted=report.accepted,
                                        truth=self._truth.pop(float(t_capture), None))


@dataclass
class SimCollection:
    data: Dataset
    truth: np.ndarray  # the parameter vector of the simulated robot (``true_parameters``)
    run: RunResult
    plan: PathPlan


def true_parameters(robot: RobotConfig, plane_map: PlaneMap, start: Sequence[float], settings: RunSettings) -> np.ndarray:
    """The parameter vector (``ParamLayout`` order) of the robot the simulated world really has."""
    world = SimWorld(settings.world_robot or robot, plane_map, start, settings.world)
    layout = ParamLayout([c.name for c in robot.cameras])
    theta = layout.nominal(world.true_robot)
    noise = settings.world.depth_noise
    for cam in robot.cameras:
        e = noise.scale_error_of(cam.name) if noise is not None else 0.0
        theta[layout.index(f"{cam.name}.depth_scale")] = 1.0 / (1.0 + e)
    odo = layout.odometry_slice
    rolling = np.asarray(world.board.rolling) * (1.0 - world.board.slip_noise * math.sqrt(2.0 / math.pi))
    radii = world.board.r * rolling  # effective radius of each wheel
    H = np.array([[-1.0, -1.0, 1.0], [1.0, 1.0, 1.0], [1.0, -1.0, -1.0], [-1.0, 1.0, -1.0]])
    theta[odo.start] = float(radii.mean())
    theta[odo.start + 1:odo.start + 4] = H.T @ (radii - radii.mean()) / 4.0
    theta[odo.start + 4] = world.board.L
    return theta


def collect_sim(robot: RobotConfig, plane_map: PlaneMap, start: Sequence[float], settings: RunSettings,
                plan: Optional[PathPlan] = None) -> SimCollection:
    """Drive the calibration motion (or ``plan``) in the simulated world and keep its data."""
    plan = plan or plan_calibration_motion(plane_map, start, speed=min(0.30, robot.control.max_speed),
                                           clearance=clearance_for(robot))
    tap = _Tap(robot)
    run = run_path(robot, plane_map, plan, settings, tap=tap)
    return SimCollection(tap.collector.dataset(), true_parameters(robot, plane_map, start, settings), run, plan)


def collect_recording(path, robot: Optional[RobotConfig] = None, plane_map: Optional[PlaneMap] = None) -> Dataset:
    """The calibration data of a recorded run: its localized frames localized again from the coarse
    poses it used (accepted planes as recorded), and its wheel reports. ``robot``/``plane_map``:
    instead of the config and map the recording carries."""
    from robot.recording import schema as ms
    from robot.recording.reader import RecordingReader
    from robot.sim.replay import _config_from_recording as config_from_recording

    reader = RecordingReader(path)
    if robot is None or plane_map is None:
        rec_robot, rec_map = config_from_recording(reader)
        robot, plane_map = robot or rec_robot, plane_map or rec_map
    collector = Collector(robot)
    planes = []
    for m in reader.messages([ms.TOPIC_ODOMETRY, ms.TOPIC_PLANES]):
        msg = m.message
        if not isinstance(msg, dict):
            continue
        if m.topic == ms.TOPIC_ODOMETRY and "angles" in msg:
            collector.odometry.add(float(msg["t"]), [float(a) for a in msg["angles"]])
        elif m.topic == ms.TOPIC_PLANES and "frame_number" in msg and msg.get("accepted"):
            planes.append(msg)
    wanted = {(p["camera"], int(p["frame_number"])): p for p in planes}
    localizer = Localizer(robot, plane_map)
    found = 0
    for m in reader.messages([ms.DEPTH_PREFIX]):
        f = m.message
        p = wanted.get((f.camera, int(f.frame_number)))
        if p is None:
            continue
        found += 1
        frame = calibrated_frame(f, robot.camera(f.camera).depth_scale)
        cov = np.array(p["coarse_cov"], float).reshape(3, 3)
        result = localizer.localize([frame], tuple(p["coarse"]), cov, p.get("method", "joint"))
        collector.add_localization(result, float(p["t"]), accepted=p.get("accepted"), truth=f.truth)
    if not planes:
        raise InputError(f"{path}: the recording has no localizations with accepted planes to calibrate from")
    if found == 0:
        raise InputError(f"{path}: the recording has none of the depth frames its localizations used "
                         "(recorded without depth?)")
    if len(collector.odometry) < 2:
        raise InputError(f"{path}: the recording has no wheel odometry")
    return collector.dataset()
