"""Sensitivity sweep of SEARCH_SIZE x CORR_SIZE, the optimum, and the whole tuning cycle.

Section 6.1 of the paper sweeps the search window width over 10..20 px and the correlation
window width over 5..15 px, with the other factors fixed at Table 4's values (MAX_FEAT_NUM 100,
THRES_PERCENT 2, UNGROUP_SIZE 5), plots t1, ex and ey over the grid (Figures 5 to 7) and picks
15 and 9 as "ideal" by eye. :func:`optimum` automates that choice: the fastest setting (least
tf) whose errors ex and ey against the reference windows (50, 30) both stay within a tolerance.

Grid step (default 2)
    A width w behaves exactly like w + 1 when both have the same ``w // 2``
    (:mod:`vistrack.common.params`), so on 10..20 x 5..15 the step-2 grid (10, 12, ..., 20) x
    (5, 7, ..., 15) already holds every distinct window geometry: 6 x 6 = 36 settings. A step
    of 1 shows the same surfaces with every value twice, at no extra cost (runs are cached by
    their effective geometry); a step of 4 is the coarse choice for quick checks.

Tolerance (default 0.5 px)
    Without sub-pixel refinement the SSD search of Eq. (1) matches whole pixels. A setting that
    loses the motion (a search window too small for it, a correlation window too small to be
    unique) is a whole pixel or more off the reference from that frame on, while one that
    differs only in a few features' matches is off by a fraction of a pixel (1/NPI per feature
    and frame). Half a pixel, half the search's resolution, separates the two. Measured: 0.03 to
    0.3 px over the whole sweep on the RubberWhale crop and on the built-in sequence (every
    setting qualifies and the fastest wins); up to 0.8 px on whole RubberWhale frames resized
    to 256x256, where the 5 px correlation windows and a few 9 px ones fall out.

The whole cycle, :func:`tune`, runs the 2^(5-1) design (:mod:`.experiment`), its analysis
and the sweep on one buffer and returns a :class:`TuneResult` whose :meth:`TuneResult.to_report`
is the ``tuner/report`` message (CONTRACT, docs/ARCHITECTURE.md).

Budget (``python -m vistrack.services.bench.tuner``): on a 30-frame 256x256 buffer, one
core, the defaults (3 timing passes, step 2), with the machine's other core busy, a cycle took
1.2 to 1.75 s with the pruned search: design 0.5 to 0.65 s (16 settings x 3 passes and 8
untimed references at (50, 30)), sweep 0.7 to 1.0 s (36 settings and the reference x 3
passes). With the exhaustive search (the paper's) it took 3.0 to 3.6 s: design 0.6 to 0.8 s
(its references stay untimed and pruned), sweep 2.4 to 2.8 s, half of which is the timed
reference (50, 30), ~15 ms a frame x 30 frames x 3 passes, measured for the speed-up. Step 1
costs the same (equal geometries are cached); 2 passes save about a quarter but leave the
times noisier; a step of 4 (a 4 x 4 grid) cuts the sweep to under half.

Pure numpy (through :mod:`.experiment`): no Zenoh, no msgpack.
"""

from __future__ import annotations

import math
import secrets
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from vistrack.common.params import FACTORS, MIN_VALID_NPI, TrackerParams
from vistrack.services.auto_tuner import anova as anova_mod
from vistrack.services.auto_tuner.design import Design, paper_design
from vistrack.services.auto_tuner.experiment import (
    METHODS,
    RESPONSES,
    Analysis,
    DesignRun,
    Experiment,
    GroundTruth,
    Progress,
    ReplicatedRun,
    Responses,
    aliases,
    analyse,
    analyse_replicated,
    levels_of,
    run_design,
    run_replicated,
)

#: The swept ranges of Section 6.1, px (inclusive).
SEARCH_RANGE = (10, 20)
CORR_RANGE = (5, 15)
DEFAULT_STEP = 2
#: Table 4: values of the factors the sweep holds fixed.
TABLE4_FIXED: Mapping[str, float] = {"max_features": 100, "thres_percent": 2.0,
                                     "ungroup_size": 5}
