"""Saying when the tracker's kernels compile, and only then (services/kernels.py, warm_up).

A real cold compile takes half a minute of CPU, so it is exercised by the first-run benchmark
(tests/bench/test_bench_first_run.py); here the compile event is raised by compiling small
functions of the test's own, and the cached case runs on the cache the session filled.
"""

from __future__ import annotations

import subprocess
import sys

import numba as nb
from numba.core import event as numba_event

from vistrack.common.vision import tracker
from vistrack.services.kernels import say_on_stderr, warm_up_kernels


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


def test_say_on_stderr_names_the_command(capsys):
    say_on_stderr("track")("compiling the tracker's kernels")
    assert capsys.readouterr().err == "vistrack track: compiling the tracker's kernels\n"


def test_track_is_silent_on_stderr_when_the_kernels_are_cached():
    run = subprocess.run([sys.executable, "-m", "vistrack.services.cli", "track",
                          "--format", "csv"], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0 and run.stderr == ""
    assert run.stdout.startswith("seq,npi,")
