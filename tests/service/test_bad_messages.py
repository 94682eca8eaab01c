"""Messages of the right shape but bad content, fed to the service code in-process through
the MemoryNode seam: each is refused, counted and logged, what was in force stays, and the
service goes on (the malformed ones are in tests/integration/test_tools.py)."""

from __future__ import annotations

import logging
import threading
import time

import msgpack
import numpy as np
import pytest

from vistrack.common.bus import MemoryNode
from vistrack.common.messages import (
    MAX_PARAMS_ID,
    CmdVel,
    Estimate,
    Frame,
    MessageError,
    Params,
    encode_frame,
    next_params_id,
)
from vistrack.common.params import TrackerParams
from vistrack.services import cli
from vistrack.services.runtime import ParamsInForce

log = logging.getLogger("test")


def parse(command: str, *argv: str):
    return cli.build_parser(command).parse_args([command, *argv])


def params_payload(params_id: int, **factors) -> bytes:
    """A tuner/params built with plain msgpack, so out-of-range values get through."""
    return msgpack.packb({"v": 1, "seq": 1, "stamp_ns": 1, "max_features": 100,
                          "thres_percent": 2.0, "search_size": 15, "corr_size": 9,
                          "ungroup_size": 5, "params_id": params_id, "source": "user",
                          "reason": "test", **factors})


def wait_for(condition, timeout=5.0, what="condition"):
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.002)


@pytest.mark.parametrize(("factor", "value", "problem"), [
    ("search_size", 500, "search_size=500 is out of range: allowed 2..128"),
    ("thres_percent", 0.0, "thres_percent=0.0 is out of range: allowed 0.1..5.0"),
    ("corr_size", 1, "corr_size=1 is out of range: allowed 2..64"),
])
def test_params_out_of_range_are_refused_and_the_old_ones_stay(factor, value, problem):
    with MemoryNode("preprocessing") as node:
        state = ParamsInForce(TrackerParams(), params_id=3)
        assert not state.apply(params_payload(4, **{factor: value}), node, log)
        assert (state.params, state.params_id) == (TrackerParams(), 3)
        assert node.status.rejected == 1
        assert node.status.last_error == f"tuner/params: field '{factor}': {problem}"
        # the next good set is applied as usual
        assert state.apply(params_payload(4, search_size=21), node, log)
        assert (state.params.search_size, state.params_id) == (21, 4)


def test_a_flood_of_bad_or_stale_params_is_said_once_and_counted_whole(caplog):
    """200 sets out of range, 100 stale ones, then 50 with a different bad `source` each,
    from a peer: one line each kind (a line each was 400 lines from preprocessing and
    motion-estimation; a kind was the line's text, which quotes the value), every one
    counted."""
    with MemoryNode("preprocessing") as node, caplog.at_level(logging.INFO, logger="test"):
        state = ParamsInForce(TrackerParams(), params_id=3)
        for _ in range(200):
            assert not state.apply(params_payload(4, search_size=999), node, log)
        for _ in range(100):
            assert not state.apply(params_payload(2, search_size=21), node, log)
        for k in range(50):  # the text quotes the value: each a different line of one kind
            assert not state.apply(params_payload(4, source=f"s{chr(97 + k % 26) * k}"),
                                   node, log)
        assert node.status.rejected == 350 and (state.params, state.params_id) == \
            (TrackerParams(), 3)
        assert state.apply(params_payload(4, search_size=21), node, log)  # a good one after
    said = [(r.levelno, r.getMessage()) for r in caplog.records]
    assert said[:3] == [
        (logging.ERROR, "rejected tuner/params: tuner/params: field 'search_size': "
                        "search_size=999 is out of range: allowed 2..128; keeping params_id 3"),
        (logging.WARNING, "ignored tuner/params with params_id 2: 3 is in force"),
        (logging.ERROR, "rejected tuner/params: tuner/params: field 'source' must be one of "
                        "'tuner', 'user', got 's'; keeping params_id 3")]
    assert not [m for _, m in said[3:] if "rejected" in m or "ignored" in m]


def test_a_params_id_beyond_the_largest_is_refused():
    """2**64 - 1 was accepted, and "one above the largest" could then not be encoded: the
    params tool died with a traceback and a tuning would have killed the auto-tuner."""
    with MemoryNode("motion_estimation") as node:
        state = ParamsInForce(TrackerParams(), params_id=3)
        assert not state.apply(params_payload(MAX_PARAMS_ID + 1, search_size=21), node, log)
        assert state.params_id == 3 and node.status.rejected == 1
        assert "'params_id' must be in 0..9007199254740991" in node.status.last_error
        assert state.apply(params_payload(MAX_PARAMS_ID, search_size=21), node, log)
    assert next_params_id(MAX_PARAMS_ID - 1) == MAX_PARAMS_ID
    with pytest.raises(MessageError, match="largest a message may carry"):
        next_params_id(MAX_PARAMS_ID)
    with pytest.raises(MessageError, match="params_id"):
        Params.from_tracker_params(TrackerParams(), seq=0, stamp_ns=0,
                                   params_id=MAX_PARAMS_ID + 1, source="user")


def test_an_update_is_judged_against_the_pending_one_while_one_waits():
    """While an accepted update waits for its kernels (motion-estimation), the tuner's
    reminder of it is neither applied again nor counted as stale; an older one is stale
    against it (it would undo the newer) and a newer one supersedes it. Nothing is in force
    until committed."""
    with MemoryNode("motion_estimation") as node:
        state = ParamsInForce(TrackerParams(), params_id=3)
        pending = state.accept(params_payload(5, corr_size=64), node, log)
        assert pending is not None and (pending.params_id, pending.params.corr_size) == (5, 64)
        assert (state.params, state.params_id) == (TrackerParams(), 3)  # not yet in force
        assert state.accept(params_payload(5, corr_size=64), node, log, pending) is None
        assert node.status.rejected == 0  # a reminder is not stale
        assert state.accept(params_payload(4, corr_size=21), node, log, pending) is None
        assert node.status.rejected == 1
        assert node.status.last_error == "stale params_id 4 <= 5"
        newer = state.accept(params_payload(6, corr_size=21), node, log, pending)
        assert newer is not None and newer.params.corr_size == 21
        state.commit(newer, node, log)
        assert (state.params.corr_size, state.params_id) == (21, 6)
        assert node.status.params["params_id"] == 6


