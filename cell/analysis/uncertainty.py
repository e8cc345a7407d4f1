"""Per-point standard uncertainty u (mm, along the nominal normal) of a measured cloud (issue 17).

Every number comes from what the cell itself measured or calibrated, never from the simulator's settings:

1. **decode** (per view and pixel, :func:`view_uncertainty`): the one-pixel model of eq 2.5, generalised to
   the point's surface orientation (:func:`cell.sensing.error_model.normal_error_per_pixel`: mm along the
   normal per camera pixel of correspondence error; the projector's incidence enters there, the camera's
   cancels), times the correspondence error in camera pixels: the image noise measured in the view's own
   pattern/inverse pairs (photon transfer) over each edge's swing (:func:`cell.sensing.noise.edge_sigma_px`),
   and the sub-code quantisation error measured on the view's own points
   (:func:`cell.sensing.noise.quantisation`, dissertation Fig 2.4);
2. **calibration** (per view and pixel): the calibration's own residual in camera pixels (the stereo
   reprojection rms of `cell calibrate projector`, or the per-pixel model's eq 2.7 residual) through the same
   one-pixel model; zero on the config's nominal geometry, which a real cell must not trust anyway
   (``requires_calibration``);
3. **registration** (per view, :func:`pose_uncertainty`): the multi-view refinement's posterior covariance of
   each view's pose (relative to the other views when the recipe's alignment fixes the whole cloud, absolute
   under kinematic alignment) along each point's normal;
4. **merge** (:func:`merged_uncertainty`): the weighted voxel mean of the views; points of one view in a voxel
   share edges and pose, so their errors add linearly; the views' add in quadrature (they are independent);
5. **alignment**: the recipe alignment's own 1-sigma displacement (:mod:`cell.analysis.alignment`), common to
   every point, added last.

u = sqrt(merged(decode^2 + calibration^2 + registration^2) + alignment^2); the decision rules use U = k u
(:mod:`cell.analysis.decision`). docs/uncertainty.md compares u with the simulator's truth.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cell.analysis.errormap import NominalMesh, signed_distance
from cell.analysis.merge import MergedCloud
from cell.analysis.view_refinement import ViewRefinement
from cell.geometry import transform_points
from cell.sensing.decode import Decoded
from cell.sensing.error_model import normal_error_per_pixel
from cell.sensing.incidence import measured_normals
from cell.sensing.noise import (
    ImageNoise,
    Quantisation,
    code_phase,
    edge_sigma_px,
    estimate_image_noise,
    quantisation,
)
from cell.sensing.patterns import PatternSet
from cell.sensing.triangulate import SensorCloud

Array = NDArray[np.float64]
TARGET_SHARE_OF_BAND = 0.25  # a gauge is fit for a tolerance when U <= a quarter of its band (gauging rule)


@dataclass(frozen=True)
class ViewUncertainty:
    """One view's per-pixel uncertainty ``u_mm`` (H, W; decode and calibration, along the measured normal;
    NaN where there is no point) and what it was made of."""

    u_mm: NDArray[np.float32]
    noise: ImageNoise
    quantisation: Quantisation
    calibration_px: float
    mm_per_px: float  # median of the one-pixel model over the view's points

    def to_json(self) -> dict[str, Any]:
        ok = np.isfinite(self.u_mm)
        return {
            "image_noise": self.noise.to_json(),
            "quantisation": self.quantisation.to_json(),
            "calibration_px": round(self.calibration_px, 5),
            "one_pixel_mm": round(self.mm_per_px, 5),
            "u_mm": stats(self.u_mm[ok]),
        }


def view_uncertainty(
    stack: NDArray[Any],
    patterns: PatternSet,
    decoded: Decoded,
    cloud: SensorCloud,
    T_C_P: Array,
    fx_px: float,
    calibration_px: float = 0.0,
    bit_depth: int = 8,
) -> ViewUncertainty | None:
    """The decode and calibration uncertainty of every pixel of one view (:class:`ViewUncertainty`), or None
    for a code other than GCLS (the edge model is GCLS's). ``T_C_P``: the projector in the camera frame as the
    triangulation uses it; ``fx_px``: the camera's focal length; ``calibration_px``: the calibration's
    residual in camera pixels (0: none known)."""
    if patterns.codec != "gcls":
        return None
    axis = decoded.primary()
    code = next(c for c in patterns.codes if c.axis == axis.axis)
    valid = cloud.valid
    points = np.asarray(cloud.points_C, dtype=np.float64)
    normals = measured_normals(points, valid)
    T = np.asarray(T_C_P, dtype=np.float64)
    g = normal_error_per_pixel(points, normals, T[:3, 3], T[:3, 1], fx_px)
    # where no normal could be measured (thin strips, isolated pixels) the view's typical value stands in
    g_ok = np.isfinite(g) & valid
    g_med = float(np.median(g[g_ok])) if g_ok.any() else float("nan")
    g = np.where(g_ok, g, g_med)
    noise = estimate_image_noise(stack, patterns, valid, bit_depth)
    sigma_x = edge_sigma_px(decoded, axis, noise, code.shift_px, code.offset_px)
    q = quantisation(points, normals, valid, g, code_phase(axis, code.shift_px, code.offset_px), sigma_x)
    px = np.sqrt(np.square(sigma_x) + q.total_px**2 + calibration_px**2)
    u = np.where(valid, g * px, np.nan).astype(np.float32)
    return ViewUncertainty(u, noise, q, float(calibration_px), g_med)


def pose_uncertainty(
    points_mm: Array,
    normals: Array,
    covariance: Array,
    centre_mm: Array,
    lever_mm: float,
) -> Array:
    """1-sigma displacement (mm) along each point's unit normal of a rigid correction x = (omega * lever,
    tau) about ``centre_mm`` with the 6x6 ``covariance`` (of
    :class:`cell.analysis.view_refinement.ViewRefinement`)."""
    p = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    J = np.column_stack([np.cross(p - np.asarray(centre_mm), n) / lever_mm, n])
    return np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", J, covariance, J), 0.0))


def view_pose_covariances(
    covariance: Array | None,
    n_views: int,
    prior_sigma_mm: Sequence[float],
    prior_sigma_rad: Sequence[float],
    lever_mm: float,
    held: Sequence[int],
) -> tuple[list[Array], Array]:
    """The views' 6x6 pose covariances after the refinement, split into what is each view's own (its
    block of the posterior relative to the views' mean: independent from view to view) and what they share
    (the covariance of the views' mean pose: one error of the whole cloud, which averaging views does not
    reduce and a measured alignment removes). A view the refinement held at its kinematic pose (``held``)
    keeps its prior. No refinement (one view): the prior, all of it the view's own."""
    prior = [
        np.diag([(r * lever_mm) ** 2] * 3 + [t**2] * 3)
        for t, r in zip(prior_sigma_mm, prior_sigma_rad, strict=True)
    ]
    if covariance is None:
        return prior, np.zeros((6, 6))
    C = np.array(covariance, dtype=np.float64)
    for v in held:  # the solve pinned it (a huge weight): its pose is what the prior says
        C[6 * v : 6 * v + 6, :] = 0.0
        C[:, 6 * v : 6 * v + 6] = 0.0
        C[6 * v : 6 * v + 6, 6 * v : 6 * v + 6] = prior[v]
    mean = np.kron(np.full((1, n_views), 1.0 / n_views), np.eye(6))
    D = np.kron(np.eye(n_views), np.eye(6)) - np.kron(np.ones((n_views, 1)), mean)
    own = D @ C @ D.T
    return [own[6 * v : 6 * v + 6, 6 * v : 6 * v + 6] for v in range(n_views)], mean @ C @ mean.T


def merged_uncertainty(
    merged: MergedCloud, weights: Sequence[Array], u_views: Sequence[Array]
) -> NDArray[np.float64]:
    """u (mm) of every merged point from its input points' ``u_views`` (one array per view, in the order and
    with the points given to :func:`cell.analysis.merge.merge_views`) and merge ``weights``: within a view the
    errors of one voxel's points are taken as fully correlated (neighbouring pixels share edges, pose and
    calibration), so their weighted u add linearly; the views add in quadrature."""
    w = np.concatenate([np.asarray(x, dtype=np.float64).ravel() for x in weights])
    u = np.concatenate([np.asarray(x, dtype=np.float64).ravel() for x in u_views])
    view = np.repeat(np.arange(len(u_views)), [len(x) for x in u_views])
    src = merged.source
    ok = src >= 0
    m = len(merged.points_mm)
    key = src[ok] * len(u_views) + view[ok]
    keys, inv = np.unique(key, return_inverse=True)
    per_view = np.bincount(inv, weights=w[ok] * u[ok])  # sum of w u of one view's points in one voxel
    var = np.bincount(keys // len(u_views), weights=per_view**2, minlength=m)
    return np.sqrt(var) / merged.weight


def combine(*terms_mm: NDArray[np.floating] | float) -> NDArray[np.float64]:
    """Independent standard uncertainties added in quadrature (arrays broadcast)."""
    return np.sqrt(sum(np.square(np.asarray(t, dtype=np.float64)) for t in terms_mm))


def stats(x: NDArray[np.floating]) -> dict[str, float | None]:
    """median, p95 and max (mm, 5 decimals) of the finite values, None without any."""
    x = np.asarray(x, dtype=np.float64)
    x = x[np.isfinite(x)]
    if not len(x):
        return {"median": None, "p95": None, "max": None}
    return {
        "median": round(float(np.median(x)), 5),
        "p95": round(float(np.percentile(x, 95)), 5),
        "max": round(float(x.max()), 5),
    }


def budget(components: dict[str, NDArray[np.floating]]) -> dict[str, dict[str, float | None]]:
    """The report's uncertainty budget: statistics of each component (mm) over the points."""
    return {name: stats(values) for name, values in components.items()}


@dataclass(frozen=True)
class CloudUncertainty:
    """u (mm) of every merged point and its parts: ``decode`` (image noise, quantisation, calibration) and
    ``registration`` (the views' own pose errors), each merged over the views as u is; ``common`` (the
    views' shared pose error, under kinematic alignment) and ``alignment`` (the recipe alignment's), which
    every view shares."""

    u_mm: NDArray[np.float64]
    decode_mm: NDArray[np.float64]
    registration_mm: NDArray[np.float64]
    common_mm: NDArray[np.float64]
    alignment_mm: float

    def budget(self) -> dict[str, Any]:
        """Statistics of u and of each part (mm) for the report."""
        return {
            "u_mm": stats(self.u_mm),
            "decode_mm": stats(self.decode_mm),
            "registration_mm": stats(self.registration_mm),
            "common_pose_mm": stats(self.common_mm),
            "alignment_mm": round(self.alignment_mm, 5),
        }


def cloud_uncertainty(
    merged: MergedCloud,
    weights: Sequence[Array],
    decode_mm: Sequence[Array],
    pose_covariances: Sequence[Array],
    centre_mm: Array,
    lever_mm: float,
    points_W: Array,
    normals_W: Array,
    alignment_mm: float = 0.0,
    common_covariance: Array | None = None,
) -> CloudUncertainty:
    """u of every merged point: each input point's decode uncertainty (``decode_mm``, one array per view, as
    given to the merge) and its view's own pose uncertainty (``pose_covariances``,
    :func:`view_pose_covariances`, evaluated at its merged point: ``points_W`` and unit ``normals_W`` (M, 3)
    in the refinement's frame {W}), merged (:func:`merged_uncertainty`); then what all views share: the
    pose error of the whole cloud (``common_covariance``; None when an alignment removed it) and the
    alignment's ``alignment_mm``."""
    src = merged.source
    reg: list[Array] = []
    start = 0
    for cov, u in zip(pose_covariances, decode_mm, strict=True):
        s = src[start : start + len(u)]
        start += len(u)
        r = np.full(len(u), np.nan)
        ok = s >= 0
        r[ok] = pose_uncertainty(points_W[s[ok]], normals_W[s[ok]], cov, centre_mm, lever_mm)
        reg.append(r)
    total = [combine(d, r) for d, r in zip(decode_mm, reg, strict=True)]
    common = (
        np.zeros(len(points_W))
        if common_covariance is None
        else pose_uncertainty(points_W, normals_W, common_covariance, centre_mm, lever_mm)
    )
    return CloudUncertainty(
        u_mm=combine(merged_uncertainty(merged, weights, total), common, alignment_mm),
        decode_mm=merged_uncertainty(merged, weights, decode_mm),
        registration_mm=merged_uncertainty(merged, weights, reg),
        common_mm=common,
        alignment_mm=float(alignment_mm),
    )


def registered_cloud_uncertainty(
    merged: MergedCloud,
    weights: Sequence[Array],
    decode_mm: Sequence[Array],
    refinement: ViewRefinement,
    prior_sigma_mm: Sequence[float],
    prior_sigma_rad: Sequence[float],
    nominal_W: NominalMesh,
    T_W_cloud: Array,
    alignment: dict[str, Any],
) -> CloudUncertainty:
    """:func:`cloud_uncertainty` of an inspection's merged cloud (points in the frame ``T_W_cloud`` maps to
    {W}) from its views' refinement (:class:`cell.analysis.view_refinement.ViewRefinement`, with the prior it
    ran under) and the recipe alignment's record (``to_json`` of :class:`cell.analysis.alignment.Alignment`):
    an alignment that measured the part fixes the cloud as a whole, so only the views' poses relative to each
    other count, plus its own uncertainty; kinematic alignment leaves the chain's common error in."""
    n = len(decode_mm)
    measured = alignment.get("method", "kinematic") != "kinematic" and "error" not in alignment
    covs, shared = view_pose_covariances(
        refinement.covariance,
        n,
        prior_sigma_mm,
        prior_sigma_rad,
        refinement.lever_mm,
        refinement.unregistered,
    )
    points_W = transform_points(np.asarray(T_W_cloud, dtype=np.float64), merged.points_mm)
    normals_W = nominal_W.face_normals[signed_distance(nominal_W, points_W).face]
    centre = refinement.centre_mm if refinement.centre_mm is not None else points_W.mean(axis=0)
    common = (alignment.get("uncertainty_mm") or {}).get("rms") or 0.0
    return cloud_uncertainty(
        merged,
        weights,
        decode_mm,
        covs,
        centre,
        refinement.lever_mm,
        points_W,
        normals_W,
        float(common),
        None if measured else shared,
    )
