"""Bench checks of the robot's hardware: cameras stream and have their intrinsics, the motor
board handshakes, every wheel follows its command, the board's watchdog stops the wheels.

``robotctl bench`` runs them short (5 s of camera, 2 s per wheel); ``tests/hil`` runs the same
measurements at full length. Every check ends as a ``CheckResult``: pass, fail (with what was
measured, or which required device is missing) or skip (with why: ``--skip-cameras``,
``--skip-motion``, motion not confirmed, no handshake). Before any single wheel turns, a short
pulse with the wheels working against each other checks that they are not loaded by the floor.

The wheel and watchdog measurements are ``robot.cli.chassis``'s. Against the firmware emulator
the watchdog is judged on the emulator's own clock: the host's timing there measures the test
machine's scheduling, not the board.
"""

from __future__ import annotations

import asyncio
import math
import os
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np

from robot.app.chassis_checks import (
    OFF_GROUND_MIN_RATIO,
    SPEED_TOLERANCE,
    WATCHDOG_LIMIT,
    WHEELS,
    measure_off_ground,
    measure_watchdog,
    measure_wheel,
)
from robot.base.errors import DriverError
from robot.config import CameraConfig, ChassisConfig, RobotConfig

PASS, FAIL, SKIP = "pass", "fail", "skip"

RATE_TOLERANCE = 0.05  # a camera passes at >= 95 % of its configured frame rate
# The config's field of view is nominal; Intel's D435 datasheet gives depth 87 +- 3 x 58 +- 1 deg,
# and units report about 90 x 59 deg at 848x480 (fx 424 px, 5 % off the nominal 447 px): so the
# field of view is compared, within the datasheet's spread plus half a degree.
HFOV_TOLERANCE_DEG = 3.5
VFOV_TOLERANCE_DEG = 1.5
CENTRE_TOLERANCE = 0.05  # principal point within 5 % of the image size from the centre
DEPTH_SCALE = 0.001  # m per unit: the D400 default, which the localizer's noise model assumes
MIN_REPORT_HZ = 100.0  # PROTOCOL.md section 6: encoder reports at >= 100 Hz
MIN_BATTERY_V = 6.0  # below this a 12 V pack is flat: wheel checks would fail for that reason
TEST_WHEEL_SPEED = 3.0  # rad/s: slow enough on blocks, fast enough for 5 % by encoder


@dataclass
class CheckResult:
    name: str
    status: str  # pass | fail | skip
    detail: str
    data: Dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> Dict[str, Any]:
        return {"name": self.name, "status": self.status, "detail": self.detail, "data": _plain(self.data)}


@dataclass(frozen=True)
class BenchOptions:
    camera_seconds: float = 5.0  # counted frames, after camera_settle
    camera_settle: float = 1.0  # s for auto exposure and the first frames; not counted
    wheel_speed: float = TEST_WHEEL_SPEED
    wheel_hold: float = 2.0  # s each wheel turns; the second half is measured
    motion: bool = True  # False: no wheel and watchdog checks (robot not on blocks)
    handshake_listen: float = 0.5  # s of reports and status looked at after the handshake
    motion_skipped: str = "--skip-motion"  # why, when motion is False
    cameras: bool = True  # False: the camera checks are skipped (--skip-cameras), else cameras are required


def exit_code(results: Sequence[CheckResult]) -> int:
    """0 when nothing failed (skips are not failures), 1 otherwise."""
    return 1 if any(r.status == FAIL for r in results) else 0


def summary(results: Sequence[CheckResult]) -> Dict[str, int]:
    return {s: sum(r.status == s for r in results) for s in (PASS, FAIL, SKIP)}


# Cameras  -----------------------------------------------------------------------------------------

