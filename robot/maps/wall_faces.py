"""Usable wall faces from element meshes: the geometry half of the IFC import (no ifcopenshell here).

Steps, for the elements of one storey already in the map frame (floor at z = 0):

1. Group each element's vertical triangles into planes; the union of a plane's triangles gives
   its faces, with the openings as holes or notches.
2. Remove the parts of faces nobody can see: pressed against a face of another element (a wall
   end against the side of the wall it joins, furring against the wall it lines), or behind a
   flat horizontal element the face runs into (a ceiling, a floor slab, a beam): above a ceiling
   that meets the face the wall is hidden all the way up, below a floor finish all the way down.
3. Clip faces to the height window the cameras see (below the ceiling, above the floor).
4. Merge coplanar, same-facing faces of different elements that touch (a wall built in segments).
5. Drop faces (connected regions) narrower than ``min_width`` or smaller than ``min_area``: wall
   ends and the reveals of doors and windows, which a depth camera cannot fit a plane to reliably.
6. Cut each kept face with holes into simple polygons without holes, by vertical cuts through
   each hole's left and right ends: a window leaves pieces left of, below, above and right of
   it. A door leaves a notch, so the face stays one (U-shaped) polygon unless the door reaches
   the top of the face and splits it in two. The renderer fills concave simple polygons.

A face is worked on in 2D coordinates of its plane: ``s`` along ``r = z x n`` (to the right of a
viewer facing the face) and ``t`` along ``u = n x r`` (up). A polygon counter-clockwise in (s, t) is
counter-clockwise seen from the normal side, which is the map's convention (docs/architecture.md, 'Frames and units').
Triangles must be counter-clockwise seen from outside the solid, so normals point at the free side.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Dict, List, Sequence, Tuple

import numpy as np
import shapely
from shapely.geometry import Polygon, box
from shapely.geometry.polygon import orient

from robot.base.geometry import plane_axes

GRID = 1e-4  # m: snapping grid for the 2D unions; far below any tolerance that matters
SIMPLIFY = 0.002  # m: outline vertices closer than this to the line of their neighbours are dropped


@dataclass(frozen=True)
class ElementMesh:
    """One building element's closed triangle mesh in the map frame (metres)."""

    guid: str
    ifc_type: str
    name: str
    storey: str
    vertices: np.ndarray  # (V, 3)
    triangles: np.ndarray  # (T, 3) vertex indices, counter-clockwise seen from outside


@dataclass(frozen=True)
class Occluder:
    """A flat horizontal element (slab, ceiling, beam): its footprint hides the faces it meets."""

    guid: str
    footprint: object  # shapely (Multi)Polygon in map x, y
    z_lo: float
    z_hi: float


@dataclass(frozen=True)
class FaceOptions:
    z_lo: float = 0.0  # m: height window kept (map frame); parts outside are cut off
    z_hi: float = 3.0
    min_width: float = 0.5  # m: horizontal extent a face needs (drops wall ends and reveals)
    min_area: float = 0.5  # m^2, after clipping to the window
    vertical_tol_deg: float = 1.0  # a face is vertical if its normal is this close to horizontal
    coplanar_tol: float = 0.003  # m: vertices this close to a plane lie on it
    contact_tol: float = 0.01  # m: opposite faces this close touch (hidden from both sides)
    merge_gap: float = 0.01  # m: coplanar faces of two elements this close are merged
    min_piece: float = 0.02  # m: pieces thinner than this after cutting are slivers and dropped
    eye_z: float = 0.5  # m: camera height; occluders above it hide upwards, below it downwards
    probe: float = 0.02  # m: how far in front of a face an occluder must reach to hide it


@dataclass
class WallPlane:
    normal: np.ndarray  # unit, towards the free side
    d: float  # normal . p + d = 0
    polygons: List[np.ndarray]  # simple polygons (K, 3), counter-clockwise seen from the normal side
    elements: List[int]  # indices into the element list, in order of contributed area


