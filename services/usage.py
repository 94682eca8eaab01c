"""What every subcommand shares about bad command lines: numeric flags with declared ranges,
the optional ``check_args`` hook, and the one-line error.

A numeric flag is declared once with its range (:func:`add_number`); argparse then converts and
checks it while parsing, wherever the flags are parsed: ``vistrack <sub>`` (``cli.py``) and a
launch file's ``flags:`` (``launcher.check_service_flags``). The error names the flag, the value
as given and the allowed range, e.g. ``--fps nan is out of range: allowed 0..1000``. Help texts
can show the range with ``%(allowed)s``.

A subcommand module may also define ``check_args(args)``: checks across flags, or of what a flag
names (a source, a file), that raise ``ValueError`` with the same kind of message. It runs after
parsing, before ``main``, in both places.

The tracker's parameter flags (:func:`add_param_flags`, :func:`params_from_args`) live here
too: every service and the offline commands take them.

Pure argparse: no Zenoh, no OpenCV, so the offline tools import it for free.
"""

from __future__ import annotations

import argparse
import math
import os
import re
import sys
from collections.abc import Callable
from dataclasses import dataclass
from types import ModuleType
from typing import Any, TextIO

from ..common.params import BOUNDS, SEARCH_KINDS, ParamError, TrackerParams


class FlagError(ValueError):
    """A flag's value is not a number or is out of its declared range; the text names the
    flag, the value as given and the allowed range.

    Raised from inside argparse (it is not an ``argparse.ArgumentError``, so it carries its
    own text out rather than argparse's "argument --x: ..." form): callers of ``parse_args``
    catch it with the ``ValueError`` of ``check_args``.
    """


def _num(value: float) -> str:
    if isinstance(value, int):
        return str(value)
    return str(int(value)) if value.is_integer() and abs(value) < 1e15 else f"{value:g}"


@dataclass(frozen=True)
class Range:
    """The allowed values of a numeric flag: ``lo..hi`` (both included, so NaN and infinities
    are out), ``lo`` excluded when ``lo_open``; whole numbers only when ``integer``."""

    lo: float
    hi: float
    integer: bool = False
    lo_open: bool = False
    unit: str = ""
    or_zero: bool = False  # 0 allowed too (an "off" value below lo)

    def allowed(self, metavar: str = "X") -> str:
        """``0..1000``, ``0 < S <= 3600``, ``0 or 0.1..1000``, with the unit after it if any."""
        text = (f"{_num(self.lo)} < {metavar} <= {_num(self.hi)}" if self.lo_open
                else f"{_num(self.lo)}..{_num(self.hi)}")
        if self.or_zero:
            text = f"0 or {text}"
        return f"{text} {self.unit}" if self.unit else text

    def contains(self, value: float) -> bool:
        """Whether ``value`` is allowed (False for NaN)."""
        if self.or_zero and value == 0:
            return True
        above = self.lo < value if self.lo_open else self.lo <= value
        return above and value <= self.hi

    def parse(self, flag: str, text: str, metavar: str = "X") -> int | float:
        """``text`` as the flag's number.

        Raises
        ------
        FlagError
            Naming ``flag``, ``text`` as given and the range.
        """
        try:
            value: int | float = int(text) if self.integer else float(text)
        except ValueError:
            kind = "an integer" if self.integer else "a number"
            raise FlagError(f"{flag} {text!r} is not {kind}: allowed "
                            f"{self.allowed(metavar)}") from None
        if not self.contains(value):
            raise FlagError(f"{flag} {text} is out of range: allowed {self.allowed(metavar)}")
        return value


class _Number(argparse.Action):
    """Stores the flag's value converted and checked by its :class:`Range`."""

    def __init__(self, option_strings: list[str], dest: str, *, range: Range,
                 **kwargs: Any) -> None:
        super().__init__(option_strings, dest, **kwargs)
        self.range = range
        self.allowed = range.allowed(self.metavar if isinstance(self.metavar, str) else "X")

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace,
                 values: Any, option_string: str | None = None) -> None:
        metavar = self.metavar if isinstance(self.metavar, str) else "X"
        flag = option_string or self.dest
        setattr(namespace, self.dest, self.range.parse(flag, values, metavar))


