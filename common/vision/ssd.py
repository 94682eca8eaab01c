"""SSD correlation search, Eq. (1) of the paper.

    S(c, d) = sum_{j=-n..n} sum_{i=-n..n} W(i, j) [I_t(c + (i, j)) - I_{t+1}(c + d + (i, j))]^2

For each feature at c in frame t, every displacement d whose centre c + d lies in the search
window (half-width SEARCH_SIZE // 2, centred at the predicted position) is scored, and the new
position is the argmin. n = CORR_SIZE // 2.

Two searches return the same argmin (ties going to the first in row-major order, like
``cv2.minMaxLoc``), and so the same positions, S and losses (``track_ssd(..., search=...)``,
``TrackerParams.search``):

``"exhaustive"``, the paper's plain Eq. (1) (:func:`_search_full`)
    scores every displacement in full: (2s+1)^2 (2n+1)^2 terms per feature, so its cost grows
    with both SEARCH_SIZE and CORR_SIZE and with their product, as the paper's Table 3 and
    sensitivity analysis assume. Vectorised over the displacements, integer arithmetic.

``"pruned"`` (default, :func:`_search`)
    is exact too but scores only a handful of displacements, so its cost barely grows with
    CORR_SIZE:

    * multilevel successive elimination (Gao et al. 2000): a lower bound of S for every
      displacement from the row sums of the windows, computed with vector instructions
      (:func:`_bounds`; the row sums of frame t+1 once per frame, :func:`_row_sums`);
    * the position nearest the prediction and its 8 neighbours are scored first: the minimum
      is among them for ~97 % of features, and the bounds then rule out all other
      displacements;
    * a displacement's sum is abandoned as soon as its partial sum exceeds the best so far (the
      terms are non-negative, so it can no longer win); all arithmetic is in integers.

On ~100 features of a 256x256 real frame (one core, ``vistrack bench tracker``): (15, 9) ~41
us pruned, ~165 us exhaustive; the reference windows (50, 30) ~0.55 ms pruned, ~12 ms
exhaustive.

Performance notes (numba compiles with LLVM's loop vectoriser only, no SLP vectoriser): the hot
loops are long, contiguous and indexed from 0 by the loop variable (offsets go into slices: a
computed index could be negative for all numba knows, and its per-element fix-up turns vector
loads into gathers), and their lengths are padded to a multiple of VEC so that no scalar
remainder runs.

Sub-pixel refinement minimises the same Eq. (1) over a continuous displacement (Gauss-Newton
from the integer minimum, :func:`_refine`), its residual corrected for what bilinear
interpolation adds at a fraction of a pixel, to the third order. A parabola through the
minimum and its neighbours, the classic shortcut, is biased towards integer positions ("pixel
locking"): on the Middlebury sequences its median end-point error was 2 to 4 times that of
Gauss-Newton, so it is only the fallback.

:func:`_search_level` also says why a search found no trustworthy minimum (the ``status``
codes below); :mod:`.pyramid` builds the coarse-to-fine tracker on it.
"""

from __future__ import annotations

from typing import Any

import numba as nb
import numpy as np
from llvmlite import ir
from numba.core import cgutils, types
from numba.cpython.unsafe.numbers import trailing_zeros
from numba.extending import intrinsic, overload

from ..params import SEARCH_KINDS

#: ``nb.njit`` options of the kernels that neither allocate nor keep an array: cached, without
#: the GIL, and without numba's runtime (NRT). With it, every view a kernel makes (a slice, a
#: row, a level of a pyramid, an element of a tuple of arrays) takes a reference: an atomic
#: increment and decrement of its buffer's count, that LLVM cannot remove across the kernels'
#: branches. perf on the bench's frames put 32 % of the (15, 9) search's time and 37 % of the
#: default tracker's in NRT_incref and NRT_decref; without them, 41.5 -> 35.9 us and 224 ->
#: 143 us a frame pair, the same outputs bit for bit. A kernel compiled so must not call one
#: that returns an array (its reference would never be released).
NO_NRT: dict[str, Any] = {"cache": True, "nogil": True, "_nrt": False}

WEIGHT_SCALE = 64  # Gaussian weights are integers with this peak, so sums stay exact


def window_weights(kind: str, n: int) -> np.ndarray:
    """W(i, j) of Eq. (1) as a (2n+1, 2n+1) int32 array.

    ``uniform``: all ones. ``gaussian``: ``round(64 exp(-(i^2 + j^2) / (2 sigma^2)))`` with
    sigma = max(n / 2, 0.5) px, at least 1, so the window's edge still counts a little.
    """
    if n < 0:
        raise ValueError(f"n={n} must be >= 0")
    if kind == "uniform":
        return np.ones((2 * n + 1, 2 * n + 1), np.int32)
    if kind == "gaussian":
        sigma = max(n / 2.0, 0.5)
        r = np.arange(-n, n + 1, dtype=np.float64)
        g = np.exp(-(r[:, None] ** 2 + r[None, :] ** 2) / (2 * sigma * sigma))
        return np.maximum(np.rint(WEIGHT_SCALE * g), 1).astype(np.int32)
    raise ValueError(f"weights={kind!r} is not allowed: use uniform or gaussian")


# Hot loops run over arrays padded to a multiple of VEC elements: LLVM's vector loop takes up to
# 4 x 32 lanes a trip, and a remainder would otherwise run element by element.
VEC = 128
# the bounds of a search row are padded to a multiple of this many displacements
LANES = 16
# pixels summed per block in _row_sums: small enough that its buffers stay in the L1 cache
ROW_BLOCK = 4096
# the sums of an exhaustive search are padded to a multiple of this many: an int32 vector loop
# takes 4 x 16 lanes a trip, and padding to VEC cost small searches up to 20 % more
FULL_VEC = 64
# above any S of Eq. (1) with int32 weights (65^2 px * 255^2 * 2^31 < 2^62); typed, so that
# a kernel given it compiles the signature it has when given an int64 bound (a plain int
# literal is a type of its own to numba: a second compile)
BIG = np.int64(1 << 62)
INT32_MAX = (1 << 31) - 1


