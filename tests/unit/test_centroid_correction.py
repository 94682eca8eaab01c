"""Step 7 of the coarse-to-fine tracker (:func:`.pyramid._affine_correction`): a translation
estimated over a window whose neighbourhood scales by a and turns by b (d = t + (a I + b R) q
at the window's pixel q) is, to first order, t + a c + b c', c = (sum H)^-1 sum H q its
texture-weighted centroid and c' = (sum H)^-1 sum H R q its turn centroid (H each pixel's
gradient outer product); where the neighbourhood scales or turns, the estimate is moved to the
feature's point by the similarity its neighbours fit."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vistrack.common.vision import pyramid, ssd

R = np.array([[0.0, -1.0], [1.0, 0.0]])


def field(seed: int, a: float, b: float, p: float = 0.0, s: float = 0.0):
    """30 features over 200 x 200 px in a displacement field t + A p, A = [[a + p, s - b],
    [s + b, a - p]] (scale a, turn b, stretch p, shear s), each window's centroids c, c', d
    and e a few px from it: (pts, where each truly went, the centroids (N, 8), what each
    window measures: truth + a c + b c' + p d + s e)."""
    rng = np.random.default_rng(seed)
    pts = rng.uniform(20, 220, (30, 2))
    A = np.array([[a + p, s - b], [s + b, a - p]])
    truth = pts + np.array([1.5, -0.7]) + (pts - 120.0) @ A.T
    cen = rng.uniform(-4.0, 4.0, (30, 8))
    measured = truth + a * cen[:, 0:2] + b * cen[:, 2:4] + p * cen[:, 4:6] + s * cen[:, 6:8]
    return pts, truth, cen, measured


def correct(pts, measured, cen):
    out = measured.copy()
    n = len(pts)
    wts = np.ones((9, 9), np.int32)
    pyramid._affine_correction(np.zeros((64, 64), np.uint8), pts, out,
                               np.full(n, ssd.OK, np.int8), np.ones(n, np.bool_), cen, 4, wts,
                               True, pyramid.AFFINE_FIT_PX, np.empty(0, np.int64),
                               np.empty((0, pyramid.NEIGHBOURS), np.int64))
    return out


def test_a_scaling_and_turning_neighbourhood_is_measured_at_each_feature():
    """A 10 % scale step with a turn: each window's estimate is off by a c + b c' (0.1 to 0.6
    px); corrected, within 0.02 px of where the feature went. (Corrected by A c, as if c'
    were R c, which holds only for a window whose texture has no direction: up to 0.3 px.)"""
    pts, truth, cen, measured = field(1, 0.10, 0.04)
    before = np.hypot(*(measured - truth).T)
    after = np.hypot(*(correct(pts, measured, cen) - truth).T)
    assert np.median(before) > 0.2, before
    assert after.max() <= 0.02, after


def test_a_neighbourhood_seen_in_perspective_is_corrected_by_its_affine_map():
    """A plane seen in perspective, approached: its scale along x and y apart (here 4 and 9
    % a frame, a little shear), no similarity. Each window's estimate is off by a c + b c' +
    p d + s e (0.1 to 0.6 px); corrected by the affine map its neighbours fit, 29 of 30
    within 0.02 px (the other's close neighbours fit a similarity, which leaves its stretch:
    0.2 px). A similarity alone left them as they were."""
    pts, truth, cen, measured = field(6, 0.065, 0.005, -0.025, 0.01)
    before = np.hypot(*(measured - truth).T)
    after = np.hypot(*(correct(pts, measured, cen) - truth).T)
    assert np.median(before) > 0.1, before
    assert np.count_nonzero(after <= 0.02) >= 27, after


def test_motions_that_are_no_similarity_are_left_alone():
    """Neighbours whose displacements fit neither a similarity nor an affine map (parallax, a
    motion boundary, a non-rigid scene): nothing moves."""
    pts, _, cen, _ = field(2, 0.0, 0.0)
    measured = pts + np.random.default_rng(3).uniform(-2.0, 2.0, pts.shape)
    assert np.array_equal(correct(pts, measured, cen), measured)


def test_a_scale_step_beyond_the_zoom_range_is_not_applied():
    """A fitted scale step of 40 % a frame is a frame's error, not an approach (AFFINE_MAX)."""
    pts, truth, cen, measured = field(4, 0.40, 0.0)
    assert np.array_equal(correct(pts, measured, cen), measured)


def test_too_few_matches_for_a_neighbourhood_are_left_alone():
    pts, truth, cen, measured = field(5, 0.10, 0.0)
    pts, cen, measured = pts[:pyramid.NEIGHBOURS], cen[:pyramid.NEIGHBOURS], \
        measured[:pyramid.NEIGHBOURS]
    assert np.array_equal(correct(pts, measured, cen), measured)


@pytest.mark.parametrize("h", [10, 20])
def test_the_refinements_centroid_is_the_windows(real_image, h):
    """The wide window's centroid from its Gauss-Newton pass (integer sums) is the one
    :func:`.pyramid._centroid` computes from the frame, on a real image, where its sums fit
    int32 (21 px: pixel dots) and where they do not (41 px: int64); and a window textured
    on its right only has its centroid to the right."""
    img = np.ascontiguousarray(real_image)
    wide = np.ones((2 * h + 1, 2 * h + 1), np.int32)
    scratch = ssd._refine_scratch(wide, ssd.refine_acc(wide))
    assert scratch[6] == (h == 10)  # which of the two ways the sums go
    for ax, ay in ((60, 70), (128, 128), (190, 40)):
        # a refinement whose centroid nobody reads leaves it alone
        scratch[5][:] = np.nan
        good, _, _ = ssd._refine_with(img, img, ax, ay, ax + 0.3, ay - 0.2, h, scratch, ssd.THIRD)
        assert good and np.isnan(scratch[5]).all()
        good, _, _ = ssd._refine_with(img, img, ax, ay, ax + 0.3, ay - 0.2, h, scratch,
                                      ssd.CENTROID)
        assert good
        np.testing.assert_allclose(scratch[5], pyramid._centroid(img, ax, ay, h, wide, True),
                                   atol=1e-9)
    wide = np.ones((21, 21), np.int32)
    half = np.zeros((40, 40), np.uint8)
    half[:, 25:] = np.random.default_rng(0).integers(0, 255, (40, 15))
    cx, cy, rx, ry, *_ = pyramid._centroid(half, 20, 20, 10, wide, True)
    assert cx > 4.0 and abs(cy) < 1.0, (cx, cy)
    # texture with no direction: the turn centroid is the centroid turned, R c
    assert ry > 4.0 and abs(rx) < 1.0, (rx, ry)


def refined(real_image, A, about, ys, xs, far=0.0):
    """Frame t (real, blurred as pre-processing does) mapped by the affine ``A`` about
    ``about`` into frame t+1, bicubic; each 21 px window centred at (x, y), ``far`` px or more
    from ``about``, refined by Gauss-Newton from where its centre went: [(its error (2,), its
    centroids (4, 2): c, c', d, e)], and A - I's scale, turn, stretch and shear."""
    img = cv2.GaussianBlur(np.ascontiguousarray(real_image), (7, 7), 1.0)
    m = np.hstack([A, (about - A @ about)[:, None]])
    curr = cv2.warpAffine(img, m, (256, 256), flags=cv2.INTER_CUBIC,
                          borderMode=cv2.BORDER_REFLECT)
    h = 10
    wide = np.ones((2 * h + 1, 2 * h + 1), np.int32)
    scratch = ssd._refine_scratch(wide, ssd.refine_acc(wide))
    out = []
    for ay in ys:
        for ax in xs:
            if np.hypot(ax - about[0], ay - about[1]) < far:
                continue
            went = m @ [ax, ay, 1.0]
            good, x, y = ssd._refine_with(img, curr, ax, ay, went[0], went[1], h, scratch,
                                          ssd.CENTROID)
            if good:
                out.append((np.array([x, y]) - went, scratch[5].reshape(4, 2).copy()))
    j = A - np.eye(2)
    return out, ((j[0, 0] + j[1, 1]) / 2, (j[1, 0] - j[0, 1]) / 2, (j[0, 0] - j[1, 1]) / 2,
                 (j[0, 1] + j[1, 0]) / 2)


def test_a_windows_estimate_under_a_turn_is_off_by_its_two_centroids(real_image):
    """Frame t+1 is frame t turned by 4 degrees about its centre; each 21 px window 40 px or
    more from there is refined from where its centre went. Its estimate is off by 0.24 px
    (median), and a c + b c' from its own sums accounts for it to within 0.04 px; A c (c'
    taken as R c, what step 7 applied before) leaves 0.45 px, more than no correction at
    all."""
    t = np.deg2rad(4.0)
    rot = np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
    windows, (a, b, _, _) = refined(real_image, rot, np.array([127.5, 127.5]),
                                    range(30, 230, 20), range(30, 230, 20), far=40.0)
    off = [np.hypot(*e) for e, _ in windows]
    explained = [np.hypot(*(e - (a * c[0] + b * c[1]))) for e, c in windows]
    as_before = [np.hypot(*(e - (a * c[0] + b * R @ c[0]))) for e, c in windows]
    assert len(off) >= 60, len(off)
    assert np.median(off) > 0.15, np.median(off)  # the test can tell
    assert np.median(explained) <= 0.06, np.median(explained)
    assert np.median(explained) <= 0.25 * np.median(as_before), (np.median(explained),
                                                                 np.median(as_before))


def test_a_windows_estimate_in_perspective_is_off_by_its_four_centroids(real_image):
    """Frame t+1 is frame t mapped as the near part of a ground plane is when the camera
    moves forward: 5.6 % wider, 11.4 % taller, a little shear. A 21 px window's estimate is
    off by 0.45 px (median); a c + b c' (its similarity part) leaves 0.16, a c + b c' + p d +
    s e, its stretch and shear centroids too, 0.04."""
    windows, (a, b, p, s) = refined(real_image, np.array([[1.056, 0.02], [0.0, 1.114]]),
                                    np.array([128.0, 20.0]), range(30, 120, 15),
                                    range(30, 230, 15))
    off = [np.hypot(*e) for e, _ in windows]
    similar = [np.hypot(*(e - a * c[0] - b * c[1])) for e, c in windows]
    affine = [np.hypot(*(e - a * c[0] - b * c[1] - p * c[2] - s * c[3])) for e, c in windows]
    assert len(off) >= 60, len(off)
    assert np.median(off) > 0.3 and np.median(similar) > 0.1, (np.median(off),
                                                               np.median(similar))
    assert np.median(affine) <= 0.06, np.median(affine)
