"""``valid`` end to end in-process (the MemoryNode seam): motion-estimation says when an
estimate has too few features to mean anything, and the fuzzy controller does not move the
robot on it."""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest

from vistrack.common import synthetic
from vistrack.common.bus import MemoryNode
from vistrack.common.messages import CmdVel, Estimate, PreFrame
from vistrack.common.params import TrackerParams
from vistrack.common.vision import preprocess
from vistrack.services import cli


def parse(command: str, *argv: str):
    return cli.build_parser(command).parse_args([command, *argv])


def wait_for(condition, timeout=10.0, what="condition"):
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.002)


class Running:
    """A service loop on a MemoryNode in a thread, stopped on exit."""

    def __init__(self, service: str, loop, args) -> None:
        self.node = MemoryNode(service)
        self.thread = threading.Thread(target=loop, args=(self.node, args))

    def __enter__(self) -> MemoryNode:
        self.node.__enter__()
        self.thread.start()
        return self.node

    def __exit__(self, *exc) -> None:
        self.node.stop.set()
        self.thread.join(10)
        self.node.__exit__(*exc)


def pre_frame(image: np.ndarray, seq: int) -> bytes:
    pre = preprocess(image, TrackerParams())
    return PreFrame(seq=seq, stamp_ns=time.time_ns(), width=image.shape[1],
                    height=image.shape[0], data=pre.filtered, candidates=pre.candidates,
                    strength=pre.strength, params_id=0).encode()


def track(node: MemoryNode, frames: list[np.ndarray]) -> None:
    """Feed ``frames`` to a running motion-estimation in turn, each once its estimate of the
    one before is out."""
    for seq, image in enumerate(frames):
        payload = pre_frame(image, seq)
        wait_for(lambda payload=payload: node.feed(node.keys.pre_frame, payload),
                 what="a subscription")
        wait_for(lambda seq=seq: len(node.published_on(node.keys.estimate)) > seq,
                 what=f"estimate {seq}")


def test_motion_estimation_marks_an_estimate_without_features_invalid():
    """Textured frames give valid estimates; an all-black frame (a covered lens) and a frame
    too small for any feature give ones that say so, with every number finite, and the
    service goes on."""
    from vistrack.services.motion_estimation.service import loop

    textured = synthetic.sequence(3, size=(128, 128))
    frames = [*textured, np.zeros((128, 128), np.uint8), np.full((6, 6), 90, np.uint8),
              textured[0]]
    with Running("motion_estimation", loop, parse("motion-estimation")) as node:
        def estimates() -> list[Estimate]:
            return [Estimate.decode(p) for p in node.published_on(node.keys.estimate)]

        track(node, frames)
        got = estimates()
    assert [e.valid for e in got] == [True, True, True, False, False, True]
    assert all(e.npi >= 10 for e in got if e.valid)
    assert got[3].npi == 0 and (got[3].xc, got[3].yc) == (63.5, 63.5)
    tiny = got[4]
    assert tiny.npi == 0 and tiny.features == []
    assert (tiny.xc, tiny.yc, tiny.xe, tiny.ye) == (2.5, 2.5, 0.0, 0.0)
    for e in got:
        assert all(math.isfinite(getattr(e, k))
                   for k in ("xc", "yc", "xe", "ye", "dx", "dy", "scale", "t_ms"))
    # each says the size of its frame (the controller's centring error is in its width)
    assert [(e.width, e.height) for e in got] == [f.shape[::-1] for f in frames]