@nb.njit(cache=True, nogil=True)
def _row_sums(curr, n, s, centers, out, bufs):  # pragma: no cover - numba
    """Row sums of the correlation window over frame t+1, for the bounds of :func:`_bounds`.

    ``out[q] = sum_{i<m} curr.flat[q + i]`` (int16: at most 65 * 255): the sum over the window
    row whose leftmost pixel is flat index q, so the window centred at (x, y) has its row sum at
    ``y * w + x - n``. Where q is within m - 1 of a row's end the sum runs on into the next row:
    such entries belong to no valid window and only fill vector lanes past a search's edge.

    Computed once per frame pair and shared by all features, whose search areas overlap, in
    blocks of rows: only the blocks that a search reads (its rows, and the next ones, into
    which the vector lanes past its right edge run) are computed, the others left unread. The
    sum of m terms is built by doubling (P_2k[q] = P_k[q] + P_k[q + k], summing the P_k of m's
    binary digits): O(log m) long, vectorised passes per pixel instead of m; where m = 3b, from
    the sums of 3 (P_3, one pass) b of them 3 apart (2 passes for m = 9). ``bufs``: (2,
    ROW_BLOCK + w + 2m) int16 scratch.
    """
    h, w = curr.shape
    m = 2 * n + 1
    total = h * w
    flat = curr.ravel()
    last = total - m + 1  # entries from here on have no full window: zero
    # the entries a search reads in each of its rows, from its leftmost window's
    span = 2 * s + LANES
    if centers.shape[0] * (2 * s + m) * (span + m) * 4 < total:
        # few searches (the few features of a frame that do not follow their prediction):
        # their own entries only. Blocks of whole rows cost ~4 us a call at 256x256 for a
        # single search, zeroing the rest as much again; a sliding sum along the flat frame
        # a row, ~1 us (one dependent chain); LANES sums at once, ~0.25 us
        out[total:] = 0
        for f in range(centers.shape[0]):
            cx = centers[f, 0]
            cy = centers[f, 1]
            x0 = max(cx - s, n) - n
            for y in range(max(cy - s - n, 0), min(cy + s + n + 1, h)):
                q0 = y * w + x0
                q1 = min(q0 + span, last)
                if q1 <= q0:
                    continue
                # LANES sums at once where their windows lie inside the frame (the lanes
                # past q1 that this writes are true sums too, of windows no search here
                # reads); the rest, near the frame's end, a sliding sum
                q = q0
                while q < q1 and q + LANES + m - 1 <= total:
                    _window_sums(out, q, flat, q, m)
                    q += LANES
                if q < q1:
                    acc = np.int32(0)
                    for i in range(m):
                        acc += np.int32(flat[q + i])
                    for r in range(q, q1 - 1):
                        out[r] = acc
                        acc += np.int32(flat[r + m]) - np.int32(flat[r])
                    out[q1 - 1] = acc
                out[q1:q0 + span] = 0  # past the last full window
        return
    rows = max(ROW_BLOCK // w, 1)
    need = np.zeros(h // rows + 1, np.bool_)
    # a search's lanes run at most LANES entries past its rightmost window: into the next
    # row, or further in a frame narrower than LANES
    spill = 1 + LANES // w
    for f in range(centers.shape[0]):
        # the blocks of rows the search reads, marked as one slice: a loop over the rows
        # themselves (a division a row) cost ~2 us a frame pair at 256x256
        cy = centers[f, 1]
        y0 = max(cy - s - n, 0)
        y1 = min(cy + s + n + 1 + spill, h)
        if y1 > y0:
            need[y0 // rows:(y1 - 1) // rows + 1] = True
    for y0 in range(0, h, rows):
        q0 = y0 * w
        q1 = min(q0 + rows * w, total)
        dst = out[q0:q1]
        if not need[y0 // rows]:
            continue
        if q0 >= last:
            dst[:] = 0
            continue
        ln = min(q1, last) - q0
        avail = min(ln + m - 1, total - q0)  # pixels the block's windows reach
        src = flat[q0:q0 + avail]
        if m % 3 == 0:
            # m = 3b (9, 15, 21, ...; the default window): the sums of 3 pixels in one pass,
            # then b of them 3 apart, three in a pass: 2 passes for m = 9 where doubling
            # takes 4 (row sums ~1/5 of the (15, 9) search)
            reach = ln + m - 3  # the 3-pixel sums the block's windows use
            p3 = bufs[0, :reach]
            a8 = src[0:reach]
            b8 = src[1:1 + reach]
            c8 = src[2:2 + reach]
            for q in range(reach):
                p3[q] = np.int16(a8[q]) + np.int16(b8[q]) + np.int16(c8[q])
            if m == 3:
                for q in range(ln):
                    dst[q] = p3[q]
            else:
                t0 = p3[0:ln]
                t1 = p3[3:3 + ln]
                t2 = p3[6:6 + ln]
                for q in range(ln):
                    dst[q] = t0[q] + t1[q] + t2[q]
                for k in range(9, m, 3):
                    tk = p3[k:k + ln]
                    for q in range(ln):
                        dst[q] += tk[q]
            dst[ln:] = 0
            continue
        # m is odd: P_1, the pixels themselves, is the first term, added with the second
        # (not copied first: a pass fewer)
        if m == 1:
            for q in range(ln):
                dst[q] = src[q]
        alone = True  # dst holds nothing yet
        off = 1
        span = 1
        rem = m >> 1
        par = 0  # which buffer of bufs holds P_span (for span > 1)
        while rem:
            # P_2span from P_span; P_1 is read from the pixels directly
            avail -= span
            nxt = bufs[1 - par, :avail]
            if span == 1:
                a8 = src[:avail]
                b8 = src[1:1 + avail]
                for q in range(avail):
                    nxt[q] = np.int16(a8[q]) + np.int16(b8[q])
            else:
                a = bufs[par, :avail]
                b = bufs[par, span:span + avail]
                for q in range(avail):
                    nxt[q] = a[q] + b[q]
            par = 1 - par
            span *= 2
            if rem & 1:
                seg = bufs[par, off:off + ln]
                if alone:
                    for q in range(ln):
                        dst[q] = np.int16(src[q]) + seg[q]
                    alone = False
                else:
                    for q in range(ln):
                        dst[q] += seg[q]
                off += span
            rem >>= 1
        dst[ln:] = 0
    out[total:] = 0


def _pairs_typed(a, b) -> bool:
    """Whether ``a`` and ``b`` are 1-D C arrays, ``b`` int16 (the row sums)."""
    return all(isinstance(x, types.Array) and x.ndim == 1 and x.layout == "C" for x in (a, b)) \
        and b.dtype == types.int16


def _add_pairs(builder, v):
    """The vector ``v`` (2k lanes) with each even lane added to the odd lane after it (k
    lanes): the pairs of a 16-bit multiply-add (vpmaddwd, vpdpwssd) when ``v`` holds 32-bit
    products of 16-bit values, the pattern LLVM turns into that instruction."""
    half = v.type.count // 2
    lanes = ir.VectorType(ir.IntType(32), half)
    return builder.add(
        builder.shuffle_vector(v, v, ir.Constant(lanes, list(range(0, 2 * half, 2)))),
        builder.shuffle_vector(v, v, ir.Constant(lanes, list(range(1, 2 * half, 2)))))


@intrinsic
def _copy_pair(typingctx, dst, doff, src, soff, step):  # pragma: no cover - numba
    """``dst[doff + 2 i] = src[soff + i]``, ``dst[doff + 2 i + 1] = src[soff + step + i]``
    for i < LANES (int16, 1-D C arrays, the ranges inside them: unchecked): two rows of row
    sums interleaved, the layout of :func:`_pair_squares`."""
    if not (_pairs_typed(dst, src) and dst.dtype == types.int16
            and all(isinstance(t, types.Integer) for t in (doff, soff, step))):
        return None
    sig = types.void(dst, doff, src, soff, step)

    def codegen(context, builder, signature, args):
        tys = signature.args
        row = ir.VectorType(ir.IntType(16), LANES)
        at = context.cast(builder, args[3], tys[3], types.intp)
        down = builder.add(at, context.cast(builder, args[4], tys[4], types.intp))
        a, b = (builder.load(builder.bitcast(_flat_at(context, builder, tys[2], args[2], o),
                                             row.as_pointer()), align=2) for o in (at, down))
        mix = builder.shuffle_vector(a, b, ir.Constant(ir.VectorType(ir.IntType(32), 2 * LANES),
                                                       [k for i in range(LANES)
                                                        for k in (i, LANES + i)]))
        out = _flat_at(context, builder, tys[0], args[0],
                       context.cast(builder, args[1], tys[1], types.intp))
        builder.store(mix, builder.bitcast(out, ir.VectorType(ir.IntType(16), 2 * LANES)
                                           .as_pointer()), align=2)
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def _pair_squares(typingctx, acc, total, pairs, width, temps, m):  # pragma: no cover
    """``acc[q] = sum_{j < m} (temps[j] - I_j[q])^2`` for q < ``total`` (a multiple of
    LANES), ``I_j[q] = pairs[2 ((j - j % 2) width + q) + j % 2]``: the bounds of a uniform
    window (:func:`_bounds`), ``pairs`` the search area's row sums as :func:`_copy_pair` lays
    them out (rows ``width`` lanes long, each row interleaved with the next), ``temps`` the
    template's row sums as int16 (one more, ignored, where m is odd: that row's odd lanes are
    masked out); ``acc`` int32, all 1-D C, read inside them (unchecked).

    Two rows' terms of a lane are one 16-bit multiply-add (vpmaddwd, the pattern of
    :func:`_pixel_dots`), where the plain loop widened each difference to 32 bits and squared
    it with vpmulld; a lane's terms are added in a register and stored once. The differences
    must fit int16 and the sums int32 (:func:`_bound_caps`' ``unit``)."""
    if not (_pairs_typed(acc, pairs) and _pairs_typed(acc, temps) and acc.dtype == types.int32
            and all(isinstance(t, types.Integer) for t in (total, width, m))):
        return None
    sig = types.void(acc, total, pairs, width, temps, m)

    def codegen(context, builder, signature, args):
        tys = signature.args
        i16 = ir.IntType(16)
        i32 = ir.IntType(32)
        pair = ir.VectorType(i16, 2 * LANES)
        out = ir.VectorType(i32, LANES)
        intp = context.get_value_type(types.intp)
        zero = context.get_constant(types.intp, 0)
        base = _flat_at(context, builder, tys[2], args[2], zero)
        tbase = builder.bitcast(_flat_at(context, builder, tys[4], args[4], zero),
                                i32.as_pointer())
        dst = _flat_at(context, builder, tys[0], args[0], zero)
        n = context.cast(builder, args[1], tys[1], types.intp)
        row = builder.mul(context.cast(builder, args[3], tys[3], types.intp),
                          ir.Constant(intp, 2))
        m = context.cast(builder, args[5], tys[5], types.intp)
        full = builder.lshr(m, ir.Constant(intp, 1))
        odd = builder.trunc(m, ir.IntType(1))
        splat = ir.Constant(ir.VectorType(i32, 2 * LANES), [0, 1] * LANES)
        last = ir.Constant(pair, [-1, 0] * LANES)

        def term(total, k, mask=None):
            # the pair k of rows (2 k, 2 k + 1): its templates broadcast, its row sums at
            # pairs[2 (2 k width + q)]
            t = builder.bitcast(builder.load(builder.gep(tbase, [k]), align=2),
                                ir.VectorType(i16, 2))
            t = builder.shuffle_vector(t, ir.Constant(ir.VectorType(i16, 2), None), splat)
            at = builder.gep(base, [builder.add(builder.add(q2, q2),
                                                builder.mul(k, builder.add(row, row)))])
            d = builder.sub(t, builder.load(builder.bitcast(at, pair.as_pointer()), align=2))
            if mask is not None:
                d = builder.and_(d, mask)
            d = builder.sext(d, ir.VectorType(i32, 2 * LANES))
            sq = builder.mul(d, d)
            return builder.add(total, _add_pairs(builder, sq))

        with cgutils.for_range_slice(builder, zero, n, ir.Constant(intp, LANES)) as (q2, _):
            sums = cgutils.alloca_once_value(builder, ir.Constant(out, [0] * LANES))
            with cgutils.for_range(builder, full, intp=intp) as loop:
                builder.store(term(builder.load(sums), loop.index), sums)
            with builder.if_then(odd):
                builder.store(term(builder.load(sums), full, last), sums)
            ptr = builder.bitcast(builder.gep(dst, [q2]), out.as_pointer())
            builder.store(builder.load(sums), ptr, align=4)
        return context.get_dummy_value()

    return sig, codegen


@nb.njit(**NO_NRT)
def _bounds(rs, w, trs, tpairs, wmin, caps, unit, lo_x, lo_y, nrow, ncol, width, n, blk,
            bnd):  # pragma: no cover - numba
    """Lower bounds (times m) of S for every displacement of one search.

    Multilevel successive elimination (Gao et al. 2000): by Cauchy-Schwarz on each row of the
    window, ``S >= sum_j wmin_j (T_j - I_j)^2 / m`` with T_j, I_j the row sums of template and
    window and wmin_j the row's smallest weight. ``bnd[r * width + k]`` is that sum for the
    window centred at (lo_x + k, lo_y + r) for k < ncol; the other lanes (up to the returned
    length, a multiple of VEC) hold junk.

    The row sums of the search area are first copied into ``blk`` with rows ``width`` long, so
    that each pass below is one long contiguous loop, which LLVM vectorises; a per-row loop of
    ``width`` lanes would cost more in loop overhead than in arithmetic. Returns the number of
    lanes computed. With ``unit`` the rows are copied in interleaved pairs and each lane's
    terms summed two at a time in 16-bit multiply-adds (:func:`_pair_squares`; ``tpairs``:
    the template's row sums ``trs`` as int16, one more entry, ignored): the (15, 9) search
    ~41.5 -> ~40 us a frame pair (old and new in turn, three rounds each; the same outputs
    bit for bit), the 32-bit squares' vpmulld having been a sixth of it.

    The bounds are int32 (twice the vector width of int64) whatever the window: each row's
    term is capped at ``caps[j]`` (:func:`_bound_caps`), so that their sum cannot overflow; a
    capped term is smaller, so the sum is still a lower bound (a weaker one only for windows
    so unlike the template that no best match comes near). With ``unit`` (uniform weights, no
    term able to reach its cap) the terms are summed as they are.

    Called by :func:`_search_level`, which allocates ``blk`` and ``bnd``. It was inlined
    there (called, the (15, 9) search took ~1 us a frame more: 67.5 against 66.5 us); inlined,
    its slices took numba's atomic reference counts in the search's loop, and called without
    numba's runtime (:data:`NO_NRT`) they take none.
    """
    m = 2 * n + 1
    x0 = lo_x - n
    total = (nrow * width + VEC - 1) // VEC * VEC
    if unit:
        # rows rr and rr + 1 of the search area's row sums interleaved (blk's row rr, 2 width
        # long), so that two window rows' terms of a lane are one 16-bit multiply-add
        for rr in range(nrow + m - 1):
            s0 = (lo_y - n + rr) * w + x0
            for c in range(0, width, LANES):
                _copy_pair(blk, 2 * (rr * width + c), rs, s0 + c, w)
        _pair_squares(bnd, total, blk, width, tpairs, m)
        return total
    # width is a multiple of LANES: the rows are copied LANES entries at a time, each a
    # vector load and store (_copy_block's loop, element by element: 10 % of the (15, 9)
    # search)
    for rr in range(nrow + m - 1):
        s0 = (lo_y - n + rr) * w + x0
        for c in range(0, width, LANES):
            _copy_lanes(blk, rr * width + c, rs, s0 + c)
    # three window rows a pass: a third of the loads and stores of bnd
    for q in range(total):
        bnd[q] = 0
    for j in range(0, m, 3):
        j1 = min(j + 1, m - 1)
        j2 = min(j + 2, m - 1)
        t0 = trs[j]
        t1 = trs[j1]
        t2 = trs[j2]
        r0 = blk[j * width:j * width + total]
        r1 = blk[j1 * width:j1 * width + total]
        r2 = blk[j2 * width:j2 * width + total]
        # rows past the window count with weight 0
        w1 = wmin[j1] if j + 1 < m else 0
        w2 = wmin[j2] if j + 2 < m else 0
        # the uniform terms never reach their caps: summed as before (_add_capped's branch
        # on a runtime flag cost the (50, 30) search ~10 %)
        if unit:
            _add_squares(bnd, total, t0, t1, t2, r0, r1, r2, wmin[j], w1, w2, j + 2 < m)
        else:
            _add_capped(bnd, total, t0, t1, t2, r0, r1, r2, wmin[j], w1, w2, caps[j], caps[j1],
                        caps[j2])
    return total


@nb.njit(cache=True, nogil=True)
def _bound_caps(wmin, uniform):  # pragma: no cover - numba
    """The caps of :func:`_bounds`' terms (each row's at most INT32_MAX // m, weight
    included, so that m of them fit int32) and whether uniform weights leave every term
    below its cap (``unit``: the terms are then summed as they are)."""
    m = wmin.shape[0]
    caps = np.empty(m, np.int64)
    for j in range(m):
        caps[j] = INT32_MAX // m // max(wmin[j], 1)
    top = m * 255  # the largest |T_j - I_j|
    return caps, uniform and top * top <= INT32_MAX // m


@nb.njit(cache=True, nogil=True, inline="always")
def _add_capped(acc, total, t0, t1, t2, r0, r1, r2, w0, w1, w2, c0, c1,
                c2):  # pragma: no cover - numba
    """:func:`_add_squares` for the bounds of weighted windows: each square capped at
    ``c0``, ``c1``, ``c2`` before its weight."""
    for q in range(total):
        d0 = t0 - np.int32(r0[q])
        d1 = t1 - np.int32(r1[q])
        d2 = t2 - np.int32(r2[q])
        acc[q] += w0 * min(d0 * d0, c0) + w1 * min(d1 * d1, c1) + w2 * min(d2 * d2, c2)


def _lanes_typed(dst, doff, src, soff) -> bool:
    """Whether the arguments of a lane copy (dst, doff, src, soff) are typed as it needs: C
    arrays, ``dst`` 1-D, integer offsets."""
    return (isinstance(dst, types.Array) and isinstance(src, types.Array) and dst.ndim == 1
            and dst.layout == "C" and src.layout == "C" and isinstance(doff, types.Integer)
            and isinstance(soff, types.Integer))


def _flat_at(context, builder, ty, arr, off):
    """A pointer to ``arr.flat[off]`` (``arr`` a C array of numba type ``ty``)."""
    return builder.gep(context.make_array(ty)(context, builder, arr).data, [off])


def _lanes_at(context, builder, signature, args):
    """A lane copy's destination and source pointers: &dst[doff], &src.flat[soff]."""
    dty, _, sty, _ = signature.args
    return (_flat_at(context, builder, dty, args[0], args[1]),
            _flat_at(context, builder, sty, args[2], args[3]))


@intrinsic
def _copy_lanes(typingctx, dst, doff, src, soff):  # pragma: no cover - numba
    """``dst[doff:doff + LANES] = src[soff:soff + LANES]`` (1-D C arrays of one dtype, the
    ranges inside them: unchecked) as one ``llvm.memcpy`` of a known size, which LLVM turns
    into a vector load and store. A loop of LANES elements ran element by element (LLVM
    unrolls a loop of a known short length fully before its loop vectoriser sees it, and numba
    has no SLP vectoriser; a loop of a run-time length this short is shorter than the vector
    loop's trip): the 23 rows of a (15, 9) search's bounds took ~85 ns to copy, now ~9."""
    if not (_lanes_typed(dst, doff, src, soff) and dst.dtype == src.dtype):
        return None
    sig = types.void(dst, doff, src, soff)

    def codegen(context, builder, signature, args):
        dty = signature.args[0]
        dptr, sptr = _lanes_at(context, builder, signature, args)
        item = context.get_abi_sizeof(context.get_data_type(dty.dtype))
        cgutils.raw_memcpy(builder, dptr, sptr, context.get_constant(types.intp, LANES), item)
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def _window_sums(typingctx, dst, doff, src, soff, m):  # pragma: no cover - numba
    """``dst[doff + k] = sum_{i < m} src[soff + k + i]`` for k < LANES: ``dst`` 1-D C int16,
    ``src`` 1-D C uint8, the ranges inside them (unchecked), the sums within int16 (m at most
    128). LANES window sums at once, m vector loads each added to all of them (a sliding sum
    is one long dependent chain; :func:`_row_sums`' few-searches path)."""
    if not (_lanes_typed(dst, doff, src, soff) and dst.dtype == types.int16
            and src.dtype == types.uint8 and isinstance(m, types.Integer)):
        return None
    sig = types.void(dst, doff, src, soff, m)

    def codegen(context, builder, signature, args):
        tys = signature.args
        short = ir.VectorType(ir.IntType(16), LANES)
        narrow = ir.VectorType(ir.IntType(8), LANES).as_pointer()
        intp = context.get_value_type(types.intp)
        dptr = _flat_at(context, builder, tys[0], args[0], args[1])
        sptr = _flat_at(context, builder, tys[2], args[2], args[3])
        count = context.cast(builder, args[4], tys[4], types.intp)
        total = cgutils.alloca_once_value(builder, ir.Constant(short, None))
        with cgutils.for_range(builder, count, intp=intp) as loop:
            at = builder.bitcast(builder.gep(sptr, [loop.index]), narrow)
            pix = builder.zext(builder.load(at, align=1), short)
            builder.store(builder.add(builder.load(total), pix), total)
        builder.store(builder.load(total), builder.bitcast(dptr, short.as_pointer()), align=2)
        return context.get_dummy_value()

    return sig, codegen


#: int16 lanes a step of :func:`_pixel_dots`: a 512-bit vector of them (two 256-bit or four
#: 128-bit ones where the core has no AVX-512: LLVM splits the vectors)
DOT_LANES = 32


def _dots_typed(gx, gy, pix, offsets, size, scale=None) -> Any:
    """The signature of :func:`_pixel_dots` (``scale`` None) or :func:`_scaled_dots` for
    these argument types, or None where they are not the ones it takes."""
    arrays = [gx, gy, pix] + ([] if scale is None else [scale])
    if not (all(isinstance(a, types.Array) and a.ndim == 1 and a.layout == "C" for a in arrays)
            and gx.dtype == gy.dtype and gx.dtype in (types.int16, types.int64)
            and (scale is None or scale.dtype == gx.dtype) and pix.dtype == types.uint8
            and isinstance(offsets, types.UniTuple) and isinstance(offsets.dtype, types.Integer)
            and isinstance(size, types.Integer)):
        return None
    out = types.UniTuple(types.int32 if gx.dtype == types.int16 else types.int64,
                         2 * offsets.count)
    return out(*([gx, gy, pix, offsets, size] if scale is None
                 else [gx, gy, scale, pix, offsets, size]))


def _dots_codegen(context, builder, signature, args, scaled: bool):
    """The code of :func:`_pixel_dots` and :func:`_scaled_dots`."""
    if scaled:  # (gx, gy, scale, pix, ...) -> the gradients times scale, then as unscaled
        tys, args = signature.args, list(args)
        scale_ty, scale = tys[2], args.pop(2)
        tys = tys[:2] + tys[3:]
    else:
        tys, scale_ty, scale = signature.args, None, None
    offsets = tys[3]
    k = offsets.count
    bits = 32 if tys[0].dtype == types.int16 else 64
    # int64 sums have no multiply-add to pair for: a vector of 8, each product added as it is
    # (pairs of 32 split over four vectors and shuffled across them took the 65 px window's
    # frames 15 to 35 % longer than the plain loop)
    lanes = DOT_LANES if bits == 32 else DOT_LANES // 4
    isum = ir.IntType(bits)
    wide = ir.VectorType(isum, lanes)
    half = ir.VectorType(isum, lanes // 2 if bits == 32 else lanes)
    grads = ir.VectorType(ir.IntType(16 if bits == 32 else 64), lanes).as_pointer()
    pixels = ir.VectorType(ir.IntType(8), lanes).as_pointer()
    intp = context.get_value_type(types.intp)
    zero = context.get_constant(types.intp, 0)
    bases = [_flat_at(context, builder, tys[j], args[j], zero) for j in range(3)]
    by = None if scale is None else _flat_at(context, builder, scale_ty, scale, zero)
    offs = [context.cast(builder, v, offsets.dtype, types.intp)
            for v in cgutils.unpack_tuple(builder, args[3], k)]
    n = context.cast(builder, args[4], tys[4], types.intp)
    sums = [cgutils.alloca_once_value(builder, ir.Constant(half, None)) for _ in range(2 * k)]
    with cgutils.for_range_slice(builder, zero, n, ir.Constant(intp, lanes)) as (q, _):
        gs = [builder.load(builder.bitcast(builder.gep(base, [q]), grads), align=2)
              for base in bases[:2]]
        if by is not None:  # in the gradients' own width: the caller says it fits
            f = builder.load(builder.bitcast(builder.gep(by, [q]), grads), align=2)
            gs = [builder.mul(g, f) for g in gs]
        if bits == 32:
            gs = [builder.sext(g, wide) for g in gs]
        for j, off in enumerate(offs):
            at = builder.gep(bases[2], [builder.add(off, q)])
            p = builder.zext(builder.load(builder.bitcast(at, pixels), align=1), wide)
            for side, g in enumerate(gs):
                prod = builder.mul(g, p)
                pair = prod if bits == 64 else _add_pairs(builder, prod)
                slot = sums[side * k + j]
                builder.store(builder.add(builder.load(slot), pair), slot)
    fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(isum, [half]),
                                        f"llvm.vector.reduce.add.v{half.count}i{bits}")
    return context.make_tuple(builder, signature.return_type,
                              [builder.call(fn, [builder.load(slot)]) for slot in sums])


@intrinsic
def _pixel_dots(typingctx, gx, gy, pix, offsets, size):  # pragma: no cover - numba
    """``(sum gx[q] pix[o + q] for o in offsets, then the same for gy)`` over q < ``size`` (a
    multiple of DOT_LANES): ``gx``, ``gy`` 1-D C int16 (the sums int32, wrapping as the sums
    of :func:`_refine` do; they cannot overflow there) or int64 (the sums int64), ``pix`` a
    1-D C uint8 array, ``offsets`` a tuple of ints, everything read inside the arrays
    (unchecked).

    Each product of a gradient and a pixel added to its neighbour's in the same 32-bit lane:
    the pattern of a 16-bit multiply-add (vpmaddwd, or vpdpwssd with AVX-512 VNNI), which
    LLVM's vectoriser makes of a loop of one such sum but not of a loop of eight: there it
    put one product in each 32-bit lane (half the multiply-add's work) or, with signed
    factors, used 32-bit multiplies. Eight sums of 640 pixels: 24 ns, against 147 ns for
    the loop (int16 gradients; 178 against 475 ns in int64)."""
    sig = _dots_typed(gx, gy, pix, offsets, size)
    if sig is None:
        return None
    return sig, lambda context, builder, signature, args: _dots_codegen(
        context, builder, signature, args, False)


@intrinsic
def _scaled_dots(typingctx, gx, gy, scale, pix, offsets, size):  # pragma: no cover - numba
    """:func:`_pixel_dots` of the gradients times ``scale`` (each product in the gradients'
    own type: the caller knows that it fits)."""
    sig = _dots_typed(gx, gy, pix, offsets, size, scale)
    if sig is None:
        return None
    return sig, lambda context, builder, signature, args: _dots_codegen(
        context, builder, signature, args, True)


#: the sums of :func:`_masked_squares`, one a mask
RING_MASKS = 5


@intrinsic
def _masked_squares(typingctx, tp, t0, cp, c0, stride, weights, masks,
                    size):  # pragma: no cover - numba
    """``(sum_q masks[k, q] & r[q]^2 for k < RING_MASKS)``, int64, over q < ``size``, of the
    residual of a window of frame t against frame t+1 sampled bilinearly, in 1/BILINEAR_ONE
    grey levels: ``r[q] = w00 cp[c0 + q] + w01 cp[c0 + q + 1]
    + w10 cp[c0 + q + stride] + w11 cp[c0 + q + stride + 1] - (w00 + .. + w11) tp[t0 + q]``
    (``weights`` (w00, w01, w10, w11), int16, summing to at most 128: every partial sum fits
    int16) and ``size`` a multiple of 2 DOT_LANES. ``tp``, ``cp`` 1-D C uint8, ``masks``
    (RING_MASKS, L) C int16 (0 or -1 a lane), read inside them (unchecked).
    :func:`.pyramid._ring_fit`'s sums.

    A residual squared is up to 2^30: a 16-bit multiply-add (vpmaddwd, the pattern of
    :func:`_pixel_dots`) of the masked residuals with the residuals puts two of them in a
    32-bit lane (at most 2 * 32640^2 < 2^31), then added into 64-bit lanes. The loop numba
    made of it ran 8 lanes a step, each square widened to 64 bits (int32 sums of residuals
    rounded to 1/8 grey level were no faster): 353 to 360 ns a 21 px window, against 138 to
    153 here, with two vectors' pairs added in 32 bits (unsigned: below 2^32) before they
    are widened (one vector a step: 173 to 207)."""
    if not (all(isinstance(a, types.Array) and a.layout == "C" for a in (tp, cp, masks))
            and tp.ndim == 1 and cp.ndim == 1 and masks.ndim == 2
            and tp.dtype == types.uint8 and cp.dtype == types.uint8
            and masks.dtype == types.int16
            and isinstance(weights, types.UniTuple) and weights.count == 4
            and weights.dtype == types.int16
            and all(isinstance(t, types.Integer) for t in (t0, c0, stride, size))):
        return None
    sig = types.UniTuple(types.int64, RING_MASKS)(tp, t0, cp, c0, stride, weights, masks, size)

    def codegen(context, builder, signature, args):
        tys = signature.args
        lanes = DOT_LANES
        i16 = ir.IntType(16)
        short = ir.VectorType(i16, lanes)
        wide = ir.VectorType(ir.IntType(32), lanes)
        half = ir.VectorType(ir.IntType(64), lanes // 2)
        narrow = ir.VectorType(ir.IntType(8), lanes).as_pointer()
        intp = context.get_value_type(types.intp)
        zero = context.get_constant(types.intp, 0)

        def at(j):
            return context.cast(builder, args[j], tys[j], types.intp)
        t0, c0, stride, size = at(1), at(3), at(4), at(7)
        tbase = _flat_at(context, builder, tys[0], args[0], zero)
        cbase = _flat_at(context, builder, tys[2], args[2], zero)
        mbase = _flat_at(context, builder, tys[6], args[6], zero)
        width = builder.extract_value(context.make_array(tys[6])(context, builder, args[6])
                                      .shape, 1)

        def splat(v):
            return builder.shuffle_vector(
                builder.insert_element(ir.Constant(short, None), v, ir.Constant(i16, 0)),
                ir.Constant(short, None), ir.Constant(wide, [0] * lanes))
        ws = [splat(builder.extract_value(args[5], k)) for k in range(4)]
        one = builder.add(builder.add(builder.extract_value(args[5], 0),
                                      builder.extract_value(args[5], 1)),
                          builder.add(builder.extract_value(args[5], 2),
                                      builder.extract_value(args[5], 3)))
        ones = splat(one)
        sums = [cgutils.alloca_once_value(builder, ir.Constant(half, None))
                for _ in range(RING_MASKS)]

        def residual(q):
            def pixels(base, off):
                ptr = builder.bitcast(builder.gep(base, [builder.add(off, q)]), narrow)
                return builder.zext(builder.load(ptr, align=1), short)
            b = [pixels(cbase, off) for off in (c0, builder.add(c0, ir.Constant(intp, 1)),
                                                  builder.add(c0, stride),
                                                  builder.add(builder.add(c0, stride),
                                                              ir.Constant(intp, 1)))]
            sample = builder.add(builder.add(builder.mul(ws[0], b[0]), builder.mul(ws[1], b[1])),
                                 builder.add(builder.mul(ws[2], b[2]), builder.mul(ws[3], b[3])))
            return builder.sub(sample, builder.mul(ones, pixels(tbase, t0)))

        def squares(q, r, k):  # the pairs of masked squares, each < 2^31
            mptr = builder.gep(mbase, [builder.add(builder.mul(ir.Constant(intp, k), width), q)])
            m = builder.load(builder.bitcast(mptr, short.as_pointer()), align=2)
            return _add_pairs(builder, builder.mul(builder.sext(builder.and_(r, m), wide),
                                                   builder.sext(r, wide)))
        step = ir.Constant(intp, 2 * lanes)
        with cgutils.for_range_slice(builder, zero, size, step) as (q, _):
            # two vectors a step: their pairs added in 32 bits (unsigned, < 2^32), then
            # widened to 64 once
            q2 = builder.add(q, ir.Constant(intp, lanes))
            r1, r2 = residual(q), residual(q2)
            for k, slot in enumerate(sums):
                both = builder.add(squares(q, r1, k), squares(q2, r2, k))
                builder.store(builder.add(builder.load(slot), builder.zext(both, half)), slot)
        fn = cgutils.get_or_insert_function(
            builder.module, ir.FunctionType(ir.IntType(64), [half]),
            f"llvm.vector.reduce.add.v{lanes // 2}i64")
        return context.make_tuple(builder, signature.return_type,
                                  [builder.call(fn, [builder.load(slot)]) for slot in sums])

    return sig, codegen


#: window rows summed (:func:`_rows_squares`) between two tests of a sum against its bound
#: (fewer tests against rows summed in vain: 2, 3, 5 and 9 rows measured the same to within
#: the rounds' spread, 3 at the front)
ROW_GROUP = 3


@intrinsic
def _rows_squares(typingctx, pf, poff, cf, coff, count, step, rows):  # pragma: no cover
    """The sum, int64, of ``(pf[poff + r step + i] - cf[coff + r step + i])^2`` for i <
    ``count`` (at most LANES) and r < ``rows``: 1-D C uint8 arrays, LANES bytes read from each
    row's offset (inside the arrays: unchecked), the lanes from ``count`` on masked out.

    A row is one vector load from each frame, widened to 16 bits, subtracted, masked and
    squared in the pairs of a 16-bit multiply-add (vpmaddwd; the even products added to the
    odd, as in :func:`_pixel_dots`); the rows' pairs are added as vectors and their lanes
    once, at the end. A row's 9 pixels summed pixel by pixel ran scalar (LLVM leaves so short
    a loop alone); one vector a row, with 32-bit multiplies (vpmulld) and its lanes added a
    row at a time, was the first version: the (15, 9) search's S summed ROW_GROUP rows a call
    took it from ~46 to ~41 us a frame pair (old and new in turn, three rounds each, the
    same outputs bit for bit)."""
    if not (isinstance(pf, types.Array) and isinstance(cf, types.Array) and pf.ndim == 1
            and cf.ndim == 1 and pf.layout == "C" and cf.layout == "C"
            and pf.dtype == types.uint8 and cf.dtype == types.uint8
            and all(isinstance(t, types.Integer) for t in (poff, coff, count, step, rows))):
        return None
    sig = types.int64(pf, poff, cf, coff, count, step, rows)

    def codegen(context, builder, signature, args):
        narrow = ir.VectorType(ir.IntType(8), LANES)
        i32 = ir.IntType(32)
        short = ir.VectorType(ir.IntType(16), LANES)
        wide = ir.VectorType(i32, LANES)
        half = ir.VectorType(i32, LANES // 2)
        tys = signature.args
        intp = context.get_value_type(types.intp)
        p0 = context.cast(builder, args[1], tys[1], types.intp)
        c0 = context.cast(builder, args[3], tys[3], types.intp)
        stride = context.cast(builder, args[5], tys[5], types.intp)
        nrows = context.cast(builder, args[6], tys[6], types.intp)
        zero = context.get_constant(types.intp, 0)
        pbase = _flat_at(context, builder, tys[0], args[0], zero)
        cbase = _flat_at(context, builder, tys[2], args[2], zero)
        n16 = context.cast(builder, args[4], tys[4], types.int16)
        splat = builder.shuffle_vector(
            builder.insert_element(ir.Constant(short, None), n16, ir.Constant(i32, 0)),
            ir.Constant(short, None), ir.Constant(wide, [0] * LANES))
        keep = builder.icmp_unsigned("<", ir.Constant(short, list(range(LANES))), splat)
        total = cgutils.alloca_once_value(builder, ir.Constant(half, [0] * (LANES // 2)))
        with cgutils.for_range(builder, nrows, intp=intp) as loop:
            at = builder.mul(loop.index, stride)
            rows = []
            for base, off in ((pbase, p0), (cbase, c0)):
                ptr = builder.gep(base, [builder.add(off, at)])
                ptr = builder.bitcast(ptr, narrow.as_pointer())
                rows.append(builder.zext(builder.load(ptr, align=1), short))
            d = builder.select(keep, builder.sub(rows[0], rows[1]),
                               ir.Constant(short, [0] * LANES))
            d = builder.sext(d, wide)
            sq = builder.mul(d, d)
            builder.store(builder.add(builder.load(total), _add_pairs(builder, sq)), total)
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(i32, [half]),
                                            f"llvm.vector.reduce.add.v{LANES // 2}i32")
        # at most rows * LANES * 255^2: positive in int32 for up to 2063 rows
        return builder.zext(builder.call(fn, [builder.load(total)]), ir.IntType(64))

    return sig, codegen


@nb.njit(cache=True, nogil=True, inline="always")
def _copy_block(src, w, x0, y0, rows, cols, dst):  # pragma: no cover - numba
    """Copy ``rows`` rows of ``cols`` entries from ``src`` (flat, rows ``w`` long), starting at
    (x0, y0), into ``dst`` with rows ``cols`` long: one contiguous block for the long loops."""
    for rr in range(rows):
        s0 = (y0 + rr) * w + x0
        row = src[s0:s0 + cols]
        out = dst[rr * cols:(rr + 1) * cols]
        for k in range(cols):
            out[k] = row[k]


@nb.njit(cache=True, nogil=True, inline="always")
def _add_squares(acc, total, t0, t1, t2, r0, r1, r2, w0, w1, w2,
                 unit):  # pragma: no cover - numba
    """``acc[q] += w0 (t0 - r0[q])^2 + w1 (t1 - r1[q])^2 + w2 (t2 - r2[q])^2`` for q < total:
    three terms a pass, so that ``acc`` is loaded and stored a third as often, in one long
    vectorised loop; with ``unit`` the weights are all 1 and the multiplications skipped."""
    if unit:
        for q in range(total):
            d0 = t0 - np.int32(r0[q])
            d1 = t1 - np.int32(r1[q])
            d2 = t2 - np.int32(r2[q])
            acc[q] += d0 * d0 + d1 * d1 + d2 * d2
    else:
        for q in range(total):
            d0 = t0 - np.int32(r0[q])
            d1 = t1 - np.int32(r1[q])
            d2 = t2 - np.int32(r2[q])
            acc[q] += w0 * (d0 * d0) + w1 * (d1 * d1) + w2 * (d2 * d2)


@nb.njit(cache=True, nogil=True, inline="always")
def _ssd_inline(pf, cf, w, ax, ay, qx, qy, n, wts, uniform, bound):  # pragma: no cover - numba
    """S of Eq. (1) between the window at (ax, ay) in frame t and at (qx, qy) in frame t+1,
    given as flat arrays ``pf``, ``cf`` of rows ``w`` long.

    Stops once a row (with uniform weights, ROW_GROUP rows: :func:`_rows_squares`) takes the
    partial sum above ``bound`` (the terms are non-negative, so the window can no longer win)
    and returns that partial sum, which is > ``bound``.

    Indices are unsigned: numba then skips its negative-index fix-up on every load (the
    windows are inside the frames), 20 % of the time of this loop.

    Inlined where it is called (numba's ``inline="always"``): in :func:`_search`, whose calls
    LLVM left as calls, the (15, 9) search took 76 us a frame instead of 73 (LK level 0 in the
    same run: 102 us). The other callers call :func:`_ssd_at`: inlined everywhere, it made the
    cold compile of the kernels 5 s longer (42.5 -> 47.9 s).
    """
    m = 2 * n + 1
    acc = 0
    t0 = np.uint64((ay - n) * w + ax - n)
    c0 = np.uint64((qy - n) * w + qx - n)
    step = np.uint64(w)
    # whole vectors of LANES pixels a row where the last row's run-on stays in the frames
    chunks = (m + LANES - 1) // LANES
    last = np.uint64((m - 1) * w + chunks * LANES)
    if uniform and t0 + last <= np.uint64(pf.shape[0]) and c0 + last <= np.uint64(cf.shape[0]):
        j = 0
        while j < m:
            k = min(ROW_GROUP, m - j)
            for c in range(chunks):
                off = np.uint64(c * LANES)
                acc += _rows_squares(pf, t0 + off, cf, c0 + off, min(m - c * LANES, LANES),
                                     step, k)
            if acc > bound:
                return acc
            t0 += step * np.uint64(k)
            c0 += step * np.uint64(k)
            j += k
        return acc
    for j in range(m):
        if uniform:
            for i in range(m):
                d = np.int32(pf[t0 + np.uint64(i)]) - np.int32(cf[c0 + np.uint64(i)])
                acc += d * d
        else:
            wrow = wts[j]
            for i in range(m):
                d = np.int32(pf[t0 + np.uint64(i)]) - np.int32(cf[c0 + np.uint64(i)])
                acc += np.int64(wrow[i]) * (d * d)
        if acc > bound:
            return acc
        t0 += step
        c0 += step
    return acc


@nb.njit(**NO_NRT)
def _ssd_at(pf, cf, w, ax, ay, qx, qy, n, wts, uniform, bound):  # pragma: no cover - numba
    """:func:`_ssd_inline`, called."""
    return _ssd_inline(pf, cf, w, ax, ay, qx, qy, n, wts, uniform, bound)


@nb.njit(cache=True, nogil=True, inline="always")
def _mark(bnd, lanes, mask, total, lim):  # pragma: no cover - numba
    """``mask[q]`` = 1 where displacement lane q's bound is at most ``lim`` (one vectorised
    pass); returns how many."""
    passing = 0
    for q in range(total):
        hit = (bnd[q] <= lim) & lanes[q]
        mask[q] = hit
        passing += hit
    return passing


@nb.njit(cache=True, nogil=True, inline="always")
def _count(bnd, lanes, total, lim):  # pragma: no cover - numba
    """How many displacement lanes have a bound at most ``lim``, of ``bnd``'s type: one
    vectorised pass in that width (an int64 ``lim`` would widen an int32 pass to int64)."""
    passing = np.int32(0)
    for q in range(total):
        passing = np.int32(passing + ((bnd[q] <= lim) & lanes[q]))
    return passing


@nb.njit(**NO_NRT)
def _search(pf, cf, w, ax, ay, cx, cy, lo_x, lo_y, nrow, ncol, width, total, n, wts, uniform,
            bnd, mscale, lanes, mask, btype, bmax):  # pragma: no cover - numba
    """The first (row-major) minimum of S over the search, pruned by the bounds ``bnd``.

    Returns (S, rank) with rank = r * ncol + k for the window centred at (lo_x + k, lo_y + r).
    ``bnd`` bounds ``mscale`` * S (m, or 0 with all bounds 0 when they are not used);
    ``lanes[q]`` is 1 where ``bnd[q]`` belongs to a displacement, else 0; ``mask``: uint8
    scratch as long; ``btype``: ``bnd``'s integer type, ``bmax`` its largest value.

    The valid position nearest the prediction is scored first, then its 8 neighbours: the
    minimum is among them for ~97 % of features on real sequences, after which the bounds rule
    out every other displacement (``bnd > m * best`` means S > best: it can neither win nor
    tie) and one vectorised count shows it, without visiting them. Otherwise every displacement
    that passes its bound is scored, its sum abandoned once it exceeds the best so far. Ties go
    to the lower rank, so the result does not depend on the order of visits.

    Tried and not kept (issue 15): the nine first scores as nine contiguous loops of m^2
    terms (the template's rows and frame t+1's copied back to back, 16-bit differences). Alone
    on the bench's frames it took the nine full sums from ~23 to ~6 us a frame pair, but in
    the search it gained nothing (47.5 against 47.7 us, old and new side by side): here most
    neighbours are ruled out by their bound, and the rest abandoned after a few rows. Where a
    frame pair's (15, 9) search goes (~45 us, 83 features, timed apart): ~3 us of fixed cost
    (the wrapper 1.8, the kernel's call 1.1), ~6 us of row sums, ~0.43 us a search, of which
    ~0.2 us at a search of one displacement (the template's row sums, the bounds' passes over
    a VEC of lanes, one S).
    """
    px = min(max(cx, lo_x), lo_x + ncol - 1) - lo_x
    py = min(max(cy, lo_y), lo_y + nrow - 1) - lo_y
    best = _ssd_inline(pf, cf, w, ax, ay, lo_x + px, lo_y + py, n, wts, uniform, BIG)
    best_k = py * ncol + px
    for r in range(max(py - 1, 0), min(py + 2, nrow)):
        for k in range(max(px - 1, 0), min(px + 2, ncol)):
            rank = r * ncol + k
            if rank == py * ncol + px or bnd[r * width + k] > best * mscale:
                continue
            v = _ssd_inline(pf, cf, w, ax, ay, lo_x + k, lo_y + r, n, wts, uniform, best)
            if v < best or (v == best and rank < best_k):
                best = v
                best_k = rank
    lim = best * mscale
    # count the displacements that pass their bound and compare their number with those among
    # the 9 already scored
    passing = _count(bnd, lanes, total, btype(min(lim, bmax)))
    near = 0
    for r in range(max(py - 1, 0), min(py + 2, nrow)):
        for k in range(max(px - 1, 0), min(px + 2, ncol)):
            near += bnd[r * width + k] <= lim
    if passing == near:
        return best, best_k
    _mark(bnd, lanes, mask, total, lim)
    # score the others, visiting only the marked ones: 8 mask bytes at a time, the set bytes
    # found by their bit (one each)
    words = mask.view(np.uint64)
    for i in range(total // 8):
        word = words[i]
        while word:
            q = i * 8 + (trailing_zeros(word) >> 3)
            word &= word - np.uint64(1)
            r = q // width
            k = q - r * width
            if abs(r - py) <= 1 and abs(k - px) <= 1:
                continue  # scored above
            if bnd[q] > lim:
                continue  # passed the bound of an earlier best, not of this one
            rank = r * ncol + k
            v = _ssd_inline(pf, cf, w, ax, ay, lo_x + k, lo_y + r, n, wts, uniform, best)
            if v < best or (v == best and rank < best_k):
                best = v
                best_k = rank
                lim = best * mscale
    return best, best_k


@nb.njit(cache=True, nogil=True)
def _search_full(prev, curr, ax, ay, lo_x, lo_y, nrow, ncol, n, wts, uniform, reg,
                 acc):  # pragma: no cover - numba
    """The first (row-major) minimum of S over the search, every displacement scored in full:
    the paper's plain Eq. (1), (2s+1)^2 (2n+1)^2 terms per feature whatever the images.

    Returns (S, rank) with rank = r * ncol + k for the window centred at (lo_x + k, lo_y + r),
    as :func:`_search` does (ties go to the lower rank), so both return the same position.

    The sums of all displacements are built together, one pass per three pixels (j, i) of the
    correlation window, each pass adding ``W(i, j) (I_t(c + (i, j)) - I_t+1(q + (i, j)))^2`` to
    the sum of every displacement q: frame t+1 around the search is first copied into ``reg``
    with rows ``stride = ncol + 2n`` long, and ``acc`` holds displacement (r, k) at
    ``r * stride + k``, so that a pass is one long contiguous loop over ``nrow * stride`` sums
    (padded to a multiple of FULL_VEC), which LLVM vectorises. The 2n sums past ``ncol`` in each row
    and the padding are junk (their frame t+1 reads run on into the next row) and are never
    read. Three window pixels a pass (:func:`_add_squares`) cut the loads and stores of ``acc``
    by three. ``acc``'s dtype (int32 where S cannot overflow) sets the vector width.
    """
    m = 2 * n + 1
    stride = ncol + m - 1
    _copy_block(curr.ravel(), curr.shape[1], lo_x - n, lo_y - n, nrow + m - 1, stride, reg)
    total = (nrow * stride + FULL_VEC - 1) // FULL_VEC * FULL_VEC
    for q in range(total):
        acc[q] = 0
    for j in range(m):
        trow = prev[ay - n + j, ax - n:ax + n + 1]
        base = j * stride
        for i in range(0, m, 3):
            i1 = min(i + 1, m - 1)
            i2 = min(i + 2, m - 1)
            t0 = np.int32(trow[i])
            t1 = np.int32(trow[i1])
            t2 = np.int32(trow[i2])
            r0 = reg[base + i:base + i + total]
            r1 = reg[base + i1:base + i1 + total]
            r2 = reg[base + i2:base + i2 + total]
            # pixels past the window weigh 0
            _add_squares(acc, total, t0, t1, t2, r0, r1, r2, np.int64(wts[j, i]),
                         np.int64(wts[j, i1]) if i + 1 < m else np.int64(0),
                         np.int64(wts[j, i2]) if i + 2 < m else np.int64(0),
                         uniform and i + 2 < m)
    best = acc[0]
    best_k = 0
    for r in range(nrow):
        row = acc[r * stride:r * stride + ncol]
        for k in range(ncol):
            if row[k] < best:  # strict: the first minimum in row-major order
                best = row[k]
                best_k = r * ncol + k
    return np.int64(best), best_k


# -- the status of a feature after a search ----------------------------------------------------
# Why a feature was found or not; :func:`_search_level` sets the first four, the coarse-to-fine
# tracker of :mod:`.pyramid` the others.

#: found
OK = 0
#: its window left the image: the template leaves frame t, or no search position fits frame t+1
LEFT = 1
#: the minimum lies on an edge of the search that the image cut short: it may be a piece of a
#: minimum outside the image (the feature is leaving it)
CUT = 2
#: the minimum lies on the border of the search window: the true one may lie outside it
BORDER = 3
#: a second minimum, away from the first, is nearly as good: repetitive or ambiguous texture
AMBIGUOUS = 4
#: the coarse-to-fine refinement did not settle within its steps
RUNAWAY = 5
#: tracked back from frame t+1, the match does not return to where the feature started
FB = 6
#: its displacement departs from its nearest neighbours' (a lookalike taken for it)
DISAGREES = 7
#: the RMS residual at the match exceeds ``max_residual`` (set by the tracker)
RESIDUAL = 8
#: not searched: the searches of its frame had spent their work budget
#: (:data:`.pyramid.FRAME_WORK`)
OVER = 9
STATUS_NAMES = ("ok", "left", "cut", "border", "ambiguous", "runaway", "fb", "disagrees",
                "residual", "budget")
#: the work budget of :func:`_search_level` that never runs out (the paper's search,
#: :func:`track_ssd`): work is counted in window pixels x displacements searched
NO_BUDGET = 2**62


@nb.njit(**NO_NRT)
def _ambiguous_pruned(pf, cf, w, ax, ay, lo_x, lo_y, nrow, ncol, width, total, n, wts, uniform,
                      bnd, mscale, lanes, mask, best_k, lim):  # pragma: no cover - numba
    """Whether a displacement outside the 3x3 neighbourhood of the minimum (rank ``best_k``)
    has S <= ``lim``. The bounds ``bnd`` of the search (times ``mscale``) rule out most of
    them in one vectorised pass (``lanes``, ``mask`` as in :func:`_search`); the others are
    scored, each abandoned once above ``lim``."""
    br = best_k // ncol
    bk = best_k - br * ncol
    passing = _mark(bnd, lanes, mask, total, lim * mscale)
    for r in range(max(br - 1, 0), min(br + 2, nrow)):
        for k in range(max(bk - 1, 0), min(bk + 2, ncol)):
            passing -= mask[r * width + k]
    if passing == 0:
        return False
    cap = np.int64(lim) if lim < BIG else BIG
    # visit only the marked ones, as _search does: a handful of the search's displacements
    # (~6 of 176 at the coarse level of the default tracker), where a scan of all of them
    # cost more than scoring those
    words = mask.view(np.uint64)
    for i in range(total // 8):
        word = words[i]
        while word:
            q = i * 8 + (trailing_zeros(word) >> 3)
            word &= word - np.uint64(1)
            r = q // width
            k = q - r * width
            if abs(r - br) <= 1 and abs(k - bk) <= 1:
                continue
            if _ssd_at(pf, cf, w, ax, ay, lo_x + k, lo_y + r, n, wts, uniform, cap) <= lim:
                return True
    return False


@nb.njit(**NO_NRT)
def _ambiguous_full(acc, nrow, ncol, stride, best_k, lim):  # pragma: no cover - numba
    """:func:`_ambiguous_pruned` over the sums of an exhaustive search (``acc``, displacement
    (r, k) at ``r * stride + k``)."""
    br = best_k // ncol
    bk = best_k - br * ncol
    for r in range(nrow):
        for k in range(ncol):
            if (abs(r - br) > 1 or abs(k - bk) > 1) and acc[r * stride + k] <= lim:
                return True
    return False


@nb.njit(cache=True, nogil=True)
def _weights_info(wts):  # pragma: no cover - numba
    """(uniform, wmin per row, mscale) of the weights W: uniform weights skip the
    multiplications; wmin bounds each row of a weighted window; the bounds compare with
    mscale * S, m unless the weights are so large (> 2^28) that m * S could overflow int64,
    and then 0 with every wmin 0, so that nothing is ruled out."""
    m = wts.shape[0]
    uniform = True
    wmax = 0
    wmin = np.empty(m, np.int64)
    for j in range(m):
        lo = wts[j, 0]
        for i in range(m):
            lo = min(lo, wts[j, i])
            wmax = max(wmax, wts[j, i])
            if wts[j, i] != 1:
                uniform = False
        wmin[j] = max(lo, 0)
    mscale = m
    if float(wmax) * m * m * m * 65025.0 >= 2.0**62:
        wmin[:] = 0
        mscale = 0
    return uniform, wmin, mscale


@nb.njit(cache=True, nogil=True)
def _search_level(prev, curr, anchors, centers, active, n, s, wts, exhaustive, ratio,
                  allowance, out_q, out_ssd, out_status, budget):  # pragma: no cover - numba
    """The searches of Eq. (1) of the ``active`` features on one pair of frames.

    For feature f: the first (row-major) minimum of S over the displacements whose centre lies
    within ``s`` of ``centers[f]`` (and whose window fits frame t+1), the template centred at
    ``anchors[f]``; pruned (:func:`_search`) or, with ``exhaustive``, every displacement in
    full (:func:`_search_full`). Results: ``out_q[f]`` (x, y) and ``out_ssd[f]`` (S there),
    ``out_status[f]``:

    * LEFT: the template leaves frame t or no displacement fits frame t+1 (nothing else set);
    * CUT: the minimum is on an edge of the search that the image cut short (nothing set);
    * AMBIGUOUS (only when ``ratio > 0``): a displacement outside the minimum's 3x3
      neighbourhood has S <= ratio * S_min + allowance;
    * BORDER: the minimum is on the border of the search window;
    * OVER: not searched, its search would cost more than is left of ``budget[0]``, which
      each search draws on (window pixels x displacements; the searches of one frame share
      one budget, so that the work of a frame stays bounded at any parameters);
    * OK otherwise.
    """
    h, w = prev.shape
    m = 2 * n + 1
    n_feat = anchors.shape[0]
    count = 0
    for f in range(n_feat):
        if active[f]:
            out_status[f] = LEFT
            out_ssd[f] = np.inf
            count += 1
    if count == 0 or m > h or m > w:
        return
    uniform, wmin, mscale = _weights_info(wts)
    pf = prev.ravel()
    cf = curr.ravel()
    side = 2 * s + 1
    # the pruned search's buffers (empty for the exhaustive one, which needs no bounds)
    prune = 0 if exhaustive else 1
    rs = np.empty(prune * (h * w + w + VEC), np.int16)
    bufs = np.empty((2, prune * (ROW_BLOCK + w + 2 * m)), np.int16)
    if not exhaustive:
        # the row sums of frame t+1, where the active features' searches reach
        reach = np.empty((count, 2), np.int64)
        c = 0
        for f in range(n_feat):
            if active[f]:
                reach[c, 0] = centers[f, 0]
                reach[c, 1] = centers[f, 1]
                c += 1
        _row_sums(curr, n, s, reach, rs, bufs)
    width_max = (side + LANES - 1) // LANES * LANES
    size = prune * ((side * width_max + VEC - 1) // VEC * VEC)
    # int32 bounds (twice the vector width of int64), their terms capped (see _bounds): one
    # variant of the pruned search's kernels to compile
    caps, unit = _bound_caps(wmin, uniform)
    bnd = np.empty(size, np.int32)
    # (rows interleaved in pairs where the bounds are paired: twice as long, and the junk
    # lanes past the search's last row read up to VEC // LANES rows further)
    blk = np.empty(prune * 2 * ((side + m + VEC // LANES) * width_max + VEC), np.int16)
    lanes = np.zeros(size, np.uint8)
    mask = np.empty(size, np.uint8)
    # the exhaustive search's buffers: frame t+1 around a search in rows of ``stride``, and
    # the sums of every displacement, in int32 where no S can overflow (|W| * 255^2 per pixel)
    stride = side + m - 1
    full = (1 - prune) * ((side * stride + FULL_VEC - 1) // FULL_VEC * FULL_VEC)
    reg = np.empty((1 - prune) * ((side + m) * stride + m) + full, np.uint8)
    wsum = 0.0
    for j in range(m):
        for i in range(m):
            wsum += abs(float(wts[j, i]))
    full32 = wsum * 65025.0 < 2.0**31
    acc32 = np.empty(full if full32 else 0, np.int32)
    acc64 = np.empty(0 if full32 else full, np.int64)
    lanes_nrow = lanes_ncol = -1
    trs = np.empty(m, np.int32)
    tpairs = np.zeros(m + 1, np.int16)  # the same as int16, for the paired bounds
    left = budget[0]  # a local in the loop: stores through budget cost ~25 ns a feature
    for f in range(n_feat):
        if not active[f]:
            continue
        ax = anchors[f, 0]
        ay = anchors[f, 1]
        cx = centers[f, 0]
        cy = centers[f, 1]
        if ax - n < 0 or ay - n < 0 or ax + n >= w or ay + n >= h:
            continue  # the template itself leaves frame t
        # valid centres: the whole correlation window inside frame t+1
        lo_x = max(cx - s, n)
        hi_x = min(cx + s, w - 1 - n)
        lo_y = max(cy - s, n)
        hi_y = min(cy + s, h - 1 - n)
        if lo_x > hi_x or lo_y > hi_y:
            continue
        ncol = hi_x - lo_x + 1
        nrow = hi_y - lo_y + 1
        cost = nrow * ncol * m * m
        if cost > left:
            out_status[f] = OVER
            continue
        left -= cost
        width = total = 0
        if exhaustive:
            if full32:
                best, best_k = _search_full(prev, curr, ax, ay, lo_x, lo_y, nrow, ncol, n, wts,
                                            uniform, reg, acc32)
            else:
                best, best_k = _search_full(prev, curr, ax, ay, lo_x, lo_y, nrow, ncol, n, wts,
                                            uniform, reg, acc64)
        else:
            width = (ncol + LANES - 1) // LANES * LANES
            # the template's row sums, by unsigned flat index: a row's view took a reference
            # (an atomic increment and decrement of numba's runtime) for 9 pixels
            t0 = np.uint64((ay - n) * w + ax - n)
            for j in range(m):
                acc = 0
                for i in range(m):
                    acc += pf[t0 + np.uint64(i)]
                trs[j] = acc
                tpairs[j] = acc
                t0 += np.uint64(w)
            if nrow != lanes_nrow or ncol != lanes_ncol:
                # which bound lanes are displacements: the same for every search inside the
                # image
                lanes[:] = 0
                for r in range(nrow):
                    lanes[r * width:r * width + ncol] = 1
                lanes_nrow = nrow
                lanes_ncol = ncol
            total = _bounds(rs, w, trs, tpairs, wmin, caps, unit, lo_x, lo_y, nrow, ncol,
                            width, n, blk, bnd)
            best, best_k = _search(pf, cf, w, ax, ay, cx, cy, lo_x, lo_y, nrow, ncol, width,
                                   total, n, wts, uniform, bnd, mscale, lanes, mask, np.int32,
                                   INT32_MAX)
        qx = lo_x + best_k % ncol
        qy = lo_y + best_k // ncol
        # a minimum on an edge that the image cut short may be a piece of a minimum outside
        # the image: the feature is leaving the image, so it is lost rather than pinned there
        if ((qx == lo_x and lo_x > cx - s) or (qx == hi_x and hi_x < cx + s)
                or (qy == lo_y and lo_y > cy - s) or (qy == hi_y and hi_y < cy + s)):
            out_status[f] = CUT
            continue
        out_q[f, 0] = qx
        out_q[f, 1] = qy
        out_ssd[f] = best
        status = OK
        if abs(qx - cx) == s or abs(qy - cy) == s:
            status = BORDER
        if ratio > 0.0:
            lim = ratio * float(best) + allowance
            if exhaustive:
                if full32:
                    amb = _ambiguous_full(acc32, nrow, ncol, ncol + m - 1, best_k, lim)
                else:
                    amb = _ambiguous_full(acc64, nrow, ncol, ncol + m - 1, best_k, lim)
            else:
                amb = _ambiguous_pruned(pf, cf, w, ax, ay, lo_x, lo_y, nrow, ncol, width, total,
                                        n, wts, uniform, bnd, mscale, lanes, mask, best_k,
                                        lim)
            if amb:
                status = AMBIGUOUS
        out_status[f] = status
    budget[0] = left


@nb.njit(cache=True, nogil=True)
def _track(prev, curr, anchors, centers, n, s, wts, subpixel, exhaustive, acc, work,
           out_pos, out_ssd, out_ok, why):  # pragma: no cover - numba
    """The searches of :func:`track_ssd` (:func:`_search_level` over every feature, no
    uniqueness test, ``work`` their budget), results into ``out_pos``, ``out_ssd``,
    ``out_ok`` and (unless it is empty) ``why``, the status. Returns -1, having done nothing,
    where a coordinate lies beyond +-MAX_COORD, else 0."""
    n_feat = anchors.shape[0]
    for f in range(n_feat):
        for c in range(2):
            if not (-MAX_COORD <= anchors[f, c] <= MAX_COORD
                    and -MAX_COORD <= centers[f, c] <= MAX_COORD):
                return -1
    q = np.zeros((n_feat, 2), np.int64)
    active = np.ones(n_feat, np.bool_)
    status = why if why.shape[0] == n_feat else np.empty(n_feat, np.int8)
    _search_level(prev, curr, anchors, centers, active, n, s, wts, exhaustive, 0.0, 0.0, q,
                  out_ssd, status, np.full(1, work, np.int64))
    for f in range(n_feat):
        # a minimum on the search window's border is kept: the paper's search
        out_ok[f] = status[f] == OK or status[f] == BORDER
        out_pos[f, 0] = q[f, 0] if out_ok[f] else np.nan
        out_pos[f, 1] = q[f, 1] if out_ok[f] else np.nan
        if not out_ok[f]:
            out_ssd[f] = np.inf
    if subpixel:
        # a pass of its own after all the searches: interleaved with them it ran ~1.5x slower
        # (caches and branch predictors shared with the search code)
        uniform, _, _ = _weights_info(wts)
        _subpixel(prev, curr, anchors, n, wts, uniform, acc, out_pos, out_ssd, out_ok)
    return 0


#: Gauss-Newton stops once a step is below this, px, or after GN_ITERATIONS
GN_STEP_PX = 1e-3
#: :func:`_refine`'s ``third``: the refinement corrects the interpolation's third-order term
THIRD = 1.0
#: ... or not
NO_THIRD = 0.0
#: ... and also puts the window's centroid into its scratch (the wide window's, which
#: :func:`.pyramid._affine_correction` reads; no other refinement's centroid is read)
CENTROID = 2.0
GN_ITERATIONS = 10
#: the largest |W (2 gradient)| * |second difference| term of the sums of :func:`_refine`, per
#: unit of weight (2 * 255 * 4 * 255): with a term of the centroid's sums (below), what
#: decides whether they fit int32
_REFINE_TERM = 520200.0
#: the terms of the centroid's sums, W (2 gradient) (2 gradient . q): at most this per unit
#: of weight and of |qx| + |qy| (2 * 255 * 2 * 255); summed in int64 (:func:`_refine`)
_CENTROID_TERM = 260100.0


@nb.njit(**NO_NRT)
def _patch(img, x0, y0, rows, cols, out, stride):  # pragma: no cover - numba
    """Copy img[y0:y0 + rows, x0:x0 + cols] into ``out`` (uint8, rows ``stride`` apart), the
    image's edge repeated where it leaves the image."""
    h, w = img.shape
    chunks = (cols + LANES - 1) // LANES
    if (x0 >= 0 and y0 >= 0 and x0 + cols <= w and y0 + rows <= h
            and (y0 + rows - 1) * w + x0 + chunks * LANES <= h * w
            and (rows - 1) * stride + chunks * LANES <= out.shape[0]):
        # whole vectors: a row's last one runs on into the image's next row and the patch's
        # next row (written after it) or its tail, both inside their arrays
        for j in range(rows):
            src = (y0 + j) * w + x0
            for c in range(chunks):
                _copy_lanes(out, j * stride + c * LANES, img, src + c * LANES)
        return
    if x0 >= 0 and y0 >= 0 and x0 + cols <= w and y0 + rows <= h:
        for j in range(rows):
            dst = out[j * stride:j * stride + cols]
            src = img[y0 + j, x0:x0 + cols]
            for i in range(cols):
                dst[i] = src[i]
        return
    for j in range(rows):
        yy = min(max(y0 + j, 0), h - 1)
        for i in range(cols):
            out[j * stride + i] = img[yy, min(max(x0 + i, 0), w - 1)]


@nb.njit(**NO_NRT)
def _corners(gx, gy, cp, off, stride, used):  # pragma: no cover - numba
    """Correlations of ``gx`` and ``gy`` with ``cp`` at the four corners of a pixel, in one
    pass: offsets off, off + 1, off + stride, off + stride + 1 (:func:`_pixel_dots`) over the
    first ``used`` lanes, as int64."""
    sx00, sx01, sx10, sx11, sy00, sy01, sy10, sy11 = _pixel_dots(
        gx, gy, cp, (off, off + 1, off + stride, off + stride + 1), used)
    return (np.int64(sx00), np.int64(sx01), np.int64(sx10), np.int64(sx11), np.int64(sy00),
            np.int64(sy01), np.int64(sy10), np.int64(sy11))


@nb.njit(cache=True, nogil=True)
def _refine_scratch(wts, acc):  # pragma: no cover - numba
    """The weights of a (2h+1)^2 window in :func:`_refine`'s layout (rows R = m + 4 apart,
    zero beyond the window, the length a multiple of VEC) and its scratch: (wpad, tp, cp, g,
    q, cen, fast), ``tp`` and ``cp`` the two patches (uint8), ``g`` the two gradients (int16 where
    :func:`_refine` sums in int32, the type of ``acc``, an empty array from
    :func:`refine_acc`; else int64); ``q`` each pixel's (i, j) from the window's centre in the
    same layout, in the type of ``acc``; ``cen`` (8,) where :func:`_refine` puts the window's
    centroid, turn, stretch and shear centroids; ``fast``: whether the centroids' sums fit
    int32, each product of a gradient and a pixel's i or j int16."""
    m = wts.shape[0]
    half = m // 2
    stride = m + 4
    rsize = (m * stride + VEC - 1) // VEC * VEC
    # the weights in the gradients' type: int16 where the sums are int32 (every weight then
    # fits it, see refine_acc), so that the gradients are made in 16-bit lanes with no
    # narrowing of each weight from 32 bits (a third of that loop)
    g = _gradients(acc, rsize)
    wpad = np.zeros(rsize, g.dtype)
    q = np.zeros((2, rsize), acc.dtype)
    for j in range(m):
        for i in range(m):
            wpad[j * stride + i] = wts[j, i]
            q[0, j * stride + i] = i - half
            q[1, j * stride + i] = j - half
    tp = np.zeros(rsize + 4 * stride + 4, np.uint8)
    cp = np.zeros(rsize + 3 * stride + 3, np.uint8)
    for k in range(rsize):
        g[2, k] = q[0, k]
        g[3, k] = q[1, k]
    # whether the centroid's sums fit int32 and its products of a gradient and i or j int16
    # (:func:`_refine`; each term at most |W| 255^2 (|i| + |j|), the differences at most 255)
    weight = np.abs(wts).astype(np.int64)
    fast = (g.itemsize == 2 and 255.0 * 255.0 * 2.0 * half * weight.sum() < 2.0**31
            and 255 * half * weight.max() <= 32767)
    return wpad, tp, cp, g, q, np.zeros(8, np.float64), fast


def _gradients(acc, size):  # pragma: no cover - numba: compiled through the overload below
    """The scratch of :func:`_refine`'s two gradients and its pixels' (i, j) (rows 2 and 3,
    filled by :func:`_refine_scratch`), (4, size): int16 where the sums are int32 (it holds
    every weighted gradient of a window whose sums fit int32), else int64."""
    raise NotImplementedError


@overload(_gradients)
def _gradients_typed(acc, size):  # pragma: no cover - numba
    if acc.dtype == types.int32:
        return lambda acc, size: np.zeros((4, size), np.int16)
    return lambda acc, size: np.zeros((4, size), np.int64)


def refine_acc(*windows: np.ndarray) -> np.ndarray:
    """An empty array of the integer type in which :func:`_refine` sums over every one of the
    weight ``windows``: int32 where no sum can overflow it and every weighted gradient fits
    int16 (its 16-bit multiply-adds), else int64. Chosen here, before the kernels, so that
    they compile for that one type only."""
    for wts in windows:
        m = wts.shape[0]
        h = m // 2
        # the sums of the normal matrix and corrections, and a single term of the centroid's
        term = max(_REFINE_TERM * m * m, _CENTROID_TERM * 2 * h)
        top = float(np.abs(wts).max(initial=0))
        # and each weighted gradient fits the int16 of the gradients' scratch (_gradients)
        if top * term >= 2.0**31 or top * 255.0 > 32767.0:
            return np.empty(0, np.int64)
    return np.empty(0, np.int32)


@nb.njit(**NO_NRT)
def _refine(prev, curr, ax, ay, x0, y0, n, wpad, tp, cp, g, third, qs, cen,
            fast):  # pragma: no cover - numba
    """Minimise Eq. (1) over a continuous position of the window of the template centred at
    the pixel (ax, ay) of frame t, by Gauss-Newton from (x0, y0) in frame t+1.

    Inverse-compositional Gauss-Newton for a translation (Baker and Matthews 2004): the template
    gradient and the 2x2 normal matrix are computed once, each iteration samples frame t+1
    bilinearly. Returns (converged, x, y); it gives up (False) if the window would leave the
    image, the template has no texture, or the estimate strays more than 1 px from (x0, y0)
    (then (x, y) is where it strayed to, else (x0, y0)).

    Bilinear interpolation at a fraction f of a pixel adds f (1 - f) / 2 times the second
    derivative to a smooth image (exactly so for a quadratic one), which pulls a plain
    estimate towards whole pixels ("pixel locking"; on the rendered sequences of
    :mod:`vistrack.common.rendered` it made the median error 15 to 25 % larger). The residual
    is corrected by that term, the second derivative taken from the template's second
    differences: four more sums, computed with the normal matrix. The next term, f (1 - f)
    (1 - 2 f) / 6 times the third derivative (odd about the half pixel, so it moves the
    estimate rather than blurring it), is corrected the same way from the template's third
    differences: four more sums, in a second pass only where ``third`` is 1.0 (the refinements
    whose estimate is returned; a check's or a coarse level's, 0.0, needs no hundredths of a
    pixel). ``third`` is a float, not a bool: numba compiles a kernel again for each constant
    True or False a caller passes (a literal type), and this one and :func:`_refine_with` were
    3 copies each, 3.6 s of a 57 s cold compile; a float has no literal type. At a
    steady sub-pixel speed that term's error is the same every frame and adds up: real frames
    shifted by exact band-limited shifts of (3.3, 1.2) px a frame, 16 frames, on Venus: +0.43
    / +0.44 px without it, +0.23 / +0.20 with it (RubberWhale +0.19 / +0.21 -> +0.07 / +0.07).
    That pass, where ``third`` is 2.0 (:data:`CENTROID`), also puts into ``cen`` the window's
    texture-weighted centroid relative to its centre, c = (sum W H)^-1 sum W H q (H the
    gradient's outer product at pixel q; ``qs`` the pixels' (i, j)), then its turn centroid
    c' = (sum W H)^-1 sum W H R q (R q = (-j, i)): where the neighbourhood also scales by a
    and turns by b, the estimate is off by a c + b c' (:func:`.pyramid._affine_correction`).
    c' is R c only where the window's texture has no direction. Then its stretch and shear
    centroids, (sum W H)^-1 sum W H (i, -j) and (sum W H)^-1 sum W H (j, i): ``cen`` (8,).

    The gradient-weighted sum of the bilinear samples splits into four integer correlations of
    the gradient with frame t+1 at the corners of the pixel holding the estimate, so an
    iteration costs O(1) unless the estimate crosses into another pixel. Everything is summed
    exactly in integers: the result equals summing in floating point up to rounding.

    Pixel (j, i) of the window sits at flat index q = j * R + i, R = m + 4 (the pad columns and
    the tail carry zero weight), so that each sum is one long loop that LLVM vectorises.
    ``wpad``, ``tp``, ``cp``, ``gx``, ``gy``: from :func:`_refine_scratch` (``tp``: frame t
    around the window with a 2 px margin, the image's edge repeated beyond it; ``cp``: frame
    t+1 around (x0, y0) with the margin the estimate can use, within 1 px; both uint8). The
    sums are in the integer type of ``qs``: int32 where they cannot overflow, the gradients
    ``gx``, ``gy`` then int16, each sum one of a gradient times a pixel, a 16-bit multiply-add
    (vpmaddwd, vpdpwssd with AVX-512 VNNI); else int64 (:func:`refine_acc`). The centroid's
    sums, which outgrow int32 from 33 px windows on, in int64 there, each term in ``acc``.
    """
    acc = qs.dtype.type
    gx = g[0]
    gy = g[1]
    g_t = gx.dtype.type
    h, w = prev.shape
    m = 2 * n + 1
    stride = m + 4
    size = wpad.shape[0]
    # the sums run over the lanes up to the window's last pixel, in whole steps of
    # _pixel_dots: the gradients are zero beyond it (544 of a 21 px window's 640 lanes)
    used = ((m - 1) * stride + m + DOT_LANES - 1) // DOT_LANES * DOT_LANES
    if ax - n - 1 < 0 or ay - n - 1 < 0 or ax + n + 1 >= w or ay + n + 1 >= h:
        return False, x0, y0
    ix = int(np.floor(x0))
    iy = int(np.floor(y0))
    _patch(prev, ax - n - 2, ay - n - 2, m + 4, m + 4, tp, stride)
    # the bilinear samples never leave the image (the loop gives up first), so the part of
    # this patch outside it is never read
    _patch(curr, ix - n - 1, iy - n - 1, m + 3, m + 3, cp, stride)
    # twice the weighted central-difference gradient, and the sums of its products; the
    # template pixel is tp[q + c]. Offsets go into slices, not indices: a computed index
    # could be negative for all numba knows, and its fix-up per element turns vector loads
    # into gathers.
    c = 2 * stride + 2
    right = tp[c + 1:c + 1 + size]
    left = tp[c - 1:c - 1 + size]
    down = tp[c + stride:c + stride + size]
    up = tp[c - stride:c - stride + size]
    for q in range(size):
        gx[q] = g_t(wpad[q] * (np.int32(right[q]) - np.int32(left[q])))
        gy[q] = g_t(wpad[q] * (np.int32(down[q]) - np.int32(up[q])))
    # every sum a gradient (int16 where the sums are int32) times a pixel (uint8), in the
    # pairs of a 16-bit multiply-add (:func:`_pixel_dots`). The normal matrix's and the
    # second differences' sums are made of them: Sum gx (right - left) = xr - xl, and so on.
    xr, xl, xd, xu, xm, yr, yl, yd, yu, ym = _pixel_dots(
        gx, gy, tp, (c + 1, c - 1, c + stride, c - stride, c), used)
    h11 = acc(xr - xl)
    h12 = acc(xd - xu)
    h22 = acc(yd - yu)
    tx = xm
    ty = ym
    axx = acc(xr + xl - acc(2) * xm)
    axy = acc(xd + xu - acc(2) * xm)
    ayx = acc(yr + yl - acc(2) * ym)
    ayy = acc(yd + yu - acc(2) * ym)
    # the centroid's sums in int64 whatever ``acc`` (each term fits ``acc``, see refine_acc):
    # in ``acc`` they made the windows of 27 px or more (the auto-tuner's reference and sweep)
    # sum everything in int64, kernels of their own that no start-up warm-up compiled (a cold
    # first tuning cycle took 28 s, 25 of them compiling)
    vx = vy = wx = wy = sdx = sdy = shx = shy = np.int64(0)
    bxx = bxy = byx = byy = acc(0)
    centroid = third > 1.0
    if third > 0.0:
        # twice the third differences are right2 - left2 - 2 (right - left) and their y twin:
        # the gradients' products with the differences 4 px wide, less twice the normal
        # matrix's sums (below); summed a pixel at a time, as above
        xr2, xl2, xd2, xu2, yr2, yl2, yd2, yu2 = _pixel_dots(
            gx, gy, tp, (c + 2, c - 2, c + 2 * stride, c - 2 * stride), used)
        bxx = acc(xr2 - xl2)
        bxy = acc(xd2 - xu2)
        byx = acc(yr2 - yl2)
        byy = acc(yd2 - yu2)
    if centroid:
        # with ``centroid`` the centroid's sums, of W (2 g) (2 g . q) (half the third pass's
        # time where they were summed for every refinement): in int32 where no sum can
        # overflow it (``fast``, from _refine_scratch: the wide window's, uniform weights, up to
        # 31 px), as pixel dots, 125 ns a 21 x 21 window, 310 in int64 as the loop below
        qx = qs[0]
        qy = qs[1]
        if fast:
            # Sum gx (right - left) i + gx (down - up) j as pixel dots of the gradients times
            # i and j (int16: at most 255 n |W|), and the same of gy; and the turn's, of
            # (2 g) (2 g . R q), R q = (-j, i): Sum gx (down - up) i - gx (right - left) j
            # and the same of gy. Each call: both gradients times i (or j) with the pixels
            # right, left, down and up (x then y: 8 sums)
            kr, kl, kd, ku, lr, ll, ld, lu = _scaled_dots(
                gx, gy, g[2], tp, (c + 1, c - 1, c + stride, c - stride), used)
            mr, ml, md, mu, nr, nl, nd, nu = _scaled_dots(
                gx, gy, g[3], tp, (c + 1, c - 1, c + stride, c - stride), used)
            vx = np.int64(np.int32(np.int32(kr - kl) + np.int32(md - mu)))
            vy = np.int64(np.int32(np.int32(lr - ll) + np.int32(nd - nu)))
            wx = np.int64(np.int32(np.int32(kd - ku) - np.int32(mr - ml)))
            wy = np.int64(np.int32(np.int32(ld - lu) - np.int32(nr - nl)))
            # and the stretch's, (2 g) (2 g . (i, -j)), and the shear's, (2 g) (2 g . (j, i))
            sdx = np.int64(np.int32(np.int32(kr - kl) - np.int32(md - mu)))
            sdy = np.int64(np.int32(np.int32(lr - ll) - np.int32(nd - nu)))
            shx = np.int64(np.int32(np.int32(mr - ml) + np.int32(kd - ku)))
            shy = np.int64(np.int32(np.int32(nr - nl) + np.int32(ld - lu)))
        else:
            for q in range(size):
                # each term in ``acc`` (numba types int32 * int32 as int64: 64-bit products)
                along = acc(acc(acc(acc(right[q]) - acc(left[q])) * qx[q])
                            + acc(acc(acc(down[q]) - acc(up[q])) * qy[q]))
                turn = acc(acc(acc(acc(down[q]) - acc(up[q])) * qx[q])
                           - acc(acc(acc(right[q]) - acc(left[q])) * qy[q]))
                stretch = acc(acc(acc(acc(right[q]) - acc(left[q])) * qx[q])
                              - acc(acc(acc(down[q]) - acc(up[q])) * qy[q]))
                shear = acc(acc(acc(acc(right[q]) - acc(left[q])) * qy[q])
                            + acc(acc(acc(down[q]) - acc(up[q])) * qx[q]))
                vx += np.int64(acc(acc(gx[q]) * along))
                vy += np.int64(acc(acc(gy[q]) * along))
                wx += np.int64(acc(acc(gx[q]) * turn))
                wy += np.int64(acc(acc(gy[q]) * turn))
                sdx += np.int64(acc(acc(gx[q]) * stretch))
                sdy += np.int64(acc(acc(gy[q]) * stretch))
                shx += np.int64(acc(acc(gx[q]) * shear))
                shy += np.int64(acc(acc(gy[q]) * shear))
    # the sums of the gradients' products with twice the third differences
    gxx3 = float(bxx) - 2.0 * h11 if third > 0.0 else 0.0
    gxy3 = float(bxy) - 2.0 * h12 if third > 0.0 else 0.0
    gyx3 = float(byx) - 2.0 * h12 if third > 0.0 else 0.0
    gyy3 = float(byy) - 2.0 * h22 if third > 0.0 else 0.0
    # the normal matrix of the half-gradient: the same floats as summing it in float64
    f11 = 0.25 * h11
    f12 = 0.25 * h12
    f22 = 0.25 * h22
    det = f11 * f22 - f12 * f12
    if det <= 1e-6 * (f11 + f22) * (f11 + f22) or det <= 0.0:
        return False, x0, y0
    if centroid:
        cen[0] = 0.25 * (f22 * vx - f12 * vy) / det
        cen[1] = 0.25 * (f11 * vy - f12 * vx) / det
        cen[2] = 0.25 * (f22 * wx - f12 * wy) / det
        cen[3] = 0.25 * (f11 * wy - f12 * wx) / det
        cen[4] = 0.25 * (f22 * sdx - f12 * sdy) / det
        cen[5] = 0.25 * (f11 * sdy - f12 * sdx) / det
        cen[6] = 0.25 * (f22 * shx - f12 * shy) / det
        cen[7] = 0.25 * (f11 * shy - f12 * shx) / det
    x = x0
    y = y0
    cbx = cby = -(1 << 30)  # the pixel whose corner correlations are in sx.., sy..
    sx00 = sx01 = sx10 = sx11 = sy00 = sy01 = sy10 = sy11 = 0
    for _ in range(GN_ITERATIONS):
        if x - n < 0 or y - n < 0 or x + n + 1 >= w or y + n + 1 >= h:
            return False, x0, y0
        bx0 = int(np.floor(x))
        by0 = int(np.floor(y))
        fx = x - bx0
        fy = y - by0
        if bx0 != cbx or by0 != cby:
            off = (by0 - iy + 1) * stride + bx0 - ix + 1
            sx00, sx01, sx10, sx11, sy00, sy01, sy10, sy11 = _corners(gx, gy, cp, off, stride, used)
            cbx = bx0
            cby = by0
        w00 = (1 - fx) * (1 - fy)
        w01 = fx * (1 - fy)
        w10 = (1 - fx) * fy
        w11 = fx * fy
        # the interpolation terms of the sample (the template's pixels need none)
        cx = 0.5 * fx * (1.0 - fx)
        cy = 0.5 * fy * (1.0 - fy)
        # and f (1 - f) (1 - 2 f) / 12 of twice the third differences
        ex = cx * (1.0 - 2.0 * fx) / 6.0
        ey = cy * (1.0 - 2.0 * fy) / 6.0
        # sum over the window of gradient * (bilinear sample - template - correction)
        b1 = 0.5 * (w00 * sx00 + w01 * sx01 + w10 * sx10 + w11 * sx11 - tx - cx * axx
                    - cy * axy - ex * gxx3 - ey * gxy3)
        b2 = 0.5 * (w00 * sy00 + w01 * sy01 + w10 * sy10 + w11 * sy11 - ty - cx * ayx
                    - cy * ayy - ex * gyx3 - ey * gyy3)
        ddx = (f22 * b1 - f12 * b2) / det
        ddy = (f11 * b2 - f12 * b1) / det
        x -= ddx
        y -= ddy
        if abs(x - x0) > 1.0 or abs(y - y0) > 1.0:
            return False, x, y  # where it strayed to (:func:`.pyramid._follow_one`)
        if ddx * ddx + ddy * ddy < GN_STEP_PX * GN_STEP_PX:
            break
    return True, x, y


@nb.njit(**NO_NRT)
def _refine_with(prev, curr, ax, ay, x0, y0, n, scratch, third):  # pragma: no cover - numba
    """:func:`_refine` with the scratch of :func:`_refine_scratch`; ``third``: 1.0 or 0.0
    (:data:`THIRD`, :data:`NO_THIRD`)."""
    wpad, tp, cp, g, qs, cen, fast = scratch
    return _refine(prev, curr, ax, ay, x0, y0, n, wpad, tp, cp, g, third, qs, cen, fast)


@nb.njit(**NO_NRT)
def _parabola(pf, cf, w, h, ax, ay, qx, qy, n, wts, uniform, best):  # pragma: no cover
    """The sub-pixel offsets (ox, oy), each within +-0.5, of a parabola per axis through S at
    the integer minimum (qx, qy) and its two neighbours, where both neighbours' windows fit
    frame t+1 (else 0): the fallback where Gauss-Newton cannot run."""
    ox = oy = 0.0
    if n < qx < w - 1 - n:
        sl = _ssd_at(pf, cf, w, ax, ay, qx - 1, qy, n, wts, uniform, BIG)
        sr = _ssd_at(pf, cf, w, ax, ay, qx + 1, qy, n, wts, uniform, BIG)
        den = sl - 2 * best + sr
        if den > 0:
            ox = min(max(0.5 * (sl - sr) / den, -0.5), 0.5)
    if n < qy < h - 1 - n:
        su = _ssd_at(pf, cf, w, ax, ay, qx, qy - 1, n, wts, uniform, BIG)
        sd = _ssd_at(pf, cf, w, ax, ay, qx, qy + 1, n, wts, uniform, BIG)
        den = su - 2 * best + sd
        if den > 0:
            oy = min(max(0.5 * (su - sd) / den, -0.5), 0.5)
    return ox, oy


@nb.njit(cache=True, nogil=True)
def _subpixel(prev, curr, anchors, n, wts, uniform, acc, out_pos, out_ssd,
              out_ok):  # pragma: no cover - numba
    """Refine the integer minima in ``out_pos`` in place: Gauss-Newton (:func:`_refine`) from
    each, or a parabola per axis (:func:`_parabola`) where it cannot run (window at the
    border, no texture)."""
    h, w = prev.shape
    pf = prev.ravel()
    cf = curr.ravel()
    scratch = _refine_scratch(wts, acc)
    for f in range(anchors.shape[0]):
        if not out_ok[f]:
            continue
        ax = anchors[f, 0]
        ay = anchors[f, 1]
        qx = int(out_pos[f, 0])
        qy = int(out_pos[f, 1])
        refined, x, y = _refine_with(prev, curr, ax, ay, float(qx), float(qy), n, scratch, THIRD)
        if not refined:
            ox, oy = _parabola(pf, cf, w, h, ax, ay, qx, qy, n, wts, uniform, out_ssd[f])
            x = qx + ox
            y = qy + oy
        out_pos[f, 0] = x
        out_pos[f, 1] = y


#: the largest |x| or |y| of a point or prediction the searches take, px
#: (:func:`track_ssd`, :func:`.pyramid.track_pyramid`): far beyond any frame (a point outside
#: the frame is simply not found), and within the kernels' integers: an index near the int64
#: limit overflowed the bounds checks' sums and read memory at random (SIGSEGV)
MAX_COORD = 2.0 ** 30
#: the sub-pixel sums' type given to :func:`_track` without sub-pixel refinement (unused): one
#: array for every call, not a new one (~0.2 us of the ~4 us a call costs around the search)
_NO_REFINE = np.empty(0, np.int32)
#: :func:`track_ssd`'s status when the caller wants none (:func:`_track` makes its own)
_NO_STATUS = np.empty(0, np.int8)


def _points(points: np.ndarray, name: str) -> np.ndarray:
    """``points`` as an (N, 2) C-contiguous int64 array: the array itself when it is one
    already (the tracker's), without the reshape's new view (~0.2 us). Floats must be finite
    within +-MAX_COORD (NaN became the int64 minimum); integers are checked in the kernel."""
    points = np.asarray(points)
    if points.dtype.kind not in "iub":
        if points.dtype.kind != "f":
            raise ValueError(f"{name} must be numbers (x, y px): got dtype {points.dtype}")
        _within(points.reshape(-1, 2), name)
    points = np.ascontiguousarray(points, np.int64)
    if points.ndim == 2 and points.shape[1] == 2:
        return points
    return points.reshape(-1, 2)


def _within(xy: np.ndarray, name: str) -> None:
    """Raise the error that names the first point of ``xy`` not finite within +-MAX_COORD."""
    out = ~((xy >= -MAX_COORD) & (xy <= MAX_COORD)).all(axis=1)  # NaN fails both
    if out.any():
        bad = xy[out][0]
        raise ValueError(f"{name} must be finite x, y px within +-{MAX_COORD:g}: got "
                         f"({bad[0]:g}, {bad[1]:g})")


def track_ssd(prev: np.ndarray, curr: np.ndarray, anchors: np.ndarray, centers: np.ndarray, *,
              corr_half: int, search_half: int, weights: np.ndarray,
              subpixel: bool = False, search: str = "pruned", work: int = NO_BUDGET,
              status: np.ndarray | None = None
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Find each feature of frame t in frame t+1 by the SSD of Eq. (1).

    Parameters
    ----------
    prev, curr : (H, W) uint8 frames t and t+1.
    anchors : (N, 2) int x, y in ``prev``: the centres c of the correlation windows.
    centers : (N, 2) int x, y in ``curr``: the predicted positions, centres of the search.
    corr_half : n of Eq. (1); the window is (2n+1)^2.
    search_half : half-width of the search window; (2 s + 1)^2 displacements are scored.
    weights : (2n+1, 2n+1) int32 W(i, j) >= 0, see :func:`window_weights`.
    subpixel : refine the integer minimum to a continuous one: Gauss-Newton on Eq. (1) with
        bilinear sampling (:func:`_refine`), falling back to a parabola per axis through the
        minimum and its neighbours where Gauss-Newton cannot run (window at the border, no
        texture).
    search : how the argmin is found; both give the same positions, S and ``ok``:
        ``"pruned"`` (default) visits only the displacements the bounds cannot rule out (see
        the module notes), ``"exhaustive"`` scores every displacement in full, the paper's
        plain Eq. (1), whose cost is proportional to (2s+1)^2 (2n+1)^2 per feature.
    work : the searches these features may make, window pixels x displacements; a feature
        whose search would exceed what is left is not searched (not ``ok``; status OVER).
        Default: no limit, the paper's search.
    status : (N,) int8 array to fill with why each feature was or was not found (OK, BORDER,
        LEFT, CUT or OVER); None: not wanted.

    Returns
    -------
    pos : (N, 2) float64 x, y of the best match in ``curr`` (NaN where not found);
    ssd : (N,) float64 S at the best match (inf where not found);
    ok : (N,) bool, False where the template leaves ``prev``, no search position fits
    ``curr``, or the search was over ``work``.
    """
    if search not in SEARCH_KINDS:
        raise ValueError(f"search={search!r} is not allowed: use one of "
                         f"{', '.join(SEARCH_KINDS)}")
    prev = np.ascontiguousarray(prev, np.uint8)
    curr = np.ascontiguousarray(curr, np.uint8)
    if prev.shape != curr.shape or prev.ndim != 2:
        raise ValueError(f"frames must be 2-D and of one size, got {prev.shape} and {curr.shape}")
    m = 2 * corr_half + 1
    if weights.shape != (m, m):
        raise ValueError(f"weights of shape {weights.shape} do not match corr_half={corr_half}")
    wts = np.ascontiguousarray(weights, np.int32)
    anchors = _points(anchors, "anchors")
    centers = _points(centers, "centers")
    if centers.shape != anchors.shape:
        raise ValueError(f"anchors {anchors.shape} and centers {centers.shape} differ in shape")
    n_feat = anchors.shape[0]
    pos = np.empty((n_feat, 2), np.float64)
    ssd = np.empty(n_feat, np.float64)
    ok = np.empty(n_feat, np.bool_)
    if not 0 <= work <= NO_BUDGET:
        raise ValueError(f"work must be 0 to {NO_BUDGET}: got {work}")
    if status is None:
        status = _NO_STATUS
    elif status.shape != (n_feat,) or status.dtype != np.int8:
        raise ValueError(f"status must be a ({n_feat},) int8 array")
    if _track(prev, curr, anchors, centers, int(corr_half), int(search_half), wts,
              bool(subpixel), search == "exhaustive",
              refine_acc(wts) if subpixel else _NO_REFINE, int(work), pos, ssd, ok, status) < 0:
        _within(anchors, "anchors")  # the kernel refused one beyond +-MAX_COORD
        _within(centers, "centers")
    return pos, ssd, ok


@nb.njit(cache=True, nogil=True)
def _surface(prev, curr, ax, ay, cx, cy, n, s, wts, out):  # pragma: no cover - numba
    h, w = prev.shape
    for dy in range(-s, s + 1):
        for dx in range(-s, s + 1):
            qx = cx + dx
            qy = cy + dy
            if (qx - n < 0 or qy - n < 0 or qx + n >= w or qy + n >= h
                    or ax - n < 0 or ay - n < 0 or ax + n >= w or ay + n >= h):
                out[dy + s, dx + s] = np.inf
                continue
            acc = 0
            for j in range(-n, n + 1):
                for i in range(-n, n + 1):
                    d = np.int64(prev[ay + j, ax + i]) - np.int64(curr[qy + j, qx + i])
                    acc += wts[j + n, i + n] * d * d
            out[dy + s, dx + s] = acc


def ssd_surface(prev: np.ndarray, curr: np.ndarray, anchor: tuple[int, int],
                center: tuple[int, int], *, corr_half: int, search_half: int,
                weights: np.ndarray) -> np.ndarray:
    """The whole S(c, d) of Eq. (1) over the search window, for analysis and plots.

    Returns a (2s+1, 2s+1) float64 array indexed [dy + s, dx + s]; positions whose window leaves
    either frame are ``inf``.
    """
    s = int(search_half)
    out = np.empty((2 * s + 1, 2 * s + 1), np.float64)
    _surface(np.ascontiguousarray(prev, np.uint8), np.ascontiguousarray(curr, np.uint8),
             int(anchor[0]), int(anchor[1]), int(center[0]), int(center[1]), int(corr_half), s,
             np.ascontiguousarray(weights, np.int64), out)
    return out
