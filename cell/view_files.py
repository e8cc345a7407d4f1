"""What an inspection view folder (``views/NNN/``) stores, and one reader for every format it was stored in.

Format 3 (docs/storage.md), written by :func:`save_view_points` and :func:`save_raw_stack`, is format 2
with the points' step differences stored as ``delta_planes`` (uint8, shape (3, 4, N)): per coordinate, the
four bytes of its int32 differences as four planes (all lowest bytes, then the next, little-endian), the same
numbers as format 2's ``delta``; the high bytes of small differences are nearly all 0 or 255, so deflate
packs them 18 % smaller (1.30 against 1.59 MB a view of the pillar). Format 2:

- ``points.npz`` (deflate): the view's points in the world frame {W}, in pixel order, as int32 steps of
  :data:`STEP_MM` (0.1 um), each the difference to the point before (neighbouring pixels lie close, so the
  differences are small numbers that compress to about 2.4 bytes a point against 24 for float64); the points'
  ``quality`` (float32 contrast, exact), ``oblique`` (bool: lit beyond the incidence limit) and ``eval``
  (bool: the evaluation subset, one point per 0.5 mm voxel) and, in folders since issue 17,
  ``uncertainty_log2`` (each point's decode and calibration uncertainty, cell.analysis.uncertainty, as
  :func:`encode_view_uncertainty` codes it: 1/32 of an octave, rounded by at most 1.1 %, differences in pixel
  order, about 0.15 bytes a point deflated against 3.2 for float32; folders of this branch before hold
  ``uncertainty`` float32 mm). The 0.1 um step
  rounds a coordinate by at most 0.05 um (0.029 um RMS), what float32 itself would do at 500 mm and a
  thousandth of the sensor's noise.
- ``raw/`` (optional, by the cell's ``retention:``): the pattern stack as the camera gave it, one lossless
  PNG a frame (8-bit cameras 8-bit files, 10/12-bit cameras 16-bit files), laid out as a capture folder
  (``raw/capture.yaml``, ``raw/frames/NN_<frame>.png``; docs/capture-folders.md), so ``cell scan --from
  views/NNN/raw`` decodes the view again and :func:`load_raw_stack` reads it with the capture-folder reader.

Format 1 (run folders before format 2): ``points_W.npy`` (float64), ``points_eval_W.npy`` (the evaluation
subset, a copy), ``quality.npy``, ``oblique.npy`` (absent in the oldest folders: no point oblique) and the
unread ``deviation_eval.npy``. :func:`load_view_points` and :func:`load_eval_points` read either.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml
from numpy.typing import NDArray

from cell.runs import RAW_IMAGES

POINTS_FILE = "points.npz"
FORMAT = 3
STEP_MM = 1e-4  # storage step of a coordinate: 0.1 um
_LIMIT = 2**30  # |coordinate| / STEP_MM: 107 m, so that differences of two stay within int32
# how the raw frames are encoded (lossless PNG, docs/storage.md): zlib level 1, every row filtered by its
# left neighbour's difference (SUB) and Huffman-coded alone (no string matching, which finds little in noisy
# images): 2.5-26 % smaller than zlib level 1 with libpng's adaptive filters (the ideal and the honest world's
# demo), for half the CPU; the same pixels. The order counts: OpenCV resets the strategy when the compression
# level follows it. Needs OpenCV >= 4.12 (IMWRITE_PNG_FILTER)
PNG_PARAMS = [
    cv2.IMWRITE_PNG_COMPRESSION,
    1,
    cv2.IMWRITE_PNG_FILTER,
    cv2.IMWRITE_PNG_FILTER_SUB,
    cv2.IMWRITE_PNG_STRATEGY,
    cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY,
]
FRAMES = "frames"


@dataclass
class ViewPoints:
    """A view's stored points (N, 3) in {W} mm, pixel order, with their quality and oblique flags (the
    evaluation subset is read on its own: :func:`load_eval_points`)."""

    points_W: NDArray[np.float64]
    quality: NDArray[np.float32]
    oblique: NDArray[np.bool_]  # lit beyond sensor.max_projector_incidence_deg: not in the merged cloud
    uncertainty: NDArray[np.float32] | None = None  # mm, decode and calibration (None: not stored)


def save_view_points(
    out_dir: Path,
    points_W: NDArray[np.float64],
    quality: NDArray[np.floating[Any]],
    oblique: NDArray[np.bool_],
    eval_index: NDArray[np.integer[Any]],
    uncertainty: NDArray[np.floating[Any]] | None = None,
) -> NDArray[np.float64]:
    """Write ``out_dir/points.npz`` (format 2) and return the points as they are stored (rounded to
    :data:`STEP_MM`), which is what every later step reads back. ``eval_index``: ascending indices of the
    evaluation subset; ``uncertainty``: each point's (mm), stored as log2 codes when given
    (:func:`encode_view_uncertainty`)."""
    steps = _steps(points_W)
    delta = np.diff(steps, axis=0, prepend=np.zeros((1, 3), np.int64)).astype(np.int32)
    mask = np.zeros(len(steps), dtype=bool)
    mask[np.asarray(eval_index, dtype=np.int64)] = True
    arrays: dict[str, NDArray[Any]] = {
        "format": np.asarray(FORMAT, np.int32),
        "step_mm": np.asarray(STEP_MM, np.float64),
        "delta_planes": _byte_planes(delta),
        "quality": np.asarray(quality, dtype=np.float32),
        "oblique": np.asarray(oblique, dtype=bool),
        "eval": mask,
    }
    if uncertainty is not None:
        arrays["uncertainty_log2"] = np.diff(encode_view_uncertainty(uncertainty), prepend=0).astype(np.int16)
    with open(out_dir / POINTS_FILE, "wb") as f:
        np.savez_compressed(f, **arrays)  # type: ignore[arg-type]  # mypy maps **arrays onto allow_pickle
    return _from_steps(delta, STEP_MM)


def _byte_planes(delta: NDArray[np.int32]) -> NDArray[np.uint8]:
    """(N, 3) int32 differences as (3, 4, N) bytes: per coordinate, its little-endian bytes as planes."""
    n = len(delta)
    return np.ascontiguousarray(np.asarray(delta, "<i4").T).view(np.uint8).reshape(3, n, 4).transpose(0, 2, 1)


def _deltas(z: Any) -> NDArray[np.int32]:
    """The (N, 3) int32 step differences of a format 3 (``delta_planes``) or format 2 (``delta``) file."""
    if "delta_planes" not in z.files:
        return np.asarray(z["delta"])
    planes = np.asarray(z["delta_planes"], dtype=np.uint8)
    n = planes.shape[2]
    return np.ascontiguousarray(planes.transpose(0, 2, 1)).view("<i4").reshape(3, n).T


def stored_points(points_W: NDArray[np.float64]) -> NDArray[np.float64]:
    """The points as :func:`save_view_points` stores them (and every reader reads them back), without
    writing them."""
    return np.asarray(_steps(points_W) * STEP_MM, dtype=np.float64)


def _steps(points_W: NDArray[np.float64]) -> NDArray[np.int64]:
    """Each coordinate in storage steps (int64)."""
    q = np.round(np.asarray(points_W, dtype=np.float64).reshape(-1, 3) / STEP_MM)
    if len(q) and not np.abs(q).max() < _LIMIT:
        raise ValueError(f"view points beyond {_LIMIT * STEP_MM / 1000:.0f} m from the world origin")
    return q.astype(np.int64)


def _from_steps(delta: NDArray[np.int32], step_mm: float) -> NDArray[np.float64]:
    """Points (N, 3) mm from their int32 step differences."""
    return np.asarray(np.cumsum(delta, axis=0, dtype=np.int64) * step_mm, dtype=np.float64)


def load_view_points(view_dir: Path) -> ViewPoints:
    """A view's points and flags, from format 3, 2 or 1."""
    path = view_dir / POINTS_FILE
    if path.is_file():
        with np.load(path) as z:
            u = _uncertainty(z)
            return ViewPoints(_from_steps(_deltas(z), float(z["step_mm"])), z["quality"], z["oblique"], u)
    points = np.load(view_dir / "points_W.npy")
    oblique_file = view_dir / "oblique.npy"
    oblique = np.load(oblique_file) if oblique_file.is_file() else np.zeros(len(points), dtype=bool)
    return ViewPoints(points, np.load(view_dir / "quality.npy"), oblique)


