"""MCAP recordings and the Foxglove live view of a real pipeline, read by programs not ours.

One run of real processes on a loopback router: preprocessing, motion-estimation,
fuzzy-controller and the auto-tuner (``--no-tune``: it announces the parameters in force),
``vistrack record run.mcap`` and ``vistrack foxglove`` listening, then the camera playing the
built-in sequence once with one frame in flight (``--fps 0``), so every frame is estimated.
Then:

* the MCAP file is read with the ``mcap`` library and every message decoded with
  ``mcap-ros2-support`` from the schema embedded in the file;
* a ``websockets`` client, connected to ``vistrack foxglove`` through the whole run, saw the
  channel advertisements, subscribed, and decoded what it received;
* the recording's frames and parameters are replayed with one frame in flight into a fresh
  preprocessing and motion-estimation (another robot id, no camera): every estimate equals
  the recorded one;
* a truncated copy replays up to the damage, then a one-line error and exit 2.
"""

from __future__ import annotations

import json
import re
import signal
import socket
import struct
import subprocess
import time
from collections import Counter

import msgpack
import pytest
import zenoh
from forkcli import vistrack
from mcap.reader import make_reader
from mcap.records import Schema
from mcap_ros2.decoder import DecoderFactory
from websockets.sync.client import ClientConnection, connect

from vistrack.common import ros2types as r2

from procs import Collector, Proc, router, service, services, zenoh_config

pytestmark = pytest.mark.integration

ROOT = "vistrack/robot"
NS = "--no-multicast-scouting"
FRAMES = 60  # the built-in sequence, played once
FRAME_RATE = 5.0  # the bridge's --frame-rate: far below the camera's rate
# what an estimate is, besides its processing time
FIELDS = ("seq", "stamp_ns", "valid", "npi", "xc", "yc", "xe", "ye", "dx", "dy", "scale",
          "first", "params_id", "features")


def _stop(proc: Proc) -> int:
    """Stop a tool as Ctrl-C does, wait for it to finish, and return its exit code."""
    if proc.p.poll() is None:
        proc.p.send_signal(signal.SIGINT)
        try:
            proc.p.wait(30)
        except subprocess.TimeoutExpired:
            pass  # Proc.stop() terminates it, and the exit code says so
    return proc.stop(timeout=10)


class FoxgloveClient:
    """A Foxglove WebSocket client: advertisements, subscribe to all, decode message data."""

    def __init__(self, ws: ClientConnection) -> None:
        self.ws = ws
        self.subprotocol = ws.subprotocol
        self.server_info: dict = {}
        self.channels: dict[int, dict] = {}
        self.decoders: dict = {}
        self.received: Counter[str] = Counter()
        self.messages: dict[str, list] = {}

    def advertised(self, topics: set[str], timeout: float = 10.0) -> None:
        deadline = time.monotonic() + timeout
        while {c["topic"] for c in self.channels.values()} < topics:
            msg = json.loads(self.ws.recv(timeout=max(0.01, deadline - time.monotonic())))
            if msg["op"] == "serverInfo":
                self.server_info = msg
            elif msg["op"] == "advertise":
                self.channels.update({c["id"]: c for c in msg["channels"]})

    def subscribe_all(self) -> None:
        for cid, c in self.channels.items():
            schema = Schema(id=cid, name=c["schemaName"], encoding=c["schemaEncoding"],
                            data=c["schema"].encode())
            self.decoders[cid] = DecoderFactory().decoder_for(c["encoding"], schema)
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": [
            {"id": cid, "channelId": cid} for cid in self.channels]}))

    def receive(self, until, timeout: float) -> None:
        """Decode message data (opcode 1: subscription id, log time, payload) until
        ``until(self)`` or ``timeout`` s."""
        deadline = time.monotonic() + timeout
        while not until(self) and time.monotonic() < deadline:
            try:
                data = self.ws.recv(timeout=0.2)
            except TimeoutError:
                continue
            if isinstance(data, bytes) and data[0] == 1:
                sub, log_time = struct.unpack_from("<IQ", data, 1)
                topic = self.channels[sub]["topic"]
                self.received[topic] += 1
                self.messages.setdefault(topic, []).append(
                    (log_time, self.decoders[sub](data[13:])))


