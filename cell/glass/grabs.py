"""A glass run's grabs on disk (``views/`` of the run folder; docs/storage.md): each camera's mean of the
frames it grabbed (:func:`cell.glass.job.grab_mean`), the image the measurement read, stored losslessly.

A camera gives integers, so the mean of ``frames`` grabs is an integer sum divided by ``frames``: the sum is
stored as a 16-bit PNG (``<name>.png``, zlib level 1 as the inspection's raw images) and ``grabs.json`` names
each file with its ``frames``. :func:`load_grab` gives back the very float32 image the measurement read, bit
for bit (``save_grab`` checks it before choosing the PNG). A mean that is not such a sum (a driver that gives
floats) or whose sum exceeds 16 bits (a 12-bit camera averaged over more than 16 frames) is stored as float32
in a deflated ``<name>.npz``. Runs from before hold ``<name>.npy`` (float32, uncompressed), read as they are.

Measured on the simulated rig's 8-bit 1024 x 768 cameras averaged over 4 frames (docs/storage.md): 3.15 MB a
camera as .npy, 0.70 MB as PNG.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from cell.view_files import PNG_PARAMS

MANIFEST = "grabs.json"
FORMAT = 1


def _mean(total: NDArray[Any], frames: int) -> NDArray[np.float32]:
    """What grab_mean computes from the float64 sum of ``frames`` grabs."""
    return (np.asarray(total, np.float64) / frames).astype(np.float32)


def save_grab(views_dir: Path, name: str, mean: NDArray[np.float32], frames: int) -> Path:
    """Store camera ``name``'s mean of ``frames`` grabs in ``views_dir``; returns the file written."""
    mean = np.asarray(mean, dtype=np.float32)
    total = np.round(mean.astype(np.float64) * frames)
    exact = total.min(initial=0) >= 0 and total.max(initial=0) <= np.iinfo(np.uint16).max
    exact = exact and np.array_equal(_mean(total, frames), mean)  # bit for bit what was measured
    if exact:
        path = views_dir / f"{name}.png"
        ok, png = cv2.imencode(".png", total.astype(np.uint16), PNG_PARAMS)  # as the raw view images
        if not ok:
            raise OSError(f"OpenCV could not encode the grab of camera '{name}' as PNG")
        path.write_bytes(png.tobytes())
        entry = {"file": path.name, "frames": frames, "stored": "sum of the frames (uint16 PNG)"}
    else:
        path = views_dir / f"{name}.npz"
        with open(path, "wb") as fh:
            np.savez_compressed(fh, mean=mean)
        entry = {"file": path.name, "frames": frames, "stored": "mean (float32, deflate)"}
    manifest_path = views_dir / MANIFEST
    manifest: dict[str, Any] = {"format": FORMAT, "grabs": {}}
    if manifest_path.is_file():
        manifest = json.loads(manifest_path.read_text())
    manifest["grabs"][name] = entry
    manifest_path.write_text(json.dumps(manifest, indent=2))
    return path


def load_grab(views_dir: Path, name: str) -> NDArray[np.float32]:
    """Camera ``name``'s mean grab as the measurement read it (float32); FileNotFoundError when the run has
    none of that name."""
    manifest_path = views_dir / MANIFEST
    if manifest_path.is_file():
        entry = json.loads(manifest_path.read_text()).get("grabs", {}).get(name)
        if entry is not None:
            path = views_dir / entry["file"]
            if path.suffix == ".npz":
                with np.load(path) as z:
                    return np.asarray(z["mean"], dtype=np.float32)
            total = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if total is None:
                raise FileNotFoundError(path)
            return _mean(total, int(entry["frames"]))
    return np.load(views_dir / f"{name}.npy")  # a run from before
