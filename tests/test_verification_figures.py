"""The VDI/VDE 2634 figures against analytic truth: synthetic points with known form, noise and outliers."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import norm

from cell.verification.figures import (
    FitError,
    fit_plane,
    fit_sphere,
    flatness,
    n_excluded,
    probing_form,
    probing_size,
    sphere_spacing,
)


def fibonacci_sphere(n: int) -> np.ndarray:
    """Nearly uniform unit vectors (n, 3)."""
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = np.pi * (1 + 5**0.5) * i
    r = np.sqrt(1 - z**2)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


CENTRE = np.array([12.0, -40.0, 395.0])  # far from the origin, as in the camera frame


def test_exact_sphere_is_recovered() -> None:
    u = fibonacci_sphere(5000)
    fit = fit_sphere(CENTRE + 10.0 * u)
    assert np.allclose(fit.centre, CENTRE, atol=1e-9)
    assert fit.radius == pytest.approx(10.0, abs=1e-9)
    assert probing_form(fit) < 1e-9
    assert probing_size(fit, 20.0) == pytest.approx(0.0, abs=1e-9)


def test_form_of_a_p2_deformed_sphere() -> None:
    # r = R + A P2(cos theta): orthogonal to the radius and centre terms over the whole sphere, so the fit
    # keeps R and the centre, and PF is the range of A P2 = A (1 - (-1/2)) = 1.5 A
    u = fibonacci_sphere(20000)
    A, R = 0.02, 12.5
    p2 = 0.5 * (3 * u[:, 2] ** 2 - 1)
    fit = fit_sphere(CENTRE + (R + A * p2)[:, None] * u, outlier_fraction=0.0)
    assert fit.radius == pytest.approx(R, abs=1e-5)
    assert np.allclose(fit.centre, CENTRE, atol=1e-5)
    assert probing_form(fit) == pytest.approx(1.5 * A, rel=1e-3)


def test_outlier_rule_drops_at_most_three_per_mille() -> None:
    u = fibonacci_sphere(10000)
    pts = CENTRE + 10.0 * u
    assert n_excluded(len(pts)) == 30
    bad = pts.copy()
    bad[:30] += 0.5 * u[:30]  # 30 spikes 0.5 mm out: all excluded
    assert probing_form(fit_sphere(bad)) < 1e-6
    worse = pts.copy()
    worse[:31] += 0.5 * u[:31]  # one spike more than the rule allows stays in
    assert probing_form(fit_sphere(worse)) > 0.45


def test_noisy_cap_gives_unbiased_size_and_spacing() -> None:
    rng = np.random.default_rng(3)
    u = fibonacci_sphere(40000)
    cap = u[u[:, 2] < -0.2]  # the half a sensor sees (facing -z, toward the camera)
    sigma = 0.005
    L = 170.0
    axis = Rotation.from_rotvec([0.2, -0.4, 0.1]).apply([1.0, 0, 0])
    fits = []
    for c in (CENTRE - axis * L / 2, CENTRE + axis * L / 2):
        pts = c + (10.0 + rng.normal(0, sigma, len(cap)))[:, None] * cap
        fits.append(fit_sphere(pts))
    n = len(cap)
    # a cap constrains the centre along its axis less than the radius: allow several sigma/sqrt(n)
    assert abs(probing_size(fits[0], 20.0)) < 20 * sigma / np.sqrt(n) * 2
    assert abs(sphere_spacing(fits[0], fits[1], L)) < 40 * sigma / np.sqrt(n)
    # PF of Gaussian noise after the 0.3 % rule: the range between the 0.15 % and 99.85 % quantiles
    assert probing_form(fits[0]) == pytest.approx(2 * norm.ppf(1 - 0.0015) * sigma, rel=0.05)


def test_plane_form_and_orientation() -> None:
    x, y = np.meshgrid(np.linspace(-80, 80, 321), np.linspace(-20, 20, 81))
    A = 0.01
    z = A * np.cos(2 * np.pi * x / 40.0)  # four whole periods: orthogonal to tilt and offset
    R = Rotation.from_rotvec([0.3, 0.2, 1.0]).as_matrix()
    pts = np.column_stack([x.ravel(), y.ravel(), z.ravel()]) @ R.T + CENTRE
    fit = fit_plane(pts, outlier_fraction=0.0)
    assert abs(abs(fit.normal @ R[:, 2]) - 1) < 1e-8
    assert flatness(fit) == pytest.approx(2 * A, rel=1e-6)
    # with the rule the 0.3 % largest residuals go and the plane is refitted: F moves by under 1 %
    assert flatness(fit_plane(pts)) == pytest.approx(2 * A, rel=0.01)


def test_degenerate_input_is_refused() -> None:
    with pytest.raises(FitError, match="at least"):
        fit_sphere(np.zeros((5, 3)))
    line = np.column_stack([np.linspace(0, 1, 50), np.zeros(50), np.zeros(50)])
    with pytest.raises(FitError, match="collinear"):
        fit_plane(line)
    pts = CENTRE + 10.0 * fibonacci_sphere(100)
    pts[:10] = np.nan  # NaN points (invalid pixels) are ignored, not fitted
    assert fit_sphere(pts).radius == pytest.approx(10.0, abs=1e-9)
