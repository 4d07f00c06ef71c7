"""Plane-map inspection: summary figures, the cameras' height band, and validity checks. Pure numpy.

Checks (``check_map_data``), each an error unless marked as a warning:

- ``invalid``: what loading rejects (structure, fewer than 3 vertices, zero area, a vertex more
  than 1 mm off its plane, polygons of one plane wound against each other). Reported per plane,
  all of them, where loading stops at the first.
- ``duplicate_id``: two planes with the same id.
- ``self_intersection``: a polygon whose edges cross. The ROI rasterizer fills it wrongly.
- ``duplicate``: two planes facing the same way on the same plane (normals within 1 deg, offsets
  within 1 cm) whose polygons overlap. The same wall is in the map twice.
- ``flipped``: a plane whose normal points away from its observable side. Two rules find it:
  1. *Back-face rule* (maps of solid walls, as imported from IFC). A ray from inside each polygon,
     along its normal, must not first hit the back of another polygon within ``max_thickness``.
     A correct face looks into free space. A flipped face looks into its own wall, and the first
     thing it meets is the back of the wall's other face.
  2. *Edge rule* (any map). Where two polygons of different planes share an edge (collinear and
     overlapping), a consistently oriented surface runs along that edge in opposite directions
     from the two sides. This is the winding rule of a closed mesh. It also holds at the corners
     of a room of single thin walls, like the paper's arena, where every normal faces inward.
     Back-to-back pairs (coplanar, opposite normals) are left out. Planes are blamed one at a
     time, each time the one whose disagreeing edges most outnumber its agreeing ones, and its
     edges then count as explained. So the neighbours of a flipped plane are not blamed with
     it. A disagreement left with no majority on either side is a warning (``inconsistent``)
     that names both planes.

A map flipped as a whole (every normal inverted) passes both rules: each face then looks at another
face across the wall's thickness, which is also what two walls a short gap apart look like.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from robot.base.errors import ConfigError
from robot.base.geometry import plane_axes
from robot.maps.plane_map import MapPlane, PlaneMap, parse_plane_map

VERTICAL_SIN = math.sin(math.radians(1.0))


# ----------------------------------------------------------------------------- camera height band

def camera_height_band(cameras: Sequence[Any], min_range: float, max_range: float) -> Tuple[float, float]:
    """(z_lo, z_hi) above the floor that any camera sees at depths min_range..max_range.

    The view frustum between two depths is a convex solid, so its height extremes are at its eight
    corners. The robot stands on a flat floor, so the robot frame's z is the height. z_lo is
    clamped at the floor.
    """
    zs = []
    for cam in cameras:
        T = cam.T_robot_camera
        tx, ty = math.tan(math.radians(cam.hfov_deg) / 2), math.tan(math.radians(cam.vfov_deg) / 2)
        for depth in (min_range, max_range):
            for sx in (-1, 1):
                for sy in (-1, 1):
                    p = T[:3, :3] @ np.array([sx * tx * depth, sy * ty * depth, depth]) + T[:3, 3]
                    zs.append(p[2])
    if not zs:
        raise ConfigError("no cameras to compute a height band from")
    return max(0.0, float(min(zs))), float(max(zs))


def camera_band_from_config(cfg) -> Tuple[float, float, float]:
    """(z_lo, z_hi, eye_z) from a RobotConfig: the band at the localizer's depth range, mean mount height."""
    lo, hi = camera_height_band(cfg.cameras, cfg.localizer.min_range, cfg.localizer.max_range)
    eye = float(np.mean([c.mount_xyz[2] for c in cfg.cameras]))
    return lo, hi, eye


# ----------------------------------------------------------------------------- summary

def _is_vertical(p: MapPlane) -> bool:
    return abs(float(p.normal[2])) < VERTICAL_SIN


def _r3(values) -> List[float]:
    return [round(float(c), 3) + 0.0 for c in values]  # + 0.0 turns -0.0 into 0.0


