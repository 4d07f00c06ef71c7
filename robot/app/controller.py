"""The controller process: one asyncio event loop around ``ControllerCore`` (DESIGN.md section 1).

Threads and tasks:

- one capture thread per camera (inside each driver) hands the newest frame to the loop; each
  camera has a one-frame slot, so a frame not yet localized is replaced by a newer one and
  counted as dropped (drop-oldest: localizing an old frame is wasted work);
- one localization worker thread (a single-thread executor) runs the CPU-heavy localizer, so the
  control loop keeps its period; the fused result comes back to the loop;
- the chassis driver's reader thread posts odometry to the loop;
- the control task ticks at ``control.rate`` on absolute deadlines and is the only sender of
  wheel commands, the only source of the systemd watchdog ping, and the place health is applied.

Operator: SIGUSR1 pauses the path (brake within the limits and hold), SIGUSR2 resumes it
(``systemctl kill -s SIGUSR1 robot-controller``).

Shutdown (SIGINT/SIGTERM, the mission's end, or ``request_stop``): the control task stops, the
wheels get STOP (the board ACKs it), cameras stop, the pose is saved, the recording is closed.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import math
import signal
import sys
import time
from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional, Sequence

import numpy as np

from drivers.camera.base import CameraDriver, CameraState
from drivers.camera.realsense_imu import yaw_rate_robot
from drivers.chassis.encoders import quantisation_variance
from robot.app import sd_notify
from robot.app.pose_store import PoseStore
from robot.base.errors import DriverError
from robot.base.samples import DepthFrame
from robot.config import RobotConfig
from robot.control.core import ControllerCore
from robot.control.path_file import PathPlan
from robot.localization.localizer import Localizer
from robot.maps.plane_map import PlaneMap
from robot.recording import schema as mcap_schema

log = logging.getLogger(__name__)

# The default 5 ms switch interval lets the localization thread hold the GIL for up to 5 ms
# between bytecode checks: a whole control-period's jitter budget. 1 ms bounds that wait.
GIL_SWITCH_INTERVAL = 0.001
# D435i (BMI055) yaw-rate variance per sample: white noise ~0.0035 rad/s at 200 Hz plus an
# uncalibrated bias of up to ~0.01 rad/s, which the filter cannot tell from noise.
GYRO_VARIANCE = 0.01 ** 2


@dataclass
class AppOptions:
    vision: bool = True
    method: str = "joint"
    status_period: float = 1.0  # s between STATUS= lines / status records
    pose_save_period: float = 2.0  # s between saves of the last pose
    connect_retry: float = 1.0  # s between chassis connection attempts at start-up
    startup_timeout: Optional[float] = None  # s to wait for the chassis at start (None: forever)
    stop_when_done: bool = True  # end the process when the path is complete
    initial_cov: Sequence[float] = (0.02, 0.02, math.radians(2.0))  # std of a given initial pose
    install_signal_handlers: bool = True


@dataclass
class AppStats:
    frames: Dict[str, int] = field(default_factory=dict)
    frames_dropped: Dict[str, int] = field(default_factory=dict)
    localizations: int = 0
    localize_ms: List[float] = field(default_factory=list)
    tick_times: List[float] = field(default_factory=list)  # loop time of each control tick (bounded)
    commands_sent: int = 0
    commands_withheld: int = 0
    odometry: int = 0
    imu_rejected: int = 0


class RobotApp:
    """Wire drivers to the core. ``chassis`` is a ``SerialChassis`` (or the same interface)."""

    def __init__(self, robot: RobotConfig, plane_map: PlaneMap, cameras: Sequence[CameraDriver], chassis,
                 options: Optional[AppOptions] = None, *, plan: Optional[PathPlan] = None, teleop=None,
                 initial_pose: Optional[Sequence[float]] = None, pose_store: Optional[PoseStore] = None,
                 recorder=None, live_view=None, on_tick: Optional[Callable[[RobotApp, float], None]] = None):
        self.robot = robot
        self.plane_map = plane_map
        self.cameras = list(cameras)
        self.chassis = chassis
        self.options = options or AppOptions()
        self.plan = plan
        self.teleop = teleop
        self.initial_pose = initial_pose
        self.pose_store = pose_store
        self.recorder = recorder
        self.live_view = live_view
        self.on_tick = on_tick  # test hook, called on the loop after each control tick
        self.core = ControllerCore(robot, vision=self.options.vision, t_start=time.monotonic())
        self.localizer = Localizer(robot, plane_map) if self.options.vision else None
        self.stats = AppStats()
        self.exit_reason = ""
        self.camera_states: Dict[str, str] = {c.name: CameraState.STOPPED.value for c in self.cameras}
        self._loop: Optional[asyncio.AbstractEventLoop] = None
        self._stop: Optional[asyncio.Event] = None
        self._new_frame: Optional[asyncio.Event] = None
        self._slots: Dict[str, Optional[DepthFrame]] = {}
        self._executor = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="localize")
        self._watchdog = sd_notify.WatchdogPinger()
        self._stall_control_until = 0.0  # test hook: the control task sleeps through its ticks
        self.last_output = None
        self._record_seq = 0

    # -- lifecycle ------------------------------------------------------------------------------

    def request_stop(self, reason: str) -> None:
        if self._stop is not None and not self._stop.is_set():
            self.exit_reason = reason
            self._loop.call_soon_threadsafe(self._stop.set)

    def pause(self) -> None:
        """Brake to a stop within the limits and hold (path following); SIGUSR1 does this."""
        if self.core.trajectory is not None:
            self.core.trajectory.pause()
            log.info("paused by operator")

    def resume(self) -> None:
        """Continue the path after ``pause``; SIGUSR2 does this."""
        if self.core.trajectory is not None:
            self.core.trajectory.resume()
            log.info("resumed by operator")

    def abort(self, reason: str = "aborted by operator") -> None:
        if self.core.trajectory is not None:
            self.core.trajectory.abort(reason)
            log.info("%s", reason)

    def stall_control_loop(self, seconds: float) -> None:
        """Test hook: make the control task miss its ticks (a hung loop) for ``seconds``."""
        self._stall_control_until = time.monotonic() + seconds

    async def run(self) -> int:
        """Run until stopped; 0 on a normal end (path done, signal), 1 on a failure at start."""
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        self._new_frame = asyncio.Event()
        sys.setswitchinterval(GIL_SWITCH_INTERVAL)
        if self.options.install_signal_handlers:
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._loop.add_signal_handler(sig, self.request_stop, f"signal {signal.Signals(sig).name}")
            self._loop.add_signal_handler(signal.SIGUSR1, self.pause)
            self._loop.add_signal_handler(signal.SIGUSR2, self.resume)
        tasks: List[asyncio.Task] = []
        try:
            sd_notify.status("starting: connecting to the motor board")
            if not await self._connect_chassis():
                return 0 if self._stop.is_set() else 1  # stopped while waiting is a normal end
            self._write_config_record()
            self._init_pose()
            for cam in self.cameras:
                self._slots[cam.name] = None
                self.stats.frames[cam.name] = 0
                self.stats.frames_dropped[cam.name] = 0
                cam.on_state_change = self._camera_state_threadsafe
                cam.start(self._frame_threadsafe, lambda sample, c=cam: self._imu_threadsafe(c, sample))
            if self.plan is not None:
                self.core.follow(self.plan)
            elif self.teleop is not None:
                self.core.teleoperate()
            if self.live_view is not None:
                if self.localizer is not None:
                    self.localizer.keep_roi_labels = True
                try:
                    await self.live_view.start(self.plane_map)
                except DriverError as e:  # an engineer's view must never keep the robot from running
                    log.warning("live view off: %s", e)
                    self.live_view = None
            tasks = [self._loop.create_task(self._odometry_task(), name="odometry"),
                     self._loop.create_task(self._control_task(), name="control"),
                     self._loop.create_task(self._status_task(), name="status")]
            if self.localizer is not None:
                tasks.append(self._loop.create_task(self._localization_task(), name="localization"))
            sd_notify.ready(self.status_line())
            log.info("running: %s", self.status_line())
            await self._stop.wait()
            return 0
        finally:
            await self._shutdown(tasks)

    async def _connect_chassis(self) -> bool:
        t0 = time.monotonic()
        last_error, attempts = "", 0
        while not self._stop.is_set():
            try:
                await self.chassis.connect()
                return True
            except DriverError as e:
                timeout = self.options.startup_timeout
                if timeout is not None and time.monotonic() - t0 > timeout:
                    self.exit_reason = f"motor board not reachable: {e}"
                    log.error("%s", self.exit_reason)
                    return False
                sd_notify.status(f"waiting for the motor board: {e}")
                attempts += 1
                if str(e) != last_error or attempts % 60 == 0:  # the journal gets news, not a flood
                    log.warning("motor board not reachable (%s); retrying every %.1f s", e, self.options.connect_retry)
                last_error = str(e)
                try:
                    await asyncio.wait_for(self._stop.wait(), self.options.connect_retry)
                except asyncio.TimeoutError:
                    pass
        return False

    def _init_pose(self) -> None:
        """Initial pose: the command line, else the path's start, else the last saved pose."""
        t = time.monotonic()
        sx, sy, sp = self.options.initial_cov
        cov = np.diag([sx * sx, sy * sy, sp * sp])
        source = ""
        pose = None
        if self.initial_pose is not None:
            pose, source = tuple(self.initial_pose), "command line"
        elif self.plan is not None and self.plan.start is not None:
            pose, source = (self.plan.start.x, self.plan.start.y, self.plan.start.heading), f"path {self.plan.source}"
        elif self.pose_store is not None:
            stored, why = self.pose_store.load(self.plane_map.source)
            if stored is not None:
                pose, source = (stored.x, stored.y, stored.phi), f"saved pose {self.pose_store.path}"
                cov = np.asarray(stored.cov, float) + np.diag([0.01 ** 2, 0.01 ** 2, math.radians(1.0) ** 2])
            else:
                log.warning("no initial pose: %s", why)
        if pose is None:
            log.warning("no initial pose given: the robot will not move until one is set")
            return
        self.core.set_pose(t, *pose, cov)
        self._record("status", t, {"t": t, "event": "set_pose", "x": pose[0], "y": pose[1], "phi": pose[2],
                                   "cov": cov.ravel().tolist(), "source": source})
        log.info("initial pose (%.3f, %.3f, %.1f deg) from %s", pose[0], pose[1], math.degrees(pose[2]), source)

    async def _shutdown(self, tasks: List[asyncio.Task]) -> None:
        sd_notify.stopping(f"stopping: {self.exit_reason or 'done'}")
        for task in tasks:
            task.cancel()
        for task in tasks:
            try:
                await task
            except (asyncio.CancelledError, Exception):  # noqa: PERF203 - shutdown must go on
                pass
        try:
            await self.chassis.close()  # sends STOP and waits for its ACK
        except Exception as e:  # a dead port must not keep the cameras running
            log.error("closing the chassis: %s", e)
        for cam in self.cameras:
            cam.stop()
        self._executor.shutdown(wait=True)
        if self.core.initialized and self.pose_store is not None:
            (x, y, phi), P = self.core.pose(time.monotonic())
            self.pose_store.save(time.monotonic(), x, y, phi, P, self.plane_map.source, force=True)
        if self.live_view is not None:
            await self.live_view.stop()
        if self.recorder is not None:
            self.recorder.close()
        if self.options.install_signal_handlers and self._loop is not None:
            for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGUSR1, signal.SIGUSR2):
                self._loop.remove_signal_handler(sig)
        log.info("stopped: %s", self.exit_reason or "done")

    # -- thread -> loop handoff -----------------------------------------------------------------

    def _frame_threadsafe(self, frame: DepthFrame) -> None:
        try:
            self._loop.call_soon_threadsafe(self._frame_arrived, frame)
        except RuntimeError:
            pass  # the loop is closed: shutting down

    def _imu_threadsafe(self, camera: CameraDriver, sample) -> None:
        if sample.gyro is None:
            return  # accelerometer samples are not used on a level floor
        try:
            self._loop.call_soon_threadsafe(self._imu, camera, sample)
        except RuntimeError:
            pass

    def _imu(self, camera: CameraDriver, sample) -> None:
        try:
            wz = yaw_rate_robot(sample, camera.T_robot_imu)
        except (AttributeError, ValueError) as e:
            self.stats.imu_rejected += 1
            log.debug("camera %s: gyro sample refused: %s", camera.name, e)
            return
        self.core.on_gyro(sample.t, wz, GYRO_VARIANCE)
        self._record("odometry", sample.t, {"t": sample.t, "gyro_wz": wz, "variance": GYRO_VARIANCE, "camera": camera.name})

    def _camera_state_threadsafe(self, name: str, state: CameraState) -> None:
        try:
            self._loop.call_soon_threadsafe(self._camera_state, name, state)
        except RuntimeError:
            pass

    def _camera_state(self, name: str, state: CameraState) -> None:
        old = self.camera_states.get(name)
        self.camera_states[name] = state.value
        if old != state.value:
            (log.info if state is CameraState.STREAMING else log.warning)("camera %s: %s", name, state.value)

    def _frame_arrived(self, frame: DepthFrame) -> None:
        self.stats.frames[frame.camera] = self.stats.frames.get(frame.camera, 0) + 1
        if self._slots.get(frame.camera) is not None:
            self.stats.frames_dropped[frame.camera] = self.stats.frames_dropped.get(frame.camera, 0) + 1
        self._slots[frame.camera] = frame
        self._new_frame.set()

    # -- tasks ----------------------------------------------------------------------------------

    async def _odometry_task(self) -> None:
        q = self.chassis.odometry_queue()
        while True:
            odo = await q.get()
            self.stats.odometry += 1
            self.core.on_odometry(odo, quantisation_variance(self.robot.chassis.ticks_per_rev, odo.dt))
            self._record("odometry", odo.t, {"t": odo.t, "wheel_speeds": list(odo.speeds), "angles": list(odo.angles),
                                             "dt": odo.dt, "t_board": odo.t_board})

    async def _localization_task(self) -> None:
        loop = self._loop
        while True:
            await self._new_frame.wait()
            self._new_frame.clear()
            for name in list(self._slots):
                frame = self._slots.get(name)
                if frame is None:
                    continue
                self._slots[name] = None
                if not self.core.initialized:
                    continue
                (x, y, phi), P = self.core.coarse_pose(frame.t_capture)
                if self.recorder is not None:
                    self.recorder.write_depth(frame.t_capture, frame)  # only the frames the localizer uses
                try:
                    result = await loop.run_in_executor(self._executor, self.localizer.localize, [frame], (x, y, phi), P,
                                                        self.options.method)
                except Exception as e:  # a bad frame is reported and skipped, never fused
                    log.warning("camera %s frame %d: localization failed: %s", name, frame.frame_number, e)
                    continue
                self.stats.localizations += 1
                self.stats.localize_ms.append(result.ms)
                if len(self.stats.localize_ms) > 10000:
                    del self.stats.localize_ms[:5000]
                report = self.core.on_localization(result, frame.t_capture, name)
                # everything replay needs to redo this localization bit for bit, and what it gave
                self._record("planes", frame.t_capture, {
                    "t": frame.t_capture, "camera": name, "frame_number": frame.frame_number, "method": self.options.method,
                    "coarse": [x, y, phi], "coarse_cov": np.asarray(P).ravel().tolist(), "status": result.status,
                    "planes": [p.to_json() for p in result.planes], "accepted": report.accepted,
                    "rejected": [list(r) for r in report.rejected]})
                if self.live_view is not None:
                    self.live_view.publish_planes(frame.t_capture, name, [p.to_json() for p in result.planes])
                    labels = self.localizer.last_roi_labels.get(name)
                    if labels is not None:
                        self.live_view.publish_roi(frame.t_capture, name, labels)

    async def _control_task(self) -> None:
        loop = self._loop
        period = 1.0 / self.robot.control.rate
        next_t = loop.time()
        while True:
            next_t += period
            delay = next_t - loop.time()
            if delay > 0:
                await asyncio.sleep(delay)
            elif delay < -period:
                next_t = loop.time()  # fell behind by more than a tick: do not burst to catch up
            if time.monotonic() < self._stall_control_until:
                time.sleep(period)  # simulate a hung loop: block the event loop itself
                continue
            self._tick(time.monotonic())

    def _tick(self, t: float) -> None:
        ticks = self.stats.tick_times
        ticks.append(t)
        if len(ticks) > 20000:
            del ticks[:10000]
        link_ok = self.chassis.link_state.value == "ready"
        self.core.set_chassis_link(link_ok, "" if link_ok else f"chassis link {self.chassis.link_state.value}")
        if self.teleop is not None:
            self.core.set_teleop_twist(t, *self.teleop.twist(t))
        out = self.core.control_step(t)
        self.last_output = out
        if out.wheels is not None and self.core.health.command_fresh(out.command.t_issued, time.monotonic()):
            if self.chassis.send_wheel_speeds(out.wheels):
                self.stats.commands_sent += 1
            else:
                self.stats.commands_withheld += 1
        else:
            self.stats.commands_withheld += 1
        self._watchdog.tick()  # only a control loop that ticks keeps systemd from restarting us
        if self.recorder is not None:
            c = out.command
            self._record("cmd", t, {"t": t, "wheel_speeds": list(out.wheels) if out.wheels else None,
                                    "sent": out.wheels is not None, "vx": c.vx, "vy": c.vy, "wz": c.wz,
                                    "state": c.state, "scale": out.speed_scale, "reason": out.reason})
        if self.live_view is not None:
            self.live_view.publish_cmd(t, out.command.vx, out.command.vy, out.command.wz)
        if self.options.stop_when_done and self.core.finished:
            self.request_stop("path complete")
        if self.on_tick is not None:
            self.on_tick(self, t)

    async def _status_task(self) -> None:
        while True:
            await asyncio.sleep(self.options.status_period)
            t = time.monotonic()
            line = self.status_line()
            sd_notify.status(line)
            if self.core.initialized:
                (x, y, phi), P = self.core.pose(t)
                q = self.core.evaluate_quality(t)
                if self.pose_store is not None:
                    self.pose_store.save(t, x, y, phi, P, self.plane_map.source)
                if self.recorder is not None:
                    self._record("pose", t, mcap_schema.pose_message(t, x, y, phi, P, q.state))
                if self.live_view is not None:
                    self.live_view.publish_pose(t, x, y, phi, P, q.state, q.reason)
            self._record("status", t, self.status(t))

    # -- reporting ------------------------------------------------------------------------------

    def status(self, t: Optional[float] = None) -> Dict[str, object]:
        t = time.monotonic() if t is None else t
        s = self.core.status(t)
        s["cameras"] = dict(self.camera_states)
        s["chassis"] = self.chassis.link_state.value
        s["frames_dropped"] = dict(self.stats.frames_dropped)
        if self.last_output is not None:
            s["speed_scale"] = self.last_output.speed_scale
            s["command_reason"] = self.last_output.reason
        return s

    def status_line(self) -> str:
        s = self.status()
        pose = (f"pose ({s['x']:.3f}, {s['y']:.3f}, {math.degrees(s['phi']):.1f} deg)" if "x" in s else "no pose")
        reason = f" ({s['reason']})" if s.get("reason") else ""
        cams = ", ".join(f"{k} {v}" for k, v in s["cameras"].items())
        return f"{s['quality']}{reason}; {pose}; chassis {s['chassis']}; cameras: {cams or 'none'}"

    def _record(self, kind: str, t: float, message: Dict[str, object]) -> None:
        """Record with a sequence number: replay redoes the core's calls in exactly this order."""
        if self.recorder is None:
            return
        self._record_seq += 1
        message["seq"] = self._record_seq
        self.recorder.write(_TOPICS[kind], t, message)

    def _write_config_record(self) -> None:
        if self.recorder is None:
            return
        self.recorder.write_config(time.monotonic(), _read_text(self.robot.source), _read_text(self.plane_map.source),
                                   robot_config_path=self.robot.source, map_path=self.plane_map.source)


_TOPICS = {"odometry": mcap_schema.TOPIC_ODOMETRY, "planes": mcap_schema.TOPIC_PLANES, "cmd": mcap_schema.TOPIC_CMD,
           "pose": mcap_schema.TOPIC_POSE, "status": mcap_schema.TOPIC_STATUS}


def _read_text(path: str) -> str:
    try:
        with open(path, encoding="utf-8") as f:
            return f.read()
    except OSError:
        return f"# {path} was not readable at record time\n"
