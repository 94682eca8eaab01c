"""The feature tracker: selection, SSD tracking with velocity prediction, loss and re-detection.

State is explicit (``Tracker.update(pre) -> Estimate``) so a recorded run replays to the same
numbers in one process or across the services.

Per frame t -> t+1:

1. prediction (Section 4): constant velocity from finite differences,
   ``x_pred = x_t + (x_t - x_{t-1})``; a feature's first step is predicted by the image motion
   of the frame before, its scale step about the tracked features' centroid included (zero
   on a track's second frame, and always with the paper's tracker,
   :meth:`TrackerParams.paper`). Frames skipped (``seq`` jumping: a camera that dropped
   frames, a pipeline that took the latest) count: the velocity, the zoom and the turn are
   extrapolated over the frames since the last one tracked, per frame of the step they were
   measured over (at most MAX_GAP frames);
2. coarse-to-fine SSD search of Eq. (1) around the prediction, refined to sub-pixel
   (:mod:`.pyramid`, :mod:`.ssd`);
3. a feature is lost when its window leaves the image, and rejected (lost too) when its match
   cannot be trusted: the minimum on the search window's border, a second minimum nearly as
   good, a failed refinement, a forward-backward error above ``max_fb_error`` or an RMS
   residual above ``max_residual`` grey levels, unless Gauss-Newton from the motion of its
   neighbours (where they move as one surface) finds it and returns (step 5c of
   :mod:`.pyramid`). The counts by reason are kept (:attr:`Tracker.lost_by`);
4. when fewer than ``redetect_fraction * max_features`` survive, new features are chosen among
   the frame's candidates (:mod:`.features`) away from the survivors; ids are never reused, and a
   feature keeps its id while it is tracked;
5. the estimate: Eq. (2) over the current features and the incremental motion of the matched
   ones (:mod:`.motion`), accumulated over the run.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field

import cv2
import numba as nb
import numpy as np
from numba.core import event as numba_event

from ..params import MIN_VALID_NPI, TrackerParams
from . import exposure, features
from .exposure import compensate, compensate_rows
from .features import (
    VOID_BLUR,
    VOID_LEVEL,
    VOID_PROOF,
    VOID_SETTLE,
    VOID_TOLERANCE,
    near_void,
    select_features,
    void_runs,
    void_step,
)
from .motion import FEW_PAIRS, STILL_PX, _incremental_motion, _median_small, centroid_scatter
from .noise import noise_level
from .preprocess import Preprocessed, candidates_above, preprocess, strength_of
from .pyramid import FRAME_WORK, Pyramid, TrackPlan, build_pyramid, sum_type, wide_tests
from .ssd import BORDER, LEFT, OK, OVER, RESIDUAL, STATUS_NAMES, track_ssd, window_weights

#: The scale steps a new feature's prediction extrapolates (:meth:`Tracker._add_features`):
#: an approach of up to 25 % a frame either way (the tests run 15 %); beyond, the frame's
#: incremental motion is more likely wrong than the camera that fast.
ZOOM_RANGE = (0.8, 1.25)
#: the most frames a prediction extrapolates the motion over where frames were skipped
#: (``seq`` jumping): beyond a quarter of a second at 30 fps, constant velocity is a guess, and
#: the guided retry's frame-wide shift finds what it missed
MAX_GAP = 8
#: frame t is scaled by the zoom of the frame before (:func:`_zoomed`) where that zoom departs
#: from 1 by more than this
ZOOM_WARP = 0.02
#: ... and turned by the turn of the frame before where that exceeds this, radians (1.1
#: degrees: it moves a point as far as ZOOM_WARP's scale step does at the same distance)
TURN_WARP = 0.02
#: a turn beyond this a frame (radians, 20 degrees) is a frame's error, not a roll: not
#: extrapolated
TURN_MAX = 0.35
#: a turn is expected again where the two frames before turned the same way, by amounts
#: within this share of the last one (:meth:`Tracker._turn_ahead`)
TURN_STEADY = 0.5
#: a frame pair searched without a zoom or a turn is searched again with them
#: (:func:`_zoom_retry`) where fewer than this share of its features were found, at least
#: ZOOM_FOUND of them, and they zoom (ZOOM_WARP) or turn (TURN_WARP); the segments between
#: pairs of them measured are ZOOM_RADIUS px long or more (:func:`_turn_step`)
ZOOM_RETRY_SHARE = 0.75
ZOOM_FOUND = 8
ZOOM_RADIUS = 10.0
#: the retry's similarity is the one most of the matches found fit to within this, px, of
#: at most RETRY_PROPOSALS proposed (with 2000 features, 3000 proposals tried on 1500 matches
#: would have taken ~70 MB and tens of ms)
RETRY_FIT_PX = 2.0
RETRY_PROPOSALS = 128
#: Frames between two estimates of the camera's noise (:mod:`.noise`, ~0.2 ms at 256 x 256):
#: a camera's noise changes with its gain, not from frame to frame.
NOISE_EVERY = 30
#: a frame that keeps fewer than FEW_KEPT features, and at most this share of those it had,
#: starts a new track (:meth:`Tracker._track`: a scene cut)
FEW_SHARE = 0.1
#: ... fewer than this many: too few for the step's inlier test to leave out a lookalike (its
#: median needs most of them right). With MIN_VALID_NPI (3), 3 of 74 cuts from RubberWhale to
#: another scene kept 3 or 4 of 82 features, lookalikes 7 px apart, and their mean jumped
#: the estimate by up to (17.4, 2.8) px, valid (a hunt on frames from other cameras). As
#: many as a step needs for its fit (motion.FEW_PAIRS): a frame of a camera's noise reduction
#: that kept exactly 5 of 91 features, all on its ghost of the frame before, was taken as a
#: step of none where the view jumped 45 px, and the jump was lost for good (a hunt of camera
#: processing effects); now a new track starts there
FEW_KEPT = FEW_PAIRS
#: A burnt-in overlay (an IP camera's timestamp and name, a dashcam's speed) and the robot's
#: own body stay put in the image while the scene moves: their features, strong corners of
#: white text outlined in black, took 29 of 62 on RubberWhale panning (3.3, 1.2) px a frame
#: and the motion read none for most frames (a drift of 103 px in 39 frames). A feature
#: within this share of the frame's size of its edges ...
OVERLAY_BAND = 0.12
#: ... that has stayed within this many px of where it stood ...
OVERLAY_STILL = 0.05
#: ... while the features away from the edges moved this far (the median of a frame's
#: displacements, |dx| + |dy|, summed over the frames; at 3 px an approach's features, slow
#: near its centre, took 2 to 3 frames to prove the text: 4.9 px of drift) is the image's,
#: not the scene's: it is dropped (lost as "left"), and the cells of OVERLAY_CELL px around
#: it are outside the picture from then on: no feature is taken, nor kept, there (a
#: timestamp's digits change).
#: The scene moves only in a frame where at most OVERLAY_STILL_SHARE of the features away
#: from the edges stood within motion.STILL_PX: a still camera watching something large cross
#: the middle of its view (a third of its width) moved them by their median, and the still
#: background at the edges was taken for an overlay.
OVERLAY_PROOF = 1.5
OVERLAY_STILL_SHARE = 0.2
OVERLAY_CELL = 8


@dataclass(frozen=True)
class Estimate:
    """The motion estimate of one frame (the fields of ``motion/estimate``).

    Attributes
    ----------
    seq : frame number (0 for the first frame of the run unless given).
    npi : number of feature points in the image (the paper's NPI).
    xc, yc, xe, ye : Eq. (2) centroid and scatter, px; with no feature the image centre and 0
        (every number of an estimate is finite).
    dx, dy : robust image motion accumulated since the first frame, px.
    scale : robust apparent scale accumulated since the first frame (> 1: closer).
    t_ms : wall time to process this frame, ms.
    first : True for the first frame of a run (its t_ms is the paper's t1).
    valid : False when NPI is below ``MIN_VALID_NPI`` (3): too few features for a meaningful
        centroid and scatter, so nothing should act on this estimate.
    ids : (npi,) int64 feature ids; points : (npi, 2) float64 x, y in px.
    """

    seq: int
    npi: int
    xc: float
    yc: float
    xe: float
    ye: float
    dx: float
    dy: float
    scale: float
    t_ms: float
    first: bool
    valid: bool
    ids: np.ndarray = field(repr=False)
    points: np.ndarray = field(repr=False)

    def features(self) -> list[list[float]]:
        """The contract's ``features``: a list of [id, x, y]."""
        # tolist() makes Python ints and floats in C: 8x faster than a loop over numpy scalars
        pts = self.points.reshape(-1, 2)
        return list(map(list, zip(self.ids.tolist(), pts[:, 0].tolist(), pts[:, 1].tolist(),
                                  strict=True)))

    def as_dict(self) -> dict:
        """The contract's ``motion/estimate`` / ``track --format jsonl`` fields."""
        return {"seq": self.seq, "npi": self.npi, "xc": self.xc, "yc": self.yc, "xe": self.xe,
                "ye": self.ye, "dx": self.dx, "dy": self.dy, "scale": self.scale,
                "t_ms": self.t_ms, "first": self.first, "valid": self.valid,
                "features": self.features()}


class Tracker:
    """SSD feature tracker over a sequence of pre-processed frames.

    Parameters
    ----------
    params : TrackerParams; may be replaced between frames with :meth:`set_params`.
    """

    def __init__(self, params: TrackerParams | None = None) -> None:
        self._all_held = np.ones(0, np.bool_)
        self.set_params(params if params is not None else TrackerParams())
        # the counters run from here, across reset(): a service resets the track on a camera
        # restart, a frame-size change or a failed frame, and its status (lost, redetections,
        # ...) read 0 again each time, just when an operator looked (service review)
        #: frames whose frame t was scaled (and turned) by the zoom (and turn) of the frame
        #: before (:func:`_zoomed`), or (a track's first pair in an approach) by the zoom of its
        #: own matches (:func:`_zoom_retry`)
        self.zoom_warps = 0
        self._lost = np.zeros(len(STATUS_NAMES), np.int64)
        self._few = 0  # matches dropped with a frame that kept too few (_track)
        self.redetections = 0
        # matches that followed their prediction (step 0 of .pyramid) rather than a search
        self.followed = 0
        # frames whose frame before was mapped onto their exposure (see .exposure)
        self.exposure_steps = 0
        self.reset()

    # -- state ---------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget every feature; the next frame is a first frame. The counters (lost,
        redetections, ...) go on."""
        self._prev: np.ndarray | None = None
        self._prev_pyr: Pyramid | None = None
        # the void regions at the frame's edges (.features.void_step): their record, how far
        # the features have moved (a frame's mean displacement, summed), and the last frame's
        # void (None: none)
        self._void_record: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._void_travel = 0.0
        self._void: np.ndarray | None = None
        # burnt-in overlays (OVERLAY_BAND): where each feature last moved from and the scene's
        # travel then, the scene's travel so far, and the cells found to hold one
        self._anchor = np.empty((0, 2), np.float64)
        self._anchor_at = np.empty(0, np.float64)
        self._scene_travel = 0.0
        self._overlay: np.ndarray | None = None  # (rows, cols) bool, cells of OVERLAY_CELL
        self._pos = np.empty((0, 2), np.float64)
        self._vel = np.empty((0, 2), np.float64)
        self._ids = np.empty(0, np.int64)
        self._next_id = 0
        self._acc_dx = 0.0
        self._acc_dy = 0.0
        self._acc_scale = 1.0
        self._motion = (0.0, 0.0)  # the image motion of the last frame, px
        self._zoom = 1.0  # its scale step, about the features' centroid in frame t+1
        self._seq: int | None = None  # the last frame's ``seq``, where given
        self._span = 1  # the frames the last step's motion (velocities, zoom, turn) spans
        # and its turn, radians (clockwise on the screen: x right, y down), and the turn of the
        # frame before it; NaN: not measured (no frame pair yet)
        self._turn = self._turn_before = np.nan
        self._frame = 0
        # the camera's noise, grey levels, estimated from the frames (see .noise), and the
        # frame it was estimated on: the wide sub-pixel window's side test allows for it
        self.noise = 0.0
        self._noise_at = -NOISE_EVERY
        # a frame whose noise is yet to be read, and its pre-filter's blur_sigma (see settle)
        self._noise_due: tuple[np.ndarray, float] | None = None

    @property
    def lost_total(self) -> int:
        """Features lost since the tracker was made: their window left the image, or their
        match was rejected."""
        return int(self._lost.sum()) + self._few

    @property
    def rejected_total(self) -> int:
        """Features lost because their match could not be trusted (not because their window
        left the image, nor because the frame's searches were over budget)."""
        return int(self._lost[BORDER:OVER].sum()) + self._few

    @property
    def over_budget(self) -> int:
        """Features lost since the tracker was made because their frame's searches had
        reached :data:`.pyramid.FRAME_WORK` (not searched)."""
        return int(self._lost[OVER])

    @property
    def lost_by(self) -> dict[str, int]:
        """Features lost since the tracker was made, by reason: ``left`` (the window left the
        image), ``cut`` (the minimum on an image edge: leaving it), ``border``, ``ambiguous``,
        ``runaway``, ``fb``, ``disagrees``, ``residual`` (rejected, see the module notes),
        ``budget`` (not searched: the frame's searches had reached
        :data:`.pyramid.FRAME_WORK`), ``few`` (the matches of a frame that kept fewer than
        FEW_KEPT of its features and at most FEW_SHARE, dropped: the track started again)."""
        by = {name: int(v) for name, v in zip(STATUS_NAMES[1:], self._lost[1:], strict=True)}
        by["few"] = self._few
        return by

    @property
    def frame_shape(self) -> tuple[int, int] | None:
        """(height, width) of the track's last frame; None before its first."""
        return None if self._prev is None else (int(self._prev.shape[0]),
                                                int(self._prev.shape[1]))

    @property
    def params(self) -> TrackerParams:
        return self._params

    def set_params(self, params: TrackerParams) -> None:
        """Apply new parameters from the next frame on; features already tracked are kept."""
        self._params = params
        self._weights = window_weights(params.weights, params.corr_half)
        self._wsum = float(self._weights.sum())
        self._plan: tuple[float, TrackPlan] | None = None  # (noise, the plan made for it)

    @property
    def points(self) -> np.ndarray:
        return self._pos.copy()

    # -- processing ----------------------------------------------------------------------
    @property
    def held(self) -> np.ndarray:
        """Which of the current features the next frame first follows from its prediction
        (step 0 of :mod:`.pyramid`): every one (see :meth:`_add_features`)."""
        return self._held(len(self._pos)).copy()

    def _held(self, n: int) -> np.ndarray:
        """:attr:`held` for the kernel, which only reads it: a view of an array kept and
        grown as needed (np.ones every frame was ~60 us of a service's frame at 30 fps, where
        every call starts from cold caches)."""
        if len(self._all_held) < n:
            self._all_held = np.ones(max(n, 2 * len(self._all_held)), np.bool_)
        return self._all_held[:n]

    def process(self, gray: np.ndarray, seq: int | None = None) -> Estimate:
        """Pre-process and track one (H, W) uint8 frame; t_ms covers both."""
        t0 = time.perf_counter()
        pre = preprocess(gray, self._params)
        return self.update(pre, seq=seq, t_start=t0)

    def update(self, pre: Preprocessed, seq: int | None = None,
               t_start: float | None = None) -> Estimate:
        """Track one pre-processed frame and return its estimate.

        ``t_start`` (a ``time.perf_counter()`` value) lets the caller include its own earlier
        work, such as pre-processing, in ``t_ms``.
        """
        t0 = time.perf_counter() if t_start is None else t_start
        self.settle()
        p = self._params
        frame = pre.filtered
        first = self._prev is None
        if not first and self._prev is not None and self._prev.shape != frame.shape:
            raise ValueError(f"frame size {frame.shape[::-1]} differs from the previous "
                             f"{self._prev.shape[::-1]} (width, height)")
        # the paper's tracker needs no pyramid (see _track)
        pyr = None if _single_level(p) else build_pyramid(frame, p.levels)
        gap = self._gap(seq)
        self._find_void(frame)
        if first:
            self._add_features(pre, frame.shape)
        else:
            self._track(frame, pyr, gap / self._span)
            self._span = gap
            lost_all = len(self._pos) == 0
            if len(self._pos) < p.redetect_fraction * p.max_features:
                self._add_features(pre, frame.shape)
            if lost_all and len(self._pos):
                # every feature was lost (a covered lens, a dark spell, a jump no match
                # survived): those found now begin a new track. Nothing measured the motion
                # in between, so the motion and scale since the track began start again,
                # and `first` says so (carried on, dx and scale went on from the old
                # track's as if the new features were the old ones)
                first = True
                self._acc_dx = self._acc_dy = 0.0
                self._acc_scale = 1.0
        self._seq = None if seq is None else int(seq)
        self._prev = frame
        self._prev_pyr = pyr
        if p.subpixel and p.refine_half and self._frame - self._noise_at >= NOISE_EVERY:
            # read by settle(), off the estimate's path; in force from the next frame on
            self._noise_due = (frame, p.blur_sigma)
            self._noise_at = self._frame
        if len(self._pos):
            xc, yc, xe, ye = centroid_scatter(self._pos)
        else:
            # no feature, no centroid: the image centre and no scatter, so that every number
            # of the estimate is finite (a NaN cannot be sent, nor written as JSON)
            xc, yc = (frame.shape[1] - 1) / 2.0, (frame.shape[0] - 1) / 2.0
            xe = ye = 0.0
        est = Estimate(
            seq=self._frame if seq is None else int(seq), npi=len(self._pos),
            xc=xc, yc=yc, xe=xe, ye=ye, dx=self._acc_dx, dy=self._acc_dy,
            scale=self._acc_scale, t_ms=(time.perf_counter() - t0) * 1e3, first=first,
            valid=len(self._pos) >= MIN_VALID_NPI, ids=self._ids.copy(), points=self._pos.copy())
        self._frame += 1
        return est

    def _gap(self, seq: int | None) -> int:
        """Frames from the last frame to this one: ``seq``'s step, 1 where either has no
        ``seq`` or it did not move on (a new track starts there), at most MAX_GAP."""
        if seq is None or self._seq is None or int(seq) <= self._seq:
            return 1
        return min(int(seq) - self._seq, MAX_GAP)

    def settle(self) -> None:
        """Work the last frame left for later, which its estimate does not wait for: the
        camera's noise read from it (every NOISE_EVERY frames, ~0.2 ms at 256 x 256 back to
        back, ~1.5 ms in a service at 30 fps, where every frame's work starts from cold
        caches), in force from the next frame on. A service calls it once the estimate is
        out; :meth:`update` calls it first where nobody did, so the estimates are the same
        either way."""
        if self._noise_due is not None:
            frame, blur_sigma = self._noise_due
            self._noise_due = None
            self.noise = noise_level(frame, blur_sigma)

    def _track(self, frame: np.ndarray, pyr: Pyramid | None, ahead: float = 1.0) -> None:
        """Track the features into ``frame``, their motion extrapolated ``ahead`` times the
        last step's (frames skipped, :meth:`_gap`)."""
        p = self._params
        vel, zoom = self._vel, self._zoom
        if ahead != 1.0:
            vel, zoom = vel * ahead, zoom ** ahead
        assert self._prev is not None
        if len(self._pos) == 0:
            self._motion = (0.0, 0.0)
            self._zoom = 1.0
            self._turn = self._turn_before = np.nan
            return
        if pyr is None:
            # the paper's tracker: its single-level search straight from track_ssd, no pyramid
            # (the same matches as track_pyramid at one level, tested; but not its per-frame
            # overhead, which the paper's factorial design would time)
            anchors, centers = _predict(self._pos, vel)
            why = np.empty(len(anchors), np.int8)
            match, ssd, ok = track_ssd(self._prev, frame, anchors, centers,
                                       corr_half=p.corr_half, search_half=p.search_half,
                                       weights=self._weights, search=p.search,
                                       work=FRAME_WORK, status=why)
            found = self._pos + (match - anchors)
            status = np.where(ok, OK, np.where(why == OVER, OVER, LEFT)).astype(np.int8)
        else:
            prev = self._prev_pyr
            if prev is None or prev.levels != pyr.levels:  # the levels changed with the params
                prev = build_pyramid(self._prev, p.levels)
            pts = self._pos
            turn = self._turn_ahead() * ahead
            zoomed = abs(zoom - 1.0) > ZOOM_WARP or abs(turn) > TURN_WARP
            if zoomed:
                # an approach (or a retreat), a roll: frame t scaled and turned by the zoom and
                # turn of the frame before, about the features' centroid, so that each
                # template shows its patch at the size and angle it has in frame t+1; the
                # features where that puts them
                prev, pts = _zoomed(self._prev, pts, zoom, p.levels, turn)
                self.zoom_warps += 1
            mapped = self._exposed(prev, pyr)
            self.exposure_steps += mapped is not prev
            prev = mapped
            # the frame's searches, the zoom retry's included, draw on one FRAME_WORK: each
            # had one of its own, and a frame of stripes at search 128 and a Gaussian 38 px
            # window took 4.7 s, two budgets of 2.3 s (a fuzzer's case; the launcher's hang
            # timeout is 5 s)
            budget = np.array((FRAME_WORK,), np.int64)
            found, ssd, status, taken = self._search(prev, pyr, pts, self._pos + vel, budget)
            retry = _zoom_retry(self._pos, found, status)
            if retry is not None:
                # a zoom or a turn no frame before measured (a track's first pair taken in an
                # approach or a spin), or not the one it did (a turn that reverses: frame t
                # turned 5 degrees the wrong way kept 41 of ~90 features, and 9 taken anew
                # beside them locked onto the knit a period away, the scale reading 1.0245 for
                # 1 eight frames later, all valid; a hunt of robot motions): searched again
                # with frame t scaled and turned by those of the matches found, each feature
                # predicted by them; kept if it finds more
                zoom, turn, preds = retry
                again, pts = _zoomed(self._prev, self._pos, zoom, p.levels, turn)
                second = self._search(self._exposed(again, pyr), pyr, pts, preds, budget)
                if np.count_nonzero(second[2] == OK) > np.count_nonzero(status == OK):
                    found, ssd, status, taken = second
                    self.zoom_warps += 1
            self.followed += int(np.count_nonzero(taken))
        if self._void is not None:
            self._off_picture(found, status, frame.shape)
        h, w = frame.shape
        if len(found):
            self._off_overlay(found, status, h, w)
        old_ids = self._ids
        pos, vel, ids, lost, moved, dx, dy, scale, turn = _advance(
            self._pos, found, ssd, status, self._ids, self._wsum, float(p.max_residual))
        if 0 < len(pos) < FEW_KEPT and len(pos) <= FEW_SHARE * len(self._pos):
            # fewer than FEW_KEPT of the frame's features kept, and almost none of many
            # (a scene cut, the lens covered from one frame to the next): those kept are as
            # likely lookalikes as the same points, and too few for the step's inlier test. A
            # cut from RubberWhale to Grove2 kept 2 of 89, moved (+26, -30) and (-9, +0.5) px,
            # and their mean stepped dx, dy by (+8.8, -14.6) px in an estimate marked valid.
            # They are dropped, lost as "few", and the track starts again (update: every
            # feature lost). A sparse track (a dim scene's 5 features keeping 2) is no cut:
            # restarted there, a rendered dim sequence's motion was 29 px off, not 1.9
            self._few += len(pos)
            pos, vel, ids = pos[:0], vel[:0], ids[:0]
            moved = False
        self._anchor, self._anchor_at, self._scene_travel = _overlay_after(
            old_ids, ids, pos, vel, self._anchor, self._anchor_at, self._scene_travel, h, w,
            OVERLAY_BAND, OVERLAY_STILL)
        if moved:
            self._acc_dx += dx
            self._acc_dy += dy
            self._acc_scale *= scale
        self._motion = (dx, dy) if moved else (0.0, 0.0)
        # a scale step beyond ZOOM_RANGE is a frame's error, not an approach: not extrapolated
        self._zoom = scale if moved and ZOOM_RANGE[0] <= scale <= ZOOM_RANGE[1] else 1.0
        self._turn_before = self._turn
        self._turn = turn if moved and abs(turn) <= TURN_MAX else 0.0
        self._lost += lost
        if len(vel) and self._void_record is not None:  # only while runs are followed
            self._void_travel += float(np.abs(vel).mean()) * 2.0  # |dx| + |dy|, over the kept
        self._pos = pos
        self._vel = vel
        self._ids = ids

    def _off_overlay(self, found: np.ndarray, status: np.ndarray, h: int, w: int) -> None:
        """Mark the matches on a burnt-in overlay (OVERLAY_BAND) as having left the picture
        (status LEFT, in place), and remember their cells; and those within cells known to
        hold one. The scene's travel counts this frame's step too, so that a fast pan proves
        an overlay at its first frame."""
        mask = self._overlay
        if mask is not None:
            _drop_in_cells(found, status, mask, OVERLAY_CELL)
        travel = _travel_now(self._pos, found, status, self._scene_travel, h, w, OVERLAY_BAND)
        if travel < OVERLAY_PROOF:
            return
        if mask is None:
            mask = np.zeros(((h + OVERLAY_CELL - 1) // OVERLAY_CELL,
                             (w + OVERLAY_CELL - 1) // OVERLAY_CELL), np.bool_)
        if _overlay_flags(found, status, self._anchor, self._anchor_at, travel, h, w,
                          OVERLAY_BAND, OVERLAY_STILL, OVERLAY_PROOF, mask, OVERLAY_CELL):
            self._overlay = mask

    def _outside_overlay(self, pre: Preprocessed) -> np.ndarray:
        """The frame's candidates with the cells of a burnt-in overlay left out before its
        THRES_PERCENT strongest are taken: its white-on-black text holds the frame's strongest
        corners, and they took most of them (RubberWhale approaching behind a timestamp kept 3
        features of 54, none found again). Computed here, from the filtered frame, only on a
        frame that selects features (~0.1 ms at 256 x 256)."""
        assert self._overlay is not None
        grad, floor = strength_of(pre.filtered, self._params)
        _clear_cells(grad, self._overlay, OVERLAY_CELL)
        return candidates_above(grad, floor, self._params)[0]

    def _find_void(self, frame: np.ndarray) -> None:
        """Find the void regions at the edges of ``frame`` (bars, a lens's dark corners:
        :func:`.features.void_runs`): those that stayed while the features moved
        (:func:`.features.void_step`). A frame with no dark run at its edges, most, costs
        ~2 us at 256 x 256 (the runs' scan)."""
        runs, any_run = void_runs(frame, VOID_LEVEL, VOID_TOLERANCE)
        record = self._void_record
        if not any_run:
            self._void = self._void_record = None  # nothing to follow: the record starts anew
            return
        if record is None or record[0].shape != runs.shape:
            record = self._void_record = (np.zeros_like(runs), np.zeros(runs.shape, np.float64),
                                          np.zeros(runs.shape, np.bool_))
        void, found = void_step(runs, *record, self._void_travel, VOID_SETTLE, VOID_PROOF)
        self._void = void if found else None

    def _void_margin(self) -> int:
        """How near a void region a feature may come, px: its widest window's half-width
        and the pre-filter's blur of the region's edge."""
        p = self._params
        return max(p.corr_half, p.refine_half) + VOID_BLUR

    def _off_picture(self, found: np.ndarray, status: np.ndarray,
                     shape: tuple[int, int]) -> None:
        """Mark the matches whose window reaches a void region of the frame as having left
        the picture (status LEFT, in place): a region that does not move with the scene pulls
        a match against it."""
        ok = np.flatnonzero(status == OK)
        if len(ok):
            assert self._void is not None
            gone = near_void(np.ascontiguousarray(found[ok]), self._void, shape,
                             self._void_margin())
            status[ok[gone]] = LEFT

    def _turn_ahead(self) -> float:
        """The turn to expect from frame t to t+1: the last frame's where the one before
        turned the same way by about as much (within TURN_STEADY of it: a roll's rate changes
        smoothly), else 0. A shake turns back and forth: frame t turned by the last frame's
        turn then made the templates fit worse than not turned (frames jittering by up to 4
        degrees and 6 px: medians 0.039 to 0.050 px and 3 % of one source's pairs off by more
        than 2 px, against 0.027 to 0.036 and 0.99 %)."""
        last, before = self._turn, self._turn_before  # math, not numpy: every frame, cold
        if math.isnan(last):
            return 0.0
        if math.isnan(before) or (last * before > 0.0
                                and abs(last - before) <= TURN_STEADY * abs(last)):
            return last  # a track's second pair has one turn measured before it: taken
        return 0.0

    def rehearse(self) -> bool:
        """Run a frame's search on a tiny job, keeping nothing: the first two features
        tracked from the last frame into itself, through the same calls and kernels as a
        frame's (:class:`~vistrack.services.runtime.Rehearsal`: a service at 30 fps runs it
        just before the next frame is expected, whose work then finds its code warm). False
        where there is nothing to rehearse on: no frame or feature yet, or the paper's
        tracker (no pyramid)."""
        pyr = self._prev_pyr
        if pyr is None or len(self._pos) == 0:
            return False
        pts = self._pos[:2].copy()
        self._search(pyr, pyr, pts, pts, np.array((FRAME_WORK,), np.int64))
        return True

    def _exposed(self, prev: Pyramid, pyr: Pyramid) -> Pyramid:
        """Frame t's pyramid in frame t+1's exposure, where it changed (``exposure``)."""
        p = self._params
        if not p.exposure:
            return prev
        mapped = compensate(prev, pyr, self._motion, p.noise_sigma)
        return compensate_rows(mapped, pyr, self._motion, p.noise_sigma)

    def _search(self, prev: Pyramid, pyr: Pyramid, pts: np.ndarray, preds: np.ndarray,
                budget: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The features at ``pts`` of frame t (``prev``) tracked into frame t+1 (``pyr``) from
        ``preds``: positions, S, status, and which step 0 took (:func:`.track_pyramid`);
        ``budget``: what is left of the frame's FRAME_WORK, drawn on."""
        noise = max(self._params.noise_sigma, self.noise)
        if self._plan is None or self._plan[0] != noise:  # new parameters, a new noise
            self._plan = noise, track_plan(self._params, noise, self._weights)
        taken = np.zeros(len(pts), np.bool_)
        found, ssd, status = self._plan[1].track(prev, pyr, pts, preds,
                                                 held=self._held(len(pts)), followed=taken,
                                                 budget=budget)
        return found, ssd, status, taken

    def _add_features(self, pre: Preprocessed, shape: tuple[int, int]) -> None:
        p = self._params
        room = p.max_features - len(self._pos)
        if room <= 0:
            return
        cands = pre.candidates if self._overlay is None else self._outside_overlay(pre)
        # a feature's correlation window must fit in the frame: preprocessing's candidates
        # keep that margin, but a peer's preprocessing/frame need not (corner candidates of
        # a black 8 x 8 frame were 4 features of an estimate marked valid)
        margin = p.corr_half + 1
        h, w = shape
        xs, ys = cands[:, 0], cands[:, 1]
        inside = (xs >= margin) & (xs < w - margin) & (ys >= margin) & (ys < h - margin)
        if self._void is not None and len(cands):
            inside &= ~near_void(np.ascontiguousarray(cands, np.float64), self._void, shape,
                                 self._void_margin())
        if not inside.all():
            cands = cands[inside]
        chosen = select_features(cands, shape, p, existing=self._pos, max_count=room)
        if len(chosen) == 0:
            return
        new = cands[chosen].astype(np.float64)
        # a new feature's first step is predicted by the image motion of the frame before,
        # its scale step included (about the tracked features' centroid: an approach moves
        # the features near the frame's edges fastest); the paper's tracker has no finite
        # difference for it yet, so zero velocity
        if _single_level(p):
            vel = np.zeros_like(new)
        else:
            vel = np.tile(np.array(self._motion), (len(new), 1))
            turn = self._turn_ahead()
            if (self._zoom != 1.0 or turn != 0.0) and len(self._pos):
                c, s = np.cos(turn), np.sin(turn)
                step = self._zoom * np.array([[c, -s], [s, c]]) - np.eye(2)
                vel += (new - self._pos.mean(axis=0)) @ step.T
        self._pos = np.concatenate([self._pos, new])
        self._vel = np.concatenate([self._vel, vel])
        self._anchor = np.concatenate([self._anchor, new])
        self._anchor_at = np.concatenate([self._anchor_at,
                                          np.full(len(new), self._scene_travel)])
        self._ids = np.concatenate([self._ids, np.arange(self._next_id,
                                                         self._next_id + len(new))])
        # a new feature is followed from its prediction as the tracked ones are (a search
        # where it does not follow). Re-detected mid-track, it is predicted as the features
        # tracked through the frame moved: on the scoreboard's rendered sequences that lost
        # fewer features to the checks (e.g. RubberWhale with exposure changes: 31 and 40 to
        # ambiguity and the way back, against 48 and 57) and took the approaches' gross errors
        # from 0.80, 0.60 and 0.43 % to 0.63, 0.00 and 0.14 %. A first frame's, from no motion
        # (Bouguet's coarse to fine from the prediction, as LK starts): on the bench's first
        # pair 97 of 100 features tracked instead of 86, the 11 more on a small object moving
        # -1.37 px against the background, which the coarse search's window straddled. A first
        # pair taken in motion, which most do not follow, is searched, and tracked again
        # around the frame-wide shift where its matches moved beyond the search's reach
        self._next_id += len(new)
        if self._frame > 0:
            self.redetections += 1


def track_plan(p: TrackerParams, noise: float, weights: np.ndarray | None = None
               ) -> TrackPlan:
    """The settings with which the tracker of ``p`` tracks a frame pair coarse to fine
    (:class:`.pyramid.TrackPlan`), for a camera noise of ``noise`` grey levels (``p``'s
    ``noise_sigma`` or more: the tracker's estimate of it, :mod:`.noise`); ``weights``: ``p``'s
    window, where already made."""
    wts = window_weights(p.weights, p.corr_half) if weights is None else weights
    # what noise alone adds to S at a perfect match: both frames' noise, over the window
    allowance = 2.0 * p.noise_sigma ** 2 * float(wts.sum())
    return TrackPlan(corr_half=p.corr_half, search_half=p.search_half, weights=wts,
                     subpixel=p.subpixel, search=p.search, uniqueness=p.uniqueness,
                     allowance=allowance, reject_border=p.reject_border,
                     guided_retry=p.guided_retry, max_fb_error=p.max_fb_error,
                     consensus=p.consensus, wide_half=p.refine_half, **wide_tests(noise),
                     follow=p.follow)


def _single_level(p: TrackerParams) -> bool:
    """Whether ``p`` is the paper's tracker (:meth:`TrackerParams.paper`): one level, integer
    positions, no test of a match."""
    return (p.levels == 1 and not p.subpixel and not p.reject_border and not p.guided_retry
            and p.uniqueness == 0.0 and p.max_fb_error == 0.0 and p.consensus == 0.0)


@nb.njit(cache=True, nogil=True)
def _predict(pos, vel):  # pragma: no cover - numba
    """Template centres (the rounded positions) and search centres (constant velocity)."""
    n = pos.shape[0]
    anchors = np.empty((n, 2), np.int64)
    centers = np.empty((n, 2), np.int64)
    for i in range(n):
        for c in range(2):
            anchors[i, c] = int(np.rint(pos[i, c]))
            centers[i, c] = int(np.rint(pos[i, c] + vel[i, c]))
    return anchors, centers


def _zoom_retry(pos: np.ndarray, found: np.ndarray, status: np.ndarray
                ) -> tuple[float, float, np.ndarray] | None:
    """Where a frame pair searched without a zoom or a turn lost most of its features and the
    matches found zoom by more than ZOOM_WARP or turn by more than TURN_WARP: (that zoom, that
    turn, every feature's position predicted by them); else None.

    Many of a first pair's few matches may be wrong (1 to 8 of 22 to 52 on the approaches at
    1241 x 376): the similarity is the one most matches agree with, to within RETRY_FIT_PX
    (each segment between two matches, half or a third of the list apart and ZOOM_RADIUS px
    long or more, proposes the similarity that maps it; the one most matches fit wins), then
    fitted to those matches by least squares. Medians over the segments, as :func:`_turn_step`
    takes them of a frame's checked matches, broke down there: Venus's zoom of 1.10 came out
    1.02, and 7 of its 46 matches were off by more than 2 px."""
    ok = status == OK
    found_ok = int(np.count_nonzero(ok))
    if found_ok < ZOOM_FOUND or found_ok >= ZOOM_RETRY_SHARE * len(pos):
        return None
    # points as complex numbers: a similarity is z p + t
    a = pos[ok] @ np.array([1.0, 1.0j])
    b = found[ok] @ np.array([1.0, 1.0j])
    first = np.tile(np.arange(found_ok), 2)
    second = np.concatenate([(np.arange(found_ok) + k) % found_ok
                             for k in (found_ok // 2, found_ok // 3)])
    u = a[second] - a[first]
    long = np.abs(u) >= ZOOM_RADIUS
    if np.count_nonzero(long) < ZOOM_FOUND:
        return None
    # at most RETRY_PROPOSALS of them, spread over the list: each is tried on every match
    pick = np.flatnonzero(long)[::max(1, -(-int(np.count_nonzero(long)) // RETRY_PROPOSALS))]
    z = (b[second[pick]] - b[first[pick]]) / u[pick]
    t = b[first[pick]] - z * a[first[pick]]
    fits = np.abs(z[:, None] * a[None, :] + t[:, None] - b[None, :]) <= RETRY_FIT_PX
    agree = fits[int(np.argmax(fits.sum(axis=1)))]
    if np.count_nonzero(agree) < ZOOM_FOUND:
        return None
    ma, mb = a[agree].mean(), b[agree].mean()
    da = a[agree] - ma
    zf = np.sum((b[agree] - mb) * np.conj(da)) / np.sum(np.abs(da) ** 2)
    zoom, turn = float(np.abs(zf)), float(np.angle(zf))
    if not (ZOOM_RANGE[0] <= zoom <= ZOOM_RANGE[1] and abs(turn) <= TURN_MAX) or (
            abs(zoom - 1.0) <= ZOOM_WARP and abs(turn) <= TURN_WARP):
        return None
    moved = zf * (pos @ np.array([1.0, 1.0j]) - ma) + mb
    return zoom, turn, np.column_stack([moved.real, moved.imag])


def _zoomed(frame: np.ndarray, pts: np.ndarray, zoom: float, levels: int, turn: float = 0.0
            ) -> tuple[Pyramid, np.ndarray]:
    """The pyramid of ``frame`` (frame t) scaled by ``zoom`` about (near) the centroid of
    ``pts``, and turned by ``turn`` radians about it where that exceeds TURN_WARP, and the
    points where that puts them.

    A translation's template taken from frame t does not fit frame t+1 when the view zooms
    between them: at 10 % a frame the SSD's valley is broad and low everywhere, the
    uniqueness test rejects most features as ambiguous, and those far from the centre are
    missed. Scaled by the zoom measured in the frame before (a robot's approach changes
    slowly), each template shows its patch at the size it has in frame t+1; the search and
    the sub-pixel refinement then measure the rest of the motion as before.

    Bicubic: bilinear blurred the templates, and the approaches' drift over 12 frames rose
    from 0.09 to 0.30 px to 0.16 to 0.63. By ``cv2.resize`` and a cut at a whole offset (the
    centre of the scaling is any point near the features: the search finds the translation),
    5 times faster than ``cv2.warpAffine``'s bicubic (54 against 266 us at 256 x 256, 0.63
    against 3.6 ms at 1280 x 720). A turn needs the warp: by ``cv2.warpAffine``, bicubic,
    about the centroid itself (bilinear, 5 times faster, left the rolls of 3 and 10 degrees a
    frame 1.3 to 1.8 times the drift: 0.18 to 0.38 px over 30 frames against 0.09 to 0.22)."""
    h, w = frame.shape
    if abs(turn) > TURN_WARP:
        c = pts.mean(axis=0)
        m = zoom * np.array([[np.cos(turn), -np.sin(turn)], [np.sin(turn), np.cos(turn)]])
        affine = np.hstack([m, (c - m @ c)[:, None]])
        turned = cv2.warpAffine(frame, affine, (w, h), flags=cv2.INTER_CUBIC,
                                borderMode=cv2.BORDER_REPLICATE)
        return build_pyramid(turned, levels), pts @ affine[:, :2].T + affine[:, 2]
    big_w, big_h = max(1, round(w * zoom)), max(1, round(h * zoom))
    sx, sy = big_w / w, big_h / h
    big = cv2.resize(frame, (big_w, big_h), interpolation=cv2.INTER_CUBIC)
    # the resized frame holds frame t's point u at s u + (s - 1) / 2 (pixel centres); it is
    # cut at the whole offset k that keeps the centroid c where it was, k ~ (s - 1)(c + 1/2)
    c = pts.mean(axis=0)
    kx = int(round((sx - 1.0) * (c[0] + 0.5)))
    ky = int(round((sy - 1.0) * (c[1] + 0.5)))
    left, top = max(0, -kx), max(0, -ky)
    right, bottom = max(0, kx + w - big_w), max(0, ky + h - big_h)
    if left or top or right or bottom:
        big = cv2.copyMakeBorder(big, top, bottom, left, right, cv2.BORDER_REPLICATE)
    scaled = np.ascontiguousarray(big[ky + top:ky + top + h, kx + left:kx + left + w])
    moved = np.column_stack([sx * pts[:, 0] + 0.5 * (sx - 1.0) - kx,
                             sy * pts[:, 1] + 0.5 * (sy - 1.0) - ky])
    return build_pyramid(scaled, levels), moved


@nb.njit(cache=True, nogil=True, inline="always")
def _in_band(x, y, h, w, band):  # pragma: no cover - numba
    """Whether (x, y) lies within ``band`` times the frame's size of its edges."""
    bx = band * w
    by = band * h
    return x < bx or x > w - 1 - bx or y < by or y > h - 1 - by


@nb.njit(cache=True, nogil=True)
def _overlay_flags(found, status, anchor, at, travel, h, w, band, still, proof, mask,
                   cell):  # pragma: no cover - numba
    """Mark LEFT (in place) the matches found (status OK) within ``band`` of the frame's edges
    that stand within ``still`` px of their ``anchor`` while the scene travelled ``proof`` px
    or more since (``travel`` - ``at``): a burnt-in overlay (OVERLAY_BAND); set their cells
    of ``cell`` px and the 8 around each in ``mask``. Returns how many."""
    marked = 0
    rows, cols = mask.shape
    for i in range(found.shape[0]):
        if status[i] != OK or travel - at[i] < proof:
            continue
        x = found[i, 0]
        y = found[i, 1]
        ex = x - anchor[i, 0]
        ey = y - anchor[i, 1]
        if ex * ex + ey * ey <= still * still and _in_band(x, y, h, w, band):
            status[i] = LEFT
            marked += 1
            cy = int(y) // cell
            cx = int(x) // cell
            for yy in range(max(cy - 1, 0), min(cy + 2, rows)):
                for xx in range(max(cx - 1, 0), min(cx + 2, cols)):
                    mask[yy, xx] = True
    return marked


@nb.njit(cache=True, nogil=True)
def _scene_step(steps, m):  # pragma: no cover - numba
    """How far the scene moved in a frame, from the |dx| + |dy| of its ``m`` features away
    from the edges (``steps[:m]``): their median, where 3 or more and at most
    OVERLAY_STILL_SHARE of them stood (within STILL_PX), else 0."""
    if m < 3:
        return 0.0
    still = 0
    for i in range(m):
        still += steps[i] <= STILL_PX
    return np.median(steps[:m]) if still <= OVERLAY_STILL_SHARE * m else 0.0


@nb.njit(cache=True, nogil=True)
def _travel_now(pos, found, status, travel, h, w, band):  # pragma: no cover - numba
    """The scene's travel with this frame's step: ``travel`` plus :func:`_scene_step` of the
    matches found (status OK) away from the frame's edges."""
    steps = np.empty(pos.shape[0], np.float64)
    m = 0
    for i in range(pos.shape[0]):
        if status[i] == OK and not _in_band(found[i, 0], found[i, 1], h, w, band):
            steps[m] = abs(found[i, 0] - pos[i, 0]) + abs(found[i, 1] - pos[i, 1])
            m += 1
    return travel + _scene_step(steps, m)


@nb.njit(cache=True, nogil=True)
def _drop_in_cells(found, status, mask, cell):  # pragma: no cover - numba
    """Mark LEFT (in place) the matches found (status OK) in a cell set in ``mask``."""
    rows, cols = mask.shape
    for i in range(found.shape[0]):
        if status[i] == OK:
            cy = int(found[i, 1]) // cell
            cx = int(found[i, 0]) // cell
            if 0 <= cy < rows and 0 <= cx < cols and mask[cy, cx]:
                status[i] = LEFT


@nb.njit(cache=True, nogil=True)
def _overlay_after(old_ids, ids, pos, vel, anchor, at, travel, h, w, band,
                   still):  # pragma: no cover - numba
    """The anchors (where each kept feature last moved from) and their travels for the
    features ``ids`` kept of ``old_ids`` (both increasing), a feature that moved beyond
    ``still`` px of its anchor anchored anew where it is; and the scene's travel, increased by
    :func:`_scene_step` of the kept features away from the edges. Returns (anchors, travels,
    travel)."""
    n = ids.shape[0]
    steps = np.empty(n, np.float64)
    m = 0
    for j in range(n):
        if not _in_band(pos[j, 0], pos[j, 1], h, w, band):
            steps[m] = abs(vel[j, 0]) + abs(vel[j, 1])
            m += 1
    # the travel after this frame: where a feature is anchored now, the scene has moved this
    # frame's step already (anchored at the travel before it, a feature of a stop-and-go that
    # stood in the next frame was taken for an overlay: 0.08 -> 0.42 % of a rolling
    # oscillation's pairs off by more than 2 px)
    travel += _scene_step(steps, m)
    new_anchor = np.empty((n, 2), np.float64)
    new_at = np.empty(n, np.float64)
    i = 0
    for j in range(n):
        while old_ids[i] != ids[j]:
            i += 1
        ax = anchor[i, 0]
        ay = anchor[i, 1]
        ex = pos[j, 0] - ax
        ey = pos[j, 1] - ay
        if ex * ex + ey * ey > still * still:
            new_anchor[j, 0] = pos[j, 0]
            new_anchor[j, 1] = pos[j, 1]
            new_at[j] = travel
        else:
            new_anchor[j, 0] = ax
            new_anchor[j, 1] = ay
            new_at[j] = at[i]
    return new_anchor, new_at, travel


@nb.njit(cache=True, nogil=True)
def _clear_cells(grad, mask, cell):  # pragma: no cover - numba
    """Zero ``grad`` (H, W) in the cells set in ``mask``, in place."""
    h, w = grad.shape
    for cy in range(mask.shape[0]):
        for cx in range(mask.shape[1]):
            if mask[cy, cx]:
                for y in range(cy * cell, min((cy + 1) * cell, h)):
                    for x in range(cx * cell, min((cx + 1) * cell, w)):
                        grad[y, x] = 0.0


@nb.njit(cache=True, nogil=True)
def _advance(pos, found, ssd, status, ids, wsum, max_residual):  # pragma: no cover - numba
    """One frame's bookkeeping after the search, in one kernel rather than ~20 small numpy
    calls: the survivors' new positions and velocities, the losses by reason (a found match
    whose RMS residual exceeds ``max_residual`` is rejected as RESIDUAL) and the incremental
    motion of the survivors.

    Returns (positions, velocities, ids of the survivors, losses (len(STATUS_NAMES),) by
    status, whether any survived, dx, dy, scale, turn (:func:`_turn_step`)).
    """
    n = pos.shape[0]
    keep = np.empty(n, np.bool_)
    lost = np.zeros(len(STATUS_NAMES), np.int64)
    kept = 0
    for i in range(n):
        st = status[i]
        if st == OK and np.sqrt(ssd[i] / wsum) > max_residual:
            st = RESIDUAL
        keep[i] = st == OK
        if st != OK:
            lost[st] += 1
        kept += keep[i]
    new_pos = np.empty((kept, 2), np.float64)
    before = np.empty((kept, 2), np.float64)
    vel = np.empty((kept, 2), np.float64)
    new_ids = np.empty(kept, ids.dtype)
    j = 0
    for i in range(n):
        if keep[i]:
            for c in range(2):
                new_pos[j, c] = found[i, c]
                before[j, c] = pos[i, c]
                vel[j, c] = found[i, c] - pos[i, c]
            new_ids[j] = ids[i]
            j += 1
    dx = dy = 0.0
    scale = 1.0
    if kept:
        dx, dy, scale = _incremental_motion(before, new_pos)
    return new_pos, vel, new_ids, lost, kept > 0, dx, dy, scale, _turn_step(before, new_pos)


@nb.njit(cache=True, nogil=True)
def _turn_step(a, b):  # pragma: no cover - numba
    """How far the points ``a`` (frame t) turned (radians) to ``b`` (frame t+1): the median
    of the angles by which the segments between pairs of them turned (each point paired with
    the ones half and a third of the list away), over the segments at least ZOOM_RADIUS px
    long in frame t (shorter, a pixel's error is a large angle). Pairs need no centre of the
    turn, and the median is robust to a few wrong matches (the per-axis median point, tried
    first, is no centre of a turn: 5 wrong matches of 40 made a 7 degree turn 2). 0 where
    fewer than ZOOM_FOUND segments are that long. (The frame's zoom is Eq. (2)'s scatter
    ratio, :func:`.motion.incremental_motion`; the median of the segments' length ratios,
    once computed here beside the turn, was never read.)

    The median is selected by each angle's pseudo-angle (:func:`_pseudo_angle`, in the same
    order as the angle, a division), and only the middle one or two angles are taken with
    ``arctan2``: the ~190 of every frame were 2.8 of its ~7 us of bookkeeping."""
    n = a.shape[0]
    if n < ZOOM_FOUND:
        return 0.0
    cross = np.empty(2 * n, np.float64)
    dot = np.empty(2 * n, np.float64)
    key = np.empty(2 * n, np.float64)
    k = 0
    for stride in (n // 2, n // 3):
        for i in range(n):
            j = (i + stride) % n
            ux = a[j, 0] - a[i, 0]
            uy = a[j, 1] - a[i, 1]
            if ux * ux + uy * uy < ZOOM_RADIUS * ZOOM_RADIUS:
                continue
            vx = b[j, 0] - b[i, 0]
            vy = b[j, 1] - b[i, 1]
            cross[k] = ux * vy - uy * vx
            dot[k] = ux * vx + uy * vy
            key[k] = _pseudo_angle(cross[k], dot[k])
            k += 1
    if k < ZOOM_FOUND:
        return 0.0
    keys = key[:k].copy()
    # reordered: keys[k // 2] is the middle key, keys[:k // 2] the smaller ones
    _median_small(keys)
    turn = _angle_of(keys[k // 2], key, cross, dot, k)
    if k % 2:
        return turn
    below = keys[0]  # the largest of the smaller ones: the lower middle key
    for i in range(1, k // 2):
        if keys[i] > below:
            below = keys[i]
    return 0.5 * (_angle_of(below, key, cross, dot, k) + turn)


@nb.njit(cache=True, nogil=True, inline="always")
def _pseudo_angle(c, d):  # pragma: no cover - numba
    """A number in [-2, 2] in the order of ``arctan2(c, d)`` over (-pi, pi] (the "diamond
    angle"): c / (|d| + |c|) where d >= 0, 2 - that where c >= 0 > d, -2 - that where both
    are negative."""
    r = abs(d) + abs(c)
    if r == 0.0:
        return 0.0
    t = c / r
    if d >= 0.0:
        return t
    return 2.0 - t if c >= 0.0 else -2.0 - t


@nb.njit(cache=True, nogil=True)
def _angle_of(value, key, cross, dot, k):  # pragma: no cover - numba
    """``arctan2`` of the segment whose pseudo-angle is ``value`` (one of ``key[:k]``)."""
    for i in range(k):
        if key[i] == value:
            return np.arctan2(cross[i], dot[i])
    return 0.0


def track_frames(frames: Iterable[np.ndarray], params: TrackerParams | None = None) -> list[
        Estimate]:
    """Run a fresh tracker over (H, W) uint8 frames; one Estimate per frame."""
    tracker = Tracker(params)
    return [tracker.process(f) for f in frames]


def over_budget_said(seq: int, unsearched: int) -> str:
    """What a frame whose searches reached :data:`FRAME_WORK` is said with, by the service
    and by ``vistrack track`` (each adds when it says it once)."""
    return (f"frame {seq}: {unsearched} features not searched, the frame's searches had "
            f"reached their budget ({FRAME_WORK:.3g} window pixels x displacements); smaller "
            "search_size, corr_size or max_features keep within it")


def timing(estimates: list[Estimate]) -> tuple[float, float]:
    """The paper's t1 (first frame) and tf (mean of the following frames), in ms; NaN where
    there is no such frame (no frames, or only one)."""
    if not estimates:
        return float("nan"), float("nan")
    t1 = estimates[0].t_ms
    rest = [e.t_ms for e in estimates[1:]]
    return t1, float(np.mean(rest)) if rest else float("nan")


def warm_up(on_compile: Callable[[], None] | None = None,
            params: TrackerParams | None = None) -> bool:
    """Compile (or load from numba's cache) every kernel the tracker uses, so that the first
    real frame, the paper's t1, measures the tracker and not the JIT: those of the default
    tracker, of its exhaustive search and of integer positions, and those of ``params`` (the
    paper's single-level search, ``--paper``: ~4 s more of a first run's compile, paid only
    by who uses it). Each set is warmed once a process; a later call for sets already warm
    returns at once.

    Parameters
    ----------
    on_compile : called once, as soon as a kernel is found missing from numba's on-disk cache
        and starts compiling (a first run, or edited kernels): the moment to say that the
        next half minute goes to the compiler. Not called when everything is cached.
    params : the parameters about to be used, if they may need kernels of their own.

    Returns
    -------
    Whether anything was compiled (False: every kernel came from the cache).
    """
    from ..synthetic import sequence

    if not _START_UP_KEYS:
        _START_UP_KEYS.update((_kernel_set(p), p) for p in _START_UP_SETS)
    keyed = dict(_START_UP_KEYS)
    if params is not None:
        keyed[_kernel_set(params)] = params  # its own, where it shares a set's key
    todo = {key: p for key, p in keyed.items() if key not in _WARM}
    if not todo:
        return False  # everything warm: the tuner asks before each of its timed runs
    with compile_watch(on_compile) as watch:
        for key, p in todo.items():
            small = p.replace(max_features=20, search_size=5, corr_size=5)
            if _kernel_set(small) != key:
                # windows whose sums need int64 (:func:`_kernel_set`): warmed at their size,
                # on frames where they fit with room to track
                small = p.replace(max_features=20, search_size=5)
            side = 64 + 4 * (max(small.corr_half, small.refine_half) + small.search_half)
            _WARMING.add(threading.get_ident())
            try:
                track_frames(sequence(3, size=(side, side), seed=1), small)
                exposure.warm()
                features.warm()
                _warm_overlay()
            finally:
                _WARMING.discard(threading.get_ident())
            _WARM.add(key)
    return watch.compiled


def _warm_overlay() -> None:
    """Compile (or load) the overlay's kernels that run only once one is found
    (OVERLAY_BAND), which a warm-up's frames need not show."""
    pts = np.zeros((1, 2), np.float64)
    status = np.zeros(1, np.int8)
    mask = np.zeros((2, 2), np.bool_)
    _overlay_flags(pts, status, pts, np.zeros(1), 0.0, 16, 16, OVERLAY_BAND, OVERLAY_STILL,
                   OVERLAY_PROOF, mask, OVERLAY_CELL)
    _drop_in_cells(pts, status, mask, OVERLAY_CELL)
    _clear_cells(np.zeros((16, 16), np.float32), mask, OVERLAY_CELL)


def kernels_warm(params: TrackerParams) -> bool:
    """Whether :func:`warm_up` has loaded the kernels ``params`` run in this process: False
    when tracking with them would first compile (or load) kernels of their own, for seconds
    on a cold cache."""
    return _kernel_set(params) in _WARM


def warming_up() -> bool:
    """Whether this thread is in :func:`warm_up` (whose compiles are expected)."""
    return threading.get_ident() in _WARMING


def _kernel_set(p: TrackerParams) -> tuple[bool, str, bool, str]:
    """What decides which kernels ``p`` runs: the search, the sub-pixel refinement, and the
    integer type its sums take (int64 for the largest windows, :func:`.pyramid.sum_type`).
    Their types depend on no other value."""
    single = _single_level(p)
    acc = "int32" if single else sum_type(window_weights(p.weights, p.corr_half),
                                          p.corr_half, p.refine_half if p.subpixel else -1)
    return single, p.search, p.subpixel, acc


#: the parameters whose kernels every warm-up loads: the default tracker's, of its
#: exhaustive search, and of integer positions
_START_UP_SETS = (TrackerParams(), TrackerParams(weights="gaussian", subpixel=False),
                  TrackerParams(search="exhaustive"))
#: their kernel sets (:func:`_kernel_set`), keyed once a process
_START_UP_KEYS: dict[tuple[bool, str, bool, str], TrackerParams] = {}
#: the kernel sets (:func:`_kernel_set`) this process has warmed up
_WARM: set[tuple[bool, str, bool, str]] = set()
#: the threads in :func:`warm_up`'s tracking
_WARMING: set[int] = set()


@contextlib.contextmanager
def compile_watch(on_compile: Callable[[], None] | None = None) -> Iterator[_CompileListener]:
    """Within the block, call ``on_compile`` once, when numba starts compiling a kernel (a
    dispatcher compiles only on a cache miss); the yielded listener's ``compiled`` tells
    afterwards whether anything was."""
    listener = _CompileListener(on_compile)
    with numba_event.install_listener("numba:compile", listener):
        yield listener


def kernel_cache_dir() -> str:
    """Where numba keeps the compiled kernels (``NUMBA_CACHE_DIR``, else beside the code)."""
    cache = getattr(_advance, "_cache", None)  # the dispatcher's cache locator knows best
    return str(getattr(cache, "_cache_path", "") or getattr(nb.config, "CACHE_DIR", "")
               or "numba's cache")


class _CompileListener(numba_event.Listener):
    """Notes numba's compile events: a dispatcher fires one only on a cache miss."""

    def __init__(self, on_compile: Callable[[], None] | None) -> None:
        self.compiled = False
        self._on_compile = on_compile

    def on_start(self, event: numba_event.Event) -> None:
        if not self.compiled:
            self.compiled = True
            if self._on_compile is not None:
                self._on_compile()

    def on_end(self, event: numba_event.Event) -> None:
        pass
