"""The ROS 2 side of the services in-process: the camera's ``ros2:TOPIC`` source through the
MemoryNode seam, and ``vistrack ros2``'s loop publishing over a real Zenoh session.

ROS 2 messages are made and read with rosbags' own type store (Jazzy, plus the ``.msg``
files of ``deploy/ros2/vistrack_msgs``); keys and attachments are written out here from the
rmw_zenoh design document (``docs/design.md``: "Topic and Service name mapping to Zenoh key
expressions", "Publishers"), not taken from the code under test.
"""

from __future__ import annotations

import json
import re
import struct
import threading
import time

import cv2
import msgpack
import numpy as np
import pytest
import zenoh
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from vistrack.common import rmw_zenoh as rmw
from vistrack.common import ros2types as r2
from vistrack.common.bus import MemoryNode
from vistrack.common.messages import CmdVel, Estimate, Frame, Params
from vistrack.common.synthetic import texture
from vistrack.services import cli
from vistrack.services.camera import service as camera
from vistrack.services.preprocessing import service as preprocessing
from vistrack.services.ros2 import service as bridge

STORE = get_typestore(Stores.ROS2_JAZZY)
STORE.register({k: v for name, text in r2.msg_files().items()
                for k, v in get_types_from_msg(text, name).items()})
T = STORE.types
STAMP_NS = 1_700_000_000_250_000_000


def ros_key(domain: int, topic: str, typename: str) -> str:
    """design.md: ``<domain_id>/<fully_qualified_name>/<type_name>/<type_hash>``."""
    pkg, kind, name = typename.split("/")
    return f"{domain}/{topic.strip('/')}/{pkg}::{kind}::dds_::{name}_/" \
           f"{STORE.hash_rihs01(typename)}"


def parse(command: str, *argv: str):
    return cli.build_parser(command).parse_args([command, *argv])


def exit_code(argv: list[str]) -> int:
    """``vistrack ARGV``'s exit code (argparse exits by itself on a flag it cannot parse)."""
    try:
        return cli.main(argv)
    except SystemExit as e:
        return int(e.code or 0)


def wait_for(condition, timeout=10.0, what="condition"):
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.002)


def image_cdr(pixels: np.ndarray, encoding: str, *, step: int | None = None,
              data: np.ndarray | None = None) -> bytes:
    h, w = pixels.shape[:2]
    header = T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=STAMP_NS // 10**9, nanosec=STAMP_NS % 10**9),
        frame_id="camera_optical")
    msg = T[r2.IMAGE](header=header, height=h, width=w, encoding=encoding, is_bigendian=0,
                      step=step or pixels.reshape(h, -1).shape[1],
                      data=pixels.reshape(-1) if data is None else data)
    return STORE.serialize_cdr(msg, r2.IMAGE).tobytes()


def test_ros2_camera_publishes_frames_and_rejects_bad_images():
    grey = np.ascontiguousarray(texture(256, seed=5)[:48, :64])
    rgb = np.dstack([grey, grey, grey])
    key = ros_key(0, "/camera/image_raw", r2.IMAGE)
    args = parse("camera", "--source", "ros2:/camera/image_raw")
    with MemoryNode("camera") as node:
        result: list[int] = []
        thread = threading.Thread(target=lambda: result.append(camera.loop(node, args)),
                                  daemon=True)
        thread.start()
        wait_for(lambda: node.feed(key, b""), what="the subscription")
        wait_for(lambda: node.status.rejected == 1, what="an empty payload rejected")
        frames = lambda: node.published_on(node.keys.frame)  # noqa: E731
        bad = [
            image_cdr(rgb, "rgb8", data=np.zeros(100, np.uint8)),   # data size
            image_cdr(rgb, "nv21"),                                 # encoding
            image_cdr(rgb, "rgb8", step=100),                       # step * height != size
            b"\x00\x01\x00\x00" + b"\x07" * 20,                     # truncated CDR
        ]
        good = image_cdr(rgb, "rgb8")
        node.feed(key, good)
        wait_for(lambda: len(frames()) == 1, what="the first frame")
        for i, payload in enumerate(bad):
            node.feed(key, payload)
            wait_for(lambda i=i: node.status.rejected == 2 + i, what=f"bad image {i}")
        node.feed(key, good)  # the camera went on
        wait_for(lambda: len(frames()) == 2, what="the frame after the bad ones")
        node.stop.set()
        thread.join(10)
    assert result == [0]
    first, second = (Frame.decode(p) for p in frames())
    np.testing.assert_array_equal(first.data, grey)
    assert (first.seq, second.seq) == (0, 1)
    assert first.stamp_ns == second.stamp_ns == STAMP_NS  # the header's stamp
    assert node.status.rejected == 5
    assert node.status.last_error.startswith("not a CDR sensor_msgs/msg/Image")


