"""The camera's noise estimated from its frames (:mod:`vistrack.common.vision.noise`)."""

from __future__ import annotations

import numpy as np
import pytest

from vistrack.common import rendered
from vistrack.common.params import TrackerParams
from vistrack.common.vision import Tracker
from vistrack.common.vision import tracker as tracker_module
from vistrack.common.vision.noise import noise_level
from vistrack.common.vision.preprocess import gaussian_filter, preprocess
from vistrack.services.bench.accuracy import run_sequence

from conftest import rendered_sequences


def _noisy(image: np.ndarray, sigma: float, seed: int = 1) -> np.ndarray:
    noise = np.random.default_rng(seed).standard_normal(image.shape)
    return np.clip(np.rint(image + sigma * noise), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("sigma", [2.0, 5.0, 10.0])
@pytest.mark.parametrize("blur", [0.0, 0.25, 0.5])
def test_the_noise_of_a_uniform_frame_is_read_in_the_cameras_grey_levels(sigma, blur):
    """Mid-grey and noise of ``sigma`` grey levels, seen through the pre-filter (none, or up
    to the default's): the estimate is the camera's sigma, to 10 %."""
    frame = _noisy(np.full((240, 320), 128.0), sigma)
    assert noise_level(gaussian_filter(frame, blur), blur) == pytest.approx(sigma, rel=0.1)


@pytest.mark.parametrize("value", [0, 77, 255])
def test_a_frame_without_noise_reads_none(value):
    assert noise_level(np.full((64, 64), value, np.uint8), 0.5) == 0.0


@pytest.mark.parametrize("shape", [(1, 1), (2, 8), (8, 2)])
def test_a_frame_too_small_for_the_operator_reads_none(shape):
    assert noise_level(np.zeros(shape, np.uint8), 0.5) == 0.0


def test_a_real_frames_texture_is_not_taken_for_much_noise(real_image):
    """A real frame (its own noise about a grey level) reads at most ~3; with 3 and 6 grey
    levels of noise added, their levels to within 25 %: the edges and fine texture that pass
    the operator do not carry the median away."""
    clean = noise_level(gaussian_filter(real_image, 0.5), 0.5)
    assert clean <= 3.0
    for sigma in (3.0, 6.0):
        got = noise_level(gaussian_filter(_noisy(real_image, sigma), 0.5), 0.5)
        assert got == pytest.approx(sigma, rel=0.25), sigma
        assert got > clean


# -- what the tracker does with it: the wide sub-pixel window's test -----------------------------


@pytest.fixture(scope="module")
def noisy_sequences():
    seqs = rendered_sequences(30, ("RubberWhale", "Urban2"))
    return [rendered.RenderedSequence(s.name, [_noisy(f, 6.0, k) for k, f in enumerate(s.frames)],
                                      s.homographies) for s in seqs]


def test_a_noisy_camera_is_tracked_as_well_as_lk_tracks_it(noisy_sequences, monkeypatch):
    """Six grey levels of noise (a dim room): the default tracker's median error is at most
    5 % above LK's from the same points (measured: 0.075 against 0.080, 0.065 against 0.074),
    none of its pairs off by more than 2 px, with the noise measured or not.

    Noise is what the wide window averages out: its sides fit the correlation window's
    estimate as well as its centre does, to within what noise leaves, so its estimate is
    taken. Without it (``refine_size`` 0) the median error is 1.5 times as large or more
    (measured 0.125 and 0.113)."""
    def run(seq: rendered.RenderedSequence, params: TrackerParams) -> tuple:
        return run_sequence(seq.frames, lambda p, k: seq.map(p, k, k + 1), params)
    for seq in noisy_sequences:
        ours, lk, _ = run(seq, TrackerParams())
        assert ours.median_epe <= 1.05 * lk.median_epe, (seq.name, ours, lk)
        assert ours.gross <= 0.02, seq.name
        with monkeypatch.context() as m:
            m.setattr(tracker_module, "noise_level", lambda frame, blur: 0.0)
            unmeasured, lk_again, _ = run(seq, TrackerParams())
        assert unmeasured.median_epe <= 1.05 * lk_again.median_epe, (seq.name, unmeasured)
        narrow, _, _ = run(seq, TrackerParams(refine_size=0))
        assert ours.median_epe <= narrow.median_epe / 1.5, (seq.name, ours, narrow)


def test_a_camera_sized_frame_reads_its_noise_too():
    """1280 x 720 (read in its middle, so that it costs what a small frame does)."""
    frame = _noisy(np.full((720, 1280), 100.0), 4.0)
    assert noise_level(gaussian_filter(frame, 0.5), 0.5) == pytest.approx(4.0, rel=0.1)


def test_a_frames_noise_is_read_after_its_estimate_and_used_from_the_next_frame():
    """The noise read is work a frame's estimate does not wait for (~1.5 ms in a service at
    30 fps, every NOISE_EVERY frames): ``update`` leaves it, ``settle`` does it, and the next
    ``update`` does it first where nobody called ``settle``; the estimates are the same
    either way, so a service that settles once its estimate is out tracks as ``vistrack track``
    does."""
    seq, = rendered_sequences(tracker_module.NOISE_EVERY + 2, ("RubberWhale",))
    params = TrackerParams()
    pres = [preprocess(_noisy(f, 6.0, k), params) for k, f in enumerate(seq.frames)]
    settled, lazy = Tracker(params), Tracker(params)
    first = settled.update(pres[0])
    assert settled.noise == 0.0  # not read on the estimate's path
    settled.settle()
    assert settled.noise == noise_level(pres[0].filtered, params.blur_sigma) > 3.0
    noises = [settled.noise]
    estimates = [(first, lazy.update(pres[0]))]
    for pre in pres[1:]:
        estimates.append((settled.update(pre), lazy.update(pre)))
        settled.settle()
        noises.append(settled.noise)
    for a, b in estimates:
        assert a.as_dict() | {"t_ms": 0} == b.as_dict() | {"t_ms": 0}
    # read again NOISE_EVERY frames on, from that frame
    k = tracker_module.NOISE_EVERY
    assert noises[k] == noise_level(pres[k].filtered, params.blur_sigma) != noises[k - 1]
    assert lazy.noise == noises[-2]  # the last frame's read is still due
