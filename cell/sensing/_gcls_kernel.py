"""Compiled per-row kernels of the GCLS decode (numba, parallel over camera rows).

Written by hand because no library decodes line-shift edges: OpenCV's GrayCodePattern gives integer stripes
only, and the NumPy formulation of the same steps (see git history of decode.py) made a dozen full-image
passes with (H, W) float64 temporaries and gathers, ~10x slower than one fused pass per row. Each row is
independent along the coded axis, so rows run in parallel (``prange``); all per-row work stays in L1/L2.

The arithmetic replicates the NumPy version exactly (same dtypes: float32 edge ratios and thresholds, float64
edge merge), so results are bit-identical to it, except that since 2026-11-27 no pixel is interpolated
between two edges that span an unusable pixel or a depth step (docs/sensing.md): such pixels are
INCONSISTENT, the others keep their bit-identical u. Arrays may be transposed views (the rows axis decodes
the transposed images); the kernels never assume a memory layout.
"""

from __future__ import annotations

import numba as nb
import numpy as np

_DARK, _SATURATED, _LOW_CONTRAST, _INCONSISTENT, _NO_CODE = 1, 2, 4, 8, 16


@nb.njit(cache=True, parallel=True, nogil=True)
def reference_masks(white, black, top, dark_thr, min_contrast):
    """Modulation white - black (DN), contrast (W-B)/(W+B) (float32) and DARK/SATURATED/LOW_CONTRAST bits."""
    H, W = white.shape
    mod = np.empty((H, W), np.float32)
    contrast = np.empty((H, W), np.float32)
    base = np.zeros((H, W), np.uint8)
    for r in nb.prange(H):
        for c in range(W):
            wf = np.float32(white[r, c])
            bf = np.float32(black[r, c])
            m = wf - bf
            ct = m / max(wf + bf, np.float32(1.0))
            mod[r, c] = m
            contrast[r, c] = ct
            b = 0
            dark = m < dark_thr
            if dark:
                b |= _DARK
            if white[r, c] >= top:
                b |= _SATURATED
            if not dark and ct < min_contrast:
                b |= _LOW_CONTRAST
            base[r, c] = b
    return mod, contrast, base


@nb.njit(cache=True, inline="always")
def _min_nan(a, b):
    """np.minimum semantics: NaN if either is NaN."""
    if a != a or b != b:
        return np.float32(np.nan)
    return a if a < b else b


