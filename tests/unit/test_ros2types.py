"""The contract's messages as ROS 2 messages (common/ros2types.py).

Checked against references that are not our code: the CDR layout of the OMG XCDR1 encoding
written out by hand for a tiny image, the type hash that ROS 2 itself prints for
``geometry_msgs/msg/Twist`` (``ros2 topic info --verbose``, and the key example of the
rmw_zenoh design document), and MCAP's own ROS 2 decoder (``mcap_ros2``) reading our CDR with
our schema text.
"""

from __future__ import annotations

import struct

import numpy as np
import pytest
from mcap.records import Schema
from mcap_ros2._dynamic import generate_dynamic
from mcap_ros2.decoder import DecoderFactory

from vistrack.common import ros2types as r2
from vistrack.common.messages import CmdVel, Estimate, Frame, Params, Report

TWIST_RIHS01 = "RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a"


def _estimate() -> Estimate:
    return Estimate(seq=7, stamp_ns=1_700_000_000_123_456_789, npi=3, xc=10.5, yc=20.25,
                    xe=4.0, ye=2.0, dx=-1.5, dy=0.25, scale=1.01, t_ms=0.3, first=False,
                    features=[[1, 10.0, 20.0], [2, 11.5, 21.0], [5, 10.0, 19.75]],
                    params_id=4)


def _report() -> Report:
    return Report(seq=2, stamp_ns=5, design=[[-1, 1], [1, -1]], factors=["A", "B"],
                  order=[1, 0], responses={"tf": [0.2, 0.3], "ex": [0.1, 0.0]},
                  effects={"tf": {"1": 0.1, "2": -0.05}, "ex": {"1": 0.0, "2": 0.1}},
                  significant={"tf": {"99": ["1"], "95": ["1", "2"]}, "ex": {"99": [],
                                                                         "95": []}},
                  optimum={"max_features": 100, "thres_percent": 2.0, "search_size": 10,
                           "corr_size": 5, "ungroup_size": 5},
                  sweep={"search": [10, 12], "corr": [5, 7]})


def test_twist_type_hash_is_the_one_ros2_prints():
    assert r2.type_hash(r2.TWIST) == TWIST_RIHS01


def test_our_types_have_stable_distinct_hashes():
    hashes = {t: r2.type_hash(t) for t in (r2.ESTIMATE, r2.PARAMS, r2.REPORT)}
    assert len(set(hashes.values())) == 3
    assert all(h.startswith("RIHS01_") and len(h) == 7 + 64 for h in hashes.values())


def test_image_cdr_bytes_follow_xcdr1_little_endian_by_hand():
    frame = Frame.from_image(np.array([[3, 250]], np.uint8), seq=0,
                             stamp_ns=2 * 10**9 + 5)
    got = r2.serialize(r2.image(frame))
    expected = b"".join([
        b"\x00\x01\x00\x00",                      # encapsulation: CDR_LE, options 0
        struct.pack("<iI", 2, 5),                 # header.stamp sec, nanosec
        struct.pack("<I", 7) + b"camera\x00",     # frame_id: length with NUL, text, NUL
        b"\x00",                                  # pad to 4
        struct.pack("<II", 1, 2),                 # height, width
        struct.pack("<I", 6) + b"mono8\x00",      # encoding
        b"\x00",                                  # is_bigendian (uint8)
        b"\x00",                                  # pad to 4
        struct.pack("<I", 2),                     # step
        struct.pack("<I", 2) + bytes([3, 250]),   # data: length, bytes
    ])
    assert got == expected


def _decode_with_mcap_ros2(typename: str, data: bytes):
    schema = Schema(id=1, name=typename, encoding="ros2msg", data=r2.msgdef(typename).encode())
    decoder = DecoderFactory().decoder_for("cdr", schema)
    assert decoder is not None
    return decoder(data)


