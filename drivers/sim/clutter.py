"""What a construction site puts in front of the simulated cameras that the plane map does not know.

Builders return :class:`Solid` (polygons in the ground frame the renderer draws from both sides,
``SimScene(clutter=[...])``); none of them changes the map. Sizes are those of the real thing:

* :func:`person`: an elliptic cylinder 0.5 x 0.3 x 1.75 m;
* :func:`pallet`: a 1.2 x 0.8 x 0.15 m pallet (decks and three runners, fork openings between),
  stacked ``stack`` high;
* :func:`leaning_boards`: boards standing on the floor, leaning on a wall at a few degrees;
* :func:`door_leaf`: a door leaf at any opening angle, hinged at a jamb of an opening of the map
  (:func:`map_openings`);
* :func:`parallel_panel`: a panel parallel to a wall a few centimetres to decimetres in front of
  it, covering a chosen fraction of the wall: to a plane fit it looks exactly like the wall moved;
* :func:`shelving`: a shelving unit (uprights, shelves, optional goods).

:func:`as_built` (or :func:`built_walls` with chosen deviations) gives the walls as built, not as
drawn: offset along their normal, bowed, out of plumb, or not built at all, for
``SimScene(walls=...)``. :func:`random_site_clutter` draws a mix of the above. Everything random
takes a ``numpy.random.Generator``: the same seed gives the same site.

Positions on a wall use its :class:`WallFrame`: ``along`` (m from the wall's start, horizontally
along it) and ``offset`` (m in front of it, towards its observable side).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple

import numpy as np

from drivers.sim.building import free_space_poses, in_free_space
from robot.base.errors import ConfigError
from robot.maps.plane_map import MapPlane, PlaneMap
from robot.maps.visibility import clip_vertex_list

SITE_KINDS = ("person", "pallet", "boards", "door", "panel", "shelving")
_EZ = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True, eq=False)
class Solid:
    """Clutter geometry: planar polygons (K, 3) in the ground frame, drawn from both sides.
    ``info`` records what was built where (for tests and evaluations)."""

    kind: str
    polygons: Tuple[np.ndarray, ...]
    info: Dict[str, Any] = field(default_factory=dict)

    def faces(self) -> List[np.ndarray]:
        return list(self.polygons)

    def bounds(self) -> Tuple[np.ndarray, np.ndarray]:
        v = np.vstack(self.polygons)
        return v.min(axis=0), v.max(axis=0)


def _check(cond: bool, message: str) -> None:
    if not cond:
        raise ConfigError(message)


def _rot_z(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def cuboid_faces(center: Sequence[float], size: Sequence[float], R: Optional[np.ndarray] = None) -> List[np.ndarray]:
    """The six faces of a box of ``size`` (along R's columns) centred at ``center``."""
    R = np.eye(3) if R is None else np.asarray(R, float)
    h = np.asarray(size, float) / 2
    c = np.asarray(center, float)
    corner = {(i, j, k): c + R @ (h * (i, j, k)) for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)}
    quads = [[(-1, -1, -1), (1, -1, -1), (1, 1, -1), (-1, 1, -1)], [(-1, -1, 1), (-1, 1, 1), (1, 1, 1), (1, -1, 1)],
             [(-1, -1, -1), (-1, -1, 1), (1, -1, 1), (1, -1, -1)], [(-1, 1, -1), (1, 1, -1), (1, 1, 1), (-1, 1, 1)],
             [(-1, -1, -1), (-1, 1, -1), (-1, 1, 1), (-1, -1, 1)], [(1, -1, -1), (1, -1, 1), (1, 1, 1), (1, 1, -1)]]
    return [np.array([corner[k] for k in q]) for q in quads]


