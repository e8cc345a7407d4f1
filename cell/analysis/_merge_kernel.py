"""Compiled kernels of the registration's merge (cell.analysis.merge.merge_bins): the voxels the views'
moved bins fall into, found in a hash of their keys, numbered in the order of their keys, and the bins'
weighted sums added up per voxel, view after view.

Written by hand because no library does a weighted voxel merge keyed this way at this speed. The NumPy
formulation (main before issue 16's item 2: a grid numbering every view's kinematic voxels, then per view the
moved means' keys looked up, ``np.unique`` of the keys that moved, a stable argsort of the view's bins by
merged point and ``np.add.reduceat`` per sum) took 1.10 s on the demo pillar's 12 views and held the
numbering of every kinematic voxel through the registration (12.6M at 5 MP); ``np.unique(...,
return_inverse=True)`` of all the bins' keys alone (the sort any group-by, NumPy's, pandas' or SciPy's, makes)
costs about a third of that. Here a first pass over each view's bins marks the voxels they move into (a hash
of bricks of 1 x 8 x 8 voxels: a view's bins come in the order of their keys, x, then y, then z, so along a
slice x = const of its surface, and the next bin is most often in the last one's brick), one sort of the
occupied bricks' keys numbers the voxels, and a second pass adds each view's sums (its bins' bricks sought in
the entries sorted by key, from the previous bin's: fewer cache misses than the hash's).

The sums are NumPy's to the bit (the registration is compared bit for bit across versions and resumes): a
view's bins in one voxel add as ``np.add.reduceat`` adds a segment (its first value, plus NumPy's pairwise
sum of the rest, which starts from -0.0), and each view's sum is added to the voxel's in view order.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from llvmlite import ir  # type: ignore[import-untyped]
from numba import types
from numba.core import cgutils
from numba.cpython.unsafe.numbers import trailing_zeros
from numba.extending import intrinsic

# a voxel's cell per axis + _HALF, as cell.analysis.merge.grid_keys keys it, in KEY_BITS bits
from cell.analysis.merge import _HALF, KEY_BITS

# a brick's key: x, y // 8, z // 8 (y // 8 and z // 8 below 2^(KEY_BITS - 3)), x the most significant
_BRICK_Y_BITS = KEY_BITS - 3
# a brick: 1 x 8 x 8 voxels along x, y, z. In the first pass's hash an entry is its key (-1: an empty entry)
# and which of its voxels are occupied (a bit each, y % 8 * 8 + z % 8): 16 bytes, so the hash of the demo
# pillar's 281k bricks (8 MB) stays in the last-level cache. The second pass's bricks, in the order of their
# keys, add the number of the first occupied voxel of each of their rows (y) in the order of the keys, two
# int32 a word (~7 occupied voxels a brick on the demo pillar): 48 bytes a brick.
_KEY, _OCCUPIED, _ROWS = 0, 1, 2
BRICK_WORDS = 6  # int64 words of a brick of the second pass
_POP = np.array([bin(i).count("1") for i in range(256)], dtype=np.int64)  # set bits of a byte
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)  # Fibonacci hashing's multiplier
OUT_OF_RANGE = -2  # a moved mean beyond the key's +-2^20 voxels (or not finite)
FULL = -1  # the hash needs more room
_AHEAD = 16  # bins ahead whose hash entry the first pass asks the CPU for


@intrinsic
def _prefetch(typingctx, table, h):
    """Ask the CPU for the cache line of ``table[h, 0]`` (a 2-D C array) without waiting for it: LLVM's
    prefetch, which numba does not offer. The first pass's bins meet their bricks' hash entries in no order
    the CPU can foresee (a view's bins share a brick ~3.3 at a time, and the entries are spread over 8 MB on
    the demo pillar); asked for 16 bins ahead, the pass took 0.07 s instead of 0.095 s on the demo's bins."""

    def codegen(context, builder, sig, args):
        aryty = sig.args[0]
        ary = context.make_array(aryty)(context, builder, args[0])
        zero = context.get_constant(types.intp, 0)
        ptr = cgutils.get_item_pointer(context, builder, aryty, ary, [args[1], zero], wraparound=False)
        i8p, i32 = ir.IntType(8).as_pointer(), ir.IntType(32)
        fnty = ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32])
        fn = builder.module.declare_intrinsic("llvm.prefetch", [i8p], fnty)
        builder.call(fn, [builder.bitcast(ptr, i8p), i32(0), i32(3), i32(1)])  # a read, kept in all caches
        return context.get_dummy_value()

    return types.void(table, h), codegen


