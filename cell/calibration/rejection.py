"""Rejection of badly located encoded points in the per-pixel calibration (dissertation 5.1.1, eq 2.7).

A few encoded points are located wrongly: near the image border a code is seen in only a few steps (a short
height range makes eq 2.7 ill-conditioned: d and S even come out negative), and a stripe edge spoiled by noise
moves one step's position. Three robust tests, each against a scale estimated from the data itself:

1. per sample: the eq 2.7 fit residuals h_k - L_k S/(d + L_k) of every point and step; the worst sample of a
   point beyond ``k`` robust sigmas (1.4826 x the MAD of the residuals over all points) is dropped and the
   point refit, a few times;
2. per point: the steps left must span at least ``min_span`` of the stepped height range;
3. per point: the ratio d/S (the slope dh/dL at the reference plane, which is well determined even though d
and
   S are not) must agree with the median of its code-grid neighbours within ``k`` robust sigmas of those
   differences; a sensor's geometry varies smoothly across the field, a mislocated point does not.
"""

from __future__ import annotations

import warnings

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import NDArray

from cell.sensing.triangulate import fit_d_S

MAD_TO_SIGMA = 1.4826  # sigma of a normal distribution per unit of median absolute deviation


def robust_sigma(x: NDArray) -> float:
    """1.4826 x the median absolute deviation from the median of the finite values of ``x``."""
    v = x[np.isfinite(x)]
    return float(MAD_TO_SIGMA * np.median(np.abs(v - np.median(v)))) if len(v) else float("nan")


def fit_residuals(h: NDArray, L: NDArray, d: NDArray, S: NDArray) -> NDArray[np.float64]:
    """(n, N) residuals h_k - L_k S / (d + L_k) of the eq 2.8 model per step and point (NaN where L is)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return h[:, None] - L * S / (d + L)


def robust_fit(
    h: NDArray, L: NDArray, k: float = 5.0, min_span: float = 0.5, max_drops: int = 3
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], dict[str, int]]:
    """Eq 2.7 per point with tests 1 and 2: returns d, S (NaN for rejected points), the cleaned L (rejected
    samples NaN) and counts of what was rejected. ``h`` (n,) step heights, ``L`` (n, N) mm."""
    L = np.array(L, dtype=np.float64)
    d, S = fit_d_S(h, L)
    sigma = robust_sigma(fit_residuals(h, L, d, S)[1:])  # step 0: L = h = 0 exactly, no information on scale
    cols = np.arange(L.shape[1])
    n_bad = 0
    for _ in range(max_drops):  # one bad sample pulls the whole fit: drop the worst per point, refit, repeat
        r = np.abs(fit_residuals(h, L, d, S))
        worst = np.argmax(np.nan_to_num(r, nan=-1.0), axis=0)
        # keep >= 4 samples: 2 for d and S, 2 degrees of freedom left to judge the fit by
        drop = (r[worst, cols] > k * sigma) & (np.isfinite(L).sum(0) > 4)
        if not drop.any():
            break
        L[worst[drop], cols[drop]] = np.nan
        n_bad += int(drop.sum())
        d, S = fit_d_S(h, L)
    seen = np.isfinite(L)
    hh = np.where(seen, h[:, None], np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # points seen in no step
        span = np.nanmax(hh, axis=0) - np.nanmin(hh, axis=0)
    short = ~(span >= min_span * (h.max() - h.min()))
    unphysical = ~((d > 0) & (S > 0))
    d[short | unphysical], S[short | unphysical] = np.nan, np.nan
    counts = {
        "samples_rejected": n_bad,
        "short_range_points": int((short & ~unphysical).sum()),
        "unphysical_points": int(unphysical.sum()),
    }
    return d, S, L, counts


def spatial_outliers(value: NDArray, side: int, k: float = 5.0, radius: int = 2) -> NDArray[np.bool_]:
    """Test 3: True where ``value`` (side*side,), on the square code grid, differs from the median of its
    (2 radius + 1)^2 neighbours (itself excluded, NaN ignored) by more than ``k`` robust sigmas."""
    # The smooth trend across the field (a quadratic surface, least squares) is removed first: on a sloped
    # map, one odd neighbour shifts the neighbourhood median by a rank, i.e. by the local slope, and would
    # make its neighbours look odd too. Odd reflection (2 f(edge) - f(inside)) continues what is left past the
    # grid edge, so that edge points are compared with an unbiased neighbourhood.
    v = np.asarray(value, dtype=np.float64).ravel()
    y, x = (a.ravel() / side for a in np.mgrid[0:side, 0:side])
    A = np.column_stack([np.ones_like(x), x, y, x * x, x * y, y * y])
    ok = np.isfinite(v)
    if ok.sum() >= A.shape[1]:
        v = v - A @ np.linalg.lstsq(A[ok], v[ok], rcond=None)[0]
    g = np.pad(v.reshape(side, side), radius, mode="reflect", reflect_type="odd")
    win = sliding_window_view(g, (2 * radius + 1, 2 * radius + 1)).reshape(side, side, -1).copy()
    win[..., win.shape[-1] // 2] = np.nan  # the point itself
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # isolated points: all-NaN neighbourhoods
        med = np.nanmedian(win, axis=-1).ravel()
    dev = v - med
    return np.abs(dev) > k * robust_sigma(dev)
