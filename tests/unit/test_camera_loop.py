"""A looping file camera's source (:func:`open_source`): a video cut short (the ``cut_video``
fixture) is played again and again, kept in memory or (too large to keep) decoded each pass."""

from __future__ import annotations

import itertools
import logging

import cv2
import numpy as np
import pytest

from vistrack.common.sources import SourceError
from vistrack.services.camera import service


def _same_frames(got, held):
    """Each frame of ``got`` is the file's next one (``held``: BGR), pass after pass (the grey
    conversion may round one grey level apart from OpenCV's)."""
    for k, frame in enumerate(got):
        ref = cv2.cvtColor(held[k % len(held)], cv2.COLOR_BGR2GRAY)
        assert frame.shape == ref.shape
        assert np.abs(frame.astype(int) - ref).max() <= 1, k


def test_kept_in_memory_it_loops_the_frames_it_holds(cut_video, capsys):
    cut, held = cut_video
    frames = service.open_source(f"file:{cut}", None, loop=True)
    err = capsys.readouterr().err
    assert err == (f"vistrack camera: warning: {cut}: the video ends after {len(held)} of the "
                   f"10 frames its header announces (cut short or damaged); looping the "
                   f"{len(held)} frames it holds\n")
    _same_frames(list(itertools.islice(frames, 3 * len(held) + 1)), held)


def test_decoded_each_pass_it_loops_and_warns_once(cut_video, monkeypatch, caplog):
    cut, held = cut_video
    monkeypatch.setattr(service, "LOOP_CACHE_BYTES", 1)  # too large to keep: every pass decoded
    with caplog.at_level(logging.WARNING, logger="vistrack.camera"):
        got = list(itertools.islice(service.open_source(f"file:{cut}", None, loop=True),
                                    4 * len(held)))
    _same_frames(got, held)
    warnings = [r.getMessage() for r in caplog.records]
    assert warnings == [f"{cut}: the video ends after {len(held)} of the 10 frames its header "
                        "announces (cut short or damaged); looping the frames it holds"]


def test_a_single_pass_still_ends_with_the_error(cut_video):
    cut, held = cut_video
    frames = service.open_source(f"file:{cut}", None, loop=False)
    got = []
    with pytest.raises(SourceError, match=f"ends after {len(held)} of the 10 frames"):
        for f in frames:
            got.append(f)
    _same_frames(got, held)


@pytest.mark.parametrize("loop", [False, True])
def test_a_frame_of_another_size_is_skipped_and_the_rest_sent(tmp_path, caplog, loop):
    """A folder whose third image has another size than the first: the camera used to end
    (exit 2) there, and the run with it; it now leaves that frame out, says so once (naming
    the file, the sizes and its own --size flag) and counts it, and sends the others, pass
    after pass when looping. An offline run (no skip) still stops with the error."""
    from vistrack.common.bus import MemoryNode
    from vistrack.common.sources import open_files

    rng = np.random.default_rng(0)
    images = [rng.integers(0, 256, (100, 100) if i == 2 else (60, 80), dtype=np.uint8)
              for i in range(5)]
    for i, image in enumerate(images):
        cv2.imwrite(str(tmp_path / f"f{i}.png"), image)
    skipped = service.Skipped()
    with MemoryNode("camera") as node, caplog.at_level(logging.WARNING, logger="vistrack.camera"):
        skipped.attach(node)
        frames = service.open_source(f"file:{tmp_path}", None, loop=loop, skip=skipped)
        got = list(itertools.islice(frames, 8 if loop else 10))
        # left out each pass, as a seq each pass (said once: a loop decodes once)
        assert node.status.extra["skipped"] == (2 if loop else 1)
    kept = [images[i] for i in (0, 1, 3, 4)]
    assert len(got) == (8 if loop else 4)
    for k, frame in enumerate(got):
        assert np.array_equal(frame, kept[k % 4]), k
    said = [r.getMessage() for r in caplog.records]
    assert said == [f"{tmp_path / 'f2.png'}: frame is 100x100 but the first was 80x60; give "
                    "--size to scale them: frame skipped, the frames after it go on"]
    with pytest.raises(SourceError, match="frame is 100x100 but the first was 80x60; give "
                                          "--resize to scale them"):
        list(open_files([str(tmp_path)]))


