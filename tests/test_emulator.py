"""The board emulator: firmware rules and motor physics on its own clock, then the pty and its faults.

Model tests drive ``BoardModel`` with ``step(dt)``: deterministic, no threads. The watchdog
assertions are measured on the board's clock, as the firmware would see them.
"""

from __future__ import annotations

import math
import os
import time

import pytest
import serial

import firmware_protocol as fp
from drivers.chassis.emulator import BoardModel, FirmwareEmulator, LineFaults
from robot.config import ChassisConfig
from robot.control.kinematics import make_kinematics

CFG = ChassisConfig()


def board(**kw) -> BoardModel:
    b = BoardModel(CFG, **kw)
    b.handle(fp.Hello(0, 1))
    b.take_outbox()
    b.sent = []  # everything the board transmitted since, decoded
    return b


def replies(b: BoardModel):
    """Messages the board transmitted since the last call (all of them stay in ``b.sent``)."""
    new = fp.Decoder().feed(b.take_outbox())
    if hasattr(b, "sent"):
        b.sent += new
    return new


def command(b: BoardModel, speeds, seq=0):
    b.handle(fp.SetWheelSpeeds.from_rad_s(speeds, seq=seq))
    return [m for m in replies(b) if isinstance(m, (fp.Ack, fp.Nack))]


def run(b: BoardModel, speeds, seconds: float, period: float = 0.05):
    """Command the same speeds afresh every period, as a live control loop does."""
    for i in range(int(round(seconds / period))):
        command(b, speeds, seq=i & 0xFF)
        b.step(period)
    replies(b)


def sent(b: BoardModel, kind):
    replies(b)
    return [m for m in b.sent if isinstance(m, kind)]


def events(b: BoardModel, kind: str):
    return [e for e in b.events if e[1] == kind]


# Firmware rules  --------------------------------------------------------------------------------

def test_hello_reply_describes_the_board():
    b = BoardModel(CFG)
    b.handle(fp.Hello(0, 0xABCDEF01, seq=3))
    (reply,) = [m for m in replies(b) if isinstance(m, fp.HelloReply)]
    assert reply.nonce == 0xABCDEF01
    assert reply.ticks_per_rev == CFG.ticks_per_rev
    assert reply.max_speed_mrad_s == 20000 and reply.max_accel_mrad_s2 == 40000
    assert reply.watchdog_ms == 200 and reply.report_period_us == 10000


def test_speed_commands_before_hello_are_refused():
    b = BoardModel(CFG)
    b.handle(fp.SetWheelSpeeds.from_rad_s([5, 5, 5, 5], seq=7))
    nacks = [m for m in replies(b) if isinstance(m, fp.Nack)]
    assert [(n.ref_seq, n.reason) for n in nacks] == [(7, fp.NackReason.NO_SESSION)]
    b.step(0.3)
    assert b.omega == [0.0] * 4 and b.flags & fp.StatusFlag.NO_SESSION


def test_in_range_command_is_acked_with_its_seq():
    b = board()
    assert [(m.ref_id, m.ref_seq) for m in command(b, [1, 2, -3, 4], seq=42)] == [(0x02, 42)]
    assert isinstance(command(b, [1, 2, -3, 4], seq=43)[0], fp.Ack)


def test_out_of_range_command_is_scaled_uniformly_and_nacked():
    b = board()
    (nack,) = command(b, [30.0, 15.0, -10.0, 0.0], seq=5)
    assert (nack.reason, nack.detail, nack.ref_seq) == (fp.NackReason.CLAMPED, 0b0001, 5)
    assert b.target == pytest.approx([20.0, 10.0, -20.0 / 3.0, 0.0])
    assert b.flags & fp.StatusFlag.CLAMPED
    assert isinstance(command(b, [1, 1, 1, 1])[0], fp.Ack)
    assert not b.flags & fp.StatusFlag.CLAMPED


