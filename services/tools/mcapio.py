"""MCAP recordings: vistrack's samples as ROS 2 messages, the files Foxglove, PlotJuggler and
``ros2 bag`` open (``vistrack record FILE.mcap``, ``vistrack replay``, ``vistrack export``).

A file has the MCAP profile ``ros2``, zstd-compressed chunks, and:

* one channel per key, on the topic ``/`` + the full key (``/vistrack/robot/camera/frame``),
  typed as :mod:`vistrack.common.ros2types` says (schema encoding ``ros2msg``, with the
  ``.msg`` definitions of ``vistrack_msgs`` embedded; message encoding ``cdr``), with the
  channel metadata rosbag2's MCAP storage writes (``rosbag2_storage_mcap``,
  ``MCAPStorage::create_topic``), the first of them required by the MCAP registry's ``ros2``
  profile: ``offered_qos_profiles`` (:func:`offered_qos_profiles`, the QoS the messages are
  offered with: :func:`offered_qos`) and ``topic_type_hash`` (the type's ``RIHS01_`` hash);
* each estimate also drawn over its frame on ``/vistrack/<robot>/camera/features`` and
  ``/vistrack/<robot>/camera/centroid`` (``visualization_msgs/msg/ImageMarker``);
* per message: log time = arrival (ns since the Unix epoch, from a monotonic clock, so it
  never goes back); publish time = the contract's ``stamp_ns`` (the capture time of the frame
  the message derives from: a Twist has no header, so this is where its stamp lives);
  sequence = the contract's ``seq`` modulo 2^32;
* a metadata record ``vistrack``: ``robot``, ``keys`` (a JSON list), ``start_ns``, ``tool``.

Keys without a ROS 2 type (``sim/pose``) and payloads that are not valid messages of their key
are not written; the writer counts them (``skipped``, ``rejected``).

Reading rebuilds the contract's messages (:func:`~vistrack.common.ros2types.of_ros`): a frame's
``seq`` from the message sequence, a command's ``stamp_ns`` from the publish time (its
``stale`` flag is not in a Twist: False). The overlays are left out (they are drawn from the
estimates); ``preprocessing/frame`` (an Image does not carry the candidates) and topics of other
programs are not rebuilt either, and :attr:`McapRecording.skipped` says which and why.
"""

from __future__ import annotations

import collections
import importlib.metadata
import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

import mcap.writer
import yaml
import zstandard
from mcap.exceptions import RecordLengthLimitExceeded
from mcap.reader import SeekingReader
from mcap.records import Channel, Chunk, Header, Message, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.summary import Summary
from mcap.writer import CompressionType, Writer

from ...common import rmw_zenoh as rmw
from ...common import ros2types as r2
from ...common.keys import PREFIX, key_suffix
from ...common.messages import CmdVel, Estimate, MessageError, Params, Report, decode_any
from .shared import Record, RecordError, ToolError

#: The first 8 bytes of every MCAP file.
MAGIC = b"\x89MCAP0\r\n"
PROFILE = "ros2"
#: Chunk size before compression: a chunk is also closed by every flush (once a second).
CHUNK_BYTES = 1 << 20
#: The most a record, or a chunk once decompressed, may hold in a file vistrack reads: 16
#: times the largest camera/frame (a 4096 x 4096 mono8 Image, 16 MiB); writers' chunks are
#: 0.75 to 4 MiB by default. A 34 KB file whose one chunk unpacked to a 32768 x 32768
#: Image took 2.2 GB of memory before its size was refused, and the reader's own limit
#: (4 GiB a record) would have let a larger one take 8 GB or more.
MAX_READ_BYTES = 256 << 20
_SEQ_MOD = 1 << 32
#: zstd level of the chunks. mcap's writer calls ``zstandard.compress`` (level 3): on 256x256
#: frames that ran at 13 MB/s here, 7 % of a core for a 30 fps recording, against 1.6 % at
#: level 1 (ratio 1.57 instead of 1.77; lz4 gained nothing on these frames: 1.02).
ZSTD_LEVEL = 1


class _Zstd:
    """Stands in for the ``zstandard`` module inside ``mcap.writer``, which offers no level:
    the same ``compress`` at :data:`ZSTD_LEVEL` (any zstd reader decompresses it)."""

    def __init__(self, level: int) -> None:
        self._compressor = zstandard.ZstdCompressor(level=level)

    def compress(self, data: bytes) -> bytes:
        return self._compressor.compress(data)


