"""``vistrack hz KEY``: the publishing rate of KEY and its jitter, once a second.

For every key matching KEY that received samples in the last second, prints the rate (Hz) and
the mean, min, max and standard deviation of the inter-arrival period over the last
``--window`` samples, the number of samples received, and the gaps: messages missing from each
publisher's ``seq`` sequence (lost in transit or dropped by a latest-only publisher; two
publishers on one key, told apart by their Zenoh source id, are not gaps). Arrival
times are this process's, so the jitter includes the network's.
"""

from __future__ import annotations

import argparse
import collections
import time
from typing import Any

import numpy as np
import zenoh

from ...common.bus import SeqGaps
from ...common.keys import Keys
from ..usage import add_number
from .shared import (
    Inbox,
    WaitingNotice,
    add_tool_args,
    print_json,
    resolve_key,
    run,
    stop_on_signals,
)

REPORT_S = 1.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("key", metavar="KEY",
                        help="camera/frame, motion/estimate, estimate, '**', or a full key")
    add_number(parser, "--window", lo=2, hi=100_000, integer=True, default=100, metavar="N",
               help="samples the period statistics are computed over, %(allowed)s "
                    "(default 100)")
    add_number(parser, "--duration", lo=0, hi=1e6, lo_open=True, unit="s", default=None,
               metavar="S", help="exit after S seconds, %(allowed)s (default: run until "
                                 "Ctrl-C)")
    parser.add_argument("--json", action="store_true",
                        help="print one JSON object per key and report")
    add_tool_args(parser)


class Rate:
    """Arrival statistics of one key.

    Parameters
    ----------
    window : arrival times kept for the rate and period statistics.
    """

    def __init__(self, window: int) -> None:
        self._arrivals: collections.deque[int] = collections.deque(maxlen=window)
        self._seq = SeqGaps()  # per publisher: two on one key are not gaps
        self.samples = 0
        self.gaps = 0
        self.fresh = 0  # samples since the last report

    def add(self, mono_ns: int, payload: bytes, source: str | None = None) -> None:
        """Record one arrival (monotonic ns) and its payload's ``seq`` (from the publisher
        ``source``)."""
        self._arrivals.append(mono_ns)
        self.gaps += self._seq.update("", payload, source)
        self.samples += 1
        self.fresh += 1

    def report(self) -> dict[str, Any]:
        """``hz``, ``mean_ms``, ``min_ms``, ``max_ms``, ``std_ms`` (None with fewer than two
        arrivals), ``window`` (arrivals used), ``samples`` and ``gaps`` (totals)."""
        times = np.fromiter(self._arrivals, dtype=np.int64, count=len(self._arrivals))
        out: dict[str, Any] = dict.fromkeys(("hz", "mean_ms", "min_ms", "max_ms", "std_ms"))
        if times.size >= 2:
            periods_ms = np.diff(times) / 1e6
            span_s = (times[-1] - times[0]) / 1e9
            out.update(hz=(times.size - 1) / span_s if span_s > 0 else None,
                       mean_ms=float(periods_ms.mean()), min_ms=float(periods_ms.min()),
                       max_ms=float(periods_ms.max()), std_ms=float(periods_ms.std()))
        out.update(window=int(times.size), samples=self.samples, gaps=self.gaps)
        self.fresh = 0
        return out


def format_report(key: str, r: dict[str, Any]) -> str:
    """One human-readable line of a :meth:`Rate.report`."""
    if r["hz"] is None:
        rate = "rate -"
    else:
        rate = (f"rate {r['hz']:8.2f} Hz  period mean {r['mean_ms']:7.2f} ms  "
                f"min {r['min_ms']:7.2f}  max {r['max_ms']:7.2f}  std {r['std_ms']:6.2f}")
    return f"{key}  {rate}  window {r['window']}  samples {r['samples']}  gaps {r['gaps']}"


def main(args: argparse.Namespace) -> int:
    return run("hz", args, lambda session, keys: hz(session, keys, args))


def hz(session: zenoh.Session, keys: Keys, args: argparse.Namespace) -> int:
    key = resolve_key(keys, args.key, "hz")
    inbox = Inbox()
    rates: dict[str, Rate] = {}
    start = time.monotonic()
    next_report = start + REPORT_S
    notice = WaitingNotice("hz", key, args)
    with stop_on_signals() as stop:
        sub = session.declare_subscriber(key, inbox)
        try:
            while not stop.is_set():
                now = time.monotonic()
                if args.duration is not None and now - start >= args.duration:
                    break
                if now >= next_report:
                    _print_reports(key, rates, args.json)
                    next_report += REPORT_S
                    continue
                item = inbox.get(timeout=min(0.1, next_report - now))
                if item is None:
                    notice.check()
                else:
                    notice.received()
                    rates.setdefault(item.key, Rate(args.window)).add(item.mono_ns, item.payload,
                                                                     item.source)
        finally:
            sub.undeclare()
    if args.duration is not None and not stop.is_set():
        # the last, partial second's report: with --duration 1 nothing was printed at all
        _print_reports(key, rates, args.json)
    return 0


def _print_reports(key: str, rates: dict[str, Rate], as_json: bool) -> None:
    fresh = {k: r for k, r in sorted(rates.items()) if r.fresh}
    if not fresh and not as_json:
        print(f"{key}  no new samples", flush=True)
    for k, rate in fresh.items():
        report = rate.report()
        if as_json:
            print_json({"key": k, **report})
        else:
            print(format_report(k, report), flush=True)
