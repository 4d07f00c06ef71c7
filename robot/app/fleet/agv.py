"""The AGV's side of VDA 5050 2.0: orders and order updates, instant actions, and the state it reports.

Transport-free and single-threaded: the link calls ``handle(subtopic, payload)`` for each
message and ``poll()`` periodically, on the event loop that also runs the core; ``publish`` is
called with (subtopic, message). The vehicle is reached through a small interface
(``Vehicle``) so that the same logic runs on the real-time app and on a simulated clock.

Orders (section 6.6 of the standard):

- a new orderId is taken only when no released node is left to drive, the position is
  initialized and the first node is "trivially reachable" (within its allowedDeviationXy, or
  ``fleet.first_node_tolerance`` without one); the first node then counts as traversed and
  the robot drives the rest of the base, never the horizon;
- an update (same orderId, higher orderUpdateId) must start at the last base node (nodeId and
  sequenceId, "stitching"); its newly released nodes are driven after the current base, its
  horizon replaces the old one; a lower orderUpdateId is an ``orderUpdateError``, the same one
  is ignored (a resend);
- every rejected message (not JSON, too large, against the schema, for another vehicle,
  another protocol version, or an order the vehicle cannot drive) becomes a WARNING in
  ``state.errors`` with references, kept until the next accepted order; nothing is driven.

Instant actions: cancelOrder (brake within the limits, clear the order; FINISHED once standing
still; FAILED with ``noOrderToCancel`` when there is none), startPause / stopPause, initPosition
(the same checked set-pose as the control socket), stateRequest, factsheetRequest. Others
fail with ``actionNotSupported``.
"""

from __future__ import annotations

import json
import logging
import math
from collections import OrderedDict
from dataclasses import dataclass
from datetime import datetime, timezone
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

from robot.app.fleet import validation
from robot.app.fleet.orders import (
    ORDER_ERROR,
    ORDER_UPDATE_ERROR,
    VALIDATION_ERROR,
    Node,
    Order,
    OrderRejected,
    plan_for,
    read_order,
)
from robot.base.geometry import wrap_angle
from robot.config.fleet import FleetConfig
from robot.control.core import CommandRefused

log = logging.getLogger(__name__)

VERSION = "2.0.0"
MAJOR = "2"
MAX_MESSAGE_ERRORS = 10  # newest rejections kept in state.errors
MAX_ACTION_STATES = 32  # newest instant actions kept in state.actionStates
STILL = 1e-3  # m/s, rad/s
SUPPORTED_ACTIONS = ("cancelOrder", "startPause", "stopPause", "initPosition", "stateRequest", "factsheetRequest")

WAITING, RUNNING, FINISHED, FAILED = "WAITING", "RUNNING", "FINISHED", "FAILED"
WARNING, FATAL = "WARNING", "FATAL"


def iso_timestamp(t_wall: float) -> str:
    """ISO 8601 UTC with milliseconds, as the standard writes it (2017-04-15T11:40:03.123Z)."""
    d = datetime.fromtimestamp(t_wall, timezone.utc)
    return d.strftime("%Y-%m-%dT%H:%M:%S.") + f"{d.microsecond // 1000:03d}Z"


def _finite_float(text: str) -> float:
    v = float(text)
    if not math.isfinite(v):
        raise ValueError(f"number {text[:20]} is out of range")
    return v


def _bounded_int(text: str) -> int:
    # VDA 5050's integers are uint32 (ids, sequence ids); a coordinate given as an integer must
    # still convert to a float: anything beyond 2^53 is refused here, not deep inside.
    v = int(text)
    if abs(v) > 2 ** 53:
        raise ValueError(f"integer {text[:20]}... is out of range")
    return v


def _no_constant(name: str):
    raise ValueError(f"{name} is not a JSON number")


def decode(payload: bytes) -> Any:
    """Strict JSON: no NaN/Infinity, no number beyond the float range; ValueError otherwise."""
    try:
        return json.loads(payload.decode("utf-8"), parse_constant=_no_constant, parse_float=_finite_float,
                          parse_int=_bounded_int)
    except RecursionError:
        raise ValueError("nested too deeply") from None


