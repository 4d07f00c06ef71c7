"""Logging set-up: plain lines on a terminal, syslog-priority lines when stderr is the journal.

Under systemd, stderr is a stream into journald (the unit's default ``StandardError=journal``)
and systemd says so in ``JOURNAL_STREAM`` (``<device>:<inode>`` of that stream). journald reads
a ``<N>`` prefix on each line as its syslog priority, so ``journalctl -p warning`` shows exactly
the app's warnings and errors; without the prefix every line would be stored as info. The
journal stamps each line itself, so these lines carry no time of their own.

``JOURNAL_STREAM`` is inherited by children, so it is trusted only when it names the stream
stderr really is (a ``robotctl`` started from a shell inside a service, with stderr redirected to
a file, writes plain lines).
"""

from __future__ import annotations

import logging
import os
import sys
import traceback
from typing import Mapping, Optional, TextIO

PLAIN_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
JOURNAL_FORMAT = "%(levelname)s %(name)s: %(message)s"

# syslog priorities (RFC 5424), what journald stores and ``journalctl -p`` filters on
EMERG, ALERT, CRIT, ERR, WARNING, NOTICE, INFO, DEBUG = range(8)


def syslog_priority(levelno: int) -> int:
    """The syslog priority of a Python log level (levels between two take the more severe one)."""
    if levelno >= logging.CRITICAL:
        return CRIT
    if levelno >= logging.ERROR:
        return ERR
    if levelno >= logging.WARNING:
        return WARNING
    if levelno >= logging.INFO:
        return INFO
    return DEBUG


class JournalFormatter(logging.Formatter):
    """``<N>LEVEL logger: message``; every line of a multi-line record (a traceback) carries the
    prefix, or journald would store its continuation lines as info."""

    def __init__(self, fmt: str = JOURNAL_FORMAT):
        super().__init__(fmt)

    def format(self, record: logging.LogRecord) -> str:
        prefix = f"<{syslog_priority(record.levelno)}>"
        return "\n".join(prefix + line for line in super().format(record).splitlines() or [""])


def stream_is_journal(stream: TextIO, environ: Optional[Mapping[str, str]] = None) -> bool:
    """True when ``stream`` is the journal stream ``JOURNAL_STREAM`` names (systemd's way to say so)."""
    value = (os.environ if environ is None else environ).get("JOURNAL_STREAM", "")
    device, sep, inode = value.partition(":")
    if not sep:
        return False
    try:
        st = os.fstat(stream.fileno())
        return (st.st_dev, st.st_ino) == (int(device), int(inode))
    except (AttributeError, OSError, ValueError):  # no file descriptor (a test's capture), or a malformed value
        return False


def journal_prefix(levelno: int, stream: Optional[TextIO] = None) -> str:
    """The priority prefix for a line written to ``stream`` (stderr) directly, or "" off the journal."""
    return f"<{syslog_priority(levelno)}>" if stream_is_journal(stream or sys.stderr) else ""


def setup_logging(verbose: bool = False, stream: Optional[TextIO] = None,
                  environ: Optional[Mapping[str, str]] = None) -> bool:
    """Configure the root logger for ``robotctl``; True when the lines go to the journal.

    On the journal, an uncaught exception is logged too (at critical, every line prefixed), so a
    crash is in ``journalctl -p err`` rather than stored as info lines.
    """
    stream = sys.stderr if stream is None else stream
    journal = stream_is_journal(stream, environ)
    root = logging.getLogger()
    ours = [h for h in root.handlers if getattr(h, "_robotctl", False)]
    if root.handlers and not ours:
        return journal  # logging set up by whoever runs us (a test harness), as logging.basicConfig leaves it
    for old in ours:  # one handler per process, however often main() runs
        root.removeHandler(old)
    handler = logging.StreamHandler(stream)
    handler.setFormatter(JournalFormatter() if journal else logging.Formatter(PLAIN_FORMAT))
    handler._robotctl = True  # type: ignore[attr-defined]
    root.addHandler(handler)
    root.setLevel(logging.DEBUG if verbose else logging.INFO)
    if journal:
        sys.excepthook = _log_uncaught
    return journal


def _log_uncaught(exc_type, exc, tb) -> None:
    if issubclass(exc_type, KeyboardInterrupt):
        sys.__excepthook__(exc_type, exc, tb)
        return
    text = "".join(traceback.format_exception(exc_type, exc, tb)).rstrip()
    logging.getLogger("robotctl").critical("uncaught exception:\n%s", text)


__all__ = ["JournalFormatter", "setup_logging", "stream_is_journal", "journal_prefix", "syslog_priority"]
