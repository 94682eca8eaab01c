"""A frame's work rehearsed just before the next frame is expected
(:class:`vistrack.services.runtime.Rehearsal`): when, how often, and that it keeps nothing."""

from __future__ import annotations

import logging
import time

import numpy as np
import pytest
from test_valid import Running, parse, pre_frame, wait_for

from vistrack.common import synthetic
from vistrack.common.bus import MemoryNode
from vistrack.common.messages import Estimate, PreFrame, encode_frame
from vistrack.common.params import TrackerParams
from vistrack.common.vision import Tracker, preprocess
from vistrack.services.runtime import REHEARSAL_LEAD_S, Rehearsal

log = logging.getLogger("test")


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def _rehearsal(rehearse=lambda: True) -> tuple[Rehearsal, Clock, MemoryNode, list[float]]:
    clock, node, calls = Clock(), MemoryNode("test"), []

    def counted(payload: bytes) -> bool:
        assert payload == b"frame"  # the last one that came
        calls.append(clock.now)
        return rehearse()

    return Rehearsal(node, "k", counted, log, clock=clock), clock, node, calls


def _arrivals(r: Rehearsal, clock: Clock, gaps: list[float]) -> None:
    for gap in gaps:
        clock.now += gap
        r.arrived(b"frame")


def test_a_frame_is_rehearsed_once_just_before_it_is_expected():
    r, clock, node, calls = _rehearsal()
    _arrivals(r, clock, [0.0, 0.033, 0.034, 0.032, 0.033])  # a period of 33 ms
    last = clock.now
    due = last + 0.033 - REHEARSAL_LEAD_S
    clock.now = last + 0.010
    assert r.wait(0.1) == pytest.approx(due - clock.now)  # the loop wakes when it is due
    assert calls == []
    clock.now = due + 0.0005
    assert r.wait(0.1) == 0.1 and calls == [clock.now]
    clock.now += 0.001
    assert r.wait(0.1) == 0.1 and len(calls) == 1  # once a frame
    assert node.status.extra["rehearsals"] == 1
    _arrivals(r, clock, [0.0025])  # the next frame: rehearsed again before the one after it
    clock.now += 0.031
    r.wait(0.1)
    assert len(calls) == 2 and node.status.extra["rehearsals"] == 2


@pytest.mark.parametrize("gaps", [
    [0.0, 0.001, 0.001, 0.001, 0.001],  # unpaced: the caches stay warm between frames
    [0.0, 2.0, 2.0, 2.0],  # too slow to predict (a camera waiting in lockstep)
    [0.0, 0.033, 0.033],  # too few gaps yet
])
def test_frames_too_close_too_far_apart_or_too_few_are_not_rehearsed(gaps):
    r, clock, node, calls = _rehearsal()
    _arrivals(r, clock, gaps)
    for _ in range(400):
        clock.now += 0.005
        assert r.wait(0.1) == 0.1
    assert calls == [] and node.status.extra["rehearsals"] == 0


def test_a_late_frame_is_not_rehearsed_for():
    """Past its time by more than the lead, the frame may be arriving: no rehearsal in its
    way."""
    r, clock, _, calls = _rehearsal()
    _arrivals(r, clock, [0.0, 0.033, 0.033, 0.033])
    clock.now += 0.033 + 0.001  # the loop was busy until after the frame was due
    assert r.wait(0.1) == 0.1 and calls == []
    clock.now += 0.040
    assert r.wait(0.1) == 0.1 and calls == []


def test_a_rehearsal_that_fails_is_said_and_not_tried_again(caplog):
    def broken() -> bool:
        raise RuntimeError("no kernel")

    r, clock, node, calls = _rehearsal(broken)
    for _ in range(3):
        _arrivals(r, clock, [0.033] * 4)
        clock.now += 0.031
        r.wait(0.1)
    assert len(calls) == 1 and node.status.extra["rehearsals"] == 0
    assert "rehearsing a frame's work failed" in caplog.text


def test_a_trackers_rehearsal_keeps_nothing():
    """Rehearsed before every frame, a tracker gives the same estimates as one that never
    is (nothing kept: its features, velocities, counters, noise)."""
    params = TrackerParams()
    pres = [preprocess(f, params) for f in synthetic.sequence(8, size=(128, 128))]
    plain, rehearsed = Tracker(params), Tracker(params)
    assert not rehearsed.rehearse()  # no frame yet
    for pre in pres:
        a = plain.update(pre)
        b = rehearsed.update(pre)
        assert rehearsed.rehearse()
        assert a.as_dict() | {"t_ms": 0} == b.as_dict() | {"t_ms": 0}
        assert plain.lost_by == rehearsed.lost_by and plain.followed == rehearsed.followed
    assert not Tracker(TrackerParams.paper()).rehearse()


