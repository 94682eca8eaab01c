"""MCAP recorder and Foxglove bridge benchmark (deselected by default: ``pytest -m bench``; or
``vistrack bench record``).

Prints the table: samples per key in the MCAP file, the .vtr file and hz's count, and the CPU
of the MCAP writer, the .vtr writer, the Foxglove bridge and hz over a 60 s run at 30 fps.
Asserts that every figure was measured and that nothing the camera sent is missing from the
MCAP file (a count, not a time); the CPU targets are printed as met or not, never asserted.
"""

from __future__ import annotations

import io
import math

import pytest

from vistrack.services.bench.record import bench_record

pytestmark = pytest.mark.bench


def test_bench_record(capsys):
    buf = io.StringIO()
    fig = bench_record(out=buf, seconds=60.0)
    with capsys.disabled():
        print("\n" + buf.getvalue())
    for key in ("mcap_cpu_pct", "vtr_cpu_pct", "bridge_cpu_pct", "hz_cpu_pct",
                "bridge_estimates_hz", "bridge_frames_hz", "window_s"):
        assert math.isfinite(fig[key]) and fig[key] > 0, key
    assert fig["camera/frame_mcap"] == fig["frames_published"] == 1800
    assert fig["samples_missing"] == 0
