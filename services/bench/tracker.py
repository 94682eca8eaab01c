"""``vistrack bench tracker``: the tracker against OpenCV, in the same process and moment.

``vistrack bench tracker`` times, on the same 256x256 real frames and the same 100 features:
our single-level SSD search at (15, 9), the paper's; a per-feature ``cv2.matchTemplate`` loop
doing the same search; ``cv2.calcOpticalFlowPyrLK`` (winSize 9, maxLevel 0 and 2, and its
defaults: winSize 21, maxLevel 3); our search at the reference windows (50, 30); the paper's
exhaustive search at (15, 9) and (50, 30); the default tracker's SSD tracking (the
coarse-to-fine search with its checks and sub-pixel refinement, given both frames' pyramids),
the pyramid it builds once a frame, the same search without its checks, and the tracker
without each of its costliest steps in turn (what that step costs); and our whole
frame (pre-processing + tracking + estimate) with the default tracker and with the paper's
(one level, no rules), and the pre-processing done every frame alone (the filter; candidates
are computed only on the frames that select or re-detect features) against
``cv2.GaussianBlur`` alone. It prints time per frame, the ratios, and the
median end-point error of ours (default parameters) and of LK against the Middlebury ground
truth. Last, the default tracker's SSD tracking of one frame pair and LK's (its defaults) after
an idle gap (:data:`GAPS_S`): a service's frames come after one, and this machine runs work
after an idle gap slower than back to back (measured: OpenCV's calls by a near fixed ~0.1 ms
after 33 ms, ours by about twice that). And the tracker over frames a camera dropped at
random (:data:`SKIPS`), told their numbers (``seq``, as motion-estimation is) against not
told: how many features follow their prediction, and the time a frame.
Everything runs on one core (OpenCV's threads set to 1; numba kernels are single-threaded).
"""

from __future__ import annotations

import functools
import sys
import time
from collections.abc import Callable

import cv2
import numpy as np

from ...common import groundtruth, rendered, synthetic
from ...common.params import TrackerParams
from ...common.vision import Tracker, preprocess, to_gray, track_ssd, warm_up, window_weights
from ...common.vision.pyramid import TrackPlan, build_pyramid
from ...common.vision.tracker import track_plan


def _batch(fn: Callable[[], object], min_time: float) -> int:
    """Calls of ``fn`` (warmed up once) that take at least ``min_time`` s together."""
    fn()
    n = 1
    while True:
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        if time.perf_counter() - t0 >= min_time:
            return n
        n *= 2


def _interleaved(fns: dict[str, Callable[[], object]], *, rounds: int = 7,
                 min_time: float = 0.05) -> dict[str, float]:
    """Seconds per call of each of ``fns``: the best of ``rounds`` batches (each >= min_time),
    as timeit does, because on a shared 2-core machine the minimum is the least disturbed
    figure. Each round times every function once, one after the other, so that all of them
    see the machine in the same states: timed one function after another instead, a step's
    cost read off two rows (the tracker with and without it) came out negative in some runs."""
    sizes = {name: _batch(fn, min_time) for name, fn in fns.items()}
    best = dict.fromkeys(fns, float("inf"))
    for _ in range(rounds):
        for name, fn in fns.items():
            n = sizes[name]
            t0 = time.perf_counter()
            for _ in range(n):
                fn()
            best[name] = min(best[name], (time.perf_counter() - t0) / n)
    return best


#: Idle gaps before a frame, s: none (back to back, as the table's rows), ~1.1 ms (a service of
#: the unpaced five-process pipeline, ~900 frames a second) and 33 ms (a service at 30 fps).
GAPS_S = (0.0, 0.0011, 0.033)


def _after_gaps(steps: dict[str, Callable[[int], object]], n: int,
                gaps: tuple[float, ...] = GAPS_S, rounds: int = 2) -> dict[str, list[float]]:
    """Median seconds of one call ``step(i)`` (i = 0, 1, ... n - 1, a frame pair) of each of
    ``steps`` when the thread slept ``gap`` s before it, for each of ``gaps`` in turn (one list
    per step, in the order of ``gaps``). The steps take turns gap by gap, ``rounds`` times."""
    times: dict[str, list[list[float]]] = {name: [[] for _ in gaps] for name in steps}
    for _ in range(rounds):
        for j, gap in enumerate(gaps):
            for name, step in steps.items():
                step(0)  # whatever the step before left, not a gap's first frame
                for i in range(n):
                    if gap:
                        time.sleep(gap)
                    t0 = time.perf_counter()
                    step(i)
                    times[name][j].append(time.perf_counter() - t0)
    return {name: [float(np.median(t)) for t in by_gap] for name, by_gap in times.items()}


