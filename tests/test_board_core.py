"""The C board core (firmware_protocol/c/board_core.c) against the Python board emulator.

Every scenario runs on a ``Twin``: the same bytes, control ticks and inputs go to the C core
(a host shared library loaded with ctypes) and to ``BoardModel``, and after every operation the
two must have transmitted exactly the same bytes and hold the same wheel setpoints. The C core
gets its encoder counts from the Python model's motor physics, as a firmware gets them from the
quadrature counters. Time is simulated: 1 ms control ticks, no wall clock anywhere.

Also here: a strict-warnings build, C-only behaviour (bounded transmit queue, config checks),
an address/undefined-behaviour sanitizer build fed a fuzzed byte stream, and the cross build
for a Cortex-M0 and an AVR (scripts/build_firmware.sh). Each skips, saying why, when its
compiler or runtime is missing.
"""

from __future__ import annotations

import ctypes
import dataclasses
import os
import random
import shutil
import struct
import subprocess
from pathlib import Path
from typing import List, Optional, Sequence, Tuple

import pytest

import firmware_protocol as fp
from drivers.chassis.emulator import BoardModel
from firmware_protocol.frame import encode_frame
from robot.config import ChassisConfig

ROOT = Path(__file__).resolve().parents[1]
C_DIR = ROOT / "firmware_protocol" / "c"
SOURCES = [C_DIR / "board_core.c", C_DIR / "mecanum_proto.c"]
CFG = ChassisConfig()
# The C setpoints are integers in urad/s, the Python ones floats in rad/s; both walk the same line.
SETPOINT_TOL = 5e-6  # rad/s

SHIM = r"""
#include "board_core.h"
size_t shim_core_size(void) { return sizeof(mb_core_t); }
size_t shim_config_size(void) { return sizeof(mb_config_t); }
void shim_setpoints(const mb_core_t *c, int32_t out[4]) { int i; for (i = 0; i < 4; i++) out[i] = c->setpoint_urad_s[i]; }
void shim_targets(const mb_core_t *c, int32_t out[4]) { int i; for (i = 0; i < 4; i++) out[i] = c->target_urad_s[i]; }
unsigned shim_flags(const mb_core_t *c) { return c->flags; }
unsigned shim_rx_errors(const mb_core_t *c) { return c->rx_errors; }
unsigned long shim_tx_dropped(const mb_core_t *c) { return (unsigned long)c->tx_dropped; }
unsigned shim_tx_capacity(void) { return MB_TX_CAPACITY; }
"""


class Config(ctypes.Structure):
    _fields_ = [("ticks_per_rev", ctypes.c_uint32), ("max_speed_mrad_s", ctypes.c_uint32),
                ("max_accel_mrad_s2", ctypes.c_uint32), ("watchdog_ms", ctypes.c_uint16),
                ("report_period_us", ctypes.c_uint16), ("status_period_us", ctypes.c_uint32),
                ("fw_major", ctypes.c_uint8), ("fw_minor", ctypes.c_uint8), ("fw_patch", ctypes.c_uint8)]


