"""The README's record/replay example, run as written (only its port is changed to a free one),
with a cold user cache, which also checks `vistrack up`'s start-up order.

Regression for a user's report: `vistrack up &` kept its built-in camera running while the
recording was replayed, so two cameras fed the pipeline (148 "camera restarted ... new track"
lines, DROPPED above 37,000). The example now runs the pipeline without a camera.
"""

from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import msgpack
import pytest
import zenoh

from procs import zenoh_config

pytestmark = pytest.mark.integration

README = Path(__file__).resolve().parents[2] / "README.md"
FIRST_LINE = "vistrack up -l tcp/127.0.0.1:7447 --no-multicast-scouting &"


def readme_block(first_line: str) -> str:
    """The ```sh block of the README that contains ``first_line``."""
    for block in re.findall(r"```sh\n(.*?)```", README.read_text(), flags=re.S):
        if first_line in block:
            return block
    raise AssertionError(f"no sh block with {first_line!r} in the README")


def status_rows(output: str) -> dict[str, dict[str, str]]:
    """The rows of the last `vistrack status` table in ``output``, by service."""
    lines = output.splitlines()
    start = max(i for i, line in enumerate(lines) if line.startswith("SERVICE "))
    headers = lines[start].split()
    rows = {}
    for line in lines[start + 1:]:
        cells = line.split()
        if not cells or not re.fullmatch(r"[a-z_]+", cells[0]) or len(cells) < len(headers):
            break
        rows[cells[0]] = dict(zip(headers, cells, strict=False))
    return rows


def ready_at(out: str, service: str) -> float:
    """The time of day (s) in the ready line of ``service`` in ``out``."""
    m = re.search(rf"^\[{service}\] (\d\d):(\d\d):(\d\d\.\d+) .* ready \(robot", out,
                  flags=re.M)
    assert m, f"no ready line of {service} in:\n" + out[-4000:]
    return int(m[1]) * 3600 + int(m[2]) * 60 + float(m[3])


def check_start_up_order(out: str) -> None:
    """The start-up order of a `vistrack up` run from its output, with a cold user cache:
    the camera is ready after every other service said ready (the fuzzy-controller once its
    surface was built), and "ready (5 services)" comes after all of them.

    The first run of a user who reported this got its camera 6 s before the controller was
    ready (its surface took 9 s to build), and "ready (5 services)" 5 s before it. The times
    are the services' own (the order of lines from different processes through the
    launcher's pipes is not theirs to the millisecond).
    """
    others = ("fuzzy-controller", "motion-estimation", "preprocessing", "auto-tuner")
    camera = ready_at(out, "camera")
    for service in others:
        assert ready_at(out, service) < camera, service
    lines = out.splitlines()
    done = lines.index("vistrack up: ready (5 services)")
    started = next(i for i, line in enumerate(lines)
                   if re.match(r"\[launcher\] [0-9:.]+ started camera", line))
    assert started < done
    for service in others:  # a camera start apart, at least
        assert any(re.match(rf"\[{service}\] .* ready \(robot", line)
                   for line in lines[:done]), service
    compiling = [line for line in lines if line.startswith("[fuzzy-controller] ")]
    assert any("compiling the fuzzy control surfaces" in line for line in compiling)


