"""The control socket: the running controller's JSON-line API on a Unix socket (docs/control-api.md).

One asyncio server on the app's event loop (``asyncio.start_unix_server``), never a network
listener. Bounds, so that no client can hurt the robot or the loop:

- a request line is at most ``control_api.max_request_bytes``; a longer one gets ``too_long``
  and the connection is closed (the stream cannot be trusted after it);
- at most ``max_clients`` connections; one more gets ``busy`` and is closed;
- each request is answered within ``request_timeout`` (``relocalize_timeout`` for relocalize)
  or gets ``timeout``; a connection silent for ``idle_timeout`` is closed;
- a client that leaves mid-request costs nothing: its reply is dropped;
- a request is parsed strictly (``robot.app.control_protocol``) before the operator
  (``robot.app.operator``) sees it, and every failure is one error reply, never a traceback.

Access: the socket file is created with ``mode`` and ``group`` before it appears under its name
(bound under a temporary name, chmod/chown, then renamed), so there is no moment in which
anybody else may connect. Commands that move the robot also check the peer's kernel
credentials (SO_PEERCRED): root, the controller's own user and members of ``motion_groups``
only. Every accepted command is logged with the peer's uid and pid.
"""

from __future__ import annotations

import asyncio
import grp
import logging
import os
import pwd
import socket
import stat
import struct
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Dict, FrozenSet, Optional, Set

from robot.app import control_protocol as proto
from robot.app.operator import json_safe
from robot.base.errors import ConfigError, RobotError
from robot.config.control_api import ControlApiConfig
from robot.control.core import CommandRefused

if TYPE_CHECKING:
    from robot.app.operator import Operator

log = logging.getLogger(__name__)

_CRED = struct.Struct("3i")  # struct ucred: pid, uid, gid


@dataclass
class Peer:
    """Who is on the other end of a connection, from the kernel (SO_PEERCRED)."""

    pid: int
    uid: int
    gid: int
    _groups: Optional[FrozenSet[int]] = field(default=None, repr=False)

    @property
    def user(self) -> str:
        try:
            return pwd.getpwuid(self.uid).pw_name
        except KeyError:
            return f"uid {self.uid}"

    def groups(self) -> FrozenSet[int]:
        """The primary group and, from the user database, the supplementary ones."""
        if self._groups is None:
            gids = {self.gid}
            try:
                gids.update(os.getgrouplist(pwd.getpwuid(self.uid).pw_name, self.gid))
            except (KeyError, OSError):
                pass  # a uid without a passwd entry has only the group the kernel reports
            self._groups = frozenset(gids)
        return self._groups

    def describe(self) -> str:
        return f"uid {self.uid} ({self.user}) pid {self.pid}"


def peer_credentials(sock: Any) -> Optional[Peer]:
    """The connected peer's credentials; None where the platform has no SO_PEERCRED."""
    option = getattr(socket, "SO_PEERCRED", None)
    if option is None or sock is None:
        return None
    try:
        pid, uid, gid = _CRED.unpack(sock.getsockopt(socket.SOL_SOCKET, option, _CRED.size))
    except OSError:
        return None
    return Peer(pid, uid, gid)


def resolve_group(name: str, key: str) -> int:
    """A gid from a group name or number; ConfigError naming the config key."""
    if name.isdigit():
        return int(name)
    try:
        return grp.getgrnam(name).gr_gid
    except KeyError:
        raise ConfigError(f"control_api.{key}: there is no group '{name}' on this system") from None


def bind_socket(config: ControlApiConfig) -> socket.socket:
    """A listening Unix socket at ``config.socket`` with its mode and group already set.

    The socket listens before its name appears: a client that finds the path (robotctl started
    beside the controller, a readiness probe) is queued in the backlog until the event loop
    serves it, never refused with "nobody listens".
    """
    path = os.path.abspath(config.socket)
    directory = os.path.dirname(path)
    try:
        os.makedirs(directory, mode=0o755, exist_ok=True)
    except OSError as e:
        raise ConfigError(f"control_api.socket: cannot create the directory {directory}: {e.strerror}") from None
    _clear_stale(path)
    gid = resolve_group(config.group, "group") if config.group else -1
    tmp = os.path.join(directory, f".ctl-{os.getpid()}.tmp")
    if os.path.lexists(tmp):
        os.unlink(tmp)
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        sock.bind(tmp)
        os.chmod(tmp, config.mode)
        if gid >= 0:
            os.chown(tmp, -1, gid)
        sock.listen(config.max_clients + 1)  # asyncio listens again with its own backlog: harmless
        os.rename(tmp, path)  # only now can anyone connect, and the mode and group are already right
    except OSError as e:
        sock.close()
        if os.path.lexists(tmp):
            os.unlink(tmp)
        raise ConfigError(f"control_api.socket: cannot create {path}: {e.strerror or e}") from None
    sock.setblocking(False)
    return sock


