"""Compiling the tracker's numba kernels on a first run: on two cores, and saying so.

On a new machine (or after the kernels' code changes) numba compiles them once into its on-disk
cache (:func:`~vistrack.common.vision.kernel_cache_dir`); every later start loads them in
about a second. Every front door that warms them up (``track``, ``tune``, ``demo``, ``up``, the
services, the auto-tuner's worker) says on stderr when, and only when, that compile happens,
so a first run is never half a minute of silence.

Warm-ups take turns to compile (a lock file beside numba's cache): processes that start at
once, such as the services of a first ``vistrack up`` or ``vistrack demo``, compile the kernels
once and load them, rather than each compiling them at the same time. Loading needs no turn of
its own: once the kernels are in the cache, the processes waiting load them at the same time.
The launcher takes its turn first and starts the services while it compiles, so their own
start-up (imports, Zenoh, the fuzzy surface) overlaps the compile.

numba compiles in one thread. When a warm-up finds the cache cold, a second process compiles
the default tracker's SSD search (``track_pyramid`` and the kernels it calls: most of the
work) while this one compiles the rest; the final :func:`~vistrack.common.vision.warm_up` then
compiles what is left and loads the rest from the cache. Each process compiles what the other
will load from the cache before it needs it: the second process starts with the single-level
search that every level of the coarse-to-fine search calls, this one with the Gauss-Newton
refinement the matching calls next, the last kernels the single-level search compiles
(:func:`_search_tail_signatures`), the other kernels of the matching
(:func:`_match_signatures`), the coarse-to-fine search's last checks
(:func:`_compile_refinement`, with the types that search gives them), then the kernels of a
first frame and of the motion estimate. Measured on a quiet machine: without the kernels of
those lists this process was done 7 s before the second one, which then had to compile them
(~3.4 s); with Gauss-Newton after the search's tail, the second process reached it a moment
before it was cached and compiled it again, with the matching's kernels that call it (~4 s:
cold warm-ups of 36.4 and 38.5 s, against 31.5 and 35.8 with this order, interleaved). The
split only changes how long the compile takes: whatever the second process did not compile,
or compiled for other types, the final warm-up compiles here.
"""

from __future__ import annotations

import contextlib
import fcntl
import inspect
import json
import logging
import os
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ..common.params import TrackerParams

#: How long a cold compile takes on the reference machines (2 cores: 23 to 59 s measured
#: for the default coarse-to-fine tracker on an AMD EPYC core, 46 to 119 s on an Intel Xeon
#: one, 2026-12-07), for the line that announces it.
COLD_COMPILE = "half a minute to two minutes on two cores"
#: Seconds between the lines that say a cold compile is still going: a minute or two of
#: silence after the first line reads as a hang (and is ended with Ctrl-C).
COMPILE_HEARTBEAT_S = 15.0
#: The warm-up lock's file, in numba's cache folder.
LOCK_NAME = "vistrack-warm-up.lock"
#: Longest wait for the second process; beyond, this one compiles what is left itself.
HELPER_TIMEOUT_S = 600.0
_HELPER = "from vistrack.services.kernels import compile_search; compile_search({parent})"
#: prctl's option that signals a process when its parent dies
PR_SET_PDEATHSIG = 1


def cache_folder_fallback(candidates: list[Path] | None = None) -> str | None:
    """Where numba has no folder to write its kernel cache to (a system-wide install whose
    packages are read-only, a HOME and XDG_CACHE_HOME that cannot be written, and no
    NUMBA_CACHE_DIR), set NUMBA_CACHE_DIR to a folder of this user's in the temporary
    folder and return it (else None). Numba's own answer was a traceback at the first
    import of a kernel (``RuntimeError: cannot cache function '_select': no locator
    available``). Call it before numba is imported. ``candidates``: the folders numba would
    write to (default: the kernels' package's ``__pycache__``, then the user-wide
    ``$XDG_CACHE_HOME/numba``); the first it can write to is used, as numba does."""
    if os.environ.get("NUMBA_CACHE_DIR"):
        return None
    if candidates is None:
        vision = Path(__file__).resolve().parent.parent / "common" / "vision"
        user = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"),
                                                                ".cache")
        candidates = [vision / "__pycache__", Path(user) / "numba"]
    if any(_writable(folder) for folder in candidates):
        return None
    folder = os.path.join(tempfile.gettempdir(), f"vistrack-numba-{os.getuid()}")
    try:
        os.makedirs(folder, mode=0o700, exist_ok=True)
        info = os.stat(folder)
        # the cache holds code numba runs: only a folder of ours that nobody else can write
        if info.st_uid != os.getuid() or info.st_mode & 0o022:
            folder = tempfile.mkdtemp(prefix="vistrack-numba-")
    except OSError:
        folder = tempfile.mkdtemp(prefix="vistrack-numba-")
    os.environ["NUMBA_CACHE_DIR"] = folder
    return folder


