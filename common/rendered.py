"""Long sequences rendered from real frames by known smooth homographies, with exact ground truth.

The Middlebury pairs (:mod:`.groundtruth`) hold one step of motion each. To measure large
motion and long-run drift, a real frame is viewed through a moving virtual camera: frame k is
the source warped by a homography M_k (source px -> frame px), so a point p of frame j lies at
``M_k M_j^-1 p`` in frame k, exactly, for any p. The camera's motion is smooth (sums of
sinusoids): its translation speed sweeps from standing still up to ``max_step`` px a frame
(12 by default), with a little rotation (a few degrees), zoom (a few percent) and perspective.
The view never leaves the source image, so no frame shows a border or a reflection.

Shared by the accuracy benchmark (``vistrack bench accuracy``) and the tests. Pure numpy and
OpenCV; deterministic for a given seed.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import cv2
import numpy as np

from . import groundtruth

#: The Middlebury sequences whose frame10 the scoreboard's long sequences are rendered from.
SOURCES = ("Dimetrodon", "RubberWhale", "Venus", "Grove2", "Urban2")


@dataclass(frozen=True, eq=False)
class RenderedSequence:
    """Frames rendered from one source image, and the homography of each.

    Attributes
    ----------
    name : what it was rendered from.
    frames : list of (H, W) uint8 frames.
    homographies : (n, 3, 3) float64; ``homographies[k]`` maps source px to frame k's px.
    """

    name: str
    frames: list[np.ndarray]
    homographies: np.ndarray

    def __len__(self) -> int:
        return len(self.frames)

    def map(self, points: np.ndarray, src: int, dst: int) -> np.ndarray:
        """The true positions in frame ``dst`` of points (N, 2) x, y of frame ``src``, px."""
        pts = np.asarray(points, np.float64).reshape(-1, 2)
        h = self.homographies[dst] @ np.linalg.inv(self.homographies[src])
        q = np.hstack([pts, np.ones((len(pts), 1))]) @ h.T
        return q[:, :2] / q[:, 2:3]


def _about(center: tuple[float, float], m: np.ndarray) -> np.ndarray:
    """``m`` applied about ``center`` instead of the origin."""
    cx, cy = center
    t = np.array([[1.0, 0.0, cx], [0.0, 1.0, cy], [0.0, 0.0, 1.0]])
    ti = np.array([[1.0, 0.0, -cx], [0.0, 1.0, -cy], [0.0, 0.0, 1.0]])
    return t @ m @ ti


def _smooth(rng: np.random.Generator, t: np.ndarray, omega: float) -> np.ndarray:
    """A smooth path in [-1, 1]: two sinusoids of random phase, the second 1.7x as fast."""
    a = np.sin(omega * t + rng.uniform(0, 2 * np.pi))
    b = np.sin(1.7 * omega * t + rng.uniform(0, 2 * np.pi))
    path = 0.7 * a + 0.3 * b
    return path / max(float(np.abs(path).max()), 1e-9)


def homographies(source_size: tuple[int, int], size: tuple[int, int], n: int, *,
                 max_step: float = 12.0, rotation_deg: float = 3.0, zoom: float = 0.04,
                 tilt: float = 0.02, travel: float = 0.2, seed: int = 0) -> np.ndarray:
    """The camera path: (n, 3, 3) homographies, source px -> frame px.

    Parameters
    ----------
    source_size, size : (width, height) of the source image and of the frames, px.
    n : frames.
    max_step : the fastest translation of the view, px a frame: the frame centre's largest
        displacement between two frames; the speed sweeps from about 0 up to it.
    rotation_deg : largest rotation of the view about its centre, degrees (either way).
    zoom : largest zoom, as a fraction (the view is scaled within 1 -/+ zoom).
    tilt : largest perspective: a frame's corner moves by up to about this fraction of its
        distance to the centre from the perspective terms alone.
    travel : farthest the view's centre goes from the source's, as a fraction of the frame's
        size along each axis (less where the source has less room).
    seed : the path's random phases.

    The translation spans the largest box that keeps every frame's view inside the source
    (2 px in) whatever the rotation, zoom and tilt of the moment; its frequency is then set so
    that the peak speed is ``max_step``.

    Raises
    ------
    ValueError
        If the frame does not fit in the source with the rotation, zoom and tilt asked for.
    """
    sw, sh = source_size
    w, h = size
    rng = np.random.default_rng(seed)
    t = np.arange(n, dtype=np.float64)
    centre_v = ((w - 1) / 2.0, (h - 1) / 2.0)
    centre_s = ((sw - 1) / 2.0, (sh - 1) / 2.0)
    corners = np.array([[0, 0, 1], [w - 1, 0, 1], [w - 1, h - 1, 1], [0, h - 1, 1]], np.float64)
    # slow paths for rotation, zoom and tilt (a period of ~60 frames)
    rot = np.deg2rad(rotation_deg) * _smooth(rng, t, 0.1)
    scl = np.exp(np.log1p(zoom) * _smooth(rng, t, 0.1))
    px = tilt / (0.5 * w) * _smooth(rng, t, 0.1)
    py = tilt / (0.5 * h) * _smooth(rng, t, 0.1)
    phases = rng.uniform(0, 2 * np.pi, 4)

    def local(k: int) -> np.ndarray:
        """Frame k's px -> source px about the view centre, before the translation."""
        c, s = np.cos(rot[k]), np.sin(rot[k])
        rs = np.array([[c / scl[k], -s / scl[k], 0.0], [s / scl[k], c / scl[k], 0.0],
                       [0.0, 0.0, 1.0]])
        persp = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [px[k], py[k], 1.0]])
        return _about(centre_v, rs @ persp)

    def shift(x: float, y: float) -> np.ndarray:
        return np.array([[1.0, 0.0, centre_s[0] - centre_v[0] + x],
                         [0.0, 1.0, centre_s[1] - centre_v[1] + y], [0.0, 0.0, 1.0]])

    def fits(ax: float, ay: float) -> bool:
        # every frame at every corner of the translation box: the path stays inside it
        for k in range(n):
            lk = local(k)
            for sx in (-1.0, 1.0):
                for sy in (-1.0, 1.0):
                    q = corners @ (shift(sx * ax, sy * ay) @ lk).T
                    q = q[:, :2] / q[:, 2:3]
                    if q.min() < 2 or q[:, 0].max() > sw - 3 or q[:, 1].max() > sh - 3:
                        return False
        return True

    if not fits(0.0, 0.0):
        raise ValueError(f"a {w}x{h} frame with rotation {rotation_deg} deg, zoom {zoom} and "
                         f"tilt {tilt} does not fit in the {sw}x{sh} source")
    # the view wanders at most a fifth of its size from the middle, so that many of the first
    # frame's features stay in view through the whole sequence and their drift is measured
    mx = min(max(sw - w, 0) / 2.0, travel * w)
    my = min(max(sh - h, 0) / 2.0, travel * h)
    lo, hi = 0.0, 1.0
    for _ in range(20):  # the largest box, in proportion to the margins, that fits
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if fits(mid * mx, mid * my) else (lo, mid)
    ax, ay = lo * mx, lo * my

    def build(omega: float) -> np.ndarray:
        # the view centre's path in the source: two sinusoids an axis, in the box
        x = ax * (0.75 * np.sin(omega * t + phases[0]) + 0.25 * np.sin(0.61 * omega * t
                                                                        + phases[1]))
        y = ay * (0.75 * np.sin(0.83 * omega * t + phases[2]) + 0.25 * np.sin(0.47 * omega * t
                                                                               + phases[3]))
        return np.stack([np.linalg.inv(shift(x[k], y[k]) @ local(k)) for k in range(n)])

    def peak(hs: np.ndarray) -> float:
        c = np.array([centre_v[0], centre_v[1], 1.0])
        steps = []
        for k in range(n - 1):
            q = hs[k + 1] @ np.linalg.inv(hs[k]) @ c
            steps.append(np.hypot(q[0] / q[2] - c[0], q[1] / q[2] - c[1]))
        return max(steps, default=0.0)

    omega = max_step / max(ax, ay, 1e-9)
    hs = build(omega)
    for _ in range(8):  # the speed grows about in proportion to omega
        got = peak(hs)
        if got <= 0 or abs(got - max_step) < 0.01:
            break
        omega *= max_step / got
        hs = build(omega)
    return hs


