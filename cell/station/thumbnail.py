"""A view's thumbnail for the live page: what each camera pixel of the view measured, or why it did not (the
view's ``reasons.png``: decode.Reason bits per pixel, 0 where a point was measured), in colours an operator
reads at a glance: green measured, grey shadow, yellow glare, orange low contrast, red inconsistent code."""

from __future__ import annotations

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


def view_thumbnail(view_dir: Path, width_px: int = 320) -> bytes:
    """PNG bytes of the view's reasons map in :data:`LEGEND`'s colours, ``width_px`` wide (nearest pixel)."""
    import cv2

    from cell.sensing.decode import Reason

    read = cv2.imread(str(view_dir / "reasons.png"), cv2.IMREAD_UNCHANGED)
    if read is None:
        raise FileNotFoundError(view_dir / "reasons.png")
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
