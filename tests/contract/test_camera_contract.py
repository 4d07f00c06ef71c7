"""The camera contract: what every ``CameraDriver`` promises the app, one suite over all of them.

Backends (the ``rig`` fixture):

- ``sim``: ``SimCamera`` rendering the paper arena;
- ``bag``: ``BagCamera``, a librealsense recording of a simulated drive (written here with
  ``write_recording``) played through the RealSense driver's pipeline; needs the robot's
  pyrealsense2 2.55, skipped with the reason otherwise;
- ``realsense``: a connected D435i of the robot config (``--hil``; it should see a wall).

Every wait is for frames to arrive, bounded by a generous timeout that only guards against a hang.
"""

from __future__ import annotations

import math
import threading
import time
from typing import List, Tuple

import numpy as np
import pytest

from drivers.camera.base import CameraDriver, CameraState
from robot.base.samples import DepthFrame
from robot.config import CameraConfig, parse_robot_config
from robot.maps.plane_map import load_plane_map

POSE = (0.5, 0.5, 3.0 * math.pi / 4.0)  # sees the north and west walls of the arena
VELOCITY = (0.05, -0.02, 0.1)  # m/s, m/s, rad/s: the drive the recording holds
N_FRAMES = 8  # frames a test waits for (the recording holds exactly these)
# A small stream keeps rendering cheap; the D435i offers it with the decimation filter at 4.
ROBOT = parse_robot_config({"cameras": [{"name": "front", "width": 212, "height": 120, "fps": 30, "hfov_deg": 87.0,
                                         "vfov_deg": 58.0, "mount": {"xyz": [0.10, 0.0, 0.12], "rpy_deg": [0, 0, 0]}}]},
                           "contract robot")
FIRST_FRAME_GUARD = 30.0  # s: a live camera may take seconds to deliver its first frame


class Collector:
    """The ``on_frame`` of a test: every frame with its host arrival time, and an event per count."""

    def __init__(self):
        self.frames: List[Tuple[float, DepthFrame]] = []
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)

    def __call__(self, frame: DepthFrame) -> None:
        with self._changed:
            self.frames.append((time.monotonic(), frame))
            self._changed.notify_all()

    def wait_for(self, n: int, timeout: float = FIRST_FRAME_GUARD) -> List[Tuple[float, DepthFrame]]:
        with self._changed:
            if not self._changed.wait_for(lambda: len(self.frames) >= n, timeout):
                raise AssertionError(f"{len(self.frames)} of {n} frames within {timeout:.0f} s")
            return list(self.frames)

    def count(self) -> int:
        with self._lock:
            return len(self.frames)