def render(source: np.ndarray, hs: np.ndarray, size: tuple[int, int], *, noise: float = 1.0,
           seed: int = 0) -> list[np.ndarray]:
    """Frames of ``source`` (grey uint8) seen through homographies ``hs`` (source -> frame),
    ``size`` (width, height), bicubic, with Gaussian noise of ``noise`` grey levels (a camera's
    own; 0 for none), rounded to uint8."""
    rng = np.random.default_rng(seed)
    src = source.astype(np.float32)
    frames = []
    for m in hs:
        f = cv2.warpPerspective(src, m, size, flags=cv2.INTER_CUBIC,
                                borderMode=cv2.BORDER_REFLECT)
        if noise > 0:
            f = f + np.float32(noise) * rng.standard_normal(f.shape, dtype=np.float32)
        frames.append(np.ascontiguousarray(np.clip(np.rint(f), 0, 255), dtype=np.uint8))
    return frames


def sequence(source: np.ndarray, name: str, *, n: int = 60, size: tuple[int, int] = (256, 256),
             max_step: float = 12.0, noise: float = 1.0, seed: int | None = None,
             rotation_deg: float = 3.0, zoom: float = 0.04, tilt: float = 0.02
             ) -> RenderedSequence:
    """A long sequence of ``n`` frames rendered from one grey ``source`` image.

    ``seed`` defaults to one derived from ``name``, so a sequence is the same on every run.
    See :func:`homographies` for the path (``max_step`` px a frame at the fastest, and the
    largest ``rotation_deg``, ``zoom`` and ``tilt``).
    """
    if seed is None:
        seed = zlib.crc32(name.encode())
    hs = homographies((source.shape[1], source.shape[0]), size, n, max_step=max_step,
                      rotation_deg=rotation_deg, zoom=zoom, tilt=tilt, seed=seed)
    return RenderedSequence(name, render(source, hs, size, noise=noise, seed=seed + 1), hs)


