"""The chassis backends beyond their shared contract (tests/contract/test_chassis_contract.py):
the serial driver, unmodified, with pyserial, against the emulated board on a real pty, and the
loopback backend on the simulated clock.

Timeouts are generous (a loaded 2-core machine): they bound how long a test waits, never what it
asserts. The board watchdog is judged on the emulator's own clock.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import threading
import time

import pytest
import serial

import firmware_protocol as fp
from drivers.chassis.base import LinkState
from drivers.chassis.emulator import BoardModel, FirmwareEmulator
from drivers.chassis.loopback import LoopbackChassis
from drivers.chassis.serial_chassis import SerialChassis, reconnect_delay
from drivers.chassis.session import BoardClock
from firmware_protocol.counters import delta_i32 as wrap_delta_i32
from robot.base.errors import DriverError
from robot.cli import chassis as cli_chassis
from robot.config import ChassisConfig

# a loaded test machine can stall the emulator thread for 100 ms; the robot's 0.1 s stays the default
CFG = ChassisConfig(link_timeout=0.5, reconnect_backoff_max=0.2)
TICK = 2 * math.pi / CFG.ticks_per_rev


def arun(coro, timeout: float = 40.0):
    return asyncio.run(asyncio.wait_for(coro, timeout))


async def until(pred, timeout: float = 10.0, what: str = "condition"):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return
        await asyncio.sleep(0.01)
    raise AssertionError(f"timed out waiting for {what}")


async def drive(chassis: SerialChassis, wheels, seconds: float, period: float = 0.02) -> int:
    sent = 0
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        sent += chassis.send_wheel_speeds(wheels)
        await asyncio.sleep(period)
    return sent


def drain(q: asyncio.Queue):
    out = []
    while not q.empty():
        out.append(q.get_nowait())
    return out


def board_msgs(emu, kind):
    return [(t, m) for t, m in emu.received() if isinstance(m, kind)]


@pytest.fixture
def emu(tmp_path):
    e = FirmwareEmulator(CFG, link_path=str(tmp_path / "robot-motor-board")).start()
    yield e
    e.close()


# Pure helpers  ----------------------------------------------------------------------------------

def test_wrap_delta_i32_across_the_int32_limits():
    assert wrap_delta_i32(-(2 ** 31) + 5, 2 ** 31 - 5) == 10
    assert wrap_delta_i32(2 ** 31 - 5, -(2 ** 31) + 5) == -10
    assert wrap_delta_i32(100, 40) == 60 and wrap_delta_i32(40, 100) == -60


def test_board_clock_unwraps_the_32_bit_microseconds():
    c = BoardClock()
    stamps = [(2 ** 32 - 20_000 + 10_000 * k) & 0xFFFFFFFF for k in range(5)]
    times = [c.unwrap(s) for s in stamps]
    assert [round(b - a, 9) for a, b in zip(times, times[1:])] == [0.01] * 4


def test_board_clock_mapping_takes_the_least_delayed_frame():
    c = BoardClock()
    true_offset = 1000.0
    delays = [0.004, 0.0011, 0.009, 0.001, 0.02, 0.003]
    mapped = [c.to_host(0.01 * k, 0.01 * k + true_offset + d) for k, d in enumerate(delays)]
    assert mapped[-1] == pytest.approx(0.05 + true_offset + 0.001, abs=1e-9)
    assert all(b >= a for a, b in zip(mapped, mapped[1:]))


@pytest.mark.parametrize("skew", [100e-6, -100e-6])  # the board's crystal 100 ppm slow or fast
def test_board_clock_follows_drift_through_its_window(skew):
    """A constant unknown delay (2 ms here) stays in the mapping; drift costs at most window * skew."""
    c = BoardClock(window=2.0)
    for k in range(1000):  # 10 s
        board = 0.01 * k
        host = 50.0 + board * (1 + skew) + 0.002
        t = c.to_host(board, host)
    assert t == pytest.approx(host, abs=2.0 * abs(skew) + 1e-6)
    assert host - t >= -1e-9  # never ahead of the receive time


def test_reconnect_delay_doubles_and_is_capped():
    assert [reconnect_delay(k, 2.0) for k in range(8)] == [0.05, 0.1, 0.2, 0.4, 0.8, 1.6, 2.0, 2.0]
    assert reconnect_delay(10_000, 2.0) == 2.0


# Handshake and odometry  ------------------------------------------------------------------------

def test_connect_handshakes_and_odometry_matches_the_wheels(emu):
    async def main():
        ch = SerialChassis(CFG, port=emu.port)
        q = ch.odometry_queue(maxsize=1000)
        await ch.connect()
        assert ch.link_state is LinkState.READY
        assert ch.board_info.ticks_per_rev == CFG.ticks_per_rev
        await drive(ch, [4.0, -4.0, 2.0, 0.0], 0.6)
        ch.stop()
        await asyncio.sleep(0.5)
        samples = drain(q)
        await ch.close()
        return samples, ch

    samples, ch = arun(main())
    assert len(samples) > 50
    # cumulative angles equal the emulated shafts to encoder quantisation
    for a, th in zip(samples[-1].angles, emu.board.theta):
        assert abs(a - th) <= 1.01 * TICK
    assert samples[-1].angles[0] > 1.0 and samples[-1].angles[1] < -1.0 and samples[-1].angles[3] == 0.0
    # sample times: host clock, increasing, spaced by the board's 10 ms
    ts = [s.t for s in samples]
    assert all(b >= a for a, b in zip(ts, ts[1:]))
    assert sum(s.dt for s in samples) / len(samples) == pytest.approx(0.01, rel=0.05)
    true_t = emu._t_start + samples[-1].t_board  # when the emulator actually sampled, on the host clock
    assert abs(samples[-1].t - true_t) < 0.05
    # mid-run speeds are the angle increments over dt
    s = samples[30]
    assert s.speeds[0] * s.dt == pytest.approx(s.angles[0] - samples[29].angles[0])
    assert ch.stats["rx_dropped_frames"] == 0 and ch.stats["commands_sent"] > 20


def test_odometry_survives_clock_and_tick_wrap_around(tmp_path):
    e = FirmwareEmulator(CFG, t0_us=2 ** 32 - 300_000, tick_offset=(2 ** 31 - 200, -(2 ** 31) + 200, 0, 0)).start()

    async def main():
        ch = SerialChassis(CFG, port=e.port)
        q = ch.odometry_queue(maxsize=1000)
        await ch.connect()
        await drive(ch, [6.0, -6.0, 0.0, 0.0], 0.8)
        ch.stop()
        await asyncio.sleep(0.4)
        out = drain(q)
        await ch.close()
        return out

    try:
        samples = arun(main())
        assert samples[0].t_board < 2 ** 32 * 1e-6 < samples[-1].t_board  # the clock wrapped mid-run
        assert all(0 < s.dt < 0.1 for s in samples)
        assert all(abs(v) < 25.0 for s in samples for v in s.speeds)  # no wrap-sized jump anywhere
        assert samples[-1].angles[0] > 1.5 and samples[-1].angles[1] < -1.5
        # the driver's angles start at its first report; the board's shafts at zero
        first = samples[0].angles[0] - samples[0].speeds[0] * samples[0].dt
        assert samples[-1].angles[0] - first == pytest.approx(e.board.theta[0], abs=3 * TICK)
    finally:
        e.close()


# Safety rules  ----------------------------------------------------------------------------------

def test_close_sends_stop_and_the_wheels_ramp_down(emu):
    async def main():
        ch = SerialChassis(CFG, port=emu.port)
        await ch.connect()
        await drive(ch, [5.0, 5.0, 5.0, 5.0], 0.4)
        await ch.close()
        return ch

    ch = arun(main())
    assert ch.link_state is LinkState.CLOSED
    last_cmd = [type(m).__name__ for _, m in emu.received() if not isinstance(m, fp.Heartbeat)][-1]
    assert last_cmd == "Stop"
    assert ch.stats["acks"] >= 1
    deadline = time.monotonic() + 10.0  # the motors' lag, waited for: a starved machine is slower
    while max(abs(w) for w in emu.true_wheel_speeds) >= 0.05 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert max(abs(w) for w in emu.true_wheel_speeds) < 0.05
    assert emu.events("watchdog") == []  # stopped by the STOP, not by the watchdog


def test_hung_control_loop_is_stopped_by_the_board_watchdog(emu):
    """The app stops calling send_wheel_speeds but the driver (and its heartbeats) live on."""
    async def main():
        ch = SerialChassis(CFG, port=emu.port)
        await ch.connect()
        await drive(ch, [5.0, 5.0, 5.0, 5.0], 0.4)
        await until(lambda: ch.status is not None and ch.status.watchdog_tripped, 5.0, "WATCHDOG in status")
        await asyncio.sleep(0.4)
        state = ch.link_state
        await ch.close()
        return state

    state = arun(main())
    last_cmd_t = board_msgs(emu, fp.SetWheelSpeeds)[-1][0]
    (trip_t, _, _), = emu.events("watchdog")
    assert 0.2 - 1e-6 <= trip_t - last_cmd_t <= 0.25  # on the emulator's clock
    assert any(t > last_cmd_t for t, _ in board_msgs(emu, fp.Heartbeat))  # heartbeats did not keep it going
    assert state is LinkState.READY  # the link was fine all along
    assert max(abs(w) for w in emu.true_wheel_speeds) < 0.05


def test_host_side_limit_scales_all_wheels_together(emu):
    async def main():
        ch = SerialChassis(CFG, port=emu.port)
        await ch.connect()
        ch.send_wheel_speeds([40.0, 20.0, -10.0, 0.0])
        await asyncio.sleep(0.1)
        await ch.close()
        return ch

    ch = arun(main())
    (_, cmd), = board_msgs(emu, fp.SetWheelSpeeds)
    assert cmd.rad_s == pytest.approx((20.0, 10.0, -5.0, 0.0))
    assert ch.stats["commands_scaled"] == 1 and ch.stats.get("nack_clamped", 0) == 0


def test_board_limit_lower_than_config_wins(tmp_path):
    e = FirmwareEmulator(CFG, max_wheel_speed=8.0).start()

    async def main():
        ch = SerialChassis(CFG, port=e.port)
        await ch.connect()
        limit = ch.max_wheel_speed
        ch.send_wheel_speeds([16.0, 0.0, 0.0, -4.0])
        await asyncio.sleep(0.1)
        await ch.close()
        return limit

    try:
        assert arun(main()) == 8.0
        (_, cmd), = board_msgs(e, fp.SetWheelSpeeds)
        assert cmd.rad_s == pytest.approx((8.0, 0.0, 0.0, -2.0))
        assert e.events("clamped") == []
    finally:
        e.close()


# Failing handshakes name the problem  -----------------------------------------------------------

def test_missing_port_is_a_clear_driver_error(tmp_path):
    with pytest.raises(DriverError, match="cannot open"):
        arun(SerialChassis(CFG, port=str(tmp_path / "nothing-here")).connect())


def test_version_mismatch_fails_loudly():
    e = FirmwareEmulator(CFG, protocol_version=2).start()
    try:
        ch = SerialChassis(CFG, port=e.port)
        with pytest.raises(DriverError, match="protocol version 2, this host speaks 1"):
            arun(ch.connect())
        assert ch.link_state is LinkState.FAULT  # the board answers, but must not be driven
        assert not board_msgs(e, fp.SetWheelSpeeds)
    finally:
        e.close()


def test_silent_board_times_out_the_handshake(emu):
    emu.go_silent(True)
    with pytest.raises(DriverError, match="no answer to HELLO"):
        arun(SerialChassis(CFG, port=emu.port).connect())
    assert len(board_msgs(emu, fp.Hello)) >= 3  # it asked more than once


# Link loss and reconnection  --------------------------------------------------------------------

def test_silence_is_link_loss_and_the_link_comes_back(emu):
    async def main():
        ch = SerialChassis(CFG, port=emu.port)
        await ch.connect()
        emu.go_silent(True)
        await until(lambda: ch.link_state is not LinkState.READY, 5.0, "link loss")
        t_lost = emu.t_board
        reason = ch.last_error
        refused = not ch.send_wheel_speeds([1.0, 1.0, 1.0, 1.0])
        await asyncio.sleep(0.3)
        emu.go_silent(False)
        await until(lambda: ch.link_state is LinkState.READY, 10.0, "reconnection")
        ok = ch.send_wheel_speeds([1.0, 1.0, 1.0, 1.0])
        await asyncio.sleep(0.05)
        await ch.close()
        return ch, t_lost, refused, ok, reason

    ch, t_lost, refused, ok, reason = arun(main())
    assert refused and ok
    assert ch.stats["link_losses"] == 1 and ch.stats["reconnects"] == 1
    assert "no encoder report" in reason or "reports stopped" in reason
    hellos = [t for t, _ in board_msgs(emu, fp.Hello)]
    cmds = [t for t, _ in board_msgs(emu, fp.SetWheelSpeeds)]
    # while down: a best-effort STOP and HELLOs only, no speed command before the new handshake
    assert not [t for t in cmds if t_lost <= t < hellos[-1]]
    assert any(t >= t_lost for t, _ in board_msgs(emu, fp.Stop))


def test_unplug_and_replug_reconnects_and_recovers_the_motion(emu):
    """The board does not reboot: the ticks turned during the outage reach the odometry."""
    async def main():
        ch = SerialChassis(CFG, port=emu.port)
        q = ch.odometry_queue(maxsize=2000)
        await ch.connect()
        await drive(ch, [5.0, 5.0, 5.0, 5.0], 0.3)
        emu.vanish()  # the wheels keep turning until the board's watchdog stops them
        await until(lambda: ch.link_state is LinkState.LOST, 5.0, "link loss")
        await asyncio.sleep(0.8)
        assert ch.stats.get("connect_attempts", 0) >= 2  # kept trying while the port was gone
        emu.reappear(reboot=False)
        await until(lambda: ch.link_state is LinkState.READY, 10.0, "reconnection")
        await asyncio.sleep(0.2)
        samples = drain(q)
        await ch.close()
        return ch, samples

    ch, samples = arun(main())
    assert ch.stats.get("board_resets", 0) == 0
    for a, th in zip(samples[-1].angles, emu.board.theta):
        assert abs(a - th) <= 1.01 * TICK  # nothing lost across the outage
    assert max(s.dt for s in samples) > 0.5  # one sample spans the outage
    assert len(emu.events("hello")) == 2


def test_board_reboot_under_open_port_rehandshakes_with_continuous_angles(emu):
    async def main():
        ch = SerialChassis(CFG, port=emu.port)
        q = ch.odometry_queue(maxsize=2000)
        await ch.connect()
        await drive(ch, [5.0, 5.0, 5.0, 5.0], 0.3)
        ch.stop()
        await asyncio.sleep(0.4)
        before = drain(q)[-1].angles
        emu.reboot(t0_us=123)
        await until(lambda: len(emu.events("hello")) == 2 and ch.link_state is LinkState.READY, 10.0,
                    "the new handshake")
        await drive(ch, [2.0, 2.0, 2.0, 2.0], 0.3)
        ch.stop()
        await asyncio.sleep(0.3)
        after = drain(q)
        await ch.close()
        return ch, before, after

    ch, before, after = arun(main())
    assert ch.stats["link_losses"] == 1
    assert all(s.angles[0] >= before[0] - TICK for s in after)  # no jump back to the board's zero
    assert after[-1].angles[0] > before[0] + 0.3


def test_reads_never_run_on_the_event_loop_thread(emu, monkeypatch):
    readers = set()
    real_read = serial.Serial.read

    def spy(self, size=1):
        readers.add(threading.get_ident())
        return real_read(self, size)

    monkeypatch.setattr(serial.Serial, "read", spy)
    emu.go_silent(True)  # a board that never answers: a blocking read would freeze the loop

    async def main():
        ticks = 0

        async def ticker():
            nonlocal ticks
            while True:
                await asyncio.sleep(0.01)
                ticks += 1

        t = asyncio.ensure_future(ticker())
        with pytest.raises(DriverError):
            await SerialChassis(CFG, port=emu.port).connect()
        t.cancel()
        return threading.get_ident(), ticks

    loop_thread, ticks = arun(main())
    assert readers and loop_thread not in readers
    assert ticks >= 20  # the loop kept running through a 1 s handshake timeout


def test_odometry_queue_merges_the_oldest_when_full_and_loses_no_tick(emu):
    async def main():
        ch = SerialChassis(CFG, port=emu.port)
        q = ch.odometry_queue(maxsize=5)
        full = ch.odometry_queue(maxsize=10000)
        await ch.connect()
        await asyncio.sleep(0.3)
        got, everything = drain(q), drain(full)
        await ch.close()
        return ch, got, everything

    ch, got, everything = arun(main())
    assert len(got) == 5 and ch.stats["odometry_coalesced"] > 10
    assert all(b.t_board > a.t_board for a, b in zip(got, got[1:]))
    # the first sample spans everything merged into it: the five cover what the full queue saw
    assert got[-1].angles == everything[-1].angles and got[-1].t_board == everything[-1].t_board
    assert sum(o.dt for o in got) == pytest.approx(sum(o.dt for o in everything), abs=1e-9)


# The bench tool on the emulator  ----------------------------------------------------------------

def test_bench_tool_on_the_emulator_passes_its_own_checks(capsys):
    parser = argparse.ArgumentParser()
    cli_chassis.register(parser.add_subparsers())
    args = parser.parse_args(["chassis", "--emulate", "--duration", "0.3", "--motion", "--hold", "0.4", "--json"])
    rc = args.func(args)
    report = json.loads(capsys.readouterr().out)
    assert rc == (0 if report["ok"] else 1)
    assert report["board"]["ticks_per_rev"] == 1320
    assert report["odometry_hz"] == pytest.approx(100.0, rel=0.05)  # board clock, not host timing
    assert [w["wheel"] for w in report["motion"]] == ["FL", "FR", "RL", "RR"]
    assert all(w["ok"] and abs(w["error_pct"]) < 5.0 for w in report["motion"])
    # the tool saw the watchdog trip and the wheels stop; its host-clock timing is judged on the
    # bench (tests/hil), the 250 ms rule on the emulator's clock (test_hung_control_loop_...)
    assert math.isfinite(report["watchdog"]["trip_s"]) and math.isfinite(report["watchdog"]["stopped_s"])


def test_bench_tool_names_a_missing_port(tmp_path):
    parser = argparse.ArgumentParser()
    cli_chassis.register(parser.add_subparsers())
    args = parser.parse_args(["chassis", "--port", str(tmp_path / "absent"), "--duration", "0"])
    with pytest.raises(DriverError, match="absent: cannot open"):
        args.func(args)


# The loopback backend on the simulated clock  ---------------------------------------------------

def sim_drive(ch: LoopbackChassis, wheels, seconds: float, step: float = 0.02):
    out = []
    for _ in range(int(round(seconds / step))):
        ch.send_wheel_speeds(wheels)
        out += ch.advance(step)
    return out


def test_loopback_odometry_is_the_boards_shafts_on_the_simulated_clock():
    board = BoardModel(CFG)
    ch = LoopbackChassis(board, CFG)
    ch.connect_now()
    samples = sim_drive(ch, [4.0, -4.0, 2.0, 0.0], 1.0)
    assert len(samples) == 99  # a report every 10 ms; the first sets the baseline
    for a, th in zip(samples[-1].angles, board.theta):
        assert abs(a - th) <= 1.01 * TICK
    # the simulation has one clock: sample times are the board's sampling instants
    assert all(s.t == pytest.approx(s.t_board, abs=1e-9) for s in samples)
    assert [round(s.t_board, 6) for s in samples[:3]] == [0.02, 0.03, 0.04]


def test_loopback_refuses_a_board_of_another_protocol_version():
    ch = LoopbackChassis(BoardModel(CFG, protocol_version=2), CFG)
    with pytest.raises(DriverError, match="protocol version 2, this host speaks 1"):
        ch.connect_now()
    assert ch.link_state is LinkState.FAULT and not ch.send_wheel_speeds([1.0, 1.0, 1.0, 1.0])


def test_loopback_rehandshakes_after_a_board_reboot_with_continuous_angles():
    board = BoardModel(CFG)
    ch = LoopbackChassis(board, CFG)
    ch.connect_now()
    before = sim_drive(ch, [5.0, 5.0, 5.0, 5.0], 0.5)
    board.reboot(t0_us=123)  # the board forgets the session; its clock and counters restart
    after = []
    for _ in range(25):
        ch.send_wheel_speeds([5.0, 5.0, 5.0, 5.0])
        after += ch.advance(0.02)
    assert ch.link_state is LinkState.READY
    assert ch.stats["link_losses"] == 1 and ch.stats["reconnects"] == 1 and ch.stats["board_resets"] == 1
    assert ch.reconnects == 1
    assert all(s.angles[0] >= before[-1].angles[0] - TICK for s in after)  # no jump back to the board's zero
    assert after[-1].angles[0] > before[-1].angles[0] + 1.0


def test_the_reader_leaves_routine_batches_for_the_next_poll_and_wakes_the_loop_for_the_rest():
    """The board ACKs every speed command, reports the encoders a hundred times a second and its
    STATUS ten times: the reader thread leaves batches of only those in the inbox for the
    consumer's next poll, and wakes the loop (one drain) for anything else (a NACK), when the line goes quiet, when the oldest has
    waited MAX_HOLD or MAX_HELD_BATCHES are waiting, and for the ACK of the STOP that ``close``
    waits for. Every batch keeps its receive time and its place in the order."""
    from drivers.chassis import serial_chassis

    ch = SerialChassis(CFG, port="loop://")
    ack = [fp.Ack(ref_id=fp.SetWheelSpeeds.MSG_ID, ref_seq=k, seq=k) for k in range(3)]
    report = fp.EncoderReport(t_us=1000, ticks=(1, 2, 3, 4), seq=9)
    status = fp.Status(battery_mv=12000, motor_faults=0, flags=0, rx_errors=0, seq=10)
    nack = fp.Nack(ref_id=fp.SetWheelSpeeds.MSG_ID, ref_seq=1, reason=fp.NackReason.NO_SESSION, seq=11)
    clock = [100.0]

    class Time:  # the reader's clock: advanced by hand, so no test outcome depends on the machine's speed
        @staticmethod
        def monotonic():
            clock[0] += 0.001
            return clock[0]

    class Line:  # what pyserial's read gives: one chunk per read, b"" for a read that timed out
        in_waiting = 0

        def __init__(self, chunks):
            self.chunks = list(chunks)

        def read(self, n):
            if not self.chunks:
                stop.set()
                return b""
            chunk = self.chunks.pop(0)
            if chunk is None:  # a pause on the line of longer than MAX_HOLD, with bytes after it
                clock[0] += MAX_HOLD
                chunk = self.chunks.pop(0)
            return chunk

    class Loop:
        def __init__(self):
            self.calls = []

        def call_soon_threadsafe(self, fn, *args):
            self.calls.append((fn.__name__, args, [m for _, _, msgs in ch._inbox for m in msgs]))

    def run(chunks):
        ch._loop = Loop()
        ch._inbox.clear()
        ch._drain_posted = False
        stop.clear()
        ch._read_loop(Line(chunks), 1, stop)
        return ch._loop.calls

    from drivers.chassis.serial_chassis import MAX_HELD_BATCHES, MAX_HOLD

    saved = serial_chassis.time
    serial_chassis.time = Time
    try:
        stop = threading.Event()
        calls = run([fp.encode(ack[0]), fp.encode(report), fp.encode(ack[1]), fp.encode(report)])
        # all routine: no wake-up until the line went quiet (the end of the chunks), then one for all
        assert [(name, seen) for name, _, seen in calls] == [("_drain", [ack[0], report, ack[1], report])]
        times = [t for _, t, _ in ch._inbox]
        assert times == sorted(times) and len(set(times)) == 4  # each batch keeps its receive time
        calls = run([fp.encode(ack[0]), fp.encode(report), b"", fp.encode(ack[1])])
        assert [(name, seen) for name, _, seen in calls] == [("_drain", [ack[0], report])]  # the quiet line let them go
        calls = run([fp.encode(report), fp.encode(status), fp.encode(nack), fp.encode(ack[2])])
        assert [(name, seen) for name, _, seen in calls] == [("_drain", [report, status, nack])]  # a NACK at once
        calls = run([fp.encode(report), None, fp.encode(report)])
        assert [(name, seen) for name, _, seen in calls] == [("_drain", [report, report])]  # waited MAX_HOLD
        ch._stop_ack = (0, None)  # while close() waits for the STOP's ACK, ACKs are not held
        assert [name for name, _, _ in run([fp.encode(ack[0])])] == ["_drain"]
        ch._stop_ack = None
        many = [fp.encode(fp.Ack(ref_id=2, ref_seq=k % 256, seq=k % 256)) for k in range(MAX_HELD_BATCHES + 2)]
        calls = run(many)  # one wake-up: a drain on its way takes what comes meanwhile
        assert [(name, len(seen)) for name, _, seen in calls] == [("_drain", MAX_HELD_BATCHES + 1)]
    finally:
        serial_chassis.time = saved


def test_a_drain_handles_the_batches_in_order_as_if_posted_one_by_one_and_survives_a_bad_one():
    """``_drain`` is ``_on_messages`` per batch, in order, each with its own generation and receive
    time; a batch that raises is reported to the loop's exception handler and the rest go on (a
    poll runs inside the control tick, which must not end with it)."""
    seen, reported = [], []
    ch = SerialChassis(CFG, port="loop://")

    def on_messages(gen, t_rx, msgs):
        if msgs == ["bad"]:
            raise ValueError("bad batch")
        seen.append((gen, t_rx, msgs))

    class Loop:
        def call_exception_handler(self, context):
            reported.append(context["exception"])

    ch._on_messages, ch._loop = on_messages, Loop()
    ch._inbox.extend([(7, 1.0, ["a"]), (7, 2.0, ["bad"]), (8, 3.0, ["b", "c"])])
    ch._drain_posted = True
    ch.poll()  # not monitoring: the drain alone
    assert seen == [(7, 1.0, ["a"]), (8, 3.0, ["b", "c"])] and not ch._inbox and not ch._drain_posted
    assert [str(e) for e in reported] == ["bad batch"]


def test_a_poll_looks_at_the_link_and_pushes_the_monitors_timer_back():
    """While the link is monitored, ``poll`` is a look (it returns the loss at once) and moves the
    fallback look a tick and a half away: a consumer polling every tick is never overtaken by it.
    Polls closer than half a tick to the last look do not look again."""
    ch = SerialChassis(CFG, port="loop://")
    ch._write = lambda data: True

    async def scenario():
        loop = ch._loop = asyncio.get_running_loop()
        s = ch._session
        s.ready, s.lost_reason, s.last_report_rx = True, None, time.monotonic() + 3600.0
        ch._last_tx = time.monotonic() + 3600.0
        task = asyncio.ensure_future(ch._monitor())
        await asyncio.sleep(0)
        t0 = loop.time()
        ch.poll()
        (timer,) = [h for h in loop._scheduled if not h.cancelled() and getattr(h._callback, "__name__", "") == "_look"]
        assert timer.when() >= t0 + 1.5 * ch._look_tick
        s.lose("the board lost the session (reset?)")
        ch.poll()  # half a tick after the last look at the earliest: this one does not look
        assert not ch._lost.done() and not timer.cancelled()
        ch._look_again = 0.0  # (as if half a tick had passed)
        ch.poll()
        assert ch._lost.done()  # this poll's look found it, not a timer
        assert await asyncio.wait_for(task, 5.0) == "the board lost the session (reset?)"
        return [h for h in loop._scheduled if not h.cancelled() and getattr(h._callback, "__name__", "") == "_look"]

    assert arun(scenario()) == []


def test_the_monitors_own_look_handles_the_held_batches_before_judging_the_link():
    """A consumer that never polls: the timer's look empties the inbox first, so reports the
    reader holds are not taken for silence."""
    ch = SerialChassis(CFG, port="loop://")
    ch._write = lambda data: True

    async def scenario():
        ch._loop = asyncio.get_running_loop()
        s = ch._session
        s.ready, s.lost_reason, s.last_report_rx = True, None, time.monotonic() - 10.0  # silent but for the inbox
        ch._last_tx = time.monotonic() + 3600.0

        def on_messages(gen, t_rx, msgs):
            s.last_report_rx = time.monotonic() + 3600.0

        ch._on_messages = on_messages
        ch._inbox.append((ch._gen, time.monotonic(), ["report"]))
        task = asyncio.ensure_future(ch._monitor())
        await asyncio.sleep(0)
        ch._look()  # what its timer calls
        healthy = not ch._lost.done() and not ch._inbox
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        return healthy

    assert arun(scenario())


def test_the_link_monitor_returns_the_loss_sends_heartbeats_and_stops_its_timer_when_cancelled():
    """The monitor looks every tick from a timer callback: it returns the first loss reason
    (a session marked lost, then silence), sends a heartbeat when nothing went out for
    HEARTBEAT_PERIOD, passes an error on like the task it was, and leaves no timer behind."""
    from drivers.chassis.session import HEARTBEAT_PERIOD

    ch = SerialChassis(CFG, port="loop://")
    sent = []
    ch._write = lambda data: sent.append(data) or True

    async def scenario():
        loop = ch._loop = asyncio.get_running_loop()
        s = ch._session
        s.ready, s.lost_reason, s.last_report_rx = True, None, time.monotonic() + 3600.0
        ch._last_tx = time.monotonic() - 2 * HEARTBEAT_PERIOD
        task = asyncio.ensure_future(ch._monitor())
        await until(lambda: sent, what="a heartbeat")
        assert not task.done()
        s.lose("the board lost the session (reset?)")
        assert await asyncio.wait_for(task, 5.0) == "the board lost the session (reset?)"
        s.lost_reason, s.last_report_rx = None, time.monotonic() - 10.0
        assert (await asyncio.wait_for(ch._monitor(), 5.0)).startswith("no encoder report for")
        s.last_report_rx = time.monotonic() + 3600.0

        def broken(data):
            raise RuntimeError("boom")

        ch._write, ch._last_tx = broken, -math.inf
        with pytest.raises(RuntimeError, match="boom"):
            await asyncio.wait_for(ch._monitor(), 5.0)
        ch._write = lambda data: True
        task = asyncio.ensure_future(ch._monitor())
        await asyncio.sleep(0.05)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        return [h for h in loop._scheduled if not h.cancelled() and getattr(h._callback, "__name__", "") == "_look"]

    assert arun(scenario()) == []
