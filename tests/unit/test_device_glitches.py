"""A camera device as robots have them: it delivers frames at its own pace into a queue (OpenCV's
V4L2 back end keeps four), fails a read now and then (a USB camera on a busy bus, V4L2's select()
timing out), and may be unplugged. The camera reads the newest frame, not the oldest queued one;
a failed read is tried again, then the device opened again; only a camera that stays silent ends
the source, with a clear error.

No camera device here: the device is a real ``cv2.VideoCapture`` of a video made from the shared
RubberWhale frames behind the ``capture`` seam of :func:`open_device`, delivering them on a clock
into a queue of four, its reads failing where a test says."""

from __future__ import annotations

import itertools
import logging
import threading
import time

import cv2
import numpy as np
import pytest

from vistrack.common.sources import SourceError, open_device
from vistrack.common.vision.preprocess import to_gray

RETRY_S = 0.2


@pytest.fixture(scope="module")
def video(rubberwhale, tmp_path_factory) -> tuple[str, list[np.ndarray]]:
    """An 8-frame MJPG video of RubberWhale, and its frames as OpenCV reads them (grey)."""
    path = str(tmp_path_factory.mktemp("device") / "rw.avi")
    first = cv2.imread(str(rubberwhale / "frame07.png"))
    out = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*"MJPG"), 10, first.shape[1::-1])
    for k in range(7, 15):
        out.write(cv2.imread(str(rubberwhale / f"frame{k:02d}.png")))
    out.release()
    cap = cv2.VideoCapture(path)
    frames = []
    while (got := cap.read())[0]:
        frames.append(to_gray(got[1]))
    cap.release()
    assert len(frames) == 8
    return path, frames


class Device:
    """Opens the video as a camera: each opening starts a clock, frame k (the video's frames
    over and over) is delivered at k ``period`` s into a queue of ``depth`` that drops its
    oldest when full, and a read takes the oldest queued (waiting for one), as V4L2 does. Frame
    k carries k % 256 in its pixel (0, 0), and the opening that delivered it (1, 2, ...) in
    pixel (0, 1). The n-th read overall (0-based) fails where
    ``fails(n)``; ``openable`` says whether each opening, in turn, succeeds."""

    def __init__(self, path: str, period: float, fails=lambda n: False,
                 openable=(True, True), depth: int = 4) -> None:
        self.path = path
        self.period = period
        self.fails = fails
        self.openable = list(openable)
        self.depth = depth
        self.opened = 0
        self.reads = 0
        self.lock = threading.Lock()

    def __call__(self, index: int) -> Device._Capture:
        assert index == 3
        ok = self.openable[self.opened]
        self.opened += 1
        return self._Capture(self, cv2.VideoCapture(self.path) if ok else None)

    def newest(self, capture: Device._Capture) -> int:
        """The frame the camera has delivered last, now."""
        return int((time.monotonic() - capture.t0) / self.period)

    class _Capture:
        def __init__(self, device: Device, cap: cv2.VideoCapture | None) -> None:
            self.device = device
            self.cap = cap
            self.opening = device.opened  # this capture's opening, 1 for the first
            self.t0 = time.monotonic()
            self.next = 0  # the next frame a read returns, if still queued
            self.images: list[np.ndarray] = []

        def isOpened(self) -> bool:  # noqa: N802 - cv2.VideoCapture's name
            return self.cap is not None and self.cap.isOpened()

        def read(self):
            d = self.device
            with d.lock:
                n = d.reads
                d.reads += 1
            if d.fails(n):
                time.sleep(0.001)
                return False, None
            newest = d.newest(self)
            self.next = max(self.next, newest - d.depth + 1)  # the older ones were dropped
            wait = self.t0 + self.next * d.period - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            while len(self.images) < 8:
                self.images.append(self.cap.read()[1])
            image = self.images[self.next % 8].copy()
            image[0, 0] = self.next % 256
            image[0, 1] = self.opening
            self.next += 1
            return True, image

        def release(self) -> None:
            if self.cap is not None:
                self.cap.release()


def _id(frame: np.ndarray) -> int:
    return int(frame[0, 0])


def _opening(frame: np.ndarray) -> int:
    return int(frame[0, 1])


def _same_picture(frame: np.ndarray, picture: np.ndarray) -> bool:
    a = frame.copy()
    a[0, :2] = picture[0, :2]
    return bool(np.array_equal(a, picture))


def _take(device: Device, count: int, frames: list[np.ndarray]) -> list[np.ndarray]:
    """The first ``count`` frames of device:3 (retries within RETRY_S), the device let go
    after; each must be the video's picture its id names."""
    source = open_device(3, retry_s=RETRY_S, capture=device)
    try:
        got = list(itertools.islice(source, count))
    finally:
        source.close()
    for f in got:
        assert _same_picture(f, frames[_id(f) % 8])
    return got


