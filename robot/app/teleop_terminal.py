"""Keyboard teleoperation, the terminal side: tty modes, non-blocking key input, a status line.

``async with TerminalKeyboard(on_quit) as kb:`` puts the terminal on stdin (or ``fd``) into a
cbreak-like mode and feeds a ``TeleopState``; the app polls ``kb.state.twist(t)`` with the same
clock (``time.monotonic`` by default) and rewrites one status line with ``kb.show(text)``.

- Mode: no echo, no line buffering, and no ISIG/IXON/IEXTEN, so Ctrl-C, Ctrl-Z, Ctrl-S and
  Ctrl-V arrive as bytes (Ctrl-C quits through ``on_quit`` like x and Esc; Ctrl-Z cannot
  suspend the process while the robot moves). Output processing stays on, so the app's own
  log lines still end with CR LF. Keys typed before teleop started are discarded.
- I/O: the terminal is reopened (``os.ttyname``) with O_NONBLOCK, a new open file description,
  so neither reads nor status writes can block the control loop and the shell's stdin keeps
  its flags. Input arrives through ``loop.add_reader``. A status write that would block is
  dropped (the next one redraws the line).
- Restore: ``__aexit__`` restores the saved modes whatever ended the block (exception,
  cancellation), discards unread keys so held-key repeats do not spill into the shell, and ends
  the status line. SIGHUP and SIGTERM, when the app has left them at their default action
  (which would kill the process with the tty in cbreak mode and the wheels commanded), call
  ``on_quit`` instead; so do end of input and a hang-up of the terminal.
"""

from __future__ import annotations

import asyncio
import math
import os
import signal
import sys
import time
from typing import Callable, List, Optional, Sequence

from robot.base.errors import RobotError
from robot.config import ControlConfig
from robot.control.teleop_keys import HELP, QUIT, KeyDecoder, TeleopState

try:  # POSIX only: importing this module must not break the CLI elsewhere
    import termios
except ImportError:  # pragma: no cover
    termios = None  # type: ignore[assignment]

CLEAR_LINE = "\r\x1b[2K"  # carriage return, then erase the whole line (VT100 EL 2)


class NotATerminalError(RobotError):
    """Teleop needs an interactive terminal on stdin."""


def fit_line(text: str, width: int) -> str:
    """``text`` on one line that does not wrap (a wrapped status line cannot be rewritten with CR)."""
    text = " ".join(text.split())
    if width <= 1 or len(text) < width:
        return text
    return text[: width - 2] + ">"


def _std_mm_deg(cov) -> Optional[Sequence[float]]:
    """Position std along the worst direction (mm) and heading std (deg) of a 3x3 covariance."""
    try:
        a, b, c, p = float(cov[0][0]), float(cov[0][1]), float(cov[1][1]), float(cov[2][2])
    except (TypeError, IndexError, ValueError):
        return None
    if not all(math.isfinite(v) for v in (a, b, c, p)):
        return None
    worst = 0.5 * (a + c) + math.hypot(0.5 * (a - c), b)  # largest eigenvalue of the 2x2 block
    return 1000.0 * math.sqrt(max(worst, 0.0)), math.degrees(math.sqrt(max(p, 0.0)))


def format_status(pose, cov, quality_state: str, reason: str, twist: Sequence[float], link_state: str,
                  speed_fraction: Optional[float] = None) -> str:
    """One status line: quality, chassis link, fused pose and its std, commanded twist, speed, reason.

    ``pose`` is (x, y, phi) in G or None, ``cov`` its 3x3 covariance or None, ``twist`` the
    commanded (vx, vy, wz). The most safety-relevant fields come first, so a narrow terminal
    cuts the reason, not the quality or the link. A quality other than ``localized`` is in
    capitals so it catches the eye.
    """
    try:
        x, y, phi = (float(v) for v in pose)  # type: ignore[union-attr]
        ok = all(math.isfinite(v) for v in (x, y, phi))
    except (TypeError, ValueError):
        ok = False
    if ok:
        pose_text = f"x {x:+.3f} y {y:+.3f} th {math.degrees(phi):+.1f}deg"
        std = _std_mm_deg(cov) if cov is not None else None
        if std is not None:
            pose_text += f" sd {std[0]:.0f}mm {std[1]:.1f}deg"
    else:
        pose_text = "no pose"
    quality = quality_state if quality_state == "localized" else (quality_state or "unknown").upper()
    vx, vy, wz = (float(v) for v in twist)
    cmd = f"v {vx:+.2f} {vy:+.2f} w {wz:+.2f}"
    if speed_fraction is not None:
        cmd += f" @{100.0 * speed_fraction:.0f}%"
    parts = [quality, f"link {link_state}", pose_text, cmd]
    if reason:
        parts.append(reason)
    return " | ".join(parts)


