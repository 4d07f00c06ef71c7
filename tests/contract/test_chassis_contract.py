"""The chassis contract: what every ``Chassis`` backend promises the app, one suite over all of them.

Backends (the ``rig`` fixture):

- ``emulator``: ``SerialChassis`` and pyserial on a real pty, the firmware emulator behind it,
  in real time;
- ``loopback``: ``LoopbackChassis`` on the board model, on a simulated clock the rig advances;
- ``board``: ``SerialChassis`` on the robot's motor board (``--hil``). THE ROBOT MUST BE ON
  BLOCKS: the wheels turn, at 3 rad/s at most.

Every wait is for an event, in the backend's own time: the real-time rigs sleep, the loopback rig
steps its board. The overall timeout only guards against a hang.
"""

from __future__ import annotations

import asyncio
import dataclasses
import math
import os
from typing import List, Optional

import pytest

import firmware_protocol as fp
from drivers.chassis.base import Chassis, LinkState
from drivers.chassis.emulator import BoardModel, FirmwareEmulator
from drivers.chassis.loopback import LoopbackChassis
from drivers.chassis.serial_chassis import SerialChassis
from robot.base.errors import DriverError
from robot.base.samples import WheelOdometry
from robot.config import ChassisConfig

# a loaded test machine can stall the emulator thread for 100 ms; the robot's 0.1 s stays the default
CFG = ChassisConfig(link_timeout=0.5, reconnect_backoff_max=0.2)
SPEED = 3.0  # rad/s: the bench's test speed, safe on blocks
PERIOD = 0.02  # s between speed commands, as the control loop sends them
REST = 0.05  # rad/s: a wheel slower than this is at rest
HANG_GUARD = 120.0  # s of wall clock for a whole test


class Rig:
    """One backend: makes chassis, lets time pass in the backend's clock, and (where it can)
    shows what the board received."""

    battery = (6.0, 30.0)  # V a healthy board reports

    def __init__(self, config: ChassisConfig):
        self.config = config

    def make(self, config: Optional[ChassisConfig] = None) -> Chassis:
        raise NotImplementedError

    async def pass_time(self, seconds: float) -> None:
        await asyncio.sleep(seconds)

    def board_received(self) -> Optional[List[fp.Message]]:
        """Every message the board decoded, or None when the board cannot tell (real hardware)."""
        return None

    def close(self) -> None:
        pass


class EmulatorRig(Rig):
    battery = (11.99, 12.01)  # the emulator's pack

    def __init__(self):
        super().__init__(CFG)
        self.emulator = FirmwareEmulator(CFG).start()

    def make(self, config=None):
        return SerialChassis(config or self.config, port=self.emulator.port)

    def board_received(self):
        return [m for _, m in self.emulator.received()]

    def close(self):
        self.emulator.close()


class LoopbackRig(Rig):
    battery = (11.99, 12.01)
    STEP = 0.005  # s of simulated time per board step

    def __init__(self):
        super().__init__(CFG)
        self.board = BoardModel(CFG)
        self.chassis: List[LoopbackChassis] = []

    def make(self, config=None):
        ch = LoopbackChassis(self.board, config or self.config)
        self.chassis.append(ch)
        return ch

    async def pass_time(self, seconds):
        for _ in range(max(1, int(round(seconds / self.STEP)))):
            self.board.step(self.STEP)
            for ch in self.chassis:
                ch.poll()
        await asyncio.sleep(0)  # let the test's other tasks run, as real time would

    def board_received(self):
        return [m for _, m in self.board.received]


class BoardRig(Rig):
    def __init__(self, config: ChassisConfig):
        super().__init__(config)

    def make(self, config=None):
        return SerialChassis(config or self.config)


@pytest.fixture(params=["emulator", "loopback", pytest.param("board", marks=pytest.mark.hil)])
def rig(request):
    if request.param == "emulator":
        r: Rig = EmulatorRig()
    elif request.param == "loopback":
        r = LoopbackRig()
    else:
        cfg = request.getfixturevalue("hil_robot").chassis
        port = os.environ.get("ROBOT_CHASSIS_PORT", cfg.port)
        if not os.path.exists(port):
            pytest.skip(f"motor board port {port} is absent (set ROBOT_CHASSIS_PORT or chassis.port)")
        r = BoardRig(dataclasses.replace(cfg, port=port))
    yield r
    r.close()