def test_ros2_camera_takes_compressed_images_on_a_compressed_topic():
    grey = np.ascontiguousarray(texture(256, seed=6)[:40, :56])
    ok, png = cv2.imencode(".png", grey)
    assert ok
    header = T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=5, nanosec=7), frame_id="c")
    cdr = STORE.serialize_cdr(T[r2.COMPRESSED_IMAGE](header=header, format="png",
                                                     data=png.reshape(-1)),
                              r2.COMPRESSED_IMAGE).tobytes()
    key = ros_key(3, "/front/image_raw/compressed", r2.COMPRESSED_IMAGE)
    args = parse("camera", "--source", "ros2:/front/image_raw/compressed", "--domain", "3",
                 "--size", "28x20")
    with MemoryNode("camera") as node:
        thread = threading.Thread(target=camera.loop, args=(node, args), daemon=True)
        thread.start()
        wait_for(lambda: node.feed(key, cdr), what="the subscription")
        wait_for(lambda: node.published_on(node.keys.frame), what="a frame")
        node.stop.set()
        thread.join(10)
    frame = Frame.decode(node.published_on(node.keys.frame)[0])
    assert (frame.width, frame.height, frame.stamp_ns) == (28, 20, 5 * 10**9 + 7)
    np.testing.assert_array_equal(frame.data, cv2.resize(grey, (28, 20),
                                                         interpolation=cv2.INTER_AREA))


def test_ros2_camera_refuses_an_image_larger_than_the_limit_and_goes_on(monkeypatch):
    """An image over the decode limit (here lowered to 1024 px: a real one is refused by
    OpenCV from its header, see test_ros2_images) is rejected, counted and said with its
    size and the limit; the camera takes the next image."""
    from vistrack.common import imagelimit

    monkeypatch.setattr(imagelimit, "MAX_PIXELS", 1024)
    header = T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=5, nanosec=7), frame_id="c")

    def cdr(grey: np.ndarray) -> bytes:
        png = cv2.imencode(".png", grey)[1]
        return STORE.serialize_cdr(T[r2.COMPRESSED_IMAGE](header=header, format="png",
                                                         data=png.reshape(-1)),
                                   r2.COMPRESSED_IMAGE).tobytes()
    large = np.ascontiguousarray(texture(256, seed=6)[:40, :56])  # 2240 px
    small = np.ascontiguousarray(large[:24, :32])  # 768 px
    key = ros_key(3, "/front/image_raw/compressed", r2.COMPRESSED_IMAGE)
    args = parse("camera", "--source", "ros2:/front/image_raw/compressed", "--domain", "3")
    with MemoryNode("camera") as node:
        thread = threading.Thread(target=camera.loop, args=(node, args), daemon=True)
        thread.start()
        wait_for(lambda: node.feed(key, cdr(large)), what="the subscription")
        wait_for(lambda: node.status.rejected == 1, what="the large image rejected")
        node.feed(key, cdr(small))
        wait_for(lambda: node.published_on(node.keys.frame), what="the next image's frame")
        node.stop.set()
        thread.join(10)
    assert not thread.is_alive()
    assert re.fullmatch(r"compressed image \(png, \d+ bytes\) is 56x40 px, more than the 1024 "
                        r"px \(32x32\) an image may have \(OPENCV_IO_MAX_IMAGE_PIXELS\)",
                        node.status.last_error), node.status.last_error
    (frame,) = (Frame.decode(p) for p in node.published_on(node.keys.frame))
    np.testing.assert_array_equal(frame.data, small)
    assert node.status.extra["frames"] == 1