def _writable(folder: Path) -> bool:
    """Whether numba could write its cache into ``folder`` (made if absent), as it tries."""
    try:
        os.makedirs(folder, exist_ok=True)
        tempfile.TemporaryFile(dir=folder).close()
    except OSError:
        return False
    return True


def warm_up_kernels(say: Callable[[str], None], *, helper: bool = True,
                    on_turn: Callable[[], None] | None = None,
                    params: TrackerParams | None = None,
                    load: Callable[[], object] | None = None) -> bool:
    """:func:`~vistrack.common.vision.warm_up`, calling ``say`` with a line when the kernels
    start compiling and another when they are done; silent when they come from the cache.

    Parameters
    ----------
    say : where the two lines go (a logger's ``info``, :func:`.usage.say_on_stderr`).
    helper : compile the SSD search in a second process when the cache is cold.
    on_turn : called once this process holds the warm-up turn, before it compiles or loads
        anything: what it starts then (the services) waits for the kernels, not with them.
    params : the tracker parameters in force, whose kernels are warmed too (``--paper``'s
        single-level search; see :func:`~vistrack.common.vision.warm_up`).
    load : where the kernels are in the cache, what loads those this process runs, instead
        of every kernel of the tracker (~0.9 s of a process's start, most of a second core's
        while a launch's processes start): pre-processing's, or nothing for the launcher,
        which runs none. On a cold cache everything is compiled, as without it.

    Returns
    -------
    Whether the kernels were compiled.
    """
    with _turn() as cached:
        # a cold search (the longest compile) is known from numba's cache index: its process
        # then starts first, ahead of the services' start-up, which competes for the cores
        early = _start_helper() if helper and not cached else None
        if on_turn is not None:
            on_turn()
        return _warm_up(say, helper, early, params, load if cached else None)


def _search_cached() -> bool:
    """Whether numba's cache holds a compiled SSD search (an index that lists it, written for
    this source): True when that cannot be told, so that the first compile decides."""
    from ..common.vision import pyramid

    try:
        return bool(cached_signatures(pyramid._track_frame))
    except Exception:  # numba's internals differ: not worth failing a start for
        return True


def cached_signatures(kernel: Any) -> set[Any]:
    """The argument types of the compiled versions of ``kernel`` (a ``numba.njit`` function
    with ``cache=True``) that numba's on-disk cache holds for its present source."""
    return {key[0] for key in kernel._cache._cache_file._load_index()}


def _start_helper() -> subprocess.Popen[bytes]:
    return subprocess.Popen([sys.executable, "-c", _HELPER.format(parent=os.getpid())],
                            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)