class Vehicle:
    """What the protocol needs of a robot. ``core`` is its ``ControllerCore``."""

    core: Any
    robot: Any
    map_bounds: Tuple[Sequence[float], Sequence[float]]

    def now(self) -> float:
        raise NotImplementedError

    def wall_time(self) -> float:
        raise NotImplementedError

    def twist(self) -> Tuple[float, float, float]:
        raise NotImplementedError

    def quality(self) -> Tuple[str, float]:
        """(localized | degraded | lost, position std in m)."""
        raise NotImplementedError

    def battery_voltage(self) -> Optional[float]:
        raise NotImplementedError

    def estop(self) -> bool:
        return False

    def field_violation(self) -> bool:
        return False

    def conditions(self) -> List[Tuple[str, str, str]]:
        """Present faults as (errorType, WARNING | FATAL, description)."""
        return []

    def request_pose(self, pose: Tuple[float, float, float], done: Callable[[bool, str], None]) -> None:
        """Set the pose after the vehicle's own checks; ``done(ok, why)`` when decided."""
        raise NotImplementedError


@dataclass
class _Action:
    action_id: str
    action_type: str
    status: str
    result: str = ""

    def state(self) -> Dict[str, Any]:
        out = {"actionId": self.action_id, "actionType": self.action_type, "actionStatus": self.status}
        if self.result:
            out["resultDescription"] = self.result
        return out


