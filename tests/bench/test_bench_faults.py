"""Faults benchmark (deselected by default: ``pytest -m bench``; or ``vistrack bench faults``).

Prints the tables: hostile and extreme input on a live ``vistrack up``, crash and hang to a new
process ready, the isolation's cost a message. Asserts what was measured and counted (no
service exited, each restart's steps in order), never a time.
"""

from __future__ import annotations

import io

import pytest

from vistrack.services.bench.faults import EXTREME, HOSTILE, bench_faults

pytestmark = pytest.mark.bench


def test_bench_faults(capsys):
    buf = io.StringIO()
    fig = bench_faults(out=buf, crashes=2, hangs=1)
    with capsys.disabled():
        print("\n" + buf.getvalue())
    assert fig["exits"] == 0 and fig["pids_unchanged"] == 1
    assert fig["estimates_after_hz"] > 0
    assert sum(v for k, v in fig.items() if k.endswith("_rejected")) > 0  # they got there
    for name in ("crash", "hang"):
        assert 0 < fig[f"{name}_restarted_s_min"] <= fig[f"{name}_ready_s_min"] \
            <= fig[f"{name}_estimate_s_min"]
    assert fig["isolation_isolated_ns"] > 0 and fig["isolation_recv_node_ns"] > 0
    assert f"{HOSTILE} hostile + {EXTREME} extreme" in buf.getvalue()
