"""The ``control_api:`` section of the robot config: the controller's local control socket.

The running controller listens on a Unix socket (never on the network) for JSON-line requests
(``docs/control-api.md``). Who may connect is decided by the socket file's ``mode`` and ``group``;
the commands that move the robot (or change where it believes it is) are further limited to
root, the controller's own user and the members of ``motion_groups``, checked on the peer's
kernel credentials (SO_PEERCRED) for every request.

YAML::

    control_api:
      socket: /run/robot-controller/control.sock
      mode: 0660                  # octal, as chmod takes it
      group: robot                # the socket file's group; absent: the controller's own group
      motion_groups: [robot-operators]
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Tuple

from robot.base.errors import ConfigError
from robot.config.ranges import check_fields, excerpt, field_range, flag, integer, number, text
from robot.config.schema import Section

DEFAULT_SOCKET = "/run/robot-controller/control.sock"
MAX_SOCKET_PATH = 107  # bytes: sun_path holds 108 including the terminating NUL on Linux
MAX_GROUP_CHARS = 64


@dataclass(frozen=True)
class ControlApiConfig:
    enabled: bool = flag(True, "listen on the control socket while the controller runs (robotctl run)")
    socket: str = text(DEFAULT_SOCKET, "path of the Unix socket; its directory must exist or be creatable")
    # 0660: owner and group may connect, nobody else; connecting needs write permission on the file.
    mode: int = integer(0o660, 0, 0o777, "", "file mode of the socket (octal in YAML: 0660)")
    group: str = text("", "group of the socket file, name or number; empty: the controller's own group")
    motion_groups: Tuple[str, ...] = text((), "groups (names or numbers) whose members may send commands that "
                                          "move the robot; root and the controller's own user always may")
    max_clients: int = integer(8, 1, 64, "", "connections served at once; one more is refused as busy")
    max_request_bytes: int = integer(65536, 1024, 2 * 1024 * 1024, "bytes", "longest request line; a path "
                                     "file travels inside one request")
    request_timeout: float = number(5.0, 0.1, 60.0, "s", "a request not answered within this gets a timeout "
                                    "error")
    relocalize_timeout: float = number(60.0, 1.0, 600.0, "s", "the same for relocalize (a global search on the "
                                       "robot's CPU)")
    idle_timeout: float = number(600.0, 1.0, 86400.0, "s", "a connection that sends nothing for this long is "
                                 "closed (frees its slot)")
    pose_check_xy: float = number(0.01, 0.0, 1.0, "m", "set-pose: the cameras may put the robot this far plus "
                                  "3 std from the given pose")
    pose_check_phi_deg: float = number(0.5, 0.0, 45.0, "deg", "set-pose: the same for the heading")
    frame_max_age: float = number(2.0, 0.1, 30.0, "s", "set-pose and relocalize use depth frames at most this "
                                  "old")

    def __post_init__(self):
        check_fields(self, "control_api")
        where = "control_api"
        if not self.socket or len(self.socket.encode("utf-8", "surrogateescape")) > MAX_SOCKET_PATH:
            raise ConfigError(f"{where}: 'socket' must be a path of 1 to {MAX_SOCKET_PATH} bytes, got "
                         f"{excerpt(self.socket)}")
        for key, g in [("group", self.group)] + [(f"motion_groups[{i}]", g) for i, g in enumerate(self.motion_groups)]:
            bad = not isinstance(g, str) or len(g) > MAX_GROUP_CHARS or any(c.isspace() or c == ":" for c in g)
            if bad or (key != "group" and not g):  # only the socket's group may be left empty
                raise ConfigError(f"{where}: '{key}' must be a group name or number, got {excerpt(g)}")


def _group(sec: Section, value, key: str) -> str:
    # A numeric gid reads as a YAML int; keep it as its decimal text.
    if isinstance(value, bool) or not isinstance(value, (str, int)):
        sec.fail(f"'{key}' must be a group name or number, got {excerpt(value)}")
    if isinstance(value, int) and not 0 <= value < 2 ** 32:
        sec.fail(f"'{key}' must be a group number from 0 to 4294967295, got {value}")
    return str(value)


def parse_control_api(sec: Section) -> ControlApiConfig:
    """The ``control_api:`` section (absent: the defaults); ConfigError naming the key."""
    ranges = {f.name: field_range(f) for f in dataclasses.fields(ControlApiConfig)}
    d = ControlApiConfig()
    values = {"enabled": sec.boolean("enabled", d.enabled), "socket": sec.string("socket", d.socket)}
    for key in ("mode", "max_clients", "max_request_bytes", "request_timeout", "relocalize_timeout", "idle_timeout",
                "pose_check_xy", "pose_check_phi_deg", "frame_max_age"):
        values[key] = sec.ranged(key, ranges[key], getattr(d, key))
    values["group"] = _group(sec, sec.raw("group"), "group") if sec.has("group") else d.group
    raw = sec.raw("motion_groups", [])
    if not isinstance(raw, (list, tuple)) or len(raw) > 32:
        sec.fail(f"'motion_groups' must be a list of at most 32 group names or numbers, got {excerpt(raw)}")
    values["motion_groups"] = tuple(_group(sec, g, f"motion_groups[{i}]") for i, g in enumerate(raw))
    sec.done()
    try:
        return ControlApiConfig(**values)
    except ValueError as e:
        msg, prefix = str(e), "control_api: "
        sec.fail(msg[len(prefix):] if msg.startswith(prefix) else msg)


__all__ = ["ControlApiConfig", "DEFAULT_SOCKET", "parse_control_api"]