class VdaAgv:
    def __init__(self, vehicle: Vehicle, cfg: FleetConfig, map_id: str, publish: Callable[[str, Dict[str, Any]], None],
                 factsheet: Callable[[], Dict[str, Any]]):
        self.vehicle = vehicle
        self.cfg = cfg
        self.map_id = map_id
        self._publish = publish
        self._factsheet = factsheet
        self._header_ids: Dict[str, int] = {}
        self.order: Optional[Order] = None
        self.order_id = ""
        self.order_update_id = 0
        self.last_node_id = ""
        self.last_node_seq = 0
        self._node_states: List[Node] = []  # still to traverse (base and horizon)
        self._edge_states: List[Any] = []
        self._driving: List[Node] = []  # released nodes handed to the core, in order
        self._plans: List[Any] = []  # the PathPlans of this order, in order, and how many nodes each covers
        self._passed = 0  # of _driving
        self._cancelled = False
        self._cancel_action: Optional[_Action] = None
        self._pause_action: Optional[_Action] = None
        self._actions: Dict[str, _Action] = OrderedDict()
        self._message_errors: List[Dict[str, Any]] = []
        self._digest: Any = None
        self._t_state = -math.inf
        self.stats = {"orders": 0, "updates": 0, "rejected": 0, "instant_actions": 0}

    # -- messages in ------------------------------------------------------------------------

    def handle(self, subtopic: str, payload: Optional[bytes], size: int = 0) -> None:
        """One incoming message; never raises (a defect becomes an error in the state)."""
        try:
            if payload is None:
                self._reject(VALIDATION_ERROR, f"{subtopic} message of {size} bytes is larger than "
                                               f"{self.cfg.max_message_bytes} bytes: not read", subtopic)
            elif subtopic == "order":
                self._on_order(payload)
            elif subtopic == "instantActions":
                self._on_instant_actions(payload)
        except Exception as e:  # a defect must never take the controller down: report it
            log.exception("fleet: handling a %s message failed", subtopic)
            self._reject("internalError", f"the vehicle failed to handle the message: {type(e).__name__}: {e}"[:300],
                         subtopic)
        self.poll(force=True)

    def _checked(self, subtopic: str, payload: bytes) -> Dict[str, Any]:
        try:
            msg = decode(payload)
        except (ValueError, UnicodeDecodeError) as e:
            raise OrderRejected(VALIDATION_ERROR, f"{subtopic}: not JSON ({str(e)[:120]})") from None
        header = [("headerId", msg.get("headerId"))] if isinstance(msg, dict) and isinstance(msg.get("headerId"), int) \
            else []
        found = validation.problems(subtopic, msg)
        if found:
            raise OrderRejected(VALIDATION_ERROR, f"{subtopic} does not match the VDA 5050 {VERSION} schema: "
                                + "; ".join(found), header)
        if msg.get("manufacturer") != self.cfg.manufacturer or msg.get("serialNumber") != self.cfg.serial_number:
            raise OrderRejected(VALIDATION_ERROR, f"{subtopic} is addressed to {msg.get('manufacturer')!r}/"
                                                  f"{msg.get('serialNumber')!r}, not this vehicle", header)
        version = msg.get("version", "")
        if not isinstance(version, str) or version.split(".")[0] != MAJOR:
            raise OrderRejected(VALIDATION_ERROR, f"{subtopic} is protocol version {version!r}; this vehicle speaks "
                                                  f"{VERSION}", header)
        return msg

    def _on_order(self, payload: bytes) -> None:
        try:
            msg = self._checked("order", payload)
            order = read_order(msg, self.map_id, self.vehicle.map_bounds)
            if self.order is not None and order.order_id == self.order_id:
                self._update(order)
            else:
                self._new_order(order)
        except OrderRejected as e:
            self._reject(e.error_type, e.description, "order", e.references)

    def _new_order(self, order: Order) -> None:
        core = self.vehicle.core
        refs = [("orderId", order.order_id), ("orderUpdateId", order.update_id)]
        if any(n.released for n in self._node_states) or (core.mission_active and not self._cancelled):
            raise OrderRejected(ORDER_ERROR, f"still driving order {self.order_id!r}: cancel it first", refs)
        if not core.initialized:
            raise OrderRejected(ORDER_ERROR, "the position is not initialized (initPosition)", refs)
        first = order.nodes[0]
        (x, y, _), _ = core.pose(self.vehicle.now())
        reach = first.deviation_xy if first.deviation_xy else self.cfg.first_node_tolerance
        gap = math.hypot(first.x - x, first.y - y)
        if gap > reach:
            raise OrderRejected(ORDER_ERROR, f"the first node {first.node_id!r} is {gap:.3f} m from the vehicle, more "
                                             f"than its deviation range {reach:.3f} m", refs + [("nodeId", first.node_id)])
        to_drive = list(order.base_nodes[1:])
        plan = plan_for(to_drive, order, self.cfg) if to_drive else None
        if plan is not None:
            try:
                core.go(plan, replace=self._cancelled)  # after a cancel: start once the vehicle has stopped
            except CommandRefused as e:
                raise OrderRejected(ORDER_ERROR, str(e), refs) from None
        self.order, self.order_id, self.order_update_id = order, order.order_id, order.update_id
        self._cancelled = False
        self._message_errors.clear()  # the standard: warnings of rejected orders last until one is accepted
        self.last_node_id, self.last_node_seq = first.node_id, first.sequence_id
        self._node_states = list(order.nodes[1:])
        self._edge_states = list(order.edges)
        self._traverse_edges_up_to(first.sequence_id)
        self._driving, self._plans, self._passed = to_drive, ([(plan, len(to_drive))] if plan else []), 0
        self.stats["orders"] += 1
        log.info("fleet: order %r accepted: %d base nodes, %d horizon nodes", order.order_id, len(order.base_nodes),
                 len(order.nodes) - len(order.base_nodes))

    def _update(self, order: Order) -> None:
        refs = [("orderId", order.order_id), ("orderUpdateId", order.update_id)]
        if order.update_id < self.order_update_id:
            raise OrderRejected(ORDER_UPDATE_ERROR, f"orderUpdateId {order.update_id} is older than the current "
                                                    f"{self.order_update_id}", refs)
        if order.update_id == self.order_update_id:
            return  # a resend: the standard says to ignore it
        if self._cancelled:
            raise OrderRejected(ORDER_UPDATE_ERROR, f"order {order.order_id!r} was cancelled: send a new order", refs)
        base_end = self._base_end()
        first = order.nodes[0]
        if base_end is None or (first.node_id, first.sequence_id) != (base_end.node_id, base_end.sequence_id):
            want = f"{base_end.node_id!r} (sequenceId {base_end.sequence_id})" if base_end else "none"
            raise OrderRejected(ORDER_UPDATE_ERROR, f"the update starts at {first.node_id!r} (sequenceId "
                                                    f"{first.sequence_id}), not at the last base node {want}", refs)
        new = list(order.base_nodes[1:])
        plan = plan_for(new, order, self.cfg) if new else None
        if plan is not None:
            try:
                self.vehicle.core.extend(plan)
            except CommandRefused as e:
                raise OrderRejected(ORDER_UPDATE_ERROR, str(e), refs) from None
            self._driving += new
            self._plans.append((plan, len(new)))
        # Keep what is left of the old base; the update's nodes after the stitching node follow it.
        self._node_states = [n for n in self._node_states if n.released and n.sequence_id <= first.sequence_id]
        self._node_states += list(order.nodes[1:])
        self._edge_states = [e for e in self._edge_states if e.released and e.sequence_id < first.sequence_id]
        self._edge_states += list(order.edges)
        self.order, self.order_update_id = order, order.update_id
        self._message_errors.clear()
        self.stats["updates"] += 1
        log.info("fleet: order %r update %d accepted: %d more base nodes", order.order_id, order.update_id, len(new))

    def _base_end(self) -> Optional[Node]:
        released = [n for n in self._node_states if n.released]
        if released:
            return released[-1]
        if self.last_node_id:
            return Node(self.last_node_id, self.last_node_seq, True)
        return None

    def _on_instant_actions(self, payload: bytes) -> None:
        try:
            msg = self._checked("instantActions", payload)
        except OrderRejected as e:
            self._reject(e.error_type, e.description, "instantActions", e.references)
            return
        for a in msg.get("actions", []):
            self.stats["instant_actions"] += 1
            self._instant(a)

    def _instant(self, a: Dict[str, Any]) -> None:
        name, aid = a["actionName"], a["actionId"]
        act = _Action(aid, name, RUNNING)
        self._actions[aid] = act
        self._actions.move_to_end(aid)
        while len(self._actions) > MAX_ACTION_STATES:
            self._actions.popitem(last=False)
        core = self.vehicle.core
        log.info("fleet: instant action %s (%s)", name, aid)
        if name == "cancelOrder":
            if self.order is None or self._cancelled or not (self._node_states or core.mission_active):
                act.status, act.result = FAILED, "no order to cancel"
                self._reject("noOrderToCancel", "cancelOrder: there is no order to cancel", "instantActions",
                             [("actionId", aid)])
                return
            core.abort("cancelled by the master control")
            self._cancelled = True
            self._node_states, self._edge_states, self._driving, self._plans = [], [], [], []
            self._cancel_action = act  # FINISHED once the vehicle stands still
        elif name == "startPause":
            core.pause()
            self._pause_action = act
        elif name == "stopPause":
            core.resume()
            act.status = FINISHED
        elif name == "initPosition":
            self._init_position(act, a.get("actionParameters") or [])
        elif name == "stateRequest":
            act.status = FINISHED
            self._t_state = -math.inf  # the next poll sends the state
        elif name == "factsheetRequest":
            self._publish("factsheet", self._with_header("factsheet", self._factsheet()))
            act.status = FINISHED
        else:
            act.status, act.result = FAILED, f"{name} is not supported by this vehicle"
            self._reject("actionNotSupported", f"instant action {name!r} is not supported (supported: "
                                               f"{', '.join(SUPPORTED_ACTIONS)})", "instantActions", [("actionId", aid)])

    def _init_position(self, act: _Action, params: List[Dict[str, Any]]) -> None:
        values = {p.get("key"): p.get("value") for p in params if isinstance(p, dict)}
        try:
            pose = tuple(_number(values, k) for k in ("x", "y", "theta"))
            if values.get("mapId", self.map_id) != self.map_id:
                raise ValueError(f"mapId {values.get('mapId')!r} is not the vehicle's map {self.map_id!r}")
            last = values.get("lastNodeId", "")
            if not isinstance(last, str):
                raise ValueError("lastNodeId must be a string")
        except ValueError as e:
            act.status, act.result = FAILED, str(e)[:200]
            self._reject(VALIDATION_ERROR, f"initPosition: {e}"[:300], "instantActions", [("actionId", act.action_id)])
            return

        def done(ok: bool, why: str) -> None:
            act.status, act.result = (FINISHED, "") if ok else (FAILED, why[:200])
            if ok:
                self.last_node_id = last or self.last_node_id
            else:
                self._reject("initPositionFailed", f"initPosition: {why}"[:300], "instantActions",
                             [("actionId", act.action_id)])
            self.poll(force=True)

        self.vehicle.request_pose(pose, done)  # type: ignore[arg-type]

    def _reject(self, error_type: str, description: str, topic: str, references: Sequence[Tuple[str, Any]] = ()) -> None:
        self.stats["rejected"] += 1
        refs = [{"referenceKey": "topic", "referenceValue": topic}]
        refs += [{"referenceKey": str(k), "referenceValue": str(v)[:200]} for k, v in references]
        self._message_errors.append({"errorType": error_type, "errorLevel": WARNING, "errorDescription": description[:500],
                                     "errorReferences": refs})
        del self._message_errors[:-MAX_MESSAGE_ERRORS]
        log.warning("fleet: %s: %s", error_type, description[:300])

    # -- progress and the state out -------------------------------------------------------

    def poll(self, force: bool = False) -> None:
        """Track progress along the order, finish actions, publish the state on change or when due."""
        self._track_progress()
        twist = self.vehicle.twist()
        still = max(abs(v) for v in twist) <= STILL
        core = self.vehicle.core
        if self._cancel_action is not None and not core.mission_active and still:
            self._cancel_action.status, self._cancel_action = FINISHED, None
        if self._pause_action is not None and still:
            self._pause_action.status, self._pause_action = FINISHED, None
        now_wall = self.vehicle.wall_time()
        state = self.state_message(now_wall)
        digest = self._state_digest(state)
        if force or digest != self._digest or now_wall - self._t_state >= self.cfg.state_period:
            self._digest, self._t_state = digest, now_wall
            self._publish("state", self._with_header("state", state, now_wall))

    def _track_progress(self) -> None:
        traj = self.vehicle.core.trajectory
        if traj is None or not self._plans:
            return
        done, offset = None, 0
        for plan, count in self._plans:
            if traj.plan is plan:
                done = offset + min(traj.waypoint_index, count)
                break
            offset += count
        if done is None:
            return
        while self._passed < done:
            node = self._driving[self._passed]
            self._passed += 1
            self.last_node_id, self.last_node_seq = node.node_id, node.sequence_id
            self._node_states = [n for n in self._node_states if n.sequence_id > node.sequence_id]
            self._traverse_edges_up_to(node.sequence_id)

    def _traverse_edges_up_to(self, seq: int) -> None:
        self._edge_states = [e for e in self._edge_states if e.sequence_id > seq]

    def _with_header(self, topic: str, body: Dict[str, Any], now_wall: Optional[float] = None) -> Dict[str, Any]:
        hid = self._header_ids.get(topic, -1) + 1
        self._header_ids[topic] = hid
        t = self.vehicle.wall_time() if now_wall is None else now_wall
        out = {"headerId": hid, "timestamp": iso_timestamp(t), "version": VERSION,
               "manufacturer": self.cfg.manufacturer, "serialNumber": self.cfg.serial_number}
        out.update(body)
        return out

    def position(self) -> Dict[str, Any]:
        core = self.vehicle.core
        if not core.initialized:
            return {"x": 0.0, "y": 0.0, "theta": 0.0, "mapId": self.map_id, "positionInitialized": False,
                    "localizationScore": 0.0}
        (x, y, phi), _ = core.pose(self.vehicle.now())
        state, pos_std = self.vehicle.quality()
        score = {"localized": 1.0, "degraded": 0.5}.get(state, 0.0)
        out = {"x": float(x), "y": float(y), "theta": float(wrap_angle(phi)), "mapId": self.map_id,
               "positionInitialized": True, "localizationScore": score}
        if pos_std is not None and math.isfinite(pos_std):
            out["deviationRange"] = float(pos_std)
        return out

    def velocity(self) -> Dict[str, float]:
        vx, vy, wz = self.vehicle.twist()
        return {"vx": float(vx), "vy": float(vy), "omega": float(wz)}

    def state_message(self, now_wall: float) -> Dict[str, Any]:
        core = self.vehicle.core
        twist = self.vehicle.twist()
        errors = [{"errorType": t, "errorLevel": level, "errorDescription": d[:500], "errorReferences": []}
                  for t, level, d in self.vehicle.conditions()]
        errors += [dict(e) for e in self._message_errors]
        horizon_only = bool(self._node_states) and not any(n.released for n in self._node_states)
        volts = self.vehicle.battery_voltage()
        battery: Dict[str, Any] = {"batteryCharge": 0.0, "charging": False}
        if volts is not None and math.isfinite(volts):
            span = self.cfg.battery_full_v - self.cfg.battery_empty_v
            battery["batteryCharge"] = round(100.0 * min(max((volts - self.cfg.battery_empty_v) / span, 0.0), 1.0), 1)
            battery["batteryVoltage"] = float(volts)
        return {
            "orderId": self.order_id, "orderUpdateId": self.order_update_id,
            "lastNodeId": self.last_node_id, "lastNodeSequenceId": self.last_node_seq,
            "nodeStates": [n.state() for n in self._node_states],
            "edgeStates": [e.state() for e in self._edge_states],
            "driving": max(abs(v) for v in twist) > STILL, "paused": bool(core.paused),
            "newBaseRequest": horizon_only,
            "operatingMode": "MANUAL" if core.mode == "teleop" else "AUTOMATIC",
            "agvPosition": self.position(), "velocity": self.velocity(),
            "actionStates": [a.state() for a in self._actions.values()],
            "batteryState": battery, "errors": errors,
            "safetyState": {"eStop": "MANUAL" if self.vehicle.estop() else "NONE",
                            "fieldViolation": bool(self.vehicle.field_violation())},
        }

    @staticmethod
    def _state_digest(state: Dict[str, Any]) -> Any:
        """What counts as a change worth a state message (not the pose, velocity or battery)."""
        return (state["orderId"], state["orderUpdateId"], state["lastNodeId"], state["lastNodeSequenceId"],
                tuple(n["nodeId"] for n in state["nodeStates"]), tuple(e["edgeId"] for e in state["edgeStates"]),
                state["driving"], state["paused"], state["newBaseRequest"], state["operatingMode"],
                tuple((a["actionId"], a["actionStatus"]) for a in state["actionStates"]),
                tuple((e["errorType"], e["errorDescription"]) for e in state["errors"]),
                state["agvPosition"]["positionInitialized"], state["safetyState"]["eStop"],
                state["safetyState"]["fieldViolation"])

    def visualization_message(self) -> Dict[str, Any]:
        return self._with_header("visualization", {"agvPosition": self.position(), "velocity": self.velocity()})

    def connection_message(self, state: str) -> Dict[str, Any]:
        return self._with_header("connection", {"connectionState": state})

    def factsheet_message(self) -> Dict[str, Any]:
        return self._with_header("factsheet", self._factsheet())


def _number(values: Dict[str, Any], key: str) -> float:
    v = values.get(key)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
        raise ValueError(f"parameter {key!r} must be a finite number, got {str(v)[:40]}")
    return float(v)


__all__ = ["VdaAgv", "Vehicle", "decode", "iso_timestamp", "VERSION", "SUPPORTED_ACTIONS"]
