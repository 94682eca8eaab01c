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
from .ssd import NO_NRT

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


@nb.njit(cache=True, nogil=True, inline="always")
def _overlap_at(pdata, cdata, geo, k, ix, iy):  # pragma: no cover - numba
    """Level k of two pyramids' buffers and the part of frame t that sees the scene frame
    t+1 does when it moved by the whole ``ix, iy`` (:func:`_overlap`): (prev, curr, x0, x1,
    y0, y1), frame t+1's part the same moved by ``ix, iy``; empty where x1 <= x0 or y1 <= y0."""
    prev = _level(pdata, geo, k)
    curr = _level(cdata, geo, k)
    h, w = prev.shape
    return (prev, curr, *_overlap_bounds(h, w, ix, iy))


@nb.njit(cache=True, nogil=True, inline="always")
def _overlap_bounds(h, w, ix, iy):  # pragma: no cover - numba
    """(x0, x1, y0, y1): the part of an (h, w) frame t that frame t+1 sees when the scene
    moved by the whole ``ix, iy`` (:func:`_overlap`); empty where x1 <= x0 or y1 <= y0."""
    return max(0, -ix), min(w, w - ix), max(0, -iy), min(h, h - iy)


#: pixels of a row summed in int32 by :func:`_overlap_stats` (their squares: 2^15 255^2 < 2^31)
ROW_CHUNK = 1 << 15


@nb.njit(**NO_NRT)
def _overlap_stats(pdata, cdata, geo, k, ix, iy):  # pragma: no cover - numba
    """The mean and standard deviation of the overlap of level k of two pyramids' buffers
    (:func:`_overlap` of a whole shift ``ix, iy``), ``(m0, s0, m1, s1)``, as
    ``cv2.meanStdDev`` gives them to the bit (exact integer sums, then its arithmetic in
    doubles); all 0 where they do not overlap. One kernel for what took ~30 Python and
    OpenCV calls, ~20 us a frame back to back but ~150 us in a service at 30 fps, whose every
    call of a function starts from cold caches. The sums of each ROW_CHUNK pixels of a row
    in int32 lanes over slices, added up in int64; no numba runtime."""
    # offsets into the buffers, not the views of _overlap_at: a kernel without the runtime
    # cannot take an array a function makes
    o = geo[k, 0]
    w = geo[k, 2]
    x0, x1, y0, y1 = _overlap_bounds(geo[k, 1], w, ix, iy)
    if x1 <= x0 or y1 <= y0:
        return 0.0, 0.0, 0.0, 0.0
    s0 = 0
    q0 = 0
    s1 = 0
    q1 = 0
    n = x1 - x0
    for y in range(y0, y1):
        pa = o + y * w + x0
        pb = o + (y + iy) * w + x0 + ix
        for c in range(0, n, ROW_CHUNK):
            m = min(ROW_CHUNK, n - c)
            a = pdata[pa + c:pa + c + m]
            b = cdata[pb + c:pb + c + m]
            ra = np.int32(0)
            rq = np.int32(0)
            rb = np.int32(0)
            rr = np.int32(0)
            for x in range(m):
                va = np.int32(a[x])
                vb = np.int32(b[x])
                ra += va
                rq += va * va
                rb += vb
                rr += vb * vb
            s0 += np.int64(ra)
            q0 += np.int64(rq)
            s1 += np.int64(rb)
            q1 += np.int64(rr)
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
    ix, iy = int(round(at[0])), int(round(at[1]))
    # _change(prev.level(k), curr.level(k), at) in one kernel (the frame's path: every frame)
    m0, s0, m1, s1 = _overlap_stats(prev.data, curr.data, prev.geo, k, ix, iy)
    if s0 < MIN_SPREAD or s1 < MIN_SPREAD:  # no contrast, or no overlap
        return prev
    gain = s1 / s0
    if not GAIN_RANGE[0] <= gain <= GAIN_RANGE[1]:
        return prev
    change = (gain, m1 - gain * m0, abs(m1 - m0) + 2.0 * abs(s1 - s0))
    if change[2] <= max(2.0 * noise_sigma, 1.0):
        return prev
    gain, offset, _ = change
    if not _explains(prev.data, curr.data, prev.geo, k, ix, iy, at[0] - ix, at[1] - iy, gain,
                     offset, BLOCKS):
        return prev
    lut = np.clip(np.rint(np.arange(256) * gain + offset), 0, 255).astype(np.uint8)
    return Pyramid(cv2.LUT(prev.data, lut).reshape(-1), prev.geo, prev.shapes)