def _at_30_fps(node: MemoryNode, key: str, out_key: str, payloads: list[bytes]) -> list[bytes]:
    """Feed ``payloads`` on ``key`` 33 ms apart, each once the one before is answered on
    ``out_key`` (a latest-only input: one fed while the service is still busy, on a slow
    first frame, could be written over); all the service has published there."""
    start = len(node.published_on(out_key))
    for n, payload in enumerate(payloads, start + 1):
        t0 = time.monotonic()
        wait_for(lambda payload=payload: node.feed(key, payload), what="a subscription")
        wait_for(lambda n=n: len(node.published_on(out_key)) == n, what=f"output {n}")
        time.sleep(max(0.0, 0.033 - (time.monotonic() - t0)))
    return node.published_on(out_key)


@pytest.mark.parametrize("flags", [(), ("--no-rehearsal",)])
def test_motion_estimation_rehearses_between_frames_at_30_fps(flags):
    """Frames 33 ms apart: the service rehearses before them (status ``rehearsals``) unless
    told not to, and its estimates are the tracker's own either way."""
    from vistrack.services.motion_estimation.service import loop

    # 30 frames: a rehearsal due while the machine is busy (the suite's other worker) wakes
    # late and is skipped, as it should be; of 12, one was rehearsed on a loaded run
    frames = synthetic.sequence(30, size=(128, 128))
    offline = Tracker(TrackerParams())
    with Running("motion_estimation", loop, parse("motion-estimation", *flags)) as node:
        out = _at_30_fps(node, node.keys.pre_frame, node.keys.estimate,
                         [pre_frame(image, seq) for seq, image in enumerate(frames)])
        got = [Estimate.decode(p) for p in out]
        rehearsals = node.status.extra.get("rehearsals")
    if flags:
        assert rehearsals is None
    else:
        assert rehearsals >= 3, rehearsals  # from the 5th frame on, one before each on time
    for est, image in zip(got, frames, strict=True):
        want = offline.update(preprocess(image, TrackerParams()))
        assert est.npi == want.npi and (est.dx, est.dy, est.scale) == (want.dx, want.dy,
                                                                       want.scale)
        assert np.array_equal([f[1:] for f in est.features],
                              want.points.reshape(-1, 2)) or want.npi == 0


def test_preprocessing_rehearses_between_frames_at_30_fps():
    """The same for pre-processing: rehearsals before frames 33 ms apart, and every frame
    filtered as ``preprocess`` filters it."""
    from vistrack.services.preprocessing.service import loop

    frames = synthetic.sequence(30, size=(128, 128))  # 30: see the test above
    with Running("preprocessing", loop, parse("preprocessing")) as node:
        out = _at_30_fps(node, node.keys.frame, node.keys.pre_frame,
                         [encode_frame(image, seq=seq, stamp_ns=seq + 1)
                          for seq, image in enumerate(frames)])
        got = [PreFrame.decode(p) for p in out]
        rehearsals = node.status.extra["rehearsals"]
    assert rehearsals >= 3, rehearsals
    for msg, image in zip(got, frames, strict=True):
        assert np.array_equal(msg.data, preprocess(image, TrackerParams()).filtered)


def test_a_malformed_frame_is_rejected_and_rehearsed_around_without_a_fault():
    """A payload that does not decode, among frames 33 ms apart: rejected as ever (counted,
    the service goes on), and the rehearsal that would decode it again skips it rather than
    fail; the frames after it are tracked and rehearsed."""
    from vistrack.services.motion_estimation.service import loop

    frames = synthetic.sequence(10, size=(128, 128))
    payloads = [pre_frame(image, seq) for seq, image in enumerate(frames)]
    with Running("motion_estimation", loop, parse("motion-estimation")) as node:
        _at_30_fps(node, node.keys.pre_frame, node.keys.estimate, payloads[:6])
        before = node.status.extra["rehearsals"]
        node.feed(node.keys.pre_frame, b"\x81\xa1v\x07")  # a map, but not a frame
        time.sleep(0.033)
        wait_for(lambda: node.status.as_dict()["rejected"] == 1, what="the rejection")
        out = _at_30_fps(node, node.keys.pre_frame, node.keys.estimate, payloads[6:])
        status = node.status.as_dict()
    assert len(out) == len(frames) and status["failed"] == 0, status
    assert status["extra"]["rehearsals"] > before
