"""The v1 message table (PROTOCOL.md section 4). Fields are in wire units, named with them.

Each message is a frozen dataclass: its fields in payload order, then ``seq`` (the frame's
sequence number, 0..255). ``LAYOUT`` is the little-endian struct of the payload. Receivers
accept a payload longer than LAYOUT (fields appended by a newer minor version) and ignore the
tail; a shorter one is malformed.
"""

from __future__ import annotations

import enum
import math
import struct
from dataclasses import dataclass
from typing import ClassVar, Dict, Sequence, Tuple, Type

Quad = Tuple[int, int, int, int]

MRAD = 1000.0  # wire speeds are integer milliradians per second (and per second squared)


class NackReason(enum.IntEnum):
    UNKNOWN_MESSAGE = 1  # valid frame, id this board does not know; detail = 0
    CLAMPED = 2  # command applied after scaling into the board's limits; detail = wheels over the limit
    NO_SESSION = 3  # speed command before any HELLO since boot: ignored
    ESTOP = 4  # e-stop input active: command ignored, wheels held at zero
    MOTOR_FAULT = 5  # a motor driver reports a fault: ignored; detail = faulted wheels
    BAD_VERSION = 6  # frame of another major version; detail = that version


class StatusFlag(enum.IntFlag):
    WATCHDOG = 0x01  # command watchdog tripped: wheels ramped to zero; cleared by a new speed command
    ESTOP = 0x02  # e-stop input active
    CLAMPED = 0x04  # the last speed command was scaled into the limits
    HOST_SILENT = 0x08  # no valid frame of any kind for the watchdog period
    NO_SESSION = 0x10  # no HELLO since boot


@dataclass(frozen=True)
class Message:
    MSG_ID: ClassVar[int] = -1
    LAYOUT: ClassVar[struct.Struct] = struct.Struct("<")

    def payload(self) -> bytes:
        try:
            return self.LAYOUT.pack(*self._fields())
        except struct.error as e:
            raise ValueError(f"{type(self).__name__}: a field is out of range for its wire type ({e})") from None

    def _fields(self) -> tuple:
        return ()

    @classmethod
    def from_payload(cls, payload: bytes, seq: int) -> Message:
        """Build from a payload at least LAYOUT.size long (longer: appended fields, ignored)."""
        return cls._build(cls.LAYOUT.unpack_from(payload), seq)

    @classmethod
    def _build(cls, values: tuple, seq: int) -> Message:
        return cls(seq=seq)


@dataclass(frozen=True)
class Hello(Message):
    """Host -> board: open a session. The board answers HELLO_REPLY echoing ``nonce``."""

    MSG_ID: ClassVar[int] = 0x01
    LAYOUT: ClassVar[struct.Struct] = struct.Struct("<BI")
    minor: int = 0
    nonce: int = 0
    seq: int = 0

    def _fields(self) -> tuple:
        return (self.minor, self.nonce)

    @classmethod
    def _build(cls, values: tuple, seq: int) -> Message:
        return cls(*values, seq=seq)


@dataclass(frozen=True)
class SetWheelSpeeds(Message):
    """Host -> board: wheel speed targets, FL, FR, RL, RR, in mrad/s. Feeds the command watchdog."""

    MSG_ID: ClassVar[int] = 0x02
    LAYOUT: ClassVar[struct.Struct] = struct.Struct("<4i")
    speeds_mrad_s: Quad = (0, 0, 0, 0)
    seq: int = 0

    def _fields(self) -> tuple:
        return tuple(self.speeds_mrad_s)

    @classmethod
    def _build(cls, values: tuple, seq: int) -> Message:
        return cls(tuple(values), seq=seq)

    @classmethod
    def from_rad_s(cls, speeds: Sequence[float], seq: int = 0) -> SetWheelSpeeds:
        if len(speeds) != 4:
            raise ValueError(f"wheel speeds must be 4 finite numbers, got {list(speeds)!r}")
        s0, s1, s2, s3 = speeds  # written out: fifty commands a second
        if not (math.isfinite(s0) and math.isfinite(s1) and math.isfinite(s2) and math.isfinite(s3)):
            raise ValueError(f"wheel speeds must be 4 finite numbers, got {list(speeds)!r}")
        return cls((int(round(s0 * MRAD)), int(round(s1 * MRAD)), int(round(s2 * MRAD)), int(round(s3 * MRAD))),
                   seq=seq)

    @property
    def rad_s(self) -> Tuple[float, ...]:
        return tuple(s / MRAD for s in self.speeds_mrad_s)


@dataclass(frozen=True)
class Stop(Message):
    """Host -> board: ramp all wheels to zero. Accepted in every state, session or not."""

    MSG_ID: ClassVar[int] = 0x03
    seq: int = 0


