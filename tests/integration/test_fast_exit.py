"""A failing service process ends at once, so that the launcher's restart comes promptly.

Each case is a real process running ``runtime.serve`` (a service's whole life: Zenoh session,
signal handling, the numba kernels warmed up as every tracker service has them) with a loop
that goes wrong in one way; the time from the fault to the process's exit is measured here and
must stay under 1 s (issue 13: a crash took ~5 s to end the process under load, most of it the
interpreter's teardown of numba's and LLVM's objects).
"""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
import threading
import time
from collections.abc import Iterator

import pytest
import zenoh

from vistrack.common.messages import unpack

from procs import router, zenoh_config

pytestmark = pytest.mark.integration

EXIT_S = 1.0  # the bound, fault to exit

SERVICE = textwrap.dedent("""
    import argparse, logging, sys, time
    from vistrack.services import threads
    threads.configure()
    from vistrack.common.vision import warm_up
    from vistrack.services.runtime import add_service_args, dispatch, ready, serve

    fault = sys.argv[1]
    log = logging.getLogger("vistrack.preprocessing")

    def loop(node, args):
        warm_up()
        node.subscribe(node.keys.frame, latest=True)
        got = []

        def on_frame(payload):
            got.append(payload)
            if fault == "stuck":  # a computation that never ends, deaf to stop
                while True:
                    pass

        def tick():
            if got and fault == "raise":  # a fault between inputs: not isolated
                raise RuntimeError("a bug outside the per-message path")

        ready(node)
        dispatch(node, {node.keys.frame: on_frame}, log, tick=tick)

    parser = argparse.ArgumentParser()
    add_service_args(parser)
    serve("preprocessing", parser.parse_args(sys.argv[2:]), loop)
""")


class Service:
    """One such process; its output lines and its exit time, as they happen."""

    def __init__(self, fault: str, endpoint: str) -> None:
        self.robot = f"exit{fault}"  # its own keys: the three run side by side
        self.p = subprocess.Popen([sys.executable, "-c", SERVICE, fault, "-e", endpoint,
                                   "--no-multicast-scouting", "--robot", self.robot],
                                  stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self.lines: list[tuple[float, str]] = []
        self.exited_at: float | None = None
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        self._waiter = threading.Thread(target=self._wait, daemon=True)
        self._waiter.start()

    def _read(self) -> None:
        assert self.p.stdout is not None
        with self.p.stdout:
            for line in self.p.stdout:
                self.lines.append((time.monotonic(), line.rstrip("\n")))

    def _wait(self) -> None:
        self.p.wait()
        self.exited_at = time.monotonic()

    def when(self, needle: str, timeout: float) -> float:
        """Arrival time of the first line containing ``needle``."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for t, line in list(self.lines):
                if needle in line:
                    return t
            time.sleep(0.002)
        raise AssertionError(f"no line with {needle!r} within {timeout} s:\n{self.output}")

    def exit_time(self, timeout: float = 10.0) -> float:
        self._waiter.join(timeout)
        assert self.exited_at is not None, f"still running after {timeout} s:\n{self.output}"
        self._reader.join(5)
        return self.exited_at

    @property
    def output(self) -> str:
        return "\n".join(line for _, line in self.lines)

    def kill(self) -> None:
        if self.p.poll() is None:
            self.p.kill()
        self.exit_time()


@pytest.fixture(scope="module")
def started(free_port_module) -> Iterator[tuple[dict[str, Service], zenoh.Session]]:
    """The three faulty services, started together (their start-up is the slow part)."""
    with router(free_port_module) as endpoint, zenoh.open(zenoh_config(endpoint)) as session:
        services = {fault: Service(fault, endpoint) for fault in ("raise", "stuck", "segv")}
        try:
            for s in services.values():
                s.when("ready (robot", 90)
            yield services, session
        finally:
            for s in services.values():
                s.kill()


def send_frame_until(session: zenoh.Session, s: Service, done) -> None:
    """Publish a frame to ``s`` until ``done()``: its subscription reaches us a moment after
    its ready line."""
    deadline = time.monotonic() + 10
    while not done():
        assert time.monotonic() < deadline, "the service never took a frame"
        session.put(f"vistrack/{s.robot}/camera/frame", b"any payload")
        time.sleep(0.05)


def busy(session: zenoh.Session, s: Service) -> bool:
    """Whether ``s`` reports its loop busy on one input (``busy_s`` of its status)."""
    for reply in session.get(f"vistrack/{s.robot}/preprocessing/status", timeout=1.0):
        if reply.ok is not None and unpack(reply.ok.payload.to_bytes())["busy_s"] > 0.1:
            return True
    return False


def test_an_uncaught_exception_ends_the_process_within_1_s(started):
    services, session = started
    s = services["raise"]
    send_frame_until(session, s, lambda: any("outside the per-message" in x for _, x in s.lines))
    fault = s.when("failed outside the per-message path: exiting", 1)
    gone = s.exit_time()
    assert s.p.returncode == 1
    assert "RuntimeError: a bug outside the per-message path" in s.output  # the traceback
    assert gone - fault < EXIT_S, f"{gone - fault:.3f} s from the fault to the exit"


def test_a_stop_request_ends_a_stuck_process_within_1_s(started):
    services, session = started
    s = services["stuck"]
    send_frame_until(session, s, lambda: busy(session, s))
    t0 = time.monotonic()
    s.p.send_signal(signal.SIGTERM)
    gone = s.exit_time()
    assert gone - t0 < EXIT_S, f"{gone - t0:.3f} s from SIGTERM to the exit"
    assert s.p.returncode == 1
    assert "the loop did not return within 0.5 s of the stop request: exiting" in s.output


def test_a_fatal_signal_ends_the_process_within_1_s_with_the_stacks(started):
    services, _ = started
    s = services["segv"]
    t0 = time.monotonic()
    s.p.send_signal(signal.SIGSEGV)
    gone = s.exit_time()
    assert gone - t0 < EXIT_S, f"{gone - t0:.3f} s from SIGSEGV to the exit"
    assert s.p.returncode == -signal.SIGSEGV
    assert "Fatal Python error: Segmentation fault" in s.output  # where every thread was
