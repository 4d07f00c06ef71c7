"""Drivers by name: the one place that decides which backends a command runs on.

The command-line modules turn their flags into a kind and ask here; nothing else builds the
drivers an application runs with.

- ``build_chassis(kind, config, port)``: "serial", the motor board on a serial port (default
  ``config.port``); "emulator", the firmware emulator on a pseudo-terminal, started here and
  closed with the chassis, with the unmodified serial driver talking to it.
- ``board_port(kind, config, port)``: the same choice for bench tools that open the port
  themselves: where the board answers, and the emulator when there is one.
- ``build_cameras(kind, robot)``: "realsense", every configured camera by its serial; "sim",
  frames rendered from a simulated scene at a pose the caller supplies; "bag", one librealsense
  recording per configured camera, played back as that camera.
- ``build_rig(kind, robot, plane_map, start)``: a whole robot's drivers: "hardware" (serial
  board, RealSense cameras) or "sim" (a seeded simulated world: emulated board with wheel-radius
  error and slip, cameras rendering the emulator's true pose).

The camera backends are imported when built, so a command loads only the libraries it uses.
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Iterator, List, Mapping, Optional, Sequence, Tuple

from drivers.camera.base import CameraDriver
from drivers.chassis.base import Chassis
from drivers.chassis.emulator import FirmwareEmulator
from drivers.chassis.serial_chassis import SerialChassis
from robot.base.errors import InputError
from robot.config import ChassisConfig, RobotConfig

if TYPE_CHECKING:  # annotations only: the renderer is loaded when a simulation is built
    from drivers.sim.render import SimScene
    from robot.maps.plane_map import PlaneMap

CHASSIS_KINDS = ("serial", "emulator")
CAMERA_KINDS = ("realsense", "sim", "bag")
RIG_KINDS = ("hardware", "sim")
EMULATOR_LINK_TIMEOUT = 0.5  # s: the slack a bench tool gives the emulator's reports

PoseSource = Callable[[], Tuple[float, float, float]]


def _check_kind(what: str, kind: str, kinds: Sequence[str]) -> None:
    if kind not in kinds:
        raise InputError(f"unknown {what} kind {kind!r} (choose from {', '.join(kinds)})")


# Chassis  -------------------------------------------------------------------------------------------


def start_emulator(config: ChassisConfig, pose: Optional[Sequence[float]] = None, **board_options) -> FirmwareEmulator:
    """A running ``FirmwareEmulator`` (real time, on a fresh pty); ``pose`` is its true start pose,
    ``board_options`` go to its ``BoardModel`` (radius_error, slip_noise, seed, ...)."""
    emulator = FirmwareEmulator(config, **board_options)
    if pose is not None:
        emulator.board.pose = tuple(float(v) for v in pose)
    return emulator.start()


def build_chassis(kind: str, config: ChassisConfig, port: Optional[str] = None, *,
                  pose: Optional[Sequence[float]] = None, **emulator_options) -> Chassis:
    """The motor board of ``kind``: "serial" on ``port`` (default ``config.port``), or "emulator"
    (a ``SerialChassis`` whose ``emulator`` attribute is the board it talks to, closed with it)."""
    _check_kind("chassis", kind, CHASSIS_KINDS)
    if kind == "serial":
        if pose is not None or emulator_options:
            raise TypeError("emulator options given for a serial chassis")
        return SerialChassis(config, port=port)
    if port is not None:
        raise InputError(f"a port ({port}) and the emulator exclude each other: the emulator brings its own")
    return EmulatedChassis(config, start_emulator(config, pose, **emulator_options))


class EmulatedChassis(SerialChassis):
    """The serial driver on a firmware emulator's pty. The emulator is the board: closing the
    chassis closes it too."""

    def __init__(self, config: ChassisConfig, emulator: FirmwareEmulator):
        super().__init__(config, port=emulator.port)
        self.emulator = emulator

    async def close(self) -> None:
        try:
            await super().close()
        finally:
            self.emulator.close()


@dataclass(frozen=True)
class BoardPort:
    """Where a bench tool finds the board, and the chassis config to drive it with."""

    port: str
    config: ChassisConfig
    emulator: Optional[FirmwareEmulator] = None


@contextmanager
def board_port(kind: str, config: ChassisConfig, port: Optional[str] = None, **emulator_options) -> Iterator[BoardPort]:
    """The board of ``kind`` for a tool that opens the port itself: "serial", ``port`` (default
    ``config.port``); "emulator", one started for the block, on its pty.

    The emulator is a thread on a shared machine, not a microcontroller: its link timeout gets
    the slack of EMULATOR_LINK_TIMEOUT, so a scheduling hiccup is not taken for a lost link."""
    _check_kind("chassis", kind, CHASSIS_KINDS)
    if kind == "serial":
        yield BoardPort(port or config.port, config)
        return
    if port is not None:
        raise InputError(f"a port ({port}) and the emulator exclude each other: the emulator brings its own")
    emulator = start_emulator(config, **emulator_options)
    try:
        yield BoardPort(emulator.port, replace(config, link_timeout=max(config.link_timeout, EMULATOR_LINK_TIMEOUT)),
                        emulator)
    finally:
        emulator.close()


# Cameras  -------------------------------------------------------------------------------------------


def build_cameras(kind: str, robot: RobotConfig, *, scene: Optional[SimScene] = None,
                  pose_source: Optional[PoseSource] = None, recordings: Optional[Mapping[str, object]] = None,
                  fps: Optional[float] = None, decimation: int = 1, seed: int = 0,
                  frame_cache: int = 0) -> List[CameraDriver]:
    """One driver of ``kind`` per configured camera, in config order.

    "sim" needs the ``scene`` to render and ``pose_source`` (the robot's true pose); ``fps``
    (default: each camera's), ``decimation``, ``seed`` and ``frame_cache`` shape its frames, and a
    camera whose ``realsense.imu_enabled`` is set simulates its gyro. "bag" needs ``recordings``,
    a .bag path for every configured camera.
    """
    _check_kind("camera", kind, CAMERA_KINDS)
    if kind == "realsense":
        from drivers.camera.realsense import RealSenseCamera

        return [RealSenseCamera(cam) for cam in robot.cameras]
    if kind == "bag":
        return _bag_cameras(robot, recordings or {})
    if scene is None or pose_source is None:
        raise TypeError("simulated cameras need the scene they render and the pose they render it from")
    from drivers.camera.sim import SimCamera

    return [SimCamera(robot, cam.name, scene, pose_source, fps=fps, decimation=decimation, seed=seed * 10 + i,
                      cache=frame_cache, imu_rate=float(cam.realsense.gyro_fps) if cam.realsense.imu_enabled else 0.0)
            for i, cam in enumerate(robot.cameras)]


def _bag_cameras(robot: RobotConfig, recordings: Mapping[str, object]) -> List[CameraDriver]:
    from drivers.camera.bag import BagCamera

    names = [cam.name for cam in robot.cameras]
    unknown = sorted(set(recordings) - set(names))
    if unknown:
        raise InputError(f"recordings for unknown camera(s) {', '.join(unknown)} (cameras in {robot.source}: "
                         f"{', '.join(names)})")
    missing = [n for n in names if n not in recordings]
    if missing:
        raise InputError(f"no recording for camera(s) {', '.join(missing)}: every configured camera needs one")
    return [BagCamera(cam, Path(str(recordings[cam.name]))) for cam in robot.cameras]


# A whole robot  -------------------------------------------------------------------------------------


@dataclass
class Rig:
    """The drivers of one robot, real or simulated. ``emulator`` is the simulated board (ground
    truth pose, fault injection), None on hardware. ``close`` releases what ``build_rig`` started."""

    chassis: Chassis
    cameras: List[CameraDriver] = field(default_factory=list)
    emulator: Optional[FirmwareEmulator] = None

    def close(self) -> None:
        if self.emulator is not None:
            self.emulator.close()


def build_rig(kind: str, robot: RobotConfig, plane_map: Optional[PlaneMap] = None,
              start: Optional[Sequence[float]] = None, *, fps: Optional[float] = None, decimation: int = 4,
              frame_cache: int = 0, seed: int = 0, radius_error_std: float = 0.01, slip_noise: float = 0.005,
              clutter: int = 0) -> Rig:
    """The drivers of a robot of ``kind``. "hardware": the serial board and the RealSense cameras of ``robot``. "sim": the world of
    ``plane_map`` seeded by ``seed`` (each wheel's radius error, ``clutter`` boxes kept clear of
    ``start``), the emulated board with the robot truly at ``start``, and cameras rendering it."""
    _check_kind("robot", kind, RIG_KINDS)
    if kind == "hardware":
        return Rig(build_chassis("serial", robot.chassis), build_cameras("realsense", robot))
    if plane_map is None or start is None:
        raise TypeError("a simulated robot needs the map of its world and its start pose")
    from drivers.sim.world import sample_world

    radius_error, scene = sample_world(plane_map, start, seed, radius_error_std, clutter)
    emulator = start_emulator(robot.chassis, start, radius_error=radius_error, slip_noise=slip_noise, seed=seed)
    try:
        cameras = build_cameras("sim", robot, scene=scene, pose_source=lambda: emulator.pose, fps=fps,
                                decimation=decimation, seed=seed, frame_cache=frame_cache)
        return Rig(SerialChassis(robot.chassis, port=emulator.port), cameras, emulator)
    except BaseException:
        emulator.close()
        raise
