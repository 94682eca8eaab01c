"""The auto-tuner takes every frame only while a tuning waits for its buffer; between tunings
it takes one frame every SCENE_SAMPLE_S for the scene signal, and a change seen in those
samples starts the buffer again from consecutive frames. It watches at most one estimate every
ESTIMATE_PERIOD_S (every one at 30 fps).

The auto-tuner's loop runs in-process on a MemoryNode with its real worker process: a frame
fed while the loop is not subscribed is not delivered (``MemoryNode.feed`` returns False),
as Zenoh would not send it.
"""

from __future__ import annotations

import time

import msgpack
import numpy as np

from vistrack.common.messages import Estimate, Frame
from vistrack.common.synthetic import Motion, sequence
from vistrack.services.auto_tuner.service import ESTIMATE_PERIOD_S, SCENE_SAMPLE_S

from loops import IDLE_S, Running

BUFFER = 6


def _until(condition, what: str, timeout: float = IDLE_S) -> float:
    t0 = time.monotonic()
    while not condition():
        assert time.monotonic() - t0 < timeout, what
        time.sleep(0.005)
    return time.monotonic() - t0


def test_the_tuner_takes_every_frame_only_while_a_tuning_waits_for_them():
    scene_a = sequence(30, motion=Motion(dx=1.0, dy=0.5), seed=1)
    scene_b = sequence(30, motion=Motion(dx=-1.0), seed=5)
    seq = iter(range(10**6))

    def frame(image) -> bytes:
        n = next(seq)
        return Frame.from_image(image, seq=n, stamp_ns=10**9 + n).encode()

    with Running("auto-tuner", "--buffer", str(BUFFER), "--min-interval", "0",
                 "--tune-sweep-step", "5") as tuner:
        node, key = tuner.node, tuner.node.keys.frame
        extra = node.status.extra
        # the initial tuning waits for its buffer: every frame is taken, one after the other
        for i in range(BUFFER - 1):
            tuner.feed(key, frame(scene_a[i]))
        assert extra["every_frame"] and extra["buffered"] == BUFFER - 1
        assert node.subscribed(key)
        tuner.feed(key, frame(scene_a[BUFFER - 1]))
        _until(lambda: extra["tunings"] == 1, "the initial tuning")

        # between tunings: one frame, then none until SCENE_SAMPLE_S later
        _until(lambda: node.subscribed(key), "a sample to be due")
        assert not extra["every_frame"]
        tuner.feed(key, frame(scene_a[10]))
        assert not node.subscribed(key) and not node.feed(key, frame(scene_a[11]))
        waited = _until(lambda: node.subscribed(key), "the next sample to be due")
        assert waited >= 0.5 * SCENE_SAMPLE_S, waited
        assert extra["buffered"] == BUFFER  # the samples are not buffered
        received = node.status.received

        # another scene, seen in the samples: the buffer starts again, empty
        for image in scene_b[:12]:
            tuner.feed(key, frame(image))
            if extra["every_frame"]:
                break
        assert extra["every_frame"], extra
        assert extra["buffered"] == 0 and extra["pending"] == "scene change"
        samples = node.status.received - received
        assert 3 <= samples <= 5, samples  # the hysteresis confirms on the third
        # and fills with consecutive frames: none is refused until the tuning has them all
        for i, image in enumerate(scene_b[12:12 + BUFFER]):
            assert node.feed(key, frame(image)), f"frame {i} of the new buffer not taken"
            assert node.wait_idle(IDLE_S)
        _until(lambda: extra["tunings"] == 2, "the re-tune")
        reports = [msgpack.unpackb(p) for p in node.published_on(node.keys.report)]
    assert [r["trigger"] for r in reports] == ["initial tuning", "scene change"]
    assert [r["frames_offered"] for r in reports] == [BUFFER, BUFFER]


