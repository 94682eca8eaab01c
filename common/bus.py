"""Zenoh plumbing shared by every service and tool.

* :func:`add_zenoh_args` / :func:`config_from_args`: the command line contract's Zenoh flags
  (``-m -e -l -c --no-multicast-scouting --robot``) turned into a ``zenoh.Config`` the way
  zenoh-python's ``examples/common/common.py`` does it, except where it listens: on loopback
  only (:data:`LOOPBACK_LISTEN`) unless ``-l`` or the config file names endpoints.
* :class:`Node`: the seam a service loop is written against (``subscribe``, ``recv``,
  ``publish``, ``status``, ``stop``), like dora's node API. :class:`ZenohNode` runs it over a
  real Zenoh session (liveliness token, status queryable); :class:`MemoryNode` runs the same
  semantics in memory, so a service loop is tested in-process by feeding scripted payloads.
* :class:`Status`: the counters every service reports on ``vistrack/<robot>/<service>/status``.
* :func:`install_signal_handlers`, :func:`query_status`, :func:`alive_services`.

Delivery semantics of :meth:`Node.recv` (identical for both nodes):

* reliable inputs (``subscribe(key, latest=False)``) are queued and delivered in arrival
  order, before anything else, without loss;
* latest-only inputs (``latest=True``) keep one slot per key: a newer payload overwrites a
  pending one, which counts as dropped. Pending slots are delivered oldest-waiting first.
  Such a stream (frames, estimates) is taken from one publisher at a time (:class:`_Route`):
  a second one on the key (a replay beside the live camera) is not taken while the first
  goes on, only counted in status ``extra.other_publishers`` and logged once.

A service loop reads::

    with ZenohNode("preprocessing", conf, robot) as node:
        install_signal_handlers(node.stop)
        node.subscribe(node.keys.frame, latest=True)
        node.subscribe(node.keys.params, latest=False)
        while not node.stop.is_set():
            item = node.recv(timeout=0.1)
            ...
"""

from __future__ import annotations

import abc
import argparse
import collections
import ipaddress
import json
import logging
import math
import os
import queue
import signal
import socket
import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from types import FrameType, TracebackType
from typing import Any, ClassVar, NamedTuple, TypeVar

import numpy as np
import zenoh

from vistrack.common.keys import Keys, validate_robot_id, validate_service_name
from vistrack.common.messages import MessageError, pack, peek_seq, unpack

log = logging.getLogger(__name__)

_N = TypeVar("_N", bound="Node")

_monotonic = time.monotonic  # bound once: recv stamps every input with it
_PUT = zenoh.SampleKind.PUT
_BLOCK = zenoh.CongestionControl.BLOCK

#: Reliable payloads a node queues before its Zenoh callback blocks (see ZenohNode).
DEFAULT_CAPACITY = 1024
#: How long the set of connected peers must stay the same before a new node's links count as
#: settled (:meth:`Node.wait_for_subscribers`): they come up within ~10 ms of each other here.
SETTLE_S = 0.1
#: Where a process listens when neither ``-l`` nor its config file names endpoints, per Zenoh
#: mode: loopback only. Zenoh's own default, every interface (``tcp/[::]:0`` for a peer), let any
#: host on the robot's network open a session with each service, read its camera and drive it.
#: The local peers still connect directly to each other, on these endpoints (gossip and
#: multicast scouting advertise them, and another host cannot reach them); a client listens on
#: nothing. As rmw_zenoh's default session config does (``tcp/localhost:0``).
LOOPBACK_LISTEN: dict[str, list[str]] = {"peer": ["tcp/127.0.0.1:0"],
                                         "router": ["tcp/127.0.0.1:7447"]}
#: How often a :class:`ZenohNode` takes in what its loop has left queued (see its notes): what a
#: stalled loop holds of a latest-only key is the newest payload and what came in this time.
SWEEP_S = 0.1
#: Congestion control of latest-only streams (``reliable=False``: frames, estimates).
#: DROP loses a message whose fragments (a frame is over one 64 KiB batch) do not all find a
#: free batch within 1 to 50 ms, even alone on an idle link: with the two cores busy, Zenoh's
#: writer thread may not run that soon. A new session's first large messages go as fragments
#: (its shared memory is still being set up), so a file camera lost its first frame now and
#: then. BLOCK_FIRST waits up to 1 ms for the one message of its link and priority still being
#: pushed, else drops the new one; the message it keeps is pushed as BLOCK would, by a Zenoh
#: thread, and put() returns at once. So the message in flight is not lost to a late writer,
#: and a stalled link drops newer ones without blocking the publisher or queueing a backlog.
#: A router forwards it as BLOCK_FIRST (the F flag of the network QoS extension). Zenoh still
#: lost one now and then at start-up with the two cores busy, on any hop of the pipeline: a
#: file camera in lockstep sends a frame again whose estimate does not come.
LATEST_CONGESTION = zenoh.CongestionControl.BLOCK_FIRST
# Longest a blocked recv() sleeps before re-checking ``stop``: bounds the shutdown delay
# without costing latency (data wake it at once through the condition variable).
_STOP_POLL_S = 0.05


class BusError(Exception):
    """A Zenoh configuration or session problem (bad config file, endpoint, closed node)."""


# -- command line --------------------------------------------------------------------------

def _robot_arg(value: str) -> str:
    try:
        return validate_robot_id(value)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def add_zenoh_args(parser: argparse.ArgumentParser) -> None:
    """Add the Zenoh flags of the command line contract to ``parser``."""
    group = parser.add_argument_group("zenoh")
    group.add_argument("-m", "--mode", choices=["peer", "client", "router"],
                       help="Zenoh session mode (default: the config file's, else peer)")
    group.add_argument("-e", "--connect", metavar="ENDPOINT", action="append",
                       help="endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable)")
    group.add_argument("-l", "--listen", metavar="ENDPOINT", action="append",
                       help="endpoint to listen on (repeatable), e.g. tcp/0.0.0.0:7447 to be "
                            "reachable from other hosts (default: the config file's, else "
                            "loopback only: a peer on tcp/127.0.0.1:0, a router on "
                            "tcp/127.0.0.1:7447, a client on nothing)")
    group.add_argument("-c", "--config", metavar="FILE.json5",
                       help="Zenoh configuration file; the flags above override it")
    group.add_argument("--no-multicast-scouting", action="store_true",
                       help="disable multicast scouting (use with -e)")
    group.add_argument("--robot", default="robot", type=_robot_arg, metavar="ID",
                       help="robot id: every key lives under vistrack/<ID>/ (default: robot)")


def config_from_args(args: argparse.Namespace) -> zenoh.Config:
    """The ``zenoh.Config`` described by the flags of :func:`add_zenoh_args`.

    Where neither ``--listen`` nor the config file names listen endpoints, the session listens
    on loopback only (:data:`LOOPBACK_LISTEN`), never on Zenoh's default of every interface.

    Raises
    ------
    BusError
        If the config file is missing or invalid, or a flag value is rejected by Zenoh; the
        text names the file or flag and the reason.
    """
    path = getattr(args, "config", None)
    if path is not None:
        if not Path(path).is_file():
            raise BusError(f"zenoh config file {path}: not found")
        try:
            conf = zenoh.Config.from_file(path)
        except zenoh.ZError as err:
            raise BusError(f"zenoh config file {path}: {err}") from None
    else:
        conf = zenoh.Config()
    settings = [
        ("--mode", "mode", getattr(args, "mode", None)),
        ("--connect", "connect/endpoints", getattr(args, "connect", None)),
        ("--listen", "listen/endpoints", getattr(args, "listen", None)),
        ("--no-multicast-scouting", "scouting/multicast/enabled",
         False if getattr(args, "no_multicast_scouting", False) else None),
    ]
    for flag, key, value in settings:
        if value is None:
            continue
        try:
            conf.insert_json5(key, json.dumps(value))
        except zenoh.ZError as err:
            raise BusError(f"zenoh {flag} {value!r}: {err}") from None
    if getattr(args, "listen", None) is None and not _names_listen_endpoints(conf):
        conf.insert_json5("listen/endpoints", json.dumps(LOOPBACK_LISTEN))
    return conf


