"""The auto-tuner's experiment, analysis, sweep and optimum (paper Section 6.1, Table 3).

Expected values come from the setting itself (a run equals its own reference; a generated
sequence moves by a known amount; planted effects), from an independent computation (least
squares on the sweep, the design's own projections), or from physics (more features or larger
windows cost more time) -- never from an earlier output of this code.
"""

from __future__ import annotations

import ast
import dataclasses
import json
import math
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from vistrack.common import groundtruth, synthetic
from vistrack.common.params import FACTORS, TrackerParams
from vistrack.common.vision import to_gray, track_frames
from vistrack.services.auto_tuner import anova as anova_mod
from vistrack.services.auto_tuner import experiment as ex_mod
from vistrack.services.auto_tuner.design import number_label, paper_design
from vistrack.services.auto_tuner.experiment import (
    DesignRun,
    Experiment,
    GroundTruth,
    ReplicatedRun,
    Responses,
    analyse,
    analyse_replicated,
    bounce,
    design_params,
    run_design,
    run_point,
    run_replicated,
)
from vistrack.services.auto_tuner.sensitivity import (
    CORR_RANGE,
    MIN_FRAMES,
    SEARCH_RANGE,
    Sweep,
    frames_within,
    grid_values,
    optimum,
    sweep,
    tune,
)

ROOT = Path(__file__).resolve().parents[2]
STEP = synthetic.Motion(dx=2.0, dy=-1.0)


@pytest.fixture(scope="module")
def small_frames() -> list[np.ndarray]:
    """6 generated 96x96 frames moving by (2, -1) px per frame: fast runs."""
    return synthetic.sequence(6, size=(96, 96), motion=STEP, seed=3)


@pytest.fixture
def count_trackers(monkeypatch):
    """Record the parameters of every Tracker the experiment builds, in order."""
    made: list[TrackerParams] = []
    real = ex_mod.Tracker

    def spy(params):
        made.append(params)
        return real(params)

    monkeypatch.setattr(ex_mod, "Tracker", spy)
    return made


# ------------------------------------------------------------------------------ run_point


def test_reference_settings_score_zero(small_frames):
    exp = Experiment(small_frames, repeats=1)
    ref = run_point(exp, TrackerParams(search_size=50, corr_size=30))
    assert ref.ex == 0.0 and ref.ey == 0.0
    # 51 x 31 is the same window geometry (widths // 2), so it is the reference too
    same = run_point(exp, TrackerParams(search_size=51, corr_size=31))
    assert same.ex == 0.0 and same.ey == 0.0
    assert ref.t1 > 0 and ref.tf > 0 and ref.npi_mean > 0


def test_a_search_too_small_for_the_motion_scores_an_error():
    """3 px per frame with a search half-width of 1 px: the first step cannot be found. (With
    the guided retry, the frame-wide shift finds it, at the cost of a second run: the retry
    is off here, for the error the experiment must score.)"""
    frames = synthetic.sequence(5, size=(96, 96), motion=synthetic.Motion(dx=3.0), seed=4)
    r = run_point(frames, TrackerParams(search_size=2, corr_size=9, guided_retry=False),
                  repeats=1)
    assert r.ex > 0.5


def test_ground_truth_motion_of_a_generated_sequence(small_frames):
    truth = GroundTruth.from_steps([STEP] * (len(small_frames) - 1))
    assert np.allclose(truth.motion[-1], [2.0 * 5, -1.0 * 5])
    r = run_point(small_frames, TrackerParams(), repeats=1, ground_truth=truth)
    assert r.gt_ex is not None and r.gt_ex <= 0.05 and r.gt_ey <= 0.05
    wrong = GroundTruth(motion=truth.motion * 2)
    r2 = run_point(small_frames, TrackerParams(), repeats=1, ground_truth=wrong)
    assert r2.gt_ex >= 1.0  # the scoring can tell a wrong motion apart
    assert r.gt_epe is None and "gt_epe" not in r.as_dict()
    with pytest.raises(ValueError, match="scale"):
        GroundTruth.from_steps([synthetic.Motion(scale=1.01)])


@pytest.mark.data
def test_middlebury_flow_scores_the_median_endpoint_error():
    folder = groundtruth.middlebury("RubberWhale")
    if folder is None:
        pytest.skip("Middlebury RubberWhale not found: set VISTRACK_DATA or put the shared "
                    "data at ../shared/data")
    crop = (slice(60, 316), slice(160, 416))
    a, b = (np.ascontiguousarray(to_gray(cv2.imread(str(folder / f"frame{i}.png")))[crop])
            for i in (10, 11))
    flow = groundtruth.read_flo(folder / "flow10.flo")[crop]
    params = TrackerParams(subpixel=True)
    good = run_point([a, b], params, repeats=1, ground_truth=GroundTruth(flow=flow))
    # the tracker's own accuracy on this pair (tests/unit/test_tracker.py) is <= 0.5 px
    assert good.gt_epe is not None and good.gt_epe <= 0.5
    off = flow.copy()
    off[..., 0] += 1.0
    bad = run_point([a, b], params, repeats=1, ground_truth=GroundTruth(flow=off))
    assert bad.gt_epe > 0.5


def test_equal_window_geometries_share_one_run(small_frames, count_trackers):
    # the premise: widths w and w + 1 with one w // 2 track identically
    a = track_frames(small_frames, TrackerParams(search_size=14, corr_size=9))
    b = track_frames(small_frames, TrackerParams(search_size=15, corr_size=8))
    assert [(e.dx, e.dy, e.npi) for e in a] == [(e.dx, e.dy, e.npi) for e in b]
    count_trackers.clear()
    exp = Experiment(small_frames, repeats=2)
    r14 = run_point(exp, TrackerParams(search_size=14, corr_size=9))
    r15 = run_point(exp, TrackerParams(search_size=15, corr_size=8))
    assert r14 == r15
    points = [p for p in count_trackers if p.search_size != 50]
    assert len(points) == 2  # two timing passes of the first; none of the second
    assert len(count_trackers) - len(points) == 1  # one shared reference, untimed