@dataclass
class CameraMeasurement:
    """What one camera delivered over a run: per-frame (host arrival, capture time, frame number,
    valid depth fraction, timestamp domain), the first frame's geometry and the driver's counters."""

    camera: CameraConfig
    frames: List[Tuple[float, float, int, float, str]] = field(default_factory=list)
    K: Optional[np.ndarray] = None
    shape: Optional[Tuple[int, int]] = None
    depth_scale: Optional[float] = None
    stats: Dict[str, int] = field(default_factory=dict)
    window: Tuple[float, float] = (0.0, 0.0)  # host times the rate is counted over
    last_error: Optional[str] = None
    device_info: Dict[str, str] = field(default_factory=dict)

    @property
    def counted(self) -> List[Tuple[float, float, int, float, str]]:
        t0, t1 = self.window
        return [f for f in self.frames if t0 <= f[0] < t1]

    @property
    def rate(self) -> float:
        t0, t1 = self.window
        return len(self.counted) / (t1 - t0) if t1 > t0 else 0.0


def connected_cameras() -> Tuple[List[str], Optional[str]]:
    """(serials of the connected RealSense devices, why none can be looked for or None)."""
    from drivers.camera.realsense import load_pyrealsense2

    try:
        rs = load_pyrealsense2()
    except DriverError as e:
        return [], str(e)
    serials = []
    try:
        for dev in rs.context().query_devices():
            try:
                serials.append(dev.get_info(rs.camera_info.serial_number))
            except RuntimeError:  # being reset: not there yet
                continue
    except RuntimeError as e:
        return [], f"cannot list RealSense devices: {e}"
    return serials, None


def match_cameras(cameras: Sequence[CameraConfig], serials: Sequence[str]) -> List[Tuple[CameraConfig, Optional[str]]]:
    """Each configured camera with None when it can be opened, else why not."""
    out: List[Tuple[CameraConfig, Optional[str]]] = []
    taken = {c.serial for c in cameras if c.serial in serials}
    free = [s for s in serials if s not in taken]
    for cam in cameras:
        if cam.serial is not None:
            out.append((cam, None if cam.serial in serials else
                        f"serial {cam.serial} is not connected (connected: {', '.join(serials) or 'none'})"))
        elif len(free) == 1:
            out.append((cam, None))
            free = []  # one device, one unnamed camera
        else:
            out.append((cam, f"no 'serial' in the config and {len(free)} unclaimed devices connected "
                             f"({', '.join(serials)}): set 'serial' for this camera"))
    return out


def measure_cameras(cameras: Sequence[CameraConfig], seconds: float, settle: float = 1.0,
                    source_for: Optional[Callable[[CameraConfig], Any]] = None) -> Dict[str, CameraMeasurement]:
    """Stream all ``cameras`` at once (as on the robot: they share the USB bus) and count frames.

    ``source_for`` gives each camera's device source (default: the live camera with its serial).
    """
    from drivers.camera.realsense import LiveDevice, RealSenseCamera

    results: Dict[str, CameraMeasurement] = {}
    drivers = []
    try:
        for cam in cameras:
            m = results[cam.name] = CameraMeasurement(cam)

            def on_frame(f, m=m):
                if m.K is None:
                    m.K, m.shape, m.depth_scale = np.array(f.K, float), tuple(f.depth.shape), float(f.depth_scale)
                valid = float(np.count_nonzero(f.depth)) / max(1, f.depth.size)
                m.frames.append((time.monotonic(), f.t_capture, int(f.frame_number), valid, f.timestamp_domain))

            source = source_for(cam) if source_for is not None else LiveDevice(cam.serial)
            d = RealSenseCamera(cam, source)  # settings: the camera's realsense section
            drivers.append((d, m))
            d.start(on_frame)
        time.sleep(settle)
        t0 = time.monotonic()
        time.sleep(seconds)
        t1 = time.monotonic()
    finally:
        for d, m in drivers:
            d.stop()
            m.stats = dict(d.stats)
            m.last_error = d.last_error
            m.device_info = dict(d.device_info)
    for m in results.values():
        m.window = (t0, t1)
    return results


