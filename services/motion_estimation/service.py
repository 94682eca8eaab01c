"""motion-estimation: feature selection, SSD tracking (Eq. 1) and the estimate (Eq. 2).

Reads   ``vistrack/<robot>/preprocessing/frame``   (latest only: drops are counted)
        ``vistrack/<robot>/tuner/params``          (reliable: applied between frames)
Writes  ``vistrack/<robot>/motion/estimate``       (one per processed frame)
        ``vistrack/<robot>/motion/demand``         (reliable: when it changes, and every s)

Parameters are put in force between frames. Those that run kernels of their own (the largest
windows, whose sums need int64), which a cold cache would compile for up to half a minute,
stay pending (status ``extra``: ``params_pending``) while the kernels are made ready beside
the loop (:class:`~vistrack.services.kernels.KernelsAhead`); the parameters in force track the
frames meanwhile, and each estimate's ``params_id`` says which ones did.

The tracker is the library's :class:`~vistrack.common.vision.Tracker`, fed the filtered frame
and candidates computed upstream, so the pipeline computes exactly what ``vistrack track`` does.
Estimates keep the camera frame's ``seq``; when it goes back (the camera restarted), the
frame's ``cuts`` changes (a ``--loop`` source's next pass: its first frame does not follow its
last), or the frame size changes, the track starts again (``first: true``). A frame that comes
again, the same ``seq`` and ``stamp_ns`` as the one just tracked (a camera in lockstep sends a
frame again when its estimate was lost on the way back), is not tracked twice: the same
estimate is published again (status ``extra``: ``repeated``).

The tracker reads a frame's candidates only to select features (a first frame, a re-detection
once fewer than ``redetect_fraction * max_features`` survive). ``motion/demand`` tells
pre-processing whether the next frames need them (:func:`wants_candidates`). A frame that
comes ``deferred`` when the tracker does read them (a first re-detection, a new track) has them
computed here from its filtered frame with the same function and parameters: the estimates are
those of ``vistrack track`` either way, only where the work is done differs.
"""

from __future__ import annotations

import argparse
import collections
import logging
import time

import numpy as np

from ...common.bus import Node
from ...common.messages import Demand, Estimate, MessageError, PreFrame, encode_estimate
from ...common.params import TrackerParams
from ...common.vision import Preprocessed, Tracker
from ...common.vision import tracker as vision_tracker
from ...common.vision.preprocess import DeferredPreprocessed
from ..kernels import KernelsAhead, kernels_failed, late_compiles_logged, warm_up_kernels
from ..runtime import (
    ParamsInForce,
    ParamsUpdate,
    Rehearsal,
    add_rehearsal_arg,
    add_service_args,
    decode_or_reject,
    dispatch,
    ready,
    serve,
)

log = logging.getLogger("vistrack.motion_estimation")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_service_args(parser, tracker_params=True)
    add_rehearsal_arg(parser)


def estimate_message(e, *, seq: int, stamp_ns: int, params_id: int,
                     shape: tuple[int, int] | None = None, cuts: int = 0) -> Estimate:
    """The ``motion/estimate`` message of a library estimate; ``shape``: its frame's
    (height, width), sent as ``height`` and ``width``; ``cuts``: its frame's."""
    height, width = (None, None) if shape is None else shape
    return Estimate(seq=seq, stamp_ns=stamp_ns, npi=e.npi, xc=e.xc, yc=e.yc, xe=e.xe, ye=e.ye,
                    dx=e.dx, dy=e.dy, scale=e.scale, t_ms=e.t_ms, first=e.first,
                    valid=e.valid, features=e.features(), params_id=params_id,
                    width=width, height=height, cuts=cuts)


def estimate_payload(e, *, seq: int, stamp_ns: int, params_id: int,
                     shape: tuple[int, int] | None = None, cuts: int = 0) -> bytes:
    """``estimate_message(...).encode()``, byte for byte, built from the estimate's arrays
    without the message object (:func:`~vistrack.common.messages.encode_estimate`)."""
    height, width = (None, None) if shape is None else shape
    return encode_estimate(seq=seq, stamp_ns=stamp_ns, npi=e.npi, xc=e.xc, yc=e.yc, xe=e.xe,
                           ye=e.ye, dx=e.dx, dy=e.dy, scale=e.scale, t_ms=e.t_ms,
                           first=e.first, ids=e.ids, points=e.points, params_id=params_id,
                           valid=e.valid, width=width, height=height, cuts=cuts)


#: Frames over which a re-detection keeps candidates coming (``motion/demand``).
READ_WINDOW = 30
#: Seconds between reminders of the demand in force (a pre-processing that restarted).
DEMAND_REMIND_S = 1.0


