"""A file camera in lockstep (``--fps 0 --in-flight 1``) loses no frame: a frame whose estimate
does not come is sent again, and motion-estimation answers a frame it has already tracked with
the same estimate, so nothing is tracked twice.

The camera, pre-processing and motion-estimation loops run in-process on MemoryNodes; the test
carries each one's output to the next, as Zenoh does, and loses the transmissions it is told
to, on any hop: Zenoh lost the one message in flight now and then on a loaded machine.
"""

from __future__ import annotations

import time

import pytest

from vistrack.common import synthetic
from vistrack.common.bus import MemoryNode
from vistrack.common.messages import CmdVel, Estimate, Frame, PreDone, peek_seq
from vistrack.common.params import TrackerParams
from vistrack.common.vision import Tracker
from vistrack.services.camera import service as camera

from loops import IDLE_S, Running

ACK_TIMEOUT_S = 0.2
N = 8
FRAME, PRE, EST = 0, 1, 2  # the hops: camera -> pre-processing -> motion-estimation -> camera


def run(lose: dict[tuple[int, int], int], *argv: str, done: bool = True
        ) -> tuple[MemoryNode, MemoryNode, list[bytes]]:
    """The three loops over the built-in sequence, the camera given ``argv``, the first
    ``lose[hop, seq]`` transmissions of ``seq`` on ``hop`` lost (and none of
    ``preprocessing/done`` carried unless ``done``); the camera's and motion-estimation's
    nodes, and what the latter published on ``motion/estimate``."""
    images = synthetic.builtin_sequence(N)
    with Running("preprocessing") as pre, Running("motion-estimation") as me:
        for r in (pre, me):  # kernels loaded, as `vistrack up` starts the camera after them
            deadline = time.monotonic() + IDLE_S
            while not r.node.alive:
                assert r.thread.is_alive() and time.monotonic() < deadline, r.node.service
                time.sleep(0.01)
        with Running("camera", "--ack-timeout", str(ACK_TIMEOUT_S), *argv, target=camera.loop,
                     extra=(iter(images),)) as cam:
            return _carry(cam, pre, me, lose, done)


def _carry(cam: Running, pre: Running, me: Running, lose: dict[tuple[int, int], int],
           done: bool) -> tuple[MemoryNode, MemoryNode, list[bytes]]:
    keys = cam.node.keys
    hops = [(cam, keys.frame, pre), (pre, keys.pre_frame, me), (me, keys.estimate, cam)]
    if done:  # what the camera subscribes to of pre-processing's (with --in-flight > 1)
        hops.append((pre, keys.pre_done, cam))
    carried = [0] * len(hops)
    sent: dict[tuple[int, int], int] = {}
    deadline = time.monotonic() + IDLE_S + 10 * N * ACK_TIMEOUT_S
    while cam.thread.is_alive():  # a file camera ends after its last frame's estimate
        assert time.monotonic() < deadline, "the camera did not end"
        moved = False
        for hop, (src, key, dst) in enumerate(hops):
            for payload, reliable in [(p.payload, p.reliable) for p in src.node.published
                                      if p.key == key][carried[hop]:]:
                carried[hop] += 1
                seq = peek_seq(payload)
                sent[hop, seq] = sent.get((hop, seq), 0) + 1
                if sent[hop, seq] > lose.get((hop, seq), 0) and dst.node.subscribed(key):
                    dst.feed(key, payload, wait=dst is not cam, reliable=reliable)
                    moved = True
        if not moved:
            time.sleep(0.001)
    for r in (cam, pre, me):
        assert (r.node.status.rejected, r.node.status.failed) == (0, 0), r.node.service
    return cam.node, me.node, me.node.published_on(keys.estimate)


def offline() -> list:
    tracker = Tracker(TrackerParams())
    return [tracker.process(f) for f in synthetic.builtin_sequence(N)]


def assert_every_frame_tracked_once(published: list[bytes], expected: list) -> None:
    first: dict[int, bytes] = {}
    for payload in published:  # an estimate published again is the same bytes: not re-tracked
        assert first.setdefault(peek_seq(payload), payload) == payload
    got = [Estimate.decode(first[seq]) for seq in sorted(first)]
    assert [m.seq for m in got] == [e.seq for e in expected]
    for msg, e in zip(got, expected, strict=True):
        for k in ("seq", "npi", "xc", "yc", "xe", "ye", "dx", "dy", "scale", "first"):
            assert getattr(msg, k) == getattr(e, k), (e.seq, k)
        assert msg.features == e.features(), e.seq