def test_preprocessing_reads_a_ros2_camera_directly_and_publishes_its_frames():
    """preprocessing --source ros2:TOPIC: the same pre-processed frame as from the equal
    camera/frame, then that camera/frame itself (for the tuner and the tools); a bad image is
    rejected and counted, and the next one goes through."""
    grey = np.ascontiguousarray(texture(256, seed=7)[:64, :80])
    bgr = np.dstack([grey, grey, grey])
    key = ros_key(2, "/camera/image_raw", r2.IMAGE)
    outputs = {}
    for source in ("camera/frame", "ros2:/camera/image_raw"):
        args = parse("preprocessing", "--source", source, "--domain", "2")
        with MemoryNode("preprocessing") as node:
            thread = threading.Thread(target=preprocessing.loop, args=(node, args),
                                      daemon=True)
            thread.start()
            if source == "camera/frame":
                frame = Frame.from_image(grey, seq=0, stamp_ns=STAMP_NS).encode()
                wait_for(lambda f=frame: node.feed(node.keys.frame, f), timeout=60,
                         what="the camera/frame subscription")
            else:
                wait_for(lambda: node.feed(key, image_cdr(bgr, "bgr8", data=np.zeros(
                    7, np.uint8))), timeout=60, what="the image subscription")
                wait_for(lambda: node.status.rejected == 1, what="the bad image rejected")
                node.feed(key, image_cdr(bgr, "bgr8"))
            wait_for(lambda n=node: n.published_on(n.keys.pre_frame), what="a pre-frame")
            if source != "camera/frame":
                wait_for(lambda n=node: n.published_on(n.keys.frame), what="its camera/frame")
            node.stop.set()
            thread.join(10)
        outputs[source] = node
    plain, ros = outputs["camera/frame"], outputs["ros2:/camera/image_raw"]
    assert ros.published_on(ros.keys.pre_frame) == plain.published_on(plain.keys.pre_frame)
    frame = Frame.decode(ros.published_on(ros.keys.frame)[0])
    assert (frame.seq, frame.stamp_ns) == (0, STAMP_NS)
    np.testing.assert_array_equal(frame.data, grey)
    assert ros.status.rejected == 1 and "data is 7 bytes" in ros.status.last_error
    assert not plain.published_on(plain.keys.frame)


