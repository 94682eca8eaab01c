"""``vistrack status``: every live service of the robot and its counters.

Lists the services whose liveliness token is present or that answer their status queryable
(``vistrack/<robot>/<service>/status``), with: state (``ok``; ``starting`` when the service
answers but has not declared its token yet, i.e. is still warming up; ``no reply`` when the
service is alive but does not answer, e.g. stuck in a long computation), pid, uptime,
received, published, dropped, rejected (bad inputs), failed (inputs whose handling failed:
skipped), busy (s the loop has been working on its current input), p50/p99 processing time,
the params_id in force, service-specific extras, and the last error. ``--json`` prints one
JSON document, a list with one object per service: ``[{"service", "state", "alive",
"answered", **status reply}, ...]``. Exit code 1 when no service answered (``[]`` with
``--json``).
"""

from __future__ import annotations

import argparse
import json
from typing import Any

import zenoh

from ...common.keys import Keys
from ...common.messages import to_jsonable
from ..usage import add_number
from .shared import ServiceState, ToolError, add_tool_args, format_table, gather, run, where

HEADERS = ("SERVICE", "STATE", "PID", "UP_S", "RECEIVED", "PUBLISHED", "DROPPED", "REJECTED",
           "FAILED", "BUSY_S", "P50_MS", "P99_MS", "PARAMS", "EXTRA", "LAST_ERROR")
_MAX_ERROR = 80  # characters of last_error in the table (--json has it all)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true",
                        help="one JSON document: a list of one object per service")
    add_number(parser, "--timeout", lo=0, hi=3600, lo_open=True, unit="s", default=1.0,
               metavar="S", help="how long to wait for the services' answers, %(allowed)s "
                                 "(default 1 s)")
    add_tool_args(parser)


def as_json(state: ServiceState) -> dict[str, Any]:
    """The ``--json`` object of one service."""
    out: dict[str, Any] = {"service": state.service, "state": state.state,
                           "alive": state.alive, "answered": state.status is not None}
    if state.status is not None:
        reply = to_jsonable(state.status)
        reply.pop("service", None)
        out.update(reply)
    return out


def table_row(state: ServiceState) -> list[object]:
    """The table cells of one service (``-`` where it did not answer)."""
    s = state.status
    if s is None:
        return [state.service, state.state] + [None] * (len(HEADERS) - 2)
    params = s.get("params") or {}
    params_text = (f"{params.get('params_id')} ({params.get('source', '?')})"
                   if "params_id" in params else None)
    extra = " ".join(f"{k}={_num(v)}" for k, v in sorted((s.get("extra") or {}).items()))
    last_error = str(s.get("last_error") or "")
    if len(last_error) > _MAX_ERROR:
        last_error = last_error[:_MAX_ERROR - 3] + "..."
    return [state.service, state.state, s.get("pid"), _num(s.get("uptime_s"), 0),
            s.get("received"), s.get("published"), s.get("dropped"), s.get("rejected"),
            s.get("failed"), _num(s.get("busy_s")), _num(s.get("p50_ms")), _num(s.get("p99_ms")),
            params_text, extra or None, last_error or None]


def _num(value: Any, digits: int = 2) -> Any:
    if isinstance(value, dict):  # counts by kind, e.g. rejected_by: the non-zero ones
        return ",".join(f"{k}:{_num(v, digits)}" for k, v in value.items() if v) or "0"
    return f"{value:.{digits}f}" if isinstance(value, float) else value


def main(args: argparse.Namespace) -> int:
    return run("status", args, lambda session, keys: status(session, keys, args))


def status(session: zenoh.Session, keys: Keys, args: argparse.Namespace) -> int:
    states = gather(session, keys, timeout=args.timeout)
    if args.json:  # one document, so that json.load() of the output works
        print(json.dumps([as_json(state) for state in states], indent=2, allow_nan=False),
              flush=True)
    if not states:
        raise ToolError(f"no live service for robot {keys.robot!r} at {where(args)}")
    if not args.json:
        print(format_table(HEADERS, [table_row(s) for s in states]), flush=True)
    return 0
