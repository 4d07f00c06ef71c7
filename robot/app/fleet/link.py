"""The fleet link as an app service: paho-mqtt in its own thread, the VDA 5050 logic on the event loop.

- ``MqttTransport``: one paho client (MQTT 3.1.1, clean session) started with ``loop_start``:
  paho's thread connects, reconnects with a doubling delay (``fleet.reconnect_min`` to
  ``reconnect_max``), and hands every event to the asyncio loop with ``call_soon_threadsafe``;
  nothing of the robot runs in paho's thread. A message larger than
  ``fleet.max_message_bytes`` is handed over unread, as a size only.
- connection topic (QoS 1, retained): ONLINE after each (re)connect, OFFLINE before a
  graceful disconnect, and CONNECTIONBROKEN as the last will the broker publishes when the
  controller dies or its network goes.
- ``FleetLink``: polls the AGV logic (progress, actions, state on change or every
  ``fleet.state_period``) and publishes ``visualization`` every ``fleet.visualization_period``.

While the broker is away the robot keeps driving the base it was given and stops at its end
(a guided vehicle's behaviour in the standard); every safety function stays in the core.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import os
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Dict, List, Optional, Tuple

from robot.app.fleet import validation
from robot.app.fleet.agv import SUPPORTED_ACTIONS, VdaAgv, Vehicle
from robot.base.errors import ConfigError
from robot.config.fleet import FleetConfig
from robot.control.path_file import MAX_WAYPOINTS
from robot.control.recovery import AMBIGUOUS

if TYPE_CHECKING:
    from robot.app.controller import RobotApp
    from robot.app.operator import Operator

log = logging.getLogger(__name__)

POLL_PERIOD = 0.05  # s between looks at the order's progress (a node passed, an action finished)


def json_bytes(message: Dict[str, Any]) -> bytes:
    from robot.app.operator import json_safe

    return json.dumps(json_safe(message), allow_nan=False, separators=(",", ":")).encode("utf-8")


class MqttTransport:
    """paho-mqtt in its own thread; callbacks reach the asyncio loop only through call_soon_threadsafe."""

    def __init__(self, cfg: FleetConfig, client_id: str, base_topic: str, will: bytes):
        self.cfg = cfg
        self.client_id = client_id
        self.base = base_topic
        self.will = will
        self.connected = False
        self._client = None
        self._loop: Optional[asyncio.AbstractEventLoop] = None
        self._on_message: Optional[Callable[[str, Optional[bytes], int], None]] = None
        self._on_connection: Optional[Callable[[bool], None]] = None

    def start(self, loop: asyncio.AbstractEventLoop, on_message: Callable[[str, Optional[bytes], int], None],
              on_connection: Callable[[bool], None]) -> None:
        try:
            import paho.mqtt.client as mqtt
        except ImportError:
            raise ConfigError("fleet: paho-mqtt is not installed (install the 'fleet' extra: pip install "
                              "'planeloc-robot[fleet]')") from None
        self._loop, self._on_message, self._on_connection = loop, on_message, on_connection
        c = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=self.client_id, protocol=mqtt.MQTTv311,
                        clean_session=True)
        c.will_set(self.base + "connection", self.will, qos=1, retain=True)
        c.reconnect_delay_set(self.cfg.reconnect_min, self.cfg.reconnect_max)
        c.max_queued_messages_set(256)  # QoS 1 messages held while the broker is away: bounded
        c.on_connect = self._connected
        c.on_disconnect = self._disconnected
        c.on_message = self._message
        self._client = c
        c.connect_async(self.cfg.host, self.cfg.port, keepalive=self.cfg.keepalive)
        c.loop_start()

    def publish(self, subtopic: str, payload: bytes, qos: int = 0, retain: bool = False) -> bool:
        if self._client is None:
            return False
        info = self._client.publish(self.base + subtopic, payload, qos=qos, retain=retain)
        return info.rc == 0

    def stop(self, farewell: Optional[bytes]) -> None:
        """OFFLINE (when connected), disconnect, end paho's thread. Blocks briefly: call off the loop."""
        c, self._client = self._client, None
        if c is None:
            return
        try:
            if farewell is not None and self.connected:
                info = c.publish(self.base + "connection", farewell, qos=1, retain=True)
                info.wait_for_publish(timeout=2.0)
        except (RuntimeError, ValueError, OSError) as e:
            log.warning("fleet: could not say OFFLINE: %s", e)
        finally:
            c.disconnect()
            c.loop_stop()
            self.connected = False

    # -- paho's thread --------------------------------------------------------------------------

    def _post(self, fn, *args) -> None:
        try:
            self._loop.call_soon_threadsafe(fn, *args)
        except RuntimeError:
            pass  # the loop is closed: shutting down

    def _connected(self, client, userdata, flags, reason_code, properties) -> None:
        if getattr(reason_code, "is_failure", False):
            log.warning("fleet: broker %s:%d refused the connection: %s", self.cfg.host, self.cfg.port, reason_code)
            return
        client.subscribe([(self.base + "order", 0), (self.base + "instantActions", 0)])
        self.connected = True
        self._post(self._on_connection, True)

    def _disconnected(self, client, userdata, flags, reason_code, properties) -> None:
        self.connected = False
        self._post(self._on_connection, False)

    def _message(self, client, userdata, msg) -> None:
        if not msg.topic.startswith(self.base):
            return
        size = len(msg.payload)
        payload = None if size > self.cfg.max_message_bytes else bytes(msg.payload)
        self._post(self._on_message, msg.topic[len(self.base):], payload, size)


