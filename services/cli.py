"""``vistrack``: the one entry point (CONTRACT: see README "Command line").

Each subcommand's arguments and code live in its own module (``add_arguments(parser)`` and
``main(args) -> exit code``); this file only wires them.
"""

from __future__ import annotations

import argparse
import atexit
import importlib
import importlib.metadata
import os
import re
import sys
import threading
from collections.abc import Mapping, Sequence
from typing import NoReturn

from . import kernels, threads, usage

# name -> (module under vistrack.services, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("launch.demo", "the whole system in closed loop on the robot simulator (main job)"),
    "track": ("offline.track", "track features over recorded frames, offline (no Zenoh)"),
    "tune": ("offline.tune",
             "factorial design, ANOVA, sweep and optimum over recorded frames, offline"),
    "bench": ("bench", "benchmarks against OpenCV / raw Zenoh peers, printed as tables"),
    "camera": ("camera.service", "service: publish frames (file camera, device, built-in)"),
    "preprocessing": ("preprocessing.service", "service: filter, gradient, candidates"),
    "motion-estimation": ("motion_estimation.service",
                          "service: SSD tracking and the motion estimate"),
    "auto-tuner": ("auto_tuner.service", "service: frame buffer, experiments, parameters"),
    "fuzzy-controller": ("fuzzy_controller.service",
                         "service: velocity commands that cancel the image motion"),
    "ros2": ("ros2.service",
             "service: commands, estimates and parameters as ROS 2 topics (rmw_zenoh)"),
    "echo": ("tools.echo", "print the samples of a key as JSON lines"),
    "hz": ("tools.hz", "rate, period jitter and seq gaps of a key, once a second"),
    "status": ("tools.status", "live services and their counters"),
    "params": ("tools.params", "get the tracker parameters in force, or set them live"),
    "record": ("tools.record", "record samples of chosen keys to a file (.vtr or MCAP)"),
    "replay": ("tools.replay", "publish a recording (.vtr or MCAP) again at its timing"),
    "export": ("tools.export", "convert a recording, e.g. .vtr to MCAP (no Zenoh)"),
    "foxglove": ("tools.foxglove_bridge",
                 "serve the robot's keys live to Foxglove (WebSocket, ROS 2 messages)"),
    "up": ("launch.up", "start and supervise the five services (and a Zenoh router)"),
    "router": ("launch.router", "run a Zenoh router for the services and tools to connect to"),
    "certs": ("launch.certs", "a CA and host certificates for Zenoh's mutual TLS (no Zenoh)"),
}


#: A flag's value that starts with "-" yet is a value, not a flag: a negative number in any
#: of the forms the flags take (``-5``, ``-0.5``, ``-1e3``) or a size (``-5x5``). argparse
#: knows only ``-5`` and ``-0.5``: ``--resize -5x5`` or ``--fps -1e3`` said "expected one
#: argument" rather than the flag's own check, which names the allowed range. No flag of
#: vistrack looks like this, so nothing is taken for a value that was meant as a flag.
_NEGATIVE_VALUE = re.compile(r"^-(\d+x-?\d+|(\d+\.?\d*|\.\d+)(e[-+]?\d+)?|inf|nan)$",
                             re.IGNORECASE)


class _Parser(argparse.ArgumentParser):
    """argparse, but a usage error is one line (``vistrack X: error: ...``) and exit code 2,
    and a negative value is a value (:data:`_NEGATIVE_VALUE`)."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]
        self._negative_number_matcher = _NEGATIVE_VALUE

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _version() -> str:
    """The installed distribution's version (what pip installed, editable or not)."""
    try:
        return importlib.metadata.version("vistrack")
    except importlib.metadata.PackageNotFoundError:  # run from a source tree, not installed
        return "(not installed)"


#: reStructuredText in the modules' docstrings, which are the subcommands' ``--help``: a role
#: (``:func:`~vistrack.common.vision.tracker.warm_up` ``, ``:mod:`.tracker` ``) and an inline
#: literal (````--json````). A terminal shows them as typed; the help shows their text alone.
_ROLE = re.compile(r":(mod|func|meth|class|data|attr|exc|obj):`~?\.?([^`]*)`")
_LITERAL = re.compile(r"``([^`]+)``")
_CONSTANT = re.compile(r"[A-Z][A-Z0-9_]*_[A-Z0-9_]+|[A-Z]{4,}")


