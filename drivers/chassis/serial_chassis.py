"""The Mecanum motor board over a serial line (PROTOCOL.md): handshake, commands, odometry, status.

Threads and the loop: one reader thread per open port blocks in ``serial.read`` and decodes (the
codec is pure), then hands the messages with their host receive time to the asyncio loop with
``call_soon_threadsafe``. Everything else runs on the loop: the state machine, odometry, and the
writes, which are non-blocking (a frame the OS will not take is dropped and counted, never
queued: a late speed command is worse than none).

Safety rules this class keeps (tests/test_chassis_driver.py proves them against the emulator):

- no speed command before the handshake or while the link is down (``send_wheel_speeds`` returns
  False instead);
- the driver never repeats a speed command by itself: only fresh commands from the caller feed
  the board's watchdog, so a hung control loop stops the robot within the watchdog period;
- STOP on link loss (best effort) and on close;
- bad input (not 4 finite numbers) stops the wheels and raises ValueError.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import math
import os
import random
import threading
import time
from typing import Callable, Deque, Dict, List, Optional, Sequence, Tuple

import serial

from drivers.chassis.base import Chassis, ChassisStatus, LinkState
from drivers.chassis.encoders import EncoderOdometry
from firmware_protocol import (
    PROTOCOL_MINOR,
    PROTOCOL_VERSION,
    Ack,
    Decoder,
    EncoderReport,
    Heartbeat,
    Hello,
    HelloReply,
    Message,
    Nack,
    NackReason,
    SetWheelSpeeds,
    Status,
    Stop,
    UnknownMessage,
    encode,
)
from firmware_protocol.counters import delta_u32
from robot.base.errors import DriverError
from robot.base.samples import WheelOdometry
from robot.config import ChassisConfig

log = logging.getLogger(__name__)

HANDSHAKE_TIMEOUT = 1.0  # s to wait for HELLO_REPLY (HELLO is resent every HELLO_RESEND)
HELLO_RESEND = 0.25
HEARTBEAT_PERIOD = 0.1  # s of no transmission before a heartbeat: half the board's watchdog
BACKOFF_START = 0.05  # s, first reconnect delay; doubles up to config.reconnect_backoff_max
READ_TIMEOUT = 0.05  # s a blocked read waits, bounding how long closing the port takes
CLOCK_WINDOW = 2.0  # s of reports the board-to-host clock offset is taken over
_TWO_PI = 2.0 * math.pi
_REPORT_WIRE_BYTES = 3 + EncoderReport.LAYOUT.size + 4 + 3  # header + payload + CRC + COBS byte + 2 delimiters


def reconnect_delay(attempt: int, cap: float) -> float:
    """Seconds to wait before reconnect attempt ``attempt`` (0, 1, ...): doubling, capped."""
    return min(BACKOFF_START * 2.0 ** min(attempt, 30), cap)


class BoardClock:
    """Maps the board's wrapping microsecond clock to host monotonic seconds.

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


class _Fatal(DriverError):
    """The board answers but must not be driven (version or configuration mismatch)."""


