"""IFC import (robot.maps.ifc_import, robot.maps.wall_faces) on the shared real models and on small IFC files
written here (millimetre units, openings, a wall without a body, an unsupported schema).

The real models are read from ../shared/data/ifc/ (see tests/data/README.md for their sources and
attribution); tests that need one skip with a reason when it is absent. Each import takes about a
second, so imports are cached for the session.
"""

from __future__ import annotations

import importlib.util
import io
import json
import subprocess
import sys
from contextlib import redirect_stdout
from pathlib import Path

import numpy as np
import pytest

from robot.base.errors import ConfigError
from robot.config import load_robot_config
from robot.maps import ifc_import
from robot.maps.ifc_import import ImportOptions, import_storey, list_storeys, open_model
from robot.maps.plane_map import load_plane_map
from robot.maps.tools import camera_band_from_config, check_plane_map

ROOT = Path(__file__).resolve().parents[1]
IFC_DIR = ROOT.parent / "shared" / "data" / "ifc"
FZK = "AC20-FZK-Haus.ifc"
DUPLEX = "Duplex_A_20110907.ifc"
INSTITUTE = "AC11-Institute-Var-2-IFC.ifc"

BAND = camera_band_from_config(load_robot_config(ROOT / "config" / "robot.yaml"))


def test_missing_extra_is_a_clear_error(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "ifcopenshell", None)  # import ifcopenshell -> ImportError
    with pytest.raises(ConfigError, match=r"IFC import needs the optional extra: pip install \.\[bim\]"):
        ifc_import.open_model(tmp_path / "x.ifc")


needs_ifc = pytest.mark.skipif(importlib.util.find_spec("ifcopenshell") is None,
                               reason="IFC import needs the optional extra [bim] (ifcopenshell)")

_CACHE = {}


def model(name: str) -> Path:
    p = IFC_DIR / name
    if not p.is_file():
        pytest.skip(f"shared IFC model {p} is not present (see tests/data/README.md)")
    return p


def imported(name: str, storey: str, openings: bool = True):
    key = (name, storey, openings)
    if key not in _CACHE:
        _CACHE[key] = import_storey(model(name), storey, BAND[:2], BAND[2], ImportOptions(openings=openings))
    return _CACHE[key]


def planes_facing(pm, direction):
    d = np.asarray(direction, float)
    return [p for p in pm.planes if p.normal @ d > 0.999]


def offsets(pm, direction):
    """Positions along ``direction`` of the planes facing that way (n . p + d = 0  =>  p . n = -d)."""
    return sorted(round(-p.d, 3) for p in planes_facing(pm, direction))


def one_plane(pm, direction, position):
    found = [p for p in planes_facing(pm, direction) if abs(-p.d - position) < 1e-6]
    assert len(found) == 1, f"{len(found)} planes facing {direction} at {position}"
    return found[0]


