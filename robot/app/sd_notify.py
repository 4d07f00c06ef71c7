"""The systemd notify protocol (``sd_notify(3)``) in plain ``socket`` code.

Under ``Type=notify`` systemd passes ``$NOTIFY_SOCKET``, an AF_UNIX datagram socket; a service
reports ``READY=1`` once it can do its job, ``STATUS=...`` for ``systemctl status``, and, with
``WatchdogSec=``, ``WATCHDOG=1`` more often than ``$WATCHDOG_USEC``. Outside systemd every call
is a no-op returning False, so the same code runs on a laptop, in tests and on the robot.

Nothing here raises: a robot must never stop because its supervisor went away. A failed send is
logged once and reported as False.

Ping the watchdog from the control loop itself (``WatchdogPinger.tick()`` once per iteration),
never from a side timer: the point is that a hung loop stops the pings and systemd restarts us.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
from typing import Callable, Optional, Union

log = logging.getLogger(__name__)

_lock = threading.Lock()
_sock: Optional[socket.socket] = None
_warned = False


def _address(value: str) -> Optional[Union[str, bytes]]:
    """The socket address for a ``$NOTIFY_SOCKET`` value, or None if we cannot use it.

    ``@name`` is Linux's abstract namespace, spelled with a leading NUL byte on the wire.
    Newer systemd may also hand out ``vsock:`` addresses (VMs); a robot never needs them.
    """
    if value.startswith("/"):
        return value
    if value.startswith("@") and len(value) > 1:
        return b"\0" + os.fsencode(value[1:])
    return None


def _warn_once(message: str, *args) -> None:
    global _warned
    if not _warned:
        _warned = True
        log.warning(message, *args)


def notify(state: str) -> bool:
    """Send one notify message (e.g. ``"READY=1\\nSTATUS=ok"``); True if it was sent."""
    global _sock
    value = os.environ.get("NOTIFY_SOCKET")
    if not value:
        return False
    addr = _address(value)
    if addr is None:
        _warn_once("NOTIFY_SOCKET=%r is not a unix socket address; systemd notifications disabled", value)
        return False
    try:
        with _lock:
            if _sock is None:
                sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
                sock.set_inheritable(False)
                _sock = sock
            _sock.sendto(state.encode("utf-8"), addr)
        return True
    except OSError as e:
        _warn_once("cannot notify systemd at %s: %s (further failures are not logged)", value, e)
        return False


def ready(status_text: Optional[str] = None) -> bool:
    """Startup is complete (cameras, chassis and map are up)."""
    msg = "READY=1"
    if status_text is not None:
        msg += "\nSTATUS=" + _one_line(status_text)
    return notify(msg)


def status(text: str) -> bool:
    """The one-line status ``systemctl status`` shows (e.g. localization quality)."""
    return notify("STATUS=" + _one_line(text))


def watchdog() -> bool:
    """One keep-alive ping. Prefer ``WatchdogPinger`` in a loop: it sends only when due."""
    return notify("WATCHDOG=1")


def stopping(status_text: Optional[str] = None) -> bool:
    """Shutdown has begun (after SIGTERM, while the wheels are being stopped)."""
    msg = "STOPPING=1"
    if status_text is not None:
        msg += "\nSTATUS=" + _one_line(status_text)
    return notify(msg)


def extend_timeout(seconds: float) -> bool:
    """Ask for more time to start or stop (``EXTEND_TIMEOUT_USEC``, systemd >= 236).

    Useful while waiting for a camera that is re-enumerating after a hardware reset, so
    ``TimeoutStartSec`` does not kill a start that is making progress.
    """
    return notify(f"EXTEND_TIMEOUT_USEC={max(0, int(seconds * 1e6))}")


def watchdog_interval() -> Optional[float]:
    """``$WATCHDOG_USEC`` in seconds if the watchdog applies to this process, else None.

    ``$WATCHDOG_PID``, when set, names the process the watchdog is meant for; a child that
    inherited the environment must not ping on its parent's behalf.
    """
    usec = os.environ.get("WATCHDOG_USEC")
    if not usec:
        return None
    pid = os.environ.get("WATCHDOG_PID")
    if pid:
        try:
            if int(pid) != os.getpid():
                return None
        except ValueError:
            return None
    try:
        value = int(usec)
    except ValueError:
        return None
    if value <= 0:
        return None
    return value / 1e6


class WatchdogPinger:
    """Sends ``WATCHDOG=1`` at most every half watchdog interval, as sd_watchdog_enabled(3) advises.

    Call ``tick()`` once per control-loop iteration. With no watchdog configured (not under
    systemd, or no ``WatchdogSec=``) ``tick()`` does nothing and returns False.
    """

    def __init__(self, interval: Optional[float] = None, clock: Callable[[], float] = time.monotonic):
        self.interval = watchdog_interval() if interval is None else interval
        self._clock = clock
        self._last: Optional[float] = None

    @property
    def enabled(self) -> bool:
        return self.interval is not None

    def tick(self) -> bool:
        """Ping if due; True when a ping was sent."""
        if self.interval is None:
            return False
        now = self._clock()
        if self._last is not None and now - self._last < self.interval / 2.0:
            return False
        self._last = now
        return watchdog()


def _one_line(text: str) -> str:
    # A newline would start a new KEY=VALUE assignment in the notify message.
    return " ".join(str(text).splitlines())


def _reset_for_tests() -> None:
    """Forget the cached socket and the warn-once flag."""
    global _sock, _warned
    with _lock:
        if _sock is not None:
            _sock.close()
        _sock = None
        _warned = False
