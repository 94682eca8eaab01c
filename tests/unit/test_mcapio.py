"""MCAP recordings (services/tools/mcapio.py) as files, without Zenoh.

Read back with readers that are not ours: the ``mcap`` library's reader and
``mcap-ros2-support``'s ROS 2 decoder (which reads the schema embedded in the file, not our
type store); foreign files written with ``mcap-ros2-support``'s own writer and CDR encoder.
Frames are the built-in sequence, estimates the real tracker's over them.
"""

from __future__ import annotations

import contextlib
import json
import os

import cv2
import msgpack
import numpy as np
import pytest
from forkcli import vistrack
from mcap.reader import make_reader
from mcap.writer import CompressionType
from mcap_ros2.decoder import DecoderFactory
from mcap_ros2.writer import Writer as Ros2Writer
from rosbags.interfaces import QosDurability, QosHistory, QosLiveliness, QosReliability
from rosbags.rosbag2.storage_mcap import McapReader as RosbagsMcapReader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from vistrack.common import ros2types as r2
from vistrack.common.messages import CmdVel, Frame, Params, Pose, Report, decode_any
from vistrack.common.params import TrackerParams
from vistrack.common.synthetic import builtin_sequence
from vistrack.common.vision import Tracker
from vistrack.services.motion_estimation.service import estimate_message
from vistrack.services.ros2.service import BRIDGES
from vistrack.services.tools.mcapio import McapRecording, McapWriter
from vistrack.services.tools.record import Recording, RecordWriter
from vistrack.services.tools.shared import RecordError

ROOT = "vistrack/robot"
T0 = 1_700_000_000_000_000_000


def _samples(n: int = 12) -> list[tuple[str, bytes, int]]:
    """(full key, payload, arrival t_ns) of a short run: frames, estimates of the real
    tracker, commands, a parameter set and simulator poses, in arrival order."""
    tracker = Tracker(TrackerParams())
    out = [(f"{ROOT}/tuner/params", Params.from_tracker_params(
        TrackerParams(), seq=2**33 + 1, stamp_ns=T0, params_id=1, source="user",
        reason="by hand").encode(), T0 + 1)]
    for seq, image in enumerate(builtin_sequence(n)):
        stamp = T0 + seq * 33_333_333
        est = estimate_message(tracker.process(image, seq=seq), seq=seq, stamp_ns=stamp,
                               params_id=1)
        cmd = CmdVel(seq=seq, stamp_ns=stamp, vx=0.01 * seq, vy=-0.02, wz=0.0)
        pose = Pose(seq=seq, stamp_ns=stamp, x=0.0, y=0.1, theta=0.0, tx=1.0, ty=2.0)
        for suffix, msg, lag_ns in (("camera/frame", Frame.from_image(image, seq=seq,
                                                                      stamp_ns=stamp), 200_000),
                                    ("motion/estimate", est, 3_000_000),
                                    ("control/cmd_vel", cmd, 3_500_000),
                                    ("sim/pose", pose, 3_600_000)):
            out.append((f"{ROOT}/{suffix}", msg.encode(), stamp + lag_ns))
    report = Report(seq=1, stamp_ns=T0, design=[[-1, 1], [1, -1]], factors=["A", "B"],
                    order=[1, 0], responses={"tf": [0.2, 0.3]}, effects={"tf": {"1": 0.1}},
                    significant={"tf": {"99": ["1"], "95": ["1"]}},
                    optimum={"search_size": 10, "corr_size": 5}, sweep={"search": [10, 12]})
    out.append((f"{ROOT}/tuner/report", report.encode(), out[-1][2] + 1))
    return out


@pytest.fixture(scope="module")
def samples() -> list[tuple[str, bytes, int]]:
    return _samples()


@pytest.fixture(scope="module")
def recording(samples, tmp_path_factory):
    path = tmp_path_factory.mktemp("mcap") / "run.mcap"
    with McapWriter(path, robot="robot", keys=[f"{ROOT}/**"]) as writer:
        for key, payload, t_ns in samples:
            writer.write_at(key, payload, t_ns)
        writer.write_at(f"{ROOT}/motion/estimate", b"\x81\xa1v\x01", T0)  # not an estimate
    return path, writer


def _read(path):
    """Every message as (topic, schema, channel, message, decoded) with mcap's own reader."""
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        header = reader.get_header()
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        rows = [(ch.topic, sch, ch, msg, dec) for sch, ch, msg, dec
                in reader.iter_decoded_messages(log_time_order=False)]
    return header, summary, rows