@nb.njit(cache=True, nogil=True)
def _shift(size):
    """64 - log2(size): Fibonacci hashing's shift for a hash of ``size`` (a power of two) slots."""
    bits = 0
    while (1 << bits) < size:
        bits += 1
    return np.uint64(64 - bits)


@nb.njit(cache=True, nogil=True)
def _moved(mean, i, T):
    """Bin ``i``'s mean (mm) moved by ``T`` (4x4), summed as cell.geometry.transform_points's einsum sums
    (x and z first: the same points to the bit, checked on the demo pillar's 3.8M bins; the merge needs
    only that each bin moves the same way in both passes and every time)."""
    x, y, z = mean[i, 0], mean[i, 1], mean[i, 2]
    return (
        (x * T[0, 0] + z * T[0, 2]) + y * T[0, 1] + T[0, 3],
        (x * T[1, 0] + z * T[1, 2]) + y * T[1, 1] + T[1, 3],
        (x * T[2, 0] + z * T[2, 2]) + y * T[2, 1] + T[2, 3],
    )


@nb.njit(cache=True, nogil=True)
def _cell(px, py, pz, voxel_mm):
    """The voxel of a point (mm; floor(p / voxel_mm) + 2^20 per axis: NumPy's voxels to the bit, as
    cell.analysis.merge.grid_keys has them): its brick's key (x, y // 8, z // 8) and its place in the brick;
    a key of -1 when out of range or not finite."""
    x, y, z = px / voxel_mm, py / voxel_mm, pz / voxel_mm
    if not (-_HALF <= x < _HALF and -_HALF <= y < _HALF and -_HALF <= z < _HALF):
        return np.int64(-1), np.int64(0)
    cx = np.int64(np.floor(x)) + _HALF
    cy = np.int64(np.floor(y)) + _HALF
    cz = np.int64(np.floor(z)) + _HALF
    brick = (cx << (2 * _BRICK_Y_BITS)) | ((cy >> 3) << _BRICK_Y_BITS) | (cz >> 3)
    return brick, ((cy & 7) << 3) | (cz & 7)


@nb.njit(cache=True, nogil=True)
def _find(table, brick, shift, mask):
    """The hash entry of ``brick``: its own, or the empty one where it would go."""
    h = np.int64((np.uint64(brick) * _GOLDEN) >> shift)
    while table[h, _KEY] != brick and table[h, _KEY] >= 0:
        h = (h + 1) & mask
    return h


@nb.njit(cache=True, nogil=True)
def insert(table, n_bricks, mean, T, kept, voxel_mm, start):
    """Mark the voxels of the bins' means ``mean[start:]`` ((N, 3) mm) moved by ``T`` (4x4), those ``kept``
    (all when empty), occupied in their bricks' entries of the hash ``table`` (H, 2), H a power of two.
    Returns the bricks now held and where it stopped: len(mean), or earlier when the hash is 3/4 full (FULL:
    grow it, :func:`rehash`, and call again from there) or at a mean out of range (OUT_OF_RANGE)."""
    size = len(table)
    mask = size - 1
    shift = _shift(size)
    every = len(kept) == 0
    n = len(mean)
    last, h = np.int64(-1), np.int64(-1)
    for i in range(start, n):
        if i + _AHEAD < n:  # (a bin's brick found twice: cheaper than waiting for its entry)
            ax, ay, az = _moved(mean, i + _AHEAD, T)
            ahead, _ = _cell(ax, ay, az, voxel_mm)
            if ahead >= 0:
                _prefetch(table, np.int64((np.uint64(ahead) * _GOLDEN) >> shift))  # type: ignore[call-arg]
        if not every and not kept[i]:
            continue
        px, py, pz = _moved(mean, i, T)
        brick, at = _cell(px, py, pz, voxel_mm)
        if brick < 0:
            return n_bricks, i, OUT_OF_RANGE
        if brick != last:
            h = _find(table, brick, shift, mask)
            if table[h, _KEY] < 0:
                if 4 * (n_bricks + 1) > 3 * size:
                    return n_bricks, i, FULL
                table[h, _KEY] = brick
                table[h, _OCCUPIED] = 0
                n_bricks += 1
            last = brick
        table[h, _OCCUPIED] |= np.int64(1) << at
    return n_bricks, n, 0


@nb.njit(cache=True, nogil=True)
def rehash(table, new_table):
    """Move the hash's bricks into the empty (keys -1), larger hash ``new_table``."""
    size = len(new_table)
    mask = size - 1
    shift = _shift(size)
    for h in range(len(table)):
        if table[h, _KEY] >= 0:
            g = _find(new_table, table[h, _KEY], shift, mask)
            new_table[g, :] = table[h, :]


