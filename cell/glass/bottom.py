"""Geometric rejection of the bottom-skin copies of the marker dots (dissertation 2.5, Figs 2.18-2.22).

Light that enters the pane, reflects at the bottom skin and leaves through the top runs parallel to the top
reflection, shifted sideways by the thickness (Fig 2.18). On the screen, the bottom copy of the dot seen at a
pixel therefore lies a predictable vector delta from the top reflection's screen point. For each detection,
its view ray meets the CAD at P with normal n (the seed); the bottom path is predicted with the skins taken as
parallel planes at P (the pane's radius of curvature, metres, is far above the few-mm path in the glass):
refract in (Snell), travel to the plane one thickness below, mirror, travel back, leave parallel to the top
reflection. Snell refraction is written out here (four lines) rather than imported from the simulator so that
the measurement does not depend on the fake.

Two tests, both insensitive to the CAD's shape error (which moves the two hypotheses together):
- pairing: the bottom copy of the dot seen at pixel u appears at u + du, du = -J^-1 delta with J the
  pixel -> screen Jacobian of the top reflection. A detection found where another detection's bottom copy
  must be is that copy (the top copy is on the near side of the pair);
- a blob whose area exceeds ``area_range[1]`` x the area a dot should cover there (its diameter through
  |det J|) has merged with its copy (thick glass seen so that the copy touches the dot) and its centroid lies
  between them; one below ``area_range[0]`` is a fragment;
- unpaired detections (the partner was not detected: tinted glass drops the weaker copies at the threshold)
  are judged by which hypothesis, top or bottom, lands nearer to a screen dot, with a margin: a detection is
  taken for a bottom copy only when its bottom hypothesis is nearer by ``margin`` of the offset |delta|.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from cell.glass.surface import plane_hits, reflect


@dataclass(frozen=True)
class CopyPrediction:
    """Per detection (N): the screen points (mm, {S}) of the top and the bottom hypotheses and the pixel
    offset (N, 2) at which the detection's own bottom copy appears; ``mm2_per_px`` is the screen area one
    pixel sees there (|det J|)."""

    screen_top: NDArray[np.float64]
    screen_bottom: NDArray[np.float64]
    pixel_offset: NDArray[np.float64]
    mm2_per_px: NDArray[np.float64]


def bottom_exit(
    points: NDArray[np.float64],
    normals: NDArray[np.float64],
    dirs: NDArray[np.float64],
    thickness_mm: float,
    refractive_index: float,
) -> NDArray[np.float64]:
    """Where the bottom-skin path of view rays ``dirs`` entering at ``points`` (unit ``normals`` facing the
    camera) leaves the top skin again (N, 3, world mm), skins taken as parallel planes."""
    cos_i = -np.einsum("ij,ij->i", dirs, normals)
    eta = 1.0 / refractive_index
    cos_t = np.sqrt(1.0 - eta**2 * (1.0 - cos_i**2))
    d_in = eta * dirs + (eta * cos_i - cos_t)[:, None] * normals
    # in: thickness / cos_t to the bottom plane; mirrored, the same length back up; net move in the plane
    return points + (2.0 * thickness_mm / cos_t)[:, None] * (d_in + cos_t[:, None] * normals)


def predict_copies(
    pixels: NDArray[np.float64],
    rays,
    cad,
    T_W_S: NDArray[np.float64],
    thickness_mm: float,
    refractive_index: float,
) -> CopyPrediction:
    """Top and bottom screen hypotheses of detections at ``pixels`` (N, 2) and their bottom copies' pixel
    offsets. ``rays(pixels) -> (origins, dirs)`` is the view-vector calibration, ``cad`` the nominal
    :class:`cell.glass.surface.SmoothSurface`, ``T_W_S`` the screen pose."""
    n = len(pixels)
    steps = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])  # the pixel and its +u, +v neighbours
    o, d = rays((pixels[None] + steps[:, None]).reshape(-1, 2))
    finite = np.all(np.isfinite(o), axis=1) & np.all(np.isfinite(d), axis=1)
    o, d = np.nan_to_num(o), np.nan_to_num(d, nan=1.0 / np.sqrt(3))
    hit = cad.cast(o, d)
    nrm = np.nan_to_num(hit.normal)
    nrm = np.where((np.einsum("ij,ij->i", nrm, d) > 0)[:, None], -nrm, nrm)
    p = np.nan_to_num(hit.point)
    out = reflect(d, nrm)
    top = plane_hits(p, out, T_W_S).reshape(3, n, 2)
    bottom = plane_hits(bottom_exit(p, nrm, d, thickness_mm, refractive_index), out, T_W_S)[:n]
    bad = ~(hit.hit & finite).reshape(3, n).all(axis=0)
    top[:, bad], bottom[bad] = np.nan, np.nan
    J = np.stack([top[1] - top[0], top[2] - top[0]], axis=2)  # (N, 2 screen, 2 pixel)
    delta = bottom - top[0]
    ok = np.all(np.isfinite(J), axis=(1, 2)) & np.all(np.isfinite(delta), axis=1)
    du = np.full((n, 2), np.nan)
    if np.any(ok):
        du[ok] = -np.linalg.solve(J[ok], delta[ok][:, :, None])[:, :, 0]
    area = np.full(n, np.nan)
    area[ok] = np.abs(np.linalg.det(J[ok]))
    return CopyPrediction(top[0], bottom, du, area)


def blob_area_ok(
    area_px: NDArray[np.int64],
    pred: CopyPrediction,
    dot_diameter_mm: float,
    area_range: tuple[float, float] = (0.3, 1.5),
) -> NDArray[np.bool_]:
    """Detections whose pixel area is within ``area_range`` x the area a single dot covers there."""
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = area_px * pred.mm2_per_px / (np.pi * dot_diameter_mm**2 / 4)
    return (ratio >= area_range[0]) & (ratio <= area_range[1])


def bottom_copies(
    pixels: NDArray[np.float64],
    pred: CopyPrediction,
    dots_mm: NDArray[np.float64],
    pair_tol: float = 0.3,
    k_local: int = 8,
) -> NDArray[np.bool_]:
    """Mask of detections taken for bottom-skin copies (see the module docstring).

    Pairs: detection j lies within ``pair_tol`` x |du_i| of u_i + du_i. Unpaired detections: the shape
    error shifts every screen prediction by a smooth field s(u); it is estimated at each detection as the
    median residual (prediction - nearest dot) of its ``k_local`` nearest references (the paired
    detections under their known hypothesis, or, with fewer than ``k_local`` pairs, all detections under the
    top hypothesis: the weaker copies are then mostly below the threshold). A detection is a bottom copy
    when its bottom hypothesis, corrected by s, lands nearer to a dot than its top one.
    """
    n = len(pixels)
    copy = np.zeros(n, dtype=bool)
    ok = np.all(np.isfinite(pred.pixel_offset), axis=1) & np.all(np.isfinite(pred.screen_bottom), axis=1)
    if n == 0 or not np.any(ok):
        return copy
    idx = np.flatnonzero(ok)
    dist, j = cKDTree(pixels).query(pixels[idx] + pred.pixel_offset[idx], distance_upper_bound=1e9)
    paired = dist <= pair_tol * np.linalg.norm(pred.pixel_offset[idx], axis=1)
    claim = np.full(n, -1)
    claim[idx[paired]] = np.asarray(j)[paired]
    # chains: a copy's own predicted copy can land on the next dot's top copy (2 offsets ~ 1 pitch), so
    # labels alternate along each chain from its unclaimed first member (a top copy)
    known = np.ones(n, dtype=bool)
    known[claim[claim >= 0]] = False
    for _ in range(n):
        src = np.flatnonzero(known & (claim >= 0) & ~known[np.maximum(claim, 0)])
        if len(src) == 0:
            break
        copy[claim[src]] = ~copy[src]
        known[claim[src]] = True
    top_of_pair = (claim >= 0) & ~copy
    dots = cKDTree(dots_mm)

    def residual(screen: NDArray[np.float64]) -> NDArray[np.float64]:
        return screen - dots_mm[dots.query(np.nan_to_num(screen, nan=1e9))[1]]

    res_top, res_bot = residual(pred.screen_top), residual(pred.screen_bottom)
    ref = np.flatnonzero(top_of_pair | copy)
    ref_res = np.where(copy[ref, None], res_bot[ref], res_top[ref])
    if len(ref) < k_local:
        ref, ref_res = idx, res_top[idx]
    single = idx[~(top_of_pair | copy)[idx]]
    if len(single) == 0:
        return copy
    k = min(k_local, len(ref))
    near = cKDTree(pixels[ref]).query(pixels[single], k=k)[1].reshape(len(single), k)
    shift = np.median(ref_res[near], axis=1)
    d_top = np.linalg.norm(res_top[single] - shift, axis=1)
    d_bot = np.linalg.norm(res_bot[single] - shift, axis=1)
    copy[single] = d_bot < d_top
    return copy
