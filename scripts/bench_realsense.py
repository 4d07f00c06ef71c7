"""Real-camera driver figures for BENCHMARKS.md, measured through librealsense playback.

A simulated drive is rendered, recorded into librealsense ``.bag`` files (one written as fast as
possible for non-real-time playback, one written at its own pace so it plays back at 30 fps like
a camera) and played through the real driver:

- playback throughput (non-real-time) with nothing attached and with the localizer attached;
- CPU of the capture thread per camera at 30 fps (``time.thread_time`` inside the thread);
- capture-to-pose latency: frame ``t_capture`` (host monotonic) to the fused (EKF) pose after
  that frame's planes, with the localizer and the filter run by a consumer thread as the app's
  event loop would;
- the cost of each optional librealsense post-processing filter on an 848x480 frame.

Playback has no USB transfer, so the latency excludes it (a few ms for depth on USB 3) and the
capture CPU excludes the USB stack's work in librealsense's own threads.
"""

from __future__ import annotations

import dataclasses
import math
import os
import platform
import queue
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from robot.config import load_robot_config  # noqa: E402

POSE = (0.45, 0.45, 3.0 * math.pi / 4.0)  # the front camera sees two walls: single-camera fixes
VELOCITY = (0.03, -0.02, 0.05)
CAMERA = "front"


def _frames(robot, scene, n_render: int, n_total: int):
    """``n_total`` frames at 30 fps cycling through ``n_render`` rendered ones (rendering is slow)."""
    from drivers.sim.drive import simulate_run
    from robot.base.samples import DepthFrame

    rendered, _ = simulate_run(robot, scene, CAMERA, POSE, VELOCITY, frames=n_render,
                               rng=np.random.default_rng(1))
    fps = robot.camera(CAMERA).fps
    out = []
    for i in range(n_total):
        f = rendered[i % n_render]
        out.append(DepthFrame(f.camera, f.depth, f.depth_scale, f.K, t_capture=i / fps, frame_number=i,
                              truth=f.truth))
    return out


def _play(robot, path, on_frame, real_time=False, timeout=120.0):
    from drivers.camera.realsense import PlaybackFile, RealSenseCamera, RealSenseConfig

    # the robot's camera, with a shorter frame timeout: the end of a recording is noticed by one
    cam_cfg = dataclasses.replace(robot.camera(CAMERA), realsense=RealSenseConfig(frame_timeout_ms=300))
    cam = RealSenseCamera(cam_cfg, PlaybackFile(path, real_time=real_time))
    t0 = time.perf_counter()
    cam.start(on_frame)
    try:
        if not cam.wait_ended(timeout):
            raise RuntimeError(f"playback of {path} did not end in {timeout} s")
    finally:
        cam.stop()
    # The driver notices the end after one frame timeout; that wait is not playback.
    wall = time.perf_counter() - t0 - cam.config.frame_timeout_ms / 1000.0
    return cam, wall


def _pct(xs, q):
    return float(np.percentile(np.asarray(xs, float), q))


def _filter_costs(rs, path, n_frames: int):
    """Median ms per frame of each librealsense filter, on the recording's 848x480 frames."""
    from drivers.camera.realsense import RealSenseConfig, make_filters

    chain = make_filters(rs, RealSenseConfig(decimation=2, spatial_filter=True, temporal_filter=True))
    # The decimation filter is timed on its own on full frames; the disparity-domain filters on
    # full frames too (what they cost when decimation is off, their most expensive use).
    dec = chain[0][1]
    rest = chain[1:]
    times = {name: [] for name, _ in chain}
    times["all (decimation 2 + spatial + temporal)"] = []
    pipe, cfg = rs.pipeline(), rs.config()
    cfg.enable_device_from_file(str(path), repeat_playback=False)
    cfg.enable_stream(rs.stream.depth)
    cfg.resolve(pipe).get_device().as_playback().set_real_time(False)
    pipe.start(cfg)
    full_chain = make_filters(rs, RealSenseConfig(decimation=2, spatial_filter=True, temporal_filter=True))
    try:
        for _ in range(n_frames):
            ok, fs = pipe.try_wait_for_frames(1000)
            if not ok:
                break
            d = fs.get_depth_frame()
            t0 = time.perf_counter()
            dec.process(d)
            times["decimation"].append(time.perf_counter() - t0)
            f = d
            for name, flt in rest:
                t0 = time.perf_counter()
                f = flt.process(f)
                times[name].append(time.perf_counter() - t0)
            f = d
            t0 = time.perf_counter()
            for _, flt in full_chain:
                f = flt.process(f)
            times["all (decimation 2 + spatial + temporal)"].append(time.perf_counter() - t0)
            del f, d, fs
    finally:
        pipe.stop()
    return {k: 1e3 * statistics.median(v) for k, v in times.items() if v}


