"""Position estimation: centroid and scatter of Eq. (2), and robust incremental motion.

Eq. (2) of the paper, over the N feature points (x_i, y_i) with centroid (xbar, ybar):

    x_e = sum_i |xbar - x_i|        y_e = sum_i |ybar - y_i|

Image motion along X is read from the centroid and along Z (approach / recede) from the scatter.
The paper uses the raw sums, which jump when features are lost (its Table 1b: 379 -> 40 as NPI
goes 19 -> 8), so we also estimate the motion from the features matched in two consecutive
frames only (:func:`incremental_motion`), which a lost feature cannot disturb.

The arithmetic runs in numba kernels (a frame's few dozen small numpy calls cost ~100 us) that
reproduce numpy's bit for bit: a column mean of an (N, 2) array sums each column in order, a
sum over a whole array sums pairwise as numpy does (:func:`_pairwise_sum`), ``hypot`` is the C
library's in both.
"""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(cache=True, nogil=True)
def _pairwise_block(a, lo, n):  # pragma: no cover - numba
    """numpy's sum of a block of up to 128: 8 running sums, combined pairwise, then the rest."""
    if n < 8:
        res = 0.0
        for i in range(lo, lo + n):
            res += a[i]
        return res
    r0 = a[lo]
    r1 = a[lo + 1]
    r2 = a[lo + 2]
    r3 = a[lo + 3]
    r4 = a[lo + 4]
    r5 = a[lo + 5]
    r6 = a[lo + 6]
    r7 = a[lo + 7]
    i = 8
    while i < n - n % 8:
        r0 += a[lo + i]
        r1 += a[lo + i + 1]
        r2 += a[lo + i + 2]
        r3 += a[lo + i + 3]
        r4 += a[lo + i + 4]
        r5 += a[lo + i + 5]
        r6 += a[lo + i + 6]
        r7 += a[lo + i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


@nb.njit(cache=True, nogil=True)
def _pairwise_sum(a, n):  # pragma: no cover - numba
    """Sum of a[:n] in numpy's order (``np.add.reduce`` of a contiguous float64 array): blocks
    of up to 128 (:func:`_pairwise_block`), above that the sum of the two halves (the first
    rounded down to a multiple of 8), recursively.

    The recursion runs on an explicit stack: numba's cache does not handle recursive functions.
    """
    # np.int64(0), not 0: a literal argument would compile _pairwise_block a second time
    lo = np.int64(0)
    if n <= 128:
        return _pairwise_block(a, lo, n)
    depth = 64
    s_lo = np.empty(depth, np.int64)
    s_n = np.empty(depth, np.int64)
    s_left = np.empty(depth, np.float64)  # the left half's sum, once known
    s_stage = np.empty(depth, np.int64)  # 0: not split yet, 1: left pending, 2: right pending
    s_lo[0] = lo
    s_n[0] = n
    s_stage[0] = 0
    top = 1
    while True:
        i = top - 1
        half = s_n[i] // 2
        half -= half % 8
        if s_stage[i] == 0 and s_n[i] > 128:
            s_stage[i] = 1
            s_lo[top] = s_lo[i]
            s_n[top] = half
            s_stage[top] = 0
            top += 1
            continue
        ret = _pairwise_block(a, s_lo[i], s_n[i])
        top -= 1
        # hand the value up until a node still needs its right half
        while top > 0:
            i = top - 1
            if s_stage[i] == 1:
                half = s_n[i] // 2
                half -= half % 8
                s_left[i] = ret
                s_stage[i] = 2
                s_lo[top] = s_lo[i] + half
                s_n[top] = s_n[i] - half
                s_stage[top] = 0
                top += 1
                break
            ret = s_left[i] + ret
            top -= 1
        if top == 0:
            return ret


@nb.njit(cache=True, nogil=True)
def _column_means(p, keep):  # pragma: no cover - numba
    """``p[keep].mean(axis=0)`` and the number kept: each column summed in order."""
    sx = 0.0
    sy = 0.0
    count = 0
    for i in range(p.shape[0]):
        if keep[i]:
            sx += p[i, 0]
            sy += p[i, 1]
            count += 1
    return sx / count, sy / count, count


@nb.njit(cache=True, nogil=True)
def _centroid_scatter(pts):  # pragma: no cover - numba
    n = pts.shape[0]
    keep = np.ones(n, np.bool_)
    xc, yc, _ = _column_means(pts, keep)
    dev = np.empty(n, np.float64)
    for i in range(n):
        dev[i] = abs(xc - pts[i, 0])
    xe = _pairwise_sum(dev, n)
    for i in range(n):
        dev[i] = abs(yc - pts[i, 1])
    ye = _pairwise_sum(dev, n)
    return xc, yc, xe, ye


def centroid_scatter(points: np.ndarray) -> tuple[float, float, float, float]:
    """Eq. (2): centroid (xc, yc) and scatter (xe, ye), all in px.

    Parameters
    ----------
    points : (N, 2) x, y feature positions.

    Returns
    -------
    xc, yc, xe, ye ; NaN centroid and zero scatter when there are no points.
    """
    pts = np.ascontiguousarray(points, np.float64).reshape(-1, 2)
    if len(pts) == 0:
        return float("nan"), float("nan"), 0.0, 0.0
    xc, yc, xe, ye = _centroid_scatter(pts)
    return float(xc), float(yc), float(xe), float(ye)


@nb.njit(cache=True, nogil=True)
def _median_small(v):  # pragma: no cover - numba
    """The median of ``v`` (non-empty, no NaN), reordering it in place: Hoare's selection of
    its middle value, then, where ``n`` is even, the largest of those left below it. No
    allocation, O(n): on 95 values 165 ns against 404 for the Shell sort it replaces, on 190
    371 against 5984 (the same values)."""
    n = v.shape[0]
    k = n // 2
    lo = 0
    hi = n - 1
    while hi > lo:
        # the median of three as the pivot; Hoare's partition around it
        a = v[lo]
        b = v[(lo + hi) >> 1]
        c = v[hi]
        if a > b:
            a, b = b, a
        if b > c:
            b = c
        pivot = a if a > b else b
        i = lo
        j = hi
        while i <= j:
            while v[i] < pivot:
                i += 1
            while v[j] > pivot:
                j -= 1
            if i <= j:
                t = v[i]
                v[i] = v[j]
                v[j] = t
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            break  # v[j + 1:i] all equal the pivot, k among them
    m = v[k]
    if n % 2:
        return m
    below = v[0]  # v[:k] holds the k smallest: their largest is the lower middle value
    for i in range(1, k):
        if v[i] > below:
            below = v[i]
    return 0.5 * (below + m)


@nb.njit(cache=True, nogil=True)
def _median(v):  # pragma: no cover - numba
    """``np.median`` of a non-empty 1-D float64 array without NaN, on a copy (the same value:
    :func:`_median_small` selects it, which numba compiles in a fraction of the time of its
    quicksort behind ``np.sort``)."""
    return _median_small(v.copy())


@nb.njit(cache=True, nogil=True)
def _similarity_inliers_nb(a, b, rounds):  # pragma: no cover - numba
    n = a.shape[0]
    keep = np.ones(n, np.bool_)
    kept = n
    da = np.empty((n, 2), np.float64)
    r = np.empty(n, np.float64)
    for _ in range(rounds):
        if kept < 3:
            break
        cax, cay, _ = _column_means(a, keep)
        cbx, cby, _ = _column_means(b, keep)
        for i in range(n):
            da[i, 0] = a[i, 0] - cax
            da[i, 1] = a[i, 1] - cay
        # the kept rows of da ** 2 and of da * (b - cb), flattened in C order as numpy sums them
        sq = np.empty(2 * kept, np.float64)
        cross = np.empty(2 * kept, np.float64)
        j = 0
        for i in range(n):
            if keep[i]:
                sq[j] = da[i, 0] * da[i, 0]
                sq[j + 1] = da[i, 1] * da[i, 1]
                cross[j] = da[i, 0] * (b[i, 0] - cbx)
                cross[j + 1] = da[i, 1] * (b[i, 1] - cby)
                j += 2
        denom = _pairwise_sum(sq, 2 * kept)
        s = _pairwise_sum(cross, 2 * kept) / denom if denom > 1e-12 else 1.0
        for i in range(n):
            r[i] = np.hypot(b[i, 0] - cbx - s * da[i, 0], b[i, 1] - cby - s * da[i, 1])
        rk = np.empty(kept, np.float64)
        j = 0
        for i in range(n):
            if keep[i]:
                rk[j] = r[i]
                j += 1
        mad = 1.4826 * _median(rk)
        lim = max(3.0 * mad, 0.5)
        same = True
        kept = 0
        for i in range(n):
            new = r[i] <= lim
            if new != keep[i]:
                same = False
            kept += new
        if same:
            break
        for i in range(n):
            keep[i] = r[i] <= lim
    return keep


def _similarity_inliers(a: np.ndarray, b: np.ndarray, rounds: int = 3) -> np.ndarray:
    """Mask of point pairs that agree with one translation + isotropic scale.

    Least-squares fit of ``b - mean(b) = s (a - mean(a))``, then pairs whose residual exceeds
    3 robust sigmas (MAD, at least 0.5 px) are left out and the fit repeated. A plain median
    of the displacements would reject the genuine outer points of a scale change.
    """
    return _similarity_inliers_nb(np.ascontiguousarray(a, np.float64),
                                  np.ascontiguousarray(b, np.float64), int(rounds))


@nb.njit(cache=True, nogil=True)
def _spread(p, keep, count):  # pragma: no cover - numba
    """Mean distance of the kept points to their centroid, as numpy computes it."""
    cx, cy, _ = _column_means(p, keep)
    dist = np.empty(count, np.float64)
    j = 0
    for i in range(p.shape[0]):
        if keep[i]:
            dist[j] = np.hypot(p[i, 0] - cx, p[i, 1] - cy)
            j += 1
    return _pairwise_sum(dist, count) / count


@nb.njit(cache=True, nogil=True)
def _incremental_motion(a, b):  # pragma: no cover - numba
    n = a.shape[0]
    if n >= 3:
        keep = _similarity_inliers_nb(a, b, 3)
    else:
        keep = np.ones(n, np.bool_)
    diff = np.empty((n, 2), np.float64)
    for i in range(n):
        diff[i, 0] = b[i, 0] - a[i, 0]
        diff[i, 1] = b[i, 1] - a[i, 1]
    dx, dy, count = _column_means(diff, keep)
    scale = 1.0
    if count >= 3:
        spread_a = _spread(a, keep, count)
        spread_b = _spread(b, keep, count)
        if spread_a > 1e-9:
            scale = spread_b / spread_a
    return dx, dy, scale


def incremental_motion(before: np.ndarray, after: np.ndarray) -> tuple[float, float, float]:
    """Image motion between two frames from the same features seen in both.

    Parameters
    ----------
    before, after : (N, 2) x, y of the matched features in frames t and t+1.

    Returns
    -------
    dx, dy : mean displacement of the inliers, px. Inliers are the pairs consistent with one
        translation and scale (:func:`_similarity_inliers`), so mismatches cannot drag it.
    scale : ratio of the inliers' mean distance to their centroid, after / before (> 1 when the
        target grows: the camera approaches it); 1 when fewer than 3 inliers.
    """
    a = np.ascontiguousarray(before, np.float64).reshape(-1, 2)
    b = np.ascontiguousarray(after, np.float64).reshape(-1, 2)
    if a.shape != b.shape:
        raise ValueError(f"before {a.shape} and after {b.shape} must have one shape")
    if len(a) == 0:
        return 0.0, 0.0, 1.0
    dx, dy, scale = _incremental_motion(a, b)
    return float(dx), float(dy), float(scale)