def _estimate(seq: int) -> bytes:
    return Estimate(seq=seq, stamp_ns=10**9 + seq, npi=0, xc=0.0, yc=0.0, xe=0.0, ye=0.0,
                    dx=0.0, dy=0.0, scale=1.0, t_ms=0.0, first=False, features=[],
                    params_id=0, valid=False).encode()


def test_the_tuner_watches_every_estimate_at_30_fps_and_paces_a_faster_stream():
    with Running("auto-tuner", "--no-tune") as tuner:
        node, key = tuner.node, tuner.node.keys.estimate

        def taken() -> int:  # one publisher, consecutive seq: what was not overwritten
            return node.status.received - node.status.dropped

        for seq in range(15):  # 30 fps
            tuner.feed(key, _estimate(seq))
            time.sleep(1 / 30)
        assert (taken(), node.status.dropped) == (15, 0)
        burst = [_estimate(seq) for seq in range(15, 215)]
        t0 = time.monotonic()
        for payload in burst:  # 200 at about 500 a second
            assert node.feed(key, payload)
            time.sleep(0.002)
        assert node.wait_idle(IDLE_S)
        elapsed = time.monotonic() - t0
        assert node.status.received == 215 and node.status.failed == 0
        assert taken() - 15 <= elapsed / ESTIMATE_PERIOD_S + 2, (taken(), elapsed)


def _tracked(seq: int, stamp_ns: int, scale: float, first: bool) -> bytes:
    """A valid estimate of 50 features (ids 0 to 49) at ``scale`` since its track began."""
    return Estimate(seq=seq, stamp_ns=stamp_ns, npi=50, xc=128.0, yc=128.0, xe=900.0, ye=900.0,
                    dx=0.0, dy=0.0, scale=scale, t_ms=1.0, first=first,
                    features=[[i, 10.0 + i, 20.0] for i in range(50)], params_id=0).encode()


def test_a_restarted_camera_starts_the_distance_watch_again_without_its_first_estimate():
    """The distance watch compares each estimate's accumulated scale with the scale when the
    last tuning started; a new track's scale starts again from 1, and so does the reference.
    The tuner reads one estimate in ESTIMATE_PERIOD_S, so a new track's first estimate
    (``first: true``) may not be read: ``seq`` going back (the camera restarted) tells it."""
    images = sequence(BUFFER, motion=Motion(dx=1.0), seed=1)
    with Running("auto-tuner", "--buffer", str(BUFFER), "--min-interval", "0",
                 "--tune-sweep-step", "5") as tuner:
        node, extra = tuner.node, tuner.node.status.extra
        for seq, scale in ((0, 1.0), (1, 1.25), (2, 1.25)):  # track A: 25 % nearer
            tuner.feed(node.keys.estimate, _tracked(seq, 10**9 + seq, scale, seq == 0))
            time.sleep(2 * ESTIMATE_PERIOD_S)
        assert extra["scale_ratio"] == 1.25
        for seq, image in enumerate(images):
            tuner.feed(node.keys.frame, Frame.from_image(image, seq=seq,
                                                         stamp_ns=10**9 + seq).encode())
        _until(lambda: extra["tunings"] == 1, "the initial tuning")  # its reference: 1.25
        # track B: the camera restarted, seq 0 (first) not read; no nearer than it began
        tuner.feed(node.keys.estimate, _tracked(1, 2 * 10**9, 1.0, False))
        assert extra["scale_ratio"] == 1.0


