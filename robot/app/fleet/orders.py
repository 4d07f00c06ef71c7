"""An ``order`` message, already valid against the schema, read into what this vehicle can drive.

VDA 5050 2.0, section 6.6: nodes and edges alternate in one sequence (sequenceId: node 0, edge
1, node 2, ...), each edge joins the nodes on either side of it, the released ("base") part is
a prefix of the sequence and the rest is the horizon, which is never driven. This vehicle
drives straight edges from node position to node position, stopping at each node (the
trajectory controller is stop-and-go), so it refuses (``orderError``, as 6.6.4.2 asks) what it
cannot honour: released nodes without a position or on another map, positions outside the
map, NURBS trajectories, edge orientations, edges that forbid rotation, and actions (it has no
load handling). Structural faults are ``validationError``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Dict, List, Optional, Sequence, Tuple

from robot.config.fleet import FleetConfig
from robot.control.path_file import MAX_SPEED, MAX_WAYPOINTS, PathPlan, Waypoint

VALIDATION_ERROR = "validationError"
ORDER_ERROR = "orderError"
ORDER_UPDATE_ERROR = "orderUpdateError"


class OrderRejected(Exception):
    """An order (or instant action) this vehicle will not take, as a VDA 5050 error."""

    def __init__(self, error_type: str, description: str, references: Sequence[Tuple[str, Any]] = ()):
        super().__init__(description)
        self.error_type = error_type
        self.description = description
        self.references = [(str(k), str(v)[:200]) for k, v in references]


@dataclass(frozen=True)
class Node:
    node_id: str
    sequence_id: int
    released: bool
    x: Optional[float] = None
    y: Optional[float] = None
    theta: Optional[float] = None
    map_id: Optional[str] = None
    deviation_xy: Optional[float] = None
    deviation_theta: Optional[float] = None

    def state(self) -> Dict[str, Any]:
        out: Dict[str, Any] = {"nodeId": self.node_id, "sequenceId": self.sequence_id, "released": self.released}
        if self.x is not None and self.y is not None and self.map_id is not None:
            pos: Dict[str, Any] = {"x": self.x, "y": self.y, "mapId": self.map_id}
            # the 2.0.0 state schema requires theta in a nodePosition: a free heading is left out whole
            if self.theta is not None:
                pos["theta"] = self.theta
                out["nodePosition"] = pos
        return out


@dataclass(frozen=True)
class Edge:
    edge_id: str
    sequence_id: int
    released: bool
    start_node_id: str
    end_node_id: str
    max_speed: Optional[float] = None

    def state(self) -> Dict[str, Any]:
        return {"edgeId": self.edge_id, "sequenceId": self.sequence_id, "released": self.released}


@dataclass(frozen=True)
class Order:
    order_id: str
    update_id: int
    nodes: Tuple[Node, ...]
    edges: Tuple[Edge, ...]

    @property
    def base_nodes(self) -> Tuple[Node, ...]:
        return tuple(n for n in self.nodes if n.released)

    def edge_into(self, node: Node) -> Optional[Edge]:
        for e in self.edges:
            if e.sequence_id == node.sequence_id - 1:
                return e
        return None


def read_order(msg: Dict[str, Any], map_id: str, bounds: Tuple[Sequence[float], Sequence[float]]) -> Order:
    """The order's nodes and edges, checked; OrderRejected naming the first problem."""
    order_id, update_id = msg["orderId"], msg["orderUpdateId"]
    refs = [("orderId", order_id), ("orderUpdateId", update_id)]
    raw_nodes, raw_edges = msg["nodes"], msg["edges"]
    if not raw_nodes:
        raise OrderRejected(VALIDATION_ERROR, "an order needs at least one node", refs)
    if len(raw_nodes) > MAX_WAYPOINTS + 1:
        raise OrderRejected(ORDER_ERROR, f"{len(raw_nodes)} nodes: this vehicle takes at most {MAX_WAYPOINTS + 1}", refs)
    if len(raw_edges) != len(raw_nodes) - 1:
        raise OrderRejected(VALIDATION_ERROR, f"{len(raw_nodes)} nodes need {len(raw_nodes) - 1} edges, the order has "
                                              f"{len(raw_edges)}", refs)
    s0 = raw_nodes[0]["sequenceId"]
    nodes: List[Node] = []
    for i, n in enumerate(raw_nodes):
        if n["sequenceId"] != s0 + 2 * i:
            raise OrderRejected(VALIDATION_ERROR, f"node {n['nodeId']!r} has sequenceId {n['sequenceId']}, expected "
                                                  f"{s0 + 2 * i} (nodes and edges alternate)", refs + [("nodeId", n["nodeId"])])
        nodes.append(_node(n, map_id, bounds, refs))
    edges: List[Edge] = []
    for i, e in enumerate(raw_edges):
        eref = refs + [("edgeId", e["edgeId"])]
        if e["sequenceId"] != s0 + 2 * i + 1:
            raise OrderRejected(VALIDATION_ERROR, f"edge {e['edgeId']!r} has sequenceId {e['sequenceId']}, expected "
                                                  f"{s0 + 2 * i + 1}", eref)
        if e["startNodeId"] != nodes[i].node_id or e["endNodeId"] != nodes[i + 1].node_id:
            raise OrderRejected(VALIDATION_ERROR, f"edge {e['edgeId']!r} must join {nodes[i].node_id!r} to "
                                                  f"{nodes[i + 1].node_id!r}", eref)
        edges.append(_edge(e, eref))
    # The base is a prefix of the sequence n0 e0 n1 e1 ...: nothing released after the horizon starts.
    sequence: List[Any] = [nodes[0]]
    for e, n in zip(edges, nodes[1:]):
        sequence += [e, n]
    horizon = False
    for item in sequence:
        if not item.released:
            horizon = True
        elif horizon:
            kind, ident = ("node", item.node_id) if isinstance(item, Node) else ("edge", item.edge_id)
            raise OrderRejected(VALIDATION_ERROR, f"released {kind} {ident!r} follows an unreleased one (the base must "
                                                  "come before the horizon)", refs)
    if not nodes[0].released:
        raise OrderRejected(VALIDATION_ERROR, "the first node of an order must be released", refs)
    return Order(order_id, update_id, tuple(nodes), tuple(edges))


