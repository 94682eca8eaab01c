"""Soak benchmark (deselected by default: ``pytest -m bench``; or ``vistrack bench soak``).

Prints every service's memory over the run and the loss accounting of the unpaced pipeline.
Asserts the accounting adds up and nothing was rejected or failed, never a rate.
"""

from __future__ import annotations

import io

import pytest

from vistrack.services.bench.soak import bench_soak

pytestmark = pytest.mark.bench


def test_bench_soak(capsys):
    buf = io.StringIO()
    fig = bench_soak(out=buf, seconds=20.0)
    with capsys.disabled():
        print("\n" + buf.getvalue())
    assert fig["sent"] > 0 and fig["exits"] == 0
    assert fig["uncounted"] == fig["sent"] - fig["estimates"] - fig["dropped"]
    assert fig["rejected_failed"] == 0
    for name in ("preprocessing", "motion-estimation", "auto-tuner", "fuzzy-controller"):
        assert fig[f"{name}_rss10_mib"] > 0 and fig[f"{name}_rss_end_mib"] > 0
