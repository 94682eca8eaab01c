"""Running the tracker as an experiment: the responses t1, tf, ex, ey of Section 6.1.

One *point* is one setting of the tracker parameters, run with a fresh
:class:`~vistrack.common.vision.Tracker` (the library code the services run) over a buffer of
grey frames. Its responses, as the paper defines them and ``docs/ARCHITECTURE.md`` makes precise:

``t1``
    wall time to process the first frame (pre-processing, feature selection, initialisation), ms.
``tf``
    mean wall time to process each following frame, ms.
``ex``, ``ey``
    mean absolute difference, over frames 1 .. n-1, between the run's estimated image motion
    since the first frame and that of a *reference run* with SEARCH_SIZE 50 and CORR_SIZE 30 and
    the run's other parameters, px. Frame 0 is left out: both motions are 0 there by definition.
``npi_mean``
    mean number of feature points per frame (the paper's NPI): the times scale with it.

Measurement choices (why)
-------------------------
* **Image motion = the estimate's accumulated robust motion** (``Estimate.dx``, ``dy``), not the
  raw centroid displacement ``xc - xc[0]``. The centroid moves whenever a feature is lost or
  re-detected (the paper's Table 1b: NPI 19 -> 8 moved xc by 6 px with no motion), and settings
  that lose features at different frames would differ by those jumps rather than by how well
  they track. ``dx``, ``dy`` accumulate the mean displacement of the features matched in both
  frames only, so they measure the tracking itself.
* **Times as the pipeline spends them.** The pre-processing service runs
  :func:`~vistrack.common.vision.preprocess` and the motion-estimation service
  ``Tracker.update`` (whose ``t_ms`` it publishes); a point's time per frame is the sum of the
  two, each measured with ``time.perf_counter`` after :func:`warm_up` compiled the numba kernels
  (the JIT is never timed). The paper's ``clock()`` counted processor time; wall time is what a
  robot waits for. Splitting the two lets the buffer be pre-processed once per distinct
  pre-processing (THRES_PERCENT, CORR_SIZE's border margin, the filter) rather than once per
  run: on a 30-frame 256x256 buffer this cut a tuning cycle from 4.6 to 3.2 s. The numbers
  tracked are identical to ``Tracker.process``'s.
* **Pre-processing is timed once, tracking in every pass.** Pre-processing does the same work
  whatever the windows: the pre-processings of a cycle differ in THRES_PERCENT (how many
  candidates are sorted) and in the border margin CORR_SIZE // 2 + 1 (which only moves the
  bounds of the candidates' scan; margins of 3 and 16 px measured the same within the timing
  noise on 256x256 to 1280x720 frames). So each distinct pre-processing runs once, timed frame
  by frame, and a point's candidates' time for frame i is the least that any pre-processing
  of the same work (filter, strength, THRES_PERCENT) took on frame i: the sweep's seven
  margins are seven samples of one cost, a whole run or more apart, as the timing passes are
  for the tracking (the filter, the same for all, is timed FILTER_TIMINGS times: below).
  Its cost grows with frames x pixels; timing it in every pass
  made a cycle at 1280x720 spend half its time pre-processing the same frames again (6.4 of
  11.8 s in one run). A slow spell over one pre-processing no longer shows as an effect of
  its CORR_SIZE either. The candidates (the gradient strength, the THRES_PERCENT selection
  and the floors: about two thirds of a frame's pre-processing) are timed apart, as the
  pipeline computes them only for the frames whose features it selects (the first, and each
  re-detection: :class:`_Watched` sees which frames a run reads them on), and those frames
  of the run are charged for them. A run whose features stay below the re-detection
  threshold pays on every frame, as the pipeline does (pre-processing computes them for
  every frame then, ``motion/demand``).
* **The filter and the strength once a buffer.** The filtered frame depends on the filter
  alone (``blur_sigma``, no factor of the design), and so do each frame's gradient strength
  and texture floor (not THRES_PERCENT nor the margin, which only threshold them): each is
  computed once for every pre-processing of the cycle, timed frame by frame, and the
  strength charged with each pre-processing's candidates. Computed per pre-processing, they
  were 13 copies of the same frames (360 MB at 1280x720) and 13 strengths of each frame, 14 %
  of a cycle's CPU there. The image pyramids the tracker builds are not shared: built once
  and read from memory a run later, they made the tracking itself 1.2 to 1.9 times slower at
  1280x720 (its reads no longer from the cache the build had just filled), a tf the pipeline
  never sees.
* **Noise: per-frame minimum over repeated, interleaved, shuffled passes** (of the tracking;
  pre-processing: above). A run is
  deterministic, so frame i does the same work in every repeat and any extra time is
  interference (other processes on this 2-core machine, interrupts, the garbage collector). The
  minimum over repeats of each frame's time estimates the interference-free cost (pre-processing
  and tracking each at their least-disturbed pass); ``tf`` is the mean over frames of those
  minima, ``t1`` the minimum of the first frame's. The thread's CPU time was tried instead and
  was no steadier: the two vCPUs share a core, so a busy neighbour slows the work itself (by up
  to 50 % for seconds at a time), it does not just pre-empt it. One run over a 30-frame buffer
  lasts some 30 ms, far shorter than such a spell, so repeats made back to back would share it:
  the repeats are *passes over all the points*, a whole pass apart. The first pass follows the
  run order; every later pass a fresh random order from the same seed, so a spell lands on
  different points in each pass rather than on the same neighbours, and is never lined up with
  a factor.
* **The search in force.** Every timed run uses the ``search`` of its parameters (the ``base``
  of the design and the sweep): ``"exhaustive"`` times the paper's plain Eq. (1), whose cost
  grows with SEARCH_SIZE^2 x CORR_SIZE^2; ``"pruned"`` (default) the search the pipeline runs
  by default. The two return identical positions, so the *untimed* reference runs, which only
  give the motion ex and ey are measured against, always use the pruned search: at (50, 30)
  it is ~15x cheaper than the exhaustive one (0.6 against 10 ms a frame), which keeps a tuning
  cycle within its budget. tests/unit/test_experiment.py checks that both searches give the
  reference the same motion.
* **Reference runs** are deterministic and untimed, so each distinct reference is run once and
  cached; the 16 runs of the 2^(5-1) design need only 8 (one per combination of factors 1, 2, 5).
  Runs are cached by their *effective* geometry too: widths w and w + 1 with the same
  ``w // 2`` behave identically (:mod:`vistrack.common.params`), so they are run once.

Ground truth (optional, :class:`GroundTruth`): with the true image motion of every frame
(generated sequences, the simulator's poses) the run's motion is also scored against it
(``gt_ex``, ``gt_ey``); with a dense flow between two frames (Middlebury ``.flo``), the median
end-point error of the features tracked across that pair (``gt_epe``).

Design and analysis: :func:`run_design` runs every design point in randomised order and
:func:`analyse` turns the responses into effects and the Table 3 significance map, by Lenth's
method (default) or ANOVA with the inactive effects pooled into error. That is the paper's
unreplicated design, and what the auto-tuner runs. :func:`run_replicated` times every point
several times, independently and in a completely randomised order, and
:func:`analyse_replicated` tests the effects against that pure error instead: on real frames
tf has more active effects than Lenth's method can cope with (the feature count multiplies
every window cost), and only the replicated design finds the paper's Table 3 row for tf.

Pure numpy/scipy (through :mod:`.anova`): no Zenoh, no msgpack.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from vistrack.common import groundtruth
from vistrack.common.params import MIN_VALID_NPI, TrackerParams
from vistrack.common.vision import Preprocessed, Tracker, preprocess, warm_up
from vistrack.common.vision.preprocess import candidates_above, strength_of
from vistrack.services.auto_tuner import anova as anova_mod
from vistrack.services.auto_tuner.design import Design, number_label

#: The paper's responses, in Table 3's order.
RESPONSES = ("t1", "tf", "ex", "ey")

#: SEARCH_SIZE and CORR_SIZE of the reference run ("large search and correlation windows").
REFERENCE_WINDOWS = (50, 30)

#: Passes over the points whose per-frame minimum gives the times (see the module notes).
DEFAULT_REPEATS = 3

#: Significance tests offered by :func:`analyse`.
METHODS = ("lenth", "anova")

#: progress(phase, done, total): called after every tracker run.
Progress = Callable[[str, int, int], None]


@dataclass(frozen=True, eq=False)
class GroundTruth:
    """What is known about a buffer's true motion; either part may be absent.

    Attributes
    ----------
    motion : (n_frames, 2) float64, optional
        True image motion (x, y) of the scene since frame 0, px; row 0 is (0, 0). For a pure
        translation every point moves by it. Scale changes are not scored: under a zoom a
        point's motion depends on where it is, so no single true value exists for the mean.
    flow : (H, W, 2) float, optional
        Dense ground-truth flow (u, v) from frame ``flow_frame`` to the next, NaN where unknown
        (as :func:`vistrack.common.groundtruth.read_flo` returns it).
    flow_frame : int
        The frame the flow starts from.
    """

    motion: np.ndarray | None = None
    flow: np.ndarray | None = None
    flow_frame: int = 0

    def __post_init__(self) -> None:
        if self.motion is not None:
            m = np.asarray(self.motion, np.float64)
            if m.ndim != 2 or m.shape[1] != 2 or not np.all(np.isfinite(m)):
                raise ValueError(f"motion must be a finite (n_frames, 2) array, got {m.shape}")
            object.__setattr__(self, "motion", m)
        if self.flow is not None:
            f = np.asarray(self.flow)
            if f.ndim != 3 or f.shape[2] != 2:
                raise ValueError(f"flow must be an (H, W, 2) array, got {f.shape}")
        if self.flow_frame < 0:
            raise ValueError(f"flow_frame={self.flow_frame} must be >= 0")

    @classmethod
    def from_steps(cls, steps: Sequence[Any]) -> GroundTruth:
        """From per-frame translation steps, e.g. the ``synthetic.Motion`` list of a generated
        sequence (objects with ``dx``, ``dy`` and ``scale`` attributes, ``scale`` == 1)."""
        for s in steps:
            if getattr(s, "scale", 1.0) != 1.0:
                raise ValueError("only translations have one true image motion; got a scale step")
        d = np.array([[s.dx, s.dy] for s in steps], np.float64).reshape(-1, 2)
        return cls(motion=np.vstack([np.zeros((1, 2)), np.cumsum(d, axis=0)]))


@dataclass(frozen=True)
class Responses:
    """Responses of one point. Times in ms, errors in px, ``npi_mean`` in features.

    The ``gt_*`` scores are None unless ground truth of that kind was given.
    """

    t1: float
    tf: float
    ex: float
    ey: float
    npi_mean: float
    gt_ex: float | None = None
    gt_ey: float | None = None
    gt_epe: float | None = None

    def as_dict(self) -> dict[str, float]:
        """Every response that has a value, as plain floats."""
        return {k: float(v) for k, v in dataclasses.asdict(self).items() if v is not None}


@dataclass
class _Run:
    """What one (deterministic) run left behind: the motion, the NPI and every pass's times."""

    dx: np.ndarray  # (n,) accumulated x motion since frame 0, px
    dy: np.ndarray
    npi: np.ndarray  # (n,)
    epe: float | None  # median end-point error against the ground-truth flow
    times: list[np.ndarray] = field(default_factory=list)  # each (n,) t_ms of one pass


