"""Plane maps from IFC building models: every use of ifcopenshell lives here.

The import runs on a workstation (optional extra ``bim``); the robot only loads the YAML it writes.
For one storey it takes the walls and columns that stand on that storey or rise into it from below,
meshes them with openings cut (ifcopenshell.geom, world coordinates in metres), moves them into the
storey's frame (floor at z = 0) and hands the meshes to :mod:`robot.maps.wall_faces`, which picks the
faces a depth camera can use. Failures a user can cause (missing extra, unreadable file, unknown
schema or storey) raise ConfigError with one line naming the problem.
"""

from __future__ import annotations

import faulthandler
import hashlib
import logging
import math
import os
import re
import signal
import time
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from robot.base.errors import ConfigError
from robot.base.files import IFC, check_regular_file, open_regular_file
from robot.base.geometry import invert_transform, transform_points
from robot.config.ranges import excerpt
from robot.maps.plane_map import MapPlane, PlaneMap, make_plane

if TYPE_CHECKING:  # needs shapely, which comes with the bim extra: imported where used
    from robot.maps import wall_faces

log = logging.getLogger(__name__)

BIM_HINT = "IFC import needs the optional extra: pip install .[bim]"
DEFAULT_TYPES = ("IfcWall", "IfcColumn")  # IfcWall includes IfcWallStandardCase and other subtypes
OCCLUDER_TYPES = ("IfcSlab", "IfcCovering", "IfcBeam")  # flat elements that hide wall parts
STOREY_TOL = 0.05  # m: storeys closer than this in elevation count as the same level
ENCLOSED_DEPTH = 0.6  # m: a face that sees the back of another face this close faces a closed pocket


def _require_ifcopenshell():
    try:
        import ifcopenshell
        import ifcopenshell.geom
        import ifcopenshell.util.element
        import ifcopenshell.util.placement
        import ifcopenshell.util.unit
        import shapely  # noqa: F401  (robot.maps.wall_faces needs it; it comes with ifcopenshell)
    except ImportError:
        raise ConfigError(BIM_HINT) from None
    return ifcopenshell


@dataclass(frozen=True)
class StoreyInfo:
    name: str
    guid: str
    elevation: float  # m, world z of the storey's placement
    height: Optional[float]  # m up to the next storey; None for the top one
    elements: int  # walls and columns contained in it


@dataclass(frozen=True)
class ImportOptions:
    min_width: float = 0.5  # m: narrower faces are wall ends or reveals
    min_area: float = 0.5  # m^2
    openings: bool = True  # cut doors and windows out of the walls (a camera sees the holes)
    types: Tuple[str, ...] = DEFAULT_TYPES
    threads: int = 2
    clip_to_storey: bool = True  # cut faces at the next storey's floor (the ceiling hides the rest)


@dataclass
class ImportResult:
    plane_map: PlaneMap
    storey: StoreyInfo
    T_storey_world: np.ndarray
    window: Tuple[float, float]  # z range kept, storey frame
    report: Dict[str, Any]
    warnings: List[str] = field(default_factory=list)

    def header(self, note: str = "") -> str:
        """The comment block written at the top of the map file."""
        r = self.report
        c = r["counts"]
        lines = [
            f"Imported by `robotctl map import-ifc` from {r['model']['file']} (sha256 {r['model']['sha256'][:16]}...),",
            f"schema {r['model']['schema']}, length unit {r['model']['length_unit_m']:g} m, "
            f"authoring tool: {(r['model']['application'] or 'unknown').rstrip('.')}.",
            f"Storey '{self.storey.name}' ({self.storey.guid}), elevation {self.storey.elevation:.3f} m: "
            f"{r['transform']['description']}.",
            f"Faces clipped to z in [{self.window[0]:.3f}, {self.window[1]:.3f}] m "
            f"(camera band {r['band'][0]:.3f}..{r['band'][1]:.3f} m"
            + (f", storey height {self.storey.height:.3f} m)." if self.storey.height else ")."),
            f"Kept vertical faces at least {r['options']['min_width']} m wide and {r['options']['min_area']} m^2; "
            f"openings {'cut' if r['options']['openings'] else 'filled'}.",
            f"{c['elements']} elements ({c['no_body']} without a body), {c['vertical_faces']} vertical faces, "
            f"dropped: {c['hidden']} hidden, {c['outside_window']} outside the window, "
            f"{c['narrow']} narrow, {c['small']} small, {c['enclosed']} facing a closed pocket; {c['merged']} merged; "
            f"{c['planes']} planes, {c['polygons']} polygons.",
        ]
        if note:
            lines.extend(note.splitlines())
        return "\n".join(lines)