@dataclass
class FaceStats:
    """Counts of faces (connected planar regions of one element's surface) at each step."""

    vertical_faces: int = 0
    hidden: int = 0  # fully covered by another element
    outside_window: int = 0  # nothing left inside the height window
    merged: int = 0  # faces merged into a touching coplanar face of another element
    narrow: int = 0  # narrower than min_width
    small: int = 0  # wide enough but smaller than min_area
    kept_faces: int = 0
    invalid: int = 0  # faces the cutting mangled (none seen in the sample models)
    planes: int = 0
    polygons: int = 0
    non_closed_elements: List[int] = field(default_factory=list)

    def as_dict(self) -> Dict[str, int]:
        out = {k: v for k, v in self.__dict__.items() if k != "non_closed_elements"}
        out["non_closed_elements"] = len(self.non_closed_elements)
        return out


@dataclass
class _Face:
    normal: np.ndarray
    d: float
    r: np.ndarray  # in-plane horizontal axis
    u: np.ndarray  # in-plane "up" axis
    shape: object  # shapely (Multi)Polygon in (s, t)
    element: int  # the element it belongs to (the largest one, once merged)
    area: float = 0.0
    elements: List[int] = field(default_factory=list)  # all contributing elements, largest first

    def lift(self, st: np.ndarray) -> np.ndarray:
        return st[:, :1] * self.r + st[:, 1:2] * self.u - self.d * self.normal

    def project(self, p: np.ndarray) -> np.ndarray:
        return np.column_stack([p @ self.r, p @ self.u])


def _face_frame(n: np.ndarray, d: float, shape, element: int) -> _Face:
    r, u = plane_axes(n)
    return _Face(n, d, r, u, shape, element, float(shape.area), [element])


def _transfer(shape, src: _Face, dst: _Face):
    """A shape in src's plane coordinates, expressed in dst's (points projected onto dst)."""
    return shapely.transform(shape, lambda st: dst.project(src.lift(st)))


def _components(shape) -> List[Polygon]:
    if shape.is_empty:
        return []
    if isinstance(shape, Polygon):
        return [shape]
    return [g for g in getattr(shape, "geoms", []) if isinstance(g, Polygon) and not g.is_empty]


def _signed_volume(v: np.ndarray, tri: np.ndarray) -> float:
    a, b, c = v[tri[:, 0]], v[tri[:, 1]], v[tri[:, 2]]
    return float(np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0)


def _element_faces(mesh: ElementMesh, index: int, opts: FaceOptions) -> Tuple[List[_Face], bool]:
    """Vertical planes of one element with their 2D regions; also whether the mesh was closed."""
    v = np.asarray(mesh.vertices, dtype=float)
    tri = np.asarray(mesh.triangles, dtype=int).reshape(-1, 3)
    if len(tri) == 0:
        return [], False
    # An inside-out mesh would put every normal into the solid: turn it round.
    vol = _signed_volume(v, tri)
    closed = abs(vol) > 1e-9
    if vol < 0:
        tri = tri[:, ::-1]
    a, b, c = v[tri[:, 0]], v[tri[:, 1]], v[tri[:, 2]]
    cross = np.cross(b - a, c - a)
    norm = np.linalg.norm(cross, axis=1)
    keep = norm > 1e-10
    n = cross[keep] / norm[keep, None]
    a, b, c, area = a[keep], b[keep], c[keep], norm[keep] / 2
    vertical = np.abs(n[:, 2]) < math.sin(math.radians(opts.vertical_tol_deg))
    cos_same = math.cos(math.radians(0.2))
    # Greedy clustering, largest triangles first so each plane is defined by its best triangle.
    clusters: List[List] = []  # [normal, d, [triangle indices]]
    for i in np.nonzero(vertical)[0][np.argsort(-area[vertical])]:
        tri_pts = np.stack([a[i], b[i], c[i]])
        for cl in clusters:
            if cl[0] @ n[i] > cos_same and np.abs(tri_pts @ cl[0] + cl[1]).max() < opts.coplanar_tol:
                cl[2].append(i)
                break
        else:
            clusters.append([n[i], float(-n[i] @ tri_pts.mean(axis=0)), [i]])
    faces = []
    for normal, d, idx in clusters:
        frame = _face_frame(normal, d, Polygon(), index)
        pts = np.stack([a[idx], b[idx], c[idx]], axis=1)  # (k, 3, 3)
        st = frame.project(pts.reshape(-1, 3)).reshape(-1, 3, 2)
        shape = shapely.union_all(shapely.polygons(st), grid_size=GRID)
        if shape.is_empty:
            continue
        faces.append(_face_frame(normal, d, shape, index))
    return faces, closed


