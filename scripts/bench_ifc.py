"""IFC import figures for BENCHMARKS.md: time and face counts per shared model.

Reads the models from ../shared/data/ifc/ (see tests/data/README.md); a model that is absent is
listed as not run.
"""

from __future__ import annotations

import os
import platform
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from robot.config import load_robot_config  # noqa: E402
from robot.maps.tools import camera_band_from_config, check_plane_map  # noqa: E402

IFC_DIR = ROOT.parent / "shared" / "data" / "ifc"
MODELS = [  # (file, storey for the ground-floor map, map written to config/maps)
    ("AC20-FZK-Haus.ifc", "Erdgeschoss", "fzk_haus_ground.yaml"),
    ("Duplex_A_20110907.ifc", "Level 1", "duplex_level1.yaml"),
    ("AC11-Institute-Var-2-IFC.ifc", "Erdgeschoss", "institute_ground.yaml"),
]
THREADS = 2


def _timed(fn, repeats):
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return out, statistics.median(times)


def large_map_check(repeats: int):
    """`map check` on a map the size of a large floor: the Institute ground floor tiled 4 x 3."""
    import yaml

    from robot.maps.tools import check_map_data

    base = yaml.safe_load((ROOT / "config" / "maps" / "institute_ground.yaml").read_text())
    planes = []
    for kx in range(4):
        for ky in range(3):
            for p in base["planes"]:
                polys = p["polygons"] if "polygons" in p else [p["vertices"]]
                moved = [[[v[0] + 50.0 * kx, v[1] + 20.0 * ky, v[2]] for v in poly] for poly in polys]
                planes.append({"id": f"{p['id']}_{kx}{ky}", "polygons": moved})
    (issues, pm), t = _timed(lambda: check_map_data({"planes": planes}), repeats)
    n_poly = sum(len(p.polygons) for p in pm.planes)
    return [f"`map check` on a large map (institute_ground.yaml tiled 4 x 3: {len(pm)} planes, {n_poly} polygons): "
            f"{t:.2f} s, {len(issues)} issues."]


def run(quick: bool = False) -> str:
    try:
        import ifcopenshell

        from robot.maps.ifc_import import ImportOptions, import_storey, list_storeys, open_model
    except ImportError as e:
        return "\n".join(["## IFC import", "", f"_import not run: {e} (pip install .[bim])_", "",
                          *large_map_check(1 if quick else 3)])
    lo, hi, eye = camera_band_from_config(load_robot_config(ROOT / "config" / "robot.yaml"))
    repeats = 1 if quick else 3
    lines = [
        "## IFC import",
        "",
        f"Ground-floor maps from the shared models; median of {repeats} run(s), {THREADS} geometry threads, "
        f"camera band z {lo:.2f}..{hi:.2f} m from config/robot.yaml. "
        "Faces are connected planar regions of one element's surface; 'hidden' are pressed against another "
        "element or behind a slab/ceiling they meet; 'outside' have nothing left in the kept height window; "
        "'narrow' are under 0.5 m wide (wall ends, door and window reveals); 'small' under 0.5 m^2; "
        "'pocket' are polygons facing a closed pocket in the construction.",
        "",
        "| model | storey | elements | vertical faces | hidden | outside | narrow | small | merged | pocket "
        "| planes | polygons | import s | without openings s | map check s |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    missing = []
    for name, storey, _ in MODELS:
        path = IFC_DIR / name
        if not path.is_file():
            missing.append(name)
            continue
        r, t_on = _timed(lambda p=path, s=storey: import_storey(p, s, (lo, hi), eye, ImportOptions(threads=THREADS)),
                         repeats)
        _, t_off = _timed(lambda p=path, s=storey: import_storey(
            p, s, (lo, hi), eye, ImportOptions(threads=THREADS, openings=False)), repeats)
        _, t_check = _timed(lambda pm=r.plane_map: check_plane_map(pm), repeats)
        c = r.report["counts"]
        lines.append(
            f"| {name} | {storey} | {c['elements']} | {c['vertical_faces']} | {c['hidden']} | {c['outside_window']} "
            f"| {c['narrow']} | {c['small']} | {c['merged']} | {c['enclosed']} | {c['planes']} | {c['polygons']} "
            f"| {t_on:.2f} | {t_off:.2f} | {t_check:.2f} |")
    if not quick:
        lines += ["", "Every storey (one run each, openings cut):", "",
                  "| model | storey | elevation m | planes | polygons | import s |", "|---|---|---:|---:|---:|---:|"]
        for name, _, _ in MODELS:
            path = IFC_DIR / name
            if not path.is_file():
                continue
            for st in list_storeys(open_model(path)):
                r, t = _timed(lambda p=path, g=st.guid: import_storey(p, g, (lo, hi), eye,
                                                                      ImportOptions(threads=THREADS)), 1)
                lines.append(f"| {name} | {st.name} | {st.elevation:.2f} | {len(r.plane_map)} "
                             f"| {r.report['counts']['polygons']} | {t:.2f} |")
    if missing:
        lines += ["", f"_not run (absent from {IFC_DIR}): {', '.join(missing)}_"]
    lines += ["", *large_map_check(repeats)]
    lines += ["", f"_Machine: {platform.machine()}, {os.cpu_count()} logical cores, Python {platform.python_version()}, "
                  f"ifcopenshell {ifcopenshell.version}._"]
    return "\n".join(lines)


if __name__ == "__main__":
    print(run(quick="--quick" in sys.argv))