def _schema_in_header(path: Path) -> str:
    try:
        with open(path, "rb") as f:
            head = f.read(65536).decode("latin-1")
    except OSError:
        return ""
    m = re.search(r"FILE_SCHEMA\s*\(\s*\(\s*'([^']*)'", head, re.IGNORECASE)
    return m.group(1) if m else ""


_SPF_START = b"ISO-10303-21;"
_SPF_END = b"END-ISO-10303-21;"


def _check_complete(p: Path) -> None:
    """ConfigError for a text (SPF) IFC file cut short: ifcopenshell reads what is there without a word."""
    with open_regular_file(p, IFC) as f:
        head = f.read(64)
        size = f.seek(0, 2)
        f.seek(max(0, size - 4096))
        tail = f.read()
    if not head.lstrip(b"\xef\xbb\xbf \t\r\n").startswith(_SPF_START):
        return  # not the text format (ifcZIP, ifcXML): ifcopenshell judges it
    tail = re.sub(rb"/\*.*?\*/", b"", tail, flags=re.DOTALL).rstrip()
    if not tail.endswith(_SPF_END):
        raise ConfigError(f"{p}: the IFC file is cut short: it does not end with {_SPF_END.decode()} "
                          f"(an interrupted copy or download?)")


PARSE_TIMEOUT = 120.0  # s: the three shared building models parse in a quarter of a second


def _parse_in_child(ifcopenshell, p: Path) -> str:
    """How ifcopenshell's parser fails on ``p`` in a forked child ("" if it does not): a damaged
    file can crash that C++ code (found by the long fuzz run: a segmentation fault), which would
    take the whole process with it instead of giving one error. The parse is deterministic, so
    a file the child survives is opened in this process. A quarter of a second on a building
    model; without fork (not Linux) the file is opened as it is."""
    if not hasattr(os, "fork"):
        return ""
    with warnings.catch_warnings():  # Python 3.12 warns about forking a threaded process; the child only parses
        warnings.simplefilter("ignore", DeprecationWarning)
        pid = os.fork()
    if pid == 0:  # the child: parse, report by exit status only
        faulthandler.disable()  # a crash here is reported by the parent, in one line, not as a stack dump
        code = 0
        try:
            ifcopenshell.open(str(p))
        except BaseException:
            code = 1  # an exception: this process reports it itself
        os._exit(code)
    deadline = time.monotonic() + PARSE_TIMEOUT
    while True:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            break
        if time.monotonic() > deadline:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            return f"ran for more than {PARSE_TIMEOUT:.0f} s"
        time.sleep(0.002)
    if os.WIFSIGNALED(status):
        sig = os.WTERMSIG(status)
        try:
            name = signal.Signals(sig).name
        except ValueError:
            name = f"signal {sig}"
        return f"crashed ({name})"
    return ""


