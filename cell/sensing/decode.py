"""Decode a captured GCLS or GCPS stack into the projector coordinate seen by every camera pixel.

Output per coded axis: ``u`` (H, W) float32 projector pixel coordinate (OpenCV pixel-centre convention, the
same as the simulator's ``projector_uv``), NaN where invalid, and per pixel the reasons it is invalid as bits
of ``reasons`` (see :class:`Reason`), so shadow and glare maps can be built from them later.

GCLS (dissertation 2.1.4-2.1.5, Fig 2.5). Each line-shift pattern j and its inverse give D = P - I; a stripe
edge lies where D changes sign between camera pixels n and n+1 along the row, at the sub-pixel position
x = n + D(n) / (D(n) - D(n+1)), i.e. x = n + (A-B)/((A-B)-(C-D)) with A, B the pattern and inverse at n and C,
D at n+1. Which projector edge it is (its code q, projector boundary ``q*shift - 0.5``) comes from the codes of
the two pixels beside it: the Gray stripe index unwraps the shift patterns' Johnson code. The edges are the
measured points; every camera pixel between two consecutive edges q and q+1 of the same row gets its
projector coordinate by linear interpolation between them (the surface is smooth at the scale of one code,
~1.7 camera px here), so the cloud stays organised (H, W). A pixel whose own code does not lie between two
found edges is marked INCONSISTENT (Gray code disagrees with the line shifts) and gets no coordinate.

GCPS: the same Gray stripes unwrap an N-step phase of period 2*stripe (see patterns.py).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntFlag

import numpy as np
from numpy.typing import NDArray

from cell.sensing.patterns import Axis, AxisCode, PatternSet


class Reason(IntFlag):
    """Why a pixel has no point; a pixel may have several."""

    DARK = 1  # no projector light: shadow, black or far-tilted surface (white - black too small)
    SATURATED = 2  # white frame at full scale: glare
    LOW_CONTRAST = 4  # lit, but the pattern modulation is too weak against ambient light
    INCONSISTENT = 8  # Gray code and line-shift/phase code disagree, or no edges bracket the pixel
    NO_CODE = 16  # outside the coded projector range


@dataclass(frozen=True)
class DecodeParams:
    """Thresholds, as fractions of the full scale (2**bits - 1) or of the local modulation."""

    dark_frac: float = 0.03  # white - black below this: DARK
    min_contrast: float = 0.2  # (white - black) / (white + black) below this: LOW_CONTRAST
    min_edge_frac: float = 0.05  # an edge's |D(n) - D(n+1)| must exceed this * local modulation


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


def _gray_stripe(stack: NDArray, ps: PatternSet, code: AxisCode, tag: str, mod_thr: NDArray
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


def _johnson_code(stack: NDArray, ps: PatternSet, code: AxisCode, tag: str) -> tuple[NDArray, list[NDArray]]:
    """Position modulo 2n (n = shifts) from the shift patterns' bits, tolerant to one flipped bit; and D_j."""
    n = code.n_shifts
    s = np.zeros(stack.shape[1:], np.int16)
    diffs = []
    first = None
    for j in range(n):
        d = _diff(stack, ps.index(f"{tag}_shift{j}"), ps.index(f"{tag}_shift{j}_inv"))
        diffs.append(d)
        bit = d > 0
        s += bit
        if j == 0:
            first = bit
    r = np.where(first, n + s - 1, n - s - 1).astype(np.int32)
    return r, diffs


def _unwrap(r: NDArray, period: int, estimate: NDArray) -> NDArray:
    """The value congruent to ``r`` modulo ``period`` nearest to ``estimate`` (all in code units)."""
    return r + period * np.rint((estimate - r) / period).astype(np.int32)


