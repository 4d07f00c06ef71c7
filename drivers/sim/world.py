"""One simulated world: the emulated motor board (motors, slip, ground truth) and the scene the
fake cameras render, so odometry and depth frames describe the same robot motion.

The board model is ``drivers.chassis.emulator.BoardModel`` (the same firmware logic the pty
emulator serves); the renderer is ``drivers.sim.render``. Frames carry the true pose at their
capture time, which only the evaluation reads.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, Optional, Sequence, Tuple

import numpy as np

from drivers.chassis.emulator import BoardModel
from drivers.sim.clutter import as_built as as_built_walls
from drivers.sim.clutter import random_site_clutter
from drivers.sim.render import DepthNoise, SimScene, random_clutter, render_depth_frame
from robot.base.errors import ConfigError
from robot.base.geometry import wrap_angle
from robot.base.samples import DepthFrame
from robot.config import RobotConfig
from robot.maps.plane_map import PlaneMap


@dataclass(frozen=True)
class WorldSettings:
    """What makes one simulated run differ from another. Defaults: the paper arena experiment."""

    seed: int = 0
    radius_error_std: float = 0.01  # relative wheel-radius mismatch per wheel (about 1 %)
    slip_noise: float = 0.005  # relative random slip per wheel and millisecond step
    depth_noise: Optional[DepthNoise] = DepthNoise.realistic()  # None: exact depth
    decimation: int = 4  # render at 1/d resolution like librealsense's decimation filter (speed)
    clutter: int = 0  # random boxes on the floor
    site: int = 0  # random construction-site items (drivers.sim.clutter) the map does not know
    as_built: bool = False  # walls rendered as built (offsets, bows, out of plumb), not as in the map
    obstacles: Tuple[Any, ...] = ()  # solids placed on purpose (a person in the path), beside the random ones
    # (x, y) points the random site items keep 0.5 m clear of, beside the start (a planned path's
    # course, so that a run through a cluttered building meets nothing that should stop it)
    keep_clear: Tuple[Tuple[float, float], ...] = ()
    motor_tau: float = 0.03  # s, first-order motor response
    board_substep: float = 0.005  # s per physics step (the firmware runs 1 ms; 5 ms is exact enough here and 5x faster)
    # How the robot differs from its config (what calibration has to find; docs/calibration.md):
    wheel_radius_error: float = 0.0  # all four wheels this much larger than configured (0.01: 1 %), beside the per-wheel errors
    # (camera, (dx, dy, dz m, droll, dpitch, dyaw deg)): the true mount is the configured one plus this
    mount_errors: Tuple[Tuple[str, Tuple[float, float, float, float, float, float]], ...] = ()


def sample_world(plane_map: PlaneMap, start: Sequence[float], seed: int, radius_error_std: float,
                 clutter: int, site: int = 0, as_built: bool = False,
                 keep_clear: Sequence[Tuple[float, float]] = ()) -> Tuple[Tuple[float, ...], SimScene]:
    """The seeded parts of a world: each wheel's radius error and the scene (with random clutter
    and site items kept clear of the start, and the walls as built if asked). Shared by the
    simulated-clock world and the real-time rig, so a seed means the same robot and room in both."""
    rng = np.random.default_rng(seed)
    radius_error = tuple(float(v) for v in rng.normal(0.0, radius_error_std, 4))
    items = list(random_clutter(plane_map, clutter, rng, keep_clear=[tuple(start[:2])])) if clutter else []
    # Drawn after the boxes, so adding site items or as-built walls keeps a seed's wheels and boxes.
    if site:
        items += random_site_clutter(plane_map, rng, site, keep_clear=[tuple(start[:2]), *keep_clear])
    walls = as_built_walls(plane_map, rng) if as_built else None
    return radius_error, SimScene(plane_map, clutter=items, walls=walls)


class SimWorld:
    """The board and the scene, advanced by the caller's clock (``step``)."""

    def __init__(self, robot: RobotConfig, plane_map: PlaneMap, start: Sequence[float],
                 settings: WorldSettings = WorldSettings(), board: Optional[BoardModel] = None):
        self.robot = robot
        self.settings = settings
        radius_error, self.scene = sample_world(plane_map, start, settings.seed, settings.radius_error_std,
                                                settings.clutter, settings.site, settings.as_built,
                                                settings.keep_clear)
        common = 1.0 + float(settings.wheel_radius_error)
        radius_error = tuple(common * (1.0 + e) - 1.0 for e in radius_error)
        # The cameras render from their true mounts; the config (self.robot) keeps what the controller believes.
        self.true_robot = with_mount_errors(robot, settings.mount_errors)
        if settings.obstacles:
            self.scene = SimScene(plane_map, clutter=list(self.scene.clutter) + list(settings.obstacles),
                                  walls=self.scene.walls)
        self.board = board or BoardModel(robot.chassis, radius_error=radius_error, slip_noise=settings.slip_noise,
                                         seed=settings.seed, motor_tau=settings.motor_tau,
                                         substep_us=int(round(settings.board_substep * 1e6)))
        self.board.pose = tuple(float(v) for v in start)  # type: ignore[assignment]
        self._rng = np.random.default_rng(settings.seed + 1)
        self._frame_numbers = {c.name: 0 for c in robot.cameras}

    @property
    def t(self) -> float:
        return self.board.t_board

    @property
    def truth(self) -> Tuple[float, float, float]:
        x, y, phi = self.board.pose
        return float(x), float(y), wrap_angle(float(phi))

    @property
    def effective_wheel_radius(self) -> float:
        """The radius the wheel odometry should use: the configured one times the mean rolling factor,
        less the mean random slip (|N(0, slip_noise)| per step: slip_noise sqrt(2/pi) on average)."""
        b = self.board
        return b.r * float(np.mean(b.rolling)) * (1.0 - b.slip_noise * math.sqrt(2.0 / math.pi))

    def step(self, dt: float) -> None:
        self.board.step(dt)

    def render(self, camera: str, t_capture: Optional[float] = None) -> DepthFrame:
        """A depth frame of ``camera`` at the current true pose, stamped ``t_capture`` (default now)."""
        n = self._frame_numbers[camera] = self._frame_numbers[camera] + 1
        return render_depth_frame(self.true_robot, self.scene, camera, self.truth, rng=self._rng,
                                  noise=self.settings.depth_noise, t_capture=self.t if t_capture is None else t_capture,
                                  frame_number=n, **_decimation_kwargs(self.settings.decimation))


def with_mount_errors(robot: RobotConfig, mount_errors) -> RobotConfig:
    """``robot`` with each named camera's mount moved by its (dx, dy, dz m, droll, dpitch, dyaw deg)."""
    errors = dict(mount_errors)
    unknown = sorted(set(errors) - {c.name for c in robot.cameras})
    if unknown:
        raise ConfigError(f"mount errors for unknown camera(s) {', '.join(unknown)}")
    cams = []
    for c in robot.cameras:
        e = errors.get(c.name)
        if e is None or len(e) != 6:
            if e is not None:
                raise ConfigError(f"mount error of camera '{c.name}' must be (dx, dy, dz, droll, dpitch, dyaw), got {e!r}")
            cams.append(c)
            continue
        cams.append(replace(c, mount_xyz=tuple(float(a) + float(b) for a, b in zip(c.mount_xyz, e[:3])),
                            mount_rpy_deg=tuple(float(a) + float(b) for a, b in zip(c.mount_rpy_deg, e[3:]))))
    return replace(robot, cameras=tuple(cams))


def _decimation_kwargs(d: int) -> dict:
    return {"decimation": d} if d > 1 else {}
