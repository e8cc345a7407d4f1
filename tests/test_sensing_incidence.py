"""The projector-incidence filter (cell/sensing/incidence.py) against analytic truth: a sphere and a tilted
plane seen by a pinhole camera, their exact normals known, with the sensor's point noise added."""

from __future__ import annotations

import numpy as np
import pytest

from cell.errors import ConfigError
from cell.sensing.incidence import lit_too_obliquely, measured_normals, projector_incidence_deg

F_PX, W, H = 2000.0, 320, 240  # a pinhole camera's focal length (px) and image size
PROJECTOR_C = np.array([429.3, 0.0, 0.0])  # the prototype's baseline along camera x (mm)


def _rays() -> np.ndarray:
    u, v = np.meshgrid(np.arange(W) - W / 2 + 0.5, np.arange(H) - H / 2 + 0.5)
    d = np.stack([u / F_PX, v / F_PX, np.ones_like(u)], axis=-1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def _sphere(centre: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Organised points (H, W, 3), valid mask and true outward normals of a sphere in front of the camera."""
    d = _rays()
    b = d @ centre
    disc = b**2 - (centre @ centre - radius**2)
    valid = disc > 0
    t = b - np.sqrt(np.where(valid, disc, 0.0))
    p = np.where(valid[..., None], d * t[..., None], np.nan)
    n = (p - centre) / radius
    return p, valid, n


def _true_angle(p: np.ndarray, n: np.ndarray) -> np.ndarray:
    ray = PROJECTOR_C - p
    ray /= np.linalg.norm(ray, axis=-1, keepdims=True)
    return np.degrees(np.arccos(np.clip(np.sum(n * ray, axis=-1), -1, 1)))


def test_normals_of_a_noisy_sphere_match_the_analytic_ones():
    p, valid, n_true = _sphere(np.array([0.0, 0.0, 400.0]), 10.0)
    rng = np.random.default_rng(0)
    noisy = p + rng.normal(0, 0.008, p.shape)  # 8 um, the simulated sensor's noise on a sphere
    n = measured_normals(noisy, valid)
    ok = np.isfinite(n).all(axis=-1)
    # inside the silhouette (not its last pixels) every pixel gets a normal
    inner = valid & (_camera_angle(n_true) < 60)
    assert ok[inner].all()
    err = np.degrees(np.arccos(np.clip(np.sum(n[ok & inner] * n_true[ok & inner], axis=-1), -1, 1)))
    assert np.median(err) < 1.0 and np.percentile(err, 99) < 3.0


def _camera_angle(n: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(-np.sum(n * _rays(), axis=-1), -1, 1)))


def test_projector_incidence_and_the_filter_follow_the_true_angle():
    p, valid, n_true = _sphere(np.array([0.0, 0.0, 400.0]), 10.0)
    truth = _true_angle(p, n_true)
    angle = projector_incidence_deg(p, valid, PROJECTOR_C)
    # where the camera sees the sphere within 60 deg: beyond, the sphere turns by degrees per pixel and the
    # 5x5 window averages its normal (1-2 deg at 60-70 deg; the camera's limb, which the rim filter drops)
    both = valid & np.isfinite(angle) & (_camera_angle(n_true) < 60.0)
    assert np.percentile(np.abs(angle[both] - truth[both]), 95) < 1.0
    drop = lit_too_obliquely(p, valid, PROJECTOR_C, 80.0)
    # clear of the limit, the filter decides as the true angle does
    assert drop[valid & (truth > 82.0) & (_camera_angle(n_true) < 60.0)].all()
    assert not drop[both & (truth < 78.0)].any()
    assert not drop[~valid].any()


def test_planes_either_side_of_the_limit():
    """Planes turned about camera y so that the projector lights them at 72 +- 5 deg and at 88 +- 5 deg over
    the image (the ray to the projector leans 47 deg off the camera axis): one kept, one dropped whole."""
    d = _rays()
    for tilt_deg, kept in ((-25.0, True), (-41.0, False)):
        a = np.radians(tilt_deg)
        normal = np.array([np.sin(a), 0.0, -np.cos(a)])  # faces the camera; a < 0: away from the projector
        point = np.array([0.0, 0.0, 400.0])
        t = (point @ normal) / (d @ normal)
        p = d * t[..., None]
        truth = _true_angle(p, np.broadcast_to(-normal if normal[2] > 0 else normal, p.shape))
        assert (truth[3:-3, 3:-3] < 78).all() if kept else (truth[3:-3, 3:-3] > 82).all()
        drop = lit_too_obliquely(p, np.ones((H, W), bool), PROJECTOR_C, 80.0)
        inner = drop[3:-3, 3:-3]
        assert (not inner.any()) if kept else inner.all()


def test_a_limit_outside_0_90_is_refused():
    p, valid, _ = _sphere(np.array([0.0, 0.0, 400.0]), 10.0)
    with pytest.raises(ConfigError, match="max_projector_incidence_deg"):
        lit_too_obliquely(p, valid, PROJECTOR_C, 95.0)


@pytest.mark.parametrize("band_rows", [7, 64])
def test_normals_in_bands_are_the_whole_image_normals(monkeypatch: pytest.MonkeyPatch, band_rows: int):
    """The banded normals against one pass over the whole image (the module's band height set above the
    image): the same NaN pattern and, where finite, the same normals to within the last bits (OpenCV's box
    sums run down the rows from each band's first)."""
    import cell.sensing.incidence as incidence

    p, valid, _ = _sphere(np.array([3.0, -2.0, 400.0]), 12.0)
    noise = np.random.default_rng(1).normal(0, 0.008, p.shape)
    noisy = (p + noise).astype(np.float32)  # float32, as a cloud holds its points
    valid &= np.random.default_rng(2).random(valid.shape) > 0.02  # holes: windows with too few neighbours
    monkeypatch.setattr(incidence, "BAND_ROWS", 10 * H)
    whole = measured_normals(noisy, valid)
    whole_angle = projector_incidence_deg(noisy, valid, PROJECTOR_C)
    monkeypatch.setattr(incidence, "BAND_ROWS", band_rows)
    banded = measured_normals(noisy, valid)
    banded_angle = projector_incidence_deg(noisy, valid, PROJECTOR_C)
    assert np.isfinite(whole).all(-1).sum() > 0.5 * valid.sum()
    assert np.array_equal(np.isnan(banded), np.isnan(whole))
    assert np.allclose(banded, whole, rtol=0, atol=1e-12, equal_nan=True)
    assert np.array_equal(np.isnan(banded_angle), np.isnan(whole_angle))
    assert np.allclose(banded_angle, whole_angle, rtol=0, atol=1e-9, equal_nan=True)
    # the bands on two threads: each band's own numbers, so the same bits as one after the other
    assert np.array_equal(measured_normals(noisy, valid, workers=2), banded, equal_nan=True)