def _pairs(faces: Sequence[_Face], same_direction: bool, tol: float) -> List[Tuple[int, int]]:
    """Index pairs (i < j) of faces of different elements on one plane, facing alike or opposite."""
    if len(faces) < 2:
        return []
    N = np.array([f.normal for f in faces])
    D = np.array([f.d for f in faces])
    E = np.array([f.element for f in faces])
    dots = N @ N.T
    cos_tol = math.cos(math.radians(0.5))
    if same_direction:
        mask = (dots > cos_tol) & (np.abs(D[:, None] - D[None, :]) < tol)
    else:
        mask = (dots < -cos_tol) & (np.abs(D[:, None] + D[None, :]) < tol)
    mask &= E[:, None] != E[None, :]
    i, j = np.nonzero(np.triu(mask, 1))
    return list(zip(i.tolist(), j.tolist()))


def _remove_contacts(faces: List[_Face], tol: float) -> None:
    """Cut from each face the parts pressed against an opposite face of another element."""
    covers: Dict[int, List] = {}
    for i, j in _pairs(faces, same_direction=False, tol=tol):
        covers.setdefault(i, []).append(_transfer(faces[j].shape, faces[j], faces[i]))
        covers.setdefault(j, []).append(_transfer(faces[i].shape, faces[i], faces[j]))
    for i, shapes in covers.items():
        f = faces[i]
        f.shape = shapely.difference(f.shape, shapely.union_all(shapes, grid_size=GRID), grid_size=GRID)


def occluder_from_mesh(guid: str, vertices: np.ndarray, triangles: np.ndarray,
                       max_thickness: float = 0.6):
    """An Occluder from a flat element's mesh, or None when the element is not flat (a roof, a ramp)."""
    v = np.asarray(vertices, dtype=float)
    tri = np.asarray(triangles, dtype=int).reshape(-1, 3)
    if len(tri) == 0 or np.ptp(v[:, 2]) > max_thickness:
        return None
    a, b, c = v[tri[:, 0]], v[tri[:, 1]], v[tri[:, 2]]
    cross = np.cross(b - a, c - a)
    norm = np.linalg.norm(cross, axis=1)
    flat = np.abs(cross[:, 2]) > 0.1 * np.maximum(norm, 1e-12)
    if not flat.any():
        return None
    xy = np.stack([a[flat], b[flat], c[flat]], axis=1)[:, :, :2]
    footprint = shapely.union_all(shapely.polygons(xy), grid_size=1e-3)
    if footprint.is_empty:
        return None
    return Occluder(guid, footprint, float(v[:, 2].min()), float(v[:, 2].max()))


