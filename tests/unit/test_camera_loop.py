"""A looping file camera's source (:func:`open_source`): a video cut short (the ``cut_video``
fixture) is played again and again, kept in memory or (too large to keep) decoded each pass."""

from __future__ import annotations

import itertools
import logging

import cv2
import numpy as np
import pytest

from vistrack.common.sources import SourceError
from vistrack.services.camera import service


def _same_frames(got, held):
    """Each frame of ``got`` is the file's next one (``held``: BGR), pass after pass (the grey
    conversion may round one grey level apart from OpenCV's)."""
    for k, frame in enumerate(got):
        ref = cv2.cvtColor(held[k % len(held)], cv2.COLOR_BGR2GRAY)
        assert frame.shape == ref.shape
        assert np.abs(frame.astype(int) - ref).max() <= 1, k


def test_kept_in_memory_it_loops_the_frames_it_holds(cut_video, capsys):
    cut, held = cut_video
    frames = service.open_source(f"file:{cut}", None, loop=True)
    err = capsys.readouterr().err
    assert err == (f"vistrack camera: warning: {cut}: the video ends after {len(held)} of the "
                   f"10 frames its header announces (cut short or damaged); looping the "
                   f"{len(held)} frames it holds\n")
    _same_frames(list(itertools.islice(frames, 3 * len(held) + 1)), held)


def test_decoded_each_pass_it_loops_and_warns_once(cut_video, monkeypatch, caplog):
    cut, held = cut_video
    monkeypatch.setattr(service, "LOOP_CACHE_BYTES", 1)  # too large to keep: every pass decoded
    with caplog.at_level(logging.WARNING, logger="vistrack.camera"):
        got = list(itertools.islice(service.open_source(f"file:{cut}", None, loop=True),
                                    4 * len(held)))
    _same_frames(got, held)
    warnings = [r.getMessage() for r in caplog.records]
    assert warnings == [f"{cut}: the video ends after {len(held)} of the 10 frames its header "
                        "announces (cut short or damaged); looping the frames it holds"]


def test_a_single_pass_still_ends_with_the_error(cut_video):
    cut, held = cut_video
    frames = service.open_source(f"file:{cut}", None, loop=False)
    got = []
    with pytest.raises(SourceError, match=f"ends after {len(held)} of the 10 frames"):
        for f in frames:
            got.append(f)
    _same_frames(got, held)
