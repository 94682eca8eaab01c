"""What the auto-tuner logs of the changes it sees: the evidence, and at INFO once per kind of
change between two tunings. A storm of lost features goes on for seconds, one confirmed change every
few estimates; at INFO each of them made a line every half second (seen at 3840x2160).

The auto-tuner's loop runs in-process on a MemoryNode with its real worker process.
"""

from __future__ import annotations

import logging
import time

from vistrack.common.messages import Estimate

from loops import Running


def _estimate(seq: int, ids: range) -> bytes:
    features = [[i, 10.0 + i % 50, 10.0 + i // 50] for i in ids]
    return Estimate(seq=seq, stamp_ns=time.time_ns(), npi=len(features), xc=30.0, yc=12.0,
                    xe=1.0, ye=1.0, dx=0.0, dy=0.0, scale=1.0, t_ms=1.0, first=False,
                    features=features, params_id=1, valid=True).encode()


def test_a_storm_is_logged_with_its_evidence_at_info_once(caplog):
    caplog.set_level(logging.DEBUG, logger="vistrack.auto_tuner")
    with Running("auto-tuner", "--min-interval", "0") as tuner:
        # every estimate renews all of its features: a turnover event each, a storm every
        # three (STORM_EVENTS), while the initial tuning is pending (no frames come)
        for seq in range(12):
            tuner.feed(tuner.node.keys.estimate, _estimate(seq, range(20 * seq, 20 * seq + 20)))
    seen = [r for r in caplog.records if r.name == "vistrack.auto_tuner" and " seen: " in
            r.getMessage()]
    assert len(seen) >= 3, [r.getMessage() for r in seen]
    assert all(r.getMessage().startswith("scene change seen: a feature storm: 3 turnovers "
                                         "(50% of the features lost or new) in the last 30 "
                                         "estimates; tuning pending: initial tuning")
               for r in seen)
    assert [r.levelno for r in seen] == [logging.INFO] + [logging.DEBUG] * (len(seen) - 1)
