"""``vistrack record FILE [KEY ...]``: record timestamped samples to a file, for ``replay``.

Two formats: ``FILE.mcap`` (or ``--format mcap``) writes MCAP with ROS 2 message schemas, which
Foxglove, PlotJuggler and ``ros2 bag`` open (:mod:`.mcapio` describes it); any other name (or
``--format vtr``) writes vistrack's own ``.vtr`` format, below.

Without KEY, records every key of the robot (``vistrack/<robot>/**``; status replies and
liveliness tokens are not samples and are not recorded). A sample whose bytes equal the last
one written of its key (a frame a camera in lockstep sent again when its estimate did not come
back in time: the same seq and stamp) is written once, and counted in the closing line. Runs
until Ctrl-C/SIGTERM, ``--duration`` or ``--count``, then flushes and closes the file (it is
also flushed every second, so a killed recorder loses at most the last second).

The ``.vtr`` format (version 1): a stream of msgpack maps, nothing else, so it can be read with any
msgpack library and written without knowing its length in advance:

* first a header ``{"format": "vistrack-record", "version": 1, "robot": ID, "keys": [key
  expressions subscribed], "start_ns": wall-clock start, ns since the Unix epoch}``;
* then one map per sample, in arrival order: ``{"t_ns": arrival time, ns since the Unix epoch
  (taken from a monotonic clock, offset by start_ns, so it never goes back), "key": full key,
  "payload": bin, the sample's bytes as published}``.

Readers ignore unknown fields in both (``"tool"`` in the header for instance).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any, BinaryIO

import msgpack
import zenoh

from ...common.keys import Keys, key_suffix
from ...common.rmw_zenoh import is_name_token
from ..usage import add_number, add_path, plural
from .mcapio import McapRecording, McapWriter, is_mcap
from .shared import (
    Inbox,
    Received,
    Record,
    RecordError,
    ToolError,
    add_tool_args,
    error,
    resolve_key,
    run,
    stop_on_signals,
    warn,
)

FORMAT = "vistrack-record"
VERSION = 1
FLUSH_S = 1.0
#: The loop takes what has arrived every BATCH_S s (arrival times are taken as samples come):
#: a process woken for each sample paid more for waking than for writing it. At 30 fps, MCAP:
#: 10.4 % of a core woken per 20 ms batch, 9.4 % per 250 ms, 9.0 to 9.2 % per 0.5 to 1 s.
BATCH_S = 0.25
_CHUNK = 1 << 20
# A record holds one sample; the largest a service accepts is a 4096x4096 frame's candidates.
_MAX_RECORD = 64 << 20
_UNPACK_ERRORS = (ValueError, TypeError, msgpack.UnpackException)


class RecordWriter:
    """Writes a recording (module docstring) to ``path``; a context manager.

    Raises
    ------
    ToolError (code 2)
        If the file cannot be created.
    """

    def __init__(self, path: str | Path, *, robot: str, keys: list[str],
                 tool: str = "vistrack record", start_ns: int | None = None) -> None:
        self.path = Path(path)
        try:
            self._file: BinaryIO = open(path, "wb")  # closed by close()
        except OSError as e:
            raise ToolError(f"cannot write {str(path) or repr(str(path))}: {e.strerror}",
                            code=2) from None
        self._packer = msgpack.Packer(use_bin_type=True)
        self.start_ns = time.time_ns() if start_ns is None else int(start_ns)
        self._start_mono = time.monotonic_ns()
        self.count = 0
        self.keys_seen: set[str] = set()
        self._file.write(self._packer.pack({"format": FORMAT, "version": VERSION,
                                            "robot": robot, "keys": keys,
                                            "start_ns": self.start_ns,
                                            "tool": tool}))

    def write(self, key: str, payload: bytes, mono_ns: int) -> bool:
        """Append one sample that arrived at ``mono_ns`` (``time.monotonic_ns``)."""
        return self.write_at(key, payload, self.start_ns + (mono_ns - self._start_mono))

    def write_at(self, key: str, payload: bytes, t_ns: int) -> bool:
        """Append one sample that arrived at ``t_ns`` (ns since the Unix epoch)."""
        self._file.write(self._packer.pack({"t_ns": t_ns, "key": key, "payload": payload}))
        self.count += 1
        self.keys_seen.add(key)
        return True

    def flush(self) -> None:
        self._file.flush()

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> RecordWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class Recording:
    """A recording opened for reading; the header is checked on opening.

    Attributes
    ----------
    path : the file.
    header : the header map.

    Raises
    ------
    RecordError
        If the file cannot be opened or does not start with a version-1 header.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        try:
            with open(self.path, "rb") as f:
                head = f.read(_CHUNK)
        except OSError as e:
            raise RecordError(path, None, f"cannot read: {e.strerror}") from None
        unpacker = _unpacker()
        unpacker.feed(head)
        try:
            header = unpacker.unpack()
        except msgpack.OutOfData:
            problem = "empty file" if not head else "truncated header: the file ends inside it"
            raise RecordError(path, 0, f"not a vistrack recording ({problem})") from None
        except _UNPACK_ERRORS:
            header = None
        if not isinstance(header, dict) or header.get("format") != FORMAT:
            raise RecordError(path, 0, "not a vistrack recording (no vistrack-record header)")
        if header.get("version") != VERSION:
            raise RecordError(path, 0, f"recording format version {header.get('version')!r} "
                                       f"is not supported (this reader: {VERSION})")
        self.header: dict[str, Any] = header

    def records(self) -> Iterator[Record]:
        """The samples in file order.

        Raises
        ------
        RecordError
            At the first record that is corrupt or cut short (after yielding the valid ones).
        """
        with open(self.path, "rb") as f:
            objects = _objects(self.path, f)
            next(objects)  # the header, checked by __init__
            for offset, obj in objects:
                yield _record(self.path, offset, obj)