def _find_gcc() -> Optional[str]:
    for name in (os.environ.get("CC"), "gcc", "cc"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


def _compile(args: List[str]) -> subprocess.CompletedProcess:
    return subprocess.run(args, capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def lib(tmp_path_factory):
    cc = _find_gcc()
    if cc is None:
        pytest.skip("no C compiler ($CC, gcc, cc): the C board core is not checked here")
    d = tmp_path_factory.mktemp("board_core")
    (d / "shim.c").write_text(SHIM, encoding="utf-8")
    so = d / "libboardcore.so"
    res = _compile([cc, "-std=c99", "-O1", "-Wall", "-Wextra", "-Werror", "-fPIC", "-shared", "-I", str(C_DIR),
                    *map(str, SOURCES), str(d / "shim.c"), "-o", str(so)])
    assert res.returncode == 0, f"the board core does not compile cleanly:\n{res.stderr}"
    so_lib = ctypes.CDLL(str(so))
    vp, u8, u16, u32, i32p = ctypes.c_void_p, ctypes.c_uint8, ctypes.c_uint16, ctypes.c_uint32, ctypes.POINTER(ctypes.c_int32)
    for name, args, res_t in [
        ("mb_config_default", [ctypes.POINTER(Config)], None),
        ("mb_core_init", [vp, ctypes.POINTER(Config), u32], ctypes.c_int),
        ("mb_core_rx_byte", [vp, u8, u32], None),
        ("mb_core_rx", [vp, ctypes.c_char_p, ctypes.c_size_t, u32], None),
        ("mb_core_tick", [vp, u32, i32p], None),
        ("mb_core_set_estop", [vp, ctypes.c_int, u32], None),
        ("mb_core_set_motor_faults", [vp, u8, u32], None),
        ("mb_core_set_battery_mv", [vp, u16], None),
        ("mb_core_tx_pending", [vp], ctypes.c_size_t),
        ("mb_core_tx_take", [vp, ctypes.c_char_p, ctypes.c_size_t], ctypes.c_size_t),
        ("mb_core_tx_pop", [vp], ctypes.c_int),
        ("shim_core_size", [], ctypes.c_size_t),
        ("shim_config_size", [], ctypes.c_size_t),
        ("shim_setpoints", [vp, i32p], None),
        ("shim_targets", [vp, i32p], None),
        ("shim_flags", [vp], ctypes.c_uint),
        ("shim_rx_errors", [vp], ctypes.c_uint),
        ("shim_tx_dropped", [vp], ctypes.c_ulong),
        ("shim_tx_capacity", [], ctypes.c_uint),
    ]:
        fn = getattr(so_lib, name)
        fn.argtypes = args
        fn.restype = res_t
    assert so_lib.shim_config_size() == ctypes.sizeof(Config), "the ctypes mirror of mb_config_t is out of date"
    return so_lib


class CBoard:
    """One mb_core_t in memory Python owns, driven through the public API."""

    def __init__(self, lib, cfg: Config, now_us: int):
        self.lib = lib
        words = (lib.shim_core_size() + 7) // 8
        self.mem = (ctypes.c_uint64 * words)()  # 8-byte aligned, as the struct needs
        self.p = ctypes.cast(self.mem, ctypes.c_void_p)
        self.init_result = lib.mb_core_init(self.p, ctypes.byref(cfg), now_us & 0xFFFFFFFF)
        self._out = ctypes.create_string_buffer(4096)

    def rx(self, data: bytes, now_us: int) -> None:
        self.lib.mb_core_rx(self.p, bytes(data), len(data), now_us & 0xFFFFFFFF)

    def tick(self, now_us: int, ticks: Sequence[int]) -> None:
        self.lib.mb_core_tick(self.p, now_us & 0xFFFFFFFF, (ctypes.c_int32 * 4)(*ticks))

    def take(self, cap: int = 4096) -> bytes:
        n = self.lib.mb_core_tx_take(self.p, self._out, min(cap, len(self._out)))
        return self._out.raw[:n]

    def _quad(self, fn) -> Tuple[int, ...]:
        out = (ctypes.c_int32 * 4)()
        fn(self.p, out)
        return tuple(out)

    @property
    def setpoints_urad_s(self) -> Tuple[int, ...]:
        return self._quad(self.lib.shim_setpoints)

    @property
    def targets_urad_s(self) -> Tuple[int, ...]:
        return self._quad(self.lib.shim_targets)

    @property
    def flags(self) -> int:
        return self.lib.shim_flags(self.p)

    @property
    def rx_errors(self) -> int:
        return self.lib.shim_rx_errors(self.p)

    @property
    def tx_dropped(self) -> int:
        return self.lib.shim_tx_dropped(self.p)


def c_config(lib, cfg: ChassisConfig = CFG, report_period: float = 0.01, status_period: float = 0.1) -> Config:
    c = Config()
    lib.mb_config_default(ctypes.byref(c))
    c.ticks_per_rev = cfg.ticks_per_rev
    c.max_speed_mrad_s = int(round(cfg.max_wheel_speed * fp.MRAD))
    c.max_accel_mrad_s2 = int(round(cfg.max_wheel_accel * fp.MRAD))
    c.watchdog_ms = int(round(cfg.watchdog_timeout * 1000))
    c.report_period_us = int(round(report_period * 1e6))
    c.status_period_us = int(round(status_period * 1e6))
    return c


class Twin:
    """The C core and the Python BoardModel side by side; every operation goes to both and compared."""

    def __init__(self, lib, cfg: ChassisConfig = CFG, *, t0_us: int = 0, tick_offset=(0, 0, 0, 0),
                 report_period: float = 0.01, status_period: float = 0.1):
        self.py = BoardModel(cfg, t0_us=t0_us, tick_offset=tick_offset, report_period=report_period,
                             status_period=status_period, battery_v=12.0)
        self.c = CBoard(lib, c_config(lib, cfg, report_period, status_period), self.py.t_us_wire)
        assert self.c.init_result == 0
        lib.mb_core_set_battery_mv(self.c.p, 12000)
        self.decoder = fp.Decoder()
        self.sent: List[fp.Message] = []  # every message the board transmitted, decoded
        self.wire = bytearray()
        self.max_setpoint_error = 0.0
        self.ms = 0

    @property
    def now(self) -> int:
        return self.py.t_us_wire

    def _compare(self) -> List[fp.Message]:
        py_bytes, c_bytes = self.py.take_outbox(), self.c.take()
        assert c_bytes == py_bytes, (f"at t={self.py.time_us} us the C core sent {c_bytes.hex()} and the "
                                     f"emulator {py_bytes.hex()}")
        c_sp = self.c.setpoints_urad_s
        err = max(abs(p - c * 1e-6) for p, c in zip(self.py.setpoint, c_sp))
        self.max_setpoint_error = max(self.max_setpoint_error, err)
        assert err <= SETPOINT_TOL, f"at t={self.py.time_us} us setpoints differ: {self.py.setpoint} vs {c_sp} urad/s"
        assert self.c.flags == self.py.flags
        self.wire += c_bytes
        new = self.decoder.feed(c_bytes)
        self.sent += new
        return new

    def feed(self, data: bytes) -> List[fp.Message]:
        """Bytes from the host, one at a time as a UART delivers them, at the current time."""
        for b in data:
            self.py.handle_bytes(bytes([b]))
            self.c.rx(bytes([b]), self.now)
        return self._compare()

    def send(self, *msgs: fp.Message) -> List[fp.Message]:
        return self.feed(b"".join(fp.encode(m) for m in msgs))

    def step(self, seconds: float) -> List[fp.Message]:
        """Advance both by whole 1 ms control ticks; the C core gets the model's encoder counts."""
        new: List[fp.Message] = []
        for _ in range(int(round(seconds * 1000))):
            self.py.step(0.001)
            self.ms += 1
            assert self.py.time_us == self.ms * 1000
            self.c.tick(self.now, self.py.ticks())
            new += self._compare()
        return new

    def set_estop(self, active: bool) -> List[fp.Message]:
        self.py.set_estop(active)
        self.c.lib.mb_core_set_estop(self.c.p, int(active), self.now)
        return self._compare()

    def set_motor_fault(self, wheel: int, active: bool) -> List[fp.Message]:
        self.py.set_motor_fault(wheel, active)
        self.c.lib.mb_core_set_motor_faults(self.c.p, self.py.motor_faults, self.now)
        return self._compare()

    @property
    def setpoints(self) -> Tuple[float, ...]:
        return tuple(v * 1e-6 for v in self.c.setpoints_urad_s)

    def of(self, kind, msgs: Optional[List[fp.Message]] = None) -> list:
        return [m for m in (self.sent if msgs is None else msgs) if isinstance(m, kind)]


def speeds(rad_s: Sequence[float], seq: int = 0) -> fp.SetWheelSpeeds:
    return fp.SetWheelSpeeds.from_rad_s(rad_s, seq=seq)


def session(twin: Twin, nonce: int = 0x1234ABCD) -> None:
    twin.send(fp.Hello(0, nonce, seq=0))


def drive(twin: Twin, rad_s: Sequence[float], seconds: float, period: float = 0.05, seq0: int = 1) -> None:
    """A live control loop: the same command afresh every period."""
    for i in range(int(round(seconds / period))):
        twin.send(speeds(rad_s, seq=(seq0 + i) & 0xFF))
        twin.step(period)


def flip_bit(frame: bytes, index: int, bit: int = 0) -> bytes:
    b = bytearray(frame)
    b[index] ^= 1 << bit
    return bytes(b)


# Handshake  -------------------------------------------------------------------------------------

def test_handshake_replies_with_the_nonce_versions_and_limits(lib):
    t = Twin(lib)
    t.step(0.005)
    refused = t.send(speeds([1, 1, 1, 1], seq=9))
    assert [(n.ref_id, n.ref_seq, n.reason) for n in t.of(fp.Nack, refused)] == [(2, 9, fp.NackReason.NO_SESSION)]
    new = t.send(fp.Hello(0, 0xDEADBEEF, seq=10))
    (reply,) = t.of(fp.HelloReply, new)
    assert reply == fp.HelloReply(minor=fp.PROTOCOL_MINOR, nonce=0xDEADBEEF, fw_major=1, fw_minor=0, fw_patch=0,
                                  ticks_per_rev=1320, max_speed_mrad_s=20000, max_accel_mrad_s2=40000,
                                  watchdog_ms=200, report_period_us=10000, capabilities=0, seq=reply.seq)
    (status,) = t.of(fp.Status, new)
    assert not status.flags & fp.StatusFlag.NO_SESSION
    # a newer host's HELLO with appended fields is accepted; the board answers in its own minor version
    t.feed(encode_frame(fp.Hello.MSG_ID, 11, struct.pack("<BI", 3, 77) + b"\x01\x02"))
    assert t.of(fp.HelloReply)[-1].nonce == 77 and t.of(fp.HelloReply)[-1].minor == fp.PROTOCOL_MINOR
    # the board's own seq counts every frame it sent
    assert [m.seq for m in t.sent] == list(range(len(t.sent)))


def test_hello_starts_a_session_from_standstill(lib):
    t = Twin(lib)
    session(t)
    drive(t, [6, 6, 6, 6], 0.3)
    assert t.setpoints == pytest.approx((6, 6, 6, 6))
    t.send(fp.Hello(0, 2, seq=40))
    assert t.c.targets_urad_s == (0, 0, 0, 0)
    t.step(0.2)
    assert t.setpoints == (0, 0, 0, 0)


# Speed commands, clamping, the ramp  -----------------------------------------------------------

def test_speeds_within_the_limits_are_acked_and_reached(lib):
    t = Twin(lib)
    session(t)
    new = t.send(speeds([5, -5, 2.5, 0], seq=21))
    assert [(a.ref_id, a.ref_seq) for a in t.of(fp.Ack, new)] == [(2, 21)] and not t.of(fp.Nack, new)
    drive(t, [5, -5, 2.5, 0], 0.2, seq0=22)
    assert t.setpoints == pytest.approx((5, -5, 2.5, 0), abs=1e-9)
    assert t.c.targets_urad_s == (5_000_000, -5_000_000, 2_500_000, 0)
    assert not t.c.flags & fp.StatusFlag.CLAMPED


def test_over_limit_command_is_scaled_uniformly_applied_and_nacked_clamped(lib):
    t = Twin(lib)
    session(t)
    new = t.send(speeds([40, -25, 10, 0], seq=5))
    (nack,) = t.of(fp.Nack, new)
    assert (nack.ref_id, nack.ref_seq, nack.reason, nack.detail) == (2, 5, fp.NackReason.CLAMPED, 0b0011)
    assert not t.of(fp.Ack, new)
    assert t.of(fp.Status, new)[-1].flags & fp.StatusFlag.CLAMPED
    # applied: one factor (0.5) for all four wheels, the fastest exactly at the limit
    assert t.c.targets_urad_s == (20_000_000, -12_500_000, 5_000_000, 0)
    drive(t, [40, -25, 10, 0], 0.6, seq0=10)  # 20 rad/s at 40 rad/s^2: 0.5 s
    assert t.setpoints == pytest.approx((20, -12.5, 5, 0), abs=1e-9)
    # the most extreme wire values scale the same way
    new = t.send(fp.SetWheelSpeeds((-2**31, 2**31 - 1, 0, 2**30), seq=6))
    assert t.of(fp.Nack, new)[0].detail == 0b1011
    assert t.c.targets_urad_s[0] == -20_000_000 and abs(t.c.targets_urad_s[1] - 20_000_000) <= 1
    assert t.c.targets_urad_s[3] == 10_000_000
    # a command within the limits is acked and clears CLAMPED at once; exactly at the limit is within
    new = t.send(fp.SetWheelSpeeds((20000, -20000, 1, 0), seq=7))
    assert t.of(fp.Ack, new) and not t.of(fp.Status, new)[-1].flags & fp.StatusFlag.CLAMPED
    new = t.send(fp.SetWheelSpeeds((20000, -20001, 1, 0), seq=8))
    assert [n.detail for n in t.of(fp.Nack, new)] == [0b0010]


def test_ramp_moves_all_wheels_along_one_line_at_max_accel(lib):
    t = Twin(lib)
    session(t)
    t.send(speeds([10, -5, 2.5, 0], seq=1))
    trace = []
    for _ in range(150):
        t.step(0.001)
        trace.append(t.setpoints)
    # the fastest-changing wheel moves 40 rad/s^2 * 1 ms per tick and gets there in 250 ms
    assert trace[0][0] == pytest.approx(0.04, abs=1e-9)
    assert trace[99][0] == pytest.approx(4.0, abs=1e-9)
    for sp in trace:  # a straight line in wheel-speed space: the ratios hold throughout
        assert sp[1] == pytest.approx(-sp[0] / 2, abs=2e-6) and sp[2] == pytest.approx(sp[0] / 4, abs=2e-6)
    # a new target mid-ramp: a new line from where the setpoints are now
    here = t.setpoints
    t.send(speeds([0, 5, 0, 0], seq=2))
    t.step(0.001)
    d = [a - b for a, b in zip(t.setpoints, here)]
    towards = [b - a for a, b in zip(here, (0, 5, 0, 0))]  # (-6, 8, -1.5, 0): wheel FR changes most
    assert d == pytest.approx([0.04 * v / 8 for v in towards], abs=2e-6)
    drive(t, [0, 5, 0, 0], 0.3, seq0=3)
    assert t.setpoints == pytest.approx((0, 5, 0, 0), abs=1e-9)


# Watchdog, heartbeat, STOP  --------------------------------------------------------------------

def test_watchdog_trips_200ms_after_the_last_command_and_a_new_command_recovers(lib):
    t = Twin(lib)
    session(t)
    drive(t, [5, 5, 5, 5], 0.2)  # last command at 150 ms
    last_cmd_ms = t.ms - 50
    before = len(t.sent)
    t.step(0.3)
    trips = [m for m in t.sent[before:] if isinstance(m, fp.Status) and m.flags & fp.StatusFlag.WATCHDOG]
    assert trips and trips[0].t_us == (last_cmd_ms + 200) * 1000  # checked every 1 ms tick
    # nothing at all came for 200 ms either: HOST_SILENT follows in the same tick, in its own STATUS
    silent = [m for m in t.sent[before:] if isinstance(m, fp.Status) and m.flags & fp.StatusFlag.HOST_SILENT]
    assert silent[0].t_us == trips[0].t_us and silent[0].seq == trips[0].seq + 1
    # from 5 rad/s at 40 rad/s^2 the wheels are at rest 125 ms after the trip
    assert t.setpoints == (0, 0, 0, 0)
    new = t.send(speeds([2, 2, 2, 2], seq=99))
    assert t.of(fp.Ack, new)
    assert not t.of(fp.Status, new)[-1].flags & (fp.StatusFlag.WATCHDOG | fp.StatusFlag.HOST_SILENT)
    drive(t, [2, 2, 2, 2], 0.2, seq0=100)
    assert t.setpoints == pytest.approx((2, 2, 2, 2))


def test_heartbeats_do_not_feed_the_watchdog(lib):
    t = Twin(lib)
    session(t)
    t.send(speeds([4, 4, 4, 4], seq=1))
    for i in range(8):
        t.step(0.05)
        t.send(fp.Heartbeat(seq=2 + i))
    statuses = t.of(fp.Status)
    assert any(s.flags & fp.StatusFlag.WATCHDOG for s in statuses)
    assert not any(s.flags & fp.StatusFlag.HOST_SILENT for s in statuses)  # the host was present
    assert t.setpoints == (0, 0, 0, 0)


def test_stop_is_acked_in_every_state_and_ramps_down(lib):
    t = Twin(lib)
    new = t.send(fp.Stop(seq=3))  # no session yet
    assert [(a.ref_id, a.ref_seq) for a in t.of(fp.Ack, new)] == [(3, 3)]
    session(t)
    drive(t, [8, -8, 8, -8], 0.3)
    new = t.send(fp.Stop(seq=50))
    assert [(a.ref_id, a.ref_seq) for a in t.of(fp.Ack, new)] == [(3, 50)]
    t.step(0.1)
    assert t.setpoints == pytest.approx((4, -4, 4, -4), abs=1e-9)  # 40 rad/s^2 down, not a cut
    t.step(0.15)
    assert t.setpoints == (0, 0, 0, 0)
    assert not any(s.flags & fp.StatusFlag.WATCHDOG for s in t.of(fp.Status))


# Bad input  -------------------------------------------------------------------------------------

def test_corrupted_and_garbage_bytes_are_counted_and_never_move_a_wheel(lib):
    t = Twin(lib)
    session(t)
    drive(t, [3, 3, 3, 3], 0.2)
    target = t.c.targets_urad_s
    good = fp.encode(speeds([15, 15, 15, 15], seq=60))
    rng = random.Random(5)
    bad = [
        flip_bit(good, 7, 3),                               # CRC error
        flip_bit(good, 1, 6),                               # COBS code byte: structure broken
        b"\x00\x03\x01\x02\x00",                            # too short
        encode_frame(fp.SetWheelSpeeds.MSG_ID, 61, bytes(15)),  # one byte short of the layout
        bytes(rng.randrange(1, 256) for _ in range(120)) + b"\x00",  # no delimiter for 120 bytes
        bytes(rng.randrange(256) for _ in range(300)),       # noise
    ]
    new = []
    for chunk in bad:
        new += t.feed(chunk)
    t.feed(b"\x00")
    assert t.c.targets_urad_s == target  # nothing was interpreted
    assert not t.of(fp.Ack, new) and not t.of(fp.Nack, new)
    assert t.c.rx_errors == t.py.decoder.stats.dropped_frames >= 5
    t.step(0.1)
    assert t.of(fp.Status)[-1].rx_errors == t.c.rx_errors
    # the line recovers at the next delimiter: a valid frame right after the noise is taken
    new = t.send(speeds([3, 3, 3, 3], seq=62))
    assert t.of(fp.Ack, new)


def test_unknown_ids_and_foreign_versions_are_nacked_by_name(lib):
    t = Twin(lib)
    session(t)
    new = t.feed(encode_frame(0x55, 17, b"\x01\x02"))
    assert [(n.ref_id, n.ref_seq, n.reason) for n in t.of(fp.Nack, new)] == [(0x55, 17, fp.NackReason.UNKNOWN_MESSAGE)]
    new = t.send(fp.Ack(2, 3, seq=18))  # a board -> host message sent to the board
    assert [(n.ref_id, n.ref_seq, n.reason) for n in t.of(fp.Nack, new)] == [(0x84, 18, fp.NackReason.UNKNOWN_MESSAGE)]
    new = t.feed(fp.encode(speeds([1, 1, 1, 1], seq=19), version=2))
    assert [(n.reason, n.detail) for n in t.of(fp.Nack, new)] == [(fp.NackReason.BAD_VERSION, 2)]
    assert t.c.targets_urad_s == (0, 0, 0, 0) and t.c.rx_errors == 1


def test_differential_fuzz_against_the_emulator(lib):
    """Seeded random traffic (valid, bit-flipped, foreign, garbage) with random timing and inputs."""
    rng = random.Random(2024)
    t = Twin(lib, t0_us=0xFFFFFFFF - 1_500_000, tick_offset=(2**31 - 5000, -(2**31) + 5000, 0, 17))
    ids = [fp.Hello.MSG_ID, fp.SetWheelSpeeds.MSG_ID, fp.Stop.MSG_ID, fp.Heartbeat.MSG_ID]
    t.send(speeds([1, 2, 3, 4], seq=0))  # before any HELLO
    seq = 0
    for _ in range(1500):
        r = rng.random()
        seq = (seq + 1) & 0xFF
        if r < 0.45:
            mrad = [int(rng.gauss(0, 12000)) for _ in range(4)]
            frame = fp.encode(fp.SetWheelSpeeds(tuple(mrad), seq=seq))
        elif r < 0.55:
            frame = fp.encode(fp.Hello(0, rng.randrange(2**32), seq=seq))
        elif r < 0.65:
            frame = fp.encode(rng.choice([fp.Stop(seq=seq), fp.Heartbeat(seq=seq)]))
        elif r < 0.72:
            frame = encode_frame(rng.choice(ids + [0x33, 0x84, 0x83]), seq,
                                 bytes(rng.randrange(256) for _ in range(rng.randrange(0, 30))))
        elif r < 0.76:
            frame = fp.encode(fp.Stop(seq=seq), version=rng.choice([0, 2, 7]))
        elif r < 0.9:
            frame = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 40)))
        else:
            frame = fp.encode(fp.SetWheelSpeeds.from_rad_s([rng.uniform(-25, 25) for _ in range(4)], seq=seq))
            frame = flip_bit(frame, rng.randrange(len(frame)), rng.randrange(8))
        t.feed(frame)
        t.step(rng.choice([0.0, 0.001, 0.003, 0.01, 0.03, 0.25]) if rng.random() < 0.6 else 0.0)
        # e-stop and motor faults come and go, each active for a few percent of the run
        if rng.random() < (0.1 if t.py.estop else 0.005):
            t.set_estop(not t.py.estop)
        if t.py.motor_faults and rng.random() < 0.1:
            t.set_motor_fault(t.py.motor_faults.bit_length() - 1, False)
        elif rng.random() < 0.005 and t.py.motor_faults != 0b1111:
            # only a real change: the emulator reports every call, the core only a change
            t.set_motor_fault(rng.choice([w for w in range(4) if not t.py.motor_faults & (1 << w)]), True)
    reasons = {n.reason for n in t.of(fp.Nack)}
    assert reasons == set(fp.NackReason)
    assert len(t.of(fp.Ack)) > 300 and len(t.of(fp.Status)) > 300 and t.c.rx_errors > 100
    assert any(m.t_us < 1_000_000 for m in t.of(fp.EncoderReport))  # the board clock wrapped
    assert t.decoder.stats.dropped_frames == 0