@nb.njit(cache=True, nogil=True)
def number(table, by_key, bricks):
    """The second pass's ``bricks`` (len(by_key), BRICK_WORDS) from the hash ``table``'s entries ``by_key``
    (in the order of their keys): their keys, occupied voxels and the numbers of their rows' first voxels,
    the occupied voxels numbered in the order of their keys (x, then y, then z: the bricks of one x and one
    y // 8 side by side, whose voxels go row y by row y). Returns how many voxels."""
    for j in range(len(by_key)):
        bricks[j, _KEY] = table[by_key[j], _KEY]
        bricks[j, _OCCUPIED] = table[by_key[j], _OCCUPIED]
    m = 0
    g0 = 0
    while g0 < len(bricks):
        g1 = g0 + 1
        row = bricks[g0, _KEY] >> _BRICK_Y_BITS
        while g1 < len(bricks) and bricks[g1, _KEY] >> _BRICK_Y_BITS == row:
            g1 += 1
        for y in range(8):
            for j in range(g0, g1):
                word = _ROWS + (y >> 1)
                if y & 1:
                    bricks[j, word] |= np.int64(m) << 32
                else:
                    bricks[j, word] = np.int64(m)
                m += _POP[(bricks[j, _OCCUPIED] >> (8 * y)) & 255]
        g0 = g1
    return m


@nb.njit(cache=True, nogil=True)
def united(old, table, by_key, out):
    """``out`` (>= len(old) + len(by_key), 2): the bricks ``old`` (:func:`number`'s, in the order of their
    keys) and the hash ``table``'s entries ``by_key`` (in the order of their keys: a view's bricks), in the
    order of their keys, a brick of both with the voxels of both: a hash's entries for :func:`number`.
    Returns how many (the bricks of a partial merge and its last view's, without hashing the partial's
    again or sorting them all)."""
    i, j, n = 0, 0, 0
    while i < len(old) or j < len(by_key):
        if j == len(by_key) or (i < len(old) and old[i, _KEY] < table[by_key[j], _KEY]):
            out[n, _KEY], out[n, _OCCUPIED] = old[i, _KEY], old[i, _OCCUPIED]
            i += 1
        elif i == len(old) or table[by_key[j], _KEY] < old[i, _KEY]:
            out[n, _KEY], out[n, _OCCUPIED] = table[by_key[j], _KEY], table[by_key[j], _OCCUPIED]
            j += 1
        else:
            out[n, _KEY], out[n, _OCCUPIED] = old[i, _KEY], old[i, _OCCUPIED] | table[by_key[j], _OCCUPIED]
            i += 1
            j += 1
        n += 1
    return n


@nb.njit(cache=True, nogil=True)
def spread(moved, wsum_old, sums_old, count_old, given_old, wsum, sums, count, given):
    """A partial merge's voxel sums (``*_old``, (m_old,), ``sums_old`` (m_old, 3)) at their voxels' new
    numbers ``moved`` (ascending) in ``wsum``, ``sums``, ``count``, ``given`` (m >= m_old, empty), the new
    voxels' set to 0: the values copied bit for bit, in one pass."""
    j = 0
    for i in range(len(moved) + 1):
        r = moved[i] if i < len(moved) else len(wsum)
        while j < r:
            wsum[j] = 0.0
            sums[j, 0], sums[j, 1], sums[j, 2] = 0.0, 0.0, 0.0
            count[j], given[j] = 0, 0
            j += 1
        if i < len(moved):
            wsum[r] = wsum_old[i]
            sums[r, 0], sums[r, 1], sums[r, 2] = sums_old[i, 0], sums_old[i, 1], sums_old[i, 2]
            count[r], given[r] = count_old[i], given_old[i]
            j = r + 1


@nb.njit(cache=True, nogil=True)
def remap(moved, rows):
    """rows[i] = moved[rows[i]], in place: a view's merged points' rows in the new numbering."""
    for i in range(len(rows)):
        rows[i] = moved[rows[i]]