def open_model(path):
    """Open an IFC file; ConfigError for a missing extra, a missing, truncated or not regular file,
    or an unreadable schema."""
    ifcopenshell = _require_ifcopenshell()
    p = Path(path)
    check_regular_file(p, IFC)
    _check_complete(p)
    crash = _parse_in_child(ifcopenshell, p)
    if crash:
        raise ConfigError(f"{p}: not a readable IFC file: ifcopenshell's parser {crash} on it (the file is damaged)")
    try:
        model = ifcopenshell.open(str(p))
    except Exception as e:  # ifcopenshell raises SchemaError, Error or RuntimeError by version
        schema = _schema_in_header(p)
        # A mangled header's "schema" can hold line breaks or a megabyte: errors stay one short line.
        shown = schema if len(schema) <= 40 and schema.isprintable() else excerpt(schema, 40)
        if isinstance(e, getattr(ifcopenshell, "SchemaError", ())) or "schema" in str(e).lower():
            raise ConfigError(
                f"{p}: IFC schema {shown or '?'} is not supported by ifcopenshell {ifcopenshell.version} "
                f"(it reads {', '.join(_supported_schemas())})"
            ) from None
        why = " ".join(str(e).split())
        raise ConfigError(f"{p}: not a readable IFC file: {why if len(why) <= 200 else why[:197] + '...'}") from None
    return model


def _supported_schemas() -> List[str]:
    try:
        from ifcopenshell import ifcopenshell_wrapper

        return [s for s in ifcopenshell_wrapper.schema_names() if s.upper().startswith("IFC")]
    except Exception:
        return ["IFC2X3", "IFC4", "IFC4X3"]


def _unit_scale(model) -> float:
    import ifcopenshell.util.unit

    return float(ifcopenshell.util.unit.calculate_unit_scale(model))


def _placement(product, scale: float) -> np.ndarray:
    """World transform of a product's placement, translation in metres."""
    import ifcopenshell.util.placement

    if getattr(product, "ObjectPlacement", None) is None:
        return np.eye(4)
    M = np.array(ifcopenshell.util.placement.get_local_placement(product.ObjectPlacement), dtype=float)
    M[:3, 3] *= scale
    return M


def _storey_of(element):
    import ifcopenshell.util.element as ue

    storey = ue.get_container(element, ifc_class="IfcBuildingStorey")
    if storey is None:
        parent = ue.get_aggregate(element)  # a part of an assembly inherits the assembly's storey
        if parent is not None:
            storey = ue.get_container(parent, ifc_class="IfcBuildingStorey")
    return storey


def _elements(model, types: Sequence[str]) -> List[Any]:
    out, seen = [], set()
    for t in types:
        try:
            items = model.by_type(t)
        except RuntimeError:  # a class this schema lacks (IfcWallStandardCase in IFC4X3)
            continue
        for e in items:
            if e.id() not in seen:
                seen.add(e.id())
                out.append(e)
    return out


def _storey_label(s) -> str:
    return s.Name if s.Name else f"<unnamed {s.GlobalId}>"


def list_storeys(model, types: Sequence[str] = DEFAULT_TYPES) -> List[StoreyInfo]:
    """The model's storeys, lowest first, with elevations in metres."""
    scale = _unit_scale(model)
    raw = []
    for s in model.by_type("IfcBuildingStorey"):
        if s.ObjectPlacement is not None:
            elev = float(_placement(s, scale)[2, 3])
        elif s.Elevation is not None:
            elev = float(s.Elevation) * scale
        else:
            elev = 0.0
        raw.append((elev, s))
    raw.sort(key=lambda x: x[0])
    counts: Dict[int, int] = {}
    for e in _elements(model, types):
        st = _storey_of(e)
        if st is not None:
            counts[st.id()] = counts.get(st.id(), 0) + 1
    out = []
    for elev, s in raw:
        above = [e for e, _ in raw if e > elev + STOREY_TOL]
        out.append(StoreyInfo(_storey_label(s), s.GlobalId, elev, (min(above) - elev) if above else None,
                              counts.get(s.id(), 0)))
    return out


def _find_storey(model, wanted: str, where: str):
    storeys = model.by_type("IfcBuildingStorey")
    hits = [s for s in storeys if wanted in (s.GlobalId, _storey_label(s))]
    if not hits:
        hits = [s for s in storeys if (s.Name or "").strip().lower() == wanted.strip().lower()]
    if len(hits) == 1:
        return hits[0]
    names = ", ".join(repr(_storey_label(s)) for s in storeys) or "none"
    if not hits:
        raise ConfigError(f"{where}: no storey named {wanted!r} (storeys: {names})")
    raise ConfigError(f"{where}: {len(hits)} storeys are named {wanted!r}: give its GlobalId instead "
                      f"({', '.join(s.GlobalId for s in hits)})")