def test_every_channel_and_message_decodes_with_mcap_ros2(recording, samples):
    path, writer = recording
    header, summary, rows = _read(path)
    assert header.profile == "ros2"
    assert writer.skipped == {f"{ROOT}/sim/pose": 12}
    assert writer.rejected == {f"{ROOT}/motion/estimate": 1}
    expected_types = {
        "camera/frame": r2.IMAGE, "motion/estimate": r2.ESTIMATE, "control/cmd_vel": r2.TWIST,
        "tuner/params": r2.PARAMS, "tuner/report": r2.REPORT,
        "camera/features": r2.IMAGE_MARKER,
        "camera/centroid": r2.IMAGE_MARKER}
    assert {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()} \
        == {f"/{ROOT}/{s}": t for s, t in expected_types.items()}
    for schema in summary.schemas.values():
        assert schema.encoding == "ros2msg" and schema.data.decode() == r2.msgdef(schema.name)
    assert all(c.message_encoding == "cdr" for c in summary.channels.values())
    counts = {c.topic: summary.statistics.channel_message_counts[c.id]
              for c in summary.channels.values()}
    assert counts[f"/{ROOT}/camera/frame"] == 12 and counts[f"/{ROOT}/camera/features"] == 12
    assert len(rows) == sum(counts.values()) == 12 * 5 + 2
    log_times = [msg.log_time for *_, msg, _ in rows]
    assert log_times == sorted(log_times)
    originals = {(key, decode_any(key, p).seq): decode_any(key, p) for key, p, _ in samples
                 if "sim/pose" not in key}
    for topic, _, _, msg, obj in rows:
        key = topic[1:]
        if key.endswith(("features", "centroid")):
            est = originals[(f"{ROOT}/motion/estimate", msg.sequence)]
            assert (obj.header.stamp.sec * 10**9 + obj.header.stamp.nanosec) == est.stamp_ns
            if key.endswith("features"):
                assert [(p.x, p.y) for p in obj.points] == [(x, y) for _, x, y in est.features]
            else:
                assert (obj.position.x, obj.position.y) == (est.xc, est.yc)
                assert obj.scale == pytest.approx((est.xe + est.ye) / (2 * est.npi), rel=1e-6)
            continue
        orig = originals[(key, msg.sequence if not key.endswith("params") else 2**33 + 1)]
        if key.endswith("report"):
            assert json.loads(obj.json)["factors"] == ["A", "B"] and list(obj.design) == \
                [-1, 1, 1, -1]
        assert msg.publish_time == orig.stamp_ns
        assert msg.sequence == orig.seq % 2**32
        if key.endswith("camera/frame"):
            assert obj.step * obj.height == len(obj.data) and obj.encoding == "mono8"
            assert np.array_equal(np.frombuffer(obj.data, np.uint8).reshape(obj.height,
                                                                            obj.width),
                                  orig.data)
        if hasattr(obj, "header"):
            assert obj.header.stamp.sec * 10**9 + obj.header.stamp.nanosec == orig.stamp_ns
        if key.endswith("estimate"):
            assert (obj.npi, obj.xc, obj.scale, len(obj.features)) == \
                (orig.npi, orig.xc, orig.scale, len(orig.features))
        if key.endswith("cmd_vel"):
            assert (obj.linear.x, obj.linear.y, obj.angular.z) == (orig.vx, orig.vy, orig.wz)


#: geometry_msgs/msg/Twist's type hash as ROS 2 Jazzy prints it (``ros2 topic info -v``)
TWIST_RIHS01 = "RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a"
#: RMW_DURATION_INFINITE, what rmw_zenoh reports for the deadline, lifespan and lease that
#: vistrack's publishers leave at its default
INFINITE = (9_223_372_036, 854_775_807)