def test_non_default_limits_and_rates(lib):
    cfg = dataclasses.replace(CFG, max_wheel_speed=7.5, max_wheel_accel=12.345, watchdog_timeout=0.15,
                              ticks_per_rev=4096)
    t = Twin(lib, cfg, report_period=0.005, status_period=0.05)
    new = t.send(fp.Hello(0, 1, seq=0))
    reply = t.of(fp.HelloReply, new)[0]
    assert (reply.max_speed_mrad_s, reply.max_accel_mrad_s2, reply.watchdog_ms, reply.report_period_us,
            reply.ticks_per_rev) == (7500, 12345, 150, 5000, 4096)
    t.send(speeds([9, -3, 1, 0.5], seq=1))
    t.step(0.4)
    assert t.of(fp.Nack)[-1].detail == 0b0001
    assert len(t.of(fp.EncoderReport)) == 80


# Reports and status  ----------------------------------------------------------------------------

def test_reports_and_status_content(lib):
    t = Twin(lib, tick_offset=(100, -200, 300, -400))
    session(t)
    drive(t, [2, 2, -2, -2], 0.5)
    reports = t.of(fp.EncoderReport)
    assert [r.t_us for r in reports] == [10_000 * (i + 1) for i in range(len(reports))] and len(reports) == 50
    assert reports[-1].ticks[0] > 100 and reports[-1].ticks[2] < 300  # cumulative, signed by direction
    periodic = [s for s in t.of(fp.Status) if s.t_us % 100_000 == 0 and s.t_us > 0]
    assert [s.t_us for s in periodic] == [100_000 * (i + 1) for i in range(5)]
    assert all(s.battery_mv == 12000 and s.motor_faults == 0 and s.rx_errors == 0 for s in periodic)
    # e-stop: setpoints at zero at once, commands refused, flag reported
    new = t.set_estop(True)
    assert t.setpoints == (0, 0, 0, 0) and t.of(fp.Status, new)[0].flags & fp.StatusFlag.ESTOP
    new = t.send(speeds([1, 1, 1, 1], seq=90))
    assert [(n.reason, n.detail) for n in t.of(fp.Nack, new)] == [(fp.NackReason.ESTOP, 0)]
    new = t.set_estop(False)
    assert not t.of(fp.Status, new)[0].flags & fp.StatusFlag.ESTOP
    # motor fault: reported at once, targets to zero, commands refused with the faulted wheels
    drive(t, [2, 2, 2, 2], 0.2, seq0=91)
    new = t.set_motor_fault(2, True)
    assert t.of(fp.Status, new)[0].motor_faults == 0b0100 and t.c.targets_urad_s == (0, 0, 0, 0)
    new = t.send(speeds([1, 1, 1, 1], seq=95))
    assert [(n.reason, n.detail) for n in t.of(fp.Nack, new)] == [(fp.NackReason.MOTOR_FAULT, 0b0100)]
    t.step(0.1)
    assert t.setpoints == (0, 0, 0, 0)  # ramped down, not cut
    new = t.set_motor_fault(2, False)
    assert t.of(fp.Status, new)[0].motor_faults == 0


