"""A ``--loop`` source's wrap end to end in-process (the MemoryNode seam): the camera counts a
cut at the first frame of each later pass (``cuts``), pre-processing passes it on with the
candidates of the frame after a cut, and motion-estimation starts a new track there instead
of tracking the jump back to the start as motion (``dx`` stepped back by the whole pass at
every wrap, a sawtooth in every recording of a looped file)."""

from __future__ import annotations

import time

import cv2
import msgpack
import numpy as np
import pytest

from vistrack.common import synthetic
from vistrack.common.messages import Demand, Estimate, Frame, PreFrame
from vistrack.common.params import TrackerParams
from vistrack.common.vision import preprocess

from loops import IDLE_S, Running


def _wait(condition, what: str) -> None:
    deadline = time.monotonic() + IDLE_S
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.002)


def _pre_frame(image: np.ndarray, seq: int, cuts: int) -> bytes:
    pre = preprocess(image, TrackerParams())
    return PreFrame(seq=seq, stamp_ns=time.time_ns() + seq, width=image.shape[1],
                    height=image.shape[0], data=pre.filtered, candidates=pre.candidates,
                    strength=pre.strength, params_id=0, cuts=cuts).encode()


@pytest.mark.parametrize("cut", [True, False])
def test_motion_estimation_starts_a_new_track_at_a_cut(cut):
    """Four frames moving 1.5 px a frame right, then the first one again (a 4-frame loop's
    wrap). With ``cuts`` one more from there, its estimate is a new track's first (dx 0,
    scale 1), and the track goes on from there; with ``cuts`` unchanged, the jump back is
    tracked as motion, as before the field."""
    frames = synthetic.sequence(4, size=(128, 128))
    feed = [*frames, frames[0], frames[1]]
    with Running("motion-estimation") as me:
        node = me.node
        for seq, image in enumerate(feed):
            payload = _pre_frame(image, seq, int(cut and seq >= 4))
            me.feed(node.keys.pre_frame, payload)
            _wait(lambda seq=seq: len(node.published_on(node.keys.estimate)) > seq,
                  f"estimate {seq}")
        got = [Estimate.decode(p) for p in node.published_on(node.keys.estimate)]
    assert [e.first for e in got] == [True, False, False, False, cut, False]
    assert all(e.valid and e.npi >= 10 for e in got)
    assert got[3].dx == pytest.approx(4.5, abs=0.3)  # 3 steps of 1.5 px before the wrap
    if cut:
        assert (got[4].dx, got[4].dy, got[4].scale) == (0.0, 0.0, 1.0)
        assert got[5].dx == pytest.approx(1.5, abs=0.3)  # the new track's first step
    else:
        assert got[4].dx == pytest.approx(0.0, abs=0.3)  # 4.5 px back: tracked as motion
        assert got[5].dx == pytest.approx(1.5, abs=0.3)


def test_a_cut_whose_frame_was_dropped_still_starts_a_new_track():
    """The wrap's first frame overwritten at a latest-only input (seq 4 never arrives): the
    frame after it counts the cut too, and starts the new track. (A flag on the cut frame
    alone went with it, and the jump was tracked as motion.)"""
    frames = synthetic.sequence(4, size=(128, 128))
    feed = [(0, frames[0], 0), (1, frames[1], 0), (2, frames[2], 0), (3, frames[3], 0),
            (5, frames[1], 1), (6, frames[2], 1)]
    with Running("motion-estimation") as me:
        node = me.node
        for k, (seq, image, cuts) in enumerate(feed):
            me.feed(node.keys.pre_frame, _pre_frame(image, seq, cuts))
            _wait(lambda k=k: len(node.published_on(node.keys.estimate)) > k, f"estimate {k}")
        got = [Estimate.decode(p) for p in node.published_on(node.keys.estimate)]
    assert [(e.seq, e.first) for e in got] == [(0, True), (1, False), (2, False), (3, False),
                                               (5, True), (6, False)]
    assert got[4].dx == 0.0 and got[5].dx == pytest.approx(1.5, abs=0.3)


def test_preprocessing_passes_a_cut_on_with_the_candidates_the_new_track_reads():
    """Motion-estimation has said it reads no candidates (a held track): a frame goes
    deferred, without them, but the first after a cut (``cuts`` 0 -> 1) goes with them; each
    keeps its ``cuts``."""
    image = synthetic.sequence(1, size=(128, 128))[0]
    with Running("preprocessing") as pre:
        node = pre.node
        pre.feed(node.keys.demand, Demand(seq=0, stamp_ns=1, candidates=False).encode(),
                 reliable=True)
        for seq, cuts in ((0, 0), (1, 1), (2, 1)):
            pre.feed(node.keys.frame, Frame.from_image(image, seq=seq, stamp_ns=10 + seq,
                                                       cuts=cuts).encode())
            _wait(lambda seq=seq: len(node.published_on(node.keys.pre_frame)) > seq,
                  f"pre-processed frame {seq}")
        got = [PreFrame.decode(p) for p in node.published_on(node.keys.pre_frame)]
    assert [(m.seq, m.cuts, m.deferred) for m in got] == [(0, 0, True), (1, 1, False),
                                                         (2, 1, True)]
    assert len(got[1].candidates) > 10 and len(got[0].candidates) == 0


def test_a_looping_camera_marks_the_first_frame_of_each_later_pass(tmp_path):
    """Three images looped at 200 fps: seq 3 and 6 start the second and third passes, and
    the count of cuts grows by one at each."""
    rng = np.random.default_rng(0)
    for i in range(3):
        cv2.imwrite(str(tmp_path / f"f{i}.png"), rng.integers(0, 256, (60, 80), dtype=np.uint8))
    with Running("camera", "--source", f"file:{tmp_path}", "--loop", "--fps", "200") as cam:
        _wait(lambda: len(cam.node.published_on(cam.node.keys.frame)) >= 8, "8 frames")
    sent = [msgpack.unpackb(p) for p in cam.node.published_on(cam.node.keys.frame)][:8]
    assert [m["seq"] for m in sent] == list(range(8))
    assert [m["cuts"] for m in sent] == [0, 0, 0, 1, 1, 1, 2, 2]


def test_a_looping_simulator_marks_the_frame_its_scenario_starts_again(tmp_path):
    """A 0.1 s scenario at 100 fps: 10 frames a pass, its start again at seq 10 and 20."""
    scenario = tmp_path / "short.yaml"
    scenario.write_text("name: short\nduration_s: 0.1\ncomponents:\n"
                        "  - {type: ramp, axis: lateral, start_s: 0, end_s: 0.1, delta_m: 0.2}\n")
    with Running("camera", "--source", f"sim:{scenario}", "--loop", "--fps", "100",
                 "--no-control", "--size", "64x48") as cam:
        _wait(lambda: len(cam.node.published_on(cam.node.keys.frame)) >= 25, "25 frames")
    sent = [msgpack.unpackb(p) for p in cam.node.published_on(cam.node.keys.frame)][:25]
    assert [m["seq"] for m in sent] == list(range(25))
    assert [m["cuts"] for m in sent] == [0] * 10 + [1] * 10 + [2] * 5
