"""The interface every depth camera driver implements, real (RealSense) or fake (simulated).

A driver owns one capture thread. It calls ``on_frame`` from that thread with a DepthFrame whose
arrays it no longer touches; the app hands it to the event loop (bounded, drop-oldest).
"""

from __future__ import annotations

import enum
import threading
from abc import ABC, abstractmethod
from typing import Callable, Dict, Optional

from robot.base.samples import DepthFrame, ImuSample

FrameCallback = Callable[[DepthFrame], None]
ImuCallback = Callable[[ImuSample], None]


class CameraState(enum.Enum):
    STOPPED = "stopped"
    STARTING = "starting"
    STREAMING = "streaming"
    STALLED = "stalled"  # device present, frames stopped arriving
    GONE = "gone"  # device removed or cannot be opened; the driver keeps trying


class CameraDriver(ABC):
    """Base: state, statistics and lifecycle live here once; drivers implement the hooks."""

    def __init__(self, name: str):
        self.name = name
        self._state = CameraState.STOPPED
        self._state_lock = threading.Lock()
        self.stats: Dict[str, int] = {"frames": 0, "timeouts": 0, "reconnects": 0, "errors": 0}
        self.on_state_change: Optional[Callable[[str, CameraState], None]] = None

    @property
    def state(self) -> CameraState:
        return self._state

    def _set_state(self, state: CameraState) -> None:
        with self._state_lock:
            changed = state is not self._state
            self._state = state
        if changed and self.on_state_change is not None:
            self.on_state_change(self.name, state)

    @abstractmethod
    def start(self, on_frame: FrameCallback, on_imu: Optional[ImuCallback] = None) -> None:
        """Start the capture thread. Returns at once; frames arrive through ``on_frame``."""

    @abstractmethod
    def stop(self) -> None:
        """Stop capturing and release the device. Idempotent."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()
