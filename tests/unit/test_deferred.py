"""Candidates computed when first read (``DeferredPreprocessed``): the same values as computed
at once, and the tracker's estimates unchanged whether they are read early, late or never."""

from __future__ import annotations

import numpy as np
import pytest

from vistrack.common import synthetic
from vistrack.common.params import TrackerParams
from vistrack.common.vision import Preprocessed, Tracker, preprocess
from vistrack.common.vision.preprocess import (
    DeferredPreprocessed,
    candidates_of,
    gaussian_filter,
    gradient_magnitude,
    min_eigen_strength,
    threshold_candidates,
)


@pytest.mark.parametrize("params", [TrackerParams(), TrackerParams(strength="gradient"),
                                    TrackerParams(thres_percent=0.5, corr_size=15)])
def test_the_candidates_are_those_of_the_three_steps(params):
    image = synthetic.builtin_sequence(3)[1]
    pre = preprocess(image, params)
    assert isinstance(pre, DeferredPreprocessed) and not pre.computed
    filtered = gaussian_filter(image, params.blur_sigma)
    np.testing.assert_array_equal(pre.filtered, filtered)
    strength_map = (min_eigen_strength if params.strength == "min_eigen"
                    else gradient_magnitude)(filtered)
    cands, strength = threshold_candidates(strength_map, params.thres_percent,
                                           margin=params.corr_half + 1)
    np.testing.assert_array_equal(pre.candidates, cands)
    assert pre.computed
    # exactly: the gradient strength no longer rounds by the arrays' place in memory
    np.testing.assert_array_equal(pre.strength, strength)
    assert pre.candidates is pre.candidates  # computed once


def test_the_tracker_reads_candidates_only_to_select():
    """A steady track reads them on its first frame only; every estimate equals that of a
    tracker fed candidates computed at once."""
    images = synthetic.sequence(12, size=(128, 128), motion=synthetic.Motion(dx=4.0, dy=1.0),
                                seed=3)
    params = TrackerParams(max_features=30)
    lazy, eager = Tracker(params), Tracker(params)
    read = []
    for image in images:
        pre = preprocess(image, params)
        full = Preprocessed(pre.filtered, *candidates_of(pre.filtered, params))
        a, b = lazy.update(pre), eager.update(full)
        read.append(pre.computed)
        assert (a.npi, a.xc, a.yc, a.xe, a.ye, a.dx, a.dy, a.scale) == \
            (b.npi, b.xc, b.yc, b.xe, b.ye, b.dx, b.dy, b.scale)
        np.testing.assert_array_equal(a.points, b.points)
        np.testing.assert_array_equal(a.ids, b.ids)
    assert read[0] and sum(read) == 1 + eager.redetections < len(images)