def bounce(frames: Sequence[np.ndarray], n: int) -> list[np.ndarray]:
    """``n`` frames made by playing ``frames`` forwards, backwards, forwards ... (no frame is
    shown twice in a row), so a short sequence such as RubberWhale's 8 frames fills a buffer.

    Returns a list of the same array objects, in the new order.
    """
    if len(frames) < 2 or n < 1:
        raise ValueError(f"need at least 2 frames and n >= 1, got {len(frames)} and {n}")
    cycle = list(range(len(frames))) + list(range(len(frames) - 2, 0, -1))
    return [frames[cycle[i % len(cycle)]] for i in range(n)]


class Experiment:
    """A buffer of frames and the runs made on it, cached.

    Parameters
    ----------
    frames : sequence of (H, W) uint8 arrays, at least 2, all one size.
    repeats : passes whose per-frame minimum gives the times (1 = a single pass).
    ground_truth : optional :class:`GroundTruth` of the buffer.
    reference : (SEARCH_SIZE, CORR_SIZE) of the reference runs.

    It keeps every run's motion and times, the buffer filtered (2 MB for 30 frames of
    256x256, 28 MB at 1280x720) once for every run, and the candidates of each distinct
    pre-processing (a tuning cycle makes 13): drop it when done.
    """

    def __init__(self, frames: Sequence[np.ndarray], *, repeats: int = DEFAULT_REPEATS,
                 ground_truth: GroundTruth | None = None,
                 reference: tuple[int, int] = REFERENCE_WINDOWS) -> None:
        self.frames = _check_frames(frames)
        if isinstance(repeats, bool) or not isinstance(repeats, int) or repeats < 1:
            raise ValueError(f"repeats={repeats!r} must be an int >= 1")
        self.repeats = repeats
        if ground_truth is not None:
            n = len(self.frames)
            if ground_truth.motion is not None and len(ground_truth.motion) != n:
                raise ValueError(f"ground-truth motion has {len(ground_truth.motion)} rows for "
                                 f"{n} frames")
            if ground_truth.flow is not None:
                if ground_truth.flow_frame + 1 >= n:
                    raise ValueError(f"flow_frame={ground_truth.flow_frame} needs a next frame; "
                                     f"the buffer has {n}")
                if ground_truth.flow.shape[:2] != self.frames[0].shape:
                    raise ValueError(f"flow is {ground_truth.flow.shape[:2]} (H, W) but frames "
                                     f"are {self.frames[0].shape}")
        self.ground_truth = ground_truth
        self.reference = (int(reference[0]), int(reference[1]))
        TrackerParams(search_size=self.reference[0], corr_size=self.reference[1])  # validate
        self._runs: dict[tuple, _Run] = {}
        # the buffer filtered (blur_sigma): its frames and (n_frames,) ms of each, once
        self._filtered: dict[float, tuple[list[np.ndarray], np.ndarray]] = {}
        self._pre: dict[tuple, list[Preprocessed]] = {}
        # (n_frames,) ms of each frame's candidates (gradient strength, THRES_PERCENT, floors),
        # once: added to a run's time of the frames whose candidates it reads
        self._cand_times: dict[tuple, np.ndarray] = {}
        warm_up()  # compile (or load) the numba kernels once, before anything is timed

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) of the frames, px."""
        h, w = self.frames[0].shape
        return w, h

    def reference_params(self, params: TrackerParams) -> TrackerParams:
        """The run's parameters with the reference SEARCH_SIZE and CORR_SIZE (and its search:
        what a timed reference, such as the sweep's, runs)."""
        return params.replace(search_size=self.reference[0], corr_size=self.reference[1])

    def _motion_reference(self, params: TrackerParams) -> TrackerParams:
        """The untimed run whose motion ``params`` is scored against: the reference windows
        with the pruned search, which gives the same positions as the exhaustive one for less
        work (see the module notes)."""
        return self.reference_params(params).replace(search="pruned")

    def textured(self, params: TrackerParams) -> float:
        """The share of the frames on which the motion reference of ``params`` (run now, once:
        every later point of the same other parameters scores against this run) tracks at
        least MIN_VALID_NPI features: an estimate that is ``valid``."""
        ref = self._motion_reference(params)
        key = _key(ref)
        if key not in self._runs:
            self._run(ref, key)
        return float(np.mean(self._runs[key].npi >= MIN_VALID_NPI))

    # -- running -------------------------------------------------------------------------
    def measure(self, points: Sequence[TrackerParams], *, order: Sequence[int] | None = None,
                shuffle_seed: int | None = None, progress: Progress | None = None,
                phase: str = "runs") -> list[Responses]:
        """Run every point ``repeats`` times in interleaved passes and score it.

        Parameters
        ----------
        points : the settings to run.
        order : the order of the points within the first pass (default: as given); a
            permutation.
        shuffle_seed : when given, every later pass runs the points in a fresh random order
            (``numpy.random.default_rng(shuffle_seed)``), so a slow spell of the machine that
            outlasts a pass lands on different points each time; otherwise every pass follows
            ``order``.
        progress : optional ``progress(phase, done, total)`` after every tracker run.

        Returns
        -------
        One :class:`Responses` per point, in the order of ``points``.
        """
        points = list(points)
        order = list(range(len(points))) if order is None else [int(i) for i in order]
        if sorted(order) != list(range(len(points))):
            raise ValueError(f"order must be a permutation of 0..{len(points) - 1}")
        keys = [_key(p) for p in points]
        refs = {_key(self._motion_reference(p)): self._motion_reference(p) for p in points}
        # a point already measured (by an earlier call, or the same geometry twice in this
        # list) is not run again: only the first of each key, and only the passes it lacks
        first: dict[tuple, int] = {}
        for i in order:
            first.setdefault(keys[i], i)
        have = {k: len(self._runs[k].times) if k in self._runs else 0 for k in first}
        todo = [[i for k, i in first.items() if have[k] <= r] for r in range(self.repeats)]
        if shuffle_seed is not None:
            rng = np.random.default_rng(shuffle_seed)
            todo = [todo[0]] + [[t[j] for j in rng.permutation(len(t))] for t in todo[1:]]
        missing_refs = [k for k in refs if k not in self._runs and k not in keys]
        tick = _ticker(progress, phase, sum(len(t) for t in todo) + len(missing_refs))
        self._prepare([*points, *refs.values()])
        for r in range(self.repeats):
            for i in todo[r]:
                self._run(points[i], keys[i])
                tick()
        self._run_references(refs, missing_refs, tick)
        return [self.responses(p) for p in points]

    def measure_replicated(self, points: Sequence[TrackerParams], replicates: int, *,
                           seed: int | None = None, progress: Progress | None = None,
                           phase: str = "runs") -> tuple[list[list[Responses]], np.ndarray]:
        """Time every point ``replicates`` times, each time independently, in random order.

        A *unit* is one replicate of one point. Every unit is timed afresh in each of the
        ``repeats`` passes: the buffer pre-processed and tracked anew with its own timer
        readings, never taken from the cache :meth:`measure` keeps (only the untimed,
        deterministic outputs are shared: the pre-processed frames, the motion, the reference
        runs). A unit's times are the per-frame minima over its own passes, as in
        :meth:`measure`.

        Parameters
        ----------
        points : the settings to run.
        replicates : independent timings of every point, >= 2.
        seed : seed of the orders (``numpy.random.default_rng(seed)``); None: fresh ones.
        progress : optional ``progress(phase, done, total)`` after every tracker run.

        Returns
        -------
        responses : ``responses[i][r]``, the :class:`Responses` of replicate ``r`` of point
            ``i``.
        order : (points * replicates, 2) int64, the units of the first pass as
            ``(point, replicate)`` in the order they ran.

        Notes
        -----
        Complete randomisation, pass by pass: every pass runs *all* points x replicates in
        a fresh random order. A slow spell of the machine then lands on units at random
        rather than on one replicate (which would make it a block and inflate the pure error)
        or on one point's replicates (which would fake an effect). The passes of a unit are
        a whole pass apart for the reason given in the module notes: a run lasts ~30 ms,
        shorter than the spells its per-frame minimum is meant to see past.
        """
        if (isinstance(replicates, bool) or not isinstance(replicates, int | np.integer)
                or replicates < 2):
            raise ValueError(f"replicates={replicates!r} must be an int >= 2 (1 is the "
                             "unreplicated design: use measure())")
        points = list(points)
        keys = [_key(p) for p in points]
        refs = {_key(self._motion_reference(p)): self._motion_reference(p) for p in points}
        missing_refs = [k for k in refs if k not in self._runs and k not in keys]
        units = [(i, r) for i in range(len(points)) for r in range(replicates)]
        rng = np.random.default_rng(seed)
        passes = [rng.permutation(len(units)) for _ in range(self.repeats)]
        pre: list[list[list[np.ndarray]]] = [[[] for _ in range(replicates)] for _ in points]
        track: list[list[list[np.ndarray]]] = [[[] for _ in range(replicates)] for _ in points]
        tick = _ticker(progress, phase, len(units) * self.repeats + len(missing_refs))
        for order in passes:
            for u in order:
                i, r = units[u]
                t_pre, t_track = self._time_afresh(points[i], keys[i])
                pre[i][r].append(t_pre)
                track[i][r].append(t_track)
                tick()
        self._run_references(refs, missing_refs, tick)
        responses = [[self._score(p, track[i][r], pre[i][r]) for r in range(replicates)]
                     for i, p in enumerate(points)]
        first = np.array([units[u] for u in passes[0]], np.int64).reshape(-1, 2)
        first.setflags(write=False)
        return responses, first

    def responses(self, params: TrackerParams) -> Responses:
        """The responses of a point already run (see :meth:`measure`)."""
        return self._score(params, self._runs[_key(params)].times, [self._pre_cost(params)])

    def _score(self, params: TrackerParams, track_times: Sequence[np.ndarray],
               pre_times: Sequence[np.ndarray]) -> Responses:
        """Responses of a point from its timing passes, each (n_frames,) ms, and the motion
        of its (deterministic) run and reference, which must have been run."""
        run = self._runs[_key(params)]
        ref = self._runs[_key(self._motion_reference(params))]
        # each part at its least-disturbed pass (see the module notes)
        times = np.min(np.stack(track_times), axis=0) + np.min(np.stack(pre_times), axis=0)
        gt_ex = gt_ey = None
        if self.ground_truth is not None and self.ground_truth.motion is not None:
            truth = self.ground_truth.motion
            gt_ex = float(np.mean(np.abs(run.dx[1:] - truth[1:, 0])))
            gt_ey = float(np.mean(np.abs(run.dy[1:] - truth[1:, 1])))
        return Responses(
            t1=float(times[0]), tf=float(np.mean(times[1:])),
            ex=float(np.mean(np.abs(run.dx[1:] - ref.dx[1:]))),
            ey=float(np.mean(np.abs(run.dy[1:] - ref.dy[1:]))),
            npi_mean=float(np.mean(run.npi)), gt_ex=gt_ex, gt_ey=gt_ey, gt_epe=run.epe)

    def _run_references(self, refs: Mapping[tuple, TrackerParams], missing: Sequence[tuple],
                        tick: Callable[[], None]) -> None:
        for k in missing:  # untimed: only their motion is used
            self._run(refs[k], k)
            tick()

    def _run(self, params: TrackerParams, key: tuple) -> None:
        warm_up(params=params)  # kernels of their own (paper, int64 sums): before the timing
        frames = [_Watched(pre) for pre in self._preprocessed(params)]
        tracker = Tracker(params)
        estimates = [tracker.update(pre) for pre in frames]
        # each frame whose candidates the run read (its first, its re-detections) costs
        # what computing them costs: the pipeline computes them for that frame
        read = np.array([pre.read for pre in frames])
        times = np.array([e.t_ms for e in estimates]) + np.where(read, self._cand_cost(params),
                                                                 0.0)
        run = self._runs.get(key)
        if run is None:
            run = self._runs[key] = self._new_run(estimates)
        run.times.append(times)

    def _new_run(self, estimates: list) -> _Run:
        return _Run(dx=np.array([e.dx for e in estimates]),
                    dy=np.array([e.dy for e in estimates]),
                    npi=np.array([e.npi for e in estimates], np.float64),
                    epe=self._epe(estimates))

    def _time_afresh(self, params: TrackerParams, key: tuple) -> tuple[np.ndarray, np.ndarray]:
        """One independent timing of a point, bypassing the timing caches: the buffer
        pre-processed and tracked anew. Returns its (n_frames,) pre-processing and tracking
        times, ms. The outputs are deterministic, so the first ones are kept for the motion
        and for the untimed runs that share them; the times are never stored."""
        warm_up(params=params)  # kernels of their own (paper, int64 sums): before the timing
        t_pre = np.empty(len(self.frames))
        frames = []
        for i, frame in enumerate(self.frames):
            t0 = time.perf_counter()
            frames.append(preprocess(frame, params))
            t_pre[i] = (time.perf_counter() - t0) * 1e3
        # fresh frames: the tracker computes the candidates it reads, timed in its t_ms
        tracker = Tracker(params)
        estimates = [tracker.update(pre) for pre in frames]
        if key not in self._runs:
            self._runs[key] = self._new_run(estimates)
        return t_pre, np.array([e.t_ms for e in estimates])

    def _preprocessed(self, params: TrackerParams) -> list[Preprocessed]:
        """The buffer pre-processed for ``params`` (:meth:`_prepare`)."""
        self._prepare([params])
        return self._pre[_pre_key(params)]

    def _prepare(self, points: Sequence[TrackerParams]) -> None:
        """Every distinct pre-processing of ``points`` not made yet, timed frame by frame,
        the filter (once per filter, :meth:`_filtered_of`) and the candidates apart (the
        pipeline computes the candidates only for the frames whose features are selected).
        A frame's gradient strength and texture floor (:func:`strength_of`), the same for every
        THRES_PERCENT and margin, are computed once for all of them, and each is charged
        their time and its own threshold's (:func:`candidates_above`): computed once for each,
        they were 13 strengths of each frame a cycle, 14 % of its CPU at 1280x720."""
        groups: dict[tuple, dict[tuple, TrackerParams]] = {}
        for p in points:
            key = _pre_key(p)
            if key not in self._pre:
                groups.setdefault(_strength_key(p), {})[key] = p
        for group in groups.values():
            first = next(iter(group.values()))
            filtered = self._filtered_of(first)[0]
            made: dict[tuple, list[Preprocessed]] = {key: [] for key in group}
            t_cand = {key: np.empty(len(filtered)) for key in group}
            for i, frame in enumerate(filtered):
                (grad, floor), shared = _least_of(STRENGTH_TIMINGS,
                                                  functools.partial(strength_of, frame, first))
                for key, p in group.items():
                    t1 = time.perf_counter()
                    cands, strength = candidates_above(grad, floor, p)
                    t_cand[key][i] = shared + (time.perf_counter() - t1) * 1e3
                    made[key].append(Preprocessed(frame, cands, strength))
            for key in group:
                self._pre[key] = made[key]
                self._cand_times[key] = t_cand[key]

    def _filtered_of(self, params: TrackerParams) -> tuple[list[np.ndarray], np.ndarray]:
        """The buffer filtered for ``params`` (:func:`preprocess`'s filter, which depends on
        ``blur_sigma`` alone), once, and (n_frames,) ms of each frame's filter: the least of
        FILTER_TIMINGS (the first kept)."""
        key = float(params.blur_sigma)
        if key not in self._filtered:
            out = []
            t_ms = np.empty(len(self.frames))
            for i, frame in enumerate(self.frames):
                pre, t_ms[i] = _least_of(FILTER_TIMINGS,
                                         functools.partial(preprocess, frame, params))
                out.append(pre.filtered)
            self._filtered[key] = (out, t_ms)
        return self._filtered[key]

    def _pre_cost(self, params: TrackerParams) -> np.ndarray:
        """(n_frames,) ms: the pre-processing time (the filter) of each frame for ``params``,
        the least of FILTER_TIMINGS (:meth:`_filtered_of`)."""
        return self._filtered_of(params)[1]

    def _cand_cost(self, params: TrackerParams) -> np.ndarray:
        """(n_frames,) ms: what computing each frame's candidates costs for ``params``, the
        least that any pre-processing of the buffer doing the same work took on that frame
        (see the module notes: the border margin, the only other thing a pre-processing key
        holds, does not change its cost)."""
        return self._least(self._cand_times, params)

    @staticmethod
    def _least(timed: Mapping[tuple, np.ndarray], params: TrackerParams) -> np.ndarray:
        work = _pre_work(params)
        return np.min(np.stack([t for k, t in timed.items() if k[:len(work)] == work]),
                      axis=0)

    def _epe(self, estimates: list) -> float | None:
        gt = self.ground_truth
        if gt is None or gt.flow is None:
            return None
        a, b = estimates[gt.flow_frame], estimates[gt.flow_frame + 1]
        start = dict(zip(a.ids.tolist(), a.points, strict=True))
        both = [k for k, i in enumerate(b.ids.tolist()) if i in start]
        if not both:
            return None
        before = np.array([start[int(b.ids[k])] for k in both])
        err = groundtruth.endpoint_errors(before, b.points[both], gt.flow)
        return float(np.median(err)) if err.size else None


