"""Accuracy on long sequences rendered from the real frames of the shared data by known smooth
homographies (large motion, exact ground truth), against OpenCV's pyramidal LK started from the
same points."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vistrack.common import rendered
from vistrack.common.params import TrackerParams
from vistrack.common.vision import Tracker, pyramid
from vistrack.services.bench.accuracy import (
    PAIRS,
    beside_truth,
    one_motion,
    run_sequence,
    scoreboard,
)

from conftest import source_image


@pytest.fixture(scope="module")
def sequences():
    seqs = rendered.middlebury_sequences(60)
    if len(seqs) < len(rendered.SOURCES):
        pytest.skip("Middlebury frames not found: set VISTRACK_DATA or put the shared data at "
                    "../shared/data")
    return seqs


def lk(a, b, points):
    """cv2.calcOpticalFlowPyrLK, default settings: positions and which were found inside."""
    p1, st, _ = cv2.calcOpticalFlowPyrLK(a, b, points.astype(np.float32).reshape(-1, 1, 2),
                                         None)
    p1 = p1.reshape(-1, 2).astype(np.float64)
    h, w = a.shape
    ok = (st.ravel() == 1) & (p1[:, 0] >= 0) & (p1[:, 1] >= 0) & (p1[:, 0] <= w - 1) \
        & (p1[:, 1] <= h - 1)
    return p1, ok


def score(seq):
    """Per-step end-point errors of ours and of LK from our points, and the survival of the
    first frame's features (ours, and LK following them alone)."""
    tracker = Tracker(TrackerParams())
    est = tracker.process(seq.frames[0])
    first = set(est.ids.tolist())
    lk_pts, lk_alive = est.points.copy(), np.ones(est.npi, bool)
    ours, theirs = [], []
    for k in range(1, len(seq)):
        before = dict(zip(est.ids.tolist(), est.points, strict=True))
        q, ok = lk(seq.frames[k - 1], seq.frames[k], est.points)
        theirs.append(np.hypot(*(q[ok] - seq.map(est.points[ok], k - 1, k)).T))
        q, ok = lk(seq.frames[k - 1], seq.frames[k], lk_pts)
        lk_alive &= ok
        lk_pts = np.where(ok[:, None], q, lk_pts)
        est = tracker.process(seq.frames[k])
        for i, p in zip(est.ids.tolist(), est.points, strict=True):
            if i in before:
                true = seq.map(before[i][None], k - 1, k)[0]
                ours.append(np.hypot(*(p - true)))
    survival = len(first & set(est.ids.tolist())) / len(first)
    return np.array(ours), np.concatenate(theirs), survival, float(lk_alive.mean())


@pytest.fixture(scope="module")
def scores(sequences):
    return {seq.name: score(seq) for seq in sequences}


def test_rendered_large_motion_median_error_at_most_lks(scores):
    """On every rendered sequence (the view moving up to 12 px a frame, with rotation, zoom
    and perspective) the median end-point error of ours is at most LK's."""
    for name, (ours, theirs, _, _) in scores.items():
        assert len(ours) > 2000, name
        assert np.median(ours) <= np.median(theirs), (name, np.median(ours),
                                                      np.median(theirs))


def test_rendered_large_motion_few_gross_errors(scores):
    """At most 2 % of the pairs tracked are off by more than 2 px, on every sequence."""
    for name, (ours, _, _, _) in scores.items():
        assert np.mean(ours > 2.0) <= 0.02, (name, np.mean(ours > 2.0))


def test_rendered_first_frame_features_survive(scores):
    """At least half as many of the first frame's features survive the 60 frames as with LK
    (which never rejects a match; most losses are features leaving the view)."""
    for name, (_, _, survival, lk_survival) in scores.items():
        assert survival >= 0.5 * lk_survival, (name, survival, lk_survival)


#: Harder than the scoreboard's paths, as a robot sees them: twice its fastest motion; and a
#: turn while approaching (rotation up to 10 degrees, the view scaled within 1 -/+ 25 %, more
#: perspective), which bends every template.
HARDER = {"fast, 24 px a frame": {"max_step": 24.0},
          "turning and approaching": {"max_step": 8.0, "rotation_deg": 10.0, "zoom": 0.25,
                                      "tilt": 0.05}}


