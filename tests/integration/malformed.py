"""Malformed messages of each input key, built with plain msgpack (no project code): the
live tests send them to real services and check each is refused, counted and survived."""

from __future__ import annotations

import random

import msgpack

HUGE = 20 * 1024 * 1024

# A well-formed message of each input key (params_id 0: stale, never applied even if valid).
GOOD: dict[str, dict] = {
    "camera/frame": {"v": 1, "seq": 1, "stamp_ns": 1, "width": 64, "height": 48,
                     "encoding": "mono8", "data": bytes(64 * 48)},
    "preprocessing/frame": {"v": 1, "seq": 1, "stamp_ns": 1, "width": 64, "height": 48,
                            "encoding": "mono8", "data": bytes(64 * 48), "candidates": b"",
                            "strength": b"", "params_id": 0},
    "tuner/params": {"v": 1, "seq": 1, "stamp_ns": 1, "max_features": 100,
                     "thres_percent": 2.0, "search_size": 15, "corr_size": 9,
                     "ungroup_size": 5, "params_id": 0, "source": "user", "reason": "test"},
    "motion/estimate": {"v": 1, "seq": 1, "stamp_ns": 1, "npi": 0, "xc": 1.0, "yc": 1.0,
                        "xe": 0.0, "ye": 0.0, "dx": 0.0, "dy": 0.0, "scale": 1.0, "t_ms": 1.0,
                        "first": False, "features": [], "params_id": 0},
}
# (field to mistype, wrong value), (field to make 20 MB)
WRONG_TYPE = {"camera/frame": ("width", "64"), "preprocessing/frame": ("candidates", [1, 2]),
              "tuner/params": ("search_size", "21"), "motion/estimate": ("npi", 1.5)}
HUGE_FIELD = {"camera/frame": "data", "preprocessing/frame": "data", "tuner/params": "reason",
              "motion/estimate": "features"}


def malformed(suffix: str) -> dict[str, bytes]:
    """Name -> bad payload for one input key, built with plain msgpack."""
    good = GOOD[suffix]
    pack = msgpack.packb
    field, wrong = WRONG_TYPE[suffix]
    missing = dict(good)
    del missing[list(good)[3]]  # the first field after v, seq, stamp_ns
    bad = {
        "random bytes": random.Random(suffix).randbytes(200),
        "not a map": pack([1, 2, 3]),
        "version 2": pack({**good, "v": 2}),
        "missing field": pack(missing),
        "wrong type": pack({**good, field: wrong}),
        "huge bin": pack({**good, HUGE_FIELD[suffix]: bytes(HUGE)}),
    }
    if "data" in good:
        bad["data length != width*height"] = pack({**good, "data": bytes(64 * 48 - 1)})
    return bad
