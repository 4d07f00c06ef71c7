"""Keyboard teleoperation, the pure part: raw terminal bytes -> key events -> a body twist.

Model and conventions:

- ``KeyDecoder`` turns the bytes a terminal sends in cbreak/raw mode into key names. Letters
  are case-insensitive (caps lock, shift). Arrows come as ``ESC [ A`` (also with modifier
  parameters, ``ESC [ 1 ; 5 A``) or ``ESC O A`` (application cursor mode). A sequence split
  across reads is kept until the rest arrives (an over-long one is dropped up to its final
  byte). A lone Esc is only known to be one when nothing follows it: ``expire(t)`` turns it
  into ``quit`` once ``esc_timeout`` has passed (like vim's ``ttimeoutlen``). Esc followed by
  an ordinary byte (Alt+key) is Esc, then that byte. Other escape sequences (function keys,
  Insert, ...), control bytes and non-ASCII bytes are counted in ``ignored`` and otherwise
  dropped, so garbage never becomes motion.
- ``TeleopState`` turns key events at explicit times into a body twist (vx, vy, wz) in the
  ROBOT frame (x forward, y left, wz counter-clockwise), SI units. Terminals send no key-up,
  only auto-repeat (first repeat after ~250-600 ms, then ~30 Hz), so a key holds its motion
  until ``deadman`` seconds pass without a repeat (default 0.6 s, longer than the initial
  repeat delay). Optionally, once a key is auto-repeating (two events less than
  ``repeat_deadman`` apart), it expires after ``repeat_deadman`` instead, so letting go
  stops sooner. Each axis (vx, vy, wz) keeps its own key, so alternating taps of W and A drive
  diagonally (holding both does not: a terminal auto-repeats only the newest key). The
  opposite key cancels an axis at once (S while W holds stops vx; S again, or its auto-repeat,
  then reverses), space stops every axis at once, quit stops and ignores all later keys. +/-
  change the speed in steps of ``1/speed_steps`` of the limits.
- Limits: translation speed ``fraction * max_speed`` along the commanded direction (a
  diagonal has the same norm as a straight line, so the norm never exceeds ``max_speed``, as in
  ``ControlConfig``), yaw rate ``fraction * max_yaw_rate``. The trajectory controller's rate
  limiter still shapes acceleration and jerk downstream.
"""

from __future__ import annotations

import math
from typing import List, Optional, Tuple

FORWARD = "forward"
BACK = "back"
LEFT = "left"
RIGHT = "right"
TURN_LEFT = "turn_left"  # counter-clockwise, +wz
TURN_RIGHT = "turn_right"
STOP = "stop"
QUIT = "quit"
FASTER = "faster"
SLOWER = "slower"

HELP = ("keys: W/A/S/D or arrows move, Q/E turn, space stops, +/- speed, "
        "x, Esc or Ctrl-C quits; release a key and the robot stops")

ESC = 0x1B
_LONE_ESC = bytes([ESC])

_SINGLE = {
    ord("w"): FORWARD, ord("s"): BACK, ord("a"): LEFT, ord("d"): RIGHT,
    ord("q"): TURN_LEFT, ord("e"): TURN_RIGHT,
    ord(" "): STOP,
    0x1A: STOP,  # Ctrl-Z: with ISIG off it does not suspend; stopping is the safe reading
    ord("x"): QUIT, 0x03: QUIT, 0x04: QUIT, 0x1C: QUIT,  # x, Ctrl-C, Ctrl-D, Ctrl-backslash
    ord("+"): FASTER, ord("="): FASTER,  # '=' is unshifted '+' on US layouts
    ord("-"): SLOWER, ord("_"): SLOWER,
}
_SINGLE.update({k - 32: v for k, v in list(_SINGLE.items()) if ord("a") <= k <= ord("z")})

_ARROWS = {ord("A"): FORWARD, ord("B"): BACK, ord("C"): RIGHT, ord("D"): LEFT}

# Key -> (axis index in (vx, vy, wz), sign).
_AXIS = {
    FORWARD: (0, 1), BACK: (0, -1),
    LEFT: (1, 1), RIGHT: (1, -1),
    TURN_LEFT: (2, 1), TURN_RIGHT: (2, -1),
}
KEYS = frozenset(list(_AXIS) + [STOP, QUIT, FASTER, SLOWER])