def test_clock_and_tick_counters_wrap(lib):
    t = Twin(lib, t0_us=2**32 - 100_000, tick_offset=(2**31 - 50, -(2**31) + 50, 0, 0))
    session(t)
    drive(t, [5, -5, 0, 0], 0.4)  # the watchdog and the report grid run across the wrap
    t.step(0.4)
    reports = t.of(fp.EncoderReport)
    t_us = [r.t_us for r in reports]
    assert t_us[0] > 2**32 - 100_000 and t_us[-1] < 1_000_000
    assert all(fp.counters.delta_u32(b, a) == 10_000 for a, b in zip(t_us, t_us[1:]))
    assert reports[-1].ticks[0] < 0 < reports[-1].ticks[1]  # both int32 counters wrapped
    assert any(s.flags & fp.StatusFlag.WATCHDOG for s in t.of(fp.Status))


# C-only behaviour  ------------------------------------------------------------------------------

def test_transmit_queue_is_bounded_and_keeps_whole_frames(lib):
    cfg = c_config(lib)
    b = CBoard(lib, cfg, 0)
    capacity = lib.shim_tx_capacity()
    flood = b"".join(fp.encode(fp.Stop(seq=i & 0xFF)) for i in range(100))
    b.rx(flood, 0)  # a host flooding STOPs while nothing drains the UART
    assert lib.mb_core_tx_pending(b.p) <= capacity and b.tx_dropped > 0
    popped = bytes(lib.mb_core_tx_pop(b.p) for _ in range(3))
    data = popped + b.take()
    assert lib.mb_core_tx_pop(b.p) == -1 and lib.mb_core_tx_pending(b.p) == 0
    d = fp.Decoder()
    acks = d.feed(data)
    assert d.stats.dropped_frames == 0 and all(isinstance(m, fp.Ack) for m in acks)
    assert len(acks) + b.tx_dropped == 100
    assert [m.ref_seq for m in acks] == list(range(len(acks)))  # the first ones, in order
    # dropped frames still used their seq: the host sees a gap, not a silent renumbering
    b.rx(fp.encode(fp.Stop(seq=200)), 0)
    (last,) = fp.Decoder().feed(b.take())
    assert last.seq == 100


