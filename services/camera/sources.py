"""Frame sources: video files, image folders, globs and lists, devices, the built-in sequence.

Pure OpenCV, no Zenoh: the camera service and the offline ``vistrack track`` / ``tune`` read
frames through exactly this code. Every frame comes out 8-bit grey, converted the way
:func:`vistrack.common.vision.to_gray` does it.
"""

from __future__ import annotations

import glob
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from ...common import synthetic
from ...common.vision import to_gray

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".webp")
VIDEO_EXTS = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv")
BUILTIN = "builtin"


class SourceError(ValueError):
    """A frame source cannot be opened or read; the message names the path and the problem."""


def parse_size(text: str) -> tuple[int, int]:
    """'WxH' -> (width, height), each 8..8192."""
    try:
        w_s, h_s = text.lower().split("x")
        w, h = int(w_s), int(h_s)
    except ValueError:
        raise SourceError(f"size {text!r} is not WIDTHxHEIGHT, e.g. 256x256") from None
    if not (8 <= w <= 8192 and 8 <= h <= 8192):
        raise SourceError(f"size {text!r} is out of range: width and height must be 8..8192")
    return w, h


def read_image(path: str) -> np.ndarray:
    """One image file as (H, W) uint8 grey."""
    if not os.path.exists(path):
        raise SourceError(f"{path}: no such file")
    if os.path.isdir(path):
        raise SourceError(f"{path}: is a folder, expected an image file")
    img = cv2.imread(path, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise SourceError(f"{path}: not a readable image")
    return to_gray(img)


@dataclass
class FileFrames:
    """Frames from files, in order, optionally resized; all frames must share one size.

    ``paths`` are image files, or a single video file. ``size`` = (width, height) resizes every
    frame; without it a frame of another size than the first is an error.
    """

    paths: list[str]
    video: bool = False
    size: tuple[int, int] | None = None
    description: str = ""

    def __iter__(self) -> Iterator[np.ndarray]:
        expected: tuple[int, int] | None = None
        for name, frame in self._raw():
            if self.size is not None:
                if frame.shape[::-1] != self.size:
                    frame = cv2.resize(frame, self.size, interpolation=cv2.INTER_AREA)
            else:
                if expected is None:
                    expected = frame.shape
                elif frame.shape != expected:
                    raise SourceError(
                        f"{name}: frame is {frame.shape[1]}x{frame.shape[0]} but the first was "
                        f"{expected[1]}x{expected[0]}; give --resize/--size to scale them")
            yield np.ascontiguousarray(frame)

    def _raw(self) -> Iterator[tuple[str, np.ndarray]]:
        if self.video:
            path = self.paths[0]
            cap = cv2.VideoCapture(path)
            if not cap.isOpened():
                raise SourceError(f"{path}: not a readable video")
            try:
                k = 0
                while True:
                    ok, img = cap.read()
                    if not ok:
                        if k == 0:
                            raise SourceError(f"{path}: video has no readable frame")
                        return
                    yield f"{path}#{k}", to_gray(img)
                    k += 1
            finally:
                cap.release()
        else:
            for p in self.paths:
                yield p, read_image(p)


@dataclass
class GeneratedFrames:
    """The built-in generated sequence (a textured scene that moves)."""

    n: int = 60
    size: tuple[int, int] | None = None
    description: str = "built-in generated sequence"

    def __iter__(self) -> Iterator[np.ndarray]:
        for f in synthetic.builtin_sequence(self.n):
            if self.size is not None and f.shape[::-1] != self.size:
                f = cv2.resize(f, self.size, interpolation=cv2.INTER_AREA)
            yield f


def _is_image(path: str) -> bool:
    return path.lower().endswith(IMAGE_EXTS)


def open_files(specs: Sequence[str], size: tuple[int, int] | None = None
               ) -> FileFrames | GeneratedFrames:
    """Resolve FRAMES arguments: a video file, a folder of images (sorted by name), a glob
    pattern, image files in order, or ``builtin`` (or nothing) for the built-in sequence."""
    specs = list(specs)
    if not specs or specs == [BUILTIN]:
        return GeneratedFrames(size=size)
    if len(specs) == 1:
        spec = specs[0]
        if os.path.isdir(spec):
            paths = sorted(os.path.join(spec, f) for f in os.listdir(spec) if _is_image(f))
            if not paths:
                raise SourceError(f"{spec}: folder holds no image ({', '.join(IMAGE_EXTS)})")
            return FileFrames(paths, size=size, description=f"{spec} ({len(paths)} images)")
        if any(ch in spec for ch in "*?[") and not os.path.exists(spec):
            paths = sorted(p for p in glob.glob(spec) if _is_image(p))
            if not paths:
                raise SourceError(f"{spec}: pattern matches no image file")
            return FileFrames(paths, size=size, description=f"{spec} ({len(paths)} images)")
        if not os.path.exists(spec):
            raise SourceError(f"{spec}: no such file or folder")
        if not _is_image(spec):
            return FileFrames([spec], video=True, size=size, description=spec)
    for p in specs:
        if not os.path.exists(p):
            raise SourceError(f"{p}: no such file")
        if os.path.isdir(p):
            raise SourceError(f"{p}: is a folder; give one folder alone, or image files")
    return FileFrames(specs, size=size, description=f"{len(specs)} images")


def open_device(index: int, size: tuple[int, int] | None = None) -> Iterator[np.ndarray]:
    """Frames from a camera device through cv2.VideoCapture, grey, optionally resized."""
    cap = cv2.VideoCapture(index)
    if not cap.isOpened():
        raise SourceError(f"device:{index}: cannot open the camera device")
    try:
        while True:
            ok, img = cap.read()
            if not ok:
                raise SourceError(f"device:{index}: the camera stopped delivering frames")
            frame = to_gray(img)
            if size is not None and frame.shape[::-1] != size:
                frame = cv2.resize(frame, size, interpolation=cv2.INTER_AREA)
            yield frame
    finally:
        cap.release()
