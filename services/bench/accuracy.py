"""``vistrack bench accuracy``: the tracker's accuracy against OpenCV's pyramidal LK.

For every sequence, our tracker (default parameters) runs over the frames, and
``cv2.calcOpticalFlowPyrLK`` (default settings: 21x21 window, 3 pyramid levels) is started from
the same points: at every step, the features our tracker holds in frame k. Scored against
ground truth:

* **pairs**: (feature, step) pairs tracked from frame k to k+1 (ours: not lost or rejected;
  LK: status 1);
* **median EPE**: median end-point error of those pairs, px; and each tracker's median over
  the pairs **both tracked**, the same (feature, step) pairs on both sides: a tracker that
  rejects a hard pair the other keeps lowers its own median by it, and the two medians of
  each one's own pairs can differ for that alone (on KITTI 2012's 000157, LK kept a feature
  ours rejected: 0.278 against 0.214 px over each one's own pairs, 0.278 against 0.284 on
  the 16 both tracked);
* **> 2 px**: the share of pairs whose error exceeds 2 px (gross errors reported as tracked);
* **survival** (long sequences): the share of the first frame's features still tracked at the
  last frame (LK: each point followed by LK alone from the first frame, lost at status 0 or
  when it leaves the image), and the median **drift** of the survivors from their true
  position there;
* on the pairs, of the pairs off by more than 2 px: the share whose correlation window holds
  one motion (:func:`one_motion`), and how many measured the ground truth of a pixel next to
  the feature's (:func:`beside_truth`: a feature on a motion contour).

Sequences: the Middlebury pairs of the shared data (ground truth: the ``.flo`` flow; any other
folder of ``frame10.png``, ``frame11.png`` and ``flow10.flo`` put beside them under
``$VISTRACK_DATA/middlebury/`` is scored too: your own sequences), the same pairs at the
end of a running track where the folder also holds the frames before frame10 (``, running
from frame07``: Middlebury's "other" sequences hold frame07 to frame14; the features held and
followed from their velocity into the pair, as on a robot, only the pair's step scored), the
long sequences of :mod:`vistrack.common.rendered` (real frames seen through smooth
homographies, translation up to 12 px a frame; exact ground truth), and the same long
sequences seen by a camera whose auto-exposure hunts (``, exposure``: gain +-8 % and offset
+-10 grey levels from frame to frame, :func:`~vistrack.common.rendered.with_exposure`), and
the same paths through a shutter open half the frame interval (``, blur 0.5``: motion blur of
up to 6 px that changes with the speed, :func:`~vistrack.common.rendered.motion_blurred`), a
bump in a steady run (``, jerk``, :func:`~vistrack.common.rendered.jerk`), an approach
(``, approach``, :func:`~vistrack.common.rendered.approach`), a view turning 3 degrees a
frame about its centre (``, roll``, :func:`~vistrack.common.rendered.roll`: a robot turning on
the spot under a camera that looks at the floor) and a slow path seen by a camera that shakes,
each frame jolted by up to 6 px and 2 degrees at random (``, shake``,
:func:`~vistrack.common.rendered.shake`: a vibrating mount, a rough floor, a hand), and that
shake seen by a rolling shutter that reads its rows out over 0.9 of the frame interval
(``, shake, rolling shutter 0.9``, :func:`~vistrack.common.rendered.with_rolling_shutter`:
a CMOS camera, each row at its own jolt).
"""

from __future__ import annotations

import dataclasses
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from ...common import groundtruth, rendered
from ...common.params import TrackerParams
from ...common.vision import Tracker, to_gray, warm_up

#: The Middlebury pairs of the shared data.
PAIRS = ("Dimetrodon", "RubberWhale", "Venus", "Grove2", "Urban2")
GROSS_PX = 2.0
#: the scoreboard's rolling shutter reads its rows out over this share of the frame interval
#: (CMOS sensors: most of it at their full frame rate)
ROLLING_READOUT = 0.9

#: ``truth(points, k)``: the true positions in frame k + 1 of points (N, 2) of frame k.
Truth = Callable[[np.ndarray, int], np.ndarray]


