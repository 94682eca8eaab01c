"""A network stream as the camera (an IP camera's ``rtsp://`` or ``http://`` URL), read through
OpenCV's FFmpeg as a device is: here an MJPEG stream served over HTTP on loopback as an IP
camera serves one, a real server and a real FFmpeg client. It was "no such file or folder"."""

from __future__ import annotations

import http.server
import itertools
import socketserver
import threading
import time

import cv2
import msgpack
import numpy as np
import pytest

from vistrack.common.sources import (
    SourceError,
    is_live,
    is_stream,
    open_stream,
    redacted,
)

from loops import IDLE_S, Running


def _mjpeg_server(jpegs: list[bytes], period_s: float):
    """An HTTP server that streams ``jpegs`` round and round as an IP camera's MJPEG stream
    does (``multipart/x-mixed-replace``), one every ``period_s``."""

    class Camera(http.server.BaseHTTPRequestHandler):
        def log_message(self, *args) -> None:
            pass

        def do_GET(self) -> None:
            if self.path != "/video.mjpg":
                self.send_error(404)
                return
            self.send_response(200)
            self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
            self.end_headers()
            try:
                for k in itertools.count():
                    jpeg = jpegs[k % len(jpegs)]
                    self.wfile.write(b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: "
                                     + str(len(jpeg)).encode() + b"\r\n\r\n" + jpeg + b"\r\n")
                    time.sleep(period_s)
            except OSError:  # the client went
                pass

    server = socketserver.ThreadingTCPServer(("127.0.0.1", 0), Camera)
    server.daemon_threads = True
    return server


@pytest.fixture
def served():
    """A live MJPEG stream of 20 distinct frames at 50 fps over HTTP on loopback: (its URL,
    the frames as decoded from their JPEGs)."""
    rng = np.random.default_rng(0)
    frames = [rng.integers(0, 256, (60, 80), dtype=np.uint8) for _ in range(20)]
    jpegs = [cv2.imencode(".jpg", f)[1].tobytes() for f in frames]
    decoded = [cv2.imdecode(np.frombuffer(j, np.uint8), cv2.IMREAD_GRAYSCALE) for j in jpegs]
    server = _mjpeg_server(jpegs, 0.02)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}/video.mjpg", decoded
    finally:
        server.shutdown()
        server.server_close()


def _which(image: np.ndarray, frames: list[np.ndarray]) -> int:
    """The frame ``image`` is (FFmpeg's JPEG decoding through colour to grey differs from
    OpenCV's by a grey level here and there: mean 0.03 against 80 between frames)."""
    diffs = [np.abs(image.astype(int) - f).mean() for f in frames]
    k = int(np.argmin(diffs))
    assert diffs[k] < 1.0, diffs[k]
    return k


def test_urls_are_streams_and_their_passwords_are_not_said():
    assert is_stream("rtsp://cam/1") and is_stream("HTTP://cam/mjpg") and is_live("srt://h:9")
    assert not is_stream("file:rtsp.mp4") and not is_stream("clips/x.mp4")
    assert is_live("device:0") and not is_live("builtin")
    assert redacted("rtsp://admin:s3cret@10.0.0.5:554/ch1") == "rtsp://admin:***@10.0.0.5:554/ch1"
    assert redacted("rtsp://10.0.0.5/ch1") == "rtsp://10.0.0.5/ch1"
    # a password with '@' or '/' (FFmpeg takes the user info up to the last '@'), a query
    # that carries a secret
    assert redacted("rtsp://admin:p@ss@10.0.0.5/s") == "rtsp://admin:***@10.0.0.5/s"
    assert redacted("rtsp://admin:p/ss@10.0.0.5/s") == "rtsp://admin:***@10.0.0.5/s"
    assert redacted("srt://h:9000?passphrase=abc&latency=20") == \
        "srt://h:9000?passphrase=***&latency=20"
    assert redacted("http://h/x.mjpg?token=zz") == "http://h/x.mjpg?token=***"


def test_a_stream_gives_its_frames_newest_first_as_a_device_does(served):
    url, frames = served
    stream = open_stream(url)
    try:
        got = [next(stream) for _ in range(5)]
    finally:
        stream.close()
    # each a frame of the stream, in order (the newest delivered: some may be passed over)
    index = [_which(g, frames) for g in got]
    steps = [(b - a) % len(frames) for a, b in itertools.pairwise(index)]
    assert all(0 < step < len(frames) // 2 for step in steps), index  # forward, never again


def test_a_stream_that_does_not_open_is_one_error_without_its_password(served):
    url, _ = served
    bad = url.replace("http://", "http://admin:s3cret@").replace("video", "none")
    start = time.monotonic()
    with pytest.raises(SourceError) as err:
        open_stream(bad)
    assert "s3cret" not in str(err.value)
    assert str(err.value).startswith(f"{redacted(bad)}: cannot open the stream (within 5 s")
    assert time.monotonic() - start < 10


def test_the_camera_publishes_a_streams_frames_as_a_live_cameras(served):
    """Paced, best effort (a live camera's frames are for whoever is there: not held for
    a consumer, not BLOCK), each frame one of the stream's."""
    url, frames = served
    with Running("camera", "--source", url, "--fps", "20") as cam:
        deadline = time.monotonic() + IDLE_S
        while len(cam.node.published_on(cam.node.keys.frame)) < 5:
            assert cam.thread.is_alive() and time.monotonic() < deadline
            time.sleep(0.01)
    sent = [p for p in cam.node.published if p.key == cam.node.keys.frame][:5]
    assert {p.reliable for p in sent} == {False}
    for p in sent:
        m = msgpack.unpackb(p.payload)
        _which(np.frombuffer(m["data"], np.uint8).reshape(m["height"], m["width"]), frames)