# -- walls ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class WallFrame:
    """A vertical map plane's own axes: ``along`` (horizontal, in the wall), ``normal``
    (horizontal, towards the observable side) and up; s = (p - origin) . along runs from 0
    (``s_min``) to the wall's length (``s_max``)."""

    plane_id: str
    origin: np.ndarray  # (3,) on the plane at the wall's start (s = 0), at z = 0
    along: np.ndarray
    normal: np.ndarray
    s_min: float
    s_max: float
    z_min: float
    z_max: float

    @property
    def length(self) -> float:
        return self.s_max - self.s_min

    @property
    def yaw(self) -> float:
        """Heading of ``along`` in the ground frame."""
        return math.atan2(self.along[1], self.along[0])

    def point(self, along: float, offset: float = 0.0, z: float = 0.0) -> np.ndarray:
        """Ground-frame point ``along`` m from the wall's start, ``offset`` m in front of it, at height z."""
        return self.origin + along * self.along + offset * self.normal + z * _EZ

    def s_of(self, p: np.ndarray) -> np.ndarray:
        return (np.asarray(p, float) - self.origin) @ self.along


def is_wall(plane: MapPlane) -> bool:
    return abs(float(plane.normal[2])) < 0.1


def wall_frame(plane: MapPlane) -> WallFrame:
    _check(is_wall(plane), f"plane '{plane.id}' is not a wall (its normal is not horizontal)")
    n = np.array([plane.normal[0], plane.normal[1], 0.0])
    n /= np.linalg.norm(n)
    along = np.array([-n[1], n[0], 0.0])
    v = plane.vertices
    foot = np.array([*(-plane.d * plane.normal[:2] / (plane.normal[:2] @ plane.normal[:2])), 0.0])
    s = (v - foot) @ along
    origin = foot + float(s.min()) * along  # s = 0 at the wall's start
    return WallFrame(plane.id, origin, along, n, 0.0, float(s.max() - s.min()), float(v[:, 2].min()),
                     float(v[:, 2].max()))


def against_wall(plane: MapPlane, along: float, offset: float) -> Tuple[float, float, float]:
    """(x, y, yaw) of a point ``along`` the wall and ``offset`` in front of it, yaw along the wall:
    place a pallet or a shelving unit with its long side parallel to the wall."""
    f = wall_frame(plane)
    p = f.point(along, offset)
    return float(p[0]), float(p[1]), f.yaw


# -- builders -------------------------------------------------------------------------------------


def person(x: float, y: float, yaw: float = 0.0, width: float = 0.5, depth: float = 0.3, height: float = 1.75,
           sides: int = 12) -> Solid:
    """A person standing at (x, y): an elliptic cylinder ``width`` x ``depth`` x ``height`` m."""
    _check(width > 0 and depth > 0 and height > 0 and sides >= 3, "person: sizes must be positive")
    t = np.linspace(0.0, 2 * math.pi, sides, endpoint=False)
    c, s = math.cos(yaw), math.sin(yaw)
    a, b = width / 2 * np.cos(t), depth / 2 * np.sin(t)
    xy = np.column_stack([x + c * a - s * b, y + s * a + c * b])
    polys = []
    for i in range(sides):
        (x0, y0), (x1, y1) = xy[i], xy[(i + 1) % sides]
        polys.append(np.array([[x0, y0, 0.0], [x1, y1, 0.0], [x1, y1, height], [x0, y0, height]]))
    polys.append(np.column_stack([xy, np.full(sides, height)]))
    return Solid("person", tuple(polys), {"x": x, "y": y, "yaw": yaw, "size": (width, depth, height)})


def pallet(x: float, y: float, yaw: float = 0.0, stack: int = 1, size: Tuple[float, float, float] = (1.2, 0.8, 0.15),
           deck: float = 0.022) -> Solid:
    """``stack`` pallets on top of each other at (x, y): each a top and a bottom deck ``deck`` thick
    on three runners along its length, with the two fork openings between them."""
    L, W, H = size
    _check(stack >= 1 and L > 0 and W > 0 and H > 2 * deck > 0, "pallet: stack >= 1 and a height above two decks")
    R = _rot_z(yaw)
    c = np.array([x, y, 0.0])
    polys: List[np.ndarray] = []
    for k in range(int(stack)):
        z0 = k * H
        polys += cuboid_faces(c + [0, 0, z0 + H - deck / 2], (L, W, deck), R)
        polys += cuboid_faces(c + [0, 0, z0 + deck / 2], (L, W, deck), R)
        for off in (-(W / 2 - 0.05), 0.0, W / 2 - 0.05):
            polys += cuboid_faces(c + R @ [0, off, 0] + [0, 0, z0 + H / 2], (L, 0.1, H - 2 * deck), R)
    return Solid("pallet", tuple(polys), {"x": x, "y": y, "yaw": yaw, "stack": int(stack), "height": stack * H})


