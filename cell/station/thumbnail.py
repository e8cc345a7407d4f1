"""A view's pictures for the live page, small and cached (never the camera's full-size image):

- the photo: the view's fully lit frame (the ``white`` pattern of its raw stack, ``views/NNN/raw``, while the
  cell's retention keeps it: :func:`cell.view_files.raw_frame`), downscaled, what the operator recognises the
  part by;
- the map: what each camera pixel of the view measured, or why it did not (the view's ``reasons.png``:
  decode.Reason bits per pixel, 0 where a point was measured), in colours an operator reads at a glance: green
  measured, grey shadow, yellow glare, orange low contrast, red inconsistent code.

A view folder does not change once written (its raw images can only go, by the retention), so each picture is
made once per file and kept in memory, keyed by the file's path, size and time (:func:`functools.lru_cache`).
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np

# (colour, BGR), first matching bit wins; a pixel without bits was measured
LEGEND = {
    "measured": (90, 190, 60),
    "glare": (40, 220, 240),
    "shadow": (70, 70, 70),
    "low contrast": (30, 140, 250),
    "inconsistent code": (50, 50, 220),
    "outside the pattern": (25, 25, 25),
}


WIDTH_PX = 320  # both pictures: the live page's card is 336 px wide on the 1280 x 800 panel
PHOTO_WHITE_PERCENTILE = 99.5  # this share of the photo's pixels is at most white (a dark part still shows)
PHOTO_MAX_GAIN = 8.0  # ... brightened at most this much (a frame without light stays dark)
PHOTO_GAMMA = 2.2  # the camera's linear values to a screen's brightness
PHOTO_JPEG_QUALITY = 85
CACHED = 64  # pictures kept in memory (about 20 kB each)


def _key(path: Path) -> tuple[str, int, int]:
    """What identifies a file's content for the cache; FileNotFoundError when it is missing."""
    st = path.stat()
    return str(path), st.st_size, st.st_mtime_ns


def view_thumbnail(view_dir: Path, width_px: int = WIDTH_PX) -> bytes:
    """PNG bytes of the view's reasons map in :data:`LEGEND`'s colours, ``width_px`` wide (nearest pixel)."""
    return _reasons_png(*_key(view_dir / "reasons.png"), width_px)


def view_photo(view_dir: Path, width_px: int = WIDTH_PX) -> bytes:
    """JPEG bytes of the view's fully lit frame, ``width_px`` wide (area-averaged), grey; the camera's values
    scaled so that :data:`PHOTO_WHITE_PERCENTILE` of the pixels are at most white (gain at most
    :data:`PHOTO_MAX_GAIN` over the camera's full scale) with a display gamma. FileNotFoundError when the view
    keeps no raw images (retention) or its stack has no white frame."""
    from cell.view_files import raw_frame

    found = raw_frame(view_dir, "white")
    if found is None:
        raise FileNotFoundError(view_dir / "raw")
    path, bit_depth = found
    return _photo_jpeg(*_key(path), bit_depth, width_px)


@lru_cache(maxsize=CACHED)
def _photo_jpeg(path: str, size: int, mtime_ns: int, bit_depth: int, width_px: int) -> bytes:
    import cv2

    frame = cv2.imread(path, cv2.IMREAD_UNCHANGED)
    if frame is None:
        raise FileNotFoundError(path)
    if frame.ndim == 3:
        frame = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
    height = max(1, round(frame.shape[0] * width_px / frame.shape[1]))
    small = cv2.resize(frame.astype(np.float32), (width_px, height), interpolation=cv2.INTER_AREA)
    full = float(2**bit_depth - 1)
    white = max(float(np.percentile(small, PHOTO_WHITE_PERCENTILE)), full / PHOTO_MAX_GAIN)
    grey = np.clip(small / white, 0.0, 1.0) ** (1.0 / PHOTO_GAMMA)
    ok, jpeg = cv2.imencode(
        ".jpg", np.round(grey * 255).astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, PHOTO_JPEG_QUALITY]
    )
    assert ok
    return jpeg.tobytes()


@lru_cache(maxsize=CACHED)
def _reasons_png(path: str, size: int, mtime_ns: int, width_px: int) -> bytes:
    import cv2

    from cell.sensing.decode import Reason

    read = cv2.imread(path, cv2.IMREAD_UNCHANGED)
    if read is None:
        raise FileNotFoundError(path)
    reasons = np.asarray(read, dtype=np.uint8)
    image = np.zeros((*reasons.shape[:2], 3), np.uint8)
    order = [
        ("outside the pattern", Reason.NO_CODE),
        ("inconsistent code", Reason.INCONSISTENT),
        ("low contrast", Reason.LOW_CONTRAST),
        ("shadow", Reason.DARK),
        ("glare", Reason.SATURATED),
    ]
    for name, bit in order:  # later ones paint over earlier ones: glare and shadow say most
        image[(reasons & int(bit)) != 0] = LEGEND[name]
    image[reasons == 0] = LEGEND["measured"]
    height = max(1, round(reasons.shape[0] * width_px / reasons.shape[1]))
    image = cv2.resize(image, (width_px, height), interpolation=cv2.INTER_NEAREST)
    ok, png = cv2.imencode(".png", image)
    assert ok
    return png.tobytes()


def legend_css() -> dict[str, str]:
    """The legend's colours as CSS ``rgb()``, for the page."""
    return {name: f"rgb({r},{g},{b})" for name, (b, g, r) in LEGEND.items()}