def map_summary(plane_map: PlaneMap, band: Optional[Tuple[float, float]] = None) -> Dict[str, Any]:
    """Counts, extent and height band of a map; with ``band``, how many planes reach into it."""
    lo, hi = plane_map.bounds()
    areas = np.array([p.area for p in plane_map.planes])
    vertical = sum(1 for p in plane_map.planes if _is_vertical(p))
    horizontal = sum(1 for p in plane_map.planes if abs(float(p.normal[2])) > math.cos(math.radians(1.0)))
    types: Dict[str, int] = {}
    storeys: Dict[str, int] = {}
    for p in plane_map.planes:
        t = p.source.get("ifc_type")
        for name in (t if isinstance(t, list) else [t] if t else []):
            types[str(name)] = types.get(str(name), 0) + 1
        if p.source.get("storey"):
            storeys[str(p.source["storey"])] = storeys.get(str(p.source["storey"]), 0) + 1
    out: Dict[str, Any] = {
        "source": plane_map.source,
        "planes": len(plane_map),
        "polygons": sum(len(p.polygons) for p in plane_map.planes),
        "vertices": sum(len(v) for p in plane_map.planes for v in p.polygons),
        "area_m2": round(float(areas.sum()), 3),
        "plane_area_m2": {"min": round(float(areas.min()), 3), "median": round(float(np.median(areas)), 3),
                          "max": round(float(areas.max()), 3)},
        "extent": {"min": _r3(lo), "max": _r3(hi), "size": _r3(hi - lo)},
        "height_band": _r3([lo[2], hi[2]]),
        "orientation": {"vertical": vertical, "horizontal": horizontal,
                        "sloped": len(plane_map) - vertical - horizontal},
    }
    if types:
        out["ifc_types"] = types
    if storeys:
        out["storeys"] = storeys
    if plane_map.not_built:
        out["not_built"] = [p.id for p in plane_map.not_built]
    if band is not None:
        inside = [p for p in plane_map.planes
                  if p.vertices[:, 2].max() > band[0] and p.vertices[:, 2].min() < band[1]]
        out["camera_band"] = [round(band[0], 3), round(band[1], 3)]
        out["planes_in_camera_band"] = len(inside)
    return out


# ----------------------------------------------------------------------------- checks

@dataclass(frozen=True)
class MapIssue:
    code: str
    severity: str  # "error" or "warning"
    planes: Tuple[str, ...]
    message: str

    def as_dict(self) -> Dict[str, Any]:
        return {"code": self.code, "severity": self.severity, "planes": list(self.planes), "message": self.message}


