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


@pytest.mark.parametrize(("shape", "value"), [
    ((8, 8), 100),        # holds no correlation window (9 x 9) plus its margin
    ((5, 7), 3),          # smaller than the correlation window
    ((1, 1), 0),
    ((1, 300), 200),
])
def test_frames_too_small_for_a_feature_give_finite_estimates(shape, value):
    """A frame too small for any feature gave xc = NaN, which no message can carry."""
    tracker = Tracker(TrackerParams())
    for _ in range(3):
        e = tracker.process(np.full(shape, value, np.uint8))
        assert e.npi == 0
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