#: Frames a camera drops before each one it sends, drawn at random (seed 7) along the
#: scoreboard's rendered path: none (half the time), one or two.
SKIPS = (0, 0, 1, 2)


def _skipping(params: TrackerParams) -> tuple[list, list[int]] | None:
    """RubberWhale's rendered 60-frame path (up to 12 px a frame) as a camera dropping
    :data:`SKIPS` frames at random sends it: (the frames kept, pre-processed; their numbers),
    or None without the shared data."""
    found = rendered.middlebury_sources(("RubberWhale",))
    if not found:
        return None
    name, image = found[0]
    seq = rendered.sequence(image, f"{name} rendered", n=60)
    rng = np.random.default_rng(7)
    kept = [0]
    while (nxt := kept[-1] + 1 + int(rng.choice(SKIPS))) < len(seq):
        kept.append(nxt)
    return [preprocess(seq.frames[k], params) for k in kept], kept


def _skipping_run(params: TrackerParams, frames: list, kept: list[int], told: bool) -> int:
    """One run of a fresh tracker over ``frames``, given their numbers (``told``) or not:
    the features that followed their prediction."""
    tracker = Tracker(params)
    for pre, k in zip(frames, kept, strict=True):
        tracker.update(pre, seq=k if told else None)
    return tracker.followed


def _whole_after_first(frames: list[np.ndarray], params: TrackerParams,
                       rounds: int = 100) -> tuple[float, float]:
    """(ours, peer) seconds a frame, the best of ``rounds``: a fresh tracker's whole frame
    (pre-processing, tracking, estimate) on the frames after its first pair, the first two
    processed untimed (a run selects its features, then the first pair follows them from no
    motion and searches those that do not follow), and in the same rounds OpenCV's LK with
    its defaults on the same frame pairs from the same features (a reference run's)."""
    ref = Tracker(params)
    starts = [ref.process(f).points.astype(np.float32).reshape(-1, 1, 2) for f in frames]
    pairs = list(zip(frames[1:-1], frames[2:], starts[1:-1], strict=True))
    ours = peer = float("inf")
    for _ in range(rounds):
        tracker = Tracker(params)
        tracker.process(frames[0])
        tracker.process(frames[1])
        t0 = time.perf_counter()
        for f in frames[2:]:
            tracker.process(f)
        ours = min(ours, (time.perf_counter() - t0) / len(pairs))
        t0 = time.perf_counter()
        for a, b, pts in pairs:
            cv2.calcOpticalFlowPyrLK(a, b, pts, None)  # type: ignore[call-overload]
        peer = min(peer, (time.perf_counter() - t0) / len(pairs))
    return ours, peer


def _frames_256() -> tuple[list[np.ndarray], str]:
    folder = groundtruth.middlebury("RubberWhale")
    if folder is None:
        return synthetic.builtin_sequence(8)[:8], "built-in sequence (no shared data found)"
    frames = [to_gray(cv2.imread(str(folder / f"frame{i:02d}.png")))[66:322, 164:420]
              for i in range(7, 15)]
    return [np.ascontiguousarray(f) for f in frames], "RubberWhale frame07-14, 256x256 crop"


def _matchtemplate_loop(prev: np.ndarray, curr: np.ndarray, pts: np.ndarray, n: int,
                        s: int) -> np.ndarray:
    """The per-feature OpenCV loop doing our search: TM_SQDIFF over the same window."""
    h, w = prev.shape
    out = np.empty((len(pts), 2))
    for k, (x, y) in enumerate(pts):
        tmpl = prev[y - n:y + n + 1, x - n:x + n + 1]
        y0, x0 = max(y - s - n, 0), max(x - s - n, 0)
        region = curr[y0:min(y + s + n + 1, h), x0:min(x + s + n + 1, w)]
        res = cv2.matchTemplate(region, tmpl, cv2.TM_SQDIFF)
        _, _, loc, _ = cv2.minMaxLoc(res)
        out[k] = (x0 + loc[0] + n, y0 + loc[1] + n)
    return out


