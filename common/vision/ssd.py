"""SSD correlation search, Eq. (1) of the paper.

    S(c, d) = sum_{j=-n..n} sum_{i=-n..n} W(i, j) [I_t(c + (i, j)) - I_{t+1}(c + d + (i, j))]^2

For each feature at c in frame t, every displacement d whose centre c + d lies in the search
window (half-width SEARCH_SIZE // 2, centred at the predicted position) is scored, and the new
position is the argmin. n = CORR_SIZE // 2.

The search is exact (it returns the same argmin as scoring every displacement, ties going to the
first in row-major order like ``cv2.minMaxLoc``) but does far less work than the brute force:

* displacements are visited from the predicted position outwards, so a good match is found early;
* a displacement's sum is abandoned as soon as its partial sum exceeds the best so far (the terms
  are non-negative, so it can no longer win): successive-elimination pruning;
* all arithmetic is in integers on small contiguous copies of the template and search patch.

Sub-pixel refinement minimises the same Eq. (1) over a continuous displacement (Gauss-Newton
from the integer minimum). A parabola through the minimum and its neighbours, the classic
shortcut, is biased towards integer positions ("pixel locking"): on the Middlebury sequences its
median end-point error was 2 to 4 times that of Gauss-Newton, so it is only the fallback.
"""

from __future__ import annotations

import numba as nb
import numpy as np

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


@nb.njit(cache=True, nogil=True)
def _spiral(s):  # pragma: no cover - numba
    """Offsets (dy, dx) of a (2s+1)^2 window ordered by ring (Chebyshev distance)."""
    m = 2 * s + 1
    out = np.empty((m * m, 2), np.int64)
    k = 0
    out[0, 0] = 0
    out[0, 1] = 0
    k = 1
    for r in range(1, s + 1):
        for dy in range(-r, r + 1):
            for dx in range(-r, r + 1):
                if max(abs(dy), abs(dx)) == r:
                    out[k, 0] = dy
                    out[k, 1] = dx
                    k += 1
    return out


@nb.njit(cache=True, nogil=True)
def _window_ssd(tmpl, patch, py, px, wts, uniform, m, bound):  # pragma: no cover - numba
    """SSD of template vs patch[py:py+m, px:px+m]; stops (returning > bound) once it exceeds
    ``bound``. Row-wise checks keep the branch out of the innermost loop."""
    acc = 0
    for j in range(m):
        row = patch[py + j]
        trow = tmpl[j]
        if uniform:
            for i in range(m):
                d = trow[i] - row[px + i]
                acc += d * d
        else:
            wrow = wts[j]
            for i in range(m):
                d = trow[i] - row[px + i]
                acc += wrow[i] * d * d
        if acc > bound:
            return acc
    return acc


@nb.njit(cache=True, nogil=True)
def _window_ssd_u(tmpl, patch, py, px, m, bound):  # pragma: no cover - numba
    """Uniform-weight SSD in int32 (exact: 129^2 * 255^2 < 2^31), same early exit."""
    acc = np.int32(0)
    for j in range(m):
        row = patch[py + j]
        trow = tmpl[j]
        for i in range(m):
            d = trow[i] - row[px + i]
            acc += d * d
        if acc > bound:
            return acc
    return acc


@nb.njit(cache=True, nogil=True)
def _refine(prev, curr, ax, ay, x0, y0, n, wts):  # pragma: no cover - numba
    """Minimise Eq. (1) over a continuous displacement, starting at the integer minimum.

    Inverse-compositional Gauss-Newton for a translation (Baker and Matthews 2004): the template
    gradient and the 2x2 normal matrix are computed once, each iteration samples frame t+1
    bilinearly. Returns (converged, x, y); it gives up (False) if the window would leave the
    image, the template has no texture, or the estimate strays more than 1 px from (x0, y0).
    """
    h, w = prev.shape
    m = 2 * n + 1
    if ax - n - 1 < 0 or ay - n - 1 < 0 or ax + n + 1 >= w or ay + n + 1 >= h:
        return False, x0, y0
    gxs = np.empty((m, m), np.float64)
    gys = np.empty((m, m), np.float64)
    h11 = 0.0
    h12 = 0.0
    h22 = 0.0
    for j in range(m):
        for i in range(m):
            yy = ay - n + j
            xx = ax - n + i
            gx = 0.5 * (float(prev[yy, xx + 1]) - float(prev[yy, xx - 1]))
            gy = 0.5 * (float(prev[yy + 1, xx]) - float(prev[yy - 1, xx]))
            wt = float(wts[j, i])
            gxs[j, i] = wt * gx
            gys[j, i] = wt * gy
            h11 += wt * gx * gx
            h12 += wt * gx * gy
            h22 += wt * gy * gy
    det = h11 * h22 - h12 * h12
    if det <= 1e-6 * (h11 + h22) * (h11 + h22) or det <= 0.0:
        return False, x0, y0
    x = x0
    y = y0
    for _ in range(10):
        if x - n < 0 or y - n < 0 or x + n + 1 >= w - 1 or y + n + 1 >= h - 1:
            return False, x0, y0
        bx0 = int(np.floor(x))
        by0 = int(np.floor(y))
        fx = x - bx0
        fy = y - by0
        w00 = (1 - fx) * (1 - fy)
        w01 = fx * (1 - fy)
        w10 = (1 - fx) * fy
        w11 = fx * fy
        b1 = 0.0
        b2 = 0.0
        for j in range(m):
            r0 = by0 - n + j
            for i in range(m):
                c0 = bx0 - n + i
                v = (w00 * curr[r0, c0] + w01 * curr[r0, c0 + 1]
                     + w10 * curr[r0 + 1, c0] + w11 * curr[r0 + 1, c0 + 1])
                e = v - float(prev[ay - n + j, ax - n + i])
                b1 += gxs[j, i] * e
                b2 += gys[j, i] * e
        ddx = (h22 * b1 - h12 * b2) / det
        ddy = (h11 * b2 - h12 * b1) / det
        x -= ddx
        y -= ddy
        if abs(x - x0) > 1.0 or abs(y - y0) > 1.0:
            return False, x0, y0
        if ddx * ddx + ddy * ddy < 1e-4:
            break
    return True, x, y


