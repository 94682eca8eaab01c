"""Saying when the tracker's kernels compile, and only then (services/kernels.py, warm_up).

A real cold compile takes half a minute of CPU, so it is exercised by the first-run benchmark
(tests/bench/test_bench_first_run.py); here the compile event is raised by compiling small
functions of the test's own, and the cached case runs on the cache the session filled.
"""

from __future__ import annotations

import fcntl
import inspect
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numba as nb
import pytest
from numba.core import event as numba_event

from vistrack.common.vision import kernel_cache_dir, pyramid, ssd, tracker
from vistrack.services import kernels
from vistrack.services.kernels import LOCK_NAME, warm_up_kernels
from vistrack.services.usage import say_on_stderr

# the cache's index of the kernels is read here: whole, with the int64 set's (conftest)
pytestmark = pytest.mark.usefixtures("int64_kernels")


def test_a_compile_is_said_once_when_it_starts():
    said = []
    listener = tracker._CompileListener(lambda: said.append(len(said)))
    first, second = nb.njit(lambda x: x + 1), nb.njit(lambda x: x * 2.5)
    with numba_event.install_listener("numba:compile", listener):
        assert first(1) == 2 and second(2.0) == 5.0  # two compiles: one line
    assert listener.compiled and said == [0]


def test_nothing_is_said_when_everything_is_cached():
    # the session's conftest has compiled or loaded every kernel: a later warm-up loads
    said: list[str] = []
    assert warm_up_kernels(said.append) is False
    assert said == []


def test_a_long_compile_says_it_is_still_going_until_it_ends():
    """A cold compile takes a minute or two on a slow machine: after its first line, a line
    every COMPILE_HEARTBEAT_S (here 0.05 s) with the seconds since it began, and none once
    it has ended; a heartbeat never started (nothing compiled) says nothing."""
    said: list[str] = []
    with kernels._Heartbeat(said.append, time.monotonic() - 12.0, every=0.05) as beat:
        beat.start()
        beat.start()  # a second compile event: still one thread
        time.sleep(0.3)
    lines = len(said)
    time.sleep(0.2)
    assert len(said) == lines and 2 <= lines <= 6, said
    assert all(re.fullmatch(r"still compiling the tracker's kernels \(1[23] s\)", line)
               for line in said), said
    with kernels._Heartbeat(said.append, time.monotonic(), every=0.01):
        time.sleep(0.1)
    assert len(said) == lines


def test_say_on_stderr_names_the_command(capsys):
    say_on_stderr("track")("compiling the tracker's kernels")
    assert capsys.readouterr().err == "vistrack track: compiling the tracker's kernels\n"