def test_candidates_whose_window_does_not_fit_make_no_features():
    """A peer's pre-processed frames with candidates on the corners (ours keep a margin of
    the correlation window's half plus one): a black 8 x 8 frame gave 4 features in an
    estimate marked valid, a 1 x 1 frame 1. None fits a window there: NPI 0, not valid.
    On a textured frame the candidates that fit are taken, those on the border are not."""
    from vistrack.services.motion_estimation.service import loop

    def forged(image: np.ndarray, seq: int, cands: list[tuple[int, int]]) -> bytes:
        return PreFrame(seq=seq, stamp_ns=time.time_ns() + seq, width=image.shape[1],
                        height=image.shape[0], data=image,
                        candidates=np.array(cands, np.int16).reshape(-1, 2),
                        strength=np.ones(len(cands), np.float32), params_id=0).encode()

    textured = synthetic.sequence(1, size=(128, 128))[0]
    margin = TrackerParams().corr_half + 1
    inner = [(margin + 10 * k, margin + 7 * k) for k in range(1, 9)]
    frames = [(np.zeros((8, 8), np.uint8), [(0, 0), (7, 0), (0, 7), (7, 7)]),
              (np.full((1, 1), 200, np.uint8), [(0, 0)]),
              (textured, [(0, 0), (127, 64), (margin - 1, 50), *inner, (50, 127 - margin + 1)])]
    with Running("motion_estimation", loop, parse("motion-estimation")) as node:
        for seq, (image, cands) in enumerate(frames):
            payload = forged(image, seq, cands)
            wait_for(lambda payload=payload: node.feed(node.keys.pre_frame, payload),
                     what="a subscription")
            wait_for(lambda seq=seq: len(node.published_on(node.keys.estimate)) > seq,
                     what=f"estimate {seq}")
        got = [Estimate.decode(p) for p in node.published_on(node.keys.estimate)]
    assert [(e.npi, e.valid) for e in got[:2]] == [(0, False), (0, False)]
    assert sorted((x, y) for _, x, y in got[2].features) == sorted(inner)


def test_motion_estimation_status_counts_rejected_features_by_reason():
    """A frame of another scene: the features find no trustworthy match there and are
    rejected, not reported; the status says how many and why, beside the features lost."""
    from vistrack.services.motion_estimation.service import loop

    frames = [*synthetic.sequence(2, size=(128, 128)),
              synthetic.sequence(1, size=(128, 128), seed=7)[0]]
    with Running("motion_estimation", loop, parse("motion-estimation")) as node:
        track(node, frames)
        extra = node.status.as_dict()["extra"]  # the tracker's counters: computed when read
    by = extra["rejected_by"]
    assert set(by) == {"border", "ambiguous", "runaway", "fb", "disagrees", "residual", "few"}
    assert extra["rejected_features"] == sum(by.values()) > 10, extra
    assert extra["lost"] >= extra["rejected_features"] and "rejected" not in extra


def test_motion_estimation_counts_features_over_the_frames_budget_apart(monkeypatch, caplog):
    """Features a frame had no search budget left for are lost as ``over_budget`` in the
    status, not as rejected matches, and the log says so once for the parameters in force,
    naming them and what to make smaller."""
    from vistrack.common.vision import tracker as tracker_module
    from vistrack.services.motion_estimation.service import loop

    monkeypatch.setattr(tracker_module, "FRAME_WORK", 0)
    frames = synthetic.sequence(4, size=(128, 128))
    with caplog.at_level("WARNING", logger="vistrack.motion_estimation"), \
            Running("motion_estimation", loop, parse("motion-estimation")) as node:
        track(node, frames)
        extra = node.status.as_dict()["extra"]
    assert extra["over_budget"] > 0, extra
    assert "budget" not in extra["rejected_by"] and extra["lost"] >= extra["over_budget"]
    said = [r.getMessage() for r in caplog.records if "budget" in r.getMessage()]
    assert len(said) == 1, said
    assert "search_size" in said[0] and "params_id 0" in said[0] and "(0 window" in said[0]


def command_for(node: MemoryNode, payload: bytes) -> CmdVel:
    """Feed an estimate to a running fuzzy controller; its command (by the estimate's stamp)."""
    stamp = Estimate.decode(payload).stamp_ns

    def answer() -> CmdVel | None:
        return next((c for p in node.published_on(node.keys.cmd_vel)
                     if (c := CmdVel.decode(p)).stamp_ns == stamp), None)

    wait_for(lambda: node.feed(node.keys.estimate, payload), what="a subscription")
    wait_for(lambda: answer() is not None, what=f"the command of stamp {stamp}")
    command = answer()
    assert command is not None
    return command