@pytest.fixture
def count_preprocessing(monkeypatch):
    """Record what the experiment computes of each frame: ``filter`` the blur_sigma of each
    filtering (:func:`preprocess`), ``strength`` that of each gradient strength,
    ``candidates`` the (THRES_PERCENT, corr_half) of each threshold."""
    made: dict[str, list] = {"filter": [], "strength": [], "candidates": []}
    real_pre, real_strength = ex_mod.preprocess, ex_mod.strength_of
    real_cand = ex_mod.candidates_above

    def filtering(frame, params):
        made["filter"].append(params.blur_sigma)
        return real_pre(frame, params)

    def strength(filtered, params):
        made["strength"].append(params.blur_sigma)
        return real_strength(filtered, params)

    def candidates(grad, floor, params):
        made["candidates"].append((params.thres_percent, params.corr_half))
        return real_cand(grad, floor, params)

    monkeypatch.setattr(ex_mod, "preprocess", filtering)
    monkeypatch.setattr(ex_mod, "strength_of", strength)
    monkeypatch.setattr(ex_mod, "candidates_above", candidates)
    return made


def test_each_preprocessing_runs_once_whatever_the_timing_passes(small_frames,
                                                                 count_preprocessing):
    """Pre-processing is deterministic and its cost the same for every margin (see the module
    notes): the filter and the gradient strength, which depend on the filter alone, are made
    once a frame for every run; the candidates' threshold once per distinct pre-processing;
    none once per timing pass."""
    run_design(small_frames, paper_design(), seed=4, repeats=3)
    n = len(small_frames)
    # each timed a few times, the first kept (see FILTER_TIMINGS)
    assert count_preprocessing["filter"] == [TrackerParams().blur_sigma] * (
        ex_mod.FILTER_TIMINGS * n)
    assert count_preprocessing["strength"] == [TrackerParams().blur_sigma] * (
        ex_mod.STRENGTH_TIMINGS * n)
    # THRES_PERCENT 0.1 and 5 x the margins of CORR_SIZE 5, 15 and of the references' 30
    keys = {(t, h) for t in (0.1, 5.0) for h in (2, 7, 15)}
    assert set(count_preprocessing["candidates"]) == keys
    assert len(count_preprocessing["candidates"]) == len(keys) * n


def test_a_slow_spell_on_one_preprocessing_does_not_reach_its_points(small_frames,
                                                                      monkeypatch):
    """A point's candidates' time is, frame by frame, the least that any pre-processing
    doing the same work took (they differ only by the border margin): a spell that slows one
    of them (here by 30 ms a frame, on CORR_SIZE 9's) does not make its windows look slower,
    where timing each one alone would have added the 30 ms to its points' t1 (and to tf,
    with every frame's candidates read)."""
    real = ex_mod.candidates_above
    slow = {"calls": 0}

    def spell(grad, floor, params):
        if params.corr_half == 4:
            slow["calls"] += 1
            time.sleep(0.03)
        return real(grad, floor, params)

    monkeypatch.setattr(ex_mod, "candidates_above", spell)
    base = TrackerParams(max_features=2000, redetect_fraction=1.0)  # reads them every frame
    sw = sweep(Experiment(small_frames, repeats=2), search_sizes=[10], corr_sizes=[5, 9],
               base=base)
    assert slow["calls"] == len(small_frames)  # the spell did happen, on every frame
    (t1_5, t1_9), (tf_5, tf_9) = sw.t1[0], sw.tf[0]
    assert abs(tf_9 - tf_5) < 10.0 and abs(t1_9 - t1_5) < 10.0, (sw.t1, sw.tf)


def test_a_frame_whose_features_are_selected_pays_for_its_candidates(small_frames,
                                                                      monkeypatch):
    """t1 holds the first frame's candidates (gradient strength, THRES_PERCENT, floors), as
    the pipeline pays for them when it selects the first features: on a clock that moves only
    while they are computed (10 ms a frame), t1 is 10 ms and tf, with no re-detection, 0. The
    buffer's frames, shared by every run and pass, computed them in the first run's first
    frame alone, and the least of the passes (0) was t1."""
    clock = {"now": 0.0}
    monkeypatch.setattr(time, "perf_counter", lambda: clock["now"])
    real = ex_mod.strength_of

    def costly(filtered, params):
        clock["now"] += 0.010
        return real(filtered, params)

    monkeypatch.setattr(ex_mod, "strength_of", costly)
    exp = Experiment(small_frames, repeats=3)
    r = run_point(exp, TrackerParams(search_size=10, corr_size=9, max_features=10))
    assert r.t1 == pytest.approx(10.0) and r.tf == 0.0
    # a run whose tracker selects on every frame (it never holds max_features) pays on every
    # frame
    every = run_point(exp, TrackerParams(search_size=10, corr_size=9, max_features=2000,
                                         redetect_fraction=1.0))
    assert every.t1 == pytest.approx(10.0) and every.tf == pytest.approx(10.0)


def test_a_run_on_the_shared_filter_tracks_as_the_tracker_alone(small_frames):
    """The shared filter and strength change nothing tracked: a point's motion and features
    are those of ``track_frames`` on the same frames, on a buffer whose runs shared them."""
    params = TrackerParams(search_size=12, corr_size=7)
    exp = Experiment(small_frames, repeats=1)
    run_point(exp, TrackerParams(search_size=16, corr_size=5, thres_percent=1.0))  # shares them
    r = run_point(exp, params)
    alone = track_frames(small_frames, params)
    assert r.npi_mean == pytest.approx(np.mean([e.npi for e in alone]))
    run = exp._runs[ex_mod._key(params)]
    np.testing.assert_array_equal(run.dx, [e.dx for e in alone])
    np.testing.assert_array_equal(run.dy, [e.dy for e in alone])


def test_experiment_rejects_bad_buffers(small_frames):
    with pytest.raises(ValueError, match="at least 2 frames"):
        Experiment(small_frames[:1])
    with pytest.raises(ValueError, match="frame 1 is"):
        Experiment([small_frames[0], small_frames[1][:50]])
    with pytest.raises(ValueError, match="uint8"):
        Experiment([f.astype(np.float32) for f in small_frames])
    with pytest.raises(ValueError, match="repeats"):
        Experiment(small_frames, repeats=0)
    with pytest.raises(ValueError, match="rows"):
        Experiment(small_frames, ground_truth=GroundTruth(motion=np.zeros((2, 2))))


def test_bounce_plays_back_and_forth():
    frames = [np.full((4, 4), i, np.uint8) for i in range(4)]
    out = bounce(frames, 11)
    assert [int(f[0, 0]) for f in out] == [0, 1, 2, 3, 2, 1, 0, 1, 2, 3, 2]
    with pytest.raises(ValueError):
        bounce(frames[:1], 5)


