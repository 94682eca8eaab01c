"""A fast approach: the camera moves towards the scene, which grows by 15 % a frame about the
frame's centre (forward driving at a low frame rate). The features near the edges move fastest
(~45 px a frame at 300 px from the centre), and those chosen there are predicted by the last
frame's motion, its scale step included (:meth:`.Tracker._add_features`). Real frames of the
shared data, zoomed by known affine maps (exact ground truth)."""

from __future__ import annotations

import cv2
import numpy as np

from vistrack.common import rendered
from vistrack.common.params import TrackerParams
from vistrack.common.vision import Tracker, pyramid
from vistrack.common.vision import tracker as tracker_module

RATE = 1.15  # scale a frame
FRAMES = 12
MARGIN = 10  # px: a feature nearer the next frame's edge may be lost with its window


def approach(image):
    h, w = image.shape
    c = np.array([w / 2.0, h / 2.0])
    frames = []
    for k in range(FRAMES):
        s = RATE ** k
        m = np.array([[s, 0.0, c[0] * (1 - s)], [0.0, s, c[1] * (1 - s)]])
        frames.append(cv2.warpAffine(image, m, (w, h), flags=cv2.INTER_LINEAR,
                                     borderMode=cv2.BORDER_REFLECT))
    return frames, c


def test_a_fast_approach_keeps_its_features_without_gross_errors(sources):
    """Over the five sources: at most 1 % of the tracked pairs off by more than 2 px (0.44 %;
    LK from the same points: 5 to 13 %), and at least 90 % of the features that stay in the
    frame tracked (96 %). Predicted by the translation alone, the new features near the
    edges were searched 20 to 45 px from where they went, and failed the uniqueness test:
    1.07 % off, 83 % tracked."""
    off = pairs = inside = 0
    for name, image in sources:
        frames, c = approach(image)
        h, w = image.shape
        tracker = Tracker(TrackerParams())
        est = tracker.process(frames[0])
        for k in range(1, FRAMES):
            before = dict(zip(est.ids.tolist(), est.points, strict=True))
            est = tracker.process(frames[k])
            ends = {i: c + RATE * (p - c) for i, p in before.items()}
            errors = [np.hypot(*(p - ends[i])) for i, p in zip(est.ids.tolist(), est.points,
                                                                strict=True) if i in ends]
            stay = sum(MARGIN <= e[0] < w - MARGIN and MARGIN <= e[1] < h - MARGIN
                       for e in ends.values())
            assert len(errors) >= 0.5 * stay, (name, k, len(errors), stay)
            off += int(np.sum(np.array(errors) > 2.0))
            pairs += len(errors)
            inside += stay
    assert off <= 0.01 * pairs, (off, pairs)
    assert pairs >= 0.9 * inside, (pairs, inside)


def test_an_approach_is_measured_at_each_feature_not_at_its_windows_centroid(sources,
                                                                              monkeypatch):
    """The scoreboard's approach (10 % a frame, 12 frames, exact ground truth), frame t not
    scaled by the zoom (``ZOOM_WARP`` off: step 7 alone, as where a zoom is not measured yet,
    or is a near object's own): each source's median error at most 0.1 px (0.047 to 0.074;
    LK from the same points 0.27 to 0.33). With step 7 off too (``AFFINE_FIT_PX`` 0), the
    estimates are of the motion at each window's texture-weighted centroid, a few pixels from
    the feature in a 21 px window: 0.16 to 0.24 px, which this test fails. (With frame t
    scaled, a translation is left to measure and step 7 has nothing to correct: see
    test_accuracy's approach test.)"""
    def median(name, image):
        seq = rendered.approach(image, name)
        tracker = Tracker(TrackerParams())
        est = tracker.process(seq.frames[0])
        errors = []
        for k in range(1, len(seq)):
            before = dict(zip(est.ids.tolist(), est.points, strict=True))
            est = tracker.process(seq.frames[k])
            starts = [before[i] for i in est.ids.tolist() if i in before]
            ends = [p for i, p in zip(est.ids.tolist(), est.points, strict=True) if i in before]
            truth = seq.map(np.array(starts), k - 1, k)
            errors.extend(np.hypot(*(np.array(ends) - truth).T))
        return float(np.median(errors))

    monkeypatch.setattr(tracker_module, "ZOOM_WARP", float("inf"))
    medians = {name: median(name, image) for name, image in sources}
    assert max(medians.values()) <= 0.1, medians
    monkeypatch.setattr(pyramid, "AFFINE_FIT_PX", 0.0)
    off = {name: median(name, image) for name, image in sources}
    assert min(off.values()) > 0.1, off  # the test can tell


def ground(image, name, speed=4.0, n=12):
    """A camera 60 px above a plane textured with ``image``, looking along it (the horizon 60
    px above the frame, focal length 200 px), driving forward ``speed`` px of the plane a
    frame: the top row sees the plane 200 px ahead and moves 1.2 px a frame, the bottom row 38
    px ahead and 35 px a frame, each patch wider by up to 11 % a frame and taller by up to 23
    %. Exact ground truth (a homography of the plane a frame)."""
    f, height, cx, horizon = 200.0, 60.0, 127.5, -60.0
    u0 = image.shape[1] / 2.0
    hs = np.array([[[f, cx, -f * u0 - cx * v0], [0.0, horizon, f * height - horizon * v0],
                    [0.0, 1.0, -v0]] for v0 in 2.0 + speed * np.arange(n)])
    return rendered.RenderedSequence(name, rendered.render(image, hs, (256, 256), seed=3), hs)


def test_a_plane_seen_in_perspective_is_measured_at_each_feature(sources):
    """Forward driving over a ground plane: each patch scales along x and y apart, which no
    similarity fits. Step 7 fits its neighbours' affine map there and corrects each estimate
    by its window's stretch and shear centroids too: medians at most half LK's on every
    source and at most 0.08 px over the five on average (0.076: 0.042 to 0.105; LK 0.18 to
    0.40). With the similarity alone (AFFINE_GENERAL off): 0.083 to 0.136, 0.116 on average
    (d938312: 0.082 to 0.135). The average, not a count
    of sources under 0.08: Urban2's median moves by +-0.005 px with the noise drawn (0.072 to
    0.081 over four seeds, the five sources' means within 0.002 of each other with and
    without step 5c of the coarse-to-fine tracker, which changes which features it holds)."""
    from vistrack.services.bench.accuracy import run_sequence

    medians = []
    for name, image in sources:
        seq = ground(image, name)
        ours, lk, _ = run_sequence(seq.frames, lambda p, k, s=seq: s.map(p, k, k + 1),
                                   TrackerParams())
        assert ours.median_epe <= 0.5 * lk.median_epe, (name, ours, lk)
        assert ours.gross <= 0.03, (name, ours.gross)
        medians.append(ours.median_epe)
    assert np.mean(medians) <= 0.08, medians