def jerk(source: np.ndarray, name: str, *, steady: tuple[float, float] = (3.3, 1.2),
         jump: tuple[float, float] = (44.6, -15.3), before: int = 8, after: int = 8,
         size: tuple[int, int] = (256, 256), noise: float = 1.0, seed: int | None = None
         ) -> RenderedSequence:
    """A view that moves by ``steady`` px a frame for ``before`` frames, by ``jump`` px in
    one frame (a bump, a frame dropped at speed), then by ``steady`` again for ``after``
    frames: every feature's constant-velocity prediction breaks twice, at the jump and at the
    step back. Translations only, the path centred in the source.

    Raises
    ------
    ValueError
        If the source has no room for the path.
    """
    steps = [np.array(steady, np.float64)] * before + [np.array(jump, np.float64)] \
        + [np.array(steady, np.float64)] * after
    scene = np.cumsum([np.zeros(2), *steps], axis=0)  # where the scene has moved to
    view = -scene  # the view's top-left corner in the source, before centring
    sw, sh = source.shape[1], source.shape[0]
    span = view.max(axis=0) - view.min(axis=0) + np.array(size, np.float64)
    if span[0] > sw - 4 or span[1] > sh - 4:
        raise ValueError(f"{name}: a {sw}x{sh} source has no room for a {size[0]}x{size[1]} "
                         f"view travelling {span[0] - size[0]:.0f}x{span[1] - size[1]:.0f} px")
    view += (np.array([sw, sh], np.float64) - span) / 2.0 - view.min(axis=0)
    hs = np.array([[[1.0, 0.0, -x], [0.0, 1.0, -y], [0.0, 0.0, 1.0]] for x, y in view])
    if seed is None:
        seed = zlib.crc32(name.encode()) + 21
    return RenderedSequence(f"{name}, jerk", render(source, hs, size, noise=noise, seed=seed),
                            hs)


