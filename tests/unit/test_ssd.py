"""Eq. (1): the numba SSD against an independent brute-force numpy version and OpenCV."""

from __future__ import annotations

import cv2
import numba as nb
import numpy as np
import pytest

from vistrack.common.vision import ssd
from vistrack.common.vision.ssd import ssd_surface, track_ssd, window_weights


def brute_ssd(prev, curr, anchor, center, n, s, weights):
    """Eq. (1) written out with numpy: S over every displacement of the search window."""
    h, w = prev.shape
    ax, ay = anchor
    cx, cy = center
    out = np.full((2 * s + 1, 2 * s + 1), np.inf)
    if ax - n < 0 or ay - n < 0 or ax + n >= w or ay + n >= h:
        return out
    tmpl = prev[ay - n:ay + n + 1, ax - n:ax + n + 1].astype(np.int64)
    for dy in range(-s, s + 1):
        for dx in range(-s, s + 1):
            qx, qy = cx + dx, cy + dy
            if qx - n < 0 or qy - n < 0 or qx + n >= w or qy + n >= h:
                continue
            win = curr[qy - n:qy + n + 1, qx - n:qx + n + 1].astype(np.int64)
            out[dy + s, dx + s] = float((weights * (tmpl - win) ** 2).sum())
    return out


def first_argmin(surface):
    """Row-major first minimum, the tie rule of cv2.minMaxLoc."""
    k = int(np.argmin(surface))
    s = surface.shape[0] // 2
    return k % surface.shape[1] - s, k // surface.shape[1] - s


def random_pair(seed, size=64):
    rng = np.random.default_rng(seed)
    a = cv2.GaussianBlur(rng.integers(0, 256, (size, size)).astype(np.uint8), (3, 3), 0.8)
    b = np.roll(a, (int(rng.integers(-3, 4)), int(rng.integers(-3, 4))), axis=(0, 1))
    noise = rng.integers(-6, 7, b.shape)
    return a, np.clip(b.astype(int) + noise, 0, 255).astype(np.uint8)


# corr_size 8 and 9 both give n = 4; even widths behave like the next odd one by definition
@pytest.mark.parametrize("corr_size", [5, 8, 9, 15])
@pytest.mark.parametrize("kind", ["uniform", "gaussian"])
def test_surface_equals_bruteforce_on_random_images(corr_size, kind):
    n, s = corr_size // 2, 5
    wts = window_weights(kind, n)
    for seed in range(4):
        a, b = random_pair(seed)
        rng = np.random.default_rng(100 + seed)
        # features anywhere, including right at and beyond the border
        for _ in range(12):
            anchor = tuple(int(v) for v in rng.integers(0, 64, 2))
            center = tuple(int(v) for v in rng.integers(0, 64, 2))
            got = ssd_surface(a, b, anchor, center, corr_half=n, search_half=s, weights=wts)
            np.testing.assert_array_equal(got, brute_ssd(a, b, anchor, center, n, s, wts))


@pytest.mark.parametrize("corr_size,search_size", [(9, 15), (8, 10), (5, 21), (15, 30)])
@pytest.mark.parametrize("kind", ["uniform", "gaussian"])
def test_pruned_search_finds_the_bruteforce_argmin(real_image, corr_size, search_size, kind):
    """The pruned, spiral-order search returns exactly the brute-force argmin of Eq. (1)."""
    n, s = corr_size // 2, search_size // 2
    wts = window_weights(kind, n)
    shifted = np.roll(real_image, (2, -3), axis=(0, 1))
    rng = np.random.default_rng(corr_size * 100 + search_size)
    h, w = real_image.shape
    # near the border too: margins from 0 px
    anchors = np.stack([rng.integers(0, w, 150), rng.integers(0, h, 150)], axis=1)
    centers = np.clip(anchors + rng.integers(-4, 5, anchors.shape), 0, w - 1)
    pos, ssd, ok = track_ssd(real_image, shifted, anchors, centers, corr_half=n,
                             search_half=s, weights=wts)
    checked = 0
    for (ax, ay), (cx, cy), p, v, good in zip(anchors, centers, pos, ssd, ok, strict=True):
        surf = brute_ssd(real_image, shifted, (ax, ay), (cx, cy), n, s, wts)
        if not np.isfinite(surf).any():
            assert not good
            continue
        if not good:
            continue  # minimum on a border-cut edge: lost on purpose (tested below)
        dx, dy = first_argmin(surf)
        assert (p[0], p[1]) == (cx + dx, cy + dy)
        assert v == surf.min()
        checked += 1
    assert checked > 100


