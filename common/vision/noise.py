"""The camera's noise, estimated from the frames themselves.

A pixel's noise shows where the image has no structure of its own at the scale of a pixel:
Immerkaer's operator (the difference of two 3x3 Laplacians, which cancels every linear and
most smooth variation of the scene) leaves mostly noise, and the median of its magnitude over
the frame, unlike its mean, is not carried away by the edges and fine texture that also pass
it (J. Immerkaer, "Fast noise variance estimation", CVIU 64(2), 1996; the median as in
Donoho's wavelet estimate). The tracker sees the frame after its Gaussian pre-filter, which
lowers the noise and correlates it; the operator's reading of white noise through that filter
is measured once per ``blur_sigma`` (:func:`_reading`), so the estimate is in grey levels of
the camera's own frame; the rounding of the filtered frame to whole grey levels, white noise of
its own, is taken out. A stronger pre-filter than the default's (0.5 px) leaves too little of
the camera's noise above that rounding to read a noise of a grey level or two (at 1 px, 2
grey levels read as none).

On frames rendered from the shared data (their own noise ~1 grey level, bicubic), the estimate
reads 1.2 to 2.7 (fine texture passes the operator); with 3 and 6 grey levels of noise added,
3.5 to 4.5 and 6.2 to 7.2.
"""

from __future__ import annotations

import functools

import cv2
import numpy as np

#: Immerkaer's mask: two 3x3 Laplacians' difference; sum of squares 36.
_MASK = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)  # exact in int16
#: Every STRIDE-th row and column of the operator's output make the median (a quarter of the
#: pixels at 2: plenty for a median, and 4 times cheaper to sort).
STRIDE = 2
#: Larger frames are read in their middle CROP x CROP px: a camera's noise is the same all
#: over, and the estimate costs the same at any size (~0.2 ms; at 1280 x 720 the whole frame
#: took ~3 ms, which landed in the 99th percentile of a frame's latency).
CROP = 256
#: The noise, grey levels, of the frame :func:`_reading` measures the pre-filter's effect on.
READING_SIGMA = 20.0
#: The standard deviation of rounding to whole grey levels (uniform over one level).
ROUNDING = 12 ** -0.5


def _median_reading(image: np.ndarray) -> float:
    """The median magnitude of the operator over a uint8 ``image``: whole numbers, so the
    median of their histogram is interpolated within its bin (a grouped median), which a
    noise of a grey level or two would otherwise round to steps of ~0.6."""
    out = cv2.filter2D(image, cv2.CV_16S, _MASK, borderType=cv2.BORDER_ISOLATED)
    counts = np.bincount(np.abs(out[1:-1:STRIDE, 1:-1:STRIDE]).ravel())
    below = np.cumsum(counts)
    half = below[-1] / 2.0
    m = int(np.searchsorted(below, half))  # the bin that holds the median
    under = float(below[m - 1]) if m else 0.0
    return m - 0.5 + (half - under) / counts[m]


@functools.lru_cache(maxsize=8)
def _reading(blur_sigma: float) -> float:
    """What :func:`_median_reading` gives for white noise of one grey level through the
    pre-filter of ``blur_sigma``: measured on a fixed 256 x 256 frame of 20 grey levels of
    noise about mid-grey (uint8, as the pre-filter takes frames; its rounding is negligible
    at 20)."""
    from .preprocess import gaussian_filter

    noise = 128.0 + READING_SIGMA * np.random.default_rng(0).standard_normal((256, 256))
    frame = np.clip(np.rint(noise), 0, 255).astype(np.uint8)
    return _median_reading(gaussian_filter(frame, blur_sigma)) / READING_SIGMA


def noise_level(filtered: np.ndarray, blur_sigma: float) -> float:
    """The camera's noise, grey levels (a standard deviation) of its frame, estimated from an
    (H, W) frame after the pre-filter of ``blur_sigma``; 0 for a frame smaller than 3 x 3."""
    if min(filtered.shape) < 3:
        return 0.0
    h, w = filtered.shape
    if h > CROP or w > CROP:  # the middle CROP x CROP: plenty of pixels for a median
        y, x = max(0, (h - CROP) // 2), max(0, (w - CROP) // 2)
        filtered = filtered[y:y + CROP, x:x + CROP]
    # the filtered frame was rounded to whole grey levels after the filter: white noise of
    # ROUNDING grey levels, read as such (it dominates once a strong filter has averaged the
    # camera's away), taken out in quadrature
    reading = _median_reading(filtered)
    rounding = ROUNDING * _reading(0.0)
    return float(np.sqrt(max(reading * reading - rounding * rounding, 0.0))) \
        / _reading(float(blur_sigma))