def test_track_is_silent_on_stderr_when_the_kernels_are_cached():
    run = subprocess.run([sys.executable, "-m", "vistrack.services.cli", "track",
                          "--format", "csv"], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0 and run.stderr == ""
    assert run.stdout.startswith("seq,npi,")


def test_warm_ups_take_turns():
    # the services of a first `vistrack up` start while the launcher compiles: each waits
    # for the lock beside numba's cache, then loads, instead of compiling at the same time
    fd = os.open(Path(kernel_cache_dir()) / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)  # another process's compile, here
        waiting = subprocess.Popen(
            [sys.executable, "-c", "from vistrack.services.kernels import warm_up_kernels; "
             "print(warm_up_kernels(print, on_turn=lambda: print('turn')), flush=True)"],
            stdout=subprocess.PIPE, text=True)
        try:
            waiting.wait(timeout=3.0)
            raise AssertionError("warm_up_kernels did not wait for the lock")
        except subprocess.TimeoutExpired:
            pass
    finally:
        os.close(fd)  # the compile is done
    out, _ = waiting.communicate(timeout=60)
    assert out.splitlines() == ["turn", "False"]  # its turn, then everything from the cache


def test_the_compile_split_compiles_only_what_the_tracker_calls(start_up_signatures):
    # a cold warm-up's two processes each compile kernels the other then loads from the cache
    # (the second one's single-level search, this one's refinement): with types of their own,
    # each would compile a version nobody uses, and the tracker's search its own besides.
    # The tracker runs one version of each of those kernels (a warm-up in one process, the
    # tracker's alone, compiled exactly one of each: 2026-12-07, and the same versions of
    # all 97 kernels as the split): the session's warm-up, split as a first run's
    # (conftest), left one of each, so the split compiled none of its own.
    # The kernels compiled ahead by their types (not run) must also have the parameters
    # those types were written for, else the second process compiles them after all.
    ahead = kernels._search_tail_signatures() + kernels._match_signatures()
    for kernel, _ in ahead:
        assert tuple(inspect.signature(kernel.py_func).parameters) == \
            kernels._AHEAD_PARAMS[kernel.__name__], kernel.__name__  # else see there
    split = (ssd._search_level, ssd._refine_with, ssd._parabola, pyramid._consensus,
             pyramid._widen, *{kernel for kernel, _ in ahead})
    if start_up_signatures is not None:  # the session compiled them (CI, a first run)
        assert {k.__name__: len(start_up_signatures[k]) for k in split} == \
            {k.__name__: 1 for k in split}
    # and the split's calls, made again, compile nothing the cache does not hold
    before = [kernels.cached_signatures(k) for k in split]
    assert all(before)
    assert kernels._single_level_call() is not None  # else its parameters changed: see there
    for kernel, args in kernels._refinement_calls():  # each runs: else its parameters changed
        kernel(*args)  # (and _compile_refinement would skip it in silence)
    kernels._compile_ahead(ahead)
    kernels._compile_refinement()
    kernels.compile_search()
    assert [kernels.cached_signatures(k) for k in split] == before


def test_a_decoded_frame_runs_the_filter_the_warm_up_compiled():
    """A service's frames are read-only views of the message payload; the warm-up's are
    writable. The pre-filter's kernel has one compiled version for both, so the warm-up
    compiles what preprocessing runs (a second version was compiled at a first run's first
    frame: ~2 s without estimates, the demo's centring error 34 px instead of 2)."""
    import importlib

    import numpy as np

    from vistrack.common.params import TrackerParams

    pre = importlib.import_module("vistrack.common.vision.preprocess")

    tracker.warm_up()
    frame = np.random.default_rng(0).integers(0, 256, (48, 64), dtype=np.uint8)
    frozen = frame.copy()
    frozen.flags.writeable = False
    pre.preprocess(frame, TrackerParams())
    pre.preprocess(frozen, TrackerParams())
    assert len(pre._blur_fixed.signatures) == 1, pre._blur_fixed.signatures


PAPER_KERNELS = """
import sys
from vistrack.common.params import TrackerParams
from vistrack.common.vision import ssd, tracker, warm_up
warm_up(params=TrackerParams.paper() if sys.argv[1] == "paper" else None)
print(len(tracker._predict.signatures), len(ssd._track.signatures))
"""


def test_the_paper_trackers_kernels_are_warmed_for_whom_uses_it():
    """``--paper``'s single-level search has kernels of its own: warmed up with its
    parameters they are ready before the first frame (on a cold cache they compiled inside
    it: ~4 s in the first design run's t1); without, they are not loaded at all (a fresh
    process, whose kernels come from the cache the session filled)."""
    tracker.warm_up(params=tracker.TrackerParams.paper())  # fill the cache
    env = {**os.environ}

    def loaded(which: str) -> list[int]:
        out = subprocess.run([sys.executable, "-c", PAPER_KERNELS, which], env=env,
                             capture_output=True, text=True, check=True, timeout=120)
        return [int(v) for v in out.stdout.split()]

    assert all(loaded("paper"))
    assert not any(loaded("default"))


def test_a_kernel_compiled_after_the_warm_up_is_a_warning(caplog):
    """A kernel of ours compiled once the service runs (types the warm-up did not cover) is
    logged as a WARNING with its name; the warm-up's own compiles are not, nor numba's own
    helpers (DEBUG). The late kernel is one of the test's, in a module named as ours (not
    cached: a kernel of ours would come from numba's cache on the next run, no compile)."""
    import logging

    def late(x):
        return x + 1

    def other(x):
        return x * 2

    late.__module__ = "vistrack.common.vision.late"

    log = logging.getLogger("vistrack.test-late")
    with kernels.late_compiles_logged(log), caplog.at_level(logging.DEBUG, logger=log.name):
        tracker.warm_up(params=tracker.TrackerParams.paper())  # warm: nothing to say
        assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
        assert nb.njit(late)(1) == 2 and nb.njit(other)(2) == 4
    assert nb.njit(late)(2.0) == 3.0  # after the block: not watched
    said = [(r.levelno, r.getMessage()) for r in caplog.records if r.name == log.name]
    warned = [m for level, m in said if level == logging.WARNING]
    assert len(warned) == 1 and "vistrack.common.vision.late" in warned[0], said
    assert any("other" in m for level, m in said if level == logging.DEBUG), said


#: a fresh process's kernels of ours loaded by the start-up warm-up, then what ``RUN`` adds
LATE_KERNELS = """
import importlib, pkgutil
import numba
import numpy as np
import vistrack.common.vision as vision
from vistrack.common import synthetic
from vistrack.common.params import TrackerParams
from vistrack.common.vision import Tracker, warm_up
from vistrack.common.vision.preprocess import DeferredPreprocessed
from vistrack.services.auto_tuner.sensitivity import tune

def loaded():
    out = set()
    for info in pkgutil.iter_modules(vision.__path__):
        mod = importlib.import_module(f"vistrack.common.vision.{info.name}")
        for name, obj in vars(mod).items():
            if isinstance(obj, numba.core.registry.CPUDispatcher):
                out |= {f"{mod.__name__}.{name}{sig}" for sig in obj.signatures}
    return out

warm_up(WARM)
before = loaded()
RUN
print("\\n".join(sorted(loaded() - before)))
"""

TUNE = """
result = tune(synthetic.builtin_sequence(10), 0)
print(result.optimum.params["search_size"] > 0)
"""

TRACK = """
frames = synthetic.builtin_sequence(60)
p = TrackerParams()
tr = Tracker(p)
for f in frames:
    tr.process(f)
for f in (np.zeros_like(frames[0]), np.full_like(frames[0], 255)):
    tr.process(f)  # black, saturated
for size in ((8, 8), (320, 240)):
    tr = Tracker(p)
    for f in frames[:5]:
        tr.process(np.ascontiguousarray(f[:size[1], :size[0]]))
tr = Tracker(p)  # an auto-exposure that hunts: every other frame brighter
for i, f in enumerate(frames[:6]):
    tr.process(np.clip(f * 1.2 + 8.0, 0, 255).astype(np.uint8) if i % 2 else f)
print(tr.exposure_steps > 0)
tr = Tracker(p)  # as motion-estimation takes a pre-processed frame: copied, deferred
for f in frames[:10]:
    tr.update(DeferredPreprocessed(np.array(np.frombuffer(f.tobytes(), np.uint8)
                                            .reshape(f.shape)), p))
print(tr.lost_total >= 0)
tr = Tracker(p)  # black bars at the sides, the picture panning between them (.features)
for i in range(10):
    f = np.roll(frames[0], 3 * i, axis=1)
    f[:, :40] = 0
    f[:, -40:] = 0
    tr.process(f)
print(tr._void is not None)
import cv2
tr = Tracker(p)  # a burnt-in timestamp over the picture panning (Tracker._off_overlay)
for i in range(8):
    f = np.roll(frames[0], (i, 3 * i), axis=(0, 1))
    cv2.putText(f, "2026-12-08 01:45:00", (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, 0, 3)
    cv2.putText(f, "2026-12-08 01:45:00", (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, 255, 1)
    tr.process(f)
print(tr._overlay is not None)
"""


def late_kernels(run: str, warm: str = "") -> list[str]:
    """What ``run`` (a script's body) prints, then the kernels of ours it loaded with types
    the start-up warm-up (``warm_up(warm)``) had not, in a fresh process: each would be
    compiled on a new machine while a frame or a tuning cycle waits (seconds to tens of
    seconds). Read from the kernels' loaded signatures, so it holds whether numba's cache is
    cold or warm."""
    script = LATE_KERNELS.replace("RUN", run).replace("WARM", warm)
    return subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          check=True, timeout=300).stdout.splitlines()


