"""preprocessing: filter, gradient and THRES_PERCENT candidates for every camera frame.

Reads   ``vistrack/<robot>/camera/frame``          (latest only: a slow stage drops, counted)
        ``vistrack/<robot>/tuner/params``          (reliable: applied between frames)
        ``vistrack/<robot>/motion/demand``         (reliable: whether candidates are read)
Writes  ``vistrack/<robot>/preprocessing/frame``   (filtered frame + candidates + strength)
        ``vistrack/<robot>/preprocessing/done``    (its seq and stamp_ns, after it, while
                                                   anything subscribes: a file camera's pacing)

A pre-processed frame keeps its camera frame's ``seq``: downstream sees the camera's gaps, and
a ``seq`` that goes back (the camera restarted) tells motion-estimation to start a new track.
It keeps its ``cuts`` too (a count that grows at a ``--loop`` source's next pass, where a new
track starts), and the first frame after a cut always has its candidates: the new track
selects features on it.

The candidates (gradient strength and threshold, two thirds of the work) are computed only
while motion-estimation says on ``motion/demand`` that it will read them (a first frame, a
re-detection ahead); otherwise the frame goes out ``deferred``, without them, and
motion-estimation computes them from the filtered frame itself should it need them after
all. Until a demand arrives, and always with ``--candidates always``, every frame has them.

``--source ros2:TOPIC`` reads a ROS 2 camera's ``sensor_msgs/msg/Image`` (or
``CompressedImage``) topic over ``rmw_zenoh`` in place of ``camera/frame``, with no camera
process between the driver and the tracker: each image is converted as the camera's
``ros2:`` source converts it (:func:`~vistrack.services.camera.ros2cam.frame_of_payload`),
pre-processed, and then published as the ``camera/frame`` the auto-tuner and the tools read
(after ``preprocessing/frame``: off the tracker's path). A bad image is rejected, counted and
logged. Run no camera service alongside.
"""

from __future__ import annotations

import argparse
import logging
import time
from collections.abc import Callable
from contextlib import nullcontext

import numpy as np

from ...common import rmw_zenoh as rmw
from ...common import ros2types as r2
from ...common.bus import Node
from ...common.messages import (
    NO_CANDIDATES,
    NO_STRENGTH,
    Demand,
    Frame,
    MessageError,
    encode_pre_done,
    encode_pre_frame,
)
from ...common.params import TrackerParams
from ...common.synthetic import sequence
from ...common.vision import preprocess
from ...common.vision.preprocess import Grey, fix_defects, gaussian_filter
from ..camera import ros2cam
from ..kernels import late_compiles_logged, warm_up_kernels
from ..runtime import (
    ParamsInForce,
    Rehearsal,
    add_rehearsal_arg,
    add_service_args,
    decode_or_reject,
    dispatch,
    ready,
    reject,
    serve,
)
from ..usage import add_number

log = logging.getLogger("vistrack.preprocessing")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--source", default=FRAME_SOURCE, metavar="SOURCE",
                        help=f"{FRAME_SOURCE} (the camera service's frames, default) or "
                             "ros2:TOPIC (a ROS 2 camera's sensor_msgs/msg/Image topic over "
                             "rmw_zenoh, read directly, e.g. ros2:/camera/image_raw; "
                             "CompressedImage when the topic ends in /compressed; this "
                             "service then publishes camera/frame: run no camera)")
    add_number(parser, "--domain", lo=rmw.DOMAIN_RANGE[0], hi=rmw.DOMAIN_RANGE[1],
               integer=True, default=ros2cam.default_domain(), metavar="ID",
               help="ROS domain id of ros2:TOPIC, %(allowed)s (default: $ROS_DOMAIN_ID, "
                    "else 0)")
    parser.add_argument("--candidates", choices=("on-demand", "always"), default="on-demand",
                        help="compute the candidates of every frame (always), or only while "
                             "motion-estimation asks for them on motion/demand (on-demand, "
                             "the default: other frames go out deferred, without them)")
    add_service_args(parser, tracker_params=True)
    add_rehearsal_arg(parser)



#: ``--source`` of the camera service's frames.
FRAME_SOURCE = "camera/frame"


def check_args(args: argparse.Namespace) -> None:
    """ValueError naming a ``--source`` that is neither camera/frame nor ros2:TOPIC."""
    if args.source != FRAME_SOURCE:
        if not ros2cam.is_ros2(args.source):
            raise ValueError(f"--source {args.source!r}: expected {FRAME_SOURCE} or "
                             "ros2:TOPIC, e.g. ros2:/camera/image_raw")
        ros2cam.topic_of(args.source)


def _load_kernels(params: TrackerParams) -> None:
    """Load the kernels this service runs (pre-processing's, from numba's cache) before the
    first frame: those of a textured frame, read-only as decoded frames are, its candidates
    read as a frame that motion-estimation wants them for. Left to the first frame, the
    candidates' load (22 ms) had the next frame of a 30 fps camera overwritten at this
    service's latest-only input, beside a busy core."""
    (frame,) = sequence(1, size=(64, 64), seed=1)
    frame.flags.writeable = False
    pre = preprocess(frame, params)
    encode_pre_frame(seq=0, stamp_ns=0, data=pre.filtered, candidates=pre.candidates,
                     strength=pre.strength, params_id=0)