@pytest.fixture(scope="module")
def run(tmp_path_factory, free_port_module):
    """The recorded run (see the module docstring): the MCAP path, the Foxglove client, the
    endpoint, and the estimates a plain subscriber saw."""
    path = tmp_path_factory.mktemp("mcap") / "run.mcap"
    extra = {"auto-tuner": ["--no-tune"]}
    names = ("preprocessing", "motion-estimation", "fuzzy-controller", "auto-tuner")
    with router(free_port_module) as ep, zenoh.open(zenoh_config(ep)) as session, \
            services(ep, names=names, extra=extra):
        fresh = [service(n, ep, "--robot", "replayed") for n in ("preprocessing",
                                                                "motion-estimation")]
        rec = Proc(["record", str(path), "-e", ep, NS])
        with socket.socket() as sock:
            sock.bind(("127.0.0.1", 0))
            ws_port = sock.getsockname()[1]
        bridge = Proc(["foxglove", "--port", str(ws_port), "--frame-rate", str(FRAME_RATE),
                       "-e", ep, NS])
        try:
            rec.wait_for("recording")
            bridge.wait_for("serving")
            # the subprotocols the Foxglove app offers: the SDK's server speaks
            # foxglove.sdk.v1, the successor of foxglove.websocket.v1 with the same messages
            with connect(f"ws://127.0.0.1:{ws_port}", max_size=None,
                         subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"]) as ws:
                client = FoxgloveClient(ws)
                client.advertised({f"/{ROOT}/{s}" for s in (*r2.ROS_TYPES, *r2.OVERLAYS)})
                client.subscribe_all()
                # the parameters in force recorded before the first frame, as the replay
                # needs them: the auto-tuner repeats them every second, and a camera started
                # at once may beat that (the replay's first estimate then had params_id 0)
                announced = Collector(session, f"{ROOT}/tuner/params")
                try:
                    announced.wait(lambda items: len(items) >= 1, timeout=10)
                finally:
                    announced.sub.undeclare()
                est = Collector(session, f"{ROOT}/motion/estimate")
                cmd = Collector(session, f"{ROOT}/control/cmd_vel")
                start = time.monotonic()
                cam = service("camera", ep, "--source", "builtin", "--fps", "0")
                try:
                    assert cam.p.wait(90) == 0  # the sequence ends after its last estimate
                finally:
                    cam.stop()
                    est.sub.undeclare()
                # every estimate, and the throttled frames and their overlays: the bridge
                # sends those at its next period, maybe after the last estimate
                client.receive(lambda c: c.received[f"/{ROOT}/motion/estimate"] >= FRAMES
                               and c.received[f"/{ROOT}/camera/frame"] >= 1
                               and c.received[f"/{ROOT}/camera/features"] >= 1, 20)
                elapsed = time.monotonic() - start
                # bad input: a payload that is no estimate, then the tools go on
                junk_ns = time.time_ns()
                session.put(f"{ROOT}/motion/estimate", b"\x81\xa1v\x01 not an estimate")
                bridge.wait_for("skipping payloads that are not valid")
                params = Collector(session, f"{ROOT}/tuner/params")  # once a second
                try:
                    params.wait(lambda items: len(items) >= 2, timeout=10)
                finally:
                    params.sub.undeclare()
                    # the commands until now, the recorder still recording: those of the
                    # estimates and the stop the controller repeats once they are stale
                    cmd.sub.undeclare()
            assert _stop(rec) == 0, "\n".join(rec.lines)
            assert _stop(bridge) == 0, "\n".join(bridge.lines)
            for p in fresh:
                p.wait_for("ready", timeout=90)
            yield {"path": path, "client": client, "endpoint": ep, "session": session,
                   "elapsed": elapsed, "live": [msgpack.unpackb(p) for _, p in est.items],
                   "commands": [msgpack.unpackb(p) for _, p in cmd.items],
                   "junk_ns": junk_ns,
                   "record": rec}
        finally:
            for p in (*fresh, rec, bridge):
                p.stop()


def _decoded(path):
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        rows = list(reader.iter_decoded_messages(log_time_order=False))
    return summary, rows


def _stamp(header) -> int:
    return header.stamp.sec * 10**9 + header.stamp.nanosec


def test_the_recording_decodes_with_mcap_ros2(run):
    summary, rows = _decoded(run["path"])
    types = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
    assert types == {
        f"/{ROOT}/camera/frame": r2.IMAGE, f"/{ROOT}/preprocessing/frame": r2.IMAGE,
        f"/{ROOT}/motion/estimate": r2.ESTIMATE, f"/{ROOT}/control/cmd_vel": r2.TWIST,
        f"/{ROOT}/tuner/params": r2.PARAMS, f"/{ROOT}/camera/features": r2.IMAGE_MARKER,
        f"/{ROOT}/camera/centroid": r2.IMAGE_MARKER}
    assert all(s.encoding == "ros2msg" for s in summary.schemas.values())
    assert all(c.message_encoding == "cdr" for c in summary.channels.values())
    by_topic: dict[str, list] = {}
    for _, channel, message, obj in rows:
        by_topic.setdefault(channel.topic, []).append((message, obj))
    log_times = [m.log_time for _, _, m, _ in rows]
    assert log_times == sorted(log_times)  # never back
    frames = by_topic[f"/{ROOT}/camera/frame"]
    assert [m.sequence for m, _ in frames] == list(range(FRAMES))  # no frame dropped
    for topic in (f"/{ROOT}/camera/frame", f"/{ROOT}/preprocessing/frame"):
        for message, img in by_topic[topic]:
            assert (img.width, img.height, img.encoding) == (256, 256, "mono8")
            assert img.step * img.height == len(img.data)
            assert message.publish_time == _stamp(img.header)
    estimates = by_topic[f"/{ROOT}/motion/estimate"]
    assert [e.seq for _, e in estimates] == list(range(FRAMES))  # one frame in flight
    frame_stamps = {_stamp(img.header) for _, img in frames}
    assert {_stamp(e.header) for _, e in estimates} == frame_stamps
    live = {m["seq"]: m for m in run["live"]}
    for message, e in estimates:  # what the plain subscriber saw on Zenoh
        m = live[e.seq]
        assert (e.npi, e.xc, e.dy, e.scale, _stamp(e.header)) == \
            (m["npi"], m["xc"], m["dy"], m["scale"], m["stamp_ns"])
        assert [[f.id, f.x, f.y] for f in e.features] == m["features"]
        assert message.sequence == e.seq and e.npi > 0
    features = {_stamp(m.header): m for _, m in by_topic[f"/{ROOT}/camera/features"]}
    for _, e in estimates:
        assert [(p.x, p.y) for p in features[_stamp(e.header)].points] == \
            [(f.x, f.y) for f in e.features]
    # commands as a plain subscriber saw them until the recorder was about to stop: those of
    # the estimates (fewer: the controller takes its estimates latest-only, of a lockstep
    # camera's full speed what it can: 47 to 60 of 60 on a quiet machine, 4 in a loaded CI
    # run) and then the stop it repeats every STALE_REPEAT_S once they are stale; the
    # recorder went on a little longer
    commands = [(m.sequence, m.publish_time, t.linear.x, t.linear.y, t.angular.z)
                for m, t in by_topic[f"/{ROOT}/control/cmd_vel"]]
    live_commands = [(c["seq"], c["stamp_ns"], c["vx"], c["vy"], c["wz"])
                     for c in run["commands"]]
    assert any(not c["stale"] for c in run["commands"])  # the estimates' commands
    assert any(c["stale"] for c in run["commands"])  # and the stop's
    assert len(live_commands) >= 5
    assert commands[:len(live_commands)] == live_commands
    assert by_topic[f"/{ROOT}/tuner/params"][0][1].search_size == 15
    log = "\n".join(run["record"].lines)
    assert "samples of 5 keys" in log
    assert f"1 samples of {ROOT}/motion/estimate not written: not valid messages" in log
    assert any(m.log_time > run["junk_ns"] for _, _, m, _ in rows)  # and it went on


def test_the_foxglove_client_received_and_decoded_every_channel(run):
    client = run["client"]
    assert client.subprotocol == "foxglove.sdk.v1"
    assert client.server_info["name"] == "vistrack robot"
    for c in client.channels.values():
        assert (c["encoding"], c["schemaEncoding"]) == ("cdr", "ros2msg")
        assert c["schema"] == r2.msgdef(c["schemaName"])
    got = client.messages
    estimates = [e for _, e in got[f"/{ROOT}/motion/estimate"]]
    assert [e.seq for e in estimates] == list(range(FRAMES))  # estimates at full rate
    frames = got[f"/{ROOT}/camera/frame"]
    # frames at most --frame-rate a second (one at the start of the run, then one a period)
    assert 1 <= len(frames) <= FRAME_RATE * run["elapsed"] + 2
    for _, img in frames:
        assert img.step * img.height == len(img.data) == 256 * 256
    by_stamp = {_stamp(e.header): e for e in estimates}
    overlays = got.get(f"/{ROOT}/camera/features", [])
    assert overlays, "no overlay of a frame sent"
    sent = {_stamp(img.header) for _, img in frames}
    for _, marker in overlays:  # drawn for frames that were sent, from their estimates
        assert _stamp(marker.header) in sent
        e = by_stamp[_stamp(marker.header)]
        assert [(p.x, p.y) for p in marker.points] == [(f.x, f.y) for f in e.features]
    assert got[f"/{ROOT}/control/cmd_vel"] and got[f"/{ROOT}/tuner/params"]


def test_replaying_the_mcap_into_a_pipeline_without_camera_gives_the_same_estimates(run):
    _, rows = _decoded(run["path"])
    recorded = {e.seq: e for _, c, _, e in rows if c.topic.endswith("motion/estimate")}
    est = Collector(run["session"], "vistrack/replayed/motion/estimate")
    try:
        replay = vistrack("replay", run["path"], "camera/frame", "tuner/params", "--fast",
                          "--in-flight", "1", "--remap-robot", "replayed", "-e",
                          run["endpoint"], NS)
        assert replay.returncode == 0, replay.stderr
        # the replay waits for the last frame's estimate before it ends
        got = [msgpack.unpackb(p) for _, p in est.wait(lambda items: len(items) >= FRAMES)]
    finally:
        est.sub.undeclare()
    assert "not replayed" not in replay.stderr  # only the keys asked for were read
    published = int(re.search(r"vistrack replay: (\d+) samples", replay.stderr).group(1))
    assert published > FRAMES  # the frames and the parameter announcements among them
    assert [m["seq"] for m in got] == list(range(FRAMES))
    for m in got:
        e = recorded[m["seq"]]
        ros = {"seq": e.seq, "stamp_ns": _stamp(e.header), "valid": e.valid, "npi": e.npi,
               "xc": e.xc,
               "yc": e.yc, "xe": e.xe, "ye": e.ye, "dx": e.dx, "dy": e.dy, "scale": e.scale,
               "first": e.first, "params_id": e.params_id,
               "features": [[f.id, f.x, f.y] for f in e.features]}
        assert {k: m[k] for k in FIELDS} == ros, m["seq"]


def test_a_truncated_mcap_replays_up_to_the_damage_then_exits_2(run, tmp_path):
    data = run["path"].read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:len(data) * 2 // 3])
    bad = vistrack("replay", cut, "--fast", "--wait", "0", "--remap-robot", "nobody", "-e",
                   run["endpoint"], NS)
    assert bad.returncode == 2
    lines = bad.stderr.splitlines()
    error = [line for line in lines if "error" in line]
    assert len(error) == 1 and error[0].startswith("vistrack replay: error: ")
    assert str(cut) in error[0] and "truncated" in error[0] and "byte offset" in error[0]
    assert any("valid samples before byte offset" in line for line in lines)


def test_the_bridge_sends_overlays_alone_and_skips_what_ros_2_cannot_hold(free_port):
    """A client watching only the overlays (features, centroid) gets them at the frames'
    rate: the bridge took the camera's frames only while their own channel was watched, and
    sent such a client nothing. And a valid estimate that no ROS 2 message holds (a stamp
    past 2038: int32 seconds) is counted and skipped, not the end of the bridge (it died on
    rosbags' struct.error), and the overlays go on."""
    import numpy as np

    from vistrack.common.messages import encode_estimate, encode_frame

    with router(free_port) as ep, zenoh.open(zenoh_config(ep)) as session:
        with socket.socket() as sock:
            sock.bind(("127.0.0.1", 0))
            ws_port = sock.getsockname()[1]
        bridge = Proc(["foxglove", "--port", str(ws_port), "--frame-rate", "20", "-e", ep, NS])
        try:
            bridge.wait_for("serving")
            with connect(f"ws://127.0.0.1:{ws_port}", max_size=None,
                         subprotocols=["foxglove.sdk.v1"]) as ws:
                client = FoxgloveClient(ws)
                overlays = {f"/{ROOT}/{s}" for s in r2.OVERLAYS}
                client.advertised(overlays | {f"/{ROOT}/camera/frame"})
                client.channels = {cid: c for cid, c in client.channels.items()
                                   if c["topic"] in overlays}
                client.subscribe_all()
                image = np.zeros((48, 64), np.uint8)
                image[10:20, 10:20] = 255
                seq = 0

                def frame_and_estimate(stamp_ns: int) -> None:
                    nonlocal seq
                    session.put(f"{ROOT}/camera/frame",
                                encode_frame(image, seq=seq, stamp_ns=stamp_ns))
                    session.put(f"{ROOT}/motion/estimate", encode_estimate(
                        seq=seq, stamp_ns=stamp_ns, npi=3, xc=20.0, yc=15.0, xe=2.0, ye=1.0,
                        dx=0.0, dy=0.0, scale=1.0, t_ms=0.1, first=seq == 0,
                        ids=np.arange(3), points=np.array([[10.0, 10], [20, 15], [30, 20]]),
                        params_id=0))
                    seq += 1
                    time.sleep(0.06)  # beyond the bridge's frame period

                features = f"/{ROOT}/camera/features"
                for _ in range(10):
                    frame_and_estimate(time.time_ns())
                client.receive(lambda c: c.received[features] >= 3, 10)
                assert client.received[features] >= 3, client.received
                assert client.received[f"/{ROOT}/camera/frame"] == 0  # not subscribed
                # valid for the contract, past what ROS 2 time holds
                frame_and_estimate(2 ** 31 * 1_000_000_000 + 5)
                bridge.wait_for("no ROS 2", timeout=10)
                before = client.received[features]
                for _ in range(10):
                    frame_and_estimate(time.time_ns())
                client.receive(lambda c: c.received[features] >= before + 3, 10)
                assert client.received[features] >= before + 3, client.received
            assert bridge.p.poll() is None, "\n".join(bridge.lines)
        finally:
            code = _stop(bridge)
    assert code == 0, "\n".join(bridge.lines)
