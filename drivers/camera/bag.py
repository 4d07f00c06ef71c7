"""librealsense recordings (``.bag``): played back as a camera, written from simulation, read back.

``BagCamera`` is the recording behind the ``CameraDriver`` interface: the RealSense driver
itself, reading the file through ``rs.pipeline`` exactly as it streams a camera.

The writer builds an ``rs.software_device`` that looks like a D435i (a "Stereo Module" with a
z16 depth stream carrying the frames' intrinsics and depth units, and, with IMU samples, a
"Motion Module" with gyro and accel streams), records it with ``rs.recorder`` and pushes the
frames through it. The result is an ordinary librealsense recording: the real driver plays it
back through ``rs.pipeline`` exactly as it streams a camera, and Intel's RealSense Viewer opens it.

File format: pyrealsense2 2.55 (the robot's version) writes ROS1 ``.bag``. From 2.58 on the
recorder writes rosbag2 ``.db3`` only, which 2.55 cannot read, so recordings are made with the
robot's version.

The reader uses librealsense's lossless recipe (load the device, non-real-time, pause, start a
callback on every sensor, resume, wait for the end): it returns every depth frame and motion
sample with the recorded timestamps, independently of the driver.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, List, Optional, Sequence, Tuple

import numpy as np

from drivers.camera.realsense import PlaybackFile, RealSenseCamera, domain_name, intrinsics_to_K, load_pyrealsense2
from robot.base.errors import DriverError, InputError
from robot.base.samples import DepthFrame, ImuSample
from robot.config import CameraConfig

DEVICE_NAME = "Intel RealSense D435I"  # what the Viewer and ``robotctl cameras`` show
DEPTH_SENSOR_NAME = "Stereo Module"  # the real D435i's sensor names
MOTION_SENSOR_NAME = "Motion Module"
IMU_FPS = 200
STEREO_BASELINE_MM = 50.0  # D435i; lets librealsense's disparity transform work on the recording


class BagCamera(RealSenseCamera):
    """A ``.bag`` recording of one camera, played back as that camera (``camera`` is its config:
    the stream's size and rate must match the recording's).

    Non-real-time by default: every frame is delivered, at the consumer's pace, and ``wait_ended``
    tells when the whole file has been. ``real_time`` plays a recording written at its own pace
    like a live camera (frames dropped when the consumer is slow); ``repeat`` loops it.
    """

    def __init__(self, camera: CameraConfig, path, repeat: bool = False, real_time: bool = False):
        p = Path(path)
        if p.suffix != ".bag":
            raise InputError(f"camera '{camera.name}': {p}: a recording to play back must be a librealsense .bag")
        if not p.is_file():
            raise InputError(f"camera '{camera.name}': recording {p} not found")
        super().__init__(camera, PlaybackFile(p, repeat=repeat, real_time=real_time))
        self.path = str(p)


@dataclass
class Recording:
    """What a recording holds, with timestamps as recorded (device clock, seconds)."""

    path: str
    frames: List[DepthFrame] = field(default_factory=list)
    imu: List[ImuSample] = field(default_factory=list)
    name: str = ""
    serial: str = ""
    fps: int = 0
    width: int = 0
    height: int = 0
    K: Optional[np.ndarray] = None
    depth_scale: float = 0.0


def _check_frames(frames: Sequence[DepthFrame]) -> Tuple[int, int, np.ndarray, float]:
    if not frames:
        raise InputError("a recording needs at least one depth frame")
    f0 = frames[0]
    h, w = f0.depth.shape
    for i, f in enumerate(frames):
        if f.depth.dtype != np.uint16 or f.depth.ndim != 2:
            raise InputError(f"frame {i}: depth must be a 2-D uint16 array, got {f.depth.dtype} {f.depth.shape}")
        if f.depth.shape != (h, w):
            raise InputError(f"frame {i}: size {f.depth.shape[1]}x{f.depth.shape[0]} differs from the first "
                             f"frame's {w}x{h}: one recording holds one stream")
        if not np.allclose(f.K, f0.K) or f.depth_scale != f0.depth_scale:
            raise InputError(f"frame {i}: intrinsics or depth scale differ from the first frame's")
    K = np.asarray(f0.K, float)
    if K.shape != (3, 3) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(f"frame 0: K is not a pinhole intrinsic matrix: {K.tolist()}")
    if not (np.isfinite(f0.depth_scale) and f0.depth_scale > 0):
        raise InputError(f"frame 0: depth_scale must be positive, got {f0.depth_scale}")
    return w, h, K, float(f0.depth_scale)


def _timestamps_ms(frames: Sequence[DepthFrame], imu: Sequence[ImuSample], fps: float):
    """Device timestamps (ms from the first sample) for frames and IMU samples.

    Frames keep their own capture times when those increase; otherwise (frames rendered without
    a time) they are spaced at 1/fps.
    """
    t = np.array([f.t_capture for f in frames], float)
    if len(t) > 1 and np.all(np.isfinite(t)) and np.all(np.diff(t) > 0):
        t_frames = t
    else:
        t_frames = np.arange(len(frames)) / float(fps)
        if imu:
            raise InputError("IMU samples need frames with increasing t_capture on the same clock")
    t_imu = np.array([s.t for s in imu], float)
    if len(t_imu) and not np.all(np.isfinite(t_imu)):
        raise InputError("IMU sample times must be finite")
    t0 = min(t_frames.min(), t_imu.min()) if len(t_imu) else t_frames.min()
    return (t_frames - t0) * 1000.0, (t_imu - t0) * 1000.0


def write_recording(path, frames: Sequence[DepthFrame], imu: Sequence[ImuSample] = (), fps: Optional[float] = None,
                    serial: str = "000000000000", name: str = DEVICE_NAME, compress: bool = True,
                    real_time: bool = False) -> Recording:
    """Record ``frames`` (one camera) and optional IMU samples into a librealsense ``.bag``.

    ``fps`` defaults to the frames' median rate (30 if they have no times). Returns what was
    written (timestamps in the recording's clock).

    librealsense stamps each message in the file with the wall-clock time it was recorded, and
    real-time playback paces itself by those stamps, not by the frames' own timestamps. With
    ``real_time`` the frames are pushed at their own pace (the recording takes as long as the run),
    so the file also plays back in real time like a camera streams; otherwise it is written as
    fast as possible and must be played non-real-time (what the driver does with recordings).
    """
    rs = load_pyrealsense2()
    p = _bag_path(path)
    stream = _stream_of(frames, fps)
    ts_frames, ts_imu = _timestamps_ms(frames, imu, stream.fps)
    numbers = _frame_numbers(frames)
    p.parent.mkdir(parents=True, exist_ok=True)
    device = _SoftwareD435i(rs, stream, name, serial, with_imu=bool(imu))
    recorder = _open_recorder(rs, p, device, compress)
    device.start()
    try:
        for ts, kind, i in _events(ts_frames, ts_imu, real_time):
            if kind == _DEPTH:
                device.push_depth(frames[i], ts, numbers[i])
            else:
                device.push_imu(imu[i], ts)
    finally:
        device.stop()
        recorder.pause()
        del recorder  # the file is complete only once the recorder is destroyed
    return _as_written(p, frames, stream, ts_frames, numbers, name, serial)


@dataclass(frozen=True)
class _Stream:
    """The one depth stream a recording holds."""

    width: int
    height: int
    K: np.ndarray
    depth_scale: float
    fps: int


_DEPTH, _IMU = 0, 1


def _bag_path(path) -> Path:
    p = Path(path)
    if p.suffix != ".bag":
        raise InputError(f"{p}: a librealsense 2.55 recording must end in .bag")
    return p


def _stream_of(frames: Sequence[DepthFrame], fps: Optional[float]) -> _Stream:
    """The frames' common geometry, and the rate: ``fps``, else their median rate, else 30."""
    w, h, K, depth_scale = _check_frames(frames)
    if fps is None:
        dt = np.diff(np.array([f.t_capture for f in frames], float))
        fps = 1.0 / float(np.median(dt)) if len(dt) and np.all(dt > 0) else 30.0
    return _Stream(w, h, K, depth_scale, max(1, int(round(fps))))


def _frame_numbers(frames: Sequence[DepthFrame]) -> List[int]:
    """The frames' own numbers when they increase, else 0, 1, 2, ..."""
    fns = [int(f.frame_number) for f in frames]
    return fns if all(b > a for a, b in zip(fns, fns[1:])) else list(range(len(frames)))


def _events(ts_frames: np.ndarray, ts_imu: np.ndarray, real_time: bool) -> Iterator[Tuple[float, int, int]]:
    """(timestamp ms, kind, index) of every frame and IMU sample in time order; with ``real_time``
    each is held back until its own time has come on the wall clock."""
    events = sorted([(float(ts), _DEPTH, i) for i, ts in enumerate(ts_frames)]
                    + [(float(ts), _IMU, i) for i, ts in enumerate(ts_imu)])
    wall0 = time.monotonic()
    for event in events:
        if real_time:
            ahead = wall0 + event[0] / 1000.0 - time.monotonic()
            if ahead > 0:
                time.sleep(ahead)
        yield event


class _SoftwareD435i:
    """An ``rs.software_device`` that looks like a D435i: a "Stereo Module" with one z16 depth
    stream carrying the intrinsics and depth units and, with IMU, a "Motion Module" with gyro
    and accel streams. Frames pushed into its sensors are what a recorder attached to it writes."""

    def __init__(self, rs, stream: _Stream, name: str, serial: str, with_imu: bool):
        self.rs = rs
        self.stream = stream
        self.dev = dev = rs.software_device()
        dev.register_info(rs.camera_info.name, name)
        dev.register_info(rs.camera_info.serial_number, str(serial))
        dev.register_info(rs.camera_info.firmware_version, "simulated")
        dev.register_info(rs.camera_info.product_line, "D400")
        self.depth_sensor = dev.add_sensor(DEPTH_SENSOR_NAME)
        self.depth_profile = self._add_depth_stream()
        self.depth_sensor.add_read_only_option(rs.option.depth_units, stream.depth_scale)
        self.depth_sensor.add_read_only_option(rs.option.stereo_baseline, STEREO_BASELINE_MM)
        self.motion_sensor = dev.add_sensor(MOTION_SENSOR_NAME) if with_imu else None
        self.motion_profiles = self._add_motion_streams() if with_imu else {}
        self._imu_counters = {"gyro": 0, "accel": 0}
        self._sink = None

    def _add_depth_stream(self):
        rs, s = self.rs, self.stream
        intr = rs.intrinsics()
        intr.width, intr.height = s.width, s.height
        intr.fx, intr.fy, intr.ppx, intr.ppy = float(s.K[0, 0]), float(s.K[1, 1]), float(s.K[0, 2]), float(s.K[1, 2])
        intr.model = rs.distortion.brown_conrady
        intr.coeffs = [0.0] * 5
        vs = rs.video_stream()
        vs.type, vs.index, vs.uid = rs.stream.depth, 0, 0
        vs.width, vs.height, vs.fps, vs.bpp, vs.fmt = s.width, s.height, s.fps, 2, rs.format.z16
        vs.intrinsics = intr
        return self.depth_sensor.add_video_stream(vs, True).as_video_stream_profile()

    def _add_motion_streams(self):
        rs = self.rs
        profiles = {}
        for uid, (key, kind) in enumerate((("gyro", rs.stream.gyro), ("accel", rs.stream.accel)), start=1):
            ms = rs.motion_stream()
            ms.type, ms.index, ms.uid, ms.fps, ms.fmt = kind, 0, uid, IMU_FPS, rs.format.motion_xyz32f
            ms.intrinsics = rs.motion_device_intrinsic()
            profiles[key] = self.motion_sensor.add_motion_stream(ms, True).as_motion_stream_profile()
        return profiles

    def start(self) -> None:
        self._sink = self.rs.frame_queue(1)  # the recorder taps the sensors; the frames themselves go nowhere
        self.depth_sensor.open(self.depth_profile)
        self.depth_sensor.start(self._sink)
        if self.motion_sensor is not None:
            self.motion_sensor.open(list(self.motion_profiles.values()))
            self.motion_sensor.start(self._sink)

    def push_depth(self, frame: DepthFrame, ts_ms: float, number: int) -> None:
        rs = self.rs
        sw = rs.software_video_frame()
        sw.pixels = np.ascontiguousarray(frame.depth)
        sw.bpp, sw.stride = 2, 2 * self.stream.width
        sw.timestamp = ts_ms
        sw.domain = rs.timestamp_domain.hardware_clock
        sw.frame_number = int(number)
        sw.profile = self.depth_profile
        sw.depth_units = self.stream.depth_scale
        self.depth_sensor.on_video_frame(sw)

    def push_imu(self, sample: ImuSample, ts_ms: float) -> None:
        rs = self.rs
        for key, vec in (("gyro", sample.gyro), ("accel", sample.accel)):
            if vec is None:
                continue
            v = rs.vector()
            v.x, v.y, v.z = (float(c) for c in vec)
            mf = rs.software_motion_frame()
            mf.data = v
            mf.timestamp = ts_ms
            mf.domain = rs.timestamp_domain.hardware_clock
            mf.frame_number = self._imu_counters[key]
            mf.profile = self.motion_profiles[key]
            self.motion_sensor.on_motion_frame(mf)
            self._imu_counters[key] += 1

    def stop(self) -> None:
        for sensor in (self.depth_sensor, self.motion_sensor):
            if sensor is not None:
                sensor.stop()
                sensor.close()


def _open_recorder(rs, p: Path, device: _SoftwareD435i, compress: bool):
    try:
        return rs.recorder(str(p), device.dev, compress)
    except RuntimeError as e:
        raise DriverError(f"{p}: cannot record with pyrealsense2 {_version()}: {e} "
                          f"(the robot's 2.55 writes .bag; 2.58+ writes only .db3)") from None


def _as_written(p: Path, frames: Sequence[DepthFrame], stream: _Stream, ts_frames: np.ndarray, numbers: List[int],
                name: str, serial: str) -> Recording:
    rec = Recording(path=str(p), name=name, serial=str(serial), fps=stream.fps, width=stream.width,
                    height=stream.height, K=stream.K, depth_scale=stream.depth_scale)
    rec.frames = [DepthFrame(camera=f.camera, depth=f.depth, depth_scale=stream.depth_scale, K=stream.K,
                             t_capture=ts / 1000.0, frame_number=int(fn), timestamp_domain="hardware_clock",
                             truth=f.truth)
                  for f, ts, fn in zip(frames, ts_frames, numbers)]
    return rec


def _version() -> str:
    from drivers.camera.realsense import pyrealsense2_version

    return pyrealsense2_version()


def read_recording(path, camera: str = "recording", timeout: float = 60.0) -> Recording:
    """Every depth frame and IMU sample of a recording, with its recorded timestamps (seconds)."""
    rs = load_pyrealsense2()
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: recording not found")
    ctx = rs.context()
    try:
        dev = ctx.load_device(str(p))
    except RuntimeError as e:
        raise InputError(f"{p}: not a readable librealsense recording ({e})") from None
    pb = dev.as_playback()
    pb.set_real_time(False)
    rec = Recording(path=str(p))
    for key, attr in (("name", "name"), ("serial", "serial_number")):
        info = getattr(rs.camera_info, attr)
        if dev.supports(info):
            setattr(rec, key, dev.get_info(info))
    lock = threading.Lock()
    errors: List[str] = []

    def on_frame(f):
        try:
            ts = f.get_timestamp() / 1000.0
            dom = domain_name(rs, f.get_frame_timestamp_domain())
            fn = int(f.get_frame_number())
            if f.is_depth_frame():
                d = f.as_depth_frame()
                vp = d.get_profile().as_video_stream_profile()
                frame = DepthFrame(camera=camera, depth=np.array(d.get_data(), dtype=np.uint16, copy=True),
                                   depth_scale=float(d.get_units()), K=intrinsics_to_K(vp.get_intrinsics()),
                                   t_capture=ts, frame_number=fn, timestamp_domain=dom)
                with lock:
                    rec.frames.append(frame)
            elif f.is_motion_frame():
                v = f.as_motion_frame().get_motion_data()
                xyz = (float(v.x), float(v.y), float(v.z))
                st = f.get_profile().stream_type()
                s = ImuSample(t=ts, gyro=xyz) if st == rs.stream.gyro else ImuSample(t=ts, accel=xyz)
                with lock:
                    rec.imu.append(s)
        except Exception as e:  # never raise into librealsense's thread
            errors.append(repr(e))

    pb.pause()
    sensors = list(dev.query_sensors())
    for s in sensors:
        s.open(list(s.get_stream_profiles()))
        s.start(on_frame)
    pb.resume()
    # Polled, not a status callback: resume() holds the GIL while librealsense calls back from its
    # reader thread, and a Python status callback then deadlocks (measured with 2.55.1).
    deadline = time.monotonic() + timeout
    finished = False
    while time.monotonic() < deadline:
        if pb.current_status() == rs.playback_status.stopped:
            finished = True
            break
        time.sleep(0.01)
    for s in sensors:
        try:
            s.stop()
            s.close()
        except RuntimeError:
            pass
    try:
        ctx.unload_device(str(p))
    except RuntimeError:
        pass
    if errors:
        raise InputError(f"{p}: could not decode a frame: {errors[0]}")
    if not finished:
        raise InputError(f"{p}: playback did not finish within {timeout:g} s")
    rec.frames.sort(key=lambda f: f.frame_number)
    rec.imu.sort(key=lambda s: s.t)
    if rec.frames:
        f0 = rec.frames[0]
        rec.height, rec.width = f0.depth.shape
        rec.K, rec.depth_scale = f0.K, f0.depth_scale
        dt = np.diff([f.t_capture for f in rec.frames])
        rec.fps = int(round(1.0 / float(np.median(dt)))) if len(dt) and np.median(dt) > 0 else 0
    return rec