#: The QoS each topic's messages are offered with (:func:`offered_qos`): those that must all
#: arrive, which vistrack publishes reliably (commands, parameters, reports), reliable with
#: KEEP_ALL history, as the ``ros2`` service offers ``/cmd_vel`` and ``vistrack/params``;
#: the rest (frames, estimates, the overlays), latest-only streams on Zenoh, reliable with
#: the last 10 kept, as it offers ``vistrack/estimate``. Reliable even for frames: a
#: reliable offer matches both reliable and best-effort subscriptions when ``ros2 bag play``
#: offers it again, a best-effort one only the latter.
QOS_ALL_KEYS = (CmdVel.KEY, Params.KEY, Report.KEY)
#: rmw_qos_liveliness_policy_t AUTOMATIC and RMW_DURATION_INFINITE: what rmw_zenoh reports
#: for a publisher whose token leaves liveliness, deadline, lifespan and lease at its
#: defaults (``qos.cpp``), as vistrack's do (:meth:`~vistrack.common.rmw_zenoh.QoS.keyexpr`)
LIVELINESS_AUTOMATIC = 1
DURATION_INFINITE = {"sec": 9_223_372_036, "nsec": 854_775_807}


def offered_qos(key: str) -> rmw.QoS:
    """The QoS the messages of ``key`` (a full key, or one of its overlays) are offered
    with (:data:`QOS_ALL_KEYS`)."""
    return rmw.QOS_ALL if key_suffix(key) in QOS_ALL_KEYS else rmw.QOS_DEFAULT


def offered_qos_profiles(qos: rmw.QoS) -> str:
    """The ``offered_qos_profiles`` channel metadata of one publisher offering ``qos``: a
    YAML list of one QoS map, laid out as rosbag2 writes it (``rosbag2_storage/qos.cpp``,
    yaml-cpp's block style, no final newline), with the enums as integers (rmw/types.h): the
    form rosbag2 wrote up to Iron, which Humble and Iron read (they read integers only) and
    Jazzy and later read too (they write names, ``reliable``, and read either)."""
    profile = {"history": qos.history, "depth": qos.depth, "reliability": qos.reliability,
               "durability": qos.durability, "deadline": dict(DURATION_INFINITE),
               "lifespan": dict(DURATION_INFINITE), "liveliness": LIVELINESS_AUTOMATIC,
               "liveliness_lease_duration": dict(DURATION_INFINITE),
               "avoid_ros_namespace_conventions": False}
    return yaml.safe_dump([profile], sort_keys=False).rstrip("\n")


def topic_of(key: str) -> str:
    """The MCAP / ROS 2 topic of a full key: ``vistrack/r/camera/frame`` ->
    ``/vistrack/r/camera/frame``."""
    return "/" + key


def key_of(topic: str) -> str:
    """The full key of a topic written by :func:`topic_of`."""
    return topic[1:] if topic.startswith("/") else topic


def _version() -> str:
    try:
        return importlib.metadata.version("vistrack")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def is_mcap(path: str | Path) -> bool:
    """Whether the file at ``path`` starts with the MCAP magic (False if it cannot be read)."""
    try:
        with open(path, "rb") as f:
            return f.read(len(MAGIC)) == MAGIC
    except OSError:
        return False