class FleetLink:
    """The VDA 5050 link of one vehicle: ``await start()``, ``await stop()``."""

    def __init__(self, vehicle: Vehicle, cfg: FleetConfig, map_id: str = "",
                 factsheet: Optional[Callable[[], Dict[str, Any]]] = None):
        self.vehicle = vehicle
        self.cfg = cfg
        self.map_id = map_id or cfg.map_id or "map"
        self.base = f"{cfg.interface_name}/v2/{cfg.manufacturer}/{cfg.serial_number}/"
        self.agv = VdaAgv(vehicle, cfg, self.map_id, self._publish, factsheet or (lambda: make_factsheet(vehicle.robot, cfg)))
        self.transport: Optional[MqttTransport] = None
        self._task: Optional[asyncio.Task] = None
        self._stopping = False
        self.published: Dict[str, int] = {}

    async def start(self) -> None:
        for topic in validation.SCHEMA_FILES:  # jsonschema missing or a broken schema: refused now, not later
            validation.validator(topic)
        loop = asyncio.get_running_loop()
        will = json_bytes(self.agv.connection_message("CONNECTIONBROKEN"))
        self.transport = MqttTransport(self.cfg, f"{self.cfg.manufacturer}-{self.cfg.serial_number}-{os.getpid()}",
                                       self.base, will)
        self.transport.start(loop, self.agv.handle, self._connection_changed)
        self._task = loop.create_task(self._run(), name="fleet")
        log.info("fleet: VDA 5050 as %s on %s:%d (map %s)", self.base, self.cfg.host, self.cfg.port, self.map_id)

    async def stop(self) -> None:
        self._stopping = True
        if self._task is not None:
            self._task.cancel()
            try:
                await self._task
            except asyncio.CancelledError:
                pass
            self._task = None
        if self.transport is not None:
            farewell = json_bytes(self.agv.connection_message("OFFLINE"))
            await asyncio.get_running_loop().run_in_executor(None, self.transport.stop, farewell)
            self.transport = None

    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        next_vis = loop.time()
        while True:
            await asyncio.sleep(POLL_PERIOD)
            self.agv.poll()
            if loop.time() >= next_vis:
                next_vis = loop.time() + self.cfg.visualization_period
                self._publish("visualization", self.agv.visualization_message())

    def _connection_changed(self, up: bool) -> None:
        if up:
            log.info("fleet: connected to %s:%d", self.cfg.host, self.cfg.port)
            self._publish("connection", self.agv.connection_message("ONLINE"))
            self._publish("factsheet", self.agv.factsheet_message())
            self.agv.poll(force=True)
        elif not self._stopping:
            log.warning("fleet: lost the broker %s:%d; reconnecting (the robot finishes its base and waits)",
                        self.cfg.host, self.cfg.port)

    def _publish(self, subtopic: str, message: Dict[str, Any]) -> None:
        if self.transport is None:
            return
        retained = subtopic in ("connection", "factsheet")
        self.transport.publish(subtopic, json_bytes(message), qos=1 if retained else 0, retain=retained)
        self.published[subtopic] = self.published.get(subtopic, 0) + 1


