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

Ranges are declared beside each field (``robot.config.ranges``); the loader checks them, and so
does :meth:`RealSenseConfig.validate` for settings built in code (the driver calls it).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from robot.config.ranges import check_fields, choice, field_choices, field_range, flag, integer, number
from robot.config.schema import Section

VISUAL_PRESETS = ("default", "high_accuracy", "high_density", "medium_density", "hand", "custom")


@dataclass(frozen=True)
class RealSenseConfig:
    """Defaults follow Intel's advice for D435 depth (848x480 at 30 fps, auto exposure) with the
    High Accuracy preset, which drops low-confidence depth instead of filling it in: a plane fit
    wants fewer, right points, not more, invented ones.
    """

    visual_preset: str = choice("high_accuracy", VISUAL_PRESETS, "depth preset; custom leaves the camera's own")
    emitter_enabled: bool = flag(True, "the IR pattern projector: texture for stereo on bare walls")
    laser_power: float = number(150.0, 0.0, 360.0, "mW", "emitter power (D435: 0 to 360, factory 150)")
    frame_timeout_ms: int = integer(1000, 50, 10_000, "ms", "a wait this long without a frame is a stall")
    stalls_before_reset: int = integer(3, 1, 1000, "", "consecutive timeouts before hardware_reset (live) or "
                                       "restart")
    reconnect_backoff_max: float = number(5.0, 0.0, 300.0, "s", "cap of the exponential backoff while the camera "
                                          "is gone")
    reset_settle: float = number(3.0, 0.0, 60.0, "s", "wait after hardware_reset before looking for the device")
    clock_window: float = number(10.0, 0.0, 600.0, "s", "of host time over which the clock offset is estimated",
                                 lo_open=True)
    imu_enabled: bool = flag(False, "stream gyro and accel (D435i) for the EKF's prediction")
    gyro_fps: int = integer(200, 1, 400, "Hz", "D435i: 200 or 400")
    accel_fps: int = integer(63, 1, 250, "Hz", "D435i: 63 or 250 (100 or 200 on firmware >= 5.16); the nearest is "
                             "taken")
    decimation: int = integer(1, 1, 8, "", "librealsense decimation_filter magnitude", text="1 (off) to 8")
    spatial_filter: bool = flag(False, "librealsense spatial_filter (edge-preserving smoothing)")
    temporal_filter: bool = flag(False, "librealsense temporal_filter (smooths over frames: lags motion)")

    def validate(self, where: str = "realsense") -> None:
        """ConfigError naming the field if a value is out of range (also for settings built in code)."""
        check_fields(self, where)


def parse_realsense_config(sec: Section) -> RealSenseConfig:
    """Read a ``realsense:`` section (every key optional; unknown keys are errors)."""
    values = {}
    for f in dataclasses.fields(RealSenseConfig):
        rng, choices = field_range(f), field_choices(f)
        if rng is not None:
            values[f.name] = sec.ranged(f.name, rng, f.default)
        elif choices is not None:
            values[f.name] = sec.string(f.name, f.default, choices=choices)
        else:
            values[f.name] = sec.boolean(f.name, f.default)
    sec.done()
    cfg = RealSenseConfig(**values)
    cfg.validate(f"{sec.source}: {sec.where}" if sec.where else sec.source)
    return cfg