def test_channels_carry_the_qos_profiles_and_type_hash_rosbag2_writes(recording):
    """The MCAP registry's ros2 profile requires ``offered_qos_profiles`` on every channel,
    and rosbag2's MCAP storage writes it and ``topic_type_hash``: ``ros2 bag play`` offers
    the recorded QoS, and a file without it is played with rosbag2's default. Judged by
    rosbags' own MCAP reader (its YAML parser, its enums), and the hash by a type store built
    from nothing but the schema embedded in the file."""
    path, _ = recording
    reliable = (QosReliability.RELIABLE, QosDurability.VOLATILE)
    expected = {  # topic suffix -> (reliability, durability), history, depth
        "camera/frame": (reliable, QosHistory.KEEP_LAST, 10),
        "camera/features": (reliable, QosHistory.KEEP_LAST, 10),
        "camera/centroid": (reliable, QosHistory.KEEP_LAST, 10),
        "motion/estimate": (reliable, QosHistory.KEEP_LAST, 10),
        "control/cmd_vel": (reliable, QosHistory.KEEP_ALL, 42),
        "tuner/params": (reliable, QosHistory.KEEP_ALL, 42),
        "tuner/report": (reliable, QosHistory.KEEP_ALL, 42)}
    reader = RosbagsMcapReader(path)
    reader.open()
    try:
        connections = {c.topic: c for c in reader.connections}
    finally:
        reader.close()
    assert set(connections) == {f"/{ROOT}/{s}" for s in expected}
    for suffix, ((reliability, durability), history, depth) in expected.items():
        profiles = connections[f"/{ROOT}/{suffix}"].ext.offered_qos_profiles
        assert len(profiles) == 1, suffix
        qos = profiles[0]
        assert (qos.reliability, qos.durability, qos.history, qos.depth) == \
            (reliability, durability, history, depth), suffix
        assert (qos.deadline, qos.lifespan, qos.liveliness_lease_duration) == (INFINITE,) * 3
        assert qos.liveliness == QosLiveliness.AUTOMATIC
        assert qos.avoid_ros_namespace_conventions is False

    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    hashes = {}
    for channel in summary.channels.values():
        schema = summary.schemas[channel.schema_id]
        store = get_typestore(Stores.EMPTY)  # the file's own definitions, nothing of ours
        store.register(get_types_from_msg(schema.data.decode(), schema.name))
        assert channel.metadata["topic_type_hash"] == store.hash_rihs01(schema.name), \
            channel.topic
        hashes[channel.topic] = channel.metadata["topic_type_hash"]
    assert hashes[f"/{ROOT}/control/cmd_vel"] == TWIST_RIHS01
    # rosbag2's layout (yaml-cpp's block style; the integer enums every distro reads)
    estimate = next(c for c in summary.channels.values() if c.topic.endswith("estimate"))
    assert estimate.metadata["offered_qos_profiles"] == (
        "- history: 1\n  depth: 10\n  reliability: 1\n  durability: 2\n"
        "  deadline:\n    sec: 9223372036\n    nsec: 854775807\n"
        "  lifespan:\n    sec: 9223372036\n    nsec: 854775807\n"
        "  liveliness: 1\n"
        "  liveliness_lease_duration:\n    sec: 9223372036\n    nsec: 854775807\n"
        "  avoid_ros_namespace_conventions: false")
    # the messages the ros2 service publishes are offered as it offers them
    for bridge in BRIDGES:
        qos = connections[f"/{ROOT}/{bridge.cls.KEY}"].ext.offered_qos_profiles[0]
        offer = bridge.qos
        assert (qos.reliability.value, qos.durability.value, qos.history.value, qos.depth) \
            == (offer.reliability, offer.durability, offer.history, offer.depth), bridge.attr


def test_reading_back_rebuilds_the_contract_messages(recording, samples):
    path, _ = recording
    rec = McapRecording(path)
    assert rec.complete and rec.info["robot"] == "robot"
    assert json.loads(rec.info["keys"]) == [f"{ROOT}/**"]
    got = list(rec.records())
    want = [(k, p, t) for k, p, t in samples if "sim/pose" not in k]
    assert [(r.key, r.t_ns) for r in got] == [(k, t) for k, _, t in want]
    for r, (key, payload, _) in zip(got, want, strict=True):
        a, b = decode_any(key, payload), decode_any(r.key, r.payload)
        if isinstance(a, Frame):
            assert (a.seq, a.stamp_ns) == (b.seq, b.stamp_ns)
            assert np.array_equal(a.data, b.data)
        else:
            assert a == b  # CmdVel: stale False travels as its default
    assert rec.skipped == {}