#: A tuning keeps the windows in force where its sweep found them within the tolerance and at
#: most this much slower than its optimum (tf, the same passes, :meth:`TuneResult.keeps`): the
#: sweep's tf spans ~10 % on a real buffer, and under load the fastest point is the noise's
#: pick (a live run published 10/5, 12/5, 18/5, 10/5, 12/5, 10/5, 20/5 on one looping scene)
KEEP_WITHIN = 0.10
#: Largest mean |ex|, |ey| against the reference windows an optimum may have, px.
DEFAULT_TOLERANCE = 0.5
#: What the command lines (``vistrack tune``, the auto-tuner service) accept: sweep steps
#: (10 already leaves only the grid's corners), tolerances (px), and frames in a tuning
#: buffer (two at least: t1 and tf).
STEP_RANGE = (1, 10)
TOLERANCE_RANGE = (0.0, 100.0)
BUFFER_RANGE = (2, 1000)
#: The buffer's work budget: the pixels of all the frames a cycle runs on, in megapixels. A
#: cycle pre-processes every frame once per distinct pre-processing (13 of them), so that part
#: of its cost grows with frames x pixels; 30 frames of 1280x720 (27.6 MP) fit, larger frames
#: keep fewer (the latest): 15 at 1920x1080, down to MIN_FRAMES. It was 20 when a cycle on
#: all 30 frames of 1280x720 took 7.0 to 7.7 s of CPU here; with the tracker's and the
#: pre-processing's speed-ups since, that cycle takes 2.6 s (``vistrack bench tuner``,
#: 2026-12-04), and the 21 frames 20 MP kept chose windows whose ex on all 30 frames was
#: 0.53 to 1.00 px, beyond the 0.5 px tolerance, in some runs: the budget is the cost, not
#: the frames that give the right answer.
DEFAULT_MEGAPIXELS = 32.0
MEGAPIXELS_RANGE = (0.1, 1000.0)
#: The fewest frames the budget leaves: t1, and three frames of tf and motion.
MIN_FRAMES = 4