def _decode_gcls_axis(stack: NDArray, ps: PatternSet, code: AxisCode, base: NDArray[np.uint8],
                      mod: NDArray[np.float32], p: DecodeParams) -> AxisDecode:
    tag = "col" if code.axis == "columns" else "row"
    n = code.n_shifts
    Q = code.n_codes
    H, W = stack.shape[1:]
    mod_thr = 0.5 * mod
    G, coded = _gray_stripe(stack, ps, code, tag, mod_thr)
    r, diffs = _johnson_code(stack, ps, code, tag)
    q_pix = _unwrap(r, 2 * n, G * n + (n - 1) / 2.0)  # integer code of each pixel: floor(x / shift)
    usable = (base == 0) & coded

    # Edges of every shift pattern: sign changes of D along the row, located by linear interpolation.
    rows_l, xs_l, qs_l, sw_l = [], [], [], []
    edge_ok = usable[:, :-1] & usable[:, 1:]
    for j, d in enumerate(diffs):
        pos = d > 0
        cand = (pos[:, :-1] != pos[:, 1:]) & edge_ok
        rr, cc = np.nonzero(cand)
        a = d[rr, cc].astype(np.float32)
        c = d[rr, cc + 1].astype(np.float32)
        swing = a - c
        keep = np.abs(swing) > p.min_edge_frac * 0.5 * (mod[rr, cc] + mod[rr, cc + 1])
        rr, cc, a, swing = rr[keep], cc[keep], a[keep], swing[keep]
        x = cc + a / swing
        est = 0.5 * (q_pix[rr, cc] + q_pix[rr, cc + 1] + 1)
        q = _unwrap(np.full(len(rr), j, np.int32), n, est)
        ok = (q >= 0) & (q <= Q)
        rows_l.append(rr[ok])
        xs_l.append(x[ok])
        qs_l.append(q[ok])
        sw_l.append(np.abs(swing[ok]) / np.maximum(0.5 * (mod[rr[ok], cc[ok]] + mod[rr[ok], cc[ok] + 1]), 1))
    rows, xs, qs = np.concatenate(rows_l), np.concatenate(xs_l), np.concatenate(qs_l)
    sharp = np.concatenate(sw_l).astype(np.float64)
    # Table of edge positions per (row, code). Noise can split one edge into several crossings within a pixel
    # or two: they land on the same (row, code) and are merged by a swing-weighted mean.
    flat = rows.astype(np.int64) * (Q + 1) + qs
    size = H * (Q + 1)
    wsum = np.bincount(flat, weights=sharp, minlength=size)
    with np.errstate(invalid="ignore", divide="ignore"):
        Xe = (np.bincount(flat, weights=sharp * xs, minlength=size) / wsum).reshape(H, Q + 1)
        Se = (wsum / np.bincount(flat, minlength=size)).reshape(H, Q + 1)

    # Each pixel lies between the edges of its code q and q+1; pixels that do not (one flipped bit beside an
    # edge) try q-1 and q+1. Flat indices into the edge table: ``np.take`` is far faster than 2-D fancy indexing.
    Xf = Xe.ravel().astype(np.float32)
    Sf = Se.ravel().astype(np.float32)
    row_base = (np.arange(H, dtype=np.int64) * (Q + 1))[:, None]
    q0 = np.clip(q_pix, 0, Q - 1)
    idx = (row_base + q0).ravel()
    cols = np.broadcast_to(np.arange(W, dtype=np.float32)[None, :], (H, W)).ravel()
    with np.errstate(invalid="ignore", divide="ignore"):
        xl = np.take(Xf, idx)
        t = (cols - xl) / (np.take(Xf, idx + 1) - xl)
    ok = (t >= 0) & (t <= 1) & usable.ravel() & (q_pix.ravel() == q0.ravel())
    u_local = np.where(ok, q0.ravel() + t, np.nan).astype(np.float32)
    sharp_px = np.where(ok, np.minimum(np.take(Sf, idx), np.take(Sf, idx + 1)), np.nan).astype(np.float32)
    retry = np.flatnonzero(~ok & usable.ravel())
    for dq in (-1, 1):
        q = q_pix.ravel()[retry] + dq
        inside = (q >= 0) & (q < Q)
        i = retry // W * (Q + 1) + np.clip(q, 0, Q - 1)
        with np.errstate(invalid="ignore", divide="ignore"):
            xl = Xf[i]
            tt = (cols[retry] - xl) / (Xf[i + 1] - xl)
        hit = inside & (tt >= 0) & (tt <= 1)
        u_local[retry[hit]] = q[hit] + tt[hit]
        sharp_px[retry[hit]] = np.minimum(Sf[i[hit]], Sf[i[hit] + 1])
        retry = retry[~hit]
    u_local = u_local.reshape(H, W)
    sharp_px = sharp_px.reshape(H, W)
    reasons = base.copy()
    reasons[(base == 0) & ~coded] |= np.uint8(Reason.NO_CODE)
    bad = usable & np.isnan(u_local)
    reasons[bad] |= np.uint8(Reason.INCONSISTENT)
    u = np.where(reasons == 0, code.offset_px + u_local * np.float32(code.shift_px) - np.float32(0.5), np.nan)
    return AxisDecode(code.axis, u.astype(np.float32), reasons, sharp_px, int(len(xs)))


def _decode_gcps_axis(stack: NDArray, ps: PatternSet, code: AxisCode, base: NDArray[np.uint8],
                      mod: NDArray[np.float32], p: DecodeParams) -> AxisDecode:
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


def decode(stack: NDArray, patterns: PatternSet, bit_depth: int = 8, params: DecodeParams = DecodeParams()
           ) -> Decoded:
    """Decode a checked (N, H, W) stack (see :func:`cell.sensing.stack.check_stack`) of ``patterns``."""
    top = float(2**bit_depth - 1)
    white = stack[patterns.index("white")]
    black = stack[patterns.index("black")]
    wf = white.astype(np.float32)
    bf = black.astype(np.float32)
    mod = wf - bf
    contrast = mod / np.maximum(wf + bf, 1.0)
    base = np.zeros(white.shape, np.uint8)
    dark = mod < params.dark_frac * top
    base[dark] |= np.uint8(Reason.DARK)
    base[white >= top] |= np.uint8(Reason.SATURATED)
    base[~dark & (contrast < params.min_contrast)] |= np.uint8(Reason.LOW_CONTRAST)
    axes: dict[str, AxisDecode] = {}
    for code in patterns.codes:
        if code.axis == "columns":
            s, b, m = stack, base, mod
        else:  # row stripes: edges run along camera columns; decode the transposed images
            s, b, m = stack.transpose(0, 2, 1), base.T, mod.T
        fn = _decode_gcls_axis if patterns.codec == "gcls" else _decode_gcps_axis
        ad = fn(s, patterns, code, np.ascontiguousarray(b), np.ascontiguousarray(m), params)
        if code.axis == "rows":
            ad = AxisDecode("rows", ad.u.T.copy(), ad.reasons.T.copy(), ad.sharpness.T.copy(), ad.n_edges)
        axes[code.axis] = ad
    return Decoded(axes, contrast, mod)
