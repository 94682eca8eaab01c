"""What every service process shares: flags, logging, the session, parameters in force, and
what happens when something goes wrong.

A service module defines ``loop(node, args)`` and calls :func:`serve` from its ``main``; this
keeps each ``service.py`` to its loop. A loop that consumes inputs hands them to
:func:`dispatch`, a map from key to handler: an exception raised while handling one input is
caught there (:class:`Faults`), counted in the status (``failed``), logged with the key and
``seq``, and the loop goes on to the next input. Anything else that raises ends the process
at once (:func:`serve`), and the launcher restarts it.
"""

from __future__ import annotations

import argparse
import collections
import faulthandler
import gc
import logging
import os
import re
import signal
import sys
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, NoReturn, TypeVar

import cv2
import numpy as np

from ..common.bus import (
    STOP_SIGNALS,
    SUPERVISED_ENV,
    BusError,
    Node,
    ZenohNode,
    add_zenoh_args,
    check_connected,
    config_from_args,
    install_signal_handlers,
    shm_pool_at_open,
)
from ..common.keys import key_suffix
from ..common.messages import Estimate, MessageError, Params, peek_seq
from ..common.params import ParamError, TrackerParams
from . import threads
from .usage import add_param_flags, params_from_args, print_error

log = logging.getLogger("vistrack")

LOG_FORMAT = "%(asctime)s.%(msecs)03d %(levelname)s %(name)s: %(message)s"

#: Longest wait for the Zenoh session to close when the process ends, s: past it the process
#: ends anyway and the operating system closes its sockets (peers see the links drop).
CLOSE_S = 0.3
#: Longest time from a stop request (SIGTERM, SIGINT) to the loop's return, s: past it the
#: process ends without waiting for the loop (stuck in a long computation, say).
STOP_DEADLINE_S = 0.5


def setup_logging(level: str = "info") -> None:
    logging.basicConfig(level=getattr(logging, level.upper(), logging.INFO), format=LOG_FORMAT,
                        datefmt="%H:%M:%S", stream=sys.stderr, force=True)


def add_service_args(parser: argparse.ArgumentParser, *, tracker_params: bool = False) -> None:
    """Zenoh flags, ``--log-level``, and optionally the initial tracker parameters."""
    add_zenoh_args(parser)
    parser.add_argument("--log-level", default="info",
                        choices=("debug", "info", "warning", "error"),
                        help="log lines at this level and above (default info)")
    if tracker_params:
        add_param_flags(parser)


