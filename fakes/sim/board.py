"""Calibration boards in the simulated world: the flat white reference board stepped toward the sensor
(per-pixel sensor calibration, dissertation 5.1.1), and textured planar boards (ChArUco) for intrinsics.

The reference board is a real mesh in the scene, rendered by :class:`fakes.sim.render.SceneRenderer` with the
camera's optics and noise. Textured boards are rendered here: every camera pixel's ray (distortion removed,
as the scene renderer does) meets the board plane, the board texture is sampled there (pre-blurred to the
pixel footprint so that edges do not alias), lit by ambient light plus the projector's uniform white, then
blurred by the camera's defocus at the board distance and turned into digital numbers with the scene
renderer's sensor model (shot + read noise, gain, quantisation).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import cast

import cv2
import numpy as np
import trimesh
from numpy.typing import NDArray

from cell.config import MaterialConfig, ProjectorConfig, SensorConfig, SimConfig
from cell.geometry import invert, look_at, transform_points
from fakes.sim.optics import blur_sigma_px, pixel_rays, project_points, projector_lut, projector_response
from fakes.sim.render import SceneRenderer
from fakes.sim.scene import Scene

WHITE_BOARD = MaterialConfig(albedo=0.8, specular=0.0, shininess=1.0)
BOARD_BASE_Z_MM = 100.0  # the reference plane (step 0) lies this far above the table


def reference_board_mesh(
    top_z_mm: float, size_mm: tuple[float, float] = (600.0, 450.0), thickness_mm: float = 10.0
) -> trimesh.Trimesh:
    """A flat board centred on the world z axis whose top face is the plane z = ``top_z_mm`` (mm)."""
    box = trimesh.creation.box(extents=(size_mm[0], size_mm[1], thickness_mm))
    box.apply_translation((0.0, 0.0, top_z_mm - thickness_mm / 2))
    return box


def sphere_on_board(radius_mm: float, height_mm: float = 0.0) -> tuple[trimesh.Trimesh, NDArray[np.float64]]:
    """A sphere resting on the reference board at step ``height_mm``, and its centre in {W} (mm). A trimesh
    icosphere of 5 subdivisions (20480 facets, within 0.03 % of the radius inside the true sphere)."""
    centre = np.array([0.0, 0.0, BOARD_BASE_Z_MM + height_mm + radius_mm])
    return trimesh.creation.icosphere(subdivisions=5, radius=radius_mm).apply_translation(centre), centre


@dataclass
class SteppedReferenceBoard:
    """The flat board on a stage that moves it toward the fixed sensor, which looks straight down at it.

    Step height h (mm) puts the board top at z = BOARD_BASE_Z_MM + h; the camera's reference-plane depth is
    ``sensor.standoff_mm`` at h = 0, so on this board the analytic truth of the per-pixel model is
    S = standoff and d = |baseline component parallel to the board| when the projector centre lies in the
    camera's z = 0 plane (see docs/calibration.md)."""

    sensor: SensorConfig
    sim: SimConfig
    material: MaterialConfig = field(default_factory=WHITE_BOARD.model_copy)

    @property
    def T_W_C(self) -> NDArray[np.float64]:
        eye = (0.0, 0.0, BOARD_BASE_Z_MM + self.sensor.standoff_mm)
        return look_at(eye, (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0))

    def renderer(self, height_mm: float, part_W: trimesh.Trimesh | None = None) -> SceneRenderer:
        """Renderer of the board at step height ``height_mm`` (optionally with ``part_W`` standing on it)."""
        board = reference_board_mesh(BOARD_BASE_Z_MM + height_mm)
        mesh = board if part_W is None else cast(trimesh.Trimesh, trimesh.util.concatenate([board, part_W]))
        return SceneRenderer(self.sensor, self.sim, Scene.from_meshes(mesh, self.sim, self.material))

    def capture(
        self,
        height_mm: float,
        patterns: Sequence[NDArray[np.uint8]],
        rng: np.random.Generator,
        exposure_ms: float | None = None,
    ) -> NDArray[np.integer]:
        """(N, H, W) camera images of ``patterns`` on the board at ``height_mm``."""
        cam = self.sensor.camera
        return self.renderer(height_mm).render_stack(
            self.T_W_C, list(patterns), exposure_ms or cam.exposure_ms, cam.gain_db, rng
        )


