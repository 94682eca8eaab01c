"""Feature selection: grid bucketing, UNGROUP_SIZE and MAX_FEAT_NUM (Section 5 of the paper).

"The method used to specify those points was to calculate the gradient of the thresholded image
and to select the points with larger gradient values. For feature points to be the most uniformly
distributed within the image area the image was divided in rectangles and the number of feature
points to be selected in each rectangle had been limited. Subsequently, the excess of points was
eliminated aiming at a limited number of points in the whole image."

Candidates arrive strongest first. Walking them in that order, a candidate is taken unless its
rectangle is full or it lies closer than UNGROUP_SIZE to a point already taken (or to a feature
still being tracked). The walk stops at MAX_FEAT_NUM: because it runs strongest first this is
exactly "remove the excess, weakest first".
"""

from __future__ import annotations

import numba as nb
import numpy as np

from ..params import TrackerParams


@nb.njit(cache=True, nogil=True)
def _select(cands, shape_hw, grid_rc, cell_cap, min_dist, max_count, existing):  # pragma: no cover
    h, w = shape_hw
    rows, cols = grid_rc
    counts = np.zeros(rows * cols, np.int64)
    # hash grid of side >= min_dist, one linked list per bin: the distance test only looks at
    # the 3x3 bins around a candidate, O(1) per candidate whatever the number of points
    bin_size = max(min_dist, 8)
    bh = h // bin_size + 1
    bw = w // bin_size + 1
    head = np.full(bh * bw, -1, np.int64)
    n_exist = existing.shape[0]
    nxt = np.full(n_exist + max_count, -1, np.int64)
    pts = np.empty((n_exist + max_count, 2), np.float64)
    for i in range(n_exist):
        ex = existing[i, 0]
        ey = existing[i, 1]
        pts[i, 0] = ex
        pts[i, 1] = ey
        b = min(max(int(ey) // bin_size, 0), bh - 1) * bw + min(max(int(ex) // bin_size, 0), bw - 1)
        nxt[i] = head[b]
        head[b] = i
        # features still tracked fill their rectangle's quota too
        cy = min(max(int(ey) * rows // h, 0), rows - 1)
        cx = min(max(int(ex) * cols // w, 0), cols - 1)
        counts[cy * cols + cx] += 1
    chosen = np.empty(max_count, np.int64)
    n_chosen = 0
    md2 = float(min_dist) * float(min_dist)
    for c in range(cands.shape[0]):
        if n_chosen >= max_count:
            break
        x = cands[c, 0]
        y = cands[c, 1]
        cell = (y * rows // h) * cols + (x * cols // w)
        if counts[cell] >= cell_cap:
            continue
        bx = x // bin_size
        by = y // bin_size
        ok = True
        if min_dist > 0:
            for yy in range(max(by - 1, 0), min(by + 2, bh)):
                for xx in range(max(bx - 1, 0), min(bx + 2, bw)):
                    p = head[yy * bw + xx]
                    while p >= 0:
                        ddx = pts[p, 0] - x
                        ddy = pts[p, 1] - y
                        if ddx * ddx + ddy * ddy < md2:
                            ok = False
                            break
                        p = nxt[p]
                    if not ok:
                        break
                if not ok:
                    break
        if not ok:
            continue
        idx = n_exist + n_chosen
        pts[idx, 0] = x
        pts[idx, 1] = y
        b = by * bw + bx
        nxt[idx] = head[b]
        head[b] = idx
        counts[cell] += 1
        chosen[n_chosen] = c
        n_chosen += 1
    return chosen[:n_chosen]


def select_features(candidates: np.ndarray, shape: tuple[int, int], params: TrackerParams, *,
                    existing: np.ndarray | None = None,
                    max_count: int | None = None) -> np.ndarray:
    """Choose feature points among the candidates.

    Parameters
    ----------
    candidates : (N, 2) int x, y, strongest gradient first (as from ``threshold_candidates``).
    shape : (H, W) of the image.
    params : uses ``max_features``, ``ungroup_size``, ``grid_rows``, ``grid_cols``, cell cap.
    existing : (M, 2) float positions of features still tracked; new points keep UNGROUP_SIZE
        from them and they count towards their rectangle's cap.
    max_count : how many new points at most (default ``max_features``).

    Returns
    -------
    (K,) int64 indices into ``candidates`` of the chosen points, strongest first.
    """
    h, w = shape
    if existing is None:
        existing = np.empty((0, 2), np.float64)
    limit = params.max_features if max_count is None else max_count
    if limit <= 0 or len(candidates) == 0:
        return np.empty(0, np.int64)
    return _select(np.ascontiguousarray(candidates, np.int64), (int(h), int(w)),
                   (params.grid_rows, params.grid_cols), params.effective_cell_cap,
                   int(params.ungroup_size), int(limit),
                   np.ascontiguousarray(existing, np.float64))