# ------------------------------------------------------------------------------ the design


def test_design_runs_each_point_per_pass_and_each_reference_once(small_frames,
                                                                count_trackers):
    design = paper_design()
    run = run_design(small_frames, design, seed=11, repeats=2)
    refs = [p for p in count_trackers if (p.search_size, p.corr_size) == (50, 30)]
    points = [p for p in count_trackers if (p.search_size, p.corr_size) != (50, 30)]
    # one reference per distinct setting of the factors it keeps: MAX_FEAT_NUM, THRES_PERCENT,
    # UNGROUP_SIZE (columns A, B, E), counted from the design itself
    distinct = {tuple(row) for row in design.matrix[:, [0, 1, 4]].tolist()}
    assert len(refs) == len(distinct) == 8
    assert len(points) == 2 * design.n_runs
    # the first pass ran the points in the run order; the second all of them again, reshuffled
    expect = design_params(design)
    assert points[:16] == [expect[i] for i in run.order]
    assert sorted(map(repr, points[16:])) == sorted(map(repr, points[:16]))
    assert len(run.responses) == 16 and all(r.tf > 0 for r in run.responses)


def test_timed_runs_use_the_base_search_and_references_the_pruned_one(small_frames,
                                                                      count_trackers):
    """With search="exhaustive" every timed run (design points, and the sweep's timed reference
    (50, 30)) uses it; the untimed references whose motion ex, ey are scored against use the
    pruned search, which gives the same motion: the exhaustive (50, 30) scores 0 against it."""
    exp = Experiment(small_frames, repeats=2)
    base = TrackerParams(search="exhaustive")
    run = run_design(exp, paper_design(), seed=1, base=base)
    timed = [p for p in count_trackers if (p.search_size, p.corr_size) != (50, 30)]
    refs = [p for p in count_trackers if (p.search_size, p.corr_size) == (50, 30)]
    assert len(timed) == 2 * 16 and {p.search for p in timed} == {"exhaustive"}
    assert len(refs) == 8 and {p.search for p in refs} == {"pruned"}
    # the same design with the pruned search: the same motion, so the same errors and NPI
    pruned = run_design(exp, paper_design(), seed=1)
    for name in ("ex", "ey", "npi_mean"):
        assert run.response(name).tolist() == pruned.response(name).tolist(), name
    assert len([p for p in count_trackers if p.search_size == 50]) == 8  # no new reference
    count_trackers.clear()
    sw = sweep(exp, search_sizes=[10], corr_sizes=[5], base=base)
    # two timing passes over the grid point and the timed reference, one untimed reference
    # (the design's references had max_features 50 or 200, the sweep's 100: a new one)
    assert sorted((p.search_size, p.search) for p in count_trackers) == sorted(
        [(10, "exhaustive"), (50, "exhaustive")] * 2 + [(50, "pruned")])
    assert sw.reference.ex == 0.0 and sw.reference.ey == 0.0
    assert sw.base.search == "exhaustive"


def test_run_order_is_a_reproducible_permutation(small_frames):
    exp = Experiment(small_frames, repeats=1)
    design = paper_design()
    a = run_design(exp, design, seed=5)
    b = run_design(exp, design, seed=5)
    c = run_design(exp, design, seed=6)
    assert sorted(a.order.tolist()) == list(range(16))
    assert a.order.tolist() == b.order.tolist()
    assert a.order.tolist() != c.order.tolist()
    # responses stay in standard order whatever the run order
    assert [r.npi_mean for r in a.responses] == [r.npi_mean for r in c.responses]


def test_every_timing_pass_is_reproducible_from_the_seed(small_frames, count_trackers):
    run_design(small_frames, paper_design(), seed=9, repeats=3)
    first = list(count_trackers)
    count_trackers.clear()
    run_design(small_frames, paper_design(), seed=9, repeats=3)
    assert count_trackers == first and len(first) == 3 * 16 + 8


def _planted_run(noise: float = 0.005, seed: int = 0) -> tuple[DesignRun, dict[str, dict]]:
    """A DesignRun whose responses are known functions of the coded factors plus noise."""
    design = paper_design()
    rng = np.random.default_rng(seed)
    cols = {t: design.columns(t)[:, 0] for t in ("A", "B", "C", "D", "E", "AB", "CD", "DE")}
    # coefficients: an effect is twice its coefficient (mean at +1 minus mean at -1)
    planted = {"t1": {"A": 0.5, "B": 0.3, "AB": 0.2},
               "tf": {"C": 0.5, "D": 0.4, "CD": 0.3},
               "ex": {"D": -0.4, "E": 0.3, "DE": 0.25}}
    y = {name: 2.0 + sum(c * cols[t] for t, c in terms.items()) + rng.normal(0, noise, 16)
         for name, terms in planted.items()}
    y["ey"] = np.zeros(16)  # e.g. every run equal to its reference: nothing to test
    responses = tuple(Responses(t1=y["t1"][i], tf=y["tf"][i], ex=y["ex"][i], ey=y["ey"][i],
                                npi_mean=10.0) for i in range(16))
    run = DesignRun(design, tuple(design_params(design)), design.randomized_order(0),
                    responses, 0)
    return run, planted


@pytest.mark.parametrize("method", ["lenth", "anova"])
def test_analysis_finds_planted_effects_in_paper_numbers(method):
    run, planted = _planted_run()
    result = analyse(run, method=method)
    for name, terms in planted.items():
        expect = sorted((number_label(t) for t in terms), key=lambda s: (len(s), s))
        assert result.significant[name]["99"] == expect, name
        for t, coef in terms.items():
            assert result.effects[name][number_label(t)] == pytest.approx(2 * coef, abs=0.02)
    assert result.significant["ey"] == {"99": [], "95": []}
    assert result.results["ey"] is None
    assert set(result.effects["tf"]) == {number_label(t) for t in run.design.terms(2)}
    with pytest.raises(ValueError, match="method"):
        analyse(run, method="bonferroni")


# ------------------------------------------------------------------------------ replicates