def test_the_controller_does_not_move_the_robot_on_an_invalid_estimate():
    """An invalid first estimate neither moves the robot nor sets the set point; an invalid
    one later stops it; valid ones move it again."""
    from vistrack.services.fuzzy_controller.service import loop

    def estimate(seq: int, xc: float, npi: int, valid: bool) -> bytes:
        return Estimate(seq=seq, stamp_ns=time.time_ns(), npi=npi, xc=xc,
                        yc=128.0, xe=400.0 if valid else 0.0, ye=400.0 if valid else 0.0,
                        dx=0.0, dy=0.0, scale=1.0, t_ms=1.0, first=seq == 0, valid=valid,
                        features=[], params_id=0).encode()

    # the first estimate has no features: its xc is the image centre, no target's; the
    # publisher's verdict is followed even where NPI alone would pass the controller's check
    script = [(0, 127.5, 0, False), (1, 90.0, 40, True), (2, 90.0, 40, True),
              (3, 127.5, 10, False), (4, 90.0, 40, True)]
    with Running("fuzzy_controller", loop, parse("fuzzy-controller")) as node:
        answered = [command_for(node, estimate(seq, xc, npi, valid))
                    for seq, xc, npi, valid in script]
    stale = [c.stale for c in answered]
    assert stale == [True, False, False, True, False]
    for c in answered:
        if c.stale:
            assert (c.vx, c.vy, c.wz) == (0.0, 0.0, 0.0)
    # the set point came from the first valid estimate (xc 90), so the target is centred on it
    # and the robot is not sent towards the image centre of the invalid one
    assert abs(answered[1].vy) < 1e-9 and abs(answered[2].vy) < 1e-9


def test_a_held_camera_sends_nothing_until_a_line_on_its_stdin(monkeypatch):
    """``--start-on-stdin`` (how the launcher starts the camera early): no liveliness token,
    no frame until a line arrives on stdin, then frames; the same camera without the line
    stops cleanly when asked, having sent nothing."""
    import os

    from vistrack.services.camera.service import loop

    read_fd, write_fd = os.pipe()
    with os.fdopen(read_fd) as stdin, os.fdopen(write_fd, "w") as go:
        monkeypatch.setattr("sys.stdin", stdin)
        args = parse("camera", "--source", "sim", "--fps", "50", "--start-on-stdin")
        with Running("camera", loop, args) as node:
            time.sleep(0.5)  # held: half a second of nothing (50 fps would be 25 frames)
            assert node.published_on(node.keys.frame) == [] and not node.alive
            go.write("go\n")
            go.flush()
            wait_for(lambda: len(node.published_on(node.keys.frame)) >= 3, what="frames")
            assert node.alive
    read_fd, write_fd = os.pipe()
    with os.fdopen(read_fd) as stdin, os.fdopen(write_fd, "w"):
        monkeypatch.setattr("sys.stdin", stdin)
        with Running("camera", loop, args) as node:
            time.sleep(0.3)
        assert node.published_on(node.keys.frame) == []


def test_the_controller_does_not_move_the_robot_on_an_estimate_already_stale():
    """An estimate stamped longer ago than --stale-after (0.3 s; a camera clock behind the
    host's, a pipeline slower than the bound) is answered with the watchdog's stale stop and
    counted (extra.late): it used to move the robot, which the watchdog stopped 0.1 s later,
    stop and go on data 0.5 to 5 s old. A fresh one moves it again."""
    from vistrack.services.fuzzy_controller.service import loop

    def estimate(seq: int, stamp_ns: int) -> bytes:
        return Estimate(seq=seq, stamp_ns=stamp_ns, npi=40, xc=90.0 + 10 * seq, yc=128.0,
                        xe=400.0, ye=400.0, dx=10.0 * seq, dy=0.0, scale=1.0, t_ms=1.0,
                        first=seq == 0, valid=True, features=[], params_id=0).encode()

    with Running("fuzzy_controller", loop, parse("fuzzy-controller")) as node:
        answered: list[CmdVel] = []
        t0 = time.time_ns()
        # the second and third stamped 1 and 2 ms after the first, but arriving 0.6 s later
        for seq, stamp, wait in ((0, t0, 0.0), (1, t0 + 10**6, 0.6), (2, t0 + 2 * 10**6, 0.0),
                                 (3, None, 0.0)):
            time.sleep(wait)
            answered.append(command_for(node, estimate(seq, time.time_ns() if stamp is None
                                                       else stamp)))
        late = node.status.extra.get("late")
    assert [c.stale for c in answered] == [False, True, True, False]
    assert all((c.vx, c.vy, c.wz) == (0.0, 0.0, 0.0) for c in answered[1:3])
    assert answered[3].vy < 0.0  # fresh, 30 px right of the set point: it moves again
    assert late == 2


