"""``motion/demand``: pre-processing leaves out the candidates motion-estimation will not read,
and the estimates stay exactly those of ``vistrack track``.

Both loops run in-process on MemoryNodes, wired by the test as Zenoh wires them: camera frames
into pre-processing, its frames into motion-estimation, motion-estimation's demands back into
pre-processing. The sequence (a texture moving 4 px a frame out of a 128x96 image, 30 features
at most) loses features every frame and re-detects three times in 40 frames.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from vistrack.common import synthetic
from vistrack.common.messages import Demand, Estimate, Frame, PreFrame
from vistrack.common.params import TrackerParams
from vistrack.common.vision import Tracker

from loops import Running

FLAGS = ["--max-features", "30"]


def frames() -> list[np.ndarray]:
    return synthetic.sequence(40, size=(96, 128), motion=synthetic.Motion(dx=4.0, dy=0.0),
                              seed=3)


def offline() -> tuple[list, Tracker]:
    tracker = Tracker(TrackerParams(max_features=30))
    return [tracker.process(f) for f in frames()], tracker


def assert_same(got: list[Estimate], expected: list) -> None:
    assert len(got) == len(expected)
    for msg, e in zip(got, expected, strict=True):
        for k in ("seq", "npi", "xc", "yc", "xe", "ye", "dx", "dy", "scale", "first"):
            assert getattr(msg, k) == getattr(e, k), (e.seq, k)
        assert msg.features == e.features(), e.seq


@pytest.mark.parametrize("mode", ["on-demand", "always"])
def test_the_demand_loop_defers_most_frames_and_estimates_as_offline(mode):
    expected, tracker = offline()
    assert tracker.redetections >= 2  # the sequence exercises re-detection
    with Running("preprocessing", *FLAGS, "--candidates", mode) as pre, \
            Running("motion-estimation", *FLAGS) as me:
        demands_fed = 0
        for seq, image in enumerate(frames()):
            pre.feed(pre.node.keys.frame,
                     Frame.from_image(image, seq=seq, stamp_ns=time.time_ns()).encode())
            me.feed(me.node.keys.pre_frame, pre.node.published_on(pre.node.keys.pre_frame)[-1])
            demands = me.node.published_on(me.node.keys.demand)
            for payload in demands[demands_fed:]:
                if mode == "on-demand":  # with --candidates always nothing subscribes to it
                    pre.feed(pre.node.keys.demand, payload)
            demands_fed = len(demands)
        sent = [PreFrame.decode(p) for p in pre.node.published_on(pre.node.keys.pre_frame)]
        got = [Estimate.decode(p) for p in me.node.published_on(me.node.keys.estimate)]
        said = [Demand.decode(p).candidates for p in me.node.published_on(me.node.keys.demand)]
        computed_here = me.node.status.extra.get("candidates_here", 0)
        for r in (pre, me):
            assert (r.node.status.rejected, r.node.status.failed) == (0, 0)
    assert_same(got, expected)
    deferred = [m.seq for m in sent if m.deferred]
    assert all(len(m.candidates) == 0 for m in sent if m.deferred)
    assert all(len(m.candidates) > 0 for m in sent if not m.deferred)
    if mode == "always":
        assert deferred == [] and computed_here == 0
    else:
        assert sent[0].deferred is False  # no demand yet: a first frame needs them
        assert True in said and False in said  # it asked, and it let go
        assert deferred, "no frame was deferred"
        assert computed_here <= tracker.redetections  # foreseen, mostly


def test_a_steady_track_defers_every_frame_after_the_first():
    """Features that stay (the built-in 256x256 sequence, no re-detection):
    only the first frame needs its candidates."""
    images = synthetic.builtin_sequence(12)
    tracker = Tracker(TrackerParams())
    expected = [tracker.process(f) for f in images]
    assert tracker.redetections == 0 and expected[-1].npi >= 90
    with Running("preprocessing") as pre, Running("motion-estimation") as me:
        for seq, image in enumerate(images):
            pre.feed(pre.node.keys.frame,
                     Frame.from_image(image, seq=seq, stamp_ns=time.time_ns()).encode())
            me.feed(me.node.keys.pre_frame, pre.node.published_on(pre.node.keys.pre_frame)[-1])
            for payload in me.node.published_on(me.node.keys.demand)[-1:]:
                pre.feed(pre.node.keys.demand, payload)
        sent = [PreFrame.decode(p) for p in pre.node.published_on(pre.node.keys.pre_frame)]
        got = [Estimate.decode(p) for p in me.node.published_on(me.node.keys.estimate)]
        assert pre.node.status.extra["deferred"] == len(images) - 1
    assert_same(got, expected)
    assert [m.deferred for m in sent] == [False] + [True] * (len(images) - 1)


def test_deferred_frames_alone_give_the_offline_estimates():
    """Every frame deferred (a pre-processing that was told no, a recording of one):
    motion-estimation computes the candidates it reads, first frame and re-detections, from
    the filtered frames, and the estimates are the same."""
    from vistrack.common.vision import preprocess

    expected, tracker = offline()
    params = TrackerParams(max_features=30)
    with Running("motion-estimation", *FLAGS) as me:
        for seq, image in enumerate(frames()):
            msg = PreFrame(seq=seq, stamp_ns=time.time_ns(), width=image.shape[1],
                           height=image.shape[0], data=preprocess(image, params).filtered,
                           candidates=np.empty((0, 2), np.int16),
                           strength=np.empty(0, np.float32), params_id=0, deferred=True)
            me.feed(me.node.keys.pre_frame, msg.encode())
        got = [Estimate.decode(p) for p in me.node.published_on(me.node.keys.estimate)]
        computed_here = me.node.status.extra.get("candidates_here", 0)
    assert_same(got, expected)
    assert computed_here == 1 + tracker.redetections  # the first frame and each re-detection