def _clear_stale(path: str) -> None:
    """Remove a socket a crashed controller left behind; refuse to touch anything else."""
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return
    if not stat.S_ISSOCK(st.st_mode):
        raise ConfigError(f"control_api.socket: {path} exists and is not a socket: refusing to replace it")
    probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    probe.settimeout(1.0)
    try:
        probe.connect(path)
    except (ConnectionRefusedError, FileNotFoundError):
        os.unlink(path)  # nobody listens: stale
        return
    except OSError as e:
        raise ConfigError(f"control_api.socket: cannot tell whether {path} is in use: {e.strerror or e}") from None
    finally:
        probe.close()
    raise ConfigError(f"control_api.socket: another process listens on {path} (a second controller?)")


class ControlServer:
    """The control socket as an app service: ``await start()``, ``await stop()``."""

    def __init__(self, operator: Operator, config: ControlApiConfig):
        self.operator = operator
        self.config = config
        self.path = os.path.abspath(config.socket)
        self._server: Optional[asyncio.AbstractServer] = None
        self._inode: Optional[int] = None
        self._motion_gids: FrozenSet[int] = frozenset()
        self._clients: Set[asyncio.Task] = set()
        self.stats: Dict[str, int] = {"connections": 0, "refused_busy": 0, "requests": 0, "errors": 0}

    async def start(self) -> None:
        self._motion_gids = frozenset(resolve_group(g, f"motion_groups ({g})") for g in self.config.motion_groups)
        sock = bind_socket(self.config)
        self._inode = os.stat(self.path).st_ino
        # The stream limit is the longest line readline accepts: a longer one raises, unread.
        self._server = await asyncio.start_unix_server(self._serve, sock=sock, limit=self.config.max_request_bytes)
        log.info("control socket %s (mode %o%s)", self.path, self.config.mode,
                 f", group {self.config.group}" if self.config.group else "")

    async def stop(self) -> None:
        if self._server is None:
            return
        self._server.close()
        for task in list(self._clients):
            task.cancel()
        for task in list(self._clients):
            try:
                await task
            except (asyncio.CancelledError, Exception):  # noqa: PERF203 - every client must go
                pass
        await self._server.wait_closed()
        self._server = None
        try:  # only our own socket: a newer controller may already have replaced it
            if os.stat(self.path).st_ino == self._inode:
                os.unlink(self.path)
        except OSError:
            pass

    # -- one connection -----------------------------------------------------------------------

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        if len(self._clients) >= self.config.max_clients:
            self.stats["refused_busy"] += 1
            await self._send_quietly(writer, proto.error_reply(
                None, proto.BUSY, f"the controller serves {self.config.max_clients} clients at once: try again later"))
            writer.close()
            return
        self._clients.add(task)
        self.stats["connections"] += 1
        peer = peer_credentials(writer.get_extra_info("socket"))
        conn = _Connection(peer)
        try:
            while True:
                try:
                    line = await asyncio.wait_for(reader.readline(), self.config.idle_timeout)
                except asyncio.TimeoutError:
                    break
                except ValueError:  # longer than the limit: the rest of the stream is not a request
                    await self._send(writer, proto.error_reply(
                        None, proto.TOO_LONG, f"a request line may be at most {self.config.max_request_bytes} bytes"))
                    break
                if not line:
                    break
                if not line.strip():
                    continue  # blank lines keep nothing waiting
                if not await self._request(line, conn, reader, writer):
                    break
        except (ConnectionError, asyncio.TimeoutError, OSError):
            pass  # the client left or stopped reading: nothing to answer
        finally:
            self._clients.discard(task)
            writer.close()

    async def _request(self, line: bytes, conn: _Connection, reader, writer) -> bool:
        """Answer one request line; False when the connection should end."""
        self.stats["requests"] += 1
        rid = None
        try:
            obj = proto.decode_json(line.strip())
            rid = proto.request_id(obj)
            req = proto.parse_request(obj)
            if req.motion:
                why = self._forbidden(conn.peer)
                if why:
                    log.warning("control: %s refused for %s: %s", req.cmd, _who(conn.peer), why)
                    raise proto.ProtocolError(proto.FORBIDDEN, why)
            conn.log_accepted(req)
            if req.cmd == "watch":
                return await self._watch(req, reader, writer)
            timeout = self.config.relocalize_timeout if req.cmd == "relocalize" else self.config.request_timeout
            result = await asyncio.wait_for(self._dispatch(req, conn.peer), timeout)
            reply = proto.ok_reply(rid, json_safe(result))
        except proto.ProtocolError as e:
            reply = proto.error_reply(rid, e.code, e.message)
        except CommandRefused as e:
            reply = proto.error_reply(rid, proto.REFUSED, str(e))
        except asyncio.TimeoutError:
            reply = proto.error_reply(rid, proto.TIMEOUT, "the controller did not finish the request in time")
        except RobotError as e:  # a bad path file, a goto target out of range, a region outside the map
            reply = proto.error_reply(rid, proto.BAD_ARGS, str(e))
        except Exception as e:  # a defect: logged with its traceback here, one line for the client
            log.exception("control: request failed")
            reply = proto.error_reply(rid, proto.INTERNAL, f"internal error: {type(e).__name__}: {str(e)[:200]}")
        if not reply["ok"]:
            self.stats["errors"] += 1
        await self._send(writer, reply)
        return True

    def _forbidden(self, peer: Optional[Peer]) -> str:
        """Why this peer may not move the robot ("" when it may)."""
        if peer is None:
            return "the client's credentials are unknown: commands that move the robot are refused"
        if peer.uid == 0 or peer.uid == os.geteuid() or peer.groups() & self._motion_gids:
            return ""
        allowed = ", ".join(self.config.motion_groups) or "none configured"
        return (f"{peer.user} (uid {peer.uid}) may not move the robot: not root, not the controller's user and in "
                f"none of control_api.motion_groups ({allowed})")

    async def _dispatch(self, req: proto.Request, peer: Optional[Peer]) -> Any:
        op, a, cmd = self.operator, req.args, req.cmd
        who = f"control socket ({_who(peer)})"
        if cmd == "status":
            return op.status()
        if cmd == "set-pose":
            std = None
            if "std_xy" in a or "std_phi" in a:
                d_xy, _, d_phi = op.app.options.initial_cov
                std = (a.get("std_xy", d_xy), a.get("std_phi", d_phi))
            return await op.set_pose((a["x"], a["y"], a["phi"]), std, a.get("force", False), source=who)
        if cmd == "go":
            return op.go_text(a["path"], a.get("name", "<path from the control socket>"), a.get("replace", False))
        if cmd == "goto":
            return op.goto(a["x"], a["y"], a.get("phi"), a.get("speed"), a.get("tolerance"), a.get("replace", False))
        if cmd == "pause":
            return op.pause()
        if cmd == "resume":
            return op.resume()
        if cmd == "abort":
            return op.abort(a.get("reason", f"aborted by {who}"))
        if cmd == "relocalize":
            return await op.relocalize(a.get("apply", True), a.get("region"))
        if cmd == "recover":
            return op.recover(f"{who} asked to relocalize again")
        if cmd == "limits":
            return op.limits(a.get("speed"), a.get("reset", False))
        raise proto.ProtocolError(proto.UNKNOWN_COMMAND, f"unknown command {cmd!r}")  # COMMANDS and here disagree

    async def _watch(self, req: proto.Request, reader: asyncio.StreamReader, writer) -> bool:
        """Stream the state every ``period`` until the client sends a line (not executed) or leaves."""
        period = req.args.get("period", 0.1)
        await self._send(writer, proto.ok_reply(req.id, {"streaming": True, "period": period}))
        ended = asyncio.ensure_future(reader.readline())
        try:
            while not ended.done():
                await self._send(writer, proto.event(req.id, "state", self.operator.status()))
                await asyncio.wait({ended}, timeout=period)
        finally:
            if not ended.done():
                ended.cancel()
        try:
            return bool(ended.result())  # EOF: the client left
        except (asyncio.CancelledError, ValueError, ConnectionError):
            return False

    async def _send(self, writer: asyncio.StreamWriter, message: Dict[str, Any]) -> None:
        writer.write(proto.encode(message))
        # A client that does not read its replies must not hold the handler forever.
        await asyncio.wait_for(writer.drain(), self.config.request_timeout)

    async def _send_quietly(self, writer, message) -> None:
        try:
            await self._send(writer, message)
        except (ConnectionError, asyncio.TimeoutError, OSError):
            pass


class _Connection:
    """Per-connection bookkeeping: the peer, and whether its reads were logged already."""

    def __init__(self, peer: Optional[Peer]):
        self.peer = peer
        self._logged_reads: Set[str] = set()

    def log_accepted(self, req: proto.Request) -> None:
        # Reads (status polls at 10 Hz from a bridge) are logged once per connection, everything
        # else every time: the journal says who did what without drowning in polls.
        if req.cmd in ("status", "watch"):
            level = logging.DEBUG if req.cmd in self._logged_reads else logging.INFO
            self._logged_reads.add(req.cmd)
        else:
            level = logging.INFO
        if log.isEnabledFor(level):
            log.log(level, "control: %s %s from %s", req.cmd, _summary(req.args), _who(self.peer))


def _who(peer: Optional[Peer]) -> str:
    return peer.describe() if peer is not None else "unknown peer"


def _summary(args: Dict[str, Any]) -> str:
    parts = []
    for k, v in args.items():
        if k == "path":
            parts.append(f"path=<{len(v)} chars>")
        else:
            parts.append(f"{k}={v!r}"[:80])
    return "{" + ", ".join(parts) + "}"


__all__ = ["ControlServer", "Peer", "bind_socket", "peer_credentials", "resolve_group"]
