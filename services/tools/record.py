"""``vistrack record FILE [KEY ...]``: record timestamped samples to a file, for ``replay``.

Without KEY, records every key of the robot (``vistrack/<robot>/**``; status replies and
liveliness tokens are not samples and are not recorded). Runs until Ctrl-C/SIGTERM,
``--duration`` or ``--count``, then flushes and closes the file (it is also flushed every
second, so a killed recorder loses at most the last second).

File format (version 1): a stream of msgpack maps, nothing else, so it can be read with any
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
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import msgpack
import zenoh

from ...common.keys import Keys, key_suffix
from ..usage import add_number
from .shared import Inbox, ToolError, add_tool_args, error, resolve_key, run, stop_on_signals

FORMAT = "vistrack-record"
VERSION = 1
FLUSH_S = 1.0
_CHUNK = 1 << 20
# A record holds one sample; the largest a service accepts is a 4096x4096 frame's candidates.
_MAX_RECORD = 64 << 20
_UNPACK_ERRORS = (ValueError, TypeError, msgpack.UnpackException)


class RecordError(Exception):
    """A recording is not readable from some byte on.

    Attributes
    ----------
    path : the file.
    offset : byte offset of the first record (or header) that could not be read; None when
        the file itself cannot be read.
    """

    def __init__(self, path: str | Path, offset: int | None, problem: str) -> None:
        where = "" if offset is None else f" at byte offset {offset}"
        super().__init__(f"{path}{where}: {problem}")
        self.path = str(path)
        self.offset = offset


@dataclass(frozen=True)
class Record:
    """One recorded sample (see the module docstring)."""

    t_ns: int
    key: str
    payload: bytes
    offset: int  # where it starts in the file


class RecordWriter:
    """Writes a recording (module docstring) to ``path``; a context manager.

    Raises
    ------
    ToolError (code 2)
        If the file cannot be created.
    """

    def __init__(self, path: str | Path, *, robot: str, keys: list[str]) -> None:
        self.path = Path(path)
        try:
            self._file: BinaryIO = open(path, "wb")  # closed by close()
        except OSError as e:
            raise ToolError(f"cannot write {str(path) or repr(str(path))}: {e.strerror}",
                            code=2) from None
        self._packer = msgpack.Packer(use_bin_type=True)
        self.start_ns = time.time_ns()
        self._start_mono = time.monotonic_ns()
        self.count = 0
        self.keys_seen: set[str] = set()
        self._file.write(self._packer.pack({"format": FORMAT, "version": VERSION,
                                            "robot": robot, "keys": keys,
                                            "start_ns": self.start_ns,
                                            "tool": "vistrack record"}))

    def write(self, key: str, payload: bytes, mono_ns: int) -> None:
        """Append one sample that arrived at ``mono_ns`` (``time.monotonic_ns``)."""
        t_ns = self.start_ns + (mono_ns - self._start_mono)
        self._file.write(self._packer.pack({"t_ns": t_ns, "key": key, "payload": payload}))
        self.count += 1
        self.keys_seen.add(key)

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
    while True:
        chunk = f.read(_CHUNK)
        if chunk:
            unpacker.feed(chunk)
            fed += len(chunk)
        while True:
            offset = unpacker.tell()
            try:
                obj = unpacker.unpack()
            except msgpack.OutOfData:
                break  # an object continues in the next chunk, or the file is cut short
            except _UNPACK_ERRORS as e:
                detail = f"{type(e).__name__}: {e}" if str(e) else type(e).__name__
                raise RecordError(path, offset, f"corrupt record ({detail})") from None
            yield offset, obj
        if not chunk:
            if unpacker.tell() < fed:
                raise RecordError(path, unpacker.tell(), "truncated record: the file ends "
                                  f"inside it ({fed - unpacker.tell()} bytes of it present)")
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


# -- the command ------------------------------------------------------------------------------

def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", metavar="FILE", help="recording to write (overwritten)")
    parser.add_argument("keys", nargs="*", metavar="KEY",
                        help="keys to record: camera/frame, estimate, '**', full keys "
                             "(default: every key of the robot)")
    add_number(parser, "--duration", lo=0, hi=1e6, lo_open=True, unit="s", default=None,
               metavar="S", help="stop after S seconds, %(allowed)s")
    add_number(parser, "--count", lo=1, hi=10**12, integer=True, default=None, metavar="N",
               help="stop after N samples, %(allowed)s")
    add_tool_args(parser)


def _recorded(key: str) -> bool:
    suffix = key_suffix(key)
    return not (suffix.startswith("alive/") or suffix.endswith("/status"))


def main(args: argparse.Namespace) -> int:
    try:
        keys = Keys(args.robot)
        exprs = sorted({resolve_key(keys, k) for k in args.keys}) or [f"{keys.root}/**"]
        writer = RecordWriter(args.file, robot=args.robot, keys=exprs)
    except ToolError as e:
        error("record", e)
        return e.code
    with writer:
        return run("record", args, lambda session, _keys: record(session, writer, exprs, args))


def record(session: zenoh.Session, writer: RecordWriter, exprs: list[str],
           args: argparse.Namespace) -> int:
    inbox = Inbox(capacity=100_000)
    start = time.monotonic()
    next_flush = start + FLUSH_S
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
                item = inbox.get(timeout=0.1)
                if item is not None and _recorded(item.key):
                    writer.write(item.key, item.payload, item.mono_ns)
        finally:
            for sub in subs:
                sub.undeclare()
            writer.flush()
    if inbox.overflow:
        print(f"vistrack record: warning: {inbox.overflow} samples lost (disk too slow)",
              file=sys.stderr)
    print(f"vistrack record: {writer.count} samples of {len(writer.keys_seen)} keys in "
          f"{time.monotonic() - start:.2f} s written to {writer.path}", file=sys.stderr)
    return 0
