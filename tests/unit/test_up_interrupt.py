"""``vistrack up`` stops at once when asked during a first run's compile of the kernels.

The compile is a long call on the launcher's main thread; the handlers that only set the stop
event ran between its bytecodes and nothing looked at the event, so Ctrl-C or SIGTERM took
effect 45 to 50 s later (measured with an empty numba cache). Within ``_interrupting`` both
raise KeyboardInterrupt, which ends the compile; outside it the handlers are those before.
"""

from __future__ import annotations

import os
import signal
import time

import pytest

from vistrack.services.launch import up


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_stop_request_ends_a_long_call_within(signum):
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    t0 = time.monotonic()
    with pytest.raises(KeyboardInterrupt), up._interrupting():
        os.kill(os.getpid(), signum)
        while time.monotonic() - t0 < 30:  # a long computation in Python, as the compiler is
            sum(range(1000))
    assert time.monotonic() - t0 < 5
    assert {s: signal.getsignal(s) for s in before} == before