def test_export_vtr_to_mcap_and_back_keeps_every_sample(samples, tmp_path):
    vtr = tmp_path / "run.vtr"
    with RecordWriter(vtr, robot="robot", keys=[f"{ROOT}/**"]) as writer:
        for key, payload, t_ns in samples:
            writer.write_at(key, payload, t_ns)
    out = tmp_path / "run.mcap"
    run = vistrack("export", vtr, out)
    assert run.returncode == 0, run.stderr
    assert (f"12 samples of vistrack/robot/sim/pose not written: it has no ROS 2 type ({vtr} "
            "keeps them)") in run.stderr  # not "record to .vtr": it was read from one
    # the closing line's counts add up to what the file holds (it said 363 of 545 samples,
    # and the file held 543 messages: the overlays drawn from the estimates)
    estimates = sum(k.endswith("motion/estimate") for k, _, _ in samples)
    written = len(samples) - 12
    overlays = estimates * len(r2.OVERLAYS)
    assert (f"{written} of {len(samples)} samples" in run.stderr
            and f"with {overlays} overlay messages drawn from the estimates" in run.stderr)
    assert len(_read(out)[2]) == written + overlays
    back = tmp_path / "back.vtr"
    run = vistrack("export", out, back)
    assert run.returncode == 0, run.stderr
    records = list(Recording(back).records())
    assert [(r.key, r.t_ns) for r in records] == [(k, t) for k, _, t in samples
                                                  if "sim/pose" not in k]


@pytest.mark.parametrize("link", ["hard", "symbolic"])
def test_export_onto_a_link_to_its_input_is_refused_and_the_input_kept(samples, tmp_path,
                                                                       link):
    """OUT a hard link of IN is IN: the export emptied it (16 MB to 108 bytes) before it read
    a record, as ``Path.resolve`` does not see hard links."""
    vtr = tmp_path / "run.vtr"
    with RecordWriter(vtr, robot="robot", keys=[f"{ROOT}/**"]) as writer:
        for key, payload, t_ns in samples:
            writer.write_at(key, payload, t_ns)
    before = vtr.read_bytes()
    other = tmp_path / "other.vtr"
    if link == "hard":
        os.link(vtr, other)
    else:
        other.symlink_to(vtr)
    run = vistrack("export", vtr, other)
    assert run.returncode == 2
    assert run.stderr == f"vistrack export: error: {other}: OUT is IN: write the export to " \
                         "another file\n"
    assert vtr.read_bytes() == before


