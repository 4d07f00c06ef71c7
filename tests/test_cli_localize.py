"""``robotctl visible | localize | render`` end to end, and every bad input giving exit 2 + one line."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from robot.cli.main import main
from robot.localization.localizer import FIX_STATUSES

ROBOT = "config/robot.yaml"
MAP = "config/maps/paper_arena.yaml"


def run(capsys, *argv):
    rc = main(list(argv))
    out, err = capsys.readouterr()
    return rc, out, err


@pytest.fixture(scope="module")
def snaps(tmp_path_factory):
    d = tmp_path_factory.mktemp("snaps")
    pose = ("0.5", "0.5", str(math.pi))
    paths = []
    for cam in ("front", "left"):
        p = d / f"{cam}.npz"
        assert main(["render", "--robot", ROBOT, "--map", MAP, "--pose", *pose, "--camera", cam,
                     "--out", str(p), "--seed", "3"]) == 0
        paths.append(p)
    return paths


def test_localize_json_from_rendered_snapshots(capsys, snaps):
    for method in ("joint", "paper"):
        rc, out, _ = run(capsys, "localize", "--robot", ROBOT, "--map", MAP, "--init", "0.56", "0.45", "3.0",
                         "--method", method, "--json", *map(str, snaps))
        assert rc == 0
        res = json.loads(out)
        assert set(res) >= {"x", "y", "phi", "cov", "status", "unobservable", "planes", "ms"}
        assert res["status"] in FIX_STATUSES and res["unobservable"] == []
        assert abs(res["x"] - 0.5) < 0.002 and abs(res["y"] - 0.5) < 0.002
        assert abs(math.remainder(res["phi"] - math.pi, 2 * math.pi)) < math.radians(0.1)
        assert np.array(res["cov"]).shape == (3, 3)
        used = {(p["id"], p["camera"]) for p in res["planes"] if p["used"]}
        assert ("wall_west", "front") in used and ("wall_south", "left") in used
        for p in res["planes"]:
            assert set(p) == {"id", "camera", "inliers", "normal", "d", "used", "reason"}


def test_visible_json(capsys):
    rc, out, _ = run(capsys, "visible", "--robot", ROBOT, "--map", MAP, "--pose", "0.5", "0.5", str(math.pi), "--json")
    assert rc == 0
    cams = {c["name"]: c for c in json.loads(out)["cameras"]}
    assert [p["id"] for p in cams["front"]["planes"]] == ["wall_west"]
    assert [p["id"] for p in cams["left"]["planes"]] == ["wall_south"]
    p = cams["front"]["planes"][0]
    # The wall spans the full image width; its rows run from the floor line up to the wall's top edge.
    cols = [c for c, _ in p["polygon"]]
    assert min(cols) == pytest.approx(-0.5) and max(cols) == pytest.approx(847.5)
    assert 0 < p["pixels"] < 848 * 480
    rc, out, _ = run(capsys, "visible", "--robot", ROBOT, "--map", MAP, "--pose", "0.5", "0.5", "2.6",
                     "--camera", "front", "--json")
    ids = {p["id"] for p in json.loads(out)["cameras"][0]["planes"]}
    assert ids == {"wall_west", "wall_north"}  # turned 30 deg towards the north-west corner


def test_console_script_runs_without_traceback(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("planes: [\n")
    r = subprocess.run([sys.executable, "-m", "robot.cli.main", "visible", "--map", str(bad), "--pose", "0", "0", "0"],
                       capture_output=True, text=True)
    assert r.returncode == 2
    assert "Traceback" not in r.stderr
    assert r.stderr.count("\n") == 1 and str(bad) in r.stderr and "malformed YAML" in r.stderr


def write(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return str(p)


def npz(tmp_path, name, **arrays):
    base = dict(depth=np.full((480, 848), 1000, np.uint16), depth_scale=0.001,
                K=np.array([[446.8, 0, 423.5], [0, 433.0, 239.5], [0, 0, 1]]), camera="front")
    base.update(arrays)
    base = {k: v for k, v in base.items() if v is not None}
    p = tmp_path / name
    np.savez(p, **base)
    return str(p)


BAD_ROBOT_UNKNOWN_KEY = """cameras:
  - {name: front, width: 848, height: 480, fps: 30, hfov_deg: 87, vfov_deg: 58, fov: 3,
     mount: {xyz: [0.1, 0, 0.12], rpy_deg: [0, 0, 0]}}