def test_the_tuner_at_the_largest_params_id_keeps_what_is_in_force():
    from vistrack.services.auto_tuner.service import AutoTuner, check_flags

    args = parse("auto-tuner", "--no-tune")
    with MemoryNode("auto_tuner") as node:
        tuner = AutoTuner(node, args, check_flags(args))
        tuner.seen_id = MAX_PARAMS_ID  # an estimate carried the largest id
        assert not tuner.announce("scene change")
        assert node.published_on(node.keys.params) == []
        assert tuner.state.params_id == 0
        assert "largest a message may carry" in node.status.last_error
        # its own set (id 0) is older than the one the estimates run: not reminded of
        assert tuner.announce()
        assert node.published_on(node.keys.params) == []


def _tuner_asking(node, in_force: dict, asked: list):
    """An auto-tuner (``--no-tune``) whose motion-estimation runs ``in_force``, each ask
    appended to ``asked``, having announced its flags' set as params_id 1."""
    from vistrack.services.auto_tuner.service import AutoTuner, check_flags

    def ask():
        asked.append(1)
        return in_force

    args = parse("auto-tuner", "--no-tune")
    tuner = AutoTuner(node, args, check_flags(args), ask_in_force=ask)
    assert tuner.announce("start-up (flags)")  # params_id 1, from its flags
    return tuner


@pytest.mark.parametrize("runs", [1, 3])
def test_a_params_id_only_an_estimate_claims_does_not_stop_the_tuner(caplog, runs):
    """One estimate with params_id 2^53 - 1 from any client (a forged one, a recording's
    replayed beside the pipeline) stopped the tuner's reminders for good (a restarted
    motion-estimation then stayed on its flags) and left no id for its next tuning. Asked,
    motion-estimation runs params_id ``runs``: that one counts, taken on where it is newer
    than the tuner's (3), the claim dropped where it is not (1); said once either way."""
    in_force = {"max_features": 70, "thres_percent": 2.0, "search_size": 15, "corr_size": 9,
                "ungroup_size": 5, "params_id": runs, "source": "user", "reason": "by hand"}
    asked: list = []
    with MemoryNode("auto_tuner") as node, caplog.at_level(logging.INFO,
                                                            logger="vistrack.auto_tuner"):
        tuner = _tuner_asking(node, in_force, asked)
        tuner.seen_id = MAX_PARAMS_ID  # an estimate claimed it
        for _ in range(3):
            assert tuner.announce()
        assert tuner.announce("scene change")
        sent = [Params.decode(p) for p in node.published_on(node.keys.params)]
    assert [m.params_id for m in sent] == [1, runs, runs, runs, runs + 1]
    assert sent[1].max_features == (70 if runs == 3 else TrackerParams().max_features)
    assert len(asked) == 1 and not node.status.last_error
    said = [r.getMessage() for r in caplog.records if "estimates carried" in r.getMessage()]
    assert said == [f"estimates carried params_id {MAX_PARAMS_ID}, but the tracker's stages run "
                    f"{runs}: " + ("taking on 3" if runs == 3 else
                                   "not taken, this tuner's 1 stays in force")
                    + " (a recording's estimates replayed beside this pipeline, or a forged "
                      "one?)"]


def test_a_restarted_tuner_takes_on_the_set_motion_estimation_runs(caplog):
    """A tuner restarted after a user's set (params_id 5: max_features 50, thres_percent 3,
    ungroup_size 8) knew only its flags' values: it reminded no one, a service restarted
    after it ran its flags, and its next tuning published its flags' max_features,
    thres_percent and ungroup_size with its windows: the user's set was gone. It now takes
    on the set motion-estimation runs (its status's params) where that is the newest the
    estimates carry, reminds of it, and tunes from it; asked once per set."""
    asked: list = []
    in_force = {"max_features": 50, "thres_percent": 3.0, "search_size": 15, "corr_size": 9,
                "ungroup_size": 8, "params_id": 5, "source": "user", "reason": "by hand"}
    with MemoryNode("auto_tuner") as node, caplog.at_level(logging.INFO,
                                                            logger="vistrack.auto_tuner"):
        tuner = _tuner_asking(node, in_force, asked)
        tuner.seen_id = 5  # the estimates run the user's set
        for _ in range(3):
            assert tuner.announce()
        sent = [Params.decode(p) for p in node.published_on(node.keys.params)]
        assert [m.params_id for m in sent] == [1, 5, 5, 5] and len(asked) == 1
        reminder = sent[-1]
        assert (reminder.max_features, reminder.thres_percent, reminder.ungroup_size,
                reminder.source) == (50, 3.0, 8, "user")
        assert any("took on params_id 5 from the tracker's stages (user, by hand)" in
                   r.getMessage()
                   for r in caplog.records)
        # a tuning's set keeps the user's other factors, with the windows it chose
        tuner.reason, tuner.id_at_start = "scene change", tuner.state.params_id
        tuner._finish(("ok", _report({"search_size": 21, "corr_size": 11}, [15], [9],
                                     np.ones((1, 1)), np.zeros((1, 1))),
                       {"search_size": 21, "corr_size": 11}, False), time.monotonic())
        p = tuner.state.params
        assert (p.max_features, p.thres_percent, p.ungroup_size, p.search_size,
                p.corr_size, tuner.state.params_id) == (50, 3.0, 8, 21, 11, 6)


@pytest.mark.parametrize(("runs", "announced"), [(None, (1, "tuner")), (0, (1, "tuner")),
                                                 (4, (4, "user"))])
