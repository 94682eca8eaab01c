"""What the command-line tools share (``echo``, ``hz``, ``status``, ``params``, ``record``,
``replay``, ``export``, ``foxglove``): one-line errors, the session, signals, recorded samples, a
sample inbox, service status, tables.

Each tool is its own module under ``vistrack.services.tools`` (``add_arguments(parser)`` and
``main(args) -> exit code``, as ``cli.py`` expects), modelled on ``ros2 topic`` and dora's CLI
but smaller. Exit codes: 0 success, 1 a runtime failure (timeout, nothing answered), 2 a usage
error (bad key, bad value, bad file, bad Zenoh flags), 130 interrupted twice.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import queue
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import zenoh

from ...common.bus import (
    BusError,
    add_zenoh_args,
    alive_services,
    check_connected,
    config_from_args,
    install_signal_handlers,
    open_session,
    query_status,
    source_of,
)
from ...common.keys import (
    CONTRACT_SUFFIXES,
    OPTIONAL_SERVICES,
    SERVICES,
    Keys,
    key_suffix,
)
from ..usage import print_error

#: How long a tool given ``-e ENDPOINT`` tries to connect before it says nothing is there.
CONNECT_TIMEOUT_S = 5.0
#: How long ``echo`` and ``hz`` wait for a first sample before saying what they wait for.
WAITING_NOTICE_S = 2.0


class ToolError(Exception):
    """A failure a tool reports as one line ``vistrack <tool>: error: ...``.

    Parameters
    ----------
    message : what went wrong, naming the key, field, file or service.
    code : exit code: 2 for usage errors (bad input from the user), 1 for runtime failures.
    """

    def __init__(self, message: str, code: int = 1) -> None:
        super().__init__(message)
        self.code = code


def add_tool_args(parser: argparse.ArgumentParser) -> None:
    """The Zenoh flags of the command line contract (``-m -e -l -c --no-multicast-scouting
    --robot``)."""
    add_zenoh_args(parser)


#: Where a tool's gossip goes, by the tool's mode (:func:`as_a_tool`): a peer's to routers.
TOOL_GOSSIP_TARGET = '{"router": [], "peer": ["router"]}'


def as_a_tool(conf: zenoh.Config, args: argparse.Namespace) -> zenoh.Config:
    """``conf`` (from the Zenoh flags) for a tool, which looks at a system and never joins two.

    * It gossips to routers only, never to peers. A peer passes on to its neighbours the
      locators of the nodes it reaches, and the services (peers, which connect to every peer
      gossip names) took those of another system: one ``vistrack status`` that reached two
      ``vistrack up`` on one machine (multicast scouting finds every router; two ``-e`` name
      two) joined their services for good, every frame of each then reaching both (two demos
      read 67 and 74 fps and centring errors of 263 and 415 px, and said nothing). Its
      gossip to a router tells that router where the tool listens, and the router tells its
      own peers, so the tools of one system reach each other: a router does not relay
      between peers, and with no gossip at all ``vistrack record`` (or ``echo``, ``hz``,
      ``foxglove``) never received what ``vistrack replay`` or ``params set`` published
      beside it (0 samples, exit 0). It still takes gossip in, to reach the services it
      looks at.
    * With ``-e`` it scouts no multicast: the endpoints name the system it looks at, and
      ``-e`` at a port where nothing answers said nothing of it while another system on the
      machine answered the scouting.

    A config file (``-c``) that sets either is left as it says (``--no-multicast-scouting``
    is what the flag says).

    Raises
    ------
    BusError
        For ``-m router``: a router routes between everything it reaches, and a tool run so
        with an ``-e`` to each of two systems joined them (each service then took the other
        system's samples, and their launchers killed services whose status queries the other
        system answered)."""
    if conf.get_json("mode") == '"router"':
        where = "-m router" if getattr(args, "mode", None) == "router" else \
            f"{args.config}: mode router"
        raise BusError(f"{where}: a tool does not run as a router (it would route between "
                       "the systems it reaches): allowed peer (the default) or client")
    unset = zenoh.Config()
    for key, value, when in (
            ("scouting/gossip/target", TOOL_GOSSIP_TARGET, True),
            ("scouting/multicast/enabled", "false", bool(args.connect))):
        if when and conf.get_json(key) == unset.get_json(key):
            conf.insert_json5(key, value)
    return conf


def error(tool: str, message: object) -> None:
    """Print the one-line error of ``tool`` on stderr."""
    print_error(tool, message)


def warn(tool: str, message: object) -> None:
    """Print a one-line warning of ``tool`` on stderr."""
    print(f"vistrack {tool}: warning: {message}", file=sys.stderr, flush=True)


def resolve_key(keys: Keys, key: str, tool: str | None = None) -> str:
    """``keys.resolve(key)`` with a bad key as a usage error; with ``tool``, a warning when
    the key, without wildcards, is none of vistrack's (``vistrack echo done`` listened on
    ``vistrack/robot/done`` in silence for ever: the key is ``preprocessing/done``, its
    name ``pre_done``)."""
    try:
        full = keys.resolve(key)
    except ValueError as e:
        raise ToolError(str(e), code=2) from None
    suffix = key_suffix(full)
    if tool is not None and "*" not in full and suffix not in CONTRACT_SUFFIXES.values():
        names = ", ".join(f"{v} ({k})" for k, v in CONTRACT_SUFFIXES.items())
        if suffix in _QUERYABLES:
            what = ("is a queryable, answered when asked, never published: `vistrack status` "
                    "asks it")
        elif suffix in _TOKENS:
            what = ("is a liveliness token, never published: `vistrack status` lists the "
                    "live services")
        else:
            what = "is none of vistrack's keys"
        warn(tool, f"{key!r} {what}; listening on {full} all the same. The keys published "
                   f"(and their short names): {names}")
    return full


_ALL_SERVICES = (*SERVICES, *OPTIONAL_SERVICES)
#: The keys after ``vistrack/<robot>/`` that are answered (status) or declared (liveliness),
#: not published: nothing comes to a subscriber there.
_QUERYABLES = frozenset(f"{s}/status" for s in _ALL_SERVICES)
_TOKENS = frozenset(f"alive/{s}" for s in _ALL_SERVICES)


def run(tool: str, args: argparse.Namespace,
        body: Callable[[zenoh.Session, Keys], int], *,
        connect_timeout: float | None = None) -> int:
    """Open the Zenoh session of ``args``, run ``body(session, keys)``, close the session.

    Every expected failure becomes one line on stderr and an exit code (2 for bad flags, 1 for
    a session that does not open or, given ``-e``, reaches nothing there within
    ``connect_timeout`` s, default ``CONNECT_TIMEOUT_S``: a tool whose own flag says how long
    it may wait, such as ``echo --timeout``, waits that long for the router too, so a script
    can start it beside a ``vistrack up &`` that is still starting); a closed stdout
    (``vistrack echo ... | head``) ends the tool quietly with 0.
    """
    try:
        conf = as_a_tool(config_from_args(args), args)
        keys = Keys(args.robot)
    except BusError as e:  # the flags: a usage error, as for the services
        error(tool, e)
        return 2
    try:
        with open_session(conf) as session:
            if args.connect:  # an absent router: an error after a while, not silence
                check_connected(session, conf, max(CONNECT_TIMEOUT_S, connect_timeout or 0.0))
            return int(body(session, keys) or 0)
    except ToolError as e:
        error(tool, e)
        return e.code
    except BusError as e:  # the session did not open (a port in use): a failure, exit 1
        error(tool, e)
        return 1
    except BrokenPipeError:
        _silence_stdout()
        return 0


def _silence_stdout() -> None:
    # The reader went away: point stdout at /dev/null so the interpreter's final flush does
    # not raise a second BrokenPipeError at exit.
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    os.close(devnull)


@contextlib.contextmanager
def stop_on_signals() -> Iterator[threading.Event]:
    """An event set by SIGINT/SIGTERM, so a streaming tool ends its loop, flushes and closes
    its session instead of dying inside a Zenoh call (a second Ctrl-C still interrupts)."""
    stop = threading.Event()
    restore = install_signal_handlers(stop)
    try:
        yield stop
    finally:
        restore()


def print_json(obj: Any) -> None:
    """One JSON line on stdout, flushed (tools are read line by line by other programs)."""
    print(json.dumps(obj, separators=(", ", ": "), allow_nan=False), flush=True)


def has_subscriber(publisher: zenoh.Publisher) -> bool:
    """Whether a subscriber anywhere on the network matches ``publisher``'s key."""
    # the 1.x stub says bool, but the binding returns a MatchingStatus (always truthy)
    status = publisher.matching_status
    return bool(getattr(status, "matching", status))