def serve(service: str, args: argparse.Namespace,
          loop: Callable[[Node, argparse.Namespace], int | None], *,
          publishes_frames: bool = False) -> NoReturn:
    """Open the service's Zenoh node, run ``loop`` until it returns or SIGINT/SIGTERM, close
    the session, and end the process with the loop's exit code. ``publishes_frames`` (64 KiB
    at 256x256, megabytes at camera resolutions): Zenoh's shared-memory pool is made when the
    session opens (:func:`~vistrack.common.bus.shm_pool_at_open`).

    The process ends promptly whatever happens (the launcher's restart waits for it):

    * an exception ``loop`` lets out (a fault outside the per-message path: inputs are
      isolated by :func:`dispatch`) is logged with its traceback and the exit code is 1;
    * a stop request ends the process within :data:`STOP_DEADLINE_S` + :data:`CLOSE_S` s even
      if the loop does not return (it is watched from a thread woken by the signal itself,
      so a loop inside a long computation does not delay it);
    * a fatal signal (SIGSEGV, SIGABRT, ...) prints every thread's Python stack
      (:mod:`faulthandler`) and the default action ends the process;
    * the session is closed, but for :data:`CLOSE_S` s at most, and the interpreter's own
      teardown is skipped (:func:`end_process`): freeing numba's and LLVM's objects took 0.3
      to 2.6 s, and a crash was seen to take 5 s to end under load.
    """
    setup_logging(args.log_level)
    faulthandler.enable()
    logger = logging.getLogger(f"vistrack.{service}")
    # One thread of OpenCV per service: the pipeline's parallelism is its processes. OpenCV's
    # own pool splits a 256x256 filter across threads that then spin waiting for work, which
    # cost pre-processing 240 us of CPU a frame on 2 cores shared by six processes.
    cv2.setNumThreads(1)
    command = service.replace("_", "-")
    try:
        if hasattr(args, "max_features"):  # the tracker parameter flags: check before Zenoh
            params_from_args(args)
        conf = config_from_args(args)
        if publishes_frames:
            conf = shm_pool_at_open(conf)
    except (BusError, ParamError) as e:
        print_error(command, e)
        end_process(2)
    try:
        # the liveliness token once ready (see ready()): a launcher that waits for it then
        # knows the service takes input, however long its warm-up took
        node = ZenohNode(service, conf, args.robot, alive_at_open=False)
    except BusError as e:  # the session did not open: a port in use, an absent interface
        print_error(command, e)
        end_process(1)
    if args.connect:
        try:  # nothing at -e ENDPOINT: say so and exit, as the tools do, not wait in silence
            check_connected(node.session, conf)
        except BusError as e:
            close_within(node, CLOSE_S, logger)
            print_error(command, e)
            end_process(1)
    signals: list[int] = []
    restore = install_signal_handlers(node.stop, signals)
    returned = threading.Event()
    _watch_stop_requests(node, returned, logger)
    try:
        rc = int(loop(node, args) or 0)
    except KeyboardInterrupt:  # a second Ctrl-C: the user wants it gone
        rc = 130
    except BaseException:
        logger.critical("%s failed outside the per-message path: exiting", command,
                        exc_info=True)
        rc = 1
    returned.set()
    restore()
    if rc == 0 and signals and os.environ.get(SUPERVISED_ENV) == "1":
        # run by `vistrack up`, a stop it did not ask for (an operator's kill, a hung-up
        # terminal) says so: exited 0, the launcher took it for an end and did not restart
        # it under `restart: on-failure`, and the run went on without it
        rc = 128 + signals[0]
    close_within(node, CLOSE_S, logger)
    logger.info("stopped")
    end_process(rc)


def end_process(code: int) -> NoReturn:
    """Flush the logs and standard streams and end the process now with ``code``, without
    the interpreter's teardown (nothing a service holds needs it: its session is closed)."""
    try:
        logging.shutdown()
        for stream in (sys.stdout, sys.stderr):
            stream.flush()
    except BaseException:  # noqa: BLE001 - a closed pipe (the launcher is gone): go anyway
        pass
    finally:
        os._exit(code)


def close_within(node: Node, seconds: float, logger: logging.Logger) -> bool:
    """Close ``node`` from a helper thread, waiting ``seconds`` at most; False if it did not
    finish (a Zenoh callback blocked, a peer that does not answer): the caller goes on."""
    closer = threading.Thread(target=node.close, name="close-session", daemon=True)
    closer.start()
    closer.join(seconds)
    if closer.is_alive():
        logger.warning("the Zenoh session did not close within %g s: exiting without it",
                       seconds)
        return False
    return True


def _watch_stop_requests(node: Node, returned: threading.Event, logger: logging.Logger
                         ) -> None:
    """End the process :data:`STOP_DEADLINE_S` s after SIGINT or SIGTERM if the loop has not
    returned by then.

    Python runs signal handlers on the main thread between bytecodes, so a loop inside a long
    call (a numba kernel) would not even see the request; the C-level handler writes the
    signal number to a wake-up pipe at once, which this thread reads.
    """
    if threading.current_thread() is not threading.main_thread():
        return
    r, w = os.pipe()
    os.set_blocking(w, False)
    signal.set_wakeup_fd(w, warn_on_full_buffer=False)

    def watch() -> None:
        while True:
            signum = os.read(r, 1)
            if signum and signum[0] in STOP_SIGNALS:
                break
        node.stop.set()
        if returned.wait(STOP_DEADLINE_S):
            return
        try:
            if node.alive:
                logger.error("the loop did not return within %g s of the stop request: "
                             "exiting", STOP_DEADLINE_S)
            else:  # still starting (loading or compiling kernels): nothing went wrong
                logger.info("stopped while starting")
            close_within(node, CLOSE_S, logger)
        finally:
            end_process(1)

    threading.Thread(target=watch, name="stop-deadline", daemon=True).start()