@pytest.mark.parametrize("field,value,code", [
    ("ticks_per_rev", 0, -2), ("max_speed_mrad_s", 0, -3), ("max_speed_mrad_s", 1_000_001, -3),
    ("max_accel_mrad_s2", 0, -4), ("max_accel_mrad_s2", 4_000_001, -4), ("watchdog_ms", 0, -5),
    ("report_period_us", 0, -6), ("status_period_us", 0, -7), ("status_period_us", 2**31, -7),
])
def test_init_names_the_bad_config_field(lib, field, value, code):
    cfg = c_config(lib)
    setattr(cfg, field, value)
    assert CBoard(lib, cfg, 0).init_result == code
    assert lib.mb_core_init(None, ctypes.byref(c_config(lib)), 0) == -1


def test_core_compiles_with_the_strictest_warnings(tmp_path):
    cc = _find_gcc()
    if cc is None:
        pytest.skip("no C compiler")
    res = _compile([cc, "-std=c99", "-c", "-O2", "-Wall", "-Wextra", "-Werror", "-pedantic", "-Wconversion",
                    "-Wshadow", "-Wcast-qual", "-Wstrict-prototypes", "-Wmissing-prototypes", "-Wundef",
                    "-I", str(C_DIR), str(C_DIR / "board_core.c"), "-o", str(tmp_path / "board_core.o")])
    assert res.returncode == 0, res.stderr