def approach(source: np.ndarray, name: str, *, rate: float = 1.1, n: int = 12,
             size: tuple[int, int] = (256, 256), noise: float = 1.0, seed: int | None = None
             ) -> RenderedSequence:
    """A view zooming in by ``rate`` a frame about the source's centre: the camera moving
    towards the scene (forward driving at a low frame rate), the features near the frame's
    edges moving fastest. The first frame's view is the largest the source holds."""
    sw, sh = source.shape[1], source.shape[0]
    w, h = size
    s0 = max(w / (sw - 4.0), h / (sh - 4.0))  # frame px per source px at frame 0
    cs = ((sw - 1) / 2.0, (sh - 1) / 2.0)
    cv = ((w - 1) / 2.0, (h - 1) / 2.0)
    hs = []
    for k in range(n):
        s = s0 * rate ** k
        hs.append([[s, 0.0, cv[0] - s * cs[0]], [0.0, s, cv[1] - s * cs[1]], [0.0, 0.0, 1.0]])
    if seed is None:
        seed = zlib.crc32(name.encode()) + 31
    return RenderedSequence(f"{name}, approach", render(source, np.array(hs), size,
                                                        noise=noise, seed=seed), np.array(hs))


def roll(source: np.ndarray, name: str, *, rate_deg: float = 3.0, n: int = 30,
         size: tuple[int, int] = (256, 256), noise: float = 1.0, seed: int | None = None
         ) -> RenderedSequence:
    """A view turning about its centre by ``rate_deg`` degrees a frame: a camera that rolls,
    or one looking down at the floor from a robot turning on the spot (90 degrees a second is
    3 a frame at 30 fps). A point r px from the centre moves r times the angle a frame (6.7
    px at 128 px and 3 degrees), each feature's window turns with it. The view is centred in
    the source, which must hold its diagonal.

    Raises
    ------
    ValueError
        If the source cannot hold the turning view.
    """
    sw, sh = source.shape[1], source.shape[0]
    w, h = size
    if np.hypot(w, h) > min(sw, sh) - 4:
        raise ValueError(f"{name}: a {sw}x{sh} source cannot hold a {w}x{h} view turning "
                         f"(its diagonal is {np.hypot(w, h):.0f} px)")
    cs = ((sw - 1) / 2.0, (sh - 1) / 2.0)
    cv = ((w - 1) / 2.0, (h - 1) / 2.0)
    hs = []
    for k in range(n):
        a = np.deg2rad(rate_deg * k)
        c, s = np.cos(a), np.sin(a)
        # frame = cv + R(a) (source - cs)
        hs.append([[c, -s, cv[0] - c * cs[0] + s * cs[1]],
                   [s, c, cv[1] - s * cs[0] - c * cs[1]], [0.0, 0.0, 1.0]])
    if seed is None:
        seed = zlib.crc32(name.encode()) + 37
    return RenderedSequence(f"{name}, roll", render(source, np.array(hs), size, noise=noise,
                                                    seed=seed), np.array(hs))