def _node(n: Dict[str, Any], map_id: str, bounds, refs) -> Node:
    nref = refs + [("nodeId", n["nodeId"])]
    if n.get("actions"):
        raise OrderRejected(ORDER_ERROR, f"node {n['nodeId']!r} has actions; this vehicle performs none",
                            nref + [("actionId", n["actions"][0].get("actionId", ""))])
    pos = n.get("nodePosition")
    if pos is None:
        if n["released"]:
            raise OrderRejected(ORDER_ERROR, f"released node {n['nodeId']!r} has no nodePosition (this vehicle drives "
                                             "to positions)", nref)
        return Node(n["nodeId"], n["sequenceId"], False)
    if pos["mapId"] != map_id:
        raise OrderRejected(ORDER_ERROR, f"node {n['nodeId']!r} is on map {pos['mapId']!r}, the vehicle on "
                                         f"{map_id!r}", nref + [("mapId", pos["mapId"])])
    x, y = float(pos["x"]), float(pos["y"])
    lo, hi = bounds
    if not (math.isfinite(x) and math.isfinite(y) and lo[0] <= x <= hi[0] and lo[1] <= y <= hi[1]):
        raise OrderRejected(ORDER_ERROR, f"node {n['nodeId']!r} at ({x:.6g}, {y:.6g}) is outside the map (x in "
                                         f"[{lo[0]:.3f}, {hi[0]:.3f}], y in [{lo[1]:.3f}, {hi[1]:.3f}])", nref)
    theta = pos.get("theta")
    dev_xy, dev_theta = pos.get("allowedDeviationXy", pos.get("allowedDeviationXY")), pos.get("allowedDeviationTheta")
    return Node(n["nodeId"], n["sequenceId"], n["released"], x, y, None if theta is None else float(theta),
                pos["mapId"], None if dev_xy is None else float(dev_xy), None if dev_theta is None else float(dev_theta))


def _edge(e: Dict[str, Any], eref) -> Edge:
    if e.get("actions"):
        raise OrderRejected(ORDER_ERROR, f"edge {e['edgeId']!r} has actions; this vehicle performs none",
                            eref + [("actionId", e["actions"][0].get("actionId", ""))])
    for key, why in (("trajectory", "it drives straight edges only"),
                     ("orientation", "it turns to the next node's heading on the way")):
        if key in e:
            raise OrderRejected(ORDER_ERROR, f"edge {e['edgeId']!r}: '{key}' is not supported ({why})", eref)
    if e.get("rotationAllowed") is False:
        raise OrderRejected(ORDER_ERROR, f"edge {e['edgeId']!r} forbids rotation; this vehicle turns while it "
                                         "drives", eref)
    speed = e.get("maxSpeed")
    if speed is not None and not (math.isfinite(float(speed)) and float(speed) > 0.0):
        raise OrderRejected(ORDER_ERROR, f"edge {e['edgeId']!r}: maxSpeed must be above 0 m/s, got {speed}", eref)
    return Edge(e["edgeId"], e["sequenceId"], e["released"], e["startNodeId"], e["endNodeId"],
                None if speed is None else float(speed))


def waypoint(node: Node, edge: Optional[Edge], cfg: FleetConfig) -> Waypoint:
    """The trajectory controller's target for driving along ``edge`` to ``node``."""
    speed = cfg.default_speed if edge is None or edge.max_speed is None else min(edge.max_speed, MAX_SPEED)
    tol = node.deviation_xy if node.deviation_xy is not None and node.deviation_xy > 0.0 else cfg.node_tolerance
    kw: Dict[str, Any] = {}
    if node.deviation_theta is not None and abs(node.deviation_theta) > 0.0:
        kw["heading_tolerance"] = min(abs(node.deviation_theta), math.pi)
    return Waypoint(x=node.x, y=node.y, heading=node.theta, speed=speed, tolerance=min(tol, 1.0), **kw)


def plan_for(nodes: Sequence[Node], order: Order, cfg: FleetConfig) -> PathPlan:
    """A path through ``nodes`` (released nodes of ``order``), each reached along its incoming edge."""
    wps = tuple(waypoint(n, order.edge_into(n), cfg) for n in nodes)
    return PathPlan(waypoints=wps, source=f"VDA 5050 order {order.order_id!r} update {order.update_id}")


__all__ = ["Edge", "Node", "Order", "OrderRejected", "ORDER_ERROR", "ORDER_UPDATE_ERROR", "VALIDATION_ERROR",
           "plan_for", "read_order", "waypoint"]
