"""The frames of a folder or a glob come in the order a person numbered them: ``f2.png`` before
``f10.png`` (``ffmpeg -i v.mp4 f%d.png`` writes such names). In plain text order frame 10 came
after frame 1, and the tracker saw the scene jump back and forth."""

from __future__ import annotations

import subprocess
import sys

import cv2
import numpy as np

from vistrack.common.sources import name_order, open_files


def test_runs_of_digits_sort_by_their_value():
    names = ["f10.png", "f2.png", "f1.png", "f100.png", "f9.png"]
    assert sorted(names, key=name_order) == ["f1.png", "f2.png", "f9.png", "f10.png",
                                             "f100.png"]


def test_zero_padded_names_keep_their_text_order():
    names = [f"frame{k:04d}.png" for k in (7, 1200, 31, 0, 999)]
    assert sorted(names, key=name_order) == sorted(names)


def test_text_around_the_numbers_still_orders():
    names = ["cam1/f2.png", "cam0/f10.png", "cam1/f1.png", "a.png", "b2.png", "b10.png"]
    assert sorted(names, key=name_order) == ["a.png", "b2.png", "b10.png", "cam0/f10.png",
                                             "cam1/f1.png", "cam1/f2.png"]


def _numbered(folder, picture, count: int) -> list[np.ndarray]:
    """Frames f1.png .. f<count>.png, frame k the picture moved k px right; returns them."""
    frames = []
    for k in range(1, count + 1):
        m = np.float32([[1, 0, float(k)], [0, 1, 0]])
        frame = cv2.warpAffine(picture, m, picture.shape[::-1], borderMode=cv2.BORDER_REFLECT)
        cv2.imwrite(str(folder / f"f{k}.png"), frame)
        frames.append(frame)
    return frames


def test_a_folder_and_a_glob_of_unpadded_numbers_read_in_numbered_order(tmp_path, real_image):
    picture = np.ascontiguousarray(real_image[:120, :160])
    expected = _numbered(tmp_path, picture, 12)
    for spec in (str(tmp_path), str(tmp_path / "f*.png")):
        got = list(open_files([spec]))
        assert len(got) == 12
        for a, b in zip(got, expected, strict=True):
            np.testing.assert_array_equal(a, b)


def test_vistrack_track_sees_the_steady_motion_of_numbered_frames(tmp_path, real_image):
    """The whole offline path: 1 px a frame to the right, every frame (in text order, frame 10
    came after frame 1: a jump of 9 px, then back)."""
    _numbered(tmp_path, np.ascontiguousarray(real_image[:200, :240]), 12)
    out = subprocess.run([sys.executable, "-m", "vistrack.services.cli", "track", str(tmp_path),
                          "--format", "csv"], capture_output=True, text=True, timeout=300,
                         check=True).stdout
    rows = [line.split(",") for line in out.splitlines() if line]
    dx = [float(r[rows[0].index("dx")]) for r in rows[1:]]
    steps = np.diff(dx)
    assert len(steps) == 11
    np.testing.assert_allclose(steps, 1.0, atol=0.1)


def test_time_stamped_names_sort_by_their_time():
    """Exporters name frames ``str(stamp)``: 1700000000.25 came after 1700000000.5 when the
    fraction's digits were read as a whole number (25 > 5), and the frames played out of
    order with no warning."""
    stamps = [1700000000.0 + 0.25 * i for i in range(8)]
    names = [f"{t!r}.png" for t in stamps]
    assert sorted(reversed(names), key=name_order) == names
    # short numbers with a point are two numbers, as they always were (a regression probe:
    # read as 1.1, cam1.10 came before cam1.2)
    names = [f"cam1.{k}.png" for k in range(1, 13)]
    assert sorted(reversed(names), key=name_order) == names
