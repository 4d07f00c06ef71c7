"""The controller process: one asyncio event loop around ``ControllerCore`` (see docs/architecture.md, 'Data flow').

Threads and tasks:

- one capture thread per camera (inside each driver) hands the newest frame to the loop; each
  camera has a one-frame slot, so a frame not yet localized is replaced by a newer one and
  counted as dropped (drop-oldest: localizing an old frame is wasted work);
- one localization worker thread (a single-thread executor) runs the CPU-heavy localizer, so the
  control loop keeps its period; the fused result comes back to the loop;
- the chassis driver's reader thread posts odometry to the loop, which fuses each sample as the
  driver hands it over (the odometry queue's listener, no task per sample);
- the control tick (a timer callback that schedules the next) runs at ``control.rate`` on
  absolute deadlines and is the only sender of wheel commands, the only source of the systemd
  watchdog ping, and the place health is applied.

Operator: SIGUSR1 pauses the path (brake within the limits and hold), SIGUSR2 resumes it
(``systemctl kill -s SIGUSR1 robot-controller``).

Shutdown (SIGINT/SIGTERM, the mission's end, or ``request_stop``): the control tick stops, the
wheels get STOP (the board ACKs it), cameras stop, the pose is saved, the recording is closed.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import functools
import logging
import math
import signal
import sys
import time
from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional, Sequence, Tuple, TypeVar, Union

import numpy as np

from drivers.camera.base import CameraDriver, CameraState
from drivers.camera.realsense_imu import yaw_rate_robot
from drivers.chassis.base import Chassis, LinkState, OdometryQueue
from drivers.chassis.encoders import quantisation_variance
from robot.app import sd_notify
from robot.app.calibration_store import CalibrationStore
from robot.app.operator import remote_services
from robot.app.pose_store import PoseStore
from robot.base.errors import DriverError
from robot.base.frames import FrameCheck
from robot.base.samples import DepthFrame, WheelOdometry
from robot.config import RobotConfig
from robot.config.calibration import calibrated_frame, error_model_note
from robot.config.dump import effective_config_dict
from robot.control.core import ControllerCore
from robot.control.path_file import PathPlan
from robot.fusion.calibration_filter import CalibrationFilter
from robot.fusion.frames import OdomFrame, camera_mounts
from robot.localization.localizer import Localizer
from robot.maps.plane_map import PlaneMap
from robot.recording import schema as channels
from robot.recording.live_view import LiveView, NullLiveView
from robot.recording.recorder import BackgroundRecorder, NullRecorder, Recorder

log = logging.getLogger(__name__)
T = TypeVar("T")

_STREAMING = CameraState.STREAMING.value  # (an enum's .value is a descriptor call: this is read per frame)
RECOVERY_POLL = 0.2  # s between looks at whether the recovery supervisor wants a relocalization

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
    connect_retry: float = 1.0  # s between chassis connection attempts at start-up
    startup_timeout: Optional[float] = None  # s to wait for the chassis at start (None: forever)
    stop_when_done: bool = True  # end the process when the path is complete
    initial_cov: Sequence[float] = (0.02, 0.02, math.radians(2.0))  # std of a given initial pose
    install_signal_handlers: bool = True
    remote: bool = False  # serve the config's control socket and fleet link (robot.app.operator)
    online_calibration: bool = False  # estimate depth scales, mounts and wheel radii while running (fusion.calibration_filter)
    # While the kernels compile at start-up: s between asks to systemd for more start time, and
    # for how long at most it asks (a compile that hangs is not kept alive): see _extend_start_while_compiling.
    start_extend_period: float = 10.0
    kernel_compile_limit: float = 1800.0


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
    """Wire drivers to the core: any ``CameraDriver``s and ``Chassis`` (``robot.app.assemble`` builds them)."""

    def __init__(self, robot: RobotConfig, plane_map: PlaneMap, cameras: Sequence[CameraDriver], chassis: Chassis,
                 options: Optional[AppOptions] = None, *, plan: Optional[PathPlan] = None, teleop=None,
                 initial_pose: Optional[Sequence[float]] = None, pose_store: Optional[PoseStore] = None,
                 recorder: Optional[Union[Recorder, BackgroundRecorder, NullRecorder]] = None,
                 live_view: Optional[Union[LiveView, NullLiveView]] = None,
                 on_tick: Optional[Callable[[RobotApp, float], None]] = None,
                 calibration_store: Optional[CalibrationStore] = None):
        self.robot = robot
        self.plane_map = plane_map
        self.cameras = list(cameras)
        self.chassis = chassis
        self.options = options or AppOptions()
        self.plan = plan
        self.teleop = teleop
        self.initial_pose = initial_pose
        self.pose_store = pose_store
        # Off is a null object (None, what the command line passes, means off too): the app
        # records and shows unconditionally and never asks whether anyone listens.
        self.recorder = NullRecorder() if recorder is None else recorder
        self.live_view = NullLiveView() if live_view is None else live_view
        self.on_tick = on_tick  # test hook, called on the loop after each control tick
        self.calibration_store = calibration_store
        self.core = ControllerCore(robot, vision=self.options.vision, t_start=time.monotonic(), plane_map=plane_map,
                                   calibration=self._online_calibration())
        self.localizer = Localizer(robot, plane_map) if self.options.vision else None
        # odom -> base_link: the wheels alone (REP-105); forward in floats, as the filter's feed takes it
        self.odom = OdomFrame(self.core.kinematics.forward_floats)
        self.stats = AppStats()
        # Live frames are judged like snapshot files, and by their time stamp: a bad one is counted, never fused.
        self.frame_check = FrameCheck(robot.health.frame_max_ahead, robot.health.frame_max_age)
        self._reconnects: Optional[int] = None  # the chassis' reconnect count at the last tick
        self.exit_reason = ""
        self.camera_states: Dict[str, str] = {c.name: CameraState.STOPPED.value for c in self.cameras}
        self._loop: Optional[asyncio.AbstractEventLoop] = None
        self._stop: Optional[asyncio.Event] = None
        # The localization pipeline: running, a set in the worker, the wait for the rest of a set.
        self._sets_running = False
        self._set_in_worker = False
        self._set_timer: Optional[asyncio.TimerHandle] = None
        self._slots: Dict[str, Optional[DepthFrame]] = {}
        self._odometry_queue: Optional[OdometryQueue] = None  # while its listener is self._odometry
        self._control_timer: Optional[asyncio.Handle] = None  # the next control tick while ticking
        self._control_period = 0.0
        self._control_next = 0.0
        self._executor = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="localize")
        self._watchdog = sd_notify.WatchdogPinger()
        self._stall_control_until = 0.0  # test hook: the control tick sleeps through its ticks
        self.last_output = None
        self._record_seq = 0
        self._fusion_steps = 0  # sets of frames fused, one filter update each
        self.latest_frames: Dict[str, DepthFrame] = {}  # newest frame per camera, for set-pose checks and relocalize
        # Started once the tasks run, stopped before anything else: objects with async start()/stop()
        # (the control socket, the fleet link); ``remote`` adds the config's.
        self.services: list = []

    def _online_calibration(self) -> Optional[CalibrationFilter]:
        """The online calibration (``AppOptions.online_calibration``), started from its saved state."""
        if not (self.options.online_calibration and self.options.vision):
            return None
        f = CalibrationFilter(self.robot, plane_map=self.plane_map)  # the walls' as-built tolerances
        if self.calibration_store is not None:
            state, why = self.calibration_store.load()
            notes = [why] if state is None else f.load_json(state)
            for note in notes:
                log.info("online calibration: %s", note)
        return f

    # -- lifecycle ------------------------------------------------------------------------------

    def request_stop(self, reason: str) -> None:
        if self._stop is not None and not self._stop.is_set():
            self.exit_reason = reason
            self._loop.call_soon_threadsafe(self._stop.set)

    def pause(self) -> None:
        """Brake to a stop within the limits and hold (path following); SIGUSR1 does this."""
        self.core.pause()
        log.info("paused by operator")

    def resume(self) -> None:
        """Continue the path after ``pause``; SIGUSR2 does this."""
        self.core.resume()
        log.info("resumed by operator")

    def abort(self, reason: str = "aborted by operator") -> None:
        if self.core.abort(reason):
            log.info("%s", reason)

    def set_pose(self, pose: Sequence[float], cov: np.ndarray, source: str, hidden_walls: Sequence[Dict] = ()) -> None:
        """Reset the fused pose now (operator, fleet); recorded, so that replay resets it too.
        ``hidden_walls``: what a relocalization could not exclude (ControllerCore.set_pose)."""
        self.chassis.poll()  # the odometry received before the reset goes in before it, as it came
        t = time.monotonic()
        self.core.set_pose(t, *pose, cov, hidden_walls=hidden_walls)
        self.core.recovery.pose_set_by_operator(t)  # the next views must confirm it
        self._record("status", t, functools.partial(channels.set_pose_message, t, pose[0], pose[1], pose[2], cov, source,
                                                    hidden_walls))
        log.info("pose set to (%.3f, %.3f, %.1f deg) by %s", pose[0], pose[1], math.degrees(pose[2]), source)

    def restart_recovery(self, why: str) -> None:
        """Start the recovery sequence afresh (operator, fleet): relocalize, then turn and move as
        the config allows, even where a stopped turn or move had ended the last one for good."""
        t = time.monotonic()
        self.core.recovery.force(t, why)
        self._record("status", t, functools.partial(channels.recovery_request_message, t, why))
        log.warning("relocalizing: %s", why)

    def call_on_loop(self, fn: Callable[[], T]) -> concurrent.futures.Future:
        """Call ``fn`` on the app's event loop from another thread (a program embedding the app, a
        test) and get its result or exception in the future: the core is not thread-safe."""
        if self._loop is None:
            raise RuntimeError("the app is not running: nothing to call on")

        async def call() -> T:
            return fn()

        return asyncio.run_coroutine_threadsafe(call(), self._loop)

    def stall_control_loop(self, seconds: float) -> None:
        """Test hook: make the control tick miss its ticks (a hung loop) for ``seconds``."""
        self._stall_control_until = time.monotonic() + seconds

    async def run(self) -> int:
        """Run until stopped; 0 on a normal end (path done, signal), 1 on a failure at start."""
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        sys.setswitchinterval(GIL_SWITCH_INTERVAL)
        if self.options.install_signal_handlers:
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._loop.add_signal_handler(sig, self.request_stop, f"signal {signal.Signals(sig).name}")
            self._loop.add_signal_handler(signal.SIGUSR1, self.pause)
            self._loop.add_signal_handler(signal.SIGUSR2, self.resume)
        tasks: List[asyncio.Task] = []
        try:
            # Before the link is up: compiling holds the interpreter for seconds, which the link's
            # watchdog would take for a dead board.
            if self.localizer is not None and not await self._warm_up_kernels():
                return 1
            sd_notify.status("starting: connecting to the motor board")
            if not await self._connect_chassis():
                return 0 if self._stop.is_set() else 1  # stopped while waiting is a normal end
            self.recorder.set_depth_budget(self.robot.recording.depth_max_mbit_s)
            self.live_view.set_depth_budget(self.robot.recording.live_depth_max_mbit_s)
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
            try:
                await self.live_view.start(self.plane_map, [c.name for c in self.cameras])
            except DriverError as e:  # an engineer's view must never keep the robot from running
                log.warning("live view off: %s", e)
                self.live_view = NullLiveView()
            self.live_view.publish_static_transforms(time.monotonic(), camera_mounts(self.robot.cameras))
            if self.localizer is not None:  # label images cost memory: only for a view or a recording
                self.localizer.keep_roi_labels = self.live_view.active or self.recorder.active
            self._odometry_queue = self.chassis.odometry_queue()
            self._odometry_queue.set_listener(self._odometry)
            self._start_control()
            tasks = [self._loop.create_task(self._status_task(), name="status")]
            if self.localizer is not None:
                self._start_localization()
                tasks.append(self._loop.create_task(self._recovery_task(), name="recovery"))
            if self.options.remote:
                self.services += remote_services(self)
            for service in self.services:
                await service.start()
            sd_notify.ready(self.status_line())
            log.info("running: %s", self.status_line())
            await self._stop.wait()
            return 0
        finally:
            await self._shutdown(tasks)

    async def _warm_up_kernels(self) -> bool:
        """Load the plane fit's, the integrity checks' and the obstacle scan's kernels (built ahead
        of time, or numba's from its cache), or compile them, before the first frame: a first start
        without them compiles for minutes (10 to 20 on a Nano), which must not fall on the
        localization or the protective stop of a moving robot."""
        from robot.control import scan_kernels
        from robot.localization import fit_kernels, integrity_kernels

        sd_notify.status("starting: loading the compiled kernels (a first start without `robotctl kernels build` "
                         "compiles them: minutes on a Nano)")
        keep_alive = self._loop.create_task(self._extend_start_while_compiling(), name="start-extension")
        try:
            for what, kernels in (("plane-fit kernels", fit_kernels), ("integrity kernels", integrity_kernels),
                                  ("obstacle-scan kernels", scan_kernels)):
                try:
                    seconds = await self._loop.run_in_executor(self._executor, kernels.warm_up)
                except Exception as e:  # ROBOT_KERNELS=numba and they do not compile: the operator asked for them
                    self.exit_reason = f"{what}: {type(e).__name__}: {e}".splitlines()[0]
                    log.error("%s", self.exit_reason)
                    return False
                log.info("%s: %s; ready in %.1f s", what, kernels.backend_note(), seconds)
        finally:
            keep_alive.cancel()
        # What the protection levels assume of the cameras: an engineer whose robot stays degraded
        # in a large room looks here first (docs/calibration.md, 'What a calibration file buys').
        log.info("%s", error_model_note(self.robot.localizer))
        return True

    async def _extend_start_while_compiling(self) -> None:
        """Ask systemd for more start time while the kernels compile. Without the ahead-of-time
        build (install step 5 failed, or an upgrade changed the kernels' sources) the first start
        compiles them with numba: about two minutes of CPU on the development machine under
        Python 3.8 (BENCHMARKS.md), so 10 to 20 minutes on a Nano, far beyond the unit's
        TimeoutStartSec. Killed there, it would restart into the rest of the same compile (numba
        keeps each kernel it finished), a failed start every three minutes until the cache is
        whole, the robot idle and the journal full of failures. Each ask reaches three periods
        past now and is renewed every period from the event loop, so a process whose loop hangs
        loses its extension within that; none is asked after ``kernel_compile_limit`` (a compile
        that hangs in its thread is not kept alive either)."""
        period = self.options.start_extend_period
        t0 = time.monotonic()
        while time.monotonic() - t0 < self.options.kernel_compile_limit:
            sd_notify.extend_timeout(3.0 * period)
            await asyncio.sleep(period)

    async def _connect_chassis(self) -> bool:
        t0 = time.monotonic()
        last_error, attempts = "", 0
        while not self._stop.is_set():
            try:
                await self.chassis.connect()
                log.info("motor board connected")
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
            if self.localizer is not None and self.robot.recovery.enabled:
                log.info("no initial pose given: relocalizing from the map")
                self.core.recovery.start_without_pose(t)
            else:
                log.warning("no initial pose given: the robot will not move until one is set")
            return
        if source.startswith("saved pose"):
            self.core.recovery.start_from_saved_pose(t)  # the robot may have been moved while off
        self.core.set_pose(t, *pose, cov)
        self._record("status", t, functools.partial(channels.set_pose_message, t, pose[0], pose[1], pose[2], cov, source))
        log.info("initial pose (%.3f, %.3f, %.1f deg) from %s", pose[0], pose[1], math.degrees(pose[2]), source)

    async def _shutdown(self, tasks: List[asyncio.Task]) -> None:
        sd_notify.stopping(f"stopping: {self.exit_reason or 'done'}")
        for service in reversed(self.services):  # no command may arrive while the robot shuts down
            try:
                await service.stop()
            except Exception as e:  # noqa: PERF203 - shutdown must go on
                log.error("stopping %s: %s", type(service).__name__, e)
        self._stop_control()  # with the tasks: no tick and none of the core's inputs after this
        self.chassis.poll()  # what the driver holds is fused before the pose is saved
        self._stop_odometry()
        self._stop_localization()
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
        if self.core.calibration is not None and self.calibration_store is not None:
            self.calibration_store.save(time.monotonic(), self.core.calibration.to_json(), force=True)
        await self.live_view.stop()
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
        self._record("odometry", sample.t, functools.partial(channels.gyro_message, sample.t, wz, GYRO_VARIANCE, camera.name))

    def _camera_state_threadsafe(self, name: str, state: CameraState) -> None:
        try:
            self._loop.call_soon_threadsafe(self._camera_state, name, state)
        except RuntimeError:
            pass

    def _camera_state(self, name: str, state: CameraState) -> None:
        old = self.camera_states.get(name)
        self.camera_states[name] = state.value
        if old != state.value:  # starting, streaming and stopping are its normal life; the rest is trouble
            trouble = state in (CameraState.STALLED, CameraState.GONE)
            (log.warning if trouble else log.info)("camera %s: %s", name, state.value)

    def _frame_arrived(self, frame: DepthFrame) -> None:
        self.stats.frames[frame.camera] = self.stats.frames.get(frame.camera, 0) + 1
        if not self.frame_check.admit(frame, time.monotonic()):  # before it can displace a good frame
            n = self.frame_check.refused[frame.camera]
            if n == 1 or n % 100 == 0:
                log.warning("frame refused (%d so far from this camera): %s", n, self.frame_check.last_reason[frame.camera])
            return
        if self._slots.get(frame.camera) is not None:
            self.stats.frames_dropped[frame.camera] = self.stats.frames_dropped.get(frame.camera, 0) + 1
        self._slots[frame.camera] = frame
        self.latest_frames[frame.camera] = frame
        self._consider_set()

    # -- tasks ----------------------------------------------------------------------------------

    def _odometry(self, odo: WheelOdometry) -> None:
        """Each wheel odometry sample, on the loop as the chassis driver receives it (its queue's
        listener: a task woken per sample cost a loop iteration a hundred times a second)."""
        try:
            self.stats.odometry += 1
            self.core.on_odometry(odo, quantisation_variance(self.robot.chassis.ticks_per_rev, odo.dt))
            self.odom.update(odo)
            if self.recorder.active:
                self._record("odometry", odo.t, functools.partial(channels.odometry_message, odo.t, odo.speeds,
                                                                  odo.angles, odo.dt, odo.t_board))
        except Exception:
            # As when this was a task that died: no more odometry is fused (the pose goes stale and
            # the control tick stops the robot), and the driver's message handling goes on.
            log.exception("wheel odometry: handling a sample failed; odometry is no longer fused")
            self._stop_odometry()

    def _stop_odometry(self) -> None:
        if self._odometry_queue is not None:
            self._odometry_queue.set_listener(None)
            self._odometry_queue = None

    # -- the localization pipeline ---------------------------------------------------------------
    #
    # The frames of all cameras are handled as one set: one hop to the worker (obstacle scans and
    # localizations) and one fusion step per set, so the filter's history is replayed once per set
    # rather than once per camera. Each frame is still localized alone, from the coarse pose at its
    # own capture time: unsynchronized cameras are up to a frame period apart. The pipeline is
    # callbacks on the loop, not a task: a frame's arrival, the end of the wait for the rest of a
    # set and the worker's result each run it on in the loop iteration that brought them (a task
    # woke one iteration later, and each iteration gives up and retakes the GIL beside the worker).

    def _start_localization(self) -> None:
        self._sets_running = True
        self._consider_set()  # frames that came before

    def _stop_localization(self) -> None:
        """No set is sent after this, and the result of one in the worker is dropped."""
        self._sets_running = False
        if self._set_timer is not None:
            self._set_timer.cancel()
            self._set_timer = None

    def _consider_set(self) -> None:
        """A frame arrived, or the worker is free: send the set when the other streaming cameras'
        frames are in, else wait for them at most half a frame period from now (unsynchronized
        cameras deliver at any phase, and the protective stop's reaction time must not wait for a
        camera that has stalled). A camera that is not streaming is not waited for."""
        if not self._sets_running or self._set_in_worker or all(f is None for f in self._slots.values()):
            return
        missing = [name for name, frame in self._slots.items()
                   if frame is None and self.camera_states.get(name) == _STREAMING]
        if not missing:
            self._send_set()
        elif self._set_timer is None:
            wait = 0.5 / max(c.fps for c in self.robot.cameras) if self.robot.cameras else 0.0
            if wait > 0.0:
                self._set_timer = self._loop.call_later(wait, self._set_wait_over)
            else:
                self._send_set()

    def _set_wait_over(self) -> None:
        self._set_timer = None
        if self._sets_running and not self._set_in_worker:
            self._send_set()

    def _send_set(self) -> None:
        """Take the frames out of their slots and hand them to the worker."""
        if self._set_timer is not None:
            self._set_timer.cancel()
            self._set_timer = None
        frames = [f for f in (self._slots.get(name) for name in list(self._slots)) if f is not None]
        for frame in frames:
            self._slots[frame.camera] = None
        if not frames:
            return
        # The protective stop sees every frame, with the pose if there is one; the localizer
        # only once there is a pose to refine. Each coarse pose with the odometry received so far.
        self.chassis.poll()
        localize = self.core.initialized and self.localizer is not None
        coarse = [self.core.coarse_pose(f.t_capture) if self.core.initialized else None for f in frames]
        for frame in frames:
            self.live_view.publish_depth(frame.t_capture, frame)
            if localize:
                self.recorder.write_depth(frame.t_capture, frame)  # only frames the localizer uses, within the budget
        self._set_in_worker = True
        walls = self.core.walls_explain_obstacles
        work = self._executor.submit(self._process_frames, frames, coarse, localize, walls)
        work.add_done_callback(functools.partial(self._set_processed_threadsafe, frames, coarse, localize))

    def _set_processed_threadsafe(self, frames: List[DepthFrame], coarse: list, localize: bool,
                                  work: concurrent.futures.Future) -> None:
        try:
            self._loop.call_soon_threadsafe(self._set_processed, frames, coarse, localize, work)
        except RuntimeError:
            pass  # the loop is closed: shutting down

    def _set_processed(self, frames: List[DepthFrame], coarse: list, localize: bool,
                       work: concurrent.futures.Future) -> None:
        self._set_in_worker = False
        if not self._sets_running:
            return  # stopped meanwhile: nothing more is fused
        self.chassis.poll()  # the odometry received so far goes in first, as it came before
        try:
            if localize:
                self._fuse_set(frames, coarse, work.result())
            else:
                work.result()
        except Exception:
            # As when this was a task that died: no more frames are scanned or localized (the
            # protective stop's scans age out and it holds the robot).
            log.exception("localization: handling a set of frames failed; no more frames are localized")
            self._stop_localization()
            return
        self._consider_set()  # frames that came meanwhile

    def _fuse_set(self, frames: List[DepthFrame], coarse: list, outcomes: list) -> None:
        done = []
        for frame, prior, result in zip(frames, coarse, outcomes):
            if isinstance(result, Exception):  # a bad frame is reported and skipped, never fused
                log.warning("camera %s frame %d: localization failed: %s", frame.camera, frame.frame_number, result)
                continue
            self.stats.localizations += 1
            self.stats.localize_ms.append(result.ms)
            done.append((frame, prior, result))
        if len(self.stats.localize_ms) > 10000:
            del self.stats.localize_ms[:5000]
        if not done:
            return
        reports = self.core.on_localizations([(result, frame.t_capture, frame.camera) for frame, _, result in done])
        self._fusion_steps += 1
        for (frame, ((x, y, phi), P), result), report in zip(done, reports):
            name = frame.camera
            # everything replay needs to redo this localization bit for bit, and what it gave
            self._record("planes", frame.t_capture, functools.partial(channels.planes_message,
                frame.t_capture, name, result.planes, frame_number=frame.frame_number, method=self.options.method,
                coarse=(x, y, phi), coarse_cov=P, status=result.status, accepted=report.accepted,
                rejected=report.rejected, measurements=result.measurements, fusion_step=self._fusion_steps))
            self.live_view.publish_planes(frame.t_capture, name, result.planes)
            if self.recorder.active:
                self.recorder.write(channels.TOPIC_PLANE_FITS, frame.t_capture, channels.plane_fits_message(
                    frame.t_capture, name, result.planes, self.plane_map))
            labels = self.localizer.last_roi_labels.get(name)
            if labels is not None:
                self.live_view.publish_roi(frame.t_capture, name, labels)
                self.recorder.write_roi(frame.t_capture, name, labels)

    def _process_frames(self, frames: Sequence[DepthFrame], coarse: Sequence[Optional[Tuple]], localize: bool,
                        walls: bool = True) -> list:
        """On the worker: each frame's obstacle scan (``walls``: mapped walls explained at the coarse
        pose), then (``localize``) its localization, or the exception that stopped it."""
        scaled = [calibrated_frame(f, self.robot.camera(f.camera).depth_scale) for f in frames]
        for frame, prior in zip(scaled, coarse):
            self._scan_obstacles(frame, None if prior is None or not walls else prior[0])
        if not localize:
            return []
        out: list = []
        for frame, ((x, y, phi), P) in zip(scaled, coarse):
            try:
                out.append(self.localizer.localize([frame], (x, y, phi), P, self.options.method))
            except Exception as e:
                out.append(e)
        return out

    async def _recovery_task(self) -> None:
        """Relocalize when the recovery supervisor asks (no pose, lost, kidnapped, a saved pose the
        cameras contradict): on the first frame of every camera taken after the request, off the loop.
        After an in-place turn (recovery.turn_in_place) or a move (recovery.move_to_tell_apart) the
        earlier views of the sequence go with it, each with its odometry pose; the answer is for
        where the robot stands now. The move is planned here, off the loop, when the supervisor
        asks for one."""
        from robot.control.recovery import views_from_latest
        from robot.localization.relocalize import Relocalizer
        from robot.localization.viewpoint import ViewpointPlanner, plan_recovery_move

        relocalizer: Optional[Relocalizer] = None
        planner: Optional[ViewpointPlanner] = None
        views: List[Tuple[List[DepthFrame], Tuple[float, float, float]]] = []
        while True:
            await asyncio.sleep(RECOVERY_POLL)
            self.chassis.poll()  # whether the robot stands still, by the odometry received so far
            t_request = time.monotonic()
            if not self.core.relocalization_due(t_request):
                continue
            sd_notify.status(f"relocalizing: {self.core.recovery.reason}")
            log.warning("relocalizing: %s", self.core.recovery.reason)
            if self.core.recovery.view_index == 0:
                views = []
            rel = self.core.recovery_view_pose()  # the robot stands still until the verdict
            frames = await self._frames_after(t_request)
            views.append((frames, rel))
            first, more = views_from_latest(views)
            if relocalizer is None:
                relocalizer = await self._loop.run_in_executor(self._executor, Relocalizer, self.robot, self.plane_map,
                                                               self.localizer)
            try:
                res = await self._loop.run_in_executor(self._executor, functools.partial(
                    relocalizer.relocalize, first, more_views=more))
            except Exception as e:  # a bad frame: report it and try again later, never move on it
                log.error("relocalization failed: %s", e)
                self.core.recovery.on_verdict(time.monotonic(), "none", [], str(e), may_turn=False)
                continue
            t_frames = max(f.t_capture for f in frames)
            self.chassis.poll()  # (the odometry received before the reset goes in before it)
            if res.verdict == "unique":
                h = res.hypotheses[0]
                self.core.set_pose(t_frames, h.x, h.y, h.phi, np.asarray(h.cov, float), hidden_walls=h.hidden_walls)
                self._record("status", t_frames, functools.partial(channels.set_pose_message, t_frames, h.x, h.y, h.phi,
                                                                           np.asarray(h.cov, float), "relocalization",
                                                                           h.hidden_walls))
                log.info("relocalized at (%.3f, %.3f, %.1f deg) from %d view(s); confirming", h.x, h.y,
                         math.degrees(h.phi), len(views))
            else:
                log.warning("relocalization %s from %d view(s): %s", res.verdict, len(views), res.reason)
            rec = self.core.recovery
            rec.on_verdict(time.monotonic(), res.verdict, [h.to_json() for h in res.hypotheses[:8]], res.reason)
            if rec.wants_move_plan:
                cfg = self.robot.recovery
                if planner is None:
                    planner = await self._loop.run_in_executor(self._executor, ViewpointPlanner, self.robot,
                                                               self.plane_map, relocalizer.index)
                move, why = await self._loop.run_in_executor(self._executor, plan_recovery_move, planner,
                                                             res.hypotheses, cfg.move_max_distance, cfg.move_clearance,
                                                             rec.moves_left)
                if move is not None:
                    log.warning("relocalization ambiguous: moving (%.2f, %.2f) m in the robot frame for a view that "
                                "tells the places apart", move[0], move[1])
                rec.move_planned(time.monotonic(), move, why)

    async def _frames_after(self, t: float) -> List[DepthFrame]:
        """The first frame of every camera captured after ``t`` (the robot stands still meanwhile)."""
        while True:
            frames = [f for f in self.latest_frames.values() if f.t_capture > t]
            if len(frames) == len(self.cameras) and frames:
                return frames
            await asyncio.sleep(RECOVERY_POLL / 4)

    def _scan_obstacles(self, frame, pose) -> None:
        try:
            self.core.safety.update_scan_frame(frame, pose)
        except Exception as e:  # a bad frame must not kill the worker; its camera's scan just ages out
            log.warning("camera %s frame %d: obstacle scan failed: %s", frame.camera, frame.frame_number, e)

    def _start_control(self) -> None:
        """Tick at ``control.rate`` on absolute deadlines. Each tick is a timer callback that
        schedules the next, not a task that sleeps: a sleeping task costs a future and a second
        loop iteration per tick. A tick that raises schedules no more (as the task died with
        it): the board's watchdog then stops the wheels and systemd's the process."""
        self._control_period = 1.0 / self.robot.control.rate
        self._control_next = self._loop.time()
        self._schedule_tick()

    def _schedule_tick(self) -> None:
        loop = self._loop
        period = self._control_period
        self._control_next += period
        delay = self._control_next - loop.time()
        if delay > 0:
            self._control_timer = loop.call_at(self._control_next, self._control_tick)
            return
        if delay < -period:
            self._control_next = loop.time()  # fell behind by more than a tick: do not burst to catch up
        self._control_timer = loop.call_soon(self._control_tick)

    def _control_tick(self) -> None:
        self._control_timer = None
        if time.monotonic() < self._stall_control_until:
            time.sleep(self._control_period)  # simulate a hung loop: block the event loop itself
        else:
            # The chassis driver holds its routine reports for this poll rather than wake the loop
            # for each: every report received before the tick's time is fused before its step.
            self.chassis.poll()
            self._tick(time.monotonic())
        self._schedule_tick()

    def _stop_control(self) -> None:
        if self._control_timer is not None:
            self._control_timer.cancel()
            self._control_timer = None

    def _tick(self, t: float) -> None:
        ticks = self.stats.tick_times
        ticks.append(t)
        if len(ticks) > 20000:
            del ticks[:10000]
        link_ok = self.chassis.link_state is LinkState.READY
        self.core.set_chassis_link(link_ok, "" if link_ok else f"chassis link {self.chassis.link_state.value}")
        reconnects = self.chassis.reconnects
        if self._reconnects is not None and reconnects != self._reconnects:
            # a new session (perhaps a rebooted board) may have come up between two ticks
            self.core.note_fault(t, "the motor board reconnected")
        self._reconnects = reconnects
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
        c = out.command
        if self.recorder.active:  # (not even the message's recipe is built for nobody)
            self._record("cmd", t, functools.partial(channels.cmd_message, t, c.vx, c.vy, c.wz, out.wheels,
                                                     sent=out.wheels is not None, state=c.state, scale=out.speed_scale,
                                                     reason=out.reason))
        self.live_view.publish_cmd(t, c.vx, c.vy, c.wz, out.wheels)
        self._publish_pose(t)
        if self.options.stop_when_done and self.core.finished:
            self.request_stop("path complete")
        if self.on_tick is not None:
            self.on_tick(self, t)

    async def _status_task(self) -> None:
        while True:
            await asyncio.sleep(self.options.status_period)
            self.chassis.poll()
            t = time.monotonic()
            line = self.status_line()
            sd_notify.status(line)
            if self.core.initialized and self.pose_store is not None:
                (x, y, phi), P = self.core.pose(t)
                self.pose_store.save(t, x, y, phi, P, self.plane_map.source)
            if self.core.calibration is not None and self.calibration_store is not None:
                self.calibration_store.save(t, self.core.calibration.to_json())
            status = self.status(t)
            self._record("status", t, functools.partial(channels.status_message, t, status))
            self.live_view.publish_status(t, status)

    def _publish_pose(self, t: float) -> None:
        """Every control tick: the fused pose the tick used, with its quality, and the REP-105
        transforms: map -> odom corrected by it, odom -> base_link from the wheels alone."""
        if not self.core.initialized or not (self.recorder.active or self.live_view.active):
            return  # nobody listens: nothing to compute
        s = self.core.status(t)  # the pose at t and the quality this tick's control step judged
        self._record("pose", t, functools.partial(channels.pose_message, t, s["x"], s["y"], s["phi"], s["cov"], quality=s["quality"],
                                                      reason=s["reason"]))
        self.live_view.publish_pose(t, s["x"], s["y"], s["phi"], s["cov"], s["quality"], s["reason"])
        # both transforms at the time of the newest odometry, so that they compose to the fused pose there
        t_odom = self.odom.t if self.odom.t is not None else t
        T_map_base, _ = self.core.pose(t_odom)
        T_map_odom, T_odom_base = self.odom.map_to_odom(T_map_base), self.odom.pose
        if self.recorder.active:
            self.recorder.write(channels.TOPIC_TF, t, channels.odometry_transforms(t_odom, T_map_odom, T_odom_base))
        self.live_view.publish_tf(t_odom, T_map_odom, T_odom_base)

    # -- reporting ------------------------------------------------------------------------------

    def status(self, t: Optional[float] = None) -> Dict[str, object]:
        self.chassis.poll()  # the pose with the odometry received so far
        t = time.monotonic() if t is None else t
        s = self.core.status(t)
        s["cameras"] = dict(self.camera_states)
        s["chassis"] = self.chassis.link_state.value
        s["frames_dropped"] = dict(self.stats.frames_dropped)
        s["frames_refused"] = dict(self.frame_check.refused)
        if self.frame_check.last_reason:
            s["frame_refusal"] = dict(self.frame_check.last_reason)
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

    def _record(self, kind: str, t: float, message: Callable[[], Dict[str, object]]) -> None:
        """Record with a sequence number: replay redoes the core's calls in exactly this order.
        ``message`` builds the message: only when recording (the loop builds hundreds a second)."""
        if not self.recorder.active:
            return
        msg = message()
        self._record_seq += 1
        msg["seq"] = self._record_seq
        self.recorder.write(_TOPICS[kind], t, msg)

    def _write_config_record(self) -> None:
        """The run's config (YAML text and effective values) and map, at the start of the recording."""
        t = time.monotonic()
        self.recorder.write_config(t, _read_text(self.robot.source), _read_text(self.plane_map.source),
                                   robot_config_path=self.robot.source, map_path=self.plane_map.source,
                                   effective_config=effective_config_dict(self.robot, self.plane_map.source))
        self.recorder.write(channels.TOPIC_MAP, t, channels.map_message(self.plane_map, t))
        self.recorder.write(channels.TOPIC_TF_STATIC, t, channels.transforms_message(t, camera_mounts(self.robot.cameras)))


_TOPICS = {"odometry": channels.TOPIC_ODOMETRY, "planes": channels.TOPIC_PLANES, "cmd": channels.TOPIC_CMD,
           "pose": channels.TOPIC_POSE, "status": channels.TOPIC_STATUS}


def _read_text(path: str) -> str:
    try:
        with open(path, encoding="utf-8") as f:
            return f.read()
    except OSError:
        return f"# {path} was not readable at record time\n"
