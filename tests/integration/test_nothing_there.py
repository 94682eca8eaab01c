"""What every command says when what it needs is not there: a taken port, no router at the
endpoint, no camera device, nobody publishing, no service answering. One line and exit 1 for
the failures, a line on stderr while a tool waits; never a traceback, never silence.

Each group of cases runs its commands at once (they spend their time waiting), as real
subprocesses on free loopback ports with multicast scouting off.
"""

from __future__ import annotations

import json
import re
import socket
import subprocess
import sys
from collections.abc import Iterator

import pytest

from procs import router

pytestmark = pytest.mark.integration

NS = "--no-multicast-scouting"
TIMEOUT_S = 60


def start(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, "-m", "vistrack.services.cli", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def finish(procs: dict[str, subprocess.Popen[str]]) -> dict[str, tuple[int, str, str]]:
    """Each command's (exit code, stdout, stderr)."""
    done = {}
    for name, proc in procs.items():
        try:
            out, err = proc.communicate(timeout=TIMEOUT_S)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
        done[name] = (proc.returncode, out, err)
    return done


@pytest.fixture
def taken_port() -> Iterator[int]:
    """A loopback port something else listens on."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        sock.listen()
        yield sock.getsockname()[1]


def test_no_router_at_the_endpoint_is_one_line_and_exit_1(free_port, tmp_path):
    # in peer mode Zenoh opens a session anyway and retries in silence: the tool waited
    # forever with no output
    endpoint = f"tcp/127.0.0.1:{free_port}"
    # a recording of the day before: the recorder emptied it to its header, then failed
    kept = tmp_path / "yesterday.vtr"
    kept.write_bytes(b"a recording of the day before")
    results = finish({
        "record": start("record", str(kept), "-e", endpoint, NS),
        "echo": start("echo", "motion/estimate", "--count", "5", "-e", endpoint, NS),
        "status": start("status", "-e", endpoint, NS),
        "preprocessing": start("preprocessing", "-e", endpoint, NS),
        "up": start("up", "-e", endpoint, NS, "--duration", "1"),
    })
    for name, (code, out, err) in results.items():
        assert (code, out, err) == (1, "", f"vistrack {name}: error: cannot connect to "
                                    f"{endpoint}: nothing answers there (is vistrack up or "
                                    "vistrack router running, on that port?)\n"), name
    assert kept.read_bytes() == b"a recording of the day before"


def test_a_taken_port_is_one_line_and_exit_1(taken_port, tmp_path):
    # the demo printed a full traceback (BusError: cannot open zenoh session: ...)
    listen = f"tcp/127.0.0.1:{taken_port}"
    results = finish({
        "demo": start("demo", "-l", listen, NS, "--out", str(tmp_path / "demo")),
        "up": start("up", "-l", listen, NS),
        "router": start("router", "-l", listen),
        "echo": start("echo", "motion/estimate", "-l", listen, NS),
    })
    for name, (code, out, err) in results.items():
        assert code == 1 and err.count("\n") == 1, (name, err)
        assert err.startswith(f"vistrack {name}: error: cannot open zenoh session: "), err
        assert "Address already in use" in err and listen in err, err
        assert err.endswith("another process listens there (a vistrack up, router or demo "
                            "already running? join it with -e ENDPOINT, or give -l another "
                            "port)\n"), err
        assert not re.search(r"\[launcher\] [0-9:.]+ started", out), (name, out)


def test_a_missing_camera_device_is_one_line_and_exit_1(free_port):
    # `up --camera device:0` without a camera failed only once every service had started
    endpoint = f"tcp/127.0.0.1:{free_port}"
    results = finish({
        "up": start("up", "--camera", "device:99", "-l", endpoint, NS),
        "camera": start("camera", "--source", "device:99", "-e", endpoint, NS),
    })
    for name, (code, out, err) in results.items():
        assert (code, out, err) == (
            1, "", f"vistrack {name}: error: device:99: cannot open the camera device\n"), name


def test_nothing_publishing_or_answering_is_said(free_port):
    with router(free_port) as endpoint:
        results = finish({
            "echo": start("echo", "motion/estimate", "--timeout", "3", "-e", endpoint, NS),
            "hz": start("hz", "camera/frame", "--duration", "3", "-e", endpoint, NS),
            "status": start("status", "-e", endpoint, NS),
            "status --json": start("status", "--json", "-e", endpoint, NS),
        })
    # echo and hz wait, and say what for, once, on stderr after 2 s
    for name, key in (("echo", "motion/estimate"), ("hz", "camera/frame")):
        code, _, err = results[name]
        assert (code, err) == (0, f"vistrack {name}: waiting for a publisher on "
                               f"vistrack/robot/{key} at {endpoint} (nothing received in "
                               "2 s)\n"), name
    assert "no new samples" in results["hz"][1]
    # status: nothing answered is a failure (it exited 0), and --json is one document
    code, out, err = results["status"]
    assert (code, out) == (1, "")
    assert err == f"vistrack status: error: no live service for robot 'robot' at {endpoint}\n"
    code, out, err = results["status --json"]
    assert code == 1 and json.loads(out) == [] and err.count("\n") == 1


def test_a_camera_waiting_for_stdin_that_ends_says_so(free_port):
    """--start-on-stdin from a unit file or a script (stdin /dev/null): it said only
    "stopped", exit 0, and no frame was ever sent."""
    endpoint = f"tcp/127.0.0.1:{free_port}"
    run = subprocess.run([sys.executable, "-m", "vistrack.services.cli", "camera", "--source",
                          "builtin", "--start-on-stdin", "-l", endpoint, NS],
                         stdin=subprocess.DEVNULL, capture_output=True, text=True,
                         timeout=TIMEOUT_S)
    assert run.returncode == 0, run.stderr
    assert ("--start-on-stdin: standard input ended before the line that starts the frames"
            in run.stderr), run.stderr


def test_a_host_name_that_does_not_resolve_is_said_so():
    """A mistyped host was reported as "nothing answers there (is vistrack up or vistrack
    router running, on that port?)", sending the user to the router rather than the name (a
    hunt of the README against the tools). ``.invalid`` never resolves (RFC 2606)."""
    endpoint = "tcp/nonexistent.invalid:7447"
    results = finish({
        "echo": start("echo", "motion/estimate", "--timeout", "3", "-e", endpoint, NS),
        "status": start("status", "-e", endpoint, NS),
    })
    for name, (code, out, err) in results.items():
        assert (code, out, err) == (1, "", f"vistrack {name}: error: cannot connect to "
                                    f"{endpoint}: the host name 'nonexistent.invalid' does not "
                                    "resolve (misspelt, or no DNS for it here?)\n"), name
