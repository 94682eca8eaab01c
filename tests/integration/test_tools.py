"""The tools (echo, hz, status, params, record, replay) and the key contract, over real Zenoh.

One router in the test process and the five services as real processes, started once for the
module (camera: the built-in sequence at 20 fps, looping). Contract checks use a subscriber
written with plain zenoh and msgpack only, as an outside program would. Everything waits for a
condition with a deadline, never a bare sleep.

``tuner/report`` and ``sim/pose`` are not checked yet: no service publishes them in this
pipeline (the auto-tuner's experiments and the simulator camera come in later issues).
"""

from __future__ import annotations

import json
import math
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import msgpack
import pytest
import zenoh
from forkcli import vistrack
from malformed import GOOD, malformed

from vistrack.common.keys import Keys
from vistrack.common.messages import Params, pack
from vistrack.common.params import TrackerParams

from procs import Collector, Proc, router, services, zenoh_config

pytestmark = pytest.mark.integration

ROOT = "vistrack/robot"
ALL = ("camera", "preprocessing", "motion-estimation", "auto-tuner", "fuzzy-controller")
SERVICE_NAMES = ("auto_tuner", "camera", "fuzzy_controller", "motion_estimation",
                 "preprocessing")
CAMERA = ["--source", "builtin", "--fps", "20", "--loop"]
NS = "--no-multicast-scouting"

# Contract fields besides v, seq, stamp_ns, with their msgpack-decoded Python types.
CONTRACT: dict[str, dict[str, type]] = {
    "camera/frame": {"width": int, "height": int, "encoding": str, "data": bytes},
    "preprocessing/frame": {"width": int, "height": int, "encoding": str, "data": bytes,
                            "candidates": bytes, "strength": bytes, "params_id": int,
                            "deferred": bool},
    "motion/estimate": {"npi": int, "xc": float, "yc": float, "xe": float, "ye": float,
                        "dx": float, "dy": float, "scale": float, "t_ms": float, "first": bool,
                        "features": list, "params_id": int},
    "tuner/params": {"max_features": int, "thres_percent": float, "search_size": int,
                     "corr_size": int, "ungroup_size": int, "params_id": int, "source": str,
                     "reason": str},
    "control/cmd_vel": {"vx": float, "vy": float, "wz": float, "stale": bool},
    "motion/demand": {"candidates": bool},
    "preprocessing/done": {},  # while anything subscribes: this test does
}


# -- fixtures and helpers -------------------------------------------------------------------

@pytest.fixture(scope="module")
def endpoint() -> Iterator[str]:
    """A Zenoh router in the test process on a free loopback port (one for the module)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    with router(port) as ep:
        yield ep


@pytest.fixture(scope="module")
def session(endpoint: str) -> Iterator[zenoh.Session]:
    """A plain Zenoh session of the test, connected to the router."""
    with zenoh.open(zenoh_config(endpoint)) as s:
        yield s


@pytest.fixture(scope="module")
def pipeline(endpoint: str) -> Iterator[dict[str, Proc]]:
    """The five services, ready, with estimates flowing."""
    # the tuner's own re-tunes would race the params set tests
    no_tune = {"camera": CAMERA, "auto-tuner": ["--no-tune"]}
    with services(endpoint, names=ALL, extra=no_tune) as procs:
        with zenoh.open(zenoh_config(endpoint)) as s:
            Collector(s, f"{ROOT}/motion/estimate").wait(lambda items: len(items) >= 3)
        yield procs


def tool(endpoint: str, *args: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
    """Run ``vistrack ARGS -e ENDPOINT --no-multicast-scouting`` to completion."""
    return vistrack(*args, "-e", endpoint, "--no-multicast-scouting", timeout=timeout)


def json_lines(text: str) -> list[dict]:
    return [json.loads(line) for line in text.splitlines() if line.strip()]


def status_of(session: zenoh.Session, service: str) -> dict:
    """One service's status reply, read with plain zenoh + msgpack."""
    for reply in session.get(f"{ROOT}/{service}/status", timeout=2.0):
        if reply.ok is not None:
            return msgpack.unpackb(reply.ok.payload.to_bytes())
    raise AssertionError(f"{service} did not answer its status query")