def test_the_controller_reads_the_centring_error_in_the_estimates_image_width():
    """The centring error is in half-image-widths. Fixed at 256 px, a 768 px camera's error
    read 3 times too large and the command swung +-0.2 m/s in a limit cycle: the estimate now
    gives its frame's width, which the controller takes unless --image-width is given. The
    same error in image widths gives the same command at 256 and at 768 px; 12 px at 768 read
    as at 256 px commands more."""
    from vistrack.services.fuzzy_controller.service import loop

    def commands(width: int | None, off: float, *argv: str) -> list[CmdVel]:
        base = time.time_ns()

        def estimate(seq: int, dx: float) -> bytes:
            return Estimate(seq=seq, stamp_ns=base + seq * 33_000_000, npi=40, xc=100.0,
                            yc=100.0, xe=400.0, ye=400.0, dx=dx, dy=0.0, scale=1.0, t_ms=1.0,
                            first=seq == 0, features=[], params_id=0, width=width,
                            height=width).encode()

        with Running("fuzzy_controller", loop, parse("fuzzy-controller", *argv)) as node:
            return [command_for(node, estimate(seq, dx))
                    for seq, dx in enumerate((0.0, off / 2, off))]

    at_256 = commands(256, 4.0)  # below the 12.8 px of a full command
    at_768 = commands(768, 12.0)
    assert all(not c.stale for c in at_256 + at_768)
    assert 0.05 < abs(at_256[2].vy) < 0.5  # the error moves the robot, short of the limit
    for a, b in zip(at_256, at_768, strict=True):
        assert math.isclose(a.vy, b.vy, rel_tol=1e-4, abs_tol=1e-9), (a, b)
    # an older publisher's estimate (no width) is read at 256 px, and --image-width wins
    assert math.isclose(commands(None, 4.0)[2].vy, at_256[2].vy, rel_tol=1e-4)
    forced = commands(768, 12.0, "--image-width", "256")
    assert abs(forced[2].vy) > abs(at_768[2].vy) + 0.05


def test_the_controller_says_when_its_watchdog_holds_the_robot_and_when_it_lets_go(caplog):
    """Stale stops went out every 0.1 s for as long as motion-estimation was gone, with the
    status 'ok', no count and no log line: an operator could not tell the robot was held."""
    import logging

    from vistrack.services.fuzzy_controller.service import loop

    caplog.set_level(logging.INFO, logger="vistrack.fuzzy_controller")

    def estimate(seq: int) -> bytes:
        return Estimate(seq=seq, stamp_ns=time.time_ns(), npi=40, xc=100.0, yc=100.0,
                        xe=400.0, ye=400.0, dx=2.0 * seq, dy=0.0, scale=1.0, t_ms=1.0,
                        first=seq == 0, features=[], params_id=0, width=256,
                        height=256).encode()

    def said(text: str) -> list[str]:
        return [r.getMessage() for r in caplog.records if text in r.getMessage()]

    with Running("fuzzy_controller", loop, parse("fuzzy-controller")) as node:
        command_for(node, estimate(0))
        assert not command_for(node, estimate(1)).stale
        wait_for(lambda: node.status.extra.get("watchdog_stops", 0) >= 3,
                 what="the watchdog's stops")
        assert "held_since" in node.status.as_dict()["extra"]
        assert len(said("holding the robot stopped")) == 1
        assert not command_for(node, estimate(2)).stale
        wait_for(lambda: said("estimates fresh again"), what="the release said")
        assert "held_since" not in node.status.as_dict()["extra"]