@dataclass(frozen=True)
class Score:
    """One tracker's score on one sequence (see the module notes)."""

    pairs: int
    median_epe: float
    gross: float  # share of pairs off by more than GROSS_PX
    survival: float | None = None
    drift: float | None = None
    # pairs: the share of pairs off by more than GROSS_PX whose correlation window holds one
    # motion (its ground truth varies by less than GROSS_PX across it)
    gross_one_motion: float | None = None
    # pairs: the share of pairs off by more than GROSS_PX whose displacement is the ground
    # truth of a pixel next to the point's, to within BESIDE_PX (:func:`beside_truth`)
    gross_beside: float | None = None
    # the pairs both trackers tracked (with ground truth), and this tracker's median end-point
    # error on them: the medians above are each over its own pairs, and a tracker that rejects
    # a hard pair the other keeps has a lower median for it (:func:`run_sequence`)
    both_pairs: int = 0
    both_median: float = float("nan")


@dataclass(frozen=True)
class Row:
    sequence: str
    frames: int
    ours: Score
    lk: Score
    rejected: int  # features our tracker rejected as untrustworthy (counted as lost)


def lk_track(a: np.ndarray, b: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.calcOpticalFlowPyrLK`` with its default settings: (positions (N, 2), ok (N,))."""
    if len(points) == 0:
        return np.empty((0, 2)), np.empty(0, bool)
    p0 = np.ascontiguousarray(points, np.float32).reshape(-1, 1, 2)
    p1, st, _ = cv2.calcOpticalFlowPyrLK(a, b, p0, None)  # type: ignore[call-overload]
    p1 = p1.reshape(-1, 2).astype(np.float64)
    h, w = a.shape
    inside = (p1[:, 0] >= 0) & (p1[:, 1] >= 0) & (p1[:, 0] <= w - 1) & (p1[:, 1] <= h - 1)
    return p1, (st.reshape(-1) == 1) & inside & np.isfinite(p1).all(axis=1)


def _score(errors: np.ndarray, one_motion: np.ndarray | None = None,
           beside: np.ndarray | None = None) -> Score:
    e = np.asarray(errors, np.float64)

    def gross_and(flags: np.ndarray | None) -> float | None:
        return None if flags is None or not len(e) else float(np.mean((e > GROSS_PX) & flags))
    return Score(pairs=len(e), median_epe=float(np.median(e)) if len(e) else float("nan"),
                 gross=float(np.mean(e > GROSS_PX)) if len(e) else float("nan"),
                 gross_one_motion=gross_and(one_motion), gross_beside=gross_and(beside))


#: the share of a window's pixels whose flow must be known for :func:`one_motion` to judge it
KNOWN_SHARE = 0.25


def one_motion(flow: np.ndarray, n: int) -> Callable[[np.ndarray, int], np.ndarray]:
    """``f(points, k)``: whether the ground truth ``flow`` (H, W, 2) varies by less than
    GROSS_PX across the (2n + 1)^2 window of each point (N, 2), over its pixels of known flow
    where they are at least KNOWN_SHARE of it (sparse ground truth, KITTI's LiDAR-based: a
    window known everywhere was none of its pairs', and every gross error there read as on a
    motion boundary). A
    window across a motion boundary holds two motions: the flow of its centre pixel is not
    the one motion a patch tracker can report (on the pairs, every feature off by more than
    2 px had 2.5 to 15.7 px of flow across its window; the others' median, 0.4 to 0.7)."""
    h, w = flow.shape[:2]

    def f(points: np.ndarray, k: int) -> np.ndarray:
        out = np.zeros(len(points), bool)
        for j, (x, y) in enumerate(np.rint(points).astype(int)):
            if n <= x < w - n and n <= y < h - n:
                win = flow[y - n:y + n + 1, x - n:x + n + 1].reshape(-1, 2)
                win = win[np.isfinite(win).all(1)]  # unknown flow is NaN (read_flo)
                if len(win) >= KNOWN_SHARE * (2 * n + 1) ** 2:
                    out[j] = np.hypot(*(win.max(0) - win.min(0))) < GROSS_PX
        return out
    return f


#: a pair's displacement within this of the ground truth at a pixel next to its point's, px,
#: is that pixel's motion (:func:`beside_truth`)
BESIDE_PX = 0.5


def beside_truth(flow: np.ndarray) -> Callable[[np.ndarray, np.ndarray, int], np.ndarray]:
    """``f(points, moved, k)``: whether each displacement ``moved`` (N, 2) of the points
    (N, 2) is within BESIDE_PX of the ground truth ``flow`` (H, W, 2) at one of the 3 x 3
    pixels around the point's own (rounded, as the error is taken), where it is known. A
    pair off by more than GROSS_PX that is has measured the motion of the surface beside
    its pixel: a feature on a motion contour (an occluding edge moves with its occluder,
    and the ground truth of the pixels along it is one surface's or the other's), not a
    false match."""
    h, w = flow.shape[:2]

    def f(points: np.ndarray, moved: np.ndarray, k: int) -> np.ndarray:
        out = np.zeros(len(points), bool)
        for j, (x, y) in enumerate(np.rint(points).astype(int)):
            win = flow[max(y - 1, 0):y + 2, max(x - 1, 0):x + 2].reshape(-1, 2)
            win = win[np.isfinite(win).all(axis=1)]  # unknown flow is NaN (read_flo)
            if len(win) and 0 <= x < w and 0 <= y < h:
                out[j] = np.hypot(*(win - moved[j]).T).min() <= BESIDE_PX
        return out
    return f


def run_sequence(frames: Sequence[np.ndarray], step_truth: Truth, params: TrackerParams, *,
                 end_truth: Callable[[np.ndarray], np.ndarray] | None = None,
                 single: Callable[[np.ndarray, int], np.ndarray] | None = None,
                 beside: Callable[[np.ndarray, np.ndarray, int], np.ndarray] | None = None
                 ) -> tuple[Score, Score, int]:
    """Ours and LK over ``frames``.

    ``step_truth(points, k)`` gives the true positions in frame k + 1 of points (N, 2) of frame
    k (NaN where unknown); ``end_truth(points)``, for long sequences, those in the last frame
    of points of the first, for the survival and drift; ``single(points, k)`` (pairs,
    :func:`one_motion`), whether each point's window in frame k holds one motion;
    ``beside(points, moved, k)`` (pairs, :func:`beside_truth`), whether each displacement is
    the ground truth of a pixel next to its point's. Returns (ours, LK, features ours
    rejected).
    """
    tracker = Tracker(params)
    est = tracker.process(frames[0])
    first = dict(zip(est.ids.tolist(), est.points, strict=True))
    ours_err: list[np.ndarray] = []
    lk_err: list[np.ndarray] = []
    ours_one: list[np.ndarray] = []
    lk_one: list[np.ndarray] = []
    ours_near: list[np.ndarray] = []
    lk_near: list[np.ndarray] = []
    lk_pts, lk_alive = est.points.copy(), np.ones(est.npi, bool)
    ours_both: list[np.ndarray] = []
    lk_both: list[np.ndarray] = []

    def errors(found: np.ndarray, starts: np.ndarray, k: int, one: list[np.ndarray],
               near: list[np.ndarray]) -> np.ndarray:
        e = np.hypot(*(found - step_truth(starts, k)).reshape(-1, 2).T)
        known = np.isfinite(e)
        if single is not None:
            one.append(single(starts, k)[known])
        if beside is not None:
            near.append(beside(starts[known], (found - starts)[known], k))
        return e[known]

    for k in range(1, len(frames)):
        starts = est.points
        before = dict(zip(est.ids.tolist(), starts, strict=True))
        # LK from the same points as ours, this step
        p1, ok_step = lk_track(frames[k - 1], frames[k], starts)
        lk_err.append(errors(p1[ok_step], starts[ok_step], k - 1, lk_one, lk_near))
        # LK alone from the first frame's features, for its survival
        if end_truth is not None and lk_alive.any():
            q, ok = lk_track(frames[k - 1], frames[k], lk_pts)
            lk_alive &= ok
            lk_pts = np.where(ok[:, None], q, lk_pts)
        est = tracker.process(frames[k])
        kept = [j for j, i in enumerate(est.ids.tolist()) if i in before]
        if kept:
            a = np.array([before[i] for i in est.ids[kept].tolist()])
            ours_err.append(errors(est.points[kept], a, k - 1, ours_one, ours_near))
            # the pairs both tracked: ours kept the feature and LK's status was 1
            at = {i: j for j, i in enumerate(before)}
            j = np.array([at[i] for i in est.ids[kept].tolist()])
            both = ok_step[j]
            truth = step_truth(starts[j[both]], k - 1)
            ours_both.append(np.hypot(*(est.points[kept][both] - truth).reshape(-1, 2).T))
            lk_both.append(np.hypot(*(p1[j[both]] - truth).reshape(-1, 2).T))

    def flags(lists: list[np.ndarray], wanted: object) -> np.ndarray | None:
        return (np.concatenate(lists) if lists else np.empty(0, bool)) \
            if wanted is not None else None

    def score(err: list[np.ndarray], one: list[np.ndarray], near: list[np.ndarray]) -> Score:
        return _score(np.concatenate(err) if err else np.empty(0), flags(one, single),
                      flags(near, beside))
    ours = _with_both(score(ours_err, ours_one, ours_near), ours_both, lk_both)
    lk = _with_both(score(lk_err, lk_one, lk_near), lk_both, ours_both)
    if end_truth is not None and first:
        start = np.array(list(first.values()))
        where = {i: j for j, i in enumerate(est.ids.tolist())}
        alive = np.array([i in where for i in first])
        ours = _with_survival(ours, alive, est.points[[where[i] for i in first if i in where]],
                              end_truth(start[alive]) if alive.any() else None)
        lk = _with_survival(lk, lk_alive, lk_pts[lk_alive],
                            end_truth(start[lk_alive]) if lk_alive.any() else None)
    return ours, lk, getattr(tracker, "rejected_total", 0)


def _with_both(score: Score, mine: list[np.ndarray], theirs: list[np.ndarray]) -> Score:
    """``score`` with its median over the pairs both trackers tracked (``mine``: this
    tracker's errors on them, ``theirs`` the other's, step by step; NaN where the ground truth
    is unknown on either side)."""
    e = np.concatenate(mine) if mine else np.empty(0)
    known = np.isfinite(e) & np.isfinite(np.concatenate(theirs) if theirs else np.empty(0))
    return dataclasses.replace(score, both_pairs=int(known.sum()), both_median=float(
        np.median(e[known])) if known.any() else float("nan"))


def _with_survival(score: Score, alive: np.ndarray, end: np.ndarray,
                   true_end: np.ndarray | None) -> Score:
    drift = None
    if true_end is not None and len(end):
        drift = float(np.median(np.hypot(*(end - true_end).T)))
    return dataclasses.replace(score, survival=float(alive.mean()), drift=drift)


def _gray(path) -> np.ndarray:
    image = cv2.imread(str(path))
    if image is None:
        raise groundtruth.DataError(f"{path}: cannot read the image")
    return to_gray(image)


def _middlebury_pairs() -> Iterator[tuple[str, list[np.ndarray], np.ndarray, Truth]]:
    """Each Middlebury pair found (:func:`.groundtruth.middlebury_pairs`): its name, its two
    frames, its ground-truth flow and the step truth of :func:`run_sequence`.

    Raises
    ------
    groundtruth.DataError
        For a pair whose files do not read or do not fit together; the text names the file.
    """
    for name in groundtruth.middlebury_pairs(PAIRS):
        folder = groundtruth.middlebury(name)
        if folder is None:
            continue
        frames = [_gray(folder / "frame10.png"), _gray(folder / "frame11.png")]
        flow = groundtruth.read_flo(folder / "flow10.flo")
        if frames[1].shape != frames[0].shape or flow.shape[:2] != frames[0].shape:
            h, w = frames[0].shape
            raise groundtruth.DataError(f"{folder}: frame11.png is {frames[1].shape[1]}x"
                             f"{frames[1].shape[0]} and flow10.flo {flow.shape[1]}x"
                             f"{flow.shape[0]}: expected frame10.png's {w}x{h}")

        def step(points: np.ndarray, k: int, flow: np.ndarray = flow) -> np.ndarray:
            h, w = flow.shape[:2]
            ix = np.clip(np.rint(points[:, 0]).astype(int), 0, w - 1)
            iy = np.clip(np.rint(points[:, 1]).astype(int), 0, h - 1)
            return points + flow[iy, ix]

        yield name, frames, flow, step


#: the earliest frame a running track starts from (Middlebury's "other" sequences hold frame07
#: to frame14, the ground truth between frame10 and frame11)
RUN_FROM = 7


def _frames_before(name: str, shape: tuple[int, ...]) -> list[np.ndarray]:
    """The frames before frame10 in a Middlebury pair's folder, in order: frame09, frame08,
    ... down to RUN_FROM, as many as follow on from frame10 (Middlebury's "other" sequences
    hold frame07 to frame14); empty where there is no frame09.

    Raises
    ------
    groundtruth.DataError
        For a frame that does not read, or whose size is not frame10's ``shape``.
    """
    folder = groundtruth.middlebury(name)
    before: list[np.ndarray] = []
    for k in range(9, RUN_FROM - 1, -1):
        path = folder / f"frame{k:02d}.png" if folder is not None else None
        if path is None or not path.is_file():
            break
        image = _gray(path)
        if image.shape != shape:
            raise groundtruth.DataError(f"{path}: {image.shape[1]}x{image.shape[0]}, "
                                        f"expected frame10.png's {shape[1]}x{shape[0]}")
        before.insert(0, image)
    return before


def _last_step_only(step: Truth, last: int) -> Truth:
    """``step`` (a pair's truth) at step ``last`` of a longer run, NaN at every other step, so
    that :func:`run_sequence` scores that step alone."""
    def run_step(points: np.ndarray, k: int) -> np.ndarray:
        if k == last:
            return step(points, 0)
        return np.full((len(points), 2), np.nan)
    return run_step


#: :func:`dense_pairs`' features: as many as a pair's texture gives, up to this many
DENSE_FEATURES = 500


def dense_pairs(params: TrackerParams) -> list[tuple[str, Score, Score, Score]]:
    """The Middlebury pairs with up to DENSE_FEATURES features each (the top 5 % of the
    pixels as candidates), so that a median moves by less than the settings compared: for
    each pair (name, ours with ``params``, ours without the wide sub-pixel window
    (``refine_size`` 0), LK from the first's features). On real scenes with depth the wide
    window averages its neighbourhood's motions: that row says what it costs there."""
    dense = params.replace(max_features=DENSE_FEATURES, thres_percent=5.0)
    out = []
    for name, frames, _, step in _middlebury_pairs():
        ours, lk, _ = run_sequence(frames, step, dense)
        narrow, _, _ = run_sequence(frames, step, dense.replace(refine_size=0))
        out.append((name, ours, narrow, lk))
    return out


def scoreboard(params: TrackerParams | None = None, *, n_frames: int = 60,
               progress: Callable[[str], None] | None = None) -> list[Row]:
    """Every sequence found: the Middlebury pairs (the shared data's, then any other folder of
    Middlebury's files, :func:`.groundtruth.middlebury_pairs`), then the long rendered
    sequences.

    Raises
    ------
    groundtruth.DataError
        For a pair whose files do not read or do not fit together; the text names the file.
    """
    params = params if params is not None else TrackerParams()
    rows = []
    runs = []

    def pair_run(frames: list[np.ndarray], step: Truth, flow: np.ndarray
                 ) -> tuple[Score, Score, int]:
        """:func:`run_sequence` on a Middlebury pair's frames, with its diagnostics."""
        return run_sequence(frames, step, params, single=one_motion(flow, params.corr_half),
                            beside=beside_truth(flow))

    for name, frames, flow, step in _middlebury_pairs():
        ours, lk, rej = pair_run(frames, step, flow)
        rows.append(Row(f"{name} (pair)", 2, ours, lk, rej))
        if progress:
            progress(name)
        before = _frames_before(name, frames[0].shape)
        if before:
            runs.append((name, [*before, *frames], flow,
                         _last_step_only(step, len(before))))
    # the same pairs at the end of a running track where the folder has the frames before
    # (a robot's tracker meets real frames so: its features held and followed from their
    # velocity, not chosen in frame10 and searched from no motion), scored after all pairs
    for name, frames, flow, step in runs:
        ours, lk, rej = pair_run(frames, step, flow)
        first = 11 - (len(frames) - 1)
        rows.append(Row(f"{name} (pair, running from frame{first:02d})", len(frames), ours, lk,
                        rej))
        if progress:
            progress(f"{name}, running")
    longs = rendered.middlebury_sequences(n_frames)
    # the same views through a camera whose auto-exposure hunts (see rendered.with_exposure)
    # and through a shutter open half the frame interval (see rendered.motion_blurred)
    sources = rendered.middlebury_sources()
    blurred = [rendered.motion_blurred(image, f"{name} rendered", exposure=0.5, n=n_frames)
               for name, image in sources]
    # a bump in a steady run, and an approach (see rendered.jerk, rendered.approach)
    jerks = [rendered.jerk(image, f"{name} rendered") for name, image in sources]
    approaches = [rendered.approach(image, f"{name} rendered") for name, image in sources]
    # a turn about the view's centre, and a camera that shakes (see rendered.roll, .shake)
    rolls = [rendered.roll(image, f"{name} rendered") for name, image in sources]
    shakes = [rendered.shake(image, f"{name} rendered") for name, image in sources]
    # the shake through a rolling shutter (see rendered.with_rolling_shutter)
    rolling = [rendered.with_rolling_shutter(
        image, rendered.shake(image, f"{name} rendered", n=31), ROLLING_READOUT)
        for name, image in sources]
    for seq in [*longs, *(rendered.with_exposure(s) for s in longs), *blurred, *jerks,
                *approaches, *rolls, *shakes, *rolling]:
        ours, lk, rej = run_sequence(seq.frames, _step_of(seq), params, end_truth=_end_of(seq))
        rows.append(Row(seq.name, len(seq), ours, lk, rej))
        if progress:
            progress(seq.name)
    return rows


def _step_of(seq: rendered.RenderedSequence) -> Truth:
    def step(points: np.ndarray, k: int) -> np.ndarray:
        return seq.map(points, k, k + 1)
    return step


def _end_of(seq: rendered.RenderedSequence) -> Callable[[np.ndarray], np.ndarray]:
    def end(points: np.ndarray) -> np.ndarray:
        return seq.map(points, 0, len(seq) - 1)
    return end


def _pct(share: float) -> str:
    """A share as the table's 6-character percentage, '-' where there is none (NaN)."""
    return f"{'-':>6s}" if not np.isfinite(share) else f"{100 * share:5.2f}%"


def _fmt(v: float | None, spec: str) -> str:
    width = int(spec.split(".")[0])
    return f"{'-':>{width}s}" if v is None or not np.isfinite(v) else format(v, spec)


def bench_accuracy(out=sys.stdout, params: TrackerParams | None = None) -> dict[str, float]:
    """Run the scoreboard, print its table, return the figures by ``<sequence>_<what>``."""
    cv2.setNumThreads(1)
    warm_up()
    params = params if params is not None else TrackerParams()
    t0 = time.perf_counter()
    rows = scoreboard(params)
    print(f"# vistrack bench accuracy: ours ({_describe(params)}) against "
          "cv2.calcOpticalFlowPyrLK (defaults: 21x21, maxLevel 3) from the same features",
          file=out)
    if not rows:
        print("(no Middlebury data found: set VISTRACK_DATA or put the shared data at "
              "../shared/data)", file=out)
        return {}
    side = max(32, *(len(r.sequence) for r in rows))  # the sequence column's width
    print(f"{'sequence':{side}s} {'frames':>6s} | {'pairs':>6s} {'median':>7s} {'>2px':>6s} "
          f"{'surv':>5s} {'drift':>6s} {'rej':>5s} | {'pairs':>6s} {'median':>7s} "
          f"{'>2px':>6s} {'surv':>5s} {'drift':>6s} | {'EPE ok':>6s} | {'pairs':>6s} "
          f"{'ours':>7s} {'LK':>7s} {'EPE ok':>6s}", file=out)
    print(f"{'':{side}s} {'':6s} | {'ours':^42s} | {'LK':^35s} | {'':6s} | "
          f"{'the pairs both tracked':^29s}", file=out)
    fig: dict[str, float] = {}
    for r in rows:
        o, lk = r.ours, r.lk
        # a row where either tracked no pair with ground truth (a user's pair whose ground
        # truth is sparse, KITTI's) has nothing to compare: '-', and no target counts it
        verdict = ("-" if not _compared(r) else
                   "yes" if o.median_epe <= lk.median_epe else "NO")
        print(f"{r.sequence:{side}s} {r.frames:6d} | {o.pairs:6d} {_fmt(o.median_epe, '7.3f')} "
              f"{_pct(o.gross)} {_fmt(o.survival, '5.2f')} {_fmt(o.drift, '6.2f')} "
              f"{r.rejected:5d} | {lk.pairs:6d} {_fmt(lk.median_epe, '7.3f')} {_pct(lk.gross)} "
              f"{_fmt(lk.survival, '5.2f')} {_fmt(lk.drift, '6.2f')} | {verdict:>6s} | "
              f"{o.both_pairs:6d} {_fmt(o.both_median, '7.3f')} {_fmt(lk.both_median, '7.3f')} "
              f"{_both_verdict(r):>6s}", file=out)
        key = _key(r)
        fig.update({f"{key}_median": o.median_epe, f"{key}_lk_median": lk.median_epe,
                    f"{key}_gross": o.gross, f"{key}_lk_gross": lk.gross,
                    f"{key}_pairs": float(o.pairs), f"{key}_lk_pairs": float(lk.pairs),
                    f"{key}_both_pairs": float(o.both_pairs),
                    f"{key}_both_median": o.both_median, f"{key}_lk_both_median": lk.both_median})
        if o.survival is not None and lk.survival is not None:
            fig[f"{key}_survival"] = o.survival
            fig[f"{key}_lk_survival"] = lk.survival
    longs = [r for r in rows if r.ours.survival is not None]
    pairs = sum(r.ours.pairs for r in rows)
    gross = sum(r.ours.gross * r.ours.pairs for r in rows if r.ours.pairs) / max(pairs, 1)
    lk_pairs = sum(r.lk.pairs for r in rows)
    lk_gross = sum(r.lk.gross * r.lk.pairs for r in rows if r.lk.pairs) / max(lk_pairs, 1)
    fig["all_gross"] = gross
    fig["all_lk_gross"] = lk_gross
    print(f"all sequences: {pairs} pairs, {100 * gross:.2f} % off by > {GROSS_PX:g} px "
          f"(LK: {lk_pairs}, {100 * lk_gross:.2f} %)"
          + ("; rendered ones alone: " + ", ".join(f"{100 * r.ours.gross:.2f} %" for r in longs)
             if longs else ""), file=out)
    pairs_rows = [r for r in rows if r.ours.gross_one_motion is not None]
    if pairs_rows:
        print(f"pairs off by > {GROSS_PX:g} px whose correlation window holds one motion "
              f"(its ground truth varying by < {GROSS_PX:g} px across it), ours / LK: "
              + ", ".join(f"{_pair_name(r)} "
                          f"{100 * (r.ours.gross_one_motion or 0):.2f}"
                          f" / {100 * (r.lk.gross_one_motion or 0):.2f} %"
                          for r in pairs_rows), file=out)
        print(f"pairs off by > {GROSS_PX:g} px whose displacement is the ground truth of a "
              f"pixel next to the feature's, to within {BESIDE_PX:g} px (a feature on a "
              "motion contour, which measured the surface beside its pixel), ours / LK: "
              + ", ".join(f"{_pair_name(r)} {_count(r.ours.gross_beside, r.ours.pairs)} of "
                          f"{_count(r.ours.gross, r.ours.pairs)} / "
                          f"{_count(r.lk.gross_beside, r.lk.pairs)} of "
                          f"{_count(r.lk.gross, r.lk.pairs)}" for r in pairs_rows), file=out)
        for r in pairs_rows:
            key = _key(r)
            fig[f"{key}_gross_one_motion"] = r.ours.gross_one_motion or 0.0
            fig[f"{key}_lk_gross_one_motion"] = r.lk.gross_one_motion or 0.0
            fig[f"{key}_gross_beside"] = r.ours.gross_beside or 0.0
            fig[f"{key}_lk_gross_beside"] = r.lk.gross_beside or 0.0
    dense = dense_pairs(params)
    if dense:
        print(f"the pairs with up to {DENSE_FEATURES} features each, median end-point error, "
              f"ours / ours with refine_size 0 (no wide window) / LK: "
              + ", ".join(f"{name} {o.median_epe:.3f} / {n.median_epe:.3f} / {lk.median_epe:.3f}"
                          f" ({o.pairs} pairs)" for name, o, n, lk in dense), file=out)
        for name, o, n, lk in dense:
            fig[f"{name}_dense_median"] = o.median_epe
            fig[f"{name}_dense_narrow_median"] = n.median_epe
            fig[f"{name}_dense_lk_median"] = lk.median_epe
    compared = [r for r in rows if _compared(r)]
    apart = len(rows) - len(compared)
    print(f"targets: median <= LK's on every sequence: "
          f"{'met' if all(r.ours.median_epe <= r.lk.median_epe for r in compared) else 'NOT met'}"
          + (f" ({apart} without pairs on one side, not counted)" if apart else "")
          + "; on the pairs both tracked: "
          + ("met" if all(_both_verdict(r) != "NO" for r in rows) else "NOT met")
          + f"; pairs off by > {GROSS_PX:g} px <= 2 % on every sequence: "
          f"{'met' if all(r.ours.gross <= 0.02 for r in compared) else 'NOT met'} (worst "
          f"{100 * max((r.ours.gross for r in compared), default=0.0):.2f} %), over all: "
          f"{'met' if gross <= 0.02 else 'NOT met'}; survival >= half LK's: "
          + ("met" if all((r.ours.survival or 0) >= 0.5 * (r.lk.survival or 0) for r in longs)
             else "NOT met")
          + f"; {time.perf_counter() - t0:.1f} s", file=out)
    return fig


def _pair_name(row: Row) -> str:
    """A pair's row in the summary lines: its source, and ``running`` for the running row."""
    return row.sequence.split(" ")[0] + (" running" if ", running" in row.sequence else "")


def _count(share: float | None, pairs: int) -> int:
    """How many of ``pairs`` a ``share`` of them is (None: none)."""
    return round((share or 0.0) * pairs)


def _key(row: Row) -> str:
    """The row's prefix in :func:`bench_accuracy`'s figures: ``<source>_pair``,
    ``<source>_running`` (the pair after a running track) or ``<source>_long`` and the
    rendered sequence's kind (``_exposure``, ``_blur``, ...)."""
    name, seq = row.sequence.split(" ")[0], row.sequence
    if ", running from" in seq:
        return f"{name}_running"
    return name + ("_pair" if row.frames == 2 else "_long") \
        + ("_exposure" if seq.endswith(", exposure") else "") \
        + ("_blur" if ", blur" in seq else "") \
        + ("_jerk" if seq.endswith(", jerk") else "") \
        + ("_approach" if seq.endswith(", approach") else "") \
        + ("_roll" if seq.endswith(", roll") else "") \
        + ("_shake" if ", shake" in seq else "") \
        + ("_rolling" if ", rolling shutter" in seq else "")


def _compared(row: Row) -> bool:
    """Whether both trackers have pairs with ground truth in ``row``."""
    return row.ours.pairs > 0 and row.lk.pairs > 0


def _both_verdict(row: Row) -> str:
    """'yes' where ours's median on the pairs both tracked is at most LK's on them, 'NO'
    where it is above, '-' where they tracked no pair in common."""
    if not row.ours.both_pairs:
        return "-"
    return "yes" if row.ours.both_median <= row.lk.both_median else "NO"


def _describe(params: TrackerParams) -> str:
    default = TrackerParams()
    changed = [f"{k}={v}" for k, v in params.as_dict().items() if getattr(default, k) != v]
    return "default parameters" + (f" but {', '.join(changed)}" if changed else "")
