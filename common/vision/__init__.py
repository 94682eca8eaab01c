"""Pure vision algorithms of the paper (no Zenoh, no msgpack): pre-processing, feature
selection, the SSD search of Eq. (1), the tracker and the position estimate of Eq. (2)."""

from .features import select_features
from .motion import centroid_scatter, incremental_motion
from .preprocess import Preprocessed, preprocess, to_gray
from .ssd import track_ssd, window_weights
from .tracker import Estimate, Tracker, kernel_cache_dir, timing, track_frames, warm_up

__all__ = ["Estimate", "Preprocessed", "Tracker", "centroid_scatter", "incremental_motion",
           "kernel_cache_dir", "preprocess", "select_features", "timing", "to_gray",
           "track_frames", "track_ssd", "warm_up", "window_weights"]
