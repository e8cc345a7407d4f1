"""The area sensor as the planner sees it: where camera and projector are for a viewpoint, and which surface
points one viewpoint measures (the task constraints TC of eq 3.4 applied point by point).

A viewpoint is the camera pose ``T_W_C`` (OpenCV optical frame, +z along the view). The projector sits at
``T_W_C @ T_C_P``. Constraints are tested projector first, then camera (section 3.1.1): a point is
measured when it is lit (inside the projector frustum, normal within theta_th1 of the ray to the projector,
not shadowed,
projector point density met) and seen (inside the image, within the focus range, normal within theta_th2 of
the ray to the camera, pixel footprint <= resolution, camera point density met, not occluded). Lens distortion
is ignored here; ``fov_margin`` keeps the planned patch away from the image border where it matters.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, overload

import numpy as np
from numpy.typing import NDArray

from cell.config import CellConfig
from cell.geometry import Pose, invert
from cell.planning.occlusion import Occluder
from cell.planning.settings import PlanSettings

Array = NDArray[np.float64]

# Order in which measurable() tests the constraints; the first failing one is the reason a point is lost.
REASONS = (
    "projector_frustum",
    "projector_angle",
    "projector_density",
    "camera_frustum",
    "focus",
    "camera_angle",
    "resolution",
    "camera_density",
    "shadow",
    "camera_occluded",
)


@dataclass(frozen=True)
class SensorModel:
    """Sensor geometry (from the cell config) plus the task thresholds (from PlanSettings)."""

    K_cam: Array
    cam_size: tuple[int, int]  # (width, height) px
    K_proj: Array
    proj_size: tuple[int, int]
    T_C_P: Pose
    T_T_C: Pose
    T_W_B: Pose
    standoff_mm: float
    dof_mm: float
    settings: PlanSettings

    @classmethod
    def from_config(cls, cfg: CellConfig, settings: PlanSettings) -> SensorModel:
        s = cfg.sensor
        return cls(
            s.camera.K(),
            (s.camera.width_px, s.camera.height_px),
            s.projector.K(),
            (s.projector.width_px, s.projector.height_px),
            s.projector.T_C_P.matrix(),
            s.T_T_C.matrix(),
            cfg.robot.T_W_B.matrix(),
            s.standoff_mm,
            s.depth_of_field_mm,
            settings,
        )

    @property
    def fov_mm(self) -> tuple[float, float]:
        """Field of view (width along camera x, height along y) at the stand-off, mm."""
        return (
            self.cam_size[0] * self.standoff_mm / self.K_cam[0, 0],
            self.cam_size[1] * self.standoff_mm / self.K_cam[1, 1],
        )

    @property
    def triangulation_angle(self) -> float:
        """Angle (rad) between camera and projector rays at the centre of the field at stand-off."""
        c = np.array([0.0, 0.0, self.standoff_mm])
        to_p = self.T_C_P[:3, 3] - c
        return float(np.arccos(to_p @ -c / (np.linalg.norm(to_p) * np.linalg.norm(c))))

    def pose(self, target_W: Array, view_dir_W: Array, roll_rad: float, ref_W: Array | None = None) -> Pose:
        """Camera pose looking along ``view_dir_W`` at ``target_W`` from the stand-off, rolled about the view
        axis by ``roll_rad`` from the reference direction ``ref_W`` (image +x; default: world x or y)."""
        z = np.asarray(view_dir_W, dtype=np.float64)
        z = z / np.linalg.norm(z)
        ref = np.array([1.0, 0.0, 0.0]) if ref_W is None else np.asarray(ref_W, dtype=np.float64)
        if abs(ref @ z) > 0.95:
            ref = np.array([0.0, 1.0, 0.0])
        x0 = ref - (ref @ z) * z
        x0 /= np.linalg.norm(x0)
        y0 = np.cross(z, x0)
        x = np.cos(roll_rad) * x0 + np.sin(roll_rad) * y0
        T = np.eye(4)
        T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
        T[:3, 3] = np.asarray(target_W, dtype=np.float64) - self.standoff_mm * z
        return T

    def bisector_pose(self, T_W_C: Pose, target_W: Array) -> Pose:
        """Rotate the sensor about ``target_W`` (about the camera y axis) so that the original view axis
        bisects the rays to camera and projector: half the triangulation angle toward the projector."""
        from scipy.spatial.transform import Rotation

        R = Rotation.from_rotvec(T_W_C[:3, 1] * (0.5 * self.triangulation_angle)).as_matrix()
        best: tuple[float, Pose] | None = None
        for sign in (1.0, -1.0):
            Rs = R if sign > 0 else R.T
            T = np.eye(4)
            T[:3, :3] = Rs @ T_W_C[:3, :3]
            T[:3, 3] = target_W + Rs @ (T_W_C[:3, 3] - target_W)
            n = -T_W_C[:3, 2]
            to_c = T[:3, 3] - target_W
            to_p = self.projector_pose(T)[:3, 3] - target_W
            err = abs(np.arccos(n @ to_c / np.linalg.norm(to_c)) - np.arccos(n @ to_p / np.linalg.norm(to_p)))
            if best is None or err < best[0]:
                best = (float(err), T)
        assert best is not None  # the loop ran
        return best[1]

    def projector_pose(self, T_W_C: Pose) -> Pose:
        return T_W_C @ self.T_C_P

    def robot_target(self, T_W_C: Pose) -> Pose:
        """Flange target ``T_B_T = inv(T_W_B) @ T_W_C @ inv(T_T_C)``."""
        return invert(self.T_W_B) @ T_W_C @ invert(self.T_T_C)

    @overload
    def measurable(
        self,
        T_W_C: Pose,
        points: Array,
        normals: Array,
        occluder: Occluder | None,
        with_reason: Literal[False] = False,
    ) -> NDArray[np.bool_]: ...

    @overload
    def measurable(
        self,
        T_W_C: Pose,
        points: Array,
        normals: Array,
        occluder: Occluder | None,
        with_reason: Literal[True],
    ) -> tuple[NDArray[np.bool_], NDArray[np.int8]]: ...

    def measurable(
        self, T_W_C: Pose, points: Array, normals: Array, occluder: Occluder | None, with_reason: bool = False
    ) -> NDArray[np.bool_] | tuple[NDArray[np.bool_], NDArray[np.int8]]:
        """Which points (N, 3) with unit normals (N, 3), world mm, this viewpoint measures.

        With ``with_reason`` also returns, per point, the index into REASONS of the first failed constraint
        (-1 when measured). Occlusion rays are cast only for points that pass every cheap test.
        """
        st = self.settings
        n = len(points)
        reason = np.full(n, -1, dtype=np.int8)

        def fail(mask: NDArray[np.bool_], name: str) -> None:
            reason[(reason < 0) & mask] = REASONS.index(name)

        T_W_P = self.projector_pose(T_W_C)
        # projector first (eq 3.3: its constraints are satisfied before the camera's)
        pp = (points - T_W_P[:3, 3]) @ T_W_P[:3, :3]
        with np.errstate(divide="ignore", invalid="ignore"):
            up = self.K_proj[0, 0] * pp[:, 0] / pp[:, 2] + self.K_proj[0, 2]
            vp = self.K_proj[1, 1] * pp[:, 1] / pp[:, 2] + self.K_proj[1, 2]
        fail(
            ~((pp[:, 2] > 0) & (up >= 0) & (up < self.proj_size[0]) & (vp >= 0) & (vp < self.proj_size[1])),
            "projector_frustum",
        )
        to_p = T_W_P[:3, 3] - points
        r_p = np.linalg.norm(to_p, axis=1)
        l_p = to_p / r_p[:, None]
        cos_p = np.einsum("ij,ij->i", normals, l_p)
        fail(cos_p < np.cos(np.deg2rad(st.theta_projector_deg)), "projector_angle")
        # projector pixels per mm^2 on the surface: (f / r)^2 * cos(incidence)
        fail(
            (self.K_proj[0, 0] / r_p) ** 2 * np.maximum(cos_p, 0) < st.point_density_per_mm2,
            "projector_density",
        )
        # then the camera
        pc = (points - T_W_C[:3, 3]) @ T_W_C[:3, :3]
        with np.errstate(divide="ignore", invalid="ignore"):
            uc = self.K_cam[0, 0] * pc[:, 0] / pc[:, 2] + self.K_cam[0, 2]
            vc = self.K_cam[1, 1] * pc[:, 1] / pc[:, 2] + self.K_cam[1, 2]
        fail(
            ~((pc[:, 2] > 0) & (uc >= 0) & (uc < self.cam_size[0]) & (vc >= 0) & (vc < self.cam_size[1])),
            "camera_frustum",
        )
        half = 0.5 * self.dof_mm
        fail(np.abs(pc[:, 2] - self.standoff_mm) > half, "focus")
        to_c = T_W_C[:3, 3] - points
        r_c = np.linalg.norm(to_c, axis=1)
        l_c = to_c / r_c[:, None]
        cos_c = np.einsum("ij,ij->i", normals, l_c)
        fail(cos_c < np.cos(np.deg2rad(st.theta_camera_deg)), "camera_angle")
        footprint = r_c / self.K_cam[0, 0] / np.maximum(cos_c, 1e-6)  # pixel length along the steepest slope
        fail(footprint > st.resolution_mm, "resolution")
        fail(
            (self.K_cam[0, 0] / r_c) ** 2 * np.maximum(cos_c, 0) < st.point_density_per_mm2, "camera_density"
        )
        if occluder is not None:
            cand = np.flatnonzero(reason < 0)
            if len(cand):
                shadow = occluder.occluded(points[cand], normals[cand], l_p[cand], r_p[cand])
                fail(np.isin(np.arange(n), cand[shadow]), "shadow")
                cand = np.flatnonzero(reason < 0)
                hidden = occluder.occluded(points[cand], normals[cand], l_c[cand], r_c[cand])
                fail(np.isin(np.arange(n), cand[hidden]), "camera_occluded")
        ok = reason < 0
        return (ok, reason) if with_reason else ok

    def mirror_angle(self, T_W_C: Pose, points: Array, normals: Array) -> Array:
        """Angle (rad) between the mirror direction of the projector light and the ray to the camera, per
        point:
        0 means the camera looks straight into the specular reflection (the glare geometry of eq 3.23)."""
        T_W_P = self.projector_pose(T_W_C)
        l_p = T_W_P[:3, 3] - points
        l_p /= np.linalg.norm(l_p, axis=1, keepdims=True)
        l_c = T_W_C[:3, 3] - points
        l_c /= np.linalg.norm(l_c, axis=1, keepdims=True)
        mirror = 2 * np.einsum("ij,ij->i", normals, l_p)[:, None] * normals - l_p
        return np.arccos(np.clip(np.einsum("ij,ij->i", mirror, l_c), -1.0, 1.0))
