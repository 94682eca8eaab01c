"""auto-tuner: keep a rolling buffer of recent frames and publish the parameters in force.

Reads   ``vistrack/<robot>/camera/frame``     (latest only, into the rolling buffer)
        ``vistrack/<robot>/motion/estimate``  (latest only: scene and distance watch)
        ``vistrack/<robot>/tuner/params``     (reliable: what users set, to keep params_id rising)
Writes  ``vistrack/<robot>/tuner/params``     (reliable)
        ``vistrack/<robot>/tuner/report``     (reliable)
"""

from __future__ import annotations

import argparse
import collections
import logging
import time

import numpy as np

from ...common.bus import Node
from ...common.messages import Frame, MessageError, Params
from ..runtime import ParamsInForce, add_service_args, ready, serve

log = logging.getLogger("vistrack.auto_tuner")

# The parameters in force are published again this often (same params_id), so a service that
# starts or reconnects after the last change still learns them.
REMIND_S = 1.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--buffer", type=int, default=30, metavar="N",
                        help="frames kept for the experiments (default 30)")
    add_service_args(parser, tracker_params=True)


def announce(node: Node, state: ParamsInForce, seq: int, reason: str | None = None) -> None:
    """Publish the parameters in force: as a new ``params_id`` from the tuner when ``reason``
    is given, else again as they are (a reminder for late joiners)."""
    if reason is not None:
        state.params_id += 1
        state.source, state.reason = "tuner", reason
        state.publish_status(node)
        log.info("publishing params_id %d (%s): %s", state.params_id, reason,
                 state.params.factors())
    msg = Params.from_tracker_params(state.params, seq=seq, stamp_ns=time.time_ns(),
                                     params_id=state.params_id, source=state.source
                                     if state.source in ("tuner", "user") else "tuner",
                                     reason=state.reason)
    node.publish(node.keys.params, msg.encode(), reliable=True)


def loop(node: Node, args: argparse.Namespace) -> None:
    if not 2 <= args.buffer <= 1000:
        raise SystemExit(f"vistrack auto-tuner: error: --buffer {args.buffer} is out of range: "
                         "allowed 2..1000")
    state = ParamsInForce.from_args(args)
    frames: collections.deque[np.ndarray] = collections.deque(maxlen=args.buffer)
    node.subscribe(node.keys.params, latest=False)
    node.subscribe(node.keys.frame, latest=True)
    node.subscribe(node.keys.estimate, latest=True)
    ready(node)
    seq = 0
    announce(node, state, seq, "initial")
    seq += 1
    last_announce = time.monotonic()
    while not node.stop.is_set():
        if time.monotonic() - last_announce >= REMIND_S:
            announce(node, state, seq)
            seq += 1
            last_announce = time.monotonic()
        item = node.recv(timeout=0.1)
        if item is None:
            continue
        key, payload = item
        if key == node.keys.params:
            try:
                msg = Params.decode(payload)
            except MessageError as e:
                node.status.reject(e)
                log.error("rejected tuner/params: %s", e)
                continue
            if msg.source != "tuner":  # a user's set: it is what is in force now
                state.apply(payload, node, log)
        elif key == node.keys.frame:
            try:
                frame = Frame.decode(payload)
            except MessageError as e:
                node.status.reject(e)
                log.error("rejected camera/frame: %s", e)
                continue
            frames.append(np.array(frame.data))  # own the pixels: the payload is reused
            node.status.extra["buffered"] = len(frames)


def main(args: argparse.Namespace) -> int:
    return serve("auto_tuner", args, loop)
