"""The motor board bench sequence: board info, live odometry, each wheel alone, the watchdog.

Shared by ``robotctl chassis`` and ``robotctl bench``; the caller decides whether the wheels may
turn (they must be off the ground).

A speed measurement during which the host itself stalled (a gap between two commands of half the
board's watchdog or more, or the link called lost meanwhile) is repeated: the board's watchdog may
have stopped the wheel, and the figure would blame the board for the host.
"""

from __future__ import annotations

import asyncio
import math
import time
from typing import Dict, List, Optional, Tuple

from drivers.chassis.base import ChassisStatus, LinkState
from drivers.chassis.serial_chassis import SerialChassis
from robot.base.errors import DriverError
from robot.base.samples import WheelOdometry
from robot.config import ChassisConfig

WHEELS = ("FL", "FR", "RL", "RR")
SPEED_TOLERANCE = 0.05  # a wheel passes within 5 % of its command, measured by its encoder
WATCHDOG_LIMIT = 0.25  # s from the last command to the board reporting its watchdog tripped
COMMAND_PERIOD = 0.02  # s: the bench commands at 50 Hz, like the controller
# The off-the-ground pulse: front wheels forward, rear wheels backward. No rigid motion has these
# wheel speeds (w_FL + w_FR = w_RL + w_RR fails), so on the floor the robot stays put while the
# wheels scrub and lag their command under the load; lifted, they turn freely and follow it.
OFF_GROUND_SPEED = 1.5  # rad/s: 4.5 cm/s of wheel rim, a scrub, not a drive
OFF_GROUND_HOLD = 0.6  # s; the second half is measured
OFF_GROUND_MIN_RATIO = 0.7  # a wheel reaching less than 70 % of its command is loaded
HOST_STALL_TRIES = 3  # measurements in all where the host stalled during the window (_measured)


async def bench(cfg: ChassisConfig, port: str, duration: float, motion: bool, speed: float, hold: float,
                out=None) -> Dict[str, object]:
    """Run the bench sequence; ``out`` gets human-readable lines as they happen."""
    say = out or (lambda line: None)
    chassis = SerialChassis(cfg, port=port)
    odo = chassis.odometry_queue(maxsize=4096)
    report: Dict[str, object] = {"port": port, "ok": True}
    await chassis.connect()
    try:
        b = chassis.board_info
        report["board"] = {"firmware": f"{b.fw_major}.{b.fw_minor}.{b.fw_patch}", "protocol_minor": b.minor,
                           "ticks_per_rev": b.ticks_per_rev, "max_wheel_speed": b.max_speed_mrad_s / 1000.0,
                           "max_wheel_accel": b.max_accel_mrad_s2 / 1000.0, "watchdog_s": b.watchdog_ms / 1000.0,
                           "report_hz": 1e6 / b.report_period_us if b.report_period_us else 0.0}
        say(f"board on {port}: firmware {report['board']['firmware']}, {b.ticks_per_rev} ticks/rev, "
            f"max {b.max_speed_mrad_s / 1000:.1f} rad/s, watchdog {b.watchdog_ms} ms")
        report["odometry_hz"] = await _live(chassis, odo, duration, say)
        if motion:
            lifted = await measure_off_ground(chassis, odo)
            report["off_ground"] = lifted
            say(f"off-the-ground pulse: wheels at {', '.join(f'{100 * r:.0f}' for r in lifted['ratios'])} % "
                f"of the command  {'ok' if lifted['ok'] else 'LOADED: are the wheels on the floor?'}")
            if not lifted["ok"]:
                report["ok"] = False
                motion = False  # a loaded wheel would drive the robot off the bench
        if motion:
            say(f"test motion: each wheel alone at {speed:.2f} rad/s for {hold:.1f} s (robot on blocks)")
            wheels = []
            for i in range(4):
                res = await measure_wheel(chassis, odo, i, speed, hold)
                wheels.append(res)
                say(f"  {res['wheel']}: measured {res['measured']:+.3f} rad/s ({res['error_pct']:+.1f} %), "
                    f"others max {res['others_max']:.3f} rad/s  {'ok' if res['ok'] else 'FAIL'}")
            report["motion"] = wheels
            wd = await measure_watchdog(chassis, odo, speed)
            report["watchdog"] = wd
            say(f"  watchdog: tripped {wd['trip_s']:.3f} s after the last command (limit {WATCHDOG_LIMIT} s), "
                f"wheels still after {wd['stopped_s']:.3f} s  {'ok' if wd['ok'] else 'FAIL'}")
            report["ok"] = all(w["ok"] for w in wheels) and wd["ok"]
        report["status"] = _status_dict(chassis.status)
        report["stats"] = {k: v for k, v in chassis.stats.items() if v}
    finally:
        await chassis.close()
    return report


