"""Put the measured part into its part frame by the recipe's ``alignment:`` (dissertation 4.1-4.3).

The views arrive in {P} through the kinematic chain (robot pose, hand-eye, the recipe's placement ``T_W_P``).
When the part does not sit exactly where the recipe says (a fixture is never perfect), that cloud is off by
the placement error, and every point looks deviated. :func:`align` computes the correction ``T`` (cloud ->
{P}) by the chosen method:

- ``kinematic``: none (``T`` = identity): right for a calibrated fixture;
- ``datums`` (3-2-1 / RPS): each datum point fixes the part along its normal; its measured offset is the
  mean signed deviation of the points within its radius. The six (or more) normal constraints are solved
  by linearised least squares, re-measured and solved again until the step vanishes (Gauss-Newton);
- ``datum_icp``: point-to-plane ICP on the datum regions only, started from the datums;
- ``features``: curvature-feature matching (eqs 4.16-4.20, :mod:`cell.analysis.features`), coarse;
- ``weighted``: the weighted combination of the estimates above (eqs 4.21-4.22);
- ``best_fit``: ICP over the whole part; it aligns global deviations away, so the report warns.

Each result carries residuals and the uncertainty the alignment adds: the 1-sigma displacement along the
nominal normal, over the nominal surface, propagated from the covariance of the 6-DOF estimate. That is the
noise part only; the part's own form error at its datums moves the alignment as well, which the per-datum
residuals show.
"""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, cast

import numpy as np
import trimesh
from numpy.typing import NDArray
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from cell.analysis.errormap import NominalMesh, signed_distance
from cell.analysis.features import feature_align
from cell.analysis.registration import combine_registrations, icp_point_to_plane
from cell.config import AlignmentConfig, AlignmentEstimate, DatumPoint
from cell.errors import ConfigError
from cell.geometry import Pose, make_pose, points_within, transform_points

MIN_DATUM_POINTS = 20  # a datum region with fewer measured points is not measured
SAME_SURFACE_COS = 0.9  # a datum region's points whose closest nominal face turns more than ~25 deg away
BEST_FIT_POINTS = 50_000  # best fit runs on a random sample of this many points
BEST_FIT_WARNING = (
    "best-fit alignment: the part was aligned to its own measurement over the whole surface, which hides "
    "global deviations (a bent, shifted or twisted part can pass); use datums or a calibrated fixture"
)


class AlignmentError(Exception):
    """The measurement does not allow the chosen alignment (a datum not measured, no features, a correction
    beyond the recipe's limit): the inspection cannot judge the part, its verdict is incomplete."""


@dataclass(frozen=True)
class Datum:
    """A datum point resolved on the nominal: position, unit normal (part frame) and region radius (mm)."""

    name: str
    point: NDArray[np.float64]
    normal: NDArray[np.float64]
    radius_mm: float


@dataclass
class Alignment:
    """``T`` maps the kinematic cloud into {P}. ``residuals``: per datum, the mean deviation before
    (kinematic) and after, with its point count; ``uncertainty_mm``: rms and max over the surface of the
    1-sigma displacement along the normal (None where not estimated)."""

    method: str
    T: Pose
    residuals: list[dict[str, Any]] = field(default_factory=list)
    rms_mm: float | None = None
    uncertainty_mm: dict[str, float] | None = None
    correction_mm: float = 0.0
    warnings: list[str] = field(default_factory=list)
    estimates: dict[str, Any] = field(default_factory=dict)
    # the aligned cloud's points (indices, ascending) within reach of a datum (:class:`_DatumIndex`): where
    # every datum's region lies at any correction the recipe allows, for who looks the regions up again
    # (cell.analysis.uncertainty); None when no datum was looked up. Not in the record.
    datum_near: NDArray[np.int64] | None = field(default=None, repr=False)

    def to_json(self) -> dict[str, Any]:
        rot = float(np.degrees(np.linalg.norm(Rotation.from_matrix(self.T[:3, :3]).as_rotvec())))
        return {
            "method": self.method,
            "T_P_cloud": np.round(self.T, 9).tolist(),
            "correction": {
                "max_mm": round(self.correction_mm, 5),
                "translation_mm": round(float(np.linalg.norm(self.T[:3, 3])), 5),
                "rotation_deg": round(rot, 5),
            },
            "residuals": self.residuals,
            "rms_mm": None if self.rms_mm is None else round(self.rms_mm, 6),
            "uncertainty_mm": self.uncertainty_mm,
            "estimates": self.estimates,
            "warnings": self.warnings,
        }


