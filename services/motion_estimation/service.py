"""motion-estimation: feature selection, SSD tracking (Eq. 1) and the estimate (Eq. 2).

Reads   ``vistrack/<robot>/preprocessing/frame``   (latest only: drops are counted)
        ``vistrack/<robot>/tuner/params``          (reliable: applied between frames)
Writes  ``vistrack/<robot>/motion/estimate``       (one per processed frame)

The tracker is the library's :class:`~vistrack.common.vision.Tracker`, fed the filtered frame
and candidates computed upstream, so the pipeline computes exactly what ``vistrack track`` does.
Estimates keep the camera frame's ``seq``; when it goes back (the camera restarted), or the
frame size changes, the track starts again (``first: true``).
"""

from __future__ import annotations

import argparse
import logging
import time

import numpy as np

from ...common.bus import Node
from ...common.messages import Estimate, PreFrame
from ...common.vision import Preprocessed, Tracker, warm_up
from ..runtime import (
    ParamsInForce,
    add_service_args,
    decode_or_reject,
    dispatch,
    ready,
    serve,
)

log = logging.getLogger("vistrack.motion_estimation")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_service_args(parser, tracker_params=True)


def estimate_message(e, *, seq: int, stamp_ns: int, params_id: int) -> Estimate:
    """The ``motion/estimate`` message of a library estimate."""
    return Estimate(seq=seq, stamp_ns=stamp_ns, npi=e.npi, xc=e.xc, yc=e.yc, xe=e.xe, ye=e.ye,
                    dx=e.dx, dy=e.dy, scale=e.scale, t_ms=e.t_ms, first=e.first,
                    valid=e.valid, features=e.features(), params_id=params_id)


def loop(node: Node, args: argparse.Namespace) -> None:
    state = ParamsInForce.from_args(args)
    state.publish_status(node)
    warm_up()
    tracker = Tracker(state.params)
    node.subscribe(node.keys.params, latest=False)
    node.subscribe(node.keys.pre_frame, latest=True)
    node.advertise(node.keys.estimate, reliable=False)
    last_seq = -1

    def on_params(payload: bytes) -> None:
        if state.apply(payload, node, log):
            tracker.set_params(state.params)

    def on_frame(payload: bytes) -> None:
        nonlocal last_seq
        t0 = time.perf_counter()
        msg = decode_or_reject(PreFrame, payload, node, log)
        if msg is None:
            return
        # decoded arrays are read-only views of the payload; numba would compile (and cache)
        # a second specialisation of every kernel for read-only inputs, 40 ms on frame one
        pre = Preprocessed(np.array(msg.data), msg.candidates, msg.strength)
        if msg.seq <= last_seq:
            log.info("camera restarted (seq %d after %d): new track", msg.seq, last_seq)
            tracker.reset()
        last_seq = msg.seq
        try:
            est = tracker.update(pre, seq=msg.seq, t_start=t0)
        except ValueError as e:  # the only one: the frame size changed (another camera)
            log.warning("%s: restarting the track", e)
            tracker.reset()
            est = tracker.update(pre, seq=msg.seq, t_start=t0)
        node.publish(node.keys.estimate, estimate_message(
            est, seq=msg.seq, stamp_ns=msg.stamp_ns, params_id=state.params_id).encode(),
            reliable=False)
        node.status.observe_ms((time.perf_counter() - t0) * 1e3)
        node.status.extra.update(npi=est.npi, lost=tracker.lost_total,
                                 redetections=tracker.redetections)

    def recover() -> None:
        # a frame that failed may have left the track half-updated: start a new one
        tracker.reset()

    ready(node)
    dispatch(node, {node.keys.params: on_params, node.keys.pre_frame: on_frame}, log,
             recover=recover)


def main(args: argparse.Namespace) -> int:
    return serve("motion_estimation", args, loop)
