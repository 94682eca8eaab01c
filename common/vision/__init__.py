"""Pure vision algorithms of the paper (no Zenoh, no msgpack): pre-processing, feature
selection, the SSD search of Eq. (1), the tracker and the position estimate of Eq. (2)."""

import sys as _sys
from pathlib import Path as _Path

from .kernelcache import prefer_full_vectors as _prefer_full_vectors
from .kernelcache import refresh as _refresh

# before numba compiles or loads a kernel: 512-bit vectors on AVX-512 cores (see kernelcache)
_prefer_full_vectors()

from .features import select_features  # noqa: E402
from .motion import centroid_scatter, incremental_motion  # noqa: E402
from .preprocess import Preprocessed, preprocess, to_gray  # noqa: E402
from .ssd import track_ssd, window_weights  # noqa: E402
from .tracker import Estimate, Tracker, kernel_cache_dir, timing, track_frames, warm_up  # noqa: E402

__all__ = ["Estimate", "Preprocessed", "Tracker", "centroid_scatter", "incremental_motion",
           "kernel_cache_dir", "preprocess", "select_features", "timing", "to_gray",
           "track_frames", "track_ssd", "warm_up", "window_weights"]

#: the modules with ``cache=True`` kernels
KERNEL_MODULES = ("features", "motion", "preprocess", "pyramid", "ssd", "tracker")

# before any kernel runs: cached kernels compiled from other sources are dropped (numba would
# load a caller with the old code of a callee from another module; see kernelcache)
_refresh([_sys.modules[f"{__name__}.{name}"] for name in KERNEL_MODULES], _Path(__file__).parent)