def shake(source: np.ndarray, name: str, *, jolt_px: float = 6.0, jolt_deg: float = 2.0,
          n: int = 30, size: tuple[int, int] = (256, 256), noise: float = 1.0,
          seed: int | None = None) -> RenderedSequence:
    """A slow path (up to 4 px a frame) seen by a camera that shakes: each frame moved by up
    to ``jolt_px`` px along each axis and turned by up to ``jolt_deg`` degrees about its
    centre, at random and independently of the frame before (a camera on a vibrating mount,
    a robot on a rough floor, a hand). From frame to frame a point then moves by up to twice
    as much either way, so a constant-velocity prediction is off by up to three times the
    jolt: at 6 px, 12 px at the median. Jolts and noise are drawn from ``seed`` (by default
    one per name).

    Raises
    ------
    ValueError
        If the source has no room for the path.
    """
    if seed is None:
        seed = zlib.crc32(name.encode()) + 53
    rng = np.random.default_rng(seed + 2)
    path = homographies((source.shape[1], source.shape[0]), size, n, max_step=4.0, seed=3,
                        travel=0.1)
    cx, cy = (size[0] - 1) / 2.0, (size[1] - 1) / 2.0
    jolted = []
    for h in path:
        t, a = rng.uniform(-jolt_px, jolt_px, 2), np.deg2rad(rng.uniform(-jolt_deg, jolt_deg))
        c, s = np.cos(a), np.sin(a)
        jolt = np.array([[c, -s, t[0] + cx - c * cx + s * cy],
                         [s, c, t[1] + cy - s * cx - c * cy], [0.0, 0.0, 1.0]])
        jolted.append(jolt @ h)
    hs = np.array(jolted)
    # the jolted views' corners, in the source: inside it, or the frames would show its edge
    w, h = size
    corners = np.array([[0.0, 0.0, 1.0], [w - 1.0, 0.0, 1.0], [0.0, h - 1.0, 1.0],
                        [w - 1.0, h - 1.0, 1.0]])
    q = np.einsum("kij,cj->kci", np.linalg.inv(hs), corners)
    q = q[..., :2] / q[..., 2:]
    sw, sh = source.shape[1], source.shape[0]
    if q[..., 0].min() < 0 or q[..., 1].min() < 0 or q[..., 0].max() > sw - 1 \
            or q[..., 1].max() > sh - 1:
        raise ValueError(f"{name}: a {sw}x{sh} source has no room for a {w}x{h} view jolted by "
                         f"{jolt_px:g} px and {jolt_deg:g} degrees")
    return RenderedSequence(f"{name}, shake", render(source, hs, size, noise=noise, seed=seed),
                            hs)


def _line_kernel(dx: float, dy: float) -> np.ndarray:
    """The normalised kernel of a straight motion (dx, dy) px during an exposure, centred:
    the mean of the image shifted along the motion, sampled every quarter pixel."""
    half = max(1, int(np.ceil(0.5 * max(abs(dx), abs(dy)))))
    k = np.zeros((2 * half + 1, 2 * half + 1), np.float32)
    steps = 4 * int(np.ceil(np.hypot(dx, dy))) + 1
    for t in np.linspace(-0.5, 0.5, steps):
        k[int(round(half + t * dy)), int(round(half + t * dx))] += 1.0
    return k / k.sum()


