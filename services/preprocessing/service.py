"""preprocessing: filter, gradient and THRES_PERCENT candidates for every camera frame.

Reads   ``vistrack/<robot>/camera/frame``          (latest only: a slow stage drops, counted)
        ``vistrack/<robot>/tuner/params``          (reliable: applied between frames)
Writes  ``vistrack/<robot>/preprocessing/frame``   (filtered frame + candidates + strength)

A pre-processed frame keeps its camera frame's ``seq``: downstream sees the camera's gaps, and
a ``seq`` that goes back (the camera restarted) tells motion-estimation to start a new track.
"""

from __future__ import annotations

import argparse
import logging
import time

from ...common.bus import Node
from ...common.messages import Frame, PreFrame
from ...common.vision import preprocess, warm_up
from ..runtime import (
    ParamsInForce,
    add_service_args,
    decode_or_reject,
    dispatch,
    ready,
    serve,
)

log = logging.getLogger("vistrack.preprocessing")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_service_args(parser, tracker_params=True)


def loop(node: Node, args: argparse.Namespace) -> None:
    state = ParamsInForce.from_args(args)
    state.publish_status(node)
    warm_up()
    node.subscribe(node.keys.params, latest=False)
    node.subscribe(node.keys.frame, latest=True)
    node.advertise(node.keys.pre_frame, reliable=False)

    def on_frame(payload: bytes) -> None:
        t0 = time.perf_counter()
        frame = decode_or_reject(Frame, payload, node, log)
        if frame is None:
            return
        pre = preprocess(frame.data, state.params)
        out = PreFrame(seq=frame.seq, stamp_ns=frame.stamp_ns, width=frame.width,
                       height=frame.height, data=pre.filtered, candidates=pre.candidates,
                       strength=pre.strength, params_id=state.params_id)
        node.publish(node.keys.pre_frame, out.encode(), reliable=False)
        node.status.observe_ms((time.perf_counter() - t0) * 1e3)

    ready(node)
    dispatch(node, {node.keys.params: lambda payload: state.apply(payload, node, log),
                    node.keys.frame: on_frame}, log)


def main(args: argparse.Namespace) -> int:
    return serve("preprocessing", args, loop)
