"""auto-tuner: tune the tracker on a rolling buffer of recent frames, off the hot path.

Reads   ``vistrack/<robot>/camera/frame``     (latest only, into the rolling buffer while a
        tuning waits for it, else one every :data:`SCENE_SAMPLE_S` s for the scene signal; a
        frame sent again, the ``stamp_ns`` of the newest one buffered, is not buffered twice)
        ``vistrack/<robot>/motion/estimate``  (latest only, at most one every
        1/60 s between tunings: scene and distance watch)
        ``vistrack/<robot>/tuner/params``     (reliable: what users set, to keep params_id rising)
Writes  ``vistrack/<robot>/tuner/params``     (reliable)
        ``vistrack/<robot>/tuner/report``     (reliable)

The last ``--buffer`` frames (default 30) are kept. A tuning cycle (the 2^(5-1) design, its
analysis, the SEARCH_SIZE x CORR_SIZE sweep and the optimum: :func:`.sensitivity.tune`) runs
once the buffer is full, then again on a scene change or a distance change (:mod:`.triggers`:
thresholds, hysteresis, at least ``--min-interval`` s between cycles). It runs in a separate
worker process at idle priority (SCHED_IDLE: it only gets CPU time the pipeline leaves; ``nice
+10`` where that is not allowed), with one OpenCV thread, while this loop keeps receiving frames
and estimates. After every cycle the full ``tuner/report`` is published, with extra fields
``trigger`` (why it ran: "initial tuning", "scene change", "distance change"), ``changed``,
``params_id`` (in force after it) and ``cycle_s`` (its wall time here); ``tuner/params``
(source "tuner", reason = the trigger, ``params_id`` one above the largest seen) only when the
optimum differs from the parameters in force. A user's set is in force until a later cycle
finds a different optimum; one that arrives while a cycle runs wins over that cycle's result.

Frames are taken only as the triggers need them (:meth:`Triggers.collecting
<.triggers.Triggers.collecting>`): every frame from the moment a tuning waits only for its
buffer (at start, after a change once the interval has passed) until it starts, so the buffer
holds consecutive frames (taking every frame resumes on an empty buffer); otherwise the
subscription is undeclared after each frame and declared again :data:`SCENE_SAMPLE_S` s
later, so that
the router forwards, and this process receives, five frames a second for the scene signal
instead of the camera's rate (unpaced, the tuner taking every frame cost the pipeline a fifth
to a quarter of its CPU; at camera resolutions each frame is a megabyte or more).

The parameters in force are published again every second (same ``params_id``) for late
joiners. ``--no-tune`` keeps only that reminder (no frame is taken). Status ``extra``:
buffered, tunings, last_reason, tuning, last_cycle_s, pending, scene_distance, scale_ratio,
skipped, failed, every_frame (frames are all taken now, not sampled), tuning_for_s (the age
of the cycle in progress, else null), tuning_disabled (why, once WORKER_STARTS workers in a row
died before they were ready).

A buffer with too little texture to tune on (the reference windows track fewer than 3
features on most frames: a covered lens, a dark room) is not tuned on: every window size would
score zero error there, and its "optimum" would be the fastest window for nothing. The cycle
is skipped (a warning, ``skipped`` counted, the parameters kept) and due again once the buffer
has been refilled with new frames, ``--min-interval`` s after it at the earliest.
"""

from __future__ import annotations

import argparse
import collections
import itertools
import logging
import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import zenoh

from ...common.bus import Node, service_status
from ...common.messages import (
    Estimate,
    Frame,
    MessageError,
    Params,
    Report,
    next_params_id,
    pack,
)
from ...common.params import FACTORS, ParamError
from ...common.vision.tracker import MAX_GAP
from ..runtime import (
    NO_ESTIMATE,
    ParamsInForce,
    add_service_args,
    came_late,
    decode_or_reject,
    dispatch,
    ready,
    serve,
    starts_track,
)
from ..usage import add_number
from . import triggers as tr
from .sensitivity import (
    BUFFER_RANGE,
    DEFAULT_MEGAPIXELS,
    DEFAULT_STEP,
    DEFAULT_TOLERANCE,
    KEEP_WITHIN,
    MEGAPIXELS_RANGE,
    MIN_FRAMES,
    STEP_RANGE,
    TABLE4_FIXED,
    TOLERANCE_RANGE,
    frames_within,
)
from .worker import Worker

