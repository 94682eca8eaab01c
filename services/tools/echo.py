"""``vistrack echo KEY``: print the samples published on KEY, one JSON line each.

KEY is a contract name (``motion/estimate``, ``camera/frame``), a ``Keys`` attribute
(``estimate``), any relative key or wildcard (``**``, ``tuner/*``), or a full key
(``vistrack/r2/motion/estimate``). Each line is ``{"key": <full key>, <fields>}``: contract
messages are decoded and validated, images and other arrays summarised (width, height, mean,
nbytes), not dumped. A payload that does not decode prints ``{"key", "nbytes", "error"}``;
``--raw`` prints the msgpack map as it is, without the contract's checks.
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

import msgpack
import zenoh

from ...common.keys import Keys
from ...common.messages import MESSAGE_TYPES, MessageError, decode_any, to_jsonable, unpack
from ..usage import add_number, plural
from .shared import (
    Inbox,
    ToolError,
    WaitingNotice,
    add_tool_args,
    print_json,
    resolve_key,
    run,
    stop_on_signals,
)

# Raw payloads are not validated, but their size still is bounded: a bin or str up to a
# 4096x4096 frame's candidates, as in common.messages.
_RAW_LIMITS = {"max_bin_len": 64 << 20, "max_str_len": 1 << 20, "max_array_len": 1 << 20,
               "max_map_len": 1 << 16, "max_ext_len": 1 << 20}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("key", metavar="KEY",
                        help="motion/estimate, camera/frame, estimate, '**', or a full key")
    add_number(parser, "--count", lo=1, hi=10**9, integer=True, default=None, metavar="N",
               help="exit after N samples, %(allowed)s")
    add_number(parser, "--timeout", lo=0, hi=1e6, lo_open=True, unit="s", default=None,
               metavar="S", help="exit after S seconds, %(allowed)s; with --count, exit 1 if "
                                 "fewer arrived. With -e, also how long to wait for the "
                                 "router (default 5 s)")
    parser.add_argument("--raw", action="store_true",
                        help="print the msgpack map as received, without validation")
    add_tool_args(parser)


def describe(key: str, payload: bytes, *, raw: bool = False) -> dict[str, Any]:
    """The JSON line of one sample: ``{"key": key, **fields}`` or ``{"key", "nbytes",
    "error"}``. Never raises on bad payloads."""
    try:
        if raw:
            obj = msgpack.unpackb(payload, raw=False, strict_map_key=False, **_RAW_LIMITS)
            fields = to_jsonable(obj if isinstance(obj, dict) else {"value": obj})
        elif _suffix_type(key):
            fields = to_jsonable(decode_any(key, payload))
        else:  # not a contract key (a tool's own key): a versioned map is all we can check
            fields = to_jsonable(unpack(payload))
    except MessageError as e:
        return {"key": key, "nbytes": len(payload), "error": str(e)}
    except (ValueError, TypeError, msgpack.UnpackException) as e:  # --raw: msgpack's errors
        return {"key": key, "nbytes": len(payload), "error": f"{type(e).__name__}: {e}"}
    fields.pop("key", None)  # "key" names the sample; a field of that name would shadow it
    return {"key": key, **fields}


def _suffix_type(key: str) -> bool:
    parts = key.split("/", 2)
    return len(parts) == 3 and parts[2] in MESSAGE_TYPES


def main(args: argparse.Namespace) -> int:
    return run("echo", args, lambda session, keys: echo(session, keys, args),
               connect_timeout=args.timeout)


def echo(session: zenoh.Session, keys: Keys, args: argparse.Namespace) -> int:
    key = resolve_key(keys, args.key, "echo")
    inbox = Inbox()
    deadline = None if args.timeout is None else time.monotonic() + args.timeout
    printed = 0
    notice = WaitingNotice("echo", key, args)
    with stop_on_signals() as stop:
        sub = session.declare_subscriber(key, inbox)
        try:
            while not stop.is_set() and (args.count is None or printed < args.count):
                if deadline is not None and time.monotonic() >= deadline:
                    break
                item = inbox.get(timeout=0.1)
                if item is None:
                    notice.check()
                    continue
                notice.received()
                print_json(describe(item.key, item.payload, raw=args.raw))
                printed += 1
        finally:
            sub.undeclare()
    if inbox.overflow:
        print(f"vistrack echo: {plural(inbox.overflow, 'sample')} dropped (output too slow)",
              file=sys.stderr)
    if args.count is not None and printed < args.count and not stop.is_set():
        raise ToolError(f"only {printed} of {args.count} samples on {key} within "
                        f"{args.timeout:g} s")
    return 0