@pytest.mark.parametrize("path", list(HARDER))
def test_harder_paths_hold_the_same_targets(sequences, path):
    """On 40-frame paths harder than the scoreboard's, from every source: median error at most
    LK's, at most 2 % of pairs off by more than 2 px, survival at least half LK's."""
    for seq in sequences:
        source = seq.name.removesuffix(" rendered")
        hard = rendered.sequence(source_image(source), f"{source} {path}", n=40,
                                 **HARDER[path])
        ours, theirs, _ = run_sequence(hard.frames, lambda p, k, s=hard: s.map(p, k, k + 1),
                                       TrackerParams(),
                                       end_truth=lambda p, s=hard: s.map(p, 0, len(s) - 1))
        what = (source, ours, theirs)
        assert ours.pairs > 1500, what
        assert ours.median_epe <= theirs.median_epe, what
        assert ours.gross <= 0.02, what
        assert ours.survival is not None and theirs.survival is not None
        assert ours.survival >= 0.5 * theirs.survival, what


@pytest.fixture(scope="module")
def blurred(sequences):
    """(exposure, source, ours, LK) on the scoreboard's paths (40 frames) with motion blur."""
    out = []
    for exposure in (0.5, 1.0):
        for seq in sequences:
            source = seq.name.removesuffix(" rendered")
            blur = rendered.motion_blurred(source_image(source), source, exposure=exposure)
            ours, theirs, _ = run_sequence(
                blur.frames, lambda p, k, s=blur: s.map(p, k, k + 1), TrackerParams(),
                end_truth=lambda p, s=blur: s.map(p, 0, len(s) - 1))
            out.append((exposure, source, ours, theirs))
    return out


def test_motion_blur_of_half_the_frame_interval_holds_the_targets(blurred):
    """A shutter open half the frame interval (1/60 s at 30 fps) blurs by up to 6 px here,
    and the blur changes with the speed from frame to frame: the correlation window's
    estimate moves, the wide window's much less. The wide one is taken where each side of its
    ring fits about as well as its centre (no second motion in it): median error at most LK's
    (measured 0.79 to 0.91 times), few gross errors, survival at least half LK's. (Taken only
    where the two agreed within 0.1 px, ours was up to 1.19 times LK's; without the wide
    window 1.26 to 1.63.)"""
    for exposure, source, ours, theirs in blurred:
        if exposure != 0.5:
            continue
        what = (source, ours, theirs)
        assert ours.median_epe <= theirs.median_epe, what
        assert ours.gross <= 0.02, what
        assert ours.survival >= 0.5 * theirs.survival, what


def test_motion_blur_of_the_whole_frame_interval_stays_near_lk(blurred):
    """Blur as long as the motion between frames (up to 12 px): within 10 % of LK's median
    error on every source (measured 0.96 to 1.08 times; without the wide window 1.79 to 2.27,
    and with the side test at the correlation window's estimate alone, without EVEN's second
    test at the wide one, up to 1.13)."""
    for exposure, source, ours, theirs in blurred:
        if exposure == 1.0:
            assert ours.median_epe <= 1.1 * theirs.median_epe, (source, ours, theirs)
            assert ours.gross <= 0.02, (source, ours)


def test_the_paper_tracker_cannot_follow_the_large_motion(sequences):
    """The same sequences with the paper's single-level (15, 9) search: its 7 px reach is
    exceeded, and a share of its matches are gross errors (what the pyramid is for)."""
    seq = sequences[0]
    tracker = Tracker(TrackerParams.paper(subpixel=True))
    est = tracker.process(seq.frames[0])
    errors = []
    for k in range(1, len(seq)):
        before = dict(zip(est.ids.tolist(), est.points, strict=True))
        est = tracker.process(seq.frames[k])
        errors += [np.hypot(*(p - seq.map(before[i][None], k - 1, k)[0]))
                   for i, p in zip(est.ids.tolist(), est.points, strict=True) if i in before]
    assert np.mean(np.array(errors) > 2.0) > 0.02


def test_one_motion_tells_a_window_across_a_motion_boundary():
    flow = np.zeros((40, 60, 2), np.float32)
    flow[:, 30:, 0] = 5.0  # two motions, the boundary at x = 30
    flow[:5] = 1e10  # unknown (as .flo files mark it)
    single = one_motion(flow, 4)
    points = np.array([[10, 20], [28, 20], [45, 20], [10, 6], [2, 20]], np.float64)
    # one motion; across the boundary; the other motion; unknown flow in it; off the frame
    assert single(points, 0).tolist() == [True, False, True, False, False]