def test_an_old_estimate_that_comes_late_is_no_new_track():
    """An estimate two frames old that comes after a newer one (seq back by 2, stamped
    earlier, not a first) is a copy come late, not a restarted camera: taken for one, it
    set the distance watch's reference again (scale 1 where the track is 25 % nearer)."""
    images = sequence(BUFFER, motion=Motion(dx=1.0), seed=1)
    with Running("auto-tuner", "--buffer", str(BUFFER), "--min-interval", "0",
                 "--tune-sweep-step", "5") as tuner:
        node, extra = tuner.node, tuner.node.status.extra
        for seq, image in enumerate(images):
            tuner.feed(node.keys.frame, Frame.from_image(image, seq=seq,
                                                         stamp_ns=10**9 + seq).encode())
        _until(lambda: extra["tunings"] == 1, "the initial tuning")  # its reference: 1.0
        for seq, scale in ((0, 1.0), (1, 1.1), (2, 1.2), (3, 1.25)):
            tuner.feed(node.keys.estimate, _tracked(seq, 10**9 + seq, scale, seq == 0))
            time.sleep(2 * ESTIMATE_PERIOD_S)
        assert extra["scale_ratio"] == 1.25
        tuner.feed(node.keys.estimate, _tracked(1, 10**9 + 1, 1.1, False))  # late
        assert extra["scale_ratio"] == 1.25  # not a new track's 1.1


def test_the_buffer_keeps_only_the_frames_a_cycle_runs_on():
    """A cycle runs on the latest frames within --max-megapixels; the buffer kept --buffer
    frames all the same: 1000 frames of 4096x4096 held 16.8 GB for cycles that ran on 4."""
    big = np.zeros((1024, 1024), np.uint8)  # 1 MP: a budget of 4 MP keeps 4 of them
    with Running("auto-tuner", "--buffer", "12", "--max-megapixels", "4") as tuner:
        node, key = tuner.node, tuner.node.keys.frame
        for n in range(6):
            tuner.feed(key, Frame.from_image(big, seq=n, stamp_ns=10**9 + n).encode())
        assert node.status.extra["buffered"] == 4


def test_a_camera_restarted_while_the_buffer_fills_starts_it_again():
    """Frames of one camera, then another's (``seq`` back to 0): the buffer held both sides
    of the cut, and the tuning ran on two scenes (19 frames of one, 11 of the other) and
    took them for one reference. It starts again at the cut, and the tuning waits for a
    whole buffer of the new frames."""
    scene_a = sequence(BUFFER, motion=Motion(dx=1.0), seed=1)
    scene_b = sequence(BUFFER, motion=Motion(dx=-1.0), seed=5)
    with Running("auto-tuner", "--buffer", str(BUFFER), "--min-interval", "0",
                 "--tune-sweep-step", "5") as tuner:
        key, extra = tuner.node.keys.frame, tuner.node.status.extra
        for seq, image in enumerate(scene_a[:BUFFER - 2]):
            tuner.feed(key, Frame.from_image(image, seq=seq, stamp_ns=10**9 + seq).encode())
        assert extra["buffered"] == BUFFER - 2
        for seq, image in enumerate(scene_b[:BUFFER - 1]):  # the other camera, from seq 0
            tuner.feed(key, Frame.from_image(image, seq=seq, stamp_ns=2 * 10**9 + seq).encode())
            assert extra["buffered"] == seq + 1
        time.sleep(0.3)
        assert extra["tunings"] == 0 and not extra["tuning"]  # BUFFER - 1 of the new frames
        tuner.feed(key, Frame.from_image(scene_b[-1], seq=BUFFER - 1,
                                         stamp_ns=2 * 10**9 + BUFFER).encode())
        _until(lambda: extra["tunings"] == 1, "the initial tuning")


def test_frames_missed_for_a_while_start_the_buffer_again_and_a_few_skipped_do_not():
    images = sequence(3 * BUFFER, motion=Motion(dx=1.0), seed=1)
    with Running("auto-tuner", "--buffer", str(3 * BUFFER), "--min-interval", "0") as tuner:
        key, extra = tuner.node.keys.frame, tuner.node.status.extra

        def feed(i: int, seq: int, t_s: float) -> None:
            tuner.feed(key, Frame.from_image(images[i], seq=seq,
                                             stamp_ns=int((1 + t_s) * 1e9)).encode())
        for i in range(4):  # 30 fps
            feed(i, i, i / 30)
        feed(4, 12, 12 / 30)  # 8 frames skipped in 0.3 s: latest-only at speed
        assert extra["buffered"] == 5
        feed(5, 60, 2.0)  # 40 frames missed over 1.3 s: the stream broke off
        assert extra["buffered"] == 1


