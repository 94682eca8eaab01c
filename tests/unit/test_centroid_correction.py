"""Step 7 of the coarse-to-fine tracker (:func:`.pyramid._affine_correction`): an estimate over
a window is of the motion at the window's texture-weighted centroid; where the neighbourhood
scales or turns, it is moved to the feature's point by the similarity its neighbours fit."""

from __future__ import annotations

import numpy as np
import pytest

from vistrack.common.vision import pyramid, ssd

R = np.array([[0.0, -1.0], [1.0, 0.0]])


def field(seed: int, a: float, b: float):
    """30 features over 200 x 200 px, each measured at a centroid c a few px from it, in a
    displacement field t + A p (A = a I + b R): (pts, where each truly went, c, A)."""
    rng = np.random.default_rng(seed)
    pts = rng.uniform(20, 220, (30, 2))
    A = a * np.eye(2) + b * R
    truth = pts + np.array([1.5, -0.7]) + (pts - 120.0) @ A.T
    cen = rng.uniform(-4.0, 4.0, (30, 2))
    return pts, truth, cen, A


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
    """A 10 % scale step with a turn: each window's estimate is off by A c (0.1 to 0.6 px);
    corrected, within 0.02 px of where the feature went."""
    pts, truth, cen, A = field(1, 0.10, 0.04)
    measured = truth + cen @ A.T
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
    pts, truth, cen, A = field(4, 0.40, 0.0)
    measured = truth + cen @ A.T
    assert np.array_equal(correct(pts, measured, cen), measured)


def test_too_few_matches_for_a_neighbourhood_are_left_alone():
    pts, truth, cen, A = field(5, 0.10, 0.0)
    pts, truth, cen = pts[:pyramid.NEIGHBOURS], truth[:pyramid.NEIGHBOURS], \
        cen[:pyramid.NEIGHBOURS]
    measured = truth + cen @ A.T
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
    cx, cy = pyramid._centroid(half, 20, 20, 10, wide, True)
    assert cx > 4.0 and abs(cy) < 1.0, (cx, cy)