def resolve_datums(
    datums: list[DatumPoint], nominal: NominalMesh, where: str = "alignment.datums"
) -> list[Datum]:
    """Datum points on the nominal: each within 1 mm of the surface; normal given or the surface's there.
    ConfigError naming the datum otherwise, and when the set does not fix all six degrees of freedom."""
    if not datums:
        return []
    p = np.array([d.point_mm for d in datums], dtype=np.float64)
    em = signed_distance(nominal, p)
    out = []
    for i, d in enumerate(datums):
        if abs(em.deviation_mm[i]) > 1.0:
            raise ConfigError(
                f"datum '{d.name}' is {abs(em.deviation_mm[i]):.2f} mm from the nominal surface; put it on "
                "the surface (part frame, mm)",
                field=f"{where}[{i}].point_mm",
            )
        n = np.asarray(
            d.normal if d.normal is not None else nominal.face_normals[em.face[i]], dtype=np.float64
        )
        out.append(Datum(d.name, em.closest_mm[i], n / np.linalg.norm(n), d.radius_mm))
    if len(out) >= 6:
        A = _constraint_rows(np.array([d.point for d in out]), np.array([d.normal for d in out]))
        s = np.linalg.svd(A, compute_uv=False)
        if s[-1] < 1e-3 * s[0]:
            raise ConfigError(
                "the datum points do not fix all six degrees of freedom (3-2-1: three on a primary face, "
                "two on a secondary face, one on a third face across both); add or move points",
                field=where,
            )
    return out


def check_datums(datums: list[DatumPoint], nominal_mesh_P: trimesh.Trimesh, recipe_path: str) -> None:
    """Refuse, before a run starts, datum points off the nominal or not fixing six degrees of freedom
    (ConfigError naming the recipe and the field)."""
    try:
        resolve_datums(datums, NominalMesh.from_trimesh(nominal_mesh_P))
    except ConfigError as exc:
        raise ConfigError(str(exc), path=recipe_path, field=exc.field) from exc


def _own_surface(mesh: trimesh.Trimesh, datum: Datum, margin_mm: float = 5.0) -> NominalMesh:
    """The datum's own surface: the nominal faces near it (within its radius + ``margin_mm``) whose normal
    is within ~25 deg of the datum's."""
    near = np.linalg.norm(mesh.triangles_center - datum.point, axis=1) <= datum.radius_mm + margin_mm
    facing = mesh.face_normals @ datum.normal > SAME_SURFACE_COS
    own = mesh.submesh([np.flatnonzero(near & facing)], append=True)
    return NominalMesh.from_trimesh(cast(trimesh.Trimesh, own))  # append=True: one mesh, not a list


def _constraint_rows(points: NDArray, normals: NDArray) -> NDArray:
    """Rows [p x n, n] of the linearised normal constraint n . (w x p + t) of a small motion (w, t)."""
    return np.column_stack([np.cross(points, normals), normals])


def _surface_samples(mesh: trimesh.Trimesh, n: int = 4000) -> tuple[NDArray, NDArray]:
    pts, face = trimesh.sample.sample_surface(mesh, n, seed=0)
    return pts, mesh.face_normals[face]


def _uncertainty(cov: NDArray, samples: tuple[NDArray, NDArray]) -> dict[str, float]:
    """rms and max over the surface samples of the 1-sigma normal displacement of a 6-DOF covariance."""
    pts, nrm = samples
    J = _constraint_rows(pts, nrm)
    sigma = np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", J, cov, J), 0.0))
    return {"rms": round(float(np.sqrt(np.mean(sigma**2))), 6), "max": round(float(sigma.max()), 6)}


def _max_motion(T: Pose, pts: NDArray) -> float:
    return float(np.linalg.norm(transform_points(T, pts) - pts, axis=1).max())


