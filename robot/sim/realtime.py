"""The app in real time on fakes: the firmware emulator on a real pty (the unmodified serial driver
talks to it) and fake cameras that render what the robot truly sees, built by
``robot.app.assemble.build_rig("sim", ...)``. Used by ``robotctl sim --realtime``, the tests and
the controller benchmark."""

from __future__ import annotations

import asyncio
import math
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Iterator, List, Optional

from drivers.camera.sim import SimCamera
from drivers.chassis.emulator import FirmwareEmulator
from robot.app.assemble import build_rig
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
    rig = build_rig("sim", robot, plane_map, start, fps=settings.fps, decimation=settings.decimation,
                    frame_cache=settings.frame_cache, seed=settings.seed, radius_error_std=settings.radius_error_std,
                    slip_noise=settings.slip_noise, clutter=settings.clutter)
    try:
        app = RobotApp(robot, plane_map, rig.cameras, rig.chassis, options, **app_kwargs)
        yield SimRig(app, rig.emulator, rig.cameras)  # type: ignore[arg-type]
    finally:
        rig.close()


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

    async def main() -> int:
        kidnap = getattr(args, "kidnap_at", None)
        if kidnap:
            t_k, x_k, y_k, phi_k = kidnap
            asyncio.get_running_loop().call_later(t_k, kidnapped, x_k, y_k, phi_k)
        return await rig.app.run()

    def kidnapped(x: float, y: float, phi: float) -> None:
        print(f"kidnap: the robot is carried to ({x:.2f}, {y:.2f}, {math.degrees(phi):.0f} deg)", flush=True)
        rig.emulator.teleport(x, y, phi)

    with sim_rig(robot, plane_map, start, settings, options, plan=plan, recorder=recorder, on_tick=on_tick) as rig:
        rc = asyncio.run(main())
    print(f"stopped: {rig.app.exit_reason}; {len(errors)}/{len(plan.waypoints)} targets reached")
    return rc if len(errors) == len(plan.waypoints) or rig.app.exit_reason.startswith("signal") else 1