log = logging.getLogger("vistrack.auto_tuner")

# The parameters in force are published again this often (same params_id), so a service that
# starts or reconnects after the last change still learns them.
REMIND_S = 1.0
#: While no tuning waits for frames, one frame is taken this often, s, for the scene signal:
#: a change then counts after about 3 x this (its hysteresis), and a tuning needs a full
#: buffer of frames after it anyway (1 s at 30 fps).
SCENE_SAMPLE_S = 0.2
#: Estimates are watched at most one every this, s (latest only: a faster camera's are
#: sampled; at up to 60 fps every one is seen). Their signals are slow (a storm over 30
#: estimates, the accumulated scale), and an estimate taken woke this process: unpaced, at
#: 800 a second, that was most of its CPU. The loop sleeps out the period only while
#: estimates come faster than 1.5 periods apart: at 30 fps that sleep would be one more
#: wake-up an estimate, not one fewer.
ESTIMATE_PERIOD_S = 1.0 / 60.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_number(parser, "--buffer", lo=BUFFER_RANGE[0], hi=BUFFER_RANGE[1], integer=True,
               default=30, metavar="N",
               help="frames kept for the experiments, %(allowed)s (default 30)")
    add_number(parser, "--max-megapixels", lo=MEGAPIXELS_RANGE[0], hi=MEGAPIXELS_RANGE[1],
               default=DEFAULT_MEGAPIXELS, metavar="MP",
               help="work budget of a tuning: it runs on the latest buffered frames whose "
                    f"pixels fit, at least {MIN_FRAMES}; %(allowed)s (default "
                    f"{DEFAULT_MEGAPIXELS:g}: 30 frames of 1280x720, 15 of 1920x1080)")
    parser.add_argument("--no-tune", action="store_true",
                        help="never tune (no frame is taken): only remind the parameters in force")
    add_number(parser, "--tune-sweep-step", lo=STEP_RANGE[0], hi=STEP_RANGE[1], integer=True,
               default=DEFAULT_STEP, metavar="PX",
               help=f"sweep grid step, %(allowed)s (default {DEFAULT_STEP})")
    add_number(parser, "--tolerance", lo=TOLERANCE_RANGE[0], hi=TOLERANCE_RANGE[1],
               default=DEFAULT_TOLERANCE, metavar="PX",
               help="largest ex, ey against the reference windows the optimum may have, "
                    f"%(allowed)s px (default {DEFAULT_TOLERANCE})")
    add_number(parser, "--min-interval", lo=0, hi=86400, default=tr.DEFAULT_MIN_INTERVAL_S,
               metavar="S", help="least time between two tunings, %(allowed)s s "
                                 f"(default {tr.DEFAULT_MIN_INTERVAL_S:g})")
    parser.add_argument("--scale-band", type=float, nargs=2, default=tr.DEFAULT_SCALE_BAND,
                        metavar=("LO", "HI"), help="re-tune when the scale since the last "
                        "tuning leaves [LO, HI], 0 < LO < 1 < HI (default 0.8 1.25)")
    add_number(parser, "--scene-threshold", lo=0.01, hi=2,
               default=tr.DEFAULT_SCENE_THRESHOLD, metavar="X",
               help="scene distance (0 same view, ~1 another scene) that re-tunes, "
                    f"%(allowed)s (default {tr.DEFAULT_SCENE_THRESHOLD})")
    add_service_args(parser, tracker_params=True)


