"""The app in real time on fakes: the firmware emulator on a real pty (the unmodified serial driver
talks to it) and fake cameras that render what the robot truly sees. Used by ``robotctl sim
--realtime``, ``robotctl teleop --sim``, the tests and the controller benchmark."""

from __future__ import annotations

import asyncio
import math
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Iterator, List, Optional

from drivers.camera.sim import SimCamera
from drivers.chassis.emulator import FirmwareEmulator
from drivers.chassis.serial_chassis import SerialChassis
from drivers.sim.world import sample_world
from robot.app.controller import AppOptions, RobotApp
from robot.config import RobotConfig
from robot.control.path_file import PathPlan
from robot.maps.plane_map import PlaneMap
from robot.sim.runner import DwellWatcher


@dataclass(frozen=True)
class RealtimeSimSettings:
    fps: Optional[float] = None  # camera rate; None = the robot config's
    decimation: int = 4
    frame_cache: int = 0  # >0: cycle this many pre-rendered frames (robot standing still)
    seed: int = 0
    radius_error_std: float = 0.01
    slip_noise: float = 0.005
    clutter: int = 0


@dataclass
class SimRig:
    app: RobotApp
    emulator: FirmwareEmulator
    cameras: List[SimCamera]


@contextmanager
def sim_rig(robot: RobotConfig, plane_map: PlaneMap, start, settings: RealtimeSimSettings = RealtimeSimSettings(),
            options: Optional[AppOptions] = None, **app_kwargs) -> Iterator[SimRig]:
    """Emulator + fake cameras + app, torn down on exit. ``start``: the true initial pose."""
    radius_error, scene = sample_world(plane_map, start, settings.seed, settings.radius_error_std, settings.clutter)
    emulator = FirmwareEmulator(robot.chassis, radius_error=radius_error, slip_noise=settings.slip_noise,
                                seed=settings.seed)
    emulator.board.pose = tuple(float(v) for v in start)
    emulator.start()
    cameras = [SimCamera(robot, c.name, scene, lambda: emulator.pose, fps=settings.fps, decimation=settings.decimation,
                         seed=settings.seed * 10 + i, cache=settings.frame_cache,
                         imu_rate=float(c.realsense.gyro_fps) if c.realsense.imu_enabled else 0.0)
               for i, c in enumerate(robot.cameras)]
    chassis = SerialChassis(robot.chassis, port=emulator.port)
    app = RobotApp(robot, plane_map, cameras, chassis, options, **app_kwargs)
    try:
        yield SimRig(app, emulator, cameras)
    finally:
        emulator.close()


def run_realtime(robot: RobotConfig, plane_map: PlaneMap, plan: PathPlan, args) -> int:
    """``robotctl sim --realtime``: one run of the full app; prints the error at each target."""
    start = (plan.start.x, plan.start.y, plan.start.heading)
    settings = RealtimeSimSettings(fps=args.vision_rate, decimation=args.decimation, clutter=args.clutter)
    options = AppOptions(vision="vision" in args.modes.split(","), method=args.method,
                         install_signal_handlers=True)
    recorder = None
    if args.record:
        from robot.recording.recorder import BackgroundRecorder, Recorder

        recorder = BackgroundRecorder(Recorder(args.record))
    errors = []
    dwell = DwellWatcher()

    def on_tick(app: RobotApp, t: float) -> None:
        reached = dwell.finished_dwell(app.core.trajectory)
        if reached is not None:
            wp = plan.waypoints[reached]
            x, y, _ = rig.emulator.pose
            errors.append((reached, math.hypot(x - wp.x, y - wp.y)))
            print(f"target {reached + 1}: ({wp.x:.2f}, {wp.y:.2f}) reached, true error {errors[-1][1] * 1e3:.1f} mm; "
                  f"{app.status_line()}", flush=True)

    with sim_rig(robot, plane_map, start, settings, options, plan=plan, recorder=recorder, on_tick=on_tick) as rig:
        rc = asyncio.run(rig.app.run())
    print(f"stopped: {rig.app.exit_reason}; {len(errors)}/{len(plan.waypoints)} targets reached")
    return rc if len(errors) == len(plan.waypoints) or rig.app.exit_reason.startswith("signal") else 1