def test_the_controller_says_when_untrusted_estimates_hold_the_robot(caplog):
    """A covered lens: 30 estimates a second, each valid: false with npi 0, each answered with
    a stale stop, as it should be; but the status stayed as before (no held_since, no count,
    no error) and vistrack status said ok, though the README says the status tells when the
    robot is held (a hunt of the controller, helper h2)."""
    import logging

    from vistrack.services.fuzzy_controller.service import loop

    caplog.set_level(logging.INFO, logger="vistrack.fuzzy_controller")

    def estimate(seq: int, npi: int) -> bytes:
        return Estimate(seq=seq, stamp_ns=time.time_ns(), npi=npi, xc=100.0, yc=100.0,
                        xe=400.0, ye=400.0, dx=2.0 * seq, dy=0.0, scale=1.0, t_ms=1.0,
                        first=seq == 0, features=[], params_id=0, width=256,
                        height=256).encode()

    with Running("fuzzy_controller", loop, parse("fuzzy-controller")) as node:
        command_for(node, estimate(0, 40))
        assert not command_for(node, estimate(1, 40)).stale
        assert "held_since" not in node.status.as_dict()["extra"]
        for seq in range(2, 6):  # the lens covered
            assert command_for(node, estimate(seq, 0)).stale
        extra = node.status.as_dict()["extra"]
        assert "held_since" in extra and extra["untrusted"] == 4
        held = [r.getMessage() for r in caplog.records
                if "holding the robot stopped" in r.getMessage()]
        assert len(held) == 1 and "seq 2 cannot be trusted (valid false, npi 0" in held[0]
        command_for(node, estimate(6, 40))  # texture again: a new set point, then moves
        assert not command_for(node, estimate(7, 40)).stale
        assert "held_since" not in node.status.as_dict()["extra"]


def test_an_estimate_that_comes_late_does_not_move_the_set_point():
    """A copy of an estimate two frames old (seq 2 lower, stamped 67 ms earlier) was taken for
    a camera restart: a new set point from it, and the commands for the same target fell from
    -0.42 to -0.10 m/s for the rest of the track (a hunt of the controller). It is ignored and
    counted; the commands are those of the same run without it."""
    from vistrack.services.fuzzy_controller.service import loop

    def run(late: bool) -> tuple[list[float], dict]:
        base = time.time_ns()

        def estimate(seq: int) -> bytes:  # a target right of centre, drifting right
            return Estimate(seq=seq, stamp_ns=base + seq * 33_000_000, npi=40,
                            xc=138.0 + seq, yc=100.0, xe=400.0, ye=400.0, dx=float(seq),
                            dy=0.0, scale=1.0, t_ms=1.0, first=seq == 0, features=[],
                            params_id=0, width=256, height=256).encode()

        with Running("fuzzy_controller", loop, parse("fuzzy-controller")) as node:
            vy = [command_for(node, estimate(seq)).vy for seq in range(6)]
            if late:
                stale = estimate(3)
                # taken before the next (the estimates' input keeps the latest only)
                taken = node.status.as_dict()["received"]
                wait_for(lambda: node.feed(node.keys.estimate, stale), what="a subscription")
                wait_for(lambda: node.status.as_dict()["received"] > taken,
                         what="the late estimate taken in")
                time.sleep(0.3)  # and handled (well under a millisecond)
            vy += [command_for(node, estimate(seq)).vy for seq in range(6, 9)]
            return vy, dict(node.status.extra)

    plain, _ = run(late=False)
    with_late, extra = run(late=True)
    # the same commands (to the controller's timing: it reads the clock for lateness)
    assert with_late == pytest.approx(plain, abs=1e-3) and plain[-1] < -0.05
    assert extra["came_late"] == 1


def test_the_controller_does_not_move_on_an_estimate_valid_with_too_few_features():
    """The CONTRACT: valid is false when NPI < 3. A peer's valid: true with npi 0, 1 or 2 moved
    the robot of a controller run with --min-npi 0 (whose own NPI check then passes)."""
    from vistrack.services.fuzzy_controller.service import loop

    base = time.time_ns()

    def estimate(seq: int, npi: int) -> bytes:
        return Estimate(seq=seq, stamp_ns=base + seq * 33_000_000, npi=npi, xc=100.0,
                        yc=100.0, xe=400.0, ye=400.0, dx=6.0 * seq, dy=0.0, scale=1.0,
                        t_ms=1.0, first=seq == 0, valid=True, features=[], params_id=0,
                        width=256, height=256).encode()

    with Running("fuzzy_controller", loop, parse("fuzzy-controller", "--min-npi", "0")) as node:
        answered = [command_for(node, estimate(seq, npi))
                    for seq, npi in enumerate((40, 40, 2, 0, 40))]
    assert [c.stale for c in answered] == [False, False, True, True, False]
    assert all((c.vx, c.vy, c.wz) == (0.0, 0.0, 0.0) for c in answered[2:4])
    assert answered[4].vy != 0.0