# Sanitizers  ------------------------------------------------------------------------------------

FUZZ_MAIN = r"""
#include <stdio.h>
#include <stdlib.h>
#include "board_core.h"

static uint32_t rng_state;
static uint32_t rnd(void) { rng_state ^= rng_state << 13; rng_state ^= rng_state >> 17; rng_state ^= rng_state << 5; return rng_state; }
static void check(int ok, const char *what) { if (!ok) { fprintf(stderr, "invariant broken: %s\n", what); abort(); } }

int main(int argc, char **argv) {
    static uint8_t in[1 << 21], out[512];
    mb_core_t core; mb_config_t cfg;
    int64_t angle_nrad[4] = {0, 0, 0, 0};
    int32_t ticks[4] = {0, 0, 0, 0};
    size_t n = fread(in, 1, sizeof in, stdin), i;
    uint32_t now = 0xFFF00000u, max_urad, stall = 0;
    int w;
    rng_state = argc > 1 ? (uint32_t)strtoul(argv[1], NULL, 10) | 1u : 1u;
    mb_config_default(&cfg);
    max_urad = cfg.max_speed_mrad_s * 1000u;
    check(mb_core_init(&core, &cfg, now) == MB_OK, "init");
    mb_core_set_battery_mv(&core, 11800);
    for (i = 0; i < n; i++) {
        mb_core_rx_byte(&core, in[i], now);
        if (rnd() % 8u == 0u) {
            uint32_t r = rnd(), dt = r % 64u == 0u ? rnd() % 400000u : 1u + rnd() % 1500u;
            now += dt;
            for (w = 0; w < 4; w++) {
                angle_nrad[w] += (int64_t)core.setpoint_urad_s[w] * dt / 1000;
                ticks[w] = (int32_t)(uint32_t)(uint64_t)(angle_nrad[w] / 4760000);  /* 1320 ticks per rev */
            }
            mb_core_tick(&core, now, ticks);
        }
        /* e-stop and faults come and go; faults may name bits beyond the four wheels */
        if (rnd() % (core.estop ? 512u : 8192u) == 0u) mb_core_set_estop(&core, !core.estop, now);
        if (rnd() % (core.motor_faults ? 512u : 8192u) == 0u) mb_core_set_motor_faults(&core, (uint8_t)rnd(), now);
        for (w = 0; w < 4; w++) {
            check((uint32_t)abs(core.setpoint_urad_s[w]) <= max_urad, "setpoint within the speed limit");
            check((uint32_t)abs(core.target_urad_s[w]) <= max_urad, "target within the speed limit");
            check(!core.estop || core.setpoint_urad_s[w] == 0, "e-stop holds the setpoints at zero");
        }
        check((core.flags & ~0x1Fu) == 0u, "only defined flags");
        check(mb_core_tx_pending(&core) <= MB_TX_CAPACITY, "bounded transmit queue");
        /* the UART drains at a random pace and now and then not at all, so the queue fills up */
        if (stall > 0) {
            stall--;
        } else if (rnd() % 4096u == 0u) {
            stall = rnd() % 3000u;
        } else if (rnd() % 2u == 0u) {
            size_t k = mb_core_tx_take(&core, out, rnd() % sizeof out);
            fwrite(out, 1, k, stdout);
        }
    }
    for (;;) { size_t k = mb_core_tx_take(&core, out, sizeof out); if (k == 0) break; fwrite(out, 1, k, stdout); }
    fprintf(stderr, "tx_dropped %lu rx_errors %u frames %lu\n", (unsigned long)core.tx_dropped, core.rx_errors,
            (unsigned long)core.decoder.stats.frames);
    return 0;
}
"""