def test_a_restarted_tuner_announces_no_stale_start_up_set(runs, announced):
    """A tuner restarted while motion-estimation runs params_id 4 announced its flags as
    params_id 1, refused as stale by every service (a warning and a rejection each); it now
    takes on the set in force at its start. A first start (no set yet, or no answer)
    announces the flags' set as 1."""
    from vistrack.services.auto_tuner.service import AutoTuner, check_flags

    in_force = None if runs is None else {
        "max_features": 60, "thres_percent": 2.0, "search_size": 15, "corr_size": 9,
        "ungroup_size": 5, "params_id": runs, "source": "user", "reason": "by hand"}
    args = parse("auto-tuner", "--no-tune")
    with MemoryNode("auto_tuner") as node:
        tuner = AutoTuner(node, args, check_flags(args), ask_in_force=lambda: in_force)
        tuner.start_up()
        sent = [Params.decode(p) for p in node.published_on(node.keys.params)]
    assert [(m.params_id, m.source) for m in sent] == [announced]


def test_a_tuner_behind_the_estimates_holds_its_reminders_back(caplog):
    """The estimates run a params_id newer than the tuner's (a recording's set, replayed
    while the tuner started, which it never received): its reminders of its older set were
    refused as stale by every service, every second. It now holds them back, says so once,
    and its next tuning takes an id above the one seen; a set it receives puts reminders
    back."""
    from vistrack.services.auto_tuner.service import AutoTuner, check_flags

    args = parse("auto-tuner", "--no-tune")
    with MemoryNode("auto_tuner") as node, caplog.at_level(logging.INFO,
                                                            logger="vistrack.auto_tuner"):
        tuner = AutoTuner(node, args, check_flags(args))
        assert tuner.announce("start-up (flags)")  # params_id 1
        tuner.seen_id = 2
        for _ in range(3):
            assert tuner.announce()
        assert [Params.decode(p).params_id for p in node.published_on(node.keys.params)] == [1]
        said = [r.getMessage() for r in caplog.records if "no reminders" in r.getMessage()]
        assert said == ["params_id 2 is in force (seen in the estimates), newer than this "
                        "tuner's 1: no reminders until a tuning or a set"]
        tuner.on_params(params_payload(5, search_size=21))  # a user's set
        assert tuner.announce()
        assert Params.decode(node.published_on(node.keys.params)[-1]).params_id == 5
        tuner.seen_id = 6
        assert tuner.announce("scene change")
        assert Params.decode(node.published_on(node.keys.params)[-1]).params_id == 7


def test_a_tuning_that_cannot_be_announced_says_so_not_already_in_force(caplog):
    """A user's set at the largest params_id (in range: the services take it) leaves no newer
    id: a tuning's different optimum cannot be published, and its log line said "(already in
    force)" while the old windows ran on. It now says why it was not published and what
    to do, and what is in force stays in force."""
    from vistrack.services.auto_tuner.service import AutoTuner, check_flags

    args = parse("auto-tuner", "--no-tune")
    with MemoryNode("auto_tuner") as node:
        tuner = AutoTuner(node, args, check_flags(args))
        tuner.on_params(params_payload(MAX_PARAMS_ID, search_size=15, corr_size=9))
        assert tuner.state.params_id == MAX_PARAMS_ID
        tuner.id_at_start = MAX_PARAMS_ID
        tuner.reason = "scene change"
        with caplog.at_level(logging.INFO, logger="vistrack.auto_tuner"):
            report = {"design": [[-1, 1], [1, -1]], "factors": ["A", "B"], "order": [1, 0],
                      "responses": {"tf": [0.2, 0.3]}, "effects": {"tf": {"1": 0.1}},
                      "significant": {"tf": {"99": ["1"], "95": ["1"]}},
                      "optimum": {"search_size": 11, "corr_size": 5},
                      "sweep": {"search": [10, 12], "corr": [5, 7]}}
            tuner._finish(("ok", report, {"search_size": 11, "corr_size": 5}, False),
                          time.monotonic())
        assert (tuner.state.params.search_size, tuner.state.params.corr_size) == (15, 9)
        done = [r.getMessage() for r in caplog.records if "done in" in r.getMessage()]
        assert len(done) == 1 and "already in force" not in done[0], done
        assert "not published: params_id 9007199254740991 in force is the largest" in done[0]
        # the report of the tuning still goes out, saying nothing changed
        report_out = msgpack.unpackb(node.published_on(node.keys.report)[-1])
        assert report_out["changed"] is False


def test_the_tuner_takes_another_tuners_newer_params_and_reminds_of_them():
    """A recording replayed into a fresh pipeline brings a tuner's params_id 2 while the live
    tuner's is 1: the services apply 2, and the tuner used to ignore every tuner/params of
    source "tuner" and remind of 1 every second, which each service refused as stale. Now
    it takes the newer set as in force and reminds of that; its own echo and an older one
    change nothing and count as nothing."""
    from vistrack.services.auto_tuner.service import AutoTuner, check_flags

    def tuner_params(params_id: int, search_size: int) -> bytes:
        return Params.from_tracker_params(TrackerParams(search_size=search_size), seq=0,
                                          stamp_ns=1, params_id=params_id, source="tuner",
                                          reason="recorded").encode()

    args = parse("auto-tuner", "--no-tune")
    with MemoryNode("auto_tuner") as node:
        tuner = AutoTuner(node, args, check_flags(args))
        assert tuner.announce("start-up (flags)")
        own = node.published_on(node.keys.params)[-1]
        assert Params.decode(own).params_id == 1
        tuner.on_params(own)  # its own, echoed back
        tuner.on_params(tuner_params(2, 21))
        assert (tuner.state.params_id, tuner.state.params.search_size) == (2, 21)
        tuner.on_params(tuner_params(1, 31))  # an older tuner's: the services refuse it too
        assert (tuner.state.params_id, tuner.state.params.search_size) == (2, 21)
        assert node.status.rejected == 0
        assert tuner.announce()
        reminder = Params.decode(node.published_on(node.keys.params)[-1])
        assert (reminder.params_id, reminder.search_size) == (2, 21)