def expected_shape(cam: CameraConfig) -> Tuple[int, int]:
    d = cam.realsense.decimation
    return (cam.height // d, cam.width // d)


class Rig:
    camera: CameraConfig

    def make(self) -> CameraDriver:
        raise NotImplementedError


class SimRig(Rig):
    def __init__(self, repo_root):
        from drivers.sim.render import SimScene

        self.camera = ROBOT.camera("front")
        self.scene = SimScene(load_plane_map(repo_root / "config" / "maps" / "paper_arena.yaml"))

    def make(self):
        from drivers.camera.sim import SimCamera

        return SimCamera(ROBOT, "front", self.scene, lambda: POSE)


class BagRig(Rig):
    def __init__(self, path):
        self.camera = ROBOT.camera("front")
        self.path = path

    def make(self):
        from drivers.camera.bag import BagCamera

        return BagCamera(self.camera, self.path)


class RealSenseRig(Rig):
    def __init__(self, camera: CameraConfig):
        self.camera = camera

    def make(self):
        from drivers.camera.realsense import RealSenseCamera

        return RealSenseCamera(self.camera)


def _pyrealsense2_problem() -> str:
    from drivers.camera.realsense import pyrealsense2_version

    try:
        import pyrealsense2  # noqa: F401
    except ImportError as e:
        return f"pyrealsense2 not importable: {e}"
    if not pyrealsense2_version().startswith("2.55."):
        return (f"pyrealsense2 {pyrealsense2_version()} installed; recordings need the robot's 2.55 "
                f"(2.58+ records .db3, which 2.55 cannot read)")
    return ""


@pytest.fixture(scope="module")
def recording(repo_root, tmp_path_factory):
    """A recording of a simulated drive seen by the contract robot's camera."""
    problem = _pyrealsense2_problem()
    if problem:
        pytest.skip(problem)
    from drivers.camera.bag import write_recording
    from drivers.sim.drive import simulate_run
    from drivers.sim.render import SimScene

    scene = SimScene(load_plane_map(repo_root / "config" / "maps" / "paper_arena.yaml"))
    frames, _ = simulate_run(ROBOT, scene, "front", POSE, VELOCITY, frames=N_FRAMES, rng=np.random.default_rng(3))
    path = tmp_path_factory.mktemp("contract") / "front.bag"
    write_recording(path, frames, serial="SIM-front")
    return path


@pytest.fixture(params=["sim", "bag", pytest.param("realsense", marks=pytest.mark.hil)])
def rig(request, repo_root):
    if request.param == "sim":
        return SimRig(repo_root)
    if request.param == "bag":
        return BagRig(request.getfixturevalue("recording"))
    from robot.app.bench_checks import connected_cameras, match_cameras

    robot = request.getfixturevalue("hil_robot")
    serials, why_not = connected_cameras()
    if why_not or not serials:
        pytest.skip(why_not or "no RealSense device connected")
    usable = [c for c, why in match_cameras(robot.cameras, serials) if why is None]
    if not usable:
        pytest.skip(f"none of the configured cameras is connected (connected: {', '.join(serials)})")
    return RealSenseRig(usable[0])


def stream(rig: Rig, n: int = N_FRAMES):
    """Start a driver, take ``n`` frames, stop it: (frames with arrival times, start time, driver, states)."""
    cam = rig.make()
    states: List[CameraState] = []
    cam.on_state_change = lambda name, s: states.append(s)
    got = Collector()
    t_start = time.monotonic()
    cam.start(got)
    try:
        frames = got.wait_for(n)
    finally:
        cam.stop()
    return frames, t_start, cam, states


# The contract  --------------------------------------------------------------------------------------


def test_frames_are_depth_frames_of_the_configured_stream(rig):
    frames, _, cam, states = stream(rig)
    assert cam.name == rig.camera.name
    for _, f in frames:
        assert isinstance(f, DepthFrame) and f.camera == rig.camera.name
        assert f.depth.dtype == np.uint16 and f.depth.shape == expected_shape(rig.camera)
        K = np.asarray(f.K)
        assert K.shape == (3, 3) and np.all(np.isfinite(K))
        assert K[0, 0] > 0 and K[1, 1] > 0 and np.array_equal(K[2], [0.0, 0.0, 1.0])
        assert math.isfinite(f.depth_scale) and f.depth_scale > 0
    assert any(np.count_nonzero(f.depth) for _, f in frames)  # the arena's walls are in view
    assert CameraState.STREAMING in states and cam.state is CameraState.STOPPED
    R = cam.T_robot_imu[:3, :3]  # the app's gyro rotation: a proper rotation for every backend
    assert cam.T_robot_imu.shape == (4, 4) and np.allclose(R @ R.T, np.eye(3), atol=1e-6)


def test_frame_numbers_and_capture_times_increase_on_the_host_clock(rig):
    frames, t_start, _, _ = stream(rig)
    numbers = [f.frame_number for _, f in frames]
    times = [f.t_capture for _, f in frames]
    assert all(b > a for a, b in zip(numbers, numbers[1:])), numbers
    assert all(b > a for a, b in zip(times, times[1:])), times
    for arrival, f in frames:
        # host monotonic time, not the device's clock: captured before it was handed over,
        # and not long before the driver was started (a device clock would start near 0)
        assert t_start - 1.0 <= f.t_capture <= arrival


def test_no_frame_is_delivered_twice(rig):
    frames, _, _, _ = stream(rig)
    assert len({f.frame_number for _, f in frames}) == len(frames)
    assert len({id(f) for _, f in frames}) == len(frames)
    for (_, a), (_, b) in zip(frames, frames[1:]):
        assert not np.shares_memory(a.depth, b.depth)  # each frame owns its pixels


def test_start_and_stop_are_idempotent(rig):
    cam = rig.make()
    cam.stop()  # before any start: nothing to do
    assert cam.state is CameraState.STOPPED
    got = Collector()
    cam.start(got)
    try:
        cam.start(got)  # already started: no second capture thread, no duplicated frames
        frames = got.wait_for(N_FRAMES)
    finally:
        cam.stop()
    cam.stop()
    assert cam.state is CameraState.STOPPED
    numbers = [f.frame_number for _, f in frames]
    assert len(set(numbers)) == len(numbers) and numbers == sorted(numbers)
    delivered = got.count()
    time.sleep(0.2)  # a stopped driver delivers nothing more
    assert got.count() == delivered