def test_replicated_run_shapes_and_run_means(small_frames):
    design = paper_design()
    run = run_replicated(small_frames, design, seed=3, replicates=3, repeats=1)
    assert isinstance(run, ReplicatedRun) and run.n_replicates == 3
    tf = run.response("tf")
    assert tf.shape == (16, 3) and np.all(tf > 0)
    assert run.order.shape == (48, 2)
    # the tracker is deterministic: what does not come from a timer is equal in every replicate
    for name in ("ex", "ey", "npi_mean"):
        y = run.response(name)
        assert np.all(y == y[:, :1]), name
    means = run.means()
    assert isinstance(means, DesignRun) and means.params == run.params
    for name in ("t1", "tf", "ex", "npi_mean"):
        assert np.allclose(means.response(name), run.response(name).mean(axis=1)), name
    # the means' run order: each run where its first replicate ran
    first = []
    for i, _ in run.order.tolist():
        if i not in first:
            first.append(i)
    assert means.order.tolist() == first and sorted(first) == list(range(16))
    with pytest.raises(KeyError, match="gt_ex"):
        run.response("gt_ex")


def test_replicates_are_independent_timings_with_the_real_clock(small_frames):
    """Not cached copies: the same run timed twice differs unless the timer is perfect (here
    about 0.06 ms a frame read to perf_counter's ~100 ns)."""
    tf = run_replicated(small_frames, paper_design(), seed=5, replicates=2,
                        repeats=1).response("tf")
    assert np.any(tf[:, 0] != tf[:, 1])


def test_every_unit_is_timed_alone_in_a_completely_randomised_order(small_frames,
                                                                    monkeypatch):
    """A fake clock: pre-processing takes no time and the k-th tracker built (k = 0, 1, ...)
    takes 1000 - k ms a frame, so a unit's tf (its minimum over 2 passes: the later one)
    names the one tracker run that timed it."""

    class FrozenClock:
        @staticmethod
        def perf_counter() -> float:
            return 0.0

    made: list[TrackerParams] = []
    real = ex_mod.Tracker

    class Numbered:
        def __init__(self, params):
            self.k = len(made)
            made.append(params)
            self.tracker = real(params)

        def update(self, pre):
            return dataclasses.replace(self.tracker.update(pre), t_ms=1000.0 - self.k)

    monkeypatch.setattr(ex_mod, "time", FrozenClock)
    monkeypatch.setattr(ex_mod, "Tracker", Numbered)
    design = paper_design()
    points = design_params(design)
    run = run_replicated(small_frames, design, seed=8, replicates=3, repeats=2)
    first = [tuple(u) for u in run.order.tolist()]
    units = [(i, r) for i in range(16) for r in range(3)]
    assert sorted(first) == units
    # pass 1 built the trackers in the order reported, then pass 2, then 8 untimed references
    assert len(made) == 2 * 48 + 8
    assert made[:48] == [points[i] for i, _ in first]
    k2 = 1000.0 - run.response("tf")
    assert sorted(k2.ravel().tolist()) == list(range(48, 96))  # one tracker run per unit
    second = sorted(units, key=lambda u: k2[u])
    assert all(made[int(k2[i, r])] == points[i] for i, r in units)
    assert second != first  # every pass reshuffles
    # complete randomisation: the replicates are interleaved, not run one after the other
    assert {r for _, r in first[:16]} == {0, 1, 2}
    assert {r for _, r in second[:16]} == {0, 1, 2}
    # and the same seed gives the same orders
    again = run_replicated(small_frames, design, seed=8, replicates=3, repeats=2)
    assert again.order.tolist() == run.order.tolist()


def test_every_unit_preprocesses_the_buffer_itself(small_frames, monkeypatch):
    """Runs that share a pre-processing (THRES_PERCENT and CORR_SIZE's margin) would share
    its timing noise if they shared its timing, as the unreplicated design does: every unit
    pre-processes afresh in every pass; the untimed references reuse the outputs where
    they can, and filter the buffer once for both THRES_PERCENT otherwise (the filter depends
    on neither; their margin is CORR_SIZE 30's), each frame's filter timed FILTER_TIMINGS
    times."""
    calls = []
    real = ex_mod.preprocess

    def spy(frame, params):
        calls.append(params)
        return real(frame, params)

    monkeypatch.setattr(ex_mod, "preprocess", spy)
    run_replicated(small_frames, paper_design(), seed=1, replicates=2, repeats=2)
    n = len(small_frames)
    design_calls = [p for p in calls if p.corr_size != 30]
    assert len(design_calls) == 16 * 2 * 2 * n
    assert len(calls) - len(design_calls) == ex_mod.FILTER_TIMINGS * n


def _planted_replicated(reps: int = 3, noise: float = 0.01,
                        seed: int = 1) -> tuple[ReplicatedRun, set[str]]:
    """tf with 10 of its 15 effects active (as on real frames) plus independent noise in every
    replicate; ex with one active effect and no replicate-to-replicate variation."""
    design = paper_design()
    rng = np.random.default_rng(seed)
    coef = {"A": 0.5, "B": 1.0, "C": 0.4, "D": 0.5, "E": -0.1, "AB": 0.4, "AD": 0.2,
            "BC": 0.2, "BD": 0.3, "CD": 0.15}
    tf = 2.0 + sum(c * design.columns(t)[:, 0] for t, c in coef.items())
    tf = tf[:, None] + rng.normal(0, noise, (16, reps))
    ex = 1.0 + 0.4 * design.columns("D")[:, 0] + rng.normal(0, 0.005, 16)
    replicates = tuple(tuple(Responses(t1=1.0 + 0.01 * r, tf=tf[i, r], ex=ex[i], ey=0.0,
                                       npi_mean=10.0) for r in range(reps))
                       for i in range(16))
    order = np.array([(i, r) for i in range(16) for r in range(reps)], np.int64)
    run = ReplicatedRun(design, tuple(design_params(design)), order, replicates, seed)
    return run, {number_label(t) for t in coef}


def test_replicated_analysis_tests_effects_against_pure_error():
    run, active = _planted_replicated()
    y = run.response("tf")
    a = analyse_replicated(run)
    assert a.method == "pure-error"
    tab = a.results["tf"]
    assert isinstance(tab, anova_mod.AnovaTable)
    assert tab.error.df == 16 * (3 - 1)
    assert tab.error.ss == pytest.approx(float(((y - y.mean(axis=1, keepdims=True)) ** 2).sum()))
    assert set(a.significant["tf"]["99"]) == active
    assert a.effects["tf"]["34"] == pytest.approx(0.3, abs=0.02)
    # with 10 of 15 effects active, Lenth's method on one replicate takes real effects for noise
    lenth = anova_mod.lenth(anova_mod.effects(run.design, y[:, 0]))
    assert not active <= {number_label(t) for t in lenth.significant(0.99)}
    # ex does not vary between replicates: no pure error, tested as unreplicated (Lenth)
    assert isinstance(a.results["ex"], anova_mod.LenthResult)
    assert a.significant["ex"]["99"] == ["4"]
    assert a.results["ey"] is None and a.significant["ey"] == {"99": [], "95": []}
    # t1 varies between replicates by the same amount in every run: no effect at all
    assert a.significant["t1"] == {"99": [], "95": []}


