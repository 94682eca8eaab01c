"""A ``vistrack up`` run for the benchmarks that measure the whole system as it is launched.

:class:`UpRun` starts ``vistrack up`` as a child process on a free loopback port (multicast
scouting off, its own robot id), collects its output line by line with arrival times, waits
for its ready line, and reads the services' pids and counters from their status queryables
through a plain Zenoh session. :func:`cpu_s` and :func:`rss_kib` read ``/proc``.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import zenoh

from ...common.bus import loopback_config, query_status
from ...common.keys import SERVICES, Keys

READY_S = 120.0  # five processes importing numpy/numba/OpenCV on a busy 2-core machine


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def cpu_s(pid: int) -> float:
    """User + system CPU seconds used so far by process ``pid`` (all its threads)."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def rss_kib(pid: int) -> int:
    """Resident set size of process ``pid``, KiB (``VmRSS``)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise RuntimeError(f"no VmRSS for pid {pid}")


def children(pid: int) -> list[int]:
    """Direct children of ``pid``."""
    out: list[int] = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            out += [int(p) for p in (task / "children").read_text().split()]
        except OSError:
            pass  # the thread ended meanwhile
    return out


def tuning_worker(auto_tuner_pid: int) -> int | None:
    """The pid of the auto-tuner's tuning worker (a multiprocessing 'spawn' child; not its
    resource tracker), or None."""
    for pid in children(auto_tuner_pid):
        try:
            if b"spawn_main" in Path(f"/proc/{pid}/cmdline").read_bytes():
                return pid
        except OSError:
            continue  # gone meanwhile
    return None


class UpRun:
    """``vistrack up LAUNCH`` (or the default launch) with ``extra`` flags, as a child process.

    Use as a context manager: entering waits for ``vistrack up: ready``, leaving sends SIGINT
    and waits for the run to end (SIGKILL after 10 s).
    """

    def __init__(self, *extra: str, launch: str | None = None,
                 env: dict[str, str] | None = None, robot: str = "bench") -> None:
        self.port = free_port()
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self.keys = Keys(robot)
        argv = [sys.executable, "-m", "vistrack.services.cli", "up",
                *([launch] if launch else []), "-l", self.endpoint, "--no-multicast-scouting",
                "--robot", robot, *extra]
        self.proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, text=True,
                                     env={**os.environ, **(env or {})}, start_new_session=True)
        self.lines: list[tuple[float, str]] = []
        self._cond = threading.Condition()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        self.session: zenoh.Session | None = None

    def _read(self) -> None:
        assert self.proc.stdout is not None
        with self.proc.stdout:
            for line in self.proc.stdout:
                with self._cond:
                    self.lines.append((time.monotonic(), line.rstrip("\n")))
                    self._cond.notify_all()

    def __enter__(self) -> UpRun:
        try:
            self.wait_line(r"^vistrack up: ready \(\d+ services\)$", READY_S)
            self.session = zenoh.open(loopback_config(self.endpoint))
        except BaseException:
            self.stop()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def stop(self) -> None:
        if self.session is not None:
            self.session.close()
            self.session = None
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGINT)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()
        self._reader.join(5)

    def wait_line(self, pattern: str, timeout: float, after: float = 0.0) -> tuple[float, str]:
        """(arrival time, line) of the first line matching ``pattern`` that arrived after the
        monotonic time ``after``."""
        regex = re.compile(pattern)
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                for t, line in self.lines:
                    if t > after and regex.search(line):
                        return t, line
                if time.monotonic() > deadline or self.proc.poll() is not None:
                    tail = "\n".join(line for _, line in self.lines[-30:])
                    raise RuntimeError(f"no line matching {pattern!r} within {timeout} s "
                                       f"(exit {self.proc.poll()}):\n{tail}")
                self._cond.wait(0.1)

    def count(self, pattern: str) -> int:
        """Output lines matching ``pattern`` so far."""
        return len(self.matching(pattern))

    def matching(self, pattern: str) -> list[str]:
        """The output lines matching ``pattern`` so far."""
        regex = re.compile(pattern)
        with self._cond:
            return [line for _, line in self.lines if regex.search(line)]

    def statuses(self, timeout: float = 2.0) -> dict[str, dict[str, Any]]:
        """Service name (as in keys) -> its status reply."""
        assert self.session is not None
        return {s["service"]: s for s in query_status(self.session, self.keys, timeout=timeout)}

    def pids(self, names: tuple[str, ...] = SERVICES, timeout: float = 30.0) -> dict[str, int]:
        """Service name -> pid, once every one of ``names`` answers its status query."""
        deadline = time.monotonic() + timeout
        while True:
            got = {n: s["pid"] for n, s in self.statuses().items() if n in names}
            if set(got) == set(names):
                return got
            if time.monotonic() > deadline:
                raise RuntimeError(f"no status from {sorted(set(names) - set(got))}")
            time.sleep(0.2)