def test_one_motion_judges_sparse_ground_truth_on_its_known_pixels():
    """KITTI's ground truth is known on a quarter of the pixels or less: a window known
    everywhere was none, and every gross error read as one on a motion boundary. A window is
    judged on its known pixels where they are at least KNOWN_SHARE of it."""
    flow = np.full((40, 60, 2), np.nan, np.float32)  # unknown, as read_flo gives it
    flow[::2, ::2] = 0.0  # a quarter of the pixels known, one motion
    flow[::2, 40::2, 0] = 6.0  # a second motion from x = 40 on
    flow[24:, :20] = np.nan  # and nothing known in the lower left
    single = one_motion(flow, 4)
    points = np.array([[10, 10], [40, 10], [10, 32]], np.float64)
    # one motion on its known pixels; two motions; too little known to tell
    assert single(points, 0).tolist() == [True, False, False]


def test_beside_truth_tells_the_motion_of_a_pixel_next_to_the_point():
    flow = np.zeros((40, 60, 2), np.float32)
    flow[:, 30:, 0] = 5.0  # two motions, the boundary between x = 29 and x = 30
    flow[:, :2] = 1e10  # unknown (as .flo files mark it)
    beside = beside_truth(flow)
    points = np.array([[29, 20], [29, 20], [28, 20], [30, 20], [1, 20], [0, 20]], np.float64)
    moved = np.array([[5.3, 0.2], [2.5, 0], [5.0, 0], [0.4, 0.3], [0.1, 0], [0, 0]])
    # the motion of the pixel beside, 0.36 px off; halfway between the two, neither's; the
    # other motion two pixels from the boundary; from the other side, 0.5 px off; unknown
    # flow at the point and one side of it, known on the other; unknown all round
    assert beside(points, moved, 0).tolist() == [True, False, False, True, True, False]


def test_middlebury_pairs_have_no_gross_error_where_the_window_holds_one_motion():
    """On the real pairs every feature off by more than 2 px lies across a motion boundary,
    where the flow of its centre pixel is not the motion of its window; away from them,
    none (LK from the same points: 2 % on Urban2). Most of them (9 of 13) lie on the motion
    contour itself: their displacement is the ground truth of the pixel beside theirs."""
    rows = [r for r in scoreboard(TrackerParams(), n_frames=3) if r.frames == 2]
    if len(rows) < len(PAIRS):
        pytest.skip("Middlebury pairs not found: set VISTRACK_DATA or put the shared data at "
                    "../shared/data")
    for r in rows:
        assert r.ours.pairs > 50 and r.ours.gross_one_motion == 0.0, r.sequence
        assert r.ours.gross_beside is not None and r.ours.gross_beside <= r.ours.gross
    gross = sum(r.ours.gross * r.ours.pairs for r in rows)
    beside = sum((r.ours.gross_beside or 0.0) * r.ours.pairs for r in rows)
    assert gross > 0 and beside >= 0.5 * gross, (beside, gross)


def test_a_pair_at_the_end_of_a_running_track_holds_the_targets():
    """RubberWhale holds frame07 to frame14: its pair (frame10 to frame11) is also scored at
    the end of a track run from frame07, its features held and followed from their velocity,
    the path a robot's frames take: median error at most LK's from the same features, at
    most 2 % of the pairs off by more than 2 px."""
    rows = [r for r in scoreboard(TrackerParams(), n_frames=3) if ", running" in r.sequence]
    if "RubberWhale (pair, running from frame07)" not in [r.sequence for r in rows]:
        pytest.skip("RubberWhale's frame07 to frame11 not found: set VISTRACK_DATA or put the "
                    "shared data at ../shared/data")
    for r in rows:
        assert r.ours.pairs > 50 and r.lk.pairs > 50, r
        assert r.ours.median_epe <= r.lk.median_epe, r
        assert r.ours.gross <= 0.02 and r.ours.gross_one_motion == 0.0, r


