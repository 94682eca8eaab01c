"""ROS 2 camera images to 8-bit grey (ros2types.grey_of_image, grey_of_compressed,
frame_of_camera), against OpenCV on real texture.

The images are built with rosbags' own ``sensor_msgs`` classes and CDR codec (not ours), from
a Middlebury frame when the shared data is there, else from the built-in sequence's texture.
The reference for colour is OpenCV's ``COLOR_BGR2GRAY`` of the BGR original, what the file
camera does with the same picture.
"""

from __future__ import annotations

import os
import struct
import subprocess
import sys
import zlib

import cv2
import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from vistrack.common import groundtruth
from vistrack.common import ros2types as r2
from vistrack.common.synthetic import texture
from vistrack.common.vision.preprocess import Grey

JAZZY = get_typestore(Stores.ROS2_JAZZY)
Image = JAZZY.types[r2.IMAGE]
CompressedImage = JAZZY.types[r2.COMPRESSED_IMAGE]
Header = JAZZY.types["std_msgs/msg/Header"]
Time = JAZZY.types["builtin_interfaces/msg/Time"]
STAMP = Header(stamp=Time(sec=1_700_000_000, nanosec=123_456_789), frame_id="cam")


@pytest.fixture(scope="module")
def bgr() -> np.ndarray:
    folder = groundtruth.middlebury("RubberWhale")
    if folder is not None:
        image = cv2.imread(str(folder / "frame10.png"), cv2.IMREAD_COLOR)
        return np.ascontiguousarray(image[:120, :161])  # odd width: rows need no padding
    grey = np.ascontiguousarray(texture(256, seed=3)[:120, :161])
    return np.dstack([grey, np.roll(grey, 7, axis=1), 255 - grey])


def _wire(msg, typename: str):
    """The message as it arrives: CDR by rosbags, decoded by our module."""
    return r2.deserialize(JAZZY.serialize_cdr(msg, typename).tobytes(), typename)


def _image(pixels: np.ndarray, encoding: str, *, pad: int = 0, bigendian: int = 0,
           width: int | None = None):
    h, w = pixels.shape[0], width or pixels.shape[1]
    rows = pixels.reshape(h, -1)
    if pad:
        rows = np.hstack([rows, np.full((h, pad), 77, np.uint8)])
    return _wire(Image(header=STAMP, height=h, width=w, encoding=encoding,
                       is_bigendian=bigendian, step=rows.shape[1],
                       data=np.ascontiguousarray(rows).reshape(-1)), r2.IMAGE)


@pytest.mark.parametrize(("encoding", "convert"), [
    ("bgr8", lambda b: b),
    ("8UC3", lambda b: b),  # generic: OpenCV's BGR, as cv_bridge reads it
    ("8UC4", lambda b: np.dstack([b, np.full(b.shape[:2], 200, np.uint8)])),
    ("rgb8", lambda b: b[:, :, ::-1]),
    ("bgra8", lambda b: np.dstack([b, np.full(b.shape[:2], 200, np.uint8)])),
    ("rgba8", lambda b: np.dstack([b[:, :, ::-1], np.full(b.shape[:2], 9, np.uint8)])),
])
@pytest.mark.parametrize("pad", [0, 3])
def test_colour_encodings_give_opencvs_grey(bgr, encoding, convert, pad):
    got = r2.grey_of_image(_image(np.ascontiguousarray(convert(bgr)), encoding, pad=pad))
    np.testing.assert_array_equal(got, cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))


def test_mono8_is_kept_as_is(bgr):
    grey = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    np.testing.assert_array_equal(r2.grey_of_image(_image(grey, "mono8", pad=5)), grey)


@pytest.mark.parametrize("bigendian", [0, 1])
def test_mono16_keeps_the_high_byte_in_either_byte_order(bgr, bigendian):
    grey = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    wide = grey.astype(np.uint16) * 256 + 255 - grey  # low byte: anything but the answer
    raw = wide.astype(">u2" if bigendian else "<u2").view(np.uint8).reshape(grey.shape[0], -1)
    got = r2.grey_of_image(_image(raw, "mono16", bigendian=bigendian, width=grey.shape[1]))
    assert got.shape == grey.shape
    np.testing.assert_array_equal(got, grey)


