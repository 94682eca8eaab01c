"""``vistrack foxglove``: the pipeline live in Foxglove, over the Foxglove WebSocket protocol.

Serves a robot's keys as the channels of a Foxglove WebSocket server (the ``foxglove-sdk``
package's, subprotocol ``foxglove.sdk.v1``), with the topics, ROS 2 types and CDR encoding of
an MCAP recording (:mod:`.mcapio`), so one Foxglove layout (``deploy/foxglove/vistrack.json``)
shows a recording and the live robot alike. In the Foxglove app: Open connection, Foxglove
WebSocket, ``ws://HOST:PORT``.

=========================================  ================================================
channel (``/vistrack/<robot>/...``)        what is sent
=========================================  ================================================
``camera/frame``, ``preprocessing/frame``  ``sensor_msgs/msg/Image``, at most ``--frame-rate``
                                           a second (default 10): the newest frame each time
``camera/features``, ``camera/centroid``   ``ImageMarker`` overlays of the frames sent
``motion/estimate``                        ``vistrack_msgs/msg/Estimate``, every one
``tuner/params``, ``tuner/report``         ``vistrack_msgs/msg/Params``, ``Report``, every one
``control/cmd_vel``                        ``geometry_msgs/msg/Twist``, every one
=========================================  ================================================

Nothing is converted for a channel no client subscribes to. Log times are arrival times at
this process. A payload that is not a valid message of its key is counted and skipped (one
warning per key), and the bridge goes on.
"""

from __future__ import annotations

import argparse
import collections
import functools
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

import foxglove
import zenoh

from ...common import ros2types as r2
from ...common.keys import Keys, key_suffix
from ...common.messages import Estimate, Frame, MessageError, PreFrame, decode_any
from ..usage import add_number
from .mcapio import topic_of
from .shared import Inbox, ToolError, add_tool_args, run, stop_on_signals, warn

#: Keys sent at most ``--frame-rate`` times a second, the newest each time.
FRAME_KEYS = (Frame.KEY, PreFrame.KEY)
#: Keys sent as they come.
STREAM_KEYS = ("motion/estimate", "tuner/params", "tuner/report", "control/cmd_vel")
#: Estimates kept to draw the overlays of a frame sent before its estimate came.
_RECENT = 16
#: Samples are taken from the inbox every BATCH_S, s.
BATCH_S = 0.02


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_number(parser, "--port", lo=0, hi=65535, integer=True, default=8765, metavar="PORT",
               help="WebSocket port, %(allowed)s (default 8765; 0: any free port)")
    parser.add_argument("--host", default="127.0.0.1",
                        help="address to listen on (default 127.0.0.1: this machine only; "
                             "0.0.0.0: every interface)")
    add_number(parser, "--frame-rate", lo=0.1, hi=1000, default=10.0, metavar="HZ",
               help="most frames sent a second, per image channel, %(allowed)s (default 10)")
    add_tool_args(parser)


def _channel(ctx: foxglove.Context, key: str, typename: str) -> foxglove.Channel:
    schema = foxglove.Schema(name=typename, encoding="ros2msg",
                             data=r2.msgdef(typename).encode())
    return foxglove.Channel(topic_of(key), schema=schema, message_encoding="cdr", context=ctx)