def test_a_tuning_changes_the_windows_and_keeps_the_rest_in_force():
    """A user's set (max_features 150, ungroup_size 7, thres_percent 3) stays in force but
    for the windows a tuning chooses: the cycle is asked to sweep at those values (not Table
    4's), and the optimum it returns changes search_size and corr_size only (before, the
    next tuning put 100 / 5 / 2.0 back). The worker is a process: a recorder of the job it
    is given stands in for it here."""
    from vistrack.services.auto_tuner.service import AutoTuner, check_flags

    class Jobs:
        ready = True

        def __init__(self) -> None:
            self.jobs: list[dict] = []

        def submit(self, job: dict) -> None:
            self.jobs.append(job)

        def poll(self) -> None:
            return None

    args = parse("auto-tuner")
    with MemoryNode("auto_tuner") as node:
        tuner = AutoTuner(node, args, check_flags(args))
        tuner.worker = jobs = Jobs()  # type: ignore[assignment]
        tuner.on_params(params_payload(4, max_features=150, thres_percent=3.0,
                                       ungroup_size=7))
        tuner.take_frames(time.monotonic())  # the initial tuning wants every frame
        rng = np.random.default_rng(0)
        for k in range(args.buffer):  # its buffer filled, the tuning is due
            tuner.on_frame(encode_frame(rng.integers(0, 256, (32, 32), dtype=np.uint8),
                                        seq=k, stamp_ns=k + 1))
        tuner.tick(time.monotonic())
        assert jobs.jobs and jobs.jobs[0]["fixed"] == {"max_features": 150,
                                                         "thres_percent": 3.0,
                                                         "ungroup_size": 7}
        report = {"design": [[-1, 1], [1, -1]], "factors": ["A", "B"], "order": [1, 0],
                  "responses": {"tf": [0.2, 0.3]}, "effects": {"tf": {"1": 0.1}},
                  "significant": {"tf": {"99": ["1"], "95": ["1"]}},
                  "optimum": {"search_size": 11, "corr_size": 5},
                  "sweep": {"search": [10, 12], "corr": [5, 7]}}
        # what the sweep at Table 4's values returned: the other factors at 100, 2.0, 5
        tuner._finish(("ok", report, {"max_features": 100, "thres_percent": 2.0,
                                      "search_size": 11, "corr_size": 5, "ungroup_size": 5},
                       False), time.monotonic())
        p = tuner.state.params
        assert (p.max_features, p.thres_percent, p.ungroup_size) == (150, 3.0, 7)
        assert (p.search_size, p.corr_size) == (11, 5)
        sent = Params.decode(node.published_on(node.keys.params)[-1])
        assert (sent.max_features, sent.search_size, sent.params_id) == (150, 11, 5)


def _report(optimum: dict, searches: list[int], corrs: list[int], tf: np.ndarray,
            ex: np.ndarray, **extra: object) -> dict:
    """A tuner/report of a sweep whose tf and ex (= ey) are given, the rest of it small."""
    return {"design": [[-1, 1], [1, -1]], "factors": ["A", "B"], "order": [1, 0],
            "responses": {"tf": [0.2, 0.3]}, "effects": {"tf": {"1": 0.1}},
            "significant": {"tf": {"99": ["1"], "95": ["1"]}}, "optimum": optimum,
            "tolerance": 0.5, **extra,
            "sweep": {"search_size": searches, "corr_size": corrs, "tf": tf.tolist(),
                      "ex": ex.tolist(), "ey": ex.tolist()}}


#: the sweeps of the keep tests: SEARCH_SIZE rows, CORR_SIZE columns (15/9 in force)
GRID = ([10, 12, 14, 16, 18, 20], [5, 7, 9, 11, 13, 15])


def _tuned(tf: np.ndarray, ex: np.ndarray, optimum: dict, index: tuple[int, int],
           within: bool):
    """A TuneResult over GRID whose tf and ex (= ey) are given and whose optimum is at
    ``index``: only the sweep's grid and responses, the optimum's and the tolerance (0.5)
    are read."""
    from vistrack.services.auto_tuner.sensitivity import Optimum, Sweep, TuneResult

    searches, corrs = GRID
    sweep = Sweep(search_sizes=tuple(searches), corr_sizes=tuple(corrs), fixed={}, t1=tf,
                  tf=tf, ex=ex, ey=ex, npi=tf, reference=None,  # type: ignore[arg-type]
                  reference_windows=(50, 30), base=TrackerParams())
    i, j = index
    best = Optimum(params=optimum, index=index, t1=1.0, tf=float(tf[i, j]), ex=float(ex[i, j]),
                   ey=float(ex[i, j]), within_tolerance=within, speedup=1.0, reason="")
    return TuneResult(run=None, analysis=None, sweep=sweep,  # type: ignore[arg-type]
                      optimum=best, tolerance=0.5, frames=30, size=(256, 256), repeats=1,
                      seconds={})


@pytest.mark.parametrize(("slower", "err", "kept"), [
    (1.05, 0.2, True), (1.25, 0.2, False), (1.05, 0.7, False)])
def test_a_tuning_keeps_windows_about_as_fast_as_its_optimum(slower, err, kept):
    """The windows in force (15/9: the sweep's 14 reads as 15) within the tolerance and at
    most 10 % slower than the optimum (10/5) in the same sweep are kept: under load the
    fastest point of a flat sweep is the noise's pick, and each retune published another
    (10/5, 12/5, 18/5, 10/5, ...). 25 % slower, or off the tolerance, the optimum is taken.
    The worker judges on its sweep (TuneResult.keeps) and the service acts on the verdict."""

    searches, corrs = GRID
    tf = np.array([[1.0 + 0.01 * (i + j) for j in range(6)] for i in range(6)])
    ex = np.full((6, 6), 0.1)
    tf[0, 0] = 1.0  # the optimum, 10/5
    tf[2, 2] = slower  # 14 (15) / 9, in force
    ex[2, 2] = err
    result = _tuned(tf, ex, {"search_size": 10, "corr_size": 5}, (0, 0), True)
    about_as_good = result.keeps(15, 9)
    assert about_as_good is kept
    assert not result.keeps(31, 15)  # not on the grid
    report = _report({"search_size": 10, "corr_size": 5}, searches, corrs, tf, ex)
    before, p, published, reports = _cycle_ends(report, {"search_size": 10, "corr_size": 5},
                                                about_as_good)
    assert (before.search_size, before.corr_size) == (15, 9)
    assert ((p.search_size, p.corr_size) == (15, 9)) is kept
    assert (published == []) is kept
    assert msgpack.unpackb(reports[-1])["changed"] is not kept