def _mosaic(rgb: np.ndarray, pattern: str) -> np.ndarray:
    """The raw Bayer image a sensor with the colour filter ``pattern`` (ROS's name: the
    colours of the 2x2 cell, row by row, e.g. "rggb") takes of an RGB scene."""
    raw = np.empty(rgb.shape[:2], np.uint8)
    for k, colour in enumerate(pattern):
        raw[k // 2::2, k % 2::2] = rgb[k // 2::2, k % 2::2, "rgb".index(colour)]
    return raw


@pytest.mark.parametrize("pattern", ["rggb", "bggr", "gbrg", "grbg"])
@pytest.mark.parametrize(("rgb", "luma"), [
    ((200, 0, 0), 0.299 * 200), ((0, 200, 0), 0.587 * 200), ((0, 0, 200), 0.114 * 200)])
def test_raw_bayer_is_demosaiced_with_its_own_pattern(pattern, rgb, luma):
    """A pure red, green or blue scene through each filter pattern comes back as that
    colour's luma: a pattern read as another swaps red and blue, or takes green for one."""
    scene = np.empty((24, 31, 3), np.uint8)
    scene[:] = rgb
    got = r2.grey_of_image(_image(_mosaic(scene, pattern), f"bayer_{pattern}8", pad=3))
    assert got.shape == (24, 31)
    assert np.abs(got[2:-2, 2:-2].astype(float) - luma).max() <= 1.5


def test_raw_bayer_of_real_texture_gives_its_grey(bgr):
    """Demosaicing loses some of the finest detail, not the picture."""
    want = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY).astype(int)
    got = r2.grey_of_image(_image(_mosaic(bgr[:, :, ::-1], "rggb"), "bayer_rggb8"))
    assert np.abs(got.astype(int) - want)[2:-2, 2:-2].mean() <= 4


@pytest.mark.parametrize(("encoding", "luma_first"), [("yuv422_yuy2", True),
                                                      ("yuv422", False),
                                                      # sensor_msgs' names of the same two
                                                      ("yuyv", True), ("uyvy", False)])
def test_yuv422_gives_its_luma_bytes(bgr, encoding, luma_first):
    """YUYV (a USB camera's, usb_cam's yuv422_yuy2) and UYVY (yuv422): the grey is the Y byte
    of each pixel, whatever the chroma bytes beside it hold."""
    grey = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    chroma = np.random.default_rng(5).integers(0, 256, grey.shape, np.uint8)
    pair = (grey, chroma) if luma_first else (chroma, grey)
    raw = np.dstack(pair).reshape(grey.shape[0], -1)
    got = r2.grey_of_image(_image(raw, encoding, pad=2, width=grey.shape[1]))
    np.testing.assert_array_equal(got, grey)


@pytest.mark.parametrize(("ext", "tolerance"), [(".png", 0), (".jpg", 12)])
def test_compressed_images_decode_to_grey(bgr, ext, tolerance):
    ok, data = cv2.imencode(ext, bgr)
    assert ok
    msg = _wire(CompressedImage(header=STAMP, format=ext[1:], data=data.reshape(-1)),
                r2.COMPRESSED_IMAGE)
    frame = r2.frame_of_camera(msg, seq=4)
    want = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY).astype(int)
    assert (frame.width, frame.height) == (bgr.shape[1], bgr.shape[0])
    assert np.abs(frame.data.astype(int) - want).mean() <= tolerance / 4
    assert np.abs(frame.data.astype(int) - want).max() <= max(tolerance * 4, 1)


def test_frame_of_camera_keeps_the_header_stamp(bgr):
    frame = r2.frame_of_camera(_image(np.ascontiguousarray(bgr[:, :, ::-1]), "rgb8"), seq=9)
    assert frame.seq == 9 and frame.stamp_ns == 1_700_000_000_123_456_789
    assert frame.data.shape == bgr.shape[:2]


def test_a_1x1_black_image_is_an_image():
    frame = r2.frame_of_camera(_image(np.zeros((1, 1, 3), np.uint8), "bgr8"), seq=0)
    assert (frame.width, frame.height) == (1, 1) and frame.data[0, 0] == 0


def _raw(encoding="rgb8", width=4, height=3, step=12, size=36):
    return _wire(Image(header=STAMP, height=height, width=width, encoding=encoding,
                       is_bigendian=0, step=step, data=np.zeros(size, np.uint8)), r2.IMAGE)


@pytest.mark.parametrize(("msg", "message"), [
    (lambda: _raw(encoding="nv21"), "image encoding 'nv21' is not supported: allowed mono8"),
    (lambda: _raw(encoding="bayer_rggb16"), "'bayer_rggb16' is not supported"),
    (lambda: _raw(size=35), "rgb8 image data is 35 bytes: expected step \\* height = 12 \\* 3"),
    (lambda: _raw(step=11, size=33), "with step >= 12"),
    (lambda: _raw(width=0, step=0, size=0), "image is 0x3: expected at least 1x1"),
    (lambda: _raw(encoding="mono8", width=5000, height=1, step=5000, size=5000),
     "field .width. must be in 1..4096, got 5000"),
])
def test_bad_images_are_refused_naming_what_is_wrong(msg, message):
    with pytest.raises(ValueError, match=message):
        r2.frame_of_camera(msg(), seq=0)