@nb.njit(cache=True, nogil=True)
def renumber(old, new, moved):
    """``moved[i]``: the number in the bricks ``new`` of voxel i of the bricks ``old`` (:func:`number`'s,
    both in the order of their keys; every brick of ``old`` is in ``new`` with at least its voxels): where a
    partial merge's voxels go when a view adds its own (cell.analysis.merge.PartialMerge). Both numberings
    are in the order of the voxels' keys, so ``moved`` ascends."""
    j = 0
    for g in range(len(old)):
        while new[j, _KEY] != old[g, _KEY]:
            j += 1
        occupied = old[g, _OCCUPIED]
        for y in range(8):
            byte = (occupied >> (8 * y)) & 255
            if byte == 0:
                continue
            i = (old[g, _ROWS + (y >> 1)] >> (32 * (y & 1))) & 0xFFFFFFFF
            for z in range(8):
                if (byte >> z) & 1:
                    moved[i] = _number(new, j, (y << 3) | z)
                    i += 1


@nb.njit(cache=True, nogil=True)
def _seek(bricks, brick, j):
    """The row of ``brick`` (present) in ``bricks`` (the hash's entries in the order of their keys), searched
    from row ``j`` outwards (galloping, then halving): a view's bins come in the order of their keys, so the
    next brick is most often a few rows on, and the rows between are in cache."""
    n = len(bricks)
    j = min(max(j, 0), n - 1)
    if bricks[j, _KEY] == brick:
        return j
    if bricks[j, _KEY] < brick:
        lo, step, hi = j, 1, j + 1
        while hi < n and bricks[hi, _KEY] < brick:
            lo, step = hi, 2 * step
            hi = j + step
        lo, hi = lo + 1, min(hi, n - 1)
    else:
        hi, step, lo = j, 1, j - 1
        while lo >= 0 and bricks[lo, _KEY] > brick:
            hi, step = lo, 2 * step
            lo = j - step
        lo = max(lo, 0)
    while lo < hi:  # the first row whose key is not below
        mid = (lo + hi) // 2
        if bricks[mid, _KEY] < brick:
            lo = mid + 1
        else:
            hi = mid
    return lo


@nb.njit(cache=True, nogil=True)
def _number(table, h, at):
    """The number of voxel ``at`` (y % 8 * 8 + z % 8, occupied) of the brick in entry ``h`` of ``table``."""
    y, z = at >> 3, at & 7
    first = (table[h, _ROWS + (y >> 1)] >> (32 * (y & 1))) & 0xFFFFFFFF
    return first + _POP[(table[h, _OCCUPIED] >> (8 * y)) & ((1 << z) - 1)]


@nb.njit(cache=True, nogil=True, inline="always")
def _merged_row(bricks, mean, T, voxel_mm, i, last, h):
    """Bin ``i``'s merged point (its voxel's number in ``bricks``), its moved mean (mm), and its brick's key
    and row, sought from the previous bin's (``last``, ``h``): the second pass's lookup of every bin."""
    px, py, pz = _moved(mean, i, T)
    brick, at = _cell(px, py, pz, voxel_mm)
    if brick != last:
        h = _seek(bricks, brick, h)
    return _number(bricks, h, at), px, py, pz, brick, h


@nb.njit(cache=True, nogil=True)
def _pairwise(x, n):
    """NumPy's pairwise sum of ``x[:n]`` (numpy/_core/src/umath/loops_utils.h.src) for 8 <= n <= 128 (its
    unrolled branch; fewer are summed in order where they are met), which is all a voxel can get of one view:
    its bins are distinct voxels of the same size, at most 27 of which a rigidly moved voxel meets."""
    if n > 128:
        raise ValueError("merge: more than 128 bins of one view in one voxel")
    r = x[:8].copy()
    i = 8
    while i < n - (n % 8):
        for j in range(8):
            r[j] += x[i + j]
        i += 8
    res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]))
    while i < n:
        res += x[i]
        i += 1
    return res


