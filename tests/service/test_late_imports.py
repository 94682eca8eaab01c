"""Nothing is imported once a service is ready: an import in the loop, or in the thread that
answers a status query, holds the GIL for milliseconds in the hot path (the first status
query imported numpy.ma in the fuzzy controller: 15 ms, 2 s into a run).

Run in a fresh interpreter, where nothing else has imported the modules a service may load
late; the loop runs on a MemoryNode in a thread, fed real messages.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

SCRIPT = textwrap.dedent("""
    import sys, time
    sys.path.insert(0, sys.argv[1])
    from loops import Running
    from vistrack.common.messages import Estimate
    with Running("fuzzy-controller") as r:
        while not r.node.alive:
            time.sleep(0.01)
        before = set(sys.modules)
        for seq in range(3):
            r.feed(r.node.keys.estimate, Estimate(
                seq=seq, stamp_ns=time.time_ns(), npi=50, xc=100.0 + seq, yc=100.0, xe=5.0,
                ye=5.0, dx=1.0, dy=0.0, scale=1.0, t_ms=1.0, first=seq == 0, features=[],
                params_id=0, valid=True).encode())
        r.node.status.as_dict()  # what a status query computes
        print(sorted(set(sys.modules) - before))
""")


def test_the_fuzzy_controller_imports_nothing_once_ready():
    out = subprocess.run([sys.executable, "-c", SCRIPT, str(Path(__file__).parent)],
                         capture_output=True, text=True, timeout=120, check=True).stdout
    assert out.strip().splitlines()[-1] == "[]", out
