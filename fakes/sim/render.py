"""Render what the simulated camera sees of a projector pattern on the scene, and expose the ground truth.

Per camera pose, one ray cast gives a :class:`ViewGeometry` (hit points, projector coordinates, shadow test,
shading factors, blur weights); it is cached, so N patterns at one pose cost one ray cast. Per pattern:

    rate_e_per_ms = ambient_e_per_ms * albedo
                  + irradiance_e_per_ms * p_lin(u_p, v_p) * (s_p/r)^2 * (albedo*cos_i + specular*cos_a^n)
    signal_e = exposure_ms * rate_e_per_ms      (then camera defocus, shot + read noise, gain, DN, clip)

with p_lin = black + (1 - black) * (pattern / 255)^gamma sampled bilinearly at the projector coordinate of the
hit point (after projector defocus blur), cos_i the incidence cosine, r the distance to the projector centre,
s_p the projector focus distance, cos_a the Phong cosine between the mirror direction of the light and the
direction to the camera. Derivation and parameters: docs/simulator.md.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from cell.config import SensorConfig, SimConfig
from cell.geometry import invert, transform_points, transform_vectors
from fakes.sim.optics import blur_sigma_px, pixel_rays, project_points, projector_lut
from fakes.sim.scene import Scene
from fakes.sim.world import value_noise

# Blur levels (px) of the layered defocus model: each pixel blends the two levels around its own sigma.
BLUR_LEVELS = (0.0, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0)
SHADOW_OFFSET_MM = 0.01  # shadow rays start this far off the surface so they do not hit their own triangle
CACHE_BYTES = 400_000_000  # poses' geometry kept at most (the newest always): 1024x768 ~50 MB, 5 MP ~0.3 GB
RAYS_PER_CHUNK = 500_000  # pixel rays a pose's geometry is computed for at a time (memory: ~0.2 GB)
_OUTSIDE = -1.0e6  # remap coordinate of pixels that see no projector light (falls in the zero border)


@dataclass(frozen=True)
class GroundTruth:
    """Per-pixel truth of one camera pose. Points in mm; NaN where the pixel ray hits nothing."""

    points_W: NDArray[np.float64]  # (H, W, 3)
    points_C: NDArray[np.float64]  # (H, W, 3)
    normals_W: NDArray[np.float64]  # (H, W, 3) unit geometric normal facing the camera
    hit: NDArray[np.bool_]  # the ray hit the table or the part
    part: NDArray[np.bool_]  # the ray hit the part
    lit: NDArray[np.bool_]  # hit, inside the projector frustum, facing it and not shadowed
    projector_uv: NDArray[np.float64]  # (H, W, 2) projector pixel coordinate; NaN outside the frustum


@dataclass(frozen=True)
class BlurLayers:
    """Layered blur: per used level sigma (px), a per-pixel weight map (None when it is 1 everywhere)."""

    sigmas: tuple[float, ...]
    weights: tuple[NDArray[np.float32] | None, ...]


@dataclass(frozen=True)
class ViewGeometry:
    """Everything about one camera pose that does not depend on the pattern shown."""

    T_W_C: NDArray[np.float64]
    distance: NDArray[np.float64]  # (H, W) along the unit pixel ray, inf on a miss
    triangle: NDArray[np.int32]  # (H, W) scene triangle, -1 on a miss
    hit: NDArray[np.bool_]
    part: NDArray[np.bool_]
    lit: NDArray[np.bool_]
    in_frustum: NDArray[np.bool_]
    map_x: NDArray[np.float32]  # projector column of each camera pixel (far outside where not lit)
    map_y: NDArray[np.float32]
    ambient_e_per_ms: NDArray[np.float32]  # ambient rate of each pixel
    projector_e_per_ms: NDArray[np.float32]  # rate per unit of linear pattern value
    projector_blur: BlurLayers
    camera_blur: BlurLayers


def blur_layers(sigma: NDArray[np.float32]) -> BlurLayers:
    """Split a per-pixel sigma map (px) into the two bracketing :data:`BLUR_LEVELS` with linear weights."""
    levels = np.asarray(BLUR_LEVELS, dtype=np.float32)
    s = np.clip(sigma, 0.0, levels[-1])
    k = np.clip(np.searchsorted(levels, s, side="right") - 1, 0, len(levels) - 2)
    frac = (s - levels[k]) / (levels[k + 1] - levels[k])
    sigmas, weights = [], []
    used = np.flatnonzero(np.bincount(k.ravel(), minlength=len(levels)))
    for j in np.union1d(used, used + 1):
        w = np.where(k == j, 1.0 - frac, 0.0) + np.where(k == j - 1, frac, 0.0)
        if not np.any(w):
            continue
        sigmas.append(float(levels[j]))
        weights.append(None if np.all(w == 1.0) else w.astype(np.float32))
    return BlurLayers(tuple(sigmas), tuple(weights))


def _apply_layers(
    image: NDArray[np.float32],
    layers: BlurLayers,
    sample: Callable[[NDArray[np.float32]], NDArray[np.float32]] | None = None,
) -> NDArray[np.float32]:
    """Sum over levels of weight * sample(blur(image, sigma)); ``sample`` maps a blurred image to the output
    grid (identity by default)."""
    out: NDArray[np.float32] | None = None
    for sigma, w in zip(layers.sigmas, layers.weights, strict=True):
        src = (
            image
            if sigma == 0
            else np.asarray(
                cv2.GaussianBlur(image, (0, 0), sigma, borderType=cv2.BORDER_REPLICATE), np.float32
            )
        )
        img = sample(src) if sample is not None else src
        if w is not None:
            img = img * w
        out = img if out is None else np.asarray(cv2.add(out, img), np.float32)
    assert out is not None  # every blur has at least one level
    return out


def standard_normal_image(shape: tuple[int, ...], rng: np.random.Generator) -> NDArray[np.float32]:
    """Standard normal float32 noise, reproducible from ``rng``. OpenCV's randn is ~6x faster than numpy's
    generator here (noise was the largest cost per frame); its thread-local RNG is re-seeded from ``rng`` on
    every call, so the images depend only on the caller's seed."""
    cv2.setRNGSeed(int(rng.integers(0, 2**31 - 1)))
    out = np.empty(shape, dtype=np.float32)
    cv2.randn(out, 0.0, 1.0)  # type: ignore[call-overload]  # OpenCV's stubs lack its scalar mean and stddev
    return out


