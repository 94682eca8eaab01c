"""Pre-processing: filtering, gradient estimation and thresholding (Section 3 of the paper).

The paper's pre-processing block filters the image, estimates its gradient and thresholds it so
that only the strongest-gradient pixels become feature candidates. Our reading: a Gaussian
filter, a gradient strength per pixel, and THRES_PERCENT = the percentage of the image's pixels,
strongest first, kept as candidates.

Two strengths (``TrackerParams.strength``):

* ``gradient``: the Sobel gradient magnitude, the paper's literal measure. It ranks points on
  straight edges highest, where the SSD minimum slides along the edge (the aperture problem);
* ``min_eigen`` (default): the smaller eigenvalue of the local gradient structure tensor,
  strong only where the gradient is strong in two directions. On the Middlebury sequences it cut
  the tracker's median end-point error 1.3 to 5x (RubberWhale 0.22 -> 0.04 px), to the level of
  OpenCV's pyramidal Lucas-Kanade on the same points.
"""

from __future__ import annotations

import functools
import logging
import math
from dataclasses import dataclass

import cv2
import numba as nb
import numpy as np
from numba.cpython.unsafe.numbers import trailing_zeros

from ..params import TrackerParams
from .noise import noise_level
from .ssd import NO_NRT

log = logging.getLogger("vistrack.frames")


@dataclass(frozen=True)
class Preprocessed:
    """One pre-processed frame.

    Attributes
    ----------
    filtered : (H, W) uint8, the Gaussian-filtered frame the tracker correlates on.
    candidates : (N, 2) int16, x, y of the candidate pixels, strongest gradient first.
    strength : (N,) float32, gradient magnitude of each candidate (grey levels per px).
    """

    filtered: np.ndarray
    candidates: np.ndarray
    strength: np.ndarray


#: Bit depths of sensors' samples in 16-bit containers (Mono10, Mono12, Mono14 and 16-bit),
#: after 8: what :func:`sample_bits` rounds a frame's brightest value up to.
SENSOR_BITS = (8, 10, 12, 14, 16)

#: The share of a frame's pixels that may lie above the depth :class:`Grey` scales it by (a
#: sensor's hot or stuck pixels, a glint; capped at 255): a 12-bit camera with a few pixels
#: stuck at 65535, as many sensors have, otherwise came out at grey levels 0 to 15, for good
#: (1280x720: 921 pixels; 256x256: 65)
HOT_SHARE = 1e-3


def sample_bits(image: np.ndarray, spare: int = 0) -> int:
    """The sensor depth a 16-bit grey frame's samples need: the least of :data:`SENSOR_BITS`
    that holds its brightest value (a 12-bit camera's frame, values 0 to 4095, needs 12), or,
    with ``spare`` > 0, every value but at most ``spare`` of the brightest (hot pixels)."""
    top = int(image.max(initial=0))
    bits = next(b for b in SENSOR_BITS if top < 1 << b)
    if spare > 0:
        # down from the brightest's depth while no more than ``spare`` values lie above the
        # next depth down (one count a frame where the brightest fits: 0.07 ms at 1280x720)
        while bits > SENSOR_BITS[0]:
            lower = SENSOR_BITS[SENSOR_BITS.index(bits) - 1]
            if np.count_nonzero(image >= 1 << lower) > spare:
                break
            bits = lower
    return bits


def to_gray(image: np.ndarray, *, bits: int = 16, unit: bool | None = None) -> np.ndarray:
    """8-bit grey from a grey, BGR or BGRA image (as the camera service converts frames).

    A 16-bit image's samples hold ``bits`` significant bits (8..16, the lowest ones: a
    12-bit sensor's values run 0 to 4095 in a 16-bit container): grey = value >> (bits - 8),
    capped at 255. The default, 16, keeps the top byte; for the samples of a stream
    :class:`Grey` finds the depth.

    A floating-point image (a 32-bit float TIFF, a frame a user's own code made) is 0 to 1
    when ``unit`` (OpenCV's convention for float images: grey = 255 value), else 0 to 255;
    ``None`` takes it as 0 to 1 when none of its values is above 1 (:func:`unit_range`).
    Rounded to the nearest level and capped to 0..255; NaN is black. Other integer images
    (8-bit signed, 32-bit) are capped to 0..255. A boolean image (a mask) is black and white:
    False 0, True 255 (it read as grey levels 0 and 1, a frame without texture)."""
    gray = _one_channel(image)
    if gray.dtype != np.uint8:
        if np.issubdtype(gray.dtype, np.integer) and gray.dtype.itemsize == 2:
            if not 8 <= bits <= 16:
                raise ValueError(f"bits={bits} is out of range: allowed 8..16")
            gray = np.clip(gray >> (bits - 8), 0, 255).astype(np.uint8)  # int16: no wrap
        elif np.issubdtype(gray.dtype, np.floating):
            if unit is None:
                unit = unit_range(gray)
            scaled = gray * np.float32(255.0) if unit else gray
            # NaN compares false both ways: the clip leaves it, nan_to_num makes it black
            gray = np.nan_to_num(np.rint(np.clip(scaled, 0, 255)), nan=0.0).astype(np.uint8)
        elif gray.dtype == np.bool_:
            gray = gray.astype(np.uint8) * np.uint8(255)
        elif np.issubdtype(gray.dtype, np.integer):
            gray = np.clip(gray, 0, 255).astype(np.uint8)
        else:
            raise ValueError(f"image of dtype {gray.dtype} is not a grey or colour image: "
                             "allowed 8- or 16-bit integers, other integers or floats")
    return np.ascontiguousarray(gray)