def run(coro):
    return asyncio.run(asyncio.wait_for(coro, HANG_GUARD))


async def until(rig: Rig, pred, what: str, timeout: float = 10.0, step: float = 0.01) -> None:
    """Wait for ``pred()`` for up to ``timeout`` seconds of the backend's time."""
    for _ in range(int(timeout / step)):
        if pred():
            return
        await rig.pass_time(step)
    raise AssertionError(f"timed out waiting for {what}")


def drain(q: asyncio.Queue, into: List[WheelOdometry]) -> List[WheelOdometry]:
    while not q.empty():
        into.append(q.get_nowait())
    return into


async def drive(rig: Rig, ch: Chassis, wheels, seconds: float) -> None:
    """Command ``wheels`` at the control rate for ``seconds`` of the backend's time."""
    for _ in range(int(round(seconds / PERIOD))):
        assert ch.send_wheel_speeds(wheels), f"command refused, link {ch.link_state}"
        await rig.pass_time(PERIOD)


def commands_received(rig: Rig) -> Optional[List[fp.Message]]:
    got = rig.board_received()
    return None if got is None else [m for m in got if not isinstance(m, fp.Heartbeat)]


# The contract  --------------------------------------------------------------------------------------


def test_handshake_reaches_ready_and_close_ends_it(rig):
    async def main():
        ch = rig.make()
        assert ch.link_state is LinkState.CLOSED
        await ch.connect()
        state, info, limit = ch.link_state, ch.board_info, ch.max_wheel_speed
        counted = (ch.reconnects, ch.stats.get("reconnects", 0))
        await ch.close()
        await ch.close()  # idempotent
        return state, info, limit, ch.link_state, counted

    state, info, limit, after, counted = run(main())
    assert state is LinkState.READY and after is LinkState.CLOSED
    assert counted == (0, 0)  # the cheap count the control loop reads is the stats' one
    assert info is not None and info.ticks_per_rev == rig.config.ticks_per_rev
    assert 0.0 < limit <= rig.config.max_wheel_speed


def test_commands_are_refused_before_ready_and_after_close(rig):
    async def main():
        ch = rig.make()
        before = (ch.send_wheel_speeds([1.0, 1.0, 1.0, 1.0]), ch.stop())
        await ch.connect()
        during = ch.send_wheel_speeds([1.0, 1.0, 1.0, 1.0])
        await rig.pass_time(0.05)
        await ch.close()
        after = (ch.send_wheel_speeds([1.0, 1.0, 1.0, 1.0]), ch.stop())
        await rig.pass_time(0.05)
        return before, during, after

    before, during, after = run(main())
    assert before == (False, False) and during is True and after == (False, False)
    msgs = commands_received(rig)
    if msgs is not None:  # a refused command is never queued: the board saw exactly the accepted one
        kinds = [type(m).__name__ for m in msgs]
        assert kinds.count("SetWheelSpeeds") == 1
        assert kinds.index("Hello") < kinds.index("SetWheelSpeeds")
        assert kinds[-1] == "Stop"  # close stops the wheels


def test_odometry_arrives_in_order_with_finite_values(rig):
    async def main():
        ch = rig.make()
        q = ch.odometry_queue(maxsize=10000)
        samples: List[WheelOdometry] = []
        await ch.connect()
        try:
            await until(rig, lambda: len(drain(q, samples)) >= 30, "30 odometry samples")
        finally:
            await ch.close()
        return samples

    samples = run(main())
    assert all(isinstance(s, WheelOdometry) for s in samples)
    assert all(b.t >= a.t for a, b in zip(samples, samples[1:]))  # host time never runs backwards
    assert all(b.t_board > a.t_board for a, b in zip(samples, samples[1:]))
    for s in samples:
        assert s.dt > 0.0 and math.isfinite(s.t) and math.isfinite(s.t_board)
        assert len(s.angles) == len(s.speeds) == 4
        assert all(math.isfinite(v) for v in s.angles + s.speeds)