def _remove_occluded(faces: List[_Face], occluders: Sequence[Occluder], opts: FaceOptions) -> None:
    """Cut from each face the heights hidden by flat elements that reach in front of it."""
    big = 1e3
    for f in faces:
        if f.shape.is_empty:
            continue
        s0, _, s1, _ = f.shape.bounds
        ends = np.array([[s0, 0.0], [s1, 0.0]])
        front = f.lift(ends) + opts.probe * f.normal
        line = shapely.LineString(front[:, :2])
        hidden = []
        for occ in occluders:
            if not line.intersects(occ.footprint):
                continue
            if occ.z_lo >= opts.eye_z:
                z0, z1 = occ.z_lo, big
            elif occ.z_hi <= opts.eye_z:
                z0, z1 = -big, occ.z_hi
            else:
                z0, z1 = occ.z_lo, occ.z_hi
            t0 = (z0 + f.d * f.normal[2]) / f.u[2]
            t1 = (z1 + f.d * f.normal[2]) / f.u[2]
            for seg in _lines(line.intersection(occ.footprint)):
                s = np.asarray(seg.coords)[:, :2] @ f.r[:2]
                if s.max() - s.min() > GRID:
                    hidden.append(box(s.min(), t0, s.max(), t1))
        if hidden:
            f.shape = shapely.difference(f.shape, shapely.union_all(hidden), grid_size=GRID)


def _lines(geom) -> List:
    if geom.is_empty:
        return []
    if geom.geom_type == "LineString":
        return [geom]
    return [g for g in getattr(geom, "geoms", []) if g.geom_type == "LineString"]


def _clip_to_window(f: _Face, z_lo: float, z_hi: float):
    # z = t * u_z - d * n_z on the plane; u_z > 0 for a near-vertical face.
    t_lo = (z_lo + f.d * f.normal[2]) / f.u[2]
    t_hi = (z_hi + f.d * f.normal[2]) / f.u[2]
    x0, _, x1, _ = f.shape.bounds
    return shapely.intersection(f.shape, box(x0 - 1.0, t_lo, x1 + 1.0, t_hi), grid_size=GRID)


class _UnionFind:
    def __init__(self, n: int):
        self.parent = list(range(n))

    def find(self, i: int) -> int:
        while self.parent[i] != i:
            self.parent[i] = self.parent[self.parent[i]]
            i = self.parent[i]
        return i

    def union(self, i: int, j: int) -> None:
        self.parent[self.find(i)] = self.find(j)


def _merge_touching(faces: List[_Face], opts: FaceOptions) -> Tuple[List[_Face], int]:
    """Merge same-facing coplanar faces of different elements that touch; returns (faces, merged)."""
    uf = _UnionFind(len(faces))
    for i, j in _pairs(faces, same_direction=True, tol=opts.coplanar_tol):
        other = _transfer(faces[j].shape, faces[j], faces[i])
        if shapely.distance(faces[i].shape, other) <= opts.merge_gap:
            uf.union(i, j)
    groups: Dict[int, List[int]] = {}
    for i in range(len(faces)):
        groups.setdefault(uf.find(i), []).append(i)
    out = []
    merged = 0
    for members in groups.values():
        members.sort(key=lambda k: -faces[k].area)
        ref = faces[members[0]]
        if len(members) == 1:
            out.append(ref)
            continue
        merged += len(members) - 1
        shapes = [ref.shape] + [_transfer(faces[k].shape, faces[k], ref) for k in members[1:]]
        g = opts.merge_gap / 2 + GRID
        # Closing (grow, union, shrink) fuses the hairline gaps left between touching elements.
        grown = [s.buffer(g, join_style="mitre") for s in shapes]
        shape = shapely.union_all(grown).buffer(-g, join_style="mitre")
        shape = shapely.set_precision(shape, GRID)
        face = _face_frame(ref.normal, ref.d, shape, ref.element)
        face.elements = [faces[k].element for k in members]
        out.append(face)
    return out, merged


def _cut_positions(poly: Polygon, min_piece: float) -> List[float]:
    """s of the vertical cuts through the left and right ends of each hole (merged when close)."""
    cuts = []
    for ring in poly.interiors:
        s = np.asarray(ring.coords)[:, 0]
        cuts.extend([float(s.min()), float(s.max())])
    cuts.sort()
    merged: List[float] = []
    for c in cuts:
        if not merged or c - merged[-1] > min_piece:
            merged.append(c)
    return merged


def _is_sliver(p: Polygon, min_piece: float) -> bool:
    x0, y0, x1, y1 = p.bounds
    return x1 - x0 < min_piece or y1 - y0 < min_piece or p.area < min_piece * min_piece


