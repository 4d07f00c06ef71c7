"""Faults for the simulated-clock runner: a host that stalls, a serial line that drops out or
corrupts bytes, and cameras that hand over bad frames.

Deterministic like the rest of the runner: a stall is a window of simulated time in which the
host runs nothing (no control tick, no odometry read, no localization; events that fall due are
delayed to the window's end) while the board and the world go on; line faults act on the real
protocol bytes between ``LoopbackChassis`` and the board model, seeded; a bad frame is the
rendered one made bad in a known way. Nothing here reads a clock.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import numpy as np

from drivers.chassis.emulator import BoardModel, LineFaults
from robot.base.samples import DepthFrame

NAN_FRAME = "nan"  # float32 depth in metres with NaN and inf holes
FUTURE_FRAME = "future"  # stamped FUTURE_STAMP seconds after its capture
FUTURE_STAMP = 0.8  # s


def _inside(windows: Sequence[Tuple[float, float]], t: float) -> Optional[float]:
    """The end of the (start, seconds) window containing t, or None."""
    for start, seconds in windows:
        if start <= t < start + seconds:
            return start + seconds
    return None


@dataclass(frozen=True)
class FaultPlan:
    host_stalls: Tuple[Tuple[float, float], ...] = ()  # (start s, seconds): the host is frozen
    line_cuts: Tuple[Tuple[float, float], ...] = ()  # (start s, seconds): no byte passes either way
    corrupt: float = 0.0  # probability per byte (both directions) that one bit is flipped
    bad_frames: Tuple[Tuple[float, float, str], ...] = ()  # (start s, end s, NAN_FRAME or FUTURE_FRAME)
    board_resets: Tuple[float, ...] = ()  # s: the board reboots (session, counters, clock) under turning wheels
    seed: int = 0

    def frozen_until(self, t: float) -> Optional[float]:
        """While the host is frozen at t: when it runs again; else None."""
        return _inside(self.host_stalls, t)

    def line_cut(self, t: float) -> bool:
        return _inside(self.line_cuts, t) is not None

    def frame(self, frame: DepthFrame, t: float) -> DepthFrame:
        """The frame a camera hands over at t: the rendered one, or it made bad."""
        for start, end, kind in self.bad_frames:
            if not start <= t < end:
                continue
            if kind == NAN_FRAME:
                depth = frame.depth.astype(np.float32) * np.float32(frame.depth_scale)
                depth[::7, ::5] = np.nan
                depth[3::11, 2::9] = np.inf
                return dataclasses.replace(frame, depth=depth, depth_scale=1.0)
            if kind == FUTURE_FRAME:
                return dataclasses.replace(frame, t_capture=frame.t_capture + FUTURE_STAMP)
            raise ValueError(f"unknown bad-frame kind {kind!r}")
        return frame


class FaultyLine:
    """The board model seen through a faulty serial line; ``LoopbackChassis`` takes it as its board.

    ``clock`` is the simulated time the line is judged at (the runner's)."""

    def __init__(self, board: BoardModel, plan: FaultPlan, clock):
        self.board = board
        self.plan = plan
        self._clock = clock
        self._to_board = LineFaults(corrupt=plan.corrupt, seed=plan.seed)
        self._to_host = LineFaults(corrupt=plan.corrupt, seed=plan.seed + 1)
        self._resets = sorted(plan.board_resets)
        self.bytes_cut = 0

    def _through(self, faults: LineFaults, data: bytes) -> bytes:
        if not data:
            return data
        if self.plan.line_cut(self._clock()):
            self.bytes_cut += len(data)
            return b""
        return faults.apply(data, 0.0)

    def handle_bytes(self, data: bytes) -> None:
        data = self._through(self._to_board, data)
        if data:
            self.board.handle_bytes(data)

    def take_outbox(self) -> bytes:
        while self._resets and self._resets[0] <= self._clock():
            self._resets.pop(0)
            self.board.reboot(t0_us=123_456_789)  # its clock restarts somewhere else
        return self._through(self._to_host, self.board.take_outbox())

    @property
    def corrupted(self) -> int:
        return self._to_board.corrupted + self._to_host.corrupted

    def __getattr__(self, name):  # everything else is the board's own
        return getattr(self.board, name)