class McapWriter:
    """Writes an MCAP recording (module docstring) to ``path``; a context manager with the
    interface of the ``.vtr`` writer (``write``, ``flush``, ``close``, ``count``, ``keys_seen``).

    Attributes
    ----------
    count : samples written (overlays not counted).
    messages : MCAP messages written (each estimate's overlays too).
    keys_seen : keys of the samples written.
    skipped : key -> samples not written because the key has no ROS 2 type.
    rejected : key -> samples not written because the payload is not a valid message, or
        holds a value its ROS 2 type cannot (a stamp past 2038: int32 seconds).
    last_error : key -> why the last rejected sample of that key was rejected.

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
        mcap.writer.zstandard = _Zstd(ZSTD_LEVEL)  # type: ignore[assignment]  # see ZSTD_LEVEL
        self._mcap = Writer(self._file, chunk_size=CHUNK_BYTES,
                            compression=CompressionType.ZSTD)
        self._mcap.start(profile=PROFILE, library=f"vistrack {_version()}")
        self.start_ns = time.time_ns() if start_ns is None else int(start_ns)
        self._start_mono = time.monotonic_ns()
        self._mcap.add_metadata("vistrack", {"robot": robot, "keys": json.dumps(keys),
                                             "start_ns": str(self.start_ns), "tool": tool})
        self.count = 0
        self.messages = 0  # MCAP messages written: the samples and their overlays
        self.keys_seen: set[str] = set()
        self.skipped: collections.Counter[str] = collections.Counter()
        self.rejected: collections.Counter[str] = collections.Counter()
        self.last_error: dict[str, str] = {}
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._last_t = 0
        self._closed = False

    def write(self, key: str, payload: bytes, mono_ns: int) -> bool:
        """Append one sample that arrived at ``mono_ns`` (``time.monotonic_ns``); False if it
        was not written (see ``skipped`` and ``rejected``)."""
        return self.write_at(key, payload, self.start_ns + (mono_ns - self._start_mono))

    def write_at(self, key: str, payload: bytes, t_ns: int) -> bool:
        """Append one sample logged at ``t_ns`` (ns since the Unix epoch; an earlier time than
        the last one written is raised to it: log times never go back)."""
        suffix = key_suffix(key)
        typename = r2.ROS_TYPES.get(suffix)
        if typename is None:
            self.skipped[key] += 1
            return False
        try:
            msg = decode_any(key, payload)
            # every message of the sample made before any is written: all or none
            parts = [(key, typename, r2.serialize(r2.to_ros(msg, payload=payload)))]
            if isinstance(msg, Estimate):
                root = key[:-len(suffix)]
                parts += [(root + overlay, r2.IMAGE_MARKER, r2.serialize(draw(msg)))
                          for overlay, draw in r2.OVERLAYS.items()]
        except (MessageError, ValueError) as e:  # ValueError: valid, but no ROS 2 message
            self.rejected[key] += 1
            self.last_error[key] = str(e)
            return False
        t_ns = max(int(t_ns), self._last_t)
        self._last_t = t_ns
        for part_key, part_type, data in parts:
            self._add(part_key, part_type, data, t_ns, msg.stamp_ns, msg.seq)
        self.count += 1
        self.messages += len(parts)
        self.keys_seen.add(key)
        return True

    def _add(self, key: str, typename: str, data: bytes, t_ns: int, stamp_ns: int,
             seq: int) -> None:
        channel = self._channels.get(key)
        if channel is None:
            channel = self._channels[key] = self._mcap.register_channel(
                topic=topic_of(key), message_encoding="cdr", schema_id=self._schema(typename),
                metadata={"offered_qos_profiles": offered_qos_profiles(offered_qos(key)),
                          "topic_type_hash": r2.type_hash(typename)})
        self._mcap.add_message(channel_id=channel, log_time=t_ns, data=data,
                               publish_time=stamp_ns, sequence=seq % _SEQ_MOD)

    def _schema(self, typename: str) -> int:
        schema = self._schemas.get(typename)
        if schema is None:
            schema = self._schemas[typename] = self._mcap.register_schema(
                name=typename, encoding="ros2msg", data=r2.msgdef(typename).encode())
        return schema

    def flush(self) -> None:
        """Close the chunk in progress and write it out: a killed recorder loses only what
        came after the last flush."""
        self._mcap.flush()

    def close(self) -> None:
        """Write the summary and footer (indexes, statistics) and close the file."""
        if self._closed:
            return
        self._closed = True
        try:
            self._mcap.finish()
        finally:
            self._file.close()

    def __enter__(self) -> McapWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class McapRecording:
    """An MCAP file opened for replay: the contract's samples rebuilt from its messages.

    Attributes
    ----------
    path : the file.
    header : ``{"format": "mcap", "profile", "library"}`` of the file.
    skipped : topic -> why its messages are not replayed (filled as the file is read).

    Raises
    ------
    RecordError
        If the file cannot be read or does not start with an MCAP magic and header.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        try:
            with open(self.path, "rb") as f:
                head = f.read(len(MAGIC))
                if head != MAGIC:
                    what = "an empty file" if not head else f"starts with {head[:8]!r}"
                    raise RecordError(path, 0, f"not an MCAP file ({what}, not the MCAP magic)")
                try:
                    f.seek(0)
                    header = next(iter(StreamReader(f, record_size_limit=1 << 20).records))
                except Exception as e:  # noqa: BLE001 - damaged bytes: mcap raises many kinds
                    raise RecordError(path, len(MAGIC), "not a readable MCAP file: its header: "
                                      f"{_damage(e)}") from None
        except OSError as e:
            raise RecordError(path, None, f"cannot read: {e.strerror}") from None
        if not isinstance(header, Header):
            raise RecordError(path, len(MAGIC), "not a readable MCAP file: no header record "
                              f"after the magic ({type(header).__name__})")
        self.header = {"format": "mcap", "profile": header.profile, "library": header.library}
        self.skipped: dict[str, str] = {}
        summary = _summary(self.path)
        #: False when the file has no summary (a recorder that was killed, or a writer that
        #: writes none): it is replayed up to where it ends.
        self.complete = summary is not None
        #: The ``vistrack`` metadata record (robot, keys, start_ns, tool) of a complete file
        #: written by vistrack; empty otherwise.
        self.info: dict[str, str] = {}
        if summary is not None:
            self.info = _vistrack_metadata(self.path)
            replayed = [c for c in summary.channels.values()
                        if self._channel(c, summary.schemas.get(c.schema_id)) is not None]
            # a vistrack recording that caught nothing (no publisher) is empty, as an empty
            # .vtr is: it replays and exports nothing (it was refused as "no vistrack topic")
            empty_own = not summary.channels and bool(self.info)
            if not replayed and not empty_own:
                ours = {t: why for t, why in self.skipped.items() if t.startswith(f"/{PREFIX}/")}
                why = "; ".join(f"{t}: {w}" for t, w in sorted(ours.items())) if ours else (
                    f"it has {_topics(summary)} (vistrack replays the /{PREFIX}/<robot>/<key> "
                    "topics that vistrack record writes)")
                raise RecordError(path, None, f"no vistrack topic to read: {why}")

    def records(self) -> Iterator[Record]:
        """The samples the file's messages rebuild, in file order (the order they were
        written, which is arrival order for vistrack's files).

        Raises
        ------
        RecordError
            At the first damaged record, or message that is not a valid message of its key
            (after yielding the samples before it).
        """
        schemas: dict[int, Schema] = {}
        channels: dict[int, tuple[str, str, str] | None] = {}  # id -> (key, suffix, type)
        last_seq: dict[int, tuple[int, int]] = {}  # channel -> (sequence, seq) of its last
        with open(self.path, "rb") as f:
            reader = iter(StreamReader(f, validate_crcs=True, emit_chunks=True,
                                       record_size_limit=MAX_READ_BYTES).records)
            while True:
                start = f.tell()  # where the record, or the chunk taken apart, starts
                try:
                    rec = next(reader)
                    inner = self._unpacked(rec, start) if isinstance(rec, Chunk) else [rec]
                except RecordError:
                    raise
                except StopIteration:
                    return
                except RecordLengthLimitExceeded as e:  # a sound file, a record too large
                    raise RecordError(self.path, start, f"{e} (vistrack reads records of at "
                                      f"most {MAX_READ_BYTES >> 20} MiB)", damaged=False) \
                        from None
                except Exception as e:  # noqa: BLE001 - damaged bytes: mcap raises many kinds
                    raise RecordError(self.path, start, _damage(e)) from None
                for rec in inner:
                    if isinstance(rec, Schema):
                        schemas[rec.id] = rec
                    elif isinstance(rec, Channel):
                        channels[rec.id] = self._channel(rec, schemas.get(rec.schema_id))
                    elif isinstance(rec, Message):
                        target = channels.get(rec.channel_id)
                        if target is not None:
                            yield self._sample(rec, target, last_seq, start)

    def _unpacked(self, chunk: Chunk, offset: int) -> list:
        """The records of ``chunk``, decompressed here, never beyond the size it declares
        (at most :data:`MAX_READ_BYTES`): a chunk that holds more than it says is refused.
        mcap's own zstd path takes the size a zstd frame's header gives over the chunk's,
        and its lz4 path takes none: a 19 KB file whose chunk declared 4 KiB unpacked to
        600 MiB (1.3 GB of memory) past the check of the declared size alone."""
        size = chunk.uncompressed_size
        if size > MAX_READ_BYTES:
            raise RecordError(self.path, offset, f"a chunk of {size:,} bytes once "
                              f"decompressed, over the {MAX_READ_BYTES >> 20} MiB vistrack "
                              "reads in one (a camera/frame is at most 16 MiB)", damaged=False)
        if chunk.compression in ("zstd", "lz4"):
            if chunk.compression == "zstd":
                with zstandard.ZstdDecompressor().stream_reader(chunk.data) as unpack:
                    data = unpack.read(size + 1)
                    whole = len(data) == size and not unpack.read(1)
            else:
                import lz4.frame  # mcap's dependency for lz4 chunks
                out = lz4.frame.LZ4FrameDecompressor()
                data = out.decompress(chunk.data, max_length=size + 1)
                whole = len(data) == size and out.eof
            if not whole:
                raise RecordError(self.path, offset, f"a {chunk.compression} chunk that does "
                                  f"not hold the {size:,} bytes it declares")
            chunk = Chunk(message_start_time=chunk.message_start_time,
                          message_end_time=chunk.message_end_time, uncompressed_size=size,
                          uncompressed_crc=chunk.uncompressed_crc, compression="", data=data)
        return breakup_chunk(chunk, validate_crc=True)

    def _channel(self, channel: Channel, schema: Schema | None) -> tuple[str, str, str] | None:
        """(key, suffix, ROS type) of a channel to replay, or None (noted in ``skipped``)."""
        topic = channel.topic
        key = key_of(topic)
        parts = key.split("/", 2)
        suffix = key_suffix(key) if len(parts) == 3 and parts[0] == PREFIX else ""
        expected = r2.ROS_TYPES.get(suffix)
        name = schema.name if schema is not None else "no schema"
        if suffix in r2.OVERLAYS:
            return None  # drawn from the estimates again whenever they are written to MCAP
        if expected is None:
            self.skipped[topic] = (f"not a vistrack key (topics /{PREFIX}/<robot>/<key> are "
                                   "replayed)")
        elif suffix not in r2.REBUILT:
            self.skipped[topic] = f"a {name} does not carry a whole {suffix} message"
        elif schema is None or name != expected or schema.encoding != "ros2msg" \
                or channel.message_encoding != "cdr":
            self.skipped[topic] = (f"{name} ({schema.encoding if schema else '-'}, "
                                   f"{channel.message_encoding}), not {expected} (ros2msg, cdr)")
        elif (problem := r2.schema_problem(expected, schema.data.decode("utf-8", "replace"))):
            self.skipped[topic] = problem
        else:
            return key, suffix, expected
        return None

    def _sample(self, msg: Message, target: tuple[str, str, str],
                last_seq: dict[int, tuple[int, int]],
                offset: int) -> Record:
        key, suffix, typename = target
        # the 32-bit sequence, unwrapped: it counts on from the last one of the channel. A
        # sequence that does not move is not one: counted here (vistrack writes a sample
        # once, so its channels' sequences always move; rosbag2 and other writers leave it
        # 0, and every frame of such a file was seq 0, a camera restart each, no frame
        # tracked)
        last = last_seq.get(msg.channel_id)
        if last is None:
            seq = msg.sequence
        else:
            raw, counted = last
            seq = counted + ((msg.sequence - raw) % _SEQ_MOD or 1)
        last_seq[msg.channel_id] = (msg.sequence, seq)
        try:
            obj = r2.deserialize(msg.data, typename)
            payload = r2.of_ros(suffix, obj, seq=seq, stamp_ns_=msg.publish_time).encode()
        except (ValueError, TypeError) as e:  # MessageError is a ValueError
            raise RecordError(self.path, offset, f"message at log time {msg.log_time} on "
                              f"{topic_of(key)} is not a valid {suffix}: {e}") from None
        return Record(msg.log_time, key, payload, offset)


