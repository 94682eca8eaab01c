"""Image files that hold more than one frame: a multi-page TIFF stack, an animated PNG or WebP.
Only their first frame was read, in silence (an 8-page TIFF tracked as one frame)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vistrack.common import sources
from vistrack.common.sources import SourceError, open_files


def _frames(n: int = 4) -> list[np.ndarray]:
    rng = np.random.default_rng(5)
    return [rng.integers(0, 256, (30, 40), dtype=np.uint8) for _ in range(n)]


def test_a_tiff_stack_gives_every_page_in_order(tmp_path):
    frames = _frames()
    path = tmp_path / "stack.tif"
    assert cv2.imwritemulti(str(path), frames)
    got = list(open_files([str(path)]))
    assert len(got) == 4
    assert all(np.array_equal(a, b) for a, b in zip(got, frames, strict=True))
    # in a folder, beside single images: each file's frames in the folder's order
    cv2.imwrite(str(tmp_path / "a.png"), frames[3])
    got = list(open_files([str(tmp_path)]))
    assert len(got) == 5 and np.array_equal(got[0], frames[3])
    assert all(np.array_equal(a, b) for a, b in zip(got[1:], frames, strict=True))


@pytest.mark.skipif(not hasattr(cv2, "imwriteanimation"), reason="OpenCV < 4.11 writes no "
                    "animation to read back")
@pytest.mark.parametrize("ext", [".png", ".webp"])
def test_an_animated_image_gives_every_frame(tmp_path, ext):
    frames = _frames()
    animation = cv2.Animation()
    animation.frames = [cv2.cvtColor(f, cv2.COLOR_GRAY2BGR) for f in frames]
    animation.durations = [40] * len(frames)
    path = tmp_path / f"anim{ext}"
    params = [cv2.IMWRITE_WEBP_QUALITY, 101] if ext == ".webp" else []  # lossless
    assert cv2.imwriteanimation(str(path), animation, params)
    got = list(open_files([str(path)]))
    assert len(got) == 4
    for a, b in zip(got, frames, strict=True):
        assert np.abs(a.astype(int) - b).max() <= 1  # grey through BGR and back


def test_an_animation_too_large_to_read_whole_is_refused_naming_its_size(tmp_path,
                                                                         monkeypatch):
    if not hasattr(cv2, "imwriteanimation"):
        pytest.skip("OpenCV < 4.11 writes no animation")
    frames = _frames()
    animation = cv2.Animation()
    animation.frames = [cv2.cvtColor(f, cv2.COLOR_GRAY2BGR) for f in frames]
    animation.durations = [40] * len(frames)
    path = tmp_path / "anim.png"
    assert cv2.imwriteanimation(str(path), animation)
    monkeypatch.setattr(sources, "MAX_ANIMATION_BYTES", 1000)
    got = []
    with pytest.raises(SourceError, match="an animation of 4 frames of 40x30 px is read "
                                          "whole, 19,200 bytes, more than 0 MiB"):
        for frame in open_files([str(path)]):
            got.append(frame)
    assert got == []  # refused before any frame: OpenCV reads an animation whole


@pytest.mark.parametrize(("spec", "said"), [
    ("frames ", "'frames ': no such file or folder"),  # a stray blank, shown
    ("rtsp://10.0.0.5/stream", "rtsp://10.0.0.5/stream: no such file or folder; a network "
                               "stream is read by the camera alone (vistrack camera --source "
                               "URL)"),
])
def test_a_missing_source_is_named_so_that_what_was_wrong_shows(tmp_path, monkeypatch, spec,
                                                                 said):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "frames").mkdir()
    with pytest.raises(SourceError) as err:
        open_files([spec])
    assert str(err.value) == said


def test_a_bad_page_is_left_out_and_the_pages_after_it_are_read(tmp_path, caplog):
    """A 4-page TIFF whose third page does not read (its strip offset beyond the file): a
    camera leaves that page out, counted, and sends the fourth; the pages after a bad one
    were lost with it. An offline run stops at it, after the pages before."""
    import logging
    import struct

    from PIL import Image

    from vistrack.common.bus import MemoryNode
    from vistrack.services.camera import service as camera

    frames = _frames()
    path = tmp_path / "stack.tif"
    images = [Image.fromarray(f) for f in frames]
    images[0].save(path, save_all=True, append_images=images[1:])
    with Image.open(path) as im:
        im.seek(2)
        offset = im.tag_v2[273][0]  # StripOffsets of page 2
    data = bytearray(path.read_bytes())
    entry = data.find(struct.pack("<HHI", 273, 4, 1) + struct.pack("<I", offset))
    assert entry >= 0
    data[entry + 8:entry + 12] = struct.pack("<I", 0x7FFFFF00)
    path.write_bytes(bytes(data))
    skipped = camera.Skipped()
    with MemoryNode("camera") as node, caplog.at_level(logging.WARNING, logger="vistrack.camera"):
        skipped.attach(node)
        got = list(camera.open_source(f"file:{path}", None, loop=False, skip=skipped))
        assert node.status.extra["skipped"] == 1
    assert len(got) == 3
    assert all(np.array_equal(a, frames[i]) for a, i in zip(got, (0, 1, 3), strict=True))
    assert [r.getMessage() for r in caplog.records] == [
        f"{path}: page 2 is not a readable image: frame skipped, the frames after it go on"]
    offline = []
    with pytest.raises(SourceError, match="page 2 is not a readable image"):
        for frame in open_files([str(path)]):
            offline.append(frame)
    assert len(offline) == 2
