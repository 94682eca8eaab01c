"""Exposure compensation: a change of brightness of the whole frame between two frames.

Eq. (1) compares grey levels, so it assumes that a point keeps its brightness from frame t to
t+1. A robot's camera breaks that whenever its auto-exposure or gain reacts (turning towards a
window, a light switched on, a flickering lamp): every pixel becomes ``g I + b``. The sum of
squared differences then grows for every feature with its own brightness, the residual bound
and the forward-backward check reject the features wholesale, and those that survive are
pulled towards brighter or darker neighbours. On frames rendered from the shared data with a
gain of +-8 % and an offset of +-10 grey levels from frame to frame (a nervous auto-exposure),
the default tracker kept 1 to 46 % of its features over 40 frames where OpenCV's LK kept 18 to
71 %, and its median error went from ~0.04 to ~0.3 px.

The change is estimated from the two frames' coarsest pyramid level, over the part of the
scene both see: frame t shifted by the image motion of the frame before (the tracker's
prediction), so the scene entering and leaving at the borders does not pass for a change of
exposure. With both frames' mean and standard deviation there, ``g = s1 / s0`` and
``b = m1 - g m0``. Frame t's pyramid is then mapped through that gain and offset (a look-up
table on every level) before the search, so Eq. (1) compares like with like. Frame t+1, the
features and the candidates are left as the camera gave them.

A change is applied only when it moves the grey levels of frame t's typical range (two
standard deviations either side of its mean) by more than ``2 noise_sigma`` somewhere: on
frames whose exposure does not change, the estimate from two different views of the scene
differs from "no change" by up to ~2.4 grey levels (measured on the rendered sequences,
p90 ~1.1), which must not be applied as a change of exposure. Frames without texture (a
standard deviation below :data:`MIN_SPREAD`) have nothing to compensate.
"""

from __future__ import annotations

import cv2
import numba as nb
import numpy as np

from .pyramid import Pyramid, _level

#: A frame whose coarsest level has a grey-level standard deviation below this has no contrast
#: to estimate a gain from (black, uniform, saturated): left as it is.
MIN_SPREAD = 1.0
#: Gains beyond these are not a camera's exposure step between two frames but a different
#: scene (or a frame of another camera): left to the tracker's checks.
GAIN_RANGE = (0.25, 4.0)


def exposure_change(prev: np.ndarray, curr: np.ndarray,
                    shift: tuple[float, float] = (0.0, 0.0)) -> tuple[float, float] | None:
    """Gain and offset ``(g, b)`` with ``curr ~ g prev + b``, from the mean and standard
    deviation of the part of the two (H, W) uint8 images that sees the same scene when
    ``curr`` is ``prev`` moved by ``shift`` (x, y, in px of these images); None when either
    has no contrast there (:data:`MIN_SPREAD`), the overlap is empty, or the gain is outside
    :data:`GAIN_RANGE`."""
    change = _change(prev, curr, shift)
    return None if change is None else change[:2]


def _change(prev: np.ndarray, curr: np.ndarray, shift: tuple[float, float]
            ) -> tuple[float, float, float] | None:
    """:func:`exposure_change`, and how far it moves frame t's typical grey levels (its mean
    over the overlap, and two standard deviations either side): ``|m1 - m0| + 2 |s1 - s0|``."""
    both = _overlap(prev, curr, shift)
    if both is None:
        return None
    m0, s0 = _mean_std(both[0])
    m1, s1 = _mean_std(both[1])
    if s0 < MIN_SPREAD or s1 < MIN_SPREAD:
        return None
    gain = s1 / s0
    if not GAIN_RANGE[0] <= gain <= GAIN_RANGE[1]:
        return None
    return gain, m1 - gain * m0, abs(m1 - m0) + 2.0 * abs(s1 - s0)


def _overlap(prev: np.ndarray, curr: np.ndarray, shift: tuple[float, float]
             ) -> tuple[np.ndarray, np.ndarray] | None:
    """The parts of ``prev`` and ``curr`` that see the same scene when ``curr`` is ``prev``
    moved by ``shift`` (x, y px, rounded); None when they do not overlap."""
    h, w = prev.shape
    ix, iy = int(round(shift[0])), int(round(shift[1]))
    x0, x1 = max(0, -ix), min(w, w - ix)
    y0, y1 = max(0, -iy), min(h, h - iy)
    if x1 <= x0 or y1 <= y0:
        return None
    return prev[y0:y1, x0:x1], curr[y0 + iy:y1 + iy, x0 + ix:x1 + ix]


def _mean_std(image: np.ndarray) -> tuple[float, float]:
    mean, std = cv2.meanStdDev(image)
    return float(mean[0, 0]), float(std[0, 0])