"""
NONPLANAR_MAP = "planes:\n  - id: w\n    vertices: [[0, 0, 0], [1, 0, 0], [1, 0.01, 1], [0, 0, 1]]\n"
DUP_MAP = ("planes:\n  - id: w\n    vertices: [[0, 0, 0], [1, 0, 0], [1, 0, 1]]\n"
           "  - id: w\n    vertices: [[0, 1, 0], [1, 1, 0], [1, 1, 1]]\n")
TWO_VERTEX_MAP = "planes:\n  - id: w\n    vertices: [[0, 0, 0], [1, 0, 0]]\n"


@pytest.mark.parametrize("case,expect", [
    ("missing_map", "file not found"),
    ("malformed_yaml", "malformed YAML"),
    ("unknown_key", "unknown key(s): fov"),
    ("nonplanar", "not planar"),
    ("duplicate_id", "duplicate id"),
    ("two_vertices", "at least 3 are needed"),
    ("unknown_camera", "unknown camera 'rear'"),
    ("missing_snapshot", "file not found"),
    ("not_npz", "not a readable .npz"),
    ("wrong_shape", "'depth' must be a 2-D array"),
    ("wrong_dtype", "'depth' must be uint16"),
    ("nan_K", "'K' must be a finite 3x3 matrix"),
    ("nan_scale", "'depth_scale' must be a positive finite number"),
    ("missing_array", "missing array(s): K"),
    ("nan_init", "--init: 'nan' is not a finite number"),
])
def test_bad_input_exit_2_with_one_clear_line(capsys, tmp_path, case, expect):
    robot, pmap = ROBOT, MAP
    snap = npz(tmp_path, "ok.npz")
    init = ["0.5", "0.5", "0"]
    if case == "missing_map":
        pmap = str(tmp_path / "nope.yaml")
    elif case == "malformed_yaml":
        pmap = write(tmp_path, "m.yaml", "planes: [ {id: a\n")
    elif case == "unknown_key":
        robot = write(tmp_path, "r.yaml", BAD_ROBOT_UNKNOWN_KEY)
    elif case == "nonplanar":
        pmap = write(tmp_path, "m.yaml", NONPLANAR_MAP)
    elif case == "duplicate_id":
        pmap = write(tmp_path, "m.yaml", DUP_MAP)
    elif case == "two_vertices":
        pmap = write(tmp_path, "m.yaml", TWO_VERTEX_MAP)
    elif case == "unknown_camera":
        snap = npz(tmp_path, "cam.npz", camera="rear")
    elif case == "missing_snapshot":
        snap = str(tmp_path / "none.npz")
    elif case == "not_npz":
        snap = write(tmp_path, "x.npz", "this is not a zip file")
    elif case == "wrong_shape":
        snap = npz(tmp_path, "s.npz", depth=np.zeros((480, 848, 3), np.uint16))
    elif case == "wrong_dtype":
        snap = npz(tmp_path, "s.npz", depth=np.zeros((480, 848), np.float32))
    elif case == "nan_K":
        snap = npz(tmp_path, "s.npz", K=np.array([[np.nan, 0, 1], [0, 1, 1], [0, 0, 1]]))
    elif case == "nan_scale":
        snap = npz(tmp_path, "s.npz", depth_scale=np.nan)
    elif case == "missing_array":
        snap = npz(tmp_path, "s.npz", K=None)
    elif case == "nan_init":
        init = ["nan", "0.5", "0"]
    rc, out, err = run(capsys, "localize", "--robot", robot, "--map", pmap, "--init", *init, "--json", snap)
    assert rc == 2
    assert out == ""
    assert err.count("\n") == 1, err
    assert expect in err, err
    assert "Traceback" not in err
    named = {"missing_map": pmap, "malformed_yaml": pmap, "unknown_key": robot, "nonplanar": pmap,
             "duplicate_id": pmap, "two_vertices": pmap, "unknown_camera": robot}.get(case, snap if "init" not in case else "")
    assert named in err