def add_number(parser: Any, *names: str, lo: float, hi: float, integer: bool = False,
               lo_open: bool = False, unit: str = "", or_zero: bool = False,
               **kwargs: Any) -> argparse.Action:
    """``parser.add_argument(*names, **kwargs)`` for a number in ``lo..hi`` (``lo`` excluded
    when ``lo_open``, whole numbers when ``integer``, 0 as well when ``or_zero``). ``parser``
    may be an argument group. The help may say ``%(allowed)s`` for the range. Defaults are
    not checked: give valid ones.
    """
    if "type" in kwargs or "nargs" in kwargs:
        raise TypeError("add_number parses one value itself: no type= or nargs=")
    if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
        raise ValueError(f"range {lo}..{hi} of {names} is not a finite interval")
    action: argparse.Action = parser.add_argument(
        *names, action=_Number, range=Range(lo, hi, integer, lo_open, unit, or_zero),
        **kwargs)
    return action


def check_path(flag: str, value: str, kind: str, example: str) -> str:
    """``value`` if it names a file or folder; a FlagError naming ``flag`` if it is empty.

    An empty name is no name: ``Path('')`` is the current folder, so ``--out ''`` wrote a
    demo's files into it and ``vistrack certs ca --dir ''`` the CA's key, and ``if args.out:``
    took it for "not given" (``vistrack tune --out ''`` wrote no plots and said nothing).
    ``kind`` is "file" or "folder"; ``example`` a value to suggest (with the flag, for a flag).
    """
    if value == "":
        show = f"{flag.split('/')[0]} {example}" if flag.startswith("-") else example
        raise FlagError(f"{flag}: empty {kind} name; give a {kind}, e.g. {show}")
    return value


class _Path(argparse.Action):
    """Stores a file or folder name (one, or a list with ``nargs``), refusing an empty one
    (:func:`check_path`)."""

    def __init__(self, option_strings: list[str], dest: str, *, kind: str, example: str,
                 **kwargs: Any) -> None:
        super().__init__(option_strings, dest, **kwargs)
        self.kind, self.example = kind, example

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace,
                 values: Any, option_string: str | None = None) -> None:
        flag = option_string or (self.metavar if isinstance(self.metavar, str) else self.dest)
        for value in values if isinstance(values, list) else [values]:
            if value is not None:  # an optional positional left out: its default
                check_path(flag, value, self.kind, self.example)
        setattr(namespace, self.dest, values)


def add_path(parser: Any, *names: str, kind: str = "file", example: str,
             **kwargs: Any) -> argparse.Action:
    """``parser.add_argument(*names, **kwargs)`` for a file (``kind="file"``) or folder
    (``kind="folder"``) name, which may not be empty: ``--out ''`` is then
    ``--out: empty folder name; give a folder, e.g. --out tune-report`` (``example`` is
    ``tune-report``). ``parser`` may be an argument group; ``nargs`` may be given."""
    if kind not in ("file", "folder"):
        raise ValueError(f"kind {kind!r} of {names}: allowed file, folder")
    if "type" in kwargs:
        raise TypeError("add_path stores the name as given: no type=")
    action: argparse.Action = parser.add_argument(*names, action=_Path, kind=kind,
                                                  example=example, **kwargs)
    return action


PARAM_FLAGS = {
    "max_features": ("--max-features", int, "MAX_FEAT_NUM: most feature points"),
    "thres_percent": ("--thres-percent", float,
                      "THRES_PERCENT: %% of pixels, strongest gradient first, kept as candidates"),
    "search_size": ("--search-size", int,
                    "SEARCH_SIZE: search window width, px (an even width searches as the next "
                    "odd one, as the paper's code does)"),
    "corr_size": ("--corr-size", int,
                  "CORR_SIZE: correlation window width, px (an even width correlates as the next "
                  "odd one)"),
    "ungroup_size": ("--ungroup-size", int, "UNGROUP_SIZE: minimum distance between features, px"),
}


