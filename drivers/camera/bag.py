"""librealsense recordings (``.bag``) written from simulation, and read back.

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
from typing import List, Optional, Sequence, Tuple

import numpy as np

from drivers.camera.realsense import domain_name, intrinsics_to_K, load_pyrealsense2
from robot.base.errors import DriverError, InputError
from robot.base.samples import DepthFrame, ImuSample

DEVICE_NAME = "Intel RealSense D435I"  # what the Viewer and ``robotctl cameras`` show
DEPTH_SENSOR_NAME = "Stereo Module"  # the real D435i's sensor names
MOTION_SENSOR_NAME = "Motion Module"
IMU_FPS = 200
STEREO_BASELINE_MM = 50.0  # D435i; lets librealsense's disparity transform work on the recording


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
    p = Path(path)
    if p.suffix != ".bag":
        raise InputError(f"{p}: a librealsense 2.55 recording must end in .bag")
    w, h, K, depth_scale = _check_frames(frames)
    if fps is None:
        t = np.array([f.t_capture for f in frames], float)
        dt = np.diff(t)
        fps = 1.0 / float(np.median(dt)) if len(dt) and np.all(dt > 0) else 30.0
    fps_int = max(1, int(round(fps)))
    ts_frames, ts_imu = _timestamps_ms(frames, imu, fps_int)
    fns = [f.frame_number for f in frames]
    if not all(b > a for a, b in zip(fns, fns[1:])):
        fns = list(range(len(frames)))
    p.parent.mkdir(parents=True, exist_ok=True)

    dev = rs.software_device()
    dev.register_info(rs.camera_info.name, name)
    dev.register_info(rs.camera_info.serial_number, str(serial))
    dev.register_info(rs.camera_info.firmware_version, "simulated")
    dev.register_info(rs.camera_info.product_line, "D400")
    depth_sensor = dev.add_sensor(DEPTH_SENSOR_NAME)
    intr = rs.intrinsics()
    intr.width, intr.height = w, h
    intr.fx, intr.fy, intr.ppx, intr.ppy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    intr.model = rs.distortion.brown_conrady
    intr.coeffs = [0.0] * 5
    vs = rs.video_stream()
    vs.type, vs.index, vs.uid = rs.stream.depth, 0, 0
    vs.width, vs.height, vs.fps, vs.bpp, vs.fmt = w, h, fps_int, 2, rs.format.z16
    vs.intrinsics = intr
    depth_profile = depth_sensor.add_video_stream(vs, True).as_video_stream_profile()
    depth_sensor.add_read_only_option(rs.option.depth_units, depth_scale)
    depth_sensor.add_read_only_option(rs.option.stereo_baseline, STEREO_BASELINE_MM)

    motion_sensor = None
    motion_profiles = {}
    if imu:
        motion_sensor = dev.add_sensor(MOTION_SENSOR_NAME)
        for uid, (key, stream) in enumerate((("gyro", rs.stream.gyro), ("accel", rs.stream.accel)), start=1):
            ms = rs.motion_stream()
            ms.type, ms.index, ms.uid, ms.fps, ms.fmt = stream, 0, uid, IMU_FPS, rs.format.motion_xyz32f
            ms.intrinsics = rs.motion_device_intrinsic()
            motion_profiles[key] = motion_sensor.add_motion_stream(ms, True).as_motion_stream_profile()

    try:
        recorder = rs.recorder(str(p), dev, compress)
    except RuntimeError as e:
        raise DriverError(f"{p}: cannot record with pyrealsense2 {_version()}: {e} "
                          f"(the robot's 2.55 writes .bag; 2.58+ writes only .db3)") from None
    sink = rs.frame_queue(1)  # the recorder taps the sensors; the frames themselves go nowhere
    depth_sensor.open(depth_profile)
    depth_sensor.start(sink)
    if motion_sensor is not None:
        motion_sensor.open(list(motion_profiles.values()))
        motion_sensor.start(sink)

    events = [(float(ts), 0, i) for i, ts in enumerate(ts_frames)]
    events += [(float(ts), 1, i) for i, ts in enumerate(ts_imu)]
    events.sort()
    imu_counters = {"gyro": 0, "accel": 0}
    wall0 = time.monotonic()
    try:
        for ts, kind, i in events:
            if real_time:
                ahead = wall0 + ts / 1000.0 - time.monotonic()
                if ahead > 0:
                    time.sleep(ahead)
            if kind == 0:
                f = frames[i]
                sw = rs.software_video_frame()
                sw.pixels = np.ascontiguousarray(f.depth)
                sw.bpp, sw.stride = 2, 2 * w
                sw.timestamp = ts
                sw.domain = rs.timestamp_domain.hardware_clock
                sw.frame_number = int(fns[i])
                sw.profile = depth_profile
                sw.depth_units = depth_scale
                depth_sensor.on_video_frame(sw)
                continue
            s = imu[i]
            for key, vec in (("gyro", s.gyro), ("accel", s.accel)):
                if vec is None:
                    continue
                v = rs.vector()
                v.x, v.y, v.z = (float(c) for c in vec)
                mf = rs.software_motion_frame()
                mf.data = v
                mf.timestamp = ts
                mf.domain = rs.timestamp_domain.hardware_clock
                mf.frame_number = imu_counters[key]
                mf.profile = motion_profiles[key]
                motion_sensor.on_motion_frame(mf)
                imu_counters[key] += 1
    finally:
        for sensor in (depth_sensor, motion_sensor):
            if sensor is None:
                continue
            sensor.stop()
            sensor.close()
        recorder.pause()
        del recorder  # the file is complete only once the recorder is destroyed
    rec = Recording(path=str(p), name=name, serial=str(serial), fps=fps_int, width=w, height=h, K=K,
                    depth_scale=depth_scale)
    rec.frames = [DepthFrame(camera=f.camera, depth=f.depth, depth_scale=depth_scale, K=K, t_capture=ts / 1000.0,
                             frame_number=int(fn), timestamp_domain="hardware_clock", truth=f.truth)
                  for f, ts, fn in zip(frames, ts_frames, fns)]
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