def _nbytes(view: ViewGeometry) -> int:
    """The bytes a cached pose's geometry holds (its images and blur weight maps)."""
    arrays = [v for v in vars(view).values() if isinstance(v, np.ndarray)]
    blurs = [w for b in (view.projector_blur, view.camera_blur) for w in b.weights if w is not None]
    return sum(a.nbytes for a in arrays + blurs)


class SceneRenderer:
    """Renders camera images of the scene lit by the projector's pattern, for any camera pose T_W_C."""

    def __init__(
        self,
        sensor: SensorConfig,
        sim: SimConfig,
        scene: Scene,
        cache_size: int = 3,
        projector_distortion: NDArray[np.float64] | None = None,
        microstructure_seed: int | None = None,
    ):
        """``sensor`` is the geometry rendered with (the world's true sensor in a simulated cell);
        ``projector_distortion`` (OpenCV order) the projector's lens, a pinhole when None;
        ``microstructure_seed`` turns on the materials' surface roughness and albedo texture."""
        self.sensor = sensor
        self.projector_distortion = projector_distortion
        self.microstructure_seed = microstructure_seed
        self.sim = sim
        self.scene = scene
        self.cam = sensor.camera
        self.proj = sensor.projector
        self.T_C_P = sensor.projector.T_C_P.matrix()
        p = self.proj
        self._lut = projector_lut(p)
        self._cache: OrderedDict[bytes, ViewGeometry] = OrderedDict()
        self._cache_size = cache_size

    # ------------------------------------------------------------------------------------------ geometry
    def view(self, T_W_C: NDArray[np.float64]) -> ViewGeometry:
        """The pattern-independent geometry of pose T_W_C (cached, least recently used dropped beyond
        ``cache_size`` poses or :data:`CACHE_BYTES`)."""
        T_W_C = np.asarray(T_W_C, dtype=np.float64)
        key = T_W_C.tobytes()
        if key in self._cache:
            self._cache.move_to_end(key)
            return self._cache[key]
        # Room first, for a pose as large as the largest cached one: the old poses are dropped before the new
        # one is computed, not after (a 5 MP camera held two poses' geometry at once: images, blur maps).
        new = max(map(_nbytes, self._cache.values()), default=0)
        while self._cache and (
            len(self._cache) >= self._cache_size
            or sum(map(_nbytes, self._cache.values())) + new > CACHE_BYTES
        ):
            self._cache.popitem(last=False)
        view = self._compute_view(T_W_C)
        self._cache[key] = view
        return view

    def forget_poses(self) -> None:
        """Drop the cached poses' geometry (a 5 MP pose's ~0.3 GB): the next :meth:`view` computes its pose
        anew, the same."""
        self._cache.clear()

    def _compute_view(self, T_W_C: NDArray[np.float64]) -> ViewGeometry:
        """The pose's geometry, its rays taken :data:`RAYS_PER_CHUNK` at a time (every per-ray step is the
        ray's own; a 5 MP camera's whole-image float64 temporaries held 2 GB at once)."""
        cam = self.cam
        H, W = cam.height_px, cam.width_px
        rays_C = pixel_rays(cam).reshape(-1, 3)
        n_rays = H * W
        out: dict[str, NDArray[Any]] = {
            "distance": np.empty(n_rays, np.float64),
            "triangle": np.empty(n_rays, np.int32),
            "hit": np.empty(n_rays, bool),
            "part": np.empty(n_rays, bool),
            "lit": np.zeros(n_rays, bool),
            "in_frustum": np.zeros(n_rays, bool),
            "map_x": np.full(n_rays, _OUTSIDE, np.float32),
            "map_y": np.full(n_rays, _OUTSIDE, np.float32),
            "ambient": np.zeros(n_rays, np.float32),
            "projector": np.zeros(n_rays, np.float32),
            "proj_sigma": np.zeros(n_rays, np.float32),
            "cam_sigma": np.zeros(n_rays, np.float32),
        }
        for start in range(0, n_rays, RAYS_PER_CHUNK):
            self._view_rays(T_W_C, rays_C, start, min(start + RAYS_PER_CHUNK, n_rays), out)

        def image(name: str) -> NDArray:
            return out[name].reshape(H, W)

        return ViewGeometry(
            T_W_C=T_W_C.copy(),
            distance=image("distance"),
            triangle=image("triangle"),
            hit=image("hit"),
            part=image("part"),
            lit=image("lit"),
            in_frustum=image("in_frustum"),
            map_x=image("map_x"),
            map_y=image("map_y"),
            ambient_e_per_ms=image("ambient"),
            projector_e_per_ms=image("projector"),
            projector_blur=blur_layers(image("proj_sigma")),
            camera_blur=blur_layers(image("cam_sigma")),
        )

    def _view_rays(
        self,
        T_W_C: NDArray[np.float64],
        rays_C: NDArray[np.float64],
        start: int,
        end: int,
        out: dict[str, NDArray],
    ) -> None:
        """Cast, shade and shadow the pixel rays ``start:end`` of pose T_W_C into the flat images ``out``."""
        cam, proj, scene = self.cam, self.proj, self.scene
        dirs_W = transform_vectors(T_W_C, rays_C[start:end])
        eye_W = T_W_C[:3, 3]
        hits = scene.cast(eye_W[None, :], dirs_W)
        hit = hits.hit
        idx = np.flatnonzero(hit)
        t = hits.triangle[idx]
        n = hits.normal[idx]
        distance = hits.distance.copy()
        alb, spec, shin = scene.albedo[t], scene.specular[t], scene.shininess[t]
        if self.microstructure_seed is not None:
            distance[idx], alb = self._microstructure(eye_W, dirs_W[idx], n, t, distance[idx], alb)
        P_W = eye_W + dirs_W[idx] * distance[idx, None]

        T_W_P = T_W_C @ self.T_C_P
        P_P = transform_points(invert(T_W_P), P_W)
        uv = project_points(proj, P_P, self.projector_distortion)
        in_frustum = (
            (P_P[:, 2] > 0)
            & np.all(uv > -0.5, axis=1)
            & (uv[:, 0] < proj.width_px - 0.5)
            & (uv[:, 1] < proj.height_px - 0.5)
        )
        to_proj = T_W_P[:3, 3] - P_W
        r = np.linalg.norm(to_proj, axis=1)
        l_dir = to_proj / r[:, None]
        cos_i = np.einsum("ij,ij->i", n, l_dir)
        cand = np.flatnonzero(in_frustum & (cos_i > 0))
        shadow = scene.occluded(
            P_W[cand] + SHADOW_OFFSET_MM * n[cand], l_dir[cand], r[cand] - SHADOW_OFFSET_MM
        )
        lit_sub = np.zeros(len(idx), dtype=bool)
        lit_sub[cand[~shadow]] = True

        # Phong: mirror direction of the light about the normal, against the direction back to the camera
        mirror = 2 * cos_i[:, None] * n - l_dir
        cos_a = np.clip(-np.einsum("ij,ij->i", mirror, dirs_W[idx]), 0.0, 1.0)
        falloff = (proj.focus_distance_mm / r) ** 2
        gain = proj.irradiance_e_per_ms * falloff * (alb * np.maximum(cos_i, 0) + spec * cos_a**shin)

        at = start + idx  # the hit pixels in the flat images
        out["distance"][start:end] = distance
        out["triangle"][start:end] = hits.triangle
        out["hit"][start:end] = hit
        out["part"][start:end] = hits.is_part
        out["lit"][at] = lit_sub
        out["in_frustum"][at] = in_frustum
        out["map_x"][at] = np.where(lit_sub, uv[:, 0], _OUTSIDE)
        out["map_y"][at] = np.where(lit_sub, uv[:, 1], _OUTSIDE)
        out["ambient"][at] = self.sim.ambient_e_per_ms * alb
        out["projector"][at] = np.where(lit_sub, gain, 0.0)
        out["proj_sigma"][at] = np.where(lit_sub, blur_sigma_px(proj, P_P[:, 2]), 0.0)
        out["cam_sigma"][at] = blur_sigma_px(cam, distance[idx] * rays_C[start:end][idx, 2])

    def _microstructure(
        self,
        eye_W: NDArray[np.float64],
        dirs_W: NDArray[np.float64],
        normals_W: NDArray[np.float64],
        triangle: NDArray[np.int64],
        distance: NDArray[np.float64],
        albedo: NDArray[np.float32],
    ) -> tuple[NDArray[np.float64], NDArray[np.float32]]:
        """Hit distances and albedos of a rough, textured surface: the surface is raised by a smooth random
        height field (std ``roughness_um``, lateral scale ``grain_mm`` of the triangle's material) along its
        normal, so the ray meets it earlier by h / cos(incidence); the albedo varies by ``albedo_texture``.
        Both fields are functions of the world position: every view sees the same surface."""
        scene, seed = self.scene, int(self.microstructure_seed or 0)
        points = eye_W + dirs_W * distance[:, None]
        height = np.zeros(len(points))
        texture = np.zeros(len(points))
        for grain in np.unique(scene.grain_mm[triangle]):
            sel = scene.grain_mm[triangle] == grain
            height[sel] = value_noise(points[sel], float(grain), seed)
            texture[sel] = value_noise(points[sel], float(grain), seed + 1)
        height *= scene.roughness_um[triangle] * 1e-3
        cos = np.maximum(-np.einsum("ij,ij->i", normals_W, dirs_W), 0.1)  # normals face the camera
        albedo = np.clip(albedo * (1.0 + scene.albedo_texture[triangle] * texture), 0.0, 1.0)
        return distance - height / cos, albedo.astype(np.float32)

    def ground_truth(self, T_W_C: NDArray[np.float64]) -> GroundTruth:
        """Per-pixel hit points, normals, masks and projector coordinates of pose T_W_C (float64)."""
        v = self.view(T_W_C)
        rays_C = pixel_rays(self.cam)
        points_C = np.where(v.hit[..., None], rays_C * v.distance[..., None], np.nan)
        points_W = transform_points(v.T_W_C, points_C)
        n = self.scene.face_normals[np.maximum(v.triangle, 0)]
        dirs_W = transform_vectors(v.T_W_C, rays_C)
        flip = np.einsum("ijk,ijk->ij", n, dirs_W) > 0
        normals_W = np.where(v.hit[..., None], np.where(flip[..., None], -n, n), np.nan)
        P_P = transform_points(invert(v.T_W_C @ self.T_C_P), points_W)
        uv = project_points(self.proj, P_P, self.projector_distortion)
        uv[~v.in_frustum] = np.nan
        return GroundTruth(points_W, points_C, normals_W, v.hit, v.part, v.lit, uv)

    # ------------------------------------------------------------------------------------------ images
    def signal_e(
        self, T_W_C: NDArray[np.float64], pattern: NDArray[np.uint8], exposure_ms: float
    ) -> NDArray[np.float32]:
        """Noise-free collected electrons per pixel (H, W) float32, after both defocus blurs."""
        proj = self.proj
        pattern = np.asarray(pattern)
        if pattern.dtype != np.uint8 or pattern.shape != (proj.height_px, proj.width_px):
            raise ValueError(
                f"pattern must be uint8 of shape {(proj.height_px, proj.width_px)} (projector "
                f"'{proj.name}'), got {pattern.dtype} {pattern.shape}"
            )
        v = self.view(T_W_C)
        lin = self._lut[pattern]

        def sample(src: NDArray[np.float32]) -> NDArray[np.float32]:
            return np.asarray(
                cv2.remap(
                    src, v.map_x, v.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0
                ),
                np.float32,
            )

        p = _apply_layers(lin, v.projector_blur, sample)
        rate = cv2.add(v.ambient_e_per_ms, cv2.multiply(v.projector_e_per_ms, p))
        signal = rate * np.float32(exposure_ms)
        return _apply_layers(signal, v.camera_blur)

    def sensor_dn(
        self,
        signal_e: NDArray[np.float32],
        gain_db: float,
        rng: np.random.Generator | None,
        bit_depth: int | None = None,
    ) -> NDArray[np.integer]:
        """Electrons to digital numbers: shot + read noise (one Gaussian of variance signal + read^2, the
        Gaussian limit of Poisson shot noise plus Gaussian read noise), full-well clip, gain, dark offset,
        rounding and clip to the bit depth. ``rng=None`` or ``sim.noise=False`` gives the noise-free image."""
        cam = self.cam
        bits = bit_depth or cam.bit_depth
        top = float(2**bits - 1)
        e = signal_e
        if rng is not None and self.sim.noise:
            noise = standard_normal_image(e.shape, rng)
            # OpenCV's stubs lack its array-and-scalar overload of add
            std = cv2.sqrt(cv2.add(e, float(cam.read_noise_e) ** 2))  # type: ignore[call-overload]
            e = np.asarray(cv2.add(e, cv2.multiply(noise, std)), np.float32)
        dn_per_e = 10 ** (gain_db / 20) * top / cam.full_well_e
        dn = np.clip(e, 0.0, cam.full_well_e) * np.float32(dn_per_e) + np.float32(cam.dark_offset_dn)
        np.clip(dn, 0.0, top, out=dn)
        np.rint(dn, out=dn)
        return dn.astype(np.uint8 if bits == 8 else np.uint16)

    def render(
        self,
        T_W_C: NDArray[np.float64],
        pattern: NDArray[np.uint8],
        exposure_ms: float,
        gain_db: float,
        rng: np.random.Generator | None,
        bit_depth: int | None = None,
    ) -> NDArray[np.integer]:
        """One camera image (H, W), uint8 for 8-bit, uint16 for 10/12-bit, of ``pattern`` from pose T_W_C."""
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
        """(N, H, W) images of every pattern from one pose: one ray cast, N shadings."""
        return np.stack([self.render(T_W_C, p, exposure_ms, gain_db, rng, bit_depth) for p in patterns])
