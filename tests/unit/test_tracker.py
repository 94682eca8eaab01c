"""The tracker and the position estimate against known motion and real ground-truth flow."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vistrack.common import groundtruth, synthetic
from vistrack.common.params import MIN_VALID_NPI, TrackerParams
from vistrack.common.vision import Tracker, centroid_scatter, incremental_motion, motion, to_gray

from conftest import load_pair, rendered_sequences


def two_frame_run(a, b, params):
    tracker = Tracker(params)
    e0 = tracker.process(a)
    e1 = tracker.process(b)
    start = dict(zip(e0.ids.tolist(), e0.points, strict=True))
    before = np.array([start[i] for i in e1.ids.tolist()])
    return e0, e1, before


@pytest.mark.parametrize("dx,dy", [(3, 0), (0, -2), (2, 1), (0.5, 0), (1.25, -0.75),
                                   (-2.3, 1.6), (0.2, 0.1)])
def test_known_shift_of_a_real_image_recovered(real_image, dx, dy):
    """Real image shifted by a known (sub-)pixel amount: translation within 0.1 px."""
    m = np.float32([[1, 0, dx], [0, 1, dy]])
    shifted = cv2.warpAffine(real_image, m, real_image.shape[::-1], flags=cv2.INTER_LINEAR,
                             borderMode=cv2.BORDER_REFLECT)
    _, e1, before = two_frame_run(real_image, shifted, TrackerParams(subpixel=True))
    disp = e1.points - before
    assert e1.npi >= 80
    # the estimate of the image motion, and the features themselves
    assert abs(e1.dx - dx) <= 0.1 and abs(e1.dy - dy) <= 0.1
    assert np.median(np.abs(disp[:, 0] - dx)) <= 0.1
    assert np.median(np.abs(disp[:, 1] - dy)) <= 0.1


@pytest.mark.parametrize("scale", [0.97, 0.99, 1.02, 1.04])
def test_known_scale_of_a_real_image_recovered(real_image, scale):
    """Real image scaled about its centre by a known factor: scale within 1 %."""
    zoomed = synthetic.warp(real_image, scale=scale)
    _, e1, before = two_frame_run(real_image, zoomed, TrackerParams(subpixel=True))
    assert e1.npi >= 50
    assert abs(e1.scale / scale - 1) <= 0.01
    # scaling about the image centre moves the features' mean by (s - 1)(mean - centre); the
    # estimate averages the inliers only, a subset whose mean differs by a fraction of a px
    centre = (np.array(real_image.shape[::-1]) - 1) / 2.0
    expect = (scale - 1) * (before.mean(axis=0) - centre)
    assert abs(e1.dx - expect[0]) < 0.25 and abs(e1.dy - expect[1]) < 0.25


@pytest.mark.parametrize("sequence", ["RubberWhale", "Dimetrodon", "Venus"])
def test_middlebury_median_endpoint_error(sequence):
    """Tracked features against Middlebury ground-truth flow: median EPE <= 0.5 px."""
    a, b, flow = load_pair(sequence)
    _, e1, before = two_frame_run(a, b, TrackerParams(subpixel=True))
    err = groundtruth.endpoint_errors(before, e1.points, flow)
    assert len(err) >= 50
    assert np.median(err) <= 0.5


def test_table1_motion_along_x_moves_xc_only():
    """Table 1a: motion along X moves xc by the true shift while yc stays put."""
    frames = synthetic.sequence(10, motion=synthetic.Motion(dx=2.0))
    tracker = Tracker(TrackerParams(subpixel=True, redetect_fraction=0.0))
    ests = [tracker.process(f) for f in frames]
    same = 0
    for prev, cur in zip(ests, ests[1:], strict=False):
        if cur.npi == prev.npi:  # the paper's sums jump when features are lost
            assert abs((cur.xc - prev.xc) - 2.0) < 0.1
            assert abs(cur.yc - prev.yc) < 0.1
            same += 1
    assert same >= 5
    assert abs(ests[-1].dx - 18.0) < 0.3 and abs(ests[-1].dy) < 0.3


def test_table1_motion_away_from_camera_shrinks_scatter():
    """Table 1b: the scene recedes (shrinks in the image): xe and ye decrease."""
    frames = synthetic.sequence(10, motion=synthetic.Motion(scale=0.97))
    tracker = Tracker(TrackerParams(subpixel=True, redetect_fraction=0.0))
    ests = [tracker.process(f) for f in frames]
    for prev, cur in zip(ests, ests[1:], strict=False):
        if cur.npi == prev.npi:
            assert cur.xe < prev.xe and cur.ye < prev.ye
    assert ests[-1].xe < 0.85 * ests[0].xe and ests[-1].ye < 0.85 * ests[0].ye
    assert abs(ests[-1].scale - 0.97 ** 9) < 0.01


def test_centroid_and_scatter_are_equation_2():
    pts = np.array([[10.0, 20.0], [14.0, 26.0], [6.0, 17.0]])
    xc, yc, xe, ye = centroid_scatter(pts)
    assert (xc, yc) == (10.0, 21.0)
    assert xe == abs(10 - 10) + abs(10 - 14) + abs(10 - 6)
    assert ye == abs(21 - 20) + abs(21 - 26) + abs(21 - 17)


def test_incremental_motion_ignores_outliers():
    rng = np.random.default_rng(3)
    a = rng.uniform(0, 200, (60, 2))
    b = 100 + 1.05 * (a - 100) + [1.5, -0.5]
    b[:6] += rng.uniform(-20, 20, (6, 2))  # six mismatches
    dx, dy, scale = incremental_motion(a, b)
    inl = slice(6, None)
    expect = (b[inl] - a[inl]).mean(axis=0)  # computed on the true inliers only
    assert abs(dx - expect[0]) < 1e-9 and abs(dy - expect[1]) < 1e-9
    assert abs(scale - 1.05) < 1e-9


@pytest.mark.parametrize("n", [3, 4, 5])
def test_a_step_from_fewer_than_six_pairs_is_their_median_and_no_scale(n):
    """With 3 to 5 pairs an outlier is as likely the fit's as the pairs': a static camera on
    sparse texture in low light read a scale of 0.939 and dx -4.6 px within 13 frames. Below
    FEW_PAIRS the step is the median displacement on each axis, and no scale."""
    assert motion.FEW_PAIRS == 6
    a = np.array([[40.0, 50.0], [120.0, 60.0], [80.0, 140.0], [30.0, 110.0], [150.0, 130.0]])[:n]
    b = a + [1.0, -0.5]
    b[0] += [2.5, 3.0]  # one pair off by a few px, as low light makes them
    dx, dy, scale = incremental_motion(a, b)
    assert (dx, dy) == pytest.approx((1.0, -0.5), abs=1e-12)
    assert scale == 1.0
    # from six pairs, the fit as before: the scale is measured
    a6 = np.vstack([a, [[100.0, 100.0]] * (6 - n) + np.arange(6 - n)[:, None] * [7.0, 11.0]])
    b6 = 90 + 1.02 * (a6 - 90) + [1.0, -0.5]
    assert incremental_motion(a6, b6)[2] == pytest.approx(1.02, abs=1e-9)
    assert incremental_motion(a6[:5], b6[:5])[2] == 1.0


@pytest.mark.parametrize("static", [19, 25, 35, 45])
@pytest.mark.parametrize("step", [1.0, 5.0, 50.0])
def test_a_group_moving_as_one_does_not_drag_the_motion_of_the_rest(static, step):
    """A group of pairs moving as one otherwise than the rest (a static bumper, a burnt-in
    timestamp in view) was kept by the least-squares start of the inlier fit wherever it
    held 18.4 % of the pairs or more: 25 static of 100 made a 5 px motion 3.75. The motion
    most of them share is measured, whatever the group's share below half."""
    rng = np.random.default_rng(static)
    a = np.c_[rng.uniform(0, 320, 100), rng.uniform(0, 240, 100)]
    b = a.copy()
    b[static:] += [step, -0.5 * step]  # the rest moves; the first ``static`` stay
    dx, dy, scale = incremental_motion(a, b)
    assert (dx, dy) == pytest.approx((step, -0.5 * step), abs=1e-9)
    assert scale == pytest.approx(1.0, abs=1e-9)
    # and with a zoom (an approach): the static group, far from the zoom's motion, left out
    b = 160 + 1.04 * (a - 160) + [10.0 * step, 0.0]
    b[:static] = a[:static]
    model = 160 + 1.04 * (a - 160) + [10.0 * step, 0.0]
    assert np.hypot(*(model - b)[:static].T).min() > 1.0  # the static ones are off the zoom
    dx, dy, scale = incremental_motion(a, b)
    inl = slice(static, None)
    assert (dx, dy) == pytest.approx(tuple((b[inl] - a[inl]).mean(axis=0)), abs=1e-9)
    assert scale == pytest.approx(1.04, abs=1e-9)