def _geom_settings(openings: bool):
    import ifcopenshell.geom

    s = ifcopenshell.geom.settings()
    s.set("use-world-coords", True)  # output in metres whatever the file's unit
    if not openings:
        s.set("disable-opening-subtractions", True)
    return s


def _meshes(model, elements, openings: bool, threads: int) -> Dict[int, Tuple[np.ndarray, np.ndarray]]:
    """Triangle meshes by element id, world coordinates in metres; elements without a body are absent."""
    import ifcopenshell.geom

    if not elements:
        return {}
    it = ifcopenshell.geom.iterator(_geom_settings(openings), model, max(1, threads), include=elements)
    out: Dict[int, Tuple[np.ndarray, np.ndarray]] = {}
    if not it.initialize():
        return out
    while True:
        shape = it.get()
        g = shape.geometry
        # Copy now: the iterator may reuse these buffers once it moves on (seen with 0.8.5).
        if hasattr(g, "verts_buffer"):
            v = np.frombuffer(g.verts_buffer, "d").reshape(-1, 3).copy()
            f = np.frombuffer(g.faces_buffer, "i").reshape(-1, 3).copy()
        else:  # ifcopenshell 0.7
            v = np.asarray(g.verts, dtype=float).reshape(-1, 3).copy()
            f = np.asarray(g.faces, dtype=int).reshape(-1, 3).copy()
        # Keep only the vertices the triangles use (0.8.5 returns unused ones, e.g. at the origin).
        used, f = np.unique(f, return_inverse=True)
        out[int(shape.id)] = (v[used], f.reshape(-1, 3))
        if not it.next():
            break
    return out


def _application(model) -> str:
    """The authoring tool, from IfcApplication (the STEP header's fields are used inconsistently)."""
    apps = []
    for a in model.by_type("IfcApplication"):
        name = (a.ApplicationFullName or "").strip()
        version = (a.Version or "").strip()
        label = name if not version or version in name else f"{name} {version}"
        if label and label not in apps:
            apps.append(label)
    if apps:
        return ", ".join(apps)
    try:
        return str(model.header.file_name.originating_system or "")
    except Exception:  # a header ifcopenshell could not parse
        return ""


def _file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _describe_transform(T: np.ndarray) -> str:
    yaw = math.degrees(math.atan2(T[1, 0], T[0, 0]))
    t = T[:3, 3]
    if np.allclose(T[:3, :3], np.eye(3), atol=1e-9):
        if np.allclose(t, 0.0, atol=1e-9):
            return "map = world (the storey's placement is the world origin)"
        if np.allclose(t[:2], 0.0, atol=1e-9):
            return f"map = world shifted by z {t[2]:+.3f} m (storey floor at z = 0)"
        return f"map = world translated by ({t[0]:+.3f}, {t[1]:+.3f}, {t[2]:+.3f}) m"
    return f"map = world rotated by {yaw:+.2f} deg about z, then translated by ({t[0]:+.3f}, {t[1]:+.3f}, {t[2]:+.3f}) m"


def _plane_id(k: int) -> str:
    return f"w{k:03d}"


def _drop_enclosed(planes: List[MapPlane], depth: float) -> Tuple[List[MapPlane], int]:
    """Drop polygons that look at the back of another face within ``depth``; renumber the planes.

    Face winding comes from closed solids, so such a polygon is not flipped. It faces a pocket
    inside the construction (a shaft between walls), whose closing face was too narrow to keep.
    No camera can see into the pocket, and the map check would rightly reject the polygon.
    """
    from robot.maps.tools import back_face_hits

    dropped = 0
    for _ in range(3):
        hits = back_face_hits(PlaneMap(planes), depth) if planes else []
        if not hits:
            break
        bad = {(h.plane, h.polygon) for h in hits}
        dropped += len(bad)
        kept = []
        for i, mp in enumerate(planes):
            polys = [poly for k, poly in enumerate(mp.polygons) if (i, k) not in bad]
            if polys:
                kept.append(make_plane(mp.id, polys, mp.source))
        planes = kept
    planes = [make_plane(_plane_id(k), mp.polygons, mp.source) for k, mp in enumerate(planes)]
    return planes, dropped