def _to2d(poly: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.column_stack([poly @ a, poly @ b])


def _inside(pt: np.ndarray, poly2: np.ndarray) -> bool:
    """Even-odd point-in-polygon test in 2D."""
    x, y = pt
    xs, ys = poly2[:, 0], poly2[:, 1]
    xn, yn = np.roll(xs, -1), np.roll(ys, -1)
    crosses = (ys > y) != (yn > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        xi = xs + (y - ys) * (xn - xs) / (yn - ys)
    return bool(np.count_nonzero(crosses & (x < xi)) % 2)


def _interior_point(poly2: np.ndarray) -> Optional[np.ndarray]:
    """A point strictly inside a simple polygon: its centroid, or a fan triangle's centroid."""
    x, y = poly2[:, 0], poly2[:, 1]
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cr = x * yn - xn * y
    A = cr.sum() / 2
    if abs(A) > 1e-12:
        c = np.array([((x + xn) * cr).sum(), ((y + yn) * cr).sum()]) / (6 * A)
        if _inside(c, poly2):
            return c
    for i in range(1, len(poly2) - 1):
        c = (poly2[0] + poly2[i] + poly2[i + 1]) / 3
        if _inside(c, poly2):
            return c
    return None


def _segments_cross(p1, p2, q1, q2) -> bool:
    """Proper crossing of two 2D segments (touching at an end does not count)."""
    def orient(a, b, c):
        return (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])

    d1, d2 = orient(q1, q2, p1), orient(q1, q2, p2)
    d3, d4 = orient(p1, p2, q1), orient(p1, p2, q2)
    eps = 1e-12
    return (d1 * d2 < -eps) and (d3 * d4 < -eps)


def _self_intersects(poly2: np.ndarray) -> bool:
    k = len(poly2)
    for i in range(k):
        for j in range(i + 2, k):
            if i == 0 and j == k - 1:
                continue  # neighbours through the closing edge
            if _segments_cross(poly2[i], poly2[(i + 1) % k], poly2[j], poly2[(j + 1) % k]):
                return True
    return False


@dataclass
class _Poly:
    plane: int
    index: int  # within its plane
    pts: np.ndarray  # (K, 3)
    pts2: np.ndarray  # in the plane's basis
    a: np.ndarray
    b: np.ndarray


def _polys(plane_map: PlaneMap) -> List[_Poly]:
    out = []
    for i, p in enumerate(plane_map.planes):
        a, b = plane_axes(p.normal)
        for k, poly in enumerate(p.polygons):
            out.append(_Poly(i, k, poly, _to2d(poly, a, b), a, b))
    return out


def _overlap_fraction(pa: _Poly, pb: _Poly, samples: int = 12) -> float:
    """Share of a grid over the overlap of two coplanar polygons' boxes that is inside both."""
    q = _to2d(pb.pts, pa.a, pa.b)
    lo = np.maximum(pa.pts2.min(0), q.min(0))
    hi = np.minimum(pa.pts2.max(0), q.max(0))
    if np.any(hi - lo <= 1e-3):
        return 0.0
    g = (np.arange(samples) + 0.5) / samples
    hits = 0
    for gx in g:
        for gy in g:
            pt = lo + (hi - lo) * np.array([gx, gy])
            hits += _inside(pt, pa.pts2) and _inside(pt, q)
    return hits / samples ** 2


def _check_duplicates(pm: PlaneMap, polys: List[_Poly]) -> List[MapIssue]:
    issues = []
    P = pm.plane_array
    same = (P[:, :3] @ P[:, :3].T > math.cos(math.radians(1.0))) & (np.abs(P[:, 3][:, None] - P[:, 3][None, :]) < 0.01)
    lo = np.array([p.pts.min(axis=0) for p in polys]) - 1e-3
    hi = np.array([p.pts.max(axis=0) for p in polys]) + 1e-3
    by_plane: Dict[int, List[int]] = {}
    for k, p in enumerate(polys):
        by_plane.setdefault(p.plane, []).append(k)
    for i, j in zip(*np.nonzero(np.triu(same, 1))):
        a, b = np.array(by_plane[i]), np.array(by_plane[j])
        # Only polygon pairs whose boxes meet can overlap.
        meet = np.all(lo[a][:, None] <= hi[b][None], axis=2) & np.all(lo[b][None] <= hi[a][:, None], axis=2)
        if any(_overlap_fraction(polys[a[x]], polys[b[y]]) > 0.01 for x, y in zip(*np.nonzero(meet))):
            ids = (pm.planes[i].id, pm.planes[j].id)
            issues.append(MapIssue("duplicate", "error", ids,
                                   f"planes '{ids[0]}' and '{ids[1]}' overlap on the same plane"))
    return issues


@dataclass(frozen=True)
class BackHit:
    plane: int  # index of the plane whose polygon looks at a back
    polygon: int  # index of that polygon within its plane
    hit_plane: int  # index of the plane whose back it sees
    distance: float  # m


def back_face_hits(pm: PlaneMap, max_dist: float) -> List[BackHit]:
    """Polygons whose normal ray, from a point inside them, first meets the back of another plane
    within ``max_dist``: the back-face rule of the module doc."""
    polys = _polys(pm)
    P = pm.plane_array
    poly_plane = np.array([p.plane for p in polys])
    out = []
    for src in polys:
        c2 = _interior_point(src.pts2)
        if c2 is None:
            continue
        n = P[src.plane, :3]
        origin = c2[0] * src.a + c2[1] * src.b - P[src.plane, 3] * n
        denom = P[:, :3] @ n  # ray direction . target normal: > 0 means the ray meets a back
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -(P[:, :3] @ origin + P[:, 3]) / denom
        tp = t[poly_plane]
        cand = np.nonzero((poly_plane != src.plane) & (np.abs(denom[poly_plane]) > 1e-6)
                          & (tp > 1e-4) & (tp <= max_dist))[0]
        for k in cand[np.argsort(tp[cand])]:
            dst = polys[k]
            hit = origin + tp[k] * n
            if _inside(np.array([hit @ dst.a, hit @ dst.b]), dst.pts2):
                if denom[dst.plane] > 0:
                    out.append(BackHit(src.plane, src.index, dst.plane, float(tp[k])))
                break
    return out


def _ray_hits(pm: PlaneMap, max_dist: float) -> List[MapIssue]:
    issues: Dict[int, MapIssue] = {}
    for h in back_face_hits(pm, max_dist):
        if h.plane in issues:
            continue
        a, b = pm.planes[h.plane].id, pm.planes[h.hit_plane].id
        issues[h.plane] = MapIssue(
            "flipped", "error", (a,),
            f"plane '{a}' faces into a solid: {h.distance:.2f} m in front of it is the back of plane '{b}' "
            f"(reverse its vertex order)")
    return list(issues.values())


def _shared_edges(pm: PlaneMap, polys: List[_Poly], tol: float = 0.005, min_overlap: float = 0.02,
                  cell: float = 0.5):
    """(plane i, plane j, consistent) for every edge two polygons of different planes share."""
    seg_a, seg_b, plane_of = [], [], []
    for p in polys:
        seg_a.append(p.pts)
        seg_b.append(np.roll(p.pts, -1, axis=0))
        plane_of.extend([p.plane] * len(p.pts))
    A, B = np.vstack(seg_a), np.vstack(seg_b)
    D = B - A
    L = np.linalg.norm(D, axis=1)
    U = D / np.maximum(L, 1e-12)[:, None]
    # Candidate pairs: edges whose floor-plan boxes share a grid cell (a map has thousands of edges).
    lo = np.floor((np.minimum(A, B)[:, :2] - tol) / cell).astype(int)
    hi = np.floor((np.maximum(A, B)[:, :2] + tol) / cell).astype(int)
    cells: Dict[Tuple[int, int], List[int]] = {}
    for e in np.nonzero(L >= min_overlap)[0]:
        for cx in range(lo[e, 0], hi[e, 0] + 1):
            for cy in range(lo[e, 1], hi[e, 1] + 1):
                cells.setdefault((cx, cy), []).append(int(e))
    pairs = set()
    for members in cells.values():
        for k, e in enumerate(members):
            for f in members[k + 1:]:
                if plane_of[e] != plane_of[f]:
                    pairs.add((e, f))
    if not pairs:
        return []
    e, f = np.array(sorted(pairs)).T
    plane = np.asarray(plane_of)
    Ue = U[e]
    parallel = np.abs(np.einsum("ij,ij->i", Ue, U[f])) >= 1 - 1e-6
    # both ends of f on e's line ...
    off_a, off_b = A[f] - A[e], B[f] - A[e]
    sa, sb = np.einsum("ij,ij->i", off_a, Ue), np.einsum("ij,ij->i", off_b, Ue)
    on_line = (np.linalg.norm(off_a - sa[:, None] * Ue, axis=1) <= tol) & \
        (np.linalg.norm(off_b - sb[:, None] * Ue, axis=1) <= tol)
    # ... and overlapping e along it
    overlap = np.minimum(np.maximum(sa, sb), L[e]) - np.maximum(np.minimum(sa, sb), 0.0) >= min_overlap
    P = pm.plane_array
    i, j = plane[e], plane[f]
    # back to back (the two sides of one thin wall) is not a surface running on across the edge
    back_to_back = (np.einsum("ij,ij->i", P[i, :3], P[j, :3]) < -math.cos(math.radians(1.0))) & \
        (np.abs(P[i, 3] + P[j, 3]) < tol)
    keep = parallel & on_line & overlap & ~back_to_back
    consistent = np.einsum("ij,ij->i", Ue, U[f]) < 0
    return [(int(a), int(b), bool(c)) for a, b, c in zip(i[keep], j[keep], consistent[keep])]


def _edge_rule(pm: PlaneMap, polys: List[_Poly], already: set) -> List[MapIssue]:
    """Blame, one at a time, the plane that explains most disagreeing shared edges.

    Greedy, so that a flipped plane's neighbours, whose only disagreement is with it, are not
    blamed as well. Planes the back-face rule flagged (``already``, ids) count as explained first.
    """
    edges = _shared_edges(pm, polys)
    blamed = {k for k, p in enumerate(pm.planes) if p.id in already}
    issues = []
    while True:
        good = np.zeros(len(pm), int)
        bad = np.zeros(len(pm), int)
        for i, j, ok in edges:
            if i in blamed or j in blamed:
                continue
            counts = good if ok else bad
            counts[i] += 1
            counts[j] += 1
        score = np.where(bad > good, bad - good, 0)
        if not score.any():
            break
        k = int(np.lexsort((-bad, -score))[0])  # largest excess of disagreements, then most of them
        blamed.add(k)
        n_bad, n_all = int(bad[k]), int(bad[k] + good[k])
        issues.append(MapIssue(
            "flipped", "error", (pm.planes[k].id,),
            f"plane '{pm.planes[k].id}' is wound against {n_bad} of its {n_all} shared edges "
            f"with neighbouring planes (reverse its vertex order)"))
    pairs = sorted({(min(i, j), max(i, j)) for i, j, ok in edges
                    if not ok and i not in blamed and j not in blamed})
    for i, j in pairs:
        a, b = pm.planes[i].id, pm.planes[j].id
        issues.append(MapIssue("inconsistent", "warning", (a, b),
                               f"planes '{a}' and '{b}' share an edge but are wound the same way along it"))
    return issues


def check_plane_map(pm: PlaneMap, max_thickness: float = 0.6) -> List[MapIssue]:
    """Geometric checks on a loaded map (see the module doc)."""
    polys = _polys(pm)
    issues: List[MapIssue] = []
    for p in polys:
        if _self_intersects(p.pts2):
            pid = pm.planes[p.plane].id
            issues.append(MapIssue("self_intersection", "error", (pid,),
                                   f"plane '{pid}' has a polygon whose edges cross"))
    issues.extend(_check_duplicates(pm, polys))
    flipped = _ray_hits(pm, max_thickness)
    issues.extend(flipped)
    issues.extend(_edge_rule(pm, polys, {i.planes[0] for i in flipped}))
    return issues


def check_map_data(data: Any, source: str = "<map>", max_thickness: float = 0.6
                   ) -> Tuple[List[MapIssue], Optional[PlaneMap]]:
    """Check parsed YAML: every plane on its own, then the valid ones together.

    Returns the issues and the map of the valid planes (None when no plane is valid).
    """
    if not isinstance(data, dict) or not isinstance(data.get("planes"), list) or not data["planes"]:
        parse_plane_map(data, source)  # raises the loader's own message
    issues: List[MapIssue] = []
    valid = []
    not_built = []
    seen: Dict[str, int] = {}
    for k, item in enumerate(data["planes"]):
        pid = str(item.get("id")) if isinstance(item, dict) else f"planes[{k}]"
        # A plane not built yet is checked on its own as any other, and kept out of the checks
        # of the planes together (nothing predicts it).
        unbuilt = isinstance(item, dict) and item.get("built") is False
        try:
            plane = parse_plane_map({"planes": [dict(item, built=True) if unbuilt else item]}, source).planes[0]
        except ConfigError as e:
            msg = str(e)
            if msg.startswith(source + ": "):
                msg = msg[len(source) + 2:]
            issues.append(MapIssue("invalid", "error", (pid,), msg))
            continue
        if plane.id in seen:
            issues.append(MapIssue("duplicate_id", "error", (plane.id,),
                                   f"id '{plane.id}' is used by planes[{seen[plane.id]}] and planes[{k}]"))
            continue
        seen[plane.id] = k
        (not_built if unbuilt else valid).append(plane)
    if not valid:
        return issues, None
    pm = PlaneMap(valid, source=source, not_built=not_built)
    issues.extend(check_plane_map(pm, max_thickness))
    return issues, pm
