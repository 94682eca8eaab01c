"""Generated scenes: the built-in textured target and moving sequences with known motion.

The built-in default of ``vistrack track`` and the file camera, and the texture of the robot
simulator, so the project runs with no data of its own. Pure numpy/OpenCV.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


def texture(size: int = 512, *, seed: int = 0) -> np.ndarray:
    """A well-textured, real-looking grey image: multi-scale noise plus shapes with edges.

    Returns
    -------
    (size, size) uint8 array.
    """
    if size < 16:
        raise ValueError(f"size={size} is too small: allowed 16 or more")
    rng = np.random.default_rng(seed)
    img = np.zeros((size, size), np.float32)
    # 1/f-like noise: octaves of upsampled random fields
    for octave, amp in ((4, 1.0), (8, 0.7), (16, 0.5), (32, 0.4), (64, 0.3), (128, 0.2)):
        cells = max(2, size * octave // 512)
        field = rng.standard_normal((cells, cells)).astype(np.float32)
        img += amp * cv2.resize(field, (size, size), interpolation=cv2.INTER_CUBIC)
    img = (img - img.min()) / max(float(np.ptp(img)), 1e-6) * 140 + 40
    # shapes give the strong, well-localised corners and edges that features lock on to
    for _ in range(size // 2):
        colour = float(rng.uniform(0, 255))
        cx, cy = (int(v) for v in rng.integers(0, size, 2))
        r = int(rng.integers(max(2, size // 160), max(3, size // 40)))
        if rng.random() < 0.5:
            cv2.circle(img, (cx, cy), r, colour, -1, lineType=cv2.LINE_AA)
        else:
            w, h = (int(v) for v in rng.integers(r, 3 * r, 2))
            cv2.rectangle(img, (cx, cy), (cx + w, cy + h), colour, -1)
    img += rng.normal(0, 3, img.shape).astype(np.float32)  # sensor-like grain
    return np.clip(img, 0, 255).astype(np.uint8)


@dataclass(frozen=True)
class Motion:
    """Per-frame image motion of a generated sequence: shift in px and scale factor."""

    dx: float = 0.0
    dy: float = 0.0
    scale: float = 1.0


def warp(image: np.ndarray, *, dx: float = 0.0, dy: float = 0.0, scale: float = 1.0,
         center: tuple[float, float] | None = None,
         out_size: tuple[int, int] | None = None) -> np.ndarray:
    """Scale ``image`` by ``scale`` about ``center`` then shift by (dx, dy) px.

    A point p of ``image`` lands at ``center + scale * (p - center) + (dx, dy)`` of the result
    (cropped to ``out_size`` = (width, height), default the input size).
    """
    h, w = image.shape[:2]
    cx, cy = center if center is not None else ((w - 1) / 2.0, (h - 1) / 2.0)
    m = np.array([[scale, 0.0, cx - scale * cx + dx],
                  [0.0, scale, cy - scale * cy + dy]], np.float64)
    size = out_size if out_size is not None else (w, h)
    return cv2.warpAffine(image, m, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


def sequence(n: int = 30, *, size: tuple[int, int] = (256, 256),
             motion: Motion | list[Motion] = Motion(dx=1.5, dy=0.0),
             seed: int = 0) -> list[np.ndarray]:
    """``n`` frames of the textured scene moving by ``motion`` each frame.

    The scene is cut from the middle of a texture twice the frame size, so motion brings new
    texture into view instead of a border. ``motion`` may be one Motion for every step or a list
    of n - 1 steps. Returns a list of (height, width) uint8 frames.
    """
    if n < 1:
        raise ValueError(f"n={n} must be at least 1")
    w, h = size
    big = texture(2 * max(w, h), seed=seed)
    steps = motion if isinstance(motion, list) else [motion] * (n - 1)
    if len(steps) != n - 1:
        raise ValueError(f"motion has {len(steps)} steps: need n - 1 = {n - 1}")
    bh, bw = big.shape
    # the frame shows big[oy:oy+h, ox:ox+w] at rest
    ox, oy = (bw - w) / 2.0, (bh - h) / 2.0
    centre = (bw / 2.0, bh / 2.0)
    frames = []
    x = y = 0.0
    s = 1.0
    for i in range(n):
        if i:
            x += steps[i - 1].dx
            y += steps[i - 1].dy
            s *= steps[i - 1].scale
        full = warp(big, dx=x, dy=y, scale=s, center=centre)
        frames.append(np.ascontiguousarray(full[int(oy):int(oy) + h, int(ox):int(ox) + w]))
    return frames


def builtin_sequence(n: int = 60) -> list[np.ndarray]:
    """The built-in demo sequence: 256x256, a sideways sweep then an approach and a recede."""
    third = max(1, (n - 1) // 3)
    steps = ([Motion(dx=1.5)] * third + [Motion(scale=1.01)] * third
             + [Motion(dx=-1.0, scale=0.99)] * (n - 1 - 2 * third))
    return sequence(n, motion=steps, seed=7)