@dataclass(frozen=True)
class _Site:
    """The storey being imported: its entity, its place among the storeys and its frame."""

    target: Any  # the IfcBuildingStorey
    info: StoreyInfo
    storeys: List[StoreyInfo]  # all of the model's, lowest first
    scale: float  # metres per model length unit
    T_storey_world: np.ndarray


@dataclass
class _StoreyElements:
    """The elements that make the storey's map, meshed and moved into the storey frame."""

    walls: List[Any]  # walls and columns of the storey and those rising into it from below
    meshes: List[wall_faces.ElementMesh]  # of the walls that have a body, in the order of ``walls``
    no_body: List[Any]  # walls without a body
    no_body_below: int  # elements of the storeys below without a body (so not known to rise into it)
    occluders: List[wall_faces.Occluder]  # flat elements that hide parts of the walls


class _Stopwatch:
    """Seconds spent in each stage of the import, for the report."""

    def __init__(self) -> None:
        self._start = self._last = time.perf_counter()
        self._laps: Dict[str, float] = {}

    def lap(self, stage: str) -> None:
        now = time.perf_counter()
        self._laps[stage] = round(now - self._last, 3)
        self._last = now

    def seconds(self) -> Dict[str, float]:
        return {**self._laps, "total": round(self._last - self._start, 3)}


def _locate_storey(model, wanted: str, where: str, types: Sequence[str]) -> _Site:
    scale = _unit_scale(model)
    target = _find_storey(model, wanted, where)
    storeys = list_storeys(model, types)
    info = next(s for s in storeys if s.guid == target.GlobalId)
    return _Site(target, info, storeys, scale, invert_transform(_placement(target, scale)))


def _height_window(band: Tuple[float, float], info: StoreyInfo, options: ImportOptions) -> Tuple[float, float]:
    """The z range to keep, storey frame: the camera band above the floor, cut at the next storey's."""
    z_hi = band[1]
    if options.clip_to_storey and info.height is not None:
        z_hi = min(z_hi, info.height)
    window = (max(0.0, band[0]), z_hi)
    if window[1] <= window[0]:
        raise ConfigError(f"camera band {band[0]:.2f}..{band[1]:.2f} m leaves no height to keep on storey "
                          f"{info.name!r}")
    return window


def _wall_elements(model, site: _Site, options: ImportOptions) -> Tuple[List[Any], int]:
    """Walls of the storey, and those of the storeys below that rise into it; also the number of
    those below that have no body. A quick mesh without openings tells how high they reach."""
    top = site.info.elevation + STOREY_TOL
    here, below = [], []
    for e in _elements(model, options.types):
        st = _storey_of(e)
        if st is None or st.id() == site.target.id():
            here.append(e)
        elif float(_placement(st, site.scale)[2, 3]) <= top:
            below.append(e)
    rough = _meshes(model, below, openings=False, threads=options.threads)
    rising = [e for e in below if e.id() in rough and rough[e.id()][0][:, 2].max() > top]
    return here + rising, sum(1 for e in below if e.id() not in rough)


def _occluder_elements(model, site: _Site) -> List[Any]:
    """Flat elements of this storey and the next one up (whose floor slab is this storey's ceiling)."""
    next_up = [s for s in site.storeys if s.elevation > site.info.elevation + STOREY_TOL][:1]
    wanted = {site.target.GlobalId} | {s.guid for s in next_up}
    out = []
    for e in _elements(model, OCCLUDER_TYPES):
        st = _storey_of(e)
        if st is None or st.GlobalId in wanted:
            out.append(e)
    return out


