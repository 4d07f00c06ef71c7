"""The motor board, emulated: its firmware logic and four motors, speaking the real protocol on a pty.

Two layers:

- ``BoardModel``: what the firmware does (handshake, limits, watchdog, reports) plus the physics
  (first-order motors, encoder quantisation, wheel-radius error and slip, the Mecanum ground
  truth pose). Deterministic: it only moves when ``step(dt)`` is called.
- ``FirmwareEmulator``: the model behind the master side of ``os.openpty()``, served by one
  thread, so the unmodified driver and pyserial open the slave side like a USB-UART. It injects
  line faults (drop, corrupt, delay bytes), goes silent, and vanishes and comes back (the pty is
  closed and a new one appears behind the same symlink, as udev does on a replug).

Clock modes: ``clock="realtime"`` steps the model from ``time.monotonic`` in 1 ms substeps;
``clock="sim"`` leaves time to the caller's ``step(dt)`` (bytes are still served at once).
"""

from __future__ import annotations

import collections
import dataclasses
import math
import os
import random
import select
import threading
import time
import tty
from dataclasses import dataclass, field
from typing import Deque, List, Optional, Sequence, Tuple

from firmware_protocol import (
    MRAD,
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
    StatusFlag,
    Stop,
    encode,
)
from firmware_protocol.counters import wrap_i32
from robot.base.geometry import integrate_twist
from robot.config import ChassisConfig

SUBSTEP_US = 1000  # physics and watchdog resolution: 1 ms, like a 1 kHz firmware control loop
FIRMWARE_VERSION = (1, 0, 0)
_TWO_PI = 2.0 * math.pi


