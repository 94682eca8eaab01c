"""Degenerate frames a robot's camera does see (a covered lens, a dark room, a white wall, a
frame too small to hold a window): finite estimates, no features where there is no texture,
and no exception."""

from __future__ import annotations

import io
import json
import math

import cv2
import numpy as np
import pytest

from vistrack.common.params import TrackerParams
from vistrack.common.vision import Tracker

NUMBERS = ("xc", "yc", "xe", "ye", "dx", "dy", "scale", "t_ms")


def assert_finite(e) -> None:
    for name in NUMBERS:
        value = getattr(e, name)
        assert math.isfinite(value), (name, value)
    assert e.scale > 0
    assert np.isfinite(e.points).all() and e.points.shape == (e.npi, 2)


@pytest.mark.parametrize("value", [0, 128, 255])
def test_black_uniform_and_saturated_frames_have_no_features(value):
    """An all-black (covered lens), uniform or saturated frame has no texture: no feature, an
    invalid estimate, every number finite."""
    tracker = Tracker(TrackerParams())
    for _ in range(3):
        e = tracker.process(np.full((256, 256), value, np.uint8))
        assert e.npi == 0 and not e.valid
        assert_finite(e)


def test_a_real_frame_then_a_black_one(real_image):
    """The lens is covered: every feature is lost at once, the estimate is invalid and
    finite, the motion accumulated so far is kept; when it is uncovered, the features found
    begin a new track (first, its motion and scale from there: the scene moved back 2 px
    unseen meanwhile, which no estimate may claim to have measured). The track used to go
    on, its dx carrying the old track's 2 px onto the new features."""
    tracker = Tracker(TrackerParams())
    e0 = tracker.process(real_image)
    assert e0.valid and e0.npi > 50
    shifted = cv2.warpAffine(real_image, np.float32([[1, 0, 2.0], [0, 1, 0]]),
                             real_image.shape[::-1], borderMode=cv2.BORDER_REFLECT)
    e1 = tracker.process(shifted)
    assert abs(e1.dx - 2.0) < 0.1
    black = tracker.process(np.zeros_like(real_image))
    assert black.npi == 0 and not black.valid
    assert_finite(black)
    assert (black.dx, black.dy, black.scale) == (e1.dx, e1.dy, e1.scale)
    again = tracker.process(real_image)
    assert again.valid and again.npi > 50
    assert_finite(again)
    assert again.first and (again.dx, again.dy, again.scale) == (0.0, 0.0, 1.0)
    moved = tracker.process(cv2.warpAffine(real_image, np.float32([[1, 0, -3.0], [0, 1, 0]]),
                                           real_image.shape[::-1],
                                           borderMode=cv2.BORDER_REFLECT))
    assert not moved.first and abs(moved.dx + 3.0) < 0.1 and abs(moved.dy) < 0.1


@pytest.mark.parametrize("sigma", [0.5, 2.0, 5.0, 8.0])
def test_a_uniform_scene_with_sensor_noise_has_no_features(sigma):
    """A white wall, a covered lens in a dark room: sensor noise is not texture, below
    noise_sigma (2 grey levels by default) or above it, where the camera's gain is up."""
    rng = np.random.default_rng(2)
    tracker = Tracker(TrackerParams())
    for _ in range(3):
        frame = np.clip(np.rint(160 + rng.normal(0, sigma, (256, 256))), 0, 255)
        e = tracker.process(frame.astype(np.uint8))
        assert e.npi == 0 and not e.valid


@pytest.mark.parametrize(("shape", "value"), [
    ((8, 8), 100),        # holds no correlation window (9 x 9) plus its margin
    ((8, 8), -1),         # the same, with texture
    ((5, 7), 3),          # smaller than the correlation window
    ((5, 7), -1),
    ((1, 1), 0),
    ((1, 300), 200),
])
def test_frames_too_small_for_a_feature_give_finite_estimates(shape, value):
    """A frame too small for any feature gave xc = NaN, which no message can carry."""
    tracker = Tracker(TrackerParams())
    rng = np.random.default_rng(0)
    for _ in range(3):
        frame = (rng.integers(0, 256, shape) if value < 0 else np.full(shape, value)
                 ).astype(np.uint8)
        e = tracker.process(frame)
        assert e.npi == 0 and not e.valid
        assert_finite(e)
        # no feature, no centroid: the centre of the image, no scatter, no motion
        assert (e.xc, e.yc) == ((shape[1] - 1) / 2, (shape[0] - 1) / 2)
        assert (e.xe, e.ye, e.dx, e.dy, e.scale) == (0.0, 0.0, 0.0, 0.0, 1.0)


def test_track_jsonl_and_csv_of_tiny_frames_are_finite(tmp_path):
    """`vistrack track` over frames too small for a feature: JSON without NaN, CSV too."""
    from vistrack.services import cli
    from vistrack.services.offline.track import run

    for k in range(3):
        cv2.imwrite(str(tmp_path / f"f{k}.png"), np.full((6, 6), 40 * k, np.uint8))
    for fmt in ("jsonl", "csv"):
        out = io.StringIO()
        args = cli.build_parser("track").parse_args(["track", str(tmp_path), "--format", fmt])
        assert run(args, out) == 0
        lines = out.getvalue().splitlines()
        if fmt == "jsonl":
            rows = [json.loads(line, parse_constant=lambda c: pytest.fail(c)) for line in lines]
        else:
            header = lines[0].split(",")
            rows = [dict(zip(header, line.split(","), strict=True)) for line in lines[1:]]
        assert len(rows) == 3
        for row in rows:
            for name in NUMBERS:
                assert math.isfinite(float(row[name])), (fmt, name, row[name])