def _wall_meshes(walls: List[Any], meshes_by_id: Dict[int, Tuple[np.ndarray, np.ndarray]],
                 T_storey_world: np.ndarray) -> Tuple[List[wall_faces.ElementMesh], List[Any]]:
    """The meshes of the walls that have a body, in the storey frame; the walls that have none."""
    from robot.maps import wall_faces

    meshes, no_body = [], []
    for e in walls:
        if e.id() not in meshes_by_id:
            no_body.append(e)
            continue
        v, tri = meshes_by_id[e.id()]
        st = _storey_of(e)
        meshes.append(wall_faces.ElementMesh(e.GlobalId, e.is_a(), e.Name or "", _storey_label(st) if st else "",
                                             transform_points(T_storey_world, v), tri))
    return meshes, no_body


def _occluders(flats: List[Any], meshes_by_id: Dict[int, Tuple[np.ndarray, np.ndarray]],
               T_storey_world: np.ndarray) -> List[wall_faces.Occluder]:
    """Occluders, in the storey frame, of the flat elements that have a body and are flat indeed."""
    from robot.maps import wall_faces

    out = []
    for e in flats:
        if e.id() in meshes_by_id:
            v, tri = meshes_by_id[e.id()]
            occ = wall_faces.occluder_from_mesh(e.GlobalId, transform_points(T_storey_world, v), tri)
            if occ is not None:
                out.append(occ)
    return out


def _storey_elements(model, site: _Site, options: ImportOptions) -> _StoreyElements:
    """Mesh the walls that reach into the storey (openings cut) and the flat elements that hide
    parts of them, and move them into the storey frame."""
    walls, no_body_below = _wall_elements(model, site, options)
    flats = _occluder_elements(model, site)
    meshes_by_id = _meshes(model, walls + flats, options.openings, options.threads)
    meshes, no_body = _wall_meshes(walls, meshes_by_id, site.T_storey_world)
    return _StoreyElements(walls, meshes, no_body, no_body_below, _occluders(flats, meshes_by_id, site.T_storey_world))


def _map_planes(planes, meshes) -> Tuple[List[MapPlane], int]:
    """MapPlanes with their IFC source, in a stable order (by first contributing element in file
    order, then direction and offset); also how many failed validation."""
    planes = sorted(planes, key=lambda wp: (wp.elements[0], round(float(np.arctan2(wp.normal[1], wp.normal[0])), 3),
                                            wp.d))
    out, invalid = [], 0
    for wp in planes:
        src = [meshes[i] for i in wp.elements]
        source = {"ifc_guid": [m.guid for m in src], "ifc_type": sorted({m.ifc_type for m in src}),
                  "name": [m.name for m in src], "storey": src[0].storey}
        try:
            out.append(make_plane(_plane_id(len(out)), wp.polygons, source))
        except ValueError as e:  # a face the cutting mangled: report it, keep the rest of the map
            log.warning("dropped a face of %s: %s", source["ifc_guid"][0], e)
            invalid += 1
    return out, invalid


def _usable_planes(elements: _StoreyElements, window: Tuple[float, float], eye_z: float,
                   options: ImportOptions) -> Tuple[List[MapPlane], wall_faces.FaceStats, int]:
    """The map planes of the faces a camera can use within the window, without the polygons that
    face a closed pocket; the face counts, and the number of polygons dropped for a pocket."""
    from robot.maps import wall_faces

    fopts = wall_faces.FaceOptions(z_lo=window[0], z_hi=window[1], min_width=options.min_width,
                                   min_area=options.min_area, eye_z=eye_z)
    planes, stats = wall_faces.wall_planes(elements.meshes, fopts, elements.occluders)
    map_planes, stats.invalid = _map_planes(planes, elements.meshes)
    map_planes, enclosed = _drop_enclosed(map_planes, ENCLOSED_DEPTH)
    return map_planes, stats, enclosed


def _no_body_warning(no_body: List[Any]) -> str:
    listed = ", ".join(f"{e.is_a()} {e.Name or ''!r} ({e.GlobalId})" for e in no_body[:20])
    more = f" and {len(no_body) - 20} more" if len(no_body) > 20 else ""
    hint = ""
    if any(getattr(e, "IsDecomposedBy", None) for e in no_body):
        hint = ("; some are decomposed into parts: add the parts' class to the types "
                "(--types IfcWall,IfcColumn,IfcBuildingElementPart)")
    return f"skipped {len(no_body)} element(s) with no solid body: {listed}{more}{hint}"