#: How many times each frame's filter and gradient strength are timed, once for every
#: pre-processing of a cycle (:meth:`Experiment._filtered_of`, :meth:`Experiment._prepare`):
#: the least is charged, as a frame's tracking is charged the least of its passes. Each
#: pre-processing timed its own once, 13 of them a cycle, and took the least of those of the
#: same work (:meth:`Experiment._least`). The first timing writes to memory fresh from the
#: system, a service's to memory its frame before freed: the filter timed once charged a
#: 1280x720 cycle's frames 0.57 ms where the least of 13 was 0.39; the least of two 0.44 to
#: 0.49. A filter is a tenth of a strength: timed 5 times, for a least within the noise of
#: the 13, at 1280x720 ~60 ms of a ~6 s cycle; the strength, twice.
FILTER_TIMINGS = 5
STRENGTH_TIMINGS = 2


def _least_of(times: int, work: Callable[[], Any]) -> tuple[Any, float]:
    """``work()`` run ``times`` times: the first result and the least time, ms."""
    best = np.inf
    first = None
    for k in range(times):
        t0 = time.perf_counter()
        got = work()
        best = min(best, time.perf_counter() - t0)
        if k == 0:
            first = got
    return first, best * 1e3


class _Watched(Preprocessed):
    """A frame of the pre-processed buffer as one run sees it: ``read`` once the run read
    its candidates (its tracker selected features there). The buffer's frames are shared by
    every run and pass, their candidates computed once (:meth:`Experiment._preprocessed`):
    read through them, only the first run's first frame paid for the candidates, and the
    least of the passes left them out (t1 at 1280x720 0.29 ms, where selecting the first
    features costs ~1.5)."""

    def __init__(self, pre: Preprocessed) -> None:
        object.__setattr__(self, "filtered", pre.filtered)
        object.__setattr__(self, "_pre", pre)
        object.__setattr__(self, "read", False)

    @property  # type: ignore[misc]
    def candidates(self) -> np.ndarray:  # type: ignore[override]
        object.__setattr__(self, "read", True)
        return self.__dict__["_pre"].candidates  # type: ignore[no-any-return]

    @property  # type: ignore[misc]
    def strength(self) -> np.ndarray:  # type: ignore[override]
        object.__setattr__(self, "read", True)
        return self.__dict__["_pre"].strength  # type: ignore[no-any-return]


