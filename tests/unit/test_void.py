"""Frames that are not picture to their edges: black bars (a stream letterboxed or
pillarboxed to another aspect) and a fisheye lens's dark corners
(:func:`vistrack.common.vision.features.void_runs`, :func:`.void_step`).

Such a region stays put while the scene moves: a feature whose window straddles its edge is
pulled by the edge against the texture. On Urban2's view panning (3.3, 1.2) px a frame with
40 px bars at the sides, the motion drifted 3.1 px in 39 frames and the scale read 0.964 for
1, every estimate valid (a hunt of frames with bars, 2026-12-08).
"""

from __future__ import annotations

import numpy as np
import pytest

from vistrack.common.vision import tracker as tracker_module
from vistrack.common.vision.features import near_void, void_runs, void_step
from vistrack.common.vision.tracker import Tracker

from conftest import panned_views


def test_bars_and_an_image_circle_are_found_from_the_edges():
    frame = np.full((60, 80), 120, np.uint8)
    frame[:10] = 0  # a bar at the top
    frame[:, 70:] = 16  # video black at the right
    runs, any_run = void_runs(frame, 24, 1)
    assert any_run
    # from the top: the bar; the columns of 16s run the whole height, which a dark sky's
    # rows and columns also do: left to the runs that end (the 16s from the right)
    assert (runs[2, :70] == 10).all() and (runs[2, 70:] == 0).all()
    assert (runs[1, :60] == 10).all()  # the 16s, from the right
    # the top rows' 0s from the left (up to the 16s, another level) span 10 rows, fewer than
    # VOID_SPAN: the bar is the columns'; nothing at the bottom
    assert not runs[0].any() and not runs[3].any()
    # a dark run too shallow, or on too few rows, is the scene's
    spots = np.full((60, 80), 120, np.uint8)
    spots[20:50, :3] = 0  # 3 px deep
    spots[5:10, -8:] = 0  # 5 rows
    assert void_runs(spots, 24, 1)[1] is False
    # an image circle: each row's dark corners reach in as far as the circle leaves them
    yy, xx = np.mgrid[:60, :80]
    circle = np.where((xx - 39.5) ** 2 + (yy - 29.5) ** 2 <= 35 ** 2, 150, 0).astype(np.uint8)
    runs, _ = void_runs(circle, 24, 1)
    lead = [int(np.argmax(row > 0)) if (row > 0).any() else 80 for row in circle]
    assert runs[0, :60].tolist() == [0 if n == 80 else n for n in lead]
    assert runs[1, :60].tolist() == runs[0, :60].tolist()  # the circle is symmetric
    # texture, a bright edge, or a dark one that is not flat, is not void
    rng = np.random.default_rng(1)
    dark_scene = rng.integers(0, 20, (60, 80)).astype(np.uint8)
    assert not void_runs(dark_scene, 24, 1)[0].any()
    assert not void_runs(np.full((60, 80), 200, np.uint8), 24, 1)[0].any()


def test_a_void_is_taken_only_once_it_stayed_while_the_features_moved():
    now = np.zeros((4, 8), np.int32)
    now[0, :] = 12
    ref, at, proven = np.zeros((4, 8), np.int32), np.zeros((4, 8)), np.zeros((4, 8), bool)
    out, found = void_step(now, ref, at, proven, 0.0, 1, 3.0)  # first seen
    assert not found
    out, found = void_step(now, ref, at, proven, 2.0, 1, 3.0)  # moved 2 px: not yet
    assert not found
    out, found = void_step(now, ref, at, proven, 3.5, 1, 3.0)  # 3.5 px: a bar
    assert found and (out[0] == 12).all() and not out[1:].any()
    # a dark part of the scene moves with it: its run changes and is never taken
    ref2, at2, proven2 = np.zeros((4, 8), np.int32), np.zeros((4, 8)), np.zeros((4, 8), bool)
    for k in range(10):
        moving = np.zeros((4, 8), np.int32)
        moving[0, :] = 12 + 2 * k
        _, found = void_step(moving, ref2, at2, proven2, 2.0 * k, 1, 3.0)
        assert not found
    # and a still camera proves nothing
    ref3, at3, proven3 = np.zeros((4, 8), np.int32), np.zeros((4, 8)), np.zeros((4, 8), bool)
    for _ in range(10):
        _, found = void_step(now, ref3, at3, proven3, 0.0, 1, 3.0)
        assert not found


def test_a_window_that_would_take_in_a_void_is_near_it():
    runs = np.zeros((4, 100), np.int32)
    runs[0, :] = 20  # a bar 20 px wide at the left of a 100 x 100 frame
    pts = np.array([[30.0, 50.0], [33.0, 50.0], [60.0, 50.0]])
    assert near_void(pts, runs, (100, 100), 13).tolist() == [True, False, False]


def _barred(name: str, n: int, step: tuple[float, float], bars: int) -> list[np.ndarray]:
    frames = panned_views(name, n, step, 3)
    for frame in frames:
        frame[:, :bars] = 0
        frame[:, -bars:] = 0
    return frames


@pytest.mark.data
@pytest.mark.parametrize("name", ["Urban2", "RubberWhale"])
def test_the_view_s_motion_holds_between_black_bars(name):
    """A pan between 40 px bars: after 39 frames the motion and scale are the view's."""
    n, step = 39, (3.3, 1.2)
    frames = _barred(name, n, step, 40)
    truth = (-step[0] * (n - 1), -step[1] * (n - 1))
    tracker = Tracker()
    for frame in frames:
        est = tracker.process(frame)
    assert (est.dx, est.dy) == pytest.approx(truth, abs=0.5), ((est.dx, est.dy), truth)
    assert est.scale == pytest.approx(1.0, abs=0.004)
    assert est.valid and not est.first


@pytest.mark.data
def test_the_bars_are_what_pulled_the_motion(monkeypatch):
    """The same run with no region taken as void (the level below black): the bars pull the
    motion off, as they did before (so the test above tests the void)."""
    monkeypatch.setattr(tracker_module, "VOID_LEVEL", -1)
    n, step = 39, (3.3, 1.2)
    tracker = Tracker()
    for frame in _barred("Urban2", n, step, 40):
        est = tracker.process(frame)
    truth = (-step[0] * (n - 1), -step[1] * (n - 1))
    off = max(abs(est.dx - truth[0]), abs(est.dy - truth[1]), 100 * abs(est.scale - 1.0))
    assert off > 1.0, ((est.dx, est.dy, est.scale), truth)