# -- recordings ------------------------------------------------------------------------------

class RecordError(Exception):
    """A recording is not readable from some byte on.

    Attributes
    ----------
    path : the file.
    offset : byte offset of the first record (or header) that could not be read; None when
        the file itself cannot be read.
    damaged : False where the file is sound but holds what vistrack does not read there (a
        chunk too large to unpack): the tools then do not call it damaged.
    """

    def __init__(self, path: str | Path, offset: int | None, problem: str, *,
                 damaged: bool = True) -> None:
        where = "" if offset is None else f" at byte offset {offset}"
        super().__init__(f"{path}{where}: {problem}")
        self.path = str(path)
        self.offset = offset
        self.damaged = damaged


@dataclass(frozen=True)
class Record:
    """One recorded sample, whatever the file format (``record.py``, ``mcapio.py``)."""

    t_ns: int
    key: str
    payload: bytes
    offset: int  # where it starts in the file (MCAP: the chunk holding it)


# -- receiving samples ------------------------------------------------------------------------

class Received(NamedTuple):
    """One sample as a tool sees it."""

    key: str
    payload: bytes
    t_ns: int  # arrival, wall clock, ns since the Unix epoch
    mono_ns: int  # arrival, monotonic clock, ns (for rates and replay timing)
    source: str | None = None  # the publisher's Zenoh source id, if it sent one


