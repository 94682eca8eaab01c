"""The kernels' median (:func:`vistrack.common.vision.motion._median_small`), a selection in
place, against ``np.median``: the same value bit for bit, for any order, ties and length."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from vistrack.common.vision.motion import _median, _median_small

finite = st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False, width=64)


@settings(max_examples=300, deadline=None)
@given(arrays(np.float64, st.integers(1, 300), elements=finite))
def test_the_median_is_numpys(values):
    assert _median(values) == np.median(values)
    v = values.copy()
    assert _median_small(v) == np.median(values)
    assert sorted(v.tolist()) == sorted(values.tolist())  # reordered, nothing lost


@settings(max_examples=200, deadline=None)
@given(arrays(np.float64, st.integers(1, 200), elements=st.sampled_from([-1.0, 0.0, 2.5])))
def test_the_median_of_many_ties_is_numpys(values):
    assert _median_small(values.copy()) == np.median(values)


def test_ordered_and_constant_inputs():
    for n in (1, 2, 3, 6, 95, 190, 501):
        up = np.arange(n, dtype=np.float64)
        for v in (up, up[::-1].copy(), np.full(n, 3.0), np.tile([1.0, 0.0], n)[:n].copy()):
            assert _median_small(v.copy()) == np.median(v), (n, v[:4])
