"""Accuracy scoreboard (deselected by default: ``pytest -m bench``; or ``vistrack bench
accuracy``).

Prints the table; asserts only that every sequence was scored, the targets being reported by
the benchmark itself (their tests are in tests/unit/test_accuracy.py).
"""

from __future__ import annotations

import io
import math

import pytest

from vistrack.common import groundtruth
from vistrack.services.bench.accuracy import PAIRS, bench_accuracy

pytestmark = pytest.mark.bench


def test_bench_accuracy(capsys):
    if groundtruth.data_dir() is None:
        pytest.skip("the shared data is needed: set VISTRACK_DATA or put it at ../shared/data")
    buf = io.StringIO()
    fig = bench_accuracy(out=buf)
    with capsys.disabled():
        print("\n" + buf.getvalue())
    for name in PAIRS:
        for kind in ("pair", "long", "long_exposure", "long_blur", "long_jerk",
                     "long_approach", "long_roll", "long_shake", "long_shake_rolling"):
            for what in ("median", "lk_median", "gross"):
                assert math.isfinite(fig[f"{name}_{kind}_{what}"]), (name, kind, what)
        assert 0 <= fig[f"{name}_long_survival"] <= 1
        folder = groundtruth.middlebury(name)
        if folder is not None and (folder / "frame09.png").is_file():  # RubberWhale's 07..14
            for what in ("median", "lk_median", "gross", "gross_one_motion", "gross_beside"):
                assert math.isfinite(fig[f"{name}_running_{what}"]), (name, what)
        assert 0 <= fig[f"{name}_pair_gross_beside"] <= fig[f"{name}_pair_gross"]
        for what in ("dense_median", "dense_narrow_median", "dense_lk_median"):
            assert math.isfinite(fig[f"{name}_{what}"]), (name, what)