def plain(doc: str, names: Mapping[str, object] | None = None) -> str:
    """A docstring's reStructuredText made plain text for ``--help``: a role by its target's
    last name (a function's and a method's with ``()``), an inline literal by its text; a
    module constant that ``names`` (the module's namespace) holds as a number, by its value
    (the help said ``up to RESENDS times``, which no user can look up)."""
    def value(name: str) -> str:
        v = (names or {}).get(name)
        if _CONSTANT.fullmatch(name) and isinstance(v, (int, float)) and \
                not isinstance(v, bool):
            return f"{v:g}"
        return name

    def target(m: re.Match[str]) -> str:
        name = m.group(2).rsplit(".", 1)[-1]
        return name + "()" if m.group(1) in ("func", "meth") else value(name)
    return _LITERAL.sub(lambda m: value(m.group(1)), _ROLE.sub(target, doc))


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The ``vistrack`` parser. Only ``command``'s module is imported (all of them when None,
    e.g. for documentation), so ``vistrack track`` never loads Zenoh and one broken or slow
    subcommand cannot break the others."""
    parser = _Parser(prog="vistrack", description="Fast, self-tuning visual tracking for "
                     "mobile robots: the services, the launcher and the tools.")
    parser.add_argument("--version", action="version", version=f"vistrack {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    for name, (module, text) in COMMANDS.items():
        if command is not None and name != command:
            sub.add_parser(name, help=text, add_help=False)
            continue
        mod = importlib.import_module(f"vistrack.services.{module}")
        p = sub.add_parser(name, help=text,
                           description=plain(mod.__doc__ or text, vars(mod)).strip(),
                           formatter_class=argparse.RawDescriptionHelpFormatter)
        mod.add_arguments(p)
        p.set_defaults(_module=mod)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    try:
        # before anything imports numpy: the numeric libraries size their pools when they load
        threads.configure()
    except ValueError as e:
        print(f"vistrack: error: {usage.one_line(e)}", file=sys.stderr, flush=True)
        return 2
    folder = kernels.cache_folder_fallback()  # and before numba reads NUMBA_CACHE_DIR
    if folder is not None:
        print(f"vistrack: note: no folder numba can write its kernel cache to (the package's, "
              f"or $XDG_CACHE_HOME/numba): caching them in {folder}; set NUMBA_CACHE_DIR to "
              "choose one", file=sys.stderr, flush=True)
    argv = list(sys.argv[1:] if argv is None else argv)
    command = next((a for a in argv if not a.startswith("-")), None)
    parser = build_parser(command if command in COMMANDS else "")
    try:
        args, unknown = parser.parse_known_args(argv)
        if unknown:  # named here, so the error says which subcommand did not know them
            raise usage.FlagError(f"unrecognized arguments: {' '.join(unknown)} "
                                  f"(see vistrack {args.command} --help)")
        usage.run_checks(args._module, args)
    except ValueError as e:  # a flag out of its range, a source that does not exist, ...
        usage.print_error(str(command), e)
        return 2
    try:
        return int(args._module.main(args) or 0)
    except KeyboardInterrupt:
        return 130


def _open_standard_streams() -> None:
    """A standard output or error closed by the caller (``2>&-``, a supervisor that closes
    them) is opened on /dev/null: Python leaves ``sys.stderr`` None then, and every command
    failed on it with exit 1 and no word (``vistrack --help 2>&-``, a demo's status line, the
    capture of OpenCV's messages, which duplicates file descriptor 2)."""
    for fd, name in ((1, "stdout"), (2, "stderr")):
        try:
            os.fstat(fd)
        except OSError:
            null = os.open(os.devnull, os.O_WRONLY)
            if null != fd:
                os.dup2(null, fd)
                os.close(null)
            setattr(sys, name, open(fd, "w", closefd=False, errors="backslashreplace"))


def entry(argv: Sequence[str] | None = None) -> NoReturn:
    """The ``vistrack`` command: :func:`main`, then the end of the process as the interpreter
    would end it (an uncaught exception's traceback and exit code 1, threads joined, ``atexit``
    run, the standard streams flushed) but for the teardown of every module, which took 1.2 s
    of the 2.5 s a ``vistrack track`` of 8 frames took here (numba's and LLVM's objects)."""
    _open_standard_streams()
    try:
        code = main(argv)
    except SystemExit as e:  # argparse's --help, and anything else that exits
        code = e.code  # type: ignore[assignment]
    except BaseException:  # noqa: BLE001 - reported as the interpreter reports it
        sys.excepthook(*sys.exc_info())
        code = 1
    if not isinstance(code, int):
        if code is not None:
            print(code, file=sys.stderr)
        code = 0 if code is None else 1
    try:
        for t in threading.enumerate():
            if t is not threading.main_thread() and not t.daemon:
                t.join()
        atexit._run_exitfuncs()  # logging's shutdown, tempfile's and weakref's finalizers
        for stream in (sys.stdout, sys.stderr):
            stream.flush()
    except BaseException:  # noqa: BLE001 - a closed pipe (the reader is gone): go anyway
        code = code or 1
    finally:
        os._exit(code)


if __name__ == "__main__":
    entry()
