"""A fake depth camera for real-time simulation: the ``CameraDriver`` interface, like the RealSense driver.

Its capture thread renders the simulated world at the robot's true pose (read from the
firmware emulator) at the configured rate, stamps each frame with host monotonic time at
"exposure", and hands it to the app like the real driver. Faults for tests: ``stall(seconds)``
(frames stop; the state goes STALLED after ``timeout``, as librealsense's wait_for_frames
would) and ``vanish()`` / ``reappear()`` (GONE).

``cache`` pre-renders that many frames at the start pose and cycles them: for benchmarks that
need full-resolution frames at 30 Hz without paying the renderer's cost while they measure.
"""

from __future__ import annotations

import math
import threading
import time
from typing import Callable, List, Optional, Tuple

from drivers.camera.base import CameraDriver, CameraState, FrameCallback, ImuCallback
from drivers.sim.render import DepthNoise, SimScene, render_depth_frame
from robot.base.samples import DepthFrame, ImuSample
from robot.config import RobotConfig

PoseSource = Callable[[], Tuple[float, float, float]]


class SimCamera(CameraDriver):
    def __init__(self, robot: RobotConfig, camera: str, scene: SimScene, pose_source: PoseSource, *,
                 fps: Optional[float] = None, decimation: int = 1, noise: Optional[DepthNoise] = DepthNoise(),
                 seed: int = 0, timeout: float = 0.5, cache: int = 0, imu_rate: float = 0.0,
                 gyro_noise: float = 0.0035):
        super().__init__(robot.camera(camera))
        import numpy as np

        self.robot = robot
        self.scene = scene
        self.pose_source = pose_source
        self.fps = float(fps or robot.camera(camera).fps)
        self.decimation = int(decimation)
        self.noise = noise
        self.timeout = float(timeout)
        self.render_seconds = 0.0  # CPU time spent rendering: the simulator's cost, reported apart
        self._rng = np.random.default_rng(seed)
        self._cache_n = int(cache)
        self._cache: List[DepthFrame] = []
        self._thread: Optional[threading.Thread] = None
        self._stop = threading.Event()
        self._stall_until = 0.0
        self._gone = False
        self._frame_number = 0
        self.imu_rate = float(imu_rate)  # Hz of simulated gyro samples (0: no IMU, like imu_enabled: false)
        self.gyro_noise = float(gyro_noise)  # rad/s white noise per sample (BMI055 at 200 Hz)
        self._imu_thread: Optional[threading.Thread] = None
        # librealsense gives IMU samples in the depth optical axes; the simulated IMU sits at the
        # optical origin, so the base's identity T_camera_imu holds

    # -- faults ---------------------------------------------------------------------------------

    def stall(self, seconds: float) -> None:
        self._stall_until = time.monotonic() + float(seconds)

    def vanish(self) -> None:
        self._gone = True

    def reappear(self) -> None:
        self._gone = False

    # -- CameraDriver -----------------------------------------------------------------------------

    def start(self, on_frame: FrameCallback, on_imu: Optional[ImuCallback] = None) -> None:
        if self._thread is not None:
            return
        self._set_state(CameraState.STARTING)
        if self._cache_n:
            self._cache = [self._render(time.monotonic()) for _ in range(self._cache_n)]
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, args=(on_frame,), name=f"camera-{self.name}", daemon=True)
        self._thread.start()
        if self.imu_rate > 0 and on_imu is not None:
            self._imu_thread = threading.Thread(target=self._run_imu, args=(on_imu,), name=f"camera-{self.name}-imu",
                                                daemon=True)
            self._imu_thread.start()

    def stop(self) -> None:
        self._stop.set()
        for th in (self._thread, self._imu_thread):
            if th is not None:
                th.join(timeout=2.0)
        self._thread = self._imu_thread = None
        self._set_state(CameraState.STOPPED)

    # -- internals --------------------------------------------------------------------------------

    def _render(self, t: float) -> DepthFrame:
        c0 = time.thread_time()
        kw = {"decimation": self.decimation} if self.decimation > 1 else {}
        self._frame_number += 1
        frame = render_depth_frame(self.robot, self.scene, self.name, self.pose_source(), rng=self._rng,
                                   noise=self.noise, t_capture=t, frame_number=self._frame_number, **kw)
        self.render_seconds += time.thread_time() - c0
        return frame

    def _run_imu(self, on_imu: ImuCallback) -> None:
        """Gyro samples from the true heading's rate, in the IMU (depth optical) axes, with noise."""
        import numpy as np

        rng = np.random.default_rng(self._frame_number + 7)
        R_imu_robot = self.T_robot_imu[:3, :3].T
        period = 1.0 / self.imu_rate
        t_prev, phi_prev = time.monotonic(), self.pose_source()[2]
        while not self._stop.wait(period):
            if self._gone or time.monotonic() < self._stall_until:
                continue
            t, phi = time.monotonic(), self.pose_source()[2]
            wz = math.remainder(phi - phi_prev, 2.0 * math.pi) / max(t - t_prev, 1e-4)
            t_prev, phi_prev = t, phi
            w = R_imu_robot @ np.array([0.0, 0.0, wz]) + rng.normal(0.0, self.gyro_noise, 3)
            try:
                on_imu(ImuSample(t=t, gyro=(float(w[0]), float(w[1]), float(w[2]))))
            except Exception:
                self.stats["errors"] += 1

    def _run(self, on_frame: FrameCallback) -> None:
        period = 1.0 / self.fps
        next_t = time.monotonic()
        last_frame = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            if now < next_t:
                self._stop.wait(next_t - now)
                continue
            next_t = max(next_t + period, now - period)  # a late frame does not cause a burst
            if self._gone:
                self._set_state(CameraState.GONE)
                last_frame = now
                continue
            if now < self._stall_until:
                if now - last_frame > self.timeout:
                    self.stats["timeouts"] += 1
                    self._set_state(CameraState.STALLED)
                    last_frame = now
                continue
            if self._cache:
                src = self._cache[self._frame_number % len(self._cache)]
                self._frame_number += 1
                frame = DepthFrame(src.camera, src.depth.copy(), src.depth_scale, src.K, t_capture=now,
                                   frame_number=self._frame_number, timestamp_domain="simulated", truth=src.truth)
            else:
                frame = self._render(now)
            last_frame = now
            self.stats["frames"] += 1
            self._set_state(CameraState.STREAMING)
            try:
                on_frame(frame)
            except Exception:  # the consumer's problem must not kill the capture thread
                self.stats["errors"] += 1