def test_bad_replicates_are_refused(small_frames):
    with pytest.raises(ValueError, match="replicates=1 must be an int >= 2"):
        run_replicated(small_frames, paper_design(), seed=1, replicates=1)
    with pytest.raises(ValueError, match="replicates=0 must be an int >= 1"):
        tune(small_frames, seed=1, replicates=0)
    with pytest.raises(ValueError, match="pure error"):
        tune(small_frames, seed=1, replicates=2, method="anova")


def test_replicated_report_keeps_the_contract_shapes(small_frames):
    result = tune(small_frames, seed=3, step=5, repeats=1, replicates=2)
    rep = result.to_report()
    check_report(rep)
    assert rep["replicates"] == 2 and rep["method"] == "pure-error"
    reps = np.array(rep["replicate_responses"]["tf"])
    assert reps.shape == (16, 2)
    assert np.allclose(rep["responses"]["tf"], reps.mean(axis=1))
    assert sorted(map(tuple, rep["replicate_order"])) == [(i, r) for i in range(16)
                                                         for r in range(2)]
    assert rep["pure_error"]["tf"]["df"] == 16 and rep["pure_error"]["tf"]["ms"] > 0
    assert "ex" not in rep["pure_error"]  # deterministic: no pure error
    unreplicated = tune(small_frames, seed=3, step=5, repeats=1).to_report()
    assert unreplicated["replicates"] == 1 and "replicate_responses" not in unreplicated


# ------------------------------------------------------------------------------ optimum


def _sweep(tf, ex, ey, ref_tf=10.0) -> Sweep:
    tf, ex, ey = (np.asarray(a, float) for a in (tf, ex, ey))
    ss, cs = (10, 12, 14)[:tf.shape[0]], (5, 7, 9)[:tf.shape[1]]
    ref = Responses(t1=1.0, tf=ref_tf, ex=0.0, ey=0.0, npi_mean=100.0)
    return Sweep(ss, cs, {"max_features": 100, "thres_percent": 2.0, "ungroup_size": 5},
                 np.ones_like(tf), tf, ex, ey, np.full_like(tf, 100.0), ref, (50, 30),
                 TrackerParams())


def test_optimum_is_the_fastest_setting_within_tolerance():
    tf = [[1.0, 2.0, 3.0], [1.5, 2.5, 3.5]]
    ex = [[0.9, 0.2, 0.1], [0.4, 0.1, 0.0]]
    ey = [[0.1, 0.6, 0.1], [0.3, 0.1, 0.0]]
    best = optimum(_sweep(tf, ex, ey), tolerance=0.5)
    # (10, 5) is fastest but ex 0.9; (10, 7) has ey 0.6; (12, 5) is the fastest that fits
    assert best.params == {"max_features": 100, "thres_percent": 2.0, "search_size": 12,
                           "corr_size": 5, "ungroup_size": 5}
    assert best.within_tolerance and best.tf == 1.5 and best.speedup == pytest.approx(10 / 1.5)
    assert set(best.params) == set(FACTORS)
    TrackerParams(**best.params)  # TrackerParams-compatible
    # a looser tolerance admits the fastest; a tighter one only the exact match
    assert optimum(_sweep(tf, ex, ey), tolerance=1.0).index == (0, 0)
    assert optimum(_sweep(tf, ex, ey), tolerance=0.0).index == (1, 2)


def test_optimum_falls_back_to_the_most_faithful_setting():
    best = optimum(_sweep([[1.0, 2.0]], [[2.0, 0.8]], [[0.1, 0.9]]), tolerance=0.5)
    assert not best.within_tolerance and best.index == (0, 1)
    assert "no swept window" in best.reason
    with pytest.raises(ValueError, match="tolerance"):
        optimum(_sweep([[1.0]], [[0.0]], [[0.0]]), tolerance=-1)


def test_grid_values_cover_the_ranges():
    assert grid_values(*SEARCH_RANGE, 2) == (10, 12, 14, 16, 18, 20)
    assert grid_values(*CORR_RANGE, 2) == (5, 7, 9, 11, 13, 15)
    assert grid_values(*CORR_RANGE, 4) == (5, 9, 13, 15)
    assert len(grid_values(*SEARCH_RANGE, 1)) == 11
    with pytest.raises(ValueError):
        grid_values(10, 20, 0)


# ------------------------------------------------------------------------------ the report


def _walk_plain(value, path="report"):
    """Every leaf is a JSON/msgpack scalar and every container a dict (str keys) or list."""
    if isinstance(value, dict):
        for k, v in value.items():
            assert isinstance(k, str), f"{path}: key {k!r}"
            _walk_plain(v, f"{path}.{k}")
    elif isinstance(value, list):
        for i, v in enumerate(value):
            _walk_plain(v, f"{path}[{i}]")
    else:
        assert value is None or type(value) in (int, float, str, bool), f"{path}: {value!r}"
        if isinstance(value, float):
            assert math.isfinite(value), path


def check_report(rep: dict) -> None:
    """The tuner/report CONTRACT fields and their shapes (shared with the CLI test)."""
    for k in ("design", "factors", "order", "responses", "effects", "significant", "optimum",
              "sweep"):
        assert k in rep, k
    _walk_plain(rep)
    assert rep["factors"] == list(FACTORS)
    assert len(rep["design"]) == 16 and all(len(r) == 5 and set(r) <= {-1, 1}
                                            for r in rep["design"])
    assert sorted(rep["order"]) == list(range(16))
    for name in ("t1", "tf", "ex", "ey"):
        assert len(rep["responses"][name]) == 16
        assert len(rep["effects"][name]) == 15
        assert set(rep["significant"][name]) == {"99", "95"}
        for term in rep["significant"][name]["99"] + rep["significant"][name]["95"]:
            assert term in rep["effects"][name]
    assert set(rep["optimum"]) == set(FACTORS)
    TrackerParams(**rep["optimum"])
    sw = rep["sweep"]
    for name in ("t1", "tf", "ex", "ey"):
        assert np.asarray(sw[name]).shape == (len(sw["search_size"]), len(sw["corr_size"]))
    assert rep["optimum"]["search_size"] in sw["search_size"]
    assert rep["optimum"]["corr_size"] in sw["corr_size"]
    assert json.loads(json.dumps(rep, allow_nan=False)) == rep


