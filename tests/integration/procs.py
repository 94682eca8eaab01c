"""Real processes for integration tests: an in-test Zenoh router and vistrack services.

Every helper waits for a condition with a deadline (a log line, a sample), never a bare sleep.
"""

from __future__ import annotations

import os
import queue
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import zenoh

from vistrack.common.bus import loopback_config

SERVICE_CLI = ("preprocessing", "motion-estimation", "auto-tuner", "fuzzy-controller")


zenoh_config = loopback_config  # the name the tests use


@contextmanager
def router(port: int) -> Iterator[str]:
    """A Zenoh router in the test process on tcp/127.0.0.1:port; yields the endpoint."""
    endpoint = f"tcp/127.0.0.1:{port}"
    with zenoh.open(zenoh_config(endpoint, router=True)):
        yield endpoint


class Proc:
    """A vistrack subprocess whose merged output is collected line by line."""

    def __init__(self, args: list[str], env: dict[str, str] | None = None) -> None:
        self.args = args
        self.lines: list[str] = []
        self._q: queue.Queue[str] = queue.Queue()
        self.p = subprocess.Popen([sys.executable, "-m", "vistrack.services.cli", *args],
                                  stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                  env={**os.environ, **(env or {})}, start_new_session=True)
        self._pump_thread = threading.Thread(target=self._pump, daemon=True)
        self._pump_thread.start()

    def _pump(self) -> None:
        assert self.p.stdout is not None
        with self.p.stdout:  # closed at EOF, or the pipe leaks a ResourceWarning
            for line in self.p.stdout:
                self.lines.append(line.rstrip("\n"))
                self._q.put(line)

    def wait_for(self, needle: str, timeout: float = 30.0) -> str:
        deadline = time.monotonic() + timeout
        for line in list(self.lines):
            if needle in line:
                return line
        while time.monotonic() < deadline:
            try:
                line = self._q.get(timeout=0.1)
            except queue.Empty:
                if self.p.poll() is not None and self._q.empty():
                    break
                continue
            if needle in line:
                return line
        raise AssertionError(f"{self.args[0]}: no line with {needle!r} within {timeout} s; "
                             f"output:\n" + "\n".join(self.lines[-30:]))

    def stop(self, timeout: float = 5.0) -> int:
        if self.p.poll() is None:
            self.p.send_signal(signal.SIGTERM)
            try:
                self.p.wait(timeout)
            except subprocess.TimeoutExpired:
                self.p.kill()
                self.p.wait()
        self._pump_thread.join(timeout)
        return self.p.returncode


def service(name: str, endpoint: str, *extra: str) -> Proc:
    return Proc([name, "-e", endpoint, "--no-multicast-scouting", *extra])


@contextmanager
def services(endpoint: str, names=SERVICE_CLI, extra: dict[str, list[str]] | None = None
             ) -> Iterator[dict[str, Proc]]:
    """Start services, wait until each is ready, stop them all at the end."""
    procs = {n: service(n, endpoint, *(extra or {}).get(n, [])) for n in names}
    try:
        for p in procs.values():
            p.wait_for("ready", timeout=90.0)
        yield procs
    finally:
        for p in procs.values():
            p.stop()


class Collector:
    """Plain Zenoh subscription collecting (key, payload bytes) in arrival order."""

    def __init__(self, session: zenoh.Session, key: str) -> None:
        self.items: list[tuple[str, bytes]] = []
        self._lock = threading.Lock()
        self.sub = session.declare_subscriber(key, self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self.items.append((str(sample.key_expr), sample.payload.to_bytes()))

    def wait(self, pred: Callable[[list[tuple[str, bytes]]], bool], timeout: float = 30.0
             ) -> list[tuple[str, bytes]]:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self._lock:
                items = list(self.items)
            if pred(items):
                return items
            time.sleep(0.02)
        raise AssertionError(f"condition not met within {timeout} s ({len(self.items)} items)")