def _ticker(progress: Progress | None, phase: str, total: int) -> Callable[[], None]:
    """A function to call after every tracker run: reports ``progress(phase, done, total)``."""
    done = 0

    def tick() -> None:
        nonlocal done
        done += 1
        if progress is not None:
            progress(phase, done, total)

    return tick


def _key(params: TrackerParams) -> tuple:
    """Cache key: every parameter, with the window widths reduced to what the tracker uses."""
    values = params.as_dict()
    values["search_size"] = params.search_half
    values["corr_size"] = params.corr_half
    return tuple(sorted(values.items()))


def _pre_key(params: TrackerParams) -> tuple:
    """What :func:`preprocess` depends on: the filter, the strength, THRES_PERCENT (its
    :func:`_pre_work`), the border margin that keeps a correlation window inside the frame,
    and the floors' settings (quality level, the camera's noise)."""
    return (*_pre_work(params), params.corr_half, params.quality_level, params.noise_sigma)


def _strength_key(params: TrackerParams) -> tuple:
    """What :func:`strength_of` depends on: the filter, the strength, the camera's noise."""
    return params.blur_sigma, params.strength, params.noise_sigma


def _pre_work(params: TrackerParams) -> tuple:
    """What the cost of :func:`preprocess` depends on, frame size aside: the filter, the
    strength and THRES_PERCENT (the number of candidates sorted). Not the border margin: it
    only moves the bounds of the candidates' scan, and measured on 256x256 to 1280x720 frames
    margins of 3 and 16 px cost the same within the timing noise."""
    return params.blur_sigma, params.strength, params.thres_percent