@dataclass(frozen=True)
class Heartbeat(Message):
    """Host -> board: host alive. Keeps HOST_SILENT clear; does NOT keep wheels turning."""

    MSG_ID: ClassVar[int] = 0x04
    seq: int = 0


@dataclass(frozen=True)
class HelloReply(Message):
    """Board -> host: versions, firmware, and the board's own limits and rates."""

    MSG_ID: ClassVar[int] = 0x81
    LAYOUT: ClassVar[struct.Struct] = struct.Struct("<BIBBBIIIHHH")
    minor: int = 0
    nonce: int = 0
    fw_major: int = 0
    fw_minor: int = 0
    fw_patch: int = 0
    ticks_per_rev: int = 0
    max_speed_mrad_s: int = 0
    max_accel_mrad_s2: int = 0
    watchdog_ms: int = 0
    report_period_us: int = 0
    capabilities: int = 0  # bit field for optional features; none defined in v1.0
    seq: int = 0

    def _fields(self) -> tuple:
        return (self.minor, self.nonce, self.fw_major, self.fw_minor, self.fw_patch, self.ticks_per_rev,
                self.max_speed_mrad_s, self.max_accel_mrad_s2, self.watchdog_ms, self.report_period_us,
                self.capabilities)

    @classmethod
    def _build(cls, values: tuple, seq: int) -> Message:
        return cls(*values, seq=seq)


@dataclass(frozen=True)
class EncoderReport(Message):
    """Board -> host at 100 Hz: board clock (us, wraps at 2^32) and cumulative ticks (wrap at 2^32)."""

    MSG_ID: ClassVar[int] = 0x82
    LAYOUT: ClassVar[struct.Struct] = struct.Struct("<I4i")
    t_us: int = 0
    ticks: Quad = (0, 0, 0, 0)
    seq: int = 0

    def _fields(self) -> tuple:
        return (self.t_us,) + tuple(self.ticks)

    @classmethod
    def _build(cls, values: tuple, seq: int) -> Message:
        return cls(values[0], tuple(values[1:]), seq=seq)


@dataclass(frozen=True)
class Status(Message):
    """Board -> host at 10 Hz and at once on any flag change."""

    MSG_ID: ClassVar[int] = 0x83
    LAYOUT: ClassVar[struct.Struct] = struct.Struct("<IHBBH")
    t_us: int = 0
    battery_mv: int = 0
    motor_faults: int = 0  # bit i: wheel i (FL, FR, RL, RR) motor driver fault
    flags: int = 0  # StatusFlag bits
    rx_errors: int = 0  # frames the board dropped (CRC, COBS, length), saturating at 65535
    seq: int = 0

    def _fields(self) -> tuple:
        return (self.t_us, self.battery_mv, self.motor_faults, self.flags, self.rx_errors)

    @classmethod
    def _build(cls, values: tuple, seq: int) -> Message:
        return cls(*values, seq=seq)


@dataclass(frozen=True)
class Ack(Message):
    """Board -> host: the command (ref_id, ref_seq) was applied as sent."""

    MSG_ID: ClassVar[int] = 0x84
    LAYOUT: ClassVar[struct.Struct] = struct.Struct("<BB")
    ref_id: int = 0
    ref_seq: int = 0
    seq: int = 0

    def _fields(self) -> tuple:
        return (self.ref_id, self.ref_seq)

    @classmethod
    def _build(cls, values: tuple, seq: int) -> Message:
        return cls(*values, seq=seq)


@dataclass(frozen=True)
class Nack(Message):
    """Board -> host: the command (ref_id, ref_seq) was refused or altered; see NackReason."""

    MSG_ID: ClassVar[int] = 0x85
    LAYOUT: ClassVar[struct.Struct] = struct.Struct("<BBBB")
    ref_id: int = 0
    ref_seq: int = 0
    reason: int = 0
    detail: int = 0
    seq: int = 0

    def _fields(self) -> tuple:
        return (self.ref_id, self.ref_seq, self.reason, self.detail)

    @classmethod
    def _build(cls, values: tuple, seq: int) -> Message:
        return cls(*values, seq=seq)


@dataclass(frozen=True)
class UnknownMessage(Message):
    """An intact frame with an id this side does not know (a newer peer's message)."""

    msg_id: int = 0
    data: bytes = b""
    seq: int = 0

    def payload(self) -> bytes:
        return bytes(self.data)


MESSAGE_TYPES: Dict[int, Type[Message]] = {
    cls.MSG_ID: cls
    for cls in (Hello, SetWheelSpeeds, Stop, Heartbeat, HelloReply, EncoderReport, Status, Ack, Nack)
}