def check_args(args: argparse.Namespace) -> None:
    """``--scale-band``, the one check across values (the others are declared with their
    flags)."""
    check_flags(args)


def check_flags(args: argparse.Namespace) -> tr.TriggerConfig:
    """The trigger configuration; ValueError names the flag, its value and the range."""
    lo, hi = args.scale_band
    if not (0 < lo < 1 < hi and math.isfinite(hi)):
        raise ValueError(f"--scale-band {lo:g} {hi:g} is out of range: allowed 0 < LO < 1 < HI")
    return tr.TriggerConfig(buffer=args.buffer, min_interval_s=args.min_interval,
                            scale_band=(lo, hi), scene_threshold=args.scene_threshold)


class AutoTuner:
    """The service between messages: the buffer, the parameters in force, the triggers."""

    def __init__(self, node: Node, args: argparse.Namespace, config: tr.TriggerConfig,
                 ask_in_force: Callable[[], dict[str, Any] | None] | None = None) -> None:
        self.node, self.args = node, args
        # the set motion-estimation runs, from its status (a restarted tuner takes it on)
        self.ask_in_force = ask_in_force if ask_in_force is not None else \
            (lambda: in_force_of(node))
        self.state = ParamsInForce.from_args(args)
        self.frames: collections.deque[tuple[np.ndarray, int]] = collections.deque(
            maxlen=args.buffer)
        # frames collected since the buffer began, up to --buffer: what it offers a cycle,
        # of which it keeps only those the cycle runs on (the latest within the work budget)
        self.offered = 0
        self.triggers = tr.Triggers(config)
        self.worker: Worker | None = None
        self.params_seq, self.report_seq = itertools.count(), itertools.count()  # per key
        # largest params_id seen in estimates (a restarted tuner lags), until motion-estimation
        # is asked: it runs that set (taken on), or another (what it runs counts)
        self.seen_id = 0
        self._refuted = -1  # the last params_id an estimate claimed that was not confirmed
        self._lagging = False  # reminders held back: the estimates run a newer set (announce)
        self._asked_for = -1  # the seen_id motion-estimation was last asked the set of
        self.last_estimate = NO_ESTIMATE  # (seq, stamp_ns) of the last estimate watched
        self.last_cuts = 0  # the cuts of the last estimate watched (a change: a cut)
        self.started = 0.0
        self.reason = ""
        self.id_at_start = 0
        self.stamp_ns = 0
        self._said: set[str] = set()  # the changes logged at INFO since the last start
        self.every_frame = False  # frames are taken one after the other into the buffer
        self.last_seq = -1  # seq of the newest buffered frame
        self.start_failures = 0  # workers in a row that died before they were ready
        self._slow_said = False  # the cycle in progress was said to be slow
        self.next_sample = 0.0  # when the next frame for the scene signal is taken
        self.watched = -math.inf  # when the last estimate was taken (monotonic)
        self.fast = False  # it came less than 1.5 ESTIMATE_PERIOD_S after the one before
        node.status.extra.update(buffered=0, tunings=0, last_reason="", tuning=False,
                                 last_cycle_s=None, skipped=0, every_frame=False)

    def announce(self, reason: str | None = None) -> bool:
        """Publish the parameters in force: a new ``params_id`` from the tuner when ``reason``
        is given, else again as they are (a reminder for late joiners). False when there is
        no new ``params_id`` to give (logged, in the status): nothing is published."""
        st = self.state
        if reason is not None:
            if self.seen_id > st.params_id:
                self._take_on_in_force()  # asked once a claim: what runs, not what was said
            try:
                new_id = next_params_id(max(st.params_id, self.seen_id))
            except MessageError as e:
                self.node.status.error(e)
                log.error("%s (%s)", e, reason)
                return False
            st.params_id = new_id
            st.source, st.reason = "tuner", reason
            st.publish_status(self.node)
            log.info("publishing params_id %d (%s): %s", st.params_id, reason,
                     st.params.factors())
        elif self.seen_id > st.params_id and not self._take_on_in_force():
            # the estimates run a newer set than this tuner knows (one it missed before it
            # subscribed: a recording's, replayed while it started): reminding of its older
            # one would only be refused as stale by every service, every second
            if not self._lagging:
                self._lagging = True
                log.info("params_id %d is in force (seen in the estimates), newer than this "
                         "tuner's %d: no reminders until a tuning or a set", self.seen_id,
                         st.params_id)
            return True
        self._lagging = False
        source = st.source if st.source in ("tuner", "user") else "tuner"
        msg = Params.from_tracker_params(st.params, seq=next(self.params_seq),
                                         stamp_ns=time.time_ns(), params_id=st.params_id,
                                         source=source, reason=st.reason)
        self.node.publish(self.node.keys.params, msg.encode(), reliable=True)
        return True

    def start_up(self) -> None:
        """Announce the flags' set as params_id 1, unless motion-estimation already runs a
        set (this tuner was restarted): that one is taken on and reminded of. A restarted
        tuner announced its flags as params_id 1 all the same, which every service refused
        as stale (a warning each, and counted as rejected) before the take-on."""
        got = self.ask_in_force()
        given = got.get("params_id") if got else None
        if isinstance(given, int) and not isinstance(given, bool) and given >= 1:
            self.seen_id = max(self.seen_id, given)
            if self._take_on_in_force(got):
                self.announce()
                return
        self.announce("start-up (flags)")

    def _take_on_in_force(self, got: dict[str, Any] | None = None) -> bool:
        """Take on the set motion-estimation runs where it is the newest seen in the
        estimates (its values, ``params_id``, source and reason): a tuner restarted after a
        user's set knew only its flags' values. It reminded no one, so a service restarted
        after it ran its own flags, and its next tuning published its flags' max_features,
        thres_percent and ungroup_size with the windows it chose: the user's set was gone,
        with no line saying so. Reminding of the set taken on puts a restarted service back
        on it. False where it cannot be asked, or runs another set.

        An estimate's ``params_id`` is a claim until the tracker's stages confirm it
        (:func:`in_force_of`: the newer of motion-estimation's and pre-processing's sets):
        where they answer with another set, that one counts (taken on if newer than this
        tuner's, else the claim is dropped, said once). One estimate with params_id
        2^53 - 1 from any client (a forged one, or a recording's estimates replayed beside
        the live pipeline) stopped the reminders for good, so a restarted motion-estimation
        stayed on its flags, and left no newer id for any tuning."""
        if got is None:
            if self._asked_for == self.seen_id:  # once a set: the query waits up to 0.5 s
                return False
            got = self.ask_in_force()
        self._asked_for = self.seen_id
        runs = got.get("params_id") if got is not None else None
        if got is None or not isinstance(runs, int) or isinstance(runs, bool) or runs < 0:
            return False  # no answer: the claim stands (reminders held back)
        if runs != self.seen_id:
            st = self.state
            log.warning("estimates carried params_id %d, but the tracker's stages run %d: "
                        "%s (a recording's estimates replayed beside this pipeline, or a "
                        "forged one?)", self.seen_id, runs,
                        f"taking on {runs}" if runs > st.params_id
                        else f"not taken, this tuner's {st.params_id} stays in force")
            self._refuted, self.seen_id, self._asked_for = self.seen_id, runs, runs
            if runs <= st.params_id:
                self.seen_id = st.params_id
                self._lagging = False
                return True
        st = self.state
        try:
            params = st.params.replace(**{k: got[k] for k in FACTORS})
        except (KeyError, TypeError, ParamError):
            return False
        st.params, st.params_id = params, int(got["params_id"])
        st.source, st.reason = str(got.get("source", "tuner")), str(got.get("reason", ""))
        st.publish_status(self.node)
        self._lagging = False
        log.info("took on params_id %d from the tracker's stages (%s, %s): %s", st.params_id,
                 st.source, st.reason or "no reason given", params.factors())
        return True

    def on_params(self, payload: bytes) -> None:
        """A user's set is in force now, and so is a tuner's with a newer ``params_id`` than
        this one's (a recording's replayed, another auto-tuner's): the services apply it, and
        this one's reminders of an older id would be refused by each, every second (a
        replayed recording's id 2 against a fresh tuner's 1: 128 warnings a minute). Its own,
        echoed back, and a tuner's older ones are not news."""
        msg = decode_or_reject(Params, payload, self.node, log)
        if msg is not None and (msg.source != "tuner" or msg.params_id > self.state.params_id):
            self.state.apply(payload, self.node, log)

    def take_frames(self, now: float) -> None:
        """Subscribe to frames as the triggers need them at monotonic time ``now``: every
        frame while a tuning waits for its buffer (which then starts again: the frames
        before were samples, not consecutive), else one frame every SCENE_SAMPLE_S (see
        :meth:`on_frame`); none without a worker."""
        node, key = self.node, self.node.keys.frame
        if self.worker is None:
            node.unsubscribe(key)
            return
        collecting = self.triggers.collecting(now)
        if collecting != self.every_frame:
            self.every_frame = collecting
            node.status.extra["every_frame"] = collecting
            if collecting:
                self.frames.clear()
                self.offered = 0
                self.triggers.restart()
                node.status.extra["buffered"] = 0
        if (collecting or now >= self.next_sample) and not node.subscribed(key):
            node.subscribe(key, latest=True)

    def on_frame(self, payload: bytes) -> None:
        t0 = time.perf_counter()
        msg = decode_or_reject(Frame, payload, self.node, log)
        if msg is None:
            return
        if not self.every_frame:  # a sample for the scene signal: the next one in a while
            self.node.unsubscribe(self.node.keys.frame)
            self.next_sample = time.monotonic() + SCENE_SAMPLE_S
        elif not self._buffer(msg):
            return  # sent again (a camera in lockstep whose estimate was lost): buffered
        if self.worker is not None:
            self._changed(self.triggers.frame(msg.data))
            self.node.status.extra["scene_distance"] = round(self.triggers.distance, 3)
        self.node.status.observe_ms((time.perf_counter() - t0) * 1e3)

    def _buffer(self, msg: Frame) -> bool:
        """Append the frame of ``msg`` to the rolling buffer; False if it is the newest one
        already there (the same ``stamp_ns``)."""
        # a read-only view of the payload, kept as it is: a received payload is bytes,
        # never reused, and a copy of every frame cost the loop 64 KiB a frame
        pixels = msg.data
        if self.frames and self.frames[-1][1] == msg.stamp_ns:
            return False
        if self.frames and self.frames[-1][0].shape != pixels.shape:
            self.frames.clear()  # another camera: one tuning runs on one frame size
            self.offered = 0
        elif self.frames and (msg.seq <= self.last_seq or (
                msg.seq - self.last_seq > MAX_GAP
                and msg.stamp_ns - self.frames[-1][1] > BREAK_S * 1e9)):
            # a camera restarted (seq back), another one, or frames missed for a while: the
            # buffer's frames are not consecutive with this one, and a tuning on both sides
            # of the break ran on two scenes (19 of one, 11 of another) and took them for
            # one reference. A pending tuning waits for a full buffer again. (Frames skipped
            # by an unpaced pipeline's latest-only delivery come within BREAK_S.)
            log.info("frames broke off (seq %d after %d): the buffer starts again",
                     msg.seq, self.last_seq)
            self.frames.clear()
            self.offered = 0
            self.triggers.restart()
        self.last_seq = msg.seq
        self.frames.append((pixels, msg.stamp_ns))
        self.offered = min(self.offered + 1, self.args.buffer)
        # only the frames a cycle runs on are kept (the latest within --max-megapixels): a
        # buffer of 1000 frames of 4096x4096 held 16.8 GB for cycles that run on 4 of them
        keep = frames_within(self.args.buffer, pixels.shape[:2], self.args.max_megapixels)
        while len(self.frames) > keep:
            self.frames.popleft()
        self.node.status.extra["buffered"] = len(self.frames)
        return True

    def on_estimate(self, payload: bytes) -> None:
        now = time.monotonic()
        self.fast, self.watched = now - self.watched < 1.5 * ESTIMATE_PERIOD_S, now
        msg = decode_or_reject(Estimate, payload, self.node, log)
        if msg is None or self.worker is None:
            return
        if msg.params_id != self._refuted:  # the same claim again is not asked about again
            self.seen_id = max(self.seen_id, msg.params_id)
        if came_late(msg, self.last_estimate):  # an old one after a newer: not a new track
            return
        # one estimate in ESTIMATE_PERIOD_S is watched: a new track's first may not be
        first = starts_track(msg, self.last_estimate)
        # a change of the source's cuts since the last estimate watched: it started again
        cut = self.last_estimate != NO_ESTIMATE and msg.cuts != self.last_cuts
        self.last_estimate = (msg.seq, msg.stamp_ns)
        self.last_cuts = msg.cuts
        self._changed(self.triggers.estimate(first=first, npi=msg.npi, scale=msg.scale,
                                             ids={f[0] for f in msg.features}, cut=cut))
        self.node.status.extra["scale_ratio"] = round(self.triggers.ratio, 4)

    def _changed(self, reason: str | None) -> None:
        """Log a change the triggers saw (``reason``), with what it was seen in: at INFO the
        first time that kind of change is seen since the last tuning started, else at DEBUG
        (a storm of lost features goes on for seconds, one change every few estimates)."""
        pending = self.triggers.pending
        if reason is not None:
            level = logging.DEBUG if reason in self._said else logging.INFO
            self._said.add(reason)
            log.log(level, "%s seen: %s; tuning pending: %s", reason, self.triggers.why,
                    pending)
        self.node.status.extra["pending"] = pending

    def tick(self, now: float) -> None:
        """Collect a finished cycle, start one when due, take frames as needed (only between
        messages: cheap)."""
        self.take_frames(now)
        if self.worker is None:
            return
        try:
            result = self.worker.poll()
            if self.worker.ready:
                self.start_failures = 0
        except (EOFError, OSError) as e:
            self.node.status.error(f"tuning worker died: {e!r}")
            self.worker.close()
            if not self.worker.ready:
                self.start_failures += 1
            if self.start_failures >= WORKER_STARTS:  # it cannot start: retrying would spin
                log.error("tuning worker died at start-up %d times in a row (last: %r): "
                          "tuning disabled", self.start_failures, e)
                self.worker = None
                self.every_frame = False
                self.node.unsubscribe(self.node.keys.frame)
                self.node.status.extra.update(tuning=False, every_frame=False, pending=None,
                                              tuning_disabled=f"the tuning worker died at "
                                              f"start-up {self.start_failures} times: {e!r}")
                self.node.status.error(f"tuning disabled: the tuning worker died at start-up "
                                       f"{self.start_failures} times in a row ({e!r})")
                return
            log.error("tuning worker died (%r): starting another", e)
            self.worker = Worker()
            result = ("error", "worker died") if self.triggers.running else None
        if result is not None:
            self._finish(result, now)
        elif self.triggers.running:
            # how long the cycle in progress has run: a slow one (a minute at 1280x720 on a
            # shaking camera) and a stuck worker looked the same, tuning true and nothing else
            running = now - self.started
            self.node.status.extra["tuning_for_s"] = round(running, 1)
            if running >= SLOW_CYCLE_S and not self._slow_said:
                self._slow_said = True
                log.warning("tuning (%s) has run for %.0f s (its worker, pid %s, at idle "
                            "priority: a busy machine, or a stopped worker?)", self.reason,
                            running, self.worker.pid)
        reason = self.triggers.due(now)
        if reason is not None and self.worker.ready and len(self.frames) >= 2:
            self.triggers.started()
            self._said.clear()
            self.started, self.reason, self.id_at_start = now, reason, self.state.params_id
            self.stamp_ns = self.frames[-1][1]
            params = self.state.params
            self.worker.submit({"frames": [f for f, _ in self.frames],
                                "offered": self.offered, "base": params,
                                # the other factors as in force: the sweep's own default is
                                # Table 4's, and its optimum put those back (a user's
                                # max_features 150 became 100 at the next tuning)
                                "fixed": {k: getattr(params, k) for k in TABLE4_FIXED},
                                # kept where about as good as the optimum (TuneResult.keeps)
                                "windows": (params.search_size, params.corr_size),
                                "tolerance": self.args.tolerance,
                                "step": self.args.tune_sweep_step,
                                "max_megapixels": self.args.max_megapixels})
            self.node.status.extra.update(tuning=True, pending=None, tuning_for_s=0.0)
            self._slow_said = False
            log.info("tuning (%s) on %d frames%s", reason, len(self.frames),
                     "" if len(self.frames) == self.offered else
                     f" (the latest of {self.offered} within --max-megapixels)")

    def _finish(self, result: tuple, now: float) -> None:
        extra = self.node.status.extra
        cycle = now - self.started
        extra.update(tuning=False, last_cycle_s=round(cycle, 3), tuning_for_s=None)
        if result[0] == "skipped":  # a covered lens, a dark room: again on new frames
            self.triggers.finished(now, ok=False, refill=True)
            extra.update(skipped=extra.get("skipped", 0) + 1, pending=self.triggers.pending)
            log.warning("tuning (%s) skipped: %s", self.reason, result[1])
            return
        if result[0] != "ok":
            self.triggers.finished(now, ok=False)
            # due again: said now, not at the next frame (there may be none for a while)
            extra.update(failed=extra.get("failed", 0) + 1, pending=self.triggers.pending)
            self.node.status.error(f"tuning failed: {result[1]}")
            log.error("tuning (%s) failed: %s", self.reason, result[1])
            return
        self.triggers.finished(now)
        _, report, optimum, about_as_good = result
        st = self.state
        # the windows are what a tuning chooses; the rest stays as in force
        new = st.params.replace(search_size=optimum["search_size"],
                                corr_size=optimum["corr_size"])
        user_meanwhile = st.params_id != self.id_at_start
        kept = new != st.params and about_as_good
        changed = new != st.params and not user_meanwhile and not kept
        unannounced = False
        if changed:
            old, st.params = st.params, new
            if not self.announce(self.reason):
                st.params, changed, unannounced = old, False, True
        extra.update(tunings=extra["tunings"] + 1, last_reason=self.reason)
        log.info("tuning (%s) done in %.1f s: optimum %s%s", self.reason, cycle, optimum,
                 "" if changed else " (a user's set arrived meanwhile: kept)" if user_meanwhile
                 else f" (the windows in force, {st.params.search_size}/"
                      f"{st.params.corr_size}, are within the tolerance and "
                      f"{100 * KEEP_WITHIN:.0f} % of its time: kept)"
                 if kept and report.get("within_tolerance", True)
                 else f" (no swept window within the tolerance; the windows in force, "
                      f"{st.params.search_size}/{st.params.corr_size}, are within it of the "
                      "closest: kept)" if kept
                 else f" (not published: params_id {st.params_id} in force is the largest a "
                      "message may carry; restart the pipeline to count from 0 again)"
                 if unannounced else " (already in force)")
        self._publish_report(report, trigger=self.reason, changed=changed, cycle_s=cycle)

    def _publish_report(self, report: dict[str, Any], **extra: Any) -> None:
        """The whole report (contract fields and the extras readers may ignore), checked to
        decode within the readers' limits before it goes out."""
        seq = next(self.report_seq)
        fields = {f: report[f] for f in ("design", "factors", "order", "responses", "effects",
                                         "significant", "optimum", "sweep")}
        try:
            Report(seq=seq, stamp_ns=self.stamp_ns, **fields)
            payload = pack({"seq": seq, "stamp_ns": self.stamp_ns, **report, **extra,
                            "params_id": self.state.params_id})
            Report.decode(payload)
        except MessageError as e:
            self.node.status.error(e)
            log.error("tuner/report not published: %s", e)
            return
        self.node.publish(self.node.keys.report, payload, reliable=True)


