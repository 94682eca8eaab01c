"""Frames skipped: a camera that drops frames, a pipeline that takes the latest. ``seq`` tells
the tracker how many frames the step spans, and the prediction extrapolates the motion over
them, per frame of the step it was measured over (:meth:`.Tracker._gap`). Real frames of the
shared data rendered along the scoreboard's path (up to 12 px a frame, exact ground truth)."""

from __future__ import annotations

import numpy as np
import pytest

from vistrack.common.params import TrackerParams
from vistrack.common.vision import Tracker
from vistrack.common.vision import tracker as tracker_module

from conftest import rendered_sequences


def _skipping(n: int, seed: int = 7) -> list[int]:
    """Frame numbers 0 to n - 1 kept by a camera that drops none, one or two at random."""
    rng = np.random.default_rng(seed)
    kept = [0]
    while (nxt := kept[-1] + int(rng.choice([1, 1, 2, 3]))) < n:
        kept.append(nxt)
    return kept


def _run(seq, kept: list[int], tell: bool):
    """The tracker over ``seq``'s frames ``kept``, told their numbers (``tell``) or not:
    (end-point errors of every tracked pair, features followed, estimates)."""
    tracker = Tracker(TrackerParams())
    est = tracker.process(seq.frames[kept[0]], seq=kept[0] if tell else None)
    errors, estimates = [], [est]
    for a, b in zip(kept, kept[1:], strict=False):
        before = dict(zip(est.ids.tolist(), est.points, strict=True))
        est = tracker.process(seq.frames[b], seq=b if tell else None)
        estimates.append(est)
        for i, p in zip(est.ids.tolist(), est.points, strict=True):
            if i in before:
                errors.append(np.hypot(*(p - seq.map(before[i][None], a, b)[0])))
    return np.array(errors), tracker.followed, estimates


@pytest.fixture(scope="module")
def sequences():
    return rendered_sequences(60, ("Dimetrodon", "Urban2"))


def test_frames_dropped_at_random_are_followed_not_searched(sequences):
    """A camera dropping none, one or two frames at random before each it sends: told the
    frames' numbers, the tracker predicts each step over the frames it spans, and 1.5 to 1.85
    times as many features follow their prediction (the rest are searched coarse to fine, at
    several times the cost), with the same errors (Dimetrodon 642 -> 1186 followed, Urban2
    739 -> 1106; medians 0.026 and 0.025 px both ways)."""
    kept = _skipping(60)
    assert any(b - a > 1 for a, b in zip(kept, kept[1:], strict=False))
    for seq in sequences:
        told, told_followed, _ = _run(seq, kept, True)
        blind, blind_followed, _ = _run(seq, kept, False)
        assert told_followed >= 1.4 * blind_followed, (seq.name, told_followed, blind_followed)
        assert np.median(told) <= 1.05 * np.median(blind), seq.name
        assert np.mean(told > 2.0) <= np.mean(blind > 2.0), seq.name
        assert len(told) >= len(blind), seq.name


def test_numbers_without_gaps_change_nothing(sequences):
    """Consecutive numbers, or every other frame (a steady lower rate: each step spans two
    frames, as the last did), give the same estimates as no numbers at all."""
    seq = sequences[1]
    for kept in (list(range(12)), list(range(0, 24, 2))):
        _, _, told = _run(seq, kept, True)
        _, _, blind = _run(seq, kept, False)
        for t, b in zip(told, blind, strict=True):
            np.testing.assert_array_equal(t.points, b.points)
            np.testing.assert_array_equal(t.ids, b.ids)


def test_a_gap_is_counted_from_the_last_number_and_capped():
    tracker = Tracker(TrackerParams())
    assert tracker._gap(5) == 1  # no number before: a new track
    tracker._seq = 5
    assert [tracker._gap(s) for s in (None, 4, 5, 6, 8, 5 + tracker_module.MAX_GAP + 9)] == \
        [1, 1, 1, 1, 3, tracker_module.MAX_GAP]
