"""How ``vistrack replay`` publishes each stream: latest-only streams BLOCK_FIRST, as the
services do, but the frames BLOCK when ``--in-flight`` paces them (a file camera's rule)."""

from __future__ import annotations

import argparse
import threading

import pytest
import zenoh

from vistrack.common.bus import loopback_config
from vistrack.services.tools import replay


@pytest.mark.parametrize(("in_flight", "frames"), [
    (0, zenoh.CongestionControl.BLOCK_FIRST),  # at the recorded pace: latest-only
    (2, zenoh.CongestionControl.BLOCK),  # paced by the pipeline: at most 2 queue, none lost
])
def test_the_frames_go_block_when_paced_by_the_pipeline(free_port, in_flight, frames):
    args = argparse.Namespace(in_flight=in_flight)
    with zenoh.open(loopback_config(f"tcp/127.0.0.1:{free_port}", router=True)) as session:
        player = replay._Player(session, args, threading.Event(), None)
        try:
            congestion = {key: player.publisher(f"vistrack/robot/{key}").publisher
                          .congestion_control
                          for key in ("camera/frame", "motion/estimate", "tuner/params")}
        finally:
            if player.acks is not None:
                player.acks.close()
            for pub in player._publishers.values():
                pub.undeclare()
    assert congestion == {"camera/frame": frames,
                          "motion/estimate": zenoh.CongestionControl.BLOCK_FIRST,
                          "tuner/params": zenoh.CongestionControl.BLOCK}