def simple_pieces(poly: Polygon, min_piece: float = 0.02, depth: int = 0) -> List[Polygon]:
    """Split a polygon (maybe with holes) into simple polygons without holes by vertical cuts."""
    if depth == 0:
        poly = poly.simplify(SIMPLIFY, preserve_topology=True)
    cuts = _cut_positions(poly, min_piece)
    x0, y0, x1, y1 = poly.bounds
    edges = [x0] + [c for c in cuts if x0 + min_piece < c < x1 - min_piece] + [x1]
    pieces: List[Polygon] = []
    for s0, s1 in zip(edges[:-1], edges[1:]):
        part = shapely.intersection(poly, box(s0, y0 - 1.0, s1, y1 + 1.0), grid_size=GRID)
        for p in _components(part):
            if _is_sliver(p, min_piece):
                continue
            if p.interiors and depth < 4:
                # A hole touching a cut only at a point: split once more through its middle.
                mid = p.interiors[0].centroid.x
                halves = [box(p.bounds[0], y0 - 1, mid, y1 + 1), box(mid, y0 - 1, p.bounds[2], y1 + 1)]
                for h in halves:
                    for q in _components(shapely.intersection(p, h, grid_size=GRID)):
                        pieces.extend(simple_pieces(q, min_piece, depth + 1))
            elif not p.interiors:
                pieces.append(p)
    return pieces


def _ring_3d(face: _Face, piece: Polygon) -> np.ndarray:
    piece = orient(piece.simplify(GRID, preserve_topology=True), 1.0)
    st = np.asarray(piece.exterior.coords)[:-1]
    return np.round(face.lift(st), 6) + 0.0  # micrometre grid, as the map file stores; no -0.0


def wall_planes(meshes: Sequence[ElementMesh], opts: FaceOptions,
                occluders: Sequence[Occluder] = ()) -> Tuple[List[WallPlane], FaceStats]:
    """The usable wall planes of a set of element meshes (see the module doc for the steps)."""
    stats = FaceStats()
    faces: List[_Face] = []
    for k, mesh in enumerate(meshes):
        fs, closed = _element_faces(mesh, k, opts)
        if not closed:
            stats.non_closed_elements.append(k)
        faces.extend(fs)
    stats.vertical_faces = sum(len(_components(f.shape)) for f in faces)

    before = [len(_components(f.shape)) for f in faces]
    _remove_contacts(faces, opts.contact_tol)
    _remove_occluded(faces, occluders, opts)
    visible = []
    for f, n_before in zip(faces, before):
        if f.shape.is_empty or f.shape.area < opts.min_piece ** 2:
            stats.hidden += n_before
            continue
        clipped = _clip_to_window(f, opts.z_lo, opts.z_hi)
        n_after = len([p for p in _components(clipped) if not _is_sliver(p, opts.min_piece)])
        if n_after == 0:
            stats.outside_window += len(_components(f.shape))
            continue
        f.shape = clipped
        f.area = float(clipped.area)
        visible.append(f)

    merged_faces, stats.merged = _merge_touching(visible, opts)

    planes: List[WallPlane] = []
    for f in merged_faces:
        kept = []
        for comp in _components(f.shape):
            x0, _, x1, _ = comp.bounds
            if _is_sliver(comp, opts.min_piece):
                continue
            if x1 - x0 < opts.min_width:
                stats.narrow += 1
            elif comp.area < opts.min_area:
                stats.small += 1
            else:
                kept.append(comp)
        if not kept:
            continue
        stats.kept_faces += len(kept)
        polys = [_ring_3d(f, p) for comp in kept for p in simple_pieces(comp, opts.min_piece)]
        if not polys:
            continue
        planes.append(WallPlane(np.asarray(f.normal, dtype=float), float(f.d), polys, list(f.elements)))
    stats.planes = len(planes)
    stats.polygons = sum(len(p.polygons) for p in planes)
    return planes, stats