def test_a_worker_killed_while_it_starts_is_replaced_and_three_in_a_row_disable_tuning():
    """A worker that dies before it is ready (killed, out of memory) was taken for one that
    cannot start: tuning was off for good after one, with the status still ok and its
    every_frame and pending stale. A replacement starts; three in a row turn tuning off,
    said in the status."""
    import multiprocessing
    import os
    import signal

    def kill_the_worker_before_it_is_ready(pid_before: int | None) -> int:
        deadline = time.monotonic() + 30
        while True:
            workers = [p for p in multiprocessing.active_children()
                       if p.name == "auto-tuner-worker" and p.pid != pid_before
                       and p.is_alive()]
            if workers:
                os.kill(workers[0].pid, signal.SIGKILL)  # it takes ~1 s to be ready
                return workers[0].pid
            assert time.monotonic() < deadline, "no worker started"
            time.sleep(0.002)

    images = sequence(BUFFER, motion=Motion(dx=1.0), seed=1)
    with Running("auto-tuner", "--buffer", str(BUFFER), "--min-interval", "0",
                 "--tune-sweep-step", "5") as tuner:
        key, extra = tuner.node.keys.frame, tuner.node.status.extra
        killed = kill_the_worker_before_it_is_ready(None)
        # the replacement is ready, and tunes
        for seq, image in enumerate(images):
            tuner.feed(key, Frame.from_image(image, seq=seq, stamp_ns=10**9 + seq).encode())
        _until(lambda: extra["tunings"] == 1, "a tuning by the replacement")
        assert "tuning_disabled" not in extra
    with Running("auto-tuner", "--buffer", str(BUFFER)) as tuner:
        extra = tuner.node.status.extra
        killed = None
        for _ in range(3):
            killed = kill_the_worker_before_it_is_ready(killed)
        _until(lambda: "tuning_disabled" in extra, "tuning disabled")
        assert "3 times" in extra["tuning_disabled"]
        assert extra["every_frame"] is False and extra["pending"] is None
        assert not tuner.node.subscribed(tuner.node.keys.frame)


def test_the_status_says_how_long_the_cycle_in_progress_has_run(caplog):
    """A stopped worker (or a slow cycle) showed tuning: true and nothing else."""
    import logging
    import multiprocessing
    import os
    import signal

    images = sequence(BUFFER, motion=Motion(dx=1.0), seed=1)
    with caplog.at_level(logging.INFO, logger="vistrack.auto_tuner"), \
            Running("auto-tuner", "--buffer", str(BUFFER), "--min-interval", "0",
                    "--tune-sweep-step", "5") as tuner:
        key, extra = tuner.node.keys.frame, tuner.node.status.extra
        tuner.feed(key, Frame.from_image(images[0], seq=0, stamp_ns=10**9).encode())
        _until(lambda: any("tuning worker ready" in r.getMessage() for r in caplog.records),
               "the worker to be ready")
        (worker,) = [p for p in multiprocessing.active_children()
                     if p.name == "auto-tuner-worker"]
        os.kill(worker.pid, signal.SIGSTOP)
        try:
            for seq, image in enumerate(images[1:], 1):
                tuner.feed(key, Frame.from_image(image, seq=seq, stamp_ns=10**9 + seq).encode())
            _until(lambda: extra["tuning"], "the tuning to start")
            _until(lambda: (extra.get("tuning_for_s") or 0.0) >= 1.0, "its age to show")
            assert extra["tunings"] == 0
        finally:
            os.kill(worker.pid, signal.SIGCONT)
        _until(lambda: extra["tunings"] == 1, "the tuning to end")
        assert extra["tuning_for_s"] is None and extra["last_cycle_s"] >= 1.0
