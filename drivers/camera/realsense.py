"""The real D435i driver (pyrealsense2): one capture thread per camera, depth only, optional IMU.

What it does, and why:

- **Depth only** at the configured resolution and rate (848x480 at 30 fps by default): no colour,
  no alignment, no pointcloud, which cost a Jetson Nano most of its frame rate.
- **Copies, never holds.** Each frame's pixels are copied into a numpy array and every
  librealsense frame reference is dropped before the frame is handed on. Frames held by the
  application starve librealsense's frame pool, a known cause of "Frame didn't arrive within
  5000".
- **Newest frame wins.** On a live camera the capture thread drains the pipeline's queue and
  hands on the newest frame; skipped frames show up as frame-number gaps and are counted as
  ``drops``, never queued. (A recording plays back non-real-time, so nothing is skipped.)
- **Never the same frame twice.** librealsense can hand the same frameset over again (seen
  after a stream restart under load, and known from bag playback): a frame whose number and
  device time are not after the last one delivered in this session is counted as a
  ``duplicates`` and dropped, unless its clock went back far enough to be a device restart.
- **Timestamps** are the camera's (hardware clock, or librealsense's global time) mapped to the
  host's ``time.monotonic()`` by :class:`ClockMapper`, with the timestamp domain kept per frame.
- **Faults** become states for the app's health supervision, and the driver recovers by itself:
  a frame timeout is STALLED; a stall that lasts ``stalls_before_reset`` timeouts triggers a
  ``hardware_reset()`` (live cameras) or a stream restart; a device that disappears (devices-
  changed callback, or a presence poll on every timeout) is GONE and is polled for with capped
  exponential backoff until it comes back, then reopened.
- **IMU** (gyro and accel of a D435i) through its own sensor callback, not the depth pipeline:
  a pipeline delivers at most one motion sample per frameset. Samples go to ``on_imu`` as
  ``ImuSample``s on the host monotonic clock, in the camera's IMU frame (the depth axes,
  :mod:`drivers.camera.realsense_imu`); ``T_robot_imu`` and ``yaw_rate_robot`` give the robot's yaw rate.

The device comes from an injectable source: :class:`LiveDevice` (by serial number, or the only
camera present) on the robot, :class:`PlaybackFile` (a librealsense ``.bag`` recording, played
back non-real-time through the same ``rs.pipeline``; ``drivers.camera.bag.BagCamera`` is this
driver on one) in tests, benchmarks and replays.

pyrealsense2 is imported lazily so that the rest of the project works where it is missing.
"""

from __future__ import annotations

import collections
import logging
import os
import threading
import time
from typing import TYPE_CHECKING, Any, Callable, Deque, Dict, List, Optional, Tuple

import numpy as np

from drivers.camera.base import CameraDriver, CameraState, FrameCallback, ImuCallback
from drivers.camera.realsense_imu import D435I_T_CAMERA_IMU, T_from_rs_extrinsics
from robot.base.errors import DriverError
from robot.base.samples import DepthFrame, ImuSample
from robot.config.realsense import (  # noqa: F401  (re-exported: the driver's settings)
    VISUAL_PRESETS,
    RealSenseConfig,
    parse_realsense_config,
)

if TYPE_CHECKING:  # only for annotations: the driver module stays importable on its own
    from robot.config import CameraConfig

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------------
# pyrealsense2 access
# --------------------------------------------------------------------------------------------


def load_pyrealsense2():
    """Import pyrealsense2, or raise DriverError saying how to get it."""
    try:
        import pyrealsense2 as rs
    except ImportError as e:
        raise DriverError(f"pyrealsense2 is not usable ({e}); install it with "
                          f"pip install 'pyrealsense2>=2.55.1,<2.56' (and apt libusb-1.0-0)") from None
    return rs


def pyrealsense2_version() -> str:
    """The installed wheel's version (2.55 has no ``rs.__version__``)."""
    try:
        from importlib.metadata import version
    except ImportError:  # pragma: no cover - Python < 3.8
        return "unknown"
    try:
        return version("pyrealsense2")
    except Exception:
        return "unknown"


