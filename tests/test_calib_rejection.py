"""Rejection of badly located encoded points (cell/calibration/rejection.py) and the robust gauge slot test,
on synthetic data with analytic truth: eq 2.8 heights h = L S / (d + L) for a known d, S per point."""

from __future__ import annotations

import numpy as np
import pytest

from cell.calibration.rejection import robust_fit, spatial_outliers
from cell.calibration.validation import GaugeSlot, slot_test

D_MM, S_MM = 429.3, 393.7


def _steps(n_points, rng, noise_mm=0.0005):
    h = np.arange(31, dtype=np.float64)
    d = D_MM + rng.normal(0, 2.0, n_points)  # smooth-ish variation across points
    S = S_MM + 0.0 * d
    L = (h[:, None] * d) / (S - h[:, None])  # invert h = L S / (d + L)
    return h, d, S, L + rng.normal(0, noise_mm, L.shape)


def test_robust_fit_drops_bad_samples_and_short_ranges():
    rng = np.random.default_rng(0)
    h, d, S, L = _steps(400, rng)
    L[12, 7] += 0.5  # one step of point 7 mislocated by 0.5 mm on the reference plane
    L[5:, 9] = np.nan  # point 9 seen only in steps 0-4 (image border)
    d_fit, S_fit, L_clean, counts = robust_fit(h, L)
    assert np.isnan(L_clean[12, 7]) and counts["samples_rejected"] >= 1
    assert np.isnan(d_fit[9])
    ratio = d_fit / S_fit
    good = np.isfinite(ratio)
    assert good.sum() >= 395
    # d/S is what the fit determines well: against truth for every kept point
    assert np.max(np.abs(ratio[good] - (d / S)[good])) < 2e-3
    assert abs(ratio[7] - d[7] / S[7]) < 2e-3  # the point with the bad step was repaired, not lost


def test_spatial_outliers_flag_only_the_odd_point():
    side = 32
    y, x = np.mgrid[0:side, 0:side]
    value = 1.09 + 1e-3 * x + 5e-4 * y + np.random.default_rng(1).normal(0, 1e-5, (side, side))
    value[10, 20] += 0.01
    flags = spatial_outliers(value.ravel(), side).reshape(side, side)
    assert flags[10, 20] and flags.sum() == 1


def test_slot_test_robust_to_stray_points():
    rng = np.random.default_rng(2)
    slots = [
        GaugeSlot(depth_um=dep, x_range_mm=(x0, x0 + 10.0), y_range_mm=(-50.0, 50.0))
        for dep, x0 in [(32.0, -50.0), (14.0, -20.0), (6.0, 10.0), (0.0, 40.0)]
    ]
    p = np.column_stack([rng.uniform(-70, 70, 200_000), rng.uniform(-50, 50, 200_000), np.zeros(200_000)])
    for s in slots:
        inside = (p[:, 0] > s.x_range_mm[0]) & (p[:, 0] < s.x_range_mm[1])
        p[inside, 2] -= s.depth_um / 1000
    p[:, 2] += rng.normal(0, 0.016, len(p))  # the sensor's noise
    stray = rng.choice(len(p), 400, replace=False)
    p[stray, 2] += rng.choice([-3.0, 3.0], 400)  # 0.2 % gross outliers (multipath, edges)
    res = {r["index"]: r for r in slot_test(p, slots)}
    for i in range(3):
        assert res[i]["resolved"], res[i]
        assert res[i]["measured_um"] == pytest.approx(slots[i].depth_um, abs=2.0)
    assert not res[3]["resolved"]  # no slot: nothing to find


def test_slot_test_takes_out_tilt_and_placement():
    """The gauge measured through a robot pose and hand-eye: tilted 0.05 deg about y (9 um over a slot's
    10 mm) and 0.05 deg about x, and 1.5 mm off its drawing position in x and y, with most points on one side
    of each slot missing (a shadow, a glint): a difference of medians would take the tilt between the two
    sides' unequal shares for depth; the plane through both bands does not. Depths within 1.5 um."""
    rng = np.random.default_rng(3)
    slots = [
        GaugeSlot(depth_um=dep, x_range_mm=(x0, x0 + 10.0), y_range_mm=(-50.0, 50.0))
        for dep, x0 in [(32.0, -50.0), (24.0, -20.0), (14.0, 10.0), (6.0, 40.0)]
    ]
    n = 300_000
    p = np.column_stack([rng.uniform(-75, 75, n), rng.uniform(-50, 50, n), np.zeros(n)])
    for s in slots:  # the real gauge, where it lies
        inside = (p[:, 0] > s.x_range_mm[0] + 1.5) & (p[:, 0] < s.x_range_mm[1] + 1.5)
        p[inside, 2] -= s.depth_um / 1000
    p[:, 1] += 1.5
    p[:, 2] += np.tan(np.radians(0.05)) * (p[:, 0] + p[:, 1]) + rng.normal(0, 0.004, n)
    beyond = np.zeros(n, bool)
    for s in slots:  # keep one point in ten in the band beyond each slot's +x wall
        x1 = s.x_range_mm[1]
        beyond |= (p[:, 0] > x1 + 2.0) & (p[:, 0] < x1 + 8.0)
    p = p[~beyond | (rng.random(n) < 0.1)]
    res = slot_test(p, slots)
    for r, s in zip(res, slots, strict=True):
        assert r["resolved"], r
        assert r["measured_um"] == pytest.approx(s.depth_um, abs=1.5)