@nb.njit(cache=True, nogil=True)
def _track(prev, curr, anchors, centers, n, s, wts, uniform, subpixel,
           out_pos, out_ssd, out_ok):  # pragma: no cover - numba
    h, w = prev.shape
    m = 2 * n + 1
    side = 2 * s + 1
    order = _spiral(s)
    big = np.int64(1) << 50  # > any S (129^2 px * 255^2 * 64), and big * m fits int64
    big32 = np.int64(2**31 - 1)
    tmpl = np.empty((m, m), np.int32)
    pm = side + m + 1
    patch = np.empty((pm, pm), np.int32)
    trs = np.empty(m, np.int64)
    rs = np.empty((pm, pm - m + 1), np.int64)
    for f in range(anchors.shape[0]):
        ax = anchors[f, 0]
        ay = anchors[f, 1]
        cx = centers[f, 0]
        cy = centers[f, 1]
        out_ok[f] = 0
        out_ssd[f] = np.inf
        out_pos[f, 0] = np.nan
        out_pos[f, 1] = np.nan
        if ax - n < 0 or ay - n < 0 or ax + n >= w or ay + n >= h:
            continue  # the template itself leaves frame t
        for j in range(m):
            for i in range(m):
                tmpl[j, i] = prev[ay - n + j, ax - n + i]
        # patch holds frame t+1 around the search window, one spare pixel each side for the
        # sub-pixel neighbours; origin at (cx - s - n - 1, cy - s - n - 1)
        ox = cx - s - n - 1
        oy = cy - s - n - 1
        for j in range(pm):
            yy = oy + j
            for i in range(pm):
                xx = ox + i
                if 0 <= yy < h and 0 <= xx < w:
                    patch[j, i] = curr[yy, xx]
                else:
                    patch[j, i] = 0
        # valid centres: the whole correlation window inside frame t+1
        lo_x = max(cx - s, n)
        hi_x = min(cx + s, w - 1 - n)
        lo_y = max(cy - s, n)
        hi_y = min(cy + s, h - 1 - n)
        if lo_x > hi_x or lo_y > hi_y:
            continue
        if uniform:
            # multilevel successive elimination (Gao et al. 2000): by Cauchy-Schwarz on each
            # row, S >= sum_j (rowsum T_j - rowsum I_j)^2 / m, a bound from row sums that are
            # cheap to share between displacements; a window whose bound already exceeds the
            # best S cannot win and is skipped without touching its pixels
            for j in range(m):
                acc_t = 0
                for i in range(m):
                    acc_t += tmpl[j, i]
                trs[j] = acc_t
            for j in range(pm):
                acc_r = 0
                for i in range(m):
                    acc_r += patch[j, i]
                rs[j, 0] = acc_r
                for i in range(1, pm - m + 1):
                    acc_r += patch[j, i + m - 1] - patch[j, i - 1]
                    rs[j, i] = acc_r
        best = big
        best_rank = side * side
        bdy = 0
        bdx = 0
        for k in range(order.shape[0]):
            dy = order[k, 0]
            dx = order[k, 1]
            qx = cx + dx
            qy = cy + dy
            if qx < lo_x or qx > hi_x or qy < lo_y or qy > hi_y:
                continue
            py = dy + s + 1
            px = dx + s + 1
            if uniform:
                lim = best * m
                bnd = 0
                for j in range(m):
                    diff = trs[j] - rs[py + j, px]
                    bnd += diff * diff
                    if bnd > lim:
                        break
                if bnd > lim:
                    continue
                v = np.int64(_window_ssd_u(tmpl, patch, py, px, m, min(best, big32)))
            else:
                v = _window_ssd(tmpl, patch, py, px, wts, uniform, m, best)
            rank = (dy + s) * side + (dx + s)
            if v < best or (v == best and rank < best_rank):
                best = v
                best_rank = rank
                bdy = dy
                bdx = dx
        qx = cx + bdx
        qy = cy + bdy
        # a minimum on an edge that the image cut short may be a piece of a minimum outside the
        # image: the feature is leaving the image, so it is lost rather than pinned to the edge
        if ((qx == lo_x and lo_x > cx - s) or (qx == hi_x and hi_x < cx + s)
                or (qy == lo_y and lo_y > cy - s) or (qy == hi_y and hi_y < cy + s)):
            continue
        fx = float(qx)
        fy = float(qy)
        refined = False
        if subpixel:
            refined, gx, gy = _refine(prev, curr, ax, ay, float(qx), float(qy), n, wts)
            if refined:
                fx = gx
                fy = gy
        if subpixel and not refined:
            # parabola through S at the minimum and its two neighbours, per axis; only where
            # both neighbours are valid positions of the same search
            if qx - 1 >= lo_x and qx + 1 <= hi_x:
                sl = _window_ssd(tmpl, patch, bdy + s + 1, bdx + s, wts, uniform, m, big)
                sr = _window_ssd(tmpl, patch, bdy + s + 1, bdx + s + 2, wts, uniform, m, big)
                den = sl - 2 * best + sr
                if den > 0:
                    off = 0.5 * (sl - sr) / den
                    fx += min(max(off, -0.5), 0.5)
            if qy - 1 >= lo_y and qy + 1 <= hi_y:
                su = _window_ssd(tmpl, patch, bdy + s, bdx + s + 1, wts, uniform, m, big)
                sd = _window_ssd(tmpl, patch, bdy + s + 2, bdx + s + 1, wts, uniform, m, big)
                den = su - 2 * best + sd
                if den > 0:
                    off = 0.5 * (su - sd) / den
                    fy += min(max(off, -0.5), 0.5)
        out_pos[f, 0] = fx
        out_pos[f, 1] = fy
        out_ssd[f] = best
        out_ok[f] = 1


