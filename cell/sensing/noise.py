"""How far image noise moves each decoded pixel: the sub-pixel decode noise, estimated from the stack itself.

No number of the camera's data sheet is used: the noise is measured in the view's own images. A pattern and
its inverse add up to white + black at every pixel (the projector is linear after its gamma LUT, and the
camera's response is linear), whatever the pattern shows there; so over the K pattern/inverse pairs of a stack
the sums S_k = P_k + I_k of one pixel differ only by noise, and their sample variance estimates
var(P) + var(I). Pooled over the pixels of a view against the level W + B (binned, averaged), it gives the
photon-transfer line var(P) + var(I) = alpha + beta (W + B) (DN^2; alpha: read noise and quantisation of two
frames, beta: shot noise per DN; EMVA 1288's mean-variance method on pairs instead of flat fields).

A GCLS edge lies where D = P - I changes sign between pixels c and c+1, at x = c + D(c) / (D(c) - D(c+1))
(decode.py); D has the variance var(P) + var(I) = alpha + beta (W + B) there (P + I = W + B again), so
    var(x) = (alpha + beta (W + B)) ((1 - t)^2 + t^2) / s^2,   s = D(c) - D(c+1) the edge's swing,
t = D(c)/s its sub-pixel place, unknown after the decode: its mean over a uniform t is 2/3. A pixel
between the edges of codes q and q+1 takes its projector coordinate by interpolation at its fraction t'
between them, so its own coordinate moves like an edge displaced by (1 - t') dx_q + t' dx_{q+1}: in camera
pixels along the row, with the swing of both edges s = sharpness * modulation (the decoder keeps both),
    sigma_x = sqrt(alpha + beta (W + B)) / s * sqrt(2/3) * sqrt((1 - t')^2 + t'^2).
That is the "error of L" that the one-pixel model of eq 2.5 turns into a height error
(cell.analysis.uncertainty).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from cell.errors import ConfigError
from cell.sensing.decode import AxisDecode, Decoded
from cell.sensing.patterns import PatternSet

MIN_PIXELS = 200  # fewer usable pixels than this: the view's noise cannot be measured
BAND_ROWS = 256  # image rows per band of the per-pixel figures (a few (rows, W, 3) float64 temporaries)
N_BINS = 16  # levels (quantiles of W + B) over which the per-pixel variances are averaged


@dataclass(frozen=True)
class ImageNoise:
    """The view's photon-transfer line: var(P) + var(I) = ``alpha_dn2`` + ``beta_dn`` * (W + B) (DN^2), from
    ``pixels`` pixels."""

    alpha_dn2: float
    beta_dn: float
    pixels: int

    def pair_variance(self, level_dn: NDArray[np.floating]) -> NDArray[np.float64]:
        """var(P) + var(I) (DN^2) at the level W + B (DN) of each pixel; never below a quantisation step's."""
        return np.maximum(self.alpha_dn2 + self.beta_dn * np.asarray(level_dn, dtype=np.float64), 1 / 6)

    def to_json(self) -> dict[str, float | int]:
        return {
            "alpha_dn2": round(self.alpha_dn2, 4),
            "beta_dn": round(self.beta_dn, 6),
            "pixels": self.pixels,
        }


def pair_names(patterns: PatternSet) -> list[tuple[int, int]]:
    """(pattern, inverse) frame indices of every coded pair (white/black not included)."""
    names = patterns.names
    return [(i, names.index(n + "_inv")) for i, n in enumerate(names) if n + "_inv" in names]


def estimate_image_noise(
    stack: NDArray, patterns: PatternSet, valid: NDArray[np.bool_], bit_depth: int = 8
) -> ImageNoise:
    """The photon-transfer line of one view from its own (N, H, W) stack, over the pixels ``valid`` (decoded,
    so lit and coded) that no frame saturates or clips at zero."""
    pairs = pair_names(patterns)
    if len(pairs) < 3:
        raise ConfigError(f"image noise needs >= 3 pattern/inverse pairs, the pattern set has {len(pairs)}")
    top = 2**bit_depth - 1
    k = len(pairs)
    ok = np.asarray(valid, dtype=bool).copy()
    # the camera's integer frames are summed in integers (exact: the float64 sums of the same integers
    # are too, so the same numbers, in 4-byte arrays where they fit, at about half the CPU); others in float64
    exact = np.issubdtype(np.asarray(stack[0]).dtype, np.integer) and k * (2 * top) ** 2 < 2**31
    acc = np.int32 if exact else np.float64
    total = np.zeros(ok.shape, acc)
    square = np.zeros(ok.shape, acc)
    for i, j in pairs:
        p, q = stack[i], stack[j]
        ok &= (p < top) & (q < top) & (p > 0) & (q > 0)
        s = p.astype(acc)
        s += q
        total += s
        s *= s
        square += s
    level = total[ok] / k
    var = (square[ok] - k * level * level) / (k - 1)
    if len(level) < MIN_PIXELS:
        raise ConfigError(
            f"image noise: only {len(level)} decoded, unsaturated pixels (need {MIN_PIXELS}); is the part "
            "in view?"
        )
    edges = np.unique(np.quantile(level, np.linspace(0, 1, N_BINS + 1)))
    which = np.clip(np.searchsorted(edges, level, side="right") - 1, 0, len(edges) - 2)
    count = np.bincount(which, minlength=len(edges) - 1)
    used = count >= 20
    x = np.bincount(which, weights=level, minlength=len(edges) - 1)[used] / count[used]
    # the mean of sample variances is unbiased; a few pixels at depth steps (mixed, moving) are trimmed first
    cut = np.quantile(var, 0.995)
    keep = var <= cut
    kc = np.bincount(which[keep], minlength=len(edges) - 1)[used]
    y = np.bincount(which[keep], weights=var[keep], minlength=len(edges) - 1)[used] / np.maximum(kc, 1)
    w = kc.astype(np.float64)
    if len(x) >= 2 and np.ptp(x) > 0:
        A = np.column_stack([np.ones_like(x), x]) * np.sqrt(w)[:, None]
        alpha, beta = np.linalg.lstsq(A, y * np.sqrt(w), rcond=None)[0]
        if beta < 0:  # no level dependence seen: one variance for all
            alpha, beta = float(np.average(y, weights=w)), 0.0
    else:
        alpha, beta = float(np.average(y, weights=w)), 0.0
    return ImageNoise(float(alpha), float(beta), int(len(level)))