class BoardModel:
    """Firmware logic and motor physics of the Mecanum board. Not thread-safe: the emulator locks."""

    def __init__(self, config: Optional[ChassisConfig] = None, *, motor_tau: float = 0.03,
                 radius_error: Sequence[float] = (0.0, 0.0, 0.0, 0.0),
                 slip: Sequence[float] = (0.0, 0.0, 0.0, 0.0), slip_noise: float = 0.0,
                 seed: int = 0, report_period: float = 0.01, status_period: float = 0.1,
                 battery_v: float = 12.0, t0_us: int = 0, tick_offset: Sequence[int] = (0, 0, 0, 0),
                 protocol_version: int = PROTOCOL_VERSION, ticks_per_rev: Optional[int] = None,
                 max_wheel_speed: Optional[float] = None, max_wheel_accel: Optional[float] = None,
                 substep_us: int = SUBSTEP_US):
        cfg = config or ChassisConfig()
        # 1 ms is the firmware's loop; the faster-than-real-time experiment may take coarser
        # steps (the motor response and the arc integration are exact per step).
        self.substep_us = int(substep_us)
        self.r = cfg.wheel_radius
        self.L = cfg.half_wheelbase + cfg.half_track
        self.ticks_per_rev = int(ticks_per_rev or cfg.ticks_per_rev)
        self.max_speed = float(max_wheel_speed if max_wheel_speed is not None else cfg.max_wheel_speed)
        self.max_accel = float(max_wheel_accel if max_wheel_accel is not None else cfg.max_wheel_accel)
        self.watchdog_us = int(round(cfg.watchdog_timeout * 1e6))
        self.report_us = int(round(report_period * 1e6))
        self.status_us = int(round(status_period * 1e6))
        self.motor_tau = float(motor_tau)
        # effective rolling radius factor per wheel: true radius / nominal, times (1 - slip)
        self.rolling = [(1.0 + e) * (1.0 - s) for e, s in zip(radius_error, slip)]
        self.slip_noise = float(slip_noise)
        self.rng = random.Random(seed)
        self.battery_v = float(battery_v)
        self.protocol_version = protocol_version
        self.decoder = Decoder(version=protocol_version)
        self.events: Deque[Tuple[float, str, object]] = collections.deque(maxlen=20000)
        self.received: Deque[Tuple[float, Message]] = collections.deque(maxlen=20000)
        self.outbox: List[Message] = []
        self.pose = (0.0, 0.0, 0.0)
        self.omega = [0.0] * 4  # true shaft speeds, rad/s
        self.theta = [0.0] * 4  # true shaft angles, rad
        self.time_us = 0  # board uptime since the emulator started, never wraps
        self._t0_us = int(t0_us)
        self._tick_offset = [int(v) for v in tick_offset]
        self._frac_us = 0.0
        self.tx_seq = 0
        self.estop = False
        self.motor_faults = 0
        self._boot()

    # Public interface  ------------------------------------------------------------------------

    @property
    def t_board(self) -> float:
        """Board uptime in seconds (the emulator's own clock)."""
        return self.time_us * 1e-6

    @property
    def t_us_wire(self) -> int:
        return (self._t0_us + self.time_us) & 0xFFFFFFFF

    def ticks(self) -> Tuple[int, int, int, int]:
        """Encoder counts as reported: quantised shaft angle, offset, wrapped to int32."""
        k = self.ticks_per_rev / _TWO_PI
        return tuple(wrap_i32(math.floor(th * k) + off) for th, off in zip(self.theta, self._tick_offset))

    def reboot(self, t0_us: int = 0) -> None:
        """MCU reset: session, counters and clock origin restart; the wheels coast on."""
        self._t0_us = int(t0_us) - self.time_us
        k = self.ticks_per_rev / _TWO_PI
        self._tick_offset = [-math.floor(th * k) for th in self.theta]
        self._log("reboot", None)
        self._boot()

    def set_estop(self, active: bool) -> None:
        self.estop = bool(active)
        if active:
            self.target = [0.0] * 4
            self.setpoint = [0.0] * 4
        self._log("estop", self.estop)
        self._update_flags(StatusFlag.ESTOP, active)

    def set_motor_fault(self, wheel: int, active: bool) -> None:
        bit = 1 << wheel
        self.motor_faults = (self.motor_faults | bit) if active else (self.motor_faults & ~bit)
        if active:
            self.target = [0.0] * 4
        self._log("motor_fault", (wheel, active))
        self._emit_status()

    def handle_bytes(self, data: bytes) -> None:
        """Bytes from the host, as the firmware's UART interrupt would see them."""
        before = self.decoder.stats.version_mismatch
        msgs = self.decoder.feed(data)
        if self.decoder.stats.version_mismatch != before:
            self._log("bad_version", self.decoder.stats.foreign_version)
            self._send(Nack(0, 0, NackReason.BAD_VERSION, int(self.decoder.stats.foreign_version or 0)))
        for m in msgs:
            self.handle(m)

    def handle(self, msg: Message) -> None:
        now = self.time_us
        self.received.append((self.t_board, msg))
        self.last_rx_us = now
        self._update_flags(StatusFlag.HOST_SILENT, False)
        if isinstance(msg, Hello):
            self._on_hello(msg)
        elif isinstance(msg, SetWheelSpeeds):
            self._on_speeds(msg)
        elif isinstance(msg, Stop):
            self.target = [0.0] * 4
            self.last_cmd_us = now
            self._log("stop", None)
            self._send(Ack(Stop.MSG_ID, msg.seq))
        elif isinstance(msg, Heartbeat):
            pass  # host presence only: it must never keep wheels turning
        else:
            msg_id = getattr(msg, "msg_id", getattr(msg, "MSG_ID", 0))
            self._send(Nack(msg_id, msg.seq, NackReason.UNKNOWN_MESSAGE, 0))

    def step(self, dt: float) -> None:
        """Advance firmware and physics by dt seconds in 1 ms substeps (a shorter last one)."""
        total = dt * 1e6 + self._frac_us
        n = int(total)
        self._frac_us = total - n
        while n > 0:
            h = min(n, self.substep_us)
            self._substep(h)
            n -= h

    def advance_to(self, t_board: float) -> None:
        """Step up to board time t_board (s); the real-time loop's way of following the wall clock."""
        n = int(t_board * 1e6) - self.time_us
        while n > 0:
            h = min(n, SUBSTEP_US)
            self._substep(h)
            n -= h

    def take_outbox(self) -> bytes:
        data = b"".join(encode(m, version=self.protocol_version) for m in self.outbox)
        self.outbox.clear()
        return data

    # Private interface  -----------------------------------------------------------------------

    def _boot(self) -> None:
        self.session = False
        self.target = [0.0] * 4
        self.setpoint = [0.0] * 4
        self.flags = int(StatusFlag.NO_SESSION) | (int(StatusFlag.ESTOP) if self.estop else 0)
        self.last_cmd_us = self.time_us
        self.last_rx_us = self.time_us
        self.rx_errors_base = self.decoder.stats.dropped_frames
        # reports on a fixed grid from boot: t_us of the n-th report is n * report_period
        self.next_report_us = self.time_us + self.report_us
        self.next_status_us = self.time_us + self.status_us

    def _log(self, kind: str, detail: object) -> None:
        self.events.append((self.t_board, kind, detail))

    def _send(self, msg: Message) -> None:
        self.outbox.append(dataclasses.replace(msg, seq=self.tx_seq))
        self.tx_seq = (self.tx_seq + 1) & 0xFF

    def _on_hello(self, msg: Hello) -> None:
        self.session = True
        self.target = [0.0] * 4  # a new session starts from standstill
        self._log("hello", msg.nonce)
        self._send(HelloReply(
            minor=PROTOCOL_MINOR, nonce=msg.nonce, fw_major=FIRMWARE_VERSION[0], fw_minor=FIRMWARE_VERSION[1],
            fw_patch=FIRMWARE_VERSION[2], ticks_per_rev=self.ticks_per_rev,
            max_speed_mrad_s=int(round(self.max_speed * MRAD)), max_accel_mrad_s2=int(round(self.max_accel * MRAD)),
            watchdog_ms=self.watchdog_us // 1000, report_period_us=self.report_us))
        self._update_flags(StatusFlag.NO_SESSION, False)

    def _on_speeds(self, msg: SetWheelSpeeds) -> None:
        refuse = None
        if self.estop:
            refuse = (NackReason.ESTOP, 0)
        elif self.motor_faults:
            refuse = (NackReason.MOTOR_FAULT, self.motor_faults)
        elif not self.session:
            refuse = (NackReason.NO_SESSION, 0)
        if refuse is not None:
            self._log("nack", (refuse[0].name, msg.rad_s))
            self._send(Nack(SetWheelSpeeds.MSG_ID, msg.seq, refuse[0], refuse[1]))
            return
        w = list(msg.rad_s)
        over = sum(1 << i for i, v in enumerate(w) if abs(v) > self.max_speed)
        if over:
            # one factor for all wheels keeps the direction of travel; per-wheel clamping would bend it
            scale = self.max_speed / max(abs(v) for v in w)
            w = [v * scale for v in w]
            self._log("clamped", (msg.rad_s, tuple(w)))
            self._send(Nack(SetWheelSpeeds.MSG_ID, msg.seq, NackReason.CLAMPED, over))
        else:
            self._send(Ack(SetWheelSpeeds.MSG_ID, msg.seq))
        self.target = w
        self.last_cmd_us = self.time_us
        self._log("command", tuple(w))
        self._update_flags(StatusFlag.CLAMPED, bool(over))
        self._update_flags(StatusFlag.WATCHDOG, False)

    def _update_flags(self, flag: StatusFlag, on: bool) -> None:
        new = (self.flags | int(flag)) if on else (self.flags & ~int(flag))
        if new != self.flags:
            self.flags = new
            self._emit_status()  # every flag change is reported at once (PROTOCOL.md section 5)

    def _emit_status(self) -> None:
        rx_errors = min(0xFFFF, self.decoder.stats.dropped_frames - self.rx_errors_base)
        self._send(Status(t_us=self.t_us_wire, battery_mv=int(round(self.battery_v * 1000)),
                          motor_faults=self.motor_faults, flags=self.flags, rx_errors=rx_errors))

    def _substep(self, h_us: int) -> None:
        self.time_us += h_us
        now = self.time_us
        h = h_us * 1e-6
        # 1. command watchdog: only fresh speed commands (or STOP) keep wheels turning
        if any(self.target) and now - self.last_cmd_us >= self.watchdog_us:
            self.target = [0.0] * 4
            self._log("watchdog", (now - self.last_cmd_us) * 1e-6)
            self._update_flags(StatusFlag.WATCHDOG, True)
        if now - self.last_rx_us >= self.watchdog_us and not self.flags & StatusFlag.HOST_SILENT:
            self._log("host_silent", None)
            self._update_flags(StatusFlag.HOST_SILENT, True)
        # 2. acceleration limit: move all setpoints along one straight line towards the target
        diff = [t - s for t, s in zip(self.target, self.setpoint)]
        peak = max(abs(d) for d in diff)
        if peak > 0.0:
            k = min(1.0, self.max_accel * h / peak)
            self.setpoint = [s + d * k for s, d in zip(self.setpoint, diff)]
        # 3. motors: exact first-order response to the held setpoint; encoders integrate the shaft
        a = 1.0 - math.exp(-h / self.motor_tau) if self.motor_tau > 0 else 1.0
        old = self.omega
        self.omega = [w + (s - w) * a for w, s in zip(old, self.setpoint)]
        self.theta = [th + 0.5 * (w0 + w1) * h for th, w0, w1 in zip(self.theta, old, self.omega)]
        # 4. ground truth: each wheel rolls with its true radius, less slip
        eff = [0.5 * (w0 + w1) * f for w0, w1, f in zip(old, self.omega, self.rolling)]
        if self.slip_noise > 0.0:
            eff = [e * (1.0 - abs(self.rng.gauss(0.0, self.slip_noise))) for e in eff]
        r4 = self.r / 4.0
        vx = r4 * (eff[0] + eff[1] + eff[2] + eff[3])
        vy = r4 * (-eff[0] + eff[1] + eff[2] - eff[3])
        wz = r4 / self.L * (-eff[0] + eff[1] - eff[2] + eff[3])
        self.pose = integrate_twist(*self.pose, vx, vy, wz, h)
        # 5. periodic reports
        if now >= self.next_report_us:
            self.next_report_us += self.report_us
            self._send(EncoderReport(t_us=self.t_us_wire, ticks=self.ticks()))
        if now >= self.next_status_us:
            self.next_status_us += self.status_us
            self._emit_status()


@dataclass
class LineFaults:
    """Faults on one direction of the serial line. Probabilities are per byte."""

    drop: float = 0.0
    corrupt: float = 0.0  # flip one random bit
    delay: float = 0.0  # seconds every byte is held back (wall clock)
    seed: int = 0
    dropped: int = 0
    corrupted: int = 0
    _held: Deque[Tuple[float, bytes]] = field(default_factory=collections.deque, repr=False)

    def __post_init__(self) -> None:
        self._rng = random.Random(self.seed)

    def apply(self, data: bytes, now: float) -> bytes:
        """Bytes to deliver now: ``data`` after drop/corrupt, and whatever delayed bytes fell due."""
        if data and (self.drop > 0.0 or self.corrupt > 0.0):
            out = bytearray()
            for b in data:
                if self._rng.random() < self.drop:
                    self.dropped += 1
                    continue
                if self._rng.random() < self.corrupt:
                    b ^= 1 << self._rng.randrange(8)
                    self.corrupted += 1
                out.append(b)
            data = bytes(out)
        if self.delay <= 0.0 and not self._held:
            return data
        if data:
            self._held.append((now + self.delay, data))
        due = bytearray()
        while self._held and self._held[0][0] <= now:
            due += self._held.popleft()[1]
        return bytes(due)

    def next_due(self) -> Optional[float]:
        return self._held[0][0] if self._held else None


class FirmwareEmulator:
    """A ``BoardModel`` on the far end of a real pseudo-terminal, served by one thread.

    ``port`` is what the driver opens: ``link_path`` (a symlink standing in for the udev one,
    re-pointed by ``reappear``) when given, else the pty slave's own path. Every public method is
    thread-safe. Use as a context manager or call ``start()`` and ``close()``.
    """

    def __init__(self, config: Optional[ChassisConfig] = None, *, clock: str = "realtime",
                 link_path: Optional[str] = None, tx_faults: Optional[LineFaults] = None,
                 rx_faults: Optional[LineFaults] = None, **board_kwargs):
        if clock not in ("realtime", "sim"):
            raise ValueError(f"clock must be 'realtime' or 'sim', got {clock!r}")
        self.board = BoardModel(config, **board_kwargs)
        self.clock = clock
        self.link_path = str(link_path) if link_path else None
        self.tx_faults = tx_faults or LineFaults()  # board -> host
        self.rx_faults = rx_faults or LineFaults()  # host -> board
        self.silent = False
        self.tx_overflow = 0  # bytes the pty would not take (nobody reading): lost, as on a UART
        self._lock = threading.RLock()
        self._master: Optional[int] = None
        self._slave: Optional[int] = None
        self._slave_name = ""
        self._wake_r, self._wake_w = os.pipe()
        self._running = False
        self._thread: Optional[threading.Thread] = None
        self._t_start = 0.0

    # Lifecycle  -------------------------------------------------------------------------------

    def start(self) -> FirmwareEmulator:
        with self._lock:
            if self._running:
                return self
            self._open_pty()
            self._running = True
            self._t_start = time.monotonic() - self.board.t_board
        self._thread = threading.Thread(target=self._serve, name="firmware-emulator", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        with self._lock:
            self._running = False
        self._wake()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        with self._lock:
            self._close_pty()
        for fd in (self._wake_r, self._wake_w):
            try:
                os.close(fd)
            except OSError:
                pass
        self._wake_r = self._wake_w = -1

    def __enter__(self) -> FirmwareEmulator:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def port(self) -> str:
        return self.link_path or self._slave_name

    # Simulation interface  --------------------------------------------------------------------

    def step(self, dt: float) -> None:
        """Advance the board by dt (clock="sim" only) and send the reports that fell due."""
        if self.clock != "sim":
            raise RuntimeError("step() drives the simulated clock; this emulator runs in real time")
        with self._lock:
            self.board.step(dt)
            self._flush_locked(time.monotonic())

    @property
    def pose(self) -> Tuple[float, float, float]:
        """Ground-truth (x, y, phi) integrated from the true wheel motion, radius error and slip."""
        with self._lock:
            return self.board.pose

    def teleport(self, x: float, y: float, phi: float) -> None:
        """Carry the simulated robot to (x, y, phi) without turning its wheels (a kidnap, for tests)."""
        with self._lock:
            self.board.pose = (float(x), float(y), float(phi))  # type: ignore[assignment]

    @property
    def true_wheel_speeds(self) -> Tuple[float, ...]:
        with self._lock:
            return tuple(self.board.omega)

    @property
    def setpoints(self) -> Tuple[float, ...]:
        with self._lock:
            return tuple(self.board.setpoint)

    @property
    def t_board(self) -> float:
        with self._lock:
            return self.board.t_board

    def events(self, kind: Optional[str] = None) -> List[Tuple[float, str, object]]:
        with self._lock:
            return [e for e in self.board.events if kind is None or e[1] == kind]

    def received(self) -> List[Tuple[float, Message]]:
        """Every message the board decoded, with its board time: the host's side of the story."""
        with self._lock:
            return list(self.board.received)

    # Fault injection  -------------------------------------------------------------------------

    def go_silent(self, silent: bool = True) -> None:
        """Stop (or resume) transmitting; the board keeps receiving and running."""
        with self._lock:
            self.silent = bool(silent)
            self.board._log("silent", self.silent)

    def set_estop(self, active: bool) -> None:
        with self._lock:
            self.board.set_estop(active)
            self._flush_locked(time.monotonic())

    def set_motor_fault(self, wheel: int, active: bool) -> None:
        with self._lock:
            self.board.set_motor_fault(wheel, active)
            self._flush_locked(time.monotonic())

    def reboot(self, t0_us: int = 0) -> None:
        """Brown-out: the board restarts while the port stays (a USB-UART powered by the host)."""
        with self._lock:
            self.board.reboot(t0_us)
            self._flush_locked(time.monotonic())

    def vanish(self) -> None:
        """Unplug: the pty (and the symlink) disappear; the board itself keeps running."""
        with self._lock:
            self.board._log("vanish", None)
            self._close_pty()
        self._wake()

    def reappear(self, reboot: bool = True, t0_us: int = 0) -> None:
        """Replug: a new pty behind the same symlink; with ``reboot`` the board restarts too."""
        with self._lock:
            if reboot:
                self.board.reboot(t0_us)
            self.board._log("reappear", reboot)
            self._open_pty()
        self._wake()

    # Private interface  -----------------------------------------------------------------------

    def _open_pty(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo, no CR/LF mangling before pyserial configures the port
        os.set_blocking(master, False)
        self._master, self._slave = master, slave
        self._slave_name = os.ttyname(slave)
        if self.link_path:
            tmp = self.link_path + ".new"
            try:
                os.unlink(tmp)
            except FileNotFoundError:
                pass
            os.symlink(self._slave_name, tmp)
            os.replace(tmp, self.link_path)
        # a fresh line starts with a delimiter so the host's decoder drops any half frame
        self._write_locked(b"\x00")

    def _close_pty(self) -> None:
        if self.link_path:
            try:
                os.unlink(self.link_path)
            except FileNotFoundError:
                pass
        for fd in (self._master, self._slave):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._master = self._slave = None

    def _wake(self) -> None:
        try:
            os.write(self._wake_w, b"x")
        except OSError:
            pass

    def _serve(self) -> None:
        while True:
            with self._lock:
                if not self._running:
                    return
                master = self._master
                due = self.tx_faults.next_due()
            now = time.monotonic()
            timeout = 0.001 if self.clock == "realtime" else 0.02
            if due is not None:
                timeout = max(0.0, min(timeout, due - now))
            fds = [self._wake_r] + ([master] if master is not None else [])
            try:
                ready, _, _ = select.select(fds, [], [], timeout)
            except (OSError, ValueError):
                ready = []  # the pty was closed under us by vanish(): loop and look again
            data = b""
            if self._wake_r in ready:
                os.read(self._wake_r, 64)
            with self._lock:
                # re-check under the lock: vanish() may have closed this fd and its number been reused
                if master is not None and master in ready and master == self._master:
                    try:
                        data = os.read(master, 4096)
                    except OSError:
                        data = b""
                now = time.monotonic()
                data = self.rx_faults.apply(data, now)
                if data:
                    # apply before stepping: a command counts from the board time it was read at
                    self.board.handle_bytes(data)
                if self.clock == "realtime":
                    self.board.advance_to(now - self._t_start)
                self._flush_locked(now)

    def _flush_locked(self, now: float) -> None:
        data = self.board.take_outbox()
        if self.silent:
            data = b""
        data = self.tx_faults.apply(data, now)
        if data:
            self._write_locked(data)

    def _write_locked(self, data: bytes) -> None:
        if self._master is None:
            return
        try:
            n = os.write(self._master, data)
        except BlockingIOError:
            n = 0
        except OSError:
            return
        self.tx_overflow += len(data) - n
