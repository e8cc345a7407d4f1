"""Vector-based camera calibration (dissertation 2.6, Figs 2.23-2.25): a view ray for every pixel.

A level dot board is imaged at two known heights z1 < z2. At each height the identified dot centroids give
pixel -> board (X, Y) correspondences; a local quadratic least-squares fit over the ``k`` nearest dots
carries them to any pixel. Like the perspective model of Fig 2.25 (and unlike the bilinear ratios of Fig
2.24) it follows perspective and lens distortion without a lens model, and being a least-squares fit it
averages the centroid noise: an exact interpolation would pass each dot's ~5 um noise straight into the ray
direction (~80 urad over an 80 mm height step, i.e. ~80 um of depth in the reflection search). The view ray
of a pixel runs from P2 = (X2, Y2, z2) down through P1 = (X1, Y1, z1).

The other cameras of the feedback (3.4) must also *project* a surface point into their image; for that an
OpenCV camera model (pinhole + Brown) is fitted to the same non-coplanar correspondences.

Saved and versioned: ``<dir>/<camera>.v<k>.npz`` holds the correspondences and the fitted model, which
define the view ray of every (sub-)pixel through :meth:`ViewVectorCalibration.rays_at` (a dense per-pixel
table would cost 16 s to fill per 1024x768 camera and is never read: markers sit at sub-pixel positions);
``<dir>/<camera>.v<k>.yaml`` the metadata (camera, serial, board, residuals, time). Loading
takes the highest version; saving never overwrites.
"""

from __future__ import annotations

import datetime as dt
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from cell.errors import CalibrationError
from cell.glass.config import BoardConfig, GlassCameraConfig
from cell.glass.markers import detect_dots
from cell.glass.surface import unit

_VERSION_RE = re.compile(r"^(?P<cam>.+)\.v(?P<v>\d+)\.npz$")


@dataclass
class ViewVectorCalibration:
    """Per-pixel view rays of one camera in {W} (mm) and a fitted projection model.

    ``pixels[i]`` (N_i, 2) and ``board_xy[i]`` (N_i, 2) are the dot correspondences at ``heights_mm[i]``.
    """

    camera: str
    serial: str
    resolution: tuple[int, int]
    heights_mm: tuple[float, float]
    pixels: list[NDArray[np.float64]]
    board_xy: list[NDArray[np.float64]]
    K: NDArray[np.float64]
    dist: NDArray[np.float64]
    T_W_C: NDArray[np.float64]
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self._interp = [LocalQuadratic(p, xy) for p, xy in zip(self.pixels, self.board_xy)]

    def rays_at(self, pixels: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Origins (on the high board plane) and unit directions (N, 3), pointing away from the camera, of
        the view rays at sub-pixel positions (N, 2) = (u, v); NaN outside the area both boards covered."""
        uv = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        p = [np.column_stack([f(uv), np.full(len(uv), z)]) for f, z in zip(self._interp, self.heights_mm)]
        return p[1], unit(p[0] - p[1])

    @property
    def centre_mm(self) -> NDArray[np.float64]:
        """Projection centre of the fitted model in {W}."""
        return self.T_W_C[:3, 3].copy()

    def project(self, points_W: NDArray[np.float64]) -> NDArray[np.float64]:
        """Pixels (N, 2) of world points (N, 3) through the fitted OpenCV model."""
        if len(points_W) == 0:  # cv2.projectPoints returns None for no points
            return np.zeros((0, 2))
        T_C_W = np.linalg.inv(self.T_W_C)
        rvec, _ = cv2.Rodrigues(T_C_W[:3, :3])
        uv, _ = cv2.projectPoints(
            np.asarray(points_W, np.float64).reshape(-1, 1, 3), rvec, T_C_W[:3, 3], self.K, self.dist
        )
        return np.asarray(uv, np.float64).reshape(-1, 2)

    # ------------------------------------------------------------------------------------------- storage
    def save(self, directory: str | Path) -> Path:
        """Write the next version ``<camera>.v<k>.npz/.yaml`` into ``directory``; returns the npz path."""
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        version = max(_versions(d, self.camera), default=0) + 1
        path = d / f"{self.camera}.v{version}.npz"
        np.savez_compressed(
            path,
            pixels0=self.pixels[0],
            board0=self.board_xy[0],
            pixels1=self.pixels[1],
            board1=self.board_xy[1],
            K=self.K,
            dist=self.dist,
            T_W_C=self.T_W_C,
        )
        meta = {
            "camera": self.camera,
            "serial": self.serial,
            "version": version,
            "resolution": list(self.resolution),
            "heights_mm": list(self.heights_mm),
            "created": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
            **self.meta,
        }
        path.with_suffix(".yaml").write_text(yaml.safe_dump(meta, sort_keys=False), encoding="utf-8")
        return path

    @classmethod
    def load(cls, directory: str | Path, camera: str) -> ViewVectorCalibration:
        """Load the highest version for ``camera`` from ``directory``."""
        d = Path(directory)
        versions = _versions(d, camera)
        if not versions:
            raise CalibrationError(
                f"{d}: no view-vector calibration for camera '{camera}'; run the "
                "calibration (cell glass calibrate) first"
            )
        path = d / f"{camera}.v{max(versions)}.npz"
        meta = yaml.safe_load(path.with_suffix(".yaml").read_text(encoding="utf-8"))
        z = np.load(path)
        extra = {k: v for k, v in meta.items() if k not in ("camera", "serial", "resolution", "heights_mm")}
        return cls(
            camera,
            meta["serial"],
            tuple(meta["resolution"]),
            tuple(meta["heights_mm"]),
            [z["pixels0"], z["pixels1"]],
            [z["board0"], z["board1"]],
            z["K"],
            z["dist"],
            z["T_W_C"],
            extra,
        )


class LocalQuadratic:
    """Map pixels (u, v) to plane points (X, Y): at each query a least-squares quadratic in the pixel offsets
    fitted to the ``k`` nearest correspondences (moving least squares, uniform weights). NaN where the query
    lies farther from its nearest correspondence than ``max_gap`` times the median dot spacing."""

    def __init__(
        self, pixels: NDArray[np.float64], xy: NDArray[np.float64], k: int = 20, max_gap: float = 1.5
    ) -> None:
        self.pixels = np.asarray(pixels, np.float64)
        self.xy = np.asarray(xy, np.float64)
        self.k = min(k, len(self.pixels))
        self.tree = cKDTree(self.pixels)
        spacing = float(np.median(np.asarray(self.tree.query(self.pixels, k=2)[0])[:, 1]))
        self.max_dist = max_gap * spacing

    def __call__(self, uv: NDArray[np.float64]) -> NDArray[np.float64]:
        dist, idx = self.tree.query(uv, k=self.k)
        du = self.pixels[idx] - uv[:, None, :]  # (n, k, 2) offsets: the fit is centred on the query
        s = 1.0 / max(self.max_dist, 1.0)  # scale offsets to ~1 for a well-conditioned normal matrix
        x, y = du[..., 0] * s, du[..., 1] * s
        A = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=-1)
        AtA = np.einsum("nki,nkj->nij", A, A)
        Atb = np.einsum("nki,nkc->nic", A, self.xy[idx])
        # a tiny ridge keeps near-collinear neighbourhoods (few markers) solvable; offsets are scaled to ~1
        AtA += 1e-9 * np.eye(6)
        coef = np.linalg.solve(AtA, Atb)  # (n, 6, 2); the constant term is the value at the query
        out = coef[:, 0, :]
        out[np.asarray(dist)[:, 0] > self.max_dist] = np.nan
        return out


def _versions(directory: Path, camera: str) -> list[int]:
    if not directory.is_dir():
        return []
    out = []
    for p in directory.iterdir():
        m = _VERSION_RE.match(p.name)
        if m and m["cam"] == camera:
            out.append(int(m["v"]))
    return out


def board_correspondences(
    image: NDArray, board: BoardConfig, height_mm: float, cam: GlassCameraConfig, gate_fraction: float = 0.35
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Detected board dots and their board-plane (X, Y) in {W} (mm), identified by the nominal camera model
    of the config: a detection is the dot whose predicted pixel is nearest, within ``gate_fraction`` of the
    local dot spacing in the image."""
    det = detect_dots(image, full_profile_px=1)  # a board has no second reflection: the whole profile
    dots = board.dots_mm() + np.asarray(board.centre_xy_mm)
    T_C_W = np.linalg.inv(cam.T_W_C.matrix())
    rvec, _ = cv2.Rodrigues(T_C_W[:3, :3])
    pts = np.column_stack([dots, np.full(len(dots), height_mm)])
    pred, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), rvec, T_C_W[:3, 3], cam.K(), cam.distortion.as_array())
    pred = pred.reshape(-1, 2)
    tree = cKDTree(pred)
    spacing = np.asarray(tree.query(pred, k=2)[0])[:, 1]
    dist, nearest = tree.query(det.centroids_px)
    idx = np.asarray(nearest)
    ok = dist < gate_fraction * spacing[idx]
    idx_ok, pix_ok = idx[ok], det.centroids_px[ok]
    unique, counts = np.unique(idx_ok, return_counts=True)
    single = np.isin(idx_ok, unique[counts == 1])
    return pix_ok[single], dots[idx_ok[single]]


