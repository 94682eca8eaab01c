"""``vistrack params get|set``: the tracker parameters in force, and changing them live.

``get`` asks every service for its status and prints the parameters each one runs with: the
paper's five factors, ``params_id``, ``source`` (``flags``, ``tuner`` or ``user``) and
``reason``.

``set NAME=VALUE ...`` changes some of the five factors (max_features, thres_percent,
search_size, corr_size, ungroup_size):

1. the values are validated locally (an unknown name or an out-of-range value is a one-line
   error naming the field and its range, exit 2);
2. the parameters in force are read from the services' status, and a ``tuner/params`` message
   with those parameters, the changes applied, ``params_id`` one above the largest in force,
   source ``user`` and reason ``set by user`` is published reliably (congestion control BLOCK)
   once a subscriber matches (what is put before the subscription is known is lost);
3. motion_estimation's status is polled until it runs with the new ``params_id`` (the message
   is repeated every second meanwhile: a duplicate is ignored by the services), else exit 1.
   While its status says the set is accepted but pending (``extra.params_pending``: windows
   whose kernels are being made ready, up to half a minute on their first use on a machine),
   the tool says so on stderr and waits up to :data:`PENDING_WAIT_S` s more.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import zenoh

from ...common.bus import SourcedPublisher, service_status
from ...common.keys import Keys
from ...common.messages import MessageError, Params, next_params_id
from ...common.params import BOUNDS, FACTORS, ParamError, TrackerParams
from ..kernels import kernels_failed
from ..usage import add_number, say_on_stderr
from .shared import (
    ServiceState,
    ToolError,
    add_tool_args,
    error,
    format_table,
    gather,
    has_subscriber,
    print_json,
    run,
)

CONFIRMING_SERVICE = "motion_estimation"
HEADERS = ("SERVICE", "PARAMS_ID", "SOURCE", *(f.upper() for f in FACTORS), "REASON")
REPEAT_S = 1.0  # how often an unconfirmed set is published again
POLL_S = 0.1  # how often the confirming service's status is asked
#: How long a set the confirming service has accepted, pending its kernels, is waited for
#: beyond ``--timeout`` (their compile on a first use: ~30 s on two cores, 80 s when busy).
PENDING_WAIT_S = 180.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    actions = parser.add_subparsers(dest="action", metavar="ACTION", parser_class=type(parser))
    actions.required = True
    get = actions.add_parser("get", help="print the parameters in force on every service")
    get.add_argument("--json", action="store_true", help="one JSON object per service")
    add_number(get, "--timeout", lo=0, hi=3600, lo_open=True, unit="s", default=1.0,
               metavar="S", help="how long to wait for the services' answers, %(allowed)s "
                                 "(default 1 s)")
    add_tool_args(get)
    ranges = ", ".join(f"{f} {_range(f)}" for f in FACTORS)
    put = actions.add_parser("set", help="change tracker parameters live",
                             description=f"Settable: {ranges}.")
    put.add_argument("assignments", nargs="+", metavar="NAME=VALUE",
                     help="e.g. search_size=21 corr_size=11")
    put.add_argument("--json", action="store_true", help="print the result as JSON")
    add_number(put, "--timeout", lo=0, hi=3600, lo_open=True, unit="s", default=5.0,
               metavar="S", help="longest wait for motion-estimation's answer (it may be "
                                 "restarting), a subscriber and the confirmation, "
                                 "%(allowed)s (default 5 s)")
    add_tool_args(put)


def _range(name: str) -> str:
    lo, hi = BOUNDS[name]
    return f"{lo:g}..{hi:g}"


def parse_assignments(items: list[str]) -> dict[str, Any]:
    """``["search_size=21", ...]`` -> ``{"search_size": 21, ...}``, validated.

    Raises
    ------
    ToolError (code 2)
        Naming the item, the field and its allowed range.
    """
    changes: dict[str, Any] = {}
    for item in items:
        name, sep, text = item.partition("=")
        name, text = name.strip(), text.strip()
        if not sep or not name or not text:
            raise ToolError(f"{item!r} is not NAME=VALUE, e.g. search_size=21", code=2)
        if name not in FACTORS:
            raise ToolError(f"unknown parameter {name!r}: settable are "
                            + ", ".join(f"{f} ({_range(f)})" for f in FACTORS), code=2)
        if name in changes:
            raise ToolError(f"parameter {name!r} is given twice", code=2)
        try:
            changes[name] = int(text)
        except ValueError:
            try:
                changes[name] = float(text)
            except ValueError:
                raise ToolError(f"{name}={text!r} is not a number: allowed {_range(name)}",
                                code=2) from None
    try:
        TrackerParams().replace(**changes)  # range and type checks, one message per field
    except ParamError as e:
        raise ToolError(str(e), code=2) from None
    return changes


def main(args: argparse.Namespace) -> int:
    if args.action == "get":
        return run("params", args, lambda session, keys: get(session, keys, args))
    try:
        changes = parse_assignments(args.assignments)  # before Zenoh: bad input fails fast
    except ToolError as e:
        error("params", e)
        return e.code
    return run("params", args, lambda session, keys: set_params(session, keys, changes, args))


# -- get --------------------------------------------------------------------------------------

def in_force(states: list[ServiceState]) -> dict[str, dict[str, Any]]:
    """Service name -> its ``params`` status map, for the services that report parameters."""
    return {s.service: s.status["params"] for s in states
            if s.status is not None and "params_id" in (s.status.get("params") or {})}


def get(session: zenoh.Session, keys: Keys, args: argparse.Namespace) -> int:
    params = in_force(gather(session, keys, timeout=args.timeout))
    if not params:
        raise ToolError(f"no service of robot {keys.robot!r} reports parameters (is "
                        f"{CONFIRMING_SERVICE} running? see vistrack status)")
    _print_params(params, args.json)
    return 0


def _print_params(params: dict[str, dict[str, Any]], as_json: bool) -> None:
    if as_json:
        for service, p in params.items():
            print_json({"service": service, **p})
        return
    rows = [[service, p.get("params_id"), p.get("source"), *(p.get(f) for f in FACTORS),
             p.get("reason")] for service, p in params.items()]
    print(format_table(HEADERS, rows), flush=True)


# -- set --------------------------------------------------------------------------------------

def set_params(session: zenoh.Session, keys: Keys, changes: dict[str, Any],
               args: argparse.Namespace) -> int:
    deadline = time.monotonic() + args.timeout
    # asked again until it answers, for up to --timeout: a set given while motion-estimation
    # restarts (a routine second) failed at once, "does not answer", within a 10 s timeout
    while True:
        left = deadline - time.monotonic()
        params = in_force(gather(session, keys, timeout=min(max(left, 0.1), 2.0)))
        current = params.get(CONFIRMING_SERVICE)
        if current is not None or time.monotonic() >= deadline:
            break
        time.sleep(min(0.2, max(0.0, deadline - time.monotonic())))
    if current is None:
        raise ToolError(f"{CONFIRMING_SERVICE} of robot {keys.robot!r} does not answer within "
                        f"{args.timeout:g} s: is it running? (see vistrack status)")
    # above every id in force, or a service that is ahead would reject the set as stale
    try:
        params_id = next_params_id(max(int(p["params_id"]) for p in params.values()))
    except MessageError as e:
        raise ToolError(str(e)) from None
    base = TrackerParams().replace(**{f: current[f] for f in FACTORS if f in current})
    try:
        new = base.replace(**changes)
    except ParamError as e:
        raise ToolError(str(e), code=2) from None
    # source info on every put: the services count seq gaps per publisher, so this one's
    # seq is never compared with the tuner's
    publisher = SourcedPublisher(session.declare_publisher(
        keys.params, congestion_control=zenoh.CongestionControl.BLOCK,
        reliability=zenoh.Reliability.RELIABLE))
    try:
        _wait_for_subscriber(publisher.publisher, keys.params, deadline)
        confirmed = _publish_until_confirmed(session, keys, publisher, new, params_id, deadline)
    finally:
        publisher.undeclare()
    if args.json:
        print_json({"service": CONFIRMING_SERVICE, **confirmed})
    else:
        print(f"params_id {params_id} in force on {CONFIRMING_SERVICE}: "
              + " ".join(f"{f}={confirmed.get(f)}" for f in FACTORS)
              + f" (source {confirmed.get('source')}: {confirmed.get('reason')})", flush=True)
    return 0


def _wait_for_subscriber(publisher: zenoh.Publisher, key: str, deadline: float) -> None:
    while not has_subscriber(publisher):
        if time.monotonic() >= deadline:
            raise ToolError(f"no subscriber of {key} appeared: nothing would receive the "
                            "parameters")
        time.sleep(0.02)


def _publish_until_confirmed(session: zenoh.Session, keys: Keys, publisher: SourcedPublisher,
                             new: TrackerParams, params_id: int, deadline: float
                             ) -> dict[str, Any]:
    """Publish the set (again every REPEAT_S) until CONFIRMING_SERVICE runs with
    ``params_id`` and the values set; return its params status map."""
    # seq: wall-clock microseconds, so it keeps increasing across invocations (a publisher
    # each). Receivers count gaps per publisher (the source info of its puts); one that
    # cannot tell publishers apart takes a jump this large for a new sequence, not for losses
    seq = time.time_ns() // 1000
    next_put = 0.0
    seen: dict[str, Any] = {}
    said_pending = False
    while True:
        now = time.monotonic()
        if now >= next_put:
            msg = Params.from_tracker_params(new, seq=seq, stamp_ns=time.time_ns(),
                                             params_id=params_id, source="user",
                                             reason="set by user")
            publisher.put(msg.encode())
            seq += 1
            next_put = now + REPEAT_S
        status = service_status(session, keys, CONFIRMING_SERVICE, timeout=0.5)
        if status is not None and isinstance(status.get("params"), dict):
            seen = status["params"]
        extra = status.get("extra") if status is not None else None
        if isinstance(extra, dict) and extra.get("params_pending") == params_id \
                and not said_pending:
            said_pending = True
            deadline = max(deadline, time.monotonic() + PENDING_WAIT_S)
            say_on_stderr("params")(
                f"params_id {params_id} accepted by {CONFIRMING_SERVICE}, not yet in force: "
                "the kernels of these windows are being made ready (on their first use on "
                "this machine, up to half a minute); waiting")
        error = status.get("last_error") if status is not None else None
        if isinstance(error, str) and error.startswith(kernels_failed(params_id)):
            # dropped for good, and its repeats refused in silence: waiting cannot confirm it
            # (the timeout used to say only that the set "may have been lost")
            raise ToolError(f"{CONFIRMING_SERVICE} dropped the set: {error}")
        found = seen.get("params_id")
        # ours, not a tuning that happened to take the same params_id (the service then keeps
        # the tuner's and refuses ours as stale: not confirmed)
        if found == params_id and seen.get("source") == "user" and \
                all(seen.get(f) == getattr(new, f) for f in FACTORS):
            return seen
        if isinstance(found, int) and found > params_id:
            raise ToolError(f"params_id {params_id} was superseded by {found} from "
                            f"{seen.get('source')} ({seen.get('reason')}) before it was "
                            "confirmed")
        if found == params_id:
            # another set (a concurrent params set, a tuning) took this params_id first: the
            # services keep it and refuse ours as stale, so waiting cannot confirm it (the
            # timeout used to say only that the set "may have been lost")
            values = " ".join(f"{f}={seen.get(f)}" for f in FACTORS)
            raise ToolError(f"params_id {params_id} was taken first by another set from "
                            f"{seen.get('source')} ({seen.get('reason')}): {values}; set "
                            "again")
        if time.monotonic() >= deadline:
            raise ToolError(f"{CONFIRMING_SERVICE} did not confirm params_id {params_id} "
                            f"(still runs params_id {found} from {seen.get('source')}); the "
                            "set may have been lost")
        time.sleep(POLL_S)