def domain_name(rs, domain) -> str:
    """``rs.timestamp_domain.hardware_clock`` -> ``"hardware_clock"``."""
    for name in ("hardware_clock", "system_time", "global_time"):
        if domain == getattr(rs.timestamp_domain, name, None):
            return name
    return str(domain).rsplit(".", 1)[-1]


def intrinsics_to_K(intr) -> np.ndarray:
    """librealsense intrinsics -> 3x3 K. Both put pixel centres at integer coordinates."""
    return np.array([[intr.fx, 0.0, intr.ppx], [0.0, intr.fy, intr.ppy], [0.0, 0.0, 1.0]], dtype=float)


# --------------------------------------------------------------------------------------------
# Clock mapping
# --------------------------------------------------------------------------------------------


class ClockMapper:
    """Maps device timestamps to the host's monotonic clock.

    For every sample, ``arrival - t_device`` is the clock offset plus that sample's transport
    latency, which is never negative. The minimum over a sliding window of host time therefore
    estimates the offset plus the *smallest* latency seen, which is robust to USB and scheduling
    jitter (those only ever add latency) and follows slow clock drift once old samples leave the
    window. The mapped time ``t_device + offset`` is never later than the sample's arrival.

    Streams in the same timestamp domain (depth, gyro, accel of one camera) share one estimate:
    the small motion packets reach the host with the least latency, so they tighten the offset
    for depth frames too. The estimate restarts when the domain changes or the device clock
    jumps (a reset or reconnect restarts it; a recording that loops restarts it; the D400's
    32-bit microsecond counter wraps after about 71 minutes). The output is kept monotonic per
    stream, so a consumer never sees time run backwards.

    Residual bias: the mapped time is late by the minimum transport latency (a constant of a few
    milliseconds for depth over USB 3), which the host cannot observe.
    """

    JUMP_BACK = 0.5  # s: a device clock this far behind its last value has restarted
    JUMP_AHEAD = 60.0  # s: ... or this far ahead (a counter wrap seen from the other side)

    def __init__(self, window: float = 10.0):
        self.window = float(window)
        self._lock = threading.Lock()
        self._domains: Dict[str, Tuple[Deque[Tuple[float, float]], List[float]]] = {}
        self._last_out: Dict[str, float] = {}
        self.resets = 0

    def reset(self) -> None:
        with self._lock:
            self._domains.clear()
            # _last_out is kept: output stays monotonic across a device restart.

    def offset(self, domain: str) -> Optional[float]:
        with self._lock:
            entry = self._domains.get(domain)
            return entry[0][0][1] if entry and entry[0] else None

    def map(self, stream: str, t_device: float, arrival: float, domain: str) -> float:
        """Host monotonic time of a sample stamped ``t_device`` (s) that arrived at ``arrival``."""
        with self._lock:
            entry = self._domains.get(domain)
            if entry is not None:
                last_t = entry[1][0]
                if t_device < last_t - self.JUMP_BACK or t_device > last_t + self.JUMP_AHEAD:
                    entry = None
                    self.resets += 1
            if entry is None:
                entry = self._domains[domain] = (collections.deque(), [t_device])
            window, last = entry
            last[0] = max(last[0], t_device)
            off = arrival - t_device
            # Monotone deque: offsets increase from the front; the front is the window minimum.
            while window and window[-1][1] >= off:
                window.pop()
            window.append((arrival, off))
            while window[0][0] < arrival - self.window:
                window.popleft()
            t = t_device + window[0][1]
            prev = self._last_out.get(stream)
            if prev is not None and t <= prev:
                t = prev + 1e-6
            self._last_out[stream] = t
            return t


# --------------------------------------------------------------------------------------------
# Device sources
# --------------------------------------------------------------------------------------------


