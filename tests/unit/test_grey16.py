"""16-bit frames (machine-vision cameras' Mono10/Mono12, 16-bit PNG and TIFF) to 8-bit grey:
scaled by the depth of the stream's samples, not by keeping the top byte, which leaves a
12-bit camera's frames at grey levels 0 to 15 (a texture floor above the noise then finds
almost nothing to track)."""

from __future__ import annotations

import subprocess
import sys

import cv2
import numpy as np
import pytest

from vistrack.common.sources import FileFrames, read_image
from vistrack.common.vision.preprocess import Grey, sample_bits, to_gray


@pytest.fixture(scope="module")
def picture(real_image) -> np.ndarray:
    """A real 8-bit grey picture (RubberWhale, 200x240), or skip."""
    return np.ascontiguousarray(real_image[:200, :240])


def test_sample_bits_rounds_up_to_a_sensor_depth():
    assert [sample_bits(np.array([[v]], np.uint16)) for v in
            (0, 255, 256, 1023, 1024, 4095, 4096, 16383, 16384, 65535)] == \
        [8, 8, 10, 10, 12, 12, 14, 14, 16, 16]


def test_to_gray_scales_by_the_bits_given_and_caps_at_255():
    a = np.array([[0, 16, 4080, 4095, 5000]], np.uint16)
    assert to_gray(a, bits=12).tolist() == [[0, 1, 255, 255, 255]]
    assert to_gray(a).tolist() == [[0, 0, 15, 15, 19]]  # the top byte, as before
    with pytest.raises(ValueError, match=r"bits=7 is out of range: allowed 8\.\.16"):
        to_gray(a, bits=7)
    with pytest.raises(ValueError, match=r"bits=17 is out of range: allowed 8\.\.16"):
        Grey(17)


@pytest.mark.parametrize("bits", [10, 12, 14])
def test_a_stream_of_n_bit_samples_comes_back_as_the_8_bit_picture(picture, bits):
    grey = Grey()
    for k in range(3):
        shifted = np.roll(picture, k, axis=1)
        out = grey(shifted.astype(np.uint16) << (bits - 8))
        np.testing.assert_array_equal(out, shifted)
    assert grey.bits == bits


def test_full_range_16_bit_keeps_the_top_byte(picture):
    wide = picture.astype(np.uint16) * 257  # 0..65535
    np.testing.assert_array_equal(Grey()(wide), picture)


def test_the_depth_only_grows_so_a_dark_start_steps_once(picture):
    grey = Grey()
    dark = (picture // 8).astype(np.uint16) << 4  # a 12-bit camera, dark scene: max < 512
    assert sample_bits(dark) == 10
    first = grey(dark)
    assert grey.bits == 10
    np.testing.assert_array_equal(first, (picture // 8) << 2)
    grey(picture.astype(np.uint16) << 4)  # the light comes on
    assert grey.bits == 12
    again = grey(dark)  # and goes off: the same scale as the bright frame, no flicker
    np.testing.assert_array_equal(again, picture // 8)
    assert grey.bits == 12


def test_signed_16_bit_samples_below_zero_are_black_not_white():
    a = np.array([[-300, -1, 0, 4095]], np.int16)
    assert Grey()(a).tolist() == [[0, 0, 0, 255]]
    assert to_gray(a).tolist() == [[0, 0, 0, 15]]


def test_colour_16_bit_is_converted_to_grey_first(picture):
    bgr = np.dstack([picture, picture, picture]).astype(np.uint16) << 4
    np.testing.assert_array_equal(Grey()(bgr), picture)


def test_8_bit_frames_pass_as_they_are(picture):
    grey = Grey()
    assert grey(picture) is not None and grey.bits == 0
    np.testing.assert_array_equal(grey(picture), picture)


def _write_sequence(folder, picture, bits: int | None) -> list[str]:
    paths = []
    for k in range(6):
        m = np.float32([[1, 0, 2.0 * k], [0, 1, 1.0 * k]])
        frame = cv2.warpAffine(picture, m, picture.shape[::-1], borderMode=cv2.BORDER_REFLECT)
        path = str(folder / f"f{k:02d}.png")
        cv2.imwrite(path, frame if bits is None else frame.astype(np.uint16) << (bits - 8))
        paths.append(path)
    return paths


def test_a_folder_of_12_bit_pngs_reads_as_its_8_bit_version(tmp_path, picture):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    eight = _write_sequence(tmp_path / "a", picture, None)
    twelve = _write_sequence(tmp_path / "b", picture, 12)
    assert cv2.imread(twelve[0], cv2.IMREAD_UNCHANGED).dtype == np.uint16
    for a, b in zip(FileFrames(eight), FileFrames(twelve), strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(read_image(twelve[0]), read_image(eight[0]))


def test_vistrack_track_on_12_bit_pngs_prints_what_it_prints_for_8_bit(tmp_path, picture):
    """The whole offline path, the CLI as a user runs it: the same rows (but for the times)."""
    rows = {}
    for name, bits in (("eight", None), ("twelve", 12)):
        (tmp_path / name).mkdir()
        _write_sequence(tmp_path / name, picture, bits)
        out = subprocess.run([sys.executable, "-m", "vistrack.services.cli", "track",
                              str(tmp_path / name), "--format", "csv"],
                             capture_output=True, text=True, timeout=300, check=True).stdout
        lines = [line.split(",") for line in out.splitlines() if line]
        t_ms = lines[0].index("t_ms")
        rows[name] = [row[:t_ms] + row[t_ms + 1:] for row in lines]
    assert rows["twelve"] == rows["eight"]
    assert min(int(r[1]) for r in rows["eight"][1:]) >= 50  # NPI: a textured picture