def edge_sigma_px(
    decoded: Decoded, axis: AxisDecode, noise: ImageNoise, shift_px: float, offset_px: float
) -> NDArray[np.float64]:
    """sigma_x (H, W): the 1-sigma displacement (camera pixels, along the coded row) of each pixel's decoded
    projector coordinate caused by image noise (see the module docstring); NaN where the pixel has no code.
    ``shift_px`` / ``offset_px``: the code's line shift and first coded projector pixel (AxisCode). Pixel by
    pixel, in bands of :data:`BAND_ROWS` rows (a 5 MP view's whole-image float64 temporaries were ~0.3 GB)."""
    mod, contrast, sharp, u = decoded.modulation_dn, decoded.contrast, axis.sharpness, axis.u
    out = np.empty(np.shape(mod), dtype=np.float64)
    for a in range(0, len(out), BAND_ROWS):
        b = slice(a, a + BAND_ROWS)
        out[b] = _edge_sigma(mod[b], contrast[b], sharp[b], u[b], axis.valid[b], noise, shift_px, offset_px)
    return out


def _edge_sigma(
    modulation_dn: NDArray[np.floating],
    contrast_: NDArray[np.floating],
    sharpness: NDArray[np.floating],
    u_px: NDArray[np.floating],
    valid: NDArray[np.bool_],
    noise: ImageNoise,
    shift_px: float,
    offset_px: float,
) -> NDArray[np.float64]:
    """:func:`edge_sigma_px` of some rows."""
    mod = np.asarray(modulation_dn, dtype=np.float64)
    contrast = np.asarray(contrast_, dtype=np.float64)
    # W + B from the modulation W - B and the contrast (W - B)/(W + B) the decoder kept
    with np.errstate(invalid="ignore", divide="ignore"):
        level = np.where(contrast > 0, mod / contrast, np.nan)
        swing = np.asarray(sharpness, dtype=np.float64) * mod
        t = _phase(u_px, shift_px, offset_px)
        spread = np.sqrt((1 - t) ** 2 + t**2)
        sigma = np.sqrt(noise.pair_variance(level)) / swing * np.sqrt(2.0 / 3.0) * spread
    return np.where(valid & (swing > 0), sigma, np.nan)


N_PHASES = 10  # sub-code phase bins of the quantisation curve


@dataclass(frozen=True)
class Quantisation:
    """The decoder's sub-code error of one view, measured on its own points: ``curve_px`` (N_PHASES) the mean
    displacement (camera px along the row) by the pixel's phase t' between its two codes, ``rms_px`` its rms
    over the view's pixels, ``scatter_px`` what remains around the curve (image noise and what the curve
    misses), ``noise_px`` the image noise's share of it (rms of :func:`edge_sigma_px`), from ``pixels``
    pixels."""

    curve_px: NDArray[np.float64]
    rms_px: float
    scatter_px: float
    noise_px: float
    pixels: int

    @property
    def total_px(self) -> float:
        """The quantisation error a pixel carries besides its own image noise (camera px, 1 sigma): the curve
        and the part of the scatter that image noise does not explain (the curve is a view's mean; pixels of
        one phase still differ by their edges' own phases and widths)."""
        return float(np.sqrt(self.rms_px**2 + max(self.scatter_px**2 - self.noise_px**2, 0.0)))

    def to_json(self) -> dict[str, float | int | list[float]]:
        return {
            "rms_px": round(self.rms_px, 5),
            "scatter_px": round(self.scatter_px, 5),
            "noise_px": round(self.noise_px, 5),
            "total_px": round(self.total_px, 5),
            "curve_px": [round(float(c), 5) for c in self.curve_px],
            "pixels": self.pixels,
        }


