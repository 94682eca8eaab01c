"""rmw_zenoh's wire format (common/rmw_zenoh.py) against the fixtures of its design document.

The expected strings are copied from ``docs/design.md`` of ``ros2/rmw_zenoh`` (the version of
2025 that documents the Jazzy/Kilted/Rolling format; in the repository at commit 99a6a2bd):

* "Topic and Service name mapping to Zenoh key expressions": the ``chatter`` keys;
* "Graph Cache": the liveliness tokens of ``demo_nodes_cpp``'s ``listener`` and ``talker``;
* "Publishers": the attachment, "8 bytes for the sequence number (int64_t), encoded as a
  little-endian, 8 bytes for the timestamp ..., 1 byte for the length of the publisher GID
  (currently always 16), 16 bytes for the publisher GID", written out here with ``struct``.

The type hash in them is the one rosbags computes for ``std_msgs/msg/String``, so these also
check our RIHS01 hash against ROS 2's own.
"""

from __future__ import annotations

import struct

import pytest
import xxhash

from vistrack.common import rmw_zenoh as rmw
from vistrack.common import ros2types as r2

STRING = "std_msgs/msg/String"
# design.md, "Topic and Service name mapping to Zenoh key expressions"
CHATTER_KEY = ("0/chatter/std_msgs::msg::dds_::String_/"
               "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18")
CHATTER_NS_KEY = ("0/robot1/chatter/std_msgs::msg::dds_::String_/"
                  "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18")
# design.md, "Graph Cache", examples using the demo_nodes_cpp package
LISTENER_NODE = "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
LISTENER_SUB = ("@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%chatter/"
                "std_msgs::msg::dds_::String_/"
                "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/"
                "::,10:,:,:,,")
TALKER_PUB = ("@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/"
              "std_msgs::msg::dds_::String_/"
              "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/"
              "::,7:,:,:,,")


def test_topic_keys_are_the_design_documents():
    h = r2.type_hash(STRING)
    assert rmw.topic_key(0, "/chatter", STRING, h) == CHATTER_KEY
    assert rmw.topic_key(0, rmw.qualified_topic("chatter", "/robot1"), STRING, h) \
        == CHATTER_NS_KEY


def test_liveliness_tokens_are_the_design_documents():
    h = r2.type_hash(STRING)
    listener = rmw.Rmw(domain=2, node="listener")
    assert rmw.liveliness_token(listener, "aac3178e146ba6f1fc6e6a4085e77f21", 0, 0,
                                rmw.NODE) == LISTENER_NODE
    assert rmw.liveliness_token(listener, "aac3178e146ba6f1fc6e6a4085e77f21", 0, 10,
                                rmw.SUBSCRIPTION, "/chatter", STRING, h,
                                rmw.QoS(depth=10)) == LISTENER_SUB
    talker = rmw.Rmw(domain=2, node="talker")
    assert rmw.liveliness_token(talker, "8b20917502ee955ac4476e0266340d5c", 0, 10,
                                rmw.PUBLISHER, "/chatter", STRING, h,
                                rmw.QoS(depth=7)) == TALKER_PUB


@pytest.mark.parametrize(("qos", "text"), [
    (rmw.QoS(), "::,:,:,:,,"),                       # rmw_zenoh's own defaults: all empty
    (rmw.QOS_DEFAULT, "::,10:,:,:,,"),               # rclcpp's default profile (design.md)
    (rmw.QOS_ALL, "::2,:,:,:,,"),                    # KEEP_ALL = 2 (rmw/types.h)
    (rmw.QOS_SENSOR, "2::,5:,:,:,,"),                # BEST_EFFORT = 2, depth 5
    (rmw.QoS(durability=rmw.TRANSIENT_LOCAL, depth=1), ":1:,1:,:,:,,"),
])
def test_qos_keyexpr_fields_are_empty_where_default(qos, text):
    assert qos.keyexpr() == text


def test_namespaced_tokens_mangle_every_slash():
    h = r2.type_hash(r2.TWIST)
    token = rmw.liveliness_token(rmw.Rmw(0, "/robot1/arm", "vistrack"), "ab", 0, 1,
                                 rmw.PUBLISHER, "/robot1/arm/cmd_vel", r2.TWIST, h,
                                 rmw.QOS_ALL)
    chunks = token.split("/")
    assert chunks[6:10] == ["%", "%robot1%arm", "vistrack", "%robot1%arm%cmd_vel"]
    assert chunks[10] == "geometry_msgs::msg::dds_::Twist_" and chunks[11] == h
    assert len(chunks) == 13  # every name is one chunk