class DeviceSource:
    """Where a driver's device comes from. The driver only talks to librealsense through this
    and ``rs.pipeline``, so the same capture code runs on a camera and on a recording."""

    description = "device"
    is_playback = False
    reset_settle: Optional[float] = None  # None: the driver's config decides

    def make_pipeline(self, rs):
        return rs.pipeline()

    def configure(self, rs, cfg) -> None:
        """Select this device in an ``rs.config``. Raise DriverError if it cannot be selected."""
        raise NotImplementedError

    def is_present(self) -> bool:
        raise NotImplementedError

    def before_stop(self, device) -> None:
        """Called just before the driver stops the pipeline of ``device`` (a camera: nothing)."""

    def finished(self, device) -> bool:
        """True when the stream ended for good (a recording played to its end)."""
        return False

    def can_reset(self) -> bool:
        return False

    def reset(self, device) -> None:
        """Hardware-reset a stuck device (only if ``can_reset``)."""

    def watch(self, on_change: Callable[[], None]) -> None:
        """Call ``on_change`` (from any thread) when devices are added or removed."""

    def unwatch(self) -> None:
        pass


class LiveDevice(DeviceSource):
    """A connected RealSense camera, by serial number, or the only one present."""

    def __init__(self, serial: Optional[str] = None, context=None):
        self.serial = serial
        self._ctx = context
        self._resolved_serial: Optional[str] = serial
        self.description = f"RealSense {serial}" if serial else "the only RealSense camera"

    def _context(self, rs):
        if self._ctx is None:
            self._ctx = rs.context()
        return self._ctx

    def make_pipeline(self, rs):
        return rs.pipeline(self._context(rs))

    def _serials(self, rs) -> List[str]:
        out = []
        for dev in self._context(rs).query_devices():
            try:
                out.append(dev.get_info(rs.camera_info.serial_number))
            except RuntimeError:  # enumerated but not openable (being reset): not present yet
                continue
        return out

    def configure(self, rs, cfg) -> None:
        serials = self._serials(rs)
        if self.serial is None:
            if len(serials) > 1:
                raise DriverError(f"{len(serials)} RealSense cameras connected ({', '.join(serials)}): "
                                  f"set 'serial' for this camera in the robot config")
            if self._resolved_serial is None:
                if not serials:
                    raise DriverError("no RealSense camera connected")
                self._resolved_serial = serials[0]
        if self._resolved_serial not in serials:
            raise DriverError(f"RealSense {self._resolved_serial} is not connected "
                              f"(connected: {', '.join(serials) or 'none'})")
        cfg.enable_device(self._resolved_serial)

    def is_present(self) -> bool:
        rs = load_pyrealsense2()
        serials = self._serials(rs)
        if self._resolved_serial is None:
            return len(serials) == 1
        return self._resolved_serial in serials

    def can_reset(self) -> bool:
        return True

    def reset(self, device) -> None:
        device.hardware_reset()

    def watch(self, on_change: Callable[[], None]) -> None:
        rs = load_pyrealsense2()
        # The callback runs on librealsense's thread: only wake the capture thread from it.
        self._context(rs).set_devices_changed_callback(lambda info: on_change())

    def unwatch(self) -> None:
        if self._ctx is not None:
            try:
                self._ctx.set_devices_changed_callback(lambda info: None)
            except RuntimeError:
                pass


