"""Rebuild tests/data/procam_kamino410/ from a clone of https://github.com/kamino410/procam-calibration (MIT).

    python tests/data/make_procam_subset.py /path/to/procam-calibration tests/data/procam_kamino410

Per pose of sample_data/: the region of interest around the chessboard (its inner corners found in the white
frame, plus 70 px, aligned to the binning), averaged 3x3 (a camera's 3x3 binning: 1280x1024 -> 426x341),
written as 8-bit PNG. Nothing else is changed: no filtering, no contrast change, every frame kept.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import cv2
import numpy as np

BIN, MARGIN_PX, FRAMES, INNER = 3, 70, 42, (9, 7)


def main(src: Path, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    poses = []
    for p in range(5):
        pdir = src / "sample_data" / f"capture_{p}"
        white = cv2.imread(str(pdir / "graycode_40.png"), cv2.IMREAD_GRAYSCALE)
        ok, c = cv2.findChessboardCorners(white, INNER)
        assert ok, pdir
        c = c.reshape(-1, 2)
        x0, y0 = (np.floor(c.min(0) - MARGIN_PX) // BIN * BIN).astype(int).clip(0)
        x1, y1 = (np.ceil(c.max(0) + MARGIN_PX) // BIN * BIN + BIN).astype(int)
        x1, y1 = min(x1, white.shape[1] // BIN * BIN), min(y1, white.shape[0] // BIN * BIN)
        (out / pdir.name).mkdir(exist_ok=True)
        for i in range(FRAMES):
            img = cv2.imread(str(pdir / f"graycode_{i:02d}.png"), cv2.IMREAD_GRAYSCALE)[y0:y1, x0:x1]
            img = cv2.resize(img, ((x1 - x0) // BIN, (y1 - y0) // BIN), interpolation=cv2.INTER_AREA)
            cv2.imwrite(str(out / pdir.name / f"graycode_{i:02d}.png"), img, [cv2.IMWRITE_PNG_COMPRESSION, 9])
        poses.append(f"  - {{dir: {pdir.name}, roi_px: [{x0 // BIN}, {y0 // BIN}]}}")
    (out / "capture.yaml").write_text(
        "# kamino410/procam-calibration sample_data (MIT), 3x3-binned ROIs; see tests/data/README.md\n"
        f"camera: {{width_px: {1280 // BIN}, height_px: {1024 // BIN}, bit_depth: 8}}\n"
        "projector: {width_px: 1024, height_px: 768}\n"
        "code: {kind: graycode}\n"
        "order: opencv\n"
        'images: "graycode_*.png"\n'
        "board: {kind: chessboard, squares: [10, 8], square_mm: 75}\n"
        "poses:\n" + "\n".join(poses) + "\n"
    )
    shutil.copy(src / "LICENSE", out / "LICENSE")


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