def leaning_boards(plane: MapPlane, along: float, rng: Optional[np.random.Generator] = None, count: int = 3,
                   width: float = 1.25, length: float = 2.5, thickness: float = 0.018, angle_deg: float = 6.0) -> Solid:
    """``count`` boards ``width`` x ``length`` standing on the floor ``along`` m from the wall's start,
    leaning ``angle_deg`` from the wall (each on the one behind it). Boards longer than the wall is
    high are cut to lean on its top edge. ``rng`` jitters each board's angle (+-1.5 deg) and place."""
    f = wall_frame(plane)
    _check(count >= 1 and width > 0 and length > 0 and thickness > 0 and 0 < angle_deg < 45,
           "leaning_boards: count >= 1, positive sizes, angle between 0 and 45 deg")
    polys: List[np.ndarray] = []
    boards = []
    top_offset = 0.0  # where the next board's back touches at its top: the wall, then the board before
    for _ in range(int(count)):
        a = math.radians(angle_deg + (rng.uniform(-1.5, 1.5) if rng is not None else 0.0))
        s = along + (rng.uniform(-0.05, 0.05) if rng is not None else 0.0)
        L = min(length, (f.z_max - 0.01) / math.cos(a))
        foot_offset = top_offset + L * math.sin(a)
        foot = f.point(s, foot_offset)  # the back face's bottom edge, on the floor
        e_len = -math.sin(a) * f.normal + math.cos(a) * _EZ  # up the board, towards the wall
        e_thk = math.cos(a) * f.normal + math.sin(a) * _EZ  # out of its face, away from the wall
        R = np.column_stack([f.along, e_thk, e_len])
        polys += cuboid_faces(foot + e_len * L / 2 + e_thk * thickness / 2, (width, thickness, L), R)
        boards.append({"along": s, "angle_deg": math.degrees(a), "length": L, "foot_offset": foot_offset,
                       "top_offset": top_offset})
        top_offset += thickness / math.cos(a)
    return Solid("boards", tuple(polys), {"plane_id": plane.id, "along": along, "width": width, "boards": boards})


@dataclass(frozen=True)
class Opening:
    """A door-sized gap in one wall plane's polygons, from ``s0`` to ``s1`` along it, ``top`` m high."""

    plane_id: str
    frame: WallFrame
    s0: float
    s1: float
    top: float

    @property
    def width(self) -> float:
        return self.s1 - self.s0


def _covered_intervals(poly: np.ndarray, f: WallFrame, z: float) -> List[Tuple[float, float]]:
    """Where a (possibly concave) wall polygon covers height z, as intervals of s (even-odd rule)."""
    nxt = np.roll(poly, -1, axis=0)
    cross = []
    for p, q in zip(poly, nxt):
        if (p[2] < z) != (q[2] < z):  # half-open, so a vertex exactly at z counts once
            t = (z - p[2]) / (q[2] - p[2])
            cross.append(float(f.s_of(p + t * (q - p))))
    cross.sort()
    return [(cross[i], cross[i + 1]) for i in range(0, len(cross) - 1, 2)]


def _vertical_cover(poly: np.ndarray, f: WallFrame, s: float) -> List[float]:
    nxt = np.roll(poly, -1, axis=0)
    sp, sq = f.s_of(poly), f.s_of(nxt)
    zs = []
    for k in range(len(poly)):
        if (sp[k] < s) != (sq[k] < s):
            t = (s - sp[k]) / (sq[k] - sp[k])
            zs.append(float(poly[k, 2] + t * (nxt[k, 2] - poly[k, 2])))
    return zs