SAN_FLAGS = ["-fsanitize=address,undefined", "-fno-sanitize-recover=all", "-fno-omit-frame-pointer", "-g", "-O1"]
SAN_ENV = {"ASAN_OPTIONS": "detect_leaks=0:abort_on_error=0", "UBSAN_OPTIONS": "print_stacktrace=1:halt_on_error=1"}


def fuzz_stream(seed: int, size: int) -> bytes:
    """Random bytes, valid host frames (some over the limits), bit-flipped frames, foreign versions."""
    rng = random.Random(seed)
    out = bytearray()
    seq = 0
    while len(out) < size:
        seq = (seq + 1) & 0xFF
        r = rng.random()
        if r < 0.15:
            out += bytes(rng.randrange(256) for _ in range(rng.randrange(1, 200)))
            continue
        if r < 0.2:
            frame = fp.encode(fp.Hello(0, rng.randrange(2**32), seq=seq))
        elif r < 0.6:
            frame = fp.encode(fp.SetWheelSpeeds(tuple(rng.choice([rng.randrange(-2**31, 2**31),
                                                                   int(rng.gauss(0, 15000))]) for _ in range(4)), seq=seq))
        elif r < 0.7:
            frame = fp.encode(rng.choice([fp.Stop(seq=seq), fp.Heartbeat(seq=seq)]), version=rng.choice([1, 1, 1, 2]))
        else:
            frame = encode_frame(rng.randrange(256), seq, bytes(rng.randrange(256) for _ in range(rng.randrange(65))))
        if rng.random() < 0.3:
            frame = bytearray(frame)
            for _ in range(rng.randrange(1, 4)):
                frame[rng.randrange(len(frame))] ^= 1 << rng.randrange(8)
        out += frame
    return bytes(out[:size])