class KeyDecoder:
    """Raw terminal bytes -> key names, robust to split escape sequences and to garbage."""

    def __init__(self, esc_timeout: float = 0.1, max_sequence: int = 16):
        if not (math.isfinite(esc_timeout) and esc_timeout > 0.0):
            raise ValueError(f"esc_timeout must be finite and > 0, got {esc_timeout}")
        self.esc_timeout = esc_timeout
        self.max_sequence = max_sequence
        self.ignored = 0  # bytes dropped as unknown keys or sequences
        self._pending = b""
        self._since = 0.0
        self._skipping = False  # inside an over-long CSI sequence: drop up to its final byte

    @property
    def pending(self) -> bool:
        """True while the start of an escape sequence waits for the rest (or for ``expire``)."""
        return bool(self._pending)

    @property
    def deadline(self) -> Optional[float]:
        """When ``expire`` turns a pending lone Esc into ``quit``, or None."""
        return self._since + self.esc_timeout if self._pending == _LONE_ESC else None

    def feed(self, data: bytes, t: float) -> List[str]:
        """Decode the bytes read at time ``t``; returns the complete keys in order."""
        if not data:
            return []
        buf = self._pending + bytes(data)
        self._pending = b""
        keys: List[str] = []
        i = 0
        while i < len(buf):
            if self._skipping:
                b = buf[i]
                self._skipping = 0x20 <= b <= 0x3F
                if 0x20 <= b <= 0x7E:  # a parameter byte, or the final byte that ends the skip
                    self.ignored += 1
                    i += 1
                continue
            if buf[i] != ESC:
                key = _SINGLE.get(buf[i])
                if key is None:
                    self.ignored += 1
                else:
                    keys.append(key)
                i += 1
                continue
            used, key = self._escape(buf, i)
            if used == 0:
                self._pending = buf[i:]
                self._since = t  # the time a lone Esc is timed from
                break
            if key is not None:
                keys.append(key)
            i += used
        return keys

    def expire(self, t: float) -> List[str]:
        """A lone Esc with nothing after it for ``esc_timeout`` is the Esc key: ``quit``.

        A started sequence (``ESC [``...) is not timed out: its rest may come late over a slow
        link, and taking it for keys would turn e.g. the ``A`` of an arrow into a motion.
        """
        if self._pending != _LONE_ESC or t < self._since + self.esc_timeout:
            return []
        self._pending = b""
        return [QUIT]

    def _escape(self, buf: bytes, i: int) -> Tuple[int, Optional[str]]:
        """Decode the escape sequence at ``buf[i]``: (bytes used, key); (0, None) if incomplete."""
        n = len(buf)
        if i + 1 >= n:
            return 0, None
        kind = buf[i + 1]
        if kind == ord("["):
            j = i + 2
            # CSI: parameter and intermediate bytes (0x20-0x3F), then one final byte (0x40-0x7E).
            while j < n and 0x20 <= buf[j] <= 0x3F:
                j += 1
            if j - i > self.max_sequence:
                self._skipping = j >= n  # drop the rest up to the final byte, in later reads too
                used = j - i + (j < n and 0x40 <= buf[j] <= 0x7E)
                self.ignored += used
                return used, None
            if j >= n:
                return 0, None
            final = buf[j]
            if not 0x40 <= final <= 0x7E:
                self.ignored += j - i  # broken sequence: drop it, go on with this byte
                return j - i, None
            if final == ord("[") and j == i + 2:
                # Linux console function keys: ESC [ [ A..E. Their last letter is not a key.
                if j + 1 >= n:
                    return 0, None
                self.ignored += 4
                return 4, None
            key = _ARROWS.get(final)
            if key is None:
                self.ignored += j - i + 1
            return j - i + 1, key
        if kind == ord("O"):
            # SS3 (application cursor keys, F1-F4): exactly one final byte.
            if i + 2 >= n:
                return 0, None
            final = buf[i + 2]
            if 0x40 <= final <= 0x7E:
                key = _ARROWS.get(final)
                if key is None:
                    self.ignored += 3
                return 3, key
        # Esc then an ordinary byte (Alt+key, or Esc typed just before a key): Esc quits.
        return 1, QUIT


