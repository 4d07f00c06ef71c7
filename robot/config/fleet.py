"""The ``fleet:`` section of the robot config: VDA 5050 (2.0) over MQTT to a master control.

Off unless ``enabled: true`` (and the ``fleet`` extra, paho-mqtt and jsonschema, installed).
Topics are ``{interface_name}/v2/{manufacturer}/{serial_number}/{order|instantActions|state|
visualization|connection|factsheet}`` (``docs/fleet.md``). Plain MQTT 3.1.1 without TLS or a
password: the broker belongs on the robots' own network segment.

YAML::

    fleet:
      enabled: true
      host: 192.168.10.2
      manufacturer: planeloc
      serial_number: robot-07
      map_id: hall-3              # absent: the map file's name without .yaml
"""

from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass

from robot.base.errors import ConfigError
from robot.config.ranges import check_fields, excerpt, field_range, flag, integer, number, text
from robot.config.schema import Section

# MQTT topic levels must not contain the wildcards '+' and '#' or '/', and VDA 5050 asks for
# ids a master control can print: letters, digits and a few separators.
_TOPIC_LEVEL = re.compile(r"^[A-Za-z0-9_.\-]{1,64}$")


@dataclass(frozen=True)
class FleetConfig:
    enabled: bool = flag(False, "connect to the fleet's MQTT broker and speak VDA 5050")
    host: str = text("127.0.0.1", "MQTT broker host name or address")
    port: int = integer(1883, 1, 65535, "", "MQTT broker port")
    interface_name: str = text("uagv", "first topic level (VDA 5050 interfaceName)")
    manufacturer: str = text("planeloc", "VDA 5050 manufacturer (topic level and message field)")
    serial_number: str = text("robot-1", "VDA 5050 serialNumber, unique in the fleet (topic level)")
    map_id: str = text("", "mapId of the plane map in the fleet's maps; empty: the map file's name")
    keepalive: int = integer(15, 5, 300, "s", "MQTT keep-alive: the broker announces a dead robot after 1.5 x this")
    reconnect_min: int = integer(1, 1, 60, "s", "first delay before reconnecting to a lost broker (doubles)")
    reconnect_max: int = integer(10, 1, 600, "s", "longest delay between reconnect attempts")
    state_period: float = number(10.0, 0.5, 30.0, "s", "a state message at least this often (VDA 5050: 30 s at "
                                 "most), and on every change")
    visualization_period: float = number(0.2, 0.02, 10.0, "s", "between visualization (pose) messages")
    max_message_bytes: int = integer(262144, 1024, 16 * 1024 * 1024, "bytes", "a larger order or "
                                     "instantActions message is refused unread")
    default_speed: float = number(0.15, 0.0, 2.0, "m/s", "cruise speed on an edge without maxSpeed", lo_open=True)
    node_tolerance: float = number(0.01, 0.001, 1.0, "m", "arrival radius at a node without allowedDeviationXy")
    first_node_tolerance: float = number(0.25, 0.001, 5.0, "m", "a new order's first node counts as reached "
                                         "within this, when it has no allowedDeviationXy")
    battery_empty_v: float = number(10.5, 0.0, 100.0, "V", "board voltage reported as 0 % charge")
    battery_full_v: float = number(12.6, 0.1, 100.0, "V", "board voltage reported as 100 % charge")

    def __post_init__(self):
        check_fields(self, "fleet")
        for key in ("interface_name", "manufacturer", "serial_number"):
            if not _TOPIC_LEVEL.match(getattr(self, key)):
                raise ConfigError(f"fleet: '{key}' must be 1 to 64 letters, digits or '_', '.', '-' (an MQTT topic "
                                  f"level), got {excerpt(getattr(self, key))}")
        if self.map_id and len(self.map_id) > 128:
            raise ConfigError("fleet: 'map_id' must be at most 128 characters")
        if not self.host or len(self.host) > 253:
            raise ConfigError(f"fleet: 'host' must be a host name or address, got {excerpt(self.host)}")
        if self.reconnect_min > self.reconnect_max:
            raise ConfigError(f"fleet: 'reconnect_min' ({self.reconnect_min} s) must not exceed 'reconnect_max' "
                              f"({self.reconnect_max} s)")
        if self.battery_empty_v >= self.battery_full_v:
            raise ConfigError(f"fleet: 'battery_empty_v' ({self.battery_empty_v} V) must be below 'battery_full_v' "
                              f"({self.battery_full_v} V)")


def parse_fleet(sec: Section) -> FleetConfig:
    """The ``fleet:`` section (absent: the defaults, off); ConfigError naming the key."""
    d = FleetConfig()
    values = {}
    for f in dataclasses.fields(FleetConfig):
        rng, default = field_range(f), getattr(d, f.name)
        if rng is not None:
            values[f.name] = sec.ranged(f.name, rng, default)
        elif isinstance(default, bool):
            values[f.name] = sec.boolean(f.name, default)
        elif f.name == "map_id" and sec.has("map_id") and sec.raw("map_id") == "":
            values[f.name] = ""  # what the effective-config dump writes for "the map file's name"
        else:
            values[f.name] = sec.string(f.name, default) if sec.has(f.name) else default
    sec.done()
    try:
        return FleetConfig(**values)
    except ValueError as e:
        msg, prefix = str(e), "fleet: "
        sec.fail(msg[len(prefix):] if msg.startswith(prefix) else msg)


__all__ = ["FleetConfig", "parse_fleet"]