def wait_until(pred: Callable[[], bool], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() >= deadline:
            raise AssertionError(f"not within {timeout} s: {what}")
        time.sleep(0.02)


def estimates_since(collector: Collector, start: int) -> list[dict]:
    return [msgpack.unpackb(p) for _, p in collector.items[start:]]


def wait_for_subscribers(session: zenoh.Session, keys: list[str], timeout: float) -> None:
    """Wait until each key has a subscriber (services subscribe after their "ready" line,
    once their kernels are compiled)."""
    publishers = [session.declare_publisher(k) for k in keys]
    try:
        def matched() -> bool:
            # the binding returns a MatchingStatus whose .matching is the bool
            return all(p.matching_status.matching for p in publishers)
        wait_until(matched, timeout, f"subscribers of {keys}")
    finally:
        for p in publishers:
            p.undeclare()


@contextmanager
def collecting(session: zenoh.Session, key: str) -> Iterator[Collector]:
    """A :class:`Collector` undeclared on exit (frames would pile up for the whole module)."""
    collector = Collector(session, key)
    try:
        yield collector
    finally:
        collector.sub.undeclare()


# -- the key contract, read by a plain subscriber ----------------------------------------

def check_contract(suffix: str, m: object) -> None:
    """Assert that a decoded payload of ``suffix`` follows ARCHITECTURE.md's contract."""
    assert isinstance(m, dict), suffix
    assert m.get("v") == 1, suffix
    assert type(m.get("seq")) is int and m["seq"] >= 0, suffix
    assert type(m.get("stamp_ns")) is int and m["stamp_ns"] > 1_600_000_000 * 10**9, suffix
    for name, typ in CONTRACT[suffix].items():
        assert type(m.get(name)) is typ, (suffix, name, type(m.get(name)))
    if "data" in m:
        assert m["encoding"] == "mono8"
        assert len(m["data"]) == m["width"] * m["height"], suffix
    if suffix == "preprocessing/frame":
        assert len(m["candidates"]) % 4 == 0  # int16 x, y pairs
        assert len(m["strength"]) == len(m["candidates"])  # one float32 per pair
        # deferred: left out, motion-estimation said it would not read them
        assert (len(m["candidates"]) == 0) == m["deferred"]
    if suffix == "motion/estimate":
        assert m["npi"] == len(m["features"])
        for f in m["features"]:
            assert type(f[0]) is int and type(f[1]) is float and type(f[2]) is float
        assert m["scale"] > 0 and m["xe"] >= 0 and m["ye"] >= 0 and m["t_ms"] >= 0
    if suffix == "tuner/params":
        assert m["source"] in ("tuner", "user")


def test_plain_subscriber_decodes_every_contract_key(pipeline, session):
    for suffix in CONTRACT:
        with collecting(session, f"{ROOT}/{suffix}") as collector:
            items = collector.wait(lambda items: len(items) >= 2, timeout=20)
        for key, payload in items[:2]:
            assert key == f"{ROOT}/{suffix}"
            check_contract(suffix, msgpack.unpackb(payload))


# -- echo, hz, status ----------------------------------------------------------------------

def test_echo_count_prints_decoded_json_lines(pipeline, endpoint):
    run = tool(endpoint, "echo", "motion/estimate", "--count", "3", "--timeout", "20")
    assert run.returncode == 0, run.stderr
    lines = json_lines(run.stdout)
    assert len(lines) == 3
    for line in lines:
        assert line["key"] == f"{ROOT}/motion/estimate"
        assert line["npi"] == len(line["features"]) and "params_id" in line
    frames = tool(endpoint, "echo", "frame", "--count", "1", "--timeout", "20")
    assert frames.returncode == 0, frames.stderr
    (frame,) = json_lines(frames.stdout)
    assert frame["data"]["width"] == frame["width"] == 256  # summarised, not dumped
    assert frame["data"]["nbytes"] == 256 * 256 and 0 < frame["data"]["mean"] < 255
    assert len(frames.stdout) < 1000


BAD = b"\xc1 not msgpack"


def test_echo_prints_an_error_line_for_a_bad_payload(pipeline, endpoint, session):
    # sim/pose: a contract key nothing publishes in this pipeline
    with subprocess.Popen([sys.executable, "-m", "vistrack.services.cli", "echo", "sim/pose",
                           "--count", "1", "--timeout", "30", "-e", endpoint,
                           "--no-multicast-scouting"], stdout=subprocess.PIPE,
                          stderr=subprocess.PIPE, text=True) as echo:
        # until echo's subscription is known, a put is lost: repeat it until echo is done
        deadline = time.monotonic() + 30
        while echo.poll() is None and time.monotonic() < deadline:
            session.put(f"{ROOT}/sim/pose", BAD)
            time.sleep(0.1)
        out, err = echo.communicate(timeout=10)
    assert echo.returncode == 0, err
    (line,) = json_lines(out)
    assert line["key"] == f"{ROOT}/sim/pose" and line["nbytes"] == len(BAD)
    assert "msgpack" in line["error"]


def test_hz_reports_rate_jitter_and_gaps(pipeline, endpoint):
    run = tool(endpoint, "hz", "camera/frame", "--duration", "2.5", "--json")
    assert run.returncode == 0, run.stderr
    reports = json_lines(run.stdout)
    assert len(reports) >= 2
    last = reports[-1]
    assert last["key"] == f"{ROOT}/camera/frame"
    assert 10 < last["hz"] < 30  # the camera runs at 20 fps on a loaded test machine
    assert last["min_ms"] <= last["mean_ms"] <= last["max_ms"] and last["std_ms"] >= 0
    assert last["samples"] >= last["window"] >= 10 and last["gaps"] >= 0
    text = tool(endpoint, "hz", "camera/frame", "--duration", "1.3")
    assert "Hz" in text.stdout and "gaps" in text.stdout
    # a run shorter than a report's second still reports (it printed nothing at all)
    short = tool(endpoint, "hz", "camera/frame", "--duration", "0.9", "--json")
    assert short.returncode == 0, short.stderr
    (report,) = json_lines(short.stdout)
    assert report["key"] == f"{ROOT}/camera/frame" and report["samples"] >= 5


def test_status_lists_every_service_and_a_silent_one(pipeline, endpoint, session):
    ghost = session.liveliness().declare_token(f"{ROOT}/alive/ghost")  # alive, never answers
    try:
        # the token takes a moment to reach the router: wait until a fresh session (as the
        # tool opens) sees it, so the tool's answer is what is tested, not the propagation
        with zenoh.open(zenoh_config(endpoint)) as other:
            deadline = time.monotonic() + 10
            while not any(r.ok is not None for r in
                          other.liveliness().get(f"{ROOT}/alive/ghost", timeout=0.5)):
                assert time.monotonic() < deadline, "ghost token never reached the router"
                time.sleep(0.05)
        run = tool(endpoint, "status", "--json")
        table = tool(endpoint, "status")
    finally:
        ghost.undeclare()
    assert run.returncode == 0, run.stderr
    rows = {r["service"]: r for r in json.loads(run.stdout)}  # one document
    assert set(rows) == {*SERVICE_NAMES, "ghost"}
    assert rows["ghost"]["state"] == "no reply" and rows["ghost"]["answered"] is False
    for name in SERVICE_NAMES:
        r = rows[name]
        assert r["state"] == "ok" and r["alive"] and r["answered"]
        for field in ("received", "published", "dropped", "rejected", "failed", "pid"):
            assert type(r[field]) is int, (name, field)
        assert type(r["busy_s"]) is float and r["busy_s"] >= 0, name
        assert {"last_error", "p50_ms", "p99_ms", "params", "extra"} <= r.keys()
    assert rows["motion_estimation"]["published"] > 0
    assert rows["motion_estimation"]["params"]["params_id"] >= 1
    assert table.returncode == 0 and table.stdout.startswith("SERVICE")
    assert all(name in table.stdout for name in SERVICE_NAMES)
    assert "no reply" in table.stdout


def test_services_run_by_hand_run_numeric_libraries_on_one_thread(pipeline, endpoint):
    """Each service's log says how many threads each numeric library it loaded has: one,
    also when the shell asks for more (numpy's OpenBLAS busy-waited a core away)."""
    extra = Proc(["fuzzy-controller", "-e", endpoint, NS, "--robot", "threads"],
                 env={"OPENBLAS_NUM_THREADS": "2", "OMP_NUM_THREADS": "2",
                      "MKL_NUM_THREADS": "2"})
    try:
        lines = {name: proc.wait_for("numeric thread pools: ", 30)
                 for name, proc in {**pipeline, "extra": extra}.items()}
    finally:
        extra.stop()
    for name, line in lines.items():
        pools = re.search(r"numeric thread pools: (.*); opencv (\d+)$", line)
        assert pools, line
        threads = re.findall(r" (\d+) \(", pools[1])  # "openblas 1 (libscipy_openblas), ..."
        assert "openblas" in pools[1] and set(threads) == {"1"} and pools[2] == "1", (name, line)


# -- params --------------------------------------------------------------------------------

def test_params_set_reaches_motion_estimation(pipeline, endpoint, session):
    consumers = ("preprocessing", "motion_estimation", "auto_tuner")
    before = {s: status_of(session, s) for s in consumers}
    with collecting(session, f"{ROOT}/motion/estimate") as est:
        _params_set_and_get(endpoint, est)
    # the user's tuner/params come from another publisher than the tuner's, with a seq of
    # its own (a clock): counted as ~1.8e15 dropped messages before seq gaps were counted
    # per publisher. Frames overwritten at the latest-only inputs meanwhile are all there is.
    for s in consumers:
        after = status_of(session, s)
        frames = after["received"] - before[s]["received"]
        assert 0 <= after["dropped"] - before[s]["dropped"] <= frames, s


@contextmanager
def stand_in_motion_estimation(session: zenoh.Session, keys: Keys, state: dict,
                               on_params: Callable[[zenoh.Sample], None]) -> Iterator[None]:
    """A motion-estimation of robot ``keys.robot`` that the params tool sees: alive, its
    status the map ``state`` (read at each query), ``on_params`` called on each set."""
    def on_status(query: zenoh.Query) -> None:
        query.reply(query.key_expr, pack({"service": "motion_estimation", **state}))

    token = session.liveliness().declare_token(keys.alive("motion_estimation"))
    queryable = session.declare_queryable(keys.status("motion_estimation"), on_status)
    sub = session.declare_subscriber(keys.params, on_params)
    try:
        yield
    finally:
        sub.undeclare()
        queryable.undeclare()
        token.undeclare()


def test_params_set_is_not_confirmed_by_another_set_with_its_id(endpoint, session):
    """The tool takes the id after the largest in force; if the tuner takes the same id first
    (its initial tuning, finishing meanwhile), motion-estimation runs that id with the tuner's
    values and refuses the user's as stale. Confirming by the id alone then reported the user's
    set as in force (seen in the multi-host test); it must say that another set took the id,
    whose, and its values (concurrent params sets took one id in a fault test). A stand-in
    motion-estimation (robot "race") answers its status with params_id 2, then, once the set
    arrives, with the tuner's params_id 3."""
    keys = Keys("race")
    tuner = {"params_id": 3, "source": "tuner", "reason": "initial tuning",
             **TrackerParams(search_size=12, corr_size=5).factors()}
    state = {"params": {**tuner, "params_id": 2}}

    with stand_in_motion_estimation(session, keys, state,
                                    lambda _: state.update(params=tuner)):
        run = tool(endpoint, "params", "set", "search_size=19", "--timeout", "3",
                   "--robot", "race")
    assert run.returncode == 1, run.stdout + run.stderr
    assert run.stderr.count("\n") == 1
    # said as soon as it is seen, with the values that took the id (it used to wait for the
    # timeout and say only "did not confirm ... the set may have been lost")
    assert "params_id 3 was taken first by another set from tuner (initial tuning)" in \
        run.stderr
    assert "search_size=12 corr_size=5" in run.stderr and run.stderr.endswith("set again\n")


def test_params_set_waits_for_a_motion_estimation_that_is_restarting(endpoint, session):
    """A set given while motion-estimation restarts (a second, under the launcher) failed at
    once, "does not answer", though --timeout was 10 s. The tool now asks again until it
    answers: a stand-in motion-estimation (robot "late") appears 1.5 s after the tool
    started, takes the set and confirms it."""
    keys = Keys("late")
    state = {"params": {"params_id": 1, "source": "tuner", "reason": "initial tuning",
                        **TrackerParams().factors()}}

    def take(sample: zenoh.Sample) -> None:
        msg = Params.decode(sample.payload.to_bytes())
        state["params"] = {"params_id": msg.params_id, "source": msg.source,
                           "reason": msg.reason, **msg.tracker_params(TrackerParams()).factors()}

    done: dict = {}
    runner = threading.Thread(target=lambda: done.update(run=tool(
        endpoint, "params", "set", "search_size=19", "--timeout", "10", "--robot", "late")))
    runner.start()
    time.sleep(1.5)
    with stand_in_motion_estimation(session, keys, state, take):
        runner.join(30)
    run = done["run"]
    assert run.returncode == 0, run.stdout + run.stderr
    assert run.stdout.startswith("params_id 2 in force on motion_estimation: ") and \
        "search_size=19" in run.stdout, run.stdout


def test_params_set_waits_for_a_set_accepted_pending_its_kernels(endpoint, session):
    """Windows whose kernels motion-estimation has not loaded (a 64 px window's int64 sums)
    stay pending while they are made ready, up to half a minute on a new machine; the tool
    gave up after its timeout, saying the set "may have been lost". It now says it waits, and
    confirms the set once in force. A stand-in motion-estimation (robot "slow") answers its
    status with the set pending for 2.5 s, past the tool's 1 s timeout, then in force."""
    keys = Keys("slow")
    before = {"params_id": 4, "source": "flags", "reason": "start-up",
              **TrackerParams().factors()}
    state: dict = {"params": before, "extra": {}}

    def on_params(sample: zenoh.Sample) -> None:
        msg = Params.decode(sample.payload.to_bytes())
        if state["extra"].get("params_pending") != msg.params_id \
                and state["params"]["params_id"] < msg.params_id:
            state["extra"] = {"params_pending": msg.params_id}
            threading.Timer(2.5, lambda: state.update(extra={}, params={
                "params_id": msg.params_id, "source": msg.source, "reason": msg.reason,
                **msg.tracker_params(TrackerParams()).factors()})).start()

    with stand_in_motion_estimation(session, keys, state, on_params):
        run = tool(endpoint, "params", "set", "corr_size=64", "--timeout", "1",
                   "--robot", "slow")
    assert run.returncode == 0, run.stdout + run.stderr
    assert "params_id 5 accepted by motion_estimation, not yet in force" in run.stderr
    assert run.stdout.startswith("params_id 5 in force on motion_estimation")
    assert "corr_size=64" in run.stdout


def test_params_set_says_at_once_that_a_set_was_dropped(endpoint, session):
    """A set whose kernels cannot be made ready is dropped, and its repeats are refused in
    silence: the tool waited for its timeout and said the set "may have been lost". It now
    says at once that motion-estimation dropped it, and why. A stand-in motion-estimation
    (robot "broken") answers its status, once the set arrives, with the service's error."""
    keys = Keys("broken")
    before = {"params_id": 4, "source": "flags", "reason": "start-up",
              **TrackerParams().factors()}
    state: dict = {"params": before, "extra": {}, "last_error": ""}

    def on_params(sample: zenoh.Sample) -> None:
        msg = Params.decode(sample.payload.to_bytes())
        state["last_error"] = (f"params_id {msg.params_id}: its kernels could not be made "
                               "ready (RuntimeError: the compiler failed); keeping params_id 4")

    with stand_in_motion_estimation(session, keys, state, on_params):
        t0 = time.monotonic()
        run = tool(endpoint, "params", "set", "corr_size=64", "--timeout", "20",
                   "--robot", "broken")
        took = time.monotonic() - t0
    assert run.returncode == 1, run.stdout + run.stderr
    assert run.stderr.count("\n") == 1
    assert "motion_estimation dropped the set: params_id 5: its kernels could not be made " \
        "ready (RuntimeError: the compiler failed)" in run.stderr
    assert took < 15  # said when seen, not after the 20 s timeout


def _params_set_and_get(endpoint: str, est: Collector) -> None:
    run = tool(endpoint, "params", "set", "search_size=21", "corr_size=11", "--json")
    assert run.returncode == 0, run.stderr
    (result,) = json_lines(run.stdout)
    new_id = result["params_id"]
    assert result["service"] == "motion_estimation" and result["source"] == "user"
    assert (result["search_size"], result["corr_size"]) == (21, 11)
    # the estimates computed with the new parameters say so
    est.wait(lambda items: any(msgpack.unpackb(p)["params_id"] == new_id for _, p in items))
    got = {r["service"]: r for r in json_lines(tool(endpoint, "params", "get", "--json").stdout)}
    assert {"motion_estimation", "preprocessing", "auto_tuner"} <= got.keys()
    me = got["motion_estimation"]
    assert (me["params_id"], me["search_size"], me["corr_size"]) == (new_id, 21, 11)
    assert (me["source"], me["reason"]) == ("user", "set by user")
    text = tool(endpoint, "params", "get")
    assert text.stdout.startswith("SERVICE") and "set by user" in text.stdout

    # invalid sets: one line naming the field and the range, exit 2, nothing changes
    bad_range = tool(endpoint, "params", "set", "search_size=500")
    assert bad_range.returncode == 2
    assert bad_range.stderr.count("\n") == 1
    assert bad_range.stderr.startswith("vistrack params: error:")
    assert "search_size" in bad_range.stderr and "2..128" in bad_range.stderr
    unknown = tool(endpoint, "params", "set", "search_sise=21")
    assert unknown.returncode == 2 and unknown.stderr.count("\n") == 1
    assert "search_sise" in unknown.stderr and "search_size (2..128)" in unknown.stderr
    start = len(est.items)
    est.wait(lambda items: len(items) >= start + 5)
    assert {e["params_id"] for e in estimates_since(est, start)} == {new_id}


# -- malformed input -----------------------------------------------------------------------

# services that decode each input key (and so count what they reject)
# (the auto-tuner runs --no-tune here: it takes no frame, so the frames are preprocessing's
# alone; test_autotune_live sends them to a tuner that takes them)
CONSUMERS = {"camera/frame": ("preprocessing",),
             "preprocessing/frame": ("motion_estimation",),
             "tuner/params": ("preprocessing", "motion_estimation", "auto_tuner"),
             "motion/estimate": ("fuzzy_controller",)}


def test_malformed_input_is_rejected_counted_and_survived(pipeline, endpoint, session):
    rejected = {s: status_of(session, s)["rejected"] for s in SERVICE_NAMES}
    sent = dict.fromkeys(SERVICE_NAMES, 0)
    for suffix, consumers in CONSUMERS.items():
        for name, payload in malformed(suffix).items():
            before = {s: status_of(session, s)["rejected"] for s in consumers}
            # a latest-only input may be overwritten by a good frame before it is read:
            # publish again until every consumer has counted one more rejection
            deadline = time.monotonic() + 15
            while True:
                session.put(f"{ROOT}/{suffix}", payload,
                            congestion_control=zenoh.CongestionControl.BLOCK)
                wait_deadline = time.monotonic() + 1.0
                done = False
                while not done and time.monotonic() < wait_deadline:
                    done = all(status_of(session, s)["rejected"] > before[s] for s in consumers)
                    time.sleep(0.01)
                if done:
                    break
                assert time.monotonic() < deadline, f"{suffix} {name}: not counted"
            for s in consumers:
                sent[s] += 1
    for name, proc in pipeline.items():
        assert proc.p.poll() is None, f"{name} died:\n" + "\n".join(proc.lines[-20:])
    # good frames are still processed
    with collecting(session, f"{ROOT}/motion/estimate") as est:
        est.wait(lambda items: len(items) >= 5, timeout=20)
    status = {r["service"]: r for r in json.loads(tool(endpoint, "status", "--json").stdout)}
    for s, n in sent.items():
        assert status[s]["state"] == "ok"
        assert status[s]["rejected"] >= rejected[s] + n, s
    assert status["motion_estimation"]["last_error"]


def test_params_out_of_range_while_frames_flow(pipeline, session):
    """A tuner/params of the right shape, newer than what is in force, with a value out of
    range: every consumer refuses and counts it, keeps its parameters, and estimates go on."""
    consumers = ("preprocessing", "motion_estimation", "auto_tuner")
    before = {s: status_of(session, s) for s in consumers}
    payload = msgpack.packb({**GOOD["tuner/params"], "params_id": 10**6, "search_size": 500})
    session.put(f"{ROOT}/tuner/params", payload,
                congestion_control=zenoh.CongestionControl.BLOCK)
    wait_until(lambda: all(status_of(session, s)["rejected"] > before[s]["rejected"]
                           for s in consumers), 10, "every consumer counted the refusal")
    with collecting(session, f"{ROOT}/motion/estimate") as est:
        est.wait(lambda items: len(items) >= 5, timeout=20)
    for s in consumers:
        after = status_of(session, s)
        assert after["params"] == before[s]["params"], s
        assert "search_size=500 is out of range: allowed 2..128" in after["last_error"], s
    in_force = before["motion_estimation"]["params"]["params_id"]
    assert {m["params_id"] for m in map(msgpack.unpackb, (p for _, p in est.items))} \
        == {in_force}


def send_frame_until(session: zenoh.Session, frame: dict, done: Callable[[], bool],
                     what: str) -> None:
    """Publish ``frame`` (stamped now) until ``done()``: a latest-only input may be
    overwritten by a camera frame before it is read."""
    deadline = time.monotonic() + 15
    while not done():
        assert time.monotonic() < deadline, what
        session.put(f"{ROOT}/camera/frame", msgpack.packb({**frame, "stamp_ns": time.time_ns()}))
        time.sleep(0.1)


def test_a_frame_of_another_size_restarts_the_track_and_estimates_go_on(pipeline, session):
    small = {**GOOD["camera/frame"], "seq": 10**6, "data": bytes(range(256)) * 12}
    with collecting(session, f"{ROOT}/motion/estimate") as est:
        send_frame_until(session, small, lambda: any(msgpack.unpackb(p)["seq"] == 10**6
                                                     for _, p in est.items),
                         "no estimate of the 64x48 frame")
        start = len(est.items)
        est.wait(lambda items: len(items) >= start + 5, timeout=20)
    got = [msgpack.unpackb(p) for _, p in est.items]
    odd = next(i for i, m in enumerate(got) if m["seq"] == 10**6)
    assert got[odd]["first"]  # a new track for the new size
    assert any(m["first"] for m in got[odd + 1:])  # and again for the camera's own size
    for name, proc in pipeline.items():
        assert proc.p.poll() is None, f"{name} died"


def test_a_featureless_8x8_frame_costs_one_input_not_a_service(pipeline, session):
    """Issue 13: 8x8 zero bytes, a frame a starting camera could send, passed pre-processing
    and gave motion-estimation an estimate with xc = NaN, which its own validation refused: an
    uncaught exception ended the process. Now it is answered with an estimate that says it
    has no feature, nothing fails or ends, and estimates go on."""
    seq = 10**6 + 13
    black = {**GOOD["camera/frame"], "seq": seq, "width": 8, "height": 8, "data": bytes(64)}
    before = status_of(session, "motion_estimation")
    with collecting(session, f"{ROOT}/motion/estimate") as est:
        send_frame_until(session, black, lambda: any(msgpack.unpackb(p)["seq"] == seq
                                                     for _, p in est.items),
                         "no estimate of the 8x8 frame")
        start = len(est.items)
        est.wait(lambda items: len(items) >= start + 5, timeout=20)
    answer = next(m for m in map(msgpack.unpackb, (p for _, p in est.items)) if m["seq"] == seq)
    assert answer["npi"] == 0 and answer["valid"] is False and math.isfinite(answer["xc"])
    after = status_of(session, "motion_estimation")
    assert after["pid"] == before["pid"] and after["failed"] == before["failed"]
    for name, proc in pipeline.items():
        assert proc.p.poll() is None, f"{name} died:\n" + "\n".join(proc.lines[-20:])


def test_an_estimate_from_the_future_is_refused_and_commands_go_on(pipeline, session):
    before = status_of(session, "fuzzy_controller")["rejected"]
    future = {**GOOD["motion/estimate"], "npi": 50, "stamp_ns": time.time_ns() + 3600 * 10**9}
    with collecting(session, f"{ROOT}/control/cmd_vel") as cmd:
        deadline = time.monotonic() + 15
        while status_of(session, "fuzzy_controller")["rejected"] == before:
            assert time.monotonic() < deadline, "the future estimate was not refused"
            session.put(f"{ROOT}/motion/estimate", msgpack.packb(future))
            time.sleep(0.1)
        start = len(cmd.items)
        cmd.wait(lambda items: len(items) >= start + 5, timeout=20)
    assert "ahead of this host's clock" in status_of(session, "fuzzy_controller")["last_error"]
    later = [msgpack.unpackb(p) for _, p in cmd.items[start:]]
    assert all(c["stamp_ns"] < future["stamp_ns"] for c in later)
    assert not all(c["stale"] for c in later)  # the camera's estimates still drive the robot


def test_the_simulator_refuses_bad_velocity_commands(pipeline, endpoint, session):
    """NaN, infinite or wrong-type commands on control/cmd_vel are refused and counted by a
    simulator camera, which keeps rendering; a huge finite one is held to the robot's limits."""
    robot = "simbad"
    cam = Proc(["camera", "-e", endpoint, NS, "--robot", robot, "--source", "sim",
                "--fps", "30", "--loop"])
    try:
        cam.wait_for("ready", timeout=60)
        key = f"vistrack/{robot}/control/cmd_vel"
        good = {"v": 1, "seq": 1, "stamp_ns": 1, "vx": 0.0, "vy": 0.0, "wz": 0.0,
                "stale": False}
        rejected = 0
        for bad in ({"vx": float("nan")}, {"wz": float("inf")}, {"vy": "fast"}):
            deadline = time.monotonic() + 15
            while status_of_robot(session, robot, "camera")["rejected"] == rejected:
                assert time.monotonic() < deadline, f"{bad} was not refused"
                session.put(key, msgpack.packb({**good, **bad}))
                time.sleep(0.05)
            rejected = status_of_robot(session, robot, "camera")["rejected"]
        assert "control/cmd_vel: field" in status_of_robot(session, robot, "camera")["last_error"]
        with collecting(session, f"vistrack/{robot}/sim/pose") as pose:
            for _ in range(10):
                session.put(key, msgpack.packb({**good, "vx": 1e308, "vy": 1e308, "wz": 1e308}))
                time.sleep(0.05)
            pose.wait(lambda items: len(items) >= 20, timeout=10)
        last = msgpack.unpackb(pose.items[-1][1])
        assert all(abs(last[k]) < 10 for k in ("x", "y", "theta")), last
        assert cam.p.poll() is None, "\n".join(cam.lines[-20:])
    finally:
        cam.stop()


def test_a_looping_file_camera_plays_a_video_cut_short_again(endpoint, session, cut_video):
    """A recording that lost its end (its header announces 10 frames, a few decode) looped by a
    file camera: the frames it holds are published again and again, in order, with a
    warning that names the shortfall; it was refused at start (exit 2), none of them sent."""
    cut, held = cut_video
    robot = "cutshort"
    with collecting(session, f"vistrack/{robot}/camera/frame") as frames:
        cam = Proc(["camera", "-e", endpoint, NS, "--robot", robot, "--source",
                    f"file:{cut}", "--fps", "50", "--loop"])
        try:
            line = cam.wait_for("warning", timeout=60).rstrip("\n")
            assert line == (f"vistrack camera: warning: {cut}: the video ends after "
                            f"{len(held)} of the 10 frames its header announces (cut short or "
                            f"damaged); looping the {len(held)} frames it holds")
            got = frames.wait(lambda items: len(items) >= 3 * len(held) + 1, timeout=60)
            assert cam.p.poll() is None, "\n".join(cam.lines[-20:])
        finally:
            cam.stop()
    data = [msgpack.unpackb(payload)["data"] for _, payload in got]
    assert len({bytes(d) for d in data}) == len(held)  # only the frames the file holds
    seqs = [msgpack.unpackb(payload)["seq"] for _, payload in got]
    first = seqs[0]
    for k, d in enumerate(data):  # in the file's order, pass after pass
        assert d == data[(seqs[k] - first) % len(held)]


def test_a_frame_the_file_camera_leaves_out_leaves_a_gap_in_seq(endpoint, session, tmp_path):
    """A folder whose third image has another size: the camera leaves it out (a warning) and
    sends the others; the frame after it carries seq 3, not 2, so that a reader sees a frame
    is missing there, as for a drop (the tracker then predicts over two steps)."""
    import cv2
    import numpy as np

    rng = np.random.default_rng(1)
    for i in range(5):
        cv2.imwrite(str(tmp_path / f"f{i}.png"),
                    rng.integers(0, 256, (100, 100) if i == 2 else (60, 80), dtype=np.uint8))
    robot = "skipgap"
    with collecting(session, f"vistrack/{robot}/camera/frame") as frames:
        cam = Proc(["camera", "-e", endpoint, NS, "--robot", robot, "--source",
                    f"file:{tmp_path}", "--fps", "50"])
        try:
            got = frames.wait(lambda items: len(items) >= 4, timeout=60)
        finally:
            cam.stop()
    assert [msgpack.unpackb(payload)["seq"] for _, payload in got] == [0, 1, 3, 4]


def status_of_robot(session: zenoh.Session, robot: str, service: str) -> dict:
    for reply in session.get(f"vistrack/{robot}/{service}/status", timeout=2.0):
        if reply.ok is not None:
            return msgpack.unpackb(reply.ok.payload.to_bytes())
    raise AssertionError(f"{service} of {robot} did not answer its status query")


# -- record and replay ---------------------------------------------------------------------

def read_recording(path) -> tuple[dict, list[dict]]:
    """The documented file format, read with plain msgpack."""
    with open(path, "rb") as f:
        objects = list(msgpack.Unpacker(f, raw=False))
    return objects[0], objects[1:]


def test_record_then_replay_drives_a_fresh_pipeline(pipeline, endpoint, session, tmp_path):
    path = tmp_path / "frames.vtr"
    run = tool(endpoint, "record", str(path), "camera/frame", "--duration", "1.5")
    assert run.returncode == 0, run.stderr
    header, records = read_recording(path)
    assert header["format"] == "vistrack-record" and header["version"] == 1
    assert header["robot"] == "robot" and header["keys"] == [f"{ROOT}/camera/frame"]
    assert len(records) >= 10
    assert all(r["key"] == f"{ROOT}/camera/frame" for r in records)
    stamps = [r["t_ns"] for r in records]
    assert stamps == sorted(stamps) and stamps[0] >= header["start_ns"]
    check_contract("camera/frame", msgpack.unpackb(records[0]["payload"]))

    # a fresh pipeline for another robot id on the same router, driven by the recording
    fresh = {"preprocessing": ["--robot", "replayed"], "motion-estimation": ["--robot",
                                                                            "replayed"]}
    with services(endpoint, names=("preprocessing", "motion-estimation"), extra=fresh), \
            collecting(session, "vistrack/replayed/motion/estimate") as est:
        wait_for_subscribers(session, ["vistrack/replayed/camera/frame",
                                       "vistrack/replayed/preprocessing/frame"], 30)
        replay = tool(endpoint, "replay", str(path), "--fast", "--remap-robot", "replayed")
        assert replay.returncode == 0, replay.stderr
        items = est.wait(lambda items: len(items) >= 1, timeout=20)
    check_contract("motion/estimate", msgpack.unpackb(items[0][1]))

    # a file cut short: what is valid is replayed, then a warning and a one-line error
    cut = tmp_path / "cut.vtr"
    data = path.read_bytes()
    cut.write_bytes(data[:len(data) // 2])
    bad = tool(endpoint, "replay", str(cut), "--fast", "--remap-robot", "nobody",
               "--wait", "0")
    assert bad.returncode == 2
    warning, error = bad.stderr.splitlines()
    assert "warning" in warning and "valid samples" in warning
    assert error.startswith("vistrack replay: error:") and str(cut) in error
    assert "byte offset" in error
    junk = tmp_path / "junk.vtr"
    junk.write_bytes(b"\x93\x01\x02\x03 not a recording")
    bad = tool(endpoint, "replay", str(junk))
    assert bad.returncode == 2 and "byte offset 0" in bad.stderr and str(junk) in bad.stderr


def test_record_stops_and_flushes_on_ctrl_c(pipeline, endpoint, tmp_path):
    path = tmp_path / "all.vtr"
    with subprocess.Popen([sys.executable, "-m", "vistrack.services.cli", "record", str(path),
                           "-e", endpoint, "--no-multicast-scouting"], stdout=subprocess.PIPE,
                          stderr=subprocess.PIPE, text=True) as rec:
        try:
            # the file is flushed every second: wait for estimates in it, then interrupt
            wait_until(lambda: path.exists() and path.stat().st_size > 300_000, 20,
                       "samples in the recording")
        finally:
            rec.send_signal(signal.SIGINT)
            _, err = rec.communicate(timeout=10)
    assert rec.returncode == 0, err
    header, records = read_recording(path)  # complete: the last record is whole
    assert header["keys"] == [f"{ROOT}/**"]
    keys = {r["key"] for r in records}
    assert {f"{ROOT}/camera/frame", f"{ROOT}/motion/estimate"} <= keys
    assert f"{len(records)} samples" in err


def test_record_writes_a_sample_sent_again_once(pipeline, endpoint, session, tmp_path):
    """A sample whose bytes equal the last one of its key (a frame a camera in lockstep sent
    again when its estimate did not come back in time) is written once, and said so; the same
    bytes after another sample are a new sample, written."""
    path = tmp_path / "again.vtr"
    key = f"{ROOT}/test/again"
    with subprocess.Popen([sys.executable, "-m", "vistrack.services.cli", "record", str(path),
                           "test/again", "-e", endpoint, "--no-multicast-scouting"],
                          stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as rec:
        try:
            wait_for_subscribers(session, [key], 30)
            for payload in (b"frame 7", b"frame 7", b"frame 8", b"frame 7"):
                session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)
                time.sleep(0.05)
            time.sleep(0.5)
        finally:
            rec.send_signal(signal.SIGINT)
            _, err = rec.communicate(timeout=10)
    assert rec.returncode == 0, err
    _, records = read_recording(path)
    assert [r["payload"] for r in records] == [b"frame 7", b"frame 8", b"frame 7"]
    assert "3 samples of 1 key in" in err
    assert "; 1 sample sent again by its publisher (the same bytes) written once" in err
