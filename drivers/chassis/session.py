"""The host end of the motor-board protocol without I/O: bytes in, messages and odometry out. Pure.

Both chassis backends drive one ``HostSession``, so the protocol means the same on the robot and
in simulation: ``SerialChassis`` feeds it what its reader thread reads from the port and writes
the frames it makes; ``LoopbackChassis`` hands bytes to and from the in-process board model. It
holds, once:

- the frames the host sends, numbered by one sequence counter;
- the handshake: the HELLO nonce, the reply that belongs to it, and the checks that refuse a
  board (another protocol version, other ticks per revolution);
- encoder reports to odometry: the board clock unwrapped and mapped to the host's
  (``BoardClock``), board resets detected, ticks differenced by ``EncoderOdometry``;
- the signs that the board lost the session: NO_SESSION in a STATUS or a NACK, a board clock
  that jumped, reports that stopped coming.

Times are arguments (receive times), never read from a clock, so a simulated clock drives it
exactly as the host's monotonic clock does. One instance lives as long as its chassis: the
odometry stays continuous across reconnects.
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass, field
from typing import Counter, Deque, List, Optional, Sequence, Tuple

from drivers.chassis.base import ChassisStatus
from drivers.chassis.encoders import EncoderOdometry
from firmware_protocol import (
    PROTOCOL_MINOR,
    PROTOCOL_VERSION,
    Ack,
    Decoder,
    EncoderReport,
    Hello,
    HelloReply,
    Message,
    Nack,
    NackReason,
    Status,
    UnknownMessage,
    encode,
)
from firmware_protocol.counters import delta_u32
from robot.base.errors import DriverError
from robot.base.samples import WheelOdometry
from robot.config import ChassisConfig

CLOCK_WINDOW = 2.0  # s of reports the board-to-host clock offset is taken over
HEARTBEAT_PERIOD = 0.1  # s of no transmission before a heartbeat: half the board's watchdog
WATCHDOG_MISMATCH = 0.0015  # s: a board watchdog further than this from the config's is worth a warning


class BoardRefused(DriverError):
    """The board answers but must not be driven: another protocol version or ticks per revolution."""


class BoardClock:
    """Maps the board's wrapping microsecond clock to host seconds.

    Unwrapping: consecutive stamps differ by the unsigned 32-bit difference (the clock wraps every
    71.6 min). Mapping: t_host = t_board + offset, with offset the minimum of (receive time -
    frame transmission time - t_board) over the last CLOCK_WINDOW seconds: transport delay is never
    negative, so the minimum is the least-delayed frame, and the window follows crystal drift.
    """

    def __init__(self, window: float = CLOCK_WINDOW):
        self.window = window
        self.reset()

    def reset(self) -> None:
        self._last_us: Optional[int] = None
        self._board_s = 0.0
        self._mins: Deque[Tuple[float, float]] = collections.deque()  # (board_s, offset), increasing offsets
        self._last_t = -math.inf

    def unwrap(self, t_us: int) -> float:
        if self._last_us is not None:
            self._board_s += delta_u32(t_us, self._last_us) * 1e-6
        else:
            self._board_s = t_us * 1e-6
        self._last_us = t_us
        return self._board_s

    def to_host(self, board_s: float, t_rx: float, latency: float = 0.0) -> float:
        offset = t_rx - latency - board_s
        mins = self._mins
        while mins and mins[-1][1] >= offset:
            mins.pop()
        mins.append((board_s, offset))
        while mins[0][0] < board_s - self.window:
            mins.popleft()
        t = board_s + mins[0][1]
        # a new minimum can pull the estimate back: never let sample times run backwards
        t = max(t, self._last_t)
        self._last_t = t
        return t


def check_wheels(wheels: object) -> List[float]:
    """Four finite wheel speeds (rad/s, FL, FR, RL, RR) as floats, else ValueError naming what came."""
    try:
        w = [float(v) for v in wheels]  # type: ignore[union-attr]
    except (TypeError, ValueError):
        w = []
    if len(w) != 4 or not (math.isfinite(w[0]) and math.isfinite(w[1]) and math.isfinite(w[2]) and math.isfinite(w[3])):
        raise ValueError(f"wheel speeds must be 4 finite numbers (rad/s), got {wheels!r}; wheels stopped")
    return w


def scale_into(wheels: Sequence[float], limit: float) -> Tuple[List[float], bool]:
    """Speeds beyond ``limit`` scaled down together, which keeps the direction of travel; and
    whether they had to be."""
    peak = max(map(abs, wheels))
    if peak <= limit:
        return list(wheels), False
    return [v * limit / peak for v in wheels], True


def _nack_reason(m: Nack) -> str:
    try:
        return NackReason(m.reason).name
    except ValueError:
        return f"reason {m.reason}"


def nack_text(m: Nack) -> str:
    """What a NACK says, for a log line or ``last_error``."""
    return f"board refused message {m.ref_id:#04x} seq {m.ref_seq}: {_nack_reason(m)}"


@dataclass
class Received:
    """What one batch of board messages gave the host."""

    odometry: List[WheelOdometry] = field(default_factory=list)
    status: Optional[ChassisStatus] = None  # the newest STATUS of the batch
    reply: Optional[HelloReply] = None  # the answer to the pending HELLO
    acks: List[Ack] = field(default_factory=list)
    nacks: List[Nack] = field(default_factory=list)


class HostSession:
    """The host's protocol state for one motor board; see the module docstring.

    Threads: ``decode`` may run on a reader thread (it only touches the decoder); everything else
    belongs to one thread (the event loop, or the simulation's).
    """

    def __init__(self, config: ChassisConfig, name: str = "motor board"):
        self.config = config
        self.name = name  # leads every error message (the port, for the serial driver)
        self.decoder = Decoder()
        self.encoders = EncoderOdometry(config.ticks_per_rev, config.max_wheel_speed)
        self.clock = BoardClock()
        self.counters: Counter[str] = collections.Counter()
        self.board_info: Optional[HelloReply] = None
        self.status: Optional[ChassisStatus] = None
        self.max_wheel_speed = float(config.max_wheel_speed)  # the lower of the config's and the board's
        self.ready = False  # handshake accepted and not lost since: commands may go out
        self.lost_reason: Optional[str] = None  # why the current connection is no good, first reason wins
        self.last_report_rx = -math.inf
        self.last_error = ""
        self.last_seq = -1  # sequence number of the last frame made
        self._tx_seq = 0
        self._rx_seq: Optional[int] = None  # seq of the board's last frame: it counts every frame it sends
        self._nonce: Optional[int] = None
        self._mismatches = 0
        self._prev_report: Optional[Tuple[int, float]] = None  # (t_us, receive time) of the last report
        self._fresh = False  # the next report is the first since a handshake

    # Frames to the board  -----------------------------------------------------------------------

    def frame(self, msg: Message) -> bytes:
        """``msg`` numbered with the next sequence number (``last_seq``), as wire bytes."""
        seq = self._tx_seq
        self._tx_seq = (seq + 1) & 0xFF
        self.last_seq = seq
        return encode(msg, seq=seq)

    # The handshake  -----------------------------------------------------------------------------

    def begin(self, nonce: int) -> None:
        """A new connection: forget the old byte stream and wait for the reply to HELLO ``nonce``."""
        self.decoder.reset()
        self._rx_seq = None
        self._nonce = int(nonce) & 0xFFFFFFFF
        self._mismatches = self.decoder.stats.version_mismatch
        self.ready = False
        self.lost_reason = None

    def hello(self) -> bytes:
        """The HELLO of the pending handshake (resend it until the reply comes)."""
        if self._nonce is None:
            raise RuntimeError("begin() a handshake before sending HELLO")
        return self.frame(Hello(minor=PROTOCOL_MINOR, nonce=self._nonce))

    def version_refusal(self) -> Optional[BoardRefused]:
        """The error to raise when the board answered in another protocol version since ``begin``."""
        if self.decoder.stats.version_mismatch == self._mismatches:
            return None
        return BoardRefused(f"{self.name}: the board speaks protocol version {self.decoder.stats.foreign_version}, "
                            f"this host speaks {PROTOCOL_VERSION}: flash matching firmware or update the host")

    def accept(self, reply: HelloReply, t: float) -> List[str]:
        """Take the board's reply at time ``t``: ready to drive, or BoardRefused naming why not.

        Returns warnings worth logging (the board's watchdog differs from the config's)."""
        if reply.ticks_per_rev != self.config.ticks_per_rev:
            raise BoardRefused(f"{self.name}: the board counts {reply.ticks_per_rev} encoder ticks per wheel "
                               f"revolution, the config says ticks_per_rev: {self.config.ticks_per_rev}")
        warnings = []
        board_wd = reply.watchdog_ms / 1000.0
        if abs(board_wd - self.config.watchdog_timeout) > WATCHDOG_MISMATCH:
            warnings.append(f"{self.name}: board watchdog is {board_wd:.3f} s, config says "
                            f"{self.config.watchdog_timeout:.3f} s")
        self.board_info = reply
        self.max_wheel_speed = min(float(self.config.max_wheel_speed), reply.max_speed_mrad_s / 1000.0)
        self.last_report_rx = t
        self._fresh = True
        self._nonce = None
        self.ready = True
        return warnings

    def end(self, reason: Optional[str] = None) -> None:
        """The connection is over (lost or closed): reports no longer count until the next handshake."""
        if reason is not None:
            self.lose(reason)
        self.ready = False

    def lose(self, reason: str) -> None:
        """Mark the connection unusable; the first reason is the one reported."""
        if self.lost_reason is None:
            self.lost_reason = reason

    def silence(self, now: float) -> Optional[str]:
        """Why the link is dead at ``now`` because reports stopped, or None while they come."""
        gap = now - self.last_report_rx
        if self.ready and gap > self.config.link_timeout:
            return f"no encoder report for {gap:.3f} s"
        return None

    def usable(self, now: float) -> bool:
        """May a speed command go out at ``now``? Marks the link lost when reports stopped."""
        if not self.ready:
            return False
        if self.silence(now) is not None:
            self.lose("encoder reports stopped")
        return self.lost_reason is None

    # Bytes and messages from the board  ---------------------------------------------------------

    def decode(self, data: bytes) -> List[Message]:
        return self.decoder.feed(data)

    def handle(self, msgs: Sequence[Message], t_rx: float, latency: float = 0.0) -> Received:
        """Messages received at ``t_rx``; ``latency`` is a report frame's transmission time."""
        out = Received()
        for m in msgs:
            if self._rx_seq is not None:
                self.counters["rx_frames_lost"] += (m.seq - self._rx_seq - 1) & 0xFF
            self._rx_seq = m.seq
            if isinstance(m, EncoderReport):
                sample = self._on_report(m, t_rx, latency)
                if sample is not None:
                    out.odometry.append(sample)
            elif isinstance(m, Status):
                out.status = self._on_status(m, t_rx)
            elif isinstance(m, Ack):
                self.counters["acks"] += 1
                out.acks.append(m)
            elif isinstance(m, Nack):
                self._on_nack(m)
                out.nacks.append(m)
            elif isinstance(m, HelloReply):
                if self._nonce is not None and m.nonce == self._nonce:
                    out.reply = m
            elif isinstance(m, UnknownMessage):
                self.counters["unknown_messages"] += 1
        return out

    def _on_status(self, m: Status, t_rx: float) -> ChassisStatus:
        st = ChassisStatus.from_message(m, t_rx)
        self.status = st
        if st.no_session and self.ready:
            self.lose("the board lost the session (reset?)")
        return st

    def _on_nack(self, m: Nack) -> None:
        self.counters["nacks"] += 1
        self.counters[f"nack_{_nack_reason(m).lower()}"] += 1
        self.last_error = nack_text(m)
        if m.reason == NackReason.NO_SESSION and self.ready:
            # the board restarted under an open line: its new session needs a new handshake
            self.lose("the board lost the session (reset?)")

    def _board_jumped(self, t_us: int, t_rx: float) -> bool:
        """Did the board's clock run differently from ours since the last report (a reset)?

        Within a session only a board clock ahead of ours counts: a stalled reader delivers old
        reports late, which makes the host gap longer, never shorter. Across a reconnect, either
        way counts: after a reset the clock may have restarted anywhere.
        """
        gap_board = delta_u32(t_us, self._prev_report[0]) * 1e-6
        gap_host = t_rx - self._prev_report[1]
        tol = 0.25 + 0.02 * gap_host
        return gap_board > gap_host + tol or (self._fresh and gap_board < gap_host - tol)

    def _on_report(self, m: EncoderReport, t_rx: float, latency: float) -> Optional[WheelOdometry]:
        if not self.ready:
            return None  # reports outside a session set no baseline
        self.last_report_rx = t_rx
        if self._prev_report is not None and self._board_jumped(m.t_us, t_rx):
            self.encoders.reset_baseline()
            self.clock.reset()
            self.counters["board_resets"] += 1
            if not self._fresh:
                self.lose("the board clock jumped (reset?)")
        self._fresh = False
        self._prev_report = (m.t_us, t_rx)
        board_s = self.clock.unwrap(m.t_us)
        t = self.clock.to_host(board_s, t_rx, latency)
        before = self.encoders.implausible
        sample = self.encoders.update(m.ticks, board_s, t)
        if self.encoders.implausible != before:
            self.counters["implausible_reports"] += 1  # faster than any wheel: counters reset or garbage
        if sample is not None:
            self.counters["odometry_samples"] += 1
        return sample