def map_openings(plane_map: PlaneMap, z: float = 0.5, min_width: float = 0.6, max_width: float = 2.5) -> List[Opening]:
    """Door-sized gaps (``min_width`` to ``max_width`` wide at height ``z``) inside each wall plane's
    polygons: the doors of a room grid or an imported storey. Gaps between different planes are
    not found."""
    out: List[Opening] = []
    for plane in plane_map.planes:
        if not is_wall(plane):
            continue
        f = wall_frame(plane)
        iv = sorted(i for poly in plane.polygons for i in _covered_intervals(poly, f, z))
        merged: List[List[float]] = []
        for a, b in iv:
            if merged and a <= merged[-1][1] + 1e-6:
                merged[-1][1] = max(merged[-1][1], b)
            else:
                merged.append([a, b])
        for (_, a), (b, _) in zip(merged, merged[1:]):
            if min_width <= b - a <= max_width:
                above = [h for poly in plane.polygons for h in _vertical_cover(poly, f, 0.5 * (a + b)) if h > z]
                out.append(Opening(plane.id, f, a, b, min(above) if above else f.z_max))
    return out


def door_leaf(opening: Opening, angle_deg: float, hinge: str = "start", thickness: float = 0.04,
              swing: int = 1) -> Solid:
    """A door leaf filling ``opening``, hinged at its ``start`` or ``end`` jamb and open by
    ``angle_deg`` (0 closed, in the wall; 90 square to it), swinging to the wall's observable side
    (``swing`` = 1) or away from it (-1)."""
    _check(hinge in ("start", "end"), f"door_leaf: hinge must be 'start' or 'end', got {hinge!r}")
    _check(swing in (1, -1) and thickness > 0 and -180 <= angle_deg <= 180, "door_leaf: swing is 1 or -1, angle +-180 deg")
    f = opening.frame
    h = 1.0 if hinge == "start" else -1.0
    s_hinge = opening.s0 if hinge == "start" else opening.s1
    th = math.radians(angle_deg)
    width, height = opening.width - 0.01, opening.top - 0.01  # a few millimetres of play at the jambs
    hinge_p = f.origin + s_hinge * f.along + 0.005 * h * f.along
    leaf_dir = math.cos(th) * h * f.along + math.sin(th) * swing * f.normal
    leaf_perp = math.sin(th) * h * f.along - math.cos(th) * swing * f.normal  # into the wall when closed
    center = hinge_p + leaf_dir * width / 2 + leaf_perp * thickness / 2 + _EZ * (0.005 + height / 2)
    polys = cuboid_faces(center, (width, thickness, height), np.column_stack([leaf_dir, leaf_perp, _EZ]))
    return Solid("door", tuple(polys), {"plane_id": opening.plane_id, "angle_deg": angle_deg, "hinge": hinge,
                                        "s0": opening.s0, "s1": opening.s1})


def parallel_panel(plane: MapPlane, offset: float, coverage: float, rng: Optional[np.random.Generator] = None,
                   region: Optional[Tuple[float, float]] = None, height: Optional[float] = None,
                   thickness: float = 0.018) -> Solid:
    """A panel parallel to the wall, its face ``offset`` m in front of it, covering ``coverage`` of
    the wall's length within ``region`` (s from the wall's start; default: all of it) and its full
    height (or ``height``). ``rng`` places it at random within the region (default: centred).
    The dangerous case for a localizer: it looks exactly like the wall ``offset`` nearer."""
    f = wall_frame(plane)
    _check(0 < coverage <= 1, f"parallel_panel: coverage is a fraction (0 to 1], got {coverage}")
    _check(offset > thickness > 0, f"parallel_panel: offset ({offset} m) must exceed the thickness ({thickness} m)")
    a, b = (0.0, f.length) if region is None else (float(region[0]), float(region[1]))
    _check(b > a, f"parallel_panel: empty region {region}")
    length = coverage * (b - a)
    start = a + (rng.uniform(0.0, (b - a) - length) if rng is not None else 0.5 * ((b - a) - length))
    top = min(f.z_max, height) if height is not None else f.z_max
    z0 = max(f.z_min, 0.0)
    center = f.point(start + length / 2, offset - thickness / 2, z0 + (top - z0) / 2)
    polys = cuboid_faces(center, (length, thickness, top - z0), np.column_stack([f.along, f.normal, _EZ]))
    return Solid("panel", tuple(polys), {"plane_id": plane.id, "offset": offset, "coverage": coverage,
                                         "s0": start, "s1": start + length, "z0": z0, "z1": top})