def _unpacker() -> msgpack.Unpacker:
    return msgpack.Unpacker(raw=False, strict_map_key=False, max_buffer_size=2 * _MAX_RECORD,
                            max_bin_len=_MAX_RECORD, max_str_len=1 << 20,
                            max_array_len=1 << 20, max_map_len=1 << 16, max_ext_len=0)


def _objects(path: Path, f: BinaryIO) -> Iterator[tuple[int, Any]]:
    """(byte offset, object) for each msgpack object of ``f``; RecordError on a bad one."""
    unpacker = _unpacker()
    fed = 0
    # where the object that ran out of data starts: the unpacker resumes it where it stopped,
    # and its tell() is then part of the way into it, not its start
    pending: int | None = None
    while True:
        chunk = f.read(_CHUNK)
        if chunk:
            unpacker.feed(chunk)
            fed += len(chunk)
        while True:
            offset = unpacker.tell() if pending is None else pending
            try:
                obj = unpacker.unpack()
            except msgpack.OutOfData:
                pending = offset  # it continues in the next chunk, or the file is cut short
                break
            except _UNPACK_ERRORS as e:
                detail = f"{type(e).__name__}: {e}" if str(e) else type(e).__name__
                raise RecordError(path, offset, f"corrupt record ({detail})") from None
            pending = None
            yield offset, obj
        if not chunk:
            start = unpacker.tell() if pending is None else pending
            if start < fed:
                raise RecordError(path, start, "truncated record: the file ends inside it "
                                  f"({fed - start} bytes of it present)")
            return


def _record(path: Path, offset: int, obj: Any) -> Record:
    if not isinstance(obj, dict):
        raise RecordError(path, offset, f"corrupt record: {type(obj).__name__} instead of a map")
    t_ns, key, payload = obj.get("t_ns"), obj.get("key"), obj.get("payload")
    if type(t_ns) is not int or t_ns < 0:
        raise RecordError(path, offset, "corrupt record: 't_ns' must be an integer >= 0")
    if not isinstance(key, str) or not key:
        raise RecordError(path, offset, "corrupt record: 'key' must be a non-empty string")
    if not _is_concrete_key(key):
        raise RecordError(path, offset, f"corrupt record: 'key' {key[:80]!r} is not a key a "
                          "sample can be published on (no empty chunk, wildcard, '#' or '?')")
    if not isinstance(payload, bytes):
        raise RecordError(path, offset, "corrupt record: 'payload' must be bin")
    return Record(t_ns, key, payload, offset)