# -- inputs: decoding, rejection and per-message fault isolation -----------------------------

Handler = Callable[[bytes], Any]


class Faults:
    """Per-message fault isolation: what a loop does when handling one input raised.

    The input is skipped: the failure is counted in the status (``failed``), its text kept as
    ``last_error``, and logged once, with the key and the input's ``seq`` (the traceback the
    first time a given exception is raised at a given line, so a bug can be found without
    flooding the log); then ``recover`` (if any) puts the service's state back in order, e.g.
    a new track after a frame that failed half-way through the tracker. A fault in ``recover``
    itself is not isolated: the state cannot be trusted, and the process ends.

    :func:`dispatch` is the loop built on it; :meth:`call` runs any other one-input step.
    """

    MAX_SITES = 64  # distinct failure sites whose traceback is logged

    def __init__(self, node: Node, logger: logging.Logger,
                 recover: Callable[[], Any] | None = None) -> None:
        self.node, self.logger, self.recover = node, logger, recover
        self._sites: set[tuple[str, str, int]] = set()

    def call(self, key: str, seq: int | None, step: Callable[..., Any], *args: Any) -> bool:
        """``step(*args)``, the handling of input ``seq`` of ``key``, isolated; False if it
        raised (counted, logged, recovered from)."""
        try:
            step(*args)
            return True
        except Exception as e:  # noqa: BLE001 - the isolation itself: counted, logged
            self.failed(key, seq, e)
            return False

    def failed(self, key: str, seq: int | None, error: Exception) -> None:
        """Count, log and recover from the failure ``error`` of the input ``seq`` on ``key``."""
        where = f"{key_suffix(key)} seq {'?' if seq is None else seq}"
        text = f"{type(error).__name__}: {error}"
        n = self.node.status.fail(f"{where}: {text}")
        tb = error.__traceback__
        while tb is not None and tb.tb_next is not None:
            tb = tb.tb_next
        site = (type(error).__name__, tb.tb_frame.f_code.co_filename if tb else "",
                tb.tb_lineno if tb else 0)
        first = site not in self._sites and len(self._sites) < self.MAX_SITES
        if first:
            self._sites.add(site)
        self.logger.error("failed on %s: %s (input skipped, %d failed so far)", where, text, n,
                          exc_info=error if first else None)
        if self.recover is not None:
            self.recover()


#: A frame's work is rehearsed this long before the next frame is expected, s (see
#: :class:`Rehearsal`): in process 1 and 3 ms ahead saved the same; in the pipeline 1.5 ms
#: saved less (a frame may come a little early, and then finds none).
REHEARSAL_LEAD_S = 0.003
#: Frames are rehearsed where they come at least this far apart, s (closer, a frame's work
#: finds the caches the one before left: ~1.3 times back to back at 1.1 ms), and at most
#: REHEARSAL_MAX_PERIOD_S (slower, nothing to predict the next by: a camera in lockstep)
REHEARSAL_MIN_PERIOD_S = 0.010
REHEARSAL_MAX_PERIOD_S = 1.0
#: Frame arrivals whose gaps make the period (their median)
REHEARSAL_GAPS = 8


