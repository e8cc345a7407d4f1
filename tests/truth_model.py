"""A measurement model from the simulator's per-pixel ground truth, independent of the planner's prediction.

Given the ground truth of one camera pose (hit points, normals, part and lit masks, as
``fakes.sim.render.SceneRenderer.ground_truth`` returns them) and the radiometry of the cell, a pixel is
measured when it sees the part, is lit by the projector, lies within the focus range, and its white-pattern
signal is neither saturated (glare: ambient + Lambert + Phong specular reach the full well, eq 3.23) nor too
weak (low contrast). Shadowed pixels (inside the projector frustum, not lit) form the shadow masks. The
planner's tests measure with it where the real scan pipeline would be too slow; it is their oracle, so it
lives with the tests, not in the product (cell/) nor in the simulator the product drives (fakes/).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from cell.config import CellConfig, MaterialConfig
from cell.geometry import Pose
from cell.planning.measured import MeasuredView, measured_view_from_masks

LOW_SIGNAL_SHARE = 0.03  # white-pattern signal under this share of the full well: too little stripe contrast


def measure_from_truth(
    gt: Any, T_W_C: Pose, cfg: CellConfig, material: MaterialConfig, nominal_W: np.ndarray | None = None
) -> MeasuredView:
    """MeasuredView of one pose from ground truth ``gt``; ``nominal_W`` (H, W, 3) defaults to the hit
    points."""
    cam, proj = cfg.sensor.camera, cfg.sensor.projector
    part = gt.part
    P = gt.points_W
    n = gt.normals_W
    depth = gt.points_C[..., 2]
    in_focus = np.abs(depth - cfg.sensor.standoff_mm) <= 0.5 * cfg.sensor.depth_of_field_mm
    T_W_P = T_W_C @ proj.T_C_P.matrix()
    with np.errstate(invalid="ignore"):
        to_p = T_W_P[:3, 3] - P
        r = np.linalg.norm(to_p, axis=-1)
        l_p = to_p / r[..., None]
        to_c = T_W_C[:3, 3] - P
        l_c = to_c / np.linalg.norm(to_c, axis=-1, keepdims=True)
        cos_i = np.clip(np.einsum("...k,...k->...", n, l_p), 0, 1)
        mirror = 2 * cos_i[..., None] * n - l_p
        cos_a = np.clip(np.einsum("...k,...k->...", mirror, l_c), 0, 1)
        rate = (
            proj.irradiance_e_per_ms
            * (proj.focus_distance_mm / r) ** 2
            * (material.albedo * cos_i + material.specular * cos_a**material.shininess)
        )
        signal = cam.exposure_ms * (rate + cfg.sim.ambient_e_per_ms * material.albedo)
    glare = part & gt.lit & (signal >= cam.full_well_e)
    low = part & gt.lit & ~glare & (signal < LOW_SIGNAL_SHARE * cam.full_well_e)
    in_frustum = np.isfinite(gt.projector_uv).all(axis=-1)
    shadow = part & in_frustum & ~gt.lit
    valid = part & gt.lit & in_focus & ~glare & ~low
    nominal = P if nominal_W is None else nominal_W
    nominal = np.where(part[..., None], nominal, np.nan)
    return measured_view_from_masks(
        T_W_C, P, valid, {"shadow": shadow, "glare": glare, "low_contrast": low}, nominal, normals_W=n
    )