def covers(plane, point) -> bool:
    """Whether any polygon of a vertical plane contains a point of that plane."""
    n = plane.normal
    r = np.cross([0.0, 0.0, 1.0], n)
    for poly in plane.polygons:
        q = np.column_stack([poly @ r, poly[:, 2]])
        x, y = point @ r, point[2]
        xs, ys = q[:, 0], q[:, 1]
        xn, yn = np.roll(xs, -1), np.roll(ys, -1)
        crossing = (ys > y) != (yn > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            xi = xs + (y - ys) * (xn - xs) / (yn - ys)
        if np.count_nonzero(crossing & (x < xi)) % 2:
            return True
    return False


# ---------------------------------------------------------------------------- the shared models

@needs_ifc
def test_storeys_of_the_shared_models():
    fzk = list_storeys(open_model(model(FZK)))
    assert [(s.name, s.elevation, s.height) for s in fzk] == [("Erdgeschoss", 0.0, pytest.approx(2.7)),
                                                             ("Dachgeschoss", pytest.approx(2.7), None)]
    assert sum(s.elements for s in fzk) == 13
    duplex = list_storeys(open_model(model(DUPLEX)))
    assert [s.name for s in duplex] == ["T/FDN", "Level 1", "Level 2", "Roof"]
    assert [round(s.elevation, 3) for s in duplex] == [-1.25, 0.0, 3.1, 6.0]
    assert sum(s.elements for s in duplex) == 57
    institute = list_storeys(open_model(model(INSTITUTE)))
    assert [round(s.elevation, 3) for s in institute] == [-3.0, 0.0, 3.0, 6.0, 9.0]
    assert sum(s.elements for s in institute) == 119 + 2  # walls and two columns


@needs_ifc
def test_fzk_haus_ground_floor_walls():
    r = imported(FZK, "Erdgeschoss")
    pm = r.plane_map
    assert r.report["counts"]["elements"] == 9 and r.report["counts"]["no_body"] == 0
    assert len(pm) == 18  # each of the 9 walls shows both sides; ends and reveals are dropped
    # The 12 m x 10 m outline with 0.30 m exterior walls; normals point at the free side.
    xs = {(round(-p.d * p.normal[0], 3), round(p.normal[0])) for p in pm.planes if abs(p.normal[0]) > 0.999}
    ys = {(round(-p.d * p.normal[1], 3), round(p.normal[1])) for p in pm.planes if abs(p.normal[1]) > 0.999}
    assert {(0.0, -1), (0.3, 1), (11.7, -1), (12.0, 1)} <= xs
    assert {(0.0, -1), (0.3, 1), (9.7, -1), (10.0, 1)} <= ys
    x_out = [p for p in pm.planes if p.normal @ [-1, 0, 0] > 0.999 and abs(p.d) < 1e-6][0]
    x_far = [p for p in pm.planes if p.normal @ [1, 0, 0] > 0.999 and abs(p.d + 12.0) < 1e-6][0]
    assert x_out.source["name"] == ["Wand-Ext-ERDG-1"] and x_far.source["storey"] == "Erdgeschoss"
    lo, hi = pm.bounds()
    assert lo == pytest.approx([0, 0, 0]) and hi == pytest.approx([12, 10, 2.7])
    assert all(abs(p.normal[2]) < 1e-9 for p in pm.planes)
    assert r.T_storey_world == pytest.approx(np.eye(4))
    assert [i for i in check_plane_map(pm) if i.severity == "error"] == []


@needs_ifc
def test_fzk_haus_openings_are_cut_from_the_outer_wall():
    pm = imported(FZK, "Erdgeschoss").plane_map
    face = [p for p in pm.planes if p.normal @ [-1, 0, 0] > 0.999 and abs(p.d) < 1e-6][0]  # x = 0, outside
    # Expected: the 10 m x 2.7 m face minus the door and windows that void this wall in the model.
    import ifcopenshell.geom

    f = open_model(model(FZK))
    s = ifcopenshell.geom.settings()
    s.set("use-world-coords", True)
    wall = [w for w in f.by_type("IfcWall") if w.Name == "Wand-Ext-ERDG-1"][0]
    holes = []
    for rel in wall.HasOpenings:
        shape = ifcopenshell.geom.create_shape(s, rel.RelatedOpeningElement)  # keep it alive while read
        tri = np.frombuffer(shape.geometry.faces_buffer, "i").copy()
        v = np.frombuffer(shape.geometry.verts_buffer, "d").reshape(-1, 3)[np.unique(tri)]  # vertices in use
        y0, y1 = max(v[:, 1].min(), 0.0), min(v[:, 1].max(), 10.0)
        z0, z1 = max(v[:, 2].min(), 0.0), min(v[:, 2].max(), 2.7)
        holes.append(((y0 + y1) / 2, (z0 + z1) / 2, (y1 - y0) * (z1 - z0)))
    assert len(holes) == 3  # the front door and two windows
    assert face.area == pytest.approx(10 * 2.7 - sum(h[2] for h in holes), abs=1e-3)
    for y, z, _ in holes:
        assert not covers(face, np.array([0.0, y, z]))
    assert covers(face, np.array([0.0, 0.5, 1.0]))
    assert len(face.polygons) > 1  # windows are holes: the face is cut into simple polygons

    filled = imported(FZK, "Erdgeschoss", openings=False).plane_map
    solid = [p for p in filled.planes if p.normal @ [-1, 0, 0] > 0.999 and abs(p.d) < 1e-6][0]
    assert solid.area == pytest.approx(27.0, abs=1e-3) and len(solid.polygons) == 1


@needs_ifc
def test_duplex_level1_walls_taller_than_the_storey_are_clipped():
    r = imported(DUPLEX, "Level 1")
    pm = r.plane_map
    assert r.storey.height == pytest.approx(3.1)
    lo, hi = pm.bounds()
    assert lo[:2] == pytest.approx([0.0, -17.8], abs=1e-3) and hi[:2] == pytest.approx([8.8, 0.0], abs=1e-3)
    # The exterior walls run from 0 to 6.0 m in the model; the ceiling of Level 1 is at 3.1 m.
    exterior = [p for p in pm.planes if any("Exterior" in n for n in p.source["name"])]
    assert exterior and max(p.vertices[:, 2].max() for p in exterior) == pytest.approx(3.1)
    # The outer faces of the 8.8 m x 17.8 m outline, each merged across the wall segments it spans.
    outer_west = one_plane(pm, [-1, 0, 0], 0.0)
    assert outer_west.vertices[:, 1].min() == pytest.approx(-17.8, abs=1e-3)
    assert outer_west.vertices[:, 1].max() == pytest.approx(0.0, abs=1e-3)
    assert len(outer_west.source["ifc_guid"]) >= 2
    assert r.report["counts"]["elements"] >= 21  # the storey's 21 walls, plus any rising from below
    assert [i for i in check_plane_map(pm) if i.severity == "error"] == []


@needs_ifc
def test_institute_ground_floor():
    r = imported(INSTITUTE, "Erdgeschoss")
    pm = r.plane_map
    lo, hi = pm.bounds()
    assert lo == pytest.approx([0, 0, 0], abs=1e-3) and hi[:2] == pytest.approx([42.0, 16.0], abs=1e-3)
    assert hi[2] <= r.window[1] + 1e-9
    c = r.report["counts"]
    assert c["narrow"] > 50  # wall ends and window reveals
    assert len(pm) > 40 and c["polygons"] > 2 * len(pm)  # many windows cut the faces into pieces
    assert {p.source["storey"] for p in pm.planes} <= {"Erdgeschoss", "Keller"}
    assert [i for i in check_plane_map(pm) if i.severity == "error"] == []


# ---------------------------------------------------------------------------- small files written here

class _Step:
    """STEP entity lines, numbered in order of addition."""

    def __init__(self):
        self.lines = []

    def add(self, text: str) -> str:
        self.lines.append(text)
        return f"#{len(self.lines)}"

    def point(self, *c) -> str:
        return self.add(f"IFCCARTESIANPOINT(({','.join(f'{float(v):.1f}' for v in c)}))")


def ifc_text(walls=(), openings=(), axis_only=(), storey_mm=3000.0, schema="IFC4") -> str:
    """An IFC4 model in millimetres: one storey at ``storey_mm``; box walls (name, x0, y0, x1, y1,
    height); box openings (wall name, x0, y0, z0, x1, y1, z1); walls with only an axis (name, x0, y0,
    x1, y1)."""
    s = _Step()
    ids = iter(f"1AbCdEfGhIjKlMnOpQr{k:03d}" for k in range(1000))
    z, x = s.add("IFCDIRECTION((0.,0.,1.))"), s.add("IFCDIRECTION((1.,0.,0.))")
    world = s.add(f"IFCAXIS2PLACEMENT3D({s.point(0, 0, 0)},{z},{x})")
    ctx = s.add(f"IFCGEOMETRICREPRESENTATIONCONTEXT($,'Model',3,1.0E-05,{world},$)")
    body = s.add(f"IFCGEOMETRICREPRESENTATIONSUBCONTEXT('Body','Model',*,*,*,*,{ctx},$,.MODEL_VIEW.,$)")
    units = s.add(f"IFCUNITASSIGNMENT(({s.add('IFCSIUNIT(*,.LENGTHUNIT.,.MILLI.,.METRE.)')}))")
    project = s.add(f"IFCPROJECT('{next(ids)}',$,'mm test',$,$,$,$,({ctx}),{units})")
    site_pl = s.add(f"IFCLOCALPLACEMENT($,{world})")
    site = s.add(f"IFCSITE('{next(ids)}',$,'Site',$,$,{site_pl},$,$,.ELEMENT.,$,$,$,$,$)")
    bldg_pl = s.add(f"IFCLOCALPLACEMENT({site_pl},{world})")
    bldg = s.add(f"IFCBUILDING('{next(ids)}',$,'Building',$,$,{bldg_pl},$,$,.ELEMENT.,$,$,$)")
    st_pl = s.add(f"IFCLOCALPLACEMENT({bldg_pl},"
                  f"{s.add(f'IFCAXIS2PLACEMENT3D({s.point(0, 0, storey_mm)},{z},{x})')})")
    storey = s.add(f"IFCBUILDINGSTOREY('{next(ids)}',$,'Level 0',$,$,{st_pl},$,$,.ELEMENT.,{storey_mm:.1f})")
    for parent, child in ((project, site), (site, bldg), (bldg, storey)):
        s.add(f"IFCRELAGGREGATES('{next(ids)}',$,$,$,{parent},({child}))")

    def box(x0, y0, z0, x1, y1, z1):
        centre = s.add(f"IFCCARTESIANPOINT(({(x0 + x1) / 2:.1f},{(y0 + y1) / 2:.1f}))")
        profile = s.add(f"IFCRECTANGLEPROFILEDEF(.AREA.,$,{s.add(f'IFCAXIS2PLACEMENT2D({centre},$)')},"
                        f"{x1 - x0:.1f},{y1 - y0:.1f})")
        pos = s.add(f"IFCAXIS2PLACEMENT3D({s.point(0, 0, z0)},{z},{x})")
        solid = s.add(f"IFCEXTRUDEDAREASOLID({profile},{pos},{z},{z1 - z0:.1f})")
        rep = s.add(f"IFCSHAPEREPRESENTATION({body},'Body','SweptSolid',({solid}))")
        return s.add(f"IFCPRODUCTDEFINITIONSHAPE($,$,({rep}))")

    contained, by_name = [], {}
    for name, x0, y0, x1, y1, h in walls:
        pl = s.add(f"IFCLOCALPLACEMENT({st_pl},{world})")
        by_name[name] = (s.add(f"IFCWALL('{next(ids)}',$,'{name}',$,$,{pl},{box(x0, y0, 0, x1, y1, h)},$,"
                               f".SOLIDWALL.)"), pl)
        contained.append(by_name[name][0])
    for name, x0, y0, z0, x1, y1, z1 in openings:
        wall, pl = by_name[name]
        o = s.add(f"IFCOPENINGELEMENT('{next(ids)}',$,'opening in {name}',$,$,"
                  f"{s.add(f'IFCLOCALPLACEMENT({pl},{world})')},{box(x0, y0, z0, x1, y1, z1)},$,.OPENING.)")
        s.add(f"IFCRELVOIDSELEMENT('{next(ids)}',$,$,$,{wall},{o})")
    for name, x0, y0, x1, y1 in axis_only:
        a, b = s.add(f"IFCCARTESIANPOINT(({x0:.1f},{y0:.1f}))"), s.add(f"IFCCARTESIANPOINT(({x1:.1f},{y1:.1f}))")
        rep = s.add(f"IFCSHAPEREPRESENTATION({ctx},'Axis','Curve2D',({s.add(f'IFCPOLYLINE(({a},{b}))')}))")
        pl = s.add(f"IFCLOCALPLACEMENT({st_pl},{world})")
        contained.append(s.add(f"IFCWALL('{next(ids)}',$,'{name}',$,$,{pl},"
                               f"{s.add(f'IFCPRODUCTDEFINITIONSHAPE($,$,({rep}))')},$,.SOLIDWALL.)"))
    s.add(f"IFCRELCONTAINEDINSPATIALSTRUCTURE('{next(ids)}',$,$,$,({','.join(contained)}),{storey})")
    data = "\n".join(f"#{k + 1}={line};" for k, line in enumerate(s.lines))
    return ("ISO-10303-21;\nHEADER;\nFILE_DESCRIPTION(('ViewDefinition [DesignTransferView]'),'2;1');\n"
            "FILE_NAME('room.ifc','2024-01-01T00:00:00',(''),(''),'','tests/test_ifc_import.py','');\n"
            f"FILE_SCHEMA(('{schema}'));\nENDSEC;\nDATA;\n{data}\nENDSEC;\nEND-ISO-10303-21;\n")


ROOM_WALLS = [  # a 5 m x 4 m room of 200 mm walls, 2.5 m high, and a 1 m high parapet beside it
    ("south", 0, 0, 5000, 200, 2500),
    ("north", 0, 3800, 5000, 4000, 2500),
    ("west", 0, 200, 200, 3800, 2500),
    ("east", 4800, 200, 5000, 3800, 2500),
    ("parapet", 6000, 0, 6200, 4000, 1000),
]
ROOM_OPENINGS = [
    ("south", 1000, -100, 0, 1900, 300, 2100),  # door 0.9 m x 2.1 m on the floor
    ("north", 2000, 3700, 900, 3200, 4100, 1900),  # window 1.2 m x 1.0 m, sill at 0.9 m
    ("east", 4700, 1500, 0, 5100, 2400, 2600),  # doorway taller than the wall
]


@pytest.fixture(scope="module")
def room_ifc(tmp_path_factory) -> Path:
    p = tmp_path_factory.mktemp("ifc") / "room_mm.ifc"
    p.write_text(ifc_text(ROOM_WALLS, ROOM_OPENINGS, axis_only=[("axis-only wall", 0, 0, 1000, 0)]))
    return p


@pytest.fixture(scope="module")
def room(room_ifc):
    return import_storey(room_ifc, "Level 0", BAND[:2], BAND[2])


@needs_ifc
def test_millimetre_file_comes_out_in_metres_in_the_storey_frame(room):
    pm = room.plane_map
    assert room.report["model"]["length_unit_m"] == pytest.approx(0.001)
    assert room.storey.elevation == pytest.approx(3.0)
    # The storey is 3 m up: the map moves it down so its floor is z = 0, and says so.
    assert room.T_storey_world[2, 3] == pytest.approx(-3.0)
    assert "z -3.000 m" in room.report["transform"]["description"]
    lo, hi = pm.bounds()
    assert lo == pytest.approx([0, 0, 0]) and hi == pytest.approx([6.2, 4.0, 2.5])
    assert offsets(pm, [0, -1, 0]) == pytest.approx([-3.8, 0.0])  # south outer y = 0, north inner y = 3.8
    assert offsets(pm, [0, 1, 0]) == pytest.approx([0.2, 4.0])
    assert offsets(pm, [1, 0, 0]) == pytest.approx([0.2, 5.0, 6.2])


@needs_ifc
def test_door_on_the_floor_leaves_a_notch_and_a_window_a_hole(room):
    pm = room.plane_map
    south_out = one_plane(pm, [0, -1, 0], 0.0)
    assert south_out.area == pytest.approx(5 * 2.5 - 0.9 * 2.1)
    assert len(south_out.polygons) == 1  # one U-shaped polygon: the lintel holds it together
    assert not covers(south_out, np.array([1.45, 0.0, 1.0]))
    south_in = one_plane(pm, [0, 1, 0], 0.2)  # inside the room, between the side walls' ends
    assert south_in.area == pytest.approx(4.6 * 2.5 - 0.9 * 2.1)
    north_out = one_plane(pm, [0, 1, 0], 4.0)
    assert north_out.area == pytest.approx(5 * 2.5 - 1.2 * 1.0)
    assert len(north_out.polygons) == 4  # left of, below, above and right of the window
    assert not covers(north_out, np.array([2.6, 4.0, 1.4]))
    assert covers(north_out, np.array([2.6, 4.0, 0.5])) and covers(north_out, np.array([2.6, 4.0, 2.2]))


@needs_ifc
def test_doorway_as_tall_as_the_wall_splits_its_faces_in_two(room):
    east_out = one_plane(room.plane_map, [1, 0, 0], 5.0)
    assert len(east_out.polygons) == 2
    # 4 m wide with the ends of the south and north walls, less the 0.9 m doorway.
    assert east_out.area == pytest.approx((4.0 - 0.9) * 2.5)
    ys = sorted((round(p[:, 1].min(), 3), round(p[:, 1].max(), 3)) for p in east_out.polygons)
    assert ys == [(0.0, 1.5), (2.4, 4.0)]


@needs_ifc
def test_coplanar_touching_faces_merge_and_hidden_faces_go(room):
    west_out = one_plane(room.plane_map, [-1, 0, 0], 0.0)
    # The west wall's outer face and the ends of the south and north walls make one plane, 4 m wide.
    assert west_out.area == pytest.approx(4.0 * 2.5)
    assert sorted(west_out.source["name"]) == ["north", "south", "west"]
    c = room.report["counts"]
    assert c["merged"] >= 2
    assert c["hidden"] >= 4  # the side walls' ends pressed against the south and north walls
    assert [i for i in check_plane_map(room.plane_map) if i.severity == "error"] == []


@needs_ifc
def test_wall_without_a_body_is_skipped_with_a_warning_naming_it(room):
    assert room.report["counts"]["no_body"] == 1
    assert len(room.warnings) == 1
    assert "'axis-only wall'" in room.warnings[0] and "no solid body" in room.warnings[0]
    assert "1AbCdEfGhIjKlMnOpQr" in room.warnings[0]  # its GlobalId


@needs_ifc
def test_faces_outside_the_camera_band_are_dropped(room_ifc, room):
    assert one_plane(room.plane_map, [1, 0, 0], 6.2).area == pytest.approx(4.0)  # the 1 m parapet
    high = import_storey(room_ifc, "Level 0", (1.2, 3.4), 0.5)
    assert 6.2 not in offsets(high.plane_map, [1, 0, 0]) and 5.0 in offsets(high.plane_map, [1, 0, 0])
    assert high.report["counts"]["outside_window"] >= 2  # both sides of the parapet
    lo, hi = high.plane_map.bounds()
    assert lo[2] == pytest.approx(1.2) and hi[2] == pytest.approx(2.5)


@needs_ifc
def test_unsupported_schema_is_a_clear_error(tmp_path):
    p = tmp_path / "old.ifc"
    p.write_text(ifc_text(ROOM_WALLS[:1], schema="IFC2X_FINAL"))
    with pytest.raises(ConfigError, match=r"old\.ifc: IFC schema IFC2X_FINAL is not supported"):
        open_model(p)


@needs_ifc
def test_a_mangled_schema_name_is_quoted_on_one_line(tmp_path):
    """Found by the long fuzz run: a header whose quote closes lines later put the file's next
    lines into the error."""
    p = tmp_path / "mangled.ifc"
    text = ifc_text(ROOM_WALLS[:1])
    p.write_text(text.replace("FILE_SCHEMA(('IFC4'))", "FILE_SCHEMA(('IFC4));\nENDSEC;\nDATA;\n#1=IFCX('a'))", 1))
    assert "FILE_SCHEMA(('IFC4));" in p.read_text()
    with pytest.raises(ConfigError) as e:
        open_model(p)
    assert "\n" not in str(e.value) and len(str(e.value)) < 400
    assert "mangled.ifc: " in str(e.value)


@needs_ifc
def test_a_file_that_crashes_the_parser_is_one_error_and_this_process_lives_on(tmp_path, monkeypatch):
    """ifcopenshell's C++ parser segfaulted on one damaged file of the long fuzz run: the file is
    parsed in a forked child first, so the crash becomes an error naming it."""
    import os
    import signal

    import ifcopenshell

    p = tmp_path / "crash.ifc"
    p.write_text(ifc_text(ROOM_WALLS[:1]))
    monkeypatch.setattr(ifcopenshell, "open", lambda *a, **k: os.kill(os.getpid(), signal.SIGSEGV))
    with pytest.raises(ConfigError, match=r"crash\.ifc: not a readable IFC file: ifcopenshell's parser crashed "
                                          r"\(SIGSEGV\)"):
        open_model(p)


@needs_ifc
def test_unreadable_and_missing_files(tmp_path):
    junk = tmp_path / "junk.ifc"
    junk.write_text("this is not STEP")
    with pytest.raises(ConfigError, match="junk.ifc: not a readable IFC file"):
        open_model(junk)
    with pytest.raises(ConfigError, match="nope.ifc: file not found"):
        open_model(tmp_path / "nope.ifc")


@needs_ifc
def test_unknown_storey_lists_the_storeys(room_ifc):
    with pytest.raises(ConfigError, match=r"room_mm\.ifc: no storey named 'Level 9' \(storeys: 'Level 0'\)"):
        import_storey(room_ifc, "Level 9", BAND[:2], BAND[2])


# ---------------------------------------------------------------------------- CLI

def run_cli(argv):
    import argparse

    from robot.cli import maps as cli_map

    parser = argparse.ArgumentParser()
    cli_map.register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(argv)
    out = io.StringIO()
    with redirect_stdout(out):
        rc = args.func(args)
    return rc, out.getvalue()


@needs_ifc
def test_cli_lists_storeys_then_imports_one(room_ifc, tmp_path):
    rc, out = run_cli(["map", "import-ifc", str(room_ifc), "--json"])
    listing = json.loads(out)
    assert rc == 0 and [s["name"] for s in listing["storeys"]] == ["Level 0"]
    assert listing["storeys"][0]["elements"] == 6

    out_map = tmp_path / "room.yaml"
    rc, out = run_cli(["map", "import-ifc", str(room_ifc), "--storey", "level 0", "--out", str(out_map),
                       "--note", "test model"])
    assert rc == 0 and "wrote" in out and "warning: skipped 1 element(s)" in out
    text = out_map.read_text()
    assert "map = world shifted by z -3.000 m" in text and "# test model" in text
    pm = load_plane_map(out_map)  # loads without ifcopenshell's help
    assert len(pm) == len(import_storey(room_ifc, "Level 0", BAND[:2], BAND[2]).plane_map)
    assert pm.planes[0].source["ifc_type"] == ["IfcWall"]
    rc, out = run_cli(["map", "check", str(out_map)])
    assert rc == 0 and "OK" in out


def test_robot_side_modules_do_not_load_ifcopenshell_or_matplotlib():
    # The robot installs without the bim and viz extras: loading the map tools must not need them.
    code = ("import sys, robot.maps.ifc_import, robot.cli.maps, robot.maps.tools, robot.maps.plot, robot.cli.main; "
            "robot.cli.main.build_parser(); print(sorted(m for m in ('ifcopenshell', 'shapely', 'matplotlib') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


@needs_ifc
def test_a_library_warning_before_a_refusal_stays_on_the_error_line(room_ifc, monkeypatch, capsys):
    """Found by the long fuzz run: numpy's RuntimeWarning from ifcopenshell's placement code on a
    damaged file came out as two raw lines on stderr before the error. robotctl routes Python
    warnings through its log, held like the others for a batch command: one line in all."""
    import logging
    import warnings

    from robot.cli.main import main
    from robot.maps import ifc_import

    def warn_then_refuse(path):
        warnings.warn("invalid value encountered in divide", RuntimeWarning, stacklevel=1)
        raise ConfigError(f"{path}: the IFC model is inconsistent, cannot import it")

    monkeypatch.setattr(ifc_import, "open_model", warn_then_refuse)
    root = logging.getLogger()
    saved = root.handlers[:], root.level
    root.handlers = []  # robotctl's own handler, as in a real run (pytest's capture sets others)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always")
            assert main(["map", "import-ifc", str(room_ifc)]) == 2
    finally:
        root.handlers, _ = saved
        root.setLevel(saved[1])
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1, err
    assert err.startswith("robotctl map: error: ") and "the IFC model is inconsistent" in err
    assert "(after 1 warning: RuntimeWarning: invalid value encountered in divide" in err
    assert warnings.formatwarning.__name__ != "_one_line_warning"  # put back for whoever runs next