def test_mcap_ros2_reads_our_schema_and_cdr():
    est = _estimate()
    got = _decode_with_mcap_ros2(r2.ESTIMATE, r2.serialize(r2.estimate(est)))
    assert (got.seq, got.npi, got.xc, got.dy, got.params_id) == (7, 3, 10.5, 0.25, 4)
    assert (got.header.stamp.sec, got.header.stamp.nanosec) == (1_700_000_000, 123_456_789)
    assert [(f.id, f.x, f.y) for f in got.features] == [(1, 10.0, 20.0), (2, 11.5, 21.0),
                                                        (5, 10.0, 19.75)]
    cmd = CmdVel(seq=1, stamp_ns=0, vx=0.5, vy=-0.25, wz=0.125)
    tw = _decode_with_mcap_ros2(r2.TWIST, r2.serialize(r2.twist(cmd)))
    assert (tw.linear.x, tw.linear.y, tw.angular.z) == (0.5, -0.25, 0.125)
    rep = _decode_with_mcap_ros2(r2.REPORT, r2.serialize(r2.report(_report())))
    assert list(rep.factors) == ["A", "B"] and list(rep.design) == [-1, 1, 1, -1]
    assert [x.name for x in rep.responses] == ["tf", "ex"]
    assert list(rep.terms) == ["1", "2"] and list(rep.responses[0].effects) == [0.1, -0.05]
    assert list(rep.responses[0].significant_95) == ["1", "2"]
    assert rep.optimum.search_size == 10


def test_every_schema_parses_as_ros2msg():
    for typename in (r2.IMAGE, r2.TWIST, r2.ESTIMATE, r2.PARAMS, r2.REPORT):
        decoders = generate_dynamic(typename, r2.msgdef(typename))
        assert typename in decoders, (typename, sorted(decoders))


@pytest.mark.parametrize("msg", [
    _estimate(),
    Params(seq=3, stamp_ns=11, max_features=50, thres_percent=1.5, search_size=21,
           corr_size=11, ungroup_size=4, params_id=9, source="user", reason="by hand"),
], ids=["estimate", "params"])
def test_round_trip_through_cdr(msg):
    ros = r2.to_ros(msg)
    back = r2.deserialize(r2.serialize(ros), ros.__msgtype__)
    again = r2.estimate_of_ros(back) if isinstance(msg, Estimate) else r2.params_of_ros(back)
    assert again == msg


def test_frame_round_trip_and_rows_with_padding():
    img = np.arange(12, dtype=np.uint8).reshape(3, 4)
    frame = Frame.from_image(img, seq=4, stamp_ns=99)
    back = r2.frame_of_image(r2.deserialize(r2.serialize(r2.image(frame)), r2.IMAGE), seq=4)
    assert back.stamp_ns == 99 and np.array_equal(back.data, img)
    padded = r2.image(frame)
    padded.step, padded.data = 6, np.pad(img, ((0, 0), (0, 2))).reshape(-1)
    assert np.array_equal(r2.frame_of_image(padded, seq=0).data, img)


@pytest.mark.parametrize("change,problem", [
    (dict(encoding="32FC1"), "encoding '32FC1' is not supported: allowed mono8, "),
    (dict(encoding="rgb8"), "step >= width \\* bytes a pixel = 4 \\* 3"),  # taken: too few bytes
    (dict(step=3), "step >= width"),
    (dict(data=np.zeros(5, np.uint8)), "5 bytes"),
])
def test_a_bad_image_is_a_value_error_naming_the_problem(change, problem):
    obj = r2.image(Frame.from_image(np.zeros((2, 4), np.uint8), seq=0, stamp_ns=0))
    for k, v in change.items():
        setattr(obj, k, v)
    with pytest.raises(ValueError, match=problem):
        r2.frame_of_image(obj, seq=0)


def test_report_travels_whole_in_its_json_field():
    rep = _report()
    back = r2.report_of_ros(r2.deserialize(r2.serialize(r2.report(rep)), r2.REPORT))
    assert back == rep


def test_truncated_cdr_is_a_value_error():
    data = r2.serialize(r2.estimate(_estimate()))
    with pytest.raises(ValueError, match="not a CDR vistrack_msgs/msg/Estimate"):
        r2.deserialize(data[:20], r2.ESTIMATE)