# -- the real-time app as a vehicle -----------------------------------------------------------------


class AppVehicle(Vehicle):
    def __init__(self, app: RobotApp, operator: Operator):
        self.app = app
        self.operator = operator
        self.core = app.core
        self.robot = app.robot
        lo, hi = app.plane_map.bounds()
        self.map_bounds = ((float(lo[0]), float(lo[1])), (float(hi[0]), float(hi[1])))
        self._status: Tuple[float, Dict[str, Any]] = (-math.inf, {})

    def _core_status(self) -> Dict[str, Any]:
        # One state message asks for the quality twice: evaluate it once per poll.
        t = time.monotonic()
        if t - self._status[0] > POLL_PERIOD / 2:
            self._status = (t, self.core.status(t))
        return self._status[1]

    def now(self) -> float:
        return time.monotonic()

    def wall_time(self) -> float:
        return time.time()

    def twist(self) -> Tuple[float, float, float]:
        out = self.app.last_output
        if out is None or out.wheels is None:
            return (0.0, 0.0, 0.0)
        c = out.command
        return (c.vx, c.vy, c.wz)

    def quality(self) -> Tuple[str, float]:
        s = self._core_status()
        return str(s.get("quality")), float(s.get("pos_std", math.inf) or math.inf)

    def battery_voltage(self) -> Optional[float]:
        s = self.app.chassis.status
        return None if s is None else s.battery_v

    def estop(self) -> bool:
        s = self.app.chassis.status
        return bool(s is not None and s.estop)

    def field_violation(self) -> bool:
        decision = getattr(self.core, "last_safety", None)
        return decision is not None and getattr(decision, "zone", "") == "stop"

    def conditions(self) -> List[Tuple[str, str, str]]:
        out: List[Tuple[str, str, str]] = []
        link = self.app.chassis.link_state.value
        if link != "ready":
            out.append(("motorBoardLink", "FATAL", f"motor board link {link}"))
        for name, state in self.app.camera_states.items():
            if state != "streaming":
                out.append(("cameraNotStreaming", "WARNING", f"camera {name}: {state}"))
        rec = self.core.recovery
        if rec.state == AMBIGUOUS:
            # Still, with several places that explain its views: a person must decide (or move it).
            out.append(("localizationAmbiguous", "FATAL", f"{rec.reason}; send initPosition"))
        elif rec.holding:  # relocalizing, turning or moving for a view, confirming
            out.append(("relocalizing", "WARNING", f"{rec.state}: {rec.reason}"))
        if not self.core.initialized:
            out.append(("positionNotInitialized", "WARNING", "no pose: send initPosition"))
        else:
            s = self._core_status()
            if s.get("quality") == "lost":
                out.append(("localizationLost", "FATAL", str(s.get("reason", ""))))
            elif s.get("quality") == "degraded":
                out.append(("localizationDegraded", "WARNING", str(s.get("reason", ""))))
        return out

    def request_pose(self, pose: Tuple[float, float, float], done: Callable[[bool, str], None]) -> None:
        from robot.base.errors import RobotError

        async def check() -> None:
            try:
                await self.operator.set_pose(pose, None, False, source="fleet initPosition")
            except RobotError as e:
                done(False, str(e))
            else:
                done(True, "")

        asyncio.ensure_future(check())