def test_a_truncated_file_replays_up_to_the_damage(recording, tmp_path):
    path, _ = recording
    data = path.read_bytes()
    whole = list(McapRecording(path).records())
    for cut_at in (len(data) // 2, len(data) - 10):
        cut = tmp_path / f"cut{cut_at}.mcap"
        cut.write_bytes(data[:cut_at])
        rec = McapRecording(cut)
        assert not rec.complete
        got = []
        with pytest.raises(RecordError, match="truncated") as err:
            for r in rec.records():
                got.append(r)
        assert str(cut) in str(err.value) and "\n" not in str(err.value)
        assert [(r.key, r.payload) for r in got] == [(r.key, r.payload)
                                                     for r in whole[:len(got)]]
    cut = tmp_path / "header.mcap"
    cut.write_bytes(data[:20])
    with pytest.raises(RecordError, match="not a readable MCAP file"):
        McapRecording(cut)


def _foreign(path, topic: str, typename: str, msgdef: str, message: dict,
             more: int = 0) -> None:
    """An MCAP file from another program: mcap-ros2-support's writer and CDR encoder; with
    ``more``, that many more messages after the first, 33 ms apart, with the sequence such
    writers leave (0, its default, as rosbag2 writes it)."""
    with open(path, "wb") as f:
        writer = Ros2Writer(f)
        schema = writer.register_msgdef(typename, msgdef)
        writer.write_message(topic=topic, schema=schema, message=message, log_time=T0,
                             publish_time=T0, sequence=0 if more else 5)
        for k in range(1, more + 1):
            t = T0 + k * 33_000_000
            writer.write_message(topic=topic, schema=schema, message=message, log_time=t,
                                 publish_time=t)
        writer.finish()


def _image(width: int, height: int, encoding: str, data: bytes, step: int) -> dict:
    return {"header": {"stamp": {"sec": 1700000000, "nanosec": 0}, "frame_id": "cam"},
            "height": height, "width": width, "encoding": encoding, "is_bigendian": 0,
            "step": step, "data": data}


def _write_frames(path, images: list[dict], **writer) -> None:
    """``images`` on the camera/frame topic of an MCAP file at ``path`` (or into a binary
    stream), written by mcap-ros2-support's writer."""
    with open(path, "wb") if not hasattr(path, "write") else contextlib.nullcontext(path) as f:
        w = Ros2Writer(f, **writer)
        schema = w.register_msgdef(r2.IMAGE, r2.msgdef(r2.IMAGE))
        for k, image in enumerate(images):
            t = T0 + k * 33_000_000
            w.write_message(topic=f"/{ROOT}/camera/frame", schema=schema, message=image,
                            log_time=t, publish_time=t, sequence=k + 1)
        w.finish()


@pytest.mark.parametrize("compression", list(CompressionType), ids=lambda c: c.name)
def test_frames_are_read_back_from_every_chunk_compression(tmp_path, compression):
    """zstd (ours), lz4 (another writer's) and none: the chunks are unpacked by vistrack
    (bounded by their declared size, :data:`MAX_READ_BYTES`), each frame as it was."""
    rng = np.random.default_rng(3)
    grey = [rng.integers(0, 256, (30, 40), dtype=np.uint8) for _ in range(5)]
    path = tmp_path / "c.mcap"
    _write_frames(path, [_image(40, 30, "mono8", g.tobytes(), 40) for g in grey],
                  compression=compression, chunk_size=4000)  # a chunk every 3 frames
    got = [decode_any(r.key, r.payload) for r in McapRecording(path).records()]
    assert [f.seq for f in got] == [1, 2, 3, 4, 5]
    assert all(np.array_equal(f.data, g) for f, g in zip(got, grey, strict=True))


@pytest.mark.parametrize(("compression", "said"), [
    (CompressionType.ZSTD, "a chunk of 4194"),
    (CompressionType.NONE, "CHUNK record has length 4194"),
], ids=["zstd", "none"])
def test_a_chunk_larger_than_vistrack_reads_is_refused_before_it_is_unpacked(
        tmp_path, monkeypatch, capsys, compression, said):
    """A 34 KB file whose one chunk unpacked to a 32768 x 32768 Image took 2.2 GB of memory
    before the frame's size was refused. A chunk that declares more than MAX_READ_BYTES
    (here made 1 MiB, the frame 4 MiB of zeros, 4 KB compressed) is refused unread; so is
    an uncompressed chunk (or any record: an attachment) over it. The frame before it is
    read, and the sound file is not called damaged."""
    from vistrack.services import cli
    from vistrack.services.tools import export, mcapio

    path = tmp_path / "big.mcap"
    small = _image(40, 30, "mono8", bytes(1200), 40)
    big = _image(2048, 2048, "mono8", bytes(2048 * 2048), 2048)
    _write_frames(path, [small, big], compression=compression,
                  chunk_size=1 << 10)  # one chunk each
    monkeypatch.setattr(mcapio, "MAX_READ_BYTES", 1 << 20)
    got = []
    with pytest.raises(RecordError) as err:
        for rec in McapRecording(path).records():
            got.append(rec)
    assert len(got) == 1 and not err.value.damaged
    text = str(err.value)
    assert "1 MiB" in text and said in text.replace(",", ""), text
    out = tmp_path / "out.vtr"
    args = cli.build_parser("export").parse_args(["export", str(path), str(out)])
    assert export.main(args) == 2
    said_err = capsys.readouterr().err
    assert f"vistrack export: warning: {path}: read the 1 valid samples before byte offset" \
        in said_err and "is damaged" not in said_err, said_err


@pytest.mark.parametrize("compression", ["zstd", "lz4"])
def test_a_chunk_that_holds_more_than_it_declares_is_refused_unpacked(tmp_path, compression):
    """A chunk that declares 4 KiB and holds 2 MiB (its zstd frame saying so in its own
    header, which mcap's reader believed over the chunk's: a 19 KB file took 1.3 GB at
    600 MiB): unpacked only to the size declared, and refused."""
    import io
    import struct

    import lz4.frame
    import zstandard
    from mcap.data_stream import RecordBuilder
    from mcap.records import Chunk, DataEnd, Footer
    from mcap.stream_reader import StreamReader

    buf = io.BytesIO()
    _write_frames(buf, [_image(40, 30, "mono8", bytes(1200), 40)],
                  compression=CompressionType.NONE, chunk_size=1 << 30)
    raw = buf.getvalue()
    chunk = next(r for r in StreamReader(io.BytesIO(raw), emit_chunks=True).records
                 if isinstance(r, Chunk))
    n = 2 << 20  # the records, then an unknown record that pads them to 2 MiB
    inner = chunk.data + b"\x7f" + struct.pack("<Q", n - len(chunk.data) - 9) \
        + bytes(n - len(chunk.data) - 9)
    packed = (zstandard.ZstdCompressor(write_content_size=True).compress(inner)
              if compression == "zstd" else lz4.frame.compress(inner))
    lying = Chunk(message_start_time=chunk.message_start_time,
                  message_end_time=chunk.message_end_time, uncompressed_size=4096,
                  uncompressed_crc=0, compression=compression, data=packed)
    old, new = RecordBuilder(), RecordBuilder()
    chunk.write(old)
    lying.write(new)
    end = RecordBuilder()
    DataEnd(data_section_crc=0).write(end)
    Footer(summary_start=0, summary_offset_start=0, summary_crc=0).write(end)
    head = raw[:raw.index(old.end())]
    path = tmp_path / "lying.mcap"
    path.write_bytes(head + new.end() + end.end() + b"\x89MCAP0\r\n")
    with pytest.raises(RecordError, match=f"a {compression} chunk that does not hold the "
                                          "4,096 bytes it declares"):
        list(McapRecording(path).records())


@pytest.mark.parametrize(("encoding", "channels", "to_grey"), [
    ("rgb8", 3, lambda px: cv2.cvtColor(px, cv2.COLOR_RGB2GRAY)),
    ("bgr8", 3, lambda px: cv2.cvtColor(px, cv2.COLOR_BGR2GRAY)),
    ("mono16", 2, lambda px: px.view("<u2")[:, :, 0] >> 8),
])
def test_a_bag_of_a_colour_or_16_bit_camera_is_replayed_grey(tmp_path, encoding, channels,
                                                             to_grey):
    """A valid rosbag2 file with rgb8, bgr8 or 16-bit frames on the camera/frame topic was
    refused as damaged at its first frame (only mono8 was read); its frames are now made
    grey as the ROS 2 camera source makes them (16-bit by the high byte)."""
    rng = np.random.default_rng(4)
    pixels = rng.integers(0, 256, (30, 40, channels), dtype=np.uint8)
    path = tmp_path / f"{encoding}.mcap"
    _write_frames(path, [_image(40, 30, encoding, pixels.tobytes(), 40 * channels)] * 2)
    got = [decode_any(r.key, r.payload) for r in McapRecording(path).records()]
    assert len(got) == 2
    expected = to_grey(pixels.reshape(30, 40, channels)).astype(np.uint8)
    assert np.array_equal(got[0].data, expected)


def test_frames_of_a_writer_that_leaves_the_sequence_0_are_numbered_in_order(tmp_path):
    """rosbag2 (and mcap-ros2-support's writer by default) leave every message's sequence 0:
    replayed, every frame was seq 0, which motion-estimation takes for a camera restarted,
    so each estimate was a first one and nothing was tracked."""
    path = tmp_path / "bag.mcap"
    image = {"header": {"stamp": {"sec": 1700000000, "nanosec": 0}, "frame_id": "cam"},
             "height": 2, "width": 3, "encoding": "mono8", "is_bigendian": 0, "step": 3,
             "data": bytes(range(6))}
    _foreign(path, f"/{ROOT}/camera/frame", r2.IMAGE, r2.msgdef(r2.IMAGE), image, more=4)
    seqs = [decode_any(r.key, r.payload).seq for r in McapRecording(path).records()]
    assert seqs == [0, 1, 2, 3, 4]


def test_an_estimate_written_by_another_encoder_is_read_back(tmp_path):
    path = tmp_path / "other.mcap"
    _foreign(path, f"/{ROOT}/motion/estimate", r2.ESTIMATE, r2.msgdef(r2.ESTIMATE), {
        "header": {"stamp": {"sec": 1700000000, "nanosec": 5}, "frame_id": "cam"},
        "seq": 9, "valid": True, "npi": 1, "xc": 3.0, "yc": 4.0, "xe": 0.0, "ye": 0.0,
        "dx": 0.5, "dy": -0.5, "scale": 1.0, "t_ms": 0.2, "first": False, "params_id": 3,
        "features": [{"id": 4, "x": 3.0, "y": 4.0}]})
    (rec,) = McapRecording(path).records()
    est = decode_any(rec.key, rec.payload)
    assert rec.key == f"{ROOT}/motion/estimate" and rec.t_ns == T0
    assert (est.seq, est.stamp_ns, est.npi, est.xc, est.dx, est.params_id) == \
        (9, 1_700_000_000_000_000_005, 1, 3.0, 0.5, 3)
    assert est.features == [[4, 3.0, 4.0]]


def test_a_foreign_mcap_file_is_refused_naming_what_it_holds(tmp_path):
    path = tmp_path / "tf.mcap"
    _foreign(path, "/chatter", "std_msgs/msg/String", "string data", {"data": "hi"})
    with pytest.raises(RecordError, match=r"no vistrack topic to read: it has /chatter "
                                          r"\(std_msgs/msg/String\)"):
        McapRecording(path)
    wrong = tmp_path / "wrong-type.mcap"
    _foreign(wrong, f"/{ROOT}/camera/frame", "std_msgs/msg/String", "string data",
             {"data": "hi"})
    with pytest.raises(RecordError, match="no vistrack topic"):
        McapRecording(wrong)
    run = vistrack("replay", path)
    assert run.returncode == 2
    assert run.stderr.count("\n") == 1 and run.stderr.startswith("vistrack replay: error: ")
    assert str(path) in run.stderr and "/chatter" in run.stderr
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"PNG not an mcap file")
    run = vistrack("export", junk, tmp_path / "out.mcap")
    assert run.returncode == 2 and run.stderr.count("\n") == 1
    assert str(junk) in run.stderr and "not an MCAP file" in run.stderr


