"""Per-message fault isolation (runtime.dispatch / Faults), in-process through the MemoryNode
seam: an input whose handling raises is skipped, counted in ``failed``, logged once with its key
and ``seq``, the state is recovered, and the loop goes on; a fault outside the per-message path
is not hidden. Also the loop's ``busy_s`` that the launcher's hang detection reads."""

from __future__ import annotations

import logging
import threading
import time

import numpy as np
import pytest

from vistrack.common.bus import MemoryNode
from vistrack.common.messages import Estimate, PreFrame, pack, unpack
from vistrack.common.params import TrackerParams
from vistrack.common.synthetic import builtin_sequence
from vistrack.common.vision import preprocess
from vistrack.services import cli
from vistrack.services.runtime import Faults, dispatch

log = logging.getLogger("vistrack.test_faults")


def wait_for(condition, timeout=10.0, what="condition"):
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.002)


def run_loop(target, *args) -> threading.Thread:
    """``target(*args)`` in a thread; its exception, if any, is kept in ``thread.error``."""
    def body():
        try:
            target(*args)
        except BaseException as e:  # noqa: BLE001 - recorded for the test to assert on
            thread.error = e
    thread = threading.Thread(target=body, daemon=True)
    thread.error = None
    thread.start()
    return thread


def payload(seq: int, **fields) -> bytes:
    return pack({"seq": seq, "stamp_ns": 1, **fields})


def test_a_failing_input_is_counted_logged_once_with_key_and_seq_and_skipped(caplog):
    handled: list[int] = []
    recovered: list[int] = []

    def on_frame(p: bytes) -> None:
        seq = unpack(p)["seq"]
        if seq in (2, 3):
            raise ZeroDivisionError(f"bug on {seq}")
        handled.append(seq)

    with MemoryNode("preprocessing") as node:
        node.subscribe(node.keys.params, latest=False)  # reliable: every payload kept, in order
        thread = run_loop(lambda: dispatch(node, {node.keys.params: on_frame}, log,
                                           recover=lambda: recovered.append(len(handled))))
        with caplog.at_level(logging.ERROR, logger="vistrack.test_faults"):
            for seq in range(5):
                node.feed(node.keys.params, payload(seq))
            wait_for(lambda: len(handled) == 3 and node.status.failed == 2, what="5 inputs")
        node.stop.set()
        thread.join(5)
    assert thread.error is None and not thread.is_alive()
    assert handled == [0, 1, 4]
    assert recovered == [2, 2]  # after each failure, before the next input
    assert node.status.failed == 2 and node.status.rejected == 0
    assert node.status.as_dict()["failed"] == 2
    assert node.status.last_error == "tuner/params seq 3: ZeroDivisionError: bug on 3"
    records = [r for r in caplog.records if r.name == "vistrack.test_faults"]
    assert [r.getMessage() for r in records] == [
        "failed on tuner/params seq 2: ZeroDivisionError: bug on 2 (input skipped, "
        "1 failed so far)",
        "failed on tuner/params seq 3: ZeroDivisionError: bug on 3 (input skipped, "
        "2 failed so far)"]
    # the traceback once per place that fails, not once per failure
    assert records[0].exc_info is not None and records[1].exc_info is None


def test_a_fault_outside_the_per_message_path_is_not_hidden():
    calls = 0

    def tick() -> None:
        nonlocal calls
        calls += 1
        if calls == 3:
            raise RuntimeError("broken between inputs")

    with MemoryNode("auto_tuner") as node:
        node.subscribe(node.keys.frame, latest=True)
        with pytest.raises(RuntimeError, match="broken between inputs"):
            dispatch(node, {node.keys.frame: lambda p: None}, log, timeout=0.01, tick=tick)
        assert node.status.failed == 0


def test_a_fault_in_recover_ends_the_loop():
    def recover() -> None:
        raise RuntimeError("the state cannot be put back")

    with MemoryNode("motion_estimation") as node:
        node.subscribe(node.keys.pre_frame, latest=True)
        node.feed(node.keys.pre_frame, payload(7))
        with pytest.raises(RuntimeError, match="cannot be put back"):
            dispatch(node, {node.keys.pre_frame: lambda p: 1 / 0}, log, timeout=0.01,
                     recover=recover)
        assert node.status.failed == 1


def test_faults_call_isolates_one_step():
    with MemoryNode("camera") as node:
        faults = Faults(node, log)
        assert faults.call(node.keys.frame, 4, lambda a, b: a + b, 1, 2)
        assert not faults.call(node.keys.frame, 5, lambda: {}["missing"])
        assert node.status.failed == 1
        assert node.status.last_error == "camera/frame seq 5: KeyError: 'missing'"