#: Workers in a row that may die before they are ready (a start-up that fails, or one killed)
#: before tuning is disabled: one killed while it warmed up disabled it for good.
WORKER_STARTS = 3
#: A cycle running this long, s, is said in the log once (its age is ``extra.tuning_for_s``).
SLOW_CYCLE_S = 120.0
#: Frames missed (``seq`` jumping by more than the tracker's MAX_GAP: beyond it its
#: prediction is a guess) over more than BREAK_S s break the buffer's run of consecutive
#: frames (:meth:`AutoTuner._buffer`).
BREAK_S = 0.5
#: How long a restarted tuner waits for each tracker stage's status (the set in force), s
IN_FORCE_QUERY_S = 0.5
#: The services whose parameters in force a tuner asks for: the tracker's two stages
IN_FORCE_OF = ("motion_estimation", "preprocessing")


def in_force_of(node: Node) -> dict[str, Any] | None:
    """The newest parameters the tracker's stages run (motion-estimation's or
    pre-processing's status ``params``: the factors, ``params_id``, ``source``, ``reason``;
    the larger ``params_id``), asked over the node's Zenoh session; None where there is
    none (an in-process node) or no answer. Motion-estimation alone was asked: where it
    and the tuner restarted together, it ran its flags, the tuner took those on, and its
    next set reused the params_id of the user's set pre-processing still ran, which refused
    it for good (two sets under one id)."""
    session = getattr(node, "session", None)
    if session is None:
        return None
    newest: dict[str, Any] | None = None
    for service in IN_FORCE_OF:
        try:
            status = service_status(session, node.keys, service, IN_FORCE_QUERY_S)
        except zenoh.ZError:  # the session is closing: the tuner goes on as it was
            return newest
        params = status.get("params") if status is not None else None
        given = params.get("params_id") if isinstance(params, dict) else None
        if isinstance(given, int) and not isinstance(given, bool) and (
                newest is None or given > newest["params_id"]):
            newest = params
    return newest


