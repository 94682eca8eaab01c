"""When the auto-tuner tunes: at start, on a scene change, on a distance change.

The decision is pure (numpy and OpenCV, no Zenoh, no msgpack, no clock: callers pass ``now``)
so it is tested alone; :mod:`.service` feeds it the frames and estimates it receives and asks
:meth:`Triggers.due` whether to start a tuning cycle.

Signals
-------
Scene (image content), :func:`scene_distance`
    Every frame is reduced to a 32 x 32 thumbnail (area average, then a Gaussian blur of 1.5
    thumbnail pixels, so sub-cell motion does not alias). Its central 24 x 24 window is
    compared by normalised cross-correlation with every window of the *reference* thumbnails
    (up to :data:`REF_FRAMES` frames evenly spread over the buffer the last tuning ran on:
    neighbouring frames differ by a pixel or two) shifted by up to 4 thumbnail pixels each way,
    i.e. one eighth of the frame: the distance is 1 - the best correlation, 0 for the same
    view, about 1 for unrelated content, up to 2. The shifts make it tolerant to the motion the
    tracker follows anyway; normalising makes it tolerant to a change of brightness or
    contrast. Measured on :func:`vistrack.common.synthetic.sequence` scenes (256 x 256): the
    same scene panned 45 px from the reference buffer 0.15 or less, 80 px 0.45; other
    scenes (seeds 2 to 9) 0.55 to 0.93. Default threshold :data:`DEFAULT_SCENE_THRESHOLD` 0.4:
    a pan of about a third of the frame counts as a new scene, which it is for the parameters
    (what the tuning saw has mostly left the view). About 0.1 ms a frame: the correlations
    are an ``einsum``, not a BLAS product, whose threads spin for milliseconds on a busy
    machine (a 2430 x 576 product took 0.1 ms alone, up to 6 ms beside the pipeline).
Feature storm (the tracker's view of a scene change), from ``motion/estimate``
    An estimate is a *turnover event* when it starts a track (``first``), when NPI fell to less
    than half of the previous estimate's, or when at least half of its feature ids were not in
    the previous estimate (the features were lost and re-detected). :data:`STORM_EVENTS`
    events within :data:`STORM_WINDOW` estimates count as a scene change: one cut loses the
    features once; repeated losses mean the parameters no longer suit the scene.
Distance, from the estimates' accumulated ``scale``
    The ratio of the current ``scale`` to its value when the last tuning started; leaving the
    band (default :data:`DEFAULT_SCALE_BAND`, 0.8 .. 1.25: the target 20 % smaller or 25 %
    bigger, symmetric in log scale) is a distance change. A new track (``first``) restarts
    the scale at 1, and the reference with it.

Hysteresis (:class:`Hysteresis`)
    A signal is normalised so that 1 is its threshold (the band's edge for the scale, in log
    scale). It is *raised* once it reaches 1 and stays raised until it falls below
    :data:`RELEASE` (half the threshold); a change counts once it has stayed raised for
    :data:`CONFIRM` observations, and it counts once per excursion. A single odd frame (a
    glitch, motion blur) is not a scene change, and a signal hovering about its threshold does
    not trigger again and again.

Timing (:meth:`Triggers.due`, :meth:`Triggers.collecting`)
    A tuning runs on the whole rolling buffer, so after a change the tuner waits until the
    buffer holds only frames from after it (``buffer`` new frames; at start, a full buffer).
    Only then are frames wanted one after the other (:meth:`Triggers.collecting`); the
    service samples them otherwise, and calls :meth:`Triggers.restart` when it goes back to
    taking every frame, so the buffer and the scene reference are consecutive frames.
    Between the end of one tuning and the start of the next at least ``min_interval_s``
    (default :data:`DEFAULT_MIN_INTERVAL_S`) pass: with a cycle of 4 to 5 s on one core, the
    default keeps the experiments' share of one core below a fifth however often the scene
    changes. One tuning runs at a time; changes seen meanwhile wait for the next.
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass, field

import cv2
import numpy as np

INITIAL = "initial tuning"
SCENE = "scene change"
DISTANCE = "distance change"
# A pending reason is only replaced by a weightier one: before the first tuning every change is
# part of the initial one, and a new scene also explains a change of the scale.
_WEIGHT = {DISTANCE: 1, SCENE: 2, INITIAL: 3}

DEFAULT_MIN_INTERVAL_S = 20.0
DEFAULT_SCALE_BAND = (0.8, 1.25)
DEFAULT_SCENE_THRESHOLD = 0.4
#: A raised signal is back to normal below this fraction of its threshold.
RELEASE = 0.5
#: Observations a signal must stay raised before a change counts.
CONFIRM = 3
#: Turnover events within STORM_WINDOW estimates that make a storm.
STORM_EVENTS = 3
STORM_WINDOW = 30
#: Fraction of new feature ids (or of NPI lost) that makes an estimate a turnover event.
TURNOVER = 0.5

THUMB = 32  # thumbnail side, px
THUMB_BLUR = 1.5  # Gaussian sigma on the thumbnail, thumbnail px
THUMB_SHIFT = 4  # largest shift tried each way, thumbnail px (THUMB / 8)
REF_FRAMES = 10  # reference thumbnails kept from a tuned buffer
FLAT_RMS = 1.0  # grey levels of RMS contrast below which a thumbnail window is flat


# -- the scene signal ------------------------------------------------------------------------

def thumbnail(frame: np.ndarray) -> np.ndarray:
    """The (THUMB, THUMB) float32 thumbnail of an (H, W) grey frame (any size)."""
    if frame.ndim != 2 or min(frame.shape) < 1:
        raise ValueError(f"frame must be a non-empty (H, W) array, got shape {frame.shape}")
    small = cv2.resize(np.asarray(frame, np.float32), (THUMB, THUMB),
                       interpolation=cv2.INTER_AREA)
    return cv2.GaussianBlur(small, (0, 0), THUMB_BLUR)


def _normalise(rows: np.ndarray) -> np.ndarray:
    """Each row less its mean, to unit norm; a flat one (an RMS contrast below FLAT_RMS grey
    levels: a covered lens, its sensor noise averaged into the thumbnail) all zeros."""
    rows = rows - rows.mean(axis=-1, keepdims=True)
    norm = np.linalg.norm(rows, axis=-1, keepdims=True)
    return rows / np.where(norm > FLAT_RMS * np.sqrt(rows.shape[-1]), norm, np.inf)


def reference_windows(thumbs: list[np.ndarray]) -> np.ndarray:
    """Every shifted central window of the reference thumbnails, normalised.

    Returns
    -------
    (len(thumbs) * (2 * THUMB_SHIFT + 1) ** 2, (THUMB - 2 * THUMB_SHIFT) ** 2) float32.
    """
    if not thumbs:
        raise ValueError("reference_windows needs at least one thumbnail")
    k, n = THUMB_SHIFT, THUMB - 2 * THUMB_SHIFT
    rows = [t[k + dy:k + dy + n, k + dx:k + dx + n].ravel()
            for t in thumbs for dy in range(-k, k + 1) for dx in range(-k, k + 1)]
    return _normalise(np.array(rows, np.float32))


def scene_distance(thumb: np.ndarray, references: np.ndarray) -> float:
    """1 - the best normalised correlation of ``thumb``'s central window with ``references``
    (from :func:`reference_windows`): 0 same view, ~1 unrelated, at most 2. A flat view
    (:func:`_normalise`) is 0 from references mostly flat (a covered lens still covered: it
    read 1, a scene change, logged after every skipped tuning), 1 from references mostly
    textured (a webcam's black first frames among them do not make darkness the scene)."""
    k = THUMB_SHIFT
    centre = _normalise(thumb[k:THUMB - k, k:THUMB - k].ravel()[None, :])[0]
    if not centre.any():
        return 0.0 if np.mean(~references.any(axis=1)) > 0.5 else 1.0
    return float(1.0 - np.max(references @ centre))


# -- hysteresis ------------------------------------------------------------------------------

@dataclass
class Hysteresis:
    """A threshold with hysteresis and confirmation over a signal normalised to its threshold.

    :meth:`update` returns True once per excursion: when the signal has been raised (it
    reached 1 and has not since fallen below ``release``) for ``confirm`` observations.
    """

    confirm: int = CONFIRM
    release: float = RELEASE
    raised: bool = False
    count: int = 0
    fired: bool = False

    def update(self, level: float) -> bool:
        if not self.raised and level >= 1.0:
            self.raised, self.count = True, 0
        if self.raised and level < self.release:
            self.reset()
        if not self.raised:
            return False
        self.count += 1
        if self.count >= self.confirm and not self.fired:
            self.fired = True
            return True
        return False

    def reset(self) -> None:
        self.raised, self.count, self.fired = False, 0, False


def band_level(ratio: float, band: tuple[float, float]) -> float:
    """How far ``ratio`` is towards leaving ``band`` = (lo, hi), lo < 1 < hi, in log scale:
    0 at 1, 1 on either edge, > 1 outside."""
    lo, hi = band
    if not ratio > 0:
        return math.inf
    return math.log(ratio) / math.log(hi if ratio >= 1.0 else lo)


# -- the decision ----------------------------------------------------------------------------

@dataclass(frozen=True)
class TriggerConfig:
    """When to tune. Raises ValueError naming the field, the value and the allowed range.

    Attributes
    ----------
    buffer : frames a tuning runs on; after a change this many new frames are awaited.
    min_interval_s : least time from the end of one tuning to the start of the next, s.
    scale_band : (lo, hi), lo < 1 < hi: the accumulated scale ratio since the last tuning
        that may pass without a re-tune.
    scene_threshold : scene distance (see :func:`scene_distance`) that is a new scene.
    confirm, release : see :class:`Hysteresis`.
    storm_events, storm_window, turnover : see the module notes.
    """

    buffer: int = 30
    min_interval_s: float = DEFAULT_MIN_INTERVAL_S
    scale_band: tuple[float, float] = DEFAULT_SCALE_BAND
    scene_threshold: float = DEFAULT_SCENE_THRESHOLD
    confirm: int = CONFIRM
    release: float = RELEASE
    storm_events: int = STORM_EVENTS
    storm_window: int = STORM_WINDOW
    turnover: float = TURNOVER

    def __post_init__(self) -> None:
        def need(ok: bool, name: str, allowed: str) -> None:
            if not ok:
                raise ValueError(f"{name}={getattr(self, name)!r} is out of range: "
                                 f"allowed {allowed}")
        need(1 <= self.buffer <= 1000, "buffer", "1..1000")
        need(0 <= self.min_interval_s <= 86400, "min_interval_s", "0..86400 s")
        lo, hi = self.scale_band
        need(0 < lo < 1 < hi < math.inf, "scale_band", "0 < lo < 1 < hi")
        need(0 < self.scene_threshold <= 2, "scene_threshold", "0 < x <= 2")
        need(1 <= self.confirm <= 1000, "confirm", "1..1000")
        need(0 <= self.release < 1, "release", "0 <= x < 1")
        need(1 <= self.storm_events <= self.storm_window, "storm_events", "1..storm_window")
        need(1 <= self.storm_window <= 10000, "storm_window", "1..10000")
        need(0 < self.turnover <= 1, "turnover", "0 < x <= 1")


@dataclass
class Triggers:
    """Watches frames and estimates and says when to tune, and why.

    Use: :meth:`frame` for every frame received, :meth:`estimate` for every estimate;
    :meth:`due` (with the current monotonic time) returns the reason to tune now or None;
    :meth:`started` when a tuning starts on the buffer, :meth:`finished` when it ends.

    Attributes
    ----------
    pending : the reason of the next tuning (INITIAL, SCENE, DISTANCE), None when nothing
        calls for one.
    fresh : frames received since ``pending`` was set (the buffer is refilled once it
        reaches ``config.buffer``).
    running : a tuning is running.
    distance, ratio : the last scene distance (0 before the first tuning) and scale ratio.
    why : what the last change returned was seen in, for a reader (e.g. "a feature storm:
        3 turnovers in the last 30 estimates").
    """

    config: TriggerConfig = field(default_factory=TriggerConfig)
    pending: str | None = INITIAL
    fresh: int = 0
    running: bool = False
    distance: float = 0.0
    ratio: float = 1.0
    why: str = ""

    def __post_init__(self) -> None:
        c = self.config
        self._thumbs: collections.deque[np.ndarray] = collections.deque(maxlen=c.buffer)
        self._shape: tuple[int, ...] | None = None
        self._refs: np.ndarray | None = None
        self._scene = Hysteresis(c.confirm, c.release)
        self._distance = Hysteresis(c.confirm, c.release)
        self._events: collections.deque[bool] = collections.deque(maxlen=c.storm_window)
        self._prev: tuple[int, set[int]] | None = None  # (npi, ids) of the last estimate
        self._scale = self._scale_ref = 1.0
        self._last_end: float | None = None
        self._running_reason: str | None = None

    # -- observations -------------------------------------------------------------------------
    def frame(self, image: np.ndarray) -> str | None:
        """Observe a frame; return SCENE when it confirms a scene change, else None."""
        self.fresh += 1
        thumb = thumbnail(image)
        if image.shape != self._shape:
            changed = self._shape is not None  # another camera: the last tuning no longer fits
            self._shape, self._refs = image.shape, None
            self._thumbs.clear()
            self._thumbs.append(thumb)
            if changed:
                self.why = f"another frame size: {image.shape[1]}x{image.shape[0]}"
                return self._change(SCENE, fresh=1)  # this frame is the first of the new scene
            return None
        self._thumbs.append(thumb)
        if self._refs is None:
            return None
        self.distance = scene_distance(thumb, self._refs)
        if self._scene.update(self.distance / self.config.scene_threshold):
            self.why = (f"scene distance {self.distance:.2f} (threshold "
                        f"{self.config.scene_threshold:g})")
            # the frames since the signal rose show the new scene already, those the
            # buffer holds (a signal that rose on sampled frames, before the buffer started
            # again, counted frames never buffered: a tuning on 29 of --buffer 30)
            return self._change(SCENE, fresh=min(self._scene.count, self.fresh))
        return None

    def estimate(self, *, first: bool, npi: int, ids: set[int] | list[int],
                 scale: float, cut: bool = False) -> str | None:
        """Observe an estimate; return SCENE (a storm) or DISTANCE when it confirms one.
        ``cut``: the source started again before it (its ``cuts`` changed: a ``--loop``
        file's next pass): a new track, but no feature lost in the scene (each pass of an
        8-frame loop at 30 fps made a storm, and a tuning every --min-interval on a scene that
        never changed: a hunt of the auto-tuner)."""
        c = self.config
        ids = set(ids)
        if first or cut:
            self._scale_ref = 1.0  # a new track restarts the accumulated scale
            self._distance.reset()
        event = first and not cut
        if self._prev is not None and not first and not cut:
            prev_npi, prev_ids = self._prev
            lost = prev_npi > 0 and npi < (1.0 - c.turnover) * prev_npi
            renewed = bool(ids) and len(ids - prev_ids) >= c.turnover * len(ids)
            event = lost or renewed
        self._prev = (npi, ids)
        self._events.append(event)
        self._scale = scale
        self.ratio = scale / self._scale_ref
        turnovers = sum(self._events)
        storm = turnovers >= c.storm_events
        if storm:
            self._events.clear()
        moved = self._distance.update(band_level(self.ratio, c.scale_band))
        if moved:
            lo, hi = c.scale_band
            self.why = f"scale ratio {self.ratio:.3f} (band {lo:g}..{hi:g})"
        elif storm:
            self.why = (f"a feature storm: {turnovers} turnovers ({c.turnover:.0%} of the "
                        f"features lost or new) in the last {c.storm_window} estimates")
        if storm or moved:
            # a change in a scene already awaiting its tuning does not restart the wait
            return self._change(DISTANCE if moved else SCENE,
                                fresh=0 if self.pending is None else None)
        return None

    def _change(self, reason: str, *, fresh: int | None) -> str:
        """Note a change; ``fresh``: frames of the buffer already showing it (None: keep
        counting as before)."""
        if self.pending is None or _WEIGHT[reason] > _WEIGHT[self.pending]:
            self.pending = reason
        if fresh is not None:
            self.fresh = fresh
        return reason

    def restart(self) -> None:
        """Frames were missed since the last one observed (they were not taken): the buffer
        starts again, and a pending tuning waits for ``config.buffer`` new frames."""
        self.fresh = 0
        self._thumbs.clear()

    # -- the decision -------------------------------------------------------------------------
    def collecting(self, now: float) -> bool:
        """Whether a tuning waits only for frames at monotonic time ``now`` (one is pending,
        none is running, the interval since the last has passed): every frame is wanted
        until it starts. Otherwise frames only serve the scene signal, and a sample of them
        is enough."""
        return (not self.running and self.pending is not None
                and (self._last_end is None
                     or now - self._last_end >= self.config.min_interval_s))

    def due(self, now: float) -> str | None:
        """The reason to start a tuning at monotonic time ``now``, or None."""
        if self.fresh < self.config.buffer or not self.collecting(now):
            return None
        return self.pending

    def started(self) -> None:
        """A tuning starts on the buffer: its frames become the scene reference and the
        current scale the distance reference."""
        thumbs, self._refs = list(self._thumbs), None
        if thumbs:
            picks = np.unique(np.linspace(0, len(thumbs) - 1, REF_FRAMES).round().astype(int))
            self._refs = reference_windows([thumbs[i] for i in picks])
        self._scale_ref = self._scale
        self.distance, self.ratio = 0.0, 1.0
        self._scene.reset()
        self._distance.reset()
        self._events.clear()
        self._running_reason, self.pending, self.running = self.pending, None, True

    def finished(self, now: float, *, ok: bool = True, refill: bool = False) -> None:
        """The tuning ended at ``now``; a failed one is due again after the interval, once
        the buffer has been refilled with new frames if ``refill`` (its frames could not be
        tuned on: a covered lens)."""
        self.running, self._last_end = False, now
        if not ok and self.pending is None:
            self.pending = self._running_reason
            self.fresh = 0 if refill else self.config.buffer