def shm_pool_at_open(conf: zenoh.Config) -> zenoh.Config:
    """``conf`` with Zenoh's shared-memory pool made when the session opens (mode ``init``)
    rather than at its first large put (``lazy``, the default): for a process that publishes
    frames. Made lazily, the pool's 16 MiB cost the camera's second frame 6 to 8 ms on a quiet
    machine and 17 to 25 ms with the cores busy (1.1 to 2.3 ms in ``init`` mode, its open 5 to
    15 ms longer, before the service is ready). A config that disables shared memory, or
    names another mode than the default, is left as it is."""
    if conf.get_json("transport/shared_memory/mode") == '"lazy"' and \
            conf.get_json("transport/shared_memory/enabled") == "true":
        conf.insert_json5("transport/shared_memory/mode", '"init"')
    return conf


def _names_listen_endpoints(conf: zenoh.Config) -> bool:
    """Whether ``conf`` (read from a file) sets ``listen/endpoints``, to anything (``[]``
    too) but the value Zenoh uses when it is not set (every interface)."""
    unset = json.loads(zenoh.Config().get_json("listen/endpoints"))
    return bool(json.loads(conf.get_json("listen/endpoints")) != unset)


def congestion(reliable: bool) -> zenoh.CongestionControl:
    """The congestion control of a publisher: BLOCK for what must all arrive (parameters,
    reports, commands), :data:`LATEST_CONGESTION` for latest-only streams (frames,
    estimates)."""
    return zenoh.CongestionControl.BLOCK if reliable else LATEST_CONGESTION


