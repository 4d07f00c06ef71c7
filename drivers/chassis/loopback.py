"""The host end of the motor-board protocol over an in-process byte pipe, for a simulated clock.

The real driver (``drivers.chassis.serial_chassis``) needs a real serial port and host time; a run
faster than real time has neither. This speaks the same bytes to the same ``BoardModel`` (the
firmware logic the pty emulator serves), with the board clock as the only clock: handshake,
speed commands, STOP, and encoder reports turned into odometry by the same
``drivers.chassis.encoders.EncoderOdometry`` the serial driver uses.
"""

from __future__ import annotations

from typing import List, Optional, Sequence

from drivers.chassis.emulator import BoardModel
from drivers.chassis.encoders import EncoderOdometry
from firmware_protocol import Decoder, EncoderReport, Hello, HelloReply, SetWheelSpeeds, Status, StatusFlag, Stop, encode
from robot.base.errors import DriverError
from robot.base.samples import WheelOdometry


class LoopbackChassis:
    def __init__(self, board: BoardModel, ticks_per_rev: int, max_wheel_speed: float):
        self.board = board
        self.decoder = Decoder()
        self.odometry = EncoderOdometry(ticks_per_rev, max_wheel_speed)
        self.status: Optional[Status] = None
        self.ready = False
        self._seq = 0
        self._pending: List[WheelOdometry] = []

    def _next_seq(self) -> int:
        self._seq = (self._seq + 1) & 0xFF
        return self._seq

    def connect(self) -> HelloReply:
        nonce = 0x5EED
        self.board.handle_bytes(encode(Hello(minor=0, nonce=nonce, seq=self._next_seq())))
        for m in self.decoder.feed(self.board.take_outbox()):
            if isinstance(m, HelloReply) and m.nonce == nonce:
                if m.ticks_per_rev != self.odometry.ticks_per_rev:
                    raise DriverError(f"board reports {m.ticks_per_rev} ticks per revolution, the config says "
                                      f"{self.odometry.ticks_per_rev}: refusing to drive")
                self.ready = True
                self.odometry.reset_baseline()
                return m
        raise DriverError("loopback board did not answer HELLO")

    def send_wheel_speeds(self, wheels: Sequence[float]) -> bool:
        if not self.ready:
            return False
        self.board.handle_bytes(encode(SetWheelSpeeds.from_rad_s(list(wheels), seq=self._next_seq())))
        return True

    def stop(self) -> None:
        self.board.handle_bytes(encode(Stop(seq=self._next_seq())))

    def poll(self) -> List[WheelOdometry]:
        """Decode what the board sent since the last poll; odometry stamped with the board clock."""
        out: List[WheelOdometry] = []
        for m in self.decoder.feed(self.board.take_outbox()):
            if isinstance(m, EncoderReport):
                board_s = m.t_us * 1e-6  # the simulated board starts at 0 and never wraps in a run
                sample = self.odometry.update(m.ticks, board_s, board_s)
                if sample is not None:
                    out.append(sample)
            elif isinstance(m, Status):
                self.status = m
                if m.flags & StatusFlag.NO_SESSION:
                    self.ready = False
        return out