def add_param_flags(parser: argparse.ArgumentParser) -> None:
    """The five paper parameters as flags (defaults: Table 4 with search 15, correlation 9),
    checked against :data:`~vistrack.common.params.BOUNDS` as they are parsed."""
    defaults = TrackerParams()
    for name, (flag, typ, text) in PARAM_FLAGS.items():
        lo, hi = BOUNDS[name]
        add_number(parser, flag, dest=name, lo=lo, hi=hi, integer=typ is int, default=None,
                   metavar="N", help=f"{text} (%(allowed)s, default {getattr(defaults, name)})")
    parser.add_argument("--subpixel", action=argparse.BooleanOptionalAction, default=None,
                        help="refine each match to sub-pixel precision (default on)")
    add_search_flag(parser)
    add_tracker_flags(parser)


def add_tracker_flags(parser: argparse.ArgumentParser) -> None:
    """``--levels N``, ``--refine-size N`` and ``--paper``: the coarse-to-fine search, the wide
    sub-pixel window, or the paper's tracker."""
    lo, hi = BOUNDS["levels"]
    add_number(parser, "--levels", dest="levels", lo=lo, hi=hi, integer=True, default=None,
               metavar="N",
               help=f"pyramid levels of the coarse-to-fine search (%(allowed)s, default "
                    f"{TrackerParams().levels}; 1: the paper's single-level search)")
    lo, hi = BOUNDS["refine_size"]
    add_number(parser, "--refine-size", dest="refine_size", lo=lo, hi=hi, integer=True,
               default=None, metavar="N",
               help=f"width of the wide sub-pixel window, px (%(allowed)s, default "
                    f"{TrackerParams().refine_size}; 0, or not wider than the correlation "
                    f"window: that window only). The wide window's estimate is taken where it "
                    f"agrees with the correlation window's: more pixels, less noise and "
                    f"motion blur, but on scenes with depth it averages the neighbourhood's "
                    f"motions (see the README's Known limits)")
    parser.add_argument("--paper", action="store_true",
                        help="the paper's tracker: single-level search, integer positions, no "
                             "test of a match (flags given with it still apply)")


def add_search_flag(parser: argparse.ArgumentParser) -> None:
    """``--search pruned|exhaustive``: how the SSD search of Eq. (1) finds its argmin."""
    parser.add_argument("--search", choices=SEARCH_KINDS, default=None,
                        help="SSD search: 'pruned' skips the displacements a bound rules out "
                             "(default, fast), 'exhaustive' scores every displacement in full "
                             "as the paper does (cost grows with both window sizes); both "
                             "give the same positions")


def params_from_args(args: argparse.Namespace, base: TrackerParams | None = None
                     ) -> TrackerParams:
    """TrackerParams from the parameter flags; a bad value raises ParamError naming the flag."""
    changes = {name: getattr(args, name) for name in (*PARAM_FLAGS, "levels", "refine_size",
                                                        "subpixel", "search")
               if getattr(args, name, None) is not None}
    if base is None:
        base = TrackerParams.paper() if getattr(args, "paper", False) else TrackerParams()
    try:
        return base.replace(**changes)
    except ParamError as e:
        text = str(e)
        flags = {**{name: flag for name, (flag, _, _) in PARAM_FLAGS.items()},
                 "levels": "--levels", "refine_size": "--refine-size"}
        for name, flag in flags.items():
            if text.startswith(name + "="):
                text = flag + " " + text[len(name) + 1:]
        raise ParamError(text) from None


def run_checks(module: ModuleType, args: argparse.Namespace) -> None:
    """The checks after parsing: the Zenoh endpoints (``-e``, ``-l``) and config file name
    (``-c``) if the subcommand takes them, then ``module.check_args(args)`` if it defines
    one. A ``ValueError`` says, in its message, what is wrong."""
    for flag, attr in (("-e/--connect", "connect"), ("-l/--listen", "listen")):
        for endpoint in getattr(args, attr, None) or ():
            check_endpoint(flag, endpoint)
    if getattr(args, "config", None) is not None:  # add_zenoh_args's (common/ has no usage)
        check_path("-c/--config", args.config, "file", "zenoh.json5")
    check = getattr(module, "check_args", None)
    if check is not None:
        check(args)