def test_a_schema_other_than_ours_is_not_replayed(tmp_path):
    path = tmp_path / "old.mcap"
    old = r2.msgdef(r2.PARAMS).replace("uint32 ungroup_size\n", "")
    _foreign(path, f"/{ROOT}/tuner/params", r2.PARAMS, old, {
        "header": {"stamp": {"sec": 1, "nanosec": 0}, "frame_id": ""}, "seq": 1,
        "max_features": 100, "thres_percent": 2.0, "search_size": 15, "corr_size": 9,
        "params_id": 1, "source": "user", "reason": ""})
    with pytest.raises(RecordError, match="ungroup_size"):
        McapRecording(path)


@pytest.mark.parametrize("cut_into", [1000, 300_000])
def test_a_vtr_cut_inside_a_record_names_where_that_record_starts(tmp_path, cut_into):
    """A .vtr whose last record is cut ``cut_into`` bytes in: the records before it are read
    and the error names the offset where the cut record starts and how much of it is there.
    It named the unpacker's position part of the way into the record (60 bytes in, '940 of
    1000 present'), and a record read across the reader's 1 MiB chunks was yielded with such
    an offset too."""
    vtr = tmp_path / "run.vtr"
    payload = bytes(range(256)) * 2000  # 512 000 bytes a record: several span a chunk
    with RecordWriter(vtr, robot="robot", keys=[f"{ROOT}/**"]) as writer:
        for k in range(6):
            writer.write_at(f"{ROOT}/camera/frame", payload, 1000 + k)
    data = vtr.read_bytes()
    whole = msgpack.Unpacker(raw=False)  # fed the whole file at once: tell() is each start
    whole.feed(data)
    starts = []
    for _ in range(7):  # the header, then the records
        starts.append(whole.tell())
        whole.unpack()
    starts = starts[1:]
    (tmp_path / "cut.vtr").write_bytes(data[:starts[-1] + cut_into])
    got = []
    with pytest.raises(RecordError) as e:
        for r in Recording(tmp_path / "cut.vtr").records():
            got.append(r.t_ns)
    assert got == [1000, 1001, 1002, 1003, 1004]
    assert str(e.value) == (f"{tmp_path / 'cut.vtr'} at byte offset {starts[-1]}: truncated "
                            f"record: the file ends inside it ({cut_into} bytes of it present)")


