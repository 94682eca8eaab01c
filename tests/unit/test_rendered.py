"""The rendered long sequences (:mod:`vistrack.common.rendered`): their ground truth is exact,
their views stay inside the source, their motion is what it says, and they are deterministic."""

from __future__ import annotations

import zlib

import cv2
import numpy as np
import pytest

from vistrack.common import groundtruth, rendered


def test_rendered_ground_truth_is_exact():
    """A frame rendered with the homographies puts a point of the source exactly where the
    ground truth says: a bright dot, found by its centre of mass, within 0.05 px in every
    frame; the views stay inside the source, and the fastest step is 12 px."""
    source = np.zeros((300, 400), np.uint8)
    cv2.circle(source, (200, 150), 6, 255, -1, lineType=cv2.LINE_AA)
    hs = rendered.homographies((400, 300), (160, 120), 40, max_step=12.0, seed=3)
    frames = rendered.render(source, hs, (160, 120), noise=0.0)
    seq = rendered.RenderedSequence("dot", frames, hs)
    for k, f in enumerate(frames):
        h = hs[k] @ [200.0, 150.0, 1.0]  # where the source's dot centre lands
        expect = h[:2] / h[2]
        if not (10 < expect[0] < 150 and 10 < expect[1] < 110):
            continue  # the dot is out of view
        m = cv2.moments(f.astype(np.float32))
        found = (m["m10"] / m["m00"], m["m01"] / m["m00"])
        assert np.hypot(found[0] - expect[0], found[1] - expect[1]) < 0.05, k
    corners = np.array([[0, 0], [159, 0], [159, 119], [0, 119]], float)
    for k in range(len(hs)):
        src = seq.map(corners, k, k)  # identity check of map
        np.testing.assert_allclose(src, corners, atol=1e-9)
        q = np.hstack([corners, np.ones((4, 1))]) @ np.linalg.inv(hs[k]).T
        q = q[:, :2] / q[:, 2:]
        assert q.min() >= 2 and q[:, 0].max() <= 397 and q[:, 1].max() <= 297
    centre = np.array([[79.5, 59.5]])
    steps = [np.hypot(*(seq.map(centre, k, k + 1) - centre)[0]) for k in range(len(hs) - 1)]
    assert abs(max(steps) - 12.0) < 0.05 and min(steps) < 6.0


def test_rendered_sequences_are_deterministic():
    folder = groundtruth.middlebury("Venus")
    if folder is None:
        pytest.skip("Middlebury Venus not found: set VISTRACK_DATA or put the shared data at "
                    "../shared/data")
    a = rendered.middlebury_sequences(5, names=("Venus",))[0]
    b = rendered.middlebury_sequences(5, names=("Venus",))[0]
    for fa, fb in zip(a.frames, b.frames, strict=True):
        np.testing.assert_array_equal(fa, fb)
    np.testing.assert_array_equal(a.homographies, b.homographies)


def _dot_source(size=(400, 300), at=(200.0, 150.0)):
    source = np.zeros((size[1], size[0]), np.uint8)
    cv2.circle(source, (int(at[0]), int(at[1])), 6, 255, -1, lineType=cv2.LINE_AA)
    return source


def _centre_of_mass(frame):
    m = cv2.moments(frame.astype(np.float32))
    return np.array([m["m10"] / m["m00"], m["m01"] / m["m00"]])


def test_a_jerk_moves_steadily_jumps_once_and_shows_its_dot_where_it_says():
    seq = rendered.jerk(_dot_source(), "dot", steady=(2.5, 1.0), jump=(30.0, -10.0), before=3,
                        after=2, size=(200, 160), noise=0.0)
    assert len(seq) == 7 and seq.name == "dot, jerk"
    p = np.array([[100.0, 80.0]])
    steps = [seq.map(p, k, k + 1)[0] - p[0] for k in range(len(seq) - 1)]
    np.testing.assert_allclose(steps, [[2.5, 1.0]] * 3 + [[30.0, -10.0]] + [[2.5, 1.0]] * 2,
                               atol=1e-9)
    start = seq.map(np.array([[0.0, 0.0]]), 0, 0)  # identity
    assert np.allclose(start, 0.0)
    for k, f in enumerate(seq.frames):  # the source's dot lands where the homography says
        h = seq.homographies[k] @ [200.0, 150.0, 1.0]
        assert np.hypot(*(_centre_of_mass(f) - h[:2] / h[2])) < 0.05, k
    with pytest.raises(ValueError, match="no room"):
        rendered.jerk(_dot_source((220, 300)), "small", size=(200, 160))