def test_features_leaving_the_image_are_lost_not_pinned():
    """Scene sliding right for 40 frames: every surviving feature moved with the scene.

    Before border-cut minima counted as losses, features pressed against the right edge stayed
    there with a wrong position and dragged the accumulated motion and scale.
    """
    from vistrack.common import synthetic
    from vistrack.common.params import TrackerParams
    from vistrack.common.vision import Tracker

    frames = synthetic.sequence(40, motion=synthetic.Motion(dx=2.0))
    tracker = Tracker(TrackerParams(subpixel=True, redetect_fraction=0.0))
    first = tracker.process(frames[0])
    for f in frames[1:]:
        last = tracker.process(f)
    start = dict(zip(first.ids.tolist(), first.points, strict=True))
    disp = np.array([p - start[i] for i, p in zip(last.ids.tolist(), last.points, strict=True)])
    assert 0 < len(disp) < first.npi  # some left the image, the rest survived
    np.testing.assert_allclose(disp, np.tile([78.0, 0.0], (len(disp), 1)), atol=0.5)
    assert abs(last.dx - 78.0) < 0.5 and abs(last.scale - 1.0) < 0.005


@pytest.mark.parametrize("corr_size,search_size", [(9, 15), (5, 11), (15, 21)])
def test_integer_displacement_equals_cv2_matchtemplate(real_image, corr_size, search_size):
    """With uniform weights the SSD argmin is OpenCV's TM_SQDIFF argmin over the same window."""
    n, s = corr_size // 2, search_size // 2
    wts = window_weights("uniform", n)
    nxt = cv2.warpAffine(real_image, np.float32([[1, 0, 2.4], [0, 1, -1.7]]),
                         real_image.shape[::-1], borderMode=cv2.BORDER_REFLECT)
    rng = np.random.default_rng(7)
    margin = n + s + 1
    h, w = real_image.shape
    anchors = np.stack([rng.integers(margin, w - margin, 100),
                        rng.integers(margin, h - margin, 100)], axis=1)
    pos, _, ok = track_ssd(real_image, nxt, anchors, anchors, corr_half=n, search_half=s,
                           weights=wts)
    compared = 0
    for (x, y), p, good in zip(anchors, pos, ok, strict=True):
        tmpl = real_image[y - n:y + n + 1, x - n:x + n + 1]
        region = nxt[y - s - n:y + s + n + 1, x - s - n:x + s + n + 1]
        res = cv2.matchTemplate(region, tmpl, cv2.TM_SQDIFF)
        _, _, loc, _ = cv2.minMaxLoc(res)
        if not good:
            # only a border-edge minimum may be refused; OpenCV then sits on the edge too
            assert loc[0] in (0, 2 * s) or loc[1] in (0, 2 * s)
            continue
        assert (p[0] - x, p[1] - y) == (loc[0] - s, loc[1] - s)
        compared += 1
    assert compared >= 90


def test_weights():
    u = window_weights("uniform", 3)
    g = window_weights("gaussian", 3)
    assert u.shape == g.shape == (7, 7) and (u == 1).all()
    assert g[3, 3] == g.max() and g.min() >= 1 and (g == g.T).all() and (g == g[::-1]).all()
    with pytest.raises(ValueError, match="weights='box'"):
        window_weights("box", 3)


# ------------------------------------------------------------------ the two searches of Eq. (1)