def _summary(path: Path) -> Summary | None:
    """The summary section of a complete MCAP file (None if it has none or is cut short)."""
    try:
        with open(path, "rb") as f:
            return SeekingReader(f).get_summary()
    except Exception:  # noqa: BLE001 - a damaged end: read on from the start instead
        return None


def _vistrack_metadata(path: Path) -> dict[str, str]:
    try:
        with open(path, "rb") as f:
            for record in SeekingReader(f).iter_metadata():
                if record.name == "vistrack":
                    return dict(record.metadata)
    except Exception:  # noqa: BLE001 - the metadata only informs; the messages are what counts
        pass
    return {}


def _topics(summary: Summary, most: int = 5) -> str:
    """"/a (type), /b (type) and N more" of a summary's channels."""
    def typename(c: Channel) -> str:
        schema = summary.schemas.get(c.schema_id)
        return schema.name if schema is not None else "no schema"
    names = [f"{c.topic} ({typename(c)})"
             for c in sorted(summary.channels.values(), key=lambda c: c.topic)]
    if not names:
        return "no channel"
    more = f" and {len(names) - most} more" if len(names) > most else ""
    return ", ".join(names[:most]) + more


def _describe(e: BaseException) -> str:
    return f"{type(e).__name__}: {e}" if str(e) else type(e).__name__


def _damage(e: BaseException) -> str:
    """What a reader exception says about the file, in a user's words."""
    if type(e).__name__ in ("EndOfFile", "EOFError") or "unpack requires" in str(e):
        return "truncated: the file ends inside a record (was the recorder killed?)"
    return f"damaged record ({_describe(e)})"