def _cycle_ends(report: dict, optimum: dict, keeps: bool):
    """An auto-tuner (--no-tune) whose scene-change cycle ends with ``report``, ``optimum``
    and the worker's verdict ``keeps``: (its params before, after, the params it published,
    the reports it published)."""
    from vistrack.services.auto_tuner.service import AutoTuner, check_flags

    args = parse("auto-tuner", "--no-tune")
    with MemoryNode("auto_tuner") as node:
        tuner = AutoTuner(node, args, check_flags(args))
        before = tuner.state.params
        tuner.reason = "scene change"
        tuner._finish(("ok", report, optimum, keeps), time.monotonic())
        return (before, tuner.state.params, node.published_on(node.keys.params),
                node.published_on(node.keys.report))


@pytest.mark.parametrize(("err", "kept"), [(4.3, True), (4.6, True), (6.0, False)])
def test_where_no_window_meets_the_tolerance_the_windows_in_force_stay_unless_far_worse(
        err, kept, caplog):
    """No swept window within the tolerance (0.5 px): the optimum is only the closest to the
    reference (ex 4.1 px). The windows in force stay where their error is within the
    tolerance of the closest's (4.3, 4.6), whatever their speed; far worse (6.0), the closest
    is taken. Published always, such choices flipped the windows from cycle to cycle on a
    scene of walkers and put slower windows as far off in force on large motion."""
    import logging


    searches, corrs = GRID
    tf = np.full((6, 6), 1.0)
    tf[2, 2] = 2.0  # in force, 15/9: twice as slow as the closest, which does not matter
    ex = np.full((6, 6), 8.0)
    ex[1, 4] = 4.1  # the closest, 12/13
    ex[2, 2] = err
    result = _tuned(tf, ex, {"search_size": 12, "corr_size": 13}, (1, 4), False)
    assert result.keeps(15, 9) is kept
    assert not result.keeps(31, 15)  # not on the grid
    report = _report({"search_size": 12, "corr_size": 13}, searches, corrs, tf, ex,
                     within_tolerance=False)
    with caplog.at_level(logging.INFO):
        _, p, published, _ = _cycle_ends(report, {"search_size": 12, "corr_size": 13}, kept)
    assert ((p.search_size, p.corr_size) == (15, 9)) is kept
    assert (published == []) is kept
    said = " ".join(r.getMessage() for r in caplog.records)
    assert ("no swept window within the tolerance; the windows in force, 15/9, are within "
            "it of the closest: kept" in said) is kept


def test_the_camera_takes_no_acknowledgement_of_a_frame_it_has_not_sent():
    """An estimate of a frame not sent yet would stand for every frame still to come: a paced
    camera would stop waiting and end a file before its last frames were processed."""
    from vistrack.services.camera.service import _Acks

    def estimate(seq: int) -> bytes:
        return Estimate(seq=seq, stamp_ns=5, npi=0, xc=0.0, yc=0.0, xe=0.0, ye=0.0,
                        dx=0.0, dy=0.0, scale=1.0, t_ms=0.0, first=True, features=[],
                        params_id=0).encode()

    with MemoryNode("camera") as node:
        acks = _Acks(node, (node.keys.estimate,))
        acks.sent = 1000
        node.feed(node.keys.estimate, estimate(10**18))
        assert not acks.wait({node.keys.estimate: 1000}, 0.05)
        assert node.status.rejected == 1
        assert "seq 1000000000000000000 is after the newest frame sent (1000)" in \
            node.status.last_error
        node.feed(node.keys.estimate, estimate(1000))
        assert acks.wait({node.keys.estimate: 1000}, 1.0)


def test_the_camera_takes_a_bad_done_for_no_acknowledgement_and_an_estimate_for_one():
    """``preprocessing/done`` is checked as estimates are: one of a frame after the newest
    sent, or without a ``seq``, is rejected and named, and pre-processing is not taken for
    free; an estimate of the frame says it is (the frame was pre-processed to be tracked)."""
    from vistrack.common.messages import PreDone
    from vistrack.services.camera.service import _Acks

    with MemoryNode("camera") as node:
        keys = node.keys
        acks = _Acks(node, (keys.estimate, keys.pre_done))
        acks.sent = 1000
        node.feed(keys.pre_done, PreDone(seq=10**18, stamp_ns=0).encode())
        assert not acks.wait({keys.pre_done: 1000}, 0.05)
        assert "preprocessing/done: seq 1000000000000000000 is after the newest frame " \
            "sent (1000)" in node.status.last_error
        node.feed(keys.pre_done, msgpack.packb({"v": 1, "stamp_ns": 0}))
        assert not acks.wait({keys.pre_done: 1000}, 0.05)
        assert node.status.rejected == 2 and "no valid seq" in node.status.last_error
        node.feed(keys.estimate, Estimate(seq=1000, stamp_ns=0, npi=0, xc=0.0, yc=0.0, xe=0.0,
                                          ye=0.0, dx=0.0, dy=0.0, scale=1.0, t_ms=0.0,
                                          first=True, features=[], params_id=0).encode())
        assert acks.wait({keys.pre_done: 1000}, 1.0)


class _SteppedClock:
    """A module's ``time`` whose wall clock (``time``, ``time_ns``) can be set back, as an NTP
    correction or ``date -s`` does; the monotonic clocks go on."""

    def __init__(self) -> None:
        self.offset_s = 0.0
        self.monotonic, self.perf_counter, self.sleep = (time.monotonic, time.perf_counter,
                                                         time.sleep)

    def time(self) -> float:
        return time.time() + self.offset_s

    def time_ns(self) -> int:
        return time.time_ns() + round(self.offset_s * 1e9)


