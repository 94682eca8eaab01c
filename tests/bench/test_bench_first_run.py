"""A new user's first `vistrack demo` against a second one (deselected by default: ``pytest
-m bench -s``; two to three minutes).

The first run starts with numba's and the user's caches empty (``NUMBA_CACHE_DIR`` and
``XDG_CACHE_HOME`` on empty folders): it compiles the tracker's kernels and builds the fuzzy
surface. The second, the peer, runs right after on the caches the first filled. Asserts what
the issue asks of the first run's result (RMS centring error within 0.5 px of the second's;
the compile said on stderr, and nothing said when cached; the camera started after every
other service was ready) and prints both wall times against the 60 s target, which it does
not assert: a time depends on the machine's other work.

It runs in the test's own venv, whose Python bytecode is already compiled; a new user's fresh
venv adds the byte-compilation of the imports to the first run (about a second).
"""

from __future__ import annotations

import json
import os
import re
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.bench

TARGET_S = 60.0


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def demo(out: Path, caches: Path) -> tuple[float, str, dict]:
    """Run ``vistrack demo`` (default scenario) on ``caches``: wall s, stderr, summary."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(caches / "numba"),
           "XDG_CACHE_HOME": str(caches / "user")}
    t0 = time.monotonic()
    run = subprocess.run([sys.executable, "-m", "vistrack.services.cli", "demo", "--out",
                          str(out), "-l", f"tcp/127.0.0.1:{free_port()}",
                          "--no-multicast-scouting"], env=env, capture_output=True, text=True,
                         timeout=600)
    wall = time.monotonic() - t0
    assert run.returncode == 0, run.stderr[-3000:]
    return wall, run.stderr, json.loads((out / "summary.json").read_text())


def ready_at(log: str, service: str) -> float:
    """The time of day (s) in the ready line of ``service`` in ``log``."""
    m = re.search(rf"^\[{service}\] (\d\d):(\d\d):(\d\d\.\d+) .* ready \(robot", log,
                  flags=re.M)
    assert m, f"no ready line of {service}"
    return int(m[1]) * 3600 + int(m[2]) * 60 + float(m[3])


def started_after_ready(log: str) -> bool:
    """Whether the camera was ready after every other service."""
    return all(ready_at(log, s) < ready_at(log, "camera") for s in (
        "fuzzy-controller", "motion-estimation", "preprocessing", "auto-tuner"))


def test_bench_first_run(tmp_path, capsys):
    caches = tmp_path / "caches"
    cold_s, cold_err, cold = demo(tmp_path / "cold", caches)
    warm_s, warm_err, warm = demo(tmp_path / "warm", caches)
    with capsys.disabled():
        print(f"\nfirst run (empty caches): {cold_s:5.1f} s, rms_center_error_px "
              f"{cold['rms_center_error_px']:.3f}, commands {cold['commands']} for "
              f"{cold['frames']} frames")
        print(f"second run (cached):      {warm_s:5.1f} s, rms_center_error_px "
              f"{warm['rms_center_error_px']:.3f}, commands {warm['commands']} for "
              f"{warm['frames']} frames")
        print(f"first run {cold_s - warm_s:+.1f} s ({cold_s / warm_s:.2f}x the second); "
              f"target < {TARGET_S:g} s: {'met' if cold_s < TARGET_S else 'NOT met'}")
    assert abs(cold["rms_center_error_px"] - warm["rms_center_error_px"]) <= 0.5
    assert "compiling the tracker's kernels" in cold_err
    assert "compil" not in warm_err
    for run in ("cold", "warm"):
        assert started_after_ready((tmp_path / run / "services.log").read_text()), run
    cold_log = (tmp_path / "cold" / "services.log").read_text()
    assert "compiling the fuzzy control surfaces" in cold_log
    assert "compiling" not in (tmp_path / "warm" / "services.log").read_text()