def die_with_parent(parent: int) -> None:
    """SIGKILL this process when ``parent`` dies (Linux; elsewhere nothing), and end it now if
    that has happened already. For the processes a vistrack process starts to work for it: the
    auto-tuner's worker (a service that crashes ends without closing it, which would finish
    its cycle for nobody) and the search's compile helper (a service stopped while it starts
    ends with ``os._exit``, no ``finally``, and left its helper compiling for half a minute,
    seen after a Ctrl-C to a first ``vistrack up``)."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes
    import signal

    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0,
                                                       0)
    except (OSError, AttributeError):
        pass  # not glibc: the parent's death is at least checked once, below
    if os.getppid() != parent:  # it died before prctl took effect
        os._exit(1)


@contextlib.contextmanager
def _turn() -> Iterator[bool]:
    """Hold the warm-up lock, a file beside numba's cache, once another process's compile has
    ended: shared when the SSD search is in the cache (:func:`_search_cached`: the processes
    that only load the kernels load them at once), exclusive when it is not (this process
    compiles; the others wait). Yields whether the search was cached. Without a writable
    cache folder, goes ahead unlocked."""
    from ..common.vision import kernel_cache_dir

    path = Path(kernel_cache_dir()) / LOCK_NAME
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    except OSError:
        yield _search_cached()
        return
    try:
        fcntl.flock(fd, fcntl.LOCK_SH)  # waits while a compile holds it exclusively
        cached = _search_cached()
        if not cached:
            # not atomic (the shared lock is let go first): a process that compiled
            # meanwhile leaves this one only the loading
            fcntl.flock(fd, fcntl.LOCK_EX)
            cached = _search_cached()
        yield cached
    finally:
        os.close(fd)  # releases the lock


def _warm_up(say: Callable[[str], None], helper: bool,
             early: subprocess.Popen[bytes] | None = None,
             params: TrackerParams | None = None,
             load: Callable[[], object] | None = None) -> bool:
    from ..common.vision import kernel_cache_dir, warm_up
    from ..common.vision.tracker import compile_watch

    t0 = time.monotonic()
    helpers = [early] if early is not None else []
    beat = _Heartbeat(say, t0)
    # kernels cached before: then this compile is of kernels other settings need (--paper,
    # --levels 1, a window whose sums need int64), not a first run (it said "first run" then)
    cache = Path(kernel_cache_dir())
    cached = cache.is_dir() and next(cache.glob("*.nbi"), None) is not None

    def on_compile() -> None:
        why = "kernels these settings need, not cached yet" if cached else "first run"
        say(f"compiling the tracker's kernels ({why}; {COLD_COMPILE}, cached in "
            f"{kernel_cache_dir()})")
        beat.start()
        if helper and not helpers and load is None:
            helpers.append(_start_helper())

    try:
        with beat, compile_watch(on_compile) as watch:
            if load is not None:  # the search is in the cache: the rest is, as a rule
                load()
            elif helper:
                _compile_first_frame()  # a cold cache shows here (the helper, if not yet)
            for proc in helpers:
                try:
                    proc.wait(HELPER_TIMEOUT_S)
                except subprocess.TimeoutExpired:
                    pass  # warm_up compiles what it did not
            if load is None:
                warm_up(params=params)
    finally:
        for proc in helpers:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    if watch.compiled:
        say(f"compiled the tracker's kernels in {time.monotonic() - t0:.0f} s; later starts "
            "load them from the cache")
    return watch.compiled


class _Heartbeat:
    """Once started, ``say`` a line every ``every`` s from a thread of its own, "still
    compiling the tracker's kernels (N s)" (N from ``t0``, a ``time.monotonic()``), until the
    ``with`` block it is the context of ends. Not started (nothing compiled): nothing said."""

    def __init__(self, say: Callable[[str], None], t0: float,
                 every: float = COMPILE_HEARTBEAT_S) -> None:
        self._say = say
        self._t0 = t0
        self._every = every
        self._done = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="compile-heartbeat",
                                            daemon=True)
            self._thread.start()

    def _run(self) -> None:
        while not self._done.wait(self._every):
            self._say(f"still compiling the tracker's kernels "
                      f"({time.monotonic() - self._t0:.0f} s)")

    def __enter__(self) -> _Heartbeat:
        return self

    def __exit__(self, *exc: object) -> None:
        self._done.set()
        if self._thread is not None:
            self._thread.join()


def _compile_first_frame() -> None:
    """The kernels of a track's first frame (pre-processing, selection, centroid and scatter),
    of the motion estimate and of the tracker's per-frame bookkeeping around the SSD search
    (prediction, losses): everything but the search itself."""
    import numpy as np

    from ..common.params import TrackerParams
    from ..common.synthetic import sequence
    from ..common.vision import Tracker, incremental_motion
    from ..common.vision import tracker as tracker_kernels

    # in the order the second process reaches them, each before it does: it compiles its
    # own copy of what is not in the cache yet. Its matching calls Gauss-Newton right after
    # its first step (~10 s in): compiled after the search's tail, it was cached a moment too
    # late, and the second process compiled it again (with the matching's kernels, ~4 s of
    # its ~30)
    _compile_refinement(gauss_newton=True)
    _compile_ahead(_search_tail_signatures())  # the end of its first step
    _compile_ahead(_match_signatures())  # its second step's (they call Gauss-Newton)
    _compile_refinement(gauss_newton=False)  # the coarse-to-fine search's last steps
    (frame,) = sequence(1, size=(64, 64), seed=1)
    Tracker(TrackerParams(subpixel=True, max_features=20, search_size=5, corr_size=5)
            ).process(frame)
    incremental_motion(np.zeros((3, 2)), np.ones((3, 2)))
    # the bookkeeping's kernel with the types Tracker._track gives it; ~3 s of compile
    # that the final warm-up would otherwise do after waiting for the second process
    pos = np.zeros((3, 2))
    tracker_kernels._advance(pos, pos + 1.0, np.zeros(3), np.zeros(3, np.int8),
                             np.arange(3, dtype=np.int64), 1.0, 5.0)


def _refinement_calls() -> list[tuple[Callable[..., object], tuple]]:
    """The sub-pixel refinement's kernels (:mod:`.ssd`: Gauss-Newton in the int32 sums of
    the default windows, the parabola of its fallback, with the kernels they call) and the
    coarse-to-fine search's last steps (:mod:`.pyramid`: consensus, wide window), each with
    arguments of the types the coarse-to-fine search
    (:func:`~vistrack.common.vision.pyramid.track_pyramid`) gives it: a window of 5 x 5 px at
    the middle of a 64 x 64 frame; one feature, not found (the last steps have nothing to
    do)."""
    import numpy as np

    from ..common.synthetic import sequence
    from ..common.vision import pyramid, ssd

    (frame,) = sequence(1, size=(64, 64), seed=1)
    wts = ssd.window_weights("uniform", 2)
    acc = ssd.refine_acc(wts)  # int32, as for the default windows
    scratch = ssd._refine_scratch(wts, acc)
    uniform, _, _ = ssd._weights_info(wts)
    flat = frame.ravel()
    pts = np.full((1, 2), 32.0)
    return [(ssd._refine_with, (frame, frame, 32, 32, 32.0, 32.0, 2, scratch, ssd.THIRD)),
            (ssd._parabola, (flat, flat, 64, 64, 32, 32, 32, 32, 2, wts, uniform, 0.0)),
            (pyramid._consensus, (pts, pts.copy(), np.full(1, ssd.LEFT, np.int8), 2.0)),
            (pyramid._widen, (frame, frame, pts, 2, 10, acc, np.zeros(1, np.bool_),
                              pts.copy(), 2.0, 1.25, 8.0, np.zeros(1, np.bool_), pts.copy())),
            (pyramid._affine_correction, (frame, pts, pts.copy(),
                                          np.full(1, ssd.LEFT, np.int8), np.zeros(1, np.bool_),
                                          pts.copy(), 2, wts, uniform, 0.2,
                                          np.empty(0, np.int64),
                                          np.empty((0, pyramid.NEIGHBOURS), np.int64)))]


#: the parameters of :func:`~vistrack.common.vision.ssd._search_level` that
#: :func:`_single_level_call` knows the types of
_SINGLE_LEVEL_PARAMS = ("prev", "curr", "anchors", "centers", "active", "n", "s", "wts",
                        "exhaustive", "ratio", "allowance", "out_q", "out_ssd", "out_status",
                        "budget")


def _single_level_call() -> tuple[Callable[..., object], tuple] | None:
    """The single-level search (:func:`~vistrack.common.vision.ssd._search_level`) with
    arguments of the types each level of the coarse-to-fine search gives it (no feature
    active: nothing is searched); None when its parameters are not the ones known here (the
    coarse-to-fine search then compiles it in its turn)."""
    import numpy as np

    from ..common.synthetic import sequence
    from ..common.vision import ssd

    if tuple(inspect.signature(ssd._search_level.py_func).parameters) != _SINGLE_LEVEL_PARAMS:
        return None
    (frame,) = sequence(1, size=(64, 64), seed=1)
    at = np.full((1, 2), 32, np.int64)
    return ssd._search_level, (
        frame, frame, at, at.copy(), np.zeros(1, np.bool_), 2, 2, ssd.window_weights("uniform", 2),
        False, 1.25, 0.0, np.zeros((1, 2), np.int64), np.zeros(1), np.zeros(1, np.int8),
        np.zeros(1, np.int64))


#: the parameters of the kernels of :func:`_search_tail_signatures` and
#: :func:`_match_signatures`, as their types there were written for
_AHEAD_PARAMS = {
    "_ambiguous_pruned": ("pf", "cf", "w", "ax", "ay", "lo_x", "lo_y", "nrow", "ncol", "width",
                          "total", "n", "wts", "uniform", "bnd", "mscale", "lanes", "mask",
                          "best_k", "lim"),
    "_descend": ("prev", "curr", "ax", "ay", "cx", "cy", "n", "wts", "uniform", "steps",
                 "seen"),
    "_from_integer": ("prev", "curr", "ax", "ay", "qx", "qy", "n", "wts", "uniform", "ssd",
                      "scratch"),
    "_follow": ("pdata", "cdata", "geo", "pts", "preds", "held", "n", "wts", "fb_bound",
                "scratch", "active", "out_pos", "out_ssd", "out_status"),
}


def _search_tail_signatures() -> list[tuple[Any, tuple]]:
    """The last kernels the single-level search (:func:`~vistrack.common.vision.ssd.
    _search_level`, the second process's first step) compiles, with the types it gives them:
    the uniqueness test of the pruned search over its int32 bounds (the search's one type of
    bound; ~0.7 s of compile that the second process then loads)."""
    from numba import types as t

    from ..common.vision import ssd

    u8, i64, i32_2 = t.Array(t.uint8, 1, "C"), t.int64, t.Array(t.int32, 2, "C")
    return [(ssd._ambiguous_pruned, (u8, u8, *[i64] * 10, i32_2, t.boolean,
                                     t.Array(t.int32, 1, "C"), i64, u8, u8, i64, t.float64))]


def _match_signatures() -> list[tuple[Any, tuple]]:
    """The kernels the coarse-to-fine search's matching (:func:`~vistrack.common.vision.
    pyramid._match`, the second process's second step) calls besides the single-level search,
    with the types it gives them: the descent at the finest level, the sub-pixel estimate
    from an integer minimum and the following of the held features (step 0; ~4 s of compile
    that the second process then loads)."""
    from numba import types as t

    from ..common.vision import pyramid

    u8_2, i64 = t.Array(t.uint8, 2, "C"), t.int64
    wts = t.Array(t.int32, 2, "C")
    u8_1, f64_1, f64_2 = t.Array(t.uint8, 1, "C"), t.Array(t.float64, 1, "C"), t.Array(
        t.float64, 2, "C")
    # .ssd._refine_scratch's (wpad, tp, cp, g, q, cen, fast): the weights in int16, the
    # patches in uint8, g in int16 and q in int32 (the sums of the default windows)
    scratch = t.Tuple((t.Array(t.int16, 1, "C"), u8_1, u8_1, t.Array(t.int16, 2, "C"), wts,
                       f64_1, t.boolean))
    b_1 = t.Array(t.boolean, 1, "C")
    return [(pyramid._descend, (u8_2, u8_2, *[i64] * 5, wts, t.boolean, t.literal(3),
                                t.Array(t.int64, 2, "C"))),
            (pyramid._from_integer, (u8_2, u8_2, *[i64] * 5, wts, t.boolean, t.float64,
                                     scratch)),
            (pyramid._follow, (u8_1, u8_1, t.Array(t.int64, 2, "C"), f64_2, f64_2, b_1, i64,
                               wts, t.float64, scratch, b_1, f64_2, f64_1,
                               t.Array(t.int8, 1, "C")))]


def _compile_ahead(signatures: list[tuple[Any, tuple]]) -> None:
    """Compile (not run) each kernel for its types, into numba's cache, for the second process
    to load; a kernel whose parameters are not the ones its types were written for is left to
    the second process (the unit test test_the_compile_split_compiles_only_what_the_tracker_
    calls says when the types no longer match)."""
    for kernel, sig in signatures:
        try:
            params = tuple(inspect.signature(kernel.py_func).parameters)
            if params == _AHEAD_PARAMS.get(kernel.__name__):
                kernel.compile(sig)
        except Exception:  # noqa: BLE001 - a changed kernel: the second process compiles it
            pass


def _compile_refinement(gauss_newton: bool | None = None) -> None:
    """Compile the sub-pixel refinement's kernels (:func:`_refinement_calls`): all of them,
    or (``gauss_newton`` True) the Gauss-Newton refinement only, (False) all but it."""
    try:
        calls = _refinement_calls()
    except Exception:  # noqa: BLE001 - a kernel renamed or changed: the final warm-up
        return  # compiles what the search calls
    if gauss_newton is not None:
        calls = calls[:1] if gauss_newton else calls[1:]
    for kernel, args in calls:
        try:
            kernel(*args)
        except Exception:  # noqa: BLE001 - its parameters changed: as above (the unit test
            pass  # test_the_compile_split_compiles_only_what_the_tracker_calls says so)


def compile_search(parent: int | None = None) -> None:
    """Compile (or load) the SSD search's kernels: the second process of a cold warm-up,
    started by ``parent`` (it dies with it). The
    default tracker's coarse-to-fine search (:func:`~vistrack.common.vision.pyramid.
    track_pyramid`, with the single-level kernels it calls), with the types the tracker gives
    it. It starts with the single-level search that each level of the coarse-to-fine search
    starts with (:func:`_single_level_call`; the most of the work), while the first process
    compiles the sub-pixel refinement (:func:`_compile_refinement`) that the coarse-to-fine
    search calls before it and then loads from the cache. The paper's ``track_ssd``
    (``--paper``) compiles when first used."""
    if parent is not None:
        die_with_parent(parent)
    import numpy as np

    from ..common.params import TrackerParams
    from ..common.synthetic import sequence
    from ..common.vision import window_weights
    from ..common.vision.pyramid import build_pyramid, track_pyramid

    single = _single_level_call()
    if single is not None:
        kernel, args = single
        kernel(*args)
    p = TrackerParams()
    first, second = sequence(2, size=(64, 64), seed=1)
    points = np.array([[32.0, 32.0], [24.0, 40.0]])
    track_pyramid(build_pyramid(first, p.levels), build_pyramid(second, p.levels), points,
                  points + 1.0, corr_half=2, search_half=2, weights=window_weights(p.weights, 2),
                  subpixel=p.subpixel, search=p.search, uniqueness=p.uniqueness,
                  allowance=1.0, reject_border=p.reject_border, guided_retry=p.guided_retry,
                  max_fb_error=p.max_fb_error, consensus=p.consensus, wide_half=p.refine_half)


def kernels_failed(params_id: int, why: str | None = None) -> str:
    """What motion-estimation says (status ``last_error``, its log) of the parameter set
    ``params_id`` whose kernels could not be made ready; without ``why``, the beginning of
    it, which ``vistrack params set`` looks for in the status."""
    said = f"params_id {params_id}: its kernels could not be made ready"
    return said if why is None else f"{said} ({why})"


class KernelsAhead:
    """Kernels of new tracker parameters, made ready beside a service's loop.

    Parameters whose windows sum in int64 (:func:`~vistrack.common.vision.tracker.
    _kernel_set`: a 64 px window, say) run kernels of their own that the start-up warm-up did
    not load: on a cold cache they compile for up to half a minute, far past the
    launcher's hang timeout (5 s) if the loop waited. :meth:`ready` answers at once; when the
    kernels are not loaded, a thread compiles them in a second process (another core, and no
    contention for this process's interpreter lock with the loop), which leaves them in
    numba's cache, then loads them here (~0.5 s, or compiles them here if the cache could not
    be written). The loop keeps its parameters in force until then.
    """

    def __init__(self, log: logging.Logger) -> None:
        self._log = log
        self._lock = threading.Lock()
        self._wanted: TrackerParams | None = None
        self._thread: threading.Thread | None = None
        self._failed: dict[TrackerParams, str] = {}

    def ready(self, params: TrackerParams) -> bool:
        """Whether ``params``'s kernels are loaded; if not, have them made ready (the latest
        parameters asked for are the ones made ready next), unless that failed
        (:meth:`failure`)."""
        from ..common.vision.tracker import kernels_warm

        if kernels_warm(params):
            return True
        with self._lock:
            if params in self._failed:
                return False
            self._wanted = params
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, daemon=True,
                                                name="kernels-ahead")
                self._thread.start()
        return False

    def failure(self, params: TrackerParams) -> str | None:
        """Why ``params``'s kernels could not be made ready, or None."""
        with self._lock:
            return self._failed.get(params)

    def _run(self) -> None:
        from ..common.vision import warm_up
        from ..common.vision.tracker import kernels_warm

        while True:
            with self._lock:
                params, self._wanted = self._wanted, None
                if params is None or kernels_warm(params):
                    if params is None:
                        self._thread = None
                        return
                    continue
            t0 = time.monotonic()
            try:
                subprocess.run([sys.executable, "-c", _AHEAD, str(os.getpid())], input=json.dumps(
                    params.as_dict()).encode(), stdout=subprocess.DEVNULL,
                    stderr=subprocess.DEVNULL, timeout=HELPER_TIMEOUT_S, check=False)
                warm_up(params=params)  # loads what the other process compiled
            except Exception as e:  # noqa: BLE001 - the loop goes on with what is in force
                with self._lock:
                    self._failed[params] = f"{type(e).__name__}: {e}"
                continue
            self._log.info("kernels of the new parameters ready in %.1f s",
                           time.monotonic() - t0)


#: The helper that compiles a new parameter set's kernels beside the loop: it dies with the
#: service (one that exited mid-compile left it compiling for nobody for up to ~30 s).
_AHEAD = ("import json, sys; from vistrack.services.kernels import die_with_parent; "
          "die_with_parent(int(sys.argv[1])); "
          "from vistrack.common.params import TrackerParams; "
          "from vistrack.common.vision import warm_up; "
          "warm_up(params=TrackerParams.from_mapping(json.load(sys.stdin)))")


@contextlib.contextmanager
def late_compiles_logged(log: logging.Logger) -> Iterator[None]:
    """Within the block (a service's loop), log a WARNING for each of the tracker's kernels
    numba compiles in this process: after the warm-up, a compile is a frame that waited for
    the compiler, up to seconds on a cold cache, and a lockstep camera that sent it again.
    Such a kernel belongs in :func:`~vistrack.common.vision.warm_up`. (Numba's own helpers,
    compiled on the way, at DEBUG.)"""
    from numba.core import event as numba_event

    from ..common.vision.tracker import warming_up

    started: dict[int, list[float]] = {}  # a thread's compiles under way (a kernel's
    # callees compile inside it)

    class LateCompiles(numba_event.Listener):
        def on_start(self, event: numba_event.Event) -> None:
            started.setdefault(threading.get_ident(), []).append(time.perf_counter())

        def on_end(self, event: numba_event.Event) -> None:
            now = time.perf_counter()
            under_way = started.get(threading.get_ident())
            took = now - (under_way.pop() if under_way else now)
            if warming_up():  # a warm-up for new parameters: expected, and said by it
                return
            data = event.data or {}
            func = getattr(data.get("dispatcher"), "py_func", None)
            name = f"{getattr(func, '__module__', '?')}.{getattr(func, '__qualname__', '?')}"
            level = logging.WARNING if name.startswith("vistrack.") else logging.DEBUG
            log.log(level, "numba compiled %s for %s in %.2f s after the warm-up: the work "
                    "that called it waited", name, data.get("args"), took)

    listener = LateCompiles()
    numba_event.register("numba:compile", listener)
    try:
        yield
    finally:
        numba_event.unregister("numba:compile", listener)


