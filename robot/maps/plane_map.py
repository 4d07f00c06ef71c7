"""The plane map (DESIGN.md section 3): bounded planar polygons in the ground frame.

YAML: ``planes: [{id, vertices: [[x, y, z], ...]}]``, vertices counter-clockwise seen from the
observable side, so the right-hand normal points at the observer. A plane may instead carry
``polygons: [[[x, y, z], ...], ...]`` (one wall face split by a door) and an optional
``source: {...}`` (IFC GlobalId, element type, storey). Single-polygon maps stay valid.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, List, Sequence, Tuple

import numpy as np

from robot.base.errors import ConfigError
from robot.base.geometry import newell_normal
from robot.config.schema import Section, check_number, load_yaml_file

PLANARITY_TOLERANCE = 0.001  # m: the bound on a vertex's distance from its plane
MIN_POLYGON_AREA = 1e-6  # m^2: below this the normal is numerically meaningless


@dataclass(frozen=True)
class MapPlane:
    id: str
    normal: np.ndarray  # n_G, unit, towards the observable side
    d: float  # n_G . p + d = 0
    polygons: Tuple[np.ndarray, ...]  # each (K, 3), counter-clockwise seen from the normal side
    source: Dict[str, Any] = field(default_factory=dict)

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

    def __post_init__(self):
        self._index = {p.id: i for i, p in enumerate(self.planes)}

    def __len__(self) -> int:
        return len(self.planes)

    def __getitem__(self, plane_id: str) -> MapPlane:
        return self.planes[self._index[plane_id]]

    def index_of(self, plane_id: str) -> int:
        return self._index[plane_id]

    @property
    def plane_array(self) -> np.ndarray:
        """(N, 4) planes (n, d) in G, in map order."""
        return np.array([p.pi for p in self.planes]).reshape(-1, 4)

    def bounds(self) -> Tuple[np.ndarray, np.ndarray]:
        v = np.vstack([p.vertices for p in self.planes])
        return v.min(axis=0), v.max(axis=0)

    def to_yaml_data(self) -> Dict[str, Any]:
        out = []
        for p in self.planes:
            item: Dict[str, Any] = {"id": p.id}
            polys = [[[round(float(c), 6) for c in v] for v in poly] for poly in p.polygons]
            if len(polys) == 1:
                item["vertices"] = polys[0]
            else:
                item["polygons"] = polys
            if p.source:
                item["source"] = dict(p.source)
            out.append(item)
        return {"planes": out}


def make_plane(plane_id: str, polygons: Sequence[Sequence[Sequence[float]]], source=None,
               where: str = "") -> MapPlane:
    """Validate polygons and build a plane; raises ValueError naming the problem."""
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
    return MapPlane(plane_id, n, d, tuple(polys), dict(source or {}))


def parse_plane_map(data: Any, source: str = "<map>") -> PlaneMap:
    top = Section(data, "", source)
    raw = top.raw("planes")
    top.done()
    if not isinstance(raw, list) or not raw:
        top.fail("'planes' must be a non-empty list")
    planes: List[MapPlane] = []
    seen = set()
    for i, item in enumerate(raw):
        sec = Section(item, f"planes[{i}]", source)
        pid = sec.raw("id")
        if not isinstance(pid, (str, int)) or isinstance(pid, bool) or str(pid) == "":
            sec.fail(f"'id' must be a non-empty string, got {pid!r}")
        pid = str(pid)
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
        for k, poly in enumerate(polygons):
            if not isinstance(poly, list) or not all(isinstance(v, list) and len(v) == 3 for v in poly):
                sec.fail(f"polygon {k} must be a list of [x, y, z] vertices")
            for v in poly:
                for c in v:
                    check_number(c, "vertex coordinate", sec)
        src = sec.raw("source", {})
        if not isinstance(src, dict):
            sec.fail("'source' must be a mapping")
        sec.done()
        try:
            planes.append(make_plane(pid, polygons, src))
        except ValueError as e:
            raise ConfigError(f"{source}: {e}") from None
    return PlaneMap(planes, source=source)


def load_plane_map(path) -> PlaneMap:
    return parse_plane_map(load_yaml_file(path), source=str(path))


def save_plane_map(plane_map: PlaneMap, path, header: str = "") -> None:
    import yaml

    text = yaml.safe_dump(plane_map.to_yaml_data(), sort_keys=False, default_flow_style=None)
    with open(path, "w", encoding="utf-8") as f:
        if header:
            f.write("".join(f"# {line}\n" for line in header.splitlines()))
        f.write(text)