#: A change that varies from row to row (mains flicker seen through a rolling shutter) is
#: fitted on this many horizontal bands of the overlap, each a gain, and checked on
#: ROW_COLS blocks across each band (:func:`compensate_rows`)
ROW_BANDS = 32
ROW_COLS = 4
#: Bands darker than this (mean grey level) have no gain of their own to tell: 1
ROW_DARK = 8.0
#: Every ROW_STEP-th row of a band is summed
ROW_STEP = 2


def compensate_rows(prev: Pyramid, curr: Pyramid, shift: tuple[float, float],
                    noise_sigma: float) -> Pyramid:
    """``prev`` with each row scaled by a gain that maps it onto ``curr``'s brightness, where
    the brightness changed from row to row; else ``prev`` itself.

    Light on mains power flickers at 100 or 120 Hz; a rolling shutter reads its rows one
    after another, so a short exposure sees the flicker as horizontal bands, and they drift
    from frame to frame. :func:`compensate` fits one gain and offset to the whole frame, which
    such bands are not (its block test refuses them): on RubberWhale with bands of +-10 %
    and an 80-row period drifting a third of a period a frame (100 Hz at 30 fps), the step
    was off by 4.7 px rms and the scale read 0.955 for 1.034 after 40 frames; on three other
    scenes the median error rose tenfold (a hunt of sensor effects, 2026-12-07).

    On the frame itself (level 0; every ROW_STEP-th row), over the part of the scene both see
    (``shift``, as :func:`compensate`'s), each of ROW_BANDS bands gets the gain of its mean
    (``curr``'s over ``prev``'s; 1 where darker than ROW_DARK). They are applied only where
    they differ from band to band and move a band's mean by more than ``2 noise_sigma`` (at
    least 1; a change alike everywhere is :func:`compensate`'s), and explain the
    ROW_COLS blocks across every band at least twice as well as no change (the sum of
    squares a quarter): a view that moved otherwise than predicted changes its blocks one by
    one, a flicker a whole band alike. Each row of every level gets the gain interpolated
    between the bands' centres (linearly, the ends held)."""
    # on level 0: level 1's bands, a pixel of misalignment there, left RubberWhale 1 px off
    ix, iy = int(round(shift[0])), int(round(shift[1]))
    gains = np.empty(ROW_BANDS)
    top, bh = _row_gains(prev.data, curr.data, prev.geo, 0, ix, iy, ROW_COLS, ROW_DARK,
                         max(2.0 * noise_sigma, 1.0), gains)
    if bh == 0:
        return prev
    centres = top + (np.arange(ROW_BANDS) + 0.5) * bh - 0.5  # the bands' centres, rows
    out = np.empty_like(prev.data)
    _scale_rows(prev.data, prev.geo, centres, gains, out)
    return Pyramid(out, prev.geo, prev.shapes)