def test_busy_s_counts_work_between_waits_only():
    with MemoryNode("preprocessing") as node:
        node.subscribe(node.keys.frame, latest=True)
        assert node.busy_s == 0.0  # before the loop's first wait
        started = threading.Event()

        def waiting() -> None:
            started.set()
            node.recv(timeout=0.3)

        thread = threading.Thread(target=waiting)
        thread.start()
        started.wait()
        time.sleep(0.1)
        assert node.busy_s == 0.0  # waiting for input is not work
        thread.join()
        time.sleep(0.05)
        assert node.busy_s >= 0.05  # back from recv: working since
        node.sleep(0.01)
        assert node.busy_s < 0.05


# -- the services' loops -----------------------------------------------------------------

def parse(command: str, *argv: str):
    return cli.build_parser(command).parse_args([command, *argv])


def pre_frame(image: np.ndarray, seq: int) -> bytes:
    pre = preprocess(image, TrackerParams())
    return PreFrame(seq=seq, stamp_ns=time.time_ns(), width=image.shape[1],
                    height=image.shape[0], data=pre.filtered, candidates=pre.candidates,
                    strength=pre.strength, params_id=0).encode()


def test_motion_estimation_survives_a_featureless_8x8_frame_and_tracks_again():
    """The frame of issue 13: 8x8 zero bytes gave an estimate with xc = NaN, which our own
    message validation refused: an uncaught exception ended the process. The isolation costs
    at most that one input (and the tracker now answers it with a finite, invalid estimate),
    and tracking resumes on the next textured frames."""
    from vistrack.services.motion_estimation.service import loop

    textured = builtin_sequence(3)
    with MemoryNode("motion_estimation") as node:
        thread = run_loop(loop, node, parse("motion-estimation"))
        wait_for(lambda: node.feed(node.keys.pre_frame, pre_frame(textured[0], 0)),
                 what="the subscription")

        def estimates() -> list[Estimate]:
            return [Estimate.decode(p) for p in node.published_on(node.keys.estimate)]
        wait_for(lambda: len(estimates()) == 1, what="the first estimate")
        node.feed(node.keys.pre_frame, pre_frame(np.zeros((8, 8), np.uint8), 1))
        wait_for(lambda: len(estimates()) + node.status.failed == 2, what="the 8x8 frame")
        for seq, image in enumerate(textured[1:], start=2):
            node.feed(node.keys.pre_frame, pre_frame(image, seq))
            wait_for(lambda seq=seq: estimates()[-1].seq == seq, what=f"frame {seq}")
        node.stop.set()
        thread.join(10)
    assert thread.error is None
    got = estimates()
    assert [e.seq for e in got if e.npi > 0] == [0, 2, 3]
    assert got[-2].first and got[-2].npi > 10  # a new track on the first textured frame
    assert node.status.rejected == 0


