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


def field(seed: int, a: float, b: float):
    """30 features over 200 x 200 px in a displacement field t + A p (A = a I + b R), each
    window's centroids c and c' a few px from it: (pts, where each truly went, the centroids
    (N, 4): c then c', what each window measures: truth + a c + b c')."""
    rng = np.random.default_rng(seed)
    pts = rng.uniform(20, 220, (30, 2))
    A = a * np.eye(2) + b * R
    truth = pts + np.array([1.5, -0.7]) + (pts - 120.0) @ A.T
    cen = rng.uniform(-4.0, 4.0, (30, 4))
    return pts, truth, cen, truth + a * cen[:, :2] + b * cen[:, 2:]


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


def test_motions_that_are_no_similarity_are_left_alone():
    """Neighbours whose displacements do not fit one similarity (parallax, a motion boundary,
    a non-rigid scene): nothing moves."""
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
    cx, cy, rx, ry = pyramid._centroid(half, 20, 20, 10, wide, True)
    assert cx > 4.0 and abs(cy) < 1.0, (cx, cy)
    # texture with no direction: the turn centroid is the centroid turned, R c
    assert ry > 4.0 and abs(rx) < 1.0, (rx, ry)


def test_a_windows_estimate_under_a_turn_is_off_by_its_two_centroids(real_image):
    """Frame t+1 is frame t (real, blurred as pre-processing does) turned by 4 degrees about
    its centre; each 21 px window 40 px or more from there is refined by Gauss-Newton from
    where its centre went. Its estimate is off by 0.24 px (median), and a c + b c' from its
    own sums accounts for it to within 0.04 px; A c (c' taken as R c, what step 7 applied
    before) leaves 0.45 px, more than no correction at all."""
    img = cv2.GaussianBlur(np.ascontiguousarray(real_image), (7, 7), 1.0)
    turn = np.deg2rad(4.0)
    rot = np.array([[np.cos(turn), -np.sin(turn)], [np.sin(turn), np.cos(turn)]])
    centre = np.array([127.5, 127.5])
    m = np.hstack([rot, (centre - rot @ centre)[:, None]])
    curr = cv2.warpAffine(img, m, (256, 256), flags=cv2.INTER_CUBIC,
                          borderMode=cv2.BORDER_REFLECT)
    a, b = rot[0, 0] - 1.0, rot[1, 0]
    h = 10
    wide = np.ones((2 * h + 1, 2 * h + 1), np.int32)
    scratch = ssd._refine_scratch(wide, ssd.refine_acc(wide))
    off, explained, as_before = [], [], []
    for ay in range(30, 230, 20):
        for ax in range(30, 230, 20):
            if np.hypot(ax - centre[0], ay - centre[1]) < 40.0:
                continue
            went = m @ [ax, ay, 1.0]
            good, x, y = ssd._refine_with(img, curr, ax, ay, went[0], went[1], h, scratch,
                                          ssd.CENTROID)
            if not good:
                continue
            e = np.array([x, y]) - went
            c, c_turn = scratch[5][:2], scratch[5][2:]
            off.append(np.hypot(*e))
            explained.append(np.hypot(*(e - (a * c + b * c_turn))))
            as_before.append(np.hypot(*(e - (a * c + b * R @ c))))
    assert len(off) >= 60, len(off)
    assert np.median(off) > 0.15, np.median(off)  # the test can tell
    assert np.median(explained) <= 0.06, np.median(explained)
    assert np.median(explained) <= 0.25 * np.median(as_before), (np.median(explained),
                                                                 np.median(as_before))
