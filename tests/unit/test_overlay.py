"""A burnt-in overlay: an IP camera's or a dashcam's timestamp and name drawn into every
frame, white text outlined in black (:data:`vistrack.common.vision.tracker.OVERLAY_BAND`).

It stays put while the scene moves, and its corners are the frame's strongest: on
RubberWhale's view panning (3.3, 1.2) px a frame they took 29 of 62 features, and the motion
read none for most frames (103 px of drift in 39 frames; Urban2 panning 8 px a frame, 311 px;
an approach read a scale of 1.02 for 1.78), every estimate valid (a hunt of frames with
overlays, 2026-12-08).
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vistrack.common.vision import tracker as tracker_module
from vistrack.common.vision.tracker import Tracker

from conftest import panned_views


def _stamp(frame: np.ndarray, k: int, fps: int = 10) -> np.ndarray:
    """``frame`` with a timestamp at its top left (its seconds counting) and a camera's name
    at its bottom right, as a camera draws them."""
    out = frame.copy()
    h, w = out.shape
    for text, org in ((f"2026-12-08 01:45:{(k // fps) % 60:02d}", (4, 14)),
                      ("CAM 1", (w - 60, h - 8))):
        cv2.putText(out, text, org, cv2.FONT_HERSHEY_SIMPLEX, 0.4, 0, 3, cv2.LINE_AA)
        cv2.putText(out, text, org, cv2.FONT_HERSHEY_SIMPLEX, 0.4, 255, 1, cv2.LINE_AA)
    return out


def _panned(name: str, n: int, step: tuple[float, float]) -> list[np.ndarray]:
    return [_stamp(view, k) for k, view in enumerate(panned_views(name, n, step, 4))]


def _run(frames: list[np.ndarray]):
    """The estimates of the second frame pair's end and of the last frame."""
    tracker = Tracker()
    ests = [tracker.process(frame) for frame in frames]
    return ests[2], ests[-1]


@pytest.mark.data
@pytest.mark.parametrize(("name", "step"), [("RubberWhale", (3.3, 1.2)),
                                            ("Urban2", (3.3, 1.2)),
                                            ("Dimetrodon", (8.0, -2.0))])
def test_the_view_s_motion_holds_behind_a_burnt_in_timestamp(name, step):
    """39 frames of the view panning behind the text: from the second frame pair on, the
    motion and scale are the view's. The first pair, before the text is known to stand
    still while the scene moves, may read less: there the text's features whose windows take
    in the background moving between its letters move up to 0.4 px, beyond the stillness
    bound, and they may be most of the features found (Urban2's read none); from the second
    pair on, the cells of the text proven in the first drop them."""
    n = 39
    early, est = _run(_panned(name, n, step))
    truth = (-step[0] * (n - 3), -step[1] * (n - 3))
    moved = (est.dx - early.dx, est.dy - early.dy)
    assert moved == pytest.approx(truth, abs=0.6), (moved, truth)
    assert est.scale / early.scale == pytest.approx(1.0, abs=0.004)
    assert est.valid and not est.first
    assert (est.dx, est.dy) == pytest.approx((-step[0] * (n - 1), -step[1] * (n - 1)),
                                             abs=abs(step[0]) + abs(step[1]) + 0.6)


@pytest.mark.data
def test_the_text_is_what_held_the_motion(monkeypatch):
    """The same run with no overlay ever proven (its proof out of reach): the text holds the
    motion back, as it did before (so the test above tests the overlay's handling)."""
    monkeypatch.setattr(tracker_module, "OVERLAY_PROOF", float("inf"))
    n, step = 39, (3.3, 1.2)
    early, est = _run(_panned("RubberWhale", n, step))
    truth = (-step[0] * (n - 3), -step[1] * (n - 3))
    moved = (est.dx - early.dx, est.dy - early.dy)
    assert max(abs(moved[0] - truth[0]), abs(moved[1] - truth[1])) > 10.0, moved