@pytest.mark.parametrize("loop", [False, True])
def test_a_video_with_empty_entries_is_complete(drop_frame_video, caplog, capsys, loop):
    """Its header counts 20 frames, 10 decode, and its timestamps reach its end: every
    frame is sent, and no pass ends with an error or a warning (it was "cut short")."""
    path, frames = drop_frame_video
    with caplog.at_level(logging.WARNING, logger="vistrack.camera"):
        got = list(itertools.islice(service.open_source(f"file:{path}", None, loop=loop), 25))
    assert len(got) == (25 if loop else 10)
    _same_frames(got, frames)
    assert not caplog.records and capsys.readouterr().err == ""


def test_a_loop_whose_files_are_gone_ends_with_an_error(tmp_path, monkeypatch, caplog):
    """Decoded each pass (too large to keep), its files removed (a USB stick pulled): each
    was skipped with a warning, and the loop went round for ever with no frame, a core busy,
    deaf to a stop. A pass that gives no frame now ends it with an error."""
    from vistrack.common.bus import MemoryNode

    monkeypatch.setattr(service, "LOOP_CACHE_BYTES", 1)
    rng = np.random.default_rng(0)
    folder = tmp_path / "stick"
    folder.mkdir()
    for i in range(3):
        cv2.imwrite(str(folder / f"f{i}.png"), rng.integers(0, 256, (60, 80), dtype=np.uint8))
    skipped = service.Skipped()
    with MemoryNode("camera") as node, caplog.at_level(logging.WARNING, logger="vistrack.camera"):
        skipped.attach(node)
        frames = service.open_source(f"file:{folder}", None, loop=True, skip=skipped)
        assert len(list(itertools.islice(frames, 4))) == 4  # a pass and one more frame
        for f in folder.iterdir():
            f.unlink()
        with pytest.raises(SourceError, match=f"{folder}: a pass of --loop gave no frame"):
            next(frames)  # the rest of this pass, then an empty one
        assert node.status.extra["skipped"] == 5  # this pass's 2, the next one's 3


@pytest.mark.parametrize("ext", [".pnm", ".pbm", ".jp2", ".ras"])
def test_a_folder_or_glob_of_other_image_types_opencv_reads_is_taken(tmp_path, ext):
    """A folder of .pnm files held "no image", and a glob of them matched "no image file",
    though each one alone opened (as a video)."""
    from vistrack.common.sources import open_files

    rng = np.random.default_rng(0)
    images = [np.where(rng.random((40, 48)) < 0.5, 0, 255).astype(np.uint8) for _ in range(3)]
    for i, image in enumerate(images):
        assert cv2.imwrite(str(tmp_path / f"f{i}{ext}"), image), ext
    # what OpenCV reads of each file (a lossy JPEG 2000 is not the image written)
    held = [cv2.imread(str(tmp_path / f"f{i}{ext}"), cv2.IMREAD_UNCHANGED) for i in range(3)]
    for spec in (str(tmp_path), str(tmp_path / f"*{ext}")):
        got = list(open_files([spec]))
        assert len(got) == 3, spec
        assert all(np.array_equal(g, h) for g, h in zip(got, held, strict=True)), spec



