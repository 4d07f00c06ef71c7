"""Keyboard teleop: byte decoding, deadman timing at explicit times, limits, and a real pty."""

from __future__ import annotations

import asyncio
import math
import os
import signal
import sys
import termios
import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robot.app.teleop_terminal import CLEAR_LINE, NotATerminalError, TerminalKeyboard, fit_line, format_status
from robot.base.errors import RobotError
from robot.config import ControlConfig
from robot.control.teleop_keys import (
    BACK,
    FASTER,
    FORWARD,
    KEYS,
    LEFT,
    QUIT,
    RIGHT,
    SLOWER,
    STOP,
    TURN_LEFT,
    TURN_RIGHT,
    KeyDecoder,
    TeleopState,
)

UP, DOWN, RIGHT_ARROW, LEFT_ARROW = b"\x1b[A", b"\x1b[B", b"\x1b[C", b"\x1b[D"

# What a user's session sends: letters, both arrow encodings, a modified arrow, function keys.
SESSION = (b"w" + UP + b"a" + b"\x1bOD" + b"\x1b[1;5C" + b"\x1b[15~" + b"Q" + b"e" + b"\x1bOP"
           + b"\xc3\xb6" + b" " + b"+" + DOWN + b"-" + b"\x1b[[A" + b"s" + b"d" + b"x")
SESSION_KEYS = [FORWARD, FORWARD, LEFT, LEFT, RIGHT, TURN_LEFT, TURN_RIGHT, STOP, FASTER, BACK, SLOWER,
                BACK, RIGHT, QUIT]


def decode_chunks(chunks):
    dec = KeyDecoder()
    keys = []
    for chunk in chunks:
        keys += dec.feed(chunk, 0.0)
    return keys, dec


# Decoder  ------

def test_letters_any_case_and_control_keys():
    keys, dec = decode_chunks([b"wasdqeWASDQE x\x03\x04+=-_"])
    assert keys == [FORWARD, LEFT, BACK, RIGHT, TURN_LEFT, TURN_RIGHT] * 2 + [STOP, QUIT, QUIT, QUIT,
                                                                              FASTER, FASTER, SLOWER, SLOWER]
    assert dec.ignored == 0


def test_arrows_in_normal_application_and_modified_forms():
    keys, _ = decode_chunks([UP + DOWN + RIGHT_ARROW + LEFT_ARROW + b"\x1bOA\x1bOB\x1bOC\x1bOD" + b"\x1b[1;2A\x1b[1;5D"])
    assert keys == [FORWARD, BACK, RIGHT, LEFT] * 2 + [FORWARD, LEFT]


def test_function_keys_and_non_ascii_are_ignored_not_motion():
    # F5, Insert, F1 (SS3), Linux console F1 (ESC [ [ A: its 'A' must not become "left"), o-umlaut.
    keys, dec = decode_chunks([b"\x1b[15~\x1b[2~\x1bOP\x1b[[A\xc3\xb6"])
    assert keys == []
    assert dec.ignored == 5 + 4 + 3 + 4 + 2
    assert not dec.pending


def test_session_split_at_every_position_decodes_the_same():
    whole, _ = decode_chunks([SESSION])
    assert whole == SESSION_KEYS
    for cut in range(1, len(SESSION)):
        assert decode_chunks([SESSION[:cut], SESSION[cut:]])[0] == SESSION_KEYS, cut
    assert decode_chunks([SESSION[i:i + 1] for i in range(len(SESSION))])[0] == SESSION_KEYS


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=80), st.lists(st.integers(0, 80), max_size=6))
def test_any_bytes_any_split_same_keys_and_no_crash(data, cuts):
    bounds = sorted(set([0, len(data)] + [c for c in cuts if c < len(data)]))
    chunks = [data[a:b] for a, b in zip(bounds, bounds[1:])]
    whole, dec_whole = decode_chunks([data])
    split, dec_split = decode_chunks(chunks)
    assert whole == split
    assert set(whole) <= KEYS
    assert dec_whole.pending == dec_split.pending


def test_lone_esc_quits_after_the_timeout_only():
    dec = KeyDecoder(esc_timeout=0.1)
    assert dec.feed(b"w\x1b", 10.0) == [FORWARD]
    assert dec.pending and dec.deadline == pytest.approx(10.1)
    assert dec.expire(10.05) == []
    assert dec.expire(10.1) == [QUIT]
    assert not dec.pending and dec.deadline is None