# Protocols whose address is host:port. Zenoh accepts "tcp/1.2.3" or a port of 99999 when it
# reads the flags and fails only when the session opens, with a message about sockets.
_IP_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")
_HOST_PORT = re.compile(r"(\[[0-9A-Za-z:.%]+\]|[^:/\[\]\s]+):(\d{1,5})")


def check_endpoint(flag: str, endpoint: str) -> str:
    """``endpoint`` if it is ``<protocol>/<address>`` and, for tcp, udp, tls, quic and ws,
    the address is ``<host>:<port>`` with a port 0..65535; else a FlagError naming ``flag``."""
    proto, sep, rest = endpoint.partition("/")
    if not (sep and proto and rest):
        raise FlagError(f"{flag} {endpoint!r} is not a Zenoh endpoint: expected "
                        "<protocol>/<address>, e.g. tcp/127.0.0.1:7447")
    address = re.split(r"[?#]", rest, maxsplit=1)[0]
    if proto in _IP_PROTOCOLS:
        match = _HOST_PORT.fullmatch(address)
        if match is None or int(match[2]) > 65535:
            raise FlagError(f"{flag} {endpoint!r} is not a Zenoh endpoint: expected "
                            f"{proto}/<host>:<port> with a port 0..65535, e.g. "
                            f"{proto}/127.0.0.1:7447")
    return endpoint


# Where a Rust library (Zenoh) says in which of its own source files an error was raised: of
# no use to the user, and the path is as long as the message.
_RUST_WHERE = re.compile(r"\s+at\s+/\S+\.rs:\d+\.?")
# A pest parser's multi-line error (Zenoh's JSON5 config reader): " --> 1:17 ... = problem".
_PEST = re.compile(r"-->\s*(\d+):(\d+).*?\n\s*=\s*(.+)", re.DOTALL)
# Zenoh's config schema error, in Rust's debug form.
_SCHEMA = re.compile(r'JSON error: Message \{ msg: "(.*)", location: (?:Some\(Location \{ '
                     r'line: (\d+), column: (\d+) \}\)|None) \}')


def plural(n: int, noun: str) -> str:
    """``n`` and the noun, singular for one: ``plural(1, "key")`` is "1 key"."""
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"


def one_line(message: object) -> str:
    """``message`` on one line: a parser's multi-line report becomes ``line L, column C:
    problem``; other line breaks and runs of spaces become one space; Rust source locations
    are dropped."""
    text = _RUST_WHERE.sub("", str(message))
    pest = _PEST.search(text)
    if pest is not None:
        line, column, problem = pest.groups()
        text = (text[:pest.start()].rstrip(" :") + f": line {line}, column {column}: "
                + problem.strip())
    schema = _SCHEMA.search(text)
    if schema is not None:
        problem, line, column = schema.groups()
        where = f"line {line}, column {column}: " if line else ""
        text = text[:schema.start()] + where + problem + text[schema.end():]
    return " ".join(text.split())


def print_error(command: str, message: object) -> None:
    """The one-line error of a subcommand on stderr: ``vistrack COMMAND: error: MESSAGE``."""
    print(f"vistrack {command}: error: {one_line(message)}", file=sys.stderr, flush=True)


def rewrites_lines(stream: TextIO) -> bool:
    """Whether a status line may be rewritten in place on ``stream`` (carriage return and the
    erase-line escape): a terminal that understands them, not a file, a pipe or TERM=dumb
    (an editor's shell, where they came out as raw characters)."""
    return stream.isatty() and os.environ.get("TERM", "") not in ("", "dumb")


def say_on_stderr(command: str, stream: TextIO | None = None) -> Callable[[str], None]:
    """A line of a subcommand that is not an error (a compile starting, a wait), as
    :func:`print_error` says errors: ``vistrack COMMAND: ...`` on ``stream`` (default: stderr
    at the time of the call). The ``say`` of :func:`.kernels.warm_up_kernels`."""
    def say(text: str) -> None:
        print(f"vistrack {command}: {text}", file=stream or sys.stderr, flush=True)
    return say
