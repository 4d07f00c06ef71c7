"""The control socket's wire format, version 1: one JSON object per line each way (docs/control-api.md).

Request::

    {"v": 1, "id": 7, "cmd": "goto", "args": {"x": 0.8, "y": 0.6, "phi": 0.0}}

Reply (same ``id``; ``id`` may be a string of up to 64 characters, an integer or absent)::

    {"v": 1, "id": 7, "ok": true, "result": {...}}
    {"v": 1, "id": 7, "ok": false, "error": {"code": "refused", "message": "a mission is running ..."}}

A ``watch`` request is answered once, then followed by event lines
``{"v": 1, "id": 7, "event": "state", "data": {...}}`` until the client sends a line or leaves.

Parsing is strict, so that nothing malformed reaches the robot: unknown keys, wrong types,
booleans for numbers, NaN or Infinity, numbers beyond the site and missing arguments are each
one ``bad_request``/``bad_args`` error naming the key. The server only calls the operator
once a request has passed here.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any, Callable, Dict, Mapping, Optional, Tuple

from robot.base.errors import RobotError
from robot.config.ranges import excerpt

VERSION = 1
MAX_ID_CHARS = 64
MAX_COORDINATE = 1000.0  # m: as in path files
MAX_NAME_CHARS = 256
MAX_REASON_CHARS = 200

# Error codes, the whole list (docs/control-api.md explains each).
BAD_JSON = "bad_json"
BAD_REQUEST = "bad_request"
UNSUPPORTED_VERSION = "unsupported_version"
UNKNOWN_COMMAND = "unknown_command"
BAD_ARGS = "bad_args"
FORBIDDEN = "forbidden"
REFUSED = "refused"
BUSY = "busy"
TOO_LONG = "too_long"
TIMEOUT = "timeout"
INTERNAL = "internal"
ERROR_CODES = (BAD_JSON, BAD_REQUEST, UNSUPPORTED_VERSION, UNKNOWN_COMMAND, BAD_ARGS, FORBIDDEN, REFUSED, BUSY,
               TOO_LONG, TIMEOUT, INTERNAL)


class ProtocolError(RobotError):
    """A request that cannot be served, with its error code."""

    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code
        self.message = message


# -- argument types ---------------------------------------------------------------------------------

def _number(lo: float, hi: float, lo_open: bool = False) -> Callable[[str, Any], float]:
    def check(key: str, v: Any) -> float:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise ProtocolError(BAD_ARGS, f"'{key}' must be a number, got {excerpt(v)}")
        f = float(v)  # a JSON integer beyond the float range: OverflowError below
        if not math.isfinite(f) or (f <= lo if lo_open else f < lo) or f > hi:
            raise ProtocolError(BAD_ARGS, f"'{key}' must be a number {'above' if lo_open else 'from'} {lo:g} to "
                                          f"{hi:g}, got {excerpt(v)}")
        return f
    return _overflow_safe(check)


def _overflow_safe(check):
    def wrapped(key: str, v: Any):
        try:
            return check(key, v)
        except OverflowError:
            raise ProtocolError(BAD_ARGS, f"'{key}' is too large a number") from None
    return wrapped


def _boolean(key: str, v: Any) -> bool:
    if not isinstance(v, bool):
        raise ProtocolError(BAD_ARGS, f"'{key}' must be true or false, got {excerpt(v)}")
    return v


def _string(max_chars: int) -> Callable[[str, Any], str]:
    def check(key: str, v: Any) -> str:
        if not isinstance(v, str) or not v or len(v) > max_chars:
            raise ProtocolError(BAD_ARGS, f"'{key}' must be a non-empty string of at most {max_chars} characters, "
                                          f"got {excerpt(v)}")
        return v
    return check


def _nullable(check):
    return lambda key, v: None if v is None else check(key, v)


def _region(key: str, v: Any) -> Tuple[float, ...]:
    if not isinstance(v, list) or len(v) != 4:
        raise ProtocolError(BAD_ARGS, f"'{key}' must be [x0, y0, x1, y1], got {excerpt(v)}")
    return tuple(_coordinate(f"{key}[{i}]", c) for i, c in enumerate(v))


_coordinate = _number(-MAX_COORDINATE, MAX_COORDINATE)
_angle = _number(-2.0 * math.pi, 2.0 * math.pi)


@dataclass(frozen=True)
class CommandSpec:
    args: Mapping[str, Tuple[Callable[[str, Any], Any], bool]]  # key -> (check, required)
    motion: Callable[[Dict[str, Any]], bool]  # whether these args need the right to move the robot
    summary: str


def _always(_args) -> bool:
    return True


def _never(_args) -> bool:
    return False


# Stopping (pause, abort) is allowed to every client that may connect: like a stop button, it
# can only make the robot safer. Everything that makes it move, or changes where it believes it
# is or how fast it may go, needs the right to move it.
COMMANDS: Dict[str, CommandSpec] = {
    "status": CommandSpec({}, _never, "pose, quality, mission, chassis, battery, cameras"),
    "set-pose": CommandSpec({"x": (_coordinate, True), "y": (_coordinate, True), "phi": (_angle, True),
                             "std_xy": (_number(0.0, 10.0, lo_open=True), False),
                             "std_phi": (_number(0.0, math.pi, lo_open=True), False),
                             "force": (_boolean, False)}, _always, "set the pose (checked against the cameras)"),
    "go": CommandSpec({"path": (_string(16 * 1024 * 1024), True), "name": (_string(MAX_NAME_CHARS), False),
                       "replace": (_boolean, False)}, _always, "follow a path file (its YAML text)"),
    "goto": CommandSpec({"x": (_coordinate, True), "y": (_coordinate, True), "phi": (_nullable(_angle), False),
                         "speed": (_number(0.0, 2.0, lo_open=True), False),
                         "tolerance": (_number(0.0, 1.0, lo_open=True), False),
                         "replace": (_boolean, False)}, _always, "drive to one target"),
    "pause": CommandSpec({}, _never, "brake within the limits and hold"),
    "resume": CommandSpec({}, _always, "continue after pause"),
    "abort": CommandSpec({"reason": (_string(MAX_REASON_CHARS), False)}, _never, "brake and end the mission"),
    "relocalize": CommandSpec({"apply": (_boolean, False), "region": (_region, False)},
                              lambda a: a.get("apply", True), "global relocalization from the newest frames"),
    "recover": CommandSpec({}, _always, "restart recovery: relocalize, then turn and move as the config allows"),
    "limits": CommandSpec({"speed": (_number(0.0, 2.0, lo_open=True), False), "reset": (_boolean, False)},
                          lambda a: "speed" in a or bool(a.get("reset")), "show or lower the speed limit"),
    "watch": CommandSpec({"period": (_number(0.02, 10.0), False)}, _never, "stream the state"),
}


@dataclass(frozen=True)
class Request:
    id: Any
    cmd: str
    args: Dict[str, Any]
    motion: bool


def _reject_constant(name: str):
    raise ValueError(f"{name} is not a number JSON allows")


def decode_json(line: bytes) -> Any:
    """The JSON value of one line; ProtocolError(bad_json) for anything else."""
    try:
        text = line.decode("utf-8")
    except UnicodeDecodeError as e:
        raise ProtocolError(BAD_JSON, f"the request is not UTF-8 (byte {e.start})") from None
    try:
        return json.loads(text, parse_constant=_reject_constant)
    except RecursionError:
        raise ProtocolError(BAD_JSON, "the request is nested too deeply") from None
    except ValueError as e:  # JSONDecodeError, NaN/Infinity, an integer of too many digits
        raise ProtocolError(BAD_JSON, f"malformed JSON: {str(e)[:120]}") from None


def request_id(obj: Any) -> Any:
    """The id to echo: only an id that is itself well formed (never a megabyte of junk)."""
    if isinstance(obj, dict):
        rid = obj.get("id")
        if rid is None or (isinstance(rid, str) and len(rid) <= MAX_ID_CHARS) or \
                (isinstance(rid, int) and not isinstance(rid, bool) and abs(rid) < 2 ** 53):
            return rid
    return None


def parse_request(obj: Any) -> Request:
    """A checked request from a decoded JSON value; ProtocolError naming the problem."""
    if not isinstance(obj, dict):
        raise ProtocolError(BAD_REQUEST, f"a request is a JSON object, got {type(obj).__name__}")
    unknown = sorted(str(k) for k in obj if k not in ("v", "id", "cmd", "args"))
    if unknown:
        raise ProtocolError(BAD_REQUEST, f"unknown key(s) in the request: {excerpt(', '.join(unknown))}")
    if "v" not in obj:
        raise ProtocolError(BAD_REQUEST, f"missing 'v' (the protocol version, {VERSION})")
    if obj["v"] != VERSION or isinstance(obj["v"], bool):
        raise ProtocolError(UNSUPPORTED_VERSION, f"protocol version {excerpt(obj['v'])} is not supported "
                                                 f"(this controller speaks {VERSION})")
    if "id" in obj and obj["id"] is not None and request_id(obj) is None:
        raise ProtocolError(BAD_REQUEST, f"'id' must be a string of at most {MAX_ID_CHARS} characters or an integer")
    cmd = obj.get("cmd")
    if not isinstance(cmd, str):
        raise ProtocolError(BAD_REQUEST, f"'cmd' must be a command name, got {excerpt(cmd)}")
    spec = COMMANDS.get(cmd)
    if spec is None:
        raise ProtocolError(UNKNOWN_COMMAND, f"unknown command {excerpt(cmd)} (commands: {', '.join(COMMANDS)})")
    raw = obj.get("args", {})
    if raw is None:
        raw = {}
    if not isinstance(raw, dict):
        raise ProtocolError(BAD_REQUEST, f"'args' must be an object, got {type(raw).__name__}")
    unknown = sorted(str(k) for k in raw if k not in spec.args)
    if unknown:
        allowed = ", ".join(spec.args) or "none"
        raise ProtocolError(BAD_ARGS, f"{cmd}: unknown argument(s) {excerpt(', '.join(unknown))} (allowed: {allowed})")
    args: Dict[str, Any] = {}
    for key, (check, required) in spec.args.items():
        if key not in raw:
            if required:
                raise ProtocolError(BAD_ARGS, f"{cmd}: missing argument '{key}'")
            continue
        try:
            args[key] = check(key, raw[key])
        except ProtocolError as e:
            raise ProtocolError(e.code, f"{cmd}: {e.message}") from None
    return Request(request_id(obj), cmd, args, bool(spec.motion(args)))


def encode(message: Mapping[str, Any]) -> bytes:
    return (json.dumps(message, allow_nan=False, separators=(",", ":")) + "\n").encode("utf-8")


def ok_reply(rid: Any, result: Any) -> Dict[str, Any]:
    return {"v": VERSION, "id": rid, "ok": True, "result": result}


def error_reply(rid: Any, code: str, message: str) -> Dict[str, Any]:
    return {"v": VERSION, "id": rid, "ok": False, "error": {"code": code, "message": message}}


def event(rid: Any, name: str, data: Any) -> Dict[str, Any]:
    return {"v": VERSION, "id": rid, "event": name, "data": data}


def make_request(cmd: str, args: Optional[Mapping[str, Any]] = None, rid: Any = None) -> Dict[str, Any]:
    out: Dict[str, Any] = {"v": VERSION, "cmd": cmd, "args": dict(args or {})}
    if rid is not None:
        out["id"] = rid
    return out


__all__ = ["VERSION", "COMMANDS", "ERROR_CODES", "ProtocolError", "Request", "decode_json", "parse_request", "encode",
           "ok_reply", "error_reply", "event", "make_request", "request_id"]
