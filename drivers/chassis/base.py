"""The chassis interface: what the robot core needs from a motor board, whatever carries the bytes.

Backends: ``serial_chassis.SerialChassis`` (the real board over a serial port, or the pty
emulator) and ``loopback.LoopbackChassis`` (the same protocol bytes to the board model on a
simulated clock); both speak through ``session.HostSession``. The app and the bench tools take a
``Chassis`` (``robot.app.assemble`` builds one by name); one contract suite
(``tests/contract/test_chassis_contract.py``) runs over every backend.
"""

from __future__ import annotations

import abc
import asyncio
import collections
import enum
from dataclasses import dataclass
from typing import Callable, Deque, Dict, Optional, Sequence, Tuple

from drivers.chassis.encoders import merge_odometry
from firmware_protocol import HelloReply, Status, StatusFlag
from robot.base.samples import WheelOdometry


class LinkState(enum.Enum):
    CLOSED = "closed"  # not connected yet, or closed
    CONNECTING = "connecting"  # opening the port and handshaking
    READY = "ready"  # handshake done and reports arriving: commands are allowed
    LOST = "lost"  # was ready; reports stopped or the port failed: reconnecting with backoff
    FAULT = "fault"  # the board answers but cannot be driven (protocol version, ticks per rev)


@dataclass(frozen=True)
class ChassisStatus:
    t: float  # host monotonic receive time
    battery_v: float
    motor_faults: Tuple[bool, bool, bool, bool]
    watchdog_tripped: bool
    estop: bool
    clamped: bool
    host_silent: bool
    no_session: bool
    board_rx_errors: int

    @classmethod
    def from_message(cls, m: Status, t: float) -> ChassisStatus:
        f = m.flags
        return cls(t=t, battery_v=m.battery_mv / 1000.0,
                   motor_faults=tuple(bool(m.motor_faults >> i & 1) for i in range(4)),
                   watchdog_tripped=bool(f & StatusFlag.WATCHDOG), estop=bool(f & StatusFlag.ESTOP),
                   clamped=bool(f & StatusFlag.CLAMPED), host_silent=bool(f & StatusFlag.HOST_SILENT),
                   no_session=bool(f & StatusFlag.NO_SESSION), board_rx_errors=m.rx_errors)


class OdometryQueue:
    """The queue ``Chassis.odometry_queue`` returns. Full, it merges its two oldest samples instead
    of dropping one, so a consumer that stalled still gets every tick: the merged sample spans both
    intervals exactly (``merge_odometry``). ``coalesced`` counts the merges.

    Not an ``asyncio.Queue``: on Python 3.8 and 3.9 that binds to ``get_event_loop()`` when it is
    built, which raises outside a loop once any ``asyncio.run`` has finished in the process, and
    the simulated-clock runner reads this queue with no loop at all. A consumer that awaits
    ``get()`` binds to its running loop at that moment instead. Like ``asyncio.Queue``, it is not
    thread-safe: feed it from the consumer's loop (or from the same thread, synchronously).

    A consumer on the feeding thread may take the samples as they are put instead
    (``set_listener``): no task wakes per sample, so no loop iteration is spent on the hand-over."""

    def __init__(self, maxsize: int = 256):
        self.limit = max(2, int(maxsize))
        self.coalesced = 0
        self._items: Deque[WheelOdometry] = collections.deque()
        self._getters: Deque[asyncio.Future] = collections.deque()
        self._listener: Optional[Callable[[WheelOdometry], None]] = None

    def set_listener(self, listener: Optional[Callable[[WheelOdometry], None]]) -> None:
        """Hand every sample to ``listener`` when it is put, in place of queueing it (None: queue
        again). Samples already queued go to it first, in order. It is called by the feeder (on
        the loop, inside the driver's message handling), so it must not raise."""
        self._listener = listener
        while listener is not None and self._items and self._listener is listener:
            listener(self._items.popleft())

    def qsize(self) -> int:
        return len(self._items)

    def empty(self) -> bool:
        return not self._items

    def put_nowait(self, item: WheelOdometry) -> None:
        listener = self._listener
        if listener is not None:
            listener(item)
            return
        q = self._items
        if len(q) >= self.limit:
            first = q.popleft()
            q.appendleft(merge_odometry(first, q.popleft()))
            self.coalesced += 1
        q.append(item)
        self._wake_one()

    def get_nowait(self) -> WheelOdometry:
        if not self._items:
            raise asyncio.QueueEmpty
        return self._items.popleft()

    async def get(self) -> WheelOdometry:
        while not self._items:
            getter = asyncio.get_running_loop().create_future()
            self._getters.append(getter)
            try:
                await getter
            except BaseException:
                getter.cancel()
                try:
                    self._getters.remove(getter)
                except ValueError:
                    pass
                if self._items and not getter.cancelled():
                    self._wake_one()  # it was woken for an item it will not take: pass the turn on
                raise
        return self._items.popleft()

    def _wake_one(self) -> None:
        while self._getters:
            getter = self._getters.popleft()
            if not getter.done():
                getter.set_result(None)
                return


class Chassis(abc.ABC):
    """A Mecanum motor board: wheel speed commands in, wheel odometry and status out.

    Commands are only accepted while ``link_state`` is ``LinkState.READY``; a refused command
    returns False and is never queued (a stale command must not reach the wheels later).
    ``connect`` raises ``DriverError`` naming the problem; a board that answers but must not be
    driven (protocol version, ticks per revolution) leaves the link in ``FAULT``. Wheel speeds
    that are not 4 finite numbers stop the wheels and raise ValueError. ``stop`` returns False
    when nothing could be sent (not connected, closed). ``close`` sends STOP and is idempotent.
    """

    @property
    @abc.abstractmethod
    def link_state(self) -> LinkState: ...

    @property
    @abc.abstractmethod
    def status(self) -> Optional[ChassisStatus]: ...

    @property
    @abc.abstractmethod
    def max_wheel_speed(self) -> float: ...

    @property
    def board_info(self) -> Optional[HelloReply]:
        """What the board said about itself in the last handshake (None before one)."""
        return None

    @property
    def stats(self) -> Dict[str, object]:
        return {}

    @property
    def reconnects(self) -> int:
        """How often the link came back after a loss (``stats["reconnects"]``): the control loop
        reads it every tick, so drivers answer it without building ``stats``."""
        return int(self.stats.get("reconnects", 0) or 0)

    @abc.abstractmethod
    async def connect(self) -> None: ...

    @abc.abstractmethod
    def send_wheel_speeds(self, wheels: Sequence[float]) -> bool: ...

    @abc.abstractmethod
    def stop(self) -> bool: ...

    def poll(self) -> None:
        """Hand over now, on the caller's loop, what the driver has received and holds back (a
        driver may keep routine messages for the next poll rather than wake the loop for each):
        call it wherever the newest odometry matters. ``SerialChassis`` hands over its reader's
        inbox; ``LoopbackChassis`` takes what its board model sent; a backend that delivers as it
        receives has nothing to do."""
        return None

    @abc.abstractmethod
    def odometry_queue(self, maxsize: int = 256) -> OdometryQueue:
        """A new ``OdometryQueue`` fed every sample; when full its two oldest samples are merged."""

    @abc.abstractmethod
    async def close(self) -> None: ...