def frames_within(n_frames: int, shape: tuple[int, int], megapixels: float | None) -> int:
    """How many of a buffer's ``n_frames`` frames of ``shape`` (H, W) a tuning cycle runs on:
    all of them while their pixels stay within ``megapixels`` (None: no budget), else as many
    as fit, but at least :data:`MIN_FRAMES` (or all, when fewer)."""
    if megapixels is None:
        return n_frames
    if not (math.isfinite(megapixels) and megapixels > 0):
        raise ValueError(f"max_megapixels={megapixels!r} must be a number > 0 (MP)")
    fit = int(megapixels * 1e6 // (shape[0] * shape[1]))
    return min(n_frames, max(fit, MIN_FRAMES))


@dataclass(frozen=True, eq=False)
class Sweep:
    """Responses over the SEARCH_SIZE x CORR_SIZE grid.

    Attributes
    ----------
    search_sizes : (S,) the swept SEARCH_SIZE values, px.
    corr_sizes : (C,) the swept CORR_SIZE values, px.
    fixed : the values of the three factors held fixed (Table 4 by default).
    t1, tf : (S, C) float64 ms; ex, ey : (S, C) float64 px; npi : (S, C) mean NPI.
        Indexed ``[i, j]`` for ``search_sizes[i]``, ``corr_sizes[j]``.
    reference : the reference windows (50, 30) with the fixed values and the base's search,
        timed in the same passes as the grid, so ``reference.tf / tf`` is a fair speed-up.
    base : the TrackerParams every point was built from (its ``search`` timed them all).
    """

    search_sizes: tuple[int, ...]
    corr_sizes: tuple[int, ...]
    fixed: dict[str, float]
    t1: np.ndarray
    tf: np.ndarray
    ex: np.ndarray
    ey: np.ndarray
    npi: np.ndarray
    reference: Responses
    reference_windows: tuple[int, int]
    base: TrackerParams

    def params(self, i: int, j: int) -> TrackerParams:
        """The TrackerParams of grid point ``[i, j]``."""
        return self.base.replace(search_size=self.search_sizes[i], corr_size=self.corr_sizes[j])

    def as_dict(self) -> dict[str, Any]:
        """Plain lists and floats: the ``sweep`` field of ``tuner/report``."""
        return {
            "search_size": list(self.search_sizes),
            "corr_size": list(self.corr_sizes),
            "fixed": dict(self.fixed),
            **{name: _grid(getattr(self, name)) for name in (*RESPONSES, "npi")},
            "reference": {"search_size": self.reference_windows[0],
                          "corr_size": self.reference_windows[1],
                          **self.reference.as_dict()},
        }


def _grid(a: np.ndarray) -> list[list[float]]:
    return [[float(v) for v in row] for row in a]


def grid_values(lo: int, hi: int, step: int) -> tuple[int, ...]:
    """lo, lo + step, ... up to hi inclusive (hi itself always included)."""
    if isinstance(step, bool) or not isinstance(step, int) or step < 1:
        raise ValueError(f"step={step!r} must be an int >= 1")
    if lo > hi:
        raise ValueError(f"range {lo}..{hi} is empty")
    values = list(range(lo, hi + 1, step))
    if values[-1] != hi:
        values.append(hi)
    return tuple(values)


def sweep(frames: Sequence[np.ndarray] | Experiment, *, step: int = DEFAULT_STEP,
          search_sizes: Sequence[int] | None = None, corr_sizes: Sequence[int] | None = None,
          fixed: Mapping[str, float] | None = None, base: TrackerParams | None = None,
          repeats: int | None = None, seed: int | None = 0,
          progress: Progress | None = None) -> Sweep:
    """Measure t1, tf, ex, ey over the SEARCH_SIZE x CORR_SIZE grid (Figures 5 to 7).

    Parameters
    ----------
    frames : (H, W) uint8 grey frames, or an :class:`Experiment` to share its runs.
    step : grid step in px over :data:`SEARCH_RANGE` x :data:`CORR_RANGE` (see the module
        notes; default 2, every distinct geometry).
    search_sizes, corr_sizes : explicit grids instead of the ranges and step.
    fixed : the values of the other factors (default Table 4: 100, 2, 5).
    base : the non-factor parameters (default TrackerParams()).
    repeats : timing passes when ``frames`` are not an Experiment.
    seed : seed of the random order of the grid points in every pass (None: grid order).
        A sweep made in grid order would meet a slow spell of the machine on a run of
        neighbouring SEARCH_SIZE rows and fake a trend; in random order it is only noise.
    progress : optional ``progress("sweep", done, total)``.
    """
    exp = frames if isinstance(frames, Experiment) else Experiment(
        frames, **({} if repeats is None else {"repeats": repeats}))
    ss = tuple(int(v) for v in (search_sizes if search_sizes is not None
                                else grid_values(*SEARCH_RANGE, step)))
    cs = tuple(int(v) for v in (corr_sizes if corr_sizes is not None
                                else grid_values(*CORR_RANGE, step)))
    if not ss or not cs:
        raise ValueError("the sweep needs at least one SEARCH_SIZE and one CORR_SIZE")
    fixed = dict(TABLE4_FIXED if fixed is None else fixed)
    allowed = [f for f in FACTORS if f not in ("search_size", "corr_size")]
    if set(fixed) - set(allowed):
        raise ValueError(f"fixed may only name {', '.join(allowed)}; got "
                         f"{', '.join(sorted(fixed))}")
    base = (base if base is not None else TrackerParams()).replace(**fixed)
    grid = [base.replace(search_size=s, corr_size=c) for s in ss for c in cs]
    ref = exp.reference_params(base)
    # the reference is timed with the grid, in the same passes, for a fair speed-up figure
    points = [*grid, ref]
    order = shuffle = None
    if seed is not None:
        rng = np.random.default_rng(seed)
        order = rng.permutation(len(points))
        shuffle = int(rng.integers(2**31))
    responses = exp.measure(points, order=order, shuffle_seed=shuffle, progress=progress,
                            phase="sweep")
    shape = (len(ss), len(cs))

    def field(name: str) -> np.ndarray:
        return np.array([getattr(r, name) for r in responses[:-1]], np.float64).reshape(shape)

    return Sweep(ss, cs, fixed, field("t1"), field("tf"), field("ex"), field("ey"),
                 field("npi_mean"), responses[-1], exp.reference, base)


@dataclass(frozen=True)
class Optimum:
    """The chosen setting and why.

    Attributes
    ----------
    params : the five factors (the fields of ``tuner/params``), TrackerParams-compatible.
    index : (i, j) of the chosen grid point.
    t1, tf : its times, ms; ex, ey : its errors, px.
    within_tolerance : False when no grid point met the tolerance (then the point with the
        smallest max(ex, ey) was chosen instead).
    speedup : reference tf / chosen tf.
    reason : one sentence for ``tuner/params.reason`` and the CLI.
    """

    params: dict[str, float]
    index: tuple[int, int]
    t1: float
    tf: float
    ex: float
    ey: float
    within_tolerance: bool
    speedup: float
    reason: str


def optimum(result: Sweep, tolerance: float = DEFAULT_TOLERANCE) -> Optimum:
    """The fastest setting (least tf) whose ex and ey are both <= ``tolerance`` px.

    When none qualifies, the setting with the smallest max(ex, ey) is returned with
    ``within_tolerance`` False: the most faithful the swept windows can be.
    """
    if not np.isfinite(tolerance) or tolerance < 0:
        raise ValueError(f"tolerance={tolerance!r} must be a number >= 0 (px)")
    err = np.maximum(result.ex, result.ey)
    # a point with a NaN response is never chosen (np.argmin would pick the first NaN)
    ok = (err <= tolerance) & np.isfinite(result.tf)
    if ok.any():
        flat = int(np.argmin(np.where(ok, result.tf, np.inf)))
    elif np.isfinite(err).any():
        flat = int(np.argmin(np.where(np.isfinite(err), err, np.inf)))
    else:
        raise ValueError("no swept window has finite errors ex and ey: nothing to choose")
    i, j = (int(v) for v in np.unravel_index(flat, result.tf.shape))
    p = result.params(i, j)
    tf = float(result.tf[i, j])
    speedup = result.reference.tf / tf if tf > 0 else float("inf")
    ref = f"({result.reference_windows[0]}, {result.reference_windows[1]})"
    if ok.any():
        reason = (f"fastest of {int(ok.sum())}/{ok.size} swept windows within {tolerance:g} px "
                  f"of the reference {ref}: tf {tf:.3f} ms ({speedup:.1f}x faster), "
                  f"ex {result.ex[i, j]:.2f} px, ey {result.ey[i, j]:.2f} px")
    else:
        reason = (f"no swept window within {tolerance:g} px of the reference {ref}; the "
                  f"closest: ex {result.ex[i, j]:.2f} px, ey {result.ey[i, j]:.2f} px, "
                  f"tf {tf:.3f} ms")
    return Optimum(params={k: getattr(p, k) for k in FACTORS}, index=(i, j),
                   t1=float(result.t1[i, j]), tf=tf, ex=float(result.ex[i, j]),
                   ey=float(result.ey[i, j]), within_tolerance=bool(ok.any()),
                   speedup=float(speedup), reason=reason)


# ------------------------------------------------------------------------------ the cycle


@dataclass(frozen=True, eq=False)
class TuneResult:
    """One tuning cycle: the design run, its analysis, the sweep and the optimum.

    ``seconds`` is the wall time of the cycle's parts: ``design`` (with its reference runs and
    the analysis), ``sweep`` and ``total``. ``frames`` is the number of frames the cycle ran
    on: the latest of the ``offered`` ones that fit the work budget ``max_megapixels``.
    ``replicated`` is the replicated design run when the design was replicated (``run`` then
    holds its per-run means), else None.
    """

    run: DesignRun
    analysis: Analysis
    sweep: Sweep
    optimum: Optimum
    tolerance: float
    frames: int
    size: tuple[int, int]
    repeats: int
    seconds: dict[str, float]
    replicated: ReplicatedRun | None = None
    offered: int = 0
    max_megapixels: float | None = None

    def keeps(self, search_size: int, corr_size: int) -> bool:
        """Whether the windows (``search_size``, ``corr_size``) are as good as the optimum to
        within the timing's noise: on the sweep's grid (an even width reads as the next odd
        one, the same half-width), within the tolerance as the optimum must be, and at most
        KEEP_WITHIN slower than it in the same passes. The auto-tuner keeps such windows in
        force rather than publish the optimum.

        Where no swept window came within the tolerance, the optimum is only the closest to the
        reference, and windows on the grid whose error is within the tolerance of the
        closest's are kept: a closest choice is worth a change for the accuracy it gains, not
        for its speed. Published, such choices made the windows flip from cycle to cycle on a
        scene of walkers (0 of 36 windows within 0.5 px in two of four cycles) and put in
        force (12, 13) for (15, 9) on large motion, 4.1 px off the reference where both were
        about as far, and slower."""
        searches = [s // 2 for s in self.sweep.search_sizes]
        corrs = [c // 2 for c in self.sweep.corr_sizes]
        if search_size // 2 not in searches or corr_size // 2 not in corrs:
            return False
        i, j = searches.index(search_size // 2), corrs.index(corr_size // 2)
        sw = self.sweep
        error = max(sw.ex[i, j], sw.ey[i, j])
        if not self.optimum.within_tolerance:
            return bool(error <= max(self.optimum.ex, self.optimum.ey) + self.tolerance)
        return bool(error <= self.tolerance
                    and sw.tf[i, j] <= (1.0 + KEEP_WITHIN) * self.optimum.tf)

    @property
    def params(self) -> TrackerParams:
        """The optimum as TrackerParams (the sweep's base with the chosen windows)."""
        return self.sweep.params(*self.optimum.index)

    def to_report(self) -> dict[str, Any]:
        """The ``tuner/report`` fields (CONTRACT): plain lists, dicts, floats, ints and str.

        Contract fields: ``design`` (rows of -1/+1, standard order), ``factors`` (names),
        ``order`` (run order: standard-order indices in the order run), ``responses`` (name ->
        list, standard order), ``effects`` (response -> paper term -> effect), ``significant``
        (response -> {"99": [...], "95": [...]}), ``optimum`` (the five parameters), ``sweep``
        (grid and responses). Extra fields (readers ignore what they do not know): ``method``,
        ``levels``, ``aliases``, ``seed``, ``tolerance``, ``reason``, ``within_tolerance``
        (whether the optimum met the tolerance, else it is the closest), ``frames`` (run on),
        ``frames_offered``, ``max_megapixels`` (the work budget that chose them), ``size``,
        ``repeats``, ``seconds``, ``search`` (the SSD search the times were measured with),
        ``replicates`` (independent timings of every design run, 1: unreplicated),
        ``tracker`` (the tracker every run tracked with: ``name``, ``"default"``, ``"paper"``
        or ``"custom"`` (:attr:`.TrackerParams.tracker`), ``levels``, ``subpixel``,
        ``refine_size``).

        A replicated design (``replicates`` >= 2, ``method`` ``"pure-error"``) keeps the
        contract's shapes: ``responses`` are the per-run means and ``order`` the order in which
        the runs first ran. It adds ``replicate_responses`` (name -> runs x replicates lists,
        standard order), ``replicate_order`` (the first timing pass's ``[run, replicate]``
        units in the order they ran) and ``pure_error`` (response -> ``{"df", "ms"}``, the
        error every effect of that response was tested against; responses identical in every
        replicate, such as ex and ey, have none and were tested by Lenth's method).
        """
        run = self.run
        base = self.sweep.base
        names = run.responses[0].as_dict().keys()
        extra: dict[str, Any] = {}
        if self.replicated is not None:
            rep = self.replicated
            extra = {
                "replicate_responses": {n: rep.response(n).tolist() for n in names},
                "replicate_order": rep.order.tolist(),
                "pure_error": {n: {"df": int(t.error.df), "ms": float(t.error.ms)}
                               for n, t in self.analysis.results.items()
                               if isinstance(t, anova_mod.AnovaTable)},
            }
        return {
            "design": run.design.matrix.tolist(),
            "factors": list(run.design.names or run.design.factors),
            "order": [int(i) for i in run.order],
            "responses": {n: [float(v) for v in run.response(n)] for n in names},
            "effects": self.analysis.effects,
            "significant": self.analysis.significant,
            "optimum": dict(self.optimum.params),
            "sweep": self.sweep.as_dict(),
            "method": self.analysis.method,
            "levels": dict(levels_of(run.design)),
            "aliases": aliases(run.design),
            "seed": run.seed,
            "tolerance": float(self.tolerance),
            "reason": self.optimum.reason,
            "within_tolerance": bool(self.optimum.within_tolerance),
            "frames": self.frames,
            "frames_offered": self.offered,
            "max_megapixels": self.max_megapixels,
            "size": list(self.size),
            "repeats": self.repeats,
            "seconds": dict(self.seconds),
            "search": base.search,
            "tracker": {"name": base.tracker, "levels": base.levels,
                        "subpixel": base.subpixel, "refine_size": base.refine_size},
            "replicates": 1 if self.replicated is None else self.replicated.n_replicates,
            **extra,
        }


def new_seed() -> int:
    """A fresh 31-bit seed for the run order (reported, so the run can be repeated)."""
    return secrets.randbits(31)


#: The share of the buffer's frames on which the reference must track enough features for a
#: tuning cycle to mean anything (:func:`tune`).
MIN_TEXTURED = 0.5


class TextureError(ValueError):
    """The frames have too little texture to tune on (:func:`tune`)."""


def tune(frames: Sequence[np.ndarray], seed: int | None = None, *,
         tolerance: float = DEFAULT_TOLERANCE, step: int = DEFAULT_STEP,
         repeats: int | None = None, method: str = "lenth", design: Design | None = None,
         ground_truth: GroundTruth | None = None, base: TrackerParams | None = None,
         fixed: Mapping[str, float] | None = None,
         progress: Progress | None = None, replicates: int = 1,
         max_megapixels: float | None = DEFAULT_MEGAPIXELS) -> TuneResult:
    """The whole tuning cycle on a buffer of frames: design, analysis, sweep, optimum.

    Parameters
    ----------
    frames : (H, W) uint8 grey frames, at least 2 (the auto-tuner's buffer holds 30).
    seed : seed of the design's run order; None draws a fresh one (:func:`new_seed`), which
        the report records. A fixed default would run every cycle in the same order, and
        randomisation only protects against drifts (thermal, load) that do not line up with it.
    tolerance : px, see :func:`optimum`.
    step : sweep grid step, see :func:`sweep`.
    repeats : timing passes (default :data:`.experiment.DEFAULT_REPEATS`).
    method : ``"lenth"`` or ``"anova"``, see :func:`.experiment.analyse`: the test of the
        unreplicated design. With ``replicates`` >= 2 it must be left at its default, as the
        effects are then tested against pure error (:func:`.experiment.analyse_replicated`).
    design : default :func:`.design.paper_design` (2^(5-1), Table 2 levels).
    ground_truth : optional :class:`GroundTruth`; adds ``gt_*`` responses.
    fixed : the values at which the sweep holds the factors other than the windows
        (default Table 4's, :data:`TABLE4_FIXED`, as the paper's sweep; the auto-tuner
        service gives those in force, so that the optimum it applies keeps them).
    base : non-factor parameters (weights, subpixel, search, ...), default TrackerParams().
        Its ``search`` is the SSD search every timed run uses (``"exhaustive"``: the paper's);
        the untimed reference runs use the pruned one, which gives the same motion.
    progress : optional ``progress(phase, done, total)``, phase ``"design"`` then ``"sweep"``.
    replicates : independent timings of every design run (default 1: the paper's unreplicated
        design, what the auto-tuner service runs). With N >= 2 the design is run N times in a
        completely randomised order (:func:`.experiment.run_replicated`), costing N times the
        design's time, and analysed against pure error; the sweep is not replicated.
    max_megapixels : the work budget (:func:`frames_within`): the cycle runs on the latest
        frames whose pixels fit it, at least :data:`MIN_FRAMES`; None runs on all. Default
        :data:`DEFAULT_MEGAPIXELS` (30 frames of 1280x720, 15 of 1920x1080).

    Raises
    ------
    TextureError
        If the reference windows track fewer than MIN_VALID_NPI features on more than half
        the frames (:data:`MIN_TEXTURED`): with no motion measured, every window size scores
        zero error, and the "optimum" would be the fastest window for nothing.
    """
    if not np.isfinite(tolerance) or tolerance < 0:
        raise ValueError(f"tolerance={tolerance!r} must be a number >= 0 (px)")
    if method not in METHODS:
        raise ValueError(f"method={method!r} is not allowed: use one of {', '.join(METHODS)}")
    if isinstance(replicates, bool) or not isinstance(replicates, int) or replicates < 1:
        raise ValueError(f"replicates={replicates!r} must be an int >= 1")
    if replicates > 1 and method != "lenth":
        raise ValueError(f"method={method!r} tests the unreplicated design; with "
                         f"replicates={replicates} the effects are tested against pure error")
    offered = len(frames)
    if offered:
        keep = frames_within(offered, np.shape(frames[0])[:2], max_megapixels)
        if keep < offered and ground_truth is not None:
            raise ValueError(f"{offered} frames exceed max_megapixels={max_megapixels:g}; "
                             "ground truth is given for all of them: pass "
                             "max_megapixels=None")
        frames = list(frames)[offered - keep:]
    exp = Experiment(frames, ground_truth=ground_truth,
                     **({} if repeats is None else {"repeats": repeats}))
    textured = exp.textured(base if base is not None else TrackerParams())
    if textured < MIN_TEXTURED:
        h, w = np.shape(exp.frames[0])[:2]
        most = (base if base is not None else TrackerParams()).max_features
        # a frame no wider than the reference's correlation window holds none of its
        # templates; one not much wider, few (a feature keeps half a window from the
        # border: 40 x 40 px frames of real texture were said to be a covered lens)
        search, corr = exp.reference
        cause = (f"frames of {w}x{h} px hold no {corr} px correlation window: "
                 "give larger frames" if min(h, w) <= corr
                 else f"frames of {w}x{h} px are small for the reference windows "
                 f"({search}, {corr}): a feature keeps {corr // 2 + 1} px from each border; "
                 "give larger frames" if min(h, w) <= search + corr
                 # max_features 1 or 2 (allowed) was said to be a covered lens
                 else f"max_features is {most}: fewer features than that can be tracked"
                 if most < MIN_VALID_NPI
                 else "a covered lens, a dark or uniform scene?")
        raise TextureError(
            f"the frames have too little texture to tune on: the reference windows "
            f"{exp.reference} track {MIN_VALID_NPI} features or more on "
            f"{100 * textured:.0f} % of the {len(exp.frames)} frames, at least "
            f"{100 * MIN_TEXTURED:.0f} % needed ({cause}); "
            "every window size would score the same zero error")
    start = time.perf_counter()  # after warm_up: a service compiles once, not every cycle
    seed = new_seed() if seed is None else int(seed)
    design = design if design is not None else paper_design()
    replicated = None
    if replicates == 1:
        run = run_design(exp, design, seed, progress=progress, base=base)
        analysis = analyse(run, method=method)
    else:
        replicated = run_replicated(exp, design, seed, replicates, progress=progress, base=base)
        run = replicated.means()
        analysis = analyse_replicated(replicated)
    mid = time.perf_counter()
    result = sweep(exp, step=step, fixed=fixed, base=base, seed=seed, progress=progress)
    best = optimum(result, tolerance)
    end = time.perf_counter()
    seconds = {"design": mid - start, "sweep": end - mid, "total": end - start}
    return TuneResult(run, analysis, result, best, float(tolerance), len(exp.frames), exp.size,
                      exp.repeats, seconds, replicated, offered, max_megapixels)