def judge_stream(m: CameraMeasurement) -> CheckResult:
    cam = m.camera
    name = f"camera {cam.name}: stream"
    if not m.frames:
        return CheckResult(name, FAIL, f"no frame in {m.window[1] - m.window[0]:.0f} s"
                                       f"{f' ({m.last_error})' if m.last_error else ''}", {"stats": m.stats})
    counted = m.counted
    valid = float(np.median([f[3] for f in counted])) if counted else 0.0
    data = {"fps": round(m.rate, 2), "configured_fps": cam.fps, "frames": len(counted),
            "valid_depth_fraction": round(valid, 3), "timestamp_domain": m.frames[-1][4], "stats": m.stats,
            "device": m.device_info}
    problems = []
    if m.rate < (1.0 - RATE_TOLERANCE) * cam.fps:
        problems.append(f"{m.rate:.1f} fps, configured {cam.fps:g}")
    for key in ("timeouts", "reconnects"):
        if m.stats.get(key, 0):
            problems.append(f"{m.stats[key]} {key}")
    if problems:
        return CheckResult(name, FAIL, "; ".join(problems), data)
    return CheckResult(name, PASS, f"{m.rate:.1f} fps (configured {cam.fps:g}), no timeouts, "
                                   f"{m.stats.get('drops', 0)} frames skipped, {100 * valid:.0f} % valid depth", data)


def judge_intrinsics(m: CameraMeasurement) -> CheckResult:
    cam = m.camera
    name = f"camera {cam.name}: intrinsics"
    if m.K is None:
        return CheckResult(name, FAIL, "no frame to read the intrinsics from")
    K, K_cfg = m.K, cam.intrinsics_from_fov()
    w, h = (m.shape[1], m.shape[0]) if m.shape else (cam.width, cam.height)
    hfov = math.degrees(2 * math.atan(w / (2 * K[0, 0])))
    vfov = math.degrees(2 * math.atan(h / (2 * K[1, 1])))
    data = {"fx": K[0, 0], "fy": K[1, 1], "ppx": K[0, 2], "ppy": K[1, 2], "hfov_deg": hfov, "vfov_deg": vfov,
            "fx_config": K_cfg[0, 0], "fy_config": K_cfg[1, 1], "depth_scale": m.depth_scale}
    problems = []
    if m.shape != (cam.height, cam.width):
        problems.append(f"depth is {w}x{h}, config says {cam.width}x{cam.height}")
    for axis, got, cfg, tol in (("horizontal", hfov, cam.hfov_deg, HFOV_TOLERANCE_DEG),
                                ("vertical", vfov, cam.vfov_deg, VFOV_TOLERANCE_DEG)):
        if abs(got - cfg) > tol:
            key = "hfov_deg" if axis == "horizontal" else "vfov_deg"
            problems.append(f"{axis} field of view {got:.2f} deg, config {key} {cfg:g} (tolerance {tol:g} deg)")
    for axis, i, size in (("ppx", 0, cam.width), ("ppy", 1, cam.height)):
        if abs(K[i, 2] - K_cfg[i, 2]) > CENTRE_TOLERANCE * size:
            problems.append(f"{axis} {K[i, 2]:.1f} px is far from the image centre {K_cfg[i, 2]:.1f} px")
    if m.depth_scale is None or abs(m.depth_scale - DEPTH_SCALE) > 1e-3 * DEPTH_SCALE:
        problems.append(f"depth scale {m.depth_scale} m, expected {DEPTH_SCALE}")
    if problems:
        return CheckResult(name, FAIL, "; ".join(problems), data)
    return CheckResult(name, PASS, f"field of view {hfov:.1f} x {vfov:.1f} deg (config {cam.hfov_deg:g} x "
                                   f"{cam.vfov_deg:g}), fx {K[0, 0]:.1f} fy {K[1, 1]:.1f}, "
                                   f"centre ({K[0, 2]:.1f}, {K[1, 2]:.1f}) px", data)


