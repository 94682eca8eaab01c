"""Pure vision algorithms of the paper (no Zenoh, no msgpack): pre-processing, feature
selection, the SSD search of Eq. (1), the tracker and the position estimate of Eq. (2)."""

import sys as _sys
from pathlib import Path as _Path

from .features import select_features
from .kernelcache import refresh as _refresh
from .motion import centroid_scatter, incremental_motion
from .preprocess import Preprocessed, preprocess, to_gray
from .ssd import track_ssd, window_weights
from .tracker import Estimate, Tracker, kernel_cache_dir, timing, track_frames, warm_up

__all__ = ["Estimate", "Preprocessed", "Tracker", "centroid_scatter", "incremental_motion",
           "kernel_cache_dir", "preprocess", "select_features", "timing", "to_gray",
           "track_frames", "track_ssd", "warm_up", "window_weights"]

#: the modules with ``cache=True`` kernels
KERNEL_MODULES = ("features", "motion", "preprocess", "pyramid", "ssd", "tracker")

# before any kernel runs: cached kernels compiled from other sources are dropped (numba would
# load a caller with the old code of a callee from another module; see kernelcache)
_refresh([_sys.modules[f"{__name__}.{name}"] for name in KERNEL_MODULES], _Path(__file__).parent)
