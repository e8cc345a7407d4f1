"""The glass measurement from one set of rig frames: markers -> view rays -> reflection search -> feedback.

Each camera in turn is the primary for the markers it identified; the others confirm or correct its points
(3.4). Identification predicts, for every detected dot, the screen point its view ray reaches when reflected
by the nominal CAD, and takes the nearest screen dot within a gate (robust to missing dots; the weaker
bottom-skin copies are dropped before it: by the detector's threshold where the tint makes them weaker,
and geometrically by :mod:`cell.glass.bottom` from the pane's thickness and index).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cell.contracts import MarkerScreen
from cell.glass.bottom import blob_area_ok, bottom_copies, predict_copies
from cell.glass.calibration import LocalQuadratic, ViewVectorCalibration
from cell.glass.config import GlassSearchConfig
from cell.glass.consistency import check_consistency, check_projection
from cell.glass.feedback import FeedbackCamera, feedback
from cell.glass.markers import DotDetections, detect_dots, identify
from cell.glass.multiprojection import ProjectionFit, multi_projection
from cell.glass.reflection import RaySearchProblem, ReflectionLaw, golden_section
from cell.glass.surface import SmoothSurface, plane_hits, reflect


@dataclass(frozen=True)
class CameraMarkers:
    """One camera's identified markers: centroids (N, 2), view rays (N, 3) and screen dot index (N,)."""

    detections: DotDetections
    origins: NDArray[np.float64]
    dirs: NDArray[np.float64]
    dot: NDArray[np.int64]


@dataclass(frozen=True)
class GlassMeasurement:
    """Measured surface points and normals (world mm) with the primary camera, the dot, the cameras used,
    the search's offset angle (rad) and iteration count per point."""

    points: NDArray[np.float64]
    normals: NDArray[np.float64]
    camera: NDArray[np.int64]
    dot: NDArray[np.int64]
    n_cameras: NDArray[np.int64]
    theta: NDArray[np.float64]
    iterations: NDArray[np.int64]
    residual: NDArray[np.float64]  # feedback cost: sum of squared normal angles to their mean (rad^2)
    curvature: NDArray[np.float64]  # its second derivative along the primary ray (rad^2/mm^2)
    cos_incidence: NDArray[np.float64]  # |primary ray . normal|
    points_single: NDArray[np.float64]  # the primary camera's CAD-seeded result before feedback
    accepted: NDArray[np.bool_]  # passed the consistency test (cell.glass.consistency)
    p_value: NDArray[np.float64]
    depth_sigma_mm: NDArray[np.float64]
    normal_sigma_rad: float  # per-camera normal noise estimated from all residuals
    # seen by one camera, measured by multi-projection: judged by its own two-screen geometry instead
    single_projection: NDArray[np.bool_]


def find_markers(
    image: NDArray,
    calib: ViewVectorCalibration,
    cad: SmoothSurface,
    screen: MarkerScreen,
    search: GlassSearchConfig,
) -> CameraMarkers:
    """Detect, ray and identify one camera's marker dots."""
    det = detect_dots(image, dark_fraction=search.dark_fraction, full_profile_px=search.centroid_profile_px)
    if search.pane_thickness_mm is not None and len(det):
        copies = predict_copies(
            det.centroids_px,
            calib.rays_at,
            cad,
            screen.T_W_S,
            search.pane_thickness_mm,
            search.pane_refractive_index,
        )
        keep = blob_area_ok(det.area_px, copies, screen.dot_diameter_mm)
        keep &= ~bottom_copies(det.centroids_px, copies, screen.dots_mm)
        det = DotDetections(det.centroids_px[keep], det.area_px[keep], det.depth[keep])
    o, d = calib.rays_at(det.centroids_px)
    hit = cad.cast(np.nan_to_num(o), np.nan_to_num(d, nan=1.0 / np.sqrt(3)))
    pred = plane_hits(np.nan_to_num(hit.point), reflect(d, np.nan_to_num(hit.normal)), screen.T_W_S)
    pred[~(hit.hit & np.all(np.isfinite(d), axis=1))] = np.nan
    pitch = float(np.median(np.linalg.norm(np.diff(screen.dots_mm, axis=0), axis=1)))
    dot = identify(pred, screen.dots_mm, search.gate_fraction * pitch)
    return CameraMarkers(det, o, d, dot)


def screen_point_W(screen: MarkerScreen, dot: NDArray[np.int64]) -> NDArray[np.float64]:
    """World coordinates (N, 3) of screen dots."""
    xy = screen.dots_mm[dot]
    T = screen.T_W_S
    return xy[:, 0:1] * T[:3, 0] + xy[:, 1:2] * T[:3, 1] + T[:3, 3]