def test_a_tuning_cycle_runs_on_the_kernels_the_start_up_warm_up_loaded():
    """A tuning cycle (the design, its reference windows, the sweep): step 7's centroid sums
    once made the 30 px reference window need int64 kernels, and a cold first cycle took 28 s
    instead of 3."""
    out = late_kernels(TUNE)
    assert out[0] == "True"  # the cycle ran to an optimum
    assert [line for line in out[1:] if line] == []


def test_a_track_runs_on_the_kernels_the_start_up_warm_up_loaded():
    """Tracking, re-detection, a black and a saturated frame, frames of 8 x 8 and 320 x 240,
    exposure steps (whose test of the blocks, :func:`.exposure._explains`, runs only where
    the exposure seems to change), the copied, deferred frames of motion-estimation, and
    frames with black bars (whose void regions, .features.near_void, only such frames show)
    and with a burnt-in timestamp (the overlay's kernels, Tracker._off_overlay)."""
    out = late_kernels(TRACK)
    assert out[:4] == ["True", "True", "True", "True"]
    assert [line for line in out[4:] if line] == []


WIDE = """
p = TrackerParams().replace(**PARAMS)
tr = Tracker(p)
for f in synthetic.builtin_sequence(20):
    e = tr.process(f)
print(e.npi > 0)
"""


