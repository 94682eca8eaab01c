"""The pre-processing filter: OpenCV's Gaussian filter, pixel for pixel, by our own kernel."""

from __future__ import annotations

import importlib

import cv2
import numpy as np
import pytest

from vistrack.common.params import TrackerParams
from vistrack.common.vision.preprocess import gaussian_filter

# the module, not the function of the same name that the package exports
preprocess_module = importlib.import_module("vistrack.common.vision.preprocess")


def opencv(frame, sigma):
    k = 2 * int(np.ceil(3 * sigma)) + 1
    return cv2.GaussianBlur(frame, (k, k), sigma, borderType=cv2.BORDER_REPLICATE)


@pytest.mark.parametrize("sigma", [TrackerParams().blur_sigma, 0.3, 0.8, 1.0, 1.5, 2.0, 3.7])
def test_the_filter_is_opencvs_gaussian_blur_pixel_for_pixel(real_image, sigma):
    """Our fixed-point kernel is used (not OpenCV behind it) and gives cv2.GaussianBlur's
    output exactly: on a real frame, random frames, saturated and 0/255 frames (the largest
    sums), and frames smaller than the kernel."""
    assert preprocess_module._fixed_kernel(sigma) is not None
    rng = np.random.default_rng(int(sigma * 10))
    y, x = np.mgrid[0:40, 0:57]
    frames = [real_image, rng.integers(0, 256, (73, 91), dtype=np.uint8),
              np.full((31, 45), 255, np.uint8), (255 * ((x + y) % 2)).astype(np.uint8),
              (255 * (x > 20)).astype(np.uint8), rng.integers(0, 256, (1, 1), dtype=np.uint8),
              rng.integers(0, 256, (3, 200), dtype=np.uint8),
              rng.integers(0, 256, (200, 2), dtype=np.uint8)]
    for frame in frames:
        np.testing.assert_array_equal(gaussian_filter(frame, sigma), opencv(frame, sigma))


def test_other_frames_and_no_blur_take_the_plain_path():
    """A frame that is not (H, W) uint8 is filtered by OpenCV; sigma 0 leaves it as it is."""
    rng = np.random.default_rng(2)
    color = rng.integers(0, 256, (20, 30, 3), dtype=np.uint8)
    np.testing.assert_array_equal(gaussian_filter(color, 0.5), opencv(color, 0.5))
    gray = rng.integers(0, 256, (20, 30), dtype=np.uint8)
    assert gaussian_filter(gray, 0.0) is gray