def wants_candidates(npi: int, redetected: collections.deque[bool],
                     params: TrackerParams) -> bool:
    """Whether the next frames should come with their candidates: when fewer features than
    the re-detection threshold are left (the next frame selects, for sure), and while
    re-detections are frequent (one in the last :data:`READ_WINDOW` frames, a track's first
    frame aside), so that pre-processing computes them in its own process rather than
    motion-estimation on the frame's path. Otherwise a re-detection that comes (features
    left near the threshold can hover above it for hundreds of frames) has them computed
    here, on that frame alone."""
    return npi < params.redetect_fraction * params.max_features or any(redetected)


class DemandSignal:
    """Whether the next frames will need their candidates, published on ``motion/demand``
    when it changes and every :data:`DEMAND_REMIND_S` s."""

    def __init__(self, node: Node) -> None:
        self.node = node
        self.redetected: collections.deque[bool] = collections.deque(maxlen=READ_WINDOW)
        self.wanted = True
        self.seq = 0
        self.next_remind = 0.0

    def reset(self) -> None:
        self.redetected.clear()

    def after(self, tracker: Tracker, npi: int, redetected: bool, stamp_ns: int) -> None:
        """Decide and publish, once a frame has been tracked (and ``redetected`` or not)."""
        self.redetected.append(redetected)
        wanted = wants_candidates(npi, self.redetected, tracker.params)
        now = time.monotonic()
        if wanted != self.wanted or now >= self.next_remind:
            self.wanted = wanted
            self.next_remind = now + DEMAND_REMIND_S
            self.node.publish(self.node.keys.demand, Demand(
                seq=self.seq, stamp_ns=stamp_ns, candidates=wanted).encode(), reliable=True)
            self.seq += 1


