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
import json
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager

import msgpack
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
def test_a_tool_given_endpoints_scouts_no_multicast_and_gossips_to_routers_only(flags,
                                                                                multicast):
    from vistrack.common.bus import add_zenoh_args, config_from_args

    parser = argparse.ArgumentParser()
    add_zenoh_args(parser)
    args = parser.parse_args(flags)
    conf = as_a_tool(config_from_args(args), args)
    assert conf.get_json("scouting/multicast/enabled") == multicast
    assert conf.get_json("scouting/gossip/target").replace(" ", "") == \
        '{"router":[],"peer":["router"]}'


def test_the_tools_of_one_system_reach_each_other(tmp_path):
    """A tool's gossip goes to routers: ``vistrack echo`` (or ``record``, ``hz``) receives
    what ``vistrack replay`` publishes beside it. A router does not relay between peers, and
    with no gossip at all neither tool learned where the other listens: the replay waited its
    ``--wait`` for a subscriber, published to nobody, and the echo got nothing."""
    recording = tmp_path / "tool.vtr"
    start = time.time_ns()
    with recording.open("wb") as f:  # the documented .vtr format, written with plain msgpack
        f.write(msgpack.packb({"format": "vistrack-record", "version": 1, "robot": "robot",
                               "keys": [KEY], "start_ns": start}))
        for n in range(5):
            f.write(msgpack.packb({"t_ns": start + n * 10_000_000, "key": KEY,
                                   "payload": b"x" * (n + 1)}))
    with ExitStack() as stack:
        endpoint = stack.enter_context(router(_free_port()))
        # a service of the system, as under vistrack up
        stack.enter_context(zenoh.open(zenoh_config(endpoint)))
        zflags = ["-e", endpoint, "--no-multicast-scouting"]
        echo = stack.enter_context(subprocess.Popen(
            [sys.executable, "-m", "vistrack.services.cli", "echo", "isolation", "--count", "3",
             "--timeout", "30", *zflags], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            text=True))
        try:
            # the replay waits for the echo's subscription before its first sample
            replay = vistrack("replay", str(recording), "--wait", "30", *zflags, timeout=60)
            out, err = echo.communicate(timeout=30)
        finally:
            if echo.poll() is None:
                echo.kill()
    assert replay.returncode == 0, replay.stderr
    assert "no subscriber" not in replay.stderr, replay.stderr
    assert echo.returncode == 0, err
    lines = [json.loads(line) for line in out.splitlines()]  # not messages: said so, sized
    assert [(d["key"], d["nbytes"]) for d in lines] == [(KEY, 1), (KEY, 2), (KEY, 3)], out


def test_a_tool_does_not_run_as_a_router(tmp_path):
    """`-m router` with an -e to each of two systems routed between them: every service
    took the other system's samples, and a launcher killed services as hung when the other
    system answered their status queries. Refused, from the flag or a config file."""
    conf = tmp_path / "router.json5"
    conf.write_text('{mode: "router"}\n')
    for flags, where in ((["-m", "router", "-e", "tcp/127.0.0.1:1", "-e", "tcp/127.0.0.1:2"],
                          "-m router"), (["-c", str(conf)], f"{conf}: mode router")):
        run = vistrack("echo", "isolation", "--count", "1", *flags, timeout=30)
        assert run.returncode == 2, run.stderr
        assert run.stderr == (f"vistrack echo: error: {where}: a tool does not run as a router "
                              "(it would route between the systems it reaches): allowed peer "
                              "(the default) or client\n")