def test_a_valid_message_no_ros_2_type_holds_is_rejected_and_the_file_goes_on(tmp_path):
    """An estimate stamped past 2038 is valid for the contract, but ROS 2 time holds int32
    seconds: the writer counts it rejected, names why, writes none of its messages (nor its
    overlays), and writes what comes after (``record`` died on rosbags' struct.error, and
    ``export`` left a file of the samples before it)."""
    samples = [(k, p, t) for k, p, t in _samples(4) if k.endswith("motion/estimate")]
    key, payload, t_ns = samples[1]
    late = msgpack.unpackb(payload)
    late["stamp_ns"] = 2 ** 31 * 1_000_000_000  # 2038-01-19T03:14:08Z
    path = tmp_path / "late.mcap"
    with McapWriter(path, robot="robot", keys=[f"{ROOT}/**"]) as writer:
        assert writer.write_at(*samples[0])
        assert not writer.write_at(key, msgpack.packb(late), t_ns)
        assert writer.write_at(*samples[2])
    assert writer.rejected[key] == 1 and writer.count == 2
    assert "2038-01-19" in writer.last_error[key] and "int32" in writer.last_error[key]
    _, _, rows = _read(path)
    stamps = {(dec.header.stamp.sec, dec.header.stamp.nanosec) for *_, dec in rows}
    written = {divmod(msgpack.unpackb(p)["stamp_ns"], 1_000_000_000) for _, p, _ in
               (samples[0], samples[2])}
    assert stamps == written
    per_topic = {topic for topic, *_ in rows}
    assert {f"/{ROOT}/motion/estimate", *(f"/{ROOT}/{s}" for s in r2.OVERLAYS)} <= per_topic
    assert len(rows) == 2 * (1 + len(r2.OVERLAYS))  # two samples, each with its overlays


