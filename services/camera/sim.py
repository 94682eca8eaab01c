"""The robot simulator: a holonomic robot with a camera, a moving textured target, a background.

The paper's experiments ran on "a robot simulator, validated by comparing the speed curve obtained
with the simulator and a physical mobile robot, a NOMAD XR4000 with a monocular camera". This is
ours: rigid-body kinematics with velocity and acceleration limits, and a pinhole camera rendering
two textured planes by homography. Pure numpy/OpenCV: no Zenoh, no msgpack; the camera service
drives it with ``control/cmd_vel`` and publishes :meth:`Simulator.render` and
:meth:`Simulator.pose` (``sim/pose``).

Conventions
-----------
World frame W (right-handed, metres): origin at the robot's start position at camera height,
``x`` forward (the start heading), ``y`` to the left, ``z`` up. The target's centre is at camera
height (z = 0), so the robot only has to correct x, y and yaw. Top view::

        y (left)
        ^                 target plane x = tx            background plane x = 6 m
        |                        |                                |
        |            ty  . . . . + target centre (tx, ty)         |
        |          x_R           |                                |
        |          /             |                                |
        |         /  theta       |                                |
        |   (x, y) R - - - - - - | - - - - - - - - - - - - - - - -|
        |                        |                                |
        o----------------------------------------------------------> x (forward)
        W: origin = the robot's start pose (theta = 0); z up, out of the page.
        R: the robot; its camera looks along the robot's own +x (x_R), theta = yaw from W's
        +x, counter-clockwise positive.

Robot frame R (REP 103, as ``control/cmd_vel`` and the fuzzy controller): ``x`` forward along
the optical axis, ``y`` left, ``z`` up; ``vx``, ``vy`` in m/s, ``wz`` in rad/s, counter-clockwise
positive. Camera frame C (OpenCV): ``X`` right (= robot -y), ``Y`` down (= -z), ``Z`` forward
(= robot x); the camera sits at the robot origin. A world point P projects to

    X_C = R_CR R_WR(theta)^T (P - (x, y, 0)),    R_CR = [[0, -1, 0], [0, 0, -1], [1, 0, 0]]
    u = f X_C / Z_C + cx,   v = f Y_C / Z_C + cy,   (cx, cy) = ((width - 1) / 2, (height - 1) / 2)

Pixel centres are at integer coordinates (OpenCV's convention), so the optical axis hits the
exact image centre. A target to the left (``ty > 0``) appears left of the image centre
(smaller u); a nearer target appears bigger.

Textures: texture pixel (a, b) (column, row, centres at integers) of a plane with centre
(X0, Y0, 0) facing the robot, ``m`` metres per texture pixel, lies at
``(X0, Y0 - (a - (w - 1) / 2) m, -(b - (h - 1) / 2) m)``: the texture is seen upright and not
mirrored from the start pose. The target is ``target_size_m`` wide (its height keeps the texture's
aspect ratio); the background is :data:`BACKGROUND_SIZE_M` wide and mirrors itself beyond its
edges, so it never ends.

Rendering: for each plane the 3x3 homography texture px -> image px is ``K R_CW [e_a, e_b,
P_00 - p]`` (e_a, e_b: world steps of one texture column and row, P_00: world position of texture
pixel (0, 0), p: camera position); ``cv2.warpPerspective`` draws the background, then the target is
composited with its warped coverage mask (premultiplied alpha, so its edges are anti-aliased).
Each texture is a mip-map pyramid, blended between the two levels bracketing the current texture
density (trilinear filtering), so a far target does not alias and its look changes smoothly as
the robot approaches. Image columns whose viewing ray does not meet a plane in front of the camera
(yaw beyond the plane's horizon) are masked, not filled with the back-projected mirror image.
Then, in this order: lighting gain/offset (scenario), Gaussian blur and Gaussian noise (camera),
rounding to 8-bit grey.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from ...common import imagelimit
from ...common.synthetic import texture as synthetic_texture
from ...common.vision.preprocess import Grey
from .scenarios import Scenario, load_scenario

#: Width (and height) of the built-in background plane, m; it is mirrored beyond its edges.
BACKGROUND_SIZE_M = 16.0
#: Seeds of the built-in textures: fixed, so the simulator seed only drives the sensor noise and a
#: scene looks the same in every run.
TARGET_TEXTURE_SEED = 11
BACKGROUND_TEXTURE_SEED = 12
#: Built-in texture sizes, px: about one texture pixel per image pixel at 1 m for the target and
#: at 6 m for the background (256x256 at 60 deg); the mip-map takes care of farther views.
TARGET_TEXTURE_PX = 256
BACKGROUND_TEXTURE_PX = 1024
#: Contrast of the built-in background relative to the target. The tracker keeps the strongest
#: gradients anywhere in the frame; a wall as salient as the target would take half the features
#: and the centroid would follow the robot's own motion against it instead of the target. With the
#: default TrackerParams about 70 % of the features land on the target at 0.25 (48 % at 0.5,
#: 93 % at 0.15, where the tracker no longer finds its 100 features).
BACKGROUND_CONTRAST = 0.25
#: Camera near limit, m: a plane closer than this (or behind) is not drawn.
NEAR_M = 0.05
#: Grey level of image columns that see no plane (beyond the background's horizon).
VOID_GREY = 128.0


#: What a scenario's end may be missed by, s, the clock summing steps in floating point.
DONE_SLACK_S = 1e-6

class TextureError(ValueError):
    """A texture file is missing or unreadable, or a texture array is unusable."""


def _check(owner: str, name: str, value: Any, lo: float, hi: float, *,
           lo_open: bool = False, integer: bool = False) -> float:
    """Validate one numeric field; the error names the field, the value and the range."""
    rng = f"{'(' if lo_open else '['}{lo:g}, {hi:g}]"
    kind = "an integer" if integer else "a number"
    # bool is an int subclass: True would silently mean 1
    if isinstance(value, bool) or not isinstance(value, (int, float)) or (
            integer and not float(value).is_integer()):
        raise ValueError(f"{owner}.{name}={value!r} must be {kind} in {rng}")
    ok = (lo < value if lo_open else lo <= value) and value <= hi  # also rejects NaN
    if not ok:
        raise ValueError(f"{owner}.{name}={value!r} is out of range: allowed {rng}")
    return float(value)


# -- robot -------------------------------------------------------------------------------------

@dataclass(frozen=True)
class RobotLimits:
    """Kinematic limits of the simulated base. Defaults are plausible for a Nomad XR4000 (a
    holonomic base of about 150 kg): our choice, not datasheet values.

    Parameters
    ----------
    max_speed : float
        Translational speed limit, m/s, on the norm of (vx, vy): a diagonal command is scaled
        down keeping its direction. (0, 10]; default 1.0.
    max_accel : float
        Acceleration limit per axis (vx and vy separately), m/s^2. (0, 100]; default 1.0.
    max_yaw_rate : float
        Yaw rate limit, rad/s. (0, 20]; default 1.5 (~86 deg/s).
    max_yaw_accel : float
        Yaw acceleration limit, rad/s^2. (0, 200]; default 3.0.
    """

    max_speed: float = 1.0
    max_accel: float = 1.0
    max_yaw_rate: float = 1.5
    max_yaw_accel: float = 3.0

    def __post_init__(self) -> None:
        for name, hi in (("max_speed", 10.0), ("max_accel", 100.0), ("max_yaw_rate", 20.0),
                         ("max_yaw_accel", 200.0)):
            value = _check("RobotLimits", name, getattr(self, name), 0.0, hi, lo_open=True)
            object.__setattr__(self, name, value)


@dataclass(frozen=True)
class Command:
    """A velocity command in the robot frame: ``vx`` forward, ``vy`` left (m/s), ``wz``
    counter-clockwise (rad/s): the fields of ``control/cmd_vel``."""

    vx: float = 0.0
    vy: float = 0.0
    wz: float = 0.0

    def __post_init__(self) -> None:
        for name in ("vx", "vy", "wz"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(
                    value):
                raise ValueError(f"Command.{name}={value!r} must be a finite number")
            object.__setattr__(self, name, float(value))

    @classmethod
    def coerce(cls, cmd: Command | Mapping[str, Any]) -> Command:
        """A Command from a Command or a mapping with ``vx``, ``vy``, ``wz`` (e.g. a decoded
        ``control/cmd_vel``; other keys such as ``stale`` are ignored, missing ones are 0)."""
        if isinstance(cmd, Command):
            return cmd
        if isinstance(cmd, Mapping):
            return cls(**{k: cmd[k] for k in ("vx", "vy", "wz") if k in cmd})
        raise TypeError(f"command {cmd!r} is neither a Command nor a mapping with vx, vy, wz")


def _toward(v: float, target: float, max_change: float) -> float:
    return v + min(max(target - v, -max_change), max_change)


class Robot:
    """Holonomic base: pose (x, y, theta) in the world frame, velocity (vx, vy, wz) in its own.

    Each :meth:`step` saturates the command (speed norm, yaw rate), moves each velocity component
    toward it by at most its acceleration limit times ``dt``, and integrates the pose with the
    mean of the old and new velocities (exact for the linear velocity ramp of one step) through
    the SE(2) exponential (exact for a constant twist: arcs stay arcs at any ``dt``).
    """

    def __init__(self, limits: RobotLimits | None = None, *, x: float = 0.0, y: float = 0.0,
                 theta: float = 0.0) -> None:
        self.limits = limits if limits is not None else RobotLimits()
        self.reset(x=x, y=y, theta=theta)

    def reset(self, *, x: float = 0.0, y: float = 0.0, theta: float = 0.0) -> None:
        """Place the robot at (x, y) m, heading ``theta`` rad, at rest."""
        for name, value in (("x", x), ("y", y), ("theta", theta)):
            _check("Robot", name, value, -1e6, 1e6)
        self.x, self.y, self.theta = float(x), float(y), _wrap(float(theta))
        self.vx = self.vy = self.wz = 0.0

    @property
    def pose(self) -> tuple[float, float, float]:
        """(x, y, theta): m, m, rad in (-pi, pi]."""
        return self.x, self.y, self.theta

    @property
    def velocity(self) -> tuple[float, float, float]:
        """(vx, vy, wz) in the robot frame: m/s, m/s, rad/s."""
        return self.vx, self.vy, self.wz

    def step(self, cmd: Command | Mapping[str, Any], dt: float) -> None:
        """Advance by ``dt`` s under the velocity command ``cmd`` (robot frame)."""
        dt = _check("Robot.step", "dt", dt, 0.0, 10.0)
        c = Command.coerce(cmd)
        lim = self.limits
        vx, vy = c.vx, c.vy
        speed = math.hypot(vx, vy)
        if speed > lim.max_speed:
            vx, vy = vx * lim.max_speed / speed, vy * lim.max_speed / speed
        wz = min(max(c.wz, -lim.max_yaw_rate), lim.max_yaw_rate)
        new_vx = _toward(self.vx, vx, lim.max_accel * dt)
        new_vy = _toward(self.vy, vy, lim.max_accel * dt)
        new_wz = _toward(self.wz, wz, lim.max_yaw_accel * dt)
        mvx, mvy, mwz = ((self.vx + new_vx) / 2, (self.vy + new_vy) / 2, (self.wz + new_wz) / 2)
        phi = mwz * dt
        if abs(phi) < 1e-6:  # series of sin(phi)/phi and (1 - cos(phi))/phi, no 0/0
            a, b = 1.0 - phi * phi / 6.0, phi / 2.0
        else:
            a, b = math.sin(phi) / phi, (1.0 - math.cos(phi)) / phi
        fx, fy = (a * mvx - b * mvy) * dt, (b * mvx + a * mvy) * dt  # in the start heading
        cos_t, sin_t = math.cos(self.theta), math.sin(self.theta)
        self.x += cos_t * fx - sin_t * fy
        self.y += sin_t * fx + cos_t * fy
        self.theta = _wrap(self.theta + phi)
        self.vx, self.vy, self.wz = new_vx, new_vy, new_wz


def _wrap(angle: float) -> float:
    """Angle in (-pi, pi]."""
    wrapped = math.atan2(math.sin(angle), math.cos(angle))
    return math.pi if wrapped == -math.pi else wrapped


# -- camera ------------------------------------------------------------------------------------

_DEFAULT_HFOV_DEG = 60.0


#: Image sides the simulated camera renders, px.
CAMERA_SIDES = (16, 4096)


@dataclass(frozen=True)
class Camera:
    """Pinhole camera at the robot origin looking along the robot's +x, square pixels.

    Parameters
    ----------
    width, height : int
        Image size, px; 16..4096. Default 256x256 as in the paper.
    focal_px : float or None
        Focal length, px, (1, 100000]. None: the focal length giving a 60 deg horizontal field
        of view, ``(width / 2) / tan(30 deg)`` (221.7 px at width 256).
    noise_sigma : float
        Standard deviation of additive Gaussian sensor noise, grey levels; 0..100, default 0.
    blur_sigma : float
        Gaussian optical blur, px; 0..20, default 0.
    """

    width: int = 256
    height: int = 256
    focal_px: float | None = None
    noise_sigma: float = 0.0
    blur_sigma: float = 0.0

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            object.__setattr__(self, name, int(_check("Camera", name, getattr(self, name),
                                                      *CAMERA_SIDES, integer=True)))
        if self.focal_px is None:
            f = (self.width / 2.0) / math.tan(math.radians(_DEFAULT_HFOV_DEG / 2.0))
            object.__setattr__(self, "focal_px", f)
        object.__setattr__(self, "focal_px",
                           _check("Camera", "focal_px", self.focal_px, 1.0, 1e5, lo_open=True))
        object.__setattr__(self, "noise_sigma",
                           _check("Camera", "noise_sigma", self.noise_sigma, 0.0, 100.0))
        object.__setattr__(self, "blur_sigma",
                           _check("Camera", "blur_sigma", self.blur_sigma, 0.0, 20.0))

    @property
    def f(self) -> float:
        """Focal length, px (never None after construction)."""
        assert self.focal_px is not None
        return self.focal_px

    @property
    def cx(self) -> float:
        return (self.width - 1) / 2.0

    @property
    def cy(self) -> float:
        return (self.height - 1) / 2.0

    @property
    def K(self) -> np.ndarray:  # noqa: N802 - the usual name of the intrinsic matrix
        """(3, 3) float64 intrinsic matrix."""
        return np.array([[self.f, 0.0, self.cx], [0.0, self.f, self.cy], [0.0, 0.0, 1.0]])

    @property
    def hfov_deg(self) -> float:
        """Horizontal field of view, degrees (edge to edge of the outer pixels)."""
        return math.degrees(2.0 * math.atan(self.width / 2.0 / self.f))


# camera axes (X right, Y down, Z forward) in the robot frame (x forward, y left, z up)
_R_CR = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])


def _r_cw(theta: float) -> np.ndarray:
    """(3, 3) rotation world -> camera for robot yaw ``theta``."""
    c, s = math.cos(theta), math.sin(theta)
    r_wr = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return _R_CR @ r_wr.T


def image_truth(pose: Mapping[str, float], camera: Camera, distance_m: float
                ) -> tuple[float, float]:
    """Ground truth of the target in the image from a ``sim/pose`` message's fields.

    Parameters
    ----------
    pose : x, y, theta of the robot and tx, ty of the target (m, rad).
    camera : the simulator's camera.
    distance_m : the scenario's reference distance.

    Returns
    -------
    u : image x of the target centre, px; scale : apparent size relative to the reference
    (``distance_m / depth``), as :meth:`Simulator.target_scale`. NaN when behind the camera.
    """
    r = _r_cw(float(pose["theta"]))
    pc = r @ np.array([pose["tx"] - pose["x"], pose["ty"] - pose["y"], 0.0])
    if pc[2] <= NEAR_M:
        return math.nan, math.nan
    return float(camera.K[0, 0] * pc[0] / pc[2] + camera.K[0, 2]), distance_m / float(pc[2])


# -- textures ----------------------------------------------------------------------------------

def load_texture(path: str | os.PathLike[str]) -> np.ndarray:
    """Read any image file OpenCV decodes as an (H, W) uint8 grey texture.

    Colour is converted as the camera service converts frames (``to_gray``: BGR -> grey with
    OpenCV's weights, 16-bit -> top byte, alpha dropped).

    Raises
    ------
    TextureError
        The file is missing, a folder, unreadable, or not an image.
    """
    text = os.fspath(path)
    if not os.path.exists(text):
        raise TextureError(f"texture {text}: no such file")
    if os.path.isdir(text):
        raise TextureError(f"texture {text}: is a folder, expected an image file")
    try:
        # np.fromfile + imdecode instead of imread: imread cannot open non-ASCII paths on
        # Windows and says nothing about why it failed
        raw = np.fromfile(text, dtype=np.uint8)
    except OSError as exc:
        raise TextureError(f"texture {text}: cannot read: {exc}") from None
    img = imagelimit.decode(f"texture {text}", lambda: cv2.imdecode(raw, cv2.IMREAD_UNCHANGED),
                            TextureError) if raw.size else None
    if img is None:
        raise TextureError(f"texture {text}: not an image OpenCV can decode")
    return _as_texture(img, text)


def _as_texture(img: Any, what: str) -> np.ndarray:
    if not isinstance(img, np.ndarray):
        raise TextureError(f"texture {what}: {type(img).__name__} is not an image array")
    try:
        grey = Grey()(img)  # a 16-bit image: scaled by the depth of its samples
    except ValueError as exc:
        raise TextureError(f"texture {what}: {exc}") from None
    if min(grey.shape) < 8:
        raise TextureError(f"texture {what}: {grey.shape[1]}x{grey.shape[0]} px is too small: "
                           "allowed 8 px or more per side")
    return grey


def builtin_target() -> np.ndarray:
    """The built-in target texture, (256, 256) uint8.

    The middle quarter of ``synthetic.texture(1024)``: its shapes (radius 1/160 to 1/40 of the
    texture size) then measure 3 to 11 image px on the 1 m target at 2 m, large enough for
    CORR_SIZE-wide windows, where a whole ``texture(256)`` would shrink them to 1 to 3 px.
    """
    n = TARGET_TEXTURE_PX
    big = synthetic_texture(4 * n, seed=TARGET_TEXTURE_SEED)
    return np.ascontiguousarray(big[3 * n // 2:5 * n // 2, 3 * n // 2:5 * n // 2])


def builtin_background() -> np.ndarray:
    """The built-in background texture, (1024, 1024) uint8, at :data:`BACKGROUND_CONTRAST`."""
    bg = synthetic_texture(BACKGROUND_TEXTURE_PX, seed=BACKGROUND_TEXTURE_SEED).astype(np.float32)
    bg = 128.0 + BACKGROUND_CONTRAST * (bg - 128.0)
    return np.clip(bg + 0.5, 0, 255).astype(np.uint8)


class _Plane:
    """A textured rectangle facing the robot (normal along world -x), with its mip-map.

    ``levels[k]`` is the texture reduced by about 2**k with INTER_AREA, straight from level 0 so
    every level has the exact pixel-centre mapping ``a0 = (ak + 0.5) * s - 0.5``; ``lift[k]`` is
    that mapping as a (3, 3) matrix (level-k px -> level-0 px). Each level carries its coverage
    as a second channel when ``alpha`` (the target, then float32); the background has none.
    """

    def __init__(self, tex: np.ndarray, width_m: float, *, alpha: bool) -> None:
        h, w = tex.shape
        self.m = width_m / w  # metres per level-0 texture pixel
        self.a_c, self.b_c = (w - 1) / 2.0, (h - 1) / 2.0
        self.alpha = alpha
        self.levels: list[np.ndarray] = []
        self.lift: list[np.ndarray] = []
        k = 0
        while True:
            lw, lh = max(1, round(w / 2**k)), max(1, round(h / 2**k))
            if k and min(lw, lh) < 8:
                break
            level = tex if k == 0 else cv2.resize(tex, (lw, lh), interpolation=cv2.INTER_AREA)
            if alpha:
                # float32: the warp's bilinear fringe must keep texture * coverage and coverage
                # unrounded, or the composite of the two is off by a grey level at the edges
                level = cv2.merge([level, np.full_like(level, 255)]).astype(np.float32)
            self.levels.append(level)
            sx, sy = w / lw, h / lh
            self.lift.append(np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5],
                                       [0.0, 0.0, 1.0]]))
            k += 1

    def homography(self, cam: Camera, pose: tuple[float, float, float],
                   centre: tuple[float, float]) -> np.ndarray:
        """(3, 3) homography level-0 texture px -> image px for robot ``pose`` and plane
        ``centre`` (X0, Y0) in m."""
        x, y, theta = pose
        x0, y0 = centre
        e_a = np.array([0.0, -self.m, 0.0])  # one texture column to the right: world -y
        e_b = np.array([0.0, 0.0, -self.m])  # one texture row down: world -z
        p00 = np.array([x0, y0, 0.0]) - self.a_c * e_a - self.b_c * e_b
        # texture (a, b, 1) -> world point minus camera position: [e_a, e_b, p00 - p]
        m = np.column_stack([e_a, e_b, p00 - np.array([x, y, 0.0])])
        return cam.K @ _r_cw(theta) @ m

    def level_weights(self, density: float) -> list[tuple[int, float]]:
        """[(level, weight)]: the one or two mip levels for ``density`` level-0 texture px per
        image px, trilinear weights summing to 1."""
        last = len(self.levels) - 1
        lvl = min(max(math.log2(density), 0.0), float(last)) if density > 0 else 0.0
        k = int(math.floor(lvl))
        frac = lvl - k
        if frac < 1e-3 or k >= last:
            return [(k, 1.0)]
        return [(k, 1.0 - frac), (k + 1, frac)]

    def warp(self, h0: np.ndarray, density: float, roi: tuple[int, int, int, int],
             border: int) -> np.ndarray:
        """The plane warped into image rectangle ``roi`` = (x0, y0, w, h), float32, mip-blended.

        Returns (h, w) or, with alpha, (h, w, 2) = (texture * coverage, coverage * 255).
        """
        x0, y0, rw, rh = roi
        shift = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]])
        out: np.ndarray | None = None
        for k, wgt in self.level_weights(density):
            hk = shift @ h0 @ self.lift[k]
            img = cv2.warpPerspective(self.levels[k], hk, (rw, rh), flags=cv2.INTER_LINEAR,
                                      borderMode=border, borderValue=0)
            img = img.astype(np.float32)
            out = img * wgt if out is None else cv2.scaleAdd(img, wgt, out)
        assert out is not None
        return out


def _valid_columns(cam: Camera, pose: tuple[float, float, float], plane_x: float,
                   ) -> np.ndarray | None:
    """(width,) bool: image columns whose viewing rays meet the plane x = ``plane_x`` in front of
    the camera; None if every column does."""
    x, _, theta = pose
    if plane_x - x <= NEAR_M:
        return np.zeros(cam.width, bool)
    # world-x component of the ray through column u, for a camera without pitch or roll
    u = np.arange(cam.width, dtype=np.float64)
    dx = math.cos(theta) + math.sin(theta) * (u - cam.cx) / cam.f
    valid = dx > 1e-6
    return None if valid.all() else valid


# -- simulator ---------------------------------------------------------------------------------

class Simulator:
    """Robot, camera, scripted target and background; renders 8-bit grey frames.

    Parameters
    ----------
    scenario : Scenario or str
        A scenario, or a built-in name or YAML path for :func:`load_scenario`.
    limits : RobotLimits, optional
        Robot limits (default :class:`RobotLimits()`).
    camera : Camera, optional
        Camera model (default :class:`Camera()`: 256x256, 60 deg, no noise, no blur).
    texture : array or path, optional
        Target texture: an image array (grey, BGR or BGRA) or an image file path. Default: the
        built-in :func:`builtin_target`.
    background : array or path, optional
        Background texture, likewise. Default :func:`builtin_background`.
    seed : int
        Seed of the sensor noise; the same seed gives identical frames.

    Notes
    -----
    :meth:`reset` puts the robot at rest at a start pose and the clock at 0; :meth:`step`
    advances the robot and the target; :meth:`render` draws the current state. The target is not
    drawn once the robot is within :data:`NEAR_M` of its plane (or past it).
    """

    def __init__(self, scenario: Scenario | str | os.PathLike[str] = "default", *,
                 limits: RobotLimits | None = None, camera: Camera | None = None,
                 texture: np.ndarray | str | os.PathLike[str] | None = None,
                 background: np.ndarray | str | os.PathLike[str] | None = None,
                 seed: int = 0) -> None:
        self.scenario = scenario if isinstance(scenario, Scenario) else load_scenario(scenario)
        self.limits = limits if limits is not None else RobotLimits()
        self.camera = camera if camera is not None else Camera()
        self.seed = int(_check("Simulator", "seed", seed, 0, 2**63 - 1, integer=True))
        tex = self._texture(texture, "target") if texture is not None else builtin_target()
        bg = (self._texture(background, "background") if background is not None
              else builtin_background())
        self._target = _Plane(tex, self.scenario.target_size_m, alpha=True)
        self._background = _Plane(bg, BACKGROUND_SIZE_M, alpha=False)
        self.robot = Robot(self.limits)
        self.reset()

    @staticmethod
    def _texture(spec: Any, what: str) -> np.ndarray:
        if isinstance(spec, (str, os.PathLike)):
            return load_texture(spec)
        return _as_texture(spec, f"({what} array)")

    # -- state --------------------------------------------------------------------------------
    def reset(self, *, x: float = 0.0, y: float = 0.0, theta: float = 0.0) -> None:
        """Clock to 0, robot at rest at (x, y) m heading ``theta`` rad, noise re-seeded."""
        self.robot.reset(x=x, y=y, theta=theta)
        self.t = 0.0
        self.frames = 0
        self._rng = np.random.default_rng(self.seed)

    def step(self, cmd: Command | Mapping[str, Any], dt: float) -> None:
        """Advance the robot under ``cmd`` (robot frame, see :class:`Command`) and the
        scripted target by ``dt`` s."""
        self.robot.step(cmd, dt)
        self.t += float(dt)

    @property
    def done(self) -> bool:
        """True once the clock has reached the scenario's duration (stepping may go on), to
        within DONE_SLACK_S: the clock is a float sum of steps, and 15 steps of 1/30 s fell
        short of 0.5 s (a 16th frame; 20 s at 7 fps gave 141)."""
        return self.t >= self.scenario.duration_s - DONE_SLACK_S

    def target_position(self) -> tuple[float, float]:
        """Ground-truth target centre (tx, ty), m, world frame, at the current time."""
        return self.scenario.target_position(self.t)

    def pose(self) -> dict[str, float]:
        """Ground truth as the contract's ``sim/pose``: robot ``x``, ``y`` (m), ``theta``
        (rad), target centre ``tx``, ``ty`` (m), world frame."""
        tx, ty = self.target_position()
        x, y, theta = self.robot.pose
        return {"x": x, "y": y, "theta": theta, "tx": tx, "ty": ty}

    def truth(self) -> dict[str, float]:
        """:meth:`pose` plus ``t`` (s), the robot velocity ``vx``, ``vy``, ``wz`` and the image
        ground truth ``u``, ``v`` (:meth:`target_center_px`) and ``scale``
        (:meth:`target_scale`), for evaluating the tracker and the controller."""
        out = {"t": self.t, **self.pose()}
        out.update(zip(("vx", "vy", "wz"), self.robot.velocity, strict=True))
        u, v = self.target_center_px()
        out.update(u=float(u), v=float(v), scale=self.target_scale())
        return out

    # -- projection ---------------------------------------------------------------------------
    def to_camera(self, point_world: Any) -> np.ndarray:
        """World points (m), shape (3,) or (N, 3) -> camera frame (X right, Y down, Z forward)."""
        p = np.asarray(point_world, np.float64)
        if p.shape[-1:] != (3,) or p.ndim > 2:
            raise ValueError(f"point_world of shape {p.shape}: expected (3,) or (N, 3)")
        x, y, theta = self.robot.pose
        return (p - np.array([x, y, 0.0])) @ _r_cw(theta).T

    def project(self, point_world: Any) -> np.ndarray:
        """Image position (u, v), px, of world point(s) (m).

        Parameters
        ----------
        point_world : array_like, shape (3,) or (N, 3)

        Returns
        -------
        (2,) or (N, 2) float64 array; NaN for points within :data:`NEAR_M` of the camera plane
        or behind it.
        """
        pc = self.to_camera(point_world)
        cam = self.camera
        z = pc[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.where(z > NEAR_M, cam.f * pc[..., 0] / z + cam.cx, np.nan)
            v = np.where(z > NEAR_M, cam.f * pc[..., 1] / z + cam.cy, np.nan)
        return np.stack([u, v], axis=-1)

    def target_center_px(self) -> np.ndarray:
        """(2,) image position (u, v) of the target centre, px; NaN if behind the camera."""
        tx, ty = self.target_position()
        return self.project((tx, ty, 0.0))

    def target_scale(self) -> float:
        """Apparent size of the target relative to the reference (the scenario's
        ``distance_m`` seen from the start pose): ``distance_m / Z``, Z the depth of the target
        centre along the optical axis, m. Exactly the ratio of the target's projected widths
        while the heading is 0. NaN if the centre is behind the camera."""
        tx, ty = self.target_position()
        z = float(self.to_camera((tx, ty, 0.0))[2])
        return self.scenario.distance_m / z if z > NEAR_M else math.nan

    # -- rendering ----------------------------------------------------------------------------
    def render(self) -> np.ndarray:
        """The camera frame of the current state, (height, width) uint8 grey."""
        cam = self.camera
        pose = self.robot.pose
        frame = self._render_background(pose)
        self._composite_target(frame, pose)
        gain, offset = self.scenario.lighting(self.t)
        if gain != 1.0 or offset != 0.0:
            frame *= gain
            frame += offset
        if cam.blur_sigma > 0:
            frame = cv2.GaussianBlur(frame, (0, 0), cam.blur_sigma,
                                     borderType=cv2.BORDER_REPLICATE)
        if cam.noise_sigma > 0:
            noise = self._rng.standard_normal(frame.shape, dtype=np.float32)
            frame += noise * np.float32(cam.noise_sigma)
        self.frames += 1
        np.clip(frame, 0.0, 255.0, out=frame)
        frame += 0.5  # round to nearest: astype truncates
        return frame.astype(np.uint8)

    def _density(self, plane: _Plane, centre_world: tuple[float, float]) -> float:
        """Level-0 texture px per image px at the plane point ``centre_world`` (x, y) m."""
        z = float(self.to_camera((centre_world[0], centre_world[1], 0.0))[2])
        return max(z, NEAR_M) / (self.camera.f * plane.m)

    def _render_background(self, pose: tuple[float, float, float]) -> np.ndarray:
        cam = self.camera
        bx = self.scenario.background_distance_m
        valid = _valid_columns(cam, pose, bx)
        if valid is not None and not valid.any():
            return np.full((cam.height, cam.width), VOID_GREY, np.float32)
        # the background point straight ahead of the robot sets the mip level
        x, y, theta = pose
        ahead = (bx, y + (bx - x) * math.tan(theta)) if abs(math.cos(theta)) > 1e-3 else (bx, y)
        h0 = self._background.homography(cam, pose, (bx, 0.0))
        frame = self._background.warp(h0, self._density(self._background, ahead),
                                      (0, 0, cam.width, cam.height), cv2.BORDER_REFLECT_101)
        if valid is not None:
            frame[:, ~valid] = VOID_GREY
        return frame

    def _composite_target(self, frame: np.ndarray, pose: tuple[float, float, float]) -> None:
        cam = self.camera
        tx, ty = self.target_position()
        valid = _valid_columns(cam, pose, tx)
        if valid is not None and not valid.any():
            return
        plane = self._target
        h0 = plane.homography(cam, pose, (tx, ty))
        levels0 = plane.levels[0]
        th, tw = levels0.shape[:2]
        corners = np.array([[-0.5, -0.5, 1.0], [tw - 0.5, -0.5, 1.0], [tw - 0.5, th - 0.5, 1.0],
                            [-0.5, th - 0.5, 1.0]])
        img = corners @ h0.T
        if valid is None and (img[:, 2] > 0).all():
            # the whole plane is in front: draw only its bounding box (+1 px for the bilinear
            # fringe) instead of the full frame
            uv = img[:, :2] / img[:, 2:]
            x0 = max(int(math.floor(uv[:, 0].min())) - 1, 0)
            y0 = max(int(math.floor(uv[:, 1].min())) - 1, 0)
            x1 = min(int(math.ceil(uv[:, 0].max())) + 2, cam.width)
            y1 = min(int(math.ceil(uv[:, 1].max())) + 2, cam.height)
            if x1 <= x0 or y1 <= y0:
                return
        else:
            x0, y0, x1, y1 = 0, 0, cam.width, cam.height
        warped = plane.warp(h0, self._density(plane, (tx, ty)), (x0, y0, x1 - x0, y1 - y0),
                            cv2.BORDER_CONSTANT)
        tex, cover = warped[..., 0], warped[..., 1]
        if valid is not None:
            cols = ~valid[x0:x1]
            tex[:, cols] = 0.0
            cover[:, cols] = 0.0
        roi = frame[y0:y1, x0:x1]
        # premultiplied alpha: the warp already multiplied the texture by its coverage
        roi *= 1.0 - cover * np.float32(1.0 / 255.0)
        roi += tex

