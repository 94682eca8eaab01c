"""A camera device that fails a read now and then (a USB camera on a busy bus, V4L2's select()
timing out) keeps delivering: the read is tried again, then the device opened again, and only a
camera that stays silent (unplugged) ends the source with a clear error.

No camera device here: the device is a real ``cv2.VideoCapture`` of a video made from the shared
RubberWhale frames, behind the ``capture`` seam of :func:`open_device`, its reads failing where a
test says."""

from __future__ import annotations

import itertools
import logging
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
    """Opens the video as a device: the n-th read overall (0-based) fails where ``fails(n)``;
    ``openable`` says whether each opening (in turn) succeeds."""

    def __init__(self, path: str, fails, openable=(True, True)) -> None:
        self.path = path
        self.fails = fails
        self.openable = list(openable)
        self.opened = 0
        self.reads = 0

    def __call__(self, index: int) -> Device._Capture:
        assert index == 3
        ok = self.openable[self.opened]
        self.opened += 1
        return self._Capture(self, cv2.VideoCapture(self.path) if ok else None)

    class _Capture:
        def __init__(self, device: Device, cap: cv2.VideoCapture | None) -> None:
            self.device = device
            self.cap = cap

        def isOpened(self) -> bool:  # noqa: N802 - cv2.VideoCapture's name
            return self.cap is not None and self.cap.isOpened()

        def read(self):
            n = self.device.reads
            self.device.reads += 1
            if self.device.fails(n):
                return False, None
            return self.cap.read()

        def release(self) -> None:
            if self.cap is not None:
                self.cap.release()


def test_reads_that_fail_now_and_then_lose_no_frame(video, caplog):
    path, frames = video
    device = Device(path, lambda n: n in (0, 3, 4, 9))
    caplog.set_level(logging.INFO, "vistrack.frames")
    got = list(itertools.islice(open_device(3, retry_s=RETRY_S, capture=device), 8))
    assert len(got) == 8
    for a, b in zip(got, frames, strict=True):
        np.testing.assert_array_equal(a, b)
    assert device.opened == 1  # never opened again
    assert "device:3: a frame could not be read; trying again" in caplog.text
    assert "device:3: a frame read again after 2 failed reads" in caplog.text


def test_a_device_silent_for_longer_is_opened_again_and_goes_on(video, caplog):
    path, frames = video
    device = Device(path, lambda n: 2 <= n < 10 ** 9 and device.opened == 1)
    caplog.set_level(logging.INFO, "vistrack.frames")
    got = list(itertools.islice(open_device(3, retry_s=RETRY_S, capture=device), 4))
    assert device.opened == 2
    # two frames, then the device opened again: the video starts over, as a camera's live
    # view goes on from where it is now
    for a, b in zip(got, frames[:2] + frames[:2], strict=True):
        np.testing.assert_array_equal(a, b)
    assert "device:3: no frame for 0.2 s: opening the device again" in caplog.text
    assert "device:3: delivering frames again, opened again" in caplog.text


@pytest.mark.parametrize("reopens", [True, False])
def test_an_unplugged_camera_ends_with_a_clear_error(video, reopens):
    path, frames = video
    device = Device(path, lambda n: n >= 1, openable=(True, reopens))
    source = open_device(3, retry_s=RETRY_S, capture=device)
    np.testing.assert_array_equal(next(source), frames[0])
    t0 = time.monotonic()
    with pytest.raises(SourceError, match=r"^device:3: the camera stopped delivering frames "
                                          r"\(none for 0\.2 s, nor once opened again\)$"):
        next(source)
    waited = time.monotonic() - t0
    assert RETRY_S <= waited < 2 * RETRY_S + 1.0  # one retry window, or two if it reopened
    assert device.opened == 2


def test_a_device_that_does_not_open_is_an_error_at_once(video):
    path, _ = video
    with pytest.raises(SourceError, match=r"^device:3: cannot open the camera device$"):
        next(open_device(3, capture=Device(path, lambda n: False, openable=(False,))))