def test_clamping_keeps_the_direction_of_travel():
    kin = make_kinematics(CFG)
    wanted = kin.inverse(1.2, 0.5, 0.8)  # 57 rad/s peak: far beyond the limit
    b = board()
    command(b, wanted)
    t_wanted, t_applied = kin.forward(wanted), kin.forward(b.target)
    assert max(abs(v) for v in b.target) == pytest.approx(20.0)
    # equal up to the mrad/s quantisation of the wire
    assert t_applied / math.hypot(*t_applied) == pytest.approx(t_wanted / math.hypot(*t_wanted), abs=1e-4)


def test_acceleration_limit_ramps_all_wheels_along_one_line():
    b = board(motor_tau=0.0)
    run(b, [10.0, -5.0, 5.0, 0.0], 0.1)  # 40 rad/s^2 * 0.1 s = 4 rad/s on the fastest wheel
    assert b.setpoint == pytest.approx([4.0, -2.0, 2.0, 0.0], abs=1e-9)
    run(b, [10.0, -5.0, 5.0, 0.0], 0.2)
    assert b.setpoint == pytest.approx([10.0, -5.0, 5.0, 0.0])


def test_first_order_motor_response():
    b = board(max_wheel_accel=1e6, motor_tau=0.05)
    run(b, [10.0, 10.0, 10.0, 10.0], 0.05)
    assert b.omega[0] == pytest.approx(10.0 * (1 - math.exp(-1)), rel=0.03)
    run(b, [10.0, 10.0, 10.0, 10.0], 0.5)
    assert b.omega[0] == pytest.approx(10.0, rel=1e-3)


def test_watchdog_stops_wheels_within_250ms_of_the_last_command():
    """Total host silence (no frame at all) after a speed command: by 250 ms the board has
    tripped, reported it, and the wheels are ramping down; they are still one ramp later."""
    b = board()
    run(b, [5.0, 5.0, 5.0, 5.0], 0.5)
    command(b, [5.0, 5.0, 5.0, 5.0])
    t_cmd = b.t_board
    assert b.omega[0] > 4.9  # up to speed: there is something to stop
    b.step(0.25)
    (trip,) = events(b, "watchdog")
    assert 0.2 - 1e-9 <= trip[0] - t_cmd <= 0.25
    assert b.target == [0.0] * 4 and b.flags & fp.StatusFlag.WATCHDOG
    assert any(m.flags & fp.StatusFlag.WATCHDOG for m in sent(b, fp.Status))  # reported, not just set
    # ramping down at the accel limit since the trip (40 rad/s^2 for >= 49 ms: <= 3.04 rad/s now)
    assert max(b.setpoint) <= 5.0 - 40.0 * (t_cmd + 0.25 - trip[0]) + 1e-9 and max(b.omega) < 4.9
    b.step(5.0 / 40.0 + 5 * b.motor_tau)  # one full ramp plus five motor time constants
    assert b.setpoint == [0.0] * 4
    assert max(abs(w) for w in b.omega) < 0.01


def test_heartbeats_do_not_keep_wheels_turning():
    """Command freshness, not link liveness: a hung control loop with a live heartbeat still stops."""
    b = board()
    command(b, [5.0, 5.0, 5.0, 5.0])
    t_cmd = b.t_board
    for _ in range(12):
        b.step(0.05)
        b.handle(fp.Heartbeat())
    (trip,) = events(b, "watchdog")
    assert trip[0] - t_cmd <= 0.25
    assert not b.flags & fp.StatusFlag.HOST_SILENT  # the host is there, it just stopped commanding
    assert max(abs(w) for w in b.omega) < 0.01


def test_fresh_commands_keep_wheels_turning():
    b = board()
    for i in range(10):
        command(b, [5.0, 5.0, 5.0, 5.0], seq=i)
        b.step(0.15)
    assert events(b, "watchdog") == []
    assert b.omega[0] == pytest.approx(5.0, rel=1e-3)


def test_host_silence_is_flagged_and_a_new_command_clears_the_watchdog():
    b = board()
    command(b, [2.0, 2.0, 2.0, 2.0])
    b.step(0.5)
    assert b.flags & fp.StatusFlag.HOST_SILENT and b.flags & fp.StatusFlag.WATCHDOG
    command(b, [2.0, 2.0, 2.0, 2.0])
    assert not b.flags & (fp.StatusFlag.HOST_SILENT | fp.StatusFlag.WATCHDOG)


