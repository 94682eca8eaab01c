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


# -- the picture's edge: bars and a lens's dark border ---------------------------------------
#
# A frame need not be picture to its edges: a stream letterboxed or pillarboxed to another
# aspect (black bars), a fisheye lens's image circle (black corners), a camera's mask. Those
# regions are flat and do not move with the scene, and where a feature's window straddles
# their edge, the edge, which stays put, pulls its match against the texture, which moves: on
# frames rendered from the shared data with 40 px bars at the sides, a pan of (3.3, 1.2) px a
# frame drifted 3.1 px in 39 frames with the scale at 0.964 for 1, an approach read a scale of
# 1.53 for 1.78, and a roll seen through an image circle drifted 21 px, every estimate valid.
# The tracker treats such a region as outside the picture, as it does the frame's edge.

#: a region of the frame's edge is void where its grey level is at most this (black, or video
#: black, 16, where a stream's range is limited) ...
VOID_LEVEL = 24
#: ... and within this of the frame's edge pixel of its row or column (a flat region: a dark
#: scene has texture; pre-filtered, a bar is one value exactly, a lens's dark border within
#: a grey level or so of its noise) ...
VOID_TOLERANCE = 1
#: ... and has stayed the same, to within this many px, while the scene moved VOID_PROOF px
#: or more (a region fixed in the frame, not a dark part of the scene, which moves with it)
VOID_SETTLE = 1
VOID_PROOF = 3.0
#: a void region reaches at least this far in from the edge, px, along at least VOID_SPAN
#: rows or columns in a row: a bar, or a lens's dark corner, not the odd dark pixel at the
#: edge of a scene (on the scoreboard's rendered sequences, runs 1 to 8 px deep on scattered
#: rows where their shadows meet the frame's edge)
VOID_DEPTH = 4
VOID_SPAN = 12
#: what blurs a void region's edge into the picture on top of the features' windows, px (the
#: pre-filter's Gaussian, 3 sigma at its default sigma 1)
VOID_BLUR = 3


@nb.njit(cache=True, nogil=True)
def void_runs(img, level, tolerance):  # pragma: no cover - numba
    """(4, max(H, W)) int32: how far a flat dark region reaches into each row of the
    (H, W) uint8 ``img`` from its left and its right edge (rows 0 and 1, entries < H) and into
    each column from the top and the bottom (rows 2 and 3, entries < W), px: the run of pixels
    from that edge within ``tolerance`` of the edge pixel, where the edge pixel is at most
    ``level`` (else 0). A run across half the row or column or more is 0 too: a bar across the
    top is found by the columns' runs, which end at its edge, and rows dark from edge to edge
    are as likely a dark sky over a skyline, which stays put (rows wholly inside it) while
    the skyline moves. An image circle's dark corners are a run from the edge in every row
    and column they cross. Returns (runs, whether any is left after :func:`_keep_regions`)."""
    h, w = img.shape
    runs = np.zeros((4, max(h, w)), np.int32)
    # a run is read up to half the row (column): one that reaches it is no bar (half the
    # frame would be one), and a pillarbox's columns are not read down their whole height
    hw = w // 2
    hh = h // 2
    for y in range(h):
        v = np.int32(img[y, 0])
        if v <= level:
            x = 1
            while x < hw and abs(np.int32(img[y, x]) - v) <= tolerance:
                x += 1
            runs[0, y] = x if x < hw else 0
        v = np.int32(img[y, w - 1])
        if v <= level:
            x = 1
            while x < hw and abs(np.int32(img[y, w - 1 - x]) - v) <= tolerance:
                x += 1
            runs[1, y] = x if x < hw else 0
    for x in range(w):
        v = np.int32(img[0, x])
        if v <= level:
            y = 1
            while y < hh and abs(np.int32(img[y, x]) - v) <= tolerance:
                y += 1
            runs[2, x] = y if y < hh else 0
        v = np.int32(img[h - 1, x])
        if v <= level:
            y = 1
            while y < hh and abs(np.int32(img[h - 1 - y, x]) - v) <= tolerance:
                y += 1
            runs[3, x] = y if y < hh else 0
    return runs, _keep_regions(runs, h, w)


