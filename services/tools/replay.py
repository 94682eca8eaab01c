"""``vistrack replay FILE [KEY ...]``: publish a recording (``vistrack record``) again, at its
timing.

FILE is a ``.vtr`` or an MCAP recording (told apart by content). An MCAP file's messages are
turned back into the contract's (see :mod:`.mcapio`: ``preprocessing/frame``, the overlays and
topics of other programs are not replayed, and the replay says so). KEY (``camera/frame``, a
full key, a wildcard) replays only the matching samples: a recorded run's frames into a live
pipeline that makes its own estimates. ``control/cmd_vel`` is replayed only where a KEY names
it: the recorded moves would drive a robot of that id (its ROS 2 bridge passes every command
on to the base).

Samples are published in file order, each at its recorded time since the first sample, divided
by ``--speed`` (``--fast``: no waiting at all). Frames, estimates and poses are published like
the services publish them, latest-only (congestion control BLOCK_FIRST: the one sample in
flight is not lost, a congested link drops the newer ones); parameters, reports and commands
reliably (BLOCK). So a recorded ``camera/frame`` stream drives the pipeline as a camera would.
Before the first sample the replay waits up to ``--wait`` s for a subscriber of its key, since
what is published before the subscription is known is lost, and for the robot's services that
are still starting (see ``vistrack status``) to be ready, as ``vistrack up`` starts its camera
only once the other services are.

``--in-flight N`` also holds each ``camera/frame`` until motion-estimation has published the
estimate of the frame N before it (or ``--ack-timeout`` s have passed), as the camera does with
``--fps 0``: with ``--fast``, the pipeline's own pace with no frame lost; at the recorded pace,
never faster than the pipeline. The replay then also waits for the last frame's estimate. Its
frames then go reliable (BLOCK), as a file camera's: at most N queue, and the stages answer
them BLOCK, so no frame or estimate is dropped on a link.

``--remap-robot ID`` publishes ``vistrack/<recorded robot>/...`` as ``vistrack/<ID>/...``;
``--restamp`` replaces each message's ``stamp_ns`` by the time it is published, for consumers
that judge freshness (the fuzzy-controller's watchdog).

A damaged file (cut short, corrupt bytes) is replayed up to its first bad record, then the
replay ends with a warning and a one-line error naming the file and the byte offset (exit 2).
"""

from __future__ import annotations

import argparse
import collections
import sys
import threading
import time
from collections.abc import Iterable

import msgpack
import zenoh

from ...common.bus import SourcedPublisher, congestion
from ...common.keys import PREFIX, Keys, key_suffix, validate_robot_id
from ...common.messages import peek_int
from ..usage import add_number, add_path, plural
from .mcapio import McapRecording, key_of
from .record import Record, RecordError, Recording, open_recording
from .shared import (
    ToolError,
    add_tool_args,
    error,
    gather,
    has_subscriber,
    resolve_key,
    run,
    stop_on_signals,
    warn,
)

# Streams where only the newest sample matters: published with the congestion control of
# latest-only streams (bus.LATEST_CONGESTION), as the camera, preprocessing and
# motion-estimation services do.
LATEST_ONLY = frozenset({"camera/frame", "preprocessing/frame", "motion/estimate", "sim/pose"})
#: The stream ``--in-flight`` paces (by its estimates), and sends reliable (BLOCK) then.
PACED = "camera/frame"


def _robot(value: str) -> str:
    try:
        return validate_robot_id(value)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


#: The key a replay leaves out unless a KEY argument names it (:class:`_Selection`).
COMMANDS = "control/cmd_vel"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_path(parser, "file", example="run.vtr", metavar="FILE",
             help="a recording made by vistrack record (.vtr or MCAP)")
    parser.add_argument("keys", nargs="*", metavar="KEY",
                        help="replay only these keys: camera/frame, estimate, '**', full keys "
                             f"(default: every recorded sample but {COMMANDS}, which only a "
                             "KEY naming it replays: a robot would move)")
    pace = parser.add_mutually_exclusive_group()
    add_number(pace, "--speed", lo=0.01, hi=1000, default=1.0, metavar="X",
               help="playback speed, a multiple of the recorded one, %(allowed)s (default 1)")
    pace.add_argument("--fast", action="store_true", help="publish as fast as possible")
    parser.add_argument("--loop", action="store_true", help="replay forever")
    parser.add_argument("--remap-robot", type=_robot, default=None, metavar="ID",
                        help="publish under vistrack/<ID>/ instead of the recorded robot")
    parser.add_argument("--restamp", action="store_true",
                        help="set each message's stamp_ns to its publication time")
    add_number(parser, "--wait", lo=0, hi=3600, unit="s", default=5.0, metavar="S",
               help="longest wait for a subscriber before the first sample (with -e, for "
                    "the router too), %(allowed)s; 0: do not wait (default 5 s)")
    add_number(parser, "--in-flight", lo=1, hi=16, integer=True, default=None, metavar="N",
               help="hold frame n until motion-estimation has published frame n-N, "
                    "%(allowed)s (default: do not wait for the pipeline)")
    add_number(parser, "--ack-timeout", lo=0, hi=3600, lo_open=True, default=1.0, metavar="S",
               help="with --in-flight, longest wait for a frame's estimate, %(allowed)s "
                    "(default 1 s)")
    add_tool_args(parser)


