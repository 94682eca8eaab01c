"""Pre-processing (THRES_PERCENT) and feature selection invariants (Section 5)."""

from __future__ import annotations

import numpy as np
import pytest

from vistrack.common.params import TrackerParams
from vistrack.common.vision import preprocess, select_features
from vistrack.common.vision.preprocess import threshold_candidates


@pytest.mark.parametrize("percent", [0.1, 1.0, 2.0, 5.0])
def test_threshold_keeps_the_strongest_percent(percent):
    rng = np.random.default_rng(int(percent * 10))
    grad = rng.random((120, 160)).astype(np.float32) * 100
    grad[rng.random(grad.shape) < 0.05] = 50.0  # many exact ties
    cands, strength = threshold_candidates(grad, percent, margin=5)
    k = int(round(grad.size * percent / 100))
    assert len(cands) == k
    inner = grad[5:-5, 5:-5]
    # independent reference: the k largest inner values (a full sort)
    ref = np.sort(inner.ravel())[::-1][:k]
    np.testing.assert_array_equal(strength, ref)
    np.testing.assert_array_equal(grad[cands[:, 1], cands[:, 0]], strength)
    assert (cands[:, 0] >= 5).all() and (cands[:, 0] < 155).all()
    assert (cands[:, 1] >= 5).all() and (cands[:, 1] < 115).all()
    # deterministic tie order: row-major among equal strengths
    same = strength[:-1] == strength[1:]
    flat = cands[:, 1].astype(int) * 160 + cands[:, 0]
    assert (flat[:-1][same] < flat[1:][same]).all()


@pytest.mark.parametrize("params", [
    TrackerParams(),
    TrackerParams(max_features=50, ungroup_size=20),
    TrackerParams(max_features=200, ungroup_size=5, thres_percent=5.0),
    TrackerParams(max_features=30, grid_rows=2, grid_cols=3, cell_cap=4, thres_percent=0.5),
    TrackerParams(ungroup_size=0),
])
def test_selection_invariants(real_image, params):
    pre = preprocess(real_image, params)
    chosen = select_features(pre.candidates, real_image.shape, params)
    pts = pre.candidates[chosen].astype(float)
    h, w = real_image.shape
    # count: never above MAX_FEAT_NUM, and all of it when candidates are plentiful
    assert len(pts) <= params.max_features
    # every point is a candidate, so above the THRES_PERCENT threshold
    threshold = pre.strength.min()
    assert (pre.strength[chosen] >= threshold).all()
    assert len(set(chosen.tolist())) == len(chosen)
    # minimum distance UNGROUP_SIZE between any two points
    if len(pts) > 1 and params.ungroup_size > 0:
        d = np.hypot(*(pts[:, None, :] - pts[None, :, :]).transpose(2, 0, 1))
        d[np.diag_indices(len(pts))] = np.inf
        assert d.min() >= params.ungroup_size
    # per-cell cap of the grid
    rows = (pts[:, 1] * params.grid_rows // h).astype(int)
    cols = (pts[:, 0] * params.grid_cols // w).astype(int)
    counts = np.bincount(rows * params.grid_cols + cols,
                         minlength=params.grid_rows * params.grid_cols)
    assert counts.max() <= params.effective_cell_cap
    # greedy in strength order: every rejected candidate stronger than the weakest chosen one
    # broke a rule (distance or full cell) against points chosen before it
    if len(pts) == params.max_features:
        last = chosen.max()
        for c in range(last):
            if c in set(chosen.tolist()):
                continue
            x, y = pre.candidates[c].astype(float)
            before = pre.candidates[chosen[chosen < c]].astype(float)
            near = (np.hypot(before[:, 0] - x, before[:, 1] - y) < params.ungroup_size).any()
            cell = (int(y * params.grid_rows // h) * params.grid_cols
                    + int(x * params.grid_cols // w))
            b_cells = ((before[:, 1] * params.grid_rows // h).astype(int) * params.grid_cols
                       + (before[:, 0] * params.grid_cols // w).astype(int))
            full = (b_cells == cell).sum() >= params.effective_cell_cap
            assert near or full


def test_existing_features_are_respected(real_image):
    params = TrackerParams(max_features=60, ungroup_size=10)
    pre = preprocess(real_image, params)
    first = pre.candidates[select_features(pre.candidates, real_image.shape, params)][:30]
    more = pre.candidates[select_features(pre.candidates, real_image.shape, params,
                                          existing=first.astype(float), max_count=30)]
    assert len(more) <= 30
    d = np.hypot(*(more[:, None, :].astype(float) - first[None, :, :]).transpose(2, 0, 1))
    assert d.min() >= 10


def test_preprocess_rejects_colour_frames():
    with pytest.raises(ValueError, match="uint8"):
        preprocess(np.zeros((8, 8, 3), np.uint8), TrackerParams())
