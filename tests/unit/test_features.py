"""Pre-processing (THRES_PERCENT) and feature selection invariants (Section 5)."""

from __future__ import annotations

import numpy as np
import pytest

from vistrack.common.params import TrackerParams
from vistrack.common.vision import preprocess, select_features
from vistrack.common.vision.preprocess import (
    STRENGTHS,
    frame_noise,
    gaussian_filter,
    magnitude,
    texture_floor,
    threshold_candidates,
)


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


@pytest.mark.parametrize(("share", "floor"), [(0.0, 0.0), (0.001, 0.0), (0.3, 50.0),
                                               (0.9, 50.0), (0.9, 1e9), (1.0, 0.0)])
def test_a_floor_keeps_the_strongest_percent_above_it(share, floor):
    """The floor keeps exactly those of the THRES_PERCENT strongest above it, ties in
    row-major order, where most of the frame lies at or below it: a black or dark frame (all
    0 but ``share`` of it), whose every pixel tied at the threshold and was collected and
    sorted (12 ms at 1280x720)."""
    rng = np.random.default_rng(int(share * 1000 + floor))
    grad = np.zeros((120, 160), np.float32)
    textured = rng.random(grad.shape) < share
    grad[textured] = (rng.integers(1, 40, int(textured.sum())) * 5).astype(np.float32)
    cands, strength = threshold_candidates(grad, 2.0, margin=5, floor=floor)
    # independent reference: the 2 % largest inner values (a full, stable sort) above it
    inner = grad[5:-5, 5:-5].ravel()
    order = np.argsort(-inner, kind="stable")[:int(round(grad.size * 0.02))]
    order = order[inner[order] > floor]
    np.testing.assert_array_equal(strength, inner[order])
    np.testing.assert_array_equal(cands[:, 0], order % 150 + 5)
    np.testing.assert_array_equal(cands[:, 1], order // 150 + 5)


def test_the_gradient_magnitude_is_the_same_wherever_it_lies_in_memory():
    # cv2.magnitude rounded a few values differently at other offsets: the same frame's
    # gradient strengths changed from run to run
    rng = np.random.default_rng(5)
    gx, gy = (rng.normal(0, 300, (240, 320)).astype(np.float32) for _ in range(2))
    first = magnitude(gx, gy)
    for offset in range(1, 8):
        moved = []
        for g in (gx, gy):
            buf = np.empty(g.size + 8, np.float32)
            moved.append(buf[offset:offset + g.size].reshape(g.shape))
            moved[-1][:] = g
        np.testing.assert_array_equal(magnitude(*moved), first)
    # each step rounded to float32: within half an ulp of the exact value or so
    exact = np.sqrt(gx.astype(np.float64) ** 2 + gy.astype(np.float64) ** 2)
    assert np.abs(first - exact).max() <= 2 * np.spacing(first).max()


def test_a_frame_without_texture_has_no_candidates():
    for value in (0, 128, 255):
        pre = preprocess(np.full((96, 128), value, np.uint8), TrackerParams())
        assert len(pre.candidates) == 0 and len(pre.strength) == 0


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


# -- the texture floor ----------------------------------------------------------------------

def noisy(value, sigma, seed, shape=(256, 256)):
    rng = np.random.default_rng(seed)
    return np.clip(np.rint(value + rng.normal(0, sigma, shape)), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("strength", ["min_eigen", "gradient"])
@pytest.mark.parametrize("blur_sigma", [0.0, 0.5, 1.0])
@pytest.mark.parametrize("sigma", [0.5, 1.0, 2.0])
def test_a_uniform_patch_with_the_cameras_noise_has_no_candidate(strength, blur_sigma, sigma):
    """The texture floor is what a uniform patch with the camera's noise reaches: frames of
    pure noise at noise_sigma, or less, give no candidate (a white wall, a covered lens)."""
    params = TrackerParams(strength=strength, blur_sigma=blur_sigma, noise_sigma=2.0)
    for seed in range(3):
        pre = preprocess(noisy(128, sigma, seed), params)
        assert len(pre.candidates) == 0, (seed, pre.strength[:5])


@pytest.mark.parametrize("sigma", [3.0, 5.0, 8.0, 16.0])
def test_more_noise_than_noise_sigma_raises_the_floor_with_it(sigma):
    """A camera's noise grows with its gain (a dark room, a covered lens): a uniform frame
    with more noise than noise_sigma has no candidate either, the floor set by the noise the
    frame shows. With the floor at noise_sigma alone, noise of 8 made over 100 candidates."""
    params = TrackerParams(noise_sigma=2.0)
    for seed in range(3):
        frame = noisy(60, sigma, seed, shape=(240, 320))
        assert len(preprocess(frame, params).candidates) == 0, seed
        assert frame_noise(gaussian_filter(frame, params.blur_sigma),
                                      params) == pytest.approx(sigma, rel=0.15)
        # the floor it sets is what lets none through: at noise_sigma's alone, some pass
        grad = STRENGTHS[params.strength](gaussian_filter(frame, params.blur_sigma))
        assert (grad > texture_floor(params)).sum() > 0


def test_a_real_scene_with_the_cameras_noise_keeps_its_candidates(real_image):
    """Noise added to a textured scene raises the floor, but the scene's texture clears it:
    its candidates are those of its clean frame's quality level, nearly all of them."""
    params = TrackerParams()
    for sigma in (3.0, 6.0):
        frame = np.clip(np.rint(real_image + np.random.default_rng(0).normal(
            0, sigma, real_image.shape)), 0, 255).astype(np.uint8)
        pre = preprocess(frame, params)
        assert len(pre.candidates) >= 0.9 * round(frame.size * params.thres_percent / 100)


@pytest.mark.parametrize("value", [0, 37, 255])
def test_a_frame_without_texture_has_no_candidate_even_with_both_floors_off(value):
    """Strength 0 everywhere: no candidate, even with noise_sigma and quality_level 0 (the
    top THRES_PERCENT of zeros used to be 51 'features')."""
    frame = np.full((256, 256), value, np.uint8)
    for params in (TrackerParams(), TrackerParams(noise_sigma=0.0, quality_level=0.0)):
        assert len(preprocess(frame, params).candidates) == 0


def test_real_frames_keep_their_candidates(real_image):
    """On a textured real frame the floors take nothing away: THRES_PERCENT keeps its
    meaning, the same candidates in the same order."""
    params = TrackerParams()
    pre = preprocess(real_image, params)
    off = preprocess(real_image, params.replace(noise_sigma=0.0, quality_level=0.0))
    np.testing.assert_array_equal(pre.candidates, off.candidates)
    assert len(pre.candidates) == round(real_image.size * params.thres_percent / 100)


def test_quality_level_keeps_the_candidates_above_a_fraction_of_the_strongest(real_image):
    """As goodFeaturesToTrack's qualityLevel: one bright spot on a dim scene keeps only the
    candidates within the fraction of it; the others are dropped, strongest first kept."""
    frame = (real_image // 8).astype(np.uint8)  # a dim scene
    frame[100:104, 100:104] = 255  # and one bright corner
    params = TrackerParams(quality_level=0.3)
    pre = preprocess(frame, params)
    full = preprocess(frame, params.replace(quality_level=0.0))
    assert 0 < len(pre.candidates) < len(full.candidates)
    assert (pre.strength >= 0.3 * full.strength[0]).all()
    np.testing.assert_array_equal(pre.candidates, full.candidates[:len(pre.candidates)])


def _min_eigen_reference(img: np.ndarray) -> np.ndarray:
    """Shi and Tomasi's strength as OpenCV and numpy compute it in float32: ``cv2.Sobel``
    (3x3, edges replicated), products and 3x3 sums in float32, the smaller eigenvalue in
    float64 from the float32 trace and sxy^2; the border ring 0."""
    import cv2

    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3, borderType=cv2.BORDER_REPLICATE)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3, borderType=cv2.BORDER_REPLICATE)
    h, w = img.shape

    def box(p: np.ndarray) -> np.ndarray:  # the 3x3 sums at the inner pixels
        return sum(p[1 + dy:h - 1 + dy, 1 + dx:w - 1 + dx]
                   for dy in (-1, 0, 1) for dx in (-1, 0, 1))

    sxx, sxy, syy = box(gx * gx), box(gx * gy), box(gy * gy)
    half_tr = 0.5 * (sxx + syy).astype(np.float64)
    d = 0.5 * (sxx.astype(np.float64) - syy.astype(np.float64))
    out = np.zeros((h, w), np.float32)
    out[1:-1, 1:-1] = half_tr - np.sqrt(d * d + (sxy * sxy).astype(np.float64))
    return out


@pytest.mark.parametrize("shape", [(3, 3), (5, 17), (64, 64), (97, 131), (256, 256)])
def test_min_eigen_strength_is_opencvs_float32_pipeline(shape, real_image):
    """The integer kernel's strength, bit for bit that of ``cv2.Sobel`` to float32 and the
    sums in float32 (its docstring's claim), on noise and on a real frame's crop."""
    from vistrack.common.vision.preprocess import min_eigen_strength

    noise = np.random.default_rng(sum(shape)).integers(0, 256, shape, dtype=np.uint8)
    h, w = shape
    crop = np.ascontiguousarray(real_image[:h, :w])
    assert crop.shape == shape
    for img in (noise, crop):
        np.testing.assert_array_equal(min_eigen_strength(img), _min_eigen_reference(img))