class _Axis:
    __slots__ = ("sign", "last", "hold")

    def __init__(self):
        self.sign = 0  # +1, -1 or 0 (no key)
        self.last = 0.0  # time of the key's newest event
        self.hold = 0.0  # the key drives while t < last + hold

    def live(self, t: float) -> bool:
        return self.sign != 0 and t < self.last + self.hold  # the same sum as the deadline a caller computes


class TeleopState:
    """Key events at explicit times -> desired body twist, with a deadman per axis."""

    def __init__(self, max_speed: float, max_yaw_rate: float, deadman: float = 0.6,
                 repeat_deadman: Optional[float] = None, speed_steps: int = 10, start_step: int = 5):
        for name, v in (("max_speed", max_speed), ("max_yaw_rate", max_yaw_rate), ("deadman", deadman)):
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f"teleop {name} must be finite and > 0, got {v}")
        if repeat_deadman is not None and not (math.isfinite(repeat_deadman) and 0.0 < repeat_deadman <= deadman):
            raise ValueError(f"teleop repeat_deadman must be in (0, deadman={deadman}], got {repeat_deadman}")
        if speed_steps < 1 or not 1 <= start_step <= speed_steps:
            raise ValueError(f"teleop speed steps: need 1 <= start_step ({start_step}) <= speed_steps ({speed_steps})")
        self.max_speed = max_speed
        self.max_yaw_rate = max_yaw_rate
        self.deadman = deadman
        self.repeat_deadman = repeat_deadman
        self.speed_steps = speed_steps
        self.step = start_step
        self.quit_requested = False
        self.last_key = ""
        self._axes = (_Axis(), _Axis(), _Axis())

    @classmethod
    def from_control(cls, control, **kwargs) -> TeleopState:
        """Limits from a ``ControlConfig`` (``max_speed``, ``max_yaw_rate``)."""
        return cls(control.max_speed, control.max_yaw_rate, **kwargs)

    @property
    def speed_fraction(self) -> float:
        return self.step / self.speed_steps

    def press(self, key: str, t: float) -> None:
        """Apply one key event that happened at time ``t`` (seconds, the clock ``twist`` uses)."""
        if key not in KEYS:
            raise ValueError(f"unknown teleop key {key!r}")
        if self.quit_requested:
            return  # nothing moves the robot once quitting
        self.last_key = key
        if key in _AXIS:
            index, sign = _AXIS[key]
            self._press_axis(self._axes[index], sign, t)
        elif key == STOP:
            self.stop()
        elif key == QUIT:
            self.stop()
            self.quit_requested = True
        elif key == FASTER:
            self.step = min(self.step + 1, self.speed_steps)
        else:
            self.step = max(self.step - 1, 1)

    def stop(self) -> None:
        """Zero twist at once; the next movement key starts afresh."""
        for axis in self._axes:
            axis.sign = 0

    def active(self, t: float) -> bool:
        return any(axis.live(t) for axis in self._axes)

    def twist(self, t: float) -> Tuple[float, float, float]:
        """The desired body twist (vx, vy, wz) at time ``t``; zero once the deadman has expired."""
        ux, uy, uw = (axis.sign if axis.live(t) else 0 for axis in self._axes)
        vx = vy = wz = 0.0
        if ux or uy:
            v = self.speed_fraction * self.max_speed / math.hypot(ux, uy)
            vx, vy = v * ux, v * uy
        if uw:
            wz = self.speed_fraction * self.max_yaw_rate * uw
        return vx, vy, wz

    def _press_axis(self, axis: _Axis, sign: int, t: float) -> None:
        if axis.live(t) and axis.sign == -sign:
            axis.sign = 0  # the opposite key brakes this axis; pressing again reverses
            return
        if axis.live(t) and axis.sign == sign:
            gap = t - axis.last
            repeating = self.repeat_deadman is not None and gap <= self.repeat_deadman
            axis.hold = self.repeat_deadman if repeating else self.deadman
            axis.last = max(axis.last, t)
            return
        axis.sign, axis.last, axis.hold = sign, t, self.deadman