class SerialChassis(Chassis):
    """Asyncio driver of the motor board. Create, ``await connect()``, command, ``await close()``.

    ``port`` defaults to ``config.port``; anything ``serial.serial_for_url`` opens works (a pty
    path in tests). Odometry and status arrive on the loop through ``on_odometry`` /
    ``on_status`` callbacks and ``odometry_queue()``.
    """

    def __init__(self, config: Optional[ChassisConfig] = None, port: Optional[str] = None,
                 on_odometry: Optional[Callable[[WheelOdometry], None]] = None,
                 on_status: Optional[Callable[[ChassisStatus], None]] = None):
        self.config = config or ChassisConfig()
        self.port = str(port or self.config.port)
        self.on_odometry = on_odometry
        self.on_status = on_status
        self.board_info: Optional[HelloReply] = None
        self.last_error = ""
        self._state = LinkState.CLOSED
        self._status: Optional[ChassisStatus] = None
        self._max_speed = self.config.max_wheel_speed
        self._counters: Dict[str, int] = collections.Counter()
        self._queues: List[asyncio.Queue] = []
        self._ser = None
        self._fd: Optional[int] = None
        self._reader: Optional[threading.Thread] = None
        self._reader_stop = threading.Event()
        self._gen = 0  # connection generation: events from an older reader are ignored
        self._decoder = Decoder()
        self._tx_seq = 0
        self._last_tx = 0.0
        self._last_report_rx = 0.0
        self.last_command_time = -math.inf  # host monotonic time the last speed command went out
        self._lost_reason: Optional[str] = None
        self._hello_wait: Optional[Tuple[int, asyncio.Future]] = None
        self._loop: Optional[asyncio.AbstractEventLoop] = None
        self._supervisor: Optional[asyncio.Task] = None
        self._closing = False
        # odometry state
        self._clock = BoardClock()
        # host-side cumulative angles: continuous across board resets and reconnects
        self._encoders = EncoderOdometry(self.config.ticks_per_rev, self.config.max_wheel_speed)
        self._prev_report: Optional[Tuple[int, float]] = None  # (t_us, host rx time) of the last report
        self._rx_seq: Optional[int] = None  # seq of the board's last frame: it counts every frame it sends
        self._fresh_session = False  # the next report is the first since a handshake
        self._stop_ack: Optional[Tuple[int, asyncio.Future]] = None

    # Public interface  ------------------------------------------------------------------------

    @property
    def link_state(self) -> LinkState:
        return self._state

    @property
    def status(self) -> Optional[ChassisStatus]:
        """The latest STATUS from the board, or None before the first."""
        return self._status

    @property
    def max_wheel_speed(self) -> float:
        """The limit commands are scaled into: the lower of the config's and the board's."""
        return self._max_speed

    @property
    def stats(self) -> Dict[str, object]:
        d: Dict[str, object] = dict(self._counters)
        d.update({f"rx_{k}": v for k, v in self._decoder.stats.as_dict().items()})
        return d

    async def connect(self) -> None:
        """Open the port and handshake; raise DriverError naming the problem if that fails.

        After a successful connect the driver supervises the link on its own: on loss it stops
        commanding and reconnects with capped backoff until ``close()``.
        """
        if self._supervisor is not None:
            return
        self._loop = asyncio.get_running_loop()
        self._closing = False
        try:
            await self._open_and_handshake()
        except DriverError:
            await self._drop_port()
            self._state = LinkState.CLOSED
            raise
        self._supervisor = self._loop.create_task(self._supervise())

    def send_wheel_speeds(self, wheels: Sequence[float]) -> bool:
        """Command wheel speeds (rad/s, FL, FR, RL, RR). True if the command went out.

        Refused (False) before the handshake and while the link is down. Speeds beyond the limit
        are scaled down together, keeping the direction of travel. Call it at the control rate:
        the board stops the wheels when commands stop coming.
        """
        try:
            w = [float(v) for v in wheels]
        except (TypeError, ValueError):
            w = []
        if len(w) != 4 or not all(math.isfinite(v) for v in w):
            self.stop()
            raise ValueError(f"wheel speeds must be 4 finite numbers (rad/s), got {wheels!r}; wheels stopped")
        if not self._link_usable():
            self._counters["commands_refused"] += 1
            return False
        peak = max(abs(v) for v in w)
        if peak > self._max_speed:
            w = [v * self._max_speed / peak for v in w]
            self._counters["commands_scaled"] += 1
        msg = SetWheelSpeeds.from_rad_s(w, seq=self._next_seq())
        if self._write(encode(msg)):
            self._counters["commands_sent"] += 1
            self.last_command_time = self._last_tx
            return True
        return False

    def stop(self) -> bool:
        """Ramp the wheels to zero. Sent whenever the port is open, handshake or not."""
        if self._ser is None:
            return False
        return self._write(encode(Stop(seq=self._next_seq())))

    def odometry_queue(self, maxsize: int = 256) -> asyncio.Queue:
        """A new queue fed every WheelOdometry; when full the oldest sample is dropped."""
        q: asyncio.Queue = asyncio.Queue(maxsize=maxsize)
        self._queues.append(q)
        return q

    async def close(self) -> None:
        """Send STOP (waiting briefly for its ACK), stop supervising and release the port. Idempotent."""
        self._closing = True
        if self._supervisor is not None:
            self._supervisor.cancel()
            try:
                await self._supervisor
            except asyncio.CancelledError:
                pass
            self._supervisor = None
        if self._ser is not None:
            seq = self._next_seq()
            fut = self._loop.create_future()
            self._stop_ack = (seq, fut)
            if self._write(encode(Stop(seq=seq))):
                try:
                    await asyncio.wait_for(fut, 0.3)
                except asyncio.TimeoutError:
                    log.warning("%s: no ACK for the STOP sent on close", self.port)
        await self._drop_port()
        self._state = LinkState.CLOSED

    async def __aenter__(self) -> SerialChassis:
        await self.connect()
        return self

    async def __aexit__(self, *exc) -> None:
        await self.close()

    # Connection lifecycle  --------------------------------------------------------------------

    async def _supervise(self) -> None:
        attempt = 0
        while not self._closing:
            if self._state is LinkState.READY:
                reason = await self._monitor()
                self._mark_lost(reason)
                self.stop()  # best effort: the board may still hear us even if it went quiet
                await self._drop_port()
                attempt = 0
            await asyncio.sleep(reconnect_delay(attempt, self.config.reconnect_backoff_max))
            attempt += 1
            self._counters["connect_attempts"] += 1
            try:
                await self._open_and_handshake()
                log.info("%s: link up again (%s)", self.port, self._describe_board())
                self._counters["reconnects"] += 1
            except DriverError as e:
                self.last_error = str(e)
                # loud once, quiet on repeats
                log.log(logging.WARNING if attempt == 1 else logging.DEBUG, "%s: reconnect failed: %s", self.port, e)
                self._state = LinkState.FAULT if isinstance(e, _Fatal) else LinkState.LOST
                await self._drop_port()

    async def _monitor(self) -> str:
        """Wait while the link is healthy, sending heartbeats; return why it is not any more."""
        tick = max(0.005, min(0.02, self.config.link_timeout / 4.0))
        while True:
            await asyncio.sleep(tick)
            now = time.monotonic()
            if self._lost_reason is not None:
                return self._lost_reason
            if now - self._last_report_rx > self.config.link_timeout:
                return f"no encoder report for {now - self._last_report_rx:.3f} s"
            if now - self._last_tx > HEARTBEAT_PERIOD:
                self._write(encode(Heartbeat(seq=self._next_seq())))

    async def _open_and_handshake(self) -> None:
        self._state = LinkState.CONNECTING
        self._lost_reason = None
        try:
            ser = serial.serial_for_url(self.port, baudrate=self.config.baud, timeout=READ_TIMEOUT,
                                        write_timeout=0.02, exclusive=True)
            ser.reset_input_buffer()
        except (serial.SerialException, OSError, ValueError) as e:
            raise DriverError(f"{self.port}: cannot open the motor board's serial port: {e}") from e
        try:
            self._fd = ser.fileno()
        except (AttributeError, OSError, ValueError):
            self._fd = None  # a URL transport without a descriptor (loop://): pyserial's writes
        self._ser = ser
        self._gen += 1
        self._decoder.reset()
        self._rx_seq = None
        self._reader_stop = threading.Event()
        self._reader = threading.Thread(target=self._read_loop, args=(ser, self._gen, self._reader_stop),
                                        name=f"chassis-reader-{self._gen}", daemon=True)
        self._reader.start()
        nonce = random.getrandbits(32)
        fut = self._loop.create_future()
        self._hello_wait = (nonce, fut)
        mismatches = self._decoder.stats.version_mismatch
        deadline = time.monotonic() + HANDSHAKE_TIMEOUT
        try:
            while True:
                self._write(encode(Hello(minor=PROTOCOL_MINOR, nonce=nonce, seq=self._next_seq())))
                left = deadline - time.monotonic()
                try:
                    reply = await asyncio.wait_for(asyncio.shield(fut), max(0.0, min(HELLO_RESEND, left)))
                    break
                except asyncio.TimeoutError:
                    pass
                if self._decoder.stats.version_mismatch != mismatches:
                    raise _Fatal(f"{self.port}: the board speaks protocol version "
                                 f"{self._decoder.stats.foreign_version}, this host speaks {PROTOCOL_VERSION}: "
                                 "flash matching firmware or update the host")
                if self._lost_reason is not None:
                    raise DriverError(f"{self.port}: {self._lost_reason} during the handshake")
                if time.monotonic() >= deadline:
                    raise DriverError(f"{self.port}: no answer to HELLO within {HANDSHAKE_TIMEOUT:.1f} s "
                                      "(board off, wrong port or baud rate?)")
        finally:
            self._hello_wait = None
        self._check_board(reply)
        self.board_info = reply
        self._max_speed = min(self.config.max_wheel_speed, reply.max_speed_mrad_s / 1000.0)
        self._last_report_rx = time.monotonic()
        self._fresh_session = True
        self._state = LinkState.READY

    def _check_board(self, reply: HelloReply) -> None:
        if reply.ticks_per_rev != self.config.ticks_per_rev:
            self._state = LinkState.FAULT
            raise _Fatal(f"{self.port}: the board counts {reply.ticks_per_rev} encoder ticks per wheel revolution, "
                         f"the config says ticks_per_rev: {self.config.ticks_per_rev}")
        board_wd = reply.watchdog_ms / 1000.0
        if abs(board_wd - self.config.watchdog_timeout) > 0.0015:
            log.warning("%s: board watchdog is %.3f s, config says %.3f s", self.port, board_wd,
                        self.config.watchdog_timeout)

    def _describe_board(self) -> str:
        b = self.board_info
        if b is None:
            return "no board"
        return (f"firmware {b.fw_major}.{b.fw_minor}.{b.fw_patch}, protocol {PROTOCOL_VERSION}.{b.minor}, "
                f"{b.ticks_per_rev} ticks/rev, max {b.max_speed_mrad_s / 1000:.1f} rad/s")

    def _mark_lost(self, reason: str) -> None:
        if self._state is LinkState.READY:
            log.warning("%s: link lost: %s", self.port, reason)
            self._counters["link_losses"] += 1
        self.last_error = reason
        self._state = LinkState.LOST

    def _link_usable(self) -> bool:
        if self._state is not LinkState.READY:
            return False
        if time.monotonic() - self._last_report_rx > self.config.link_timeout:
            self._lost_reason = self._lost_reason or "encoder reports stopped"
            return False
        return self._lost_reason is None

    async def _drop_port(self) -> None:
        ser, reader = self._ser, self._reader
        self._ser = None
        self._fd = None
        self._reader = None
        self._gen += 1
        try:
            if reader is not None:
                self._reader_stop.set()
                try:
                    ser.cancel_read()
                except (AttributeError, OSError, serial.SerialException):
                    pass
                await self._loop.run_in_executor(None, reader.join, 1.0)
        finally:
            # even when cancelled mid-join: the port is released (the reader then fails and exits)
            if ser is not None:
                try:
                    ser.close()
                except (OSError, serial.SerialException):
                    pass

    # I/O  -------------------------------------------------------------------------------------

    def _next_seq(self) -> int:
        seq = self._tx_seq
        self._tx_seq = (seq + 1) & 0xFF
        return seq

    def _write(self, data: bytes) -> bool:
        """Non-blocking write of whole frames. A short write loses the frame, never the link:
        each frame starts with a delimiter, so the board resynchronises on the next one."""
        ser = self._ser
        if ser is None:
            return False
        try:
            if self._fd is not None:
                n = os.write(self._fd, data)
            else:
                n = ser.write(data) or 0
        except (BlockingIOError, serial.SerialTimeoutException):
            n = 0
        except (OSError, serial.SerialException) as e:
            self._lost_reason = self._lost_reason or f"write failed: {e}"
            return False
        self._last_tx = time.monotonic()
        if n < len(data):
            self._counters["tx_dropped"] += 1
            return False
        self._counters["frames_sent"] += 1
        return True

    def _read_loop(self, ser, gen: int, stop: threading.Event) -> None:
        """Reader thread: block in read, decode, hand messages to the loop. Owns the decoder."""
        loop = self._loop
        decoder = self._decoder
        while not stop.is_set():
            try:
                data = ser.read(1)
                if data:
                    waiting = ser.in_waiting
                    if waiting:
                        data += ser.read(waiting)
            except Exception as e:  # pyserial raises several types when a device vanishes
                if not stop.is_set():
                    self._post(loop, self._on_port_error, gen, f"port error: {e}")
                return
            if not data:
                continue
            t_rx = time.monotonic()
            msgs = decoder.feed(data)
            if msgs and not self._post(loop, self._on_messages, gen, t_rx, msgs):
                return

    @staticmethod
    def _post(loop, fn, *args) -> bool:
        try:
            loop.call_soon_threadsafe(fn, *args)
            return True
        except RuntimeError:  # the loop is closed: nobody is listening any more
            return False

    # Message handling (on the loop)  ----------------------------------------------------------

    def _on_port_error(self, gen: int, reason: str) -> None:
        if gen == self._gen:
            self._lost_reason = self._lost_reason or reason

    def _on_messages(self, gen: int, t_rx: float, msgs: List[Message]) -> None:
        if gen != self._gen:
            return
        for m in msgs:
            if self._rx_seq is not None:
                self._counters["rx_frames_lost"] += (m.seq - self._rx_seq - 1) & 0xFF
            self._rx_seq = m.seq
            if isinstance(m, EncoderReport):
                self._on_report(m, t_rx)
            elif isinstance(m, Status):
                self._on_status(m, t_rx)
            elif isinstance(m, Ack):
                self._counters["acks"] += 1
                stop_ack = self._stop_ack
                if stop_ack and m.ref_id == Stop.MSG_ID and m.ref_seq == stop_ack[0] and not stop_ack[1].done():
                    stop_ack[1].set_result(m)
            elif isinstance(m, Nack):
                self._on_nack(m)
            elif isinstance(m, HelloReply):
                if self._hello_wait and m.nonce == self._hello_wait[0] and not self._hello_wait[1].done():
                    self._hello_wait[1].set_result(m)
            elif isinstance(m, UnknownMessage):
                self._counters["unknown_messages"] += 1

    def _on_nack(self, m: Nack) -> None:
        self._counters["nacks"] += 1
        try:
            reason = NackReason(m.reason).name
        except ValueError:
            reason = f"reason {m.reason}"
        self._counters[f"nack_{reason.lower()}"] += 1
        self.last_error = f"board refused message {m.ref_id:#04x} seq {m.ref_seq}: {reason}"
        if m.reason == NackReason.NO_SESSION and self._state is LinkState.READY:
            # the board restarted under an open port: its new session needs a new handshake
            self._lost_reason = self._lost_reason or "the board lost the session (reset?)"
        elif m.reason != NackReason.CLAMPED:
            log.warning("%s: %s", self.port, self.last_error)

    def _on_status(self, m: Status, t_rx: float) -> None:
        st = ChassisStatus.from_message(m, t_rx)
        old = self._status
        self._status = st
        if st.watchdog_tripped and not (old and old.watchdog_tripped):
            log.warning("%s: the board's watchdog stopped the wheels (no fresh speed command)", self.port)
        if st.no_session and self._state is LinkState.READY:
            self._lost_reason = self._lost_reason or "the board lost the session (reset?)"
        if self.on_status is not None:
            self.on_status(st)

    def _board_jumped(self, t_us: int, t_rx: float) -> bool:
        """Did the board's clock run differently from ours since the last report (a reset)?

        Within a session only a board clock ahead of ours counts: a stalled reader delivers old
        reports late, which makes the host gap longer, never shorter. Across a reconnect, either
        way counts: after a reset the clock may have restarted anywhere.
        """
        gap_board = delta_u32(t_us, self._prev_report[0]) * 1e-6
        gap_host = t_rx - self._prev_report[1]
        tol = 0.25 + 0.02 * gap_host
        return gap_board > gap_host + tol or (self._fresh_session and gap_board < gap_host - tol)

    def _on_report(self, m: EncoderReport, t_rx: float) -> None:
        if self._state is not LinkState.READY:
            return  # reports before the handshake belong to no session: they set no baseline
        self._last_report_rx = t_rx
        if self._prev_report is not None and self._board_jumped(m.t_us, t_rx):
            self._encoders.reset_baseline()
            self._clock.reset()
            self._counters["board_resets"] += 1
            if not self._fresh_session:
                self._lost_reason = self._lost_reason or "the board clock jumped (reset?)"
        self._fresh_session = False
        self._prev_report = (m.t_us, t_rx)
        board_s = self._clock.unwrap(m.t_us)
        latency = _REPORT_WIRE_BYTES * 10.0 / self.config.baud
        t = self._clock.to_host(board_s, t_rx, latency)
        before = self._encoders.implausible
        sample = self._encoders.update(m.ticks, board_s, t)
        if self._encoders.implausible != before:
            self._counters["implausible_reports"] += 1  # faster than any wheel: counters reset or garbage
        if sample is None:
            return
        self._counters["odometry_samples"] += 1
        if self.on_odometry is not None:
            self.on_odometry(sample)
        for q in self._queues:
            if q.full():
                q.get_nowait()
                self._counters["odometry_dropped"] += 1
            q.put_nowait(sample)
