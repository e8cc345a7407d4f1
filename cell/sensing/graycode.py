"""Plain binary-reflected Gray code, laid out as OpenCV's ``structured_light.GrayCodePattern`` generates it.

Many projector-camera calibration tools capture this code (one Gray bit per projector pixel, no line shifts
or phase), so capture sets made elsewhere can be decoded here. OpenCV's layout: ceil(log2(width)) column
patterns, most significant bit first, each followed by its inverse, then ceil(log2(height)) row patterns
likewise; the tools append an all-white and an all-black frame. Projector column ``x`` is Gray-coded directly
(no stripe width, no offset), so the decoded coordinate is the integer projector pixel (pixel-centre
convention, as :mod:`cell.sensing.patterns`), what ``GrayCodePattern.getProjPixel`` returns.

The frames and names reuse :mod:`cell.sensing.patterns` (``col_gray{b}``, ``col_gray{b}_inv``, ...; a
:class:`PatternSet` of codec ``graycode`` with one-pixel "stripes") and the decode reuses the Gray stripe
decoder and reference masks of :mod:`cell.sensing.decode`.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from cell.errors import ConfigError
from cell.sensing import _gcls_kernel
from cell.sensing.decode import AxisDecode, Decoded, DecodeParams, Reason, _diff, _gray_stripe
from cell.sensing.patterns import AxisCode, Direction, PatternSet, _assemble, _axes

# OpenCV's default whiteThreshold: a bit whose pattern and inverse differ by less (8-bit DN) is unclear.
WHITE_THRESHOLD_DN8 = 5


def graycode_patterns(width_px: int, height_px: int, direction: Direction = "both") -> PatternSet:
    """The plain Gray code set of a ``width_px`` x ``height_px`` projector, in the cell's frame order
    (white, black, then per axis each bit and its inverse); :func:`opencv_order` gives OpenCV's order."""
    if width_px < 2 or height_px < 2:
        raise ConfigError(f"Gray code: projector {width_px}x{height_px} px is too small")
    codes = [
        AxisCode(a, int(np.ceil(np.log2(width_px if a == "columns" else height_px))), 1, 0, 0, 0)
        for a in _axes(direction)
    ]
    return _assemble("graycode", width_px, height_px, codes)


def opencv_order(patterns: PatternSet) -> list[str]:
    """Frame names in the order OpenCV's ``GrayCodePattern.generate()`` lists its patterns (column bits, then
    row bits, each followed by its inverse), then white, then black."""
    return [n for n in patterns.names if n not in ("white", "black")] + ["white", "black"]


def decode_graycode(
    stack: NDArray,
    patterns: PatternSet,
    bit_depth: int = 8,
    params: DecodeParams = DecodeParams(),
    white_threshold_dn8: float = WHITE_THRESHOLD_DN8,
) -> Decoded:
    """Integer projector column/row per camera pixel from a checked (N, H, W) stack in ``patterns`` order.

    A bit is unclear where pattern and inverse differ by no more than ``white_threshold_dn8`` (scaled to
    the bit depth); OpenCV's ``getProjPixel`` rejects such pixels. Here one unclear bit is accepted when its
    two readings give adjacent codes, i.e. the pixel straddles that bit's stripe edge (mostly the finest bit,
    whose one-pixel stripes the optics blur): the code is then off by one projector pixel at most. Other
    pixels with unclear bits are INCONSISTENT. NO_CODE: a code beyond the projector's width or height.
    Sharpness is 1 where decoded (plain Gray has no edge measure)."""
    top = 2**bit_depth - 1
    mod, contrast, base = _gcls_kernel.reference_masks(
        stack[patterns.index("white")],
        stack[patterns.index("black")],
        top,
        np.float32(params.dark_frac * top),
        np.float32(params.min_contrast),
    )
    thr = np.full(base.shape, white_threshold_dn8 * top / 255.0, np.float32)
    axes: dict[str, AxisDecode] = {}
    for code in patterns.codes:
        tag = "col" if code.axis == "columns" else "row"
        g, coded = _gray_stripe(stack, patterns, code, tag, thr)
        # Flipping Gray bit b (MSB first) inverts the binary bits from b down: the other reading is g ^ flip.
        flip = np.zeros_like(g)
        for b in range(code.n_gray):
            unclear = np.abs(
                _diff(stack, patterns.index(f"{tag}_gray{b}"), patterns.index(f"{tag}_gray{b}_inv"))
            )
            flip[unclear <= thr] |= (1 << (code.n_gray - b)) - 1
        coded &= (flip == 0) | (np.abs(g - (g ^ flip)) == 1)
        length = patterns.width_px if code.axis == "columns" else patterns.height_px
        reasons = base.copy()
        reasons[(reasons == 0) & ~coded] |= np.uint8(Reason.INCONSISTENT)
        reasons[(reasons == 0) & (g >= length)] |= np.uint8(Reason.NO_CODE)
        ok = reasons == 0
        u = np.where(ok, g.astype(np.float32), np.float32(np.nan))
        axes[code.axis] = AxisDecode(code.axis, u, reasons, ok.astype(np.float32))
    return Decoded(axes, contrast, mod)