@pytest.mark.usefixtures("int64_kernels")  # compiled beside the tests (conftest)
def test_parameters_with_kernels_of_their_own_wait_for_them_beside_the_loop(monkeypatch):
    """A 64 px correlation window sums in int64: kernels the start-up warm-up does not load,
    which a cold cache compiled for ~27 s inside the loop (the launcher killed the service
    as hung: 6 exits in ``vistrack bench faults``). The update now waits, pending in the
    status, while a second process makes them ready; frames go on being tracked with the
    parameters in force, and each estimate's params_id says which ones; then it is in
    force. (The kernels are unloaded for this test's process: a cache that holds them still
    takes the second process's start, seconds, against a frame's milliseconds.)"""
    from vistrack.common.messages import Params
    from vistrack.common.vision import tracker as tracker_module
    from vistrack.services.motion_estimation.service import loop

    big = TrackerParams(corr_size=64)
    key = tracker_module._kernel_set(big)
    assert key[-1] == "int64"  # what makes the set one of its own
    monkeypatch.setattr(tracker_module, "_WARM", set(tracker_module._WARM) - {key})
    frames = builtin_sequence(40)
    with MemoryNode("motion_estimation") as node:
        thread = run_loop(loop, node, parse("motion-estimation"))
        wait_for(lambda: node.feed(node.keys.pre_frame, pre_frame(frames[0], 0)),
                 timeout=60, what="the subscription")

        def estimates() -> list[Estimate]:
            return [Estimate.decode(p) for p in node.published_on(node.keys.estimate)]
        wait_for(lambda: len(estimates()) == 1, timeout=60, what="the first estimate")
        node.feed(node.keys.params, Params.from_tracker_params(
            big, seq=0, stamp_ns=time.time_ns(), params_id=7, source="user",
            reason="test").encode())
        node.feed(node.keys.pre_frame, pre_frame(frames[1], 1))
        wait_for(lambda: len(estimates()) == 2, what="the frame after the update")
        assert estimates()[-1].params_id == 0  # tracked with the parameters in force
        assert node.status.extra.get("params_pending") == 7
        assert node.status.params["params_id"] == 0
        seq = 2
        # the second process loads the int64 set from the cache conftest filled (a cold
        # cache: it compiles it, ~30 s, 80 s when busy)
        deadline = time.monotonic() + 300.0
        while estimates()[-1].params_id != 7:
            assert time.monotonic() < deadline and thread.is_alive(), \
                "the update never came in force"
            node.feed(node.keys.pre_frame, pre_frame(frames[seq % 40], seq))
            wait_for(lambda seq=seq: estimates()[-1].seq == seq, what=f"frame {seq}")
            seq += 1
            time.sleep(0.05)
        node.stop.set()
        thread.join(10)
    assert thread.error is None
    assert seq > 3  # frames went on while the kernels were made ready
    got = estimates()
    ids = [e.params_id for e in got]
    assert ids == sorted(ids)  # never back to the old parameters
    assert node.status.params["params_id"] == 7 and node.status.params["corr_size"] == 64
    assert "params_pending" not in node.status.extra
    assert tracker_module.kernels_warm(big)
    assert node.status.failed == 0 and node.status.rejected == 0


@pytest.mark.usefixtures("int64_kernels")  # compiled beside the tests (conftest)
def test_parameters_whose_kernels_were_pending_come_in_force_without_a_frame(monkeypatch):
    """A set pending its kernels came in force only with the next frame: on a pipeline with
    no camera (vistrack up --camera none) params set waited its 180 s, then said the set may
    have been lost; it came in force minutes later, with the first frame."""
    from vistrack.common.messages import Params
    from vistrack.common.vision import tracker as tracker_module
    from vistrack.services.motion_estimation.service import loop

    big = TrackerParams(corr_size=64)
    monkeypatch.setattr(tracker_module, "_WARM",
                        set(tracker_module._WARM) - {tracker_module._kernel_set(big)})
    with MemoryNode("motion_estimation") as node:
        thread = run_loop(loop, node, parse("motion-estimation"))
        wait_for(lambda: node.feed(node.keys.params, Params.from_tracker_params(
            big, seq=0, stamp_ns=time.time_ns(), params_id=7, source="user",
            reason="test").encode()), timeout=60, what="the subscription")
        wait_for(lambda: node.status.extra.get("params_pending") == 7, what="pending")
        # the second process loads the int64 set from the cache conftest filled (a cold
        # cache: it compiles it, ~30 s, 80 s when busy)
        wait_for(lambda: node.status.params["params_id"] == 7, timeout=300,
                 what="the set in force, no frame fed")
        node.stop.set()
        thread.join(10)
    assert thread.error is None and "params_pending" not in node.status.extra
    assert node.published_on(node.keys.estimate) == []