def _check_frames(frames: Sequence[np.ndarray]) -> list[np.ndarray]:
    out = [np.ascontiguousarray(f) for f in frames]
    if len(out) < 2:
        raise ValueError(f"an experiment needs at least 2 frames (t1 and tf), got {len(out)}")
    for i, f in enumerate(out):
        if f.ndim != 2 or f.dtype != np.uint8:
            raise ValueError(f"frame {i} must be a 2-D uint8 grey image, got {f.dtype} "
                             f"{f.shape}")
        if f.shape != out[0].shape:
            raise ValueError(f"frame {i} is {f.shape[1]}x{f.shape[0]} but frame 0 is "
                             f"{out[0].shape[1]}x{out[0].shape[0]}")
    return out


def _experiment(frames: Sequence[np.ndarray] | Experiment, repeats: int | None,
                ground_truth: GroundTruth | None) -> Experiment:
    if isinstance(frames, Experiment):
        if ground_truth is not None and ground_truth is not frames.ground_truth:
            raise ValueError("give ground_truth to the Experiment, not to each call")
        if repeats is not None and repeats != frames.repeats:
            raise ValueError(f"repeats={repeats} differs from the Experiment's {frames.repeats}")
        return frames
    return Experiment(frames, repeats=DEFAULT_REPEATS if repeats is None else repeats,
                      ground_truth=ground_truth)


