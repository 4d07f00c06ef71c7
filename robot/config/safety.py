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
from dataclasses import dataclass
from typing import Tuple


@dataclass(frozen=True)
class SafetyConfig:
    enabled: bool = True
    footprint_length: float = 0.22  # m along robot x (the prototype's body is about 0.2 m x 0.2 m)
    footprint_width: float = 0.22  # m along robot y
    footprint_offset_x: float = 0.0  # m: footprint centre ahead of the robot origin
    min_height: float = 0.04  # m above the floor: lower points are floor (noise, cables below this pass)
    max_height: float = 1.8  # m: higher points cannot touch the robot (and its load)
    wall_tolerance: float = 0.04  # m: a point this close to a mapped wall is that wall
    always_distance: float = 0.06  # m from the footprint: anything this close is an obstacle, wall or not
    stop_margin: float = 0.08  # m left between footprint and obstacle after braking
    reaction_time: float = 0.15  # s: frame age + localization + control tick + board ramp start
    brake_decel: float = 0.5  # m/s^2 the controller can always brake with (control.max_accel)
    slowdown_distance: float = 0.6  # m of free distance below which the speed is capped
    slowdown_speed: float = 0.15  # m/s cap inside the slow-down zone
    rotation_margin: float = 0.03  # m added to the swept circle when turning
    max_scan_age: float = 0.5  # s: an older scan no longer guards its camera's directions
    fov_margin_deg: float = 3.0  # a direction this close to a camera's FOV edge counts as unseen
    lookahead: float = 0.4  # m ahead of the footprint that a fresh view must cover to drive faster than creep
    blind_creep_speed: float = 0.05  # m/s toward directions no camera sees
    stride: int = 8  # every n-th depth pixel in rows and columns (at 848x480: 6,000 points a frame, ~1 ms)
    max_range: float = 3.0  # m: farther points cannot matter within one control horizon
    memory_time: float = 3.0  # s obstacle points are remembered (they vanish closer than the minimum range)
    memory_points: int = 20000  # bound on the remembered points
    memory_cell: float = 0.02  # m: remembered points are thinned to one per cell of this size
    near_blind_fraction: float = 0.6  # invalid share of the view's centre that means "something at the lens"
    near_blind_range: float = 0.03  # m from the lens where such a blinded view places its obstacle
    guarded_sectors_deg: Tuple[Tuple[float, float], ...] = ()  # bearings covered by other sensors

    def __post_init__(self):
        for name in ("footprint_length", "footprint_width", "max_height", "brake_decel", "max_scan_age",
                     "max_range"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f"safety.{name} must be finite and > 0, got {v}")
        for name in ("min_height", "wall_tolerance", "always_distance", "stop_margin", "reaction_time",
                     "slowdown_distance", "slowdown_speed", "rotation_margin", "fov_margin_deg", "blind_creep_speed",
                     "lookahead"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0.0):
                raise ValueError(f"safety.{name} must be finite and >= 0, got {v}")
        if self.min_height >= self.max_height:
            raise ValueError(f"safety.min_height ({self.min_height}) must be below max_height ({self.max_height})")
        if not 0.0 <= self.memory_time <= 10.0:
            raise ValueError(f"safety.memory_time must be in [0, 10] s, got {self.memory_time}")
        if not 0.0 < self.near_blind_fraction <= 1.0:
            raise ValueError(f"safety.near_blind_fraction must be in (0, 1], got {self.near_blind_fraction}")
        if not 0.005 <= self.memory_cell <= 0.1:
            raise ValueError(f"safety.memory_cell must be in [0.005, 0.1] m, got {self.memory_cell}")
        if self.memory_points < 100:
            raise ValueError(f"safety.memory_points must be >= 100, got {self.memory_points}")
        if self.stride < 1:
            raise ValueError(f"safety.stride must be >= 1, got {self.stride}")
        if self.reaction_time > 1.0 or self.max_scan_age > 2.0:
            raise ValueError("safety.reaction_time must be <= 1 s and max_scan_age <= 2 s: longer values would let "
                             "the robot drive on stale obstacle data")
        for lo, hi in self.guarded_sectors_deg:
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi and hi - lo <= 360.0):
                raise ValueError(f"safety.guarded_sectors_deg: [{lo}, {hi}] is not a sector (lo < hi, at most 360 deg)")
