"""The demo's status line (vistrack demo prints one every 2 s while it runs)."""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace

from vistrack.services.launch.demo import _status_line


def _recorder(n: int, period_s: float) -> SimpleNamespace:
    """What _status_line reads of the demo's Recorder: n estimates arriving period_s apart."""
    t = time.time_ns()
    estimates = [(t + int(k * period_s * 1e9), {"stamp_ns": t + int(k * period_s * 1e9) - 2_000_000,
                                                  "npi": 99}) for k in range(n)]
    return SimpleNamespace(lock=threading.Lock(), estimates=estimates,
                           params={"search_size": 15, "corr_size": 9, "params_id": 1})


def test_the_rate_is_given_over_half_a_second_or_more_only():
    """The first line read '0.1 s frames 3 407.5 fps': a rate over three estimates that came
    at once (a hunt of the README against the tools)."""
    t0 = time.monotonic()
    first = _status_line(_recorder(3, 0.0025), t0)
    assert " frames     3      - fps  latency   2.0 ms  NPI  99  search 15 corr 9" in first
    steady = _status_line(_recorder(60, 1 / 30), t0)
    assert " frames    60   30.0 fps  latency   2.0 ms" in steady
