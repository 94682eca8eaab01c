"""``vistrack export IN OUT``: convert a recording, e.g. an existing ``.vtr`` to MCAP.

IN is a ``.vtr`` or an MCAP recording (told apart by content); OUT is written as MCAP when it
ends in ``.mcap`` (or with ``--format mcap``), else as ``.vtr``. Every sample keeps its key and
its arrival time; what MCAP cannot carry is reported (``sim/pose`` has no ROS 2 type), and so
is what an MCAP file does not replay (:mod:`.mcapio`). No Zenoh: this runs anywhere.

A damaged IN (cut short, corrupt bytes) is converted up to its first bad record; OUT is then
closed as a valid file, and the export ends with a warning and a one-line error naming IN and
the byte offset (exit 2).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

from ...common.keys import validate_robot_id
from ..usage import add_path
from .mcapio import McapRecording
from .record import (
    FORMATS,
    Recording,
    Writer,
    format_of,
    not_written,
    open_recording,
    open_writer,
)
from .shared import RecordError, ToolError, error, warn

PROGRESS_S = 2.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_path(parser, "input", example="run.vtr", metavar="IN", help="a recording: .vtr or MCAP")
    add_path(parser, "output", example="run.mcap", metavar="OUT",
             help="file to write (overwritten): MCAP if it ends in .mcap, else .vtr")
    parser.add_argument("--format", choices=FORMATS, default=None,
                        help="format of OUT (default: mcap for a .mcap name, else vtr)")


def _origin(recording: Recording | McapRecording) -> tuple[str, list[str], int | None]:
    """(robot, keys, start_ns) the input says it was recorded with."""
    if isinstance(recording, McapRecording):
        info = recording.info
        try:
            keys = json.loads(info.get("keys", "[]"))
            start: int | None = int(info["start_ns"]) if "start_ns" in info else None
        except (ValueError, TypeError):
            keys, start = [], None
        robot = info.get("robot", "robot")
    else:
        keys, start = recording.header.get("keys", []), recording.header.get("start_ns")
        robot = recording.header.get("robot", "robot")
    try:
        robot = validate_robot_id(robot)
    except ValueError:
        robot = "robot"
    keys = [k for k in keys if isinstance(k, str)] if isinstance(keys, list) else []
    return robot, keys, start if isinstance(start, int) else None


def _same_file(a: str, b: str) -> bool:
    """Whether ``a`` and ``b`` name one file: one path, a symbolic link, or a hard link
    (which ``Path.resolve`` does not see: an export onto a hard link of its input emptied
    the input, 16 MB to 108 bytes, before it read a record)."""
    if Path(a).resolve() == Path(b).resolve():
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:  # either does not exist (yet): not one file
        return False


def main(args: argparse.Namespace) -> int:
    try:
        if _same_file(args.input, args.output):
            raise ToolError(f"{args.output}: OUT is IN: write the export to another file",
                            code=2)
        recording = open_recording(args.input)
        robot, keys, start_ns = _origin(recording)
        writer = open_writer(args.output, args.format, robot=robot, keys=keys,
                             tool="vistrack export", start_ns=start_ns)
    except RecordError as e:
        error("export", e)
        return 2
    except ToolError as e:
        error("export", e)
        return e.code
    try:
        with writer:
            return export(recording, writer, args)
    except OSError as e:  # a full disk, /dev/full: a traceback, then one from the close
        error("export", f"{args.output}: {e.strerror or e} (the export is incomplete)")
        return 1


def export(recording: Recording | McapRecording, writer: Writer,
           args: argparse.Namespace) -> int:
    start = time.monotonic()
    next_progress = start + PROGRESS_S
    read = 0
    damage: RecordError | None = None
    try:
        for rec in recording.records():
            writer.write_at(rec.key, rec.payload, rec.t_ns)
            read += 1
            if time.monotonic() >= next_progress:
                print(f"vistrack export: {read} samples read ...", file=sys.stderr, flush=True)
                next_progress += PROGRESS_S
    except RecordError as e:
        damage = e
    for line in not_written(writer, f"{args.input} keeps them" if isinstance(recording, Recording)
                            else "only a .vtr recording keeps them"):
        warn("export", line)
    for topic, why in sorted(getattr(recording, "skipped", {}).items()):
        warn("export", f"{topic} not exported: {why}")
    overlays = getattr(writer, "messages", writer.count) - writer.count
    print(f"vistrack export: {writer.count} of {read} samples ({len(writer.keys_seen)} keys) "
          f"from {recording.path} written to {writer.path} as "
          f"{format_of(args.output, args.format)}"
          + (f", with {overlays} overlay messages drawn from the estimates" if overlays else "")
          + f" in {time.monotonic() - start:.2f} s", file=sys.stderr)
    if damage is not None:
        warn("export", f"{recording.path}{' is damaged' if damage.damaged else ''}: read the "
                       f"{read} valid samples before byte offset {damage.offset}, and wrote "
                       f"{writer.count} of them")
        error("export", damage)
        return 2
    return 0