def border_features(rng, shape, count, margin, spread):
    """(anchors, centers): half anywhere, half within ``margin`` px of a border (at and beyond
    the limits where the windows fit); centers within ``spread`` px of the anchors."""
    h, w = shape
    anywhere = np.stack([rng.integers(0, w, count // 2), rng.integers(0, h, count // 2)],
                        axis=1)
    near = np.stack([rng.integers(0, w, count - count // 2),
                     rng.integers(0, h, count - count // 2)], axis=1)
    for k, p in enumerate(near):
        axis = k % 2
        size = (w, h)[axis]
        off = int(rng.integers(0, margin + 1))
        p[axis] = off if k % 4 < 2 else size - 1 - off
    anchors = np.concatenate([anywhere, near])
    centers = np.clip(anchors + rng.integers(-spread, spread + 1, anchors.shape), 0,
                      [w - 1, h - 1])
    return anchors, centers


def check_bruteforce(prev, curr, anchors, centers, n, s, wts, result, subpixel):
    """Every result against Eq. (1) written out (:func:`brute_ssd`); returns how many were
    found. A feature is found exactly when its template fits frame t, some displacement fits
    frame t+1 and the first minimum is not on an edge of the search that the image cut short
    (a neighbour inside the search whose window leaves the image)."""
    pos, ssd, ok = result
    found = 0
    for (ax, ay), (cx, cy), p, v, good in zip(anchors, centers, pos, ssd, ok, strict=True):
        surf = brute_ssd(prev, curr, (ax, ay), (cx, cy), n, s, wts)
        if not np.isfinite(surf).any():
            assert not good and np.isnan(p).all() and v == np.inf
            continue
        dx, dy = first_argmin(surf)
        iy, ix = dy + s, dx + s
        side = 2 * s + 1
        around = [surf[y, x] for y, x in ((iy, ix - 1), (iy, ix + 1), (iy - 1, ix), (iy + 1, ix))
                  if 0 <= y < side and 0 <= x < side]
        cut = any(np.isinf(a) for a in around)
        assert good == (not cut), (ax, ay, cx, cy)
        if not good:
            assert np.isnan(p).all() and v == np.inf
            continue
        assert v == surf.min()
        if subpixel:  # refined within a pixel of the integer minimum
            assert abs(p[0] - (cx + dx)) <= 1.0 and abs(p[1] - (cy + dy)) <= 1.0
        else:
            assert (p[0], p[1]) == (cx + dx, cy + dy)
        found += 1
    return found


def both_searches(prev, curr, anchors, centers, n, s, wts, subpixel):
    """The results of the pruned and the exhaustive search, asserted identical; the pruned."""
    kw = dict(corr_half=n, search_half=s, weights=wts, subpixel=subpixel)
    pruned = track_ssd(prev, curr, anchors, centers, search="pruned", **kw)
    full = track_ssd(prev, curr, anchors, centers, search="exhaustive", **kw)
    for a, b in zip(pruned, full, strict=True):
        np.testing.assert_array_equal(a, b)  # NaN where both lost it
    return pruned


def weights_of(kind, n):
    if kind == "heavy":  # sums past int32: the searches' 64-bit paths
        return window_weights("gaussian", n) * 4000
    return window_weights(kind, n)


# (corr_size, search_size): odd and even widths (8 behaves like 9, 10 like 11)
@pytest.mark.parametrize("corr_size,search_size", [(5, 10), (8, 15), (9, 11), (15, 10)])
@pytest.mark.parametrize("kind", ["uniform", "gaussian"])
@pytest.mark.parametrize("subpixel", [False, True])
def test_exhaustive_and_pruned_equal_bruteforce_on_random_frames(corr_size, search_size, kind,
                                                                 subpixel):
    n, s = corr_size // 2, search_size // 2
    wts = weights_of(kind, n)
    found = 0
    for seed in range(3):
        a, b = random_pair(seed)
        anchors, centers = border_features(np.random.default_rng(50 + seed), a.shape, 24,
                                           n + s, 4)
        result = both_searches(a, b, anchors, centers, n, s, wts, subpixel)
        found += check_bruteforce(a, b, anchors, centers, n, s, wts, result, subpixel)
    assert found >= 20


@pytest.mark.parametrize("corr_size,search_size", [(9, 15), (8, 10), (15, 30), (30, 50)])
@pytest.mark.parametrize("kind", ["uniform", "gaussian", "heavy"])
@pytest.mark.parametrize("subpixel", [False, True])
def test_exhaustive_and_pruned_equal_bruteforce_on_real_frames(real_image, corr_size,
                                                               search_size, kind, subpixel):
    n, s = corr_size // 2, search_size // 2
    wts = weights_of(kind, n)
    nxt = cv2.warpAffine(real_image, np.float32([[1, 0, 1.6], [0, 1, -2.3]]),
                         real_image.shape[::-1], borderMode=cv2.BORDER_REFLECT)
    count = 12 if s > 20 else 30  # the brute force visits (2s+1)^2 windows each
    anchors, centers = border_features(np.random.default_rng(corr_size * search_size),
                                       real_image.shape, count, n + s, 3)
    result = both_searches(real_image, nxt, anchors, centers, n, s, wts, subpixel)
    found = check_bruteforce(real_image, nxt, anchors, centers, n, s, wts, result, subpixel)
    assert found >= count // 3


@pytest.mark.parametrize("corr_size,kind", [(3, "uniform"), (5, "uniform"), (9, "uniform"),
                                             (15, "uniform"), (31, "uniform"),
                                             (9, "gaussian")])
def test_bounds_are_the_row_sums_bound(real_image, corr_size, kind):
    """The pruned search's bounds (paired rows with uniform weights) are exactly
    sum_j wmin_j min((T_j - I_j)^2, cap_j), T_j and I_j the row sums of template and window,
    computed here with numpy, and at most m S."""
    n, s = corr_size // 2, 7
    m = 2 * n + 1
    wts = window_weights(kind, n)
    curr = cv2.warpAffine(real_image, np.float32([[1, 0, 1.6], [0, 1, -2.3]]),
                          real_image.shape[::-1], borderMode=cv2.BORDER_REFLECT)
    h, w = curr.shape
    rng = np.random.default_rng(corr_size)
    centers = rng.integers(n + s + 1, min(h, w) - n - s - 1, (6, 2))
    rs = np.empty(h * w + w + ssd.VEC, np.int16)
    bufs = np.empty((2, ssd.ROW_BLOCK + w + 2 * m), np.int16)
    ssd._row_sums(curr, n, s, centers, rs, bufs)
    uniform, wmin, _ = ssd._weights_info(wts)
    caps, unit = ssd._bound_caps(wmin, uniform)
    assert unit == (kind == "uniform")
    side = 2 * s + 1
    width = (side + ssd.LANES - 1) // ssd.LANES * ssd.LANES
    blk = np.empty(2 * ((side + m + ssd.VEC // ssd.LANES) * width + ssd.VEC), np.int16)
    bnd = np.empty((side * width + ssd.VEC - 1) // ssd.VEC * ssd.VEC, np.int32)
    prev64 = real_image.astype(np.int64)
    rows = np.lib.stride_tricks.sliding_window_view(curr.astype(np.int64), m, axis=1).sum(-1)
    for cx, cy in centers:
        ax, ay = cx + 2, cy - 1
        trs = prev64[ay - n:ay + n + 1, ax - n:ax + n + 1].sum(1).astype(np.int32)
        tpairs = np.zeros(m + 1, np.int16)
        tpairs[:m] = trs
        lo_x, lo_y = cx - s, cy - s
        total = ssd._bounds(rs, w, trs, tpairs, wmin, caps, unit, lo_x, lo_y, side, side,
                            width, n, blk, bnd)
        assert total >= side * width
        got = bnd[:side * width].reshape(side, width)[:, :side].astype(np.int64)
        # window centred at (lo_x + k, lo_y + r): its row j sums curr row lo_y + r - n + j
        # from column lo_x + k - n
        win = np.stack([rows[lo_y - n + j:lo_y - n + j + side, lo_x - n:lo_x - n + side]
                        for j in range(m)])
        want = (wmin[:, None, None]
                * np.minimum((trs[:, None, None] - win) ** 2, caps[:, None, None])).sum(0)
        np.testing.assert_array_equal(got, want)
        surface = brute_ssd(real_image, curr, (ax, ay), (cx, cy), n, s, wts)
        assert np.all(got <= m * surface)


def test_searches_agree_on_many_features_of_real_frames(real_image):
    """Many more features than the brute force can afford: the two searches agree exactly."""
    nxt = np.roll(real_image, (-1, 2), axis=(0, 1))
    rng = np.random.default_rng(3)
    for corr_size, search_size in ((5, 10), (9, 15), (15, 20), (30, 50)):
        n, s = corr_size // 2, search_size // 2
        anchors, centers = border_features(rng, real_image.shape, 400, n + s, 4)
        pos, _, ok = both_searches(real_image, nxt, anchors, centers, n, s,
                                   window_weights("uniform", n), False)
        assert ok.sum() > 200


def test_search_kind_is_checked():
    a, b = random_pair(0)
    with pytest.raises(ValueError, match="search='full' is not allowed: use one of pruned, "
                                         "exhaustive"):
        track_ssd(a, b, [[30, 30]], [[30, 30]], corr_half=2, search_half=3,
                  weights=window_weights("uniform", 2), search="full")


@pytest.mark.parametrize("search", ["pruned", "exhaustive"])
def test_ties_go_to_the_first_displacement_in_row_major_order(search):
    """A flat frame scores S = 0 everywhere: the top-left displacement of the search wins.
    Flat patches of a blocky frame tie too: both searches still equal the brute force."""
    flat = np.full((48, 48), 100, np.uint8)
    n, s = 2, 4
    wts = window_weights("uniform", n)
    centers = np.array([[24, 24], [20, 30]])
    pos, ssd, ok = track_ssd(flat, flat, centers, centers, corr_half=n, search_half=s,
                             weights=wts, search=search)
    assert ok.all() and (ssd == 0).all()
    np.testing.assert_array_equal(pos, centers - s)
    rng = np.random.default_rng(9)
    blocks = np.kron(rng.integers(0, 2, (8, 8)) * 200, np.ones((8, 8))).astype(np.uint8)
    shifted = np.roll(blocks, (1, 3), axis=(0, 1))
    anchors, near = border_features(rng, blocks.shape, 40, n + s, 2)
    result = track_ssd(blocks, shifted, anchors, near, corr_half=n, search_half=s, weights=wts,
                       search=search)
    assert check_bruteforce(blocks, shifted, anchors, near, n, s, wts, result, False) >= 10


# 256x256: the sums around the searches alone; 400x16 with three features, 600x12: in blocks
# of rows, those no search reads skipped (12: narrower than a vector of sums)
@pytest.mark.parametrize("shape", [(256, 256), (400, 16), (600, 12)])
def test_a_few_searches_equal_the_exhaustive_one(real_image, shape):
    """One to three features at a time, the way the coarse-to-fine search hands over the few
    that do not follow their prediction: the pruned search then sums the rows of frame t+1
    around those searches only, and finds what the exhaustive search finds, at the frame's
    edges and in frames narrower than a vector too."""
    h, w = shape
    tall = np.tile(real_image, (3, 1))
    prev = np.ascontiguousarray(tall[:h, :w])
    curr = np.ascontiguousarray(np.roll(tall, (2, -1), axis=(0, 1))[:h, :w])
    n, s = 4, 7
    wts = window_weights("uniform", n)
    rng = np.random.default_rng(h * w)
    anchors, centers = border_features(rng, prev.shape, 60, n + s, 3)
    found = 0
    for k in range(0, len(anchors), 3):
        for size in (1, 3):
            pos, _, ok = both_searches(prev, curr, anchors[k:k + size], centers[k:k + size], n,
                                       s, wts, False)
            found += int(ok.sum())
    assert found >= 10  # not all cut short: the narrowest frame holds few searches


@pytest.mark.parametrize("corr_size", [3, 5, 9, 15, 21])
@pytest.mark.parametrize("searches", [2, 60])
@pytest.mark.parametrize("corner", [False, True])
def test_row_sums_are_the_window_rows_sums(corr_size, searches, corner):
    """The row sums behind the search's bounds (:func:`ssd._row_sums`), by either path (a few
    searches: their own entries, LANES at a time and, near the frame's end, one at a time;
    many: blocks of whole rows) and either scheme (doubling, or sums of 3 for a window of 3b
    px), equal a plain sum over each window row that a search reads, on a random frame whose
    sums reach the int16 range's top (all-255 rows); with ``corner``, the last search centred
    on the frame's last pixel."""
    from vistrack.common.vision import ssd

    rng = np.random.default_rng(corr_size)
    frame = rng.integers(0, 256, (72, 90), dtype=np.uint8)
    frame[30:34] = 255
    h, w = frame.shape
    n, s = corr_size // 2, 5
    m = 2 * n + 1
    centers = np.stack([rng.integers(0, w, searches), rng.integers(0, h, searches)], axis=1)
    if corner:
        centers[-1] = (w - 1, h - 1)
    out = np.empty(h * w + w + ssd.VEC, np.int16)
    bufs = np.empty((2, ssd.ROW_BLOCK + w + 2 * m), np.int16)
    ssd._row_sums(frame, n, s, centers.astype(np.int64), out, bufs)
    flat = frame.ravel().astype(np.int64)
    checked = 0
    for cx, cy in centers:
        # the windows of the search (centres within s of (cx, cy), inside the frame)
        for y in range(max(cy - s, n), min(cy + s, h - 1 - n) + 1):
            for x in range(max(cx - s, n), min(cx + s, w - 1 - n) + 1):
                for j in range(-n, n + 1):
                    q = (y + j) * w + x - n
                    assert out[q] == flat[q:q + m].sum()
                    checked += 1
    assert checked > 0


@pytest.mark.parametrize("n", [0, 4, 7, 8, 12, 15])
def test_window_sum_equals_numpy_everywhere_in_the_frame(real_image, n):
    """S of Eq. (1) at one displacement (the rows read as vectors of LANES pixels where the
    last one's run-on stays inside the frames, else pixel by pixel) equals numpy's sum, for
    windows of 1 to 31 px (one or two vectors a row) anywhere: at the top-left corner, the
    middle, and the bottom-right corner, where no vector can be read."""
    prev = real_image
    curr = np.ascontiguousarray(np.roll(real_image, (3, -2), axis=(0, 1)))
    h, w = prev.shape
    pf, cf = prev.ravel(), curr.ravel()
    m = 2 * n + 1
    uniform = window_weights("uniform", n)
    gaussian = window_weights("gaussian", n)
    spots = [(n, n), (w // 2, h // 2), (w - 1 - n, h - 1 - n), (w - 1 - n, n), (n, h - 1 - n)]
    for ax, ay in spots:
        for qx, qy in spots:
            d = (prev[ay - n:ay + n + 1, ax - n:ax + n + 1].astype(np.int64)
                 - curr[qy - n:qy + n + 1, qx - n:qx + n + 1])
            for wts, flag in ((uniform, True), (gaussian, False)):
                want = int((wts * d * d).sum())
                got = ssd._ssd_at(pf, cf, w, ax, ay, qx, qy, n, wts, flag, ssd.BIG)
                assert got == want, (m, ax, ay, qx, qy, flag)
            # the sum stops at the first row that takes it above the bound, and says so
            bound = int((d * d).sum()) // 2
            assert ssd._ssd_at(pf, cf, w, ax, ay, qx, qy, n, uniform, True, bound) > bound \
                or bound == 0



def test_sub_pixel_refinement_reaches_as_close_to_the_right_edge_as_to_the_left(real_image):
    """Gauss-Newton samples frame t+1 bilinearly over the window: it needs the pixel right of
    (below) the window's last one, and runs while that pixel is in the frame, at the right
    and bottom edges as at the left and top ones. It once stopped a pixel short there, and
    such features got the parabola's estimate instead (on three crops of real frames shifted
    by 0.25 px: median errors 0.06 to 0.53 px, the worst 0.78, against 0.03 to 0.06 at the
    left and top). Windows whose estimate reaches the frame's last usable column or row:
    each within 0.2 px of the true shift, their median within 0.08 px."""
    n, shift = 4, 0.25
    near, far = n + 1, 64 - n - 2  # estimates at far + 0.25: the last sample at column 63
    rows = [16, 24, 32, 40, 48]
    anchors = np.array([[far, r] for r in rows] + [[r, far] for r in rows]
                       + [[near, r] for r in rows] + [[r, near] for r in rows], np.int64)
    errors = []
    for y0, x0 in ((40, 60), (100, 100), (150, 30)):
        prev = np.ascontiguousarray(real_image[y0:y0 + 64, x0:x0 + 64])
        m = np.float32([[1, 0, shift], [0, 1, shift]])
        curr = cv2.warpAffine(prev, m, (64, 64), flags=cv2.INTER_CUBIC,
                              borderMode=cv2.BORDER_REFLECT)
        pos, _, ok = track_ssd(prev, curr, anchors, anchors, corr_half=n, search_half=2,
                               weights=window_weights("uniform", n), subpixel=True)
        assert ok.all()
        errors.append(np.hypot(*(pos - (anchors + shift)).T))
    far_side = np.concatenate([e[:10] for e in errors])
    near_side = np.concatenate([e[10:] for e in errors])
    assert far_side.max() <= 0.2 and np.median(far_side) <= 0.08, np.sort(far_side)[-5:]
    assert np.median(near_side) <= 0.08


@nb.njit(cache=True)
def _dots_of(gx, gy, scale, pix, o0, o1, o2):
    plain = ssd._pixel_dots(gx, gy, pix, (o0, o1, o2), gx.shape[0])
    scaled = ssd._scaled_dots(gx, gy, scale, pix, (o0, o1), gx.shape[0])
    return plain, scaled


@pytest.mark.parametrize("dtype", [np.int16, np.int64])
def test_pixel_dots_are_the_plain_sums(dtype):
    """The refinement's multiply-add sums (a gradient times a pixel, in pairs of lanes) equal
    numpy's sums in int64, for gradients of either sign up to the int16 range and pixels up to
    255, at several offsets; scaled, of the gradients times a factor (in their own width:
    kept within int16 here, as the refinement does)."""
    rng = np.random.default_rng(3)
    size = 4 * ssd.DOT_LANES
    top = 32767 if dtype == np.int16 else 1 << 40
    gx = rng.integers(-top, top + 1, size).astype(dtype)
    gy = rng.integers(-top, top + 1, size).astype(dtype)
    gx[:3] = [top, -top, 0]
    pix = rng.integers(0, 256, size + 40).astype(np.uint8)
    pix[:8] = 255
    offs = (0, 7, 33)
    scale = rng.integers(-3, 4, size).astype(dtype)
    small_x, small_y = gx // 16, gy // 16  # times at most 3: still int16
    plain, _ = _dots_of(gx, gy, scale, pix, *offs)
    _, scaled = _dots_of(small_x, small_y, scale, pix, *offs)
    p = pix.astype(np.int64)
    want = [int(g.astype(np.int64) @ p[o:o + size]) for g in (gx, gy) for o in offs]
    want_scaled = [int((g.astype(np.int64) * scale) @ p[o:o + size])
                   for g in (small_x, small_y) for o in offs[:2]]
    if dtype == np.int16:  # int32 sums: what fits (these do) is exact
        assert all(abs(v) < 2**31 for v in want + want_scaled)
    assert [int(v) for v in plain] == want
    assert [int(v) for v in scaled] == want_scaled


def test_track_ssd_refuses_coordinates_the_search_cannot_index():
    """A NaN, an infinity or an integer near the int64 limit as an anchor or a centre
    overflowed the search's bounds checks and read memory at random (SIGSEGV, found by a
    fuzzer); a NaN anchor came back ok with a made-up match. Refused, naming the point and the
    range, as track_pyramid does."""
    rng = np.random.default_rng(0)
    a = rng.integers(0, 256, (100, 120), dtype=np.uint8)
    w = window_weights("uniform", 4)
    good = np.array([[50.0, 50.0]])
    cases = [("centers", good, np.array([[np.nan, 50.0]])),
             ("anchors", np.array([[50.0, np.nan]]), good),
             ("centers", good, np.array([[50.0, -np.inf]])),
             ("anchors", np.array([[1e300, 50.0]]), good),
             ("centers", np.array([[50, 50]]), np.array([[np.iinfo(np.int64).max, 50]])),
             ("anchors", np.array([[np.iinfo(np.int64).min, 50]]), np.array([[50, 50]])),
             ("anchors", np.array([[2**31, 50]]), np.array([[50, 50]]))]
    for name, anchors, centers in cases:
        for search in ("pruned", "exhaustive"):
            with pytest.raises(ValueError, match=rf"{name} must be finite x, y px within "
                                                 r"\+-1\.07374e\+09: got \("):
                track_ssd(a, a, anchors, centers, corr_half=4, search_half=7, weights=w,
                          search=search, subpixel=True)
    with pytest.raises(ValueError, match="differ in shape"):
        track_ssd(a, a, np.array([[50, 50], [60, 60]]), np.array([[50, 50]]), corr_half=4,
                  search_half=7, weights=w)
    with pytest.raises(ValueError, match="must be numbers"):
        track_ssd(a, a, np.array([["50", "50"]]), np.array([["50", "50"]]), corr_half=4,
                  search_half=7, weights=w)
    # far outside the frame but within the range: simply not found, the other one tracked
    pos, _, ok = track_ssd(a, a, np.array([[50, 50], [-10**8, 50]]),
                           np.array([[50, 50], [-10**8, 50]]), corr_half=4, search_half=7,
                           weights=w)
    assert ok.tolist() == [True, False] and pos[0].tolist() == [50.0, 50.0]
