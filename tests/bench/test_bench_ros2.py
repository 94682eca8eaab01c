"""ROS 2 benchmark (deselected by default: ``pytest -m bench``; or ``vistrack bench ros2``):
estimates from a ROS 2 image topic (through the camera service, and read by preprocessing
directly) against a plain ``camera/frame`` at 256x256 and 30 fps,
and every ``control/cmd_vel`` against ``/cmd_vel``.

Prints the table; asserts that every figure was measured and that no command was lost or
reordered (a count, not a time).
"""

from __future__ import annotations

import io
import math

import pytest

from vistrack.services.bench.ros2 import MODES, bench_ros2

pytestmark = pytest.mark.bench


def test_bench_ros2(capsys):
    buf = io.StringIO()
    fig = bench_ros2(out=buf)
    with capsys.disabled():
        print("\n" + buf.getvalue())
    for mode in MODES:
        key = mode.replace(" ", "_")
        assert fig[f"{key}_estimates"] > 0.9 * fig[f"{key}_frames"], mode
        assert math.isfinite(fig[f"{key}_p50_ms"])
    assert fig["cmd_vel_sent"] > 0
    assert fig["cmd_vel_ros"] == fig["cmd_vel_sent"] == fig["cmd_vel_in_order"]
    assert fig["cmd_vel_seq_contiguous"] == 1.0
    assert fig["camera_rejected"] == fig["direct_rejected"] == 0  # good images all taken