def unit_range(gray: np.ndarray) -> bool:
    """Whether a floating-point frame reads as 0 to 1 (OpenCV's convention for float images):
    at most half its pixels are above 1. A high-dynamic-range frame of 0 to 1 has highlights
    above 1 (a lamp, the sky: capped at 255), and one of 0 to 255 has most of its pixels above
    1 unless it is all but black. Taken as 0 to 255 wherever any value was above 1, an HDR
    frame with one highlight came out black (grey levels 0 and 1: no feature)."""
    return bool(2 * np.count_nonzero(gray > 1.0) <= gray.size)


#: :class:`Grey` steps its depth down after this many frames in a row that needed fewer bits
#: (2 s at 30 fps: a flash, a glitch, a moment of darkness does not change the scale)
STEP_DOWN_FRAMES = 60


class Grey:
    """:func:`to_gray` for the frames of one stream (a camera, a video, a folder of images).

    16-bit frames are scaled by the depth of the stream's samples: the largest
    :func:`sample_bits` of its frames so far (``bits`` gives it instead), each frame's brightest
    :data:`HOT_SHARE` of its pixels aside (hot and stuck pixels, capped at 255). Keeping the
    top byte of a 12-bit camera's samples, as OpenCV converts 16-bit images to 8-bit, left grey
    levels 0 to 15: a real 12-bit sequence gave 4 features where its 8-bit version gave 100.
    The depth grows at once, so a stream that starts dark steps once, when its first bright
    frame comes, rather than changing scale with every frame; it steps down only when each of
    the last :data:`STEP_DOWN_FRAMES` frames needed fewer bits, to the most they needed (a
    flash, a glitch, a moment of darkness does not change the scale; a dark spell of a few
    seconds brings out what texture it has). 8-bit frames pass as they are.

    Floating-point frames are 0 to 1 (OpenCV's convention for float images) while most of
    their pixels are at most 1 (:func:`unit_range`: an HDR frame's highlights are capped at
    255), and 0 to 255 from the first frame that reads so, until each of the last
    :data:`STEP_DOWN_FRAMES` frames read as 0 to 1 again: like the depth, the range holds
    through a short spell (capping 0..1 frames at 255 made them black and white: no feature
    at all; reading them as 0 to 255, black).
    """

    def __init__(self, bits: int | None = None) -> None:
        if bits is not None and not 8 <= bits <= 16:
            raise ValueError(f"bits={bits} is out of range: allowed 8..16")
        self.fixed = bits
        self.bits = 0  # the depth in use (0: no 16-bit frame yet)
        self._below = 0  # frames in a row that needed fewer bits than in use
        self._below_bits = 0  # the most of them needed
        self.unit: bool | None = None  # float frames: 0 to 1 (None: no float frame yet)
        self._unit_run = 0  # float frames in a row that read as 0 to 1 while 0 to 255 in use

    def __call__(self, image: np.ndarray) -> np.ndarray:
        if np.issubdtype(image.dtype, np.floating):
            return self._float(image)
        if image.dtype.itemsize != 2 or not np.issubdtype(image.dtype, np.integer):
            return to_gray(image)
        grey16 = _one_channel(image)
        bits = self.fixed or self._depth(sample_bits(grey16, int(grey16.size * HOT_SHARE)))
        if bits != self.bits:
            log.info("16-bit frames with %d significant bits: grey = value >> %d", bits,
                     bits - 8)
            self.bits = bits
        return to_gray(grey16, bits=bits)

    def _depth(self, needed: int) -> int:
        """The depth to scale a frame by, given the bits it ``needed``: more at once, fewer
        once :data:`STEP_DOWN_FRAMES` frames in a row needed fewer."""
        if needed >= self.bits:
            self._below = 0
            return needed
        self._below_bits = needed if self._below == 0 else max(self._below_bits, needed)
        self._below += 1
        if self._below < STEP_DOWN_FRAMES:
            return self.bits
        self._below = 0
        return self._below_bits

    def _float(self, image: np.ndarray) -> np.ndarray:
        grey = _one_channel(image)
        unit = unit_range(grey)
        if unit and self.unit is False:  # 0 to 255 in use: back to 0 to 1 after a spell
            self._unit_run += 1
            unit = self._unit_run >= STEP_DOWN_FRAMES
        else:
            self._unit_run = 0
        if unit != self.unit:
            self._unit_run = 0
            log.info("floating-point frames taken as %s", "0 to 1: grey = 255 value" if unit
                     else "0 to 255")
            self.unit = unit
        return to_gray(grey, unit=unit)


def _one_channel(image: np.ndarray) -> np.ndarray:
    """The grey of a grey, BGR or BGRA image, of the image's own depth (OpenCV's luma
    weights)."""
    if image.ndim == 2:
        return image
    if image.dtype not in (np.uint8, np.uint16, np.float32):  # what cvtColor takes
        image = image.astype(np.float32)
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
    if image.ndim == 3 and image.shape[2] == 1:
        return image[:, :, 0]
    raise ValueError(f"image of shape {image.shape} is not grey, BGR or BGRA")


