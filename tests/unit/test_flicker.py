"""Mains flicker seen through a rolling shutter: horizontal bands of brightness that drift
from frame to frame (:func:`vistrack.common.vision.exposure.compensate_rows`).

Light on mains power flickers at 100 or 120 Hz and a rolling shutter reads its rows one after
another: a short exposure sees bands. One gain and offset for the whole frame cannot take them
out; on RubberWhale with bands of +-10 % and an 80-row period drifting a third of a period a
frame the step was off by 4.7 px rms (a hunt of sensor effects, 2026-12-07).
"""

from __future__ import annotations

import numpy as np
import pytest

from vistrack.common.params import TrackerParams
from vistrack.common.vision.exposure import compensate_rows
from vistrack.common.vision.pyramid import build_pyramid
from vistrack.common.vision.tracker import Tracker

from conftest import source_image, view_of

#: 100 Hz light at 30 fps through a rolling shutter reading 256 rows in ~27 ms
PERIOD_ROWS = 80.0
DRIFT = 1.0 / 3.0


def _bands(k: int, rows: int, amp: float = 0.10) -> np.ndarray:
    """The flicker's gain on each row of frame ``k``."""
    y = np.arange(rows, dtype=np.float32)
    return 1.0 + amp * np.sin(2.0 * np.pi * (y / PERIOD_ROWS + DRIFT * k))


def _frames(name: str, n: int, step: tuple[float, float], amp: float) -> list[np.ndarray]:
    source = source_image(name)
    rng = np.random.default_rng(5)
    out = []
    for k in range(n):
        view = view_of(source, 150.0 + step[0] * k, 80.0 + step[1] * k)
        lit = view * _bands(k, view.shape[0], amp)[:, None]
        noisy = lit + rng.standard_normal(view.shape).astype(np.float32)
        out.append(np.clip(np.rint(noisy), 0, 255).astype(np.uint8))
    return out


@pytest.mark.data
@pytest.mark.parametrize("name", ["RubberWhale", "Venus"])
def test_the_view_s_motion_holds_under_drifting_flicker_bands(name):
    """The view moves (1.5, 1) px a frame under bands of +-10 %: after 30 frames the motion
    and the scale are the view's, as without the bands."""
    n, step = 30, (1.5, 1.0)
    tracker = Tracker()
    for frame in _frames(name, n, step, 0.10):
        est = tracker.process(frame)
    truth = (-step[0] * (n - 1), -step[1] * (n - 1))
    assert (est.dx, est.dy) == pytest.approx(truth, abs=0.25), ((est.dx, est.dy), truth)
    assert est.scale == pytest.approx(1.0, abs=0.005)
    assert tracker.exposure_steps >= n - 2  # the bands moved on every frame


@pytest.mark.data
def test_bands_are_taken_out_and_a_steady_or_black_frame_left_alone():
    source = source_image("Urban2")
    view = view_of(source, 100.0, 60.0)
    prev = build_pyramid(np.clip(np.rint(view), 0, 255).astype(np.uint8), 4)
    lit = np.clip(np.rint(view * _bands(1, 256, 0.15)[:, None] / _bands(0, 256, 0.15)[:, None]),
                  0, 255).astype(np.uint8)
    curr = build_pyramid(lit, 4)
    mapped = compensate_rows(prev, curr, (0.0, 0.0), 2.0)
    assert mapped is not prev
    before = np.abs(prev.level(0).astype(float) - lit).mean()
    after = np.abs(mapped.level(0).astype(float) - lit).mean()
    assert after < 0.2 * before, (before, after)
    # the same frame again, and a frame gone black: nothing to take out
    assert compensate_rows(prev, prev, (0.0, 0.0), 2.0) is prev
    black = build_pyramid(np.zeros((256, 256), np.uint8), 4)
    assert compensate_rows(prev, black, (0.0, 0.0), 2.0) is prev


def test_exposure_off_leaves_the_bands_to_the_tracker():
    """``exposure`` false (``--paper`` and its like) maps nothing, rows included."""
    frames = [np.full((64, 64), 100, np.uint8)] * 2
    tracker = Tracker(TrackerParams(exposure=False))
    for frame in frames:
        tracker.process(frame)
    assert tracker.exposure_steps == 0
