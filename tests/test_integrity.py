"""The integrity benchmark's short mode (scripts/bench_integrity.py) on a fixed sample of random
realistic scenes: protection levels bound the error, and 'ok' is never badly wrong where a frame
can tell. The full run (2,000 scenes) is in BENCHMARKS.md."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))

import bench_integrity  # noqa: E402

SCENES = 40
SEED = 20240601


@pytest.fixture(scope="module")
def sample():
    return bench_integrity.run(SCENES, SEED)


def test_no_result_is_misleading(sample):
    bad = [r for r in sample["rows"] if r["misleading"]]
    assert bad == [], bad


def test_ok_is_never_wrong_beyond_its_own_covariance_where_the_frames_can_tell(sample):
    # An 'ok' pose more than 50 mm off is either what its honest covariance says can happen (a wall
    # metres away seen through a depth scale known to 1 %), or the one case a single frame cannot
    # resolve: clutter hiding all a camera sees of a wall, with the prior admitting its offset. The
    # protection level, which assumes one wall may be wrong, bounds both (test above).
    for r in sample["rows"]:
        if r["status"] == "ok" and not r["hidden_wall"]:
            assert not r["ok_beyond_cov"], r
        if r["ok_gt"]:
            assert r["hidden_wall"] or r["nees"] <= bench_integrity.NEES_LIMIT, r
            assert r["err_h"] <= r["hpl"]


def test_wrong_identifications_are_only_walls_hidden_behind_clutter(sample):
    for r in sample["rows"]:
        assert all(share < bench_integrity.HIDDEN_SHARE for share in r["wrong_visible"]), r


def test_the_covariance_is_honest_on_average(sample):
    s = bench_integrity.summarise([r for r in sample["rows"] if not r["wrong"]])
    assert 1.0 < s["nees_mean"] < 5.0, s
    assert s["status"]["ok"] >= SCENES // 2
    assert not math.isnan(s["err_h_median_mm"]) and s["err_h_median_mm"] < 50.0