def run_point(frames: Sequence[np.ndarray] | Experiment, params: TrackerParams, *,
              repeats: int | None = None, ground_truth: GroundTruth | None = None) -> Responses:
    """Responses of one setting over a buffer of frames.

    Parameters
    ----------
    frames : (H, W) uint8 grey frames (at least 2), or an :class:`Experiment` to share its
        cache of runs (references in particular) between calls.
    params : the setting; its reference run uses SEARCH_SIZE 50, CORR_SIZE 30.
    repeats : timing passes (default :data:`DEFAULT_REPEATS`); with one point they run back to
        back.
    ground_truth : optional :class:`GroundTruth` of the buffer.
    """
    return _experiment(frames, repeats, ground_truth).measure([params], phase="point")[0]


# ------------------------------------------------------------------------------ the design


@dataclass(frozen=True, eq=False)
class DesignRun:
    """A design run on a buffer: every point's responses, in standard order.

    Attributes
    ----------
    design : the design (with factor names and levels).
    params : TrackerParams of every run, standard order.
    order : (runs,) int64, the run order: ``order[k]`` is the standard-order index of the
        k-th run made (in the first timing pass; later passes reshuffle, see the module notes).
    responses : Responses of every run, standard order.
    seed : the seed of the run order.
    """

    design: Design
    params: tuple[TrackerParams, ...]
    order: np.ndarray
    responses: tuple[Responses, ...]
    seed: int | None

    def response(self, name: str) -> np.ndarray:
        """(runs,) float64 values of one response (``"t1"``, ``"tf"``, ..., ``"npi_mean"``)."""
        values = [r.as_dict().get(name) for r in self.responses]
        if any(v is None for v in values):
            raise KeyError(f"no response {name!r}; have {sorted(self.responses[0].as_dict())}")
        return np.array(values, np.float64)