def gaussian_filter(gray: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian low-pass filter; ``sigma`` in px, 0 returns the frame unchanged.

    ``cv2.GaussianBlur`` (a (k, k) kernel, k = 2 ceil(3 sigma) + 1, edges replicated), pixel for
    pixel: for an (H, W) uint8 frame by :func:`_blur_fixed`, OpenCV's own fixed-point
    arithmetic in one kernel (2 to 4x faster on 256x256 frames: the filter was a tenth of a
    frame's work), wherever :func:`_fixed_kernel` finds it equal to OpenCV's; else by OpenCV.
    """
    if sigma <= 0:
        return gray
    if gray.ndim == 2 and gray.dtype == np.uint8:
        taps = _fixed_kernel(float(sigma))
        if taps is not None:
            out = np.empty(gray.shape, np.uint8)
            # always a read-only view: one compiled version for the frames a service decodes
            # (read-only views of the payload, passed as they are: each call less on a
            # service's frame path is ~10 to 30 us at 30 fps, from cold caches) and those
            # made here, so that the warm-up compiles the one a service runs (a writable
            # frame in the warm-up and a read-only one in preprocessing's first frame
            # compiled anew there: ~2 s without estimates at the start of a first run)
            flags = gray.flags
            src = gray
            if flags.writeable or not flags.c_contiguous:
                src = np.ascontiguousarray(gray).view()
                src.flags.writeable = False
            _blur_fixed(src, taps, out)
            return out
    k = 2 * math.ceil(3 * sigma) + 1
    return cv2.GaussianBlur(gray, (k, k), sigma, borderType=cv2.BORDER_REPLICATE)


#: How far a pixel must stand out of all 8 of its neighbours, above their brightest or below
#: their darkest, in grey levels, to be taken for a sensor's defect (a hot, stuck or dead
#: pixel) and set to that brightest or darkest (:func:`fix_defects`). A camera's optics spread
#: a point of light over more than one pixel, so no scene gives such a spike; noise of
#: sigma 10 does once in ~10^7 pixels.
DEFECT_LEVEL = 40


def fix_defects(gray: np.ndarray) -> np.ndarray:
    """``gray`` (H, W) uint8 with each isolated spike (a pixel more than :data:`DEFECT_LEVEL`
    above the brightest of its 8 neighbours, or below the darkest) set to that brightest or
    darkest, as a camera's defect-pixel correction does; ``gray`` itself where there is none.

    A hot pixel is the strongest corner a frame has (min_eigen ranks a lone spike first) and
    matches itself perfectly where it stands: on Urban2's real frames moving up to 2 px a
    frame, 66 hot pixels (0.1 %) took 63 of the first 100 features and the view's motion
    read (53.0, 16.4) px for (69.0, 20.7), 300 of them 99 % of the pairs off by more than 2 px
    (a hunt of sensor effects, 2026-12-07). Only a spike is touched: a corner or a line one
    pixel wide has a neighbour as bright as itself."""
    h, w = gray.shape
    if h < 3 or w < 3:
        return gray
    src = gray
    if gray.flags.writeable or not gray.flags.c_contiguous:
        src = np.ascontiguousarray(gray).view()  # one compiled version (gaussian_filter's)
        src.flags.writeable = False
    found = np.empty((max(16, h * w // 16), 3), np.int32)
    n = _spikes(src, DEFECT_LEVEL, found)
    if n == 0:
        return gray
    out = np.array(gray, np.uint8, order="C")
    out[found[:n, 0], found[:n, 1]] = found[:n, 2]
    return out


@nb.njit(cache=True, nogil=True)
def _spikes(src, level, found):  # pragma: no cover - numba
    """The spikes of ``src`` (:func:`fix_defects`), as rows of ``found``: y, x and the value to
    set; returns how many (at most ``found``'s rows). First one branch-free pass a row in
    uint8 lanes: does a pixel stand out of its 4 nearest (left, right, above, below) by more
    than ``level``? Almost nowhere (a line one pixel wide has neighbours along it as bright);
    only in such a row are a pixel's 8 compared, where its 4 are."""
    h, w = src.shape
    cap = found.shape[0]
    out = np.empty(w, np.uint8)  # by how much each pixel of a row stands out of its 4
    n = 0
    for y in range(h):
        row = src[y]
        up = src[max(y - 1, 0)] if y > 0 else src[min(1, h - 1)]
        down = src[min(y + 1, h - 1)] if y < h - 1 else src[max(h - 2, 0)]
        for x in range(1, w - 1):
            p = row[x]
            hi = max(max(row[x - 1], row[x + 1]), max(up[x], down[x]))
            lo = min(min(row[x - 1], row[x + 1]), min(up[x], down[x]))
            out[x] = max(np.uint8(p - min(p, hi)), np.uint8(lo - min(lo, p)))
        for x in (0, w - 1):  # the ends: one neighbour in the row
            p = row[x]
            q = row[1] if x == 0 else row[w - 2]
            hi = max(q, max(up[x], down[x]))
            lo = min(q, min(up[x], down[x]))
            out[x] = max(np.uint8(p - min(p, hi)), np.uint8(lo - min(lo, p)))
        most = np.uint8(0)
        for x in range(w):
            most = max(most, out[x])
        if most <= level:
            continue
        for x in range(w):
            if out[x] <= level:
                continue  # not out of its 4 nearest: no spike
            p = np.int16(row[x])
            hi = np.int16(-1)
            lo = np.int16(256)
            for yy in range(max(y - 1, 0), min(y + 2, h)):
                for xx in range(max(x - 1, 0), min(x + 2, w)):
                    if yy != y or xx != x:
                        v = np.int16(src[yy, xx])
                        hi = max(hi, v)
                        lo = min(lo, v)
            if n < cap and (p - hi > level or lo - p > level):
                found[n, 0] = y
                found[n, 1] = x
                found[n, 2] = hi if p - hi > level else lo
                n += 1
    return n


#: fraction bits of OpenCV's fixed-point kernel for 8-bit Gaussian filters (its ufixedpoint16)
_FIXED_BITS = 8


@functools.lru_cache(maxsize=16)
def _fixed_kernel(sigma: float) -> np.ndarray | None:
    """The integer taps (summing to 2^8) with which OpenCV filters 8-bit frames for ``sigma``
    (its ``getGaussianKernelFixedPoint_ED``: the Gaussian's samples, normalised, each rounded
    with the error carried on to the next, the centre taking what is left), or None where
    :func:`_blur_fixed` with them does not give ``cv2.GaussianBlur``'s output on a random
    probe frame (an OpenCV computing its kernel otherwise): OpenCV then filters."""
    k = 2 * int(np.ceil(3 * sigma)) + 1
    half = k // 2
    x = np.arange(k, dtype=np.float64) - half
    g = np.exp(x * x * (-0.5 / (sigma * sigma)))
    g /= g.sum()
    one = 1 << _FIXED_BITS
    taps = np.empty(k, np.int64)
    err = 0.0
    for i in range(half):
        v = g[i] * one + err
        r = int(np.rint(v))
        err = v - r
        taps[i] = taps[k - 1 - i] = r
    taps[half] = one - 2 * int(taps[:half].sum())
    if taps.min() < 0:
        return None
    probe = np.random.default_rng(15).integers(0, 256, (23, 2 * k + 17), dtype=np.uint8)
    probe[:, :3] = 255  # the largest sums
    probe.flags.writeable = False  # as gaussian_filter passes frames: one compiled version
    ours = np.empty(probe.shape, np.uint8)
    _blur_fixed(probe, taps, ours)
    theirs = cv2.GaussianBlur(probe, (k, k), sigma, borderType=cv2.BORDER_REPLICATE)
    return taps if np.array_equal(ours, theirs) else None


@nb.njit(cache=True, nogil=True)
def _blur_fixed(src, taps, out):  # pragma: no cover - numba
    """``src`` (H, W) uint8 filtered by the symmetric integer kernel ``taps`` (k, summing to
    2^8) along rows, then along columns, edges replicated, into ``out``: OpenCV's fixed-point
    8-bit Gaussian filter. A row's sums are exact in uint16 (at most 2^8 * 255), a column's in
    uint32 (at most 2^16 * 255), rounded at the end: ``(sum + 2^15) >> 16``. Each pass is one
    long loop per tap, in 16 lanes (rows) or 8 (columns) a vector; zero taps are skipped (for
    sigma 0.5, 3 of 5 count)."""
    h, w = src.shape
    k = taps.shape[0]
    half = k // 2
    u16 = np.uint16
    u32 = np.uint32
    rows = np.empty((h, w), np.uint16)
    line = np.empty(w + 2 * half, np.uint8)
    for y in range(h):
        row = src[y]
        for x in range(w):
            line[half + x] = row[x]
        for x in range(half):
            line[x] = row[0]
            line[half + w + x] = row[w - 1]
        acc = rows[y]
        c = u16(taps[half])
        mid = line[half:half + w]
        for x in range(w):
            acc[x] = u16(c * mid[x])
        for d in range(1, half + 1):
            c = u16(taps[half - d])
            if c == 0:
                continue
            lo = line[half - d:half - d + w]
            hi = line[half + d:half + d + w]
            for x in range(w):
                acc[x] = u16(acc[x] + c * u16(u16(lo[x]) + u16(hi[x])))
    # columns: the pairs of taps first, the centre added with the rounding: (sum + 2^15) >> 16
    col = np.empty(w, np.uint32)
    for y in range(h):
        first = True
        for d in range(1, half + 1):
            c = u32(taps[half - d])
            if c == 0:
                continue
            lo = rows[max(y - d, 0)]
            hi = rows[min(y + d, h - 1)]
            if first:
                for x in range(w):
                    col[x] = u32(c * u32(u32(lo[x]) + u32(hi[x])))
                first = False
            else:
                for x in range(w):
                    col[x] = u32(col[x] + c * u32(u32(lo[x]) + u32(hi[x])))
        if first:
            col[:] = 0
        c = u32(taps[half])
        mid = rows[y]
        dst = out[y]
        for x in range(w):
            dst[x] = u32(col[x] + c * u32(mid[x]) + u32(32768)) >> 16


def _sobel(filtered: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    gx = cv2.Sobel(filtered, cv2.CV_32F, 1, 0, ksize=3, borderType=cv2.BORDER_REPLICATE)
    gy = cv2.Sobel(filtered, cv2.CV_32F, 0, 1, ksize=3, borderType=cv2.BORDER_REPLICATE)
    return gx, gy


def gradient_magnitude(filtered: np.ndarray) -> np.ndarray:
    """Sobel gradient magnitude, (H, W) float32 (3x3 Sobel, so up to ~1443 grey levels/px)."""
    return magnitude(*_sobel(filtered))


def magnitude(gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    """sqrt(gx^2 + gy^2) of float32 arrays, each step rounded to float32: the same bits
    wherever the arrays lie in memory. ``cv2.magnitude`` gave a few values a last bit apart
    when the arrays moved by a few bytes (its vector loop and its scalar tail round
    differently), and numpy places the Sobel's outputs wherever its allocator does: the same
    frame's strengths changed from run to run (43 of 324 frame and parameter cases of the
    shared data, run twice), and with them the order of tied candidates. ~0.4 ms at 1280x720
    against 0.14, for ``strength="gradient"`` only."""
    out = gx * gx
    out += gy * gy
    return np.sqrt(out, out=out)


@nb.njit(cache=True, nogil=True)
def _min_eigen(img, out):  # pragma: no cover - numba
    """:func:`_min_eigen_rows` with its scratch: its loops run without numba's runtime,
    whose row views took atomic reference counts, ~20 a row (256 x 256: 60.8 -> 47.8 us)."""
    w = img.shape[1]
    _min_eigen_rows(img, out, np.empty(w + 2, np.int32), np.empty(w + 2, np.int32),
                    np.zeros((3, 3, w + 2), np.int32), np.empty((3, w + 2), np.int32))


@nb.njit(**NO_NRT)
def _min_eigen_rows(img, out, vs, vd, prod, col):  # pragma: no cover - numba
    """Smaller eigenvalue of the 3x3 structure tensor of the 3x3 Sobel gradient of ``img``
    (uint8), into ``out`` (float32, border ring 0).

    Bit for bit the values of the former float32 pipeline (``cv2.Sobel`` to float32, products
    and 3x3 sums in float32, the eigenvalue in float64): the gradient and the tensor sums are
    integers below 2^24, so they are computed exactly in int32 here and converted where that
    pipeline first rounded (the sum sxx + syy, which may exceed 2^24, and sxy * sxy in
    float32). One pass down the rows with a ring of 3 rows of gradient products, every loop a
    long contiguous one that vectorises. At 1280 x 720 it takes ~1.3 ms, as long without the
    float64 square root (1.36 against 1.28 ms, the square root replaced by its argument in a
    copy): the passes over the rows bound it, not the square root.

    Scratch (from :func:`_min_eigen`): ``vs`` and ``vd`` (w + 2,) int32, the vertical
    [1 2 1] and [-1 0 1] of a row, border-replicated; ``prod`` (3, 3, w + 2) int32 zeros, a
    ring of 3 rows of gx^2, gx gy, gy^2 at 1..w (0 in the pad columns); ``col`` (3, w + 2)
    int32, their sums over 3 rows.
    """
    h, w = img.shape
    if h < 3 or w < 3:
        out[:, :] = 0
        return
    out[0, :] = 0  # the other rows are written whole below
    out[h - 1, :] = 0
    for r in range(h + 1):
        if r < h:
            # gradient products of row r into ring slot r % 3 (Sobel, border replicated)
            up = img[max(r - 1, 0)]
            mid = img[r]
            dn = img[min(r + 1, h - 1)]
            vsm = vs[1:w + 1]
            vdm = vd[1:w + 1]
            for x in range(w):
                a = np.int32(up[x])
                b = np.int32(mid[x])
                c = np.int32(dn[x])
                vsm[x] = a + 2 * b + c
                vdm[x] = c - a
            vs[0] = vs[1]
            vs[w + 1] = vs[w]
            vd[0] = vd[1]
            vd[w + 1] = vd[w]
            pxx = prod[r % 3, 0, 1:w + 1]
            pxy = prod[r % 3, 1, 1:w + 1]
            pyy = prod[r % 3, 2, 1:w + 1]
            s_left = vs[0:w]
            s_right = vs[2:w + 2]
            d_left = vd[0:w]
            d_mid = vd[1:w + 1]
            d_right = vd[2:w + 2]
            for x in range(w):
                gx = np.int32(s_right[x] - s_left[x])
                gy = np.int32(d_left[x] + 2 * d_mid[x] + d_right[x])
                pxx[x] = np.int32(gx * gx)
                pxy[x] = np.int32(gx * gy)
                pyy[x] = np.int32(gy * gy)
        y = r - 1  # the output row whose 3 product rows are now complete
        if y < 1 or y > h - 2:
            continue
        # sums of the products over the 3 rows, then over 3 columns with the eigenvalue, over
        # the whole row (border pixels included and zeroed after): loops of exactly w leave no
        # scalar remainder
        for c in range(3):
            p0 = prod[(y - 1) % 3, c]
            p1 = prod[y % 3, c]
            p2 = prod[(y + 1) % 3, c]
            dst = col[c]
            for x in range(w + 2):
                dst[x] = np.int32(p0[x] + p1[x] + p2[x])
        xx0 = col[0, 0:w]
        xx1 = col[0, 1:w + 1]
        xx2 = col[0, 2:w + 2]
        xy0 = col[1, 0:w]
        xy1 = col[1, 1:w + 1]
        xy2 = col[1, 2:w + 2]
        yy0 = col[2, 0:w]
        yy1 = col[2, 1:w + 1]
        yy2 = col[2, 2:w + 2]
        dst = out[y]
        for x in range(w):
            # np.int32: the sums fit (< 2^25), and LLVM then converts 16 lanes at a time
            sxx = np.int32(xx0[x] + xx1[x] + xx2[x])
            sxy = np.float32(np.int32(xy0[x] + xy1[x] + xy2[x]))
            syy = np.int32(yy0[x] + yy1[x] + yy2[x])
            half_tr = 0.5 * np.float64(np.float32(np.int32(sxx + syy)))
            d = 0.5 * np.float64(np.int32(sxx - syy))
            dst[x] = half_tr - np.sqrt(d * d + np.float64(sxy * sxy))
        dst[0] = 0
        dst[w - 1] = 0


def min_eigen_strength(filtered: np.ndarray) -> np.ndarray:
    """Smaller eigenvalue of the 3x3 structure tensor of the Sobel gradient, (H, W) float32.

    Large only where the gradient is strong in two directions (a corner or a textured spot),
    the "good features to track" measure of Shi and Tomasi (1994) cited by the paper. The
    border pixel ring is 0.
    """
    out = np.empty(filtered.shape, np.float32)
    _min_eigen(np.ascontiguousarray(filtered, np.uint8), out)
    return out


STRENGTHS = {"gradient": gradient_magnitude, "min_eigen": min_eigen_strength}


@nb.njit(cache=True, nogil=True)
def _monotonic_keys(vals, keys):  # pragma: no cover - numba
    """uint32 keys ordered like the float32 ``vals``: the bits with the sign flipped for
    values >= 0 and all flipped for values < 0; -0.0 is first made 0.0, its equal."""
    canon = np.empty(vals.shape[0], np.float32)
    for i in range(vals.shape[0]):
        canon[i] = vals[i] + np.float32(0.0)
    bits = canon.view(np.uint32)
    for i in range(vals.shape[0]):
        b = bits[i]
        keys[i] = ~b if b >> 31 else b | np.uint32(0x80000000)


@nb.njit(cache=True, nogil=True)
def _sort_desc(keys):  # pragma: no cover - numba
    """Indices that sort uint32 ``keys`` descending, stable (equal keys keep their order): LSD
    radix sort of the complemented keys, 11 bits a pass.

    The keys travel with their indices (sequential access) and the three digit histograms are
    counted in one pass; a pass whose digit is the same for every key is skipped.
    """
    n = keys.shape[0]
    ks = np.empty((2, n), np.uint32)  # keys and indices, current and next by pass parity
    ix = np.empty((2, n), np.int64)
    hist = np.zeros((3, 2048), np.int64)
    for i in range(n):
        key = ~keys[i]
        ks[0, i] = key
        ix[0, i] = i
        hist[0, key & 2047] += 1
        hist[1, (key >> 11) & 2047] += 1
        hist[2, key >> 22] += 1
    cur = 0
    for p in range(3):
        count = hist[p]
        if count.max() == n:
            continue  # one digit for all: this pass would not move anything
        acc = 0
        for d in range(2048):
            c = count[d]
            count[d] = acc
            acc += c
        shift = 11 * p
        src_k = ks[cur]
        src_i = ix[cur]
        dst_k = ks[1 - cur]
        dst_i = ix[1 - cur]
        for i in range(n):
            key = src_k[i]
            d = (key >> shift) & 2047
            at = count[d]
            dst_k[at] = key
            dst_i[at] = src_i[i]
            count[d] = at + 1
        cur = 1 - cur
    return ix[cur]


@nb.njit(cache=True, nogil=True)
def _top_k(grad, k, margin, floor):  # pragma: no cover - numba
    """The k largest values inside the margin that exceed ``floor`` (float32), largest first,
    ties in row-major order.

    Returns (candidates (k, 2) int16 x, y; values (k,) float32); fewer than k where fewer
    values exceed the floor (NaN never does).

    The floor bounds the work where most of the frame has no texture: a black or uniform
    frame, whose k-th largest strength (0) every pixel ties with, had every pixel collected and
    sorted (12 ms at 1280x720, against 1.5 for a textured frame); pixels at or below the
    texture floor cannot be candidates, so they are never collected.

    A threshold T at most the k-th largest value is estimated from a 1-in-16 sample, the
    pixels >= T (a few more than k) are collected in row-major order and stably sorted by a
    radix sort: a few linear passes. (A histogram of the whole frame followed by a comparison
    sort, the previous method, cost several times more.)
    """
    h, w = grad.shape
    x0 = margin
    x1 = w - margin
    y0 = margin
    y1 = h - margin
    inner = (y1 - y0) * (x1 - x0)
    # 1. T: about the value of rank ~1.3 k among the pixels, estimated from that rank among
    # every 4th row and column: a histogram of the samples' top 12 key bits finds its bin (a
    # value range of 1/8 octave), whose least sample is T
    n_s = ((y1 - y0 + 3) // 4) * ((x1 - x0 + 3) // 4)
    sample = np.empty(n_s, np.float32)
    c = 0
    for y in range(y0, y1, 4):
        for x in range(x0, x1, 4):
            sample[c] = grad[y, x]
            c += 1
    skeys = np.empty(n_s, np.uint32)
    _monotonic_keys(sample, skeys)
    hist = np.zeros(4097, np.int64)
    for i in range(n_s):
        if not np.isnan(sample[i]):
            hist[skeys[i] >> 20] += 1
    rank = int(k * n_s / inner * 1.3) + 16
    flat = grad.ravel()
    lo = y0 * w
    hi = y1 * w
    rows = flat[lo:hi]
    n_words = (hi - lo + 31) // 32 * 4
    mask = np.empty(n_words * 8, np.uint8)
    mask[hi - lo:] = 0
    words = mask.view(np.uint64)
    # room for the pixels >= T: ~1.3 k expected; a frame that holds more starts again with
    # room for all
    cap = min(inner, 4 * k + 1024)
    xs = np.empty(cap, np.int16)
    ys = np.empty(cap, np.int16)
    vals = np.empty(cap, np.float32)
    while True:
        # the bin of the sample of that rank; -inf when the rank exceeds the samples
        above = 0
        top_bin = 4096
        while top_bin >= 0 and above + hist[top_bin] < rank:
            above += hist[top_bin]
            top_bin -= 1
        thr = np.float32(-np.inf)
        if top_bin >= 0:
            # the bin's least sample: at most that rank's, found without a sort (numba's
            # np.sort took ~2.5 s of a first run's compile for a few values)
            thr = np.float32(np.inf)
            for i in range(n_s):
                if skeys[i] >> 20 == top_bin and sample[i] < thr:
                    thr = sample[i]
        # at the floor: every value above it is collected, and no lower threshold is tried
        floored = not thr > floor
        if floored:
            thr = np.nextafter(floor, np.float32(np.inf))
        # 2. mark the pixels >= T: one vectorised pass over whole rows
        for q in range(hi - lo):
            mask[q] = rows[q] >= thr
        # 3. collect those inside the margin in row-major order, 32 mask bytes at a time
        # (most are all zero)
        total = 0
        y = 0
        row_end = w
        for i in range(0, n_words, 4):
            if words[i] | words[i + 1] | words[i + 2] | words[i + 3] == 0:
                continue
            for u in range(i, i + 4):
                word = words[u]
                while word:
                    # each marked byte holds one set bit: the lowest is the next pixel
                    q = u * 8 + (trailing_zeros(word) >> 3)
                    word &= word - np.uint64(1)
                    while q >= row_end:
                        y += 1
                        row_end += w
                    x = q - (row_end - w)
                    if x0 <= x < x1:
                        if total == cap:
                            break
                        xs[total] = x
                        ys[total] = y + y0
                        vals[total] = rows[q]
                        total += 1
        if total == cap and cap < inner:
            cap = inner
            xs = np.empty(cap, np.int16)
            ys = np.empty(cap, np.int16)
            vals = np.empty(cap, np.float32)
            continue  # collect again, with room for every pixel
        if total >= k or top_bin < 0 or floored:
            break
        rank = 2 * rank + 16  # the sample misled us: take a lower threshold
    vals = vals[:total]
    # 4. sort by value, descending; the radix sort is stable, so ties stay in row-major order
    keys = np.empty(total, np.uint32)
    _monotonic_keys(vals, keys)
    order = _sort_desc(keys)
    kk = min(k, total)
    cands = np.empty((kk, 2), np.int16)
    out = np.empty(kk, np.float32)
    for i in range(kk):
        j = order[i]
        cands[i, 0] = xs[j]
        cands[i, 1] = ys[j]
        out[i] = vals[j]
    return cands, out


def threshold_candidates(grad: np.ndarray, thres_percent: float, margin: int = 0,
                         floor: float = -np.inf) -> tuple[np.ndarray, np.ndarray]:
    """The THRES_PERCENT % strongest-gradient pixels, strongest first, less those at or below
    ``floor``.

    Parameters
    ----------
    grad : (H, W) float32 gradient magnitude.
    thres_percent : percentage (0, 100] of the image's pixels to keep.
    margin : pixels this close to the border are never candidates (a feature there could not
        hold a correlation window).
    floor : only strengths above it (compared in float32, as numpy compares a float32 array
        with a Python float) are kept: the same as keeping those of the THRES_PERCENT % above
        it, without collecting the pixels below it.

    Returns
    -------
    candidates : (N, 2) int16 x, y; strength : (N,) float32; sorted by strength, descending,
    ties broken by row-major position so the order is deterministic.
    """
    h, w = grad.shape
    if 2 * margin >= min(h, w):
        return np.empty((0, 2), np.int16), np.empty(0, np.float32)
    inner = (h - 2 * margin) * (w - 2 * margin)
    k = min(max(int(round(grad.size * thres_percent / 100.0)), 1), inner)
    return _top_k(np.ascontiguousarray(grad, np.float32), k, int(margin), np.float32(floor))


# The largest strength that a uniform patch with white Gaussian noise reaches, per unit of the
# noise at the Sobel derivative (standard deviation, :func:`_sobel_sd`): the largest of 4
# million samples (pixels of 16 512x512 uniform frames with noise of 1 to 8 grey levels,
# filtered at blur_sigma 0, 0.5, 1 and 2 and rounded to uint8 as the frames are). The smaller
# eigenvalue grows with the noise's variance (its largest ~61 times it, its mean ~5 times),
# the gradient magnitude with its standard deviation (~6.6 times).
_NOISE_PEAK = {"min_eigen": 61.0, "gradient": 6.6}
_NOISE_POWER = {"min_eigen": 2, "gradient": 1}


@functools.lru_cache(maxsize=32)
def _sobel_gain(blur_sigma: float) -> float:
    """Standard deviation of the 3x3 Sobel x derivative of unit white noise filtered as
    :func:`gaussian_filter` filters it."""
    if blur_sigma > 0:
        k = 2 * int(np.ceil(3 * blur_sigma)) + 1
        g1 = cv2.getGaussianKernel(k, blur_sigma).ravel()
    else:
        g1 = np.ones(1)
    smooth = np.convolve(g1, [1.0, 2.0, 1.0])  # across the derivative
    deriv = np.convolve(g1, [-1.0, 0.0, 1.0])  # along it
    return float(np.linalg.norm(smooth) * np.linalg.norm(deriv))


def _sobel_sd(noise_sigma: float, blur_sigma: float) -> float:
    """Standard deviation of the Sobel derivative of a uniform patch: the camera's noise
    through the filter, and the rounding of the filtered frame to whole grey levels (uniform,
    variance 1/12, after the filter)."""
    camera = noise_sigma * _sobel_gain(blur_sigma)
    rounding = _sobel_gain(0.0) / np.sqrt(12.0)
    return float(np.hypot(camera, rounding))


def texture_floor(params: TrackerParams, noise: float | None = None) -> float:
    """The absolute texture floor: the largest strength a uniform patch reaches with the
    camera's noise (``noise`` grey levels, default ``noise_sigma``) after this pre-processing
    (~1660 for ``min_eigen`` at the defaults); a candidate must exceed it."""
    sd = _sobel_sd(params.noise_sigma if noise is None else noise, params.blur_sigma)
    return _NOISE_PEAK[params.strength] * sd ** _NOISE_POWER[params.strength]


def frame_noise(filtered: np.ndarray, params: TrackerParams) -> float:
    """The noise the texture floor of ``filtered`` is set for, grey levels: ``noise_sigma``,
    or the noise the frame itself shows (:func:`.noise.noise_level`) where that is more.

    A camera's noise grows with its gain: a dark room or a covered lens read 3 to 8 grey
    levels here, and with the floor at ``noise_sigma`` (2) a uniform frame of 5 made 100
    features of noise every frame, re-detected as fast as they were lost, and a *valid*
    estimate whose centroid jumped about (the controller would have moved the robot). On the
    real frames of the shared data the estimate reads 1.1 to 3.9 (fine texture passes the
    operator), and the floor it sets stays below the quality level's (a fraction of the
    strongest): their candidates are the same. A scene textured at the scale of one pixel,
    white like noise, would read as noise; a camera's optics do not pass such texture.
    """
    return max(float(params.noise_sigma), noise_level(filtered, params.blur_sigma))


def candidates_of(filtered: np.ndarray, params: TrackerParams) -> tuple[np.ndarray, np.ndarray]:
    """The THRES_PERCENT candidates of a filtered frame and their strengths: the gradient
    strength, threshold and texture floor steps of :func:`preprocess`."""
    grad, floor = strength_of(filtered, params)
    return candidates_above(grad, floor, params)


def strength_of(filtered: np.ndarray, params: TrackerParams) -> tuple[np.ndarray, float]:
    """The gradient strength of a filtered frame, (H, W) float32, and the texture floor its
    candidates must exceed: what :func:`candidates_of` computes before it thresholds, the same
    for every THRES_PERCENT and CORR_SIZE (the auto-tuner's experiment computes it once a
    frame for all of them)."""
    return (STRENGTHS[params.strength](filtered),
            texture_floor(params, frame_noise(filtered, params)))


def candidates_above(grad: np.ndarray, floor: float, params: TrackerParams
                     ) -> tuple[np.ndarray, np.ndarray]:
    """The candidates of a frame of strength ``grad`` and texture floor ``floor``
    (:func:`strength_of`) for ``params``' THRES_PERCENT, CORR_SIZE and quality level, and their
    strengths; ``grad`` is not written to."""
    # a candidate must hold a correlation window plus one pixel for the Sobel support, and
    # exceed the texture floor (strictly, so that a frame without texture, strength 0
    # everywhere, has none even with a floor of 0)
    cands, strength = threshold_candidates(grad, params.thres_percent,
                                           margin=params.corr_half + 1, floor=floor)
    if len(strength):
        # and a fraction of the strongest: strongest first, so those that pass are a prefix
        keep = int(np.count_nonzero(strength > max(floor, params.quality_level
                                                   * float(strength[0]))))
        cands, strength = cands[:keep], strength[:keep]
    return cands, strength


class DeferredPreprocessed(Preprocessed):
    """A :class:`Preprocessed` whose candidates are computed when first read.

    The tracker reads them only on a first frame and when it re-detects (a few frames in a
    hundred); the gradient strength and threshold are about two thirds of pre-processing.
    The values are those :func:`candidates_of` gives for ``filtered`` and ``params``, computed
    once, so whether they are read early, late or never, nothing else changes.
    """

    __slots__ = ()

    def __init__(self, filtered: np.ndarray, params: TrackerParams) -> None:
        object.__setattr__(self, "filtered", filtered)
        object.__setattr__(self, "_params", params)
        object.__setattr__(self, "_computed", None)

    def _get(self) -> tuple[np.ndarray, np.ndarray]:
        got = self.__dict__["_computed"]
        if got is None:
            got = candidates_of(self.filtered, self.__dict__["_params"])
            object.__setattr__(self, "_computed", got)
        return got  # type: ignore[no-any-return]

    @property  # type: ignore[misc]
    def candidates(self) -> np.ndarray:  # type: ignore[override]
        return self._get()[0]

    @property  # type: ignore[misc]
    def strength(self) -> np.ndarray:  # type: ignore[override]
        return self._get()[1]

    @property
    def computed(self) -> bool:
        """Whether the candidates have been computed (read) yet."""
        return self.__dict__["_computed"] is not None


def preprocess(gray: np.ndarray, params: TrackerParams) -> Preprocessed:
    """Filter, gradient and threshold one 8-bit grey frame (H, W) uint8.

    The filter runs now; the gradient strength and threshold when the candidates are first
    read (:class:`DeferredPreprocessed`): same values, only when they are needed.

    The candidates are the THRES_PERCENT % strongest pixels that also have texture: a strength
    above the noise floor (:func:`texture_floor`) and at least ``quality_level`` times the
    frame's strongest, as OpenCV's ``goodFeaturesToTrack`` has it. An all-black, uniform or
    saturated frame has none.
    """
    if gray.ndim != 2 or gray.dtype != np.uint8:
        raise ValueError(f"expected a (H, W) uint8 frame, got {gray.shape} {gray.dtype}")
    filtered = gaussian_filter(fix_defects(gray), params.blur_sigma)
    return DeferredPreprocessed(np.ascontiguousarray(filtered), params)