def app_vehicle(app: RobotApp, operator: Operator) -> AppVehicle:
    return AppVehicle(app, operator)


def map_id_for(app: RobotApp, cfg: FleetConfig) -> str:
    return cfg.map_id or Path(str(app.plane_map.source)).stem or "map"


# -- the factsheet ----------------------------------------------------------------------------------


def make_factsheet(robot: Any, cfg: FleetConfig) -> Dict[str, Any]:
    """What a master control needs to plan for this vehicle (VDA 5050 2.0 section 7)."""
    c, ch = robot.control, robot.chassis
    safety = getattr(robot, "safety", None)
    length = float(getattr(safety, "footprint_length", 2.0 * (ch.half_wheelbase + ch.wheel_radius)))
    width = float(getattr(safety, "footprint_width", 2.0 * ch.half_track + 0.04))
    height = max([float(cam.mount_xyz[2]) for cam in robot.cameras] + [0.1]) + 0.05
    wheels = [{"type": "MECANUM", "isActiveDriven": True, "isActiveSteered": False,
               "position": {"x": sx * ch.half_wheelbase, "y": sy * ch.half_track},
               "diameter": 2.0 * ch.wheel_radius, "width": 0.03}
              for sx, sy in ((1, 1), (1, -1), (-1, 1), (-1, -1))]
    init_params = [{"key": k, "valueDataType": "NUMBER", "description": d} for k, d in
                   (("x", "m in the map frame"), ("y", "m in the map frame"), ("theta", "rad in the map frame"))]
    init_params += [{"key": "mapId", "valueDataType": "STRING", "isOptional": True},
                    {"key": "lastNodeId", "valueDataType": "STRING", "isOptional": True}]
    actions = []
    for name in SUPPORTED_ACTIONS:
        a: Dict[str, Any] = {"actionType": name, "actionScopes": ["INSTANT"]}
        if name == "initPosition":
            a["actionParameters"] = init_params
            a["actionDescription"] = "checked against the depth cameras and the map before it is taken"
        actions.append(a)
    optional = [{"parameter": p, "support": "SUPPORTED"} for p in (
        "order.nodes.nodePosition.theta", "order.nodes.nodePosition.allowedDeviationXy",
        "order.nodes.nodePosition.allowedDeviationTheta", "order.edges.maxSpeed")]
    return {
        "typeSpecification": {"seriesName": "planeloc-mecanum", "seriesDescription": "Mecanum robot localizing on a "
                              "plane map with depth cameras", "agvKinematic": "OMNI", "agvClass": "CARRIER",
                              "maxLoadMass": 0.0, "localizationTypes": ["NATURAL"],
                              "navigationTypes": ["VIRTUAL_LINE_GUIDED"]},
        "physicalParameters": {"speedMin": 0.0, "speedMax": float(c.max_speed), "accelerationMax": float(c.max_accel),
                               "decelerationMax": float(c.max_accel), "heightMin": 0.0, "heightMax": height,
                               "width": width, "length": length},
        "protocolLimits": {"maxStringLens": {"msgLen": int(cfg.max_message_bytes), "topicSerialLen": 64,
                                             "topicElemLen": 64},
                           "maxArrayLens": {"order.nodes": MAX_WAYPOINTS + 1, "order.edges": MAX_WAYPOINTS,
                                            "node.actions": 0, "edge.actions": 0},
                           "timing": {"minOrderInterval": POLL_PERIOD, "minStateInterval": POLL_PERIOD,
                                      "defaultStateInterval": float(cfg.state_period),
                                      "visualizationInterval": float(cfg.visualization_period)}},
        "protocolFeatures": {"optionalParameters": optional, "agvActions": actions},
        "agvGeometry": {"wheelDefinitions": wheels},
        "loadSpecification": {"loadPositions": [], "loadSets": []},
    }


__all__ = ["AppVehicle", "FleetLink", "MqttTransport", "app_vehicle", "make_factsheet", "map_id_for"]