def design_params(design: Design, base: TrackerParams | None = None) -> list[TrackerParams]:
    """TrackerParams of every run of ``design`` (standard order): its factor names must be
    TrackerParams fields and it must carry levels, like :func:`.design.paper_design`."""
    if design.names is None or design.levels is None:
        raise ValueError("the design needs factor names and levels (see paper_design())")
    base = base if base is not None else TrackerParams()
    return [base.replace(**dict(zip(design.names, (float(v) for v in row), strict=True)))
            for row in design.with_levels()]


def run_design(frames: Sequence[np.ndarray] | Experiment, design: Design, seed: int | None, *,
               progress: Progress | None = None, repeats: int | None = None,
               ground_truth: GroundTruth | None = None,
               base: TrackerParams | None = None) -> DesignRun:
    """Run every point of ``design`` over the frames, in a randomised run order.

    Parameters
    ----------
    frames : grey frames or an :class:`Experiment` (see :func:`run_point`).
    design : a two-level design with names and levels, e.g. ``paper_design()``.
    seed : seed of the run order (:meth:`Design.randomized_order`); the same seed gives the
        same order.
    progress : optional ``progress("design", done, total)``.
    repeats, ground_truth : see :func:`run_point`.
    base : values of the parameters the design does not vary (default TrackerParams()).

    Returns
    -------
    DesignRun with the responses in standard order and the run order.
    """
    exp = _experiment(frames, repeats, ground_truth)
    points = design_params(design, base)
    order = design.randomized_order(seed)
    # later timing passes reshuffle from the same seed: reproducible, and independent of order
    shuffle = None if seed is None else int(np.random.default_rng(seed).integers(2**31))
    responses = exp.measure(points, order=order, shuffle_seed=shuffle, progress=progress,
                            phase="design")
    order = order.astype(np.int64)
    order.setflags(write=False)
    return DesignRun(design, tuple(points), order, tuple(responses), seed)


@dataclass(frozen=True, eq=False)
class ReplicatedRun:
    """A replicated design run on a buffer: every replicate's responses, in standard order.

    Attributes
    ----------
    design : the design (with factor names and levels).
    params : TrackerParams of every run, standard order.
    order : (runs * replicates, 2) int64, the first timing pass's units as ``(run,
        replicate)`` in the order they ran, runs in standard order (later passes reshuffle
        all the units again, see :func:`run_replicated`).
    replicates : ``replicates[i][r]``, the Responses of replicate ``r`` of run ``i``.
    seed : the seed of the orders.
    """

    design: Design
    params: tuple[TrackerParams, ...]
    order: np.ndarray
    replicates: tuple[tuple[Responses, ...], ...]
    seed: int | None

    @property
    def n_replicates(self) -> int:
        """Replicates of every run."""
        return len(self.replicates[0])

    def response(self, name: str) -> np.ndarray:
        """(runs, replicates) float64 values of one response (``"t1"``, ``"tf"``, ...)."""
        values = [[r.as_dict().get(name) for r in reps] for reps in self.replicates]
        if any(v is None for row in values for v in row):
            raise KeyError(f"no response {name!r}; have "
                           f"{sorted(self.replicates[0][0].as_dict())}")
        return np.array(values, np.float64)

    def means(self) -> DesignRun:
        """The per-run means as a :class:`DesignRun`; its ``order`` is the order in which
        the runs first ran (their first replicate in the first pass)."""
        mean = tuple(_mean_responses(reps) for reps in self.replicates)
        first = dict.fromkeys(int(i) for i in self.order[:, 0])  # insertion order
        order = np.array(list(first), np.int64)
        order.setflags(write=False)
        return DesignRun(self.design, self.params, order, mean, self.seed)


def _mean_responses(reps: Sequence[Responses]) -> Responses:
    """The mean of each response over replicates (a ``gt_*`` score only if all have it)."""

    def mean(name: str) -> float:
        return float(np.mean([getattr(r, name) for r in reps]))

    def mean_or_none(name: str) -> float | None:
        return None if any(getattr(r, name) is None for r in reps) else mean(name)

    return Responses(t1=mean("t1"), tf=mean("tf"), ex=mean("ex"), ey=mean("ey"),
                     npi_mean=mean("npi_mean"), gt_ex=mean_or_none("gt_ex"),
                     gt_ey=mean_or_none("gt_ey"), gt_epe=mean_or_none("gt_epe"))


def run_replicated(frames: Sequence[np.ndarray] | Experiment, design: Design, seed: int | None,
                   replicates: int, *, base: TrackerParams | None = None,
                   progress: Progress | None = None, repeats: int | None = None,
                   ground_truth: GroundTruth | None = None) -> ReplicatedRun:
    """Run every point of ``design`` ``replicates`` times, each an independent timing.

    The unreplicated design (:func:`run_design`) leaves no degree of freedom for error, so
    its effects are tested against the smaller effects (Lenth's method), which fails when
    most effects are real (tf's, on real frames: the feature count, set by factors 1, 2, 5,
    multiplies every window cost). Replicates measure the timing noise itself, *pure error*,
    and :func:`analyse_replicated` tests every effect against it.

    Parameters
    ----------
    frames : grey frames or an :class:`Experiment` (its cached runs are shared for the
        untimed outputs only; every unit is timed afresh, see
        :meth:`Experiment.measure_replicated`).
    design : a two-level design with names and levels, e.g. ``paper_design()``.
    seed : seed of the orders: the same seed gives the same orders.
    replicates : independent timings of every run, >= 2.
    base : values of the parameters the design does not vary (default TrackerParams()).
    progress : optional ``progress("design", done, total)``.
    repeats, ground_truth : see :func:`run_point`.

    Returns
    -------
    ReplicatedRun with responses of shape (runs, replicates).

    Notes
    -----
    The order is completely randomised over all runs x replicates: every timing pass runs
    all the units in a fresh random order (units are not grouped by replicate). Each unit
    pre-processes the buffer itself, so even runs that share a pre-processing (THRES_PERCENT
    and CORR_SIZE's border margin) do not share its timing noise: within a replicate as
    between replicates, every observation is its own.
    """
    exp = _experiment(frames, repeats, ground_truth)
    points = design_params(design, base)
    responses, order = exp.measure_replicated(points, replicates, seed=seed,
                                              progress=progress, phase="design")
    return ReplicatedRun(design, tuple(points), order,
                         tuple(tuple(reps) for reps in responses), seed)