# The counts are lower bounds: a frame slower than ACK_TIMEOUT_S (a loaded machine) is sent
# again too, and answered again; what must hold exactly is that every frame is tracked once.
@pytest.mark.parametrize(("lose", "resent", "repeated"), [
    ({(FRAME, 2): 1}, 1, 0),  # a frame lost on its way to pre-processing
    ({(PRE, 4): 1}, 1, 0),  # a pre-processed frame on its way to motion-estimation
    ({(EST, 6): 1}, 1, 1),  # an estimate on its way back to the camera
    ({(FRAME, 1): 1, (PRE, 3): 1, (EST, 5): 2}, 4, 2),  # all three, the last one twice
], ids=["frame", "pre-processed", "estimate", "every-hop"])
def test_a_lost_message_is_sent_again_and_no_frame_is_lost(lose, resent, repeated):
    cam, me, published = run(lose)
    assert_every_frame_tracked_once(published, offline())
    assert cam.status.extra.get("resent", 0) >= resent
    assert cam.status.extra.get("ack_timeouts", 0) == 0
    assert me.status.extra.get("repeated", 0) >= repeated
    assert len(published) == N + me.status.extra.get("repeated", 0)
    assert me.status.dropped == 0  # no gap in the frames' seq either
    # reliable (BLOCK): a subscriber outside the loop (a recorder) loses none either
    frames = [p for p in cam.published if p.key == cam.keys.frame]
    assert len(frames) >= N + resent and all(p.reliable for p in frames)
    # and so are the answers to them, the ones sent again included: a recorder gets every
    # estimate of a file's run
    answers = [p for p in me.published if p.key == me.keys.estimate]
    assert len(answers) == len(published) and all(p.reliable for p in answers)


@pytest.mark.parametrize("done", [True, False], ids=["done", "no-done"])
def test_two_in_flight_track_every_frame_once_without_the_pre_processed_frames(done):
    """--fps 0 --in-flight 2: pre-processing works on frame n while motion-estimation tracks
    n-1. The camera sends a frame once pre-processing is free, which ``preprocessing/done``
    tells it in a few bytes; it never receives the pre-processed frames themselves. Without
    those (a pre-processing that does not publish them) each frame's estimate tells it
    instead, one frame in flight: slower, and still no frame overwritten or lost."""
    cam, me, published = run({}, "--in-flight", "2", done=done)
    assert cam.subscribed(cam.keys.pre_done) and not cam.subscribed(cam.keys.pre_frame)
    assert_every_frame_tracked_once(published, offline())
    assert me.status.dropped == 0 and cam.status.extra.get("ack_timeouts", 0) == 0
    assert len(published) == N  # none sent again (that is one in flight, lockstep's)


def test_pre_processing_says_it_is_done_with_each_frame_after_publishing_it():
    """``preprocessing/done`` follows each ``preprocessing/frame``, with the frame's seq and
    stamp_ns, BLOCK where the frame came BLOCK (a file camera's pacing) and latest-only
    where it did not (a live camera's)."""
    images = synthetic.builtin_sequence(4)
    with Running("preprocessing") as pre:
        keys = pre.node.keys
        for seq, image in enumerate(images):
            pre.feed(keys.frame, Frame.from_image(image, seq=seq, stamp_ns=1000 + seq).encode(),
                     reliable=seq % 2 == 0)
        out = [p for p in pre.node.published if p.key in (keys.pre_frame, keys.pre_done)]
    assert [(p.key, peek_seq(p.payload), p.reliable) for p in out] == [
        (key, seq, seq % 2 == 0) for seq in range(4) for key in (keys.pre_frame, keys.pre_done)]
    done = [PreDone.decode(p.payload) for p in out if p.key == keys.pre_done]
    assert [(m.seq, m.stamp_ns) for m in done] == [(seq, 1000 + seq) for seq in range(4)]


def test_a_paced_camera_publishes_latest_only():
    """At --fps F a frame is worth less than the next one: a slow link drops it (BLOCK_FIRST)
    rather than hold the camera back."""
    images = synthetic.builtin_sequence(N)
    with Running("camera", "--fps", "200", "--ack-timeout", str(ACK_TIMEOUT_S),
                 target=camera.loop, extra=(iter(images),)) as cam:
        cam.thread.join(IDLE_S + 2 * ACK_TIMEOUT_S)  # no estimate comes: it waits, then ends
        assert not cam.thread.is_alive()
    frames = [p for p in cam.node.published if p.key == cam.node.keys.frame]
    assert len(frames) == N and not any(p.reliable for p in frames)


