"""The plane map: bounded planar polygons in the ground frame (docs/architecture.md, 'Frames and units').

YAML: ``planes: [{id, vertices: [[x, y, z], ...]}]``, vertices counter-clockwise seen from the
observable side, so the right-hand normal points at the observer. A plane may instead carry
``polygons: [[[x, y, z], ...], ...]`` (one wall face split by a door) and an optional
``source: {...}`` (IFC GlobalId, element type, storey). Single-polygon maps stay valid.

Each plane has an as-built ``tolerance`` (m): one standard deviation of how far the built
surface may lie from the drawn plane (plaster and drywall layers, walls set out a little off,
bows). A plane's own ``tolerance:`` wins; else the map's top-level ``tolerance:``; else one
from the IFC element type in its ``source`` (:func:`tolerance_for_source`); else
``DEFAULT_TOLERANCE``. The localizer counts it as an error of every measurement of that plane
that more pixels cannot average away.

A plane marked ``built: false`` is in the building model but not on the site yet (a site builds
its partitions late): it is kept in ``PlaneMap.not_built`` and saved again, but left out of
``planes``, so that nothing predicts it. A wall the map predicts where the cameras see through
makes every localization there ``inconsistent``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from robot.base.errors import ConfigError
from robot.base.files import MAP
from robot.base.geometry import newell_normal
from robot.config.ranges import Range, excerpt
from robot.config.schema import Section, load_yaml_file

PLANARITY_TOLERANCE = 0.001  # m: how far a vertex may lie from its plane
MIN_POLYGON_AREA = 1e-6  # m^2: below this the normal is numerically meaningless
# Bounds of a map file: a site is under 2 km across (larger coordinates are unit mistakes, and
# squared in the geometry they overflow); an imported campus storey has a few thousand planes.
COORDINATE_RANGE = Range(-1000.0, 1000.0, "m")
MAX_PLANES = 100_000
MAX_POLYGONS_PER_PLANE = 1000
MAX_VERTICES_PER_POLYGON = 10_000
MAX_ID_CHARS = 200
DEFAULT_TOLERANCE = 0.01  # m, 1 sigma: a wall on a site within about +-2 cm of the drawing
TOLERANCE_RANGE = Range(0.0, 1.0, "m")
# 1 sigma by IFC element type: a curtain wall is set out to a few millimetres, a plastered wall to
# about a centimetre, slabs and stairs to more; furniture and proxies are wherever they were put.
IFC_TYPE_TOLERANCE = {
    "IfcCurtainWall": 0.005, "IfcColumn": 0.008, "IfcWall": 0.01, "IfcWallStandardCase": 0.01,
    "IfcWallElementedCase": 0.01, "IfcCovering": 0.01, "IfcPlate": 0.01, "IfcMember": 0.01,
    "IfcSlab": 0.015, "IfcRoof": 0.015, "IfcDoor": 0.02, "IfcWindow": 0.02, "IfcStair": 0.02,
    "IfcStairFlight": 0.02, "IfcRamp": 0.02, "IfcRailing": 0.02, "IfcBuildingElementProxy": 0.03,
    "IfcFurnishingElement": 0.05,
}


@dataclass(frozen=True)
class MapPlane:
    id: str
    normal: np.ndarray  # n_G, unit, towards the observable side
    d: float  # n_G . p + d = 0
    polygons: Tuple[np.ndarray, ...]  # each (K, 3), counter-clockwise seen from the normal side
    source: Dict[str, Any] = field(default_factory=dict)
    tolerance: float = DEFAULT_TOLERANCE  # m, 1 sigma of the built surface from this plane, along its normal

    @property
    def pi(self) -> np.ndarray:
        return np.array([*self.normal, self.d])

    @property
    def vertices(self) -> np.ndarray:
        return np.vstack(self.polygons)

    @property
    def area(self) -> float:
        return float(sum(0.5 * np.linalg.norm(newell_normal(p)) for p in self.polygons))


@dataclass
class PlaneMap:
    planes: List[MapPlane]
    source: str = "<map>"
    # In the building model, marked ``built: false``: not predicted anywhere (see the module note).
    not_built: List[MapPlane] = field(default_factory=list)

    def __post_init__(self):
        self._index = {p.id: i for i, p in enumerate(self.planes)}

    def __len__(self) -> int:
        return len(self.planes)

    def __getitem__(self, plane_id: str) -> MapPlane:
        return self.planes[self._index[plane_id]]

    @property
    def plane_array(self) -> np.ndarray:
        """(N, 4) planes (n, d) in G, in map order."""
        return np.array([p.pi for p in self.planes]).reshape(-1, 4)

    def bounds(self) -> Tuple[np.ndarray, np.ndarray]:
        v = np.vstack([p.vertices for p in self.planes])
        return v.min(axis=0), v.max(axis=0)

    def to_yaml_data(self) -> Dict[str, Any]:
        out = []
        unbuilt = {p.id for p in self.not_built}
        for p in self.planes + self.not_built:
            item: Dict[str, Any] = {"id": p.id}
            polys = [[[round(float(c), 6) for c in v] for v in poly] for poly in p.polygons]
            if len(polys) == 1:
                item["vertices"] = polys[0]
            else:
                item["polygons"] = polys
            if p.source:
                item["source"] = dict(p.source)
            if p.tolerance != tolerance_for_source(p.source):
                item["tolerance"] = round(float(p.tolerance), 6)
            if p.id in unbuilt:
                item["built"] = False
            out.append(item)
        return {"planes": out}


def tolerance_for_source(source: Any) -> float:
    """The as-built tolerance of a plane imported from these IFC element types (the loosest of
    them), DEFAULT_TOLERANCE when the source names none."""
    types = source.get("ifc_type") if isinstance(source, dict) else None
    if isinstance(types, str):
        types = [types]
    known = [IFC_TYPE_TOLERANCE[t] for t in types or () if isinstance(t, str) and t in IFC_TYPE_TOLERANCE]
    return max(known) if known else DEFAULT_TOLERANCE


def make_plane(plane_id: str, polygons: Sequence[Sequence[Sequence[float]]], source=None,
               where: str = "", tolerance: Optional[float] = None) -> MapPlane:
    """Validate polygons and build a plane; raises ValueError naming the problem. ``tolerance``
    None: from the source's IFC element type (:func:`tolerance_for_source`)."""
    where = where or f"plane '{plane_id}'"
    polys = []
    for k, poly in enumerate(polygons):
        arr = np.asarray(poly, dtype=float)
        if arr.ndim != 2 or arr.shape[1] != 3:
            raise ValueError(f"{where}: polygon {k} must be a list of [x, y, z] vertices")
        if len(arr) < 3:
            raise ValueError(f"{where}: polygon {k} has {len(arr)} vertices, at least 3 are needed")
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{where}: polygon {k} has a non-finite coordinate")
        polys.append(arr)
    if not polys:
        raise ValueError(f"{where}: no polygons")
    n_sum = newell_normal(polys[0])
    area2 = np.linalg.norm(n_sum)
    if area2 < 2 * MIN_POLYGON_AREA:
        raise ValueError(f"{where}: polygon 0 has zero area (collinear or repeated vertices)")
    n = n_sum / area2
    d = float(-n @ polys[0].mean(axis=0))
    for k, arr in enumerate(polys):
        dist = np.abs(arr @ n + d)
        worst = float(dist.max())
        if worst > PLANARITY_TOLERANCE:
            raise ValueError(
                f"{where}: polygon {k} is not planar: vertex {int(dist.argmax())} is {worst * 1000:.1f} mm "
                f"off its plane (tolerance {PLANARITY_TOLERANCE * 1000:.0f} mm)"
            )
        nk = newell_normal(arr)
        if k > 0 and nk @ n <= 0:
            raise ValueError(f"{where}: polygon {k} is listed clockwise relative to polygon 0 (flipped)")
    tol = tolerance_for_source(source) if tolerance is None else float(tolerance)
    if not (np.isfinite(tol) and TOLERANCE_RANGE.lo <= tol <= TOLERANCE_RANGE.hi):
        raise ValueError(f"{where}: tolerance must be in {TOLERANCE_RANGE.describe()}, got {tol}")
    return MapPlane(plane_id, n, d, tuple(polys), dict(source or {}), tol)


