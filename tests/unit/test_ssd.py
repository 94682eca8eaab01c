"""Eq. (1): the numba SSD against an independent brute-force numpy version and OpenCV."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

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
