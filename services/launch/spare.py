"""A warmed-up spare process that the launcher turns into a service it restarts.

``python -m vistrack.services.launch.spare`` sets the numeric libraries to one thread,
imports what every service needs (numpy, numba, OpenCV, Zenoh, the runtime), loads the
tracker's compiled kernels (numba's first load costs ~1.5 s: it imports much of numba and
scipy's linear algebra), and waits. The launcher (:class:`~.supervisor.Launcher`) writes one
line to its standard input, the service's command line as a JSON list (what follows
``python -m vistrack.services.cli``), and the process becomes that service; end of input
ends it. A restart then costs the service's own set-up, a fraction of a second, instead of
~2.5 s of a new interpreter's imports and numba's first load: a crash to a new process ready
in about a second. No Zenoh session is opened before the line arrives.
"""

from __future__ import annotations

import json
import sys


def main() -> int:
    from .. import threads

    threads.configure()
    import gc

    from ...common.vision import warm_up
    from .. import runtime  # noqa: F401 - loaded now, not when a service is needed

    warm_up()
    gc.collect()
    line = sys.stdin.readline()
    if not line:
        return 0  # the launcher stopped without needing us
    argv = json.loads(line)
    sys.stdin.close()
    from ..cli import main as cli_main

    sys.argv = ["vistrack", *argv]
    return cli_main(argv)


if __name__ == "__main__":
    sys.exit(main())