def remap(key: str, robot: str | None) -> str:
    """``key`` moved to ``vistrack/<robot>/`` (unchanged without a robot or outside
    ``vistrack/``)."""
    parts = key.split("/", 2)
    if robot is None or len(parts) < 3 or parts[0] != PREFIX:
        return key
    return f"{PREFIX}/{robot}/{parts[2]}"


def restamp(payload: bytes, stamp_ns: int) -> bytes:
    """``payload`` with its ``stamp_ns`` replaced; unchanged if it has none or is not a map."""
    try:
        obj = msgpack.unpackb(payload, raw=False, strict_map_key=False)
    except (ValueError, TypeError, msgpack.UnpackException):
        return payload  # published as recorded: the consumers judge it
    if not isinstance(obj, dict) or "stamp_ns" not in obj:
        return payload
    obj["stamp_ns"] = stamp_ns
    return msgpack.packb(obj, use_bin_type=True)


def main(args: argparse.Namespace) -> int:
    try:
        # a file that is no recording fails before Zenoh
        recording = open_recording(args.file)
        selected = [_key_filter(Keys(args.robot), k) for k in args.keys]
    except RecordError as e:
        error("replay", e)
        return 2
    except ToolError as e:
        error("replay", e)
        return e.code
    return run("replay", args,
               lambda session, keys: replay(session, keys, recording, selected, args),
               connect_timeout=args.wait)


def _key_filter(keys: Keys, key: str) -> zenoh.KeyExpr:
    """The key expression KEY selects among recorded keys: a contract name (``camera/frame``,
    ``estimate``) matches it under any robot id, a full key or wildcard as written."""
    expr = resolve_key(keys, key)
    if not key.startswith(f"{PREFIX}/"):
        expr = f"{PREFIX}/*/{expr.split('/', 2)[2]}"
    return zenoh.KeyExpr(expr)


def names_commands(keys: list[str], exprs: list[zenoh.KeyExpr]) -> bool:
    """Whether a KEY argument asks for ``control/cmd_vel``: one that selects it and is not a
    bare wildcard (``**``, ``*/**``: every key, not commands in particular). ``control/**``
    asked for them, and the replay said no recorded sample matched it."""
    commands = zenoh.KeyExpr(f"{PREFIX}/*/{COMMANDS}")
    return any(k.strip("*/") != "" and e.intersects(commands)
               for k, e in zip(keys, exprs, strict=True))


class _Selection:
    """Whether a recorded key is among the KEY arguments (all keys without any), but
    ``control/cmd_vel`` only where a KEY names it (``commands``): replayed with the rest, the
    recorded moves went to the ROS 2 bridge of a robot of that id, which drove its base with
    them (29 moving commands in a 1 s replay, interleaved with its own controller's stops).
    ``held_back`` says whether one was left out."""

    def __init__(self, exprs: list[zenoh.KeyExpr], commands: bool = False) -> None:
        self._exprs = exprs
        self._commands = commands
        self._known: dict[str, bool] = {}
        self.held_back = False

    def __call__(self, key: str) -> bool:
        chosen = self._known.get(key)
        if chosen is None:
            chosen = self._chosen(key)
            if chosen and not self._commands and key.endswith("/" + COMMANDS):
                self.held_back = True  # selected (no KEY, a wildcard) but not named
                chosen = False
            self._known[key] = chosen
        return chosen

    def _chosen(self, key: str) -> bool:
        if not self._exprs:
            return True
        try:
            concrete = zenoh.KeyExpr(key)
        except zenoh.ZError:  # a topic of another program that is no Zenoh key
            return False
        return any(e.intersects(concrete) for e in self._exprs)


