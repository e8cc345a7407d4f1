"""The angle at which the projector lights each measured point, from the view's own organised cloud.

Near the projector's terminator (the surface turning away from the projector) the stripes are stretched over
many camera pixels, their edges blur, and the shading falls across the blurred edge: the decoded edge moves
and the point lands inside the surface. On the ideal world's 20 mm spheres the points the filter drops for
their angle (truly lit at 79-85 deg) read -16 um on average and down to -58 um, the kept ones -2.4 um (since
the decoder's edge-pair rule; before it, 25-67 um inside on average and down to -180 um: docs/sensing.md).
The planner already keeps the surface it counts within ``theta_projector_deg`` of eq 3.5; the sensor drops
what it lights more obliquely than ``sensor.max_projector_incidence_deg``, as commercial area sensors filter
by angle. The normal comes from the measured points (the nominal surface is not
known to the sensor, and a part may deviate from it), so the filter works the same for any part.
"""

from __future__ import annotations

from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np
from numpy.typing import NDArray

from cell.errors import ConfigError

BAND_ROWS = 256  # image rows per band of the normals: ~10 float64 (rows, W, 3) temporaries, not full images


def measured_normals(
    points_C: NDArray[np.floating], valid: NDArray[np.bool_], half_window_px: int = 2, workers: int = 1
) -> NDArray[np.float64]:
    """Unit surface normals (H, W, 3) of an organised cloud (camera frame, mm), facing the camera, NaN where
    the window around a pixel holds too few valid neighbours. The tangents are central differences of the
    points over ``half_window_px`` pixels, box-averaged over the window with invalid pixels left out (a
    normalised convolution), so 5-10 um point noise at a 0.2 mm pitch tilts a normal by well under 1 deg.
    Where the surface turns by degrees per pixel the window averages it (a 10 mm sphere at 400 mm: 1-2 deg
    at 60-70 deg from the camera, more at its limb, which the rim filter drops).

    Computed in bands of :data:`BAND_ROWS` rows, each with the ``2 * half_window_px`` rows around it that its
    normals read (a 5 MP view's normals took ten whole-image float64 temporaries, 1.1 GB, at the peak of the
    hires inspection's decode). A normal reads only its own window, so a band gives the normals the whole
    image gives, but for OpenCV's box sums, which run down the rows from the band's first: they may differ
    in the last bits (tests/test_sensing_incidence.py bounds it). ``workers``: threads the bands are computed
    on (NumPy and OpenCV release the GIL; the same numbers, a band's temporaries held by each)."""
    p = np.asarray(points_C)
    if p.ndim != 3 or p.shape[2] != 3 or p.shape[:2] != np.shape(valid):
        raise ConfigError(f"measured_normals: expected (H, W, 3) points and an (H, W) mask, got {p.shape}")
    out = np.empty(p.shape, dtype=np.float64)

    def one(rows: tuple[int, int, int, int]) -> None:
        start, end, lo, hi = rows
        band = _band_normals(np.asarray(p[lo:hi], dtype=np.float64), valid[lo:hi], half_window_px)
        out[start:end] = band[start - lo : end - lo]

    bands = list(_row_bands(p.shape[0], 2 * half_window_px))
    if workers > 1 and len(bands) > 1:
        with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="normals") as pool:
            list(pool.map(one, bands))
    else:
        for rows in bands:
            one(rows)
    return out


def _row_bands(height: int, halo: int) -> Iterator[tuple[int, int, int, int]]:
    """(start, end, lo, hi) of each band of :data:`BAND_ROWS` image rows: its rows [start, end) and, with the
    ``halo`` rows around it that a window reads, [lo, hi)."""
    for start in range(0, height, BAND_ROWS):
        end = min(start + BAND_ROWS, height)
        yield start, end, max(start - halo, 0), min(end + halo, height)


