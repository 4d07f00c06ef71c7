"""The interface every depth camera driver implements: a live D435i, a recording, a simulation.

Backends: ``realsense.RealSenseCamera`` (a camera through librealsense), ``bag.BagCamera`` (a
``.bag`` recording played through the same librealsense pipeline) and ``sim.SimCamera`` (frames
rendered from the simulated world). The app takes ``CameraDriver``s (``robot.app.assemble``
builds them by name); one contract suite (``tests/contract/test_camera_contract.py``) runs over
every backend.

What every driver promises:

- it owns one capture thread and calls ``on_frame`` from it with a ``DepthFrame`` whose arrays
  it no longer touches: uint16 depth of the stream's shape, the stream's 3x3 K, a positive
  depth scale, frame numbers and capture times (host monotonic clock, never after delivery)
  that increase, and never the same frame twice; the app hands it to the event loop;
- ``on_imu`` (optional) gets ``ImuSample``s in the camera's IMU frame, ``T_robot_imu`` maps that
  frame to the robot's;
- ``start`` returns at once and does nothing when already started; ``stop`` releases the
  device, may be called any number of times, and no frame is delivered after it returns;
- faults are states (``CameraState``), reported through ``on_state_change``, never exceptions
  out of the capture thread.
"""

from __future__ import annotations

import enum
import threading
from abc import ABC, abstractmethod
from typing import Callable, Dict, Optional

import numpy as np

from robot.base.samples import DepthFrame, ImuSample
from robot.config import CameraConfig

FrameCallback = Callable[[DepthFrame], None]
ImuCallback = Callable[[ImuSample], None]


class CameraState(enum.Enum):
    STOPPED = "stopped"
    STARTING = "starting"
    STREAMING = "streaming"
    STALLED = "stalled"  # device present, frames stopped arriving
    GONE = "gone"  # device removed or cannot be opened; the driver keeps trying


class CameraDriver(ABC):
    """Base: configuration, state, statistics and lifecycle live here once; drivers implement
    ``start`` and ``stop``."""

    def __init__(self, camera: CameraConfig):
        self.camera = camera
        self.name = camera.name
        self._state = CameraState.STOPPED
        self._state_lock = threading.Lock()
        self.stats: Dict[str, int] = {"frames": 0, "timeouts": 0, "reconnects": 0, "errors": 0}
        self.on_state_change: Optional[Callable[[str, CameraState], None]] = None
        # IMU frame -> depth optical frame; a driver that knows better (the device's extrinsics) replaces it
        self.T_camera_imu: np.ndarray = np.eye(4)

    @property
    def state(self) -> CameraState:
        return self._state

    @property
    def T_robot_imu(self) -> np.ndarray:
        """The camera's IMU frame -> robot frame, for the robot's yaw rate from this camera's gyro."""
        return self.camera.T_robot_camera @ self.T_camera_imu

    def _set_state(self, state: CameraState) -> None:
        with self._state_lock:
            changed = state is not self._state
            self._state = state
        if changed and self.on_state_change is not None:
            self.on_state_change(self.name, state)

    @abstractmethod
    def start(self, on_frame: FrameCallback, on_imu: Optional[ImuCallback] = None) -> None:
        """Start the capture thread. Returns at once; frames arrive through ``on_frame``.
        A driver already started keeps running as it is."""

    @abstractmethod
    def stop(self) -> None:
        """Stop capturing and release the device. Idempotent."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()
