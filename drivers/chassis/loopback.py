"""The motor board's protocol over an in-process byte pipe, on a simulated clock.

The serial driver needs a real port and host time; a run faster than real time has neither.
``LoopbackChassis`` speaks the same bytes to the same ``BoardModel`` the pty emulator serves,
through the same ``HostSession`` (handshake checks, reports to odometry, session loss), and its
only clock is the simulation's (default: the board's uptime, which the simulated world steps).

It implements the ``Chassis`` interface, so the app and the contract suite drive it like the
serial driver. Nothing runs by itself: a simulated-clock runner steps the board and calls
``poll()`` (or ``advance(dt)``, which does both); the synchronous ``connect_now()`` /
``close_now()`` are what ``connect()`` / ``close()`` run. The board answers a HELLO at once, so
a lost session is re-handshaken at the next poll.
"""

from __future__ import annotations

import asyncio
import math
from typing import Callable, Dict, List, Optional, Sequence

from drivers.chassis.base import Chassis, ChassisStatus, LinkState, OdometryQueue
from drivers.chassis.emulator import BoardModel
from drivers.chassis.encoders import EncoderOdometry
from drivers.chassis.session import HEARTBEAT_PERIOD, BoardRefused, HostSession, Received, check_wheels, scale_into
from firmware_protocol import Heartbeat, HelloReply, SetWheelSpeeds, Stop
from robot.base.errors import DriverError
from robot.base.samples import WheelOdometry
from robot.config import ChassisConfig

NONCE = 0x5EED  # fixed: a simulated run must repeat exactly


class LoopbackChassis(Chassis):
    def __init__(self, board: BoardModel, config: Optional[ChassisConfig] = None,
                 clock: Optional[Callable[[], float]] = None):
        self.board = board
        self.config = config or ChassisConfig()
        self._clock = clock or (lambda: board.t_board)
        self._session = HostSession(self.config, name="loopback board")
        self._state = LinkState.CLOSED
        self._open = False  # between a connect attempt and close: frames reach the board
        self._last_tx = -math.inf  # simulated time of the last frame sent
        self._queues: List[asyncio.Queue] = []

    # Chassis  -----------------------------------------------------------------------------------

    @property
    def link_state(self) -> LinkState:
        return self._state

    @property
    def status(self) -> Optional[ChassisStatus]:
        return self._session.status

    @property
    def board_info(self) -> Optional[HelloReply]:
        return self._session.board_info

    @property
    def max_wheel_speed(self) -> float:
        return self._session.max_wheel_speed

    @property
    def reconnects(self) -> int:
        return int(self._session.counters.get("reconnects", 0))

    @property
    def stats(self) -> Dict[str, object]:
        d: Dict[str, object] = dict(self._session.counters)
        d.update({f"rx_{k}": v for k, v in self._session.decoder.stats.as_dict().items()})
        return d

    @property
    def encoders(self) -> EncoderOdometry:
        """The encoder model turning reports into odometry (its speed variance, its refusals)."""
        return self._session.encoders

    async def connect(self) -> None:
        self.connect_now()

    def send_wheel_speeds(self, wheels: Sequence[float]) -> bool:
        try:
            w = check_wheels(wheels)
        except ValueError:
            self.stop()
            raise
        counters = self._session.counters
        if self._state is not LinkState.READY or not self._session.usable(self._clock()):
            counters["commands_refused"] += 1
            return False
        w, scaled = scale_into(w, self.max_wheel_speed)
        if scaled:
            counters["commands_scaled"] += 1
        self._send(SetWheelSpeeds.from_rad_s(w))
        counters["commands_sent"] += 1
        return True

    def stop(self) -> bool:
        if not self._open:
            return False
        self._send(Stop())
        return True

    def odometry_queue(self, maxsize: int = 256) -> OdometryQueue:
        """A new queue fed every WheelOdometry; when full its two oldest samples are merged, never dropped."""
        q = OdometryQueue(maxsize)
        self._queues.append(q)
        return q

    async def close(self) -> None:
        self.close_now()

    # The simulated clock's side  ----------------------------------------------------------------

    def connect_now(self) -> HelloReply:
        """Handshake at once (the board model answers in the same call); DriverError if refused."""
        if self._state is LinkState.READY:
            return self._session.board_info
        self._open = True
        self._state = LinkState.CONNECTING
        try:
            reply = self._handshake()
        except BoardRefused:
            self._state = LinkState.FAULT
            raise
        except DriverError:
            self._state = LinkState.CLOSED
            raise
        self._state = LinkState.READY
        return reply

    def poll(self) -> List[WheelOdometry]:
        """Take what the board sent since the last poll; odometry on the simulated clock."""
        data = self.board.take_outbox()
        if not self._open:
            return []
        now = self._clock()
        got = self._session.handle(self._session.decode(data), now)
        self._supervise(now)
        self._publish(got)
        return got.odometry

    def advance(self, dt: float) -> List[WheelOdometry]:
        """Step the board by ``dt`` seconds, then ``poll``: for a caller that owns no world."""
        self.board.step(dt)
        return self.poll()

    def close_now(self) -> None:
        """STOP, then no more frames either way. Idempotent."""
        if self._open:
            self.stop()
            self._session.handle(self._session.decode(self.board.take_outbox()), self._clock())
        self._open = False
        self._session.end()
        self._state = LinkState.CLOSED

    # Internals  ---------------------------------------------------------------------------------

    def _handshake(self) -> HelloReply:
        session = self._session
        session.begin(NONCE)
        self.board.handle_bytes(session.hello())
        self._last_tx = self._clock()
        now = self._clock()
        got = session.handle(session.decode(self.board.take_outbox()), now)
        refusal = session.version_refusal()
        if refusal is not None:
            raise refusal
        if got.reply is None:
            raise DriverError(f"{session.name} did not answer HELLO")
        session.accept(got.reply, now)
        return got.reply

    def _send(self, msg) -> None:
        self.board.handle_bytes(self._session.frame(msg))
        self._last_tx = self._clock()

    def _supervise(self, now: float) -> None:
        """After each poll: heartbeats while idle, as the serial driver sends them; a session lost
        (board reset, reports stopped) is LOST, then re-handshaken."""
        session = self._session
        if self._state is LinkState.READY:
            reason = session.lost_reason or session.silence(now)
            if reason is None:
                if now - self._last_tx > HEARTBEAT_PERIOD:
                    self._send(Heartbeat())
                return
            session.end(reason)
            session.counters["link_losses"] += 1
            self._state = LinkState.LOST
        if self._state is LinkState.LOST:
            session.counters["connect_attempts"] += 1
            try:
                self._handshake()
            except DriverError as e:
                session.last_error = str(e)
                if isinstance(e, BoardRefused):
                    self._state = LinkState.FAULT
                return
            session.counters["reconnects"] += 1
            self._state = LinkState.READY

    def _publish(self, got: Received) -> None:
        for sample in got.odometry:
            for q in self._queues:
                q.put_nowait(sample)  # full, an OdometryQueue merges its oldest samples: no tick is lost
            self._session.counters["odometry_coalesced"] = sum(q.coalesced for q in self._queues)
