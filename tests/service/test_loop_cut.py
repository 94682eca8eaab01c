"""A ``--loop`` source's wrap end to end in-process (the MemoryNode seam): the camera marks the
first frame of each later pass ``cut``, pre-processing passes it on with its candidates, and
motion-estimation starts a new track there instead of tracking the jump back to the start
as motion (``dx`` stepped back by the whole pass at every wrap, a sawtooth in every
recording of a looped file)."""

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


def _pre_frame(image: np.ndarray, seq: int, cut: bool) -> bytes:
    pre = preprocess(image, TrackerParams())
    return PreFrame(seq=seq, stamp_ns=time.time_ns() + seq, width=image.shape[1],
                    height=image.shape[0], data=pre.filtered, candidates=pre.candidates,
                    strength=pre.strength, params_id=0, cut=cut).encode()


@pytest.mark.parametrize("cut", [True, False])
def test_motion_estimation_starts_a_new_track_at_a_cut(cut):
    """Four frames moving 1.5 px a frame right, then the first one again (a 4-frame loop's
    wrap). Marked cut, its estimate is a new track's first (dx 0, scale 1), and the track
    goes on from there; unmarked, the jump back is tracked as motion, as before the field."""
    frames = synthetic.sequence(4, size=(128, 128))
    feed = [*frames, frames[0], frames[1]]
    with Running("motion-estimation") as me:
        node = me.node
        for seq, image in enumerate(feed):
            payload = _pre_frame(image, seq, cut and seq == 4)
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


def test_preprocessing_passes_a_cut_on_with_the_candidates_the_new_track_reads():
    """Motion-estimation has said it reads no candidates (a held track): a plain frame goes
    deferred, without them; a cut frame goes with them, and says it is a cut."""
    image = synthetic.sequence(1, size=(128, 128))[0]
    with Running("preprocessing") as pre:
        node = pre.node
        pre.feed(node.keys.demand, Demand(seq=0, stamp_ns=1, candidates=False).encode(),
                 reliable=True)
        for seq, cut in ((0, False), (1, True), (2, False)):
            pre.feed(node.keys.frame, Frame.from_image(image, seq=seq, stamp_ns=10 + seq,
                                                       cut=cut).encode())
            _wait(lambda seq=seq: len(node.published_on(node.keys.pre_frame)) > seq,
                  f"pre-processed frame {seq}")
        got = [PreFrame.decode(p) for p in node.published_on(node.keys.pre_frame)]
    assert [(m.seq, m.cut, m.deferred) for m in got] == [(0, False, True), (1, True, False),
                                                        (2, False, True)]
    assert len(got[1].candidates) > 10 and len(got[0].candidates) == 0


def test_a_looping_camera_marks_the_first_frame_of_each_later_pass(tmp_path):
    """Three images looped at 200 fps: seq 3 and 6 start the second and third passes, and
    only they say ``cut``."""
    rng = np.random.default_rng(0)
    for i in range(3):
        cv2.imwrite(str(tmp_path / f"f{i}.png"), rng.integers(0, 256, (60, 80), dtype=np.uint8))
    with Running("camera", "--source", f"file:{tmp_path}", "--loop", "--fps", "200") as cam:
        _wait(lambda: len(cam.node.published_on(cam.node.keys.frame)) >= 8, "8 frames")
    sent = [msgpack.unpackb(p) for p in cam.node.published_on(cam.node.keys.frame)][:8]
    assert [m["seq"] for m in sent] == list(range(8))
    assert [m["seq"] for m in sent if m["cut"]] == [3, 6]


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
    assert [m["seq"] for m in sent if m["cut"]] == [10, 20]