@nb.njit(cache=True, nogil=True)
def add_view(
    bricks, mean, T, kept, voxel_mm, w, c, wu, wsum, sums, count, given, local, seen, many, first, rest
):
    """Add one view's bins (means ``mean`` (N, 3) mm moved by ``T``, weight sums ``w``, point counts ``c``,
    weighted u sums ``wu``), those ``kept`` (all when empty), to the merged voxels' sums ``wsum`` (M,),
    ``sums`` (M, 3) (of w * mean), ``count`` and ``given`` (views a voxel has); the voxels' numbers in
    ``bricks`` (:func:`number`). Scratch, reused from view to view (new pages cost more than the sums) and
    left as found: ``local`` (M,) int32 all -1 (a merged point's place t among the view's, in the order its
    bins meet them), ``seen`` (ceil(M / 64),) uint64 all 0 (a bit a merged point the view has); ``many`` (>=
    N,) int32, ``first`` and ``rest`` (>= N, 5): a point t's bins, its first bin's w, w x, w y, w z, wu and
    NumPy's pairwise sum of the others' (while fewer than 8; a row of ``rest`` is written only when a
    point has more than one of the view's bins, a few in a hundred: the bytes each bin moves are what the
    second pass costs). Returns the merged points the view has (ascending), its weight sum and weighted u
    sum at each."""
    n = len(w)
    every = len(kept) == 0
    nt = 0
    lo, hi = len(wsum), -1
    last, h = np.int64(-1), np.int64(0)
    for i in range(n):
        if not every and not kept[i]:
            continue
        r, px, py, pz, last, h = _merged_row(bricks, mean, T, voxel_mm, i, last, h)
        wi = w[i]
        count[r] += c[i]  # (integers: in any order)
        t = local[r]
        if t < 0:
            t = nt
            local[r] = t
            nt += 1
            seen[r >> 6] |= np.uint64(1) << np.uint64(r & 63)
            lo, hi = min(lo, r), max(hi, r)
            many[t] = 1
            first[t, 0], first[t, 1], first[t, 2] = wi, wi * px, wi * py
            first[t, 3], first[t, 4] = wi * pz, np.float64(wu[i])
            continue
        many[t] += 1
        if many[t] == 2:  # (-0.0 + x is x, to the bit)
            rest[t, 0], rest[t, 1], rest[t, 2] = wi, wi * px, wi * py
            rest[t, 3], rest[t, 4] = wi * pz, np.float64(wu[i])
        else:
            rest[t, 0] += wi
            rest[t, 1] += wi * px
            rest[t, 2] += wi * py
            rest[t, 3] += wi * pz
            rest[t, 4] += np.float64(wu[i])
    # a merged point with more than 8 of the view's bins: NumPy sums the others pairwise (never on the
    # demo pillar, whose refinements are tens of um); summed again so, from its bins in order
    for t in range(nt):
        if many[t] > 8:
            _sum_pairwise(bricks, mean, T, kept, voxel_mm, w, wu, local, rest, t, many[t])
    rows = np.empty(nt, np.int32)
    w_rows = np.empty(nt)
    wu_rows = np.empty(nt)
    k = 0
    for word in range(lo >> 6, (hi >> 6) + 1):  # the view's merged points in order
        bits = seen[word]
        seen[word] = 0
        while bits:
            r = (word << 6) + np.int64(trailing_zeros(bits))  # type: ignore[call-arg]  # (an intrinsic: cttz)
            bits &= bits - np.uint64(1)
            t = local[r]
            local[r] = -1
            if many[t] == 1:
                s0, s4 = first[t, 0], first[t, 4]
                sums[r, 0] += first[t, 1]
                sums[r, 1] += first[t, 2]
                sums[r, 2] += first[t, 3]
            else:
                s0, s4 = first[t, 0] + rest[t, 0], first[t, 4] + rest[t, 4]
                sums[r, 0] += first[t, 1] + rest[t, 1]
                sums[r, 1] += first[t, 2] + rest[t, 2]
                sums[r, 2] += first[t, 3] + rest[t, 3]
            wsum[r] += s0
            given[r] += 1
            rows[k], w_rows[k], wu_rows[k] = r, s0, s4
            k += 1
    return rows, w_rows, wu_rows


@nb.njit(cache=True, nogil=True)
def _sum_pairwise(bricks, mean, T, kept, voxel_mm, w, wu, local, rest, t, many):
    """rest[t] again as NumPy sums it: the pairwise sums of all but the first of the ``many`` bins (in order)
    whose merged point is the view's t-th."""
    every = len(kept) == 0
    idx = np.empty(many, np.int64)
    k, last, h = 0, np.int64(-1), np.int64(0)
    for i in range(len(w)):
        if not every and not kept[i]:
            continue
        r, _, _, _, last, h = _merged_row(bricks, mean, T, voxel_mm, i, last, h)
        if local[r] == t:
            idx[k] = i
            k += 1
    vals = np.empty(many - 1)
    for q in range(5):
        for j in range(1, many):
            i = idx[j]
            wi = w[i]
            p = _moved(mean, i, T)
            vals[j - 1] = wi if q == 0 else (np.float64(wu[i]) if q == 4 else wi * p[q - 1])
        rest[t, q] = _pairwise(vals, many - 1)


@nb.njit(cache=True, nogil=True)
def add_squares(var, rows, x):
    """var[rows] += x * x (``rows`` distinct): NumPy's ``var[rows] += np.square(x)`` to the bit."""
    for j in range(len(rows)):
        var[rows[j]] += x[j] * x[j]