def test_arrow_split_across_reads_is_an_arrow_not_esc():
    dec = KeyDecoder(esc_timeout=0.1)
    assert dec.feed(b"\x1b", 0.0) == []
    assert dec.feed(b"[", 0.02) == []
    # A started sequence never times out into keys: its rest may come late over ssh.
    assert dec.deadline is None and dec.expire(5.0) == []
    assert dec.feed(b"1;5", 5.1) == []
    assert dec.feed(b"D", 5.2) == [LEFT]


def test_esc_followed_by_a_key_and_double_esc():
    dec = KeyDecoder()
    assert dec.feed(b"\x1bw", 0.0) == [QUIT, FORWARD]  # Alt+w, or Esc typed just before w
    assert dec.feed(b"\x1b\x1b", 0.0) == [QUIT]  # the second may still start a sequence
    assert dec.feed(b"[B", 0.01) == [BACK]


def test_overlong_and_broken_sequences_are_dropped_whole():
    dec = KeyDecoder(max_sequence=16)
    # 40 parameter bytes then final 'A': dropped through the 'A', across reads too.
    assert dec.feed(b"\x1b[" + b"1" * 30, 0.0) == []
    assert dec.feed(b"1" * 10 + b"Aw", 0.0) == [FORWARD]
    # A control byte inside a CSI ends it; the byte itself is still read (Ctrl-C quits).
    assert dec.feed(b"\x1b[12\x03", 0.0) == [QUIT]
    assert not dec.pending


# Deadman and limits  ------

def make_state(**kw):
    return TeleopState.from_control(ControlConfig(max_speed=0.3, max_yaw_rate=1.0), **kw)


def hold_key(state, key, t0, duration, first_delay=0.5, rate=30.0):
    """Events of a held key as a terminal sends them: press, first repeat after a delay, then ~30 Hz."""
    times = [t0]
    t = t0 + first_delay
    while t <= t0 + duration:
        times.append(t)
        t += 1.0 / rate
    for t in times:
        state.press(key, t)
    return times[-1]


def test_held_key_drives_through_repeat_delay_and_stops_after_deadman():
    s = make_state(deadman=0.6)
    v = 0.5 * 0.3  # start at 50 % of max_speed
    last = hold_key(s, FORWARD, 1.0, 2.0, first_delay=0.55)
    for t in (1.0, 1.3, 1.54, 1.56, 2.0, 2.9, last + 0.59):
        assert s.twist(t) == (pytest.approx(v), 0.0, 0.0), t
    assert s.twist(last + 0.6) == (0.0, 0.0, 0.0)
    assert not s.active(last + 0.6)


def test_single_tap_without_repeat_stops_after_deadman():
    s = make_state(deadman=0.6)
    s.press(TURN_LEFT, 0.0)
    assert s.twist(0.59) == (0.0, 0.0, pytest.approx(0.5))
    assert s.twist(0.6) == (0.0, 0.0, 0.0)


def test_repeat_deadman_stops_sooner_once_repeating():
    s = make_state(deadman=0.6, repeat_deadman=0.2)
    s.press(RIGHT, 0.0)
    s.press(RIGHT, 0.5)  # first repeat: still the long deadman
    assert s.twist(1.05)[1] == pytest.approx(-0.15)
    last = hold_key(s, RIGHT, 0.5, 1.0, first_delay=1.0 / 30.0)
    assert s.twist(last + 0.19)[1] == pytest.approx(-0.15)
    assert s.twist(last + 0.2) == (0.0, 0.0, 0.0)


def test_space_stops_at_once_and_next_key_starts_afresh():
    s = make_state()
    hold_key(s, FORWARD, 0.0, 1.0)
    s.press(TURN_RIGHT, 1.0)
    s.press(STOP, 1.01)
    assert s.twist(1.01) == (0.0, 0.0, 0.0)
    s.press(BACK, 1.2)
    assert s.twist(1.2) == (pytest.approx(-0.15), 0.0, 0.0)


def test_opposite_key_brakes_then_reverses():
    s = make_state()
    s.press(FORWARD, 0.0)
    s.press(BACK, 0.1)
    assert s.twist(0.1) == (0.0, 0.0, 0.0)
    s.press(BACK, 0.6)  # its first auto-repeat
    assert s.twist(0.6)[0] == pytest.approx(-0.15)