def test_sanitized_core_survives_a_fuzzed_byte_stream(tmp_path):
    cc = _find_gcc()
    if cc is None:
        pytest.skip("no C compiler")
    probe = tmp_path / "probe.c"
    probe.write_text("int main(void) { return 0; }\n", encoding="utf-8")
    res = _compile([cc, *SAN_FLAGS, str(probe), "-o", str(tmp_path / "probe")])
    if res.returncode == 0:
        res = subprocess.run([str(tmp_path / "probe")], capture_output=True, text=True, timeout=60,
                             env={**os.environ, **SAN_ENV})
    if res.returncode != 0:
        pytest.skip(f"{cc} cannot build or run -fsanitize=address,undefined here: {res.stderr.strip()[:300]}")
    (tmp_path / "fuzz.c").write_text(FUZZ_MAIN, encoding="utf-8")
    exe = tmp_path / "fuzz"
    res = _compile([cc, "-std=c99", "-Wall", "-Wextra", "-Werror", *SAN_FLAGS, "-I", str(C_DIR), *map(str, SOURCES),
                    str(tmp_path / "fuzz.c"), "-o", str(exe)])
    assert res.returncode == 0, res.stderr
    stream = fuzz_stream(seed=7, size=300_000)
    res = subprocess.run([str(exe), "7"], input=stream, capture_output=True, timeout=300,
                         env={**os.environ, **SAN_ENV})
    err = res.stderr.decode("utf-8", "replace")
    assert res.returncode == 0 and "runtime error" not in err and "Sanitizer" not in err, err[-3000:]
    counts = dict(zip(*[iter(err.split())] * 2))
    # everything the core transmitted is whole, valid frames, numbered without gaps but the drops
    d = fp.Decoder()
    msgs = d.feed(res.stdout)
    assert d.stats.dropped_frames == 0 and len(msgs) > 1000
    gaps = sum((b.seq - a.seq - 1) & 0xFF for a, b in zip(msgs, msgs[1:]))
    assert gaps == int(counts["tx_dropped"])
    assert int(counts["rx_errors"]) > 100 and int(counts["frames"]) > 1000 and int(counts["tx_dropped"]) > 0
    assert {type(m) for m in msgs} >= {fp.Ack, fp.Nack, fp.Status, fp.EncoderReport, fp.HelloReply}


# Cross build  -----------------------------------------------------------------------------------

def test_cross_build_for_cortex_m0_and_avr(tmp_path):
    missing = [c for c in ("arm-none-eabi-gcc", "avr-gcc") if shutil.which(c) is None]
    if missing:
        pytest.skip(f"{' and '.join(missing)} not installed (scripts/ensure_ci_tools.sh installs gcc-arm-none-eabi "
                    "and gcc-avr): the firmware cross build is not checked here")
    res = subprocess.run(["bash", str(ROOT / "scripts" / "build_firmware.sh")], capture_output=True, text=True,
                         timeout=600, env={**os.environ, "BUILD_DIR": str(tmp_path)})
    assert res.returncode == 0, res.stdout + res.stderr
    flash = {line.split()[0]: int(line.split()[2]) for line in res.stdout.splitlines() if line.startswith(("cortex-m0 ", "atmega328p "))
             and line.split()[1] == "flash"}
    assert set(flash) == {"cortex-m0", "atmega328p"}
    assert all(0 < v < 32 * 1024 for v in flash.values())  # fits the smallest parts of both families


def test_cross_build_fails_on_a_warning(tmp_path):
    if shutil.which("arm-none-eabi-gcc") is None:
        pytest.skip("arm-none-eabi-gcc not installed")
    src = tmp_path / "src"
    src.mkdir()
    for f in C_DIR.iterdir():
        if f.suffix in (".c", ".h"):
            shutil.copy(f, src / f.name)
    with open(src / "board_core.c", "a", encoding="utf-8") as fh:
        fh.write("\nstatic int unused_helper(void) { return 1; }\n")
    res = subprocess.run(["bash", str(ROOT / "scripts" / "build_firmware.sh"), "--target", "cortex-m0"],
                         capture_output=True, text=True, timeout=600,
                         env={**os.environ, "BUILD_DIR": str(tmp_path / "out"), "FIRMWARE_SRC": str(src)})
    assert res.returncode != 0 and "unused_helper" in res.stderr
