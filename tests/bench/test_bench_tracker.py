"""Tracker benchmark (deselected by default: ``pytest -m bench``; or ``vistrack bench tracker``).

Prints the table; asserts only that every figure was measured, never a time.
"""

from __future__ import annotations

import io
import math

import pytest

from vistrack.common import groundtruth
from vistrack.services.bench.tracker import bench_tracker

pytestmark = pytest.mark.bench


def test_bench_tracker(capsys):
    buf = io.StringIO()
    fig = bench_tracker(out=buf)
    with capsys.disabled():
        print("\n" + buf.getvalue())
    for key in ("ssd_15_9", "matchtemplate_15_9", "lk_level0", "lk_level2", "lk_default",
                "default_ssd", "default_ssd_no_checks", "default_ssd_no_fb",
                "default_ssd_no_wide", "default_ssd_no_consensus", "default_ssd_no_uniqueness",
                "pyramid_build", "ssd_50_30", "ssd_15_9_exhaustive", "ssd_50_30_exhaustive",
                "whole_frame", "whole_frame_paper", "preprocess", "gaussian_blur",
                "whole_frame_steady", "lk_default_steady",
                "default_ssd_gap_0ms", "default_ssd_gap_1.1ms", "default_ssd_gap_33ms",
                "lk_default_gap_0ms", "lk_default_gap_1.1ms", "lk_default_gap_33ms"):
        assert math.isfinite(fig[key]) and fig[key] > 0
    if groundtruth.data_dir() is not None:  # the frames dropped at random need the shared data
        for key in ("skipping_told", "skipping_blind"):
            assert math.isfinite(fig[key]) and fig[key] > 0