def test_attachment_is_the_documented_33_bytes():
    gid = bytes(range(100, 116))
    att = rmw.Attachment(seq=1, stamp_ns=1_700_000_000_123_456_789, gid=gid).encode()
    assert att == struct.pack("<qqB", 1, 1_700_000_000_123_456_789, 16) + gid
    assert rmw.Attachment.decode(att) == (1, 1_700_000_000_123_456_789, gid)


def _labelled(seq: int, stamp: int, gid: bytes, last: str = "source_gid") -> bytes:
    """The attachment of rmw_zenoh before its PR #601 (Jazzy 0.2.0 to 0.2.3, Humble 0.1.0
    and 0.1.1), as zenoh's serializer writes it: each label a LEB128 length and its bytes,
    then its field (int64 LE, or the GID's length and the GID)."""
    def label(text: str) -> bytes:
        return bytes([len(text)]) + text.encode()
    return (label("sequence_number") + struct.pack("<q", seq) + label("source_timestamp")
            + struct.pack("<q", stamp) + label(last) + bytes([len(gid)]) + gid)


def test_the_labelled_attachment_of_older_releases_is_read():
    gid = bytes(range(16))
    data = _labelled(7, 1_700_000_000_123_456_789, gid)
    assert len(data) == 77 == rmw.LABELLED_SIZE
    assert rmw.Attachment.decode(data) == (7, 1_700_000_000_123_456_789, gid)
    with pytest.raises(ValueError, match="attachment of 77 bytes: expected 33"):
        rmw.Attachment.decode(_labelled(7, 8, gid, last="source_gix"))  # not those labels


@pytest.mark.parametrize(("data", "message"), [
    (None, "no attachment"),
    (b"\x01" * 32, "attachment of 32 bytes: expected 33"),
    (struct.pack("<qqB", 1, 2, 15) + bytes(16), "GID length 16"),
])
def test_a_bad_attachment_is_refused_with_what_is_wrong(data, message):
    with pytest.raises(ValueError, match=message):
        rmw.Attachment.decode(data)


def test_gid_is_xxh3_128_of_the_token_low_half_first():
    # liveliness_utils.cpp: memcpy(gid, &hash.low64, 8); memcpy(gid + 8, &hash.high64, 8)
    digest = xxhash.xxh3_128_intdigest(TALKER_PUB.encode())
    low, high = digest & (2**64 - 1), digest >> 64
    assert rmw.gid(TALKER_PUB) == struct.pack("<QQ", low, high)


def test_dds_type_names():
    assert rmw.dds_type(r2.IMAGE) == "sensor_msgs::msg::dds_::Image_"
    assert rmw.dds_type(r2.ESTIMATE) == "vistrack_msgs::msg::dds_::Estimate_"


@pytest.mark.parametrize(("topic", "namespace", "expected"), [
    ("cmd_vel", "/", "/cmd_vel"),
    ("cmd_vel", "", "/cmd_vel"),
    ("cmd_vel", "robot1", "/robot1/cmd_vel"),
    ("vistrack/estimate", "/robot1", "/robot1/vistrack/estimate"),
    ("/cmd_vel", "/robot1", "/cmd_vel"),             # absolute names ignore the namespace
])
def test_qualified_topic_names(topic, namespace, expected):
    assert rmw.qualified_topic(topic, namespace) == expected


@pytest.mark.parametrize(("call", "message"), [
    (lambda: rmw.qualified_topic("/camera//image"), "ROS topic '/camera//image' is not valid"),
    (lambda: rmw.qualified_topic("/camera/"), "ROS topic '/camera/' is not valid"),
    (lambda: rmw.qualified_topic("/2d/image"), "ROS topic '/2d/image' is not valid"),
    (lambda: rmw.qualified_topic("/cam*"), "ROS topic '/cam\\*' is not valid"),
    (lambda: rmw.validate_namespace("/robot1/"), "ROS namespace '/robot1/' is not valid"),
    (lambda: rmw.validate_node_name("my-node"), "ROS node name 'my-node' is not valid"),
    (lambda: rmw.validate_domain(233), "ROS domain id 233 is out of range: allowed 0..232"),
    (lambda: rmw.validate_domain(-1), "allowed 0..232"),
])
def test_bad_names_are_refused_naming_them(call, message):
    with pytest.raises(ValueError, match=message):
        call()
