"""A tool looks at one system and never joins two (:func:`.tools.shared.as_a_tool`).

Two systems on one machine, each a router with peers connected to it as a ``vistrack up``'s
services are (loopback, multicast scouting off): one tool that reached both routers (here two
``-e``; multicast scouting finds every router on the machine as well) passed each system's
peers the locators of the other's, and the peers connected: every sample of one system then
reached the other, for good. Found with two ``vistrack demo`` and one ``vistrack status``:
67 and 74 fps, centring errors of 263 and 415 px, and not a warning.
"""

from __future__ import annotations

import argparse
import socket
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager

import pytest
import zenoh
from forkcli import vistrack

from vistrack.services.tools.shared import as_a_tool

from procs import router, zenoh_config

pytestmark = pytest.mark.integration

KEY = "vistrack/robot/isolation"


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@contextmanager
def _counting(session: zenoh.Session) -> Iterator[list[bytes]]:
    got: list[bytes] = []
    sub = session.declare_subscriber(KEY, lambda s: got.append(s.payload.to_bytes()))
    try:
        yield got
    finally:
        sub.undeclare()


def _until(condition, timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.02)
    return condition()


def test_a_tool_that_reaches_two_systems_leaves_them_apart():
    with ExitStack() as stack:
        ea = stack.enter_context(router(_free_port()))
        eb = stack.enter_context(router(_free_port()))
        a = stack.enter_context(zenoh.open(zenoh_config(ea)))
        b1 = stack.enter_context(zenoh.open(zenoh_config(eb)))
        b2 = stack.enter_context(zenoh.open(zenoh_config(eb)))
        in_a = stack.enter_context(_counting(a))
        in_b = stack.enter_context(_counting(b2))
        pub = b1.declare_publisher(KEY)
        stop = threading.Event()

        def publish() -> None:
            while not stop.is_set():
                pub.put(b"b")
                time.sleep(0.01)

        thread = threading.Thread(target=publish, daemon=True)
        thread.start()
        try:
            assert _until(lambda: len(in_b) > 0)  # system B's samples flow within B
            # the tool reaches both routers, and the services of both through them
            done = vistrack("echo", "isolation", "-e", ea, "-e", eb, "--count", "3",
                            "--timeout", "10")
            assert done.returncode == 0, done.stderr
            seen = len(in_b)
            assert _until(lambda: len(in_b) >= seen + 50)  # half a second of B's samples
            assert in_a == [], f"{len(in_a)} of system B's samples reached system A"
        finally:
            stop.set()
            thread.join()
            pub.undeclare()


@pytest.mark.parametrize(("flags", "multicast"), [
    ([], "null"),  # no endpoint: the local network is where it looks
    (["-e", "tcp/127.0.0.1:7447"], "false"),
    (["-e", "tcp/127.0.0.1:7447", "--no-multicast-scouting"], "false"),
])
def test_a_tool_given_endpoints_scouts_no_multicast_and_sends_no_gossip(flags, multicast):
    from vistrack.common.bus import add_zenoh_args, config_from_args

    parser = argparse.ArgumentParser()
    add_zenoh_args(parser)
    args = parser.parse_args(flags)
    conf = as_a_tool(config_from_args(args), args)
    assert conf.get_json("scouting/multicast/enabled") == multicast
    assert conf.get_json("scouting/gossip/target").replace(" ", "") == \
        '{"router":[],"peer":[]}'