def test_a_file_run_with_two_in_flight_publishes_its_frames_reliable():
    """--fps 0 --in-flight 2: frames BLOCK as in lockstep (at most two queue), so no frame
    and no estimate of a file's run is lost uncounted; a frame whose estimate does not come
    is not sent again (that is lockstep's, one in flight)."""
    images = synthetic.builtin_sequence(N)
    with Running("camera", "--in-flight", "2", "--ack-timeout", str(ACK_TIMEOUT_S),
                 target=camera.loop, extra=(iter(images),)) as cam:
        cam.thread.join(IDLE_S + (N + 2) * ACK_TIMEOUT_S)  # no answer comes: it ends
        assert not cam.thread.is_alive()
    frames = [p for p in cam.node.published if p.key == cam.node.keys.frame]
    assert [peek_seq(p.payload) for p in frames] == list(range(N))
    assert all(p.reliable for p in frames)


def test_a_frame_that_never_gets_through_is_given_up_and_the_camera_goes_on():
    """A pipeline that stops answering (a service restarted) costs the camera (1 + RESENDS)
    ack timeouts for that frame, then it goes on: every other frame is tracked."""
    cam, me, published = run({(FRAME, 3): 1 + camera.RESENDS})
    assert sorted({peek_seq(p) for p in published}) == [s for s in range(N) if s != 3]
    assert cam.status.extra["resent"] >= camera.RESENDS
    assert cam.status.extra["ack_timeouts"] >= 1
    assert me.status.dropped == 1  # the seq gap


def _estimate(seq: int, stamp_ns: int) -> bytes:
    return Estimate(seq=seq, stamp_ns=stamp_ns, npi=40, xc=90.0, yc=128.0, xe=400.0, ye=400.0,
                    dx=0.0, dy=0.0, scale=1.0, t_ms=1.0, first=seq == 0, valid=True,
                    features=[], params_id=0).encode()


@pytest.mark.parametrize(("argv", "reliable"), [
    (("--lockstep", "--no-control", "--ack-timeout", "0.05"), True),  # one frame in flight
    (("--fps", "100"), False),  # real time: the next frame is worth more
])
def test_the_simulator_in_lockstep_publishes_its_frames_reliable(argv, reliable):
    with Running("camera", "--source", "sim", *argv, target=camera.loop) as cam:
        deadline = time.monotonic() + IDLE_S
        while len(cam.node.published_on(cam.node.keys.frame)) < 3:
            assert cam.thread.is_alive() and time.monotonic() < deadline
            time.sleep(0.01)
    frames = [p for p in cam.node.published if p.key == cam.node.keys.frame]
    assert {p.reliable for p in frames} == {reliable}


def test_an_estimate_published_again_moves_the_robot_once():
    """The controller sends one command for an estimate that comes twice (published again
    for a frame the camera sent again), and does not count it as bad input. A later frame
    stamped before it (the camera's clock set back) is no bad input either: it was refused
    as out of order, and so was every one after it for as long as the step; it is taken,
    its timing anew, and counted as a clock step."""
    now = time.time_ns()
    with Running("fuzzy-controller") as fc:
        key = fc.node.keys.estimate
        for payload in (_estimate(0, now), _estimate(0, now), _estimate(1, now + 10**7)):
            fc.feed(key, payload, wait=True)
        stamps = [CmdVel.decode(p).stamp_ns for p in fc.node.published_on(fc.node.keys.cmd_vel)]
        # (the watchdog's stops, should these estimates get old, carry the time they are sent)
        assert (stamps.count(now), stamps.count(now + 10**7)) == (1, 1)
        assert fc.node.status.extra["repeated"] == 1 and fc.node.status.rejected == 0
        fc.feed(key, _estimate(2, now + 5 * 10**6), wait=True)  # stamped before seq 1's
        assert fc.node.status.rejected == 0 and fc.node.status.extra["clock_steps"] == 1
        stamps = [CmdVel.decode(p).stamp_ns for p in fc.node.published_on(fc.node.keys.cmd_vel)]
        assert stamps.count(now + 5 * 10**6) == 1


def test_a_frame_sent_again_is_buffered_once_by_the_tuner():
    images = synthetic.builtin_sequence(N)
    stamp = time.time_ns()
    # tuning on (no cycle starts: the buffer of 30 is far from full), so that it takes every
    # frame for its initial tuning's buffer
    with Running("auto-tuner") as tuner:
        key = tuner.node.keys.frame
        for seq, image in ((0, images[0]), (0, images[0]), (1, images[1])):
            tuner.feed(key, Frame.from_image(image, seq=seq, stamp_ns=stamp + seq).encode(),
                       wait=True)
        assert tuner.node.status.extra["buffered"] == 2