@pytest.mark.usefixtures("int64_kernels")  # compiled beside the tests (conftest)
def test_parameters_whose_kernels_fail_are_dropped_and_the_old_ones_stay(monkeypatch, caplog):
    """Should their kernels fail to build (a compiler error), a pending update is dropped with
    an error in the status and the log, once: the parameters in force stay, and the loop does
    not retry a compile of half a minute on every frame."""
    from vistrack.common import vision
    from vistrack.common.messages import Params
    from vistrack.common.vision import tracker as tracker_module
    from vistrack.services.motion_estimation.service import loop

    big = TrackerParams(corr_size=64)
    key = tracker_module._kernel_set(big)
    monkeypatch.setattr(tracker_module, "_WARM", set(tracker_module._WARM) - {key})
    tries = []
    real_warm_up = vision.warm_up

    def broken_warm_up(*args, params=None, **kwargs):
        if params != big:  # the start-up's: as it is
            return real_warm_up(*args, params=params, **kwargs)
        tries.append(params)
        raise RuntimeError("the compiler failed")
    monkeypatch.setattr(vision, "warm_up", broken_warm_up)
    frames = builtin_sequence(10)
    with MemoryNode("motion_estimation") as node:
        thread = run_loop(loop, node, parse("motion-estimation"))
        wait_for(lambda: node.feed(node.keys.pre_frame, pre_frame(frames[0], 0)),
                 timeout=60, what="the subscription")
        node.feed(node.keys.params, Params.from_tracker_params(
            big, seq=0, stamp_ns=time.time_ns(), params_id=7, source="user",
            reason="test").encode())
        seq = 1
        while "could not be made ready" not in (node.status.last_error or ""):
            assert seq < 2000 and thread.is_alive(), "the failure was never said"
            node.feed(node.keys.pre_frame, pre_frame(frames[seq % 10], seq))
            time.sleep(0.05)
            seq += 1
        for more in range(seq, seq + 5):  # tracking goes on, with what is in force
            node.feed(node.keys.pre_frame, pre_frame(frames[more % 10], more))
        wait_for(lambda: Estimate.decode(node.published_on(node.keys.estimate)[-1]).seq
                 == seq + 4, what="the frames after")
        # the set again, as params set repeats it every second and the auto-tuner reminds it:
        # it was accepted, dropped and logged again each time, and left params_pending stuck
        # at 7 with nothing pending (params set then waited its 180 s)
        for reminder in range(3):
            node.feed(node.keys.params, Params.from_tracker_params(
                big, seq=1 + reminder, stamp_ns=time.time_ns(), params_id=7, source="user",
                reason="test").encode())
            assert node.wait_idle(10)
            time.sleep(0.15)  # a tick or more
        node.stop.set()
        thread.join(10)
    assert thread.error is None
    assert "params_id 7" in node.status.last_error
    assert {Estimate.decode(p).params_id for p in node.published_on(node.keys.estimate)} == {0}
    assert node.status.params["params_id"] == 0 and "params_pending" not in node.status.extra
    assert tries == [big]  # tried once, not again on every frame
    # said once, not again with each reminder (an error and a "making them ready" each)
    said = [r.getMessage() for r in caplog.records if "params_id 7" in r.getMessage()
            and r.name == "vistrack.motion_estimation" and r.levelname == "ERROR"]
    assert len(said) == 1, said


def test_the_controller_stops_the_robot_after_a_failed_estimate_when_the_estimates_stop():
    """An estimate whose handling fails (here its command's publish) resets the controller's
    set point (recover). The robot's last command was a move: once the estimates stop, the
    watchdog must still send its stale stops, as it does without the fault (it sent nothing,
    and the move stood)."""
    from vistrack.common.messages import CmdVel
    from vistrack.services.fuzzy_controller.service import loop

    def estimate(seq: int, xc: float) -> bytes:
        return Estimate(seq=seq, stamp_ns=time.time_ns(), npi=40, xc=xc, yc=128.0, xe=400.0,
                        ye=400.0, dx=xc - 128.0, dy=0.0, scale=1.0, t_ms=1.0, first=seq == 0,
                        valid=True, features=[], params_id=0).encode()

    node = MemoryNode("fuzzy_controller")
    publish, sends = node.publish, []

    def flaky(key, payload, **kw):  # the transport refuses the answer to estimate 2
        sends.append(key)
        if key == node.keys.cmd_vel and len(sends) == 3:
            raise RuntimeError("publish failed")
        return publish(key, payload, **kw)

    node.publish = flaky  # type: ignore[method-assign]
    thread = run_loop(loop, node, cli.build_parser("fuzzy-controller").parse_args(
        ["fuzzy-controller"]))
    try:
        for seq, xc in ((0, 128.0), (1, 150.0), (2, 150.0)):
            while not node.feed(node.keys.estimate, estimate(seq, xc)):
                time.sleep(0.01)
            assert node.wait_idle(10)
        time.sleep(1.2)  # no estimates for 4 times --stale-after (0.3 s)
    finally:
        node.stop.set()
        thread.join(10)
        node.close()
    assert thread.error is None
    cmds = [CmdVel.decode(p) for p in node.published_on(node.keys.cmd_vel)]
    assert node.status.failed == 1
    # estimate 1 moved the robot (the target 22 px right of the set point)
    assert not cmds[1].stale and cmds[1].vy < -0.1
    # then, after the failed answer to estimate 2, the watchdog's stops (not the final stop
    # of the loop's end only: several, 0.1 s apart, before it)
    stops = [c for c in cmds[2:] if c.stale and (c.vx, c.vy, c.wz) == (0.0, 0.0, 0.0)]
    assert len(stops) >= 4, cmds