@pytest.mark.parametrize("params", ["dict(corr_size=64)", "dict(weights='gaussian')",
                                    "dict(refine_size=64)"])
def test_parameters_whose_sums_need_int64_are_warmed_with_them(params):
    """Windows whose sub-pixel sums outgrow int32 (a 64 px window, Gaussian weights, a 64 px
    wide window) run the kernels in int64, a set of their own: the warm-up for them loaded
    the int32 set instead (it warmed every set at a 5 px window), and they compiled in the
    first frames, ~27 s on a cold cache (motion-estimation, judged hung, was killed)."""
    out = late_kernels(WIDE.replace("PARAMS", params),
                       f"params=TrackerParams().replace(**{params})")
    assert out[0] == "True"
    assert [line for line in out[1:] if line] == []


def test_the_auto_tuners_windows_sum_in_the_default_trackers_type():
    """Every correlation window a tuning cycle runs (its design's levels, its sweep's range,
    the reference windows), each with the wide window, has the sub-pixel sums' type of the
    default tracker's, so that the cycle runs the kernels the start-up warm-up compiled.
    Step 7's centroid sums, once summed in that type, made the reference window (30 px) need
    int64: on a cold cache the first tuning cycle after the warm-up took 28 s instead of 3,
    compiling the int64 kernels."""
    from vistrack.common.params import TrackerParams
    from vistrack.common.vision import window_weights
    from vistrack.services.auto_tuner.design import PAPER_LEVELS
    from vistrack.services.auto_tuner.experiment import REFERENCE_WINDOWS
    from vistrack.services.auto_tuner.sensitivity import CORR_RANGE

    base = TrackerParams()

    def sum_type(corr_size: int) -> str:
        p = base.replace(corr_size=corr_size)
        wts = window_weights(p.weights, p.corr_half)
        return str(pyramid._sum_type(wts.tobytes(), p.corr_half, p.refine_half).dtype)

    sizes = ({*range(CORR_RANGE[0], CORR_RANGE[1] + 1), REFERENCE_WINDOWS[1]}
             | {int(v) for v in PAPER_LEVELS["corr_size"]})
    assert REFERENCE_WINDOWS[1] == 30 and sum_type(base.corr_size) == "int32"
    assert {c: sum_type(c) for c in sorted(sizes)} == dict.fromkeys(sorted(sizes), "int32")


def test_the_compile_helper_dies_with_its_parent(tmp_path):
    """A service stopped while it starts ends at once (``os._exit``): its helper, compiling
    the search into an empty cache (half a minute), used to go on for nobody."""

    parent = subprocess.run(
        [sys.executable, "-c", "import os; from vistrack.services import kernels; "
         "print(kernels._start_helper().pid, flush=True); os._exit(0)"],
        env={**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}, capture_output=True, text=True,
        check=True, timeout=60)
    helper = int(parent.stdout)
    _ends_within(helper, 15.0, "the helper outlived its parent")


def test_the_helper_that_makes_new_parameters_ready_dies_with_its_service(tmp_path):
    """motion-estimation compiles a new parameter set's kernels in a helper beside its loop;
    a service that exited meanwhile left it compiling for nobody for up to ~30 s. Here the
    helper compiles into an empty cache, and its service exits 2 s later."""

    parent = subprocess.run(
        [sys.executable, "-c", "import os, subprocess, sys; from vistrack.services import "
         "kernels; p = subprocess.Popen([sys.executable, '-c', kernels._AHEAD, "
         "str(os.getpid())], stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, "
         "stderr=subprocess.DEVNULL); p.stdin.write(b'{\"search_size\": 21}'); "
         "p.stdin.close(); print(p.pid, flush=True); import time; time.sleep(2); os._exit(0)"],
        env={**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}, capture_output=True, text=True,
        check=True, timeout=60)
    helper = int(parent.stdout)
    _ends_within(helper, 15.0, "the helper outlived its service")