def camera_checks(robot: RobotConfig, opts: BenchOptions) -> List[CheckResult]:
    """Every configured camera is required: a missing one fails its stream check."""
    if not opts.cameras:
        return [CheckResult(f"camera {c.name}: {what}", SKIP, "--skip-cameras") for c in robot.cameras
                for what in ("stream", "intrinsics")]
    serials, why_not = connected_cameras()
    if why_not is None and not serials:
        why_not = "no RealSense device"
    if why_not is not None:
        out: List[CheckResult] = []
        for c in robot.cameras:
            out += [CheckResult(f"camera {c.name}: stream", FAIL, why_not),
                    CheckResult(f"camera {c.name}: intrinsics", SKIP, "camera not connected")]
        return out
    matches = match_cameras(robot.cameras, serials)
    usable = [cam for cam, missing in matches if missing is None]
    measured = measure_cameras(usable, opts.camera_seconds, opts.camera_settle) if usable else {}
    results: List[CheckResult] = []
    for cam, missing in matches:
        if missing is None:
            results += [judge_stream(measured[cam.name]), judge_intrinsics(measured[cam.name])]
        else:
            results += [CheckResult(f"camera {cam.name}: stream", FAIL, missing),
                        CheckResult(f"camera {cam.name}: intrinsics", SKIP, "camera not connected")]
    return results


# Chassis  -----------------------------------------------------------------------------------------

def _drain(q: asyncio.Queue) -> list:
    out = []
    while not q.empty():
        out.append(q.get_nowait())
    return out


def judge_handshake(chassis, samples: list, listen: float) -> CheckResult:
    b, st = chassis.board_info, chassis.status
    report_hz = 1e6 / b.report_period_us if b.report_period_us else 0.0
    data: Dict[str, Any] = {
        "firmware": f"{b.fw_major}.{b.fw_minor}.{b.fw_patch}", "ticks_per_rev": b.ticks_per_rev,
        "watchdog_ms": b.watchdog_ms, "report_hz": report_hz, "max_wheel_speed": b.max_speed_mrad_s / 1000.0,
        "odometry_samples": len(samples), "battery_v": st.battery_v if st else None}
    problems = []
    if b.watchdog_ms > 1000 * WATCHDOG_LIMIT:
        problems.append(f"board watchdog {b.watchdog_ms} ms > {1000 * WATCHDOG_LIMIT:.0f} ms")
    if report_hz < MIN_REPORT_HZ:
        problems.append(f"encoder reports at {report_hz:.0f} Hz < {MIN_REPORT_HZ:.0f} Hz")
    if len(samples) < 0.8 * listen * max(report_hz, 1.0):
        problems.append(f"only {len(samples)} odometry samples in {listen:.1f} s")
    if st is None:
        problems.append("no STATUS from the board")
    else:
        if _refusal(st):
            problems.append(_refusal(st))
        if st.battery_v < MIN_BATTERY_V:
            problems.append(f"battery {st.battery_v:.2f} V")
    if problems:
        return CheckResult("chassis: handshake", FAIL, "; ".join(problems), data)
    return CheckResult("chassis: handshake", PASS,
                       f"firmware {data['firmware']}, {b.ticks_per_rev} ticks/rev, watchdog {b.watchdog_ms} ms, "
                       f"reports {report_hz:.0f} Hz, battery {st.battery_v:.1f} V", data)


OFF_GROUND = "wheels: off the ground"


def _repeated(res: Dict[str, Any]) -> str:
    n = int(res.get("host_stall_repeats", 0))
    return f" (measured again: the host stalled {n} time(s) while commanding the wheels)" if n else ""