@nb.njit(cache=True, parallel=True, nogil=True)
def gcls_axis(
    stack,
    gray_idx,
    shift_idx,
    base,
    mod,
    n_codes,
    shift_px,
    offset_px,
    edge_frac,
    max_span,
    u,
    reasons,
    sharp,
):
    """Decode one coded axis; rows of the (N, R, C) ``stack`` run along the coded axis.

    ``gray_idx`` / ``shift_idx`` (k, 2) frame indices of each pattern and its inverse; ``base`` and ``mod``
    (R, C) from :func:`reference_masks`; ``edge_frac`` float32 (min_edge_frac * 0.5); ``max_span`` the
    widest edge pair a pixel is interpolated between, as a multiple of the row's mean spacing of adjacent
    edges. Writes ``u`` (projector px, NaN where invalid), ``reasons`` and ``sharp`` (R, C) and returns the
    number of edges found.
    """
    _, R, C = stack.shape
    n_gray = gray_idx.shape[0]
    n = shift_idx.shape[0]
    Q = n_codes
    half = np.float32(0.5)
    one = np.float32(1.0)
    sh = np.float32(shift_px)
    off = np.float32(offset_px)
    edges = np.zeros(R, np.int64)
    for r in nb.prange(R):
        g = np.zeros(C, np.int32)
        binary = np.zeros(C, np.int32)
        clear = np.zeros(C, np.int16)
        cnt = np.zeros(C, np.int16)
        first = np.zeros(C, np.bool_)
        # Gray stripe index; a pixel is coded when at most one Gray pattern lacks a clear difference.
        for b in range(n_gray):
            P, I = gray_idx[b, 0], gray_idx[b, 1]
            for c in range(C):
                d = np.int32(stack[P, r, c]) - np.int32(stack[I, r, c])
                bit = np.int32(1) if d > 0 else np.int32(0)
                binary[c] ^= bit
                g[c] = (g[c] << 1) | binary[c]
                if np.float32(abs(d)) > half * mod[r, c]:
                    clear[c] += 1
        # Johnson code of the shift bits, unwrapped by the Gray stripe to the pixel's integer code.
        for j in range(n):
            P, I = shift_idx[j, 0], shift_idx[j, 1]
            for c in range(C):
                pos = np.int32(stack[P, r, c]) > np.int32(stack[I, r, c])
                if pos:
                    cnt[c] += 1
                if j == 0:
                    first[c] = pos
        qpix = np.empty(C, np.int32)
        usable = np.empty(C, np.bool_)
        for c in range(C):
            rr = (n + cnt[c] - 1) if first[c] else (n - cnt[c] - 1)
            est = g[c] * n + (n - 1) / 2.0
            qpix[c] = rr + 2 * n * np.int32(np.rint((est - rr) / (2 * n)))
            usable[c] = base[r, c] == 0 and clear[c] >= n_gray - 1
        nbad = np.empty(C + 1, np.int32)  # unusable pixels in [0, c): a shadow between two edges shows
        k = np.int32(0)
        for c in range(C):
            nbad[c] = k
            k += np.int32(not usable[c])
        nbad[C] = k
        # Edges: sign changes of D_j between pixels c and c+1, at x = c + D(c) / (D(c) - D(c+1)); crossings
        # that land on the same code are merged by a swing-weighted mean.
        wsum = np.zeros(Q + 1)
        wx = np.zeros(Q + 1)
        hits = np.zeros(Q + 1)
        ne = 0
        for j in range(n):
            P, I = shift_idx[j, 0], shift_idx[j, 1]
            d0 = np.int32(stack[P, r, 0]) - np.int32(stack[I, r, 0])
            for c in range(C - 1):
                d1 = np.int32(stack[P, r, c + 1]) - np.int32(stack[I, r, c + 1])
                if (d0 > 0) != (d1 > 0) and usable[c] and usable[c + 1]:
                    a = np.float32(d0)
                    swing = a - np.float32(d1)
                    msum = mod[r, c] + mod[r, c + 1]
                    if abs(swing) > edge_frac * msum:
                        x = np.float64(c) + np.float64(a / swing)
                        est = 0.5 * (qpix[c] + qpix[c + 1] + 1)
                        q = j + n * np.int64(np.rint((est - j) / n))
                        if q >= 0 and q <= Q:
                            w = np.float64(abs(swing) / max(half * msum, one))
                            wsum[q] += w
                            wx[q] += w * x
                            hits[q] += 1.0
                            ne += 1
                d0 = d1
        edges[r] = ne
        Xf = np.empty(Q + 1, np.float32)
        Sf = np.empty(Q + 1, np.float32)
        for q in range(Q + 1):
            Xf[q] = np.float32(wx[q] / wsum[q]) if wsum[q] > 0 else np.float32(np.nan)
            Sf[q] = np.float32(wsum[q] / hits[q]) if hits[q] > 0 else np.float32(np.nan)
        # An edge pair brackets pixels only if no unusable pixel lies between its edges (else the line would
        # run across a shadow or an undecoded area to an edge on another surface) and it is not much wider
        # than the row's mean spacing of the adjacent edge pairs that pass the first rule (a depth step).
        # ``span[q]`` = X[q+1] - X[q] (the interpolation's denominator), NaN for a pair that brackets nothing.
        span = np.empty(Q, np.float32)
        span_sum = 0.0
        n_span = 0
        for q in range(Q):
            xl, xr = Xf[q], Xf[q + 1]
            dx = xr - xl
            if dx == dx and nbad[np.int64(max(xl, xr)) + 1] != nbad[np.int64(min(xl, xr)) + 1]:
                dx = np.float32(np.nan)
            if dx == dx:
                span_sum += abs(dx)
                n_span += 1
            span[q] = dx
        if n_span > 0:
            widest = max_span * span_sum / n_span
            for q in range(Q):
                if abs(span[q]) > widest:
                    span[q] = np.float32(np.nan)
        # Every pixel between the edges of its code q and q+1 interpolates its coordinate; a pixel that is not
        # (one flipped bit beside an edge) tries q-1 then q+1; else it is INCONSISTENT.
        for c in range(C):
            b = base[r, c]
            if b == 0 and not usable[c]:
                b |= _NO_CODE
            ul = np.float32(np.nan)
            sp = np.float32(np.nan)
            if usable[c]:
                cf = np.float32(c)
                q0 = min(max(qpix[c], 0), Q - 1)
                t = (cf - Xf[q0]) / span[q0]
                if t >= 0 and t <= 1 and qpix[c] == q0:
                    ul = np.float32(np.float64(q0) + np.float64(t))
                    sp = _min_nan(Sf[q0], Sf[q0 + 1])
                else:  # (rare) outside its own pair, or inside a dropped one: then it gets no coordinate
                    t = (cf - Xf[q0]) / (Xf[q0 + 1] - Xf[q0])
                    if not (t >= 0 and t <= 1 and qpix[c] == q0):
                        for dq in (-1, 1):
                            q = qpix[c] + dq
                            i = min(max(q, 0), Q - 1)
                            tt = (cf - Xf[i]) / (Xf[i + 1] - Xf[i])
                            if q >= 0 and q < Q and tt >= 0 and tt <= 1:
                                if span[i] == span[i]:  # not a dropped pair
                                    ul = np.float32(np.float64(q) + np.float64(tt))
                                    sp = _min_nan(Sf[i], Sf[i + 1])
                                break
                if ul != ul:
                    b |= _INCONSISTENT
            reasons[r, c] = b
            sharp[r, c] = sp
            u[r, c] = off + ul * sh - half if b == 0 else np.float32(np.nan)
    return edges.sum()