def measure(
    images: list[NDArray],
    calibs: list[ViewVectorCalibration],
    cad: SmoothSurface,
    screen: MarkerScreen,
    search: GlassSearchConfig,
    max_cameras: int | None = None,
    second: tuple[list[NDArray], MarkerScreen] | None = None,
) -> GlassMeasurement:
    """Measure the pane from one frame per camera. ``max_cameras`` caps the cameras per point (1 = no
    feedback; None = until the normal settles below ``search.feedback_tol_urad``, or all when forced by
    ``max_cameras``). ``second``: the frames with the screen at its second position and that screen, which
    ``search.method`` = "multi_projection" needs."""
    if search.method == "multi_projection" and second is None:
        raise ValueError("the multi-projection method needs the frames at the second screen position")
    markers = [find_markers(img, cal, cad, screen, search) for img, cal in zip(images, calibs)]
    markers2 = (
        [find_markers(img, cal, cad, second[1], search) for img, cal in zip(second[0], calibs)]
        if search.method == "multi_projection" and second is not None
        else None
    )
    fb_cams = []
    for m, cal in zip(markers, calibs):
        ok = m.dot >= 0
        screen_map = LocalQuadratic(m.detections.centroids_px[ok], screen.dots_mm[m.dot[ok]], k=12)
        fb_cams.append(FeedbackCamera(cal, screen_map))
    forced = max_cameras is not None
    tol = 0.0 if forced else search.feedback_tol_urad * 1e-6
    out: dict[str, list] = {k: [] for k in _PER_CAMERA}
    for c, m in enumerate(markers):
        ok = (m.dot >= 0) & np.all(np.isfinite(m.dirs), axis=1)
        prob = RaySearchProblem(m.origins[ok], m.dirs[ok], screen_point_W(screen, m.dot[ok]))
        law = ReflectionLaw(prob, cad)
        if markers2 is not None and second is not None:
            m2 = markers2[c]
            ok2 = m2.dot >= 0
            res, fit = multi_projection(
                law,
                m.detections.centroids_px[ok],
                m2.detections.centroids_px[ok2],
                second[1].dots_mm[m2.dot[ok2]],
                second[1],
            )
        else:
            res = golden_section(
                law, search.max_surface_error_mm, search.angle_tol_urad * 1e-6, search.length_tol_mm
            )
            fit = ProjectionFit(*(np.full(len(res.t), np.nan) for _ in range(3)))
        others = [fb for j, fb in enumerate(fb_cams) if j != c]
        if max_cameras is not None:  # forced
            others = others[: max(max_cameras - 1, 0)]
        fb = feedback(law, res, others, screen.T_W_S, search.max_surface_error_mm, tol, search.length_tol_mm)
        keep = res.ok
        out["points"].append(fb.points[keep])
        out["normals"].append(fb.normals[keep])
        out["camera"].append(np.full(int(keep.sum()), c))
        out["dot"].append(m.dot[ok][keep])
        out["n_cameras"].append(fb.n_cameras[keep])
        out["theta"].append(res.theta[keep])
        out["iterations"].append(res.iterations[keep])
        out["residual"].append(fb.residual[keep])
        out["curvature"].append(fb.curvature[keep])
        out["cos_incidence"].append(np.abs(np.einsum("ij,ij->i", prob.dirs, fb.normals))[keep])
        out["points_single"].append(res.points[keep])
        out["miss_mm"].append(fit.miss_mm[keep])
        out["lever"].append(fit.lever[keep])
        out["sin_angle"].append(fit.sin_angle[keep])
    cat = {k: np.concatenate(v) for k, v in out.items()}
    miss_mm, lever, sin_angle = (cat.pop(k) for k in ("miss_mm", "lever", "sin_angle"))
    cons = check_consistency(
        cat["residual"],
        cat["curvature"],
        cat["n_cameras"],
        cat["cos_incidence"],
        search.outlier_alpha,
        search.max_depth_sigma_mm,
    )
    accepted, p_value, depth_sigma = cons.accepted.copy(), cons.p_value.copy(), cons.depth_sigma_mm.copy()
    single = (cat["n_cameras"] == 1) & np.isfinite(miss_mm)
    if single.any():  # multi-projection points no other camera confirms: their own geometry judges them
        proj = check_projection(
            miss_mm, lever, sin_angle, cat["cos_incidence"], search.outlier_alpha, search.max_depth_sigma_mm
        )
        accepted[single], p_value[single] = proj.accepted[single], proj.p_value[single]
        depth_sigma[single] = proj.depth_sigma_mm[single]
    return GlassMeasurement(
        **cat,
        accepted=accepted,
        p_value=p_value,
        depth_sigma_mm=depth_sigma,
        normal_sigma_rad=cons.sigma_rad,
        single_projection=single,
    )


_PER_CAMERA = (
    "points",
    "normals",
    "camera",
    "dot",
    "n_cameras",
    "theta",
    "iterations",
    "residual",
    "curvature",
    "cos_incidence",
    "points_single",
    "miss_mm",
    "lever",
    "sin_angle",
)
