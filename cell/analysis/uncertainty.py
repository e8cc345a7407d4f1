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
3. **pose** (:func:`pose_uncertainty_of_points`): the views' pose errors as the multi-view refinement
   leaves them (its posterior covariance; a view it could not register keeps its prior) along each point's
   normal, less what the recipe's alignment takes out: a datum alignment the rigid motion its datums see
   (:func:`datum_alignment_map`), kinematic alignment nothing (the chain's whole error stays);
4. **merge** (:class:`MergeShares`): the weighted voxel mean of the views; points
   of one view in a voxel share edges and pose, so their decode errors add linearly, the views' in
   quadrature; the pose errors through the views' shares of each point;
5. **alignment**: the recipe alignment's own 1-sigma displacement from the noise of what it measured
   (:mod:`cell.analysis.alignment`), common to every point, added last.

u = sqrt(merged decode^2 + pose^2 + alignment^2); the decision rules use U = k u
(:mod:`cell.analysis.decision`). docs/uncertainty.md compares u with the simulator's truth.
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import Executor
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cell.analysis.alignment import Datum
from cell.analysis.merge import MergedCloud
from cell.analysis.view_refinement import ViewRefinement
from cell.geometry import points_within, transform_points
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
POINTS_PER_CHUNK = 65_536  # merged points whose pose u one call of the compiled kernel computes
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


def has_view_uncertainty(patterns: PatternSet) -> bool:
    """Whether :func:`view_uncertainty` models ``patterns``' code (GCLS's edge model; None for the others)."""
    return patterns.codec == "gcls"


def view_uncertainty(
    stack: NDArray[Any],
    patterns: PatternSet,
    decoded: Decoded,
    cloud: SensorCloud,
    T_C_P: Array,
    fx_px: float,
    calibration_px: float = 0.0,
    bit_depth: int = 8,
    normals: NDArray[np.float64] | None = None,
) -> ViewUncertainty | None:
    """The decode and calibration uncertainty of every pixel of one view (:class:`ViewUncertainty`), or None
    for a code other than GCLS (the edge model is GCLS's). ``T_C_P``: the projector in the camera frame as the
    triangulation uses it; ``fx_px``: the camera's focal length; ``calibration_px``: the calibration's
    residual in camera pixels (0: none known); ``normals``: the cloud's
    :func:`cell.sensing.incidence.measured_normals` when the caller has them."""
    if not has_view_uncertainty(patterns):
        return None
    axis = decoded.primary()
    code = next(c for c in patterns.codes if c.axis == axis.axis)
    valid = cloud.valid
    points = cloud.points_C
    normals = measured_normals(points, valid) if normals is None else normals
    T = np.asarray(T_C_P, dtype=np.float64)
    g = np.full(valid.shape, np.nan)
    g[valid] = normal_error_per_pixel(points[valid], normals[valid], T[:3, 3], T[:3, 1], fx_px)
    # where no normal could be measured (thin strips, isolated pixels) the view's typical value stands in
    g_ok = np.isfinite(g) & valid
    g_med = float(np.median(g[g_ok])) if g_ok.any() else float("nan")
    g[valid & ~g_ok] = g_med
    noise = estimate_image_noise(stack, patterns, valid, bit_depth)
    sigma_x = edge_sigma_px(decoded, axis, noise, code.shift_px, code.offset_px)
    q = quantisation(points, normals, valid, g, code_phase(axis, code.shift_px, code.offset_px), sigma_x)
    px = np.sqrt(np.square(sigma_x) + q.total_px**2 + calibration_px**2)
    u = np.where(valid, g * px, np.nan).astype(np.float32)
    return ViewUncertainty(u, noise, q, float(calibration_px), g_med)


def posterior_covariance(
    information: Array | None,
    n_views: int,
    prior_sigma_mm: Sequence[float],
    prior_sigma_rad: Sequence[float],
    lever_mm: float,
) -> Array:
    """The (6n, 6n) covariance of the views' pose errors after the refinement: its overlaps' ``information``
    (:attr:`cell.analysis.view_refinement.ViewRefinement.information`) plus the prior (1 sigma per view,
    translation mm and rotation rad), inverted. A view the refinement held at its kinematic pose keeps its
    prior and informs no other view: the refinement leaves its overlaps out of ``information``; no refinement
    (one view): the prior. Parameters as the refinement's: x = (omega * lever, tau) per view."""
    prior = np.concatenate(
        [[(r * lever_mm) ** 2] * 3 + [t**2] * 3 for t, r in zip(prior_sigma_mm, prior_sigma_rad, strict=True)]
    )
    H = np.zeros((6 * n_views, 6 * n_views)) if information is None else np.asarray(information, np.float64)
    return np.asarray(np.linalg.inv(H + np.diag(1.0 / np.maximum(prior, 1e-18))), dtype=np.float64)


def _rows(points: Array, normals: Array, centre_mm: Array, lever_mm: float) -> Array:
    """(N, 6) rows mapping a correction x = (omega * lever, tau) to each point's motion along its normal."""
    p, n = np.asarray(points, np.float64).reshape(-1, 3), np.asarray(normals, np.float64).reshape(-1, 3)
    d = p - np.asarray(centre_mm)
    out = np.empty((len(p), 6))
    for i, (j, k) in enumerate(((1, 2), (2, 0), (0, 1))):  # (d x n) / lever: np.cross's products, column-wise
        out[:, i] = (d[:, j] * n[:, k] - d[:, k] * n[:, j]) / lever_mm
    out[:, 3:] = n
    return out


class ViewShares:
    """(M, n) each view's share of the weight of every merged point (rows sum to 1), held by view: the merged
    points each view has (ascending) and its shares of them; a point has a few of the views, so this is a
    fraction of the dense (M, n) float64 (1.1 GB for a 5 MP camera's 40 views). Indexed by a slice of rows or
    an array of row indices, it gives those rows dense."""

    def __init__(self, m: int, index: Sequence[NDArray[np.integer]], value: list[Array]) -> None:
        self.shape = (m, len(index))
        self._index, self._value = index, value

    def __getitem__(self, rows: slice | NDArray[np.int64]) -> Array:
        if isinstance(rows, slice):
            start, stop, step = rows.indices(self.shape[0])
            assert step == 1, "rows a step apart: index them by an array"
            out = np.zeros((max(stop - start, 0), self.shape[1]))
            for k, (idx, val) in enumerate(zip(self._index, self._value, strict=True)):
                # the bounds in the index's own dtype: searched as int64, the index would be copied as such
                lo, hi = np.searchsorted(idx, np.array([start, stop], dtype=idx.dtype))
                out[idx[lo:hi] - start, k] = val[lo:hi]
            return out
        assert np.asarray(rows).dtype.kind in "iu", "rows by index, not by a mask"
        rows = np.asarray(rows, dtype=np.int64).ravel()
        out = np.zeros((len(rows), self.shape[1]))
        for k, (idx, val) in enumerate(zip(self._index, self._value, strict=True)):
            if len(idx):
                at = np.minimum(np.searchsorted(idx, rows.astype(idx.dtype, copy=False)), len(idx) - 1)
                hit = idx[at] == rows
                out[hit, k] = val[at[hit]]
        return out


class MergeShares:
    """Each view's share of the merged points' weight (:class:`ViewShares`) and their merged decode u, summed
    view by view as the merge gives the views' voxels (its ``each_view``:
    :func:`cell.analysis.merge.merge_bins`). Within a view the errors of one voxel's points are taken as fully
    correlated (neighbouring pixels share edges, pose and calibration), so their weighted u add linearly;
    the views add in quadrature: u = sqrt(sum_v (sum_i w_i u_i)_v^2) / sum w."""

    def __init__(self, n_views: int) -> None:
        self.n_views = n_views
        self._index: list[NDArray[np.int32]] = [np.zeros(0, np.int32)] * n_views  # a view's merged points
        self._value: list[Array] = [np.zeros(0)] * n_views  # its summed weights there (then its shares)
        self._var: Array | None = None  # (M,) sum over views of (sum of w u of the view's points)^2

    def __call__(
        self, k: int, rows: NDArray[np.int64], m: int, weight: Array, wu: NDArray[np.floating]
    ) -> None:
        """Add view ``k``: the merged points it has (``rows`` of ``m``, ascending, distinct), its points'
        weight sum at each and their weighted decode u sum (mm; NaN: none known)."""
        from cell.analysis._merge_kernel import add_squares  # compiled: NumPy's fancy += is ~10 ns a point

        self._index[k], self._value[k] = np.asarray(rows, np.int32), np.asarray(weight, np.float64)
        if self._var is None:
            self._var = np.zeros(m)
        add_squares(self._var, self._index[k], np.asarray(wu, dtype=np.float64))

    def shares(self, merged: MergedCloud) -> ViewShares:
        """(M, n) each view's share of every merged point's weight (rows sum to 1)."""
        value = [v / merged.weight[i] for i, v in zip(self._index, self._value, strict=True)]
        return ViewShares(len(merged.weight), self._index, value)

    def decode(self, merged: MergedCloud) -> NDArray[np.float64]:
        """u (mm) of every merged point from its views' decode u."""
        assert self._var is not None, "no view was added"
        return np.asarray(np.sqrt(self._var) / merged.weight, dtype=np.float64)


def datum_alignment_map(
    datum_points: Array,
    datum_normals: Array,
    datum_shares: Array,
    centre_mm: Array,
    lever_mm: float,
) -> Array:
    """B (6, 6n): the rigid correction a datum alignment (3-2-1 / RPS) makes of the views' pose errors x,
    x_align = B x. Each datum is measured as the mean offset along its normal of the points near it, which
    the views measured in the shares ``datum_shares`` (D, n); the alignment is the least-squares rigid motion
    that zeroes those offsets. Datums in the refinement's frame, unit normals."""
    A = _rows(datum_points, datum_normals, centre_mm, lever_mm)  # (D, 6)
    shares = np.asarray(datum_shares, dtype=np.float64)
    M = (shares[:, :, None] * A[:, None, :]).reshape(len(A), -1)  # (D, 6n)
    return np.linalg.pinv(A) @ M


class PointRows:
    """:func:`_rows` of (M, 3) points and their normals, made a slice at a time when indexed (a chunk of the
    pose kernel's: cache-sized, not a (M, 6) array of the whole cloud; the same values either way). ``T``:
    the points are given in another frame, which it maps to the normals' (moved a slice at a time: each
    point alone, the same values as all at once); ``face``: the normals are given per face, the points' are
    ``normals[face]``."""

    def __init__(
        self,
        points: Array,
        normals: Array,
        centre_mm: Array,
        lever_mm: float,
        T: Array | None = None,
        face: NDArray[np.int64] | None = None,
    ) -> None:
        self.points, self.normals, self.T, self.face = points, normals, T, face
        self.centre_mm, self.lever_mm = centre_mm, lever_mm

    def __len__(self) -> int:
        return len(self.points)

    def __getitem__(self, rows: slice) -> Array:
        points = self.points[rows] if self.T is None else transform_points(self.T, self.points[rows])
        # (np.take: several times faster than indexing by the faces)
        normals = self.normals[rows] if self.face is None else np.take(self.normals, self.face[rows], axis=0)
        return _rows(points, normals, self.centre_mm, self.lever_mm)


def pose_uncertainty_of_points(
    shares: Array | ViewShares,
    rows: Array | PointRows,
    covariance: Array,
    alignment_map: Array | None,
    pool: Executor | None = None,
) -> NDArray[np.float64]:
    """1-sigma error (mm) along each merged point's normal from the views' pose errors (``covariance``,
    :func:`posterior_covariance`): the point is the ``shares``-weighted mean of its views' points, each moved
    by its view's error, less what the alignment takes out (``alignment_map`` B: x_align = B x; None:
    kinematic alignment, nothing). ``rows`` (M, 6): :func:`_rows` of the merged points (or a
    :class:`PointRows`). With a ``pool`` two of its threads compute the chunks beside this one, each taking
    the next chunk when free (the kernel releases the GIL; each chunk writes its own points: the same values
    as one thread's), so this thread works on while the pool's are busy with something else."""
    from cell.analysis._pose_kernel import pose_sigma  # compiled: only the views a point has enter it

    out = np.empty(len(rows), dtype=np.float64)

    def chunk(a: int) -> None:  # every point's row is its own
        s, r = shares[a : a + POINTS_PER_CHUNK], rows[a : a + POINTS_PER_CHUNK]
        out[a : a + len(r)] = pose_sigma(s, r, covariance, alignment_map)

    starts = iter(range(0, len(rows), POINTS_PER_CHUNK))

    def work() -> None:
        for a in starts:  # (a range's iterator hands each start out once, to one thread)
            chunk(a)

    helpers = [] if pool is None else [pool.submit(work) for _ in range(2)]
    work()
    for helper in helpers:  # one that has not started (its thread busy elsewhere) has nothing left to do
        if not helper.cancel():
            helper.result()
    return out


def combine(*terms_mm: NDArray[np.floating] | float) -> NDArray[np.float64]:
    """Independent standard uncertainties added in quadrature (arrays broadcast), summed in their order into
    one array (not a new one a term: a million points' u is 16 MB an array)."""
    total = np.zeros(np.broadcast_shapes(*(np.shape(t) for t in terms_mm)))
    for t in terms_mm:
        total += np.square(np.asarray(t, dtype=np.float64))
    return np.sqrt(total, out=total)


def stats(x: NDArray[np.floating]) -> dict[str, float | None]:
    """median, p95 and max (mm, 5 decimals) of the finite values, None without any."""
    x = np.asarray(x, dtype=np.float64)
    x = x[np.isfinite(x)]  # a copy, which numpy's order statistics may reorder: no second copy for each
    if not len(x):
        return {"median": None, "p95": None, "max": None}
    top = float(x.max())
    median = float(np.median(x, overwrite_input=True))  # (the same values as of x in its order)
    return {
        "median": round(median, 5),
        "p95": round(float(np.percentile(x, 95, overwrite_input=True)), 5),
        "max": round(top, 5),
    }


@dataclass(frozen=True)
class CloudUncertainty:
    """u (mm) of every merged point and its parts: ``decode`` (image noise, quantisation, calibration; merged
    over the views as u is), ``pose`` (the views' pose errors as the alignment leaves them) and
    ``alignment`` (the alignment's own, from the noise of what it measured; common to all points)."""

    u_mm: NDArray[np.float64]
    decode_mm: NDArray[np.float64]
    pose_mm: NDArray[np.float64]
    alignment_mm: float

    def budget(self, pool: Executor | None = None) -> dict[str, Any]:
        """Statistics of u and of each part (mm) for the report (``pool``: two of them on its threads beside
        the third on this one)."""
        if pool is None:
            u, decode = stats(self.u_mm), stats(self.decode_mm)
        else:
            found = pool.submit(stats, self.u_mm), pool.submit(stats, self.decode_mm)
        pose = stats(self.pose_mm)
        if pool is not None:
            u, decode = (f.result() for f in found)
        return {"u_mm": u, "decode_mm": decode, "pose_mm": pose, "alignment_mm": round(self.alignment_mm, 5)}


def registered_cloud_uncertainty(
    merged: MergedCloud,
    shares: Array | ViewShares,
    decode_mm: Array,
    refinement: ViewRefinement,
    prior: dict[str, Any],
    face_normals_W: Array,
    face: NDArray[np.int64],
    T_W_cloud: Array,
    alignment: dict[str, Any],
    datums: Sequence[Datum] = (),
    pool: Executor | None = None,
    datum_near: NDArray[np.int64] | None = None,
) -> CloudUncertainty:
    """u of every point of an inspection's merged cloud (in the frame ``T_W_cloud`` maps to {W}) from the
    views' ``shares`` (M, n) of its points (:class:`ViewShares`) and its merged decode u ``decode_mm`` (M,)
    (both from :class:`MergeShares` while the views merge); the views' pose errors after the refinement
    (:class:`cell.analysis.view_refinement.ViewRefinement`) under the ``prior`` it ran under (its record:
    ``prior_sigma_mm`` and ``prior_sigma_deg`` per view) along the nominal normal at each point, that of
    its ``face`` (M,: the nominal face nearest the point as judged, from its error map) of the nominal's
    ``face_normals_W`` (F, 3, {W}), less what the recipe's alignment removes (its record: ``to_json`` of
    :class:`cell.analysis.alignment.Alignment`): a datum alignment (the ``datums`` resolved on the nominal, in
    the cloud's frame) the rigid motion its datums see (:func:`datum_alignment_map`), any other measured
    alignment the views' mean motion, kinematic alignment nothing; plus the alignment's own uncertainty.
    ``pool``: threads for the points' pose u (:func:`pose_uncertainty_of_points`); ``datum_near``: the merged
    points (indices, ascending) that can lie in a datum's region, when the alignment found them
    (:attr:`cell.analysis.alignment.Alignment.datum_near`): the regions are looked up among them alone."""
    n = shares.shape[1]
    T = np.asarray(T_W_cloud, dtype=np.float64)
    sigma_mm = prior.get("prior_sigma_mm", [0.0] * n)
    sigma_rad = np.deg2rad(prior.get("prior_sigma_deg", [0.0] * n))
    lever = refinement.lever_mm
    C = posterior_covariance(refinement.information, n, sigma_mm, sigma_rad, lever)
    centre = refinement.centre_mm
    if centre is None:
        centre = transform_points(T, merged.points_mm).mean(axis=0)
    method = alignment.get("method", "kinematic")
    B: Array | None = None
    if "error" in alignment or method == "kinematic":
        B = None
    elif datums and method in ("datums", "datum_icp"):
        d_shares = []
        search = merged.points_mm if datum_near is None else merged.points_mm[datum_near]
        for d in datums:
            near = points_within(search, d.point, d.radius_mm)  # (each point tested alone: the same points)
            near = near if datum_near is None else datum_near[near]
            d_shares.append(shares[near].mean(axis=0) if len(near) else np.full(n, 1.0 / n))
        B = datum_alignment_map(
            transform_points(T, np.array([d.point for d in datums])),
            np.array([d.normal for d in datums]) @ T[:3, :3].T,
            np.array(d_shares),
            centre,
            lever,
        )
    else:  # best fit, features, weighted: taken as removing the views' mean motion
        B = np.kron(np.full((1, n), 1.0 / n), np.eye(6))
    rows = PointRows(merged.points_mm, face_normals_W, centre, lever, T, face)  # in {W}, a chunk at a time
    pose = pose_uncertainty_of_points(shares, rows, C, B, pool)
    decode = np.asarray(decode_mm, dtype=np.float64)
    common = float((alignment.get("uncertainty_mm") or {}).get("rms") or 0.0)
    return CloudUncertainty(combine(decode, pose, common), decode, pose, common)