async def _live(chassis: SerialChassis, odo: asyncio.Queue, duration: float, say) -> float:
    samples: List[WheelOdometry] = []
    t_end = time.monotonic() + duration
    say("    t[s]  angle FL/FR/RL/RR [rad]              speed FL/FR/RL/RR [rad/s]       battery  flags")
    t0 = time.monotonic()
    next_line = t0
    while time.monotonic() < t_end:
        await asyncio.sleep(0.05)
        samples += _drain(odo)
        if samples and time.monotonic() >= next_line:
            s = samples[-1]
            st = chassis.status
            say(f"  {s.t - t0:6.2f}  " + " ".join(f"{a:+8.3f}" for a in s.angles) + "  "
                + " ".join(f"{v:+7.2f}" for v in s.speeds)
                + (f"  {st.battery_v:6.2f} V  {_flags(st)}" if st else "  (no status yet)"))
            next_line += 0.25
    hz = (len(samples) - 1) / (samples[-1].t_board - samples[0].t_board) if len(samples) > 2 else 0.0
    if duration > 0:
        say(f"  odometry at {hz:.1f} Hz, link {chassis.link_state.value}")
    return hz


def _drain(q: asyncio.Queue) -> List[WheelOdometry]:
    out = []
    while not q.empty():
        out.append(q.get_nowait())
    return out


async def _command_for(chassis: SerialChassis, odo: asyncio.Queue, wheels, seconds: float) -> List[WheelOdometry]:
    samples, _ = await _command_window(chassis, odo, wheels, seconds)
    return samples


async def _command_window(chassis: SerialChassis, odo: asyncio.Queue, wheels,
                          seconds: float) -> Tuple[List[WheelOdometry], float]:
    """Command ``wheels`` for ``seconds``: the odometry received, and the longest gap between two
    commands (s; a host that stalls that long may have let the board's watchdog stop the wheels)."""
    samples: List[WheelOdometry] = []
    t_end = time.monotonic() + seconds
    t_prev, gap = time.monotonic(), 0.0
    while time.monotonic() < t_end:
        if not chassis.send_wheel_speeds(wheels):
            raise DriverError(f"{chassis.port}: command refused, link {chassis.link_state.value}: {chassis.last_error}")
        now = time.monotonic()
        gap, t_prev = max(gap, now - t_prev), now
        await asyncio.sleep(COMMAND_PERIOD)
        samples += _drain(odo)
    return samples, max(gap, time.monotonic() - t_prev)


async def _measured(chassis: SerialChassis, odo: asyncio.Queue, wheels, seconds: float) -> Tuple[List[WheelOdometry], int]:
    """``_command_window`` then braking, repeated (up to ``HOST_STALL_TRIES`` in all) while the
    host itself spoiled the window: a gap between commands of half the board's watchdog or more,
    or a link the driver called lost meanwhile (a stalled host reads no reports). What it then
    measures is the host, not the board. The samples of the last window, and the repeats made."""
    watchdog = chassis.board_info.watchdog_ms / 1000.0 if chassis.board_info is not None else WATCHDOG_LIMIT
    repeats = 0
    while True:
        last = repeats + 1 >= HOST_STALL_TRIES
        try:
            samples, gap = await _command_window(chassis, odo, wheels, seconds)
            spoiled = gap >= 0.5 * watchdog
        except DriverError:
            if last or not await _link_back(chassis):
                raise
            spoiled = True
        await _settle(chassis, odo, 0.3)
        if not spoiled or last:
            return samples, repeats
        repeats += 1


async def _link_back(chassis: SerialChassis, wait: float = 3.0) -> bool:
    """Whether the link is (again) ready within ``wait`` s (the driver reconnects by itself)."""
    t_end = time.monotonic() + wait
    while time.monotonic() < t_end:
        if chassis.link_state is LinkState.READY:
            return True
        await asyncio.sleep(0.05)
    return False