class TerminalKeyboard:
    """Async context manager: the terminal's keys feed ``self.state``; ``show`` draws the status line.

    ``on_quit()`` is called once, from the event loop, when the user quits (x, Esc, Ctrl-C,
    Ctrl-D), when input ends or the terminal hangs up, or on an unhandled SIGHUP/SIGTERM;
    ``quit_reason`` says which. The twist is zero from that moment on.
    """

    def __init__(self, on_quit: Callable[[], None], state: Optional[TeleopState] = None, fd: Optional[int] = None,
                 clock: Callable[[], float] = time.monotonic, esc_timeout: float = 0.1, banner: bool = True):
        self.state = state if state is not None else TeleopState.from_control(ControlConfig())
        self.quit_reason = ""
        self._on_quit = on_quit
        self._fd = fd
        self._clock = clock
        self._decoder = KeyDecoder(esc_timeout)
        self._banner = banner
        self._loop: Optional[asyncio.AbstractEventLoop] = None
        self._tty = -1
        self._saved = None
        self._reading = False
        self._timer: Optional[asyncio.TimerHandle] = None
        self._signals: List[int] = []
        self._status = ""
        self.dropped_writes = 0

    # Public interface  ------

    async def __aenter__(self) -> TerminalKeyboard:
        fd = self._input_fd()
        if termios is None:  # pragma: no cover
            raise NotATerminalError("robotctl teleop needs a POSIX terminal (no termios on this system)")
        try:
            self._tty = os.open(os.ttyname(fd), os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
            self._saved = termios.tcgetattr(self._tty)
        except OSError as e:
            self._close_tty()
            raise NotATerminalError(f"robotctl teleop cannot open its terminal: {e}") from e
        self._loop = asyncio.get_running_loop()
        try:
            termios.tcsetattr(self._tty, termios.TCSAFLUSH, _teleop_mode(self._saved))
            self._loop.add_reader(self._tty, self._on_readable)
            self._reading = True
            self._install_signals()
            if self._banner:
                self._write(CLEAR_LINE + "teleop: " + _help_text(self.state) + "\n")
        except BaseException:
            self._restore()
            raise
        return self

    async def __aexit__(self, *exc) -> None:
        self._restore()

    def show(self, text: str) -> None:
        """Rewrite the status line in place (cut to the terminal width). Never blocks."""
        line = fit_line(text, self._width())
        if line == self._status or self._tty < 0:
            return
        self._status = line
        self._write(CLEAR_LINE + line)

    def message(self, text: str) -> None:
        """Print a line above the status line (events the user must see), then redraw the status."""
        if self._tty >= 0:
            self._write(CLEAR_LINE + text + "\n" + self._status)

    # Private interface  ------

    def _input_fd(self) -> int:
        if self._fd is not None:
            fd = self._fd
        else:
            try:
                fd = sys.stdin.fileno()
            except (AttributeError, ValueError, OSError):  # None, closed or a replaced stdin
                raise NotATerminalError("robotctl teleop reads keys from stdin, but there is no stdin "
                                        "(run it in an interactive terminal)") from None
        if not os.isatty(fd):
            raise NotATerminalError("robotctl teleop reads keys from a terminal, but stdin is not one (a pipe or "
                                    "a file?); run it in an interactive terminal, over ssh with `ssh -t`")
        return fd

    def _on_readable(self) -> None:
        try:
            data = os.read(self._tty, 1024)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as e:  # EIO: the terminal hung up
            self._end_input(f"terminal closed ({e.strerror})")
            return
        if not data:
            self._end_input("end of input")
            return
        t = self._clock()
        for key in self._decoder.feed(data, t):
            self._key(key, t, "key")
        self._schedule_expire()

    def _expire(self) -> None:
        self._timer = None
        t = self._clock()
        for key in self._decoder.expire(t):
            self._key(key, t, "key")
        self._schedule_expire()

    def _schedule_expire(self) -> None:
        deadline = self._decoder.deadline
        if deadline is None or self._timer is not None or self._loop is None:
            return
        self._timer = self._loop.call_later(max(deadline - self._clock(), 0.0) + 1e-3, self._expire)

    def _key(self, key: str, t: float, why: str) -> None:
        self.state.press(key, t)
        if key == QUIT and not self.quit_reason:
            self.quit_reason = why
            self._on_quit()

    def _end_input(self, why: str) -> None:
        self._stop_reading()  # a hung-up fd stays readable: keep it from spinning the loop
        self._key(QUIT, self._clock(), why)

    def _on_signal(self, signum: int) -> None:
        self._key(QUIT, self._clock(), signal.Signals(signum).name)

    def _install_signals(self) -> None:
        for sig in (signal.SIGHUP, signal.SIGTERM):
            # Only where the default would kill us; the app's own handlers take precedence.
            if signal.getsignal(sig) is not signal.SIG_DFL:
                continue
            try:
                self._loop.add_signal_handler(sig, self._on_signal, int(sig))  # type: ignore[union-attr]
            except (RuntimeError, ValueError, NotImplementedError):  # not the main thread
                continue
            self._signals.append(sig)

    def _stop_reading(self) -> None:
        if self._reading and self._loop is not None:
            self._loop.remove_reader(self._tty)
        self._reading = False

    def _restore(self) -> None:
        # Every step runs even if an earlier one fails: the tty modes matter most.
        self._stop_reading()
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        for sig in self._signals:
            try:
                self._loop.remove_signal_handler(sig)  # type: ignore[union-attr]
            except (RuntimeError, ValueError):
                pass
        self._signals = []
        if self._tty >= 0 and self._saved is not None:
            if self._status:
                self._write("\n")
            for step in (lambda: termios.tcflush(self._tty, termios.TCIFLUSH),
                         lambda: termios.tcsetattr(self._tty, termios.TCSANOW, self._saved)):
                try:
                    step()
                except (OSError, termios.error):
                    pass  # the terminal is gone; nothing left to restore
        self._close_tty()

    def _close_tty(self) -> None:
        if self._tty >= 0:
            try:
                os.close(self._tty)
            except OSError:
                pass
        self._tty = -1

    def _width(self) -> int:
        try:
            cols = os.get_terminal_size(self._tty).columns
        except (OSError, ValueError):
            cols = 0
        return cols if cols > 0 else 80  # a fresh pty reports 0 columns

    def _write(self, text: str) -> None:
        try:
            os.write(self._tty, text.encode("utf-8", "replace"))
        except OSError:  # full (would block) or gone: the status line is best effort
            self.dropped_writes += 1


def _teleop_mode(saved: list) -> list:
    mode = list(saved)
    mode[6] = list(saved[6])
    mode[0] &= ~termios.IXON
    mode[3] &= ~(termios.ECHO | termios.ICANON | termios.ISIG | termios.IEXTEN)
    mode[6][termios.VMIN] = 1
    mode[6][termios.VTIME] = 0
    return mode


def _help_text(state: TeleopState) -> str:
    return (f"{HELP} within {state.deadman:.1f} s. Max {state.max_speed:.2f} m/s, "
            f"{state.max_yaw_rate:.2f} rad/s; now {100.0 * state.speed_fraction:.0f}%.")