# ------------------------------------------------------------------------------ analysis


@dataclass(frozen=True, eq=False)
class Analysis:
    """Effects and significance of every response of a design run.

    Attributes
    ----------
    method : ``"lenth"`` or ``"anova"`` (:func:`analyse`), or ``"pure-error"``
        (:func:`analyse_replicated`).
    effects : response -> {term: effect}, terms in the paper's numbers (``"34"``), response
        units (ms or px) per change from the low to the high level.
    significant : response -> ``{"99": [...], "95": [...]}`` (Table 3: at 99 %, and at 95 %
        but not 99 %), paper numbers.
    results : response -> the LenthResult or AnovaTable behind it, or None when the response
        could not be tested (e.g. all of its effects are 0).
    """

    method: str
    effects: dict[str, dict[str, float]]
    significant: dict[str, dict[str, list[str]]]
    results: dict[str, Any]


def analyse(run: DesignRun, *, method: str = "lenth",
            responses: Sequence[str] = RESPONSES) -> Analysis:
    """Effects of the main effects and two-factor interactions, and the Table 3 map.

    ``method="lenth"`` (default): Lenth's pseudo standard error, individual t tests on m/3
    degrees of freedom. The 16 unreplicated runs of the 2^(5-1) design leave no degree of
    freedom for error, and Lenth's method is the standard answer: it estimates the noise from
    the smallest effects without deciding in advance which ones are noise.

    ``method="anova"``: the classical ANOVA (what the paper reports) with the effects Lenth's
    method treats as inactive (|effect| < 2.5 * 1.5 * median |effect|) pooled into error. It
    is more liberal: pooling chosen from the data makes the error too small, so read it as the
    paper's view rather than as a calibrated test.
    """
    if method not in METHODS:
        raise ValueError(f"method={method!r} is not allowed: use one of {', '.join(METHODS)}")

    def test(y: np.ndarray, eff: dict[str, float]) -> Any:
        if method == "lenth":
            return anova_mod.lenth(eff)
        return anova_mod.anova(run.design, y, pool="auto")

    return _analysis(method, run.design, {name: run.response(name) for name in responses}, test)


def _analysis(method: str, design: Design, ys: Mapping[str, np.ndarray],
              test: Callable[[np.ndarray, dict[str, float]], Any]) -> Analysis:
    """Effects of every response ``ys[name]`` ((runs,) or (runs, reps)) and the Table 3 map
    of ``test(y, effects)``, a LenthResult or AnovaTable."""
    effects: dict[str, dict[str, float]] = {}
    results: dict[str, Any] = {}
    for name, y in ys.items():
        eff = anova_mod.effects(design, y)
        effects[name] = {number_label(t): float(v) for t, v in eff.items()}
        try:
            results[name] = test(y, eff)
        except ValueError:
            # half or more of the effects are exactly 0 (e.g. every run equals its reference):
            # there is no scale to test against, so nothing is declared significant
            results[name] = None
    tested = {k: v for k, v in results.items() if v is not None}
    significant = anova_mod.table3(tested)
    for name in ys:
        significant.setdefault(name, {"99": [], "95": []})
    return Analysis(method, effects, {k: significant[k] for k in ys}, results)


def analyse_replicated(run: ReplicatedRun, *,
                       responses: Sequence[str] = RESPONSES) -> Analysis:
    """Effects and the Table 3 map of a replicated design run, tested against pure error.

    Every response that varies between the replicates of a run (the times t1, tf) is
    analysed by ANOVA with y of shape (runs, replicates): each term's F test is against the
    within-run variation, on runs x (replicates - 1) degrees of freedom, with no pooling and
    no assumption about which effects are small. A response identical in every replicate
    (ex, ey, NPI: the tracker is deterministic, only its timing varies) has no pure error;
    its replicates add nothing, so it is analysed as the unreplicated design is, by Lenth's
    method on the run means (``results[name]`` is then a LenthResult, not an AnovaTable).

    Effects are those of the run means. ``method`` is ``"pure-error"``.
    """

    def test(y: np.ndarray, eff: dict[str, float]) -> Any:
        if np.all(y == y[:, :1]):
            return anova_mod.lenth(eff)
        return anova_mod.anova(run.design, y)

    return _analysis("pure-error", run.design,
                     {name: run.response(name) for name in responses}, test)


def aliases(design: Design) -> dict[str, list[str]]:
    """Alias chains of the main effects and 2FIs in the paper's numbers: ``{"1": ["2345"]}``."""
    return {number_label(t): [_signed_number(w) for w in chain]
            for t, chain in design.aliases(2).items()}


def _signed_number(word: str) -> str:
    return ("-" if word.startswith("-") else "") + number_label(word.lstrip("-"))


def levels_of(design: Design) -> Mapping[str, list[float]]:
    """Factor name -> [low, high] (the design's levels)."""
    if design.names is None or design.levels is None:
        raise ValueError("the design has no names or levels")
    return {n: [float(lo), float(hi)] for n, (lo, hi) in zip(design.names, design.levels,
                                                             strict=True)}