def _accuracy() -> list[tuple[str, float, float, float, int]]:
    """(sequence, ours median EPE, LK level 0, LK level 2, points) on full Middlebury frames."""
    rows = []
    for name in ("RubberWhale", "Dimetrodon", "Venus"):
        folder = groundtruth.middlebury(name)
        if folder is None:
            continue
        a = to_gray(cv2.imread(str(folder / "frame10.png")))
        b = to_gray(cv2.imread(str(folder / "frame11.png")))
        flow = groundtruth.read_flo(folder / "flow10.flo")
        tracker = Tracker(TrackerParams())
        e0 = tracker.process(a)
        e1 = tracker.process(b)
        start = dict(zip(e0.ids.tolist(), e0.points, strict=True))
        before = np.array([start[i] for i in e1.ids.tolist()])
        ours = float(np.median(groundtruth.endpoint_errors(before, e1.points, flow)))
        p0 = e0.points.astype(np.float32).reshape(-1, 1, 2)
        lk = []
        for level in (0, 2):
            p1, st, _ = cv2.calcOpticalFlowPyrLK(a, b, p0, None,  # type: ignore[call-overload]
                                         winSize=(9, 9), maxLevel=level)
            good = st[:, 0] == 1
            lk.append(float(np.median(groundtruth.endpoint_errors(
                p0.reshape(-1, 2)[good], p1.reshape(-1, 2)[good], flow))))
        rows.append((name, ours, lk[0], lk[1], e0.npi))
    return rows