def test_a_paced_camera_keeps_pacing_after_its_wall_clock_is_set_back(monkeypatch):
    """--fps 0 sends a frame once the one before has its estimate. Acknowledgements were
    matched by stamp: after the wall clock was set back 10 s every frame looked acknowledged
    already and the camera sent 17,390 frames a second, a run meant to lose none."""
    from vistrack.services.camera import service as camera

    clock = _SteppedClock()
    monkeypatch.setattr(camera, "time", clock)
    with MemoryNode("camera") as node:
        thread = threading.Thread(target=camera.loop, args=(
            node, parse("camera", "--source", "builtin", "--fps", "0", "--loop")), daemon=True)
        thread.start()

        def answer() -> None:  # the pipeline: each frame's estimate 20 ms after it was sent
            done = 0
            while not node.stop.is_set():
                frames = node.published_on(node.keys.frame)
                if len(frames) > done:
                    done = len(frames)
                    time.sleep(0.02)
                    node.feed(node.keys.estimate, Estimate(
                        seq=Frame.decode(frames[-1]).seq,
                        stamp_ns=Frame.decode(frames[-1]).stamp_ns, npi=10, xc=1.0, yc=1.0,
                        xe=1.0, ye=1.0, dx=0.0, dy=0.0, scale=1.0, t_ms=1.0, first=False,
                        features=[], params_id=0).encode())
                else:
                    time.sleep(0.002)
        responder = threading.Thread(target=answer, daemon=True)
        try:
            responder.start()
            wait_for(lambda: len(node.published_on(node.keys.frame)) >= 5, what="frames")
            clock.offset_s = -10.0
            before = len(node.published_on(node.keys.frame))
            time.sleep(0.5)
            sent = len(node.published_on(node.keys.frame)) - before
        finally:
            node.stop.set()
            thread.join(5)
            responder.join(5)
    assert 3 <= sent <= 30, sent  # one a frame's answer, 20 ms and more apart: not thousands


def test_a_controller_whose_wall_clock_is_set_back_tracks_on_and_still_stops(monkeypatch):
    """The controller judged ages and the order of estimates on the wall clock. Set back by
    20 s, it refused every estimate as out of order for 20 s, and its watchdog saw every age
    negative: once the estimates stopped, the robot went on with its last move for 18 s. It
    now takes the set-back stamps as a new start, and the watchdog stops the robot when no
    estimate has been taken for --stale-after s of the host's monotonic clock."""
    from vistrack.services.fuzzy_controller import service as controller

    clock = _SteppedClock()
    monkeypatch.setattr(controller, "time", clock)

    def estimate(seq: int, xc: float) -> bytes:
        return Estimate(seq=seq, stamp_ns=clock.time_ns(), npi=40, xc=xc, yc=128.0, xe=400.0,
                        ye=400.0, dx=xc - 90.0, dy=0.0, scale=1.0, t_ms=1.0, first=seq == 0,
                        features=[], params_id=0).encode()

    with MemoryNode("fuzzy_controller") as node:
        thread = threading.Thread(target=controller.loop,
                                  args=(node, parse("fuzzy-controller")), daemon=True)
        thread.start()
        try:
            wait_for(lambda: node.feed(node.keys.estimate, estimate(0, 90.0)),
                     what="the controller's subscription")
            for seq in range(1, 16):  # the target drifting: commands that move
                time.sleep(1 / 30)
                node.feed(node.keys.estimate, estimate(seq, 110.0))
            wait_for(lambda: len(node.published_on(node.keys.cmd_vel)) >= 16, what="commands")
            before = CmdVel.decode(node.published_on(node.keys.cmd_vel)[-1])
            clock.offset_s = -20.0
            for seq in range(16, 46):
                time.sleep(1 / 30)
                node.feed(node.keys.estimate, estimate(seq, 110.0))
            wait_for(lambda: len(node.published_on(node.keys.cmd_vel)) >= 46,
                     what="a command for every estimate after the step")
            moving = CmdVel.decode(node.published_on(node.keys.cmd_vel)[-1])
            # the target still 20 px off the set point, which the step did not move
            assert not moving.stale and moving.vy == pytest.approx(before.vy, rel=0.05)
            assert node.status.rejected == 0, node.status.last_error
            assert node.status.extra["clock_steps"] == 1
            stopped_at = time.monotonic()  # no estimate any more: the watchdog stops it
            wait_for(lambda: CmdVel.decode(node.published_on(node.keys.cmd_vel)[-1]).stale,
                     timeout=5.0, what="a stop")
            assert time.monotonic() - stopped_at < 1.0
        finally:
            node.stop.set()
            thread.join(5)


def test_the_controller_refuses_an_estimate_from_the_future():
    """Accepted, a stamp from the future never looked stale (its command was kept however old
    it got) and every later estimate was refused as out of order: the robot kept moving."""
    from vistrack.services.fuzzy_controller.service import loop

    def estimate(seq: int, stamp_ns: int, first: bool = False) -> bytes:
        return Estimate(seq=seq, stamp_ns=stamp_ns, npi=50, xc=128.0 + seq, yc=128.0, xe=400.0,
                        ye=400.0, dx=float(seq), dy=0.0, scale=1.0, t_ms=1.0, first=first,
                        features=[], params_id=0).encode()

    def answered(stamp_ns: int) -> list[CmdVel]:  # the command of an estimate has its stamp
        return [c for c in map(CmdVel.decode, node.published_on(node.keys.cmd_vel))
                if c.stamp_ns == stamp_ns]

    with MemoryNode("fuzzy_controller") as node:
        thread = threading.Thread(target=loop, args=(node, parse("fuzzy-controller")))
        thread.start()
        try:
            stamp = time.time_ns()
            wait_for(lambda: node.feed(node.keys.estimate, estimate(0, stamp, True)),
                     what="the controller's subscription")
            wait_for(lambda: answered(stamp), what="the first command")
            future = time.time_ns() + 3_600 * 10**9
            node.feed(node.keys.estimate, estimate(1, future))
            wait_for(lambda: node.status.rejected == 1, what="the refusal")
            assert "s ahead of this host's clock (allowed: 1 s)" in node.status.last_error
            for seq in (2, 3):  # later estimates are taken as before
                stamp = time.time_ns()
                node.feed(node.keys.estimate, estimate(seq, stamp))
                wait_for(lambda stamp=stamp: answered(stamp), what=f"command {seq}")
                assert not answered(stamp)[0].stale
        finally:
            node.stop.set()
            thread.join(5)
        assert not answered(future) and node.status.rejected == 1


