"""Decode a captured GCLS or GCPS stack into the projector coordinate seen by every camera pixel.

Output per coded axis: ``u`` (H, W) float32 projector pixel coordinate (OpenCV pixel-centre convention, the
same as the simulator's ``projector_uv``), NaN where invalid, and per pixel the reasons it is invalid as bits
of ``reasons`` (see :class:`Reason`), so shadow and glare maps can be built from them later.

GCLS (dissertation 2.1.4-2.1.5, Fig 2.5). Each line-shift pattern j and its inverse give D = P - I; a stripe
edge lies where D changes sign between camera pixels n and n+1 along the row, at the sub-pixel position
x = n + D(n) / (D(n) - D(n+1)), i.e. x = n + (A-B)/((A-B)-(C-D)) with A, B the pattern and inverse at n and
C, D at n+1. Which projector edge it is (its code q, projector boundary ``q*shift - 0.5``) comes from the
codes of the two pixels beside it: the Gray stripe index unwraps the shift patterns' Johnson code. The edges
are the measured points; every camera pixel between two consecutive edges q and q+1 of the same row gets its
projector coordinate by linear interpolation between them (the surface is smooth at the scale of one code,
~1.7 camera px here), so the cloud stays organised (H, W). A pixel whose own code does not lie between two
found edges is marked INCONSISTENT (Gray code disagrees with the line shifts) and gets no coordinate, and so
is a pixel whose edge pair has an unusable pixel between its edges (a shadow: the edge beyond it lies on
another surface) or is more than ``max_edge_span`` times the row's mean edge spacing wide (a depth step);
docs/sensing.md.

GCPS: the same Gray stripes unwrap an N-step phase of period 2*stripe (see patterns.py).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntFlag

import cv2
import numpy as np
from numpy.typing import NDArray

from cell.sensing import _gcls_kernel
from cell.sensing.patterns import Axis, AxisCode, PatternSet


class Reason(IntFlag):
    """Why a pixel has no point; a pixel may have several."""

    DARK = 1  # no projector light: shadow, black or far-tilted surface (white - black too small)
    SATURATED = 2  # white frame at full scale: glare
    LOW_CONTRAST = 4  # lit, but the pattern modulation is too weak against ambient light
    # Gray code and line-shift/phase code disagree, or no edges bracket the pixel, or its edges span a
    # shadow, an undecoded area or a depth step (GCLS: no interpolation across them)
    INCONSISTENT = 8
    NO_CODE = 16  # outside the coded projector range


@dataclass(frozen=True)
class DecodeParams:
    """Thresholds, as fractions of the full scale (2**bits - 1) or of the local modulation."""

    dark_frac: float = 0.03  # white - black below this: DARK
    min_contrast: float = 0.2  # (white - black) / (white + black) below this: LOW_CONTRAST
    min_edge_frac: float = 0.05  # an edge's |D(n) - D(n+1)| must exceed this * local modulation
    # GCLS: no pixel is interpolated between two edges further apart than this * the row's mean spacing of
    # adjacent edges (a depth step between them); see docs/sensing.md
    max_edge_span: float = 8.0


@dataclass
class AxisDecode:
    """Decoding of one coded axis. Arrays are (H, W)."""

    axis: Axis
    u: NDArray[np.float32]  # projector coordinate along the axis (px), NaN where invalid
    reasons: NDArray[np.uint8]  # Reason bits
    sharpness: NDArray[np.float32]  # edge swing / modulation (GCLS) or phase modulation ratio (GCPS)
    n_edges: int = 0

    @property
    def valid(self) -> NDArray[np.bool_]:
        return self.reasons == 0


@dataclass
class Decoded:
    """A decoded stack: per-axis coordinates and the per-pixel image quality shared by the axes."""

    axes: dict[str, AxisDecode]
    contrast: NDArray[np.float32]  # (white - black) / (white + black)
    modulation_dn: NDArray[np.float32]  # white - black
    extra: dict[str, float] = field(default_factory=dict)

    def primary(self) -> AxisDecode:
        """The axis used for triangulation: columns when coded (they vary along the baseline)."""
        return self.axes["columns"] if "columns" in self.axes else self.axes["rows"]


def _diff(stack: NDArray, i: int, j: int) -> NDArray:
    dt = np.int16 if stack.dtype == np.uint8 else np.int32
    return np.subtract(stack[i], stack[j], dtype=dt)


def _gray_stripe(
    stack: NDArray, ps: PatternSet, code: AxisCode, tag: str, mod_thr: NDArray
) -> tuple[NDArray[np.int32], NDArray[np.bool_]]:
    """Gray stripe index per pixel and whether the pixel is inside the coded range (all but at most one
    Gray pattern show a clear pattern/inverse difference there; only one bit changes at any boundary)."""
    g = np.zeros(stack.shape[1:], np.int32)
    binary = np.zeros(stack.shape[1:], np.int32)
    clear = np.zeros(stack.shape[1:], np.int16)
    for b in range(code.n_gray):
        d = _diff(stack, ps.index(f"{tag}_gray{b}"), ps.index(f"{tag}_gray{b}_inv"))
        bit = (d > 0).view(np.uint8)
        binary ^= bit  # Gray -> binary: b_k = g_0 xor ... xor g_k
        g = (g << 1) | binary
        clear += np.abs(d) > mod_thr
    return g, clear >= code.n_gray - 1


def _unwrap(r: NDArray, period: int, estimate: NDArray) -> NDArray:
    """The value congruent to ``r`` modulo ``period`` nearest to ``estimate`` (all in code units)."""
    return r + period * np.rint((estimate - r) / period).astype(np.int32)


def _decode_gcls_axis(
    stack: NDArray,
    ps: PatternSet,
    code: AxisCode,
    base: NDArray[np.uint8],
    mod: NDArray[np.float32],
    p: DecodeParams,
) -> AxisDecode:
    """One axis through the compiled per-row kernel (:mod:`cell.sensing._gcls_kernel`), which walks camera
    rows; row stripes are decoded on transposed copies of their frames (contiguous, so the kernel streams
    memory) and the results transposed back."""
    tag = "col" if code.axis == "columns" else "row"
    names = [
        f"{tag}_{kind}{k}{inv}"
        for kind, m in (("gray", code.n_gray), ("shift", code.n_shifts))
        for k in range(m)
        for inv in ("", "_inv")
    ]
    frames = [ps.index(nm) for nm in names]
    if code.axis == "rows":
        sub = np.empty((len(frames),) + stack.shape[:0:-1], stack.dtype)
        for i, k in enumerate(frames):
            cv2.transpose(stack[k], sub[i])
        stack, frames = sub, list(range(len(frames)))
        base, mod = np.ascontiguousarray(base.T), np.ascontiguousarray(mod.T)
    pairs = np.array(frames, np.int64).reshape(-1, 2)
    R, C = base.shape
    u = np.empty((R, C), np.float32)
    reasons = np.empty((R, C), np.uint8)
    sharp = np.empty((R, C), np.float32)
    n_edges = _gcls_kernel.gcls_axis(
        np.ascontiguousarray(stack),
        pairs[: code.n_gray],
        pairs[code.n_gray :],
        base,
        mod,
        code.n_codes,
        code.shift_px,
        code.offset_px,
        np.float32(p.min_edge_frac * 0.5),
        p.max_edge_span,
        u,
        reasons,
        sharp,
    )
    if code.axis == "rows":
        u, reasons, sharp = (
            np.ascontiguousarray(u.T),
            np.ascontiguousarray(reasons.T),
            np.ascontiguousarray(sharp.T),
        )
    return AxisDecode(code.axis, u, reasons, sharp, int(n_edges))


def _decode_gcps_axis(
    stack: NDArray,
    ps: PatternSet,
    code: AxisCode,
    base: NDArray[np.uint8],
    mod: NDArray[np.float32],
    p: DecodeParams,
) -> AxisDecode:
    tag = "col" if code.axis == "columns" else "row"
    G, coded = _gray_stripe(stack, ps, code, tag, 0.5 * mod)
    N = code.n_phase
    period = 2 * code.stripe_px
    S = np.zeros(stack.shape[1:], np.float32)
    C = np.zeros(stack.shape[1:], np.float32)
    for k in range(N):
        img = stack[ps.index(f"{tag}_phase{k}")].astype(np.float32)
        delta = 2 * np.pi * k / N
        S += np.float32(np.sin(delta)) * img
        C += np.float32(np.cos(delta)) * img
    theta = np.mod(np.arctan2(S, C), 2 * np.pi)
    frac = theta / (2 * np.pi) * period  # position within the period, from the boundary at x = -0.5
    x = _unwrap(frac, period, (G + 0.5) * code.stripe_px)  # in local pixels + 0.5
    amp = 2.0 / N * np.hypot(S, C)  # phase modulation in DN; the full white-black swing is ``mod``
    ratio = amp / np.maximum(mod, 1)
    reasons = base.copy()
    reasons[(base == 0) & ~coded] |= np.uint8(Reason.NO_CODE)
    usable = reasons == 0
    # Gray vs phase consistency: the unwrapped position must fall in (or next to) the Gray stripe.
    off = np.abs(x / code.stripe_px - (G + 0.5))
    reasons[usable & ((off > 1.0) | (ratio < 0.25))] |= np.uint8(Reason.INCONSISTENT)
    u = np.where(reasons == 0, code.offset_px + x - 0.5, np.nan).astype(np.float32)
    return AxisDecode(code.axis, u, reasons, ratio.astype(np.float32))


def decode(
    stack: NDArray, patterns: PatternSet, bit_depth: int = 8, params: DecodeParams = DecodeParams()
) -> Decoded:
    """Decode a checked (N, H, W) stack (see :func:`cell.sensing.stack.check_stack`) of ``patterns``."""
    if patterns.codec == "graycode":  # plain Gray code; imported here as graycode.py builds on this module
        from cell.sensing.graycode import decode_graycode

        return decode_graycode(stack, patterns, bit_depth, params)
    top = 2**bit_depth - 1
    white = stack[patterns.index("white")]
    black = stack[patterns.index("black")]
    mod, contrast, base = _gcls_kernel.reference_masks(
        white, black, top, np.float32(params.dark_frac * top), np.float32(params.min_contrast)
    )
    axes: dict[str, AxisDecode] = {}
    for code in patterns.codes:
        if patterns.codec == "gcls":
            axes[code.axis] = _decode_gcls_axis(stack, patterns, code, base, mod, params)
        elif code.axis == "columns":
            axes[code.axis] = _decode_gcps_axis(stack, patterns, code, base, mod, params)
        else:  # row stripes: phase runs along camera columns; decode the transposed images
            ad = _decode_gcps_axis(
                stack.transpose(0, 2, 1),
                patterns,
                code,
                np.ascontiguousarray(base.T),
                np.ascontiguousarray(mod.T),
                params,
            )
            axes[code.axis] = AxisDecode(
                "rows",
                np.ascontiguousarray(ad.u.T),
                np.ascontiguousarray(ad.reasons.T),
                np.ascontiguousarray(ad.sharpness.T),
            )
    return Decoded(axes, contrast, mod)