def _approach(source, zoom_warp, monkeypatch):
    """Ours on the scoreboard's approach of ``source`` (10 % a frame), frame t scaled by the
    zoom of the frame before from a zoom step of ``zoom_warp`` on: (score, features rejected,
    frames scaled)."""
    from vistrack.common.vision import tracker as tracker_module

    seq = rendered.approach(source_image(source), f"{source} rendered")
    monkeypatch.setattr(tracker_module, "ZOOM_WARP", zoom_warp)
    ours, _, rejected = run_sequence(seq.frames, lambda p, k: seq.map(p, k, k + 1),
                                     TrackerParams(),
                                     end_truth=lambda p: seq.map(p, 0, len(seq) - 1))
    tracker = Tracker(TrackerParams())
    for frame in seq.frames:
        tracker.process(frame)
    monkeypatch.undo()
    return ours, rejected, tracker.zoom_warps


@pytest.mark.parametrize("source", ["RubberWhale", "Urban2"])
def test_an_approach_is_searched_with_frame_t_scaled_by_the_zoom(sequences, source,
                                                                 monkeypatch):
    """Zooming 10 % a frame, a translation's template fits no displacement well: frame t
    scaled by the zoom of the frame before (ZOOM_WARP) fits it. Against the same tracker
    without the scaling: the median error at most 3/4 of it, fewer matches rejected, no more
    gross errors, and every frame pair but the first (no zoom measured yet) scaled."""
    scaled, rejected, warps = _approach(source, 0.02, monkeypatch)
    plain, plain_rejected, plain_warps = _approach(source, float("inf"), monkeypatch)
    assert plain_warps == 0
    assert warps >= 9  # of the 12 frames' 10 pairs after the first
    assert scaled.median_epe <= 0.75 * plain.median_epe, (scaled, plain)
    assert rejected < plain_rejected
    assert scaled.gross <= plain.gross


def test_frames_without_zoom_are_not_scaled(sequences):
    """The long rendered sequences zoom by a few per mille a frame at most: never scaled."""
    tracker = Tracker(TrackerParams())
    for frame in sequences[0].frames[:30]:
        tracker.process(frame)
    assert tracker.zoom_warps == 0


def _first_pair(source, retry_share, monkeypatch, rescue=True):
    """A track's first frame pair on an approach (10 % a frame) seen by a driving camera's
    1241 x 376 frame, the zoom retry from ``retry_share`` on, the rescue of rejected matches
    (step 5c of :mod:`.pyramid`) on or off: (features tracked, of them off by more than 2 px,
    frames scaled)."""
    from vistrack.common.vision import pyramid
    from vistrack.common.vision import tracker as tracker_module

    monkeypatch.setattr(tracker_module, "ZOOM_RETRY_SHARE", retry_share)
    if not rescue:
        monkeypatch.setattr(pyramid, "RESCUE_FIT_PX", 0.0)
    seq = rendered.approach(source_image(source), f"{source} rendered", n=2, size=(1241, 376))
    tracker = Tracker(TrackerParams())
    first = tracker.process(seq.frames[0])
    second = tracker.process(seq.frames[1])
    monkeypatch.undo()
    before = dict(zip(first.ids.tolist(), first.points, strict=True))
    kept = [(before[i], p) for i, p in zip(second.ids.tolist(), second.points, strict=True)
            if i in before]
    starts = np.array([a for a, _ in kept])
    ends = np.array([b for _, b in kept])
    errors = np.hypot(*(ends - seq.map(starts, 0, 1)).T)
    return len(kept), int(np.count_nonzero(errors > 2.0)), tracker.zoom_warps


@pytest.mark.parametrize("source", ["RubberWhale", "Urban2", "Venus"])
def test_a_tracks_first_pair_in_an_approach_is_searched_again_with_its_zoom(
        sequences, source, monkeypatch):
    """No frame before measured the zoom of a track's first pair, and most features near the
    frame's sides, moving 40 to 60 px, are not found (28, 52 and 22 of 100 here, 1 to 8 of them
    wrongly). Searched again with frame t scaled by the zoom of the matches found, each
    feature predicted by it (:func:`_zoom_retry`): at least 1.5 times as many, none off by
    more than 2 px. The retry is tested alone, the rescue of rejected matches (step 5c of
    :mod:`.pyramid`) off: on, it follows RubberWhale's from their neighbours' zoom and finds
    86 of 100 itself, none off (the retry then has no need to run); with both on (the
    default), as many again, none off: 86, 91 and 76 (alone 29, 50 and 26)."""
    tracked, gross, warps = _first_pair(source, 0.75, monkeypatch, rescue=False)
    alone, _, alone_warps = _first_pair(source, 0.0, monkeypatch, rescue=False)
    assert (warps, alone_warps) == (1, 0)
    assert tracked >= 1.5 * alone, (tracked, alone)
    assert gross == 0
    tracked, gross, _ = _first_pair(source, 0.75, monkeypatch)
    assert tracked >= 1.5 * alone, (tracked, alone)
    assert gross == 0