class Inbox:
    """Zenoh subscriber callback that queues samples for the tool's main loop.

    The callback runs on a Zenoh thread and must not block it, so a full queue drops the
    sample and counts it in ``overflow`` instead (the main loop is too slow, e.g. a terminal).

    Parameters
    ----------
    capacity : samples held before new ones are dropped.
    """

    def __init__(self, capacity: int = 10_000) -> None:
        self._queue: queue.Queue[Received] = queue.Queue(capacity)
        self.capacity = capacity
        self.overflow = 0

    def __call__(self, sample: zenoh.Sample) -> None:
        if sample.kind != zenoh.SampleKind.PUT:
            return  # the project never deletes; a DELETE carries no message
        item = Received(str(sample.key_expr), sample.payload.to_bytes(), time.time_ns(),
                        time.monotonic_ns(), source_of(sample))
        try:
            self._queue.put_nowait(item)
        except queue.Full:
            self.overflow += 1

    def get(self, timeout: float) -> Received | None:
        """The next sample, or None after ``timeout`` s."""
        try:
            return self._queue.get(timeout=max(0.0, timeout))
        except queue.Empty:
            return None

    def take(self, most: int = 10_000) -> list[Received]:
        """Every sample waiting (at most ``most``), without waiting: a consumer that takes
        them in batches wakes once a batch, not once a sample."""
        items: list[Received] = []
        try:
            while len(items) < most:
                items.append(self._queue.get_nowait())
        except queue.Empty:
            pass
        return items