def test_report_has_the_contract_fields_as_plain_types(small_frames):
    result = tune(small_frames, seed=3, step=5, repeats=1)
    rep = result.to_report()
    check_report(rep)
    assert rep["order"] == paper_design().randomized_order(3).tolist()
    assert rep["seed"] == 3 and rep["frames"] == 6 and rep["size"] == [96, 96]
    assert rep["sweep"]["search_size"] == [10, 15, 20] and rep["sweep"]["corr_size"] == [5, 10, 15]
    assert result.params.search_size == rep["optimum"]["search_size"]


def test_work_budget_keeps_the_latest_frames_that_fit():
    assert frames_within(30, (480, 640), 28.0) == 30  # 9.2 MP
    assert frames_within(30, (720, 1280), 28.0) == 30  # 27.6 MP
    assert frames_within(30, (1080, 1920), 28.0) == 13  # 28 MP // 2.07 MP
    assert frames_within(30, (4096, 4096), 28.0) == MIN_FRAMES  # never fewer
    assert frames_within(3, (4096, 4096), 28.0) == 3  # nor more than there are
    assert frames_within(30, (4096, 4096), None) == 30  # no budget
    for bad in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(ValueError, match="max_megapixels"):
            frames_within(30, (96, 96), bad)


def test_a_cycle_over_budget_runs_on_the_latest_frames(small_frames):
    """6 frames of 96x96 (55 kpx) with a 0.04 MP budget: the cycle runs on the latest 4 (the
    floor), exactly as on those 4 frames alone: the same motion, so the same ex, ey and NPI."""
    capped = tune(small_frames, seed=3, step=5, repeats=1, max_megapixels=0.04)
    alone = tune(small_frames[2:], seed=3, step=5, repeats=1, max_megapixels=None)
    assert capped.frames == 4 and capped.offered == 6 and alone.offered == 4
    for name in ("ex", "ey", "npi_mean"):
        assert capped.run.response(name).tolist() == alone.run.response(name).tolist(), name
    for name in ("ex", "ey", "npi"):
        assert getattr(capped.sweep, name).tolist() == getattr(alone.sweep, name).tolist()
    rep = capped.to_report()
    assert rep["frames"] == 4 and rep["frames_offered"] == 6 and rep["max_megapixels"] == 0.04
    with pytest.raises(ValueError, match="ground truth"):
        tune(small_frames, seed=3, max_megapixels=0.04,
             ground_truth=GroundTruth.from_steps([STEP] * 5))