def test_a_controller_that_cannot_drive_says_why(caplog):
    """Settings in range that make every command a stop, --min-npi above any feature count
    and a --stale-after below the pipeline's latency, stopped the robot for ever in silence
    (range-limits sweep): the first is said at the start, the second after 30 estimates."""
    from vistrack.services.fuzzy_controller.service import LATE_SAID_AFTER, loop

    caplog.set_level(logging.WARNING, logger="vistrack.fuzzy_controller")
    for flags, estimates in ((["--min-npi", "10000"], 1),
                             (["--stale-after", "0.000001"], LATE_SAID_AFTER + 5)):
        with MemoryNode("fuzzy_controller") as node:
            thread = threading.Thread(target=loop, daemon=True,
                                      args=(node, parse("fuzzy-controller", *flags)))
            thread.start()
            try:
                for seq in range(estimates):
                    est = Estimate(seq=seq, stamp_ns=time.time_ns() - 10**6, npi=50,
                                   xc=128.0, yc=128.0, xe=400.0, ye=400.0, dx=0.0, dy=0.0,
                                   scale=1.0, t_ms=1.0, first=seq == 0, features=[],
                                   params_id=0).encode()
                    wait_for(lambda est=est: node.feed(node.keys.estimate, est),
                             what="the controller's subscription")
                    wait_for(lambda seq=seq: len(node.published_on(node.keys.cmd_vel)) > seq,
                             what=f"command {seq}")
            finally:
                node.stop.set()
                thread.join(5)
    said = [r.getMessage() for r in caplog.records]
    assert sum("--min-npi 10000 is more features than a tracker ever holds" in m
               for m in said) == 1, said
    assert sum(f"the last {LATE_SAID_AFTER} estimates were all older than --stale-after" in m
               for m in said) == 1, said


def test_a_controller_that_stops_sends_a_stop_last():
    """Stopped (SIGTERM, Ctrl-C, the launcher's stop) after a moving command, its last
    command is a stale zero: a clean stop of vistrack up left the last move standing (the
    controller ended before its watchdog fired), for a base without a timeout of its own."""
    from vistrack.services.fuzzy_controller.service import loop

    with MemoryNode("fuzzy_controller") as node:
        thread = threading.Thread(target=loop, args=(node, parse("fuzzy-controller")))
        thread.start()
        try:
            for seq in range(3):  # the target moving sideways: commands that move
                est = Estimate(seq=seq, stamp_ns=time.time_ns(), npi=50, xc=128.0 + 20 * seq,
                               yc=128.0, xe=400.0, ye=400.0, dx=20.0 * seq, dy=0.0, scale=1.0,
                               t_ms=1.0, first=seq == 0, features=[], params_id=0).encode()
                wait_for(lambda est=est: node.feed(node.keys.estimate, est),
                         what="the controller's subscription")
                wait_for(lambda seq=seq: len(node.published_on(node.keys.cmd_vel)) > seq,
                         what=f"command {seq}")
            moving = CmdVel.decode(node.published_on(node.keys.cmd_vel)[-1])
            assert not moving.stale and (moving.vx, moving.vy, moving.wz) != (0.0, 0.0, 0.0)
        finally:
            node.stop.set()
            thread.join(5)
        last = CmdVel.decode(node.published_on(node.keys.cmd_vel)[-1])
        assert last.stale and (last.vx, last.vy, last.wz) == (0.0, 0.0, 0.0)


def test_on_the_cameras_clock_a_simulated_clock_ahead_of_the_host_is_followed():
    """A lockstep simulator stamps its frames on a simulated clock running faster than real
    time. On the host's clock its estimates more than 1 s ahead were refused and the simulator
    waited a second for each missing command; with ``--clock camera`` each is answered, and the
    watchdog still stops the robot once none has come for ``--stale-after`` s of host time."""
    from vistrack.services.fuzzy_controller.service import loop

    def estimate(seq: int, stamp_ns: int) -> bytes:
        return Estimate(seq=seq, stamp_ns=stamp_ns, npi=50, xc=128.0 + seq, yc=128.0, xe=400.0,
                        ye=400.0, dx=float(seq), dy=0.0, scale=1.0, t_ms=1.0, first=seq == 0,
                        features=[], params_id=0).encode()

    def commands() -> list[CmdVel]:
        return [CmdVel.decode(p) for p in node.published_on(node.keys.cmd_vel)]

    start = time.time_ns() + 3_600 * 10**9  # an hour ahead of this host, and 10 s a frame
    stamps = [start + seq * 10 * 10**9 for seq in range(4)]
    with MemoryNode("fuzzy_controller") as node:
        args = parse("fuzzy-controller", "--clock", "camera", "--stale-after", "0.3")
        thread = threading.Thread(target=loop, args=(node, args))
        thread.start()
        try:
            wait_for(lambda: node.feed(node.keys.estimate, estimate(0, stamps[0])),
                     what="the controller's subscription")
            for seq, stamp in enumerate(stamps):
                if seq:
                    node.feed(node.keys.estimate, estimate(seq, stamp))
                wait_for(lambda stamp=stamp: any(c.stamp_ns == stamp for c in commands()),
                         what=f"the command of estimate {seq}")
            assert node.status.rejected == 0
            answers = [c for c in commands() if c.stamp_ns in stamps]
            assert not any(c.stale for c in answers) and answers[-1].vy != 0.0
            # no estimate for longer than --stale-after: the watchdog stops the robot
            wait_for(lambda: commands()[-1].stale, timeout=5.0, what="the watchdog's stop")
            assert commands()[-1].vy == commands()[-1].vx == commands()[-1].wz == 0.0
        finally:
            node.stop.set()
            thread.join(5)