def judge_off_ground(res: Dict[str, Any]) -> CheckResult:
    ratios = ", ".join(f"{w} {100 * r:.0f} %" for w, r in zip(WHEELS, res["ratios"])) + _repeated(res)
    if res["ok"]:
        return CheckResult(OFF_GROUND, PASS, f"the wheels turned freely against each other ({ratios} of the "
                                             f"command); a board that makes up for load would pass too", res)
    return CheckResult(OFF_GROUND, FAIL, f"the wheels lag their command under load ({ratios}, need "
                                         f"{100 * OFF_GROUND_MIN_RATIO:.0f} %): put the robot on blocks", res)


def judge_wheel(res: Dict[str, Any]) -> CheckResult:
    name = f"wheel {res['wheel']}"
    detail = (f"{res['measured']:+.3f} rad/s for {res['command']:+.3f} ({res['error_pct']:+.1f} %), "
              f"others up to {res['others_max']:.3f} rad/s" + _repeated(res))
    if res["ok"]:
        return CheckResult(name, PASS, detail, res)
    why = []
    if abs(res["error_pct"]) > 100 * SPEED_TOLERANCE:
        why.append(f"off by more than {100 * SPEED_TOLERANCE:.0f} %")
    if res["others_max"] > SPEED_TOLERANCE * abs(res["command"]):
        why.append("another wheel turned (wiring or wheel order?)")
    return CheckResult(name, FAIL, detail + ": " + ", ".join(why or ["failed"]), res)


def board_clock_trip(emulator) -> Optional[float]:
    """Watchdog trip after the last speed command the board received, on the emulator's clock."""
    from firmware_protocol import SetWheelSpeeds

    trips = emulator.events("watchdog")
    cmds = [t for t, m in emulator.received() if isinstance(m, SetWheelSpeeds)]
    if not trips or not cmds:
        return None
    t_trip = trips[-1][0]
    before = [t for t in cmds if t <= t_trip]
    return t_trip - before[-1] if before else None


def judge_watchdog(res: Dict[str, Any], board_trip: Optional[float] = None, emulated: bool = False) -> CheckResult:
    name = "chassis: watchdog"
    data = dict(res)
    stopped = math.isfinite(res["stopped_s"])
    if emulated:
        data["board_trip_s"] = board_trip
        trip = board_trip if board_trip is not None else math.inf
        clock = f"on the emulated board's clock, host saw {res['trip_s']:.3f} s"
    else:
        trip = res["trip_s"]
        clock = "host clock, transport included"
    detail = (f"tripped {trip:.3f} s after the last command ({clock}; limit {WATCHDOG_LIMIT:.2f} s), "
              f"wheels still {res['stopped_s']:.3f} s after it")
    ok = trip <= WATCHDOG_LIMIT and stopped
    if not math.isfinite(trip):
        detail = "the board never reported its watchdog after the commands stopped"
    elif not stopped:
        detail += ": the wheels did not stop within 2 s"
    return CheckResult(name, PASS if ok else FAIL, detail, data)


def _refusal(status) -> str:
    """Why the board would refuse speed commands (PROTOCOL.md: e-stop, motor fault), or ""."""
    if status is None:
        return ""
    if status.estop:
        return "e-stop pressed"
    faults = [w for w, f in zip(WHEELS, status.motor_faults) if f]
    return f"motor fault on {', '.join(faults)}" if faults else ""


def _port_absent(port: str) -> bool:
    return "://" not in port and not os.path.exists(port)