def shelving(x: float, y: float, yaw: float = 0.0, length: float = 1.8, depth: float = 0.5, height: float = 2.0,
             levels: int = 5, rng: Optional[np.random.Generator] = None, goods: float = 0.5) -> Solid:
    """A shelving unit at (x, y), ``length`` along ``yaw``: four uprights and ``levels`` shelves;
    with ``rng``, boxes of goods on about ``goods`` of the shelf space."""
    _check(length > 0 and depth > 0 and height > 0 and levels >= 1, "shelving: positive sizes and levels >= 1")
    R = _rot_z(yaw)
    c = np.array([x, y, 0.0])
    post, board = 0.05, 0.025
    polys: List[np.ndarray] = []
    for sx in (-1, 1):
        for sy in (-1, 1):
            p = c + R @ [sx * (length - post) / 2, sy * (depth - post) / 2, 0.0]
            polys += cuboid_faces(p + [0, 0, height / 2], (post, post, height), R)
    shelf_z = np.linspace(0.1, height - board, int(levels))
    gap = (shelf_z[1] - shelf_z[0]) if levels > 1 else height - 0.1
    for z in shelf_z:
        polys += cuboid_faces(c + [0, 0, z + board / 2], (length, depth, board), R)
        if rng is None or z > height - 0.2:
            continue
        slot = -length / 2 + 0.05
        while slot < length / 2 - 0.25:
            w = rng.uniform(0.15, 0.4)
            if slot + w > length / 2 - 0.05:
                break
            if rng.random() < goods:
                d = rng.uniform(0.2, depth - 0.05)
                hgt = rng.uniform(0.1, max(0.11, 0.8 * gap))
                polys += cuboid_faces(c + R @ [slot + w / 2, 0.0, 0.0] + [0, 0, z + board + hgt / 2], (w - 0.02, d, hgt), R)
            slot += w
    return Solid("shelving", tuple(polys), {"x": x, "y": y, "yaw": yaw, "size": (length, depth, height)})


# -- walls as built -------------------------------------------------------------------------------


