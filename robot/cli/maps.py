"""``robotctl map``: import-ifc (building model to plane map), info (summary, floor plan), check (validity)."""

from __future__ import annotations

import logging
import math
import sys
from typing import Any, Dict, List, Optional, Tuple

from robot.base.errors import ConfigError, RobotError
from robot.base.files import MAP, check_writable_file
from robot.cli.common import DEFAULT_ROBOT, float_in, int_in, print_json
from robot.config.schema import load_yaml_file


def register(subparsers) -> None:
    p = subparsers.add_parser("map", help="import, inspect and check plane maps")
    sub = p.add_subparsers(dest="map_command", metavar="MAP_COMMAND")
    sub.required = True

    imp = sub.add_parser("import-ifc", help="make a plane map from one storey of an IFC building model "
                                            "(lists the storeys when --storey is not given)")
    imp.add_argument("model", help="IFC file (IFC2X3, IFC4 or IFC4X3)")
    imp.add_argument("--storey", help="storey name or GlobalId")
    imp.add_argument("--out", help="map YAML to write (without it, only the report is printed)")
    imp.add_argument("--robot", default=str(DEFAULT_ROBOT),
                     help="robot config whose cameras set the height band (default: %(default)s)")
    imp.add_argument("--band", nargs=2, type=float_in(-100.0, 100.0, "m"), metavar=("Z_LO", "Z_HI"),
                     help="height band to keep, metres above the floor, instead of the cameras' band")
    imp.add_argument("--min-width", type=float_in(0.0, 100.0, "m"), default=0.5, help="narrowest face kept, m (default 0.5)")
    imp.add_argument("--min-area", type=float_in(0.0, 10000.0, "m^2"), default=0.5,
                     help="smallest face kept, m^2 (default 0.5)")
    imp.add_argument("--no-openings", action="store_true",
                     help="do not cut doors and windows out of walls (5-16x faster, but the map then "
                          "claims wall where the camera sees holes)")
    imp.add_argument("--no-storey-clip", action="store_true",
                     help="keep faces above the next storey's floor (only the camera band limits them)")
    imp.add_argument("--types", default="IfcWall,IfcColumn",
                     help="comma-separated IFC classes to take faces from (default %(default)s)")
    imp.add_argument("--threads", type=int_in(1, 64), default=2, help="geometry threads, 1 to 64 (default 2)")
    imp.add_argument("--note", default="", help="text added to the map's header comment (e.g. attribution)")
    imp.add_argument("--json", action="store_true", help="print the report as JSON")
    imp.set_defaults(func=cmd_import_ifc)

    info = sub.add_parser("info", help="plane count, extent, height band; optionally a PNG floor plan")
    info.add_argument("map", help="map YAML")
    info.add_argument("--png", help="write a floor plan with plane ids to this PNG")
    info.add_argument("--robot",
                      help=f"robot config for the camera band (default: {DEFAULT_ROBOT} if present)")
    info.add_argument("--json", action="store_true", help="print JSON")
    info.set_defaults(func=cmd_info)

    chk = sub.add_parser("check", help="validity: planarity, orientation, duplicates (exit 1 on errors)")
    chk.add_argument("map", help="map YAML")
    chk.add_argument("--max-thickness", type=float_in(0.0, 10.0, "m", lo_open=True), default=0.6,
                     help="thickest wall, m: how far the back-face test looks (default 0.6)")
    chk.add_argument("--json", action="store_true", help="print JSON")
    chk.set_defaults(func=cmd_check)


def _emit(args, obj: Dict[str, Any], lines: List[str]) -> None:
    if getattr(args, "json", False):
        print_json(obj)
    else:
        sys.stdout.write("\n".join(lines) + "\n")


def _camera_band(config_path) -> Tuple[float, float, float]:
    from robot.config import load_robot_config
    from robot.maps.tools import camera_band_from_config

    return camera_band_from_config(load_robot_config(config_path))


def _band(args) -> Tuple[float, float, float]:
    """(z_lo, z_hi, eye_z) from --band or from the robot config's cameras."""
    lo, hi, eye = _camera_band(args.robot)
    if args.band is not None:
        lo, hi = args.band
        if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
            raise ConfigError(f"--band: Z_HI must be above Z_LO, got {lo} {hi}")
    return lo, hi, eye


def cmd_import_ifc(args) -> int:
    try:
        return _import_ifc(args)
    except (AttributeError, KeyError, IndexError, TypeError, ValueError, RuntimeError, ZeroDivisionError) as e:
        # ConfigError is a ValueError: it passes as it is. Anything else came out of a model whose
        # entities do not fit together (a reference to an entity that is not there, a geometry the
        # kernel refuses): a bad file, not a crash. -v logs the traceback.
        if isinstance(e, RobotError):
            raise
        logging.getLogger(__name__).debug("import of %s failed", args.model, exc_info=True)
        raise ConfigError(f"{args.model}: the IFC model is inconsistent, cannot import it "
                          f"({type(e).__name__}: {str(e)[:120]})") from None