def motion_blurred(source: np.ndarray, name: str, *, exposure: float, n: int = 40,
                   size: tuple[int, int] = (256, 256), max_step: float = 12.0,
                   noise: float = 1.0, seed: int | None = None) -> RenderedSequence:
    """:func:`sequence`'s path seen by a camera whose shutter stays open for ``exposure``
    (0..1) of the frame interval: each frame is blurred along the view's motion at its centre
    during the exposure (from half-way to the frame before to half-way to the frame after,
    times ``exposure``), then gets its noise. The blur is centred on the frame's own time, so
    the ground truth (the homographies) is unchanged. One kernel a frame: the rotation and
    zoom's part of the blur, which varies across the frame, is left out."""
    if not 0.0 <= exposure <= 1.0:
        raise ValueError(f"exposure={exposure} is out of range: allowed 0..1")
    sharp = sequence(source, name, n=n, size=size, max_step=max_step, noise=0.0, seed=seed)
    rng = np.random.default_rng(zlib.crc32(name.encode()) + 11 if seed is None else seed + 11)
    centre = np.array([[(size[0] - 1) / 2.0, (size[1] - 1) / 2.0]])
    frames = []
    for k, f in enumerate(sharp.frames):
        before = sharp.map(centre, k, max(k - 1, 0))[0]
        after = sharp.map(centre, k, min(k + 1, n - 1))[0]
        dx, dy = (after - before) * 0.5 * exposure
        out = cv2.filter2D(f.astype(np.float32), -1, _line_kernel(dx, dy),
                           borderType=cv2.BORDER_REFLECT)
        if noise > 0:
            out = out + np.float32(noise) * rng.standard_normal(out.shape, dtype=np.float32)
        frames.append(np.ascontiguousarray(np.clip(np.rint(out), 0, 255), dtype=np.uint8))
    return RenderedSequence(f"{name}, blur {exposure:g}", frames, sharp.homographies)


def middlebury_sources(names: tuple[str, ...] = SOURCES) -> list[tuple[str, np.ndarray]]:
    """(name, grey frame10) of each Middlebury sequence found (:data:`SOURCES`); empty when
    the shared data is absent."""
    out = []
    for name in names:
        folder = groundtruth.middlebury(name)
        if folder is None:
            continue
        image = cv2.imread(str(folder / "frame10.png"), cv2.IMREAD_GRAYSCALE)
        if image is not None:
            out.append((name, image))
    return out


def middlebury_sequences(n: int = 60, *, size: tuple[int, int] = (256, 256),
                         names: tuple[str, ...] = SOURCES) -> list[RenderedSequence]:
    """A long sequence from frame10 of each Middlebury sequence found (:data:`SOURCES`);
    empty when the shared data is absent."""
    return [sequence(image, f"{name} rendered", n=n, size=size)
            for name, image in middlebury_sources(names)]


def with_exposure(seq: RenderedSequence, *, gain: float = 0.08, offset: float = 10.0,
                  seed: int | None = None) -> RenderedSequence:
    """``seq`` seen by a camera whose auto-exposure hunts: every frame but the first gets its
    own gain, uniform in 1 +- ``gain``, and offset, uniform in +- ``offset`` grey levels
    (rounded, clipped to 0..255). The geometry, and so the ground truth, is ``seq``'s."""
    rng = np.random.default_rng(zlib.crc32(seq.name.encode()) + 7 if seed is None else seed)
    frames = [seq.frames[0]]
    for f in seq.frames[1:]:
        g = 1.0 + rng.uniform(-gain, gain)
        b = rng.uniform(-offset, offset)
        frames.append(np.clip(np.rint(f.astype(np.float32) * np.float32(g) + np.float32(b)),
                              0, 255).astype(np.uint8))
    return RenderedSequence(f"{seq.name}, exposure", frames, seq.homographies)