class PlaybackFile(DeviceSource):
    """A librealsense recording, played back through ``rs.pipeline`` exactly as a camera streams.

    Non-real-time by default: librealsense paces real-time playback by the wall-clock time at
    which each frame was recorded, not by its timestamp, so a recording written faster than real
    time would drop frames. Non-real-time playback delivers every frame and waits for the consumer
    (set before ``pipeline.start`` through ``config.resolve``, or the first frames can be lost).
    ``real_time=True`` plays a recording written at its own pace (``write_recording(real_time=True)``)
    like a live camera: frames are dropped when the consumer is slow, and ``pause()`` never waits
    on the consumer. The file existing stands for the device being plugged in.
    """

    is_playback = True

    def __init__(self, path, repeat: bool = False, real_time: bool = False):
        self.path = str(path)
        self.repeat = repeat
        self.real_time = real_time
        self.description = f"recording {self.path}"

    def configure(self, rs, cfg) -> None:
        if not os.path.isfile(self.path):
            raise DriverError(f"{self.path}: recording not found")
        cfg.enable_device_from_file(self.path, repeat_playback=self.repeat)

    def is_present(self) -> bool:
        return os.path.isfile(self.path)

    def finished(self, device) -> bool:
        rs = load_pyrealsense2()
        try:
            return device.as_playback().current_status() == rs.playback_status.stopped
        except RuntimeError:
            return False

    def before_stop(self, device) -> None:
        """Resume a paused playback, so that stopping its pipeline is librealsense's ordinary path
        (stopping a paused recording's is not, and is where a crash in our suite first showed; its
        cause was the recording's file moved away while open, which the tests no longer do)."""
        rs = load_pyrealsense2()
        try:
            pb = device.as_playback()
            if pb.current_status() == rs.playback_status.paused:
                pb.resume()
        except RuntimeError:
            pass


# --------------------------------------------------------------------------------------------
# The driver
# --------------------------------------------------------------------------------------------


class _Session:
    """One open stream: the pipeline, its device and the motion sensor if started."""

    def __init__(self, pipe, device, motion_sensor):
        self.pipe = pipe
        self.device = device
        self.motion_sensor = motion_sensor
        self.got_frame = False