@pytest.mark.parametrize(("argv", "message"), [
    (["--source", "camera"], "--source 'camera': expected camera/frame or ros2:TOPIC"),
    (["--source", "ros2:/camera//image"], "ROS topic '/camera//image' is not valid"),
    (["--source", "ros2:/cam", "--domain", "-1"], "--domain -1 is out of range"),
])
def test_bad_preprocessing_sources_are_one_line_errors(argv, message, capsys):
    assert exit_code(["preprocessing", *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


@pytest.mark.parametrize(("argv", "message"), [
    (["--source", "ros2:"], "names no topic"),
    (["--source", "ros2:/camera//image"], "ROS topic '/camera//image' is not valid"),
    (["--source", "ros2:/cam", "--domain", "300"], "--domain 300 is out of range: allowed "
                                                    "0..232"),
])
def test_bad_ros2_camera_flags_are_one_line_errors(argv, message, capsys):
    assert exit_code(["camera", *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


@pytest.mark.parametrize(("argv", "expected"), [
    ([], {"cmd_vel": "/cmd_vel", "estimate": "/vistrack/estimate",
          "params": "/vistrack/params"}),
    (["--namespace", "robot1"], {"cmd_vel": "/robot1/cmd_vel",
                                 "estimate": "/robot1/vistrack/estimate",
                                 "params": "/robot1/vistrack/params"}),
    (["--namespace", "/robot1", "--remap", "cmd_vel:=/mobile_base/cmd_vel",
      "--remap", "vistrack/estimate:=tracking/estimate"],
     {"cmd_vel": "/mobile_base/cmd_vel", "estimate": "/robot1/tracking/estimate",
      "params": "/robot1/vistrack/params"}),
    (["--remap", "/vistrack/params:=params"], {"cmd_vel": "/cmd_vel",
                                               "estimate": "/vistrack/estimate",
                                               "params": "/params"}),
])
def test_namespace_and_remaps_name_the_topics(argv, expected):
    assert bridge.topics(parse("ros2", *argv)) == expected


@pytest.mark.parametrize(("argv", "message"), [
    (["--remap", "cmd_vel"], "argument --remap: 'cmd_vel': expected FROM:=TO"),
    (["--remap", "odom:=/odom"], "'odom' is none of this service's topics"),
    (["--namespace", "/a//b"], "ROS namespace '/a//b' is not valid"),
    (["--node-name", "vis-track"], "ROS node name 'vis-track' is not valid"),
    (["--domain", "233"], "--domain 233 is out of range: allowed 0..232"),
])
def test_bad_ros2_flags_are_one_line_errors(argv, message, capsys):
    assert exit_code(["ros2", *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


def test_ros2_bridge_publishes_every_command_in_order_as_rmw_zenoh_does(free_port):
    """Commands, an estimate and parameters fed in memory come out on a real Zenoh session
    as ROS 2 samples: rmw_zenoh keys, CDR that rosbags reads, attachments numbered from 1;
    a bad command is rejected and counted and the ones after it still go out."""
    listen = zenoh.Config()
    listen.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{free_port}"]))
    listen.insert_json5("scouting/multicast/enabled", "false")
    got: list[tuple[str, bytes, bytes]] = []
    lock = threading.Lock()

    def on_sample(s: zenoh.Sample) -> None:
        with lock:
            got.append((str(s.key_expr), s.payload.to_bytes(), s.attachment.to_bytes()))

    def samples(key: str) -> list[tuple[bytes, bytes]]:
        with lock:
            return [(p, a) for k, p, a in got if k == key]

    args = parse("ros2", "--domain", "7")
    with zenoh.open(listen) as ours, zenoh.open(rmw_config(free_port)) as theirs, \
            MemoryNode("ros2") as node, \
            rmw.Participant(ours, rmw.Rmw(7, "/", "vistrack")) as participant:
        sub = theirs.declare_subscriber("7/**", on_sample)
        try:
            thread = threading.Thread(target=bridge.loop, args=(node, args, participant),
                                      daemon=True)
            thread.start()
            wait_for(lambda: "/cmd_vel" in node.status.extra, what="the bridge")
            twist_key = ros_key(7, "/cmd_vel", r2.TWIST)
            wait_for(lambda: any(p.key == twist_key and p.matched()
                                 for p in participant.publishers), what="matching")
            now = time.time_ns()
            commands = [CmdVel(seq=i, stamp_ns=now + i, vx=0.01 * i, vy=-0.015 * i, wz=0.5,
                               stale=i % 7 == 0) for i in range(60)]
            for i, cmd in enumerate(commands):
                node.feed(node.keys.cmd_vel, cmd.encode())
                if i == 30:
                    node.feed(node.keys.cmd_vel, msgpack.packb({"v": 1, "seq": 99}))
            est = Estimate(seq=4, stamp_ns=STAMP_NS, npi=2, xc=1.5, yc=2.5, xe=3.0, ye=4.0,
                           dx=0.1, dy=0.2, scale=1.01, t_ms=0.3, first=True,
                           features=[[1, 1.0, 2.0], [2, 2.0, 3.0]], params_id=6)
            node.feed(node.keys.estimate, est.encode())
            params = Params(seq=1, stamp_ns=STAMP_NS, max_features=100, thres_percent=2.0,
                            search_size=15, corr_size=9, ungroup_size=5, params_id=6,
                            source="user", reason="test")
            node.feed(node.keys.params, params.encode())
            est_key = ros_key(7, "/vistrack/estimate", r2.ESTIMATE)
            params_key = ros_key(7, "/vistrack/params", r2.PARAMS)
            wait_for(lambda: len(samples(twist_key)) == 60 and samples(est_key)
                     and samples(params_key), what="every sample")
            node.stop.set()
            thread.join(10)
        finally:
            sub.undeclare()
    assert node.status.rejected == 1 and "control/cmd_vel" in node.status.last_error
    twists = samples(twist_key)
    gids = set()
    for n, (payload, attachment) in enumerate(twists, start=1):
        seq, stamp, length = struct.unpack_from("<qqB", attachment)
        assert (seq, length, len(attachment)) == (n, 16, 33)
        assert abs(stamp - time.time_ns()) < 60 * 10**9
        gids.add(attachment[17:])
        t = STORE.deserialize_cdr(payload, r2.TWIST)
        c = commands[n - 1]
        if c.stale:  # a stop, whatever its numbers
            c = CmdVel(seq=c.seq, stamp_ns=c.stamp_ns, vx=0.0, vy=0.0, wz=0.0, stale=True)
        assert (t.linear.x, t.linear.y, t.linear.z) == (c.vx, c.vy, 0.0)
        assert (t.angular.x, t.angular.y, t.angular.z) == (0.0, 0.0, c.wz)
    assert len(gids) == 1
    e = STORE.deserialize_cdr(samples(est_key)[0][0], r2.ESTIMATE)
    assert (e.seq, e.npi, e.xc, e.scale, e.first, e.params_id) == (4, 2, 1.5, 1.01, True, 6)
    assert e.header.stamp.sec * 10**9 + e.header.stamp.nanosec == STAMP_NS
    assert [(f.id, f.x, f.y) for f in e.features] == [(1, 1.0, 2.0), (2, 2.0, 3.0)]
    p = STORE.deserialize_cdr(samples(params_key)[0][0], r2.PARAMS)
    assert (p.search_size, p.corr_size, p.params_id, p.source) == (15, 9, 6, "user")


def test_the_bridge_sends_the_base_a_stop_for_a_stale_or_old_command_and_clamps_speeds(
        free_port):
    """/cmd_vel is the last hop before the motors, and it passed on whatever came: a command
    an hour old, 1e6 m/s, one marked stale with 0.5 m/s, and a replay's recorded moves ten
    seconds after they were made. Each now goes out safe, and the status counts it."""
    listen = zenoh.Config()
    listen.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{free_port}"]))
    listen.insert_json5("scouting/multicast/enabled", "false")
    got: list[bytes] = []
    lock = threading.Lock()

    def on_sample(s: zenoh.Sample) -> None:
        with lock:
            got.append(s.payload.to_bytes())

    now = time.time_ns()
    sent = [  # (vx, vy, wz, stale, stamp_ns) -> what the base must get
        ((0.3, -0.2, 0.1, False, now), (0.3, -0.2, 0.1)),
        ((0.5, 0.5, 0.0, True, now), (0.0, 0.0, 0.0)),
        ((0.5, 0.0, 0.0, False, now - 3_600 * 10**9), (0.0, 0.0, 0.0)),
        ((1e6, -1e300, 50.0, False, now), (1.0, -1.0, 1.0)),
        ((0.2, 0.0, -0.3, False, now), (0.2, 0.0, -0.3)),
    ]
    args = parse("ros2", "--domain", "8")
    with zenoh.open(listen) as ours, zenoh.open(rmw_config(free_port)) as theirs, \
            MemoryNode("ros2") as node, \
            rmw.Participant(ours, rmw.Rmw(8, "/", "vistrack")) as participant:
        twist_key = ros_key(8, "/cmd_vel", r2.TWIST)
        sub = theirs.declare_subscriber(twist_key, on_sample)
        try:
            thread = threading.Thread(target=bridge.loop, args=(node, args, participant),
                                      daemon=True)
            thread.start()
            wait_for(lambda: "/cmd_vel" in node.status.extra, what="the bridge")
            wait_for(lambda: any(p.key == twist_key and p.matched()
                                 for p in participant.publishers), what="matching")
            for i, ((vx, vy, wz, stale, stamp), _) in enumerate(sent):
                node.feed(node.keys.cmd_vel, CmdVel(seq=i, stamp_ns=stamp, vx=vx, vy=vy,
                                                    wz=wz, stale=stale).encode())
            wait_for(lambda: len(got) == len(sent), what="every command")
            node.stop.set()
            thread.join(10)
        finally:
            sub.undeclare()
    twists = [STORE.deserialize_cdr(p, r2.TWIST) for p in got]
    assert [(t.linear.x, t.linear.y, t.angular.z) for t in twists] == [w for _, w in sent]
    extra = node.status.extra
    assert (extra["old_stopped"], extra["clamped"], node.status.rejected) == (1, 1, 0)


def rmw_config(port: int) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return conf
