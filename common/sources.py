"""Frame sources: video files, image folders, globs and lists, devices, the built-in sequence.

Pure OpenCV, no Zenoh: the camera service and the offline ``vistrack track`` / ``tune`` read
frames through exactly this code. Every frame comes out 8-bit grey, converted the way
:func:`vistrack.common.vision.to_gray` does it; 16-bit frames (machine-vision cameras, 16-bit
PNG or TIFF) scaled by the depth of the stream's samples (:class:`.vision.preprocess.Grey`).
"""

from __future__ import annotations

import functools
import glob
import logging
import math
import os
import re
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from decimal import Decimal
from typing import Any

import cv2
import numpy as np

from . import imagelimit, synthetic
from .vision.preprocess import Grey

#: Image files a folder or glob source takes: those cv2.imread reads (OpenEXR is off in
#: OpenCV's wheels). The Netpbm, JPEG 2000, Radiance, PFM and Sun raster ones were left out:
#: a folder of .pnm files held "no image".
IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".jpe", ".bmp", ".dib", ".tif", ".tiff", ".pgm",
              ".ppm", ".pbm", ".pnm", ".pam", ".pxm", ".webp", ".jp2", ".hdr", ".pic", ".pfm",
              ".ras", ".sr")
VIDEO_EXTS = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv")
BUILTIN = "builtin"
#: The slowest paced camera, frames a second (``--fps``: 0, unpaced, or at least this): the
#: simulator steps its robot at most 10 s at a time, and below it ``--fps 1e-10`` crashed the
#: file camera's sleep (time_t overflow) and stamped the simulator's frames past int64.
MIN_FPS = 0.1
#: Frame sides ``parse_size`` accepts by default, px.
SIZE_RANGE = (8, 8192)
#: Camera device indices ``device:N`` accepts (cv2.VideoCapture(-1) crashes the process).
DEVICE_RANGE = (0, 99)
#: Seconds a camera device may fail to deliver a frame, read after read, before it is opened
#: again (once); a USB camera on a busy bus, or V4L2's select() timing out, fails a read now
#: and then and delivers the next.
DEVICE_RETRY_S = 1.0
#: Seconds between two reads of a device that failed (a read of an unplugged camera returns
#: at once).
DEVICE_RETRY_PAUSE_S = 0.005

log = logging.getLogger("vistrack.frames")

#: Network streams a camera reads as it reads a device (OpenCV's FFmpeg back end): an IP
#: camera's RTSP, an MJPEG or HLS stream over HTTP, RTMP, SRT, UDP or TCP.
STREAM_SCHEMES = ("rtsp", "rtsps", "rtmp", "http", "https", "srt", "udp", "tcp")
_STREAM_RE = re.compile(rf"^({'|'.join(STREAM_SCHEMES)})://", re.IGNORECASE)
#: How long opening a stream, and a read of it, may take before it counts as failed, ms
#: (FFmpeg's own: 30 s and more for a camera that does not answer)
STREAM_TIMEOUT_MS = 5000


def is_stream(spec: str) -> bool:
    """Whether a SOURCE is a network stream's URL (:data:`STREAM_SCHEMES`)."""
    return _STREAM_RE.match(spec) is not None


def is_live(spec: str) -> bool:
    """Whether a SOURCE is a live camera: a device or a network stream (its frames are the
    newest it delivers, for whoever is there; a file's wait for their consumers)."""
    return spec.startswith("device:") or is_stream(spec)


#: Query parameters that carry a secret (``?token=...``, SRT's ``passphrase``)
_SECRET_QUERY = re.compile(r"(?i)([?&;](?:password|passwd|pwd|pass|passphrase|token|"
                           r"access_token|auth|key|secret)=)[^&;#]*")


