"""Tuning-cycle benchmark (deselected by default: ``pytest -m bench``; or
``python -m vistrack.services.bench.tuner``).

Prints the table: for each SSD search (pruned, exhaustive), the time of one whole tuning cycle
(design + sweep) on a 30-frame 256x256 buffer, the optimum's tf against the reference windows
(50, 30) in the same search, its ex and ey, and the Table 3 map. Asserts only that every figure
was measured and is consistent, never a time.
"""

from __future__ import annotations

import io
import math

import pytest

from vistrack.services.auto_tuner.sensitivity import CORR_RANGE, SEARCH_RANGE
from vistrack.services.bench.tuner import SEARCHES, bench_tuner

pytestmark = pytest.mark.bench


def test_bench_tuner(capsys):
    buf = io.StringIO()
    fig = bench_tuner(out=buf)
    with capsys.disabled():
        print("\n" + buf.getvalue())
    runs = {"_".join(k.split("_")[:2]) for k in fig}
    assert {"builtin_pruned", "builtin_exhaustive"} <= runs
    assert {r.split("_")[1] for r in runs} == set(SEARCHES)
    for b in runs:
        for key in ("cycle_s", "design_s", "sweep_s", "tf_ms", "ref_tf_ms", "speedup"):
            assert math.isfinite(fig[f"{b}_{key}"]) and fig[f"{b}_{key}"] > 0, key
        assert fig[f"{b}_speedup"] == pytest.approx(fig[f"{b}_ref_tf_ms"] / fig[f"{b}_tf_ms"])
        assert fig[f"{b}_ex_px"] >= 0 and fig[f"{b}_ey_px"] >= 0
        assert fig[f"{b}_within_tolerance"] in (0.0, 1.0)
        assert SEARCH_RANGE[0] <= fig[f"{b}_search_size"] <= SEARCH_RANGE[1]
        assert CORR_RANGE[0] <= fig[f"{b}_corr_size"] <= CORR_RANGE[1]
    assert buf.getvalue().count(" tf 99 % [") == 1 + len(runs)  # the paper's, then each run
