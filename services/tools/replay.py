"""``vistrack replay FILE``: publish a recording (``vistrack record``) again, at its timing.

Samples are published in file order, each at its recorded time since the first sample, divided
by ``--speed`` (``--fast``: no waiting at all). Frames, estimates and poses are published like
the services publish them, latest-only (congestion control DROP: a slow consumer skips to the
newest); parameters, reports and commands reliably (BLOCK). So a recorded ``camera/frame``
stream drives the pipeline as a camera would. Before the first sample the replay waits up to
``--wait`` s for a subscriber of its key, since what is published before the subscription is
known is lost.

``--remap-robot ID`` publishes ``vistrack/<recorded robot>/...`` as ``vistrack/<ID>/...``;
``--restamp`` replaces each message's ``stamp_ns`` by the time it is published, for consumers
that judge freshness (the fuzzy-controller's watchdog).

A damaged file (cut short, corrupt bytes) is replayed up to its first bad record, then the
replay ends with a warning and a one-line error naming the file and the byte offset (exit 2).
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from collections.abc import Iterable

import msgpack
import zenoh

from ...common.keys import PREFIX, Keys, key_suffix, validate_robot_id
from ..usage import add_number
from .record import Record, RecordError, Recording
from .shared import (
    ToolError,
    add_tool_args,
    error,
    has_subscriber,
    run,
    stop_on_signals,
    warn,
)

# Streams where only the newest sample matters: published with congestion control DROP, as
# the camera, preprocessing and motion-estimation services do.
LATEST_ONLY = frozenset({"camera/frame", "preprocessing/frame", "motion/estimate", "sim/pose"})


def _robot(value: str) -> str:
    try:
        return validate_robot_id(value)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", metavar="FILE", help="a recording made by vistrack record")
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
               help="longest wait for a subscriber before the first sample, %(allowed)s; 0: "
                    "do not wait (default 5 s)")
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
        recording = Recording(args.file)  # a file that is no recording fails before Zenoh
    except RecordError as e:
        error("replay", e)
        return 2
    return run("replay", args, lambda session, keys: replay(session, keys, recording, args))


class _Player:
    """Publishers per key, declared on first use, and the pacing of one pass."""

    def __init__(self, session: zenoh.Session, args: argparse.Namespace,
                 stop: threading.Event) -> None:
        self.session = session
        self.args = args
        self.stop = stop
        self.published = 0
        self._publishers: dict[str, zenoh.Publisher] = {}

    def publisher(self, key: str) -> zenoh.Publisher:
        pub = self._publishers.get(key)
        if pub is None:
            latest = key_suffix(key) in LATEST_ONLY
            try:
                pub = self.session.declare_publisher(
                    key, congestion_control=(zenoh.CongestionControl.DROP if latest
                                             else zenoh.CongestionControl.BLOCK))
            except zenoh.ZError as e:
                raise ToolError(f"cannot publish on {key!r}: {e}") from None
            self._publishers[key] = pub
        return pub

    def wait_for_subscriber(self, key: str) -> None:
        pub = self.publisher(key)
        deadline = time.monotonic() + self.args.wait
        while not has_subscriber(pub):
            if time.monotonic() >= deadline:
                warn("replay", f"no subscriber of {key} after {self.args.wait:g} s; "
                               "replaying anyway")
                return
            if self.stop.wait(0.02):
                return

    def play(self, records: Iterable[Record]) -> bool:
        """Publish one pass; False if stopped by a signal or if there was nothing to play."""
        t0: int | None = None
        start = time.monotonic()
        for rec in records:
            key = remap(rec.key, self.args.remap_robot)
            if t0 is None:
                t0 = rec.t_ns
                if self.published == 0 and self.args.wait > 0:
                    self.wait_for_subscriber(key)
                start = time.monotonic()
            if not self.args.fast:
                delay = start + (rec.t_ns - t0) / 1e9 / self.args.speed - time.monotonic()
                if delay > 0 and self.stop.wait(delay):
                    return False
            if self.stop.is_set():
                return False
            payload = restamp(rec.payload, time.time_ns()) if self.args.restamp \
                else rec.payload
            self.publisher(key).put(payload)
            self.published += 1
        return t0 is not None

    def close(self) -> None:
        for pub in self._publishers.values():
            try:
                pub.undeclare()
            except zenoh.ZError:
                pass  # the session is closing anyway
        self._publishers.clear()


def replay(session: zenoh.Session, keys: Keys, recording: Recording,
           args: argparse.Namespace) -> int:
    start = time.monotonic()
    with stop_on_signals() as stop:
        player = _Player(session, args, stop)
        try:
            while player.play(recording.records()) and args.loop:
                pass
        except RecordError as e:
            warn("replay", f"{recording.path} is damaged: replayed the {player.published} "
                           f"valid samples before byte offset {e.offset}")
            raise ToolError(str(e), code=2) from None
        finally:
            player.close()
    print(f"vistrack replay: {player.published} samples from {recording.path} in "
          f"{time.monotonic() - start:.2f} s", file=sys.stderr)
    return 0