def test_axes_combine_and_diagonal_respects_max_speed():
    s = make_state(start_step=10)
    s.press(FORWARD, 0.0)
    s.press(LEFT, 0.2)
    s.press(TURN_RIGHT, 0.3)
    vx, vy, wz = s.twist(0.4)
    assert math.hypot(vx, vy) == pytest.approx(0.3)
    assert vx == pytest.approx(vy) and vx > 0
    assert wz == pytest.approx(-1.0)
    assert s.twist(0.61) == (0.0, pytest.approx(0.3), pytest.approx(-1.0))  # forward's deadman expired


def test_speed_steps_are_clamped_to_the_limits():
    s = make_state(speed_steps=4, start_step=2)
    for _ in range(10):
        s.press(FASTER, 0.0)
    s.press(TURN_LEFT, 0.0)
    assert s.speed_fraction == 1.0 and s.twist(0.0)[2] == pytest.approx(1.0)
    for _ in range(10):
        s.press(SLOWER, 0.0)
    assert s.speed_fraction == 0.25 and s.twist(0.0)[2] == pytest.approx(0.25)


def test_quit_stops_and_ignores_later_keys():
    s = make_state()
    s.press(FORWARD, 0.0)
    s.press(QUIT, 0.1)
    s.press(FORWARD, 0.2)
    assert s.quit_requested and s.twist(0.2) == (0.0, 0.0, 0.0)


def test_bad_limits_and_keys_are_refused():
    with pytest.raises(ValueError, match="max_speed"):
        TeleopState(float("nan"), 1.0)
    with pytest.raises(ValueError, match="repeat_deadman"):
        TeleopState(0.3, 1.0, deadman=0.6, repeat_deadman=0.7)
    with pytest.raises(ValueError, match="unknown teleop key"):
        make_state().press("jump", 0.0)


# Status line  ------

def test_format_status_shows_pose_quality_and_fits_the_terminal():
    cov = [[1e-4, 0.0, 0.0], [0.0, 4e-6, 0.0], [0.0, 0.0, (math.radians(0.5)) ** 2]]
    line = format_status((1.2345, -0.5, math.radians(90.0)), cov, "degraded", "no plane fit for 2.3 s",
                         (0.15, 0.0, -0.5), "ok", speed_fraction=0.5)
    assert line == ("DEGRADED | link ok | x +1.234 y -0.500 th +90.0deg sd 10mm 0.5deg | v +0.15 +0.00 w -0.50 @50% | "
                    "no plane fit for 2.3 s")
    assert format_status(None, None, "lost", "", (0, 0, 0), "down").startswith("LOST | link down | no pose |")
    nan_pose = format_status((float("nan"), 0.0, 0.0), cov, "localized", "", (0, 0, 0), "ok")
    assert nan_pose == "localized | link ok | no pose | v +0.00 +0.00 w +0.00"
    cut = fit_line(line, 60)
    assert len(cut) == 59 and cut.endswith(">") and "\n" not in fit_line("a\nb", 80)


# Real terminal (pty)  ------

def read_available(fd):
    out = b""
    while True:
        try:
            chunk = os.read(fd, 4096)
        except (BlockingIOError, OSError):
            return out
        if not chunk:
            return out
        out += chunk


async def wait_for(predicate, timeout=5.0):
    """Poll until the event loop has delivered the input (bounded, not a timing assertion)."""
    end = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < end, "no reaction from TerminalKeyboard"
        await asyncio.sleep(0.005)


@pytest.fixture
def pty_pair():
    """[master, slave] of a fresh pty; a test that closes one sets it to -1."""
    pair = list(os.openpty())
    os.set_blocking(pair[0], False)
    yield pair
    for fd in pair:
        if fd >= 0:
            os.close(fd)


