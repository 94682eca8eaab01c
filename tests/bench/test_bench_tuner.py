"""Tuning-cycle benchmark (deselected by default: ``pytest -m bench``; or
``python -m vistrack.services.auto_tuner.bench``).

Prints the table: the time of one whole tuning cycle (design + sweep) on a 30-frame 256x256
buffer, the optimum's tf against the reference windows (50, 30), and its ex and ey. Asserts only
that every figure was measured and is consistent, never a time.
"""

from __future__ import annotations

import io
import math

import pytest

from vistrack.services.auto_tuner.bench import bench_tuner
from vistrack.services.auto_tuner.sensitivity import CORR_RANGE, SEARCH_RANGE

pytestmark = pytest.mark.bench


def test_bench_tuner(capsys):
    buf = io.StringIO()
    fig = bench_tuner(out=buf)
    with capsys.disabled():
        print("\n" + buf.getvalue())
    buffers = {k.split("_")[0] for k in fig}
    assert "builtin" in buffers
    for b in buffers:
        for key in ("cycle_s", "design_s", "sweep_s", "tf_ms", "ref_tf_ms", "speedup"):
            assert math.isfinite(fig[f"{b}_{key}"]) and fig[f"{b}_{key}"] > 0, key
        assert fig[f"{b}_speedup"] == pytest.approx(fig[f"{b}_ref_tf_ms"] / fig[f"{b}_tf_ms"])
        assert fig[f"{b}_ex_px"] >= 0 and fig[f"{b}_ey_px"] >= 0
        assert SEARCH_RANGE[0] <= fig[f"{b}_search_size"] <= SEARCH_RANGE[1]
        assert CORR_RANGE[0] <= fig[f"{b}_corr_size"] <= CORR_RANGE[1]
