"""Message benchmark (deselected by default: ``pytest -m bench``; or ``vistrack bench
messages``): msgspec against the hand-written checks. Asserts only that every figure was
measured and that the trip sums are those of the figures, never a time.
"""

from __future__ import annotations

import io
import math

import pytest

from vistrack.services.bench.messages import TRIP, bench_messages

pytestmark = pytest.mark.bench


def test_bench_messages(capsys):
    buf = io.StringIO()
    fig = bench_messages(out=buf, rounds=2)
    with capsys.disabled():
        print("\n" + buf.getvalue())
    for key in TRIP:
        for what in ("decode", "encode"):
            for kind in ("msgspec", "checks"):
                v = fig[f"{key.replace('/', '_')}_{what}_{kind}_us"]
                assert math.isfinite(v) and v > 0, (key, what, kind)
    assert fig["trip_saved_us"] == pytest.approx(fig["trip_checks_us"] - fig["trip_msgspec_us"])