def track_ssd(prev: np.ndarray, curr: np.ndarray, anchors: np.ndarray, centers: np.ndarray, *,
              corr_half: int, search_half: int, weights: np.ndarray,
              subpixel: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Find each feature of frame t in frame t+1 by the SSD of Eq. (1).

    Parameters
    ----------
    prev, curr : (H, W) uint8 frames t and t+1.
    anchors : (N, 2) int x, y in ``prev``: the centres c of the correlation windows.
    centers : (N, 2) int x, y in ``curr``: the predicted positions, centres of the search.
    corr_half : n of Eq. (1); the window is (2n+1)^2.
    search_half : half-width of the search window; (2 s + 1)^2 displacements are scored.
    weights : (2n+1, 2n+1) int32 W(i, j), see :func:`window_weights`.
    subpixel : refine the integer minimum to a continuous one: Gauss-Newton on Eq. (1) with
        bilinear sampling, falling back to a parabola per axis through the minimum and its
        neighbours where Gauss-Newton cannot run (window at the border, no texture).

    Returns
    -------
    pos : (N, 2) float64 x, y of the best match in ``curr`` (NaN where not found);
    ssd : (N,) float64 S at the best match (inf where not found);
    ok : (N,) bool, False where the template leaves ``prev`` or no search position fits
    ``curr``.
    """
    prev = np.ascontiguousarray(prev, np.uint8)
    curr = np.ascontiguousarray(curr, np.uint8)
    if prev.shape != curr.shape or prev.ndim != 2:
        raise ValueError(f"frames must be 2-D and of one size, got {prev.shape} and {curr.shape}")
    m = 2 * corr_half + 1
    if weights.shape != (m, m):
        raise ValueError(f"weights of shape {weights.shape} do not match corr_half={corr_half}")
    wts = np.ascontiguousarray(weights, np.int32)
    uniform = bool(np.all(wts == 1))
    anchors = np.ascontiguousarray(anchors, np.int64).reshape(-1, 2)
    centers = np.ascontiguousarray(centers, np.int64).reshape(-1, 2)
    n_feat = anchors.shape[0]
    pos = np.empty((n_feat, 2), np.float64)
    ssd = np.empty(n_feat, np.float64)
    ok = np.empty(n_feat, np.uint8)
    _track(prev, curr, anchors, centers, int(corr_half), int(search_half), wts, uniform,
           bool(subpixel), pos, ssd, ok)
    return pos, ssd, ok.astype(bool)


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
