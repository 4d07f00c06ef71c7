"""The ``safety:`` section of the robot config: the protective stop from the depth cameras.

Zones follow the idea of Nav2's collision monitor (stop, slow-down and approach zones from range
data), specialised to a holonomic robot that knows its walls:

- the robot's footprint is a rectangle in the robot frame (``footprint_length`` along x,
  ``footprint_width`` along y, centred on the robot origin unless ``footprint_offset_x`` moves it);
- along the commanded direction of travel the *free distance* is how far the footprint can
  translate before it touches an obstacle point; the allowed speed is the largest one that can
  still brake to a stop ``stop_margin`` short of it, with ``reaction_time`` of travel before the
  brakes act and ``brake_decel`` of deceleration (the approach zone);
- inside ``slowdown_distance`` of free distance the speed is also capped at ``slowdown_speed``;
- rotation is stopped while an obstacle point lies inside the circle the footprint sweeps when
  it turns, plus ``rotation_margin``;
- a point counts as an obstacle when it lies between ``min_height`` and ``max_height`` above
  the floor and no map wall explains it within ``wall_tolerance``, or, whatever explains it, when
  it is closer than ``always_distance`` to the footprint;
- a direction of travel that no camera with a fresh scan (younger than ``max_scan_age``) looks
  along is *blind*: its speed is limited to ``blind_creep_speed`` unless it lies in one of
  ``guarded_sectors_deg`` (bearings in the robot frame, counter-clockwise from +x, covered by
  something else such as a bumper or a lidar).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Tuple

from robot.config.ranges import check_fields, flag, integer, number


@dataclass(frozen=True)
class SafetyConfig:
    enabled: bool = flag(True, "the protective stop; false only on a test stand with the wheels off the ground")
    footprint_length: float = number(0.22, 0.05, 3.0, "m", "robot footprint along robot x (the prototype is about 0.2 m)")
    footprint_width: float = number(0.22, 0.05, 3.0, "m", "robot footprint along robot y")
    footprint_offset_x: float = number(0.0, -1.0, 1.0, "m", "footprint centre ahead of the robot origin")
    min_height: float = number(0.04, 0.0, 0.5, "m", "lower points are floor (depth noise, cables)")
    max_height: float = number(1.8, 0.1, 3.0, "m", "higher points cannot touch the robot and its load")
    wall_tolerance: float = number(0.04, 0.005, 0.2, "m", "a point this close to a mapped wall is that wall")
    always_distance: float = number(0.06, 0.0, 0.5, "m", "from the footprint: anything this close is an obstacle, "
                                    "wall or not")
    stop_margin: float = number(0.08, 0.02, 1.0, "m", "left between footprint and obstacle after braking")
    reaction_time: float = number(0.15, 0.02, 1.0, "s", "frame age + localization + control tick + board ramp start")
    brake_decel: float = number(0.5, 0.05, 5.0, "m/s^2", "deceleration the controller can always brake with")
    slowdown_distance: float = number(0.6, 0.0, 5.0, "m", "free distance below which the speed is capped")
    slowdown_speed: float = number(0.15, 0.0, 2.0, "m/s", "cap inside the slow-down zone")
    rotation_margin: float = number(0.03, 0.0, 0.5, "m", "added to the circle the footprint sweeps when turning")
    max_scan_age: float = number(0.5, 0.05, 2.0, "s", "an older scan no longer guards its camera's directions")
    fov_margin_deg: float = number(3.0, 0.0, 30.0, "deg", "a direction this close to a camera's FOV edge is unseen")
    lookahead: float = number(0.4, 0.0, 3.0, "m", "ahead of the footprint a fresh view must cover to drive faster "
                              "than creep")
    blind_creep_speed: float = number(0.05, 0.0, 0.2, "m/s", "toward directions no camera sees")
    stride: int = integer(8, 1, 64, "px", "every n-th depth pixel in rows and columns (at 848x480: about 6,000 "
                          "points a frame)")
    max_range: float = number(3.0, 0.5, 10.0, "m", "farther points cannot matter within one control horizon")
    memory_time: float = number(3.0, 0.0, 10.0, "s", "obstacle points are remembered this long (they vanish "
                                "closer than the cameras' minimum range)")
    memory_points: int = integer(20000, 100, 1000000, "", "bound on the remembered points")
    memory_cell: float = number(0.02, 0.005, 0.1, "m", "remembered points are thinned to one per cell of this size")
    near_blind_fraction: float = number(0.6, 0.01, 1.0, "", "invalid share of a view's centre that means "
                                        "something is right at the lens")
    near_blind_range: float = number(0.03, 0.0, 0.5, "m", "from the lens, where such a blinded view puts its obstacle")
    guarded_sectors_deg: Tuple[Tuple[float, float], ...] = field(
        default=(), metadata={"doc": "bearings [lo, hi] (deg, counter-clockwise from robot +x) covered by other "
                                     "sensors (bumper, lidar): not limited to the creep speed"})

    def __post_init__(self):
        check_fields(self, "safety")
        if self.min_height >= self.max_height:
            raise ValueError(f"safety.min_height ({self.min_height}) must be below max_height ({self.max_height})")
        for lo, hi in self.guarded_sectors_deg:
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi and hi - lo <= 360.0):
                raise ValueError(f"safety.guarded_sectors_deg: [{lo}, {hi}] is not a sector (lo < hi, at most 360 deg)")