def where(args: argparse.Namespace) -> str:
    """Where a tool looks for publishers, for its messages: the ``-e`` endpoints, the
    config file, or the local network."""
    if args.connect:
        return ", ".join(args.connect)
    if args.config:
        return f"the endpoints of {args.config}"
    if args.listen:
        return f"{', '.join(args.listen)} (listening)"
    if getattr(args, "no_multicast_scouting", False):  # nothing reaches it: said so
        return ("no endpoint (--no-multicast-scouting without -e, -l or -c: nothing can be "
                "reached; give -e ENDPOINT for a router)")
    return "the local network (multicast scouting; give -e ENDPOINT for a router)"


class WaitingNotice:
    """Says once on stderr, ``WAITING_NOTICE_S`` after the start with nothing received, what
    a streaming tool is waiting for: a tool that only waits looks hung otherwise.

    Call :meth:`check` in the receive loop, :meth:`received` on a sample.
    """

    def __init__(self, tool: str, key: str, args: argparse.Namespace) -> None:
        self._text = (f"vistrack {tool}: waiting for a publisher on {key} at {where(args)} "
                      f"(nothing received in {WAITING_NOTICE_S:g} s)")
        self._due: float | None = time.monotonic() + WAITING_NOTICE_S

    def received(self) -> None:
        self._due = None

    def check(self) -> None:
        if self._due is not None and time.monotonic() >= self._due:
            self._due = None
            print(self._text, file=sys.stderr, flush=True)


# -- services and their status ----------------------------------------------------------------

@dataclass
class ServiceState:
    """What the network says about one service.

    Attributes
    ----------
    service : service name (``motion_estimation``, ...).
    alive : its liveliness token is present.
    status : its status reply (``ZenohNode.status_reply``), or None if it did not answer.
    """

    service: str
    alive: bool
    status: dict[str, Any] | None

    @property
    def state(self) -> str:
        """``ok``, ``no reply`` (alive, not answering: busy or stuck) or ``starting``
        (answering, no token yet: services declare it once they are ready)."""
        if self.status is None:
            return "no reply"
        return "ok" if self.alive else "starting"


def gather(session: zenoh.Session, keys: Keys, timeout: float = 1.0) -> list[ServiceState]:
    """Every service that is alive or answers its status query, sorted by name.

    A session that has just connected may not know every token and queryable yet (a first
    liveliness query can come back empty, or short of some), so both queries are repeated
    until their answers agree and a further round finds no one new, or until ``timeout`` s
    have passed: a service alive but silent, or a robot without services, costs the timeout.
    (A CI run's status table once had no row for a live auto-tuner: the likeliest reading is
    that both answers of a first round had left it out, and agreeing, ended the gathering.)
    """
    deadline = time.monotonic() + timeout
    alive: set[str] = set()
    statuses: dict[str, dict[str, Any]] = {}
    agreed: set[str] | None = None  # the services both answers named in the last round
    while True:
        remaining = max(0.2, deadline - time.monotonic())
        alive.update(alive_services(session, keys, timeout=remaining))
        for reply in query_status(session, keys, timeout=remaining):
            statuses[str(reply.get("service", "?"))] = reply
        if alive and alive == statuses.keys():
            if agreed == alive:
                break  # the same in two rounds in a row
            agreed = set(alive)
        else:
            agreed = None
        if time.monotonic() >= deadline:
            break
        time.sleep(0.05)  # let the missing declarations arrive, then ask again
    return [ServiceState(name, name in alive, statuses.get(name))
            for name in sorted(alive | statuses.keys())]


def format_table(headers: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    """Rows aligned in columns under ``headers`` (the last column is not padded)."""
    cells = [[str(h) for h in headers]] + [["-" if c is None else str(c) for c in r]
                                           for r in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(headers))]
    lines = []
    for r in cells:
        padded = [c.ljust(w) for c, w in zip(r[:-1], widths[:-1], strict=True)] + [r[-1]]
        lines.append("  ".join(padded).rstrip())
    return "\n".join(lines)