def test_a_report_keeps_the_fields_beyond_the_contract_in_its_json(tmp_path):
    """The README: "the whole report as JSON in json". It held only the contract's fields:
    the auto-tuner's trigger, changed and params_id were dropped on the way."""
    key, payload, t_ns = next(s for s in _samples(4) if s[0].endswith("tuner/report"))
    published = msgpack.unpackb(payload)
    published.update(trigger="scene change", changed=True, params_id=7)
    path = tmp_path / "report.mcap"
    with McapWriter(path, robot="robot", keys=[f"{ROOT}/**"]) as writer:
        assert writer.write_at(key, msgpack.packb(published), t_ns)
    _, _, rows = _read(path)
    (whole,) = [json.loads(dec.json) for topic, *_, dec in rows if topic.endswith("report")]
    assert (whole["trigger"], whole["changed"], whole["params_id"]) == ("scene change", True, 7)
    assert whole["optimum"] == published["optimum"] and whole["seq"] == published["seq"]


def test_an_empty_recording_replays_and_exports_nothing_as_an_empty_vtr_does(tmp_path):
    """A recorder that caught nothing (no publisher) writes an MCAP file with no channel: it
    was refused ("no vistrack topic to read", exit 2, for export too) where an empty .vtr
    replays and exports with exit 0."""
    for name, writer_type in (("empty.mcap", McapWriter), ("empty.vtr", RecordWriter)):
        path = tmp_path / name
        with writer_type(path, robot="robot", keys=[f"{ROOT}/**"]):
            pass
        out = tmp_path / f"out-{name}.vtr"
        run = vistrack("export", path, out)
        assert run.returncode == 0, (name, run.stderr)
        assert f"0 of 0 samples (0 keys) from {path}" in run.stderr
        assert list(Recording(out).records()) == []
    with pytest.raises(RecordError, match="no vistrack topic"):  # another program's, empty
        path = tmp_path / "foreign.mcap"
        with open(path, "wb") as f:
            Ros2Writer(f).finish()
        McapRecording(path)


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="no /dev/full here")
@pytest.mark.parametrize("fmt", ["vtr", "mcap"])
def test_an_export_onto_a_full_disk_is_one_line_not_a_traceback(samples, tmp_path, fmt):
    """/dev/full (every write fails, as on a full disk): two chained tracebacks, the second
    from the writer's close."""
    vtr = tmp_path / "run.vtr"
    with RecordWriter(vtr, robot="robot", keys=[f"{ROOT}/**"]) as writer:
        for key, payload, t_ns in samples:
            writer.write_at(key, payload, t_ns)
    run = vistrack("export", vtr, "/dev/full", "--format", fmt)
    assert run.returncode == 1, run.stderr
    assert run.stderr.splitlines()[-1] == ("vistrack export: error: /dev/full: No space left "
                                           "on device (the export is incomplete)")
    assert "Traceback" not in run.stderr


@pytest.mark.parametrize(("robot", "like"), [("robot-1", "robot_1"), ("2wheels", "r2wheels"),
                                             ("robot_1", None)])
def test_a_robot_id_that_makes_no_ros_2_topic_is_said_when_writing_mcap(tmp_path, capsys,
                                                                        robot, like):
    """Robot ids may hold '-' and start with a digit; ROS 2 names may not, so the topics of
    such a file (/vistrack/robot-1/...) are no ROS 2 names and `ros2 bag` refuses them:
    written all the same (Foxglove and the mcap tools read them), with a warning that says
    so and names an id that works. A .vtr has no topics: nothing to say."""
    from vistrack.services.tools.record import open_writer

    with open_writer(tmp_path / "r.mcap", None, robot=robot, keys=[f"vistrack/{robot}/**"]):
        pass
    said = capsys.readouterr().err
    if like is None:
        assert said == ""
    else:
        assert said.startswith(f"vistrack record: warning: robot id {robot!r} makes topics "
                               "that are not ROS 2 names") and said.count("\n") == 1
        assert f"a robot id such as {like!r} makes it one" in said
    with open_writer(tmp_path / "r.vtr", None, robot=robot, keys=[f"vistrack/{robot}/**"]):
        pass
    assert capsys.readouterr().err == ""