def run(quick: bool = False) -> str:
    title = "## Real camera driver: librealsense playback"
    try:
        from drivers.camera.realsense import load_pyrealsense2, pyrealsense2_version

        rs = load_pyrealsense2()
    except Exception as e:  # pyrealsense2 missing or libusb absent
        return f"{title}\n\n_not run: {e}_\n"
    from drivers.camera.bag import write_recording
    from drivers.sim.render import SimScene
    from robot.base.geometry import wrap_angle
    from robot.fusion.ekf import PoseFilter
    from robot.localization.localizer import FIX_STATUSES, Localizer
    from robot.maps.plane_map import load_plane_map

    robot = load_robot_config(ROOT / "config" / "robot.yaml")
    plane_map = load_plane_map(ROOT / "config" / "maps" / "paper_arena.yaml")
    scene = SimScene(plane_map)
    n_render = 10 if quick else 30
    n_fast = 60 if quick else 300
    n_rt = 60 if quick else 300  # frames of real-time playback (2 s or 10 s)
    cam_cfg = robot.camera(CAMERA)
    lines = [title, ""]
    with tempfile.TemporaryDirectory() as tmp:
        frames = _frames(robot, scene, n_render, max(n_fast, n_rt))
        truth = {f.frame_number: f.truth for f in frames}
        fast_path, rt_path = Path(tmp) / "fast.bag", Path(tmp) / "rt.bag"
        t0 = time.perf_counter()
        write_recording(fast_path, frames[:n_fast])
        t_write = time.perf_counter() - t0
        write_recording(rt_path, frames[:n_rt], real_time=True)
        size_mb = os.path.getsize(fast_path) / 1e6

        # 1. Throughput, non-real-time playback.
        count = [0]

        def count_only(f):
            count[0] += 1

        cam, wall = _play(robot, fast_path, count_only)
        fps_bare = count[0] / wall
        cpu_bare = cam.cpu_time / max(count[0], 1) * 1e3
        loc = Localizer(robot, plane_map)
        results = []

        def localize(f):
            x, y, phi = truth[f.frame_number]
            results.append(loc.localize([f], coarse=(x + 0.02, y - 0.02, phi + 0.03)))

        cam, wall_loc = _play(robot, fast_path, localize)
        fps_loc = len(results) / wall_loc
        ok = sum(r.status in FIX_STATUSES for r in results)
        err = [math.hypot(r.x - truth[i][0], r.y - truth[i][1]) for i, r in enumerate(results)]
        loc_ms = statistics.median(r.ms for r in results)

        # 2 + 3. Real time (30 fps, like a camera): capture CPU and capture-to-pose latency.
        # The consumer does what the app does with a frame: coarse pose from the EKF at the frame's
        # capture time, localize, fuse the planes, read the fused pose. Odometry is the true motion
        # between the frames it takes (the wheel odometry's job on the robot).
        q: queue.Queue = queue.Queue(maxsize=1)
        latencies, drops_consumer, fused = [], [0], [0, 0]
        stop = threading.Event()
        pf = PoseFilter(robot.fusion)
        prev = []

        def consumer():
            while not stop.is_set():
                try:
                    f = q.get(timeout=0.2)
                except queue.Empty:
                    continue
                x, y, phi = truth[f.frame_number]
                if not prev:
                    pf.set_pose(f.t_capture - 1e-3, x + 0.02, y - 0.02, phi + 0.03, np.diag([4e-4, 4e-4, 1e-3]))
                else:
                    x0, y0, phi0 = prev[-1]
                    dphi = float(wrap_angle(phi - phi0))
                    c, s = math.cos(phi0 + dphi / 2), math.sin(phi0 + dphi / 2)
                    dx, dy = x - x0, y - y0
                    pf.predict_increment(f.t_capture, c * dx + s * dy, -s * dx + c * dy, dphi, np.diag([1e-6] * 3))
                prev[:] = [(x, y, phi)]
                cx, cy, cphi, P = pf.predicted(f.t_capture)
                r = loc.localize([f], coarse=(cx, cy, cphi), coarse_cov=P)
                accepted = [u.accepted for u in pf.update_planes(r.measurements)]
                pf.state()  # the fused pose, as the app publishes it
                latencies.append(time.monotonic() - f.t_capture)
                fused[0] += sum(accepted)
                fused[1] += len(accepted)

        def hand_over(f):  # what the app does: newest frame wins, a full queue drops the oldest
            try:
                q.put_nowait(f)
            except queue.Full:
                try:
                    q.get_nowait()
                    drops_consumer[0] += 1
                except queue.Empty:
                    pass
                q.put_nowait(f)

        th = threading.Thread(target=consumer, daemon=True)
        th.start()
        cam_rt, wall_rt = _play(robot, rt_path, hand_over, real_time=True)
        stop.set()
        th.join(5)
        cpu_pct = 100.0 * cam_rt.cpu_time / wall_rt
        cpu_ms = 1e3 * cam_rt.cpu_time / max(cam_rt.stats["frames"], 1)
        # The same at 30 fps with nothing attached: the capture thread's own cost.
        cam_idle, wall_idle = _play(robot, rt_path, lambda f: None, real_time=True)
        cpu_idle_pct = 100.0 * cam_idle.cpu_time / wall_idle

        # 4. Post-processing filters.
        filt = _filter_costs(rs, fast_path, 30 if quick else 100)

    lines += [
        f"A simulated drive of the `{CAMERA}` camera ({cam_cfg.width}x{cam_cfg.height} z16, noisy depth, "
        f"{n_render} rendered frames cycled) recorded with `rs.software_device` + `rs.recorder` "
        f"({n_fast} frames written in {t_write:.2f} s, {size_mb:.1f} MB compressed) and played through "
        f"`RealSenseCamera` via `rs.pipeline`.",
        "",
        "| measurement | value |",
        "|---|---|",
        f"| playback throughput, nothing attached (non-real-time) | {fps_bare:.0f} frames/s |",
        f"| capture thread CPU per frame (copy out, timestamps) | {cpu_bare:.2f} ms |",
        f"| playback throughput, localizer attached in the capture thread | {fps_loc:.1f} frames/s "
        f"({ok}/{len(results)} ok, median position error {1e3 * statistics.median(err):.2f} mm, "
        f"localize {loc_ms:.1f} ms/frame) |",
        f"| capture thread CPU at 30 fps, one camera, nothing attached | {cpu_idle_pct:.1f} % of a core |",
        f"| capture thread CPU at 30 fps, one camera, localizer consuming | {cpu_pct:.1f} % of a core "
        f"({cpu_ms:.2f} ms/frame; frames {cam_rt.stats['frames']}, driver drops {cam_rt.stats['drops']}) |",
        f"| capture-to-fused-pose latency at 30 fps (t_capture to EKF pose after the frame's planes), median | "
        f"{1e3 * statistics.median(latencies):.1f} ms ({fused[0]}/{fused[1]} plane measurements accepted) |",
        f"| capture-to-fused-pose latency, 95th percentile / max | {1e3 * _pct(latencies, 95):.1f} / "
        f"{1e3 * max(latencies):.1f} ms ({len(latencies)} poses, {drops_consumer[0]} frames superseded "
        f"before the localizer took them) |",
        "",
        "Optional librealsense post-processing (off by default), median ms per 848x480 frame:",
        "",
        "| filter | ms/frame |",
        "|---|---|",
    ]
    for name, ms in filt.items():
        lines.append(f"| {name} | {ms:.2f} |")
    lines += [
        "",
        "Spatial and temporal filters run on disparity (`to_disparity` / `to_depth` convert), as Intel "
        "recommends; with decimation 2 first they see a quarter of the pixels. Playback has no USB "
        "transfer: on a camera, add its transport latency (a few ms on USB 3) to the latency and the "
        "USB stack's CPU (librealsense's threads) to the capture cost.",
        "",
        f"_Machine: {platform.machine()}, {os.cpu_count()} cores shared, Python {platform.python_version()}, "
        f"pyrealsense2 {pyrealsense2_version()}; {'quick' if quick else 'full'} run._",
        "",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    print(run(quick="--quick" in sys.argv))