@nb.njit(cache=True, nogil=True)
def _overlap_stats(pdata, cdata, geo, k, ix, iy):  # pragma: no cover - numba
    """The mean and standard deviation of the overlap of level k of two pyramids' buffers
    (:func:`_overlap` of a whole shift ``ix, iy``), ``(m0, s0, m1, s1)``, as
    ``cv2.meanStdDev`` gives them to the bit (exact integer sums, then its arithmetic in
    doubles); all 0 where they do not overlap. One kernel for what took ~30 Python and
    OpenCV calls, ~20 us a frame back to back but ~150 us in a service at 30 fps, whose every
    call of a function starts from cold caches."""
    prev = _level(pdata, geo, k)
    curr = _level(cdata, geo, k)
    h, w = prev.shape
    x0, x1 = max(0, -ix), min(w, w - ix)
    y0, y1 = max(0, -iy), min(h, h - iy)
    if x1 <= x0 or y1 <= y0:
        return 0.0, 0.0, 0.0, 0.0
    s0 = 0
    q0 = 0
    s1 = 0
    q1 = 0
    for y in range(y0, y1):
        for x in range(x0, x1):
            a = np.int64(prev[y, x])
            b = np.int64(curr[y + iy, x + ix])
            s0 += a
            q0 += a * a
            s1 += b
            q1 += b * b
    scale = 1.0 / ((x1 - x0) * (y1 - y0))
    m0 = s0 * scale
    m1 = s1 * scale
    return (m0, np.sqrt(max(q0 * scale - m0 * m0, 0.0)),
            m1, np.sqrt(max(q1 * scale - m1 * m1, 0.0)))


def compensate(prev: Pyramid, curr: Pyramid, shift: tuple[float, float],
               noise_sigma: float) -> Pyramid:
    """``prev`` mapped onto ``curr``'s exposure (see the module notes), or ``prev`` itself
    when the change is within ``2 noise_sigma`` grey levels (at least one) or cannot be told.

    ``shift``: the image motion expected from ``prev`` to ``curr``, px of level 0."""
    k = min(prev.levels, curr.levels) - 1
    at = (shift[0] * 0.5 ** k, shift[1] * 0.5 ** k)
    # _change(prev.level(k), curr.level(k), at) in one kernel (the frame's path: every frame)
    m0, s0, m1, s1 = _overlap_stats(prev.data, curr.data, prev.geo, k, int(round(at[0])),
                                    int(round(at[1])))
    if s0 < MIN_SPREAD or s1 < MIN_SPREAD:  # no contrast, or no overlap
        return prev
    gain = s1 / s0
    if not GAIN_RANGE[0] <= gain <= GAIN_RANGE[1]:
        return prev
    change = (gain, m1 - gain * m0, abs(m1 - m0) + 2.0 * abs(s1 - s0))
    if change[2] <= max(2.0 * noise_sigma, 1.0):
        return prev
    gain, offset, _ = change
    if not _explains(prev.level(k), curr.level(k), at, gain, offset):
        return prev
    lut = np.clip(np.rint(np.arange(256) * gain + offset), 0, 255).astype(np.uint8)
    return Pyramid(cv2.LUT(prev.data, lut).reshape(-1), prev.geo, prev.shapes)


#: The overlap is cut into BLOCKS x BLOCKS blocks for :func:`_explains`.
BLOCKS = 4


def _explains(prev: np.ndarray, curr: np.ndarray, shift: tuple[float, float], gain: float,
              offset: float) -> bool:
    """Whether the change ``(gain, offset)`` explains how the blocks of the overlap differ:
    mapped by it, frame t's block means come at least twice as close to frame t+1's (RMS over
    the blocks). A change of exposure moves every block alike; a view that moved further than
    predicted (a fast turn, the first frame of a track) changes the blocks' content, which a
    gain and offset fitted to the whole overlap do not explain."""
    both = _overlap(prev, curr, shift)
    if both is None:
        return False
    a: np.ndarray = both[0].astype(np.float32)
    b: np.ndarray = both[1]
    # the part of the shift the overlap's whole pixels leave out (up to half a pixel of the
    # coarsest level, 2 px of the frame's), applied to frame t bilinearly: its blocks' means
    # then see the scene frame t+1's do
    fx, fy = shift[0] - round(shift[0]), shift[1] - round(shift[1])
    if fx or fy:
        a = cv2.warpAffine(a, np.array([[1.0, 0.0, fx], [0.0, 1.0, fy]], np.float32),
                           (a.shape[1], a.shape[0]), flags=cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_REPLICATE)
    a, b = a.astype(np.float64), b.astype(np.float64)
    bh, bw = a.shape[0] // BLOCKS, a.shape[1] // BLOCKS
    if bh < 1 or bw < 1:
        return False
    ma = a[:bh * BLOCKS, :bw * BLOCKS].reshape(BLOCKS, bh, BLOCKS, bw).mean(axis=(1, 3))
    mb = b[:bh * BLOCKS, :bw * BLOCKS].reshape(BLOCKS, bh, BLOCKS, bw).mean(axis=(1, 3))
    before = float(np.sqrt(np.mean((mb - ma) ** 2)))
    after = float(np.sqrt(np.mean((mb - (gain * ma + offset)) ** 2)))
    return after <= 0.5 * before
