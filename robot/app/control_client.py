"""A client of the control socket (``robotctl status``, ``go``, ...; any Python tool or bridge).

Blocking and dependency-free (``socket`` and ``json``), so that a ROS 2 node or a shell script
can use it as it is. Every failure is a ``ControlError`` with the server's error code (or
``unreachable`` / ``timeout`` / ``bad_reply`` for the connection itself) and one sentence.
"""

from __future__ import annotations

import json
import os
import socket
from typing import Any, Dict, Iterator, Mapping, Optional

from robot.app import control_protocol as proto
from robot.base.errors import RobotError
from robot.config.control_api import DEFAULT_SOCKET

SOCKET_ENV = "ROBOT_CONTROL_SOCKET"  # overrides the default socket path for the command line
MAX_REPLY_BYTES = 16 * 1024 * 1024
UNREACHABLE = "unreachable"
BAD_REPLY = "bad_reply"


def default_socket() -> str:
    return os.environ.get(SOCKET_ENV) or DEFAULT_SOCKET


class ControlError(RobotError):
    """A request the controller refused or could not answer."""

    def __init__(self, code: str, message: str):
        super().__init__(f"{code}: {message}")
        self.code = code
        self.message = message


class ControlClient:
    """One connection to the controller; requests are answered in order."""

    def __init__(self, path: Optional[str] = None, timeout: float = 15.0):
        self.path = path or default_socket()
        self.timeout = float(timeout)
        self._sock: Optional[socket.socket] = None
        self._buf = b""
        self._next_id = 1

    def __enter__(self) -> ControlClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if self._sock is not None:
            try:
                self._sock.close()
            finally:
                self._sock = None
                self._buf = b""

    def connect(self) -> None:
        if self._sock is not None:
            return
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.settimeout(self.timeout)
        try:
            s.connect(self.path)
        except FileNotFoundError:
            s.close()
            raise ControlError(UNREACHABLE, f"no controller socket at {self.path} (is the controller running? "
                                            f"set --socket or {SOCKET_ENV})") from None
        except ConnectionRefusedError:
            s.close()
            raise ControlError(UNREACHABLE, f"nobody listens on {self.path} (a controller that stopped?)") from None
        except PermissionError:
            s.close()
            raise ControlError(UNREACHABLE, f"not allowed to connect to {self.path}: its mode and group decide "
                                            "(control_api.mode, control_api.group)") from None
        except socket.timeout:
            s.close()
            raise ControlError(proto.TIMEOUT, f"connecting to {self.path} timed out") from None
        except OSError as e:
            s.close()
            raise ControlError(UNREACHABLE, f"cannot connect to {self.path}: {e.strerror or e}") from None
        self._sock = s

    def request(self, cmd: str, args: Optional[Mapping[str, Any]] = None, timeout: Optional[float] = None) -> Any:
        """Send one request and return its result; ControlError when it failed."""
        reply = self.exchange(proto.make_request(cmd, args, self._take_id()), timeout)
        if reply.get("ok") is True:
            return reply.get("result")
        err = reply.get("error") if isinstance(reply.get("error"), dict) else {}
        raise ControlError(str(err.get("code", BAD_REPLY)), str(err.get("message", "the controller gave no reason")))

    def exchange(self, message: Mapping[str, Any], timeout: Optional[float] = None) -> Dict[str, Any]:
        """Send a raw request object (or anything JSON) and return the raw reply object."""
        self.connect()
        data = (json.dumps(message, allow_nan=False, separators=(",", ":")) + "\n").encode("utf-8")
        return self.exchange_bytes(data, timeout)

    def exchange_bytes(self, data: bytes, timeout: Optional[float] = None) -> Dict[str, Any]:
        """Send raw bytes (a test's malformed line) and return the reply line as an object."""
        self.connect()
        assert self._sock is not None
        self._sock.settimeout(self.timeout if timeout is None else timeout)
        try:
            self._sock.sendall(data)
        except (BrokenPipeError, ConnectionResetError):
            pass  # the server may have answered and closed (a line too long): read what it said
        except socket.timeout:
            raise ControlError(proto.TIMEOUT, "sending the request timed out") from None
        return self.read_reply()

    def read_reply(self) -> Dict[str, Any]:
        line = self._read_line()
        try:
            reply = json.loads(line.decode("utf-8"))
        except (UnicodeDecodeError, ValueError):
            raise ControlError(BAD_REPLY, "the controller's reply is not JSON") from None
        if not isinstance(reply, dict):
            raise ControlError(BAD_REPLY, "the controller's reply is not a JSON object")
        return reply

    def watch(self, period: float = 0.1) -> Iterator[Dict[str, Any]]:
        """The state every ``period`` seconds, until the caller stops iterating."""
        self.request("watch", {"period": float(period)})
        try:
            while True:
                event = self.read_reply()
                if "event" in event:
                    yield event.get("data", {})
        finally:
            self.close()  # closing ends the stream on the server's side

    def _take_id(self) -> int:
        rid, self._next_id = self._next_id, self._next_id + 1
        return rid

    def _read_line(self) -> bytes:
        assert self._sock is not None
        while b"\n" not in self._buf:
            try:
                chunk = self._sock.recv(65536)
            except socket.timeout:
                raise ControlError(proto.TIMEOUT, f"no reply from the controller within {self._sock.gettimeout():g} s") \
                    from None
            except ConnectionResetError:
                chunk = b""
            if not chunk:
                self.close()
                raise ControlError(UNREACHABLE, "the controller closed the connection without a reply")
            self._buf += chunk
            if len(self._buf) > MAX_REPLY_BYTES:
                self.close()
                raise ControlError(BAD_REPLY, "the controller's reply is too long")
        line, _, self._buf = self._buf.partition(b"\n")
        return line


__all__ = ["ControlClient", "ControlError", "default_socket", "SOCKET_ENV"]