class Rehearsal:
    """A frame's work rehearsed on a tiny input just before the next frame is expected.

    A service at 30 fps finds its caches emptied by the 33 ms between frames (on this 2-core
    VM, by the rest of the machine; on a robot's computer, by its cores' sleep states): each
    frame then starts from cold code and data, and measured in process, motion-estimation's
    work for a frame took ~1.9 ms against 0.3 ms back to back. ``rehearse(payload)`` runs
    the same code on the last input on ``key`` (``payload``: decoded again) and a tiny job
    (a tracker: two features tracked from the last frame into itself; a tiny frame encoded;
    nothing kept) :data:`REHEARSAL_LEAD_S` before the next frame is expected on ``key``, by
    the median of the last :data:`REHEARSAL_GAPS` gaps between arrivals, where that period is
    between REHEARSAL_MIN_PERIOD_S and REHEARSAL_MAX_PERIOD_S. Measured in process on
    motion-estimation's frame path (decode to encoded estimate) after 33 ms idle: 1.95 to
    2.07 ms a frame; after a rehearsal of the search alone (~0.7 ms) 3 ms before, 1.2 to
    1.3 ms; with the decode and encode rehearsed too (~0.3 ms more), 0.74 to 0.89 against
    1.02 ms. Pre-processing's filter alone rehearsed: 0.54 against 0.90 ms. In the pipeline
    at 30 fps (`vistrack bench pipeline`'s processes, 256x256), the other processes' work
    between the rehearsal and the frame takes back part of what it warmed: capture to
    estimate 3.25 to 3.31 ms at the median against 3.78 to 3.93, p99 5.24 to 5.42 against
    5.89 to 6.64, for ~0.45 ms more CPU a frame in motion-estimation (2300 to 2450 against
    1900 to 1983 us with its Zenoh threads) and ~0.35 ms in pre-processing (1583 to 1717
    against 1267 to 1333): ~2.4 % of a core in all. ``--no-rehearsal`` turns it off.

    At most one rehearsal a frame, and none once the frame is late (it may be coming: the
    rehearsal would only stand in its way). The loop (:func:`dispatch`) calls
    :meth:`arrived` for each input on ``key`` and waits for the next input no longer than
    :meth:`wait` says. ``rehearse`` returns whether it rehearsed (counted in the status's
    extra ``rehearsals``); an exception there is logged once and rehearsals stop (nothing
    depends on them).
    """

    def __init__(self, node: Node, key: str, rehearse: Callable[[bytes], bool],
                 logger: logging.Logger, clock: Callable[[], float] = time.monotonic) -> None:
        self.node, self.key, self.logger = node, key, logger
        self.rehearse: Callable[[bytes], bool] | None = rehearse
        self._payload = b""
        self.clock = clock
        self._last: float | None = None
        self._gaps: collections.deque[float] = collections.deque(maxlen=REHEARSAL_GAPS)
        self._due: float | None = None
        node.status.extra["rehearsals"] = 0

    def arrived(self, payload: bytes) -> None:
        """``payload`` came on ``key``: the next is expected a period after it."""
        if self.rehearse is None:
            return
        self._payload = payload
        now = self.clock()
        if self._last is not None:
            self._gaps.append(now - self._last)
        self._last = now
        self._due = None
        if len(self._gaps) >= 3:
            period = sorted(self._gaps)[len(self._gaps) // 2]
            if REHEARSAL_MIN_PERIOD_S <= period <= REHEARSAL_MAX_PERIOD_S:
                self._due = now + period - REHEARSAL_LEAD_S

    def wait(self, timeout: float) -> float:
        """Rehearse if it is time; how long the loop may then wait for an input, s (at
        most ``timeout``)."""
        due = self._due
        if due is None:
            return timeout
        now = self.clock()
        if now < due:
            return min(timeout, due - now)
        self._due = None
        if now < due + REHEARSAL_LEAD_S and self.rehearse is not None:  # else late
            try:
                if self.rehearse(self._payload):
                    self.node.status.extra["rehearsals"] += 1
            except Exception as e:  # noqa: BLE001 - nothing depends on it: said, and stopped
                self.logger.warning("rehearsing a frame's work failed (%r): no more "
                                    "rehearsals", e, exc_info=e)
                self.rehearse = None
        return timeout


def add_rehearsal_arg(parser: argparse.ArgumentParser) -> None:
    """``--no-rehearsal`` (:class:`Rehearsal`)."""
    parser.add_argument("--no-rehearsal", action="store_true",
                        help="do not rehearse a frame's path just before the next frame is "
                             "expected: less CPU (measured at 30 fps: ~0.4 ms a frame in "
                             "motion-estimation, ~0.35 in preprocessing), ~0.5 ms more "
                             "latency a frame")


def dispatch(node: Node, handlers: Mapping[str, Handler], logger: logging.Logger, *,
             timeout: float = 0.1, tick: Callable[[], Any] | None = None,
             recover: Callable[[], Any] | None = None,
             rehearsal: Rehearsal | None = None) -> None:
    """The input loop of a service: until ``node.stop`` is set, receive the next input and
    call ``handlers[key](payload)``, isolated (:class:`Faults`: a failure is counted, logged
    with the key and ``seq``, ``recover`` runs, and the loop goes on).

    ``tick()`` runs before every receive (at least every ``timeout`` s): periodic work
    between inputs. It is not isolated: a fault there is not one input's, and ends the
    process (:func:`serve`). ``rehearsal``: a frame's work rehearsed before each frame of
    its key is expected (:class:`Rehearsal`).

    The isolation costs a ``try`` block (free in CPython 3.11 unless it raises) and nothing
    is allocated per input beyond what ``recv`` returns.
    """
    faults = Faults(node, logger, recover)
    recv, stop = node.recv, node.stop
    while not stop.is_set():
        if tick is not None:
            tick()
        item = recv(timeout if rehearsal is None else rehearsal.wait(timeout))
        if item is None:
            continue
        key, payload = item
        if rehearsal is not None and key == rehearsal.key:
            rehearsal.arrived(payload)
        try:
            handlers[key](payload)
        except Exception as e:  # noqa: BLE001 - the isolation itself: counted, logged
            faults.failed(key, peek_seq(payload), e)


#: Rejections of one input (its key or type) for one kind of error are logged at most once
#: every this, s, each later line with the count of those not logged since; the status counts
#: every one.
REJECTED_LOG_S = 5.0
_NUMBERS = re.compile(r"[-+]?\d[\d.]*(?:e[-+]?\d+)?")


def reject(node: Node, logger: logging.Logger, what: str, error: BaseException | str,
           line: str | None = None, level: int = logging.ERROR) -> None:
    """Count a bad input in the status and log why (the loop goes on): the first of ``what``
    at once, then at most once every :data:`REJECTED_LOG_S` with how many more came (a peer
    sending 3000 bad messages in a second wrote 3000 ERROR lines, and a depth camera on a
    ROS 2 topic 30 a second for as long as it ran). ``line`` is what is logged, at
    ``level`` (default: "rejected WHAT: ERROR")."""
    node.status.reject(error)
    # one window per kind of error: the first of a new kind is said at once (a flood of one
    # kind hid another: clocks out of step behind a bad version). A kind is the field a
    # message error names (its text quotes the value: 200 sets with a random `source` were
    # 200 kinds, 200 lines), else the text with its numbers left out
    field = getattr(error, "field", None)
    kind = f"field {field!r}" if isinstance(field, str) else _NUMBERS.sub("#", str(error))[:80]
    unsaid = node.status.say(f"rejected {what}: {kind}", REJECTED_LOG_S)
    if unsaid is not None:
        more = f" ({unsaid} more rejected since the last said, each counted in the status)" \
            if unsaid else ""
        logger.log(level, "%s%s", f"rejected {what}: {error}" if line is None else line, more)


M = TypeVar("M")


def decode_or_reject(cls: type[M], payload: bytes, node: Node, logger: logging.Logger
                     ) -> M | None:
    """Decode a contract message; a bad one is counted in the status, logged with what was
    wrong, and None is returned so the loop goes on to the next input."""
    try:
        return cls.decode(payload)  # type: ignore[attr-defined, no-any-return]
    except MessageError as e:
        reject(node, logger, getattr(cls, "KEY", cls.__name__), e)
        return None


#: ``(seq, stamp_ns)`` before any estimate: for :func:`starts_track`
NO_ESTIMATE = (-1, -1)


#: an estimate at most this many ``seq`` behind the last one taken, and stamped before it, not
#: a track's first, is an old one come late (:func:`came_late`)
LATE_SEQ_BACK = 30


def came_late(est: Estimate, last: tuple[int, int]) -> bool:
    """Whether ``est`` is an old estimate that came after a newer one (``last``: ``(seq,
    stamp_ns)`` of the estimate taken before it): its ``seq`` at most LATE_SEQ_BACK behind
    and its stamp earlier, and not a track's ``first``. A restarted camera's frames go back in
    ``seq`` but on in time; taken for a restart (:func:`starts_track`), a copy two frames old
    moved the controller's set point for the rest of the track (a hunt of the controller).
    A restart whose ``first`` was lost with its stamps gone back too (a lockstep simulator
    ahead of the host's clock, started again) is taken for one only once it is more than
    LATE_SEQ_BACK frames behind, or, behind by less, from its next frame after the old
    track's last ``seq``, as a clock step."""
    seq, stamp = last
    return not est.first and seq - LATE_SEQ_BACK <= est.seq < seq and est.stamp_ns < stamp


def starts_track(est: Estimate, last: tuple[int, int]) -> bool:
    """Whether ``est`` begins a new track, ``last`` being ``(seq, stamp_ns)`` of the estimate
    taken before it (:data:`NO_ESTIMATE`: none).

    ``first`` says so, but an input that keeps only the latest estimate can lose it (written
    over before it was read, or not watched then). Estimates keep the camera's ``seq``, and
    motion-estimation starts a new track when it goes back (the camera restarted): so ``seq``
    going back, or the same ``seq`` with another stamp, begins one too. The same estimate
    again (``seq`` and ``stamp_ns``: published again for a frame sent again) does not.
    """
    seq, stamp = last
    return est.first or est.seq < seq or (est.seq == seq and est.stamp_ns != stamp)


def ready(node: Node) -> None:
    """Declare the service's liveliness token and log the line launchers and tests wait for:
    call it once the loop has warmed up and subscribed to its inputs, so nothing published
    after the token or the line is missed.

    Everything allocated so far (numba's and llvmlite's compiler objects among it: hundreds of
    thousands) is frozen out of the garbage collector: a full collection walked all of it,
    a pause of milliseconds in the hot path, and the collector ran often because every
    estimate allocates a hundred small lists.
    """
    # the status's first percentiles import numpy.ma (np.unique asks np.ma.is_masked): 15 ms
    # holding the GIL in the queryable's thread, at the first status query after the start
    np.percentile(np.zeros(3), [50, 90, 99])
    gc.collect()
    gc.freeze()
    logger = logging.getLogger(f"vistrack.{node.service}")
    # every library the warm-up loaded (numba loads scipy's BLAS) is known by now
    logger.info("numeric thread pools: %s; opencv %d", threads.describe(threads.limit_loaded()),
                cv2.getNumThreads())
    node.declare_alive()
    logger.info("ready (robot %s, liveliness token %s)", node.robot,
                node.keys.alive(node.service))


def wait_for_consumers(node: Node, key: str, *, reliable: bool = False) -> bool:
    """Block until something subscribes to ``key`` (False if the node is stopped first).

    A source that must lose nothing (a file camera, a lockstep simulator) calls it before its
    first publish: a process that has just joined learns of the subscriptions already declared
    only a moment after its session opens, and what it publishes before then reaches nobody
    (the first frame of a file was lost that way about once in twenty runs). Logs once if no
    one has subscribed after 2 s.
    """
    logger = logging.getLogger(f"vistrack.{node.service}")
    if node.wait_for_subscribers(key, reliable=reliable, timeout=2.0):
        return True
    if node.stop.is_set():
        return False
    logger.info("waiting for a subscriber of %s", key)
    while not node.wait_for_subscribers(key, reliable=reliable, timeout=1.0):
        if node.stop.is_set():
            return False
    logger.info("%s has a subscriber: starting", key)
    return True


@dataclass(frozen=True)
class ParamsUpdate:
    """A ``tuner/params`` update accepted by :meth:`ParamsInForce.accept`."""

    params: TrackerParams
    params_id: int
    source: str
    reason: str


@dataclass
class ParamsInForce:
    """The tracker parameters a service runs with and how it accepts ``tuner/params``.

    An update is validated first and applied only if it is valid and newer (a larger
    ``params_id``) than what is in force: a bad or stale update is rejected with a logged error
    naming the field and range, counted, and the old parameters stay (validate-then-apply, as
    ROS 2 parameter callbacks do).
    """

    params: TrackerParams
    params_id: int = 0
    source: str = "flags"
    reason: str = "start-up"

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> ParamsInForce:
        return cls(params_from_args(args))

    def apply(self, payload: bytes, node: Node, logger: logging.Logger) -> bool:
        """Apply an encoded ``tuner/params``; return True when the parameters changed."""
        update = self.accept(payload, node, logger)
        if update is None:
            return False
        self.commit(update, node, logger)
        return True

    def accept(self, payload: bytes, node: Node, logger: logging.Logger,
               pending: ParamsUpdate | None = None) -> ParamsUpdate | None:
        """Validate an encoded ``tuner/params`` against what is in force, or against the
        ``pending`` update (accepted, not yet in force) when there is one: the update to put
        in force, or None (rejected and counted, stale, or a reminder of what is already)."""
        try:
            msg = Params.decode(payload)
            new = msg.tracker_params(self.params)
        except (MessageError, ParamError) as e:
            # through reject(): a flood of bad sets wrote a line each (200 sets, 400 lines
            # from preprocessing and motion-estimation)
            reject(node, logger, "tuner/params", e,
                   f"rejected tuner/params: {e}; keeping params_id {self.params_id}")
            return None
        latest_id, latest = ((pending.params_id, pending.params) if pending is not None
                             else (self.params_id, self.params))
        if msg.params_id == latest_id and new == latest:
            return None  # the tuner's periodic reminder of what is in force (or pending)
        if msg.params_id <= latest_id:
            reject(node, logger, "tuner/params", f"stale params_id {msg.params_id} <= {latest_id}",
                   f"ignored tuner/params with params_id {msg.params_id}: {latest_id} is "
                   f"{'pending' if pending is not None else 'in force'}", logging.WARNING)
            return None
        return ParamsUpdate(new, msg.params_id, msg.source, msg.reason)

    def commit(self, update: ParamsUpdate, node: Node, logger: logging.Logger) -> None:
        """Put an accepted update in force, in the status and the log."""
        self.params, self.params_id = update.params, update.params_id
        self.source, self.reason = update.source, update.reason
        self.publish_status(node)
        logger.info("params_id %d from %s (%s): %s", update.params_id, update.source,
                    update.reason or "no reason given", update.params.factors())

    def publish_status(self, node: Node) -> None:
        node.status.set_params({**self.params.factors(), "params_id": self.params_id,
                                "source": self.source, "reason": self.reason})


def paced(node: Node, next_t: float, period: float,
          wait: Callable[[float], object] | None = None) -> float:
    """Wait until ``next_t + period`` (``time.perf_counter``) or ``node.stop``; return that
    time, the frame's slot. A frame more than half a period late (a wake-up the machine
    delayed, a process stopped) moves the slots after it: the next frame comes a period
    later, not at once (frames 416 and 0.2 ms apart after a wake-up 0.3 s late). ``wait``
    (seconds): how to wait, if not asleep (``node.sleep``): a loop with input to take
    meanwhile takes it."""
    next_t += period
    delay = next_t - time.perf_counter()
    if delay > 0:
        (node.sleep if wait is None else wait)(delay)
    now = time.perf_counter()
    return now if now - next_t > period / 2 else next_t