@dataclass(frozen=True)
class WallDeviation:
    """How one map plane was built. Signs: + is towards the plane's observable side (into the room)."""

    offset: float = 0.0  # m, the whole face moved along its normal
    bow: float = 0.0  # m at mid-wall, zero at its ends (a parabola along the wall)
    tilt_deg: float = 0.0  # out of plumb about the floor line z = 0: the top moves by z tan(tilt)
    built: bool = True  # False: in the map but not built yet (not drawn)

    def displacement(self, frame: Optional[WallFrame], s: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Displacement (m, along the normal) of the built surface at wall coordinates (s, z)."""
        out = np.full(np.broadcast(np.asarray(s), np.asarray(z)).shape, self.offset, float)
        if frame is not None:
            half = max(frame.length / 2, 1e-9)
            t = (np.asarray(s, float) - 0.5 * (frame.s_min + frame.s_max)) / half
            out = out + self.bow * (1.0 - np.clip(t, -1, 1) ** 2) + np.asarray(z, float) * math.tan(math.radians(self.tilt_deg))
        return out


@dataclass
class BuiltWalls:
    """The walls as built, for ``SimScene(walls=...)``: ``polygons`` to draw and per polygon the map
    plane (n, d) whose front alone is drawn; ``deviations`` per plane id."""

    plane_map: PlaneMap
    deviations: Dict[str, WallDeviation]
    polygons: List[np.ndarray]
    sides: List[np.ndarray]

    def displacement(self, plane_id: str, point_G: Sequence[float]) -> float:
        """How far (m, along the map normal, + into the room) the built surface is from the map plane
        at the wall coordinates of ``point_G``."""
        plane = self.plane_map[plane_id]
        dev = self.deviations.get(plane_id, WallDeviation())
        p = np.asarray(point_G, float)
        if not is_wall(plane):
            return float(dev.offset)
        f = wall_frame(plane)
        return float(dev.displacement(f, f.s_of(p), p[2]))


def built_walls(plane_map: PlaneMap, deviations: Mapping[str, WallDeviation], segments: int = 8,
                end_overlap: Optional[float] = None) -> BuiltWalls:
    """The map's polygons moved by ``deviations`` (plane id -> WallDeviation; others as drawn).

    A bowed wall is split into ``segments`` strips along it, each planar (its chord: 1/segments^2
    of the bow off the curve at most). A wall moved back from a corner would leave a slit to the
    backdrop there, which real walls do not have: each deviating wall is extended at its two ends
    by ``end_overlap`` (default: twice its largest displacement plus 2 mm), hidden behind the
    wall it meets."""
    unknown = sorted(set(deviations) - {p.id for p in plane_map.planes})
    _check(not unknown, f"built_walls: no plane {', '.join(map(repr, unknown))} in the map")
    polys: List[np.ndarray] = []
    sides: List[np.ndarray] = []
    for plane in plane_map.planes:
        dev = deviations.get(plane.id, WallDeviation())
        if not dev.built:
            continue
        if dev == WallDeviation():
            polys += [np.array(p, float) for p in plane.polygons]
            sides += [plane.pi] * len(plane.polygons)
            continue
        if not is_wall(plane):
            polys += [np.array(p, float) + dev.offset * plane.normal for p in plane.polygons]
            sides += [plane.pi] * len(plane.polygons)
            continue
        f = wall_frame(plane)
        z_hi = max(abs(f.z_min), abs(f.z_max))
        worst = abs(dev.offset) + abs(dev.bow) + z_hi * abs(math.tan(math.radians(dev.tilt_deg)))
        ext = 2 * worst + 0.002 if end_overlap is None else float(end_overlap)
        cuts = np.linspace(f.s_min, f.s_max, (int(segments) if dev.bow != 0 else 1) + 1)
        o_a = float(f.origin @ f.along)
        for poly in plane.polygons:
            poly = np.array(poly, float)
            s = f.s_of(poly)
            # Extend the wall's two ends (vertices on them), so a displaced wall still meets its neighbours.
            poly[np.isclose(s, f.s_min, atol=1e-6)] -= ext * f.along
            poly[np.isclose(s, f.s_max, atol=1e-6)] += ext * f.along
            for k in range(len(cuts) - 1):
                lo = -math.inf if k == 0 else cuts[k]
                hi = math.inf if k == len(cuts) - 2 else cuts[k + 1]
                half_spaces = []
                if math.isfinite(lo):
                    half_spaces.append([*f.along, -o_a - lo])
                if math.isfinite(hi):
                    half_spaces.append([*(-f.along), o_a + hi])
                piece = clip_vertex_list(poly.tolist(), half_spaces) if half_spaces else poly.tolist()
                if piece is None:
                    continue
                piece = np.array(piece)
                # The strip's chord of the bow: linear between its cut lines, so the piece stays planar.
                sp = np.clip(f.s_of(piece), cuts[k], cuts[k + 1])
                b0, b1 = dev.displacement(f, np.array([cuts[k], cuts[k + 1]]), np.zeros(2)) - dev.offset
                w = (sp - cuts[k]) / max(cuts[k + 1] - cuts[k], 1e-12)
                delta = dev.offset + b0 + w * (b1 - b0) + piece[:, 2] * math.tan(math.radians(dev.tilt_deg))
                polys.append(piece + delta[:, None] * f.normal)
                sides.append(plane.pi)
    return BuiltWalls(plane_map, dict(deviations), polys, sides)


def as_built(plane_map: PlaneMap, rng: np.random.Generator, offset_std: float = 0.01, bow_max: float = 0.01,
             tilt_deg: float = 0.3, unbuilt: float = 0.0) -> BuiltWalls:
    """Random as-built deviations of every plane: offset ~ N(0, offset_std) (cut at 2.5 std),
    bow uniform within +-bow_max for walls of 4 m or more (scaled by (length / 4 m)^2 below),
    out of plumb uniform within +-tilt_deg, and a fraction ``unbuilt`` of planes not built."""
    _check(offset_std >= 0 and bow_max >= 0 and tilt_deg >= 0 and 0 <= unbuilt < 1,
           "as_built: deviations must not be negative and unbuilt is a fraction below 1")
    devs: Dict[str, WallDeviation] = {}
    for plane in plane_map.planes:
        off = float(np.clip(rng.normal(0.0, offset_std), -2.5 * offset_std, 2.5 * offset_std)) if offset_std else 0.0
        bow = tilt = 0.0
        u = rng.uniform(-1.0, 1.0, 2)
        if is_wall(plane):
            length = wall_frame(plane).length
            bow = float(u[0] * bow_max * min(1.0, (length / 4.0) ** 2))
            tilt = float(u[1] * tilt_deg)
        built = not (unbuilt > 0 and rng.random() < unbuilt)
        devs[plane.id] = WallDeviation(off, bow, tilt, built)
    return built_walls(plane_map, devs)


# -- a random site --------------------------------------------------------------------------------


def _overlaps(a: Solid, placed: Sequence[Solid], gap: float = 0.05) -> bool:
    lo, hi = a.bounds()
    for b in placed:
        blo, bhi = b.bounds()
        if np.all(lo[:2] < bhi[:2] + gap) and np.all(blo[:2] < hi[:2] + gap):
            return True
    return False


def _clear_of(a: Solid, points: Sequence[Tuple[float, float]], clearance: float) -> bool:
    lo, hi = a.bounds()
    for p in points:
        q = np.clip(np.asarray(p[:2], float), lo[:2], hi[:2])
        if math.hypot(*(q - np.asarray(p[:2], float))) < clearance:
            return False
    return True


def random_site_clutter(plane_map: PlaneMap, rng: np.random.Generator, n: int,
                        keep_clear: Sequence[Tuple[float, float]] = (), clearance: float = 0.5,
                        kinds: Sequence[str] = SITE_KINDS) -> List[Solid]:
    """Up to ``n`` items of ``kinds`` (of SITE_KINDS) where they fit: people, pallets and shelving in
    free space inside the building, boards and panels at walls, doors in the map's openings; none
    within ``clearance`` of the ``keep_clear`` points or on top of another. Fewer if the map has no
    room for them (the paper arena is too small for most)."""
    bad = [k for k in kinds if k not in SITE_KINDS]
    _check(not bad and len(kinds) > 0, f"random_site_clutter: unknown kind(s) {bad} (choose from {', '.join(SITE_KINDS)})")
    walls = [p for p in plane_map.planes if is_wall(p) and wall_frame(p).length >= 1.0 and wall_frame(p).z_max >= 0.5]
    openings = map_openings(plane_map)
    placed: List[Solid] = []
    tries = 0
    while len(placed) < n and tries < 40 * max(n, 1):
        tries += 1
        kind = kinds[int(rng.integers(len(kinds)))]
        item = _random_item(kind, plane_map, rng, walls, openings)
        if item is None or _overlaps(item, placed) or not _clear_of(item, keep_clear, clearance):
            continue
        placed.append(item)
    return placed


def _random_item(kind: str, plane_map: PlaneMap, rng: np.random.Generator, walls: List[MapPlane],
                 openings: List[Opening]) -> Optional[Solid]:
    if kind in ("person", "pallet", "shelving"):
        half = {"person": 0.3, "pallet": 0.75, "shelving": 1.0}[kind]
        poses = free_space_poses(plane_map, 1, rng, clearance=half + 0.1, max_tries=200)
        if not poses:
            return None
        x, y, yaw = poses[0]
        if kind == "person":
            return person(x, y, yaw, height=float(rng.uniform(1.6, 1.9)))
        if kind == "pallet":
            return pallet(x, y, yaw, stack=int(rng.integers(1, 6)))
        return shelving(x, y, yaw, rng=rng)
    if kind == "door":
        if not openings:
            return None
        o = openings[int(rng.integers(len(openings)))]
        return door_leaf(o, float(rng.uniform(0.0, 120.0)), hinge=("start", "end")[int(rng.integers(2))])
    if not walls:
        return None
    plane = walls[int(rng.integers(len(walls)))]
    f = wall_frame(plane)
    # Only a wall's room side takes boards and panels (not the outside of the building).
    if not in_free_space(plane_map, f.point(0.5 * f.length, 0.4)[:2]):
        return None
    if kind == "boards":
        width = min(1.25, f.length - 0.2)
        return leaning_boards(plane, float(rng.uniform(width / 2, f.length - width / 2)), rng,
                              count=int(rng.integers(1, 6)), width=width, angle_deg=float(rng.uniform(4.0, 12.0)))
    return parallel_panel(plane, float(rng.uniform(0.05, 0.3)), float(rng.uniform(0.3, 0.7)), rng,
                          height=float(rng.uniform(1.2, 2.6)))