def _urban2_pair_off(monkeypatch, margin: float) -> tuple[int, int]:
    """Ours on Urban2's pair with up to 500 features (as the scoreboard reads it), the guided
    retry's run kept where it found more by more than ``margin`` of them: (pairs, pairs off
    by more than 2 px)."""
    from vistrack.services.bench.accuracy import _middlebury_pairs

    found = [(frames, step) for name, frames, _, step in _middlebury_pairs() if name == "Urban2"]
    if not found:
        pytest.skip("Middlebury's Urban2 not found: set VISTRACK_DATA or put the shared data "
                    "at ../shared/data")
    frames, step = found[0]
    monkeypatch.setattr(pyramid, "RETRY_MARGIN", margin)
    ours = run_sequence(frames, step, TrackerParams(max_features=500))[0]
    monkeypatch.undo()
    return ours.pairs, round(ours.gross * ours.pairs)


def test_a_retry_that_finds_a_few_more_does_not_replace_the_first_run(monkeypatch):
    """Urban2's pair starts beyond the coarsest search's reach for its foreground, so the
    first run's matches move otherwise than predicted and every feature is tracked again
    around the frame-wide shift. That run found 442 against 425, and took 3 more features on
    motion boundaries, which the foreground's shift pulls to its own motion (2 to 10 px off):
    the first run stands (12 of 425 off, 2.8 %), the retry's would have 14 of 442 (3.2 %)."""
    pairs, off = _urban2_pair_off(monkeypatch, pyramid.RETRY_MARGIN)
    any_gain_pairs, any_gain_off = _urban2_pair_off(monkeypatch, 0.0)
    assert any_gain_pairs > pairs  # the retry did find more: the margin decided
    assert off / pairs <= 0.029 < any_gain_off / any_gain_pairs, (off, pairs, any_gain_off,
                                                                  any_gain_pairs)


def test_the_medians_on_the_pairs_both_tracked_are_over_the_same_pairs():
    """Each tracker's own median is over its own pairs: one that rejects a hard pair the
    other keeps lowers its median for that alone. The scoreboard also gives both medians
    over the pairs both tracked: here an occluder hides some features in the second frame
    (ours rejects them, LK reports them at a wrong place or loses them), and both medians are
    over exactly the features ours kept and LK found, counted here independently."""
    image = source_image("RubberWhale")
    h, w = image.shape
    shift = np.array([3.0, -2.0])
    moved = cv2.warpAffine(image, np.float64([[1, 0, shift[0]], [0, 1, shift[1]]]), (w, h),
                           borderMode=cv2.BORDER_REFLECT)
    moved[h // 3:2 * h // 3, w // 3:2 * w // 3] = 128  # an occluder, uniform grey
    frames = [image, moved]

    def truth(points, k):
        return points + shift

    ours, theirs, _ = run_sequence(frames, truth, TrackerParams())
    # the same run, counted by hand: the features ours kept, and those LK found
    tracker = Tracker(TrackerParams())
    first = tracker.process(image)
    second = tracker.process(moved)
    kept = dict(zip(second.ids.tolist(), second.points, strict=True))
    q, ok = lk(image, moved, first.points)
    both = [j for j, i in enumerate(first.ids.tolist()) if i in kept and ok[j]]
    assert 0 < len(both) < min(ours.pairs, theirs.pairs) or ours.pairs != theirs.pairs
    expected_ours = np.median([np.hypot(*(kept[first.ids[j]] - first.points[j] - shift))
                               for j in both])
    expected_lk = np.median([np.hypot(*(q[j] - first.points[j] - shift)) for j in both])
    assert ours.both_pairs == theirs.both_pairs == len(both)
    assert ours.both_median == pytest.approx(expected_ours)
    assert theirs.both_median == pytest.approx(expected_lk)