def test_flag_changes_are_reported_at_once():
    b = board()
    command(b, [2.0, 2.0, 2.0, 2.0])
    b.take_outbox()
    b.step(0.205)
    statuses = [m for m in replies(b) if isinstance(m, fp.Status)]
    assert any(s.flags & fp.StatusFlag.WATCHDOG for s in statuses)


def test_stop_is_accepted_without_a_session_and_ramps_down():
    b = board(motor_tau=0.0)
    run(b, [8.0, 8.0, 8.0, 8.0], 0.3)
    b.session = False  # even a board that lost the session obeys STOP
    b.handle(fp.Stop(seq=9))
    assert [(m.ref_id, m.ref_seq) for m in replies(b) if isinstance(m, fp.Ack)] == [(0x03, 9)]
    b.step(0.1)
    assert b.setpoint[0] == pytest.approx(4.0)  # 8 - 40 * 0.1
    b.step(0.2)
    assert b.setpoint == [0.0] * 4


def test_estop_refuses_commands_and_holds_zero():
    b = board()
    run(b, [5.0] * 4, 0.3)
    b.set_estop(True)
    assert b.setpoint == [0.0] * 4  # at once, not a ramp (the watchdog would ramp)
    (nack,) = command(b, [5.0] * 4)
    assert nack.reason == fp.NackReason.ESTOP
    b.step(0.3)
    assert b.setpoint == [0.0] * 4 and max(abs(w) for w in b.omega) < 0.01
    b.set_estop(False)
    assert isinstance(command(b, [1.0] * 4)[0], fp.Ack)


def test_motor_fault_stops_all_wheels_and_is_reported():
    b = board()
    run(b, [5.0] * 4, 0.3)
    b.set_motor_fault(2, True)
    assert b.target == [0.0] * 4 and not events(b, "watchdog")  # the fault, not the watchdog
    (st,) = [m for m in replies(b) if isinstance(m, fp.Status)][-1:]
    assert st.motor_faults == 0b0100
    (nack,) = command(b, [5.0] * 4)
    assert (nack.reason, nack.detail) == (fp.NackReason.MOTOR_FAULT, 0b0100)
    b.step(0.5)
    assert b.target == [0.0] * 4 and max(abs(w) for w in b.omega) < 0.01


def test_unknown_and_foreign_version_frames_are_nacked():
    b = board()
    b.handle_bytes(fp.encode_frame(0x42, 4, b"\x01\x02"))
    b.handle_bytes(fp.encode(fp.Stop(seq=5), version=2))
    nacks = [m for m in replies(b) if isinstance(m, fp.Nack)]
    assert [(n.ref_id, n.reason, n.detail) for n in nacks] == [
        (0x42, fp.NackReason.UNKNOWN_MESSAGE, 0), (0, fp.NackReason.BAD_VERSION, 2)]


def test_rx_errors_are_reported_in_status():
    b = board()
    b.handle_bytes(b"\x00\x05\x01\x00" + fp.encode(fp.Stop(seq=1))[:-3] + b"\x00")
    b.step(0.1)
    st = [m for m in replies(b) if isinstance(m, fp.Status)][-1]
    assert st.rx_errors == 2


# Physics and reports  ---------------------------------------------------------------------------

def test_reports_come_at_100hz_with_quantised_cumulative_ticks():
    b = board(motor_tau=0.02)
    run(b, [3.0, -3.0, 1.5, 0.0], 1.0)
    reports = sent(b, fp.EncoderReport)
    assert len(reports) == 100
    assert reports[0].t_us == 10000
    assert all(r2.t_us - r1.t_us == 10000 for r1, r2 in zip(reports, reports[1:]))
    k = CFG.ticks_per_rev / (2 * math.pi)
    for th, t in zip(b.theta, reports[-1].ticks):
        assert t == math.floor(th * k)  # quantised, never rounded up
    assert reports[-1].ticks[0] > 0 > reports[-1].ticks[1] and reports[-1].ticks[3] == 0