@nb.njit(cache=True, nogil=True)
def _keep_regions(runs, h, w):  # pragma: no cover - numba
    """Zero the runs less than VOID_DEPTH deep, then those of a stretch of fewer than
    VOID_SPAN rows (columns) in a row with runs (:func:`void_runs`), in place; return whether
    any is left."""
    left = False
    for k in range(4):
        n = h if k < 2 else w
        for i in range(n):
            if runs[k, i] < VOID_DEPTH:
                runs[k, i] = 0
        i = 0
        while i < n:
            if runs[k, i] == 0:
                i += 1
                continue
            j = i
            while j < n and runs[k, j] > 0:
                j += 1
            if j - i < VOID_SPAN:
                for t in range(i, j):
                    runs[k, t] = 0
            else:
                left = True
            i = j
    return left


@nb.njit(cache=True, nogil=True)
def void_step(now, ref, at, proven, travel, settle, proof):  # pragma: no cover - numba
    """The void regions of a frame: the runs ``now`` (:func:`void_runs`) that have stayed
    within ``settle`` px of a run seen before (``ref``) while the features moved ``proof`` px
    or more (``travel``: how far the features moved, the mean of a frame's displacements
    summed over the frames so far; ``at``: its value when each ``ref`` was seen), as a bar or a
    lens's border stays and a dark part of the scene does not; 0 elsewhere. A travel, not the
    image motion: an approach or a roll moves the features, not their centroid. ``ref``,
    ``at`` (4, L) and ``proven`` (4, L) bool are the record, updated in place: a run that
    changed starts a new one. Returns (runs, any)."""
    out = np.zeros_like(now)
    found = False
    for k in range(now.shape[0]):
        for i in range(now.shape[1]):
            a = now[k, i]
            r = ref[k, i]
            if a == 0 or r == 0 or abs(a - r) > settle:
                ref[k, i] = a
                at[k, i] = travel
                proven[k, i] = False
                continue
            if not proven[k, i]:
                proven[k, i] = travel - at[k, i] >= proof
            if proven[k, i]:
                out[k, i] = min(a, r)
                found = True
    return out, found


@nb.njit(cache=True, nogil=True)
def near_void(points, runs, shape_hw, margin):  # pragma: no cover - numba
    """(N,) bool: whether a void region (``runs``, :func:`void_runs`) reaches within
    ``margin`` px of each point (x, y) of ``points`` (N, 2), in the rows and columns within
    ``margin`` of it: where a window of that half-width would take in some of it."""
    h, w = shape_hw
    out = np.zeros(points.shape[0], np.bool_)
    for i in range(points.shape[0]):
        x = int(np.rint(points[i, 0]))
        y = int(np.rint(points[i, 1]))
        hit = False
        for yy in range(max(y - margin, 0), min(y + margin + 1, h)):
            if (runs[0, yy] > 0 and runs[0, yy] > x - margin) or (
                    runs[1, yy] > 0 and runs[1, yy] > w - 1 - x - margin):
                hit = True
                break
        if not hit:
            for xx in range(max(x - margin, 0), min(x + margin + 1, w)):
                if (runs[2, xx] > 0 and runs[2, xx] > y - margin) or (
                        runs[3, xx] > 0 and runs[3, xx] > h - 1 - y - margin):
                    hit = True
                    break
        out[i] = hit
    return out


def warm() -> None:
    """Compile (or load) the void kernels: :func:`near_void` runs only where a frame has a
    void region, which a warm-up's frames need not show."""
    runs, _ = void_runs(np.zeros((16, 16), np.uint8), VOID_LEVEL, VOID_TOLERANCE)
    out, _ = void_step(runs, np.zeros_like(runs), np.zeros(runs.shape, np.float64),
                       np.zeros(runs.shape, np.bool_), 0.0, VOID_SETTLE, VOID_PROOF)
    near_void(np.zeros((1, 2), np.float64), out, (16, 16), 1)