class _DatumIndex:
    """The cloud's points near the datums, for the datum regions' look-ups: a KD-tree over the points within
    ``reach_mm`` (plus its radius) of each datum, not over the whole cloud (millions of points, seconds of
    tree). A look-up whose datum an alignment step moved farther than ``reach_mm`` builds the whole cloud's
    tree instead, so the answer never depends on the shortcut. Indices (ascending) are into the cloud."""

    def __init__(
        self, points: NDArray, datums: list[Datum], reach_mm: float, index: NDArray[np.int64] | None = None
    ) -> None:
        """``index``: the points within reach of a datum when an index of these points found them already."""
        self.points, self.datums, self.reach_mm = points, datums, reach_mm
        if index is None:
            near = np.zeros(len(points), dtype=bool)
            for d in datums:
                near[points_within(points, d.point, d.radius_mm + reach_mm)] = True
            index = np.flatnonzero(near)
        self.index = index
        self.tree = cKDTree(points[self.index])
        self.whole: cKDTree | None = None
        self._lock = threading.Lock()  # datums are looked up side by side (:meth:`Aligner._datum_offsets`)

    def ball(self, k: int, centre: NDArray, radius_mm: float) -> NDArray[np.int64]:
        """The points within ``radius_mm`` of ``centre``: where datum ``k`` lies in the cloud's frame."""
        d = self.datums[k]
        if radius_mm <= d.radius_mm and float(np.linalg.norm(centre - d.point)) <= self.reach_mm:
            return np.sort(self.index[self.tree.query_ball_point(centre, radius_mm)])
        with self._lock:
            if self.whole is None:
                self.whole = cKDTree(self.points)
        return np.sort(np.asarray(self.whole.query_ball_point(centre, radius_mm), dtype=np.int64))