def load_eval_points(view_dir: Path) -> NDArray[np.float64]:
    """A view's evaluation subset (mm, {W}), from format 3, 2 or 1."""
    path = view_dir / POINTS_FILE
    if path.is_file():
        with np.load(path) as z:
            return _from_steps(_deltas(z), float(z["step_mm"]))[z["eval"]]
    return np.load(view_dir / "points_eval_W.npy")


def load_eval_uncertainty(view_dir: Path) -> NDArray[np.float32] | None:
    """The evaluation subset's uncertainty (mm), or None when the view stored none."""
    path = view_dir / POINTS_FILE
    if not path.is_file():
        return None
    with np.load(path) as z:
        u = _uncertainty(z)
        return None if u is None else u[z["eval"]]


U_CODES_PER_OCTAVE = 32  # view points' u: 2^(1/64) - 1 = 1.09 % at most from the value computed
_U_UNIT_MM = 1e-6  # code 0: 1 nm
_U_UNKNOWN = -1


def encode_view_uncertainty(u_mm: NDArray[np.floating[Any]]) -> NDArray[np.int64]:
    """Each u (mm) as round(32 log2(u / 1 nm)) (0 below 1 nm), -1 where not known: u is a standard
    uncertainty known to a few percent, and the codes of neighbouring pixels repeat, so they deflate to a
    twentieth of float32's bytes."""
    u = np.asarray(u_mm, dtype=np.float64)
    ok = np.isfinite(u) & (u > 0)
    codes = np.full(u.shape, _U_UNKNOWN, dtype=np.int64)
    codes[ok] = np.maximum(np.round(U_CODES_PER_OCTAVE * np.log2(u[ok] / _U_UNIT_MM)), 0)
    codes[np.isfinite(u) & (u <= 0)] = 0
    return codes