def _band_normals(
    p: NDArray[np.float64], valid: NDArray[np.bool_], half_window_px: int
) -> NDArray[np.float64]:
    """:func:`measured_normals` of one band of rows, all at once."""
    h = half_window_px
    ok = valid & np.isfinite(p).all(axis=2)
    z = np.where(ok[..., None], p, 0.0)
    # tangents along the image axes where both ends of the central difference are valid
    du = np.zeros_like(z)
    dv = np.zeros_like(z)
    okx = np.zeros_like(ok)
    oky = np.zeros_like(ok)
    du[:, h:-h] = z[:, 2 * h :] - z[:, : -2 * h]
    okx[:, h:-h] = ok[:, 2 * h :] & ok[:, : -2 * h]
    dv[h:-h, :] = z[2 * h :, :] - z[: -2 * h, :]
    oky[h:-h, :] = ok[2 * h :, :] & ok[: -2 * h, :]
    size = (2 * h + 1, 2 * h + 1)
    tu = np.stack([cv2.boxFilter(du[..., k] * okx, -1, size, normalize=False) for k in range(3)], axis=-1)
    tv = np.stack([cv2.boxFilter(dv[..., k] * oky, -1, size, normalize=False) for k in range(3)], axis=-1)
    nu = cv2.boxFilter(okx.astype(np.float64), -1, size, normalize=False)
    nv = cv2.boxFilter(oky.astype(np.float64), -1, size, normalize=False)
    n = np.cross(tu, tv)
    norm = np.linalg.norm(n, axis=2, keepdims=True)
    enough = ok & (nu >= size[0]) & (nv >= size[0])
    with np.errstate(invalid="ignore", divide="ignore"):
        n = n / norm
    n = np.where((enough & (norm[..., 0] > 0))[..., None], n, np.nan)
    facing = np.sum(n * p, axis=2) > 0  # normals point back toward the camera at the origin
    return np.where(facing[..., None], -n, n)


def projector_incidence_deg(
    points_C: NDArray[np.floating],
    valid: NDArray[np.bool_],
    projector_centre_C: NDArray[np.floating],
    half_window_px: int = 2,
    normals: NDArray[np.float64] | None = None,
) -> NDArray[np.float64]:
    """Angle (deg, (H, W)) between each point's measured normal and its ray to the projector's centre
    (camera frame, mm); NaN where no normal could be measured. Computed in bands of :data:`BAND_ROWS` rows,
    each with the ``2 * half_window_px`` rows around it that its normals read (a 5 MP image's normals took
    ten full-image float64 temporaries, 1.2 GB). ``normals``: :func:`measured_normals` of the same cloud with
    the same window when the caller has them (the same numbers: each band's are computed the same way)."""
    out = np.empty(np.shape(valid), dtype=np.float64)
    centre = np.asarray(projector_centre_C, dtype=np.float64)
    for start, end, lo, hi in _row_bands(np.shape(valid)[0], 2 * half_window_px):
        band = np.asarray(points_C[lo:hi], dtype=np.float64)
        if normals is None:
            n = _band_normals(band, valid[lo:hi], half_window_px)[start - lo : end - lo]
        else:
            n = normals[start:end]
        ray = centre - band[start - lo : end - lo]
        with np.errstate(invalid="ignore"):
            ray /= np.linalg.norm(ray, axis=2, keepdims=True)
            cos = np.clip(np.sum(n * ray, axis=2), -1.0, 1.0)
        out[start:end] = np.degrees(np.arccos(cos))
    return out


def lit_too_obliquely(
    points_C: NDArray[np.floating],
    valid: NDArray[np.bool_],
    projector_centre_C: NDArray[np.floating],
    max_deg: float,
    normals: NDArray[np.float64] | None = None,
) -> NDArray[np.bool_]:
    """Valid pixels the projector lights more obliquely than ``max_deg`` (or whose normal cannot be measured:
    an isolated pixel or a thin strip, which the link filter and the rim filter also drop); ``normals``: the
    cloud's :func:`measured_normals` when the caller has them."""
    if not 0 < max_deg <= 90:
        raise ConfigError(f"max_projector_incidence_deg must be in (0, 90], got {max_deg}")
    angle = projector_incidence_deg(points_C, valid, projector_centre_C, normals=normals)
    with np.errstate(invalid="ignore"):
        return valid & ~(angle <= max_deg)