# --------------------------------------------------------------------------------------------- textured
# boards
def charuco_board(
    squares: tuple[int, int] = (9, 7),
    square_mm: float = 20.0,
    marker_mm: float = 15.0,
    dictionary: int = cv2.aruco.DICT_5X5_100,
) -> cv2.aruco.CharucoBoard:
    """An OpenCV ChArUco board (lengths in mm)."""
    return cv2.aruco.CharucoBoard(
        squares, square_mm, marker_mm, cv2.aruco.getPredefinedDictionary(dictionary)
    )


def board_texture(
    board: cv2.aruco.CharucoBoard,
    px_per_mm: float = 8.0,
    black_albedo: float = 0.05,
    white_albedo: float = 0.85,
) -> tuple[NDArray[np.float32], float]:
    """Albedo image (float32) of the board's printed face and its resolution (texture px per mm)."""
    nx, ny = board.getChessboardSize()
    s = board.getSquareLength()
    img = board.generateImage(
        (int(round(nx * s * px_per_mm)), int(round(ny * s * px_per_mm))), marginSize=0, borderBits=1
    )
    return (black_albedo + (white_albedo - black_albedo) * img.astype(np.float32) / 255.0), px_per_mm


def render_textured_board(
    renderer: SceneRenderer,
    T_C_Bd: NDArray[np.float64],
    texture: NDArray[np.float32],
    px_per_mm: float,
    rng: np.random.Generator | None,
    white_level: float = 1.0,
    exposure_ms: float | None = None,
) -> NDArray[np.integer]:
    """Camera image of a textured board whose plane is z = 0 of {Bd} (x right, y down along the texture,
    origin at the texture's top-left corner, mm), at pose ``T_C_Bd`` in front of the camera.

    Only the board is in view (it hides what lies behind it); ``white_level`` is the projector's uniform
    grey (0..1) lighting it, besides the ambient light."""
    view = _BoardView(renderer, T_C_Bd, texture, px_per_mm)
    proj = renderer.proj
    return view.image(float(projector_response(proj, float(white_level))), rng, exposure_ms)


def render_textured_board_stack(
    renderer: SceneRenderer,
    T_C_Bd: NDArray[np.float64],
    texture: NDArray[np.float32],
    px_per_mm: float,
    patterns: Sequence[NDArray[np.uint8]],
    rng: np.random.Generator | None,
    exposure_ms: float | None = None,
) -> NDArray[np.integer]:
    """(N, H, W) camera images of projector ``patterns`` on the textured board (projector calibration): each
    board point shows the pattern where it lies in the projector image (pinhole projector at
    ``renderer.T_C_P``, its response curve and its defocus blur at the board distance). One geometry pass."""
    view = _BoardView(renderer, T_C_Bd, texture, px_per_mm)
    proj = renderer.proj
    uv = project_points(
        proj, transform_points(invert(renderer.T_C_P), view.P_C), renderer.projector_distortion
    ).astype(np.float32)
    uv[~view.hit | ~np.isfinite(uv[..., 0])] = -1e6
    p_depth = float(np.median(transform_points(invert(renderer.T_C_P), view.P_C[view.hit])[:, 2]))
    p_sigma = float(blur_sigma_px(proj, np.array([p_depth]))[0])
    out = []
    for pattern in patterns:
        pat = np.asarray(pattern)
        if pat.shape != (proj.height_px, proj.width_px) or pat.dtype != np.uint8:
            raise ValueError(
                f"pattern must be uint8 {(proj.height_px, proj.width_px)}, got {pat.dtype} {pat.shape}"
            )
        out.append(view.image(_projected(proj, pat, uv, p_sigma), rng, exposure_ms))
    return np.stack(out)


def _projected(
    proj: ProjectorConfig, pattern: NDArray[np.uint8], uv: NDArray[np.float32], p_sigma: float
) -> NDArray[np.float32]:
    """Relative projector radiance (0..1) at each camera pixel: ``pattern`` through the projector's response,
    blurred by its defocus (``p_sigma`` px) and sampled at the pixel's projector coordinates ``uv`` (black
    level outside the projector image)."""
    lin = projector_lut(proj)[pattern]
    if p_sigma > 0.3:
        lin = np.asarray(cv2.GaussianBlur(lin, (0, 0), p_sigma, borderType=cv2.BORDER_REPLICATE), np.float32)
    return np.asarray(
        cv2.remap(
            lin,
            uv[..., 0],
            uv[..., 1],
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=float(proj.black_level),
        ),
        np.float32,
    )