def test_clock_and_ticks_wrap_like_the_hardware():
    b = board(t0_us=2 ** 32 - 25_000, tick_offset=(2 ** 31 - 100, -(2 ** 31) + 100, 0, 0), motor_tau=0.0,
              max_wheel_accel=1e6)
    run(b, [10.0, -10.0, 0.0, 0.0], 0.1)  # 1 rad = 210 ticks: past the int32 limit both ways
    reports = sent(b, fp.EncoderReport)
    stamps = [r.t_us for r in reports]
    assert stamps[0] > 2 ** 32 - 30_000 and stamps[-1] < 100_000  # wrapped through zero
    assert reports[-1].ticks[0] < 0 < reports[-1].ticks[1]  # int32 wrapped both ways


def test_ground_truth_follows_the_true_radius_not_the_nominal_one():
    kin = make_kinematics(CFG)
    b = board(radius_error=(0.02, 0.02, 0.02, 0.02))
    w = kin.inverse(0.3, 0.0, 0.0)
    for i in range(40):
        command(b, w, seq=i)
        b.step(0.05)
    nominal = sum(b.theta) / 4 * CFG.wheel_radius  # what the encoders say
    x, y, phi = b.pose
    assert x == pytest.approx(1.02 * nominal, rel=1e-6)
    assert y == pytest.approx(0.0, abs=1e-9) and phi == pytest.approx(0.0, abs=1e-9)


def test_slip_on_the_right_wheels_turns_the_robot_right():
    b = board(slip=(0.0, 0.1, 0.0, 0.1))
    for i in range(40):
        command(b, [10.0] * 4, seq=i)
        b.step(0.05)
    x, y, phi = b.pose
    assert phi < -0.05 and y < 0.0 and x > 0.4


def test_sideways_command_moves_the_truth_sideways():
    kin = make_kinematics(CFG)
    b = board()
    for i in range(20):
        command(b, kin.inverse(0.0, 0.2, 0.0), seq=i)
        b.step(0.05)
    x, y, phi = b.pose
    assert y > 0.1 and abs(x) < 1e-9 and abs(phi) < 1e-9


def test_same_inputs_same_outputs_in_sim_clock():
    runs = []
    for _ in range(2):
        b = board(slip_noise=0.05, seed=11)
        for i in range(30):
            command(b, [4.0, 5.0, 6.0, 7.0], seq=i)
            b.step(0.033)
        runs.append((b.pose, b.ticks(), b.t_us_wire))
    assert runs[0] == runs[1]


def test_reboot_resets_session_clock_and_counters():
    b = board()
    command(b, [5.0] * 4)
    b.step(0.5)
    b.reboot(t0_us=1000)
    assert not b.session and b.flags & fp.StatusFlag.NO_SESSION
    assert b.t_us_wire == 1000 and b.ticks() == (0, 0, 0, 0)


# The emulator on a real pty  --------------------------------------------------------------------

def open_port(emu: FirmwareEmulator) -> serial.Serial:
    s = serial.serial_for_url(emu.port, baudrate=115200, timeout=0.02)
    s.reset_input_buffer()
    return s


def read_until(s, dec, pred, timeout=5.0):
    got = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        got += dec.feed(s.read(4096))
        if pred(got):
            return got
    raise AssertionError(f"timed out; got {len(got)} messages: {got[-5:]}")


