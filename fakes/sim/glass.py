"""Back-imaging simulator: cameras see a dot screen reflected in both skins of a glass pane (world {W}, mm).

Per pixel (pinhole + Brown distortion rays from :mod:`fakes.sim.optics`):
- top path: the ray hits the top skin, reflects with the unpolarised Fresnel reflectance R(theta_i) and reads
  the screen radiance where the reflected ray meets the screen;
- bottom path (Fig 2.18): it refracts into the glass (Snell, index n), reflects at the bottom skin with the
  internal Fresnel reflectance, refracts out through the top skin, and is weighted by (1-R_in) R_bottom
  (1-R_out) and the tint's absorption exp(-alpha * path in glass). It leaves parallel to the top reflection,
  offset by the thickness, so each dot shows a second, weaker copy beside it (Figs 2.19-2.22);
- the screen is white with black dots; each dot's edge is anti-aliased analytically with the pixel's footprint
  on the screen, measured from the screen coordinates of the neighbouring pixels (so a curved mirror's
  magnification is honoured);
- sensor: shot noise, read noise, dark offset, gain, quantisation and saturation of the camera config.
Nothing lies below the pane (a black fixture), so light transmitted through the glass adds nothing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from numpy.typing import NDArray
from scipy.special import erfc

from cell.glass.config import BoardConfig, DotGridConfig, GlassCameraConfig, GlassRigConfig
from cell.glass.surface import SmoothSurface, plane_hits, reflect, rotate, unit
from fakes.sim.glass_pane import bottom_skin
from fakes.sim.optics import pixel_rays

_EPS_MM = 1e-4  # start offset of secondary rays so that they do not hit the surface they leave
_FOOTPRINT_TO_SIGMA = 0.45  # box pixel (0.29 px) combined with a small lens blur, in pixels of footprint


def fresnel_unpolarised(cos_i: NDArray[np.float64], n1: float, n2: float) -> NDArray[np.float64]:
    """Reflectance of unpolarised light going from index n1 into n2 at incidence cos_i; 1 beyond TIR."""
    cos_i = np.clip(cos_i, 0.0, 1.0)
    sin_t2 = (n1 / n2) ** 2 * (1 - cos_i**2)
    tir = sin_t2 >= 1
    cos_t = np.sqrt(np.clip(1 - sin_t2, 0, 1))
    rs = ((n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t)) ** 2
    rp = ((n1 * cos_t - n2 * cos_i) / (n1 * cos_t + n2 * cos_i)) ** 2
    return np.where(tir, 1.0, 0.5 * (rs + rp))


def refract(d: NDArray[np.float64], n: NDArray[np.float64], eta: float) -> NDArray[np.float64]:
    """Snell refraction of unit ``d`` through a surface with unit normal ``n`` facing against ``d``
    (d.n < 0), eta = n_from / n_to. NaN where the light is totally reflected."""
    cos_i = -np.einsum("ij,ij->i", d, n)
    k = 1 - eta**2 * (1 - cos_i**2)
    with np.errstate(invalid="ignore"):
        return eta * d + (eta * cos_i - np.sqrt(np.where(k >= 0, k, np.nan)))[:, None] * n


def dot_grid_value(xy: NDArray[np.float64], grid: DotGridConfig, sigma_mm: NDArray[np.float64]) -> NDArray:
    """Relative radiance (0..1) of a dot grid at plane points ``xy`` (N, 2, mm): 1 on white, black_level in a
    dot, analytic Gaussian-blurred edge of width ``sigma_mm``; 0 off the grid's sheet (half a pitch
    margin)."""
    p = grid.pitch_mm
    half = np.array([(grid.cols - 1) / 2, (grid.rows - 1) / 2])
    ij = np.clip(np.round(xy / p + half), 0, [grid.cols - 1, grid.rows - 1])
    d = np.linalg.norm(xy - (ij - half) * p, axis=1)
    coverage = 0.5 * erfc((d - grid.dot_diameter_mm / 2) / (np.sqrt(2) * sigma_mm))
    value = 1 - (1 - grid.black_level) * coverage
    on_sheet = np.all(np.abs(xy / p) <= half + 0.5, axis=1)
    return np.where(on_sheet & np.isfinite(d), value, 0.0)


def _footprint_sigma(xy: NDArray[np.float64]) -> NDArray[np.float64]:
    """Per-pixel blur (mm on the viewed plane) from the spacing of neighbouring pixels' plane points."""
    gy = np.gradient(xy, axis=0)
    gx = np.gradient(xy, axis=1)
    area = np.abs(gx[..., 0] * gy[..., 1] - gx[..., 1] * gy[..., 0])
    s = np.sqrt(area)
    fallback = np.nanmedian(s) if np.any(np.isfinite(s)) else 1.0
    return _FOOTPRINT_TO_SIGMA * np.where(np.isfinite(s), s, fallback)


@dataclass(frozen=True)
class GlassTruth:
    """Ground truth of one rendered camera: per pixel (H, W) the screen point (mm, {S}) of the top and of
    the bottom reflection and their weights (fraction of the screen radiance reaching the pixel)."""

    screen_top: NDArray[np.float64]
    screen_bottom: NDArray[np.float64]
    weight_top: NDArray[np.float64]
    weight_bottom: NDArray[np.float64]