async def _settle(chassis: SerialChassis, odo: asyncio.Queue, seconds: float) -> None:
    chassis.stop()
    await asyncio.sleep(seconds)
    _drain(odo)


def _mean_speeds(samples: List[WheelOdometry]) -> List[float]:
    """Mean wheel speeds over the second half of the samples: after the ramp and motor lag."""
    half = samples[len(samples) // 2:]
    if len(half) < 2:
        raise DriverError("too few odometry samples to measure wheel speed: is the board reporting?")
    span = half[-1].t_board - half[0].t_board
    return [(b - a) / span for a, b in zip(half[0].angles, half[-1].angles)]


async def measure_wheel(chassis: SerialChassis, odo: asyncio.Queue, wheel: int, speed: float,
                        hold: float = 1.0) -> Dict[str, object]:
    """Turn one wheel alone and measure every wheel by its encoder."""
    cmd = [0.0, 0.0, 0.0, 0.0]
    cmd[wheel] = speed
    _drain(odo)
    samples, repeats = await _measured(chassis, odo, cmd, hold)
    mean = _mean_speeds(samples)
    err = (mean[wheel] - speed) / speed
    others = max(abs(v) for i, v in enumerate(mean) if i != wheel)
    return {"wheel": WHEELS[wheel], "command": speed, "measured": mean[wheel], "error_pct": 100.0 * err,
            "others_max": others, "ok": abs(err) <= SPEED_TOLERANCE and others <= SPEED_TOLERANCE * abs(speed),
            "host_stall_repeats": repeats}


async def measure_off_ground(chassis: SerialChassis, odo: asyncio.Queue, speed: float = OFF_GROUND_SPEED,
                             hold: float = OFF_GROUND_HOLD) -> Dict[str, object]:
    """A short pulse that moves no robot on the floor: do the wheels turn freely (off the ground)?

    A board whose speed control makes up for the load passes while on the floor: this check
    can tell that the wheels are loaded, not prove that they are lifted.
    """
    cmd = [speed, speed, -speed, -speed]
    _drain(odo)
    samples, repeats = await _measured(chassis, odo, cmd, hold)
    mean = _mean_speeds(samples)
    ratios = [m / c for m, c in zip(mean, cmd)]
    return {"command": cmd, "measured": mean, "ratios": ratios, "ok": min(ratios) >= OFF_GROUND_MIN_RATIO,
            "host_stall_repeats": repeats}


async def measure_watchdog(chassis: SerialChassis, odo: asyncio.Queue, speed: float) -> Dict[str, object]:
    """Drive, then stop commanding (no STOP): time until the board reports its watchdog and is still.

    Host-side timing: it includes the status frame's transport delay, so it overstates the board's.
    """
    samples = await _command_for(chassis, odo, [speed] * 4, 0.5)
    t_last = chassis.last_command_time
    trip: Optional[float] = None
    still: Optional[float] = None
    while time.monotonic() - t_last < 2.0 and (trip is None or still is None):
        await asyncio.sleep(0.005)
        st = chassis.status
        if trip is None and st is not None and st.watchdog_tripped and st.t > t_last:
            trip = st.t - t_last
        samples += _drain(odo)
        if trip is not None and still is None and samples and max(abs(v) for v in samples[-1].speeds) < 0.05 * speed:
            still = samples[-1].t - t_last
    await _settle(chassis, odo, 0.2)
    ok = trip is not None and trip <= WATCHDOG_LIMIT and still is not None
    return {"trip_s": trip if trip is not None else math.inf, "stopped_s": still if still is not None else math.inf,
            "ok": ok}


def _flags(st: ChassisStatus) -> str:
    names = [n for n, on in (("WATCHDOG", st.watchdog_tripped), ("ESTOP", st.estop), ("CLAMPED", st.clamped),
                             ("HOST_SILENT", st.host_silent), ("NO_SESSION", st.no_session)) if on]
    names += [f"FAULT_{w}" for w, f in zip(WHEELS, st.motor_faults) if f]
    return ",".join(names) or "-"


def _status_dict(st: Optional[ChassisStatus]) -> Optional[Dict[str, object]]:
    if st is None:
        return None
    return {"battery_v": st.battery_v, "flags": _flags(st), "board_rx_errors": st.board_rx_errors}