def redacted(url: str) -> str:
    """``url`` with its secrets hidden (``rtsp://admin:***@cam/1``, ``?token=***``): an IP
    camera's URL often carries a password, and it goes into logs and the status. The user
    info ends at the last ``@`` (as FFmpeg reads it: a password may hold ``@`` or ``/``), so
    an ``@`` in a path after a port may hide more than the password, never less."""
    scheme, sep, rest = url.partition("://")
    if not sep:
        return url
    at, colon = rest.rfind("@"), rest.find(":")
    if 0 <= colon < at:
        rest = f"{rest[:colon]}:***{rest[at:]}"
    return scheme + sep + _SECRET_QUERY.sub(r"\1***", rest)

# OpenCV and its FFmpeg back end print their own warnings on stderr ("moov atom not found",
# "can't open camera by index") before the one-line error that names the file or device.
os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # AV_LOG_QUIET; read at first capture
cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)


class SourceError(ValueError):
    """A frame source cannot be opened or read; the message names the path and the problem."""


class VideoCutShort(SourceError):
    """A video ended well before the frame count of its header, once its readable frames were
    used (:func:`_check_complete`): an error for a single pass, which has used what there was;
    a looping camera plays those frames again instead (:func:`.camera.service.open_source`)."""


def resize(frame: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``frame`` scaled to ``size`` (width, height): by pixel area along a side that shrinks
    (``cv2.INTER_AREA``, which averages rather than aliases), bilinearly along one that grows.

    ``INTER_AREA`` enlarging is nearest-neighbour in OpenCV: each pixel becomes a block whose
    edges stay on the grid while the scene moves under them, so a match's template changes
    from frame to frame. The built-in sequence enlarged from 256x256 to 1280x720 that way
    lost 544 features in 59 frames to the tracker's checks (forward-backward, residual,
    ambiguity), against 58 enlarged bilinearly, and re-detected so often that
    pre-processing computed candidates for nearly every frame. A frame that shrinks along one
    side and grows along the other is scaled one side at a time."""
    w, h = size
    fh, fw = frame.shape[:2]
    if (fw, fh) == (w, h):
        return frame
    if w <= fw and h <= fh:
        return cv2.resize(frame, size, interpolation=cv2.INTER_AREA)
    if w < fw:
        frame = cv2.resize(frame, (w, fh), interpolation=cv2.INTER_AREA)
    elif h < fh:
        frame = cv2.resize(frame, (fw, h), interpolation=cv2.INTER_AREA)
    return cv2.resize(frame, size, interpolation=cv2.INTER_LINEAR)


def parse_size(text: str, flag: str = "size", *,
               sides: tuple[int, int] = SIZE_RANGE) -> tuple[int, int]:
    """'WxH' -> (width, height), each within ``sides`` (default 8..8192); errors name ``flag``
    (the flag the text came from, e.g. ``--resize``)."""
    try:
        w_s, h_s = text.lower().split("x")
        w, h = int(w_s), int(h_s)
    except ValueError:
        raise SourceError(f"{flag} {text!r} is not WIDTHxHEIGHT, e.g. 256x256") from None
    lo, hi = sides
    if not (lo <= w <= hi and lo <= h <= hi):
        raise SourceError(f"{flag} {text} is out of range: width and height must be "
                          f"{lo}..{hi}")
    return w, h


#: The most memory an animation read whole (OpenCV reads an animated PNG or WebP at once) may
#: take, its frames' pixels times 4 bytes.
MAX_ANIMATION_BYTES = 1 << 30


def frame_reads(path: str, grey: Grey | None = None) -> list[Callable[[], np.ndarray]]:
    """The reads of the frames of one image file, one call each, each giving a frame as
    :func:`read_image` does (or raising :class:`SourceError` for that frame alone): a
    multi-page TIFF page by page, an animated PNG or WebP frame by frame (read whole, once,
    at the first call), any other image once. Only the first of them was read, in silence:
    an 8-page TIFF stack tracked as one frame; and a bad page ended its file's pages there,
    where a camera leaves a bad frame out and goes on."""
    pages = _pages(path)
    if pages <= 1:
        return [functools.partial(read_image, path, grey)]
    grey = grey or Grey()
    if path.lower().endswith((".tif", ".tiff")):
        return [functools.partial(read_image, path, grey, page=k) for k in range(pages)]
    whole: list[np.ndarray] = []  # OpenCV reads an animation whole (a page alone: the first)
    failed: list[SourceError] = []

    def frame(k: int) -> np.ndarray:
        if not whole and not failed:
            try:
                whole.extend(_animation_frames(path, grey, pages))
            except SourceError as e:
                failed.append(e)
        if failed:
            raise failed[0]
        return whole[k]
    return [functools.partial(frame, k) for k in range(pages)]


#: The image types that may hold more than one frame (TIFF pages, APNG, animated WebP)
_MULTI_FRAME_EXTS = (".tif", ".tiff", ".png", ".webp")


def _pages(path: str) -> int:
    """How many frames OpenCV finds in an image file (1 where it cannot say): ~0.6 ms a
    PNG frame (its read ~10 ms), its complaints about a damaged file caught (the read names
    it)."""
    if not (path.lower().endswith(_MULTI_FRAME_EXTS) and utf8_name(path)
            and os.path.isfile(path) and os.path.getsize(path)):
        return 1
    try:
        n, said = _stderr_of(cv2.imcount, path)
    except cv2.error:
        return 1
    # what was caught is not passed on: a library's warning about the file (libpng's about
    # a colour profile) comes again from its read, which passes it on (said twice a frame)
    return max(1, int(n))


def _animation_frames(path: str, grey: Grey, pages: int) -> Iterator[np.ndarray]:
    """The frames of an animated PNG or WebP (``cv2.imreadanimation``, OpenCV 4.11 and
    later), read whole within :data:`MAX_ANIMATION_BYTES`."""
    first = read_image(path, None)  # its size, for the bound (and the limit on pixels)
    need = pages * first.shape[0] * first.shape[1] * 4
    if not hasattr(cv2, "imreadanimation"):
        raise SourceError(f"{path}: an animation of {pages} frames, which this OpenCV "
                          f"({cv2.__version__}) does not read: convert it to a video or to "
                          "image files")
    if need > MAX_ANIMATION_BYTES:
        raise SourceError(f"{path}: an animation of {pages} frames of {first.shape[1]}x"
                          f"{first.shape[0]} px is read whole, {need:,} bytes, more than "
                          f"{MAX_ANIMATION_BYTES >> 20} MiB: convert it to a video or to "
                          "image files")
    (ok, animation), _ = _stderr_of(cv2.imreadanimation, path)
    frames = list(animation.frames) if ok else []
    if len(frames) != pages:
        raise SourceError(f"{path}: an animation of {pages} frames, {len(frames)} of which "
                          "read")
    for image in frames:
        yield grey(image)


def read_image(path: str, grey: Grey | None = None, page: int | None = None) -> np.ndarray:
    """One image file as (H, W) uint8 grey (16-bit images scaled by ``grey``, the stream's,
    else by the depth of this image's own samples: see :class:`Grey`); ``page``: that page
    of a multi-page file (:func:`image_frames`)."""
    if not os.path.exists(path):
        raise SourceError(f"{path}: no such file")
    if os.path.isdir(path):
        raise SourceError(f"{path}: is a folder, expected an image file")
    if os.path.getsize(path) == 0:
        raise SourceError(f"{path}: not a readable image: the file is empty (0 bytes)")
    if page is not None:
        read = functools.partial(_read_page, path, page)
    elif utf8_name(path):
        read = functools.partial(cv2.imread, path, cv2.IMREAD_UNCHANGED)
    else:  # read here, decoded from memory (OpenCV would crash on the name)
        read = functools.partial(cv2.imdecode, np.fromfile(path, np.uint8),
                                 cv2.IMREAD_UNCHANGED)
    # an image whose header claims more pixels than the limit is refused unread (imagelimit)
    img, said = _stderr_of(imagelimit.decode, path, read, SourceError)
    if img is not None and "Premature end" in said and path.lower().endswith((".jpg", ".jpeg")):
        raise SourceError(f"{path}: damaged image: the JPEG data ends before the image "
                          "does (cut short?)")
    _pass_on(said, read=img is not None)
    if img is None:
        raise SourceError(f"{path}: not a readable image" if page is None
                          else f"{path}: page {page} is not a readable image")
    return (grey or Grey())(img)


def _read_page(path: str, page: int) -> np.ndarray | None:
    ok, mats = cv2.imreadmulti(path, start=page, count=1, flags=cv2.IMREAD_UNCHANGED)
    return mats[0] if ok and mats else None


def utf8_name(path: str) -> bool:
    """Whether OpenCV can be given ``path``: its bindings pass a name on as UTF-8, and a name
    that is not (a file named in another encoding, which Python holds as surrogate escapes,
    e.g. ``frame\\udce9.png`` for Latin-1's ``frame\\xe9.png``) crashed the process in
    ``cv2.imread``, ``cv2.haveImageReader`` and ``cv2.VideoCapture`` (SIGSEGV, no message).
    Such an image is read by Python and decoded from memory; such a video cannot be opened
    (an error says so)."""
    try:
        path.encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True


def _stderr_of(fn: Callable[..., Any], *args: Any) -> tuple[Any, str]:
    """``fn(*args)`` and what it printed on the process's stderr meanwhile (the C libraries
    under OpenCV print there: libpng's "libpng error: Read Error" before a damaged image's
    None, libjpeg's "Premature end of JPEG file" as the only sign of a JPEG cut short, the
    AVI reader's "Unexpected element" for a file that is no video): caught on its way, so
    that a bad file is one line of ours naming it. Other threads' lines written meanwhile
    land here too: :func:`_pass_on` gives them back where the file was read."""
    with tempfile.TemporaryFile() as caught:
        sys.stderr.flush()
        saved = os.dup(2)
        os.dup2(caught.fileno(), 2)
        try:
            out = fn(*args)
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        caught.seek(0)
        return out, caught.read().decode("utf-8", "replace")


def _pass_on(said: str, read: bool) -> None:
    """Write ``said`` (:func:`_stderr_of`) to stderr again where the file was ``read`` (a
    library's warning about a file it read is still news); where it was not, the caller's
    error says what the library's complaint did (whose last line may be binary garbage: the
    AVI reader prints the bytes it did not expect)."""
    if read and said:
        sys.stderr.write(said)
        sys.stderr.flush()


#: a number in a file name: a time stamp in s with its fraction (9 or more digits before the
#: point: s since the Unix epoch), else a run of digits (``cam1.10``: 1 and 10, not 1.1)
_DIGITS = re.compile(r"(\d{9,}\.\d+|\d+)")


def name_order(path: str) -> tuple[tuple[tuple[int, Decimal | str], ...], str]:
    """Sort key of the frames of a folder or glob: by name, the numbers in it by their value
    (``f2.png`` before ``f10.png``, as a file browser shows them; ``ffmpeg -i v.mp4 f%d.png``
    writes such names), zero-padded names in the same order as plain text, and a time stamp
    with a fraction by its value: frames named by their time stamp (``1700000000.25.png``, as
    exporters write ``str(stamp)``) played .0, .5, .25, .75 when the fraction's digits were
    read as a whole number. Only a number of 9 or more digits before the point is a time
    stamp: ``cam1.10.png`` comes after ``cam1.9.png``, as it always did."""
    parts = _DIGITS.split(path)
    return tuple((1, Decimal(p)) if i % 2 else (0, p) for i, p in enumerate(parts)), path


def _check_images(paths: list[str]) -> None:
    """Fail now, not after the first frames, on a file that is not an image at all: OpenCV
    knows a format from a file's first bytes. (A damaged image of a known format still fails
    when it is read, naming the file; so does an empty one, the usual damage of a recorder
    cut off, which a camera then leaves out as it does a truncated one: refused here, it
    ended a run before its first frame.)"""
    for p in paths:
        # (a name OpenCV cannot take is checked when it is read, :func:`read_image`)
        if os.path.isfile(p) and utf8_name(p) and os.path.getsize(p) \
                and not cv2.haveImageReader(p):
            if p.lower().endswith(VIDEO_EXTS):
                raise SourceError(f"{p}: a video among {len(paths)} files: give one video "
                                  "alone, or image files")
            raise SourceError(f"{p}: not a readable image")


@dataclass
class FileFrames:
    """Frames from files, in order, optionally resized; all frames must share one size.

    ``paths`` are image files, or a single video file. ``size`` = (width, height) resizes every
    frame; without it a frame of another size than the first is an error, whose text names
    ``size_flag`` as the way to scale them. With ``skip``, an image that cannot be read or a
    frame of another size is given to it (a :class:`SourceError` naming the file) and left
    out, and the frames after it follow: a camera goes on where an offline run stops.
    """

    paths: list[str]
    video: bool = False
    size: tuple[int, int] | None = None
    description: str = ""
    size_flag: str = "--resize"
    skip: Callable[[SourceError], None] | None = None

    def __iter__(self) -> Iterator[np.ndarray]:
        expected: tuple[int, int] | None = None
        for name, frame in self._raw():
            if self.size is not None:
                frame = resize(frame, self.size)
            else:
                if expected is None:
                    expected = frame.shape
                elif frame.shape != expected:
                    self._bad(SourceError(
                        f"{name}: frame is {frame.shape[1]}x{frame.shape[0]} but the first was "
                        f"{expected[1]}x{expected[0]}; give {self.size_flag} to scale them"))
                    continue
            yield np.ascontiguousarray(frame)

    def _bad(self, e: SourceError) -> None:
        if self.skip is None:
            raise e
        self.skip(e)

    def _raw(self) -> Iterator[tuple[str, np.ndarray]]:
        grey = Grey()  # one stream: 16-bit frames scaled by the depth of its samples
        if self.video:
            path = self.paths[0]
            if not utf8_name(path):
                raise SourceError(f"{path}: OpenCV cannot open a video whose name is not "
                                  "UTF-8: rename it, or link to it under a UTF-8 name")
            cap, said = _stderr_of(cv2.VideoCapture, path)
            _pass_on(said, read=cap.isOpened())
            if not cap.isOpened():
                raise SourceError(f"{path}: not a readable video")
            try:
                announced = cap.get(cv2.CAP_PROP_FRAME_COUNT)
                fps = cap.get(cv2.CAP_PROP_FPS)
                k = 0
                # the stream positions read, ms: the first picture's and the furthest
                start = reached = 0.0
                while True:
                    ok, img = cap.read()
                    if not ok:
                        if k == 0:
                            raise SourceError(f"{path}: video has no readable frame")
                        _check_complete(path, k, announced, fps, start, reached)
                        return
                    at = cap.get(cv2.CAP_PROP_POS_MSEC)
                    if k == 0:
                        start = at
                    reached = max(reached, at)
                    yield f"{path}#{k}", grey(img)
                    k += 1
            finally:
                cap.release()
        else:
            for p in self.paths:
                for k, read in enumerate(frame_reads(p, grey)):
                    try:
                        image = read()
                    except SourceError as e:
                        self._bad(e)
                        continue
                    yield (p if not k else f"{p}#{k}"), image


def _check_complete(path: str, read: int, announced: float, fps: float = 0.0,
                    start_ms: float = 0.0, reached_ms: float = 0.0) -> None:
    """A video that ends well before the frame count of its header is cut short or damaged:
    say so once its readable frames have been used. Containers without an index estimate the
    count from the duration, so a shortfall of a frame or two percent is not an error.

    Nor is a shortfall where the stream's timestamps got to the end the header announces
    (``announced`` frames at ``fps``): the last picture read (at ``reached_ms``; the first at
    ``start_ms``) and the spacing of the pictures read reach it to within a frame or two
    percent. The container then counts entries that hold no picture. OpenCV's own
    ``vtest.avi`` is one: 25 fps stored at 50, every other of its 682 index entries empty (an
    AVI's "repeat the last frame"), its 341 pictures 40 ms apart from 40 ms to 13.60 s of
    13.64; it was reported cut short, and ``vistrack up`` ended the run as a failure. A file
    that lost its end stops short in time as well (that one's first half: at 6.12 s)."""
    if not (math.isfinite(announced) and announced > 0
            and announced - read > max(1, 0.02 * announced)):
        return
    if math.isfinite(fps) and fps > 0 and math.isfinite(reached_ms) and reached_ms > 0:
        end_ms = 1e3 * announced / fps
        spacing = (reached_ms - start_ms) / (read - 1) if read > 1 else 1e3 / fps
        if reached_ms + spacing >= end_ms - max(1e3 / fps, 0.02 * end_ms):
            return
    raise VideoCutShort(f"{path}: the video ends after {read} of the {announced:.0f} "
                        "frames its header announces (cut short or damaged)")


@dataclass
class GeneratedFrames:
    """The built-in generated sequence (a textured scene that moves)."""

    n: int = 60
    size: tuple[int, int] | None = None
    description: str = "built-in generated sequence"

    def __iter__(self) -> Iterator[np.ndarray]:
        for f in synthetic.builtin_sequence(self.n):
            yield f if self.size is None else resize(f, self.size)


def _is_image(path: str) -> bool:
    return path.lower().endswith(IMAGE_EXTS)


def _listed(name: str) -> bool:
    """Whether a folder's entry ``name`` is one of its frames: an image file by its name,
    not a hidden one (as a glob has it). A folder copied from a Mac holds ``._f0.png`` beside
    each ``f0.png`` (AppleDouble metadata, 4 KiB, no image), and was refused whole."""
    return _is_image(name) and not name.startswith(".")


def open_files(specs: Sequence[str], size: tuple[int, int] | None = None
               ) -> FileFrames | GeneratedFrames:
    """Resolve FRAMES arguments: a video file, a folder of images (in :func:`name_order`), a glob
    pattern, image files in order, or ``builtin`` (or nothing) for the built-in sequence."""
    specs = list(specs)
    if not specs or specs == [BUILTIN]:
        return GeneratedFrames(size=size)
    if len(specs) == 1:
        spec = specs[0]
        if os.path.isdir(spec):
            paths = sorted((os.path.join(spec, f) for f in os.listdir(spec) if _listed(f)),
                           key=name_order)
            if not paths:
                raise SourceError(f"{spec}: folder holds no image ({', '.join(IMAGE_EXTS)})")
            _check_images(paths)
            return FileFrames(paths, size=size, description=f"{spec} ({len(paths)} images)")
        if any(ch in spec for ch in "*?[") and not os.path.exists(spec):
            paths = sorted((p for p in glob.glob(spec) if _is_image(p)), key=name_order)
            if not paths:
                raise SourceError(f"{spec}: pattern matches no image file")
            _check_images(paths)
            return FileFrames(paths, size=size, description=f"{spec} ({len(paths)} images)")
        if not spec:
            raise SourceError("'' is not a file or folder: give a video, a folder of images, "
                              "a glob or image files")
        if not os.path.exists(spec):
            # quoted where blanks would hide ('rgba ' from a stray space)
            shown = repr(spec) if spec != spec.strip() else spec
            raise SourceError(f"{shown}: no such file or folder"
                              + ("; a network stream is read by the camera alone "
                                 "(vistrack camera --source URL)" if is_stream(spec) else ""))
        if not _is_image(spec):
            return FileFrames([spec], video=True, size=size, description=spec)
    for p in specs:
        if not os.path.exists(p):
            raise SourceError(f"{p!r}: no such file" if not p else f"{p}: no such file")
        if os.path.isdir(p):
            raise SourceError(f"{p}: is a folder; give one folder alone, or image files")
    _check_images(specs)
    # one image is named (a user who gave one file reads its name, not "1 images")
    what = specs[0] if len(specs) == 1 else f"{len(specs)} images"
    return FileFrames(specs, size=size, description=what)


def device_index(spec: str) -> int:
    """N of a ``device:N`` source, checked against :data:`DEVICE_RANGE`."""
    text = spec.split(":", 1)[1]
    lo, hi = DEVICE_RANGE
    try:
        index = int(text)
    except ValueError:
        raise SourceError(f"{spec!r}: the device index must be an integer {lo}..{hi}, "
                          "e.g. device:0") from None
    if not lo <= index <= hi:
        raise SourceError(f"{spec!r}: device index {index} is out of range: allowed {lo}..{hi}")
    return index


def probe_device(spec: str) -> None:
    """Open the ``device:N`` source (or a network stream's URL), read one frame and let the
    device go: a camera that is missing, busy or mute is found before anything that needs it
    starts.

    Raises
    ------
    SourceError
        Naming the device and what failed.
    """
    frames = open_stream(spec) if is_stream(spec) else open_device(device_index(spec))
    try:
        next(frames)
    finally:
        frames.close()


def open_device(index: int, size: tuple[int, int] | None = None, *,
                retry_s: float = DEVICE_RETRY_S, capture=cv2.VideoCapture) -> DeviceFrames:
    """Frames from a camera device through cv2.VideoCapture, grey, optionally resized: the
    newest the device has delivered each time one is asked for (:class:`DeviceFrames`).

    Raises
    ------
    SourceError
        If the index is out of range or the device does not open.
    """
    lo, hi = DEVICE_RANGE
    if not lo <= index <= hi:  # a negative index crashes OpenCV (segmentation fault)
        raise SourceError(f"device:{index}: device index out of range: allowed {lo}..{hi}")
    cap = capture(index)
    if not cap.isOpened():
        raise SourceError(f"device:{index}: cannot open the camera device")
    return DeviceFrames(cap, index, size, retry_s, capture)


def _capture_stream(url: str) -> Any:
    """``cv2.VideoCapture`` of a stream by FFmpeg, its open and reads bounded by
    :data:`STREAM_TIMEOUT_MS`."""
    return cv2.VideoCapture(url, cv2.CAP_FFMPEG, [
        cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, STREAM_TIMEOUT_MS,
        cv2.CAP_PROP_READ_TIMEOUT_MSEC, STREAM_TIMEOUT_MS])


def open_stream(url: str, size: tuple[int, int] | None = None, *,
                retry_s: float = STREAM_TIMEOUT_MS / 1000,
                capture: Callable[[str], Any] = _capture_stream) -> DeviceFrames:
    """A network stream (an IP camera's ``rtsp://...``, :data:`STREAM_SCHEMES`) read as a
    device is (:class:`DeviceFrames`: the newest frame it has delivered each time one is
    asked for, opened again once when it stops delivering).

    Raises
    ------
    SourceError
        If the stream does not open within :data:`STREAM_TIMEOUT_MS` (naming the URL without
        its password).
    """
    cap, said = _stderr_of(capture, url)
    if not cap.isOpened():
        cap.release()
        raise SourceError(f"{redacted(url)}: cannot open the stream (within "
                          f"{STREAM_TIMEOUT_MS / 1000:g} s: a wrong address, or the camera "
                          "does not answer)")
    return DeviceFrames(cap, url, size, retry_s, capture)


class DeviceFrames:
    """The frames of an open camera device, each the newest it has delivered: a thread reads
    the device as fast as it delivers, and each ``next()`` returns the newest frame not
    returned before (waiting for one if there is none), grey and resized; ``capture_ns`` is
    when it was read.

    A device queues its frames (OpenCV's V4L2 back end four): read at a slower pace than the
    camera's own, as ``--fps 15`` on a 30 fps camera does, every frame read was the oldest of
    the queue, 4 frames (133 ms at 30 fps) old, for as long as the run lasted, and a robot
    acting on it steers by where it was. Reading as the device delivers keeps the queue empty.

    A read that fails is tried again, for up to ``retry_s`` seconds of reads failing in a
    row; then the device is opened again (``capture(index)``, ``cv2.VideoCapture``: a seam
    for tests), once, and only if that brings no frame either does ``next()`` raise
    :class:`SourceError` (a camera unplugged: the launcher restarts the camera service by its
    policy). :meth:`close` stops the thread, which lets the device go.
    """

    def __init__(self, cap, index: int | str, size: tuple[int, int] | None, retry_s: float,
                 capture) -> None:
        self.index = index  # a device's number, or a stream's URL (:func:`open_stream`)
        #: how logs and errors name it: ``device:N``, or the URL without its password
        self.name = f"device:{index}" if isinstance(index, int) else redacted(index)
        self.size = size
        self.retry_s = retry_s
        self.capture_ns = 0
        self._capture = capture
        self._grey = Grey()
        self._ready = threading.Condition()
        self._newest: tuple[np.ndarray, int] | None = None
        self._error: SourceError | None = None
        self._stop = threading.Event()
        #: another stop that ends ``next()``'s wait (the camera's): a stream that delivers
        #: nothing (a video over HTTP at its end, a camera gone) held a stop for up to two
        #: read timeouts while it was tried and opened again
        self.stop_with: threading.Event | None = None
        self.cap = cap  # the capture being read (another once the device is opened again)
        self._thread = threading.Thread(target=self._read_all, daemon=True,
                                        name=self.name)
        self._thread.start()

    def __iter__(self) -> DeviceFrames:
        return self

    def __next__(self) -> np.ndarray:
        with self._ready:
            while (self._newest is None and self._error is None) or self._stop.is_set():
                if self._stop.is_set() or (self.stop_with is not None
                                           and self.stop_with.is_set()):
                    raise StopIteration
                self._ready.wait(0.1)
            if self._newest is None:
                raise self._error  # type: ignore[misc]
            img, self.capture_ns = self._newest
            self._newest = None
        frame = self._grey(img)
        return frame if self.size is None else resize(frame, self.size)

    def close(self) -> None:
        """Stop reading; the thread lets the device go once its read in progress returns."""
        self._stop.set()
        self._thread.join(timeout=2.0)

    def _read_all(self) -> None:
        index, name = self.index, self.name
        cap = self.cap
        try:
            while not self._stop.is_set():
                img = self._read(cap)
                if img is None and not self._stop.is_set():
                    log.warning("%s: no frame for %g s: opening the device again",
                                name, self.retry_s)
                    cap.release()
                    cap = self.cap = self._capture(index)
                    img = self._read(cap) if cap.isOpened() else None
                    if img is None:
                        raise SourceError(f"{name}: the camera stopped delivering "
                                          f"frames (none for {self.retry_s:g} s, nor once "
                                          "opened again)")
                    log.info("%s: delivering frames again, opened again", name)
                if img is not None:
                    with self._ready:
                        self._newest = (img, time.time_ns())
                        self._ready.notify()
        except Exception as e:  # noqa: BLE001 - said by next(), not lost with the thread
            # any failure of the device or its driver (OpenCV raises cv2.error): next()
            # waited for a frame for ever once this thread had died of one
            error = e if isinstance(e, SourceError) else SourceError(
                f"{name}: reading the camera failed: {type(e).__name__}: {e}")
            with self._ready:
                self._error = error
                self._ready.notify()
        finally:
            cap.release()

    def _read(self, cap) -> np.ndarray | None:
        """The next frame the device delivers, reads that fail tried again for up to
        ``retry_s`` seconds (logged once each way); None if none came (or on close)."""
        ok, img = cap.read()
        if ok and img is not None:
            return img
        name = self.name
        log.warning("%s: a frame could not be read; trying again", name)
        deadline = time.monotonic() + self.retry_s
        failed = 1
        while time.monotonic() < deadline and not self._stop.wait(DEVICE_RETRY_PAUSE_S):
            ok, img = cap.read()
            if ok and img is not None:
                log.info("%s: a frame read again after %d failed reads", name, failed)
                return img
            failed += 1
        return None