def _warnings(elements: _StoreyElements, stats: wall_faces.FaceStats) -> List[str]:
    """What the user should know the map may lack: walls without a body, faces left unchecked."""
    warnings = []
    if elements.no_body:
        warnings.append(_no_body_warning(elements.no_body))
    if stats.non_closed_elements:
        names = ", ".join(elements.meshes[i].guid for i in stats.non_closed_elements[:10])
        warnings.append(f"{len(stats.non_closed_elements)} element mesh(es) are not closed, "
                        f"so their face orientation is unchecked: {names}")
    return warnings


def _counts(elements: _StoreyElements, stats: wall_faces.FaceStats, enclosed: int,
            map_planes: List[MapPlane]) -> Dict[str, int]:
    counts = dict(elements=len(elements.walls), occluders=len(elements.occluders), no_body=len(elements.no_body),
                  no_body_below=elements.no_body_below, **stats.as_dict())
    counts.update(enclosed=enclosed, planes=len(map_planes), polygons=sum(len(mp.polygons) for mp in map_planes))
    return counts


def _report(p: Path, model, site: _Site, band: Tuple[float, float], eye_z: float, window: Tuple[float, float],
            options: ImportOptions, counts: Dict[str, int], warnings: List[str],
            seconds: Dict[str, float]) -> Dict[str, Any]:
    """How the map was made: model, storey and frame, what was asked and what came of it."""
    return {
        "model": {
            "file": p.name,
            "sha256": _file_sha256(p),
            "schema": getattr(model, "schema_identifier", model.schema),
            "length_unit_m": site.scale,
            "application": _application(model),
        },
        "storey": asdict(site.info),
        "transform": {"T_storey_world": np.round(site.T_storey_world, 9).tolist(),
                      "description": _describe_transform(site.T_storey_world)},
        "band": [float(band[0]), float(band[1])],
        "eye_z": float(eye_z),
        "window": [float(window[0]), float(window[1])],
        "options": {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(options).items()},
        "counts": counts,
        "warnings": warnings,
        "seconds": seconds,
        "ifcopenshell": _require_ifcopenshell().version,
    }


def import_storey(path, storey: str, band: Tuple[float, float], eye_z: float = 0.5,
                  options: ImportOptions = ImportOptions()) -> ImportResult:
    """Import the usable wall planes of one storey, in the storey's frame.

    ``band`` is the (z_lo, z_hi) the cameras see above the floor and ``eye_z`` their height (see
    :func:`robot.maps.tools.camera_height_band`); faces are clipped to the band and to the storey
    height, and cut where a slab, ceiling or beam meets them (above it when it is above the cameras).
    """
    p = Path(path)
    clock = _Stopwatch()
    # Open the model; find the storey, its height and its frame.
    model = open_model(p)
    clock.lap("open")
    site = _locate_storey(model, storey, str(p), options.types)
    # The heights to keep: the camera band, cut at the next storey's floor.
    window = _height_window(band, site.info, options)
    # Mesh the walls that reach into the storey and the flat elements that hide parts of them.
    elements = _storey_elements(model, site, options)
    clock.lap("geometry")
    # Keep the wall faces a camera can use, as map planes.
    map_planes, stats, enclosed = _usable_planes(elements, window, eye_z, options)
    if not map_planes:
        raise ConfigError(f"{p}: storey {site.info.name!r} has no usable wall faces "
                          f"({len(elements.walls)} elements, {len(elements.no_body)} without a body)")
    clock.lap("faces")
    # Say what the map may lack, and record how it was made.
    warnings = _warnings(elements, stats)
    report = _report(p, model, site, band, eye_z, window, options, _counts(elements, stats, enclosed, map_planes),
                     warnings, clock.seconds())
    plane_map = PlaneMap(map_planes, source=f"{p.name}:{site.info.name}")
    return ImportResult(plane_map, site.info, site.T_storey_world, window, report, warnings)