def loop(node: Node, args: argparse.Namespace) -> None:
    state = ParamsInForce.from_args(args)
    state.publish_status(node)
    # a first run's compile is logged, a cache load is not
    warm_up_kernels(log.info, params=state.params)
    tracker = Tracker(state.params)
    node.subscribe(node.keys.params, latest=False)
    node.subscribe(node.keys.pre_frame, latest=True)
    node.advertise(node.keys.estimate, reliable=False)
    node.advertise(node.keys.demand, reliable=True)
    demand = DemandSignal(node)
    last_seq = -1
    last_cuts = 0  # the last frame's cuts (camera/frame's): another starts a new track
    # (seq, stamp_ns) of the frame last tracked, and its estimate: what a frame sent again gets
    answered: tuple[int, int, bytes] = (-1, -1, b"")
    last_npi, last_valid = 0, False  # the last estimate's, for the status
    last_est: vision_tracker.Estimate | None = None  # the last frame's, for a rehearsal
    warned_budget = -1  # the params_id whose frames were last said to be over budget

    ahead = KernelsAhead(log)
    pending: ParamsUpdate | None = None  # accepted, waiting for kernels of its own

    # params_id of the sets dropped because their kernels could not be made ready: their
    # reminders (params set repeats a set every second, the auto-tuner for good) are refused
    # in silence, not accepted, dropped and logged again each time (service review)
    dropped: set[int] = set()

    def on_params(payload: bytes) -> None:
        nonlocal pending
        update = state.accept(payload, node, log, pending)
        if update is None:
            return
        failed = ahead.failure(update.params)
        if failed is not None:
            if update.params_id not in dropped:
                dropped.add(update.params_id)
                node.status.reject(kernels_failed(update.params_id, failed))
                log.error("%s: refused; keeping params_id %d",
                          kernels_failed(update.params_id, failed), state.params_id)
            return
        pending = update
        if not put_in_force() and pending is not None:  # waiting, not dropped
            log.info("params_id %d needs kernels of its own: making them ready beside the "
                     "loop (on a cold cache up to half a minute); params_id %d stays in "
                     "force until then", update.params_id, state.params_id)
            node.status.extra["params_pending"] = update.params_id

    def put_in_force() -> bool:
        """Put the pending update in force once its kernels are loaded (at once when they
        are): never a frame, nor the loop, waits for a compile."""
        nonlocal pending
        if pending is None:
            return False
        if not ahead.ready(pending.params):
            failed = ahead.failure(pending.params)
            if failed is not None:  # never comes in force: said, and the set in force stays
                said = kernels_failed(pending.params_id, failed)
                node.status.error(f"{said}; keeping params_id {state.params_id}")
                log.error("%s: dropped; keeping params_id %d", said, state.params_id)
                dropped.add(pending.params_id)
                pending = None
                node.status.extra.pop("params_pending", None)
            return False
        state.commit(pending, node, log)
        tracker.set_params(state.params)
        pending = None
        node.status.extra.pop("params_pending", None)
        return True

    def on_frame(payload: bytes) -> None:
        nonlocal last_seq, last_cuts, answered, last_npi, last_valid, warned_budget, last_est
        t0 = time.perf_counter()
        if pending is not None:
            put_in_force()
        msg = decode_or_reject(PreFrame, payload, node, log)
        if msg is None:
            return
        if (msg.seq, msg.stamp_ns) == answered[:2]:
            node.publish(node.keys.estimate, answered[2], reliable=node.answer_reliably)
            node.status.extra["repeated"] = node.status.extra.get("repeated", 0) + 1
            return
        # decoded arrays are read-only views of the payload; numba would compile (and cache)
        # a second specialisation of every kernel for read-only inputs, 40 ms on frame one
        filtered = np.array(msg.data)
        # candidates pre-processed under another set (pre-processing puts a set in force at
        # once, this service once its kernels are ready, or never if they fail) are not this
        # set's: computed here from the filtered frame, as a deferred frame's are, so that the
        # estimate is the one its params_id names (a dropped set had 17 of 40 estimates differ
        # from vistrack track's: service review)
        pre = DeferredPreprocessed(filtered, state.params) \
            if msg.deferred or msg.params_id != state.params_id else \
            Preprocessed(filtered, msg.candidates, msg.strength)
        if msg.seq <= last_seq:
            log.info("camera restarted (seq %d after %d): new track", msg.seq, last_seq)
            tracker.reset()
        elif msg.cuts != last_cuts and tracker.frame_shape is not None:
            # the source started again (a --loop file's next pass): its first frame does not
            # follow the last, and tracked across the two it moved dx by the whole pass
            log.debug("cut at seq %d (the source started again): new track", msg.seq)
            tracker.reset()
        elif tracker.frame_shape not in (None, filtered.shape):
            # another camera, or the camera's size changed: checked here, not caught as the
            # tracker's ValueError, which hid a fault of ours as a size change
            log.warning("frame size %dx%d differs from the track's %dx%d: restarting the "
                        "track", filtered.shape[1], filtered.shape[0],
                        *tracker.frame_shape[::-1])
            tracker.reset()
        last_seq, last_cuts = msg.seq, msg.cuts
        redetections, over = tracker.redetections, tracker.over_budget
        est = tracker.update(pre, seq=msg.seq, t_start=t0)
        if tracker.over_budget > over and warned_budget != state.params_id:
            warned_budget = state.params_id
            log.warning("%s (params_id %d, %s; said once per params_id)",
                        vision_tracker.over_budget_said(msg.seq, tracker.over_budget - over),
                        state.params_id, state.params.factors())
        out = estimate_payload(est, seq=msg.seq, stamp_ns=msg.stamp_ns,
                               params_id=state.params_id, shape=filtered.shape, cuts=msg.cuts)
        last_est = est
        node.publish(node.keys.estimate, out, reliable=node.answer_reliably)
        answered = (msg.seq, msg.stamp_ns, out)
        if isinstance(pre, DeferredPreprocessed) and pre.computed:
            node.status.extra["candidates_here"] = \
                node.status.extra.get("candidates_here", 0) + 1
        demand.after(tracker, est.npi, tracker.redetections > redetections, msg.stamp_ns)
        node.status.observe_ms((time.perf_counter() - t0) * 1e3)
        tracker.settle()  # the work the estimate did not wait for (the camera's noise)
        last_npi, last_valid = est.npi, est.valid
        if node.status.extra_on_read is None:
            node.status.extra_on_read = tracked

    def tracked() -> dict[str, object]:
        """The tracker's counters, when the status is read (~9 us a frame when they were
        written every frame): features lost since the start, and those of them whose match
        was rejected, by reason (not ``rejected``: that is the status's count of bad
        messages)."""
        lost_by = tracker.lost_by
        return dict(
            npi=last_npi, valid=last_valid, lost=tracker.lost_total,
            rejected_features=tracker.rejected_total, redetections=tracker.redetections,
            exposure_steps=tracker.exposure_steps, zoom_warps=tracker.zoom_warps,
            noise=round(tracker.noise, 2), over_budget=lost_by["budget"],
            rejected_by={k: v for k, v in lost_by.items()
                         if k not in ("left", "cut", "budget")})

    def rehearse(payload: bytes) -> bool:
        """The frame's path on the last frame, nothing kept (:class:`Rehearsal`): its
        payload decoded, a search of two features, its estimate encoded."""
        est = last_est
        if est is None or not tracker.rehearse():
            return False
        try:
            PreFrame.decode(payload)
        except MessageError:
            return False
        estimate_payload(est, seq=est.seq, stamp_ns=0, params_id=state.params_id)
        return True

    def recover() -> None:
        # a frame that failed may have left the track half-updated: start a new one
        tracker.reset()
        demand.reset()

    def tick() -> None:
        # a pending set comes in force once its kernels are ready, frames or not: it waited
        # for the next frame, and on a pipeline with no camera (--camera none) params set
        # waited its 180 s and said the set may have been lost
        if pending is not None:
            put_in_force()

    ready(node)
    with late_compiles_logged(log):
        dispatch(node, {node.keys.params: on_params, node.keys.pre_frame: on_frame}, log,
                 tick=tick, recover=recover,
                 rehearsal=None if args.no_rehearsal
                 else Rehearsal(node, node.keys.pre_frame, rehearse, log))


def main(args: argparse.Namespace) -> int:
    return serve("motion_estimation", args, loop)