def test_algorithm_modules_import_neither_zenoh_nor_msgpack():
    for path in ("auto_tuner/experiment.py", "auto_tuner/sensitivity.py", "auto_tuner/plots.py",
                 "bench/tuner.py"):
        tree = ast.parse((ROOT / "services" / path).read_text())
        for node in ast.walk(tree):
            mods = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                    [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            assert not any(m.split(".")[0] in ("zenoh", "msgpack") for m in mods), path


# ------------------------------------------------------------------------------ real frames


@pytest.fixture(scope="module")
def rubberwhale_buffer() -> list[np.ndarray]:
    """RubberWhale 07-14 (256x256 crop) played back and forth to 30 frames, or skip."""
    folder = groundtruth.middlebury("RubberWhale")
    if folder is None:
        pytest.skip("Middlebury RubberWhale not found: set VISTRACK_DATA or put the shared "
                    "data at ../shared/data")
    frames = [np.ascontiguousarray(to_gray(cv2.imread(str(folder / f"frame{i:02d}.png")))
                                   [60:316, 160:416]) for i in range(7, 15)]
    return bounce(frames, 30)


@pytest.fixture(scope="module")
def rubberwhale_cycle(rubberwhale_buffer):
    """One tuning cycle on the RubberWhale buffer, of the paper's tracker (its single-level
    search of Eq. (1), pruned): the paper's study, which the tests below reproduce. Its times
    the minima of SWEEP_REPEATS passes, not the auto-tuner's 3: this machine has slow spells
    of a few seconds, and with 3 the corr-size effect's t fell to 2.6 and 2.9 in 2 of 8
    quiet cycles (5.4 to 14 in the others; t > 3 is asserted below)."""
    return tune(rubberwhale_buffer, seed=2024, base=TrackerParams.paper(),
                repeats=SWEEP_REPEATS)


#: Timing passes of the exhaustive sweep, whose interaction is tested: with the default 3 its
#: t fell to 2.4 to 3.9 in 2 of 6 sweeps with the other core busy (a spell of the busy
#: neighbour outlasts the ~1.3 s between passes and slows every pass of some points); with 8
#: it stayed at 4.0 to 7.1 (4 sweeps, other core busy; 6.2 to 7.7 quiet), for ~7 s more.
SWEEP_REPEATS = 8


@pytest.fixture(scope="module")
def rubberwhale_searches(rubberwhale_buffer):
    """Over the RubberWhale buffer: the paper's design timed with the exhaustive search (the
    paper's Eq. (1)), and the sweep timed with each search; the exhaustive sweep on its own
    Experiment, its times the per-frame minima of interleaved passes (2 SWEEP_REPEATS,
    SWEEP_REPEATS for the pruned one)."""
    exp = Experiment(rubberwhale_buffer)
    # the paper's tracker: the claims below are about the cost of its search of Eq. (1)
    exhaustive, pruned = TrackerParams.paper(search="exhaustive"), TrackerParams.paper()
    run = run_design(exp, paper_design(), seed=2024, base=exhaustive)
    # the pruned sweep's times the same minima of interleaved passes: from one pass, a
    # spell of load on a few points of its grid once made its interaction 1/3.95 of the
    # exhaustive's (the test below asks less than 1/4; measured 1/7 to 1/60), in one of a
    # day's 5 CI runs
    return {"design": run,
            # twice the passes: its interaction's t read 2.82 (asserted > 3; 4.0 to 7.1
            # measured) in one of five CI runs on 2026-12-07, a spell over part of its grid
            "exhaustive": sweep(Experiment(rubberwhale_buffer, repeats=2 * SWEEP_REPEATS),
                                base=exhaustive, seed=2024),
            "pruned": sweep(Experiment(rubberwhale_buffer, repeats=SWEEP_REPEATS),
                            base=pruned, seed=2024)}


@pytest.mark.data
def test_real_frames_too_few_features_re_detect_and_pay_every_frame(rubberwhale_cycle):
    """THRES_PERCENT 0.1 -> 5 % multiplies the candidates by 50 and so the features (NPI's
    effect). At 0.1 % the buffer gives 13 to 21 features, fewer than half of MAX_FEAT_NUM: the
    tracker re-detects on every frame, and each such frame pays for its candidates (the
    gradient strength and the THRES_PERCENT selection, ~0.17 ms at 256x256), as the pipeline
    computes them for it. That costs more than tracking the 50 features held at 5 % (~0.05 ms
    with the paper's search), so tf's effect of THRES_PERCENT is no longer the paper's (more
    features, more searches; the sweep's test below holds the features and finds it): it was
    only while the experiment charged the candidates to no frame but the first run's first,
    and the least of the passes left even that out."""
    r = rubberwhale_cycle
    npi_effect = float(np.mean(r.run.response("npi_mean")[r.run.design.matrix[:, 1] > 0])
                       - np.mean(r.run.response("npi_mean")[r.run.design.matrix[:, 1] < 0]))
    assert npi_effect > 0
    tf = r.run.response("tf")
    fifty = np.array([p.max_features == 50 for p in r.run.params])
    starved = fifty & (r.run.design.matrix[:, 1] < 0)
    held = fifty & (r.run.design.matrix[:, 1] > 0)
    assert (r.run.response("npi_mean")[starved] < 25).all()
    assert (r.run.response("npi_mean")[held] >= 25).all()
    assert tf[starved].min() > 2 * tf[held].max(), (tf[starved], tf[held])
    # a larger search window means more displacements to score
    assert r.analysis.effects["tf"]["3"] > 0


@pytest.mark.data
def test_real_frames_window_sizes_drive_tf_at_fixed_features(rubberwhale_cycle):
    """With the feature count held (Table 4), tf grows with SEARCH_SIZE and CORR_SIZE: the
    paper's reason to sweep them. Least squares tf ~ a + b S + c C + d S C over the grid, t
    tests on the coefficients (t > 3: one-sided p < 0.005 on 32 degrees of freedom; on a quiet
    machine both exceed 20)."""
    sw = rubberwhale_cycle.sweep
    s, c = np.meshgrid(sw.search_sizes, sw.corr_sizes, indexing="ij")
    s, c = s.ravel().astype(float), c.ravel().astype(float)
    coef, t = sweep_fit(sw)
    assert coef[1] > 0 and t[1] > 3, (coef, t)
    assert coef[2] > 0 and t[2] > 3, (coef, t)


def sweep_fit(sw: Sweep) -> tuple[np.ndarray, np.ndarray]:
    """Least squares tf ~ a + b S + c C + d S C over the sweep grid (S, C centred), ms and px:
    the coefficients and their t statistics (32 degrees of freedom on the 6 x 6 grid)."""
    s, c = np.meshgrid(sw.search_sizes, sw.corr_sizes, indexing="ij")
    s, c = s.ravel().astype(float), c.ravel().astype(float)
    x = np.column_stack([np.ones_like(s), s - s.mean(), c - c.mean(),
                         (s - s.mean()) * (c - c.mean())])
    y = sw.tf.ravel()
    coef, *_ = np.linalg.lstsq(x, y, rcond=None)
    resid = y - x @ coef
    sigma2 = resid @ resid / (len(y) - x.shape[1])
    se = np.sqrt(np.diag(sigma2 * np.linalg.inv(x.T @ x)))
    return coef, coef / se


@pytest.mark.data
def test_real_frames_exhaustive_search_cost_grows_with_both_windows_and_their_product(
        rubberwhale_searches):
    """The paper's reason to sweep SEARCH_SIZE and CORR_SIZE: Eq. (1) scored in full costs
    (2s+1)^2 (2n+1)^2 per feature, so at Table 4's fixed features tf grows with both windows
    and with their product (the interaction d > 0; measured t 4.0 to 7.1 for it, > 7 for the
    main effects, with the other core busy: times from SWEEP_REPEATS passes). The pruned
    search, timed on the same buffer, barely has that interaction (measured 7 to 60 times
    smaller): its bounds rule out most displacements before their (2n+1)^2 terms are summed."""
    coef, t = sweep_fit(rubberwhale_searches["exhaustive"])
    assert all(coef[1:] > 0) and all(t[1:] > 3), (coef, t)
    pruned, _ = sweep_fit(rubberwhale_searches["pruned"])
    assert coef[3] > 4 * pruned[3], (coef, pruned)


@pytest.mark.data
def test_real_frames_exhaustive_optimum_against_the_reference(rubberwhale_searches):
    """With the paper's search the reference windows (50, 30) cost (51 x 31)^2 / (11 x 5)^2 ~
    800 times the SSD work of the smallest swept windows; with pre-processing and bookkeeping
    the optimum is still well over 10 times faster (measured ~50x). The exhaustive reference,
    timed, scores 0 against the pruned one its errors are measured against: same motion."""
    sw = rubberwhale_searches["exhaustive"]
    best = optimum(sw)
    assert best.within_tolerance and best.speedup > 10, best
    assert sw.reference.ex == 0.0 and sw.reference.ey == 0.0


@pytest.mark.data
def test_real_frames_feature_count_spreads_over_the_design(rubberwhale_searches):
    """Why the unreplicated design cannot reproduce Table 3's tf row (the replicated tests
    below show what it misses): across the design the feature count, set by factors 1, 2 and
    5, spans more than a factor of 5, and tf is about NPI times the window cost. Even
    without any timing noise, tf = NPI x (2s+1)^2 (2n+1)^2 with the measured NPI has more
    than half of its 15 effects active, and Lenth's method, which takes the smaller half for
    noise, finds no term at 99 %."""
    run = rubberwhale_searches["design"]
    npi = run.response("npi_mean")
    assert npi.max() > 5 * npi.min()
    geometry = np.array([(2 * (p.search_size // 2) + 1) ** 2 * (2 * (p.corr_size // 2) + 1) ** 2
                         for p in run.params], np.float64)
    model = DesignRun(run.design, run.params, run.order,
                      tuple(Responses(t1=1.0, tf=float(v), ex=0.0, ey=0.0, npi_mean=float(n))
                            for v, n in zip(npi * geometry, npi, strict=True)), run.seed)
    effects = np.abs(list(analyse(model, responses=["tf"]).effects["tf"].values()))
    assert np.sum(effects > 0.1 * effects.max()) > 7
    assert analyse(model, responses=["tf"]).significant["tf"]["99"] == []


#: Replicates of the real-frame replicated design: with 2 the F ratio of 34 (threshold 8.5 on
#: 16 df) fell to 32 while the machine was busy; 3 (threshold 7.5 on 32 df) kept it above 70.
REPLICATES = 3


@pytest.fixture(scope="module")
def rubberwhale_replicated(rubberwhale_buffer):
    """The paper's design on the RubberWhale buffer, timed with the paper's exhaustive search,
    every run replicated 3 times (a completely randomised order over the 48 units)."""
    return run_replicated(rubberwhale_buffer, paper_design(), seed=2024, replicates=REPLICATES,
                          base=TrackerParams.paper(search="exhaustive"))


@pytest.mark.data
def test_real_frames_paper_table3_tf_row_against_pure_error(rubberwhale_replicated):
    """Paper Table 3: tf is significant at 99 % for SEARCH_SIZE (3), CORR_SIZE (4) and their
    interaction (34): Eq. (1) scored in full costs (2s+1)^2 (2n+1)^2 per feature. Tested
    against pure error, the variation between independent timings of the same run, as the
    physical question asks: is the time's dependence on the windows larger than the timing
    noise? (The unreplicated design cannot say: see the next test.)

    Measured on a 2-core machine, quiet or with both cores busy: the within-run standard
    deviation was 3 to 45 us against effects of 0.1 to 0.4 ms, and F(34) 70 to 11000 against
    the 99 % threshold of 7.5. Every term of tf was significant at 99 % in most runs."""
    run = rubberwhale_replicated
    a = analyse_replicated(run)
    tab = a.results["tf"]
    assert isinstance(tab, anova_mod.AnovaTable) and tab.error.df == 16 * (REPLICATES - 1)
    assert tab.error.ms > 0  # independent timings, not copies: else every effect would pass
    assert {"3", "4", "34"} <= set(a.significant["tf"]["99"]), (a.significant["tf"], tab.error)
    # and in the direction of the cost model: bigger windows, and both together, cost more
    assert all(a.effects["tf"][t] > 0 for t in ("3", "4", "34")), a.effects["tf"]


@pytest.mark.data
def test_real_frames_unreplicated_tf_has_more_real_effects_than_lenth_allows(
        rubberwhale_replicated):
    """Why the paper's unreplicated design cannot reproduce Table 3's tf row here. Against the
    timing noise the replicates measure, more than half of tf's 15 effects are real (the
    feature count, set by factors 1, 2 and 5, multiplies every window cost: see
    test_real_frames_feature_count_spreads_over_the_design). Lenth's method, which takes the
    smaller half of the effects for noise, then estimates the noise from real effects: on one
    replicate (the unreplicated design, timed the same way) its pseudo standard error is
    several times the true standard error of an effect (measured 8 to 60 times) and it does
    not find the interaction 34 at 99 % (measured: no term at all)."""
    run = rubberwhale_replicated
    a = analyse_replicated(run)
    assert len(a.significant["tf"]["99"]) > 7, a.significant["tf"]
    one = run.response("tf")[:, 0]
    lenth = anova_mod.lenth(anova_mod.effects(run.design, one))
    # the standard error of an effect of 16 single observations, from the pure error
    se = math.sqrt(4 * a.results["tf"].error.ms / 16)
    assert lenth.pse > 3 * se, (lenth.pse, se)
    assert "CD" not in lenth.significant(0.99)


@pytest.mark.data
def test_real_frames_searches_give_the_reference_the_same_motion(rubberwhale_buffer):
    """The untimed reference runs use the pruned search (see the experiment module): at the
    reference windows it gives every frame the same estimate as the exhaustive one."""
    ref = TrackerParams(search_size=50, corr_size=30)
    a = track_frames(rubberwhale_buffer, ref)
    b = track_frames(rubberwhale_buffer, ref.replace(search="exhaustive"))
    assert [{k: v for k, v in e.as_dict().items() if k != "t_ms"} for e in a] == \
           [{k: v for k, v in e.as_dict().items() if k != "t_ms"} for e in b]


@pytest.mark.data
def test_real_frames_optimum_is_inside_the_sweep_and_within_tolerance(rubberwhale_cycle):
    r = rubberwhale_cycle
    opt, sw = r.optimum, r.sweep
    assert SEARCH_RANGE[0] <= opt.params["search_size"] <= SEARCH_RANGE[1]
    assert CORR_RANGE[0] <= opt.params["corr_size"] <= CORR_RANGE[1]
    assert opt.within_tolerance
    assert opt.ex <= r.tolerance and opt.ey <= r.tolerance
    # no setting within tolerance is faster
    ok = np.maximum(sw.ex, sw.ey) <= r.tolerance
    assert opt.tf == sw.tf[ok].min()
    # the reference windows do several times the SSD work: smaller windows are faster
    assert opt.speedup > 1.5
    assert sw.reference.ex == 0.0 and sw.reference.ey == 0.0
    check_report(r.to_report())


def test_optimum_never_chooses_a_nan_response():
    nan = float("nan")
    # (10, 5) is the fastest within tolerance but its tf is NaN: (12, 7) is the answer
    best = optimum(_sweep([[nan, 3.0], [2.5, 2.0]], [[0.1, 0.1], [0.9, 0.1]],
                          [[0.1, 0.1], [0.1, 0.1]]), tolerance=0.5)
    assert best.index == (1, 1) and best.within_tolerance
    # none within tolerance: the closest with finite errors, not the NaN one first in order
    best = optimum(_sweep([[1.0, 2.0]], [[nan, 0.8]], [[0.1, 0.9]]), tolerance=0.5)
    assert best.index == (0, 1) and not best.within_tolerance
    with pytest.raises(ValueError, match="finite errors"):
        optimum(_sweep([[1.0]], [[nan]], [[nan]]), tolerance=0.5)