def loop(node: Node, args: argparse.Namespace) -> None:
    state = ParamsInForce.from_args(args)
    state.publish_status(node)
    # a first run's compile is logged, a cache load is not; from the cache, its own kernels
    warm_up_kernels(log.info, load=lambda: _load_kernels(state.params))
    always = getattr(args, "candidates", "always") == "always"
    wanted = True  # until motion-estimation says otherwise
    cuts: int | None = None  # the last frame's (camera/frame's cuts)
    node.subscribe(node.keys.params, latest=False)
    if not always:
        node.subscribe(node.keys.demand, latest=False)
    node.advertise(node.keys.pre_frame, reliable=False)
    node.advertise(node.keys.pre_done, reliable=True)
    node.status.extra["deferred"] = 0

    def on_demand(payload: bytes) -> None:
        nonlocal wanted
        msg = decode_or_reject(Demand, payload, node, log)
        if msg is not None and msg.candidates != wanted:
            wanted = msg.candidates
            log.debug("candidates %s from seq %d on", "wanted" if wanted else "deferred",
                      msg.seq)

    def process(frame: Frame, t0: float) -> None:
        nonlocal cuts
        pre = preprocess(frame.data, state.params)
        # a cut starts a new track downstream, which selects features: its candidates go
        # with it whatever the demand said
        cut, cuts = cuts is not None and frame.cuts != cuts, frame.cuts
        if wanted or cut:
            out = encode_pre_frame(seq=frame.seq, stamp_ns=frame.stamp_ns, data=pre.filtered,
                                   candidates=pre.candidates, strength=pre.strength,
                                   params_id=state.params_id, cuts=frame.cuts)
        else:
            out = encode_pre_frame(seq=frame.seq, stamp_ns=frame.stamp_ns, data=pre.filtered,
                                   candidates=NO_CANDIDATES, strength=NO_STRENGTH,
                                   params_id=state.params_id, deferred=True, cuts=frame.cuts)
            node.status.extra["deferred"] += 1
        node.publish(node.keys.pre_frame, out, reliable=node.answer_reliably)
        if node.has_subscribers(node.keys.pre_done):  # a file camera pacing its frames
            node.publish(node.keys.pre_done, encode_pre_done(seq=frame.seq,
                                                             stamp_ns=frame.stamp_ns),
                         reliable=node.answer_reliably)
        node.status.observe_ms((time.perf_counter() - t0) * 1e3)

    def on_frame(payload: bytes) -> None:
        t0 = time.perf_counter()
        frame = decode_or_reject(Frame, payload, node, log)
        if frame is not None:
            process(frame, t0)

    handlers: dict[str, Callable[[bytes], object]] = {
        node.keys.params: lambda payload: state.apply(payload, node, log),
        node.keys.demand: on_demand}
    if args.source == FRAME_SOURCE:
        node.subscribe(node.keys.frame, latest=True)
        handlers[node.keys.frame] = on_frame
        tiny = np.zeros((16, 16), np.uint8)
        tiny.flags.writeable = False  # as decoded frames come: the kernel they run

        def rehearse(payload: bytes) -> bool:
            """The frame's path on the last frame and a tiny one, nothing kept
            (:class:`Rehearsal`): decoded, filtered, encoded."""
            try:
                Frame.decode(payload)
            except MessageError:
                return False
            filtered = gaussian_filter(fix_defects(tiny), state.params.blur_sigma)
            encode_pre_frame(seq=0, stamp_ns=0, data=filtered, candidates=NO_CANDIDATES,
                             strength=NO_STRENGTH, params_id=state.params_id, deferred=True)
            return True

        ready(node)
        with late_compiles_logged(log):
            dispatch(node, handlers, log, rehearsal=None if args.no_rehearsal
                     else Rehearsal(node, node.keys.frame, rehearse, log))
        return
    topic = ros2cam.topic_of(args.source)
    typename = ros2cam.type_of(topic)
    key = rmw.topic_key(args.domain, topic, typename, "*")  # any type hash, as the camera
    node.subscribe(key, latest=True)
    node.advertise(node.keys.frame, reliable=False)
    seq = 0
    node.status.extra["frames"] = 0
    grey = Grey()  # 16-bit images: scaled by the depth of the camera's samples

    def on_image(payload: bytes) -> None:
        nonlocal seq
        t0 = time.perf_counter()
        try:
            frame = ros2cam.frame_of_payload(payload, typename, seq, grey=grey)
        except ValueError as e:
            reject(node, log, typename, e)
            return
        process(frame, t0)
        node.publish(node.keys.frame, frame.encode(), reliable=False)
        seq += 1
        node.status.extra["frames"] = seq

    # samples come on the publisher's key, with its own type hash: any key of the topic
    handlers = _AndTopic(handlers, key.rsplit("/", 1)[0] + "/", on_image)
    session = getattr(node, "session", None)  # the graph tokens need Zenoh; memory has none
    with rmw.Participant(session, rmw.Rmw(domain=args.domain, node=ros2cam.NODE_NAME)) \
            if session is not None else nullcontext() as participant:
        if participant is not None:
            participant.subscription(topic, typename, r2.type_hash(typename), rmw.QOS_SENSOR)
        log.info("ROS 2 camera read directly: %s (%s) on domain %d", topic, typename,
                 args.domain)
        ready(node)
        with late_compiles_logged(log):
            dispatch(node, handlers, log)


class _AndTopic(dict[str, Callable[[bytes], object]]):
    """``dispatch``'s handlers, and ``on_image`` for every key under ``prefix`` (a ROS 2
    topic's key up to its type hash)."""

    def __init__(self, handlers: dict[str, Callable[[bytes], object]], prefix: str,
                 on_image: Callable[[bytes], object]) -> None:
        super().__init__(handlers)
        self.prefix, self.on_image = prefix, on_image

    def __missing__(self, key: str) -> Callable[[bytes], object]:
        if key.startswith(self.prefix):
            return self.on_image
        raise KeyError(key)


def main(args: argparse.Namespace) -> int:
    return serve("preprocessing", args, loop, publishes_frames=True)