def test_terminal_keyboard_on_a_pty(pty_pair):
    master, slave = pty_pair
    before = termios.tcgetattr(slave)
    quits = []
    os.write(master, b"w")  # typed before teleop starts: must be discarded
    end = time.monotonic() + 5.0
    while b"w" not in read_available(master):  # its echo: the key is in the slave's input queue
        assert time.monotonic() < end
        time.sleep(0.001)

    async def main():
        kb = TerminalKeyboard(lambda: quits.append(1), fd=slave, state=make_state(deadman=0.6))
        async with kb:
            mode = termios.tcgetattr(slave)
            assert not mode[3] & (termios.ECHO | termios.ICANON | termios.ISIG)
            await asyncio.sleep(0.05)
            assert kb.state.twist(time.monotonic()) == (0.0, 0.0, 0.0)  # the early 'w' was flushed
            os.write(master, b"w")
            await wait_for(lambda: kb.state.twist(time.monotonic())[0] > 0.0)
            os.write(master, b" ")
            await wait_for(lambda: kb.state.last_key == STOP)
            assert kb.state.twist(time.monotonic()) == (0.0, 0.0, 0.0)
            os.write(master, b"\x1b[")  # an arrow split across two reads
            await asyncio.sleep(0.02)
            os.write(master, b"D")
            await wait_for(lambda: kb.state.twist(time.monotonic())[1] > 0.0)
            kb.show("status one")
            kb.show("status two")
            kb.message("chassis link lost")
            os.write(master, b"\x03")  # Ctrl-C arrives as a byte, not as SIGINT
            await wait_for(lambda: quits)
            assert kb.quit_reason == "key" and kb.state.twist(time.monotonic()) == (0.0, 0.0, 0.0)

    asyncio.run(main())
    assert quits == [1]
    assert termios.tcgetattr(slave) == before
    out = read_available(master)
    assert (CLEAR_LINE + "status one").encode() in out and (CLEAR_LINE + "status two").encode() in out
    assert b"W/A/S/D" in out  # the key help
    assert (CLEAR_LINE + "chassis link lost\r\n" + "status two").encode() in out  # status redrawn below it


def test_lone_esc_on_a_pty_quits_after_the_timeout(pty_pair):
    master, slave = pty_pair
    quits = []

    async def main():
        async with TerminalKeyboard(lambda: quits.append(1), fd=slave, esc_timeout=0.05, banner=False) as kb:
            os.write(master, b"\x1b")
            await wait_for(lambda: quits)
            assert kb.state.quit_requested

    asyncio.run(main())


def test_modes_restored_after_an_exception_and_hangup_quits(pty_pair):
    master, slave = pty_pair
    before = termios.tcgetattr(slave)
    quits = []

    async def crash():
        async with TerminalKeyboard(lambda: quits.append(1), fd=slave, banner=False):
            raise RuntimeError("app failed")

    with pytest.raises(RuntimeError, match="app failed"):
        asyncio.run(crash())
    assert termios.tcgetattr(slave) == before

    async def hangup():
        async with TerminalKeyboard(lambda: quits.append(1), fd=slave, banner=False) as kb:
            os.close(master)  # the terminal goes away (ssh dropped): reads fail with EIO
            pty_pair[0] = -1
            await wait_for(lambda: quits)
            assert kb.quit_reason.startswith("terminal closed") or kb.quit_reason == "end of input"

    asyncio.run(hangup())
    assert quits == [1]


@pytest.mark.skipif(signal.getsignal(signal.SIGHUP) is not signal.SIG_DFL, reason="SIGHUP already handled here")
def test_sighup_quits_instead_of_killing(pty_pair):
    master, slave = pty_pair
    before = termios.tcgetattr(slave)
    quits = []

    async def main():
        async with TerminalKeyboard(lambda: quits.append(1), fd=slave, banner=False) as kb:
            assert signal.SIGHUP in kb._signals  # otherwise the kill below would end pytest
            os.kill(os.getpid(), signal.SIGHUP)
            await wait_for(lambda: quits)
            assert kb.quit_reason == "SIGHUP"

    asyncio.run(main())
    assert signal.getsignal(signal.SIGHUP) is signal.SIG_DFL
    assert termios.tcgetattr(slave) == before


def test_not_a_terminal_is_a_clear_error():
    r, w = os.pipe()
    try:
        async def main():
            async with TerminalKeyboard(lambda: None, fd=r):
                pass

        with pytest.raises(NotATerminalError, match="not one .a pipe or a file") as err:
            asyncio.run(main())
        assert isinstance(err.value, RobotError)
    finally:
        os.close(r)
        os.close(w)


def test_cli_style_stdin_pipe_is_refused(monkeypatch):
    r, w = os.pipe()
    try:
        with open(r, "rb", closefd=False) as f:
            monkeypatch.setattr(sys, "stdin", f)

            async def main():
                async with TerminalKeyboard(lambda: None):
                    pass

            with pytest.raises(NotATerminalError, match="stdin is not one"):
                asyncio.run(main())
    finally:
        os.close(r)
        os.close(w)