def _is_concrete_key(key: str) -> bool:
    """Whether ``key`` is a valid Zenoh key without wildcards (what a recorded sample had)."""
    if "*" in key or "$" in key:
        return False
    try:
        zenoh.KeyExpr(key)
    except zenoh.ZError:
        return False
    return True


# -- either format ---------------------------------------------------------------------------

FORMATS = ("mcap", "vtr")
Writer = RecordWriter | McapWriter


def format_of(path: str | Path, fmt: str | None = None) -> str:
    """The format to write ``path`` in: ``fmt`` if given, else ``mcap`` for a ``.mcap``
    name and ``vtr`` for any other."""
    if fmt is not None:
        return fmt
    return "mcap" if Path(path).suffix.lower() == ".mcap" else "vtr"


def open_writer(path: str | Path, fmt: str | None, *, robot: str, keys: list[str],
                tool: str = "vistrack record", start_ns: int | None = None) -> Writer:
    """A writer of ``path`` in :func:`format_of` ``(path, fmt)`` (ToolError, code 2, if the
    file cannot be created)."""
    if format_of(path, fmt) == "mcap":
        if not is_name_token(robot):
            # the topics are /vistrack/<robot>/...: valid for MCAP and Foxglove, but a ROS 2
            # name refuses them, and `ros2 bag play` with them
            like = ("" if robot[:1].isalpha() else "r") + robot.replace("-", "_")
            warn(tool.removeprefix("vistrack "),
                 f"robot id {robot!r} makes topics that are not ROS 2 names "
                 f"(/vistrack/{robot}/camera/frame: each part letters, digits and '_', not "
                 "starting with a digit): Foxglove and the mcap tools read the file, "
                 f"`ros2 bag` does not; a robot id such as {like!r} makes it one")
        return McapWriter(path, robot=robot, keys=keys, tool=tool, start_ns=start_ns)
    return RecordWriter(path, robot=robot, keys=keys, tool=tool, start_ns=start_ns)


def open_recording(path: str | Path) -> Recording | McapRecording:
    """A recording opened for reading, MCAP or ``.vtr`` by its content (RecordError if it is
    neither: saying why it is no MCAP file when it is named ``.mcap``)."""
    if is_mcap(path):
        return McapRecording(path)
    try:
        return Recording(path)
    except RecordError:
        if Path(path).suffix.lower() == ".mcap":
            return McapRecording(path)  # raises, naming what is wrong for an MCAP file
        raise


def not_written(writer: Writer, keep: str = "record to .vtr to keep them") -> list[str]:
    """One line per key whose samples an MCAP writer left out, saying why (none for .vtr);
    ``keep``: how to keep those that have no ROS 2 type (an export: in the .vtr it read)."""
    if not isinstance(writer, McapWriter):
        return []
    lines = [f"{n} samples of {key} not written: it has no ROS 2 type ({keep})"
             for key, n in sorted(writer.skipped.items())]
    lines += [f"{n} samples of {key} not written: not valid messages (last: "
              f"{writer.last_error[key]})" for key, n in sorted(writer.rejected.items())]
    return lines


# -- the command ------------------------------------------------------------------------------

def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_path(parser, "file", example="run.vtr", metavar="FILE",
             help="recording to write (overwritten)")
    parser.add_argument("keys", nargs="*", metavar="KEY",
                        help="keys to record: camera/frame, estimate, '**', full keys "
                             "(default: every key of the robot)")
    add_number(parser, "--duration", lo=0, hi=1e6, lo_open=True, unit="s", default=None,
               metavar="S", help="stop after S seconds, %(allowed)s")
    add_number(parser, "--count", lo=1, hi=10**12, integer=True, default=None, metavar="N",
               help="stop after N samples, %(allowed)s")
    parser.add_argument("--format", choices=FORMATS, default=None,
                        help="mcap (ROS 2 messages, for Foxglove, PlotJuggler, ros2 bag) or vtr "
                             "(vistrack's msgpack stream); default: mcap for a .mcap FILE, "
                             "else vtr")
    add_tool_args(parser)