def calibrate_view_vectors(
    images: tuple[NDArray, NDArray], board: BoardConfig, cam: GlassCameraConfig
) -> ViewVectorCalibration:
    """Vector calibration of ``cam`` from its images of ``board`` at ``board.heights_mm`` (low, high).

    The config's camera model (intrinsics, pose) is used only to identify the dots; the result comes from
    the images. Raises CalibrationError when too few dots are found.
    """
    pixels, board_xy = [], []
    for img, z in zip(images, board.heights_mm):
        p, xy = board_correspondences(img, board, z, cam)
        if len(p) < 50:
            raise CalibrationError(
                f"camera '{cam.name}': only {len(p)} board dots identified at z={z} mm "
                "(need 50); check the board placement and the camera's nominal pose"
            )
        pixels.append(p)
        board_xy.append(xy)
    obj = np.vstack([np.column_stack([xy, np.full(len(xy), z)]) for xy, z in zip(board_xy, board.heights_mm)])
    img_pts = np.vstack(pixels)
    flags = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_K3
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(
        [obj.astype(np.float32)],
        [img_pts.astype(np.float32)],
        (cam.width_px, cam.height_px),
        cam.K().copy(),
        np.zeros(5),
        flags=flags,
    )
    R, _ = cv2.Rodrigues(rvecs[0])
    T_C_W = np.eye(4)
    T_C_W[:3, :3], T_C_W[:3, 3] = R, tvecs[0].ravel()
    return ViewVectorCalibration(
        cam.name,
        cam.serial,
        (cam.width_px, cam.height_px),
        board.heights_mm,
        pixels,
        board_xy,
        np.asarray(K, np.float64),
        np.asarray(dist, np.float64).ravel(),
        np.linalg.inv(T_C_W).astype(np.float64),
        {"model_rms_px": float(rms), "dots": [len(p) for p in pixels]},
    )