def code_phase(axis: AxisDecode, shift_px: float, offset_px: float) -> NDArray[np.float64]:
    """t' (H, W) in [0, 1): where each pixel lies between the edges of its code q and q + 1."""
    out = np.empty(np.shape(axis.u), dtype=np.float64)
    for a in range(0, len(out), BAND_ROWS):  # in bands: no whole-image float64 temporaries
        b = slice(a, a + BAND_ROWS)
        out[b] = _phase(axis.u[b], shift_px, offset_px)
    return out


def _phase(u_px: NDArray[np.floating], shift_px: float, offset_px: float) -> NDArray[np.float64]:
    """t' of some pixels from their decoded projector coordinates (:func:`code_phase`)."""
    return np.mod((np.asarray(u_px, dtype=np.float64) + 0.5 - offset_px) / shift_px, 1.0)


def quantisation(
    points_C: NDArray[np.floating],
    normals_C: NDArray[np.floating],
    valid: NDArray[np.bool_],
    mm_per_px: NDArray[np.floating],
    phase: NDArray[np.floating],
    sigma_x_px: NDArray[np.floating],
    half_window_px: int = 3,
) -> Quantisation:
    """The sub-code quantisation error of a view (dissertation Fig 2.4: an edge between pixels n and n+1 is
    found by interpolating two samples of a blurred step, which is exact only for some profiles; the pixel's
    coordinate then interpolates between two such edges). It is a function of where the pixel sits between
    its codes (t'), the same all over a view whose stripes have similar width and blur, so it shows in the
    view's own points: each point's offset along its normal from the mean of its (2h+1)^2 neighbours (a
    smooth surface is flat at that scale; the window spans several codes, so the curve averages out of the
    mean), in camera pixels (divided by ``mm_per_px``,
    :func:`cell.sensing.error_model.normal_error_per_pixel`), averaged per phase bin over the view: noise
    and shape average out, the quantisation curve stays. ``sigma_x_px``: each pixel's image-noise sigma
    (:func:`edge_sigma_px`), to tell noise from the rest of the scatter."""
    p, n = np.asarray(points_C), np.asarray(normals_C)
    ok = valid & np.isfinite(p).all(-1) & np.isfinite(n).all(-1)
    size = (2 * half_window_px + 1,) * 2
    cnt = cv2.boxFilter(ok.astype(np.float64), -1, size, normalize=False)
    full = ok & (cnt >= size[0] * size[1])
    # the window sums one coordinate at a time, the offsets in bands of rows (a 5 MP view's (H, W, 3) float64
    # copies and temporaries were ~0.8 GB at the decode's peak); each pixel's offset is the same einsum of
    # the same float64 numbers as over the whole image: the same bits
    mean = [
        cv2.boxFilter(np.where(ok, np.asarray(p[..., k], np.float64), 0.0), -1, size, normalize=False)
        for k in range(3)
    ]
    mm = np.broadcast_to(np.asarray(mm_per_px, np.float64), ok.shape)
    r = np.empty(ok.shape, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        for a in range(0, ok.shape[0], BAND_ROWS):
            b = slice(a, a + BAND_ROWS)
            d = np.asarray(p[b], np.float64) - np.stack([m[b] for m in mean], -1) / cnt[b, :, None]
            r[b] = np.einsum("ijk,ijk->ij", d, np.asarray(n[b], np.float64)) / mm[b]
    use = full & np.isfinite(r) & np.isfinite(phase)
    r, t, sx = r[use], np.asarray(phase)[use], np.asarray(sigma_x_px, np.float64)[use]
    if len(r) < MIN_PIXELS:
        return Quantisation(np.zeros(N_PHASES), 0.0, 0.0, 0.0, int(len(r)))
    # a point's own offset counts once in its window's mean: scale back by (1 - 1/N)
    r = r / (1.0 - 1.0 / (size[0] * size[1]))
    k = np.minimum((t * N_PHASES).astype(np.int64), N_PHASES - 1)
    med = np.median(r)
    mad = 1.4826 * np.median(np.abs(r - med))
    keep = np.abs(r - med) <= 5 * mad + 1e-9  # steps and spikes the rim filter left
    cnt_k = np.bincount(k[keep], minlength=N_PHASES)
    curve = np.bincount(k[keep], weights=r[keep], minlength=N_PHASES) / np.maximum(cnt_k, 1)
    curve -= np.average(curve, weights=cnt_k)  # the mean offset is the surface's, not the decoder's
    rms = float(np.sqrt(np.average(curve**2, weights=cnt_k)))
    scatter = float(np.sqrt(np.mean((r[keep] - curve[k[keep]]) ** 2)))
    noise = float(np.sqrt(np.nanmean(sx[keep] ** 2)))
    return Quantisation(curve, rms, scatter, noise, int(keep.sum()))