class _BoardView:
    """Pattern-independent geometry and shading of a textured board at one pose (see
    render_textured_board)."""

    def __init__(
        self,
        renderer: SceneRenderer,
        T_C_Bd: NDArray[np.float64],
        texture: NDArray[np.float32],
        px_per_mm: float,
    ):
        self.renderer = renderer
        cam, proj = renderer.cam, renderer.proj
        rays = pixel_rays(cam)
        T_Bd_C = invert(T_C_Bd)
        o = T_Bd_C[:3, 3]
        d = rays @ T_Bd_C[:3, :3].T
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -o[2] / d[..., 2]
        self.hit = hit = np.isfinite(t) & (t > 0)
        P = o + d * np.where(hit, t, 0)[..., None]
        map_x = (P[..., 0] * px_per_mm - 0.5).astype(np.float32)
        map_y = (P[..., 1] * px_per_mm - 0.5).astype(np.float32)
        map_x[~hit] = -1e6
        # footprint of one camera pixel on the board, in texture px: pre-blur the texture to it
        # (anti-aliasing)
        self.depth = float(np.median(t[hit] * rays[..., 2][hit])) if hit.any() else cam.focus_distance_mm
        footprint = self.depth / cam.fx_px * px_per_mm
        tex = cv2.GaussianBlur(texture, (0, 0), max(0.5 * footprint, 0.3))
        self.albedo = cv2.remap(
            tex, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0
        )
        n_C = T_C_Bd[:3, 2]
        self.P_C = rays * (t * hit)[..., None]
        to_proj = renderer.T_C_P[:3, 3] - self.P_C
        r = np.linalg.norm(to_proj, axis=-1)
        cos_i = np.abs(to_proj @ n_C) / np.maximum(r, 1e-9)
        self.proj_rate = (proj.irradiance_e_per_ms * (proj.focus_distance_mm / r) ** 2 * cos_i).astype(
            np.float32
        )

    def image(
        self, lit: float | NDArray[np.float32], rng: np.random.Generator | None, exposure_ms: float | None
    ) -> NDArray[np.integer]:
        """The camera image when the projector's linear output at each pixel's board point is ``lit``."""
        r, cam = self.renderer, self.renderer.cam
        rate = self.albedo * (r.sim.ambient_e_per_ms + self.proj_rate * lit)
        signal = (rate * np.float32(exposure_ms or cam.exposure_ms)).astype(np.float32)
        signal[~self.hit] = 0.0
        sigma = float(blur_sigma_px(cam, np.array([self.depth]))[0])
        if sigma > 0.3:
            signal = cv2.GaussianBlur(signal, (0, 0), sigma)
        return r.sensor_dn(signal, cam.gain_db, rng)


def board_poses(
    board: cv2.aruco.CharucoBoard,
    distance_mm: float,
    n: int,
    rng: np.random.Generator,
    max_tilt_deg: float = 30.0,
    spread_mm: float = 25.0,
) -> list[NDArray[np.float64]]:
    """``n`` poses ``T_C_Bd`` of a planar board in front of the camera for calibration: board centre near the
    optical axis at ``distance_mm`` (+-10 %), shifted up to ``spread_mm`` sideways, tilted up to
    ``max_tilt_deg`` about a random in-plane axis and turned up to +-20 deg about its normal."""
    from scipy.spatial.transform import Rotation

    nx, ny = board.getChessboardSize()
    s = board.getSquareLength()
    centre_Bd = np.array([nx * s / 2, ny * s / 2, 0.0])
    out = []
    for _ in range(n):
        axis = rng.uniform(0, 2 * np.pi)
        tilt = np.radians(rng.uniform(0.3, 1.0) * max_tilt_deg)
        R = (
            Rotation.from_rotvec(tilt * np.array([np.cos(axis), np.sin(axis), 0.0]))
            * Rotation.from_rotvec([0.0, 0.0, np.radians(rng.uniform(-20, 20))])
        ).as_matrix()
        c_C = np.array([*rng.uniform(-spread_mm, spread_mm, 2), distance_mm * rng.uniform(0.9, 1.1)])
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = c_C - R @ centre_Bd
        out.append(T)
    return out


