"""Network benchmark (deselected by default: ``pytest -m bench``; or
``python -m vistrack.services.bench.net``): latency and frame throughput on loopback and, as
root, across network namespaces through a router, over TCP, mutual TLS and the deploy/multi-host
chain.

Prints the table; asserts only that every figure was measured, never a time.
"""

from __future__ import annotations

import io
import math
import os

import pytest

from vistrack.services.bench.net import bench_net

pytestmark = pytest.mark.bench


def test_bench_net(capsys):
    buf = io.StringIO()
    fig = bench_net(out=buf, seconds=2.0, rounds=200, repeat=2)
    with capsys.disabled():
        print("\n" + buf.getvalue())
    paths = ["loopback_p2p_shm", "loopback_p2p", "loopback_router"]
    if os.geteuid() == 0 and "(namespace paths skipped" not in buf.getvalue():
        paths += ["netns_router_tcp", "netns_router_tls", "netns_deployment"]
    for path in paths:
        for figure in ("frame_ms", "small_ms", "fps"):
            value = fig[f"{path}_{figure}"]
            assert math.isfinite(value) and value > 0, (path, figure)