def loopback_config(endpoint: str, *, router: bool = False) -> zenoh.Config:
    """A ``zenoh.Config`` that connects to ``endpoint`` (or, ``router=True``, a router that
    listens on it), multicast scouting off: the explicit wiring benchmarks and tests use, so
    they work in sandboxes without multicast and run side by side on their own ports. The
    peer listens on loopback only, as the services do."""
    conf = zenoh.Config()
    if router:
        conf.insert_json5("mode", '"router"')
        conf.insert_json5("listen/endpoints", json.dumps([endpoint]))
    else:
        conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
        conf.insert_json5("listen/endpoints", json.dumps(LOOPBACK_LISTEN["peer"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return conf


def open_session(conf: zenoh.Config) -> zenoh.Session:
    """``zenoh.open`` with errors (e.g. a listen port in use, no router where it should
    connect) raised as :class:`BusError`."""
    try:
        return zenoh.open(conf)
    except zenoh.ZError as err:
        if "Unable to connect" in str(err):  # client mode, or exit_on_failure
            raise _nothing_answers(conf) from None
        if "Address already in use" in str(err):
            raise BusError(f"cannot open zenoh session: {err}: another process listens there "
                           "(a vistrack up, router or demo already running? join it with "
                           "-e ENDPOINT, or give -l another port)") from None
        raise BusError(f"cannot open zenoh session: {err}") from None


def _connect_endpoints(conf: zenoh.Config) -> list[str]:
    try:
        endpoints = json.loads(conf.get_json("connect/endpoints"))
    except (zenoh.ZError, ValueError):
        endpoints = None
    if isinstance(endpoints, dict):  # per-mode endpoints
        endpoints = [e for v in endpoints.values() for e in (v or [])]
    return [str(e) for e in endpoints] if isinstance(endpoints, list) else []


def _endpoints(conf: zenoh.Config) -> str:
    endpoints = _connect_endpoints(conf)
    return ", ".join(endpoints) if endpoints else "the configured endpoints"


def _nothing_answers(conf: zenoh.Config) -> BusError:
    """The error of connect endpoints where nothing answered: a host name that does not
    resolve is said as such (it read "nothing answers there (is vistrack up ... running?)",
    sending the user to check the router rather than the name)."""
    for endpoint in _connect_endpoints(conf):
        host = endpoint.partition("/")[2].split("#")[0].rpartition(":")[0].strip("[]")
        if not host:
            continue
        try:
            ipaddress.ip_address(host)
            continue  # an address: nothing to resolve
        except ValueError:
            pass
        try:
            socket.getaddrinfo(host, None)
        except (OSError, UnicodeError):
            return BusError(f"cannot connect to {endpoint}: the host name {host!r} does not "
                            "resolve (misspelt, or no DNS for it here?)")
    where = _endpoints(conf)
    if "tls/" in where or "quic/" in where:  # a router may be there and refuse us
        return BusError(f"cannot connect to {where}: nothing answers there, or it refused this "
                        "host's TLS certificate (check -c CONFIG's certificates)")
    return BusError(f"cannot connect to {where}: nothing answers there (is vistrack up or "
                    "vistrack router running, on that port?)")


def check_connected(session: zenoh.Session, conf: zenoh.Config, timeout_s: float = 2.0) -> None:
    """Wait up to ``timeout_s`` for the session to reach a router or peer at one of its
    connect endpoints. In peer mode Zenoh opens a session whatever it could reach and goes on
    retrying in silence: a tool pointed at an absent router would wait forever.

    Raises
    ------
    BusError
        Naming the endpoints, when nothing answered.
    """
    deadline = time.monotonic() + timeout_s
    while not (list(session.info.routers_zid()) or list(session.info.peers_zid())):
        if time.monotonic() >= deadline:
            raise _nothing_answers(conf)
        time.sleep(0.02)


# -- status ------------------------------------------------------------------------------

def _nothing() -> None:
    return None


class Status:
    """Thread-safe service counters, reported by the status queryable.

    Parameters
    ----------
    window : number of most recent processing times the percentiles are computed over.

    Attributes
    ----------
    received : payloads that arrived on subscribed keys.
    published : payloads published.
    dropped : payloads lost: latest-only payloads overwritten before being consumed, plus
        gaps in each publisher's ``seq`` (see :class:`SeqGaps`).
    rejected : bad inputs (counted by the service through :meth:`reject`).
    failed : inputs whose handling raised (a fault of ours, counted through :meth:`fail`):
        the input was skipped and the service went on.
    last_error : text of the last rejection, failure or error, "" if none.
    params : the parameters in force (set by the service).
    extra : service-specific values (e.g. frames, npi), msgpack-encodable; reported as is.
        Mutate from the service loop's thread only.
    extra_on_read : optional; called when the status is read (:meth:`as_dict`, from the
        status queryable's thread), its map added to ``extra``: values a service would
        otherwise recompute every frame for a status read once a second or less (it must only
        read what the loop writes). Should it raise, the status still answers, with
        ``extra_on_read_error`` in ``extra`` (and the traceback in the log).
    started : wall-clock start time, s since the Unix epoch.
    """

    def __init__(self, window: int = 1000) -> None:
        self._lock = threading.Lock()
        self._times_ms: collections.deque[float] = collections.deque(maxlen=window)
        self._received = 0
        self.published = 0
        self._dropped = 0
        self.rejected = 0
        self.failed = 0
        self.last_error = ""
        self.params: dict[str, Any] = {}
        self.extra: dict[str, Any] = {}
        self.extra_on_read: Callable[[], Mapping[str, Any]] | None = None
        self.started = time.time()
        self._started_mono = time.monotonic()
        self._said: dict[str, tuple[float, int]] = {}  # what -> (last logged at, unsaid since)
        # Takes in what has arrived but is not counted yet (set by the node: its arrivals
        # are counted when the loop or a reader of these counters first looks at them).
        self.absorb: Callable[[], object] = _nothing

    @property
    def received(self) -> int:
        self.absorb()
        return self._received

    @property
    def dropped(self) -> int:
        self.absorb()
        return self._dropped

    def count_received(self, n: int = 1) -> None:
        with self._lock:
            self._received += n

    def count_arrivals(self, received: int, dropped: int) -> None:
        """Count a batch of arrivals (one lock for all of them)."""
        with self._lock:
            self._received += received
            self._dropped += dropped

    def count_other(self) -> None:
        """Count a sample received from a second publisher of a latest-only stream, not taken
        (``extra.other_publishers``; see :class:`_Route`)."""
        with self._lock:
            self._received += 1
            self.extra["other_publishers"] = self.extra.get("other_publishers", 0) + 1

    def count_published(self, n: int = 1) -> None:
        with self._lock:
            self.published += n

    def count_dropped(self, n: int = 1) -> None:
        with self._lock:
            self._dropped += n

    def say(self, what: str, every_s: float) -> int | None:
        """Whether to log a repeated message about ``what`` now: None while the last was
        logged less than ``every_s`` s ago (this one is counted as unsaid), else how many went
        unsaid since (0: the first, or the first after a quiet ``every_s``). A peer sending
        bad input at 1 kHz then costs one log line every ``every_s`` s, not a thousand a
        second; the counters keep every one."""
        now = time.monotonic()
        with self._lock:
            at, unsaid = self._said.get(what, (-math.inf, 0))
            if now - at < every_s:
                self._said[what] = at, unsaid + 1
                return None
            if len(self._said) >= 256:  # keys named by peers: bounded
                self._said.clear()
            self._said[what] = now, 0
            return unsaid

    def reject(self, error: BaseException | str) -> None:
        """Count a bad input and remember why (logged by the caller)."""
        with self._lock:
            self.rejected += 1
            self.last_error = str(error)

    def fail(self, error: BaseException | str) -> int:
        """Count an input whose handling failed and remember why; return the count."""
        with self._lock:
            self.failed += 1
            self.last_error = str(error)
            return self.failed

    def error(self, error: BaseException | str) -> None:
        """Remember an error that is not a rejected input."""
        with self._lock:
            self.last_error = str(error)

    def set_params(self, params: Mapping[str, Any]) -> None:
        with self._lock:
            self.params = dict(params)

    def observe_ms(self, ms: float) -> None:
        """Record one processing time, ms."""
        with self._lock:
            self._times_ms.append(float(ms))

    def timed(self) -> _Timer:
        """Context manager recording the wall time of its block: ``with status.timed():``."""
        return _Timer(self)

    @property
    def uptime_s(self) -> float:
        return time.monotonic() - self._started_mono

    def as_dict(self) -> dict[str, Any]:
        """A msgpack/JSON-friendly snapshot.

        Keys: received, published, dropped, rejected, failed, last_error, p50_ms, p90_ms, p99_ms
        (None before the first observation), samples (processing times in the window),
        params, extra, started.
        """
        self.absorb()  # before the lock: it takes the node's, then this one
        on_read = self.extra_on_read
        try:
            late = {} if on_read is None else dict(on_read())
        except Exception as err:  # noqa: BLE001 - a status without them beats none at all
            log.exception("status: the values read at query time failed")
            late = {"extra_on_read_error": repr(err)}
        with self._lock:
            times = np.fromiter(self._times_ms, dtype=float, count=len(self._times_ms))
            snap: dict[str, Any] = {
                "received": self._received, "published": self.published,
                "dropped": self._dropped, "rejected": self.rejected, "failed": self.failed,
                "last_error": self.last_error, "params": dict(self.params),
                "extra": {**self.extra, **late}, "started": self.started,
            }
        p50: float | None = None
        p90: float | None = None
        p99: float | None = None
        if times.size:
            p50, p90, p99 = (float(p) for p in np.percentile(times, [50, 90, 99]))
        snap.update(p50_ms=p50, p90_ms=p90, p99_ms=p99, samples=int(times.size))
        return snap


class _Timer:
    def __init__(self, status: Status) -> None:
        self._status = status
        self._t0 = 0.0

    def __enter__(self) -> _Timer:
        self._t0 = time.perf_counter()
        return self

    def __exit__(self, *exc: object) -> None:
        self._status.observe_ms((time.perf_counter() - self._t0) * 1e3)


#: A forward jump of ``seq`` larger than this starts a new sequence instead of counting
#: losses: no link loses a million messages, but a publisher whose ``seq`` is a clock (a
#: ``vistrack params set``) would otherwise read as 10^15 of them.
MAX_SEQ_GAP = 1_000_000
#: Publishers remembered per key (the oldest forgotten beyond): every ``params set`` is one.
MAX_PUBLISHERS = 64


class SeqGap:
    """Counts messages missing from one publisher's ``seq`` sequence.

    A ``seq`` that does not increase (the publisher restarted) or jumps by more than
    :data:`MAX_SEQ_GAP` restarts the count without counting anything. Payloads without a
    readable ``seq`` are skipped. :class:`SeqGaps` keeps one per publisher.
    """

    def __init__(self) -> None:
        self._last: int | None = None
        self._lock = threading.Lock()

    def observe(self, seq: int) -> int:
        """Record ``seq``; return how many sequence numbers were skipped before it."""
        with self._lock:
            last, self._last = self._last, seq
        if last is None or seq <= last or seq - last > MAX_SEQ_GAP:
            return 0
        return seq - last - 1

    def update(self, payload: bytes) -> int:
        """:meth:`observe` the payload's ``seq`` (peeked, not fully decoded); 0 if none."""
        seq = peek_seq(payload)
        return 0 if seq is None else self.observe(seq)


class SeqGaps:
    """:class:`SeqGap` per publisher of each key, so that two publishers on one key (a
    replayed recording beside a camera, a user's ``params set`` beside the tuner) are never
    counted as losses.

    A publisher is told apart by its Zenoh source id (``source``: what ZenohNode and the
    tools attach to every sample they put, see :func:`source_of`); samples without one (an
    outside publisher) share one sequence per key, as before.
    """

    def __init__(self) -> None:
        self._gaps: dict[tuple[str, str | None], SeqGap] = {}
        self._per_key: collections.Counter[str] = collections.Counter()
        self._lock = threading.Lock()

    def update(self, key: str, payload: bytes, source: str | None = None) -> int:
        """:meth:`SeqGap.update` for the publisher ``source`` of ``key``."""
        with self._lock:
            gap = self._gaps.get((key, source))
            if gap is None:
                if self._per_key[key] >= MAX_PUBLISHERS:  # forget the oldest of this key
                    oldest = next(k for k in self._gaps if k[0] == key)
                    del self._gaps[oldest]
                    self._per_key[key] -= 1
                gap = self._gaps[(key, source)] = SeqGap()
                self._per_key[key] += 1
        return gap.update(payload)


def source_of(sample: zenoh.Sample) -> str | None:
    """The id of the publisher of ``sample`` (its Zenoh source info), None if it has none."""
    info = sample.source_info
    return None if info is None else str(info.source_id)


#: Publisher ids as text (``str`` of a zenoh EntityGlobalId costs 3 us, a lookup 0.3 us).
_SOURCE_NAMES: dict[Any, tuple[str, str]] = {}


def _source_name(sample: zenoh.Sample) -> tuple[str | None, str | None]:
    """:func:`source_of` and the id of the publisher's session (its process), the texts made
    once per publisher: they are read for every message."""
    info = sample.source_info
    if info is None:
        return None, None
    sid = info.source_id
    names = _SOURCE_NAMES.get(sid)
    if names is None:
        if len(_SOURCE_NAMES) >= 4096:  # publishers come and go: forget them all at times
            _SOURCE_NAMES.clear()
        names = _SOURCE_NAMES[sid] = (str(sid), str(sid.zid))
    return names


class SourcedPublisher:
    """A ``zenoh.Publisher`` whose puts carry Zenoh source info (its entity id and a sample
    number), so that receivers count ``seq`` gaps per publisher (:class:`SeqGaps`)."""

    __slots__ = ("publisher", "_id", "_sn")

    def __init__(self, publisher: zenoh.Publisher) -> None:
        self.publisher = publisher
        self._id = publisher.id
        self._sn = 0

    def put(self, payload: bytes) -> None:
        self._sn = (self._sn + 1) & 0xFFFFFFFF  # Zenoh's source sample number is 32-bit
        self.publisher.put(payload, source_info=zenoh.SourceInfo(self._id, self._sn))

    def undeclare(self) -> None:
        self.publisher.undeclare()


# -- the inbox: the delivery semantics both nodes share ------------------------------------

#: A latest-only stream's publisher is followed until it has been silent this long, s, or
#: three of its own periods if longer (a slow camera): then another one's samples are taken.
#: Short: a camera that ends and the next that starts (a test's runs, a restart) are not
#: two at once.
SOURCE_SILENT_S = 0.25


class _Route:
    """How payloads of one subscription are taken in: latest-only or reliable, and the
    publishers' ``seq`` sequences seen on it.

    A latest-only stream is a sequence of frames or estimates: each is read as the next of
    the one before. Two publishers on it (a replay beside the live camera, two cameras
    given one robot id) interleaved their frames: every frame's ``seq`` went back or jumped
    by thousands, motion-estimation started a new track on every one, and each service
    downstream counted 186,721 drops in 3 s (the README said such a publisher was "never
    counted as drops"). So a latest-only route follows one publisher (by its Zenoh session,
    one process, whichever of its publishers puts the key): another one's samples are not
    taken, but counted (:meth:`Status.count_other`), while it goes on; once it has been
    silent :data:`SOURCE_SILENT_S` (or three of its periods), the next publisher's samples
    are (a camera restarted is a new publisher)."""

    __slots__ = ("latest", "gaps", "source", "seen", "period", "others")

    def __init__(self, latest: bool) -> None:
        self.latest = latest
        self.gaps = SeqGaps()
        self.source: str | None = None  # the publisher followed (latest-only routes)
        self.seen = 0.0  # when its last sample was taken in (monotonic)
        self.period = 0.0  # the time between its last two samples
        self.others: set[str] = set()  # other publishers already logged

    def follows(self, key: str, source: str | None) -> bool:
        """Whether a sample of ``source`` on this latest-only route is taken (see above);
        a sample without a source id (an outside publisher) always is."""
        if source is None:
            return True
        now = _monotonic()
        if source != self.source:
            if self.source is not None and \
                    now - self.seen <= max(SOURCE_SILENT_S, 3.0 * self.period):
                if source not in self.others and len(self.others) < MAX_PUBLISHERS:
                    self.others.add(source)
                    log.warning("%s: samples from a second publisher (session %s) while %s "
                                "goes on: "
                                "not taken (one publisher per stream: frames and estimates "
                                "are a sequence); taken once it has been silent for %g s. "
                                "Counted in status extra.other_publishers", key, source,
                                self.source, max(SOURCE_SILENT_S, 3.0 * self.period))
                return False
            if self.source is not None:
                log.info("%s: now taken from %s (%s silent for %.1f s)", key, source,
                         self.source, now - self.seen)
            self.source, self.period = source, 0.0
        else:
            self.period = now - self.seen
        self.seen = now
        return True


class _Inbox:
    """Reliable FIFO + one latest-only slot per key, fed by Zenoh without Python.

    Zenoh's receiving thread only puts each sample on a ``queue.SimpleQueue`` (a C call, the
    subscriber's callback run in that thread), which is also what the loop waits on: one
    wake-up primitive for every input, waited on with the GIL released. Everything else
    (the payload's bytes, counting, ``seq`` gaps, latest-only overwrites) is done when the
    samples are taken in (:meth:`absorb`), by the loop in :meth:`get` or by whoever reads the
    counters first (the status queryable, a test). Python code in Zenoh's thread, or in the
    thread zenoh-python starts by default to run a Python callback, cost 60 to 100 us more a
    64 KiB message here than a zenoh ``RingChannel`` read in a loop: that thread's Python
    state and the GIL going back and forth between threads; this costs what the ring does
    (measured with two processes on this machine, see ``vistrack bench pipeline``).

    Why not one zenoh RingChannel(1) per latest-only key and a FifoChannel per reliable one:
    ``recv`` must wait on *any* input, and their ``recv`` has no timeout.

    Reliable samples count against ``capacity`` from their arrival: when it is reached the
    callback of a reliable subscription waits (``block``: backpressure through Zenoh, whose
    BLOCK publishers then wait) or :meth:`arrive` raises :class:`BusError` (not ``block``).
    """

    def __init__(self, capacity: int, *, block: bool, status: Status) -> None:
        if capacity < 1:
            raise ValueError(f"capacity={capacity} must be >= 1")
        self._capacity = capacity
        self._block = block
        self._status = status
        self._lock = threading.Lock()
        self._loop_waiting = False  # the loop waits on ``arrivals`` in get()
        self._reliable: collections.deque[tuple[str, bytes]] = collections.deque()
        # dict order = order in which slots became pending; an overwrite keeps the position
        self._latest: dict[str, bytes] = {}
        self._latest_block: set[str] = set()  # latest-only keys whose payload came BLOCK
        #: whether the payload get() last handed out was sent BLOCK (see Node.answer_reliably)
        self.last_block = False
        #: what Zenoh's callbacks put (samples) and wake-up tokens (None)
        self.arrivals: queue.SimpleQueue[zenoh.Sample | None] = queue.SimpleQueue()
        self._routes: list[tuple[zenoh.KeyExpr, _Route]] = []
        self._route_of: dict[str, _Route] = {}  # key of a sample -> its subscription's route
        # reliable samples arrived and not yet taken (block mode): the callbacks wait on it
        self._room = threading.Condition(threading.Lock())
        self._reliable_pending = 0
        self._closed = False
        self.taken = 0  # payloads handed out by get()

    # -- Zenoh's side ---------------------------------------------------------------------
    def add_route(self, key: str, route: _Route) -> None:
        with self._lock:
            self._routes.append((zenoh.KeyExpr(key), route))
            self._route_of.clear()

    def remove_route(self, route: _Route) -> None:
        """Stop taking in samples for ``route``: those Zenoh has queued for it and not yet
        taken in are dropped (a payload already taken in stays pending: it was accepted)."""
        with self._lock:
            self._routes = [(e, r) for e, r in self._routes if r is not route]
            self._route_of.clear()

    def reliable_callback(self) -> Callable[[zenoh.Sample], None]:
        """The callback of a reliable subscription: waits while ``capacity`` reliable
        payloads are pending, then queues the sample (block mode)."""
        put, room, capacity = self.arrivals.put, self._room, self._capacity

        def on_sample(sample: zenoh.Sample) -> None:
            with room:
                while self._reliable_pending >= capacity and not self._closed:
                    room.wait(_STOP_POLL_S)
                self._reliable_pending += 1
            put(sample)
        return on_sample

    # -- the loop's side ------------------------------------------------------------------
    def absorb(self) -> int:
        """Take in every sample Zenoh has queued (from a reader of the counters); return how
        many. Nothing while the loop waits in :meth:`get`: it takes them in itself at once,
        and a sample it has just been handed must go in before any that came after it."""
        with self._lock:
            return 0 if self._loop_waiting else self._absorb()

    def _absorb(self) -> int:
        taken = 0
        arrivals = self.arrivals
        # only one thread takes from it at a time: one holding the lock, or the loop waiting
        # in get() (when absorb() takes nothing)
        while not arrivals.empty():
            sample = arrivals.get_nowait()
            if sample is not None:
                self._take_in(sample)
                taken += 1
        return taken

    def wake(self) -> None:
        self.arrivals.put(None)

    def _take_in(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        route = self._route_of.get(key)
        if route is None:
            route = self._route(key)
            if route is None:  # queued before its subscription was undeclared
                return
        if sample.kind != _PUT:
            if not route.latest:
                self._release_room()
            return
        source, session = _source_name(sample)
        self._arrive(key, sample.payload.to_bytes(), source, route,
                     sample.congestion_control == _BLOCK, session)

    def _route(self, key: str) -> _Route | None:
        # a key two subscriptions match (a wildcard and an exact one) arrives once for each:
        # the first subscription's mode, or reliable if any is (lose nothing). None: the
        # subscription was undeclared after Zenoh queued the sample (a latest-only one: a
        # reliable subscription is never undeclared but at close)
        matches = [route for expr, route in self._routes if expr.intersects(key)]
        route = next((r for r in matches if not r.latest), matches[0] if matches else None)
        if route is not None:
            self._route_of[key] = route
        return route

    def arrive(self, key: str, payload: bytes, source: str | None, route: _Route,
               block: bool = False) -> None:
        """Count ``payload`` (from the publisher ``source``, sent BLOCK if ``block``) and queue
        it per ``route``.

        Raises
        ------
        BusError
            In non-block mode, if ``capacity`` reliable payloads are pending.
        """
        with self._lock:
            self._arrive(key, payload, source, route, block)

    def _arrive(self, key: str, payload: bytes, source: str | None, route: _Route,
                block: bool, session: str | None = None) -> None:
        if self._closed:
            return
        # a stream is followed by the publishing process (its session): one process may put
        # a key through two publishers (motion-estimation answers a frame that came BLOCK
        # with its BLOCK publisher, one that came latest-only with the other)
        if route.latest and not route.follows(key, source if session is None else session):
            self._status.count_other()
            return
        missing = route.gaps.update(key, payload, source)
        if route.latest:
            overwritten = key in self._latest
            self._latest[key] = payload
            if block:
                self._latest_block.add(key)
            else:
                self._latest_block.discard(key)
            missing += overwritten
        else:
            if not self._block and len(self._reliable) >= self._capacity:
                raise BusError(f"inbox full ({self._capacity} reliable payloads "
                               "pending): consume with recv() first")
            self._reliable.append((key, payload))
        self._status.count_arrivals(1, missing)

    def _release_room(self) -> None:
        if self._block:
            with self._room:
                self._reliable_pending -= 1
                self._room.notify()

    def get(self, timeout: float, stop: threading.Event) -> tuple[str, bytes] | None:
        deadline = -1.0
        get = self.arrivals.get
        sample: zenoh.Sample | None = None
        while True:
            with self._lock:
                self._loop_waiting = False
                if sample is not None:
                    self._take_in(sample)
                    sample = None
                self._absorb()
                if self._reliable:
                    item = self._reliable.popleft()
                    self._release_room()
                    self.taken += 1
                    self.last_block = True  # all of it must be processed: so must its answers
                    return item
                if self._latest:
                    key = next(iter(self._latest))
                    self.taken += 1
                    self.last_block = key in self._latest_block
                    return key, self._latest.pop(key)
                now = _monotonic()
                if deadline < 0.0:
                    deadline = now + max(0.0, timeout)
                remaining = deadline - now
                if self._closed or remaining <= 0 or stop.is_set():
                    return None
                self._loop_waiting = True
            try:
                sample = get(timeout=min(remaining, _STOP_POLL_S))
            except queue.Empty:
                pass

    def close(self) -> None:
        with self._lock:
            self._closed = True
        with self._room:
            self._room.notify_all()
        self.wake()

    def pending(self) -> int:
        """Payloads queued and not yet taken."""
        with self._lock:
            if not self._loop_waiting:
                self._absorb()
            return len(self._reliable) + len(self._latest)


class _StopEvent(threading.Event):
    """``Node.stop``: a :class:`threading.Event` whose ``set`` also wakes the loop's wait in
    :meth:`_Inbox.get` (a wake-up token on its queue).

    The wait is ``queue.SimpleQueue.get(timeout)`` in slices of ``_STOP_POLL_S``. When a
    signal handler runs during it and takes longer than what was left of the slice, CPython
    3.11 waits again with the negative time left, which its lock takes for "forever"
    (``_queuemodule.c`` recomputes the timeout without the check ``threading.Lock`` has): the
    loop then slept until the next message, however set ``stop`` was. A service stopped by
    SIGINT or SIGTERM while nothing came in hung (4 of 100 in a loop; the process was killed
    at its stop deadline, its session not closed); a handler that sleeps 0.2 s hangs it every
    time. The token ends that wait."""

    def __init__(self, wake: Callable[[], None]) -> None:
        super().__init__()
        self._wake = wake

    def set(self) -> None:
        super().set()
        self._wake()


# -- nodes --------------------------------------------------------------------------------

class Node(abc.ABC):
    """What a service loop sees of the bus.

    Parameters
    ----------
    service : the service name (key chunk; see ``keys.SERVICES``).
    robot : robot id, default ``"robot"``.
    capacity : reliable payloads queued before arrival blocks (:class:`ZenohNode`) or
        raises (:class:`MemoryNode`).

    Attributes
    ----------
    service, robot : as given.
    keys : :class:`~vistrack.common.keys.Keys` of ``robot``.
    status : the node's :class:`Status`; ``received``/``dropped``/``published`` are counted
        here, ``rejected`` and processing times by the service.
    stop : set to end the service loop (signal handlers, tests, launcher); ``recv`` returns
        None promptly once it is set and nothing is pending.
    """

    # What arrival does when ``capacity`` reliable payloads are pending: block (backpressure
    # through the transport) or raise BusError (in-memory: the feeder is the consumer too).
    _BLOCK_WHEN_FULL: ClassVar[bool] = True

    def __init__(self, service: str, robot: str = "robot", *,
                 capacity: int = DEFAULT_CAPACITY) -> None:
        self.service = validate_service_name(service)
        self.robot = validate_robot_id(robot)
        self.keys = Keys(robot)
        self.status = Status()
        self._inbox = _Inbox(capacity, block=self._BLOCK_WHEN_FULL, status=self.status)
        self.stop = _StopEvent(self._inbox.wake)
        self.status.absorb = self._inbox.absorb
        self._subscriptions: dict[str, _Route] = {}
        self._closed = False
        # when the loop last came back from waiting (recv, sleep); None while it waits and
        # before it first does: see busy_s
        self._busy_since: float | None = None
        self.alive = False  # the liveliness token is declared (declare_alive)

    # -- the service-facing API ---------------------------------------------------------------
    def subscribe(self, key: str, *, latest: bool) -> None:
        """Receive payloads published on ``key`` (a full key expression).

        ``latest=True`` for inputs where only the newest matters (frames, estimates),
        ``latest=False`` for inputs that must all be processed in order (params, commands).
        Subscribing again with the same mode is a no-op.
        """
        if self._closed:
            raise BusError(f"node {self.service!r} is closed")
        if key in self._subscriptions:
            if self._subscriptions[key].latest != latest:
                raise BusError(f"{key} is already subscribed with latest="
                               f"{self._subscriptions[key].latest}")
            return
        route = _Route(latest)
        self._inbox.add_route(key, route)
        self._declare(key, route)
        self._subscriptions[key] = route

    def unsubscribe(self, key: str) -> None:
        """Stop receiving ``key`` (subscribed latest-only): the network no longer sends its
        samples here, which is what a service taking only some frames saves (a router
        forwards, and Zenoh's thread queues, every sample of a subscription). A payload
        already taken in stays pending; one Zenoh had queued and not yet handed over is
        dropped, as a newer one would have replaced it. Subscribing again starts the key's
        ``seq`` count afresh: the samples not subscribed to are not losses. A no-op if
        ``key`` is not subscribed.

        Raises
        ------
        BusError
            If ``key`` is subscribed reliably (``latest=False``): what such a subscription
            has not yet received would be lost.
        """
        route = self._subscriptions.get(key)
        if route is None or self._closed:
            return
        if not route.latest:
            raise BusError(f"{key} is subscribed with latest=False: it cannot be "
                           "unsubscribed without losing what is in flight")
        del self._subscriptions[key]
        self._undeclare(key)
        self._inbox.remove_route(route)

    def subscribed(self, key: str) -> bool:
        """Whether ``key`` is subscribed (:meth:`subscribe`, not since :meth:`unsubscribe`)."""
        return key in self._subscriptions

    def declare_alive(self) -> None:
        """Declare the liveliness token ``vistrack/<robot>/alive/<service>`` (if not yet):
        the service is ready, warmed up and subscribed to its inputs. Launchers wait for it
        before they start the services upstream; idempotent."""
        if self._closed:
            raise BusError(f"node {self.service!r} is closed")
        if not self.alive:
            self._declare_token()
            self.alive = True

    def recv(self, timeout: float) -> tuple[str, bytes] | None:
        """The next ``(key, payload)`` from any subscribed key, or None after ``timeout`` s
        (or once ``stop`` is set or the node is closed, with nothing pending)."""
        self._busy_since = None
        item = self._inbox.get(timeout, self.stop)
        self._busy_since = _monotonic()
        return item

    @property
    def answer_reliably(self) -> bool:
        """Whether what answers the payload :meth:`recv` last returned must reach every
        subscriber: the payload was sent BLOCK (``reliable=True``, as a camera in lockstep
        sends its frames), or came on a subscription with ``latest=False``. A stage answers
        such a frame with ``publish(..., reliable=node.answer_reliably)``: with one frame in
        flight BLOCK queues no backlog, and a recorder of a file's run loses no estimate
        (BLOCK_FIRST, at a router's hop to a client, lost one now and then at start-up)."""
        return self._inbox.last_block

    def sleep(self, seconds: float) -> bool:
        """Wait ``seconds`` (a loop's pacing) or until ``stop`` is set; True if it was.
        Time spent here is waiting, not work, for :attr:`busy_s`."""
        self._busy_since = None
        try:
            return self.stop.wait(seconds)
        finally:
            self._busy_since = time.monotonic()

    def wait_event(self, event: threading.Event, timeout: float) -> bool:
        """Wait until ``event`` is set (True), or ``timeout`` s pass or ``stop`` is set
        (False): a loop whose input comes through a callback of its own. Time spent here is
        waiting, not work, for :attr:`busy_s`."""
        self._busy_since = None
        try:
            deadline = time.monotonic() + timeout
            while not self.stop.is_set():
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                if event.wait(min(left, 0.1)):
                    return True
            return False
        finally:
            self._busy_since = time.monotonic()

    @property
    def busy_s(self) -> float:
        """Seconds the loop has been working since it last waited (in :meth:`recv`,
        :meth:`sleep` or :meth:`wait_for_subscribers`); 0 while it waits and before its first
        wait. Reported in the status: a loop stuck on one input shows here while Zenoh's
        threads still answer the status query."""
        since = self._busy_since
        return 0.0 if since is None else max(0.0, time.monotonic() - since)

    def advertise(self, key: str, *, reliable: bool) -> None:
        """Declare the publisher of ``key`` now, before the loop is ready: declaring it on the
        first :meth:`publish` put 0.2 to 18 ms into the first frame's latency."""
        if self._closed:
            raise BusError(f"node {self.service!r} is closed: cannot publish on {key}")
        self._advertise(key, reliable)

    def has_subscribers(self, key: str, *, reliable: bool = True) -> bool:
        """Whether a subscriber anywhere on the network matches ``key`` (declares and caches
        the publisher of ``key``). Always True in memory, where the test is the network."""
        return self._has_subscribers(key, reliable)

    def wait_for_subscribers(self, key: str, *, reliable: bool, timeout: float) -> bool:
        """Wait until a subscriber matches ``key``; False after ``timeout`` s or on stop.

        A process that has just joined learns of the subscriptions already declared a moment
        after its session opens: what it publishes before that reaches nobody. A source that
        must lose nothing (a file camera) waits for this before its first frame.
        """
        deadline = time.monotonic() + timeout
        self._busy_since = None
        try:
            while not self.has_subscribers(key, reliable=reliable):
                if self.stop.wait(0.01) or time.monotonic() >= deadline:
                    return False
            self._settle(deadline)
            return True
        finally:
            self._busy_since = time.monotonic()

    def publish(self, key: str, payload: bytes, *, reliable: bool) -> None:
        """Publish ``payload`` on ``key``.

        ``reliable=True`` (parameters, reports, commands) blocks rather than drop under
        congestion; ``reliable=False`` (frames, estimates) never blocks for long: under
        congestion the network keeps the one message in flight and drops newer ones (see
        :data:`LATEST_CONGESTION`).
        """
        if self._closed:
            raise BusError(f"node {self.service!r} is closed: cannot publish on {key}")
        self._send(key, bytes(payload), reliable)
        self.status.count_published()

    def close(self) -> None:
        """Stop receiving and release everything; idempotent."""
        if self._closed:
            return
        self._closed = True
        self._inbox.close()
        self._release()

    def __enter__(self: _N) -> _N:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    # -- the transport seam -------------------------------------------------------------------
    @abc.abstractmethod
    def _declare(self, key: str, route: _Route) -> None:
        """Start delivering payloads of ``key`` to the inbox, taken in per ``route``."""

    @abc.abstractmethod
    def _undeclare(self, key: str) -> None:
        """Stop delivering payloads of ``key`` (declared by :meth:`_declare`)."""

    @abc.abstractmethod
    def _send(self, key: str, payload: bytes, reliable: bool) -> None:
        """Put ``payload`` on ``key``."""

    @abc.abstractmethod
    def _advertise(self, key: str, reliable: bool) -> None:
        """Prepare to publish on ``key``."""

    @abc.abstractmethod
    def _has_subscribers(self, key: str, reliable: bool) -> bool:
        """Whether a subscriber matches ``key``."""

    @abc.abstractmethod
    def _settle(self, deadline: float) -> None:
        """Once a subscriber matches, wait (until ``deadline`` at most) for the transport's
        links to stop changing."""

    @abc.abstractmethod
    def _declare_token(self) -> None:
        """Declare the liveliness token."""

    @abc.abstractmethod
    def _release(self) -> None:
        """Release transport resources (called once, by :meth:`close`)."""


class Published(NamedTuple):
    """One payload a :class:`MemoryNode` published."""

    key: str
    payload: bytes
    reliable: bool


class MemoryNode(Node):
    """:class:`Node` in memory, for testing a service loop in-process.

    ``feed(key, payload, source=None)`` plays a payload arriving from the network (from the
    publisher ``source``): it is delivered to every matching subscription with exactly
    :class:`ZenohNode`'s semantics (counters, latest-only overwrite, seq gaps per publisher).
    Published payloads are appended to ``published``.
    """

    _BLOCK_WHEN_FULL: ClassVar[bool] = False

    def __init__(self, service: str = "test", robot: str = "robot", *,
                 capacity: int = DEFAULT_CAPACITY) -> None:
        super().__init__(service, robot, capacity=capacity)
        self._waiting_after = 0  # inbox.taken when the loop last began to wait (wait_idle)
        self.published: list[Published] = []
        self._deliver: dict[str, tuple[zenoh.KeyExpr, _Route]] = {}
        self._published_lock = threading.Lock()

    def feed(self, key: str, payload: bytes, source: str | None = None, *,
             reliable: bool = False) -> bool:
        """Deliver ``payload`` as if published on ``key`` by the publisher ``source`` (None:
        one without a source id), sent BLOCK if ``reliable``; False if no subscription
        matches.

        Raises
        ------
        BusError
            If the reliable queue is full (a test would deadlock waiting for itself).
        """
        matched = False
        for expr, route in list(self._deliver.values()):
            if expr.intersects(key):
                self._inbox.arrive(key, bytes(payload), source, route, reliable)
                matched = True
        if matched:
            self._inbox.wake()
        return matched

    def published_on(self, key: str) -> list[bytes]:
        """Payloads published on ``key``, in order."""
        with self._published_lock:
            return [p.payload for p in self.published if p.key == key]

    def recv(self, timeout: float) -> tuple[str, bytes] | None:
        self._waiting_after = self._inbox.taken  # everything taken so far has been handled
        return super().recv(timeout)

    def sleep(self, seconds: float) -> bool:
        self._waiting_after = self._inbox.taken
        return super().sleep(seconds)

    def wait_idle(self, timeout: float) -> bool:
        """Wait until every fed payload has been taken and the loop (in another thread) is
        waiting in :meth:`recv` or :meth:`sleep` again: what it did with them is done. False
        after ``timeout`` s."""
        deadline = time.monotonic() + timeout
        while (self._inbox.pending() or self._busy_since is not None
               or self._waiting_after != self._inbox.taken):
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.0005)
        return True

    def _declare(self, key: str, route: _Route) -> None:
        self._deliver[key] = (zenoh.KeyExpr(key), route)

    def _undeclare(self, key: str) -> None:
        del self._deliver[key]

    def _advertise(self, key: str, reliable: bool) -> None:
        pass  # in memory there is nothing to declare

    def _declare_token(self) -> None:
        pass  # nor a token: ``alive`` tells a test the service said it was ready

    def _has_subscribers(self, key: str, reliable: bool) -> bool:
        return True

    def _settle(self, deadline: float) -> None:
        pass  # in memory every subscription is there at once

    def _send(self, key: str, payload: bytes, reliable: bool) -> None:
        with self._published_lock:
            self.published.append(Published(key, payload, reliable))

    def _release(self) -> None:
        self._deliver.clear()


class ZenohNode(Node):
    """:class:`Node` over a Zenoh session.

    Opening declares a queryable on ``vistrack/<robot>/<service>/status`` that replies a
    msgpack map ``{v: 1, service, robot, pid, uptime_s, busy_s, **status.as_dict()}``, and
    the liveliness token ``vistrack/<robot>/alive/<service>``; with ``alive_at_open=False``
    the token waits for :meth:`declare_alive` (a service declares it once it is ready, so
    that "alive" means "takes input", which launchers wait for). Always use it as a context
    manager (or call :meth:`close`): a session with callback subscribers left open hangs the
    interpreter at exit.

    Subscriptions use callbacks run in Zenoh's receiving thread that only queue the sample
    for the loop (see :class:`_Inbox`). When ``capacity`` reliable payloads are pending the
    callback of a reliable key blocks,
    which stalls that Zenoh link and, through BLOCK congestion control, the reliable
    publishers: backpressure instead of loss or unbounded memory.

    A latest-only key's callback is ``SimpleQueue.put`` itself, a C function: a Python one,
    however short (a single-slot hand-off that drops the pending sample), cost 45 to 100 us
    a hop here, the loop and Zenoh's thread handing the GIL back and forth. So the older
    samples are dropped when taken in, by the loop or a reader of the counters; a thread of
    the node's does it every :data:`SWEEP_S` s while the loop is not waiting and something
    is queued, so a loop that is busy, stalled, or run by hand with nobody asking
    its status holds the newest payload of the key and what came in the last 0.1 s, not
    every frame since it stopped.

    Publishers are declared once per (key, reliable) and cached; ``reliable`` selects
    congestion control BLOCK, otherwise BLOCK_FIRST (:func:`congestion`).

    Raises
    ------
    BusError
        If the session cannot be opened.
    """

    def __init__(self, service: str, conf: zenoh.Config, robot: str = "robot", *,
                 capacity: int = DEFAULT_CAPACITY, alive_at_open: bool = True) -> None:
        super().__init__(service, robot, capacity=capacity)
        self._publishers: dict[tuple[str, bool], SourcedPublisher] = {}
        self._publishers_lock = threading.Lock()
        self._subscribers: dict[str, zenoh.Subscriber] = {}
        self._token: zenoh.LivelinessToken | None = None
        self.session = open_session(conf)
        try:
            self._queryable = self.session.declare_queryable(self.keys.status(service),
                                                             self._on_status_query)
            if alive_at_open:
                self.declare_alive()
        except BaseException:
            self.session.close()
            raise
        self._sweeping = threading.Event()
        self._sweeper = threading.Thread(target=self._sweep, name=f"{service}-inbox-sweep",
                                         daemon=True)
        self._sweeper.start()

    def _sweep(self) -> None:
        queued = self._inbox.arrivals.qsize
        while not self._sweeping.wait(SWEEP_S):
            if queued():
                self._inbox.absorb()  # nothing while the loop waits: it takes them in itself

    def _declare_token(self) -> None:
        self._token = self.session.liveliness().declare_token(self.keys.alive(self.service))

    def status_reply(self) -> dict[str, Any]:
        """The map the status queryable replies."""
        return {"service": self.service, "robot": self.robot, "pid": os.getpid(),
                "uptime_s": self.status.uptime_s, "busy_s": self.busy_s,
                **self.status.as_dict()}

    def _settle(self, deadline: float) -> None:
        # A peer that has just joined opens direct links to the other peers one after the
        # other, a few ms apart; a key matches as soon as the first link that carries one of
        # its subscriptions is up, and a sample published then may miss a subscriber whose
        # link is not (the first frame of a file was lost once in twenty runs). Wait until the
        # set of connected peers has not changed for SETTLE_S.
        peers = {str(z) for z in self.session.info.peers_zid()}
        since = time.monotonic()
        while time.monotonic() - since < SETTLE_S and time.monotonic() < deadline:
            if self.stop.wait(0.01):
                return
            now = {str(z) for z in self.session.info.peers_zid()}
            if now != peers:
                peers, since = now, time.monotonic()

    def _has_subscribers(self, key: str, reliable: bool) -> bool:
        # the 1.x stub says bool, but the binding returns an (always truthy) MatchingStatus
        status = self._publisher(key, reliable).publisher.matching_status
        return bool(getattr(status, "matching", status))

    def _on_status_query(self, query: zenoh.Query) -> None:
        try:
            query.reply(self.keys.status(self.service), pack(self.status_reply()))
        except zenoh.ZError as err:  # the session is closing or the querier went away
            log.debug("status reply failed: %s", err)

    def _declare(self, key: str, route: _Route) -> None:
        # Zenoh's receiving thread runs the callback itself (indirect=False), not a thread
        # zenoh-python would start for it: for a latest-only key the callback is the C
        # function that queues the sample for the loop (see _Inbox); a reliable key's waits
        # for room first (backpressure).
        on_sample = self._inbox.arrivals.put if route.latest else \
            self._inbox.reliable_callback()
        self._subscribers[key] = self.session.declare_subscriber(
            key, zenoh.handlers.Callback(on_sample, indirect=False))

    def _undeclare(self, key: str) -> None:
        try:
            self._subscribers.pop(key).undeclare()
        except zenoh.ZError as err:  # the session is closing
            log.debug("undeclare of the subscriber of %s failed: %s", key, err)

    def _publisher(self, key: str, reliable: bool) -> SourcedPublisher:
        with self._publishers_lock:
            pub = self._publishers.get((key, reliable))
            if pub is None:
                pub = SourcedPublisher(self.session.declare_publisher(
                    key, congestion_control=congestion(reliable)))
                self._publishers[(key, reliable)] = pub
            return pub

    def _advertise(self, key: str, reliable: bool) -> None:
        self._publisher(key, reliable)

    def _send(self, key: str, payload: bytes, reliable: bool) -> None:
        self._publisher(key, reliable).put(payload)

    def _release(self) -> None:
        self._sweeping.set()
        if self._sweeper is not threading.current_thread():
            self._sweeper.join(1.0)
        # Undeclare in reverse order of use, then close: subscribers first so no callback
        # runs against a closing session; every step is attempted even if one fails.
        entities: list[Any] = [*self._subscribers.values(), self._queryable,
                               *([self._token] if self._token is not None else []),
                               *self._publishers.values()]
        for entity in entities:
            try:
                entity.undeclare()
            except zenoh.ZError as err:
                log.debug("undeclare failed: %s", err)
        self._subscribers.clear()
        self._publishers.clear()
        self.session.close()


# -- process helpers ----------------------------------------------------------------------

#: The signals that stop a process in order: SIGHUP too (a terminal or SSH session that
#: went), which killed the launcher at once, its children then all at the same moment by
#: their parent-death signal, the ros2 bridge perhaps before the controller's last stop.
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


#: Set to "1" by `vistrack up` in its services' environment: a service stopped by a signal
#: then exits 128 + the signal's number, not 0, so that the launcher tells a stop from outside
#: (restarted under ``restart: on-failure``) from a service's end
SUPERVISED_ENV = "VISTRACK_SUPERVISED"


def install_signal_handlers(stop: threading.Event, received: list[int] | None = None
                            ) -> Callable[[], None]:
    """Make SIGINT, SIGTERM and SIGHUP set ``stop`` so the service loop ends and closes its
    session; each such signal is appended to ``received`` where given.

    A second SIGINT raises KeyboardInterrupt, so a stuck process can still be interrupted.
    Signal handlers can only be installed from the main thread; elsewhere (a service run in
    a test thread) this does nothing.

    Returns
    -------
    restore : call to put the previous handlers back.
    """
    if threading.current_thread() is not threading.main_thread():
        return lambda: None

    requested = False

    def handler(signum: int, frame: FrameType | None) -> None:
        # No logging and no lock here: the handler runs on the main thread between bytecodes,
        # possibly inside Event.wait() or inside an earlier run of itself (a burst of
        # parent-death SIGTERMs, one per exiting launcher thread), and Event.set() takes the
        # lock that code may hold: a deadlock. A helper thread sets the event instead.
        nonlocal requested
        if received is not None:
            received.append(signum)
        if signum == signal.SIGINT and stop.is_set():
            raise KeyboardInterrupt
        if not requested:
            requested = True
            threading.Thread(target=stop.set, name="stop-request", daemon=True).start()

    previous = {sig: signal.signal(sig, handler) for sig in STOP_SIGNALS}

    def restore() -> None:
        for sig, old in previous.items():
            signal.signal(sig, old)
    return restore


def query_status(session: zenoh.Session, keys: Keys, timeout: float = 1.0) -> list[dict]:
    """Status maps of every live service of ``keys.robot``, sorted by service name.

    Replies that are errors or not valid status maps are logged and skipped.
    """
    statuses = []
    # every answer, two processes of one service's name included (the default consolidation
    # keeps one reply a key)
    replies = session.get(keys.status_any(), target=zenoh.QueryTarget.ALL, timeout=timeout,
                          consolidation=zenoh.ConsolidationMode.NONE)
    for reply in replies:
        if reply.ok is None:
            err = reply.err
            text = err.payload.to_string() if err is not None else "(empty)"
            # Zenoh's own reply for a queryable that did not answer in time (a service busy
            # or starting): the callers count it as not answering, so it is no warning (a
            # bare "status query error reply: Timeout" line in replay --wait's output)
            (log.debug if text == "Timeout" else log.warning)(
                "status query error reply: %s", text)
            continue
        try:
            statuses.append(unpack(reply.ok.payload.to_bytes()))
        except MessageError as err:
            log.warning("bad status reply on %s: %s", reply.ok.key_expr, err)
    return sorted(statuses, key=lambda s: str(s.get("service", "")))


def service_status(session: zenoh.Session, keys: Keys, service: str, timeout: float
                   ) -> dict[str, Any] | None:
    """One service's status reply (a map), or None if it did not answer with one."""
    for reply in session.get(keys.status(service), timeout=timeout):
        if reply.ok is None:
            continue
        try:
            status = unpack(reply.ok.payload.to_bytes())
        except MessageError:
            continue
        if isinstance(status, dict):
            return status
    return None


def alive_services(session: zenoh.Session, keys: Keys, timeout: float = 1.0) -> list[str]:
    """Names of the services of ``keys.robot`` whose liveliness token is present, sorted."""
    return sorted(token_names(session, keys.alive_any(), timeout))


def token_names(session: zenoh.Session, expr: str, timeout: float = 1.0) -> set[str]:
    """The last chunk of every liveliness token present under ``expr`` (a service's name, a
    launcher's Zenoh id)."""
    return {str(reply.ok.key_expr).rsplit("/", 1)[-1]
            for reply in session.liveliness().get(expr, timeout=timeout)
            if reply.ok is not None}