@dataclass(frozen=True, eq=False)
class LensSequence(RenderedSequence):
    """A :class:`RenderedSequence` seen through a lens with radial (barrel) distortion
    (:func:`with_lens`); ``map`` goes through the lens both ways, exactly up to the
    inversion's 1e-9 px."""

    k: float = 0.0

    def _scale(self, r2: np.ndarray, corner2: float) -> np.ndarray:
        return (1.0 + self.k * r2) / (1.0 + self.k * corner2)

    def _geometry(self) -> tuple[np.ndarray, float, float]:
        h, w = self.frames[0].shape
        c = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
        f = max(w, h) / 2.0
        return c, f, float(((c / f) ** 2).sum())

    def ideal(self, points: np.ndarray) -> np.ndarray:
        """Where points (N, 2) of the lens's frames lie in the undistorted view."""
        c, f, corner2 = self._geometry()
        q = (np.asarray(points, np.float64).reshape(-1, 2) - c) / f
        return c + f * q * self._scale((q ** 2).sum(axis=1, keepdims=True), corner2)

    def seen(self, points: np.ndarray) -> np.ndarray:
        """Where points (N, 2) of the undistorted view appear through the lens (the inverse
        of :meth:`ideal`, by Newton's method on the radius: monotonic for k >= 0)."""
        c, f, corner2 = self._geometry()
        u = (np.asarray(points, np.float64).reshape(-1, 2) - c) / f
        ru = np.sqrt((u ** 2).sum(axis=1, keepdims=True)) * (1.0 + self.k * corner2)
        rd = ru / (1.0 + self.k * corner2)
        for _ in range(50):
            step = (rd + self.k * rd ** 3 - ru) / (1.0 + 3.0 * self.k * rd ** 2)
            rd = rd - step
            if np.abs(step).max(initial=0.0) < 1e-12:
                break
        ratio = np.where(ru > 0, rd / np.maximum(ru, 1e-300), 1.0 / (1.0 + self.k * corner2))
        return c + f * u * ratio * (1.0 + self.k * corner2)

    def map(self, points: np.ndarray, src: int, dst: int) -> np.ndarray:
        return self.seen(super().map(self.ideal(points), src, dst))


def with_lens(seq: RenderedSequence, k: float = 0.25) -> LensSequence:
    """``seq`` seen through a wide-angle lens: barrel distortion, the point at radius r of the
    lens's frame (in half-widths from its centre) seen where the undistorted view has it at
    r (1 + k r^2), scaled so that the corners stay where they were. The view's centre is then
    magnified by about 1 + 2k and its edges compressed (k 0.25: 1.5 times), and the frames sample
    only the undistorted view, so they show no border. Each frame is resampled (bicubic); the
    ground truth is exact.

    Raises
    ------
    ValueError
        If ``k`` is negative or not finite (pincushion is not modelled).
    """
    if not (np.isfinite(k) and k >= 0.0):
        raise ValueError(f"k={k!r}: the lens's distortion must be finite and >= 0")
    h, w = seq.frames[0].shape
    out = LensSequence(f"{seq.name}, lens {k:g}", list(seq.frames), seq.homographies, k)
    ys, xs = np.mgrid[0:h, 0:w]
    where = out.ideal(np.column_stack([xs.ravel(), ys.ravel()]))
    mx = where[:, 0].reshape(h, w).astype(np.float32)
    my = where[:, 1].reshape(h, w).astype(np.float32)
    for i, f in enumerate(seq.frames):
        g = cv2.remap(f.astype(np.float32), mx, my, cv2.INTER_CUBIC,
                      borderMode=cv2.BORDER_REPLICATE)
        out.frames[i] = np.clip(np.rint(g), 0, 255).astype(np.uint8)
    return out


def _rows_at(hs: np.ndarray, k: int, y: np.ndarray, per_row: float) -> np.ndarray:
    """The homographies (N, 3, 3) of rows ``y`` (N,) of frame k, each exposed ``per_row`` of
    a frame interval after the row above: interpolated between ``hs[k]`` and ``hs[k + 1]``."""
    f = per_row * np.asarray(y, np.float64).reshape(-1)
    return (1.0 - f)[:, None, None] * hs[k] + f[:, None, None] * hs[k + 1]


