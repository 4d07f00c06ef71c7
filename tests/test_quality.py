"""QualityMonitor: localized / degraded / lost with reasons, from explicit time and covariance."""

from __future__ import annotations

import math

import numpy as np

from robot.config import QualityConfig
from robot.fusion.quality import DEGRADED, LOCALIZED, LOST, QualityMonitor


def cov(sx: float, sy: float = None, heading_deg: float = 0.2) -> np.ndarray:
    sy = sx if sy is None else sy
    return np.diag([sx ** 2, sy ** 2, math.radians(heading_deg) ** 2])


def test_fresh_updates_and_small_covariance_is_localized():
    q = QualityMonitor()
    q.note_fix(0.0)
    for k in range(10):
        q.note_update(0.1 * k, True)
    r = q.evaluate(1.0, cov(0.005))
    assert r.state == LOCALIZED and r.reason == ""
    assert r.pos_std == 0.005 and abs(r.since_accepted - 0.1) < 1e-12


def test_nothing_yet_is_lost():
    r = QualityMonitor().evaluate(0.0, cov(0.005))
    assert r.state == LOST and "no plane accepted" in r.reason


def test_odometry_only_degrades_then_loses():
    q = QualityMonitor()
    q.note_fix(0.0)
    q.note_update(0.5, True)
    assert q.evaluate(1.0, cov(0.005)).state == LOCALIZED
    r = q.evaluate(3.0, cov(0.012))
    assert r.state == DEGRADED and "odometry only for 2.5 s" in r.reason
    r = q.evaluate(11.0, cov(0.03))
    assert r.state == LOST and "odometry only for 10.5 s" in r.reason


def test_growing_covariance_reasons_and_direction():
    q = QualityMonitor()
    q.note_fix(0.0)
    q.note_update(0.9, True)
    # A corridor along x: the position is unknown along 0 deg and the status says so.
    r = q.evaluate(1.0, cov(0.05, 0.004))
    assert r.state == DEGRADED and "position std 50 mm along 0 deg" in r.reason
    r = q.evaluate(1.0, cov(0.004, 0.15))
    assert r.state == LOST and "along 90 deg" in r.reason
    q2 = QualityMonitor()
    q2.note_fix(0.0)
    q2.note_update(0.9, True)
    assert "heading std 3.0 deg" in q2.evaluate(1.0, cov(0.004, heading_deg=3.0)).reason
    assert q2.evaluate(1.0, cov(0.004, heading_deg=6.0)).state == LOST


def test_gate_rejections_degrade_and_then_lose():
    q = QualityMonitor()
    q.note_fix(0.0)
    t = 0.0
    for k in range(10):
        t = 0.1 * k
        q.note_update(t, k % 3 != 0)  # 4 of 10 refused: fine
    assert q.evaluate(t, cov(0.005)).state == LOCALIZED
    for k in range(10):
        t = 1.0 + 0.1 * k
        q.note_update(t, k % 4 == 0)  # most refused now
    r = q.evaluate(t, cov(0.005))
    assert r.state == DEGRADED and "gate refused" in r.reason
    for k in range(30):
        t = 2.0 + 0.1 * k
        q.note_update(t, False)
    r = q.evaluate(t, cov(0.005))
    assert r.state == LOST and "gate refused" in r.reason


def test_few_decisions_do_not_judge_the_ratio():
    q = QualityMonitor(QualityConfig(min_decisions=5))
    q.note_fix(0.0)
    q.note_update(0.5, True)
    q.note_update(0.6, False)
    q.note_update(0.7, False)
    r = q.evaluate(0.8, cov(0.005))
    assert r.state == LOCALIZED and math.isnan(r.rejection_ratio)


def test_hysteresis_keeps_the_state_from_flickering():
    q = QualityMonitor()
    q.note_fix(0.0)
    q.note_update(0.9, True)
    assert q.evaluate(1.0, cov(0.021)).state == DEGRADED
    # Just under the threshold is not enough to come back ...
    assert q.evaluate(1.0, cov(0.019)).state == DEGRADED
    # ... well under it is.
    assert q.evaluate(1.0, cov(0.015)).state == LOCALIZED
    assert q.evaluate(1.0, cov(0.019)).state == LOCALIZED


def test_non_finite_covariance_is_lost():
    q = QualityMonitor()
    q.note_fix(0.0)
    P = cov(0.005)
    P[0, 0] = math.nan
    r = q.evaluate(0.1, P)
    assert r.state == LOST and "not finite" in r.reason
    assert r.as_dict()["state"] == LOST