class _Latest:
    """Zenoh callback keeping the newest frame of each key (no queue: older ones are skipped
    unread), and only while a client watches what is made of it (``watched(key)``)."""

    def __init__(self, watched: Callable[[str], bool]) -> None:
        self._watched = watched
        self._lock = threading.Lock()
        self.frames: dict[str, tuple[bytes, int]] = {}

    def __call__(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        if not self._watched(key):
            return
        item = (sample.payload.to_bytes(), time.time_ns())
        with self._lock:
            self.frames[key] = item

    def take(self) -> dict[str, tuple[bytes, int]]:
        with self._lock:
            frames, self.frames = self.frames, {}
        return frames


class Bridge:
    """Turns a robot's samples into messages on the Foxglove channels of ``ctx``."""

    def __init__(self, ctx: foxglove.Context, keys: Keys) -> None:
        self.keys = keys
        root = keys.root + "/"
        self.channels = {root + s: _channel(ctx, root + s, r2.ROS_TYPES[s])
                         for s in (*FRAME_KEYS, *STREAM_KEYS)}
        self.overlays = {root + s: _channel(ctx, root + s, r2.IMAGE_MARKER)
                         for s in r2.OVERLAYS}
        self.frame_key = root + Frame.KEY
        self.sent: collections.Counter[str] = collections.Counter()
        self.rejected: collections.Counter[str] = collections.Counter()
        self._recent: collections.deque[Estimate] = collections.deque(maxlen=_RECENT)
        self._frames_sent: collections.deque[int] = collections.deque(maxlen=_RECENT)

    def _log(self, key: str, channel: foxglove.Channel, make: Callable[[], Any],
             t_ns: int) -> None:
        """Send the ROS 2 message ``make()`` on ``channel``; one that cannot be made (a valid
        message holding what its ROS 2 type cannot: a stamp past 2038) is counted and
        skipped, as an invalid payload is, and the bridge goes on."""
        try:
            data = r2.serialize(make())
        except ValueError as e:
            self._refuse(key, f"skipping messages whose values no ROS 2 "
                              f"{channel.schema_name()} holds (first: {e})")
            return
        channel.log(data, log_time=t_ns)
        self.sent[channel.topic()] += 1

    def _refuse(self, key: str, why: str) -> None:
        if not self.rejected[key]:
            warn("foxglove", f"{key}: {why}")
        self.rejected[key] += 1

    def _decode(self, key: str, payload: bytes) -> Any:
        try:
            return decode_any(key, payload)
        except MessageError as e:
            self._refuse(key, f"skipping payloads that are not valid messages (first: {e})")
            return None

    def frame(self, key: str, payload: bytes, t_ns: int) -> None:
        """Send a frame (the caller throttles) and the overlays of its estimate if it came."""
        msg = self._decode(key, payload)
        if msg is None:
            return
        if self.channels[key].has_sinks():
            self._log(key, self.channels[key], lambda: r2.image(msg), t_ns)
        if key == self.frame_key:
            self._frames_sent.append(msg.stamp_ns)
            for est in self._recent:
                if est.stamp_ns == msg.stamp_ns:
                    self._overlays(est, t_ns)

    def sample(self, key: str, payload: bytes, t_ns: int) -> None:
        """Send a streamed sample (estimate, params, report, command) as it comes."""
        channel = self.channels.get(key)
        if channel is None:
            return
        watched = channel.has_sinks()
        is_estimate = key_suffix(key) == Estimate.KEY
        if not watched and not (is_estimate and self._overlays_watched()):
            return
        msg = self._decode(key, payload)
        if msg is None:
            return
        if watched:
            self._log(key, channel, lambda: r2.to_ros(msg, payload=payload), t_ns)
        if isinstance(msg, Estimate):
            self._recent.append(msg)
            if msg.stamp_ns in self._frames_sent:
                self._overlays(msg, t_ns)

    def _overlays_watched(self) -> bool:
        return any(c.has_sinks() for c in self.overlays.values())

    def frame_watched(self, key: str) -> bool:
        """Whether a client watches what is made of the frames of ``key``: their channel, or
        for the camera's the overlays drawn at them (sent at the frames' rate, a client
        watching only the features and centroid got nothing)."""
        channel = self.channels.get(key)
        if channel is None:
            return False
        return channel.has_sinks() or (key == self.frame_key and self._overlays_watched())

    def _overlays(self, est: Estimate, t_ns: int) -> None:
        for key, channel in self.overlays.items():
            if channel.has_sinks():
                self._log(key, channel, functools.partial(r2.OVERLAYS[key_suffix(key)], est),
                          t_ns)


def main(args: argparse.Namespace) -> int:
    return run("foxglove", args, lambda session, keys: serve(session, keys, args))


def serve(session: zenoh.Session, keys: Keys, args: argparse.Namespace) -> int:
    ctx = foxglove.Context()
    bridge = Bridge(ctx, keys)
    try:
        server = foxglove.start_server(name=f"vistrack {keys.robot}", host=args.host,
                                       port=args.port, context=ctx)
    except RuntimeError as e:  # FoxgloveError: the port is taken, the address is not ours
        raise ToolError(f"cannot serve on {args.host}:{args.port}: {e}") from None
    latest = _Latest(bridge.frame_watched)
    inbox = Inbox(capacity=10_000)
    period = 1.0 / args.frame_rate
    start = time.monotonic()
    with stop_on_signals() as stop:
        subs = [session.declare_subscriber(k, latest if key_suffix(k) in FRAME_KEYS else inbox)
                for k in bridge.channels]
        print(f"vistrack foxglove: serving {keys.root}/** on ws://{args.host}:{server.port} "
              "(Foxglove: Open connection, Foxglove WebSocket)", file=sys.stderr, flush=True)
        try:
            next_frames = time.monotonic()
            while not stop.is_set():
                for item in inbox.take():
                    bridge.sample(item.key, item.payload, item.t_ns)
                now = time.monotonic()
                if now >= next_frames:
                    for key, (payload, t_ns) in latest.take().items():
                        bridge.frame(key, payload, t_ns)
                    next_frames = max(next_frames + period, now)
                # woken once a batch, not once a sample (estimates wait BATCH_S at most)
                stop.wait(min(BATCH_S, max(0.0, next_frames - time.monotonic())))
        finally:
            for sub in subs:  # a callback subscriber left declared hangs the exit
                sub.undeclare()
            server.stop()
    sent = ", ".join(f"{n} on {t}" for t, n in sorted(bridge.sent.items())) or "none"
    print(f"vistrack foxglove: {time.monotonic() - start:.1f} s, messages sent: {sent}",
          file=sys.stderr)
    if inbox.overflow:
        warn("foxglove", f"{inbox.overflow} samples lost (the bridge could not keep up)")
    return 0
