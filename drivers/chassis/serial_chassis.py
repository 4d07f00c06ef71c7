"""The Mecanum motor board over a serial line (PROTOCOL.md): handshake, commands, odometry, status.

The protocol itself (frames, handshake checks, reports to odometry, session loss) is
``drivers.chassis.session.HostSession``, shared with the simulated-clock backend; this module is
the I/O and the link supervision around it.

Threads and the loop: one reader thread per open port blocks in ``serial.read`` and decodes (the
codec is pure), then puts the messages with their host receive time in an inbox that the asyncio
loop empties. Routine batches (encoder reports, ACKs, STATUS) wait there for the consumer's
``poll`` (the controller polls at the start of every control tick) or at most ``MAX_HOLD``;
anything else wakes the loop at once with ``call_soon_threadsafe`` (``_read_loop``). Everything
else runs on the loop: the state machine, odometry, and the writes, which are non-blocking (a
frame the OS will not take is dropped and counted, never queued: a late speed command is worse
than none).

Safety rules this class keeps (tests/test_chassis_driver.py and the chassis contract suite prove
them against the emulator):

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

from drivers.chassis.base import Chassis, ChassisStatus, LinkState, OdometryQueue
from drivers.chassis.session import HEARTBEAT_PERIOD, BoardRefused, HostSession, check_wheels, nack_text, scale_into
from firmware_protocol import (
    PROTOCOL_VERSION,
    Ack,
    EncoderReport,
    Heartbeat,
    HelloReply,
    Message,
    NackReason,
    SetWheelSpeeds,
    Status,
    Stop,
)
from robot.base.errors import DriverError
from robot.base.samples import WheelOdometry
from robot.config import ChassisConfig

log = logging.getLogger(__name__)

HANDSHAKE_TIMEOUT = 1.0  # s to wait for HELLO_REPLY (HELLO is resent every HELLO_RESEND)
HELLO_RESEND = 0.25
BACKOFF_START = 0.05  # s, first reconnect delay; doubles up to config.reconnect_backoff_max
READ_TIMEOUT = 0.05  # s a blocked read waits, bounding how long closing the port takes
_REPORT_WIRE_BYTES = 3 + EncoderReport.LAYOUT.size + 4 + 3  # header + payload + CRC + COBS byte + 2 delimiters
# Routine batches (nothing but encoder reports, ACKs and STATUS) the reader leaves in the inbox without
# waking the loop, and for how long at most (see _read_loop): a little over one control period at
# 50 Hz, so a consumer that polls every tick takes them all, and one that never polls gets them late
# by this much.
MAX_HELD_BATCHES = 8
MAX_HOLD = 0.03  # s
# What may wait for the poll: the reports, the ACKs of speed commands and the 10 Hz STATUS (a lost
# session it reports is acted on by the link monitor's look, which every poll makes after draining).
_ROUTINE = frozenset((Ack, EncoderReport, Status))


def reconnect_delay(attempt: int, cap: float) -> float:
    """Seconds to wait before reconnect attempt ``attempt`` (0, 1, ...): doubling, capped."""
    return min(BACKOFF_START * 2.0 ** min(attempt, 30), cap)


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
        self._session = HostSession(self.config, name=self.port)
        self._report_latency = _REPORT_WIRE_BYTES * 10.0 / self.config.baud  # s on the wire per report
        self._state = LinkState.CLOSED
        self._counters = self._session.counters  # one set of counters: the protocol's and the link's
        self._queues: List[asyncio.Queue] = []
        self._ser = None
        self._fd: Optional[int] = None
        self._reader: Optional[threading.Thread] = None
        self._reader_stop = threading.Event()
        self._gen = 0  # connection generation: events from an older reader are ignored
        self._last_tx = 0.0
        self.last_command_time = -math.inf  # host monotonic time the last speed command went out
        self._hello_wait: Optional[asyncio.Future] = None
        self._loop: Optional[asyncio.AbstractEventLoop] = None
        self._supervisor: Optional[asyncio.Task] = None
        self._closing = False
        self._stop_ack: Optional[Tuple[int, asyncio.Future]] = None
        # (generation, receive time, messages) from the reader thread, in order; emptied on the loop.
        self._inbox: Deque[Tuple[int, float, List[Message]]] = collections.deque()
        self._drain_posted = False  # a _drain is on its way to the loop
        # The link monitor while the link is up: its verdict, its look period and fallback timer.
        self._lost: Optional[asyncio.Future] = None
        self._look_tick = 0.02
        self._look_timer: Optional[asyncio.TimerHandle] = None
        self._look_again = 0.0  # monotonic time before which a poll does not look again

    # Public interface  ------------------------------------------------------------------------

    @property
    def link_state(self) -> LinkState:
        return self._state

    @property
    def status(self) -> Optional[ChassisStatus]:
        """The latest STATUS from the board, or None before the first."""
        return self._session.status

    @property
    def board_info(self) -> Optional[HelloReply]:
        return self._session.board_info

    @property
    def max_wheel_speed(self) -> float:
        """The limit commands are scaled into: the lower of the config's and the board's."""
        return self._session.max_wheel_speed

    @property
    def last_error(self) -> str:
        return self._session.last_error

    @last_error.setter
    def last_error(self, text: str) -> None:
        self._session.last_error = text

    @property
    def reconnects(self) -> int:
        return int(self._session.counters.get("reconnects", 0))

    @property
    def stats(self) -> Dict[str, object]:
        d: Dict[str, object] = dict(self._counters)
        d.update({f"rx_{k}": v for k, v in self._session.decoder.stats.as_dict().items()})
        return d

    async def connect(self) -> None:
        """Open the port and handshake; raise DriverError naming the problem if that fails.

        After a successful connect the driver supervises the link on its own: on loss it stops
        commanding and reconnects with capped backoff until ``close()``. A board that must not be
        driven (``BoardRefused``) leaves the link in FAULT.
        """
        if self._supervisor is not None:
            return
        self._loop = asyncio.get_running_loop()
        self._closing = False
        try:
            await self._open_and_handshake()
        except DriverError as e:
            await self._drop_port()
            self._state = LinkState.FAULT if isinstance(e, BoardRefused) else LinkState.CLOSED
            raise
        self._supervisor = self._loop.create_task(self._supervise())

    def send_wheel_speeds(self, wheels: Sequence[float]) -> bool:
        """Command wheel speeds (rad/s, FL, FR, RL, RR). True if the command went out.

        Refused (False) before the handshake and while the link is down. Speeds beyond the limit
        are scaled down together, keeping the direction of travel. Call it at the control rate:
        the board stops the wheels when commands stop coming.
        """
        try:
            w = check_wheels(wheels)
        except ValueError:
            self.stop()
            raise
        if self._inbox:  # the reports the reader holds decide whether the link is still alive
            self._drain()
        if self._state is not LinkState.READY or not self._session.usable(time.monotonic()):
            self._counters["commands_refused"] += 1
            return False
        w, scaled = scale_into(w, self.max_wheel_speed)
        if scaled:
            self._counters["commands_scaled"] += 1
        if self._write(self._session.frame(SetWheelSpeeds.from_rad_s(w))):
            self._counters["commands_sent"] += 1
            self.last_command_time = self._last_tx
            return True
        return False

    def stop(self) -> bool:
        """Ramp the wheels to zero. Sent whenever the port is open, handshake or not."""
        if self._ser is None:
            return False
        return self._write(self._session.frame(Stop()))

    def poll(self) -> None:
        """Handle now what the reader thread received (odometry to the queues and callbacks), and
        look at the link. Call it on the loop wherever fresh odometry matters (the controller does at
        the start of every control tick): between polls, routine messages wait up to ``MAX_HOLD``
        instead of waking the loop for every report."""
        if self._inbox:
            self._drain()
        if self._lost is not None and time.monotonic() >= self._look_again:
            # A tick and a half: a consumer polling at the look period keeps ahead of the fallback.
            self._look(1.5 * self._look_tick)

    def odometry_queue(self, maxsize: int = 256) -> OdometryQueue:
        """A new queue fed every WheelOdometry; when full its two oldest samples are merged, never dropped."""
        q = OdometryQueue(maxsize)
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
            frame = self._session.frame(Stop())
            fut = self._loop.create_future()
            self._stop_ack = (self._session.last_seq, fut)
            if self._write(frame):
                try:
                    await asyncio.wait_for(fut, 0.3)
                except asyncio.TimeoutError:
                    log.warning("%s: no ACK for the STOP sent on close", self.port)
        await self._drop_port()
        self._session.end()
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
                self._state = LinkState.FAULT if isinstance(e, BoardRefused) else LinkState.LOST
                await self._drop_port()

    async def _monitor(self) -> str:
        """Wait while the link is healthy, sending heartbeats; return why it is not any more.

        It looks every ``tick`` from a timer callback (a task that slept cost a future and a second
        loop iteration per wake-up) and at every ``poll``, which pushes the timer back: a consumer
        that polls every control tick carries the looks, and the timer never wakes the loop."""
        self._look_tick = max(0.005, min(0.02, self.config.link_timeout / 4.0))
        lost: asyncio.Future = self._loop.create_future()
        self._lost = lost
        self._look_timer = self._loop.call_later(self._look_tick, self._look)
        try:
            return await lost
        finally:
            self._lost = None
            if self._look_timer is not None:
                self._look_timer.cancel()
                self._look_timer = None

    def _look(self, next_in: Optional[float] = None) -> None:
        """One look of the monitor: the session lost, reports stopped, a heartbeat due. The next
        look is ``next_in`` seconds from now (a tick when None)."""
        lost = self._lost
        if lost is None or lost.done():
            return
        if self._look_timer is not None:
            self._look_timer.cancel()
            self._look_timer = None
        if self._inbox:  # (from the timer: a consumer that does not poll) the reports held decide
            self._drain()
        session = self._session
        try:
            now = time.monotonic()
            # Polls come from every control tick and frame set: half a tick apart is often enough.
            self._look_again = now + 0.5 * self._look_tick
            if session.lost_reason is not None:
                lost.set_result(session.lost_reason)
                return
            silent = session.silence(now)
            if silent is not None:
                lost.set_result(silent)
                return
            if now - self._last_tx > HEARTBEAT_PERIOD:
                self._write(session.frame(Heartbeat()))
        except Exception as e:  # raised out of _monitor, as from the task that slept here
            lost.set_exception(e)
            return
        self._look_timer = self._loop.call_later(self._look_tick if next_in is None else next_in, self._look)

    async def _open_and_handshake(self) -> None:
        self._state = LinkState.CONNECTING
        session = self._session
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
        session.begin(random.getrandbits(32))
        self._reader_stop = threading.Event()
        self._reader = threading.Thread(target=self._read_loop, args=(ser, self._gen, self._reader_stop),
                                        name=f"chassis-reader-{self._gen}", daemon=True)
        self._reader.start()
        fut = self._loop.create_future()
        self._hello_wait = fut
        deadline = time.monotonic() + HANDSHAKE_TIMEOUT
        try:
            while True:
                self._write(session.hello())
                left = deadline - time.monotonic()
                try:
                    reply = await asyncio.wait_for(asyncio.shield(fut), max(0.0, min(HELLO_RESEND, left)))
                    break
                except asyncio.TimeoutError:
                    pass
                refusal = session.version_refusal()
                if refusal is not None:
                    raise refusal
                if session.lost_reason is not None:
                    raise DriverError(f"{self.port}: {session.lost_reason} during the handshake")
                if time.monotonic() >= deadline:
                    raise DriverError(f"{self.port}: no answer to HELLO within {HANDSHAKE_TIMEOUT:.1f} s "
                                      "(board off, wrong port or baud rate?)")
        finally:
            self._hello_wait = None
        for warning in session.accept(reply, time.monotonic()):
            log.warning("%s", warning)
        self._state = LinkState.READY

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
        self._session.end(reason)
        self._state = LinkState.LOST

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
            self._session.lose(f"write failed: {e}")
            return False
        self._last_tx = time.monotonic()
        if n < len(data):
            self._counters["tx_dropped"] += 1
            return False
        self._counters["frames_sent"] += 1
        return True

    def _read_loop(self, ser, gen: int, stop: threading.Event) -> None:
        """Reader thread: block in read, decode, put the messages in the inbox. Owns the decoder.

        Waking the loop costs it about as much as handling an encoder report (its self-pipe, a
        select, a callback), and routine messages come 160 times a second: the board's encoder
        reports (100 Hz), the ACK of every speed command (50 Hz) and its STATUS (10 Hz). A batch of
        nothing but those therefore stays in the inbox for the consumer's next ``poll`` (at the
        start of every control tick, which needs the reports), for at most ``MAX_HOLD`` and
        ``MAX_HELD_BATCHES`` batches, or until a read times out (a quiet line). Anything else (a
        NACK, the handshake's reply, the ACK of the STOP that ``close`` waits for) wakes the loop
        at once, which empties the inbox in order, each batch with its own receive time."""
        loop = self._loop
        session = self._session
        inbox = self._inbox
        since = 0.0  # receive time of the oldest batch put in the inbox since it was last empty
        while not stop.is_set():
            try:
                data = ser.read(1)
                if data:
                    waiting = ser.in_waiting
                    if waiting:
                        data += ser.read(waiting)
            except Exception as e:  # pyserial raises several types when a device vanishes
                if not stop.is_set():
                    if inbox:
                        self._post_drain(loop)
                    self._post(loop, self._on_port_error, gen, f"port error: {e}")
                return
            if not data:
                if inbox and not self._post_drain(loop):  # the line went quiet: what waits goes now
                    return
                continue
            t_rx = time.monotonic()
            msgs = session.decode(data)
            if not msgs:
                continue
            if not inbox:
                since = t_rx
            inbox.append((gen, t_rx, msgs))
            if (t_rx - since < MAX_HOLD and len(inbox) <= MAX_HELD_BATCHES and self._stop_ack is None
                    and all(type(m) in _ROUTINE for m in msgs)):
                continue
            if not self._post_drain(loop):
                return

    def _post_drain(self, loop) -> bool:
        """Wake the loop to empty the inbox (once: a drain on its way takes what comes meanwhile)."""
        if self._drain_posted:
            return True
        self._drain_posted = True
        return self._post(loop, self._drain)

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
            self._session.lose(reason)

    def _drain(self) -> None:
        """Handle every batch in the inbox, in order, each as its own loop callback was handled:
        an exception is reported to the loop's handler and the next batch goes on (a poll inside
        the control tick must not end the tick)."""
        self._drain_posted = False  # first: a batch put after this posts a drain of its own
        inbox = self._inbox
        while inbox:
            gen, t_rx, msgs = inbox.popleft()
            try:
                self._on_messages(gen, t_rx, msgs)
            except Exception as e:  # noqa: PERF203 - one bad batch must not hold back the others
                self._loop.call_exception_handler({"message": f"{self.port}: handling a received batch failed",
                                                   "exception": e})

    def _on_messages(self, gen: int, t_rx: float, msgs: List[Message]) -> None:
        if gen != self._gen:
            return
        old_status = self._session.status
        got = self._session.handle(msgs, t_rx, latency=self._report_latency)
        if got.reply is not None and self._hello_wait is not None and not self._hello_wait.done():
            self._hello_wait.set_result(got.reply)
        stop_ack = self._stop_ack
        for ack in got.acks:
            if stop_ack and ack.ref_id == Stop.MSG_ID and ack.ref_seq == stop_ack[0] and not stop_ack[1].done():
                stop_ack[1].set_result(ack)
        for nack in got.nacks:
            # CLAMPED is routine; a lost session is reported once, as the link loss
            if nack.reason != NackReason.CLAMPED and not (nack.reason == NackReason.NO_SESSION and self._session.lost_reason):
                log.warning("%s: %s", self.port, nack_text(nack))
        if got.status is not None:
            st = got.status
            if st.watchdog_tripped and not (old_status and old_status.watchdog_tripped):
                log.warning("%s: the board's watchdog stopped the wheels (no fresh speed command)", self.port)
            if self.on_status is not None:
                self.on_status(st)
        if got.odometry:
            for sample in got.odometry:
                if self.on_odometry is not None:
                    self.on_odometry(sample)
                for q in self._queues:
                    q.put_nowait(sample)  # full, an OdometryQueue merges its oldest samples: no tick is lost
            self._counters["odometry_coalesced"] = sum(q.coalesced for q in self._queues)