class Aligner:
    """Alignment of a cloud (mm, {P} by the kinematic chain) to the nominal (mm, {P}) by ``config``."""

    def __init__(self, config: AlignmentConfig, nominal_mesh_P: trimesh.Trimesh) -> None:
        self.config = config
        self.mesh = nominal_mesh_P
        self.nominal = NominalMesh.from_trimesh(nominal_mesh_P)
        self.datums = resolve_datums(config.datums, self.nominal)
        self.datum_surfaces = [_own_surface(nominal_mesh_P, d) for d in self.datums]
        self.samples = _surface_samples(nominal_mesh_P)

    # ------------------------------------------------------------------ per datum
    def _index(self, points: NDArray, near: NDArray[np.int64] | None = None) -> _DatumIndex:
        """The datum regions' look-up for ``points``, for corrections up to the recipe's limit (``near``: the
        points within its reach, an earlier look-up's :attr:`Alignment.datum_near` of the same points)."""
        return _DatumIndex(points, self.datums, self.config.max_correction_mm + 1.0, near)

    def _datum_offsets(self, tree: _DatumIndex, points: NDArray, T: Pose) -> list[tuple[float, float, int]]:
        """(mean deviation, its std, point count) of each datum region with the cloud moved by ``T``: the
        datums on two threads (the trees' look-ups and the error map's kernel release the GIL; each datum's
        figures its own), the first datum not measured, in their order, raised."""
        T_inv = np.linalg.inv(T)

        def offset(k: int) -> tuple[float, float, int]:
            d = self.datums[k]
            idx = tree.ball(k, transform_points(T_inv, d.point), d.radius_mm)
            if len(idx) < MIN_DATUM_POINTS:
                raise AlignmentError(
                    f"datum '{d.name}' not measured: {len(idx)} points within {d.radius_mm} mm of it "
                    f"(needs {MIN_DATUM_POINTS}); plan views that see it or move it"
                )
            # deviations from the datum's own surface only (its faces near it that face its way): a point
            # of a thin sheet displaced by the placement error may lie nearer the sheet's other skin, and
            # points across an edge or a fillet belong to another face; those are the robust outliers
            surface = self.datum_surfaces[k]
            moved = transform_points(T, points[idx])
            em = signed_distance(surface, moved)
            dev = em.deviation_mm
            # a point whose closest point is on the surface's rim (not straight below it) is off its faces
            along = np.abs(np.einsum("ij,ij->i", moved - em.closest_mm, surface.face_normals[em.face]))
            inside = along >= 0.99 * np.abs(dev) - 1e-6
            if not inside.any():
                inside[:] = True
            spread = np.abs(dev - np.median(dev[inside]))
            own = inside & (spread <= max(3 * 1.4826 * float(np.median(spread[inside])), 0.05))
            if own.sum() < MIN_DATUM_POINTS:
                raise AlignmentError(
                    f"datum '{d.name}' not measured: {int(own.sum())} points of its surface within "
                    f"{d.radius_mm} mm of it (needs {MIN_DATUM_POINTS}); plan views that see it or move it"
                )
            dev = dev[own]
            return float(dev.mean()), float(dev.std()), int(own.sum())

        with ThreadPoolExecutor(2, thread_name_prefix="datums") as pool:
            return list(pool.map(offset, range(len(self.datums))))

    def _residuals(self, before: list, after: list) -> list[dict[str, Any]]:
        return [
            {
                "name": d.name,
                "before_mm": round(b[0], 5),
                "after_mm": round(a[0], 5),
                "spread_mm": round(a[1], 5),
                "n_points": a[2],
            }
            for d, b, a in zip(self.datums, before, after, strict=True)
        ]

    # ------------------------------------------------------------------ methods
    def kinematic(self, points: NDArray) -> Alignment:
        """No correction: the fixture's placement. The datums, where the recipe has them and they are
        measured, show how far off the part sits."""
        fixture = self.config.fixture_uncertainty_mm
        result = Alignment(
            "kinematic",
            np.eye(4),
            uncertainty_mm=None if fixture is None else {"rms": fixture, "max": fixture},
        )
        if fixture is None:
            result.warnings.append(
                "kinematic alignment: the part is judged where the recipe's T_W_P places it; its placement "
                "uncertainty is the fixture's, not measured here"
            )
        if self.datums:
            try:
                tree = self._index(points)
                result.datum_near = tree.index
                offsets = self._datum_offsets(tree, points, np.eye(4))
                result.residuals = self._residuals(offsets, offsets)
            except AlignmentError as exc:
                result.warnings.append(str(exc))
        return result

    def datums_fit(self, points: NDArray, max_iter: int = 20) -> Alignment:
        """3-2-1 / RPS: Gauss-Newton on the datums' normal constraints, re-measuring the regions each step."""
        if len(self.datums) < 6:
            raise AlignmentError(
                f"datum alignment needs >= 6 datum points, the recipe has {len(self.datums)}"
            )
        tree = self._index(points)
        P = np.array([d.point for d in self.datums])
        N = np.array([d.normal for d in self.datums])
        centre = P.mean(0)
        T = np.eye(4)
        before = offsets = self._datum_offsets(tree, points, T)
        for _ in range(max_iter):
            r = np.array([o[0] for o in offsets])
            A = _constraint_rows(P - centre, N)  # about the datums' centre: better conditioned
            step = np.linalg.lstsq(A, -r, rcond=None)[0]
            R = Rotation.from_rotvec(step[:3]).as_matrix()
            T = make_pose(R, centre + step[3:] - R @ centre) @ T
            offsets = self._datum_offsets(tree, points, T)
            if np.linalg.norm(step[:3]) * 1e3 + np.linalg.norm(step[3:]) < 1e-7:
                break
        sig2 = np.array([max(o[1], 1e-4) ** 2 / o[2] for o in offsets])  # variance of each region's mean
        A = _constraint_rows(P, N)
        cov = np.linalg.pinv(A.T @ (A / sig2[:, None]))
        res = np.array([o[0] for o in offsets])
        return Alignment(
            "datums",
            T,
            self._residuals(before, offsets),
            rms_mm=float(np.sqrt(np.mean(res**2))),
            uncertainty_mm=_uncertainty(cov, self.samples),
            datum_near=tree.index,
        )

    def datum_icp(self, points: NDArray, start: Alignment | None = None) -> Alignment:
        """Point-to-plane ICP on the points of the datum regions only, from ``start`` (default: datums)."""
        start = start or self.datums_fit(points)
        tree = self._index(points, start.datum_near)  # the datums' fit looked the same points up
        T_inv = np.linalg.inv(start.T)
        idx = sorted(
            {
                int(i)
                for k, d in enumerate(self.datums)
                for i in tree.ball(k, transform_points(T_inv, d.point), d.radius_mm)
            }
        )
        sub = points[idx]
        icp = icp_point_to_plane(self.nominal, sub, T_init=start.T)
        x = transform_points(icp.T, sub)
        em = signed_distance(self.nominal, x)
        A = _constraint_rows(x, self.nominal.face_normals[em.face])
        cov = np.linalg.pinv(A.T @ A) * max(icp.rms_mm, 1e-4) ** 2
        before = self._datum_offsets(tree, points, np.eye(4))
        after = self._datum_offsets(tree, points, icp.T)
        return Alignment(
            "datum_icp",
            icp.T,
            self._residuals(before, after),
            rms_mm=icp.rms_mm,
            uncertainty_mm=_uncertainty(cov, self.samples),
            estimates={"icp_points": len(sub), "icp_iterations": icp.iterations},
            datum_near=tree.index,
        )

    def features(self, points: NDArray) -> Alignment:
        """Curvature-feature matching (eqs 4.16-4.20): coarse, to about the point spacing."""
        try:
            fa = feature_align(self.mesh, points)
        except ConfigError as exc:
            raise AlignmentError(f"feature alignment failed: {exc}") from exc
        return Alignment(
            "features",
            fa.T,
            rms_mm=fa.rms_mm,
            uncertainty_mm={"rms": round(fa.rms_mm, 6), "max": round(fa.rms_mm, 6)},
            estimates={"matched_patches": fa.n_matched},
        )

    def best_fit(self, points: NDArray) -> Alignment:
        """ICP over the whole part (a random sample), from the datums when the recipe has them."""
        start = self.datums_fit(points).T if len(self.datums) >= 6 else np.eye(4)
        rng = np.random.default_rng(0)
        sub = points[rng.choice(len(points), min(len(points), BEST_FIT_POINTS), replace=False)]
        icp = icp_point_to_plane(self.nominal, sub, T_init=start)
        return Alignment("best_fit", icp.T, rms_mm=icp.rms_mm, warnings=[BEST_FIT_WARNING])

    def weighted(self, points: NDArray) -> Alignment:
        """Eqs 4.21-4.22: the recipe-weighted combination of kinematic, datums, datum ICP and features."""
        w = self.config.weights
        found: dict[AlignmentEstimate, Alignment] = {"kinematic": Alignment("kinematic", np.eye(4))}
        warnings = []
        if len(self.datums) >= 6:
            found["datums"] = self.datums_fit(points)
            found["datum_icp"] = self.datum_icp(points, found["datums"])
        if w.get("features", 0) > 0:
            try:
                found["features"] = self.features(points)
            except AlignmentError as exc:
                warnings.append(f"weighted alignment without features: {exc}")
        reference = found.get("datums", found["kinematic"]).T
        for k in [k for k in found if k != "kinematic"]:
            off = _max_motion(np.linalg.inv(reference) @ found[k].T, self.samples[0])
            if off > self.config.max_correction_mm:  # a wrong feature match must not drag the rest along
                warnings.append(
                    f"weighted alignment without {k}: it disagrees with the others by {off:.1f} mm"
                )
                del found[k]
        used = [(k, a) for k, a in found.items() if w.get(k, 0) > 0]
        if not used:
            raise AlignmentError("weighted alignment: every available estimate has weight 0")
        centre = points.mean(0)
        T = combine_registrations([(a.T, w[k]) for k, a in used], centre)
        spread = max(_max_motion(np.linalg.inv(T) @ a.T, self.samples[0]) for _, a in used)
        best = found.get("datum_icp") or found.get("datums")
        return Alignment(
            "weighted",
            T,
            best.residuals if best else [],
            uncertainty_mm={
                **(best.uncertainty_mm if best and best.uncertainty_mm else {}),
                "disagreement_max": round(spread, 6),
            },
            warnings=warnings,
            estimates={k: {"weight": w[k], "T_P_cloud": np.round(a.T, 9).tolist()} for k, a in used},
        )

    def align(self, points: NDArray) -> Alignment:
        """The recipe's alignment of ``points``; AlignmentError when the measurement does not allow it."""
        method = self.config.method
        if method == "kinematic":
            result = self.kinematic(points)
        elif method == "datums":
            result = self.datums_fit(points)
        elif method == "datum_icp":
            result = self.datum_icp(points)
        elif method == "features":
            result = self.features(points)
        elif method == "best_fit":
            result = self.best_fit(points)
        else:
            result = self.weighted(points)
        result.correction_mm = _max_motion(result.T, self.samples[0])
        if result.correction_mm > self.config.max_correction_mm:
            raise AlignmentError(
                f"{method} alignment would move the part by up to {result.correction_mm:.2f} mm, more than "
                f"alignment.max_correction_mm = {self.config.max_correction_mm} mm: wrong datums, wrong part "
                "or a wrong placement"
            )
        return result
