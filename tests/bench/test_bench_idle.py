"""Idle CPU benchmark (deselected by default: ``pytest -m bench``; or ``vistrack bench idle``).

Prints every process's share of one core under a plain ``vistrack up`` at 30 fps, with one
thread per numeric library and with the libraries' own count, and the raw Zenoh skeleton's.
Asserts that every figure was measured and the totals are their parts' sums, never a share.
"""

from __future__ import annotations

import io
import math

import pytest

from vistrack.services.bench.idle import bench_idle

pytestmark = pytest.mark.bench


def test_bench_idle(capsys):
    buf = io.StringIO()
    fig = bench_idle(out=buf, seconds=5.0)
    with capsys.disabled():
        print("\n" + buf.getvalue())
    for run in ("ours", "spinning"):
        parts = [v for k, v in fig.items() if k.startswith(f"{run}_") and k[len(run) + 1:]
                 in ("camera", "preprocessing", "motion-estimation", "auto-tuner",
                     "fuzzy-controller", "tuning worker")]
        assert len(parts) >= 5 and all(math.isfinite(v) and v >= 0 for v in parts)
        assert fig[f"{run}_services"] == pytest.approx(sum(parts))
        assert fig[f"{run}_total"] >= fig[f"{run}_services"]
        assert fig[f"{run}_fps"] > 20  # the system was running at its 30 fps
    assert fig["skeleton_percent"] > 0
    assert fig["ratio_skeleton"] == pytest.approx(fig["ours_total"] / fig["skeleton_percent"])