@pytest.mark.parametrize("rows", [48, 72, 88])
def test_a_static_bumper_in_view_does_not_slow_the_measured_motion(rows):
    """A robot's camera sees its own bumper: the frame's bottom 20 to 37 % holds static real
    texture (Urban2's) while the scene (RubberWhale) moves (2, 1) px a frame. After 19 frames
    the estimate read (27.5, 12.6) px with 48 rows, every frame valid, and a scale shrinking
    0.3 % a frame (the target moving away, to the controller); it reads the scene's motion, as
    LK's median displacement does (a hunt on frames from cameras it was not developed on)."""
    scene, _, _ = load_pair("RubberWhale")
    bumper = load_pair("Urban2")[0][300:300 + rows, 100:420]
    tracker = Tracker()
    for k in range(20):
        frame = scene[60 - k:300 - k, 60 - 2 * k:380 - 2 * k].copy()
        frame[-rows:] = bumper
        est = tracker.process(frame)
        assert est.valid and not (k and est.first)
    assert (est.dx, est.dy) == pytest.approx((38.0, 19.0), abs=0.1)
    assert est.scale == pytest.approx(1.0, abs=0.002)


@pytest.mark.parametrize("step", [(3, 0), (2, -2)])
def test_a_still_camera_watching_something_go_by_reads_no_motion(step):
    """The mirror of the bumper: the camera stands still over RubberWhale while a patch of
    Urban2's real texture (a third of the view's width) moves through it. Its features moving
    as one were averaged with the still ones (30 % of the pairs moving 8 px read dx 2.39 and
    a scale of 1.025; a hunt of camera processing effects): the robot, standing, was told it
    moved. The view's motion is none."""
    scene, _, _ = load_pair("RubberWhale")
    walker = load_pair("Urban2")[0][200:340, 150:260]
    tracker = Tracker()
    for k in range(12):
        frame = scene[60:300, 60:380].copy()
        x, y = 40 + step[0] * k, 50 + step[1] * k
        frame[y:y + 140, x:x + 110] = walker
        est = tracker.process(frame)
        assert est.valid
    assert (est.dx, est.dy) == pytest.approx((0.0, 0.0), abs=0.1)
    assert est.scale == pytest.approx(1.0, abs=0.002)