class GlassScene:
    """A pane (top skin, bottom skin derived from the thickness) in front of the rig's marker screen."""

    def __init__(self, rig: GlassRigConfig, top_W: trimesh.Trimesh) -> None:
        self.rig = rig
        self.top = SmoothSurface(top_W)
        self.bottom = SmoothSurface(
            bottom_skin(top_W, rig.glass.thickness_mm), vertex_normals=np.asarray(top_W.vertex_normals)
        )
        self.T_W_S = rig.screen.T_W_S.matrix()

    def trace(self, cam: GlassCameraConfig) -> GlassTruth:
        """Trace every pixel of ``cam`` through both reflection paths (no radiance, no noise)."""
        T_W_C = cam.T_W_C.matrix()
        d = rotate(T_W_C[:3, :3], pixel_rays(cam).reshape(-1, 3))
        o = np.broadcast_to(T_W_C[:3, 3], d.shape)
        n_px = len(d)
        g = self.rig.glass
        top = self.top.cast(o, d)
        hit = top.hit & (np.einsum("ij,ij->i", d, np.nan_to_num(top.normal)) < 0)
        screen_top = np.full((n_px, 2), np.nan)
        screen_bot = np.full((n_px, 2), np.nan)
        w_top = np.zeros(n_px)
        w_bot = np.zeros(n_px)
        dh, nh, ph = d[hit], top.normal[hit], top.point[hit]
        cos_i = -np.einsum("ij,ij->i", dh, nh)
        r_in = fresnel_unpolarised(cos_i, 1.0, g.refractive_index)
        w_top[hit] = r_in
        screen_top[hit] = plane_hits(ph, reflect(dh, nh), self.T_W_S)
        # bottom path: in through the top, mirror at the bottom, out through the top
        d_in = refract(dh, nh, 1.0 / g.refractive_index)
        bot = self.bottom.cast(ph + _EPS_MM * d_in, d_in)
        ok = bot.hit.copy()
        nb = np.where(
            (np.einsum("ij,ij->i", d_in, np.nan_to_num(bot.normal)) > 0)[:, None], -bot.normal, bot.normal
        )
        r_bot = fresnel_unpolarised(-np.einsum("ij,ij->i", d_in, nb), g.refractive_index, 1.0)
        d_up = reflect(d_in, nb)
        out = self.top.cast(bot.point + _EPS_MM * d_up, d_up)
        ok &= out.hit
        n_out = -out.normal  # faces against the upgoing ray inside the glass
        cos_out = -np.einsum("ij,ij->i", d_up, n_out)
        r_out = fresnel_unpolarised(cos_out, g.refractive_index, 1.0)
        d_out = refract(d_up, n_out, g.refractive_index)
        ok &= np.all(np.isfinite(d_out), axis=1)
        path = bot.distance + out.distance
        w = (1 - r_in) * r_bot * (1 - r_out) * np.exp(-g.absorption_per_mm * path)
        idx = np.flatnonzero(hit)[ok]
        w_bot[idx] = w[ok]
        screen_bot[idx] = plane_hits(out.point[ok], unit(d_out[ok]), self.T_W_S)
        shape = (cam.height_px, cam.width_px)
        return GlassTruth(
            screen_top.reshape(*shape, 2),
            screen_bot.reshape(*shape, 2),
            w_top.reshape(shape),
            w_bot.reshape(shape),
        )

    def radiance(self, truth: GlassTruth) -> NDArray[np.float64]:
        """Camera signal rate (e/ms) per pixel from the traced paths and the screen's dots."""
        scr = self.rig.screen
        total = np.full(truth.weight_top.shape, self.rig.ambient_e_per_ms)
        for xy, w in ((truth.screen_top, truth.weight_top), (truth.screen_bottom, truth.weight_bottom)):
            sigma = _footprint_sigma(xy)
            v = dot_grid_value(xy.reshape(-1, 2), scr, sigma.ravel()).reshape(w.shape)
            total += scr.radiance_e_per_ms * w * np.nan_to_num(v)
        return total


def board_radiance(
    cam: GlassCameraConfig, board: BoardConfig, height_mm: float, ambient_e_per_ms: float = 0.0
) -> NDArray[np.float64]:
    """Signal rate (e/ms) of ``cam`` seeing the level calibration board at ``height_mm`` directly."""
    T_W_C = cam.T_W_C.matrix()
    d = rotate(T_W_C[:3, :3], pixel_rays(cam).reshape(-1, 3))
    o = np.broadcast_to(T_W_C[:3, 3], d.shape)
    T_W_B = np.eye(4)
    T_W_B[:3, 3] = (*board.centre_xy_mm, height_mm)
    xy = plane_hits(o, d, T_W_B).reshape(cam.height_px, cam.width_px, 2)
    v = dot_grid_value(xy.reshape(-1, 2), board, _footprint_sigma(xy).ravel())
    return ambient_e_per_ms + board.radiance_e_per_ms * v.reshape(cam.height_px, cam.width_px)


def expose(
    cam: GlassCameraConfig,
    rate_e_per_ms: NDArray[np.float64],
    rng: np.random.Generator | None,
    exposure_ms: float | None = None,
    gain_db: float | None = None,
) -> NDArray:
    """Sensor model: electrons -> shot + read noise -> DN with gain, dark offset, quantisation, saturation.

    ``rng=None`` renders without noise. uint8 for 8-bit cameras, uint16 otherwise.
    """
    exposure = cam.exposure_ms if exposure_ms is None else exposure_ms
    gain = cam.gain_db if gain_db is None else gain_db
    e = np.minimum(rate_e_per_ms * exposure, cam.full_well_e)
    if rng is not None:
        e = e + rng.standard_normal(e.shape) * np.sqrt(e + cam.read_noise_e**2)
    full = 2**cam.bit_depth - 1
    dn = e * full / cam.full_well_e * 10 ** (gain / 20) + cam.dark_offset_dn
    return np.clip(np.round(dn), 0, full).astype(np.uint8 if cam.bit_depth == 8 else np.uint16)