class RealSenseCamera(CameraDriver):
    """A D435i behind the CameraDriver interface.

    ``on_frame`` is called from this camera's capture thread; ``on_imu`` from librealsense's
    motion-sensor thread. Both must return quickly (hand the data to the event loop).

    Besides the base statistics, ``stats`` counts ``drops`` (frame-number gaps), ``resets``
    (hardware resets issued), ``imu`` and ``imu_drops`` (motion samples and their gaps),
    ``imu_errors``. ``cpu_time`` is the capture thread's CPU seconds, ``last_error`` the last
    fault as text, ``intrinsics`` the stream's K and ``device_info`` name/serial/firmware/USB.

    Settings come from the camera's config: ``camera.realsense`` (the ``realsense:`` section of
    the camera in robot.yaml). IMU samples are ``ImuSample``s in the camera's IMU frame;
    ``T_robot_imu`` maps that frame to the robot's (``drivers.camera.realsense_imu.yaw_rate_robot``).
    """

    BACKOFF_START = 0.1  # s, first wait before looking for a GONE device again; doubles up to the cap
    FIRST_FRAME_TIMEOUT_MS = 5000  # a camera just started may take seconds to deliver its first frame

    def __init__(self, camera: CameraConfig, source: Optional[DeviceSource] = None):
        super().__init__(camera)
        self.config: RealSenseConfig = camera.realsense
        self.config.validate(f"camera '{camera.name}': realsense")
        self.source = source if source is not None else LiveDevice(camera.serial)
        self.stats.update({"drops": 0, "duplicates": 0, "resets": 0, "imu": 0, "imu_drops": 0, "imu_errors": 0})
        self.cpu_time = 0.0
        self.last_error: Optional[str] = None
        self.intrinsics: Optional[np.ndarray] = None
        self.depth_scale: Optional[float] = None
        self.device_info: Dict[str, str] = {}
        # IMU frame -> depth optical frame: the device's gyro extrinsics once the IMU streams
        self.T_camera_imu = D435I_T_CAMERA_IMU.copy()
        self.imu_extrinsics_source = "default"  # or "device"
        self.clock = ClockMapper(self.config.clock_window)
        self.ended = threading.Event()  # set when a recording played to its end
        self._rs = None
        self._thread: Optional[threading.Thread] = None
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._on_frame: Optional[FrameCallback] = None
        self._on_imu: Optional[ImuCallback] = None
        self._session: Optional[_Session] = None
        self._last_fn: Optional[int] = None
        self._last_t_dev = 0.0  # device time (s) of the last frame delivered in this session
        self._imu_last_fn: Dict[str, int] = {}
        self._filters: List[Tuple[str, Any]] = []
        self._logged: set = set()

    # ---- public ------------------------------------------------------------------------------

    @property
    def device(self):
        """The open librealsense device (a playback device for recordings), or None."""
        s = self._session
        return s.device if s is not None else None

    def start(self, on_frame: FrameCallback, on_imu: Optional[ImuCallback] = None) -> None:
        if self._thread is not None and self._thread.is_alive():
            return
        self._rs = load_pyrealsense2()
        self._on_frame = on_frame
        self._on_imu = on_imu
        self._stop.clear()
        self._wake.clear()
        self.ended.clear()
        self._filters = make_filters(self._rs, self.config)
        self._set_state(CameraState.STARTING)
        self.source.watch(self._wake.set)
        self._thread = threading.Thread(target=self._run, name=f"camera-{self.name}", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        t = self._thread
        if t is not None and t is not threading.current_thread():
            t.join(timeout=10.0)
            if t.is_alive():
                log.error("camera '%s': capture thread did not stop within 10 s", self.name)
        self._thread = None
        self.source.unwatch()
        if self.state is not CameraState.STOPPED:
            self._set_state(CameraState.STOPPED)

    def wait_ended(self, timeout: Optional[float] = None) -> bool:
        """For recordings: wait until the whole file has been delivered."""
        return self.ended.wait(timeout)

    # ---- capture thread ------------------------------------------------------------------------

    def _run(self) -> None:
        cpu0 = time.thread_time()
        cfg = self.config
        backoff = self.BACKOFF_START
        opened_before = False
        not_before = 0.0
        consecutive = 0
        try:
            while not self._stop.is_set():
                self.cpu_time = time.thread_time() - cpu0
                if self._session is None:
                    wait = not_before - time.monotonic()
                    if wait > 0:
                        self._wake.wait(wait)
                        self._wake.clear()
                        continue
                    if not self._open_or_fail():
                        self._wake.wait(backoff)
                        self._wake.clear()
                        backoff = min(backoff * 2.0, max(cfg.reconnect_backoff_max, self.BACKOFF_START))
                        continue
                    if opened_before:
                        self.stats["reconnects"] += 1
                        log.info("camera '%s': reconnected to %s", self.name, self.source.description)
                    opened_before = True
                    backoff = self.BACKOFF_START
                    consecutive = 0
                fs = self._wait_frames()
                if fs is None:
                    consecutive += 1
                    not_before = self._on_timeout(consecutive)
                    if self.ended.is_set():
                        break
                    if self._session is None:
                        consecutive = 0
                    continue
                consecutive = 0
                frame = self._extract(fs, time.monotonic())
                fs = None  # no librealsense frame may outlive this iteration (frame pool)
                if frame is not None:
                    self._session.got_frame = True
                    self._deliver(frame)
        except Exception as e:  # a bug must not kill the thread silently
            self.stats["errors"] += 1
            self.last_error = f"capture thread crashed: {e!r}"
            log.exception("camera '%s': capture thread crashed", self.name)
            self._set_state(CameraState.GONE)
        finally:
            self._close()
            self.cpu_time = time.thread_time() - cpu0

    def _open_or_fail(self) -> bool:
        if not self.source.is_present():
            self._set_state(CameraState.GONE)
            self._note(f"{self.source.description} is not present")
            return False
        try:
            self._session = self._open()
        except (RuntimeError, DriverError) as e:
            self.stats["errors"] += 1
            self._set_state(CameraState.GONE)
            self._note(f"cannot open {self.source.description}: {e}")
            return False
        self._last_fn = None
        self._imu_last_fn.clear()
        self.clock.reset()
        self.last_error = None
        self._logged.clear()
        return True

    def _note(self, msg: str) -> None:
        """Record a fault; log each distinct one once per outage, not once per retry."""
        self.last_error = msg
        if msg not in self._logged:
            self._logged.add(msg)
            log.warning("camera '%s': %s", self.name, msg)

    def _wait_frames(self):
        s = self._session
        timeout = self.config.frame_timeout_ms if s.got_frame else max(self.config.frame_timeout_ms,
                                                                       self.FIRST_FRAME_TIMEOUT_MS)
        try:
            ok, fs = s.pipe.try_wait_for_frames(timeout)
        except RuntimeError as e:  # device lost mid-wait on some backends
            self.stats["errors"] += 1
            self._note(f"wait for frames failed: {e}")
            return None
        if not ok:
            return None
        if not self.source.is_playback or getattr(self.source, "real_time", False):
            # A live camera keeps producing: hand on the newest frame, count the rest as drops.
            while True:
                newer = s.pipe.poll_for_frames()
                if not newer:
                    break
                fs = newer
        return fs

    def _on_timeout(self, consecutive: int) -> float:
        """Handle a frame timeout; return the earliest host time to reopen at (0 = now)."""
        s = self._session
        self.stats["timeouts"] += 1
        if self.source.is_playback and self.source.finished(s.device):
            self._close()
            self.ended.set()
            self._set_state(CameraState.STOPPED)
            return 0.0
        if not self.source.is_present():
            self._note(f"{self.source.description} was removed")
            self._close()
            self._set_state(CameraState.GONE)
            return 0.0
        self._set_state(CameraState.STALLED)
        self._note(f"no frame for {consecutive * self.config.frame_timeout_ms} ms")
        if consecutive < self.config.stalls_before_reset:
            return 0.0
        device = s.device
        self._close()
        if self.source.can_reset():
            log.warning("camera '%s': stuck for %d timeouts, hardware reset", self.name, consecutive)
            self._set_state(CameraState.GONE)  # a reset drops the camera off the bus for seconds
            try:
                self.source.reset(device)
                self.stats["resets"] += 1
            except RuntimeError as e:
                self.stats["errors"] += 1
                self._note(f"hardware reset failed: {e}")
            settle = self.source.reset_settle
            return time.monotonic() + (self.config.reset_settle if settle is None else settle)
        log.warning("camera '%s': stuck for %d timeouts, restarting the stream", self.name, consecutive)
        self._set_state(CameraState.STARTING)
        return 0.0

    def _extract(self, fs, arrival: float) -> Optional[DepthFrame]:
        """Copy everything needed out of a frameset; librealsense's buffers die with this call."""
        d = fs.get_depth_frame()
        if not d:
            return None
        fn = int(d.get_frame_number())
        t_dev = d.get_timestamp() / 1000.0
        if self._repeats(fn, t_dev):
            self.stats["duplicates"] += 1
            return None
        f = d
        for _name, flt in self._filters:
            f = flt.process(f)
        depth_frame = f.as_depth_frame()
        dom = domain_name(self._rs, d.get_frame_timestamp_domain())
        scale = float(depth_frame.get_units())
        intr = depth_frame.get_profile().as_video_stream_profile().get_intrinsics()
        depth = np.array(depth_frame.get_data(), dtype=np.uint16, copy=True)
        del f, d, depth_frame
        if self._last_fn is not None:
            gap = fn - self._last_fn - 1
            if gap > 0:
                self.stats["drops"] += gap
        self._last_fn, self._last_t_dev = fn, t_dev
        return DepthFrame(camera=self.name, depth=depth, depth_scale=scale, K=intrinsics_to_K(intr),
                          t_capture=self.clock.map("depth", t_dev, arrival, dom), frame_number=fn,
                          timestamp_domain=dom)

    def _repeats(self, fn: int, t_dev: float) -> bool:
        """A frame already delivered in this session (or an older one) handed over again."""
        if self._last_fn is None:
            return False
        restarted = t_dev < self._last_t_dev - ClockMapper.JUMP_BACK  # the device's clock started again
        return fn <= self._last_fn and t_dev <= self._last_t_dev and not restarted

    def _deliver(self, frame: DepthFrame) -> None:
        self.stats["frames"] += 1
        self._set_state(CameraState.STREAMING)
        if self._on_frame is None:
            return
        try:
            self._on_frame(frame)
        except Exception as e:  # the consumer's bug must not stop the camera
            self.stats["errors"] += 1
            if "on_frame" not in self._logged:
                self._logged.add("on_frame")
                log.exception("camera '%s': on_frame raised %r", self.name, e)

    # ---- IMU (librealsense's thread) --------------------------------------------------------------

    def _on_motion(self, f) -> None:
        try:
            arrival = time.monotonic()
            rs = self._rs
            st = f.get_profile().stream_type()
            kind = "gyro" if st == rs.stream.gyro else "accel"
            v = f.as_motion_frame().get_motion_data()
            xyz = (float(v.x), float(v.y), float(v.z))
            fn = int(f.get_frame_number())
            t = self.clock.map(kind, f.get_timestamp() / 1000.0, arrival,
                               domain_name(rs, f.get_frame_timestamp_domain()))
            del f, v
            last = self._imu_last_fn.get(kind)
            if last is not None and fn > last + 1:
                self.stats["imu_drops"] += fn - last - 1
            self._imu_last_fn[kind] = fn
            self.stats["imu"] += 1
            sample = ImuSample(t=t, gyro=xyz) if kind == "gyro" else ImuSample(t=t, accel=xyz)
            if self._on_imu is not None:
                self._on_imu(sample)
        except Exception as e:  # never let an exception cross into librealsense's thread
            self.stats["imu_errors"] += 1
            if "imu" not in self._logged:
                self._logged.add("imu")
                log.warning("camera '%s': IMU sample failed: %r", self.name, e)

    # ---- open / close -------------------------------------------------------------------------

    def _open(self) -> _Session:
        rs = self._rs
        cam = self.camera
        pipe = self.source.make_pipeline(rs)
        rcfg = rs.config()
        self.source.configure(rs, rcfg)
        rcfg.enable_stream(rs.stream.depth, cam.width, cam.height, rs.format.z16, int(round(cam.fps)))
        try:
            resolved = rcfg.resolve(pipe)
        except RuntimeError as e:
            raise DriverError(f"depth {cam.width}x{cam.height} z16 at {cam.fps:g} fps is not available "
                              f"({e})") from None
        device = resolved.get_device()
        playback = device.as_playback() if device.is_playback() else None
        if playback is not None:
            # Before start, or the first frames can be lost; paused until every sensor is started,
            # or the first samples of the later ones are.
            playback.set_real_time(bool(getattr(self.source, "real_time", False)))
            playback.pause()
        else:
            self._apply_options(device)
        motion = None
        try:
            if self.config.imu_enabled and self._on_imu is not None:
                motion = self._start_imu(device)
            profile = pipe.start(rcfg)
        except RuntimeError:
            _stop_sensor(motion)
            raise
        if playback is not None:
            playback.resume()
        stream = profile.get_stream(rs.stream.depth).as_video_stream_profile()
        if self.config.imu_enabled:
            self._read_imu_extrinsics(device, stream)
        K = intrinsics_to_K(stream.get_intrinsics())
        scale = float(device.first_depth_sensor().get_depth_scale())
        info = describe_device_info(rs, device)
        self.intrinsics, self.depth_scale, self.device_info = K, scale, info
        log.info("camera '%s': streaming from %s (%s), depth %dx%d at %g fps, fx=%.1f fy=%.1f, scale %g m",
                 self.name, self.source.description, info.get("name", "?"), cam.width, cam.height, cam.fps,
                 K[0, 0], K[1, 1], scale)
        return _Session(pipe, device, motion)

    def _apply_options(self, device) -> None:
        rs = self._rs
        cfg = self.config
        sensor = device.first_depth_sensor()

        def set_opt(opt, value, what):
            try:
                if not sensor.supports(opt):
                    return
                r = sensor.get_option_range(opt)
                sensor.set_option(opt, float(min(max(value, r.min), r.max)))
            except RuntimeError as e:
                self._note(f"cannot set {what}: {e}")

        if cfg.visual_preset != "custom":
            set_opt(rs.option.visual_preset, float(getattr(rs.rs400_visual_preset, cfg.visual_preset)),
                    "visual preset")
        set_opt(rs.option.emitter_enabled, 1.0 if cfg.emitter_enabled else 0.0, "emitter")
        if cfg.emitter_enabled:
            set_opt(rs.option.laser_power, cfg.laser_power, "laser power")

    def _start_imu(self, device):
        rs = self._rs
        sensor = None
        for s in device.query_sensors():
            if s.is_motion_sensor():
                sensor = s
                break
        if sensor is None:
            self._note("IMU enabled but the device has no motion sensor (a D435 without 'i'?)")
            return None
        chosen = []
        for st, want in ((rs.stream.gyro, self.config.gyro_fps), (rs.stream.accel, self.config.accel_fps)):
            cands = [p for p in sensor.get_stream_profiles() if p.stream_type() == st]
            if cands:
                chosen.append(min(cands, key=lambda p: abs(p.fps() - want)))
        if not chosen:
            self._note("IMU enabled but the motion sensor has no gyro or accel stream")
            return None
        sensor.open(chosen)
        sensor.start(self._on_motion)
        return sensor

    def _read_imu_extrinsics(self, device, depth_stream) -> None:
        """``T_camera_imu`` from the device's gyro -> depth extrinsics, else the D435i default."""
        rs = self._rs
        for sensor in device.query_sensors():
            for p in sensor.get_stream_profiles():
                if p.stream_type() != rs.stream.gyro:
                    continue
                try:
                    ext = p.get_extrinsics_to(depth_stream)
                    T = T_from_rs_extrinsics(ext.rotation, ext.translation)
                except (RuntimeError, ValueError) as e:  # recordings from a software_device carry none
                    log.info("camera '%s': no gyro extrinsics from the device (%s): D435i default used",
                             self.name, e)
                    return
                self.T_camera_imu, self.imu_extrinsics_source = T, "device"
                return

    def _close(self) -> None:
        s = self._session
        self._session = None
        if s is None:
            return
        _stop_sensor(s.motion_sensor)
        self.source.before_stop(s.device)
        try:
            s.pipe.stop()
        except RuntimeError as e:  # already stopped, or the device vanished under it
            log.debug("camera '%s': pipeline stop: %s", self.name, e)


def _stop_sensor(sensor) -> None:
    if sensor is None:
        return
    for call in (sensor.stop, sensor.close):
        try:
            call()
        except RuntimeError:
            pass


def make_filters(rs, cfg: RealSenseConfig) -> List[Tuple[str, Any]]:
    """librealsense post-processing in Intel's recommended order; empty by default.

    Spatial and temporal filtering run on disparity, as Intel recommends, so the chain converts
    depth to disparity and back around them.
    """
    chain: List[Tuple[str, Any]] = []
    if cfg.decimation > 1:
        dec = rs.decimation_filter()
        dec.set_option(rs.option.filter_magnitude, float(cfg.decimation))
        chain.append(("decimation", dec))
    if cfg.spatial_filter or cfg.temporal_filter:
        chain.append(("to_disparity", rs.disparity_transform(True)))
        if cfg.spatial_filter:
            chain.append(("spatial", rs.spatial_filter()))
        if cfg.temporal_filter:
            chain.append(("temporal", rs.temporal_filter()))
        chain.append(("to_depth", rs.disparity_transform(False)))
    return chain


def describe_device_info(rs, device) -> Dict[str, str]:
    """name, serial, firmware, recommended firmware, USB type, product id (what the device has)."""
    keys = {
        "name": "name",
        "serial": "serial_number",
        "firmware": "firmware_version",
        "recommended_firmware": "recommended_firmware_version",
        "usb_type": "usb_type_descriptor",
        "product_id": "product_id",
        "product_line": "product_line",
    }
    out: Dict[str, str] = {}
    for key, attr in keys.items():
        info = getattr(rs.camera_info, attr, None)
        try:
            if info is not None and device.supports(info):
                out[key] = device.get_info(info)
        except RuntimeError:
            continue
    return out