def test_the_record_replay_example_runs_as_written(tmp_path, free_port):
    script = readme_block(FIRST_LINE).replace(":7447", f":{free_port}")
    assert "--camera none" in script and "replay" in script
    env = {**os.environ,
           # the vistrack of this interpreter first on PATH, as after `pip install`
           "PATH": os.path.dirname(sys.executable) + os.pathsep + os.environ.get("PATH", ""),
           # a first run's user cache: the fuzzy surface is built at start-up
           "XDG_CACHE_HOME": str(tmp_path / "cache")}
    # its own process group, output to a file: whatever the script leaves running (a
    # `vistrack up &` after a failed line) neither holds a pipe open nor outlives the test
    log = tmp_path / "output.txt"
    with open(log, "w") as sink:
        run = subprocess.Popen(["bash", "-e", "-c", script], cwd=tmp_path, env=env,
                               stdout=sink, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        run.wait(timeout=240)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(run.pid, signal.SIGTERM)
        run.wait()
    out = log.read_text()
    assert run.returncode == 0, out[-4000:]
    # the first system with its camera, the second without
    assert "vistrack up: ready (5 services)" in out and "vistrack up: ready (4 services)" in out
    check_start_up_order(out.split("vistrack up: stopped")[0])
    assert out.count("vistrack up: stopped (exit 0)") == 2, out[-4000:]
    recorded = re.search(r"vistrack record: (\d+) samples of 1 key in", out)
    assert recorded and int(recorded[1]) >= 45, out[-4000:]  # 3 s at 30 fps
    replayed = re.search(r"vistrack replay: (\d+) samples? from", out)
    assert replayed and int(replayed[1]) == int(recorded[1])
    # one camera only: no track restarted by a second sequence of frames
    assert "camera restarted" not in out and "[camera]" not in out.split(
        "vistrack up: ready (4 services)")[1]
    rows = status_rows(out)
    assert "camera" not in rows and {"preprocessing", "motion_estimation", "auto_tuner",
                                     "fuzzy_controller"} <= rows.keys()
    me = rows["motion_estimation"]
    # the replayed frames tracked (the first few may beat motion-estimation's start: the
    # replay waits for the first subscriber of camera/frame, preprocessing)
    assert int(me["PUBLISHED"]) >= int(recorded[1]) * 9 // 10, me
    for row in rows.values():
        # the report was DROPPED above 37,000: seq gaps between two cameras' sequences; with
        # one, what a slow stage skips (latest-only) is all there is, a part of the frames
        assert row["STATE"] == "ok", row
        assert int(row["DROPPED"]) < int(recorded[1]) // 2, row
        assert int(row["REJECTED"]) == 0, row


def test_the_subscriber_example_reads_its_system_and_joins_no_other(free_port):
    """The README's Python subscriber, run as written (only its port and robot id changed),
    prints the estimates of the system whose router it names, and nothing of another system
    beside it.

    Run as a peer (Zenoh's default, as the example first was), it found a second system on
    the machine by multicast scouting, printed both systems' estimates mixed, and its gossip
    joined the two systems' services for good (found by a user walking the README while
    another pipeline ran)."""
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    script = next(b for b in blocks if "vistrack/robot/motion/estimate" in b)
    key = "vistrack/robot/motion/estimate"
    assert "tcp/127.0.0.1:7447" in script
    # a robot id of the test's own: the other system below answers multicast scouts, and a
    # pipeline running on the machine (multicast scouting on) finds it too
    mine_key = f"vistrack/readme{free_port}/motion/estimate"
    script = script.replace(":7447", f":{free_port}").replace(key, mine_key)
    endpoint = f"tcp/127.0.0.1:{free_port}"
    # the other system: a peer that answers multicast scouts, as a service under `vistrack
    # up` without --no-multicast-scouting does (it connects to nothing it finds itself)
    other = zenoh.Config()
    other.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
    other.insert_json5("scouting/multicast/autoconnect", '{"router": [], "peer": []}')
    other.insert_json5("scouting/gossip/enabled", "false")

    def estimate(seq: int) -> bytes:
        return msgpack.packb({"v": 1, "seq": seq, "npi": 50, "xc": 1.0, "yc": 2.0,
                              "dx": 0.5, "scale": 1.0})

    with zenoh.open(zenoh_config(endpoint, router=True)), \
            zenoh.open(zenoh_config(endpoint)) as ours, zenoh.open(other) as theirs, \
            subprocess.Popen([sys.executable, "-c", script], stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as sub:
        try:
            assert sub.stdout is not None and sub.stdin is not None
            assert sub.stdout.readline().startswith("press Enter")
            mine = ours.declare_publisher(mine_key)
            deadline = time.monotonic() + 20
            while not mine.matching_status.matching:  # the example has subscribed
                assert time.monotonic() < deadline, "the example never subscribed"
                time.sleep(0.05)
            for n in range(20):  # a second of each system's estimates
                mine.put(estimate(1000 + n))
                theirs.put(mine_key, estimate(5000 + n))
                time.sleep(0.05)
            time.sleep(0.5)
            out, err = sub.communicate("\n", timeout=20)
        finally:
            if sub.poll() is None:
                sub.kill()
    assert sub.returncode == 0, err
    seqs = [int(line.split()[0]) for line in out.splitlines() if line.strip()]
    assert seqs == list(range(1000, 1020)), out  # ours, each once, and none of theirs