def _ends_within(pid: int, seconds: float, what: str) -> None:
    """Assert that ``pid`` ends within ``seconds`` (killed if it does not)."""
    import time

    try:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline and _running(pid):
            time.sleep(0.1)
        assert not _running(pid), what
    finally:
        if _running(pid):
            os.kill(pid, 9)


def _running(pid: int) -> bool:
    """Whether ``pid`` runs (an orphan is reaped by init; a zombie counts as gone)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def test_no_writable_cache_folder_falls_back_to_one_of_the_users(tmp_path, monkeypatch):
    """Numba's answer where it can write to no cache folder (a read-only install, HOME and
    XDG_CACHE_HOME unwritable) was a traceback at the first import of a kernel. A path
    under a regular file cannot be made, by root either: the folders numba would try."""
    blocker = tmp_path / "file"
    blocker.write_text("")
    # set, then deleted: monkeypatch restores what was there before (a delenv of a variable
    # not set records nothing, and the later delenv's undo left the fallback set for every
    # later test's processes, where CI sets none)
    monkeypatch.setenv("NUMBA_CACHE_DIR", "")
    monkeypatch.delenv("NUMBA_CACHE_DIR")
    monkeypatch.setattr(kernels.tempfile, "tempdir", str(tmp_path / "tmp"))
    (tmp_path / "tmp").mkdir()
    folder = kernels.cache_folder_fallback([blocker / "a", blocker / "b"])
    assert folder == str(tmp_path / "tmp" / f"vistrack-numba-{os.getuid()}")
    assert os.environ["NUMBA_CACHE_DIR"] == folder and os.path.isdir(folder)
    assert os.stat(folder).st_mode & 0o077 == 0  # numba runs what it holds: ours alone
    # one it can write to: nothing changes
    monkeypatch.delenv("NUMBA_CACHE_DIR")
    assert kernels.cache_folder_fallback([blocker / "a", tmp_path / "ok"]) is None
    assert "NUMBA_CACHE_DIR" not in os.environ
    # a folder of that name that another could write to is not used
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    os.chmod(folder, 0o777)
    other = kernels.cache_folder_fallback([blocker / "a"])
    assert other != folder and os.path.dirname(other) == str(tmp_path / "tmp")


LOAD_ONLY = """
import importlib
import json
import sys
import numba
import numpy as np
from vistrack.common.messages import Frame, encode_pre_frame
from vistrack.common.params import TrackerParams
from vistrack.common.vision import preprocess, pyramid
from vistrack.services.kernels import warm_up_kernels
from vistrack.services.preprocessing.service import _load_kernels

def loaded():
    return {f"{name}.{key}": len(kernel.signatures)
            for name, module in list(sys.modules.items())
            if name.startswith("vistrack.common.vision.")
            for key, kernel in vars(module).items()
            if isinstance(kernel, numba.core.registry.CPUDispatcher) and kernel.signatures}

pre = importlib.import_module("vistrack.common.vision.preprocess")  # the module
print(warm_up_kernels(print, load=lambda: _load_kernels(TrackerParams())))
print(len(pyramid._track_frame.signatures), len(pre._blur_fixed.signatures))
before = loaded()
image = np.random.default_rng(0).integers(0, 256, (96, 128), dtype=np.uint8)
frame = Frame.decode(Frame(seq=0, stamp_ns=1, width=128, height=96, data=image).encode())
# a decoded frame, as the service's come, through the service's path with candidates wanted
out = preprocess(frame.data, TrackerParams())
encode_pre_frame(seq=0, stamp_ns=1, data=out.filtered, candidates=out.candidates,
                 strength=out.strength, params_id=0)
print(json.dumps(sorted(set(loaded().items()) - set(before.items()))))
"""


def test_a_process_that_runs_pre_processing_alone_loads_only_its_kernels():
    """With the kernels in the cache, every warm-up loaded all of the tracker's (~0.9 s of a
    process's start): pre-processing, which runs its filter's, and the launcher, which runs
    none, while the services around them started on the same cores. ``load`` loads what the
    process runs instead, and a decoded frame then runs only what it loaded: the candidates'
    kernels too, or their load (22 ms) on the first frame had the next one overwritten at
    pre-processing's latest-only input (a 30 fps file camera's frame 1, beside a busy core)."""
    out = subprocess.run([sys.executable, "-c", LOAD_ONLY], capture_output=True, text=True,
                         check=True, timeout=300).stdout.splitlines()
    assert out[:2] == ["False", "0 1"]  # from the cache; no search; the filter, once
    assert json.loads(out[2]) == []  # the frame's path loaded nothing more
