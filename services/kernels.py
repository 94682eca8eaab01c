"""Compiling the tracker's numba kernels on a first run, and saying so.

On a new machine (or after the kernels' code changes) numba compiles them once, about half a
minute on two cores, into its on-disk cache (:func:`~vistrack.common.vision.kernel_cache_dir`);
every later start loads them in about a second. Every front door that warms them up (``track``,
``tune``, ``demo``, ``up``, the services, the auto-tuner's worker) says on stderr when, and only
when, that compile happens, so a first run is never half a minute of silence.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import TextIO

#: About how long a cold compile takes on the reference machine (2 cores), s.
COLD_COMPILE_S = 30


def warm_up_kernels(say: Callable[[str], None]) -> bool:
    """:func:`~vistrack.common.vision.warm_up`, calling ``say`` with a line when the kernels
    start compiling and another when they are done; silent when they come from the cache.

    Returns
    -------
    Whether the kernels were compiled.
    """
    from ..common.vision import kernel_cache_dir, warm_up

    t0 = time.monotonic()
    compiled = warm_up(on_compile=lambda: say(
        f"compiling the tracker's kernels (first run; about {COLD_COMPILE_S} s, cached in "
        f"{kernel_cache_dir()})"))
    if compiled:
        say(f"compiled the tracker's kernels in {time.monotonic() - t0:.0f} s; later starts "
            "load them from the cache")
    return compiled


def say_on_stderr(command: str, stream: TextIO | None = None) -> Callable[[str], None]:
    """A ``say`` for :func:`warm_up_kernels` that prints ``vistrack COMMAND: ...`` on
    ``stream`` (default: stderr at the time of the call)."""
    def say(text: str) -> None:
        print(f"vistrack {command}: {text}", file=stream or sys.stderr, flush=True)
    return say