@pytest.mark.parametrize("kept", [True, False], ids=["kept", "decoded-each-pass"])
def test_a_loop_says_which_frames_start_a_later_pass(tmp_path, monkeypatch, kept):
    """``cuts`` grows by one exactly at the first frame of the second and later passes, kept
    in memory or decoded each pass; a single image looped is a still scene, never a cut."""
    if not kept:
        monkeypatch.setattr(service, "LOOP_CACHE_BYTES", 1)
    rng = np.random.default_rng(0)
    for i in range(3):
        cv2.imwrite(str(tmp_path / f"f{i}.png"), rng.integers(0, 256, (60, 80), dtype=np.uint8))
    frames = service.open_source(f"file:{tmp_path}", None, loop=True)
    cuts = [frames.cuts for _ in itertools.islice(frames, 10)]
    assert cuts == [0, 0, 0, 1, 1, 1, 2, 2, 2, 3]
    still = tmp_path / "still.png"
    cv2.imwrite(str(still), rng.integers(0, 256, (60, 80), dtype=np.uint8))
    frames = service.open_source(f"file:{still}", None, loop=True)
    assert not any(frames.cuts for _ in itertools.islice(frames, 5))


def test_the_first_frame_read_ahead_keeps_a_loops_cuts(tmp_path):
    """The camera reads a source's first frame before it starts (to fail early on a bad
    file): a looping source is kept as it is, so its cuts are still seen, and its first
    frame is given once."""
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 256, (60, 80), dtype=np.uint8) for _ in range(2)]
    for i, image in enumerate(images):
        cv2.imwrite(str(tmp_path / f"f{i}.png"), image)
    source = service.open_source(f"file:{tmp_path}", None, loop=True)
    frames = service._first_frame_read(source)
    assert frames is source
    got = [(next(frames), source.cuts) for _ in range(5)]
    assert [cuts for _, cuts in got] == [0, 0, 1, 1, 2]
    for k, (frame, _) in enumerate(got):
        assert np.array_equal(frame, images[k % 2]), k


def test_a_folder_copied_from_a_mac_is_read_without_its_hidden_files(tmp_path):
    """macOS leaves ``._NAME`` (AppleDouble, no image) beside each file on a stick or a
    share: the folder was refused whole ("._f0.png: not a readable image") where a glob of
    it, which skips hidden names, was read."""
    from vistrack.common.sources import open_files

    rng = np.random.default_rng(0)
    images = [rng.integers(0, 256, (60, 80), dtype=np.uint8) for _ in range(3)]
    for i, image in enumerate(images):
        cv2.imwrite(str(tmp_path / f"f{i}.png"), image)
        (tmp_path / f"._f{i}.png").write_bytes(b"\x00\x05\x16\x07" + bytes(4092))
    got = list(open_files([str(tmp_path)]))
    assert len(got) == 3 and all(np.array_equal(a, b) for a, b in zip(got, images, strict=True))


def test_an_empty_frame_is_left_out_by_a_camera_and_ends_an_offline_run_there(tmp_path,
                                                                              caplog):
    """A 0-byte image (a recorder cut off) was refused before the first frame, ending a
    camera's run at its start, where a truncated one is left out with a warning. It is now
    read as a damaged image: a camera leaves it out and goes on, an offline run gives the
    frames before it and then the error naming it."""
    from vistrack.common.bus import MemoryNode
    from vistrack.common.sources import open_files

    rng = np.random.default_rng(0)
    images = [rng.integers(0, 256, (60, 80), dtype=np.uint8) for _ in range(4)]
    for i, image in enumerate(images):
        if i == 2:
            (tmp_path / "f2.png").write_bytes(b"")
        else:
            cv2.imwrite(str(tmp_path / f"f{i}.png"), image)
    skipped = service.Skipped()
    with MemoryNode("camera") as node, caplog.at_level(logging.WARNING, logger="vistrack.camera"):
        skipped.attach(node)
        got = list(service.open_source(f"file:{tmp_path}", None, loop=False, skip=skipped))
        assert node.status.extra["skipped"] == 1
    assert [r.getMessage() for r in caplog.records] == [
        f"{tmp_path / 'f2.png'}: not a readable image: the file is empty (0 bytes): frame "
        "skipped, the frames after it go on"]
    assert len(got) == 3
    assert all(np.array_equal(a, images[i]) for a, i in zip(got, (0, 1, 3), strict=True))
    offline = []
    with pytest.raises(SourceError, match="f2.png: not a readable image: the file is empty"):
        for frame in open_files([str(tmp_path)]):
            offline.append(frame)
    assert len(offline) == 2