@dataclass(frozen=True, eq=False)
class RollingShutterSequence(RenderedSequence):
    """A :class:`RenderedSequence` seen by a rolling shutter (:func:`with_rolling_shutter`):
    row y of frame k is exposed at k + ``readout`` y / H frame intervals, where the camera's
    homography is interpolated linearly between ``homographies[k]`` and ``[k + 1]`` (one more
    homography than frames). ``map`` finds each point's row in the destination frame by a
    fixed-point iteration, exact to 1e-9 px."""

    readout: float = 0.0

    def at(self, k: int, y: np.ndarray) -> np.ndarray:
        """The homographies (N, 3, 3), source px -> frame px, of rows ``y`` (N,) of frame k."""
        return _rows_at(self.homographies, k, y, self.readout / self.frames[0].shape[0])

    def to_source(self, points: np.ndarray, k: int) -> np.ndarray:
        """The source's points (N, 2) seen at ``points`` (N, 2) of frame k."""
        p = np.asarray(points, np.float64).reshape(-1, 2)
        s = np.einsum("nij,nj->ni", np.linalg.inv(self.at(k, p[:, 1])),
                      np.column_stack([p, np.ones(len(p))]))
        return s[:, :2] / s[:, 2:3]

    def from_source(self, source_points: np.ndarray, k: int) -> np.ndarray:
        """Where the source's points (N, 2) are seen in frame k: the row that sees a point is
        the row the homography of its own moment puts it in."""
        src = np.asarray(source_points, np.float64).reshape(-1, 2)
        s = np.column_stack([src, np.ones(len(src))])
        q = s @ self.homographies[k].T
        q = q[:, :2] / q[:, 2:3]
        for _ in range(100):
            r = np.einsum("nij,nj->ni", self.at(k, q[:, 1]), s)
            nq = r[:, :2] / r[:, 2:3]
            done = np.abs(nq - q).max(initial=0.0) < 1e-10
            q = nq
            if done:
                break
        return q

    def map(self, points: np.ndarray, src: int, dst: int) -> np.ndarray:
        return self.from_source(self.to_source(points, src), dst)


def with_rolling_shutter(source: np.ndarray, seq: RenderedSequence, readout: float = 0.9, *,
                         noise: float = 1.0, seed: int | None = None
                         ) -> RollingShutterSequence:
    """``seq``'s camera path seen by a CMOS camera whose rolling shutter reads its rows out
    over ``readout`` of the frame interval (0: a global shutter; 1: the whole interval): row
    y of frame k sees the scene at k + readout y / H, where a camera that shakes has moved on.
    Rendered again from ``source`` (grey uint8, what ``seq`` was rendered from), bicubic, with
    Gaussian noise of ``noise`` grey levels drawn from ``seed`` (by default one per name):
    ``len(seq) - 1`` frames, the last homography giving the last frame's later rows. The
    ground truth is exact (:meth:`RollingShutterSequence.map`).

    Raises
    ------
    ValueError
        If ``readout`` is not within 0 to 1, or ``seq`` has fewer than two frames.
    """
    if not (np.isfinite(readout) and 0.0 <= readout <= 1.0):
        raise ValueError(f"readout={readout!r}: the rows' readout must be 0 to 1 of the frame "
                         f"interval")
    if len(seq) < 2:
        raise ValueError(f"{seq.name}: a rolling shutter needs two frames or more, got "
                         f"{len(seq)}")
    h, w = seq.frames[0].shape
    out = RollingShutterSequence(f"{seq.name}, rolling shutter {readout:g}", [],
                                 seq.homographies, readout)
    rng = np.random.default_rng(zlib.crc32(out.name.encode()) if seed is None else seed)
    src = source.astype(np.float32)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    pix = np.stack([xs, ys, np.ones_like(xs)], axis=-1)  # (h, w, 3)
    for k in range(len(seq) - 1):
        inv = np.linalg.inv(_rows_at(out.homographies, k, np.arange(h), readout / h))
        s = np.einsum("yij,yxj->yxi", inv, pix)
        mx = (s[..., 0] / s[..., 2]).astype(np.float32)
        my = (s[..., 1] / s[..., 2]).astype(np.float32)
        f = cv2.remap(src, mx, my, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
        if noise > 0:
            f = f + np.float32(noise) * rng.standard_normal(f.shape, dtype=np.float32)
        out.frames.append(np.ascontiguousarray(np.clip(np.rint(f), 0, 255), dtype=np.uint8))
    return out