def test_an_approach_zooms_about_the_centre_and_shows_its_dot_where_it_says():
    seq = rendered.approach(_dot_source(at=(230.0, 170.0)), "dot", rate=1.2, n=4,
                            size=(200, 160), noise=0.0)
    assert len(seq) == 4 and seq.name == "dot, approach"
    centre = np.array([[99.5, 79.5]])
    p = centre + [[40.0, -20.0]]
    for k in range(3):  # the view's centre stays; a point 40 px right moves out by 20 %
        np.testing.assert_allclose(seq.map(centre, k, k + 1), centre, atol=1e-9)
        np.testing.assert_allclose(seq.map(p, k, k + 1), centre + 1.2 * (p - centre),
                                   atol=1e-9)
    for k, f in enumerate(seq.frames):
        h = seq.homographies[k] @ [230.0, 170.0, 1.0]
        assert np.hypot(*(_centre_of_mass(f) - h[:2] / h[2])) < 0.05, k
    corners = np.array([[0.0, 0.0, 1.0], [199.0, 159.0, 1.0]])
    q = corners @ np.linalg.inv(seq.homographies[0]).T  # the first view inside the source
    assert q[:, :2].min() >= 1.0 and q[1, 0] <= 399.0 and q[1, 1] <= 299.0


def test_a_roll_turns_about_the_centre_and_shows_its_dot_where_it_says():
    seq = rendered.roll(_dot_source(at=(230.0, 170.0)), "dot", rate_deg=5.0, n=4,
                        size=(200, 160), noise=0.0)
    assert len(seq) == 4 and seq.name == "dot, roll"
    centre = np.array([[99.5, 79.5]])
    p = centre + [[40.0, 0.0]]
    turn = np.deg2rad(5.0)
    for k in range(3):  # the view's centre stays; a point 40 px right turns 5 degrees
        np.testing.assert_allclose(seq.map(centre, k, k + 1), centre, atol=1e-9)
        np.testing.assert_allclose(seq.map(p, k, k + 1),
                                   centre + 40.0 * np.array([[np.cos(turn), np.sin(turn)]]),
                                   atol=1e-9)
    for k, f in enumerate(seq.frames):
        h = seq.homographies[k] @ [230.0, 170.0, 1.0]
        assert np.hypot(*(_centre_of_mass(f) - h[:2] / h[2])) < 0.05, k
    with pytest.raises(ValueError, match="cannot hold"):
        rendered.roll(_dot_source((220, 300)), "small", size=(200, 160))


def test_a_shake_jolts_each_frame_within_its_bounds_and_shows_its_dot_where_it_says():
    """Each frame of the slow path jolted by up to 6 px and 2 degrees at random: from frame to
    frame the view's centre moves by the path's step (at most 4 px) and two jolts (at most 12
    px a side), turns by at most 4 degrees and the path's little; the steps scatter as a shake
    does (not a steady path); the dot shows where the homographies put it; a seed repeats."""
    seq = rendered.shake(_dot_source(), "dot", n=12, size=(200, 160), noise=0.0)
    assert len(seq) == 12 and seq.name == "dot, shake"
    ends = np.array([[99.5, 79.5], [139.5, 79.5]])
    steps, turns = [], []
    for k in range(11):
        moved = seq.map(ends, k, k + 1)
        steps.append(moved[0] - ends[0])
        turns.append(np.degrees(np.arctan2(*(moved[1] - moved[0])[::-1])))
    steps = np.array(steps)
    assert np.abs(steps).max() <= 16.0 and (steps.std(axis=0) > 2.0).all(), steps
    assert np.abs(turns).max() <= 4.5, turns
    for k, f in enumerate(seq.frames):
        h = seq.homographies[k] @ [200.0, 150.0, 1.0]
        assert np.hypot(*(_centre_of_mass(f) - h[:2] / h[2])) < 0.05, k
    again = rendered.shake(_dot_source(), "other", n=12, size=(200, 160), noise=0.0,
                           seed=zlib.crc32(b"dot") + 53)
    np.testing.assert_array_equal(again.homographies, seq.homographies)
    with pytest.raises(ValueError, match="no room"):
        rendered.shake(_dot_source(), "far", size=(200, 160), jolt_px=90.0)