def test_a_flood_of_bad_messages_is_counted_in_full_and_logged_once_a_window(
        caplog, monkeypatch):
    """A peer sending bad estimates at 1 kHz wrote one ERROR line each (3000 in a burst, a
    depth camera's images 30 a second for as long as it ran): the first is logged at once,
    the rest at most once every REJECTED_LOG_S with how many came meanwhile; the status
    counts every one, and good input still goes through."""
    from vistrack.services import runtime
    from vistrack.services.fuzzy_controller.service import loop

    monkeypatch.setattr(runtime, "REJECTED_LOG_S", 3600.0)  # the flood within one window
    caplog.set_level(logging.ERROR, logger="vistrack.fuzzy_controller")
    said = lambda: [r.getMessage() for r in caplog.records  # noqa: E731
                    if r.getMessage().startswith("rejected motion/estimate")]
    bad = msgpack.packb({"v": 1, "seq": "one"})
    with MemoryNode("fuzzy_controller") as node:
        thread = threading.Thread(target=loop, args=(node, parse("fuzzy-controller")))
        thread.start()
        try:
            wait_for(lambda: node.feed(node.keys.estimate, bad), what="the subscription")
            for n in range(2, 201):  # one at a time: the estimate is latest-only
                wait_for(lambda n=n: node.status.rejected == n - 1, what=f"rejection {n - 1}")
                node.feed(node.keys.estimate, bad)
            wait_for(lambda: node.status.rejected == 200, what="200 rejections")
            assert len(said()) == 1 and "more rejected" not in said()[0]
            monkeypatch.setattr(runtime, "REJECTED_LOG_S", 0.0)  # the window is over
            node.feed(node.keys.estimate, bad)
            wait_for(lambda: len(said()) == 2, what="the second line")
            assert "(199 more rejected since the last said, each counted in the status)" \
                in said()[1]
            # another kind of error on the same key is said at once, in its own window
            monkeypatch.setattr(runtime, "REJECTED_LOG_S", 3600.0)
            node.feed(node.keys.estimate, msgpack.packb({"v": 2, "seq": 1}))
            wait_for(lambda: len(said()) == 3, what="the new kind said")
            assert "version" in said()[2] and "more rejected" not in said()[2]
            stamp = time.time_ns()
            node.feed(node.keys.estimate, Estimate(
                seq=1, stamp_ns=stamp, npi=50, xc=128.0, yc=128.0, xe=400.0, ye=400.0,
                dx=0.0, dy=0.0, scale=1.0, t_ms=1.0, first=True, features=[],
                params_id=0).encode())
            wait_for(lambda: any(CmdVel.decode(c).stamp_ns == stamp
                                 for c in node.published_on(node.keys.cmd_vel)),
                     what="the good estimate's command")
        finally:
            node.stop.set()
            thread.join(5)
    assert node.status.rejected == 202


#: a map whose field holds lists nested 1000 deep: 1 KB, within every size limit
DEEP = b"\x82\xa1v\x01\xa1j" + b"\x91" * 1000 + b"\x81\x01\x01"


def test_a_payload_nested_1000_deep_is_rejected_and_the_service_goes_on():
    """msgspec raises RecursionError, not DecodeError, on nesting beyond its stack: a 1 KB
    payload on camera/frame ended pre-processing ("failed outside the per-message path:
    exiting", from the arrival's look at its seq) and every decoder raised it, not
    MessageError. It is rejected and counted, and the next frame is filtered as ever."""
    from vistrack.common.messages import PreFrame, peek_seq
    from vistrack.services.preprocessing.service import loop

    assert peek_seq(DEEP) is None
    for cls in (Frame, Estimate, CmdVel, PreFrame, Params):
        with pytest.raises(MessageError):
            cls.decode(DEEP)
    image = (np.arange(64 * 64, dtype=np.uint32).reshape(64, 64) * 2654435761 >> 24
             ).astype(np.uint8)
    with MemoryNode("preprocessing") as node:
        thread = threading.Thread(target=loop, args=(node, parse("preprocessing")),
                                  daemon=True)
        thread.start()
        try:
            deadline = time.monotonic() + 60
            while not node.feed(node.keys.frame, DEEP):
                assert time.monotonic() < deadline, "no subscription"
                time.sleep(0.01)
            assert node.wait_idle(30)
            node.feed(node.keys.frame, encode_frame(image, seq=1, stamp_ns=1))
            assert node.wait_idle(30)
            out = [PreFrame.decode(p) for p in node.published_on(node.keys.pre_frame)]
            status = node.status.as_dict()
        finally:
            node.stop.set()
            thread.join(10)
    assert not thread.is_alive()
    assert status["rejected"] == 1 and status["failed"] == 0, status
    assert [m.seq for m in out] == [1]


def test_the_simulator_says_a_flood_of_bad_commands_once(caplog):
    """50 velocity commands with ``vx: "fast"``: a line each before; one now, all counted,
    and the simulator renders on."""
    from loops import Running

    bad = msgpack.packb({"v": 1, "seq": 1, "stamp_ns": 1, "vx": "fast", "vy": 0.0, "wz": 0.0,
                         "stale": False})
    with caplog.at_level(logging.INFO, logger="vistrack.camera"), \
            Running("camera", "--source", "sim", "--fps", "100", "--size", "64x48") as cam:
        node = cam.node
        for _ in range(50):
            cam.feed(node.keys.cmd_vel, bad, reliable=True, wait=False)
        wait_for(lambda: node.status.rejected == 50, timeout=30, what="50 rejections")
        rendered = len(node.published_on(node.keys.frame))
        wait_for(lambda: len(node.published_on(node.keys.frame)) > rendered + 5,
                 what="frames after the flood")
    said = [r.getMessage() for r in caplog.records if "rejected" in r.getMessage()]
    assert len(said) == 1 and said[0].startswith("rejected control/cmd_vel: ") \
        and "'vx'" in said[0], said