class _Acks:
    """The newest ``stamp_ns`` published on each watched ``motion/estimate`` key (the camera's
    pacing with ``--fps 0``: an estimate of frame k acknowledges every frame up to k)."""

    def __init__(self, session: zenoh.Session) -> None:
        self._session = session
        self._cond = threading.Condition()
        self._newest: dict[str, int] = {}
        self._subs: list[zenoh.Subscriber] = []
        self.timeouts = 0

    def watch(self, key: str) -> None:
        if key in self._newest:
            return
        self._newest[key] = -1

        def on_estimate(sample: zenoh.Sample) -> None:
            stamp = peek_int(sample.payload.to_bytes(), "stamp_ns")
            if stamp is not None:
                with self._cond:
                    self._newest[key] = max(self._newest[key], stamp)
                    self._cond.notify_all()
        self._subs.append(self._session.declare_subscriber(key, on_estimate))

    def reset(self) -> None:
        """Forget what was acknowledged (a new pass replays the same stamps)."""
        with self._cond:
            self._newest = dict.fromkeys(self._newest, -1)

    def wait(self, key: str, stamp: int, timeout: float, stop: threading.Event) -> bool:
        """Until ``key`` has acknowledged ``stamp``; False after ``timeout`` s or on stop."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while self._newest[key] < stamp:
                remaining = deadline - time.monotonic()
                if remaining <= 0 or stop.is_set():
                    return False
                self._cond.wait(min(remaining, 0.1))
        return True

    def close(self) -> None:
        for sub in self._subs:  # a callback subscriber left declared hangs the exit
            sub.undeclare()
        self._subs.clear()


class _Player:
    """Publishers per key, declared on first use, and the pacing of one pass."""

    def __init__(self, session: zenoh.Session, args: argparse.Namespace,
                 stop: threading.Event, selected: _Selection) -> None:
        self.session = session
        self.args = args
        self.stop = stop
        self.selected = selected
        self.published = 0
        self.acks = _Acks(session) if args.in_flight else None
        self._publishers: dict[str, SourcedPublisher] = {}

    def publisher(self, key: str) -> SourcedPublisher:
        """The publisher of ``key``: its puts carry source info, so receivers count this
        replay's ``seq`` apart from any live publisher's."""
        pub = self._publishers.get(key)
        if pub is None:
            # with --in-flight the frames go BLOCK, as the camera's of a file run: at most N
            # queue, the stages answer BLOCK in turn, and none is lost on a link
            latest = key_suffix(key) in LATEST_ONLY and not self._paced(key)
            try:
                pub = SourcedPublisher(self.session.declare_publisher(
                    key, congestion_control=congestion(reliable=not latest)))
            except zenoh.ZError as e:
                raise ToolError(f"cannot publish on {key!r}: {e}") from None
            self._publishers[key] = pub
        return pub

    def wait_for_subscriber(self, key: str) -> None:
        """Wait (up to ``--wait`` s) for a subscriber of ``key``, then for the services of
        its robot that are still starting (answering their status, no liveliness token yet:
        loading their kernels) to be ready, as ``vistrack up`` holds its camera back until
        then: frames sent to a pipeline half started are lost."""
        pub = self.publisher(key)
        deadline = time.monotonic() + self.args.wait
        while not has_subscriber(pub.publisher):
            if time.monotonic() >= deadline:
                warn("replay", f"no subscriber of {key} after {self.args.wait:g} s; "
                               "replaying anyway")
                return
            if self.stop.wait(0.02):
                return
        parts = key.split("/", 2)
        if len(parts) < 3 or parts[0] != PREFIX:
            return  # not a vistrack key: no services to wait for
        keys = Keys(parts[1])
        while starting := [s.service for s in gather(self.session, keys, timeout=0.5)
                           if s.state == "starting"]:
            if time.monotonic() >= deadline:
                warn("replay", f"{', '.join(starting)} still starting after "
                               f"{self.args.wait:g} s; replaying anyway")
                return
            if self.stop.wait(0.1):
                return

    def play(self, records: Iterable[Record]) -> bool:
        """Publish one pass; False if stopped by a signal or if there was nothing to play."""
        t0: int | None = None
        start = time.monotonic()
        in_flight: dict[str, collections.deque[int]] = {}  # ack key -> stamps of frames sent
        if self.acks is not None:
            self.acks.reset()
        for rec in records:
            if not self.selected(rec.key):
                continue
            key = remap(rec.key, self.args.remap_robot)
            ack_key = self._ack_key(key)
            if t0 is None:
                t0 = rec.t_ns
                if self.published == 0 and self.args.wait > 0:
                    self.wait_for_subscriber(key)
                start = time.monotonic()
            if not self.args.fast:
                delay = start + (rec.t_ns - t0) / 1e9 / self.args.speed - time.monotonic()
                if delay > 0 and self.stop.wait(delay):
                    return False
            sent = None
            if ack_key is not None:
                sent = in_flight.setdefault(ack_key, collections.deque())
                if len(sent) >= self.args.in_flight:
                    self._wait_ack(ack_key, sent.popleft(), sent)
            if self.stop.is_set():
                return False
            payload = restamp(rec.payload, time.time_ns()) if self.args.restamp \
                else rec.payload
            self.publisher(key).put(payload)
            self.published += 1
            stamp = peek_int(payload, "stamp_ns")
            if sent is not None and stamp is not None:
                sent.append(stamp)
        for ack_key, sent in in_flight.items():  # the last frames through the pipeline too
            if sent and not self.stop.is_set():
                self._wait_ack(ack_key, sent[-1], sent)
        return t0 is not None

    def _paced(self, key: str) -> bool:
        """Whether ``--in-flight`` paces what is published on ``key``."""
        return self.acks is not None and key_suffix(key) == PACED

    def _ack_key(self, key: str) -> str | None:
        """The estimate key that acknowledges a frame published on ``key`` (None: no pacing)."""
        if self.acks is None or not self._paced(key):
            return None
        ack_key = key[:-len(PACED)] + "motion/estimate"
        self.acks.watch(ack_key)
        return ack_key

    def _wait_ack(self, ack_key: str, stamp: int, sent: collections.deque[int]) -> None:
        assert self.acks is not None
        if not self.acks.wait(ack_key, stamp, self.args.ack_timeout, self.stop):
            if not self.stop.is_set():
                self.acks.timeouts += 1
                sent.clear()  # lost downstream (a service restarted): go on

    def close(self) -> None:
        if self.acks is not None:
            self.acks.close()
        for pub in self._publishers.values():
            try:
                pub.undeclare()
            except zenoh.ZError:
                pass  # the session is closing anyway
        self._publishers.clear()


def replay(session: zenoh.Session, keys: Keys, recording: Recording | McapRecording,
           selected: list[zenoh.KeyExpr], args: argparse.Namespace) -> int:
    start = time.monotonic()
    with stop_on_signals() as stop:
        selection = _Selection(selected, commands=names_commands(args.keys, selected))
        player = _Player(session, args, stop, selection)
        try:
            while player.play(recording.records()) and args.loop:
                pass
        except RecordError as e:
            warn("replay", f"{recording.path}{' is damaged' if e.damaged else ''}: replayed "
                           f"the {player.published} valid samples before byte offset {e.offset}")
            raise ToolError(str(e), code=2) from None
        finally:
            player.close()
            _note_skipped(recording, selection)
            if selection.held_back:
                print(f"vistrack replay: note: {COMMANDS} not replayed (a robot of this id "
                      f"would move): name it to replay it (vistrack replay FILE {COMMANDS} "
                      "...)", file=sys.stderr)
    acks = player.acks
    waited = f" ({acks.timeouts} estimates not seen within --ack-timeout)" \
        if acks is not None and acks.timeouts else ""
    print(f"vistrack replay: {plural(player.published, 'sample')} from {recording.path} in "
          f"{time.monotonic() - start:.2f} s{waited}", file=sys.stderr)
    if player.published == 0 and selected:
        raise ToolError(f"{recording.path}: no recorded sample matches "
                        f"{' '.join(args.keys)}", code=2)
    return 0


def _note_skipped(recording: Recording | McapRecording, selected: _Selection) -> None:
    """One line naming what the MCAP file holds of the keys asked for but cannot replay."""
    skipped = {t: why for t, why in getattr(recording, "skipped", {}).items()
               if selected(key_of(t))}
    if skipped:
        print("vistrack replay: note: not replayed: " + "; ".join(
            f"{topic} ({why})" for topic, why in sorted(skipped.items())), file=sys.stderr)