def bench_tracker(out=sys.stdout) -> dict[str, float]:
    """Run the tracker benchmark, print its table, return the figures (us per frame)."""
    cv2.setNumThreads(1)
    warm_up()
    frames, what = _frames_256()
    params = TrackerParams()
    pre = [preprocess(f, params) for f in frames]
    # one real run fixes, for every frame pair, the 100 features (anchors in frame t) and
    # their predicted positions in frame t+1: every method below gets exactly these inputs
    tracker = Tracker(params)
    anchors, centers, points, preds, helds = [], [], [], [], []
    est = tracker.update(pre[0])
    vel = np.zeros_like(est.points)
    for p in pre[1:]:
        anchors.append(np.rint(est.points).astype(np.int64))
        centers.append(np.rint(est.points + vel).astype(np.int64))
        points.append(est.points.copy())
        preds.append(est.points + vel)
        helds.append(tracker.held)  # what the tracker follows first
        prev_pts = dict(zip(est.ids.tolist(), est.points, strict=True))
        est = tracker.update(p)
        vel = np.array([pt - prev_pts.get(i, pt)
                        for i, pt in zip(est.ids.tolist(), est.points, strict=True)])
    n_feat = int(np.mean([len(a) for a in anchors]))
    jobs = list(zip(pre[:-1], pre[1:], anchors, centers, strict=True))
    raw = list(zip(frames[:-1], frames[1:], anchors, strict=True))

    def ssd_at(search: int, corr: int, subpixel: bool = False,
               kind: str = "pruned") -> Callable[[], None]:
        wts = window_weights("uniform", corr // 2)

        def run() -> None:
            for a, b, anc, cen in jobs:
                track_ssd(a.filtered, b.filtered, anc, cen, corr_half=corr // 2,
                          search_half=search // 2, weights=wts, subpixel=subpixel, search=kind)
        return run

    pyrs = [build_pyramid(p.filtered, params.levels) for p in pre]
    pjobs = list(zip(pyrs[:-1], pyrs[1:], points, preds, helds, strict=True))

    def default_tracker(checks: bool = True, pairs: slice = slice(None),
                        **without: object) -> Callable[[], None]:
        """The default tracker's SSD tracking (:meth:`Tracker._track`), pyramids given, over
        ``pairs`` of the frame pairs; ``without``: parameters that turn one of its steps
        off."""
        p = params if checks else params.replace(uniqueness=0.0, max_fb_error=0.0,
                                                 consensus=0.0, reject_border=False,
                                                 guided_retry=False, subpixel=False,
                                                 refine_size=0)
        # the settings as the tracker makes them once (Tracker._search)
        plan = track_plan(p.replace(**without), params.noise_sigma)

        def run() -> None:
            for job in pjobs[pairs]:
                track_pair(plan, job)
        return run

    def track_pair(plan: TrackPlan, job: tuple) -> None:
        a, b, pts, pr, hd = job
        plan.track(a, b, pts, pr, held=hd)

    def pyramid() -> None:
        for p in pre[1:]:
            build_pyramid(p.filtered, params.levels)

    def mt() -> None:
        for a, b, anc, _ in jobs:
            _matchtemplate_loop(a.filtered, b.filtered, anc, 4, 7)

    pts32 = [anc.astype(np.float32).reshape(-1, 1, 2) for _, _, anc in raw]

    def lk_pair(i: int, level: int = 3, win: int = 21) -> None:
        a, b, _ = raw[i]
        cv2.calcOpticalFlowPyrLK(a, b, pts32[i], None,  # type: ignore[call-overload]
                                 winSize=(win, win), maxLevel=level)

    def lk(level: int, win: int = 9) -> Callable[[], None]:
        def run() -> None:
            for i in range(len(raw)):
                lk_pair(i, level, win)
        return run

    def whole(p: TrackerParams = params) -> Callable[[], None]:
        def run() -> None:
            tr = Tracker(p)
            for f in frames[1:]:
                tr.process(f)
        return run

    def pre_only() -> None:
        for f in frames[1:]:
            preprocess(f, params)

    # OpenCV's filter itself, not ours (gaussian_filter gives its output by its own kernel)
    ksize = 2 * int(np.ceil(3 * params.blur_sigma)) + 1

    def blur() -> None:
        for f in frames[1:]:
            cv2.GaussianBlur(f, (ksize, ksize), params.blur_sigma,
                             borderType=cv2.BORDER_REPLICATE)

    k = len(jobs)
    n_frames = len(frames) - 1
    # name -> (what is timed, calls it stands for: frame pairs or frames)
    timed: dict[str, tuple[Callable[[], None], int]] = {
        "ssd_15_9": (ssd_at(15, 9), k),
        "ssd_15_9_subpixel": (ssd_at(15, 9, True), k),
        "matchtemplate_15_9": (mt, k),
        "lk_level0": (lk(0), k),
        "lk_level2": (lk(2), k),
        "lk_default": (lk(3, 21), k),
        "default_ssd": (default_tracker(), k),
        "default_ssd_no_checks": (default_tracker(False), k),
        # the frame pairs after the first, whose features were tracked into frame t
        "default_ssd_steady": (default_tracker(pairs=slice(1, None)), k - 1),
        "default_ssd_no_follow": (default_tracker(follow=False), k),
        # what each step of the default tracker costs: the tracker without it
        "default_ssd_no_fb": (default_tracker(max_fb_error=0.0), k),
        "default_ssd_no_wide": (default_tracker(refine_size=0), k),
        "default_ssd_no_consensus": (default_tracker(consensus=0.0), k),
        "default_ssd_no_uniqueness": (default_tracker(uniqueness=0.0), k),
        "pyramid_build": (pyramid, k),
        "ssd_50_30": (ssd_at(50, 30), k),
        "ssd_15_9_exhaustive": (ssd_at(15, 9, kind="exhaustive"), k),
        "ssd_50_30_exhaustive": (ssd_at(50, 30, kind="exhaustive"), k),
        # the first frame of each run selects features; the rest track: t_ms of tf frames
        "whole_frame": (whole(), n_frames),
        "whole_frame_paper": (whole(TrackerParams.paper()), n_frames),
        "preprocess": (pre_only, n_frames),
        "gaussian_blur": (blur, n_frames),
    }
    seconds = _interleaved({name: fn for name, (fn, _) in timed.items()})
    fig = {name: seconds[name] / calls * 1e6 for name, (_, calls) in timed.items()}
    print(f"# vistrack bench tracker: {what}; {n_feat} features per frame (mean); one core",
          file=out)
    print(f"{'method':44s} {'us/frame':>10s} {'vs ours (15,9)':>15s}", file=out)
    base = fig["ssd_15_9"]
    labels = [("ssd_15_9", "ours SSD (15, 9)"),
              ("ssd_15_9_subpixel", "ours SSD (15, 9) + sub-pixel"),
              ("matchtemplate_15_9", "cv2.matchTemplate loop, same search"),
              ("lk_level0", "cv2.calcOpticalFlowPyrLK win 9 maxLevel 0"),
              ("lk_level2", "cv2.calcOpticalFlowPyrLK win 9 maxLevel 2"),
              ("lk_default", "cv2.calcOpticalFlowPyrLK defaults (21, 3)"),
              ("default_ssd", "ours default tracker: SSD tracking"),
              ("default_ssd_steady", "  its frames after the first (features held)"),
              ("default_ssd_no_follow", "  every feature coarse to fine (no follow)"),
              ("default_ssd_no_checks", "  its search alone (no checks, integer)"),
              ("default_ssd_no_fb", "  without the FB check (nor follow)"),
              ("default_ssd_no_wide", "  without the wide sub-pixel window"),
              ("default_ssd_no_consensus", "  without the consensus"),
              ("default_ssd_no_uniqueness", "  without the uniqueness test"),
              ("pyramid_build", "  + its pyramid, built once a frame"),
              ("ssd_50_30", "ours SSD reference (50, 30)"),
              ("ssd_15_9_exhaustive", "ours SSD (15, 9), exhaustive search"),
              ("ssd_50_30_exhaustive", "ours SSD (50, 30), exhaustive search"),
              ("whole_frame", "ours whole frame: pre + track + estimate"),
              ("whole_frame_paper", "  the same with the paper's tracker (levels 1)"),
              ("preprocess", "  its pre-processing, every frame (filter)"),
              ("gaussian_blur", "  cv2.GaussianBlur alone, the same filter")]
    for key, label in labels:
        print(f"{label:44s} {fig[key]:10.1f} {fig[key] / base:14.2f}x", file=out)
    print(f"default tracker (levels {params.levels}, checks, sub-pixel {params.subpixel}): "
          f"{fig['default_ssd']:.1f} us a frame, {fig['default_ssd'] / base:.2f}x the "
          f"single-level search, {fig['default_ssd'] / fig['lk_default']:.2f}x OpenCV's LK "
          f"with its defaults; with its pyramid {fig['default_ssd'] + fig['pyramid_build']:.1f}"
          " us", file=out)
    print(f"speed-up over the matchTemplate loop: {fig['matchtemplate_15_9'] / base:.1f}x, over "
          f"LK level 0: {fig['lk_level0'] / base:.2f}x; "
          f"tf ratio (50, 30) / (15, 9): {fig['ssd_50_30'] / base:.1f}x pruned, "
          f"{fig['ssd_50_30_exhaustive'] / fig['ssd_15_9_exhaustive']:.1f}x exhaustive (the "
          "paper's search, which scores every displacement in full)", file=out)
    rounds = 100
    ours, peer = _whole_after_first(frames, params, rounds)
    fig["whole_frame_steady"], fig["lk_default_steady"] = ours * 1e6, peer * 1e6
    print(f"ours whole frame after a run's first pair: {ours * 1e6:.1f} us a frame (its "
          f"{len(frames) - 2} frames, best of {rounds} runs), {ours / peer:.2f}x OpenCV's LK with "
          f"its defaults on the same pairs in the same rounds ({peer * 1e6:.1f} us)", file=out)
    default_plan = track_plan(params, params.noise_sigma)
    gaps = _after_gaps({"ours": lambda i: track_pair(default_plan, pjobs[i % k]),
                        "lk": lambda i: lk_pair(i % k)}, n=8 * k)
    print("\nafter an idle gap (median of one frame pair; the rows above run back to back):",
          file=out)
    print(f"{'gap':>8s} {'ours default tracker':>21s} {'LK defaults':>12s} {'ours / LK':>10s}",
          file=out)
    for j, gap in enumerate(GAPS_S):
        ours, peer = gaps["ours"][j] * 1e6, gaps["lk"][j] * 1e6
        fig[f"default_ssd_gap_{gap * 1e3:g}ms"] = ours
        fig[f"lk_default_gap_{gap * 1e3:g}ms"] = peer
        print(f"{gap * 1e3:6.1f}ms {ours:16.1f} us {peer:9.1f} us {ours / peer:9.2f}x "
              f"  ({ours / (gaps['ours'][0] * 1e6):.2f}x and {peer / (gaps['lk'][0] * 1e6):.2f}x"
              " back to back)", file=out)
    skipping = _skipping(params)
    if skipping is not None:
        frames_kept, kept = skipping
        runs = _interleaved({t: functools.partial(_skipping_run, params, frames_kept, kept,
                                                  t == "told") for t in ("told", "blind")},
                            rounds=5)
        followed = {t: _skipping_run(params, frames_kept, kept, t == "told")
                    for t in ("told", "blind")}
        per = {t: runs[t] / len(kept) * 1e6 for t in runs}
        fig["skipping_told"], fig["skipping_blind"] = per["told"], per["blind"]
        print(f"\nframes dropped at random (RubberWhale's rendered path, {len(kept)} of 60 "
              f"frames kept, 0 to 2 dropped before each), the tracker told their seq "
              f"{per['told']:.1f} us a frame, not told {per['blind']:.1f} us "
              f"({per['told'] / per['blind']:.2f}x); "
              f"features that followed their prediction {followed['told']} against "
              f"{followed['blind']}", file=out)
    acc = _accuracy()
    if acc:
        print("\nmedian end-point error vs Middlebury ground truth (px), same features:",
              file=out)
        print(f"{'sequence':12s} {'ours':>10s} {'LK lvl0':>8s} {'LK lvl2':>8s} "
              f"{'points':>6s}", file=out)
        for name, ours, lk0, lk2, npts in acc:
            print(f"{name:12s} {ours:10.3f} {lk0:8.3f} {lk2:8.3f} {npts:6d}", file=out)
            fig[f"epe_{name}"] = ours
            fig[f"epe_lk2_{name}"] = lk2
    else:
        print("\n(no Middlebury data: accuracy table skipped)", file=out)
    return fig