@pytest.mark.parametrize("degrees", [5.0, 8.0])
def test_a_turn_that_reverses_is_searched_again_at_the_turn_it_took(degrees):
    """A camera looking down from a robot that turns on the spot and back: the view rolls
    ``degrees`` a frame about its centre for 12 frames, then as many the other way. Frame t
    was turned by the last turn, the wrong way at the reversal, and a pair so warped was
    never searched again: 41 of ~90 features kept at 5 degrees, new ones beside them locked
    onto the knit a period away, and the scale read 1.0245 (8 degrees: 1.0098) for a view
    that only turned, every estimate valid (a hunt of robot motions)."""
    source = load_pair("RubberWhale")[0].astype(np.float32)
    h, w = source.shape
    rng = np.random.default_rng(2)
    tracker = Tracker()
    angle = 0.0
    ids = {}
    for k in range(30):
        turn = cv2.getRotationMatrix2D((w / 2.0, h / 2.0), angle, 1.0)
        view = cv2.warpAffine(source, turn, (w, h), flags=cv2.INTER_CUBIC,
                              borderMode=cv2.BORDER_REFLECT)
        view = view[h // 2 - 128:h // 2 + 128, w // 2 - 128:w // 2 + 128]
        noisy = view + rng.standard_normal(view.shape).astype(np.float32)
        est = tracker.process(np.clip(np.rint(noisy), 0, 255).astype(np.uint8))
        assert est.valid and not (k and est.first), k
        ids[k] = set(est.ids.tolist())
        angle += degrees if k < 12 else -degrees
    # the features of the frame before the reversal go on through it (without the search
    # again 39 % and 56 % of them were lost in its two frames, and others taken anew)
    kept = len(ids[12] & ids[14]) / len(ids[12])
    assert kept >= 0.8, kept
    assert est.scale == pytest.approx(1.0, abs=0.002)


@pytest.mark.parametrize("x0", [60, 80, 240])
def test_a_cut_that_keeps_a_few_lookalikes_starts_a_new_track(x0):
    """A cut from RubberWhale to Grove2 (crops moving (2, 1) px a frame) kept 3 or 4 of 82
    features, lookalikes whose displacements were 7 px apart: no new track, and their mean
    jumped the estimate by up to (17.4, 2.8) px, marked valid (3 of 74 such cuts, a hunt on
    frames from other cameras). Fewer than FEW_KEPT of many is a cut: a new track."""
    scene, _, _ = load_pair("RubberWhale")
    other, _, _ = load_pair("Grove2")

    def crop(img, k, left, top):
        return img[top - k:top - k + 240, left - 2 * k:left - 2 * k + 320].copy()

    tracker = Tracker()
    for k in range(12):
        frame = crop(scene, k, 60, 60) if k < 10 else crop(other, k, x0, 40)
        est = tracker.process(frame)
        assert est.first == (k in (0, 10)), k
        if k == 9:
            assert (est.dx, est.dy) == pytest.approx((18.0, 9.0), abs=0.1)
    assert (est.dx, est.dy) == pytest.approx((2.0, 1.0), abs=0.1)  # the new track's first step


@pytest.mark.parametrize("n", [1, 2, 3, 4, 7, 8, 100, 129, 2000])
def test_the_kernels_median_and_sum_are_numpys(n):
    # the robust motion's MAD and sums reproduce numpy's bit for bit (the motion module's
    # notes), ties and repeated values included
    rng = np.random.default_rng(n)
    for v in (rng.uniform(0, 5, n), rng.integers(0, 4, n).astype(np.float64), np.ones(n),
              np.arange(n, 0, -1, dtype=np.float64)):
        assert motion._median(v) == np.median(v)
        assert motion._pairwise_sum(v, n) == np.add.reduce(v)


def test_ids_persist_while_tracked_and_are_never_reused():
    frames = synthetic.sequence(30, motion=synthetic.Motion(dx=3.0, dy=1.0))
    tracker = Tracker(TrackerParams(redetect_fraction=0.9))
    seen: set[int] = set()
    prev = None
    for f in frames:
        e = tracker.process(f)
        ids = e.ids.tolist()
        assert len(ids) == len(set(ids))
        if prev is not None:
            old = dict(zip(prev.ids.tolist(), prev.points, strict=True))
            for i, p in zip(ids, e.points, strict=True):
                if i in old:  # the same feature, moved by the scene's motion
                    assert np.allclose(p - old[i], [3.0, 1.0], atol=1.0)
                else:
                    assert i not in seen  # a new feature gets a new id
        seen.update(ids)
        prev = e
    assert tracker.redetections > 0


def test_parameters_change_between_frames():
    frames = synthetic.sequence(4, motion=synthetic.Motion(dx=1.0))
    tracker = Tracker(TrackerParams())
    tracker.process(frames[0])
    tracker.set_params(TrackerParams(search_size=31, corr_size=15))
    e = tracker.process(frames[1])
    assert tracker.params.search_size == 31 and e.npi > 50 and abs(e.dx - 1.0) < 0.2


def test_frame_size_change_is_an_error():
    tracker = Tracker()
    tracker.process(np.zeros((64, 64), np.uint8))
    with pytest.raises(ValueError, match="differs"):
        tracker.process(np.zeros((64, 80), np.uint8))


@pytest.mark.parametrize("params", [TrackerParams(), TrackerParams(subpixel=True),
                                    TrackerParams(weights="gaussian", search_size=21,
                                                  corr_size=11),
                                    TrackerParams(search_size=50, corr_size=30)])
def test_both_searches_give_identical_estimates_over_a_real_sequence(params):
    """RubberWhale 07-14 at full size, forwards then back: every estimate (features, ids,
    Eq. (2), the accumulated motion) is the same with the pruned and the exhaustive search."""
    folder = groundtruth.middlebury("RubberWhale")
    if folder is None:
        pytest.skip("Middlebury RubberWhale not found: set VISTRACK_DATA or put the shared "
                    "data at ../shared/data")
    frames = [to_gray(cv2.imread(str(folder / f"frame{i:02d}.png"))) for i in range(7, 15)]
    frames += frames[-2::-1]
    runs = {}
    for search in ("pruned", "exhaustive"):
        tracker = Tracker(params.replace(search=search))
        runs[search] = [tracker.process(f) for f in frames]
        runs[search + " lost"] = tracker.lost_total
    for a, b in zip(runs["pruned"], runs["exhaustive"], strict=True):
        assert {k: v for k, v in a.as_dict().items() if k != "t_ms"} == \
               {k: v for k, v in b.as_dict().items() if k != "t_ms"}
    assert runs["pruned lost"] == runs["exhaustive lost"]
    assert min(e.npi for e in runs["pruned"]) >= 50  # the run tracks something


def test_features_redetected_mid_track_are_followed_like_the_others():
    """Features chosen at a re-detection are predicted by the frame's motion and, on the next
    frame, followed from there as the features tracked through it are (step 0 of .pyramid),
    not searched: most of the re-detected ones that survive count among the followed
    matches, and they land where the rendered sequence's exact motion puts them."""
    seq, = rendered_sequences(40, ("RubberWhale",))
    tracker = Tracker(TrackerParams())
    est = tracker.process(seq.frames[0])
    for k in range(1, len(seq.frames) - 1):
        ids_before = set(est.ids.tolist())
        redetections = tracker.redetections
        est = tracker.process(seq.frames[k])
        if tracker.redetections == redetections:
            continue
        new = set(est.ids.tolist()) - ids_before
        start = dict(zip(est.ids.tolist(), est.points, strict=True))
        followed = tracker.followed
        est = tracker.process(seq.frames[k + 1])
        kept_new = [j for j, i in enumerate(est.ids.tolist()) if i in new]
        kept_old = est.npi - len(kept_new)
        assert len(kept_new) >= 10, (len(new), len(kept_new))
        assert tracker.followed - followed >= kept_old + 0.5 * len(kept_new), \
            (tracker.followed - followed, kept_old, len(kept_new))
        starts = np.array([start[i] for i in est.ids[kept_new].tolist()])
        errors = np.hypot(*(est.points[kept_new] - seq.map(starts, k, k + 1)).T)
        assert np.median(errors) <= 0.1 and errors.max() <= 0.5, np.sort(errors)[-5:]
        return
    pytest.fail("no re-detection in the sequence")


@pytest.mark.parametrize("sequence", ["RubberWhale", "Dimetrodon"])
def test_a_first_frames_features_follow_from_no_motion(sequence):
    """A track's first pair has no prediction but no motion, which is close on a camera that
    moves little between frames: its features are followed from there (Bouguet's coarse to
    fine, as LK starts) rather than searched, and land where Middlebury's ground truth puts
    them."""
    a, b, flow = load_pair(sequence)
    tracker = Tracker(TrackerParams())
    e0 = tracker.process(a)
    e1 = tracker.process(b)
    assert tracker.followed >= 0.8 * e0.npi, (tracker.followed, e0.npi)
    start = dict(zip(e0.ids.tolist(), e0.points, strict=True))
    before = np.array([start[i] for i in e1.ids.tolist()])
    err = groundtruth.endpoint_errors(before, e1.points, flow)
    assert e1.npi >= 0.9 * e0.npi and len(err) >= 0.8 * e0.npi  # some flow is unknown
    assert np.median(err) <= 0.05 and np.mean(err <= 0.5) >= 0.9, (np.median(err),
                                                                    np.mean(err <= 0.5))


def test_a_scene_cut_that_leaves_a_match_or_two_starts_a_new_track():
    """A cut from RubberWhale to Grove2 kept 2 of 89 features, lookalikes that moved (+26,
    -30) and (-9, +0.5) px: their mean stepped dx, dy by (+8.8, -14.6) px in an estimate marked
    valid and not first, and the controller would have chased it. A frame that keeps fewer
    than MIN_VALID_NPI (3) of its features drops them and starts a new track."""
    folders = [groundtruth.middlebury(seq) for seq in ("RubberWhale", "Grove2")]
    if None in folders:
        pytest.skip("Middlebury frames not found: set VISTRACK_DATA or put the shared data at "
                    "../shared/data")
    before = [to_gray(cv2.imread(str(p))) for p in sorted(folders[0].glob("frame*.png"))[:5]]
    h, w = before[0].shape
    after = [cv2.resize(to_gray(cv2.imread(str(folders[1] / f"frame{k}.png"))), (w, h))
             for k in (10, 11)]
    tracker = Tracker(TrackerParams())
    ests = [tracker.process(f) for f in before + after]
    steps = [(b.dx - a.dx, b.dy - a.dy) for a, b in zip(ests[:4], ests[1:5], strict=True)]
    assert max(np.hypot(*s) for s in steps) < 2.0  # RubberWhale barely moves
    cut = ests[5]
    # the cut keeps none of the old features; a new track has measured nothing yet
    assert not set(cut.ids.tolist()) & set(ests[4].ids.tolist())
    assert cut.first and (cut.dx, cut.dy, cut.scale) == (0.0, 0.0, 1.0)
    assert cut.valid  # features chosen in the new scene
    # the case itself, made so that it does not hang on which lookalikes the sub-pixel
    # estimates happen to leave (since the wide window's side test this cut keeps none): the
    # new scene with two 31 px patches of the old one left where two features lie, far apart
    tracker = Tracker(TrackerParams())
    ests = [tracker.process(f) for f in before]
    order = np.argsort(ests[-1].points[:, 0])
    left = after[0].copy()
    for x, y in np.rint(ests[-1].points[order[[len(order) // 4, 3 * len(order) // 4]]]):
        x, y = int(x), int(y)
        left[y - 15:y + 16, x - 15:x + 16] = before[-1][y - 15:y + 16, x - 15:x + 16]
    cut = tracker.process(left)
    assert not set(cut.ids.tolist()) & set(ests[-1].ids.tolist())
    assert cut.first and (cut.dx, cut.dy, cut.scale) == (0.0, 0.0, 1.0) and cut.valid
    # a match or two kept (a patch may hold a second feature), dropped as too few
    assert 1 <= tracker.lost_by["few"] <= 2
    assert sum(tracker.lost_by.values()) == tracker.lost_total


def test_a_sparse_track_that_keeps_two_features_is_no_scene_cut():
    """A dim scene holds a handful of features: a frame that keeps 2 of 5 is not a cut. The
    first rule (fewer than 3 kept) restarted such a track at 7 of 60 frames of Dimetrodon
    rendered at 6 % exposure, and its motion ended 29 px off instead of 1.9."""
    from vistrack.common import rendered

    sources = dict(rendered.middlebury_sources(("Dimetrodon",)))
    if "Dimetrodon" not in sources:
        pytest.skip("Middlebury frames not found: set VISTRACK_DATA or put the shared data at "
                    "../shared/data")
    seq = rendered.sequence(sources["Dimetrodon"], "Dimetrodon rendered", n=60)
    rng = np.random.default_rng(5)
    dim = [np.clip(f.astype(np.float32) * 0.06 + rng.normal(0, 1.0, f.shape), 0, 255)
           .astype(np.uint8) for f in seq.frames]
    tracker = Tracker(TrackerParams())
    ests = [tracker.process(f) for f in dim]
    assert min(e.npi for e in ests[1:]) < MIN_VALID_NPI  # the sparse case itself
    assert [k for k, e in enumerate(ests) if e.first] == [0]
    assert tracker.lost_by["few"] == 0