def loop(node: Node, args: argparse.Namespace) -> None:
    tuner = AutoTuner(node, args, check_flags(args))
    node.subscribe(node.keys.params, latest=False)
    node.subscribe(node.keys.estimate, latest=True)
    handlers = {node.keys.params: tuner.on_params, node.keys.frame: tuner.on_frame,
                node.keys.estimate: tuner.on_estimate}
    tuner.worker = None if args.no_tune else Worker()  # warms up while the loop runs
    tuner.take_frames(time.monotonic())  # the initial tuning's buffer, before ready
    last_announce = 0.0

    def tick() -> None:
        """Between inputs: remind the parameters in force, collect and start tunings, pace
        the estimates watched."""
        nonlocal last_announce
        now = time.monotonic()
        if now - last_announce >= REMIND_S:
            tuner.announce()
            last_announce = now
        tuner.tick(now)
        if tuner.fast and not tuner.every_frame:  # the next estimate no sooner than that
            wait = tuner.watched + ESTIMATE_PERIOD_S - time.monotonic()
            if wait > 0:
                node.sleep(wait)

    try:
        node.advertise(node.keys.params, reliable=True)
        node.advertise(node.keys.report, reliable=True)
        ready(node)
        tuner.start_up()
        last_announce = time.monotonic()
        dispatch(node, handlers, log, tick=tick)
    finally:
        if tuner.worker is not None:
            tuner.worker.close()


def main(args: argparse.Namespace) -> int:
    return serve("auto_tuner", args, loop)