def test_a_compressed_image_that_does_not_decode_is_refused():
    msg = _wire(CompressedImage(header=STAMP, format="jpeg",
                                data=np.frombuffer(b"\xff\xd8not a jpeg", np.uint8)),
                r2.COMPRESSED_IMAGE)
    with pytest.raises(ValueError, match="compressed image \\(jpeg, 12 bytes\\) does not decode"):
        r2.frame_of_camera(msg, seq=0)


def png_of_black(width: int, height: int) -> bytes:
    """A grey PNG of ``width`` x ``height`` black pixels, deflated row by row (no image of
    that size is ever held): a decompression bomb of about a thousandth of its pixels."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data)))
    deflate, row = zlib.compressobj(9), bytes(1 + width)  # filter byte 0, then the pixels
    idat = b"".join(deflate.compress(row) for _ in range(height)) + deflate.flush()
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0,
                                                               0, 0, 0))
            + chunk(b"IDAT", idat) + chunk(b"IEND", b""))


# the camera's process: a fresh interpreter whose first import is the camera's own
_DECODE_IN_A_CAMERA_PROCESS = """
import resource, sys
from vistrack.services.camera import ros2cam
from vistrack.common import ros2types as r2
payload = open(sys.argv[1], "rb").read()
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
try:
    frame = ros2cam.frame_of_payload(payload, r2.COMPRESSED_IMAGE, 0, size=(256, 256))
    said = f"accepted as {frame.width}x{frame.height}"
except ValueError as e:
    said = f"refused: {e}"
grown = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before
print(grown // 1024, said)
"""


def test_a_compressed_image_bomb_is_refused_from_its_header_before_it_is_decoded(tmp_path):
    """146 KB of PNG that decodes to 12000x12000 px (144 MB): refused by OpenCV's own limit,
    which vistrack sets before OpenCV loads, without the memory (the camera's --size took
    it and scaled it, after decoding all of it)."""
    png = png_of_black(12000, 12000)
    msg = CompressedImage(header=STAMP, format="png", data=np.frombuffer(png, np.uint8))
    path = tmp_path / "bomb.cdr"
    path.write_bytes(JAZZY.serialize_cdr(msg, r2.COMPRESSED_IMAGE).tobytes())
    run = subprocess.run([sys.executable, "-c", _DECODE_IN_A_CAMERA_PROCESS, str(path)],
                         capture_output=True, text=True, timeout=120, check=True)
    grown_mb, said = run.stdout.strip().split(" ", 1)
    assert said == (f"refused: compressed image (png, {len(png)} bytes) decodes to more than "
                    "the 67108864 px (8192x8192) an image may have (OPENCV_IO_MAX_IMAGE_PIXELS)"
                    ": refused from its header")
    assert int(grown_mb) < 32, f"peak RSS grew by {grown_mb} MB"


def test_an_image_larger_than_the_limit_decoded_anyway_is_refused_naming_its_size(
        bgr, monkeypatch):
    # where OpenCV loaded before vistrack (a program's own import cv2 first), its default
    # limit is in force and the image decodes: ours is checked then
    from vistrack.common import imagelimit

    monkeypatch.setattr(imagelimit, "MAX_PIXELS", 1024)
    ok, png = cv2.imencode(".png", bgr[:40, :56])
    msg = _wire(CompressedImage(header=STAMP, format="png", data=png.reshape(-1)),
                r2.COMPRESSED_IMAGE)
    with pytest.raises(ValueError) as e:
        r2.frame_of_camera(msg, seq=0)
    assert str(e.value) == (f"compressed image (png, {png.size} bytes) is 56x40 px, more than "
                            "the 1024 px (32x32) an image may have "
                            "(OPENCV_IO_MAX_IMAGE_PIXELS)")


@pytest.mark.parametrize("bigendian", [0, 1])
@pytest.mark.parametrize("bits", [10, 12, 16])
def test_a_camera_s_16_bit_images_are_scaled_by_the_depth_of_its_samples(bgr, bits, bigendian):
    """A machine-vision camera's mono16 images hold 10 or 12 significant bits (values up to
    1023 or 4095): through the camera's Grey they come back as the 8-bit picture, not as the
    high byte's 0 to 3 or 0 to 15."""
    grey = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    wide = grey.astype(np.uint16) << (bits - 8)
    raw = wide.astype(">u2" if bigendian else "<u2").view(np.uint8).reshape(grey.shape[0], -1)
    msg = _image(raw, "mono16", bigendian=bigendian, width=grey.shape[1])
    stream = Grey()
    for _ in range(2):
        frame = r2.frame_of_camera(msg, seq=0, grey=stream)
        np.testing.assert_array_equal(frame.data, grey)
    assert stream.bits == bits
    assert r2.grey_of_image(msg).max() < 256 >> (16 - bits) or bits == 16  # the high byte