def test_a_camera_read_slower_than_it_delivers_gives_its_newest_frame(video):
    """At --fps 10 on a camera of 50 fps: each frame is the newest the camera has delivered
    (or the one before, if it delivered one meanwhile), not the oldest of its queue of four
    (three frames behind, 60 ms here, for the whole run)."""
    path, frames = video
    period = 0.02
    device = Device(path, period)
    source = open_device(3, capture=device)
    try:
        behind = []
        for _ in range(6):
            time.sleep(5 * period)
            frame = next(source)
            behind.append(device.newest(source.cap) % 256 - _id(frame))
            assert _same_picture(frame, frames[_id(frame) % 8])
    finally:
        source.close()
    assert max(behind) <= 1, behind  # 3 or 4 each with the queue's oldest


def test_reads_that_fail_now_and_then_keep_frames_coming(video, caplog):
    path, frames = video
    device = Device(path, 0.01, lambda n: n in (0, 3, 4, 9))
    caplog.set_level(logging.INFO, "vistrack.frames")
    got = _take(device, 8, frames)
    ids = [_id(f) for f in got]
    assert ids == sorted(set(ids)), ids  # in order, none twice
    assert device.opened == 1  # never opened again
    assert "device:3: a frame could not be read; trying again" in caplog.text
    assert "device:3: a frame read again after 2 failed reads" in caplog.text


def test_a_device_silent_for_longer_is_opened_again_and_goes_on(video, caplog):
    path, frames = video
    device = Device(path, 0.01, lambda n: n >= 2 and device.opened == 1)
    caplog.set_level(logging.INFO, "vistrack.frames")
    got = _take(device, 4, frames)
    assert device.opened == 2
    # the first opening's frames (its reads 0 and 1 succeed; the newest is taken when the
    # camera asks, so one or both), then the second's: in order, none twice
    seen = [(_opening(f), _id(f)) for f in got]
    assert seen == sorted(set(seen)) and seen[0][0] == 1 and seen[-1][0] == 2, seen
    assert "device:3: no frame for 0.2 s: opening the device again" in caplog.text
    assert "device:3: delivering frames again, opened again" in caplog.text


@pytest.mark.parametrize("reopens", [True, False])
def test_an_unplugged_camera_ends_with_a_clear_error(video, reopens):
    path, frames = video
    device = Device(path, 0.01, lambda n: n >= 1, openable=(True, reopens))
    source = open_device(3, retry_s=RETRY_S, capture=device)
    try:
        assert _same_picture(next(source), frames[0])
        t0 = time.monotonic()
        with pytest.raises(SourceError, match=r"^device:3: the camera stopped delivering "
                                              r"frames \(none for 0\.2 s, nor once opened "
                                              r"again\)$"):
            next(source)
        waited = time.monotonic() - t0
    finally:
        source.close()
    assert RETRY_S * 0.9 <= waited < 2 * RETRY_S + 1.0  # one retry window, two if reopened
    assert device.opened == 2


def test_a_read_that_raises_is_an_error_of_next_not_a_wait_for_ever(video):
    """A driver's exception (OpenCV's cv2.error) killed the reading thread, and next()
    waited for a frame for ever; only the launcher's hang watch got the camera going."""
    path, _ = video

    def fails(n: int) -> bool:
        if n == 3:
            raise cv2.error("unsupported pixel format")
        return False

    source = open_device(3, retry_s=RETRY_S, capture=Device(path, 0.01, fails=fails))
    got: list[object] = []

    def take() -> None:
        try:
            while True:
                next(source)
        except Exception as e:  # noqa: BLE001 - what next() raised, checked below
            got.append(e)
    reader = threading.Thread(target=take, daemon=True)
    reader.start()
    reader.join(5)
    source.close()
    assert got and isinstance(got[0], SourceError), got
    assert "device:3: reading the camera failed: error: unsupported pixel format" in str(got[0])


def test_a_device_that_does_not_open_is_an_error_at_once(video):
    path, _ = video
    with pytest.raises(SourceError, match=r"^device:3: cannot open the camera device$"):
        open_device(3, capture=Device(path, 0.01, openable=(False,)))


def test_close_lets_the_device_go(video):
    path, _ = video
    device = Device(path, 0.01)
    source = open_device(3, capture=device)
    next(source)
    source.close()
    assert not source.cap.isOpened()  # released by the reading thread
    with pytest.raises(StopIteration):
        next(source)