def test_emulator_speaks_the_protocol_over_a_pty():
    with FirmwareEmulator(CFG) as emu:
        assert os.path.realpath(emu.port).startswith("/dev/pts/")
        s = open_port(emu)
        dec = fp.Decoder()
        s.write(fp.encode(fp.Hello(0, 77, seq=0)) + fp.encode(fp.SetWheelSpeeds.from_rad_s([3, 3, 3, 3], seq=1)))
        got = read_until(s, dec, lambda g: sum(isinstance(m, fp.EncoderReport) for m in g) >= 20)
        assert any(isinstance(m, fp.HelloReply) and m.nonce == 77 for m in got)
        assert [(m.ref_id, m.ref_seq) for m in got if isinstance(m, fp.Ack)] == [(0x02, 1)]
        assert dec.stats.dropped_frames == 0
        # The wheel turned up to the command: judged from the reports (board time), not from the
        # emulator's state when this thread reads it, which on a busy machine can be after the
        # command watchdog has stopped the wheel again.
        reports = [m for m in got if isinstance(m, fp.EncoderReport)]
        speeds = [(b.ticks[0] - a.ticks[0]) / CFG.ticks_per_rev * 2.0 * math.pi / ((b.t_us - a.t_us) * 1e-6)
                  for a, b in zip(reports, reports[1:]) if b.t_us > a.t_us]
        assert max(speeds) > 1.5  # (commanded 3 rad/s; a 10 ms report holds 6 or 7 ticks of it)
        s.close()


def test_over_the_wire_clamped_command_is_nacked_and_a_dead_host_is_stopped_by_the_watchdog():
    """A host process speaks raw bytes: one command beyond the speed limit (clamped, NACKed on the
    wire), fresh commands at 50 Hz, then it dies (port closed, not one more byte). Timed on the
    board's own clock."""
    with FirmwareEmulator(CFG) as emu:
        s = open_port(emu)
        dec = fp.Decoder()
        s.write(fp.encode(fp.Hello(0, 12, seq=0)))
        read_until(s, dec, lambda g: any(isinstance(m, fp.HelloReply) for m in g))
        s.write(fp.encode(fp.SetWheelSpeeds.from_rad_s([30.0, -15.0, 6.0, 0.0], seq=1)))
        got = read_until(s, dec, lambda g: any(isinstance(m, (fp.Ack, fp.Nack)) for m in g))
        (answer,) = [m for m in got if isinstance(m, (fp.Ack, fp.Nack))]
        assert isinstance(answer, fp.Nack)
        assert (answer.ref_id, answer.ref_seq, answer.reason, answer.detail) == (0x02, 1, fp.NackReason.CLAMPED, 0b0001)
        assert emu.board.target == pytest.approx([20.0, -10.0, 4.0, 0.0])  # applied, scaled as one
        for i in range(15):
            s.write(fp.encode(fp.SetWheelSpeeds.from_rad_s([4.0, 4.0, 4.0, 4.0], seq=2 + i)))
            time.sleep(0.02)
        s.close()  # the host process died
        deadline = time.monotonic() + 5.0
        while not emu.events("watchdog") and time.monotonic() < deadline:
            time.sleep(0.01)
        # a ramp from 4 rad/s (0.1 s) and the motor lag: waited for, a starved machine is slower
        deadline = time.monotonic() + 10.0
        while max(abs(w) for w in emu.true_wheel_speeds) >= 0.05 and time.monotonic() < deadline:
            time.sleep(0.01)
        last_cmd = max(t for t, m in emu.received() if isinstance(m, fp.SetWheelSpeeds))
        (trip,) = emu.events("watchdog")
        assert 0.2 - 1e-6 <= trip[0] - last_cmd <= 0.25
        assert max(abs(w) for w in emu.true_wheel_speeds) < 0.05


def test_sim_clock_reports_only_when_the_simulation_steps():
    with FirmwareEmulator(CFG, clock="sim") as emu:
        s = open_port(emu)
        dec = fp.Decoder()
        s.write(fp.encode(fp.Hello(0, 5)))
        read_until(s, dec, lambda g: any(isinstance(m, fp.HelloReply) for m in g))  # served without stepping
        time.sleep(0.1)
        assert not [m for m in dec.feed(s.read(4096)) if isinstance(m, fp.EncoderReport)]
        for _ in range(5):
            emu.step(0.01)
        got = read_until(s, dec, lambda g: sum(isinstance(m, fp.EncoderReport) for m in g) >= 5)
        stamps = [m.t_us for m in got if isinstance(m, fp.EncoderReport)]
        assert stamps == [10000, 20000, 30000, 40000, 50000]
        with pytest.raises(RuntimeError):
            FirmwareEmulator(CFG).step(0.01)
        s.close()


