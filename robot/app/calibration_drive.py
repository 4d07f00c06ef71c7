"""``robotctl calibrate`` on the robot: drive the calibration motion with the real app and record it.

The robot runs its ordinary controller (the same ``RobotApp``, the configured localizer and pose
filter, the protective stop) along the motion ``robot.control.calibration_path`` planned from where
it stands, and records the run (depth frames the localizer used, wheel reports, planes). The
calibration is then computed from that recording (``robot.sim.calibration_run.collect_recording``),
exactly as ``--from RUN.mcap`` would, so a drive can be calibrated again later from its file.
"""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import List, Optional, Sequence

from robot.app.assemble import build_rig
from robot.app.controller import AppOptions, RobotApp
from robot.base.errors import ConfigError, DriverError
from robot.config import RobotConfig
from robot.control.path_file import PathPlan
from robot.maps.plane_map import PlaneMap


def record_calibration_drive(robot: RobotConfig, plane_map: PlaneMap, plan: PathPlan, record_dir,
                             kind: str = "hardware", start: Optional[Sequence[float]] = None,
                             startup_timeout: float = 10.0) -> List[str]:
    """Drive ``plan`` with the app on ``kind`` drivers and record it in ``record_dir``; the MCAP files.
    DriverError when the run does not complete (the robot is then stopped, like any app run)."""
    from robot.recording.recorder import BackgroundRecorder, Recorder

    d = Path(record_dir)
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ConfigError(f"{d}: cannot create the recording directory: {e}") from None
    recorder = BackgroundRecorder(Recorder(str(d / "calibration-{start}.mcap"), compression="none"))
    rig = build_rig(kind, robot, plane_map, start)
    try:
        app = RobotApp(robot, plane_map, rig.cameras, rig.chassis,
                       AppOptions(stop_when_done=True, startup_timeout=startup_timeout), plan=plan, recorder=recorder)
        rc = asyncio.run(app.run())
    finally:
        rig.close()
    if rc != 0 or app.exit_reason != "path complete":
        raise DriverError(f"the calibration drive did not complete: {app.exit_reason or 'the controller failed to start'}")
    return list(recorder.files)