async def chassis_checks(config: ChassisConfig, port: str, opts: BenchOptions, emulator=None,
                         port_required: bool = False) -> List[CheckResult]:
    """Handshake, then (``opts.motion``) the off-the-ground pulse, each wheel alone and the board watchdog.

    The motor board is required: a port that does not exist fails the handshake (``port_required``
    is kept for callers; the board is always required now).
    """
    motion_names = [OFF_GROUND] + [f"wheel {w}" for w in WHEELS] + ["chassis: watchdog"]
    if _port_absent(port):
        why = f"motor board port {port} is absent"
        first = CheckResult("chassis: handshake", FAIL, why)
        return [first] + [CheckResult(n, SKIP, why) for n in motion_names]
    chassis = _serial_chassis(config, port)
    odo = chassis.odometry_queue(maxsize=4096)
    try:
        await chassis.connect()
    except DriverError as e:
        return [CheckResult("chassis: handshake", FAIL, str(e))] + [CheckResult(n, SKIP, "no handshake")
                                                                     for n in motion_names]
    results: List[CheckResult] = []
    try:
        _drain(odo)
        await asyncio.sleep(opts.handshake_listen)
        results.append(judge_handshake(chassis, _drain(odo), opts.handshake_listen))
        if not opts.motion:
            return results + [CheckResult(n, SKIP, opts.motion_skipped) for n in motion_names]
        refusal = _refusal(chassis.status)
        if refusal:
            # the board refuses every speed command: spinning would only measure zeros
            return results + [CheckResult(OFF_GROUND, SKIP, "cannot drive: " + refusal)] + [
                CheckResult(f"wheel {w}", FAIL, f"the board refuses speed commands: {refusal}")
                for w in WHEELS] + [CheckResult("chassis: watchdog", SKIP, "cannot drive: " + refusal)]
        try:
            lifted = judge_off_ground(await measure_off_ground(chassis, odo))
        except DriverError as e:
            lifted = CheckResult(OFF_GROUND, FAIL, str(e))
        results.append(lifted)
        if lifted.status == FAIL:  # a loaded wheel would drive the robot off the bench: stop here
            return results + [CheckResult(n, SKIP, "the wheels seem to be on the floor") for n in motion_names[1:]]
        for i in range(4):
            try:
                results.append(judge_wheel(await measure_wheel(chassis, odo, i, opts.wheel_speed, opts.wheel_hold)))
            except DriverError as e:  # the link went down or the board refused: this wheel failed
                results.append(CheckResult(f"wheel {WHEELS[i]}", FAIL, str(e)))
        try:
            wd = await measure_watchdog(chassis, odo, opts.wheel_speed)
            results.append(judge_watchdog(wd, board_clock_trip(emulator) if emulator is not None else None,
                                          emulated=emulator is not None))
        except DriverError as e:
            results.append(CheckResult("chassis: watchdog", FAIL, str(e)))
    finally:
        await chassis.close()
    return results


def _serial_chassis(config: ChassisConfig, port: str):
    from robot.app.assemble import build_chassis

    return build_chassis("serial", config, port)


def run_bench(robot: RobotConfig, opts: BenchOptions, port: Optional[str] = None,
              chassis_kind: str = "serial") -> List[CheckResult]:
    """All checks in order: cameras, then the chassis of ``chassis_kind`` ("serial": on ``port``
    or the config's; "emulator": the firmware emulator)."""
    from robot.app.assemble import board_port

    results = camera_checks(robot, opts)
    with board_port(chassis_kind, robot.chassis, port) as board:
        results += asyncio.run(chassis_checks(board.config, board.port, opts, board.emulator,
                                              port_required=port is not None))
    return results


def _plain(o: Any) -> Any:
    """JSON-ready: numpy to Python, non-finite floats to None."""
    if isinstance(o, dict):
        return {str(k): _plain(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_plain(v) for v in o]
    if isinstance(o, np.ndarray):
        return _plain(o.tolist())
    if isinstance(o, np.generic):
        o = o.item()
    if isinstance(o, float) and not math.isfinite(o):
        return None
    return o


__all__ = ["BenchOptions", "CheckResult", "PASS", "FAIL", "SKIP", "run_bench", "camera_checks", "chassis_checks",
           "measure_cameras", "match_cameras", "judge_stream", "judge_intrinsics", "judge_handshake", "judge_wheel",
           "judge_watchdog", "judge_off_ground", "OFF_GROUND", "exit_code", "summary"]