class TexturedBoardRenderer:
    """A stand-in for :class:`SceneRenderer` (same ``render`` call) that shows a textured board at a fixed
    world pose ``T_W_Bd`` lit by whatever the projector emits: what a simulated camera sees while a board
    stage holds a ChArUco board in front of it. ``base`` gives the true optics (camera, projector, T_C_P), the
    noise model and the scene around the board (pixels whose ray misses the board see ``base``'s scene)."""

    def __init__(
        self, base: SceneRenderer, T_W_Bd: NDArray[np.float64], texture: NDArray[np.float32], px_per_mm: float
    ) -> None:
        self.base = base
        self.sensor, self.sim, self.cam, self.proj = base.sensor, base.sim, base.cam, base.proj
        self.T_C_P = base.T_C_P
        self.T_W_Bd = np.asarray(T_W_Bd, dtype=np.float64)
        self.texture, self.px_per_mm = texture, px_per_mm
        self._view: tuple[bytes, _BoardView, NDArray[np.float32], float] | None = None
        self._on_board: NDArray[np.bool_] = np.zeros(0, bool)

    def _geometry(self, T_W_C: NDArray[np.float64]) -> tuple[_BoardView, NDArray[np.float32], float]:
        key = np.asarray(T_W_C, dtype=np.float64).tobytes()
        if self._view is None or self._view[0] != key:
            view = _BoardView(self.base, invert(T_W_C) @ self.T_W_Bd, self.texture, self.px_per_mm)
            P_P = transform_points(invert(self.T_C_P), view.P_C)
            uv = project_points(self.proj, P_P, self.base.projector_distortion).astype(np.float32)
            uv[~view.hit | ~np.isfinite(uv[..., 0])] = -1e6
            depth = float(np.median(P_P[view.hit][:, 2])) if view.hit.any() else self.proj.focus_distance_mm
            # the board plane is infinite in _BoardView; the board itself ends at the texture's edges
            T_Bd_C = invert(invert(T_W_C) @ self.T_W_Bd)
            P = transform_points(T_Bd_C, view.P_C)
            h, w = self.texture.shape
            on = view.hit & (P[..., 0] >= 0) & (P[..., 1] >= 0)
            on &= (P[..., 0] <= w / self.px_per_mm) & (P[..., 1] <= h / self.px_per_mm)
            self._on_board = on
            self._view = (key, view, uv, float(blur_sigma_px(self.proj, np.array([depth]))[0]))
        return self._view[1], self._view[2], self._view[3]

    def signal_e(
        self, T_W_C: NDArray[np.float64], pattern: NDArray[np.uint8], exposure_ms: float
    ) -> NDArray[np.float32]:
        """Noise-free electrons per pixel (H, W) of the board lit by projector image ``pattern`` (its response
        curve and defocus) and of the scene around it; the simulated camera sums these over its exposure."""
        view, uv, p_sigma = self._geometry(T_W_C)
        lit = _projected(self.proj, np.asarray(pattern), uv, p_sigma)
        rate = view.albedo * (self.sim.ambient_e_per_ms + view.proj_rate * lit)
        signal = (rate * np.float32(exposure_ms)).astype(np.float32)
        sigma = float(blur_sigma_px(self.cam, np.array([view.depth]))[0])
        if sigma > 0.3:
            signal = cv2.GaussianBlur(signal, (0, 0), sigma)
        # around the board the camera sees the rest of the scene (the table)
        behind = self.base.signal_e(T_W_C, pattern, exposure_ms)
        return np.where(self._on_board, signal, behind).astype(np.float32)

    def sensor_dn(
        self,
        signal_e: NDArray[np.float32],
        gain_db: float,
        rng: np.random.Generator | None,
        bit_depth: int | None = None,
    ) -> NDArray[np.integer]:
        """Electrons to digital numbers with the base renderer's noise model."""
        return self.base.sensor_dn(signal_e, gain_db, rng, bit_depth)

    def render(
        self,
        T_W_C: NDArray[np.float64],
        pattern: NDArray[np.uint8],
        exposure_ms: float,
        gain_db: float,
        rng: np.random.Generator | None,
        bit_depth: int | None = None,
    ) -> NDArray[np.integer]:
        """One camera image of the board lit by projector image ``pattern``."""
        return self.sensor_dn(self.signal_e(T_W_C, pattern, exposure_ms), gain_db, rng, bit_depth)

    def render_stack(
        self,
        T_W_C: NDArray[np.float64],
        patterns: Sequence[NDArray[np.uint8]],
        exposure_ms: float,
        gain_db: float,
        rng: np.random.Generator | None,
        bit_depth: int | None = None,
    ) -> NDArray[np.integer]:
        return np.stack([self.render(T_W_C, p, exposure_ms, gain_db, rng, bit_depth) for p in patterns])