def parse_plane_map(data: Any, source: str = "<map>") -> PlaneMap:
    top = Section(data, "", source)
    raw = top.raw("planes")
    map_tolerance = top.ranged("tolerance", TOLERANCE_RANGE, None) if top.has("tolerance") else None
    top.done()
    if not isinstance(raw, list) or not raw:
        top.fail("'planes' must be a non-empty list")
    if len(raw) > MAX_PLANES:
        top.fail(f"'planes' lists {len(raw)} planes, at most {MAX_PLANES} are allowed")
    planes: List[MapPlane] = []
    not_built: List[MapPlane] = []
    seen = set()
    for i, item in enumerate(raw):
        sec = Section(item, f"planes[{i}]", source)
        pid = sec.raw("id")
        if not isinstance(pid, (str, int)) or isinstance(pid, bool) or str(pid) == "":
            sec.fail(f"'id' must be a non-empty string, got {excerpt(pid)}")
        if isinstance(pid, int) and pid.bit_length() > 64:
            sec.fail(f"'id' must be a string of at most {MAX_ID_CHARS} characters")
        pid = str(pid)
        if len(pid) > MAX_ID_CHARS:
            sec.fail(f"'id' must be at most {MAX_ID_CHARS} characters, got {excerpt(pid)}")
        sec.where = f"plane '{pid}'"
        if pid in seen:
            sec.fail("duplicate id")
        seen.add(pid)
        if sec.has("vertices") == sec.has("polygons"):
            sec.fail("give exactly one of 'vertices' or 'polygons'")
        if sec.has("vertices"):
            polygons = [sec.raw("vertices")]
        else:
            polygons = sec.raw("polygons")
            if not isinstance(polygons, list) or not polygons:
                sec.fail("'polygons' must be a non-empty list of polygons")
            if len(polygons) > MAX_POLYGONS_PER_PLANE:
                sec.fail(f"{len(polygons)} polygons, at most {MAX_POLYGONS_PER_PLANE} are allowed per plane")
        for k, poly in enumerate(polygons):
            if not isinstance(poly, list) or not all(isinstance(v, list) and len(v) == 3 for v in poly):
                sec.fail(f"polygon {k} must be a list of [x, y, z] vertices")
            if len(poly) > MAX_VERTICES_PER_POLYGON:
                sec.fail(f"polygon {k} has {len(poly)} vertices, at most {MAX_VERTICES_PER_POLYGON} are allowed")
            for j, v in enumerate(poly):
                for c in v:
                    why = COORDINATE_RANGE.problem(c)
                    if why is not None:
                        sec.fail(f"polygon {k} vertex {j}: a coordinate {why}")
        src = sec.raw("source", {})
        if not isinstance(src, dict):
            sec.fail("'source' must be a mapping")
        tol = sec.ranged("tolerance", TOLERANCE_RANGE) if sec.has("tolerance") else map_tolerance
        built = sec.raw("built", True)
        if not isinstance(built, bool):
            sec.fail(f"'built' must be true or false, got {excerpt(built)}")
        sec.done()
        try:
            (planes if built else not_built).append(make_plane(pid, polygons, src, tolerance=tol))
        except ValueError as e:
            raise ConfigError(f"{source}: {e}") from None
    if not planes:
        top.fail("every plane is marked 'built: false': nothing is left to localize against")
    return PlaneMap(planes, source=source, not_built=not_built)


def load_plane_map(path) -> PlaneMap:
    return parse_plane_map(load_yaml_file(path, MAP), source=str(path))


def save_plane_map(plane_map: PlaneMap, path, header: str = "") -> None:
    import yaml

    text = yaml.safe_dump(plane_map.to_yaml_data(), sort_keys=False, default_flow_style=None)
    with open(path, "w", encoding="utf-8") as f:
        if header:
            f.write("".join(f"# {line}\n" for line in header.splitlines()))
        f.write(text)