@nb.njit(cache=True, nogil=True)
def _row_gains(pdata, cdata, geo, k, ix, iy, cols, dark, least, gains):  # pragma: no cover
    """:func:`compensate_rows`'s test on level k of two pyramids' buffers: each band's gain
    into ``gains`` (one a band, their number its length) and ``(top, bh)``, the overlap's
    first row and the bands' height, where the change is to be applied; ``bh`` 0 where not
    (no such change, or a block under 2 x 4 pixels). The blocks' sums in int32 lanes over
    slices (a block of a row: at most 2^23 pixels of 255), in one pass."""
    prev, curr, x0, x1, y0, y1 = _overlap_at(pdata, cdata, geo, k, ix, iy)
    bands = gains.shape[0]
    bh = (y1 - y0) // bands
    bw = (x1 - x0) // cols
    if x1 <= x0 or y1 <= y0 or bh < 2 or bw < 4 or bw >= 1 << 23:
        return y0, 0
    ma = np.zeros((bands, cols))
    mb = np.zeros((bands, cols))
    for r in range(bands):
        for y in range(y0 + r * bh, y0 + (r + 1) * bh, ROW_STEP):
            row_a = prev[y]
            row_b = curr[y + iy]
            for c in range(cols):
                lo = x0 + c * bw
                a = row_a[lo:lo + bw]
                b = row_b[lo + ix:lo + ix + bw]
                sa = np.int32(0)
                sb = np.int32(0)
                for x in range(bw):
                    sa += np.int32(a[x])
                    sb += np.int32(b[x])
                ma[r, c] += sa
                mb[r, c] += sb
    n = float(((bh + ROW_STEP - 1) // ROW_STEP) * bw)
    lit = 0
    lo_g = np.inf
    hi_g = -np.inf
    level = 0.0
    moved = 0.0
    for r in range(bands):
        a = 0.0
        b = 0.0
        for c in range(cols):
            ma[r, c] /= n
            mb[r, c] /= n
            a += ma[r, c]
            b += mb[r, c]
        a /= cols
        b /= cols
        g = 1.0
        if a >= dark:
            g = min(max(b / a, GAIN_RANGE[0]), GAIN_RANGE[1])
            lit += 1
            level += a
            lo_g = min(lo_g, g)
            hi_g = max(hi_g, g)
        gains[r] = g
        moved = max(moved, abs(g - 1.0) * a)
    # a change alike in every band is the whole frame's (compensate's, which may have refused
    # it: a frame gone black has no contrast to take a gain from)
    if lit < 3 or (hi_g - lo_g) * level / lit <= least or moved <= least:
        return y0, 0
    before = 0.0
    after = 0.0
    for r in range(bands):
        for c in range(cols):
            before += (mb[r, c] - ma[r, c]) ** 2
            after += (mb[r, c] - gains[r] * ma[r, c]) ** 2
    if after > 0.25 * before:
        return y0, 0
    return y0, bh


@nb.njit(cache=True, nogil=True)
def _scale_rows(data, geo, centres, gains, out):  # pragma: no cover - numba
    """Every level of a pyramid's buffer ``data`` with each row multiplied by the gain
    interpolated at its row of level 0 between ``centres`` (ascending) and ``gains``, the ends
    held, rounded and capped at 255, into ``out``."""
    last = centres.shape[0] - 1
    for k in range(geo.shape[0]):
        o = geo[k, 0]
        h = geo[k, 1]
        w = geo[k, 2]
        i = 0
        for y in range(h):
            at = float(y * (1 << k))
            if at <= centres[0]:
                g = gains[0]
            elif at >= centres[last]:
                g = gains[last]
            else:
                while centres[i + 1] < at:
                    i += 1
                t = (at - centres[i]) / (centres[i + 1] - centres[i])
                g = gains[i] + t * (gains[i + 1] - gains[i])
            row = data[o + y * w:o + (y + 1) * w]
            dst = out[o + y * w:o + (y + 1) * w]
            for x in range(w):
                dst[x] = min(255, int(row[x] * g + 0.5))


#: The overlap is cut into BLOCKS x BLOCKS blocks for :func:`_explains`.
BLOCKS = 4


@nb.njit(cache=True, nogil=True)
def _explains(pdata, cdata, geo, k, ix, iy, fx, fy, gain, offset,
              blocks):  # pragma: no cover - numba
    """Whether the change ``(gain, offset)`` explains how the blocks of the overlap of level k
    of two pyramids' buffers differ (:func:`_overlap` of the whole shift ``ix, iy``, cut into
    ``blocks`` x ``blocks``): mapped by it, frame t's block means come at least twice as close
    to frame t+1's (RMS over the blocks). A change of exposure moves every block alike; a view
    that moved further than predicted (a fast turn, the first frame of a track) changes the
    blocks' content, which a gain and offset fitted to the whole overlap do not explain.

    The part of the shift the whole pixels leave out, ``(fx, fy)`` (up to half a pixel of the
    coarsest level, 2 px of the frame's), moves frame t's overlap bilinearly first, its edge
    repeated: its blocks' means then see the scene frame t+1's do. One kernel for what was
    ~10 numpy and OpenCV calls (a bilinear ``cv2.warpAffine``, conversions, block means): 42
    -> 15 us at 64 x 64 back to back, the same decision on every one of 368 frames where it
    ran (the rendered sequences with exposure changes; the built-in sequence at 256 x 256,
    640 x 480 and 1280 x 720 with exposure steps and its jumps); after 33 ms idle, as in a
    service at 30 fps, whose calls start from cold caches, see the commit that made it a
    kernel (473643b)."""
    prev, curr, x0, x1, y0, y1 = _overlap_at(pdata, cdata, geo, k, ix, iy)
    if x1 <= x0 or y1 <= y0:
        return False
    ow = x1 - x0
    oh = y1 - y0
    bw = ow // blocks
    bh = oh // blocks
    if bw < 1 or bh < 1:
        return False
    # the sample of frame t at (x - fx, y - fy): between its pixels dx and dx + 1 (dy, dy + 1)
    dx = int(np.floor(-fx))
    dy = int(np.floor(-fy))
    tx = -fx - dx
    ty = -fy - dy
    # bilinear sampling is linear: a block's sum of samples is the blend of four sums of frame
    # t's pixels over the block moved by whole pixels (dx or dx + 1, dy or dy + 1). Per row of
    # frame t (sample row y reads rows y + dy and y + dy + 1), each block's sums over its
    # columns moved by dx and dx + 1, in integers, the overlap's edge repeated
    rows = bh * blocks
    left = np.zeros((rows + 1, blocks), np.int64)
    right = np.zeros((rows + 1, blocks), np.int64)
    for j in range(rows + 1):
        row = prev[min(max(j + dy, 0), oh - 1) + y0]
        for c in range(blocks):
            left[j, c] = _row_sum(row, x0, ow, c * bw + dx, (c + 1) * bw + dx)
            right[j, c] = _row_sum(row, x0, ow, c * bw + dx + 1, (c + 1) * bw + dx + 1)
    ma = np.zeros((blocks, blocks))
    mb = np.zeros((blocks, blocks))
    for r in range(blocks):
        for y in range(r * bh, (r + 1) * bh):
            seen = curr[y0 + y + iy]
            for c in range(blocks):
                ma[r, c] += ((1.0 - ty) * ((1.0 - tx) * left[y, c] + tx * right[y, c])
                             + ty * ((1.0 - tx) * left[y + 1, c] + tx * right[y + 1, c]))
                mb[r, c] += _row_sum(seen, x0 + ix, ow, c * bw, (c + 1) * bw)
    n = float(bw * bh)
    before = 0.0
    after = 0.0
    for r in range(blocks):
        for c in range(blocks):
            a = ma[r, c] / n
            b = mb[r, c] / n
            before += (b - a) ** 2
            after += (b - (gain * a + offset)) ** 2
    return after <= 0.25 * before


@nb.njit(cache=True, nogil=True, inline="always")
def _row_sum(row, x0, width, lo, hi):  # pragma: no cover - numba
    """Sum of ``row[x0 + clamp(x)]`` for x in [lo, hi), clamp(x) within [0, width): the
    row's part from x0, its ends repeated beyond it."""
    s = np.int64(0)
    a = max(lo, 0)
    part = row[x0 + a:x0 + max(min(hi, width), a)]  # a slice: no wraparound test an index
    for i in range(part.shape[0]):
        s += part[i]
    if lo < 0:
        s += (min(hi, 0) - lo) * np.int64(row[x0])
    if hi > width:
        s += (hi - max(lo, width)) * np.int64(row[x0 + width - 1])
    return s


def warm() -> None:
    """Compile (or load) this module's kernels: :func:`_explains` runs only on a frame whose
    exposure seems to change, which a warm-up's frames need not show."""
    from .pyramid import build_pyramid

    pyr = build_pyramid(np.zeros((16, 16), np.uint8), 1)
    _explains(pyr.data, pyr.data, pyr.geo, 0, 0, 0, 0.25, -0.25, 1.0, 0.0, BLOCKS)
    _scale_rows(pyr.data, pyr.geo, np.arange(ROW_BANDS, dtype=np.float64), np.ones(ROW_BANDS),
                np.empty_like(pyr.data))
