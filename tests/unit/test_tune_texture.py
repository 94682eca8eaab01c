"""Tuning on frames without texture (a covered lens, a dark room): every window size would
score zero error there, so the cycle refuses the buffer rather than pick the fastest window for
nothing."""

from __future__ import annotations

import numpy as np
import pytest

from vistrack.common.params import TrackerParams
from vistrack.services.auto_tuner.experiment import Experiment
from vistrack.services.auto_tuner.sensitivity import TextureError, tune


def _noise(n: int, sigma: float = 5.0, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [np.clip(np.rint(40 + rng.normal(0, sigma, (120, 160))), 0, 255).astype(np.uint8)
            for _ in range(n)]


def test_a_buffer_without_texture_is_not_tuned_on():
    with pytest.raises(TextureError, match=r"too little texture to tune on: the reference "
                                           r"windows \(50, 30\) track 3 features or more on "
                                           r"0 % of the 6 frames, at least 50 % needed"):
        tune(_noise(6), seed=1)


def test_frames_smaller_than_the_reference_window_say_so(real_image):
    """Real texture, but frames of 24x20 px hold no 30 px correlation window: the error names
    the size, not a covered lens."""
    small = [np.ascontiguousarray(real_image[k:k + 20, k:k + 24]) for k in range(6)]
    with pytest.raises(TextureError, match=r"frames of 24x20 px hold no 30 px correlation "
                                           r"window: give larger frames"):
        tune(small, seed=1)
    with pytest.raises(TextureError, match=r"a covered lens"):
        tune(_noise(6), seed=1)
    # wider than the window, but not by much: 40 x 40 px of real texture is no covered lens
    small = [np.ascontiguousarray(real_image[k:k + 40, k:k + 40]) for k in range(6)]
    with pytest.raises(TextureError, match=r"frames of 40x40 px are small for the reference "
                                           r"windows \(50, 30\): a feature keeps 16 px from "
                                           r"each border; give larger frames"):
        tune(small, seed=1)


@pytest.mark.parametrize("most", [1, 2])
def test_a_feature_cap_below_three_says_so_not_a_covered_lens(real_image, most):
    """--max-features 1 or 2 (allowed) leaves no estimate valid (3 features or more): every
    tuning was skipped as if the lens were covered."""
    frames = [np.ascontiguousarray(real_image[k:k + 120, k:k + 160]) for k in range(6)]
    with pytest.raises(TextureError, match=rf"max_features is {most}: fewer features than "
                                           r"that can be tracked"):
        tune(frames, seed=1, base=TrackerParams(max_features=most))


def test_the_share_of_textured_frames_counts_the_frames_with_a_valid_estimate(real_image):
    """A real scene whose last frames go dark: the reference tracks it on the frames before."""
    frames = [real_image] * 4 + [np.zeros_like(real_image)] * 4
    assert Experiment(frames).textured(TrackerParams()) == pytest.approx(4 / 8)
    assert Experiment([real_image] * 5).textured(TrackerParams()) == 1.0


def test_the_sweep_holds_the_other_factors_where_it_is_told(real_image):
    """The auto-tuner tunes the windows for the parameters in force: its sweep holds
    max_features, thres_percent and ungroup_size at the values it is given, and the optimum
    carries them. Held at Table 4's (the paper's sweep, the default), the optimum put a
    user's max_features 150 back to 100 at the next tuning."""
    frames = [np.ascontiguousarray(np.roll(real_image, (k, 2 * k), axis=(0, 1)))
              for k in range(6)]
    held = {"max_features": 150, "thres_percent": 3.0, "ungroup_size": 7}
    result = tune(frames, seed=1, repeats=1, fixed=held)
    assert {k: result.optimum.params[k] for k in held} == held
    assert {k: getattr(result.params, k) for k in held} == held
    default = tune(frames, seed=1, repeats=1)
    assert {k: default.optimum.params[k] for k in held} == {
        "max_features": 100, "thres_percent": 2.0, "ungroup_size": 5}