def _recorded(key: str) -> bool:
    suffix = key_suffix(key)
    return not (suffix.startswith("alive/") or suffix.endswith("/status"))


def check_writable(path: str | Path) -> None:
    """ToolError (code 2) where ``path`` cannot be written, an existing file left untouched
    (nothing truncated) and none left behind."""
    p = Path(path)
    existed = p.exists()
    try:
        with open(p, "ab"):
            pass
    except OSError as e:
        raise ToolError(f"cannot write {str(path) or repr(str(path))}: {e.strerror}",
                        code=2) from None
    if not existed:
        p.unlink(missing_ok=True)


def main(args: argparse.Namespace) -> int:
    try:
        keys = Keys(args.robot)
        exprs = sorted({resolve_key(keys, k, "record") for k in args.keys}) or [f"{keys.root}/**"]
        check_writable(args.file)
    except ToolError as e:
        error("record", e)
        return e.code

    def connected(session: zenoh.Session, _keys: Keys) -> int:
        # the file is created (an existing one emptied) once the router answered: a
        # recorder that cannot connect leaves it as it was (it cut a 16 MB recording to
        # its 108-byte header, then said "cannot connect")
        with open_writer(args.file, args.format, robot=args.robot, keys=exprs) as writer:
            return record(session, writer, exprs, args)
    return run("record", args, connected)


def record(session: zenoh.Session, writer: Writer, exprs: list[str],
           args: argparse.Namespace) -> int:
    inbox = Inbox(capacity=100_000)
    start = time.monotonic()
    next_flush = start + FLUSH_S

    last: dict[str, bytes] = {}  # the last payload written of each key
    repeats = 0

    def write(items: list[Received]) -> None:
        nonlocal repeats
        for item in items:
            if args.count is not None and writer.count >= args.count:
                return
            if not _recorded(item.key):
                continue
            if last.get(item.key) == item.payload:
                # the same bytes again: a sample its publisher sent again (a camera in
                # lockstep whose estimate did not come back in time), written once
                repeats += 1
                continue
            last[item.key] = item.payload
            writer.write(item.key, item.payload, item.mono_ns)

    with stop_on_signals() as stop:
        subs = [session.declare_subscriber(expr, inbox) for expr in exprs]
        print(f"vistrack record: recording {' '.join(exprs)} to {writer.path}",
              file=sys.stderr, flush=True)
        try:
            while not stop.is_set():
                now = time.monotonic()
                if args.duration is not None and now - start >= args.duration:
                    break
                if args.count is not None and writer.count >= args.count:
                    break
                if now >= next_flush:
                    writer.flush()
                    next_flush = now + FLUSH_S
                write(inbox.take())
                wake = min(next_flush, time.monotonic() + BATCH_S)
                if args.duration is not None:
                    wake = min(wake, start + args.duration)
                stop.wait(max(0.0, wake - time.monotonic()))
        finally:
            for sub in subs:
                sub.undeclare()
            write(inbox.take(most=inbox.capacity))  # what had arrived is written too
            writer.flush()
    if inbox.overflow:
        print(f"vistrack record: warning: {plural(inbox.overflow, 'sample')} lost (disk too "
              "slow)", file=sys.stderr)
    for line in not_written(writer):
        warn("record", line)
    again = (f"; {plural(repeats, 'sample')} sent again by its publisher (the same bytes) "
             "written once" if repeats else "")
    print(f"vistrack record: {plural(writer.count, 'sample')} of "
          f"{plural(len(writer.keys_seen), 'key')} in {time.monotonic() - start:.2f} s written "
          f"to {writer.path}{again}", file=sys.stderr)
    return 0