def test_an_image_wider_than_a_frame_carries_is_taken_with_size():
    """A 5472 x 3648 camera (20 MP) with --size was refused, 'width must be in 1..4096':
    the size was checked before the resize. Without --size the error says to give it."""
    from vistrack.common.sources import resize

    big = np.tile(np.arange(5472, dtype=np.uint8)[None, :], (8, 1))  # 5472 x 8
    msg = _image(big, "mono8")
    frame = r2.frame_of_camera(msg, seq=0, resize=lambda image: resize(image, (684, 8)))
    assert (frame.width, frame.height) == (684, 8)
    with pytest.raises(ValueError, match=r"give --size WxH to scale the images"):
        r2.frame_of_camera(msg, seq=0)


@pytest.mark.parametrize("given", ["3000", "1KB", "2kb", "1Mb"])
def test_a_limit_of_the_user_s_own_is_read_as_opencv_reads_it(given, tmp_path):
    """OPENCV_IO_MAX_IMAGE_PIXELS=100MB (OpenCV's parser takes KB, MB and GB) was read as no
    number, so vistrack refused, as over its own 2^26, an image OpenCV had decoded under the
    user's limit. OpenCV is the judge: in a process given the value, an image of exactly the
    pixels parse_limit reads decodes, and one of a pixel more is refused."""
    from vistrack.common.imagelimit import parse_limit

    limit = parse_limit(given)
    assert limit is not None
    side = 1 << 10 if limit >= 1 << 20 else 1  # a 1 MiB limit: 1024 rows of 1024
    for name, width in (("at.png", limit // side), ("over.png", limit // side + 1)):
        cv2.imwrite(str(tmp_path / name), np.zeros((side, width), np.uint8))
    code = ("import cv2, sys\nfor f in sys.argv[1:]:\n"
            "    try: print(cv2.imread(f, -1).shape)\n"
            "    except cv2.error: print('refused')\n")
    out = subprocess.run([sys.executable, "-c", code, str(tmp_path / "at.png"),
                          str(tmp_path / "over.png")], capture_output=True, text=True,
                         env={**os.environ, "OPENCV_IO_MAX_IMAGE_PIXELS": given}, timeout=60)
    assert out.stdout.split("\n")[:2] == [str((side, limit // side)), "refused"], out
    assert parse_limit("50M") is None and parse_limit("1e9") is None  # OpenCV aborts on them
    assert parse_limit("0") == 0


def test_a_restarted_camera_driver_is_a_new_publisher_not_a_second_one(monkeypatch, caplog):
    """A camera driver restarted publishes under a new GID: it was said to be "a second
    publisher on the topic (2 in all)", 3 after the next restart, and so on. A publisher
    silent for PUBLISHER_GONE_S has gone; one that comes then replaces it (said at INFO). Two
    sending at once are still two (a warning)."""
    import types

    import zenoh

    from vistrack.common.bus import MemoryNode
    from vistrack.common.rmw_zenoh import GID_SIZE, Attachment
    from vistrack.services.camera import ros2cam

    clock = [100.0]
    monkeypatch.setattr(ros2cam.time, "monotonic", lambda: clock[0])

    def sample(gid: int, seq: int):  # what Zenoh's callback is given: payload and attachment
        att = Attachment(seq=seq, stamp_ns=1, gid=bytes([gid]) * GID_SIZE).encode()
        return types.SimpleNamespace(payload=zenoh.ZBytes(b"image"),
                                     attachment=zenoh.ZBytes(att))

    with MemoryNode("camera") as node, caplog.at_level("INFO", logger="vistrack.camera"):
        conv = ros2cam._Converter(node, r2.IMAGE, None)
        for seq in (1, 2, 3):
            conv.on_sample(sample(1, seq))
            clock[0] += 0.1
        clock[0] += ros2cam.PUBLISHER_GONE_S  # driver 1 gone, driver 2 (a restart) comes
        for seq in (1, 2):
            conv.on_sample(sample(2, seq))
            clock[0] += 0.1
        conv.on_sample(sample(3, 1))  # a third while the second sends: two cameras
    said = [(r.levelname, r.getMessage()) for r in caplog.records]
    assert said == [
        ("INFO", "images from a new publisher on the topic (the camera driver restarted?)"),
        ("WARNING", "a second publisher on the topic (2 in all): their images are taken as "
                    "one camera's")]
