"""Numeric libraries on one thread in every vistrack process: the parallelism is the processes.

numpy and scipy each bundle an OpenBLAS whose worker threads busy-wait between calls: the
auto-tuner's scene watch makes small matrix products every frame, and its process used 104 %
of one core at 30 fps (5 % with one thread). :func:`configure` sets the variables the numeric
libraries read when they load (OpenBLAS, OpenMP, MKL, BLIS, Accelerate, numexpr, numba), so it
must run before numpy is first imported: ``vistrack``'s entry point calls it first, for the
processes ``vistrack up`` starts and those run by hand alike. :func:`limit_loaded` then
enforces the limit on whatever is already loaded (threadpoolctl) and describes the pools.

``VISTRACK_NUMERIC_THREADS`` (1 to 64, default 1) changes the number, for benchmarks and for
experiments on larger machines. OpenCV is set to one thread separately (``cv2.setNumThreads``).
"""

from __future__ import annotations

import os
from typing import Any

ENV = "VISTRACK_NUMERIC_THREADS"
RANGE = (1, 64)
#: Read by each numeric library when it loads.
POOL_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS",
             "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS", "NUMBA_NUM_THREADS")


def configured() -> int:
    """The number of threads ``VISTRACK_NUMERIC_THREADS`` asks for (default 1).

    Raises
    ------
    ValueError
        If it is not an integer in :data:`RANGE`, naming the variable, value and range.
    """
    text = os.environ.get(ENV, "1")
    try:
        n = int(text)
    except ValueError:
        n = 0
    if not RANGE[0] <= n <= RANGE[1]:
        raise ValueError(f"{ENV}={text!r} is out of range: allowed {RANGE[0]}..{RANGE[1]}")
    return n


def configure() -> int:
    """Set every pool variable to :func:`configured` threads (overriding what the environment
    had: a shell's OMP_NUM_THREADS=8 must not make the services spin); return the number."""
    n = configured()
    numba_max = os.cpu_count() or 1  # numba refuses more threads than cores
    for var in POOL_VARS:
        os.environ[var] = str(min(n, numba_max) if var == "NUMBA_NUM_THREADS" else n)
    return n


def limit_loaded(n: int | None = None) -> list[dict[str, Any]]:
    """Limit the thread pools of the numeric libraries loaded so far to ``n`` (default
    :func:`configured`) and return threadpoolctl's description of each pool: libraries
    loaded before :func:`configure` ran (numpy imported first by an embedding program) are
    limited too."""
    from threadpoolctl import threadpool_info, threadpool_limits

    threadpool_limits(limits=configured() if n is None else n)
    return threadpool_info()


def describe(pools: list[dict[str, Any]]) -> str:
    """``openblas 1 (libscipy_openblas64_), ...``: one entry per pool, for a log line."""
    if not pools:
        return "none loaded"
    return ", ".join(f"{p.get('internal_api', '?')} {p.get('num_threads', '?')} "
                     f"({p.get('prefix', '?')})" for p in pools)