def decode_view_uncertainty(codes: NDArray[np.integer[Any]]) -> NDArray[np.float32]:
    """u (mm, float32) from :func:`encode_view_uncertainty`'s codes (NaN where not known)."""
    c = np.asarray(codes, dtype=np.int64)
    u = (_U_UNIT_MM * np.exp2(c / U_CODES_PER_OCTAVE)).astype(np.float32)
    u[c == _U_UNKNOWN] = np.nan
    return u


def _uncertainty(z: Any) -> NDArray[np.float32] | None:
    if "uncertainty_log2" in z.files:
        return decode_view_uncertainty(np.cumsum(z["uncertainty_log2"].astype(np.int64)))
    return z["uncertainty"] if "uncertainty" in z.files else None


# --------------------------------------------------------------------------------------------- raw images
def save_raw_stack(
    view_dir: Path,
    stack: NDArray[Any],
    patterns: Any,
    bit_depth: int,
    projector_size: tuple[int, int],
    durable: bool = False,
) -> int:
    """Write the checked pattern stack ``stack`` ((N, H, W) uint8 or uint16, in the order of ``patterns``, a
    :class:`cell.sensing.patterns.PatternSet`) losslessly as a capture folder ``view_dir/raw/``; returns the
    bytes written. The manifest names the code by its parameters and the frames by name, so the capture-folder
    reader puts them back in the code's order. The manifest is written last: a folder whose write was cut
    short has none and reads as no raw stack (:func:`load_raw_stack`, :func:`raw_frame`). ``durable``: into
    a view folder committed already (no commit flushes it): a ``raw/`` left by a write cut short is replaced,
    and the frames are flushed to disk before the manifest, the manifest and the folders after it."""
    from cell.calibration.capture_folder import code_spec
    from cell.storage import fsync_path

    root = view_dir / RAW_IMAGES
    if durable and root.exists():
        shutil.rmtree(root)
    (root / FRAMES).mkdir(parents=True)
    n = len(patterns.names)
    width = len(str(n - 1))
    written = 0
    for k, (name, frame) in enumerate(zip(patterns.names, stack, strict=True)):
        ok, png = cv2.imencode(".png", frame, PNG_PARAMS)
        if not ok:
            raise OSError(f"OpenCV could not encode frame '{name}' as PNG")
        frame_path = root / FRAMES / f"{k:0{width}d}_{name}.png"
        frame_path.write_bytes(png.tobytes())
        if durable:
            fsync_path(frame_path)
        written += len(png)
    manifest = {
        "version": 1,
        "camera": {"width_px": int(stack.shape[2]), "height_px": int(stack.shape[1]), "bit_depth": bit_depth},
        "projector": {"width_px": projector_size[0], "height_px": projector_size[1]},
        "code": code_spec(patterns),
        "order": list(patterns.names),
        "images": "*.png",
        "poses": [{"dir": FRAMES}],
    }
    text = yaml.safe_dump(manifest, sort_keys=False).encode()
    if durable:
        fsync_path(root / FRAMES)
    (root / "capture.yaml").write_bytes(text)
    if durable:
        for path in (root / "capture.yaml", root, view_dir):
            fsync_path(path)
    return written + len(text)


def load_raw_stack(view_dir: Path) -> NDArray[Any] | None:
    """The view's raw pattern stack ((N, H, W), the code's order) read back by the capture-folder reader, or
    None when the view has none (not stored, pruned, or a folder from before raw images were kept)."""
    from cell.calibration.capture_folder import load_capture_folder

    root = view_dir / RAW_IMAGES
    if not (root / "capture.yaml").is_file():
        return None
    folder = load_capture_folder(root)
    return folder.stack(folder.poses[0])


def raw_frame(view_dir: Path, name: str = "white") -> tuple[Path, int] | None:
    """The file of frame ``name`` (default the fully lit one) of the view's raw stack, and the camera's bit
    depth (the file holds the values as the camera gave them: 8-bit files for 8 bits, else 16-bit files), or
    None when the view keeps no raw images or its stack has no such frame. Reads only ``raw/capture.yaml``."""
    root = view_dir / RAW_IMAGES
    try:
        manifest = yaml.safe_load((root / "capture.yaml").read_text())
        order = list(manifest["order"])
        bit_depth = int(manifest["camera"]["bit_depth"])
    except (OSError, yaml.YAMLError, KeyError, TypeError, ValueError):
        return None
    if name not in order:
        return None
    path = root / FRAMES / f"{order.index(name):0{len(str(len(order) - 1))}d}_{name}.png"
    return (path, bit_depth) if path.is_file() else None
