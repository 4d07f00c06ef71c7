"""One simulated world: the emulated motor board (motors, slip, ground truth) and the scene the
fake cameras render, so odometry and depth frames describe the same robot motion.

The board model is ``drivers.chassis.emulator.BoardModel`` (the same firmware logic the pty
emulator serves); the renderer is ``drivers.sim.render``. Frames carry the true pose at their
capture time, which only the evaluation reads.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import numpy as np

from drivers.chassis.emulator import BoardModel
from drivers.sim.render import DepthNoise, SimScene, random_clutter, render_depth_frame
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
    depth_noise: Optional[DepthNoise] = DepthNoise()
    decimation: int = 4  # render at 1/d resolution like librealsense's decimation filter (speed)
    clutter: int = 0  # random boxes on the floor
    motor_tau: float = 0.03  # s, first-order motor response
    board_substep: float = 0.005  # s per physics step (the firmware runs 1 ms; 5 ms is exact enough here and 5x faster)


def sample_world(plane_map: PlaneMap, start: Sequence[float], seed: int, radius_error_std: float,
                 clutter: int) -> Tuple[Tuple[float, ...], SimScene]:
    """The seeded parts of a world: each wheel's radius error and the scene (with random clutter
    kept clear of the start). Shared by the simulated-clock world and the real-time rig, so a
    seed means the same robot and room in both."""
    rng = np.random.default_rng(seed)
    radius_error = tuple(float(v) for v in rng.normal(0.0, radius_error_std, 4))
    boxes = random_clutter(plane_map, clutter, rng, keep_clear=[tuple(start[:2])]) if clutter else ()
    return radius_error, SimScene(plane_map, clutter=boxes)


class SimWorld:
    """The board and the scene, advanced by the caller's clock (``step``)."""

    def __init__(self, robot: RobotConfig, plane_map: PlaneMap, start: Sequence[float],
                 settings: WorldSettings = WorldSettings(), board: Optional[BoardModel] = None):
        self.robot = robot
        self.settings = settings
        radius_error, self.scene = sample_world(plane_map, start, settings.seed, settings.radius_error_std,
                                                settings.clutter)
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

    def step(self, dt: float) -> None:
        self.board.step(dt)

    def render(self, camera: str, t_capture: Optional[float] = None) -> DepthFrame:
        """A depth frame of ``camera`` at the current true pose, stamped ``t_capture`` (default now)."""
        n = self._frame_numbers[camera] = self._frame_numbers[camera] + 1
        return render_depth_frame(self.robot, self.scene, camera, self.truth, rng=self._rng,
                                  noise=self.settings.depth_noise, t_capture=self.t if t_capture is None else t_capture,
                                  frame_number=n, **_decimation_kwargs(self.settings.decimation))


def _decimation_kwargs(d: int) -> dict:
    return {"decimation": d} if d > 1 else {}