def test_a_wheel_speed_command_turns_each_wheel_in_its_sign(rig):
    command = [SPEED, -SPEED, 0.5 * SPEED, -0.5 * SPEED]

    async def main():
        ch = rig.make()
        q = ch.odometry_queue(maxsize=10000)
        samples: List[WheelOdometry] = []
        await ch.connect()
        try:
            await until(rig, lambda: len(drain(q, samples)) >= 2, "odometry before driving")
            start = samples[-1].angles
            await drive(rig, ch, command, 0.6)
            end = drain(q, samples)[-1].angles
        finally:
            await ch.close()
        return start, end

    start, end = run(main())
    for wheel, (a, b, w) in enumerate(zip(start, end, command)):
        # 0.6 s at 1.5 to 3 rad/s is 0.9 to 1.8 rad less the ramp: a tenth of a radian is unmistakable
        assert (b - a) * math.copysign(1.0, w) > 0.1, f"wheel {wheel}: {b - a:+.3f} rad for {w:+.1f} rad/s"


def test_stop_brings_the_wheels_to_rest_without_the_watchdog(rig):
    async def main():
        ch = rig.make()
        q = ch.odometry_queue(maxsize=10000)
        samples: List[WheelOdometry] = []
        await ch.connect()
        try:
            await drive(rig, ch, [SPEED] * 4, 0.4)
            moving = max(abs(v) for v in drain(q, samples)[-1].speeds)
            assert ch.stop()

            def at_rest():
                recent = drain(q, samples)[-5:]
                return len(recent) == 5 and all(abs(v) < REST for s in recent for v in s.speeds)

            await until(rig, at_rest, "the wheels at rest after STOP", timeout=5.0)
            # twice the board's watchdog period without a command: STOP left nothing for it to stop
            await rig.pass_time(2 * rig.config.watchdog_timeout)
            status = ch.status
        finally:
            await ch.close()
        return moving, status

    moving, status = run(main())
    assert moving > 0.5 * SPEED
    assert status is not None and not status.watchdog_tripped


def test_ticks_per_rev_mismatch_refuses_to_drive(rig):
    wrong = dataclasses.replace(rig.config, ticks_per_rev=rig.config.ticks_per_rev + 7)

    async def main():
        ch = rig.make(wrong)
        with pytest.raises(DriverError, match=f"ticks.*ticks_per_rev: {wrong.ticks_per_rev}"):
            await ch.connect()
        state = ch.link_state
        refused = not ch.send_wheel_speeds([1.0, 1.0, 1.0, 1.0])
        await ch.close()
        return state, refused

    state, refused = run(main())
    assert state is LinkState.FAULT and refused
    msgs = commands_received(rig)
    if msgs is not None:
        assert not [m for m in msgs if isinstance(m, fp.SetWheelSpeeds)]


def test_status_carries_the_battery_voltage(rig):
    async def main():
        ch = rig.make()
        await ch.connect()
        try:
            await until(rig, lambda: ch.status is not None, "a STATUS from the board")
            return ch.status
        finally:
            await ch.close()

    status = run(main())
    lo, hi = rig.battery
    assert lo <= status.battery_v <= hi
    assert math.isfinite(status.t) and len(status.motor_faults) == 4
    assert not status.no_session  # the handshake opened the session


@pytest.mark.parametrize("bad", [[float("nan"), 0.0, 0.0, 0.0], [1.0, 2.0, 3.0], ["fast", 0, 0, 0], None])
def test_bad_wheel_speeds_stop_the_wheels_and_raise(rig, bad):
    async def main():
        ch = rig.make()
        await ch.connect()
        try:
            await drive(rig, ch, [SPEED] * 4, 0.1)
            with pytest.raises(ValueError, match="4 finite numbers"):
                ch.send_wheel_speeds(bad)
            await rig.pass_time(0.05)
        finally:
            await ch.close()

    run(main())
    msgs = commands_received(rig)
    if msgs is not None:  # the bad command never went out; a STOP did (and close's STOP after it)
        kinds = [type(m).__name__ for m in msgs]
        assert kinds[-3:] == ["SetWheelSpeeds", "Stop", "Stop"]