def test_corrupted_line_is_counted_and_never_accepted():
    faults = LineFaults(corrupt=0.01, drop=0.005, seed=3)
    with FirmwareEmulator(CFG, clock="sim", tx_faults=faults) as emu:
        s = open_port(emu)
        dec = fp.Decoder()
        for _ in range(300):
            emu.step(0.01)
        got = read_until(s, dec, lambda g: dec.stats.dropped_frames >= 20 and len(g) >= 150)
        reports = [m for m in got if isinstance(m, fp.EncoderReport)]
        # every accepted report is a true one: on the 10 ms grid, wheels still
        assert all(r.t_us % 10000 == 0 and r.ticks == (0, 0, 0, 0) for r in reports)
        assert faults.corrupted > 0 and faults.dropped > 0
        s.close()


def test_dropped_host_bytes_show_up_in_the_board_rx_errors():
    faults = LineFaults(drop=0.05, seed=4)
    with FirmwareEmulator(CFG, rx_faults=faults) as emu:
        s = open_port(emu)
        dec = fp.Decoder()
        for i in range(100):
            s.write(fp.encode(fp.Heartbeat(seq=i)))
        got = read_until(s, dec, lambda g: any(isinstance(m, fp.Status) and m.rx_errors > 0 for m in g))
        worst = max(m.rx_errors for m in got if isinstance(m, fp.Status))
        assert 0 < worst <= 100 - len([m for t, m in emu.received() if isinstance(m, fp.Heartbeat)]) + 5
        s.close()


def test_delayed_bytes_arrive_late_but_intact():
    with FirmwareEmulator(CFG, clock="sim", tx_faults=LineFaults(delay=0.3)) as emu:
        s = open_port(emu)
        dec = fp.Decoder()
        s.write(fp.encode(fp.Hello(0, 9)))
        early = dec.feed(s.read(4096)) + dec.feed(s.read(4096))  # up to ~40 ms: far less than the delay
        assert not any(isinstance(m, fp.HelloReply) for m in early)
        read_until(s, dec, lambda g: any(isinstance(m, fp.HelloReply) and m.nonce == 9 for m in g))
        s.close()


def test_silent_board_sends_nothing_but_still_listens():
    with FirmwareEmulator(CFG) as emu:
        s = open_port(emu)
        dec = fp.Decoder()
        read_until(s, dec, lambda g: any(isinstance(m, fp.EncoderReport) for m in g))
        emu.go_silent(True)
        time.sleep(0.05)
        s.reset_input_buffer()
        s.write(fp.encode(fp.Hello(0, 31)))
        time.sleep(0.3)
        assert dec.feed(s.read(4096)) == []
        assert any(isinstance(m, fp.Hello) and m.nonce == 31 for _, m in emu.received())
        emu.go_silent(False)
        read_until(s, dec, lambda g: any(isinstance(m, fp.EncoderReport) for m in g))
        s.close()


def test_vanish_and_reappear_behind_the_same_symlink(tmp_path):
    link = str(tmp_path / "motor-board")
    with FirmwareEmulator(CFG, link_path=link) as emu:
        s = open_port(emu)
        dec = fp.Decoder()
        s.write(fp.encode(fp.Hello(0, 1)))
        read_until(s, dec, lambda g: any(isinstance(m, fp.HelloReply) for m in g))
        emu.vanish()
        assert not os.path.lexists(link)
        with pytest.raises(serial.SerialException):
            for _ in range(100):
                s.read(100)  # the device is gone: reads fail instead of blocking forever
        s.close()
        emu.reappear()
        assert os.path.exists(link)
        s = open_port(emu)
        dec = fp.Decoder()
        got = read_until(s, dec, lambda g: any(isinstance(m, fp.Status) for m in g))
        st = [m for m in got if isinstance(m, fp.Status)][-1]
        assert st.flags & fp.StatusFlag.NO_SESSION  # it rebooted: a new handshake is needed
        assert [e[1] for e in emu.events() if e[1] in ("vanish", "reboot", "reappear")] == \
            ["vanish", "reboot", "reappear"]
        s.close()
