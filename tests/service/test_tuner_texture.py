"""The auto-tuner on a buffer without texture (a covered lens, a dark room): no cycle can
measure any motion there, so every window size scores zero error and the "optimum" would be
the fastest window for nothing. The cycle is skipped, said and counted; the parameters in
force are kept.

The auto-tuner's loop runs in-process on a MemoryNode with its real worker process.
"""

from __future__ import annotations

import time

import numpy as np

from vistrack.common.messages import Frame, Params

from loops import IDLE_S, Running

BUFFER = 15


def _noise(n: int, sigma: float = 5.0, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [np.clip(np.rint(40 + rng.normal(0, sigma, (120, 160))), 0, 255).astype(np.uint8)
            for _ in range(n)]


def test_the_auto_tuner_skips_a_cycle_on_a_covered_lens_and_keeps_its_parameters():
    with Running("auto-tuner", "--buffer", str(BUFFER), "--min-interval", "0") as tuner:
        node = tuner.node
        stamp = time.time_ns()
        for seq, image in enumerate(_noise(BUFFER)):
            tuner.feed(node.keys.frame,
                       Frame.from_image(image, seq=seq, stamp_ns=stamp + seq).encode())
        deadline = time.monotonic() + IDLE_S
        while not node.status.extra["skipped"]:
            assert tuner.thread.is_alive() and time.monotonic() < deadline, node.status.extra
            time.sleep(0.05)
        extra = dict(node.status.extra)
        published = [Params.decode(p) for p in node.published_on(node.keys.params)]
    assert extra["skipped"] == 1 and extra["tunings"] == 0 and not extra["tuning"]
    # due again, said at once (it said None until a frame came, maybe long after)
    assert extra["pending"] == "initial tuning"
    assert node.status.last_error in ("", None)  # not a fault
    # only the start-up announcement of the parameters in force, repeated; nothing tuned
    assert published and {(p.params_id, p.reason) for p in published} == \
        {(published[0].params_id, "start-up (flags)")}
    assert {(p.search_size, p.corr_size) for p in published} == {(15, 9)}
    assert node.published_on(node.keys.report) == []
