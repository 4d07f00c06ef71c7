"""Per-camera RealSense settings: the optional ``realsense:`` sub-section of a camera in robot.yaml.

Pure (no pyrealsense2, no numpy), so the robot config loads on machines without librealsense.
``drivers.camera.realsense`` applies these settings to the camera.

    cameras:
      - name: front
        ...
        realsense:              # every key optional; unknown keys are errors
          visual_preset: high_accuracy
          laser_power: 150
          imu_enabled: true
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from robot.base.errors import ConfigError
from robot.config.schema import Section

VISUAL_PRESETS = ("default", "high_accuracy", "high_density", "medium_density", "hand", "custom")


@dataclass(frozen=True)
class RealSenseConfig:
    """Defaults follow Intel's advice for D435 depth (848x480 at 30 fps, auto exposure) with the
    High Accuracy preset, which drops low-confidence depth instead of filling it in: a plane fit
    wants fewer, right points, not more, invented ones.
    """

    visual_preset: str = "high_accuracy"  # one of VISUAL_PRESETS; "custom" leaves the camera's own
    emitter_enabled: bool = True  # the IR pattern projector; texture for stereo on bare walls
    laser_power: float = 150.0  # mW, clamped to the camera's range (D435: 0..360, factory 150)
    frame_timeout_ms: int = 1000  # a wait this long without a frame is a stall
    stalls_before_reset: int = 3  # consecutive timeouts before hardware_reset (live) / restart
    reconnect_backoff_max: float = 5.0  # s, cap of the exponential backoff while GONE
    reset_settle: float = 3.0  # s to wait after hardware_reset before looking for the device
    clock_window: float = 10.0  # s of host time over which the clock offset is estimated
    imu_enabled: bool = False  # stream gyro and accel (D435i) for the EKF's prediction
    gyro_fps: int = 200  # D435i: 200 or 400
    accel_fps: int = 63  # D435i: 63 or 250 (100 or 200 on firmware >= 5.16); nearest is taken
    decimation: int = 1  # librealsense decimation_filter magnitude; 1 = off
    spatial_filter: bool = False  # librealsense spatial_filter (edge-preserving smoothing)
    temporal_filter: bool = False  # librealsense temporal_filter (smooths over frames: lags motion)

    def validate(self, where: str = "realsense") -> None:
        """ConfigError naming the field if a value is out of range (also for settings built in code)."""
        if self.visual_preset not in VISUAL_PRESETS:
            raise ConfigError(f"{where}: 'visual_preset' must be one of {list(VISUAL_PRESETS)}, "
                              f"got {self.visual_preset!r}")
        if not 1 <= self.decimation <= 8:
            raise ConfigError(f"{where}: 'decimation' must be 1 (off) to 8, got {self.decimation}")
        if self.frame_timeout_ms < 50:
            raise ConfigError(f"{where}: 'frame_timeout_ms' must be >= 50, got {self.frame_timeout_ms}")
        if self.stalls_before_reset < 1:
            raise ConfigError(f"{where}: 'stalls_before_reset' must be >= 1, got {self.stalls_before_reset}")
        for name in ("laser_power", "reconnect_backoff_max", "reset_settle", "clock_window"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ConfigError(f"{where}: '{name}' must be a finite number >= 0, got {v}")
        if self.clock_window <= 0:
            raise ConfigError(f"{where}: 'clock_window' must be > 0, got {self.clock_window}")
        if self.gyro_fps <= 0 or self.accel_fps <= 0:
            raise ConfigError(f"{where}: 'gyro_fps' and 'accel_fps' must be > 0")


def parse_realsense_config(sec: Section) -> RealSenseConfig:
    """Read a ``realsense:`` section (every key optional; unknown keys are errors)."""
    d = RealSenseConfig()
    cfg = RealSenseConfig(
        visual_preset=sec.string("visual_preset", d.visual_preset, choices=VISUAL_PRESETS),
        emitter_enabled=sec.boolean("emitter_enabled", d.emitter_enabled),
        laser_power=sec.number("laser_power", d.laser_power, lo=0.0),
        frame_timeout_ms=sec.integer("frame_timeout_ms", d.frame_timeout_ms, lo=50),
        stalls_before_reset=sec.integer("stalls_before_reset", d.stalls_before_reset, lo=1),
        reconnect_backoff_max=sec.number("reconnect_backoff_max", d.reconnect_backoff_max, lo=0.0),
        reset_settle=sec.number("reset_settle", d.reset_settle, lo=0.0),
        clock_window=sec.number("clock_window", d.clock_window, positive=True),
        imu_enabled=sec.boolean("imu_enabled", d.imu_enabled),
        gyro_fps=sec.integer("gyro_fps", d.gyro_fps, lo=1),
        accel_fps=sec.integer("accel_fps", d.accel_fps, lo=1),
        decimation=sec.integer("decimation", d.decimation, lo=1),
        spatial_filter=sec.boolean("spatial_filter", d.spatial_filter),
        temporal_filter=sec.boolean("temporal_filter", d.temporal_filter),
    )
    sec.done()
    cfg.validate(f"{sec.source}: {sec.where}" if sec.where else sec.source)
    return cfg