def _import_ifc(args) -> int:
    from robot.maps import ifc_import

    model = ifc_import.open_model(args.model)
    if args.out and args.storey is not None:
        check_writable_file(args.out, "--out")  # before minutes of geometry, not after
    types = tuple(t.strip() for t in args.types.split(",") if t.strip())
    if not types:
        raise ConfigError("--types: give at least one IFC class")
    if args.storey is None:
        storeys = ifc_import.list_storeys(model, types)
        obj = {"model": str(args.model), "schema": model.schema, "storeys": [s.__dict__ for s in storeys]}
        lines = [f"{args.model}: {model.schema}, {len(storeys)} storeys (give one with --storey NAME):"]
        for s in storeys:
            h = f"{s.height:.2f} m high" if s.height is not None else "top storey"
            lines.append(f"  {s.name!r:28} elevation {s.elevation:+8.3f} m  {h:14}  {s.elements:4d} walls/columns"
                         f"  ({s.guid})")
        _emit(args, obj, lines)
        return 0
    for name in ("min_width", "min_area"):
        value = getattr(args, name)
        if not (math.isfinite(value) and value >= 0):
            raise ConfigError(f"--{name.replace('_', '-')} must be a number >= 0, got {value}")
    lo, hi, eye = _band(args)
    options = ifc_import.ImportOptions(min_width=args.min_width, min_area=args.min_area,
                                       openings=not args.no_openings, types=types,
                                       threads=max(1, args.threads), clip_to_storey=not args.no_storey_clip)
    result = ifc_import.import_storey(args.model, args.storey, (lo, hi), eye, options)
    if args.out:
        from robot.maps.plane_map import save_plane_map

        try:
            save_plane_map(result.plane_map, args.out, header=result.header(args.note))
        except OSError as e:
            raise ConfigError(f"{args.out}: cannot write: {e}") from None
    r = result.report
    c = r["counts"]
    obj = dict(r, out=args.out)
    lines = [
        f"{r['model']['file']} storey {result.storey.name!r}: {c['planes']} planes, {c['polygons']} polygons "
        f"from {c['elements']} elements in {r['seconds']['total']:.1f} s",
        f"  frame: {r['transform']['description']}",
        f"  kept z {r['window'][0]:.3f}..{r['window'][1]:.3f} m (camera band {lo:.3f}..{hi:.3f} m)",
        f"  vertical faces {c['vertical_faces']}: hidden {c['hidden']}, outside the window {c['outside_window']}, "
        f"narrow {c['narrow']}, small {c['small']}, merged {c['merged']}, kept {c['kept_faces']}; "
        f"{c['enclosed']} polygons facing a closed pocket dropped",
    ]
    lines.extend(f"  warning: {w}" for w in result.warnings)
    lines.append(f"  wrote {args.out}" if args.out else "  (no --out: nothing written)")
    _emit(args, obj, lines)
    return 0


def _load(path: str):
    from robot.maps.plane_map import load_plane_map

    return load_plane_map(path)


def cmd_info(args) -> int:
    from robot.maps.tools import map_summary

    pm = _load(args.map)
    if args.png:
        check_writable_file(args.png, "--png")
    band: Optional[Tuple[float, float]] = None
    config = args.robot or (DEFAULT_ROBOT if DEFAULT_ROBOT.is_file() else None)
    if config is not None:
        band = _camera_band(config)[:2]
    s = map_summary(pm, band)
    if args.png:
        from robot.maps.plot import save_floor_plan

        save_floor_plan(pm, args.png)
        s["png"] = args.png
    e = s["extent"]
    lines = [
        f"{args.map}: {s['planes']} planes, {s['polygons']} polygons, {s['vertices']} vertices, "
        f"{s['area_m2']:.1f} m^2",
        f"  extent x {e['min'][0]:.3f}..{e['max'][0]:.3f}, y {e['min'][1]:.3f}..{e['max'][1]:.3f} m "
        f"({e['size'][0]:.2f} x {e['size'][1]:.2f} m)",
        f"  height band z {s['height_band'][0]:.3f}..{s['height_band'][1]:.3f} m",
        f"  planes: {s['orientation']['vertical']} vertical, {s['orientation']['horizontal']} horizontal, "
        f"{s['orientation']['sloped']} sloped; area per plane {s['plane_area_m2']['min']:.2f}.."
        f"{s['plane_area_m2']['max']:.2f} m^2 (median {s['plane_area_m2']['median']:.2f})",
    ]
    if band is not None:
        lines.append(f"  camera band z {band[0]:.3f}..{band[1]:.3f} m: {s['planes_in_camera_band']} planes reach into it")
    if "ifc_types" in s:
        lines.append("  from " + ", ".join(f"{k} ({v})" for k, v in sorted(s["ifc_types"].items())))
    if "not_built" in s:
        lines.append(f"  not built yet (predicted nowhere): {', '.join(s['not_built'])}")
    if args.png:
        lines.append(f"  floor plan: {args.png}")
    _emit(args, s, lines)
    return 0


def cmd_check(args) -> int:
    from robot.maps.tools import check_map_data

    if not (math.isfinite(args.max_thickness) and args.max_thickness > 0):
        raise ConfigError(f"--max-thickness must be a positive number of metres, got {args.max_thickness}")
    data = load_yaml_file(args.map, MAP)
    issues, pm = check_map_data(data, source=str(args.map), max_thickness=args.max_thickness)
    errors = [i for i in issues if i.severity == "error"]
    warnings = [i for i in issues if i.severity == "warning"]
    n = len(data["planes"])
    obj = {"map": str(args.map), "planes": n, "valid": not errors,
           "errors": len(errors), "warnings": len(warnings), "issues": [i.as_dict() for i in issues]}
    verdict = "OK" if not errors else "INVALID"
    lines = [f"{args.map}: {verdict}: {n} planes, {len(errors)} errors, {len(warnings)} warnings"]
    lines.extend(f"  {i.severity}: [{i.code}] {i.message}" for i in issues)
    _emit(args, obj, lines)
    return 1 if errors else 0
