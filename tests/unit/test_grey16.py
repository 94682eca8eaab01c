"""16-bit frames (machine-vision cameras' Mono10/Mono12, 16-bit PNG and TIFF) to 8-bit grey:
scaled by the depth of the stream's samples, not by keeping the top byte, which leaves a
12-bit camera's frames at grey levels 0 to 15 (a texture floor above the noise then finds
almost nothing to track). Floating-point frames (32-bit float TIFF): 0 to 1 as OpenCV takes
them, not capped at 255, which left them black and white (no feature at all)."""

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


def test_a_flash_of_full_scale_does_not_darken_the_stream_for_good(picture):
    """A 12-bit camera's frame at full 16-bit scale (a corrupt transfer, a flash of another
    camera's frames) stepped the depth to 16 bits, and every frame after it came out at grey
    levels 0 to 15 (almost no texture above the floor), for good. The depth steps down once
    each of the last STEP_DOWN_FRAMES frames needed fewer bits, and not before."""
    from vistrack.common.vision.preprocess import STEP_DOWN_FRAMES

    grey = Grey()
    frame = picture.astype(np.uint16) << 4  # 12 bits
    np.testing.assert_array_equal(grey(frame), picture)
    grey(picture.astype(np.uint16) << 8)  # the flash: 16 bits
    assert grey.bits == 16
    for _ in range(STEP_DOWN_FRAMES - 1):  # the scale holds through a short spell
        np.testing.assert_array_equal(grey(frame), picture >> 4)
    assert grey.bits == 16
    np.testing.assert_array_equal(grey(frame), picture)  # and then steps down
    assert grey.bits == 12
    # a dark spell steps down to the most bits its frames needed
    darker = (picture // 16).astype(np.uint16) << 4  # below 256: 8 bits
    dark = (picture // 8).astype(np.uint16) << 4  # below 512: 10 bits
    assert (sample_bits(darker), sample_bits(dark)) == (8, 10)
    for k in range(STEP_DOWN_FRAMES):
        grey(dark if k == 5 else darker)
    assert grey.bits == 10


@pytest.mark.parametrize("stuck", [1, 40])
def test_hot_and_stuck_pixels_do_not_set_the_depth(picture, stuck):
    """A 12-bit camera with pixels stuck at 65535 in every frame (many sensors have a few) came
    out at grey levels 0 to 15 for good: the depth followed the brightest sample. Up to
    HOT_SHARE of a frame's pixels are now left aside, capped at 255; the rest of the frame is
    the 8-bit picture, and it is tracked as the 8-bit picture is."""
    from vistrack.common.vision import Tracker
    from vistrack.common.vision.preprocess import HOT_SHARE

    assert stuck <= picture.size * HOT_SHARE  # 48 of 48,000
    rng = np.random.default_rng(stuck)
    where = rng.choice(picture.size, stuck, replace=False)
    grey, tracker, plain = Grey(), Tracker(), Tracker()
    for k in range(3):
        shifted = np.roll(picture, 2 * k, axis=1)
        frame = shifted.astype(np.uint16) << 4
        frame.flat[where] = 65535
        out = grey(frame)
        assert grey.bits == 12
        expected = shifted.copy()
        expected.flat[where] = 255
        np.testing.assert_array_equal(out, expected)
        est, ref = tracker.process(out), plain.process(expected)
        assert est.npi == ref.npi > 50
    assert sample_bits(frame) == 16  # the brightest alone would have set 16 bits
    # a bright region larger than the share is scene, not a hot pixel: it sets the depth
    lamp = (picture.astype(np.uint16) << 4)
    lamp[:20, :20] = 60000  # 400 pixels
    assert Grey()(lamp)[100, 100] == picture[100, 100] >> 4


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


def _write_sequence(folder, picture, bits: int | str | None) -> list[str]:
    """Six shifted frames of ``picture``: 8-bit PNGs (``bits`` None), ``bits``-bit samples in
    16-bit PNGs, or (``"float"``) 32-bit float TIFFs of 0 to 1."""
    paths = []
    for k in range(6):
        m = np.float32([[1, 0, 2.0 * k], [0, 1, 1.0 * k]])
        frame = cv2.warpAffine(picture, m, picture.shape[::-1], borderMode=cv2.BORDER_REFLECT)
        if bits == "float":
            path = str(folder / f"f{k:02d}.tiff")
            cv2.imwrite(path, frame.astype(np.float32) / 255)
        else:
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


def test_a_folder_of_float_tiffs_of_0_to_1_reads_as_its_8_bit_version(tmp_path, picture):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    eight = _write_sequence(tmp_path / "a", picture, None)
    floats = _write_sequence(tmp_path / "b", picture, "float")
    assert cv2.imread(floats[0], cv2.IMREAD_UNCHANGED).dtype == np.float32
    for a, b in zip(FileFrames(eight), FileFrames(floats), strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(read_image(floats[0]), read_image(eight[0]))


def test_float_frames_of_0_to_255_pass_as_their_values_rounded():
    a = np.array([[0.0, 2.4, 2.6, 254.5, 300.0]], np.float32)
    assert to_gray(a).tolist() == [[0, 2, 3, 254, 255]]  # rint: 254.5 to the even 254
    assert Grey()(a).tolist() == [[0, 2, 3, 254, 255]]


def test_float_frames_without_a_number_or_out_of_range_give_finite_grey():
    a = np.array([[np.nan, np.inf, -np.inf, -0.5, 0.5, 1.0]], np.float32)
    assert to_gray(a).tolist() == [[0, 255, 0, 0, 128, 255]]
    assert to_gray(np.full((4, 4), np.nan, np.float32)).tolist() == [[0] * 4] * 4


def test_float_colour_and_other_depths_are_converted_to_grey_first(picture):
    bgr = np.dstack([picture, picture, picture])
    np.testing.assert_array_equal(to_gray(bgr.astype(np.float64) / 255), picture)
    np.testing.assert_array_equal(to_gray(bgr.astype(np.float16)), picture)
    np.testing.assert_array_equal(to_gray(bgr.astype(np.int32)), picture)
    assert to_gray(np.array([[-7, 9, 70000]], np.int32)).tolist() == [[0, 9, 255]]


def test_the_float_range_holds_so_a_0_to_255_stream_is_read_as_such(picture):
    from vistrack.common.vision.preprocess import STEP_DOWN_FRAMES

    grey = Grey()
    unit = picture.astype(np.float32) / 255
    np.testing.assert_array_equal(grey(unit), picture)
    assert grey.unit is True
    np.testing.assert_array_equal(grey(picture.astype(np.float32)), picture)  # above 1
    assert grey.unit is False
    dark = np.full(picture.shape, 0.8, np.float32)  # would read as 204 in 0..1
    for _ in range(STEP_DOWN_FRAMES - 1):
        assert grey(dark).max() == 1  # 0..255 through a spell: no flicker to bright
    assert grey.unit is False
    np.testing.assert_array_equal(grey(picture.astype(np.float32)), picture)  # not counted
    for _ in range(STEP_DOWN_FRAMES - 1):
        grey(unit)
    assert grey.unit is False
    np.testing.assert_array_equal(grey(unit), picture)  # and then back to 0 to 1
    assert grey.unit is True


def test_hdr_float_frames_with_highlights_are_not_black(picture):
    """A high-dynamic-range float frame (0 to 1, highlights above: a lamp, the sky) was read as
    0 to 255 wherever one value was above 1: grey levels 0 and 1, no feature. Highlights are
    capped at 255 and the rest is the 8-bit picture, alone and in a stream."""
    from vistrack.common.vision import Tracker

    hdr = picture.astype(np.float32) / 255
    lit = picture > 200  # the brightest tenth or so of the picture, 4 to 16 times over
    assert 0.01 < lit.mean() < 0.5
    hdr[lit] *= np.linspace(4.0, 16.0, int(lit.sum()), dtype=np.float32)
    expected = np.where(lit, 255, picture).astype(np.uint8)
    np.testing.assert_array_equal(to_gray(hdr), expected)
    grey = Grey()
    np.testing.assert_array_equal(grey(hdr), expected)
    assert grey.unit is True
    assert Tracker().process(grey(hdr)).npi > 50


def test_a_boolean_mask_is_black_and_white_and_tracked(picture):
    """A bool frame (a mask a user's code made) read as grey levels 0 and 1: no texture above
    the floor, no feature (a fuzzer's note). It is black and white, and has features."""
    from vistrack.common.vision import Tracker

    mask = picture > 128
    assert to_gray(mask).tolist()[:1] == [[255 if v else 0 for v in mask[0]]]
    assert to_gray(np.dstack([mask, mask, mask])).max() == 255
    assert Tracker().process(to_gray(mask)).npi > 10


def test_a_dtype_that_is_not_a_number_is_a_clear_error():
    with pytest.raises(ValueError, match=r"dtype <U1 is not a grey or colour image"):
        to_gray(np.array([["a"]]))


@pytest.mark.parametrize("kind", [12, "float"])
def test_vistrack_track_on_12_bit_and_float_frames_prints_what_it_prints_for_8_bit(
        tmp_path, picture, kind):
    """The whole offline path, the CLI as a user runs it: the same rows (but for the times)."""
    rows = {}
    for name, bits in (("eight", None), ("other", kind)):
        (tmp_path / name).mkdir()
        _write_sequence(tmp_path / name, picture, bits)
        out = subprocess.run([sys.executable, "-m", "vistrack.services.cli", "track",
                              str(tmp_path / name), "--format", "csv"],
                             capture_output=True, text=True, timeout=300, check=True).stdout
        lines = [line.split(",") for line in out.splitlines() if line]
        t_ms = lines[0].index("t_ms")
        rows[name] = [row[:t_ms] + row[t_ms + 1:] for row in lines]
    assert rows["other"] == rows["eight"]
    assert min(int(r[1]) for r in rows["eight"][1:]) >= 50  # NPI: a textured picture
