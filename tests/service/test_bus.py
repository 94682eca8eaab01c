"""The bus seam (common/bus.py): real Zenoh sessions on loopback, and MemoryNode parity.

Two ZenohNodes per test: one listens on tcp/127.0.0.1:<free port>, the other connects there,
multicast scouting off (it may not work in the sandbox). Conditions are awaited by polling
with a deadline, never by sleeping a fixed time.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time

import numpy as np
import pytest
import zenoh

from vistrack.common.bus import (
    MAX_PUBLISHERS,
    MAX_SEQ_GAP,
    BusError,
    MemoryNode,
    Node,
    SeqGap,
    SeqGaps,
    Status,
    ZenohNode,
    add_zenoh_args,
    alive_services,
    config_from_args,
    install_signal_handlers,
    query_status,
    shm_pool_at_open,
)
from vistrack.common.keys import Keys
from vistrack.common.messages import Frame, pack, unpack

DEADLINE_S = 5.0


def wait_for(condition, timeout=DEADLINE_S, what="condition"):
    """Poll ``condition`` until true; fail after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.002)


def parse(argv):
    parser = argparse.ArgumentParser()
    add_zenoh_args(parser)
    return parser.parse_args(argv)


def msg(seq, **fields):
    """A small versioned payload with a seq (the bus only peeks at seq)."""
    return pack({"seq": seq, "stamp_ns": 0, **fields})


def seqs(items):
    return [unpack(payload)["seq"] for _, payload in items]


def drain(node, timeout=0.0):
    items = []
    while (item := node.recv(timeout)) is not None:
        items.append(item)
    return items


@pytest.fixture
def nodes(free_port):
    """Factory of connected ZenohNode pairs: ``nodes(service_a, service_b, **kw)``.

    The first listens, the second connects; both are closed at teardown.
    """
    endpoint = f"tcp/127.0.0.1:{free_port}"
    with contextlib.ExitStack() as stack:
        def make(service_a="camera", service_b="auto_tuner", *, capacity=1024):
            a = stack.enter_context(ZenohNode(
                service_a, config_from_args(parse(["-l", endpoint, "--no-multicast-scouting"])),
                capacity=capacity))
            b = stack.enter_context(ZenohNode(
                service_b, config_from_args(parse(["-e", endpoint, "--no-multicast-scouting"]))))
            wait_for(lambda: b.session.info.peers_zid(), what="the peers to connect")
            return a, b
        yield make


def subscribe_and_match(sub: ZenohNode, pub: ZenohNode, key: str, *, latest: bool,
                        reliable: bool = True):
    sub.subscribe(key, latest=latest)
    wait_for(lambda: pub.has_subscribers(key, reliable=reliable),
             what=f"the subscription to {key} to reach the publisher")


# -- command line and config ------------------------------------------------------------------

def test_flags_become_config():
    args = parse(["-m", "client", "-e", "tcp/127.0.0.1:7447", "-e", "tcp/10.0.0.2:7447",
                  "-l", "tcp/127.0.0.1:0", "--no-multicast-scouting", "--robot", "r2"])
    conf = config_from_args(args)
    assert json.loads(conf.get_json("mode")) == "client"
    assert json.loads(conf.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7447",
                                                              "tcp/10.0.0.2:7447"]
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:0"]
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert args.robot == "r2"


def test_defaults_leave_config_alone():
    args = parse([])
    assert args.robot == "robot" and args.mode is None and args.connect is None
    conf = config_from_args(args)
    assert json.loads(conf.get_json("connect/endpoints")) == []


def test_config_file_is_read_and_flags_override(tmp_path):
    path = tmp_path / "peer.json5"
    path.write_text('{ mode: "client", connect: { endpoints: ["tcp/127.0.0.1:7000"] } }')
    conf = config_from_args(parse(["-c", str(path), "-m", "peer"]))
    assert json.loads(conf.get_json("mode")) == "peer"
    assert json.loads(conf.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7000"]


def test_missing_config_file(tmp_path):
    path = tmp_path / "nope.json5"
    with pytest.raises(BusError, match="not found") as info:
        config_from_args(parse(["-c", str(path)]))
    assert str(path) in str(info.value)


def test_frame_publishers_make_their_shared_memory_pool_at_open(tmp_path):
    conf = shm_pool_at_open(config_from_args(parse([])))
    assert conf.get_json("transport/shared_memory/mode") == '"init"'
    # a config that disables shared memory or chose its mode is left alone
    off = tmp_path / "off.json5"
    off.write_text('{transport: {shared_memory: {enabled: false}}}')
    conf = shm_pool_at_open(config_from_args(parse(["--config", str(off)])))
    assert conf.get_json("transport/shared_memory/mode") == '"lazy"'
    assert conf.get_json("transport/shared_memory/enabled") == "false"


def test_invalid_config_file(tmp_path):
    path = tmp_path / "bad.json5"
    path.write_text("{ mode: ")
    with pytest.raises(BusError) as info:
        config_from_args(parse(["-c", str(path)]))
    assert str(path) in str(info.value)


def test_invalid_endpoint_names_the_flag():
    with pytest.raises(BusError, match="--connect"):
        config_from_args(parse(["-e", "not-an-endpoint"]))


def test_invalid_robot_flag(capsys):
    with pytest.raises(SystemExit):
        parse(["--robot", "a/b"])
    assert "robot id" in capsys.readouterr().err


def test_listen_port_in_use_is_a_bus_error(free_port):
    endpoint = f"tcp/127.0.0.1:{free_port}"
    conf = config_from_args(parse(["-l", endpoint, "--no-multicast-scouting"]))
    with ZenohNode("camera", conf):
        with pytest.raises(BusError, match="cannot open"):
            ZenohNode("camera", config_from_args(
                parse(["-l", endpoint, "--no-multicast-scouting"])))


# -- real Zenoh --------------------------------------------------------------------------

def test_publish_and_receive(nodes):
    a, b = nodes()
    subscribe_and_match(a, b, a.keys.frame, latest=True, reliable=False)
    frame = Frame.from_image(np.full((4, 5), 7, np.uint8), seq=0, stamp_ns=1)
    b.publish(b.keys.frame, frame.encode(), reliable=False)
    key, payload = a.recv(timeout=DEADLINE_S)
    assert key == "vistrack/robot/camera/frame"
    assert Frame.decode(payload).data.tolist() == [[7] * 5] * 4
    assert (a.status.received, a.status.dropped, b.status.published) == (1, 0, 1)
    assert a.recv(timeout=0.01) is None


def test_advertise_declares_the_publisher_before_the_first_publish(nodes):
    a, b = nodes()
    b.advertise(b.keys.estimate, reliable=False)
    declared = dict(b._publishers)
    assert list(declared) == [(b.keys.estimate, False)]
    subscribe_and_match(a, b, a.keys.estimate, latest=True, reliable=False)
    b.publish(b.keys.estimate, msg(0), reliable=False)
    assert a.recv(timeout=DEADLINE_S) is not None
    assert b._publishers[(b.keys.estimate, False)] is declared[(b.keys.estimate, False)]
    b.close()
    with pytest.raises(BusError, match="closed"):
        b.advertise(b.keys.estimate, reliable=False)


def test_wait_for_subscribers(nodes):
    a, b = nodes()
    t0 = time.monotonic()
    assert b.wait_for_subscribers(b.keys.frame, reliable=False, timeout=0.3) is False
    assert time.monotonic() - t0 >= 0.3
    a.subscribe(a.keys.frame, latest=True)
    assert b.wait_for_subscribers(b.keys.frame, reliable=False, timeout=DEADLINE_S)
    b.publish(b.keys.frame, msg(0), reliable=False)  # and the first sample reaches it
    assert a.recv(timeout=DEADLINE_S) is not None
    b.stop.set()  # a stopped node does not wait out the timeout
    t0 = time.monotonic()
    assert b.wait_for_subscribers(b.keys.pose, reliable=True, timeout=30.0) is False
    assert time.monotonic() - t0 < 1.0


def test_subscriptions_start_no_python_thread_and_reads_count_what_is_pending(nodes):
    # zenoh-python runs a plain Python callback in a thread of its own, one more thread to
    # wake (and hand the GIL to) for every message: the node's callbacks run in Zenoh's
    # receiving thread and only queue the sample; counting waits for someone to look
    a, b = nodes()
    before = threading.active_count()
    subscribe_and_match(a, b, a.keys.frame, latest=True)
    subscribe_and_match(a, b, a.keys.estimate, latest=True)
    subscribe_and_match(a, b, a.keys.params, latest=False)
    for seq in (0, 1, 3):
        b.publish(b.keys.frame, msg(seq), reliable=True)
    b.publish(b.keys.params, msg(0), reliable=True)
    wait_for(lambda: a.status.as_dict()["received"] == 4, what="4 payloads")
    assert threading.active_count() == before
    assert a.status.dropped == 1 + 2  # seq 2 missing; seq 0 and 1 overwritten by the next
    assert a.status.dropped == 3  # reading again counts nothing twice
    assert drain(a) == [(a.keys.params, msg(0)), (a.keys.frame, msg(3))]
    assert (a.status.received, a.status.dropped) == (4, 3)


def test_latest_only_keeps_the_newest_and_counts_drops(nodes):
    a, b = nodes()
    # BLOCK on the publisher, so every payload reaches the node: drops are the slot's only
    subscribe_and_match(a, b, a.keys.frame, latest=True)
    for seq in range(20):
        b.publish(b.keys.frame, msg(seq), reliable=True)
    wait_for(lambda: a.status.received == 20, what="20 frames to arrive")
    items = drain(a)
    assert seqs(items) == [19]
    assert a.status.dropped == 19


def test_a_stalled_loop_holds_one_frame_of_a_latest_only_key(nodes):
    # a loop that does not take its inputs (stuck, or a service run by hand that nobody asks
    # the status of) keeps the newest frame, not every frame that came since it stopped
    a, b = nodes()
    subscribe_and_match(a, b, a.keys.frame, latest=True)
    frames = [Frame.from_image(np.full((64, 64), seq, np.uint8), seq=seq, stamp_ns=seq).encode()
              for seq in range(50)]
    for payload in frames:
        b.publish(b.keys.frame, payload, reliable=True)
    inbox = a._inbox  # the loop's side is not called: nothing here takes samples in
    wait_for(lambda: inbox.arrivals.qsize() == 0 and inbox._latest.get(a.keys.frame) == frames[-1],
             what="the node's sweep to leave only the newest frame")
    assert len(inbox._latest) == 1 and not inbox._reliable
    assert (a.status.received, a.status.dropped) == (50, 49)
    assert drain(a) == [(a.keys.frame, frames[-1])]


def test_unsubscribe_stops_the_samples_at_the_network_and_counts_no_gap(nodes):
    # a service that takes some frames only (the auto-tuner between tunings) undeclares its
    # subscription: the publisher sees no subscriber, nothing arrives, and the frames it did
    # not take are not counted as lost once it subscribes again
    a, b = nodes()
    key = a.keys.frame
    subscribe_and_match(a, b, key, latest=True)
    b.publish(key, msg(0), reliable=True)
    wait_for(lambda: a.status.received == 1, what="the first frame")
    a.unsubscribe(key)
    assert not a.subscribed(key)
    wait_for(lambda: not b.has_subscribers(key, reliable=True),
             what="the publisher to see the subscription gone")
    for seq in range(1, 6):
        b.publish(key, msg(seq), reliable=True)
    assert [seqs([item]) for item in drain(a, timeout=0.2)] == [[0]]  # taken in before: kept
    assert a.status.received == 1
    a.unsubscribe(key)  # again: a no-op
    subscribe_and_match(a, b, key, latest=True)
    b.publish(key, msg(6), reliable=True)
    assert seqs([a.recv(timeout=DEADLINE_S)]) == [6]
    assert (a.status.received, a.status.dropped) == (2, 0)
    a.subscribe(a.keys.params, latest=False)
    with pytest.raises(BusError, match="latest=False"):
        a.unsubscribe(a.keys.params)  # what is in flight would be lost
    assert a.subscribed(a.keys.params)


def test_memory_node_unsubscribes_like_zenoh_node():
    with MemoryNode("auto_tuner") as node:
        key = node.keys.frame
        node.subscribe(key, latest=True)
        assert node.feed(key, msg(0))
        node.unsubscribe(key)
        assert not node.feed(key, msg(1))  # nobody takes it
        assert seqs(drain(node)) == [0]
        node.subscribe(key, latest=True)
        assert node.feed(key, msg(5))
        assert seqs(drain(node)) == [5]
        assert (node.status.received, node.status.dropped) == (2, 0)


def test_reliable_before_latest(nodes):
    a, b = nodes()
    subscribe_and_match(a, b, a.keys.frame, latest=True)
    subscribe_and_match(a, b, a.keys.params, latest=False)
    b.publish(b.keys.frame, msg(0), reliable=True)
    b.publish(b.keys.params, msg(0), reliable=True)
    b.publish(b.keys.params, msg(1), reliable=True)
    wait_for(lambda: a.status.received == 3, what="3 payloads")
    assert [k for k, _ in drain(a)] == [a.keys.params, a.keys.params, a.keys.frame]


def test_answer_reliably_follows_how_the_payload_was_sent(nodes):
    # a frame sent BLOCK (a camera in lockstep) is answered BLOCK; one sent BLOCK_FIRST (a
    # live camera) latest-only; anything on a reliable subscription (parameters) BLOCK
    a, b = nodes()
    subscribe_and_match(a, b, a.keys.frame, latest=True, reliable=False)
    subscribe_and_match(a, b, a.keys.frame, latest=True, reliable=True)
    subscribe_and_match(a, b, a.keys.params, latest=False)
    got = []
    for payload, key, reliable in [(msg(0), a.keys.frame, True), (msg(1), a.keys.frame, False),
                                   (msg(2), a.keys.params, True), (msg(3), a.keys.frame, True)]:
        b.publish(key, payload, reliable=reliable)
        item = a.recv(timeout=DEADLINE_S)
        assert item is not None
        got.append((seqs([item])[0], a.answer_reliably))
    assert got == [(0, True), (1, False), (2, True), (3, True)]
    # the newest payload of a latest-only key decides: BLOCK overwritten by BLOCK_FIRST
    b.publish(b.keys.frame, msg(4), reliable=True)
    wait_for(lambda: a.status.received == 5, what="frame 4")
    b.publish(b.keys.frame, msg(5), reliable=False)
    wait_for(lambda: a.status.received == 6, what="frame 5")
    assert seqs(drain(a)) == [5] and not a.answer_reliably


def test_reliable_in_order_without_loss_to_a_slow_consumer(nodes):
    # a small inbox makes the Zenoh callback block: backpressure instead of loss
    a, b = nodes(capacity=8)
    subscribe_and_match(a, b, a.keys.params, latest=False)
    n = 500

    def produce():
        for seq in range(n):
            b.publish(b.keys.params, msg(seq, reason="x" * 200), reliable=True)

    producer = threading.Thread(target=produce)
    producer.start()
    got = []
    deadline = time.monotonic() + 10
    while len(got) < n and time.monotonic() < deadline:
        item = a.recv(timeout=1.0)
        if item is not None:
            got.append(item)
            if len(got) % 50 == 0:
                time.sleep(0.02)  # a consumer that falls behind now and then
    producer.join(timeout=10)
    assert seqs(got) == list(range(n))
    assert a.status.dropped == 0 and a.status.received == n and b.status.published == n


def test_seq_gaps_are_counted(nodes):
    a, b = nodes()
    subscribe_and_match(a, b, a.keys.params, latest=False)
    payloads = [msg(0), msg(1), msg(2), msg(5), msg(6), b"\xc1 not msgpack", msg(10),
                msg(0), msg(1)]  # the last two: the publisher restarted, not a gap
    for payload in payloads:
        b.publish(b.keys.params, payload, reliable=True)
    wait_for(lambda: a.status.received == len(payloads), what="all payloads")
    assert [p for _, p in drain(a)] == payloads  # the bus delivers garbage; services reject
    assert a.status.dropped == 2 + 3


def test_status_queryable_answers_with_counters(nodes):
    a, b = nodes()
    subscribe_and_match(a, b, a.keys.params, latest=False)
    a.status.set_params({"search_size": 15, "corr_size": 9})
    a.status.extra["frames"] = 3
    for ms in (1.0, 2.0, 3.0, 4.0):
        a.status.observe_ms(ms)
    a.status.reject("tuner/params: field 'corr_size' bad")
    b.publish(b.keys.params, msg(0), reliable=True)
    wait_for(lambda: a.status.received == 1, what="the payload")
    statuses = query_status(b.session, b.keys, timeout=2.0)
    assert [s["service"] for s in statuses] == ["auto_tuner", "camera"]
    cam = statuses[1]
    assert cam["v"] == 1 and cam["robot"] == "robot" and cam["pid"] == os.getpid()
    assert cam["received"] == 1 and cam["rejected"] == 1 and cam["dropped"] == 0
    assert cam["last_error"] == "tuner/params: field 'corr_size' bad"
    assert cam["params"] == {"search_size": 15, "corr_size": 9}
    assert cam["extra"] == {"frames": 3}
    assert cam["p50_ms"] == pytest.approx(2.5) and cam["p99_ms"] <= 4.0
    assert cam["uptime_s"] >= 0 and statuses[0]["published"] == 1


def test_status_values_computed_when_read_come_in_extra(nodes):
    """``extra_on_read``: a service's counters computed when the status is read (a status
    query), not written every frame; they join ``extra``, as of the moment of the read."""
    a, b = nodes()
    state = {"npi": 7}
    reads = []

    def on_read():
        reads.append(1)
        return {"npi": state["npi"], "lost_by": {"fb": 2}}

    a.status.extra["frames"] = 3
    a.status.extra_on_read = on_read
    assert reads == []  # nothing computed until read
    first = [s for s in query_status(b.session, b.keys, timeout=2.0)
             if s["service"] == "camera"][0]
    assert first["extra"] == {"frames": 3, "npi": 7, "lost_by": {"fb": 2}}
    state["npi"] = 9
    second = [s for s in query_status(b.session, b.keys, timeout=2.0)
              if s["service"] == "camera"][0]
    assert second["extra"]["npi"] == 9 and len(reads) >= 2
    assert "npi" not in a.status.extra  # read, never written into the loop's own map
    # a fault there leaves the status answering, the fault named
    a.status.extra_on_read = lambda: {"npi": 1 // 0}
    broken = [s for s in query_status(b.session, b.keys, timeout=2.0)
              if s["service"] == "camera"]
    assert broken and broken[0]["extra"]["frames"] == 3
    assert "ZeroDivisionError" in broken[0]["extra"]["extra_on_read_error"]


def test_liveliness_visible_then_gone_after_close(nodes, free_port):
    a, b = nodes()
    wait_for(lambda: alive_services(b.session, b.keys) == ["auto_tuner", "camera"],
             what="both tokens")
    a.close()
    a.close()  # idempotent
    wait_for(lambda: alive_services(b.session, b.keys) == ["auto_tuner"],
             what="the camera token to go")
    with pytest.raises(BusError, match="closed"):
        a.publish(a.keys.frame, msg(0), reliable=False)


def test_robots_do_not_see_each_other(free_port):
    endpoint = f"tcp/127.0.0.1:{free_port}"
    listen = config_from_args(parse(["-l", endpoint, "--no-multicast-scouting"]))
    connect = config_from_args(parse(["-e", endpoint, "--no-multicast-scouting"]))
    with ZenohNode("camera", listen, "r1") as r1, ZenohNode("camera", connect, "r2") as r2:
        wait_for(lambda: alive_services(r2.session, r2.keys) == ["camera"], what="r2 token")
        assert [s["robot"] for s in query_status(r2.session, r2.keys)] == ["r2"]
        assert alive_services(r1.session, r1.keys) == ["camera"]


def test_token_only_once_declared_alive(free_port):
    # a service declares its token when it is ready, not when its session opens: a launcher
    # that waits for the token then knows the service takes input
    endpoint = f"tcp/127.0.0.1:{free_port}"
    listen = config_from_args(parse(["-l", endpoint, "--no-multicast-scouting"]))
    connect = config_from_args(parse(["-e", endpoint, "--no-multicast-scouting"]))
    with ZenohNode("auto_tuner", listen) as watcher, \
            ZenohNode("camera", connect, alive_at_open=False) as camera:
        wait_for(lambda: [s["service"] for s in query_status(watcher.session, watcher.keys)]
                 == ["auto_tuner", "camera"], what="the camera's status queryable")
        assert alive_services(watcher.session, watcher.keys) == ["auto_tuner"]
        assert not camera.alive
        camera.declare_alive()
        camera.declare_alive()  # idempotent
        wait_for(lambda: alive_services(watcher.session, watcher.keys)
                 == ["auto_tuner", "camera"], what="the camera's token")
        assert camera.alive


def test_two_publishers_on_one_key_are_not_drops(free_port):
    # a replay beside a live camera, a user's params set beside the tuner: each publisher has
    # its own seq, told apart by the Zenoh source info of its puts
    endpoint = f"tcp/127.0.0.1:{free_port}"
    listen = config_from_args(parse(["-l", endpoint, "--no-multicast-scouting"]))
    connect = config_from_args(parse(["-e", endpoint, "--no-multicast-scouting"]))
    with ZenohNode("preprocessing", listen) as sub, ZenohNode("camera", connect) as cam, \
            ZenohNode("auto_tuner", connect) as tuner:
        sub.subscribe(sub.keys.params, latest=False)
        for pub in (cam, tuner):
            wait_for(lambda pub=pub: pub.has_subscribers(pub.keys.params), what="matching")
        clock = time.time_ns() // 1000  # a seq that is a clock, as params set's
        for seq in range(5):
            tuner.publish(tuner.keys.params, msg(seq), reliable=True)
            cam.publish(cam.keys.params, msg(clock + seq), reliable=True)
        tuner.publish(tuner.keys.params, msg(7), reliable=True)  # 5 and 6 lost: counted
        wait_for(lambda: sub.status.received == 11, what="every message")
        assert sub.status.dropped == 2


# A link whose reader has stopped, made deterministic: the subscriber's reliable inbox (one
# payload) is full, so its Zenoh callback waits and nothing more is read off the socket; the
# socket buffers are small and shared memory is off, so a 1 MiB frame goes as fragments that
# cannot all be written. What the link holds then stands for a writer thread that is late on
# a loaded machine, which lost the first frame of a file camera now and then with DROP.
_STALLABLE = {"transport/shared_memory/enabled": "false",
              "transport/link/tcp/so_sndbuf": "65536", "transport/link/tcp/so_rcvbuf": "65536"}


def _stallable(argv):
    conf = config_from_args(parse([*argv, "--no-multicast-scouting"]))
    for key, value in _STALLABLE.items():
        conf.insert_json5(key, value)
    return conf


def _big_frame(seq):
    return Frame.from_image(np.full((1024, 1024), seq, np.uint8), seq=seq, stamp_ns=seq).encode()


@pytest.mark.parametrize("via", ["direct", "router"])
def test_the_latest_only_frame_in_flight_survives_a_stalled_link(free_port, via):
    """A latest-only frame published while the link to its subscriber is stalled arrives
    once the link clears (BLOCK_FIRST; DROP lost it), also through a router, which forwards
    the congestion control it is given; the publisher does not wait for the link, and a
    newer frame published meanwhile is dropped, not queued."""
    endpoint = f"tcp/127.0.0.1:{free_port}"
    with contextlib.ExitStack() as stack:
        if via == "router":
            stack.enter_context(zenoh.open(_stallable(["-m", "router", "-l", endpoint])))
            sub_argv = pub_argv = ["-m", "client", "-e", endpoint]
        else:
            sub_argv, pub_argv = ["-l", endpoint], ["-e", endpoint]
        a = stack.enter_context(ZenohNode("preprocessing", _stallable(sub_argv), capacity=1))
        b = stack.enter_context(ZenohNode("camera", _stallable(pub_argv)))
        subscribe_and_match(a, b, a.keys.params, latest=False)
        subscribe_and_match(a, b, a.keys.frame, latest=True, reliable=False)
        if via == "router":
            # a's link clears when its loop takes its inputs again: not before the router has
            # dealt with the frame. c, not stalled, receives it, then a marker b publishes
            # after that: the router reads b's link in order, so it has routed the frame to a.
            c = stack.enter_context(ZenohNode("auto_tuner", config_from_args(
                parse([*pub_argv, "--no-multicast-scouting"]))))
            c.subscribe(c.keys.frame, latest=True)
            subscribe_and_match(c, b, c.keys.estimate, latest=False)  # declared after it
        b.publish(b.keys.params, msg(0), reliable=True)
        b.publish(b.keys.params, msg(1), reliable=True)  # its callback waits: link stalled
        b.publish(b.keys.frame, _big_frame(0), reliable=False)  # returns: nothing waits on a
        if via == "router":
            wait_for(lambda: c.status.received == 1, what="the frame at the router")
            b.publish(b.keys.estimate, msg(0), reliable=True)
            wait_for(lambda: c.status.received == 2, what="the marker after it")
        else:
            # the frame before is still being pushed: this one is dropped, here, at once
            b.publish(b.keys.frame, _big_frame(1), reliable=False)
        got = [a.recv(timeout=DEADLINE_S) for _ in range(3)]  # the loop takes its inputs again
        assert [item[0] for item in got if item is not None] == \
            [a.keys.params] * 2 + [a.keys.frame]
        assert Frame.decode(got[2][1]).seq == 0
        if via == "direct":  # the dropped frame never comes: the next one does, after a gap
            b.publish(b.keys.frame, _big_frame(2), reliable=False)
            key, payload = a.recv(timeout=DEADLINE_S)
            assert Frame.decode(payload).seq == 2
            assert (a.status.received, a.status.dropped) == (4, 1)


def test_memory_node_counts_gaps_per_publisher():
    with MemoryNode("preprocessing") as node:
        node.subscribe(node.keys.frame, latest=False)
        for seq in range(3):  # interleaved, as two cameras on one key
            node.feed(node.keys.frame, msg(seq), source="camera")
            node.feed(node.keys.frame, msg(1000 + seq), source="replay")
        assert node.status.dropped == 0
        node.feed(node.keys.frame, msg(5), source="camera")  # 3 and 4 missing
        assert node.status.dropped == 2
        # without source ids they share one sequence: a jump of a clock is a new sequence,
        # never 10^15 losses
        node.feed(node.keys.params, msg(0))
        node.subscribe(node.keys.params, latest=False)
        for seq in (3, time.time_ns() // 1000, 4, 6):
            node.feed(node.keys.params, msg(seq))
        assert node.status.dropped == 2 + 1  # only 5, between 4 and 6
        assert node.status.received == 6 + 1 + 4


def test_a_latest_only_stream_follows_one_publisher_at_a_time(monkeypatch):
    """A replay beside the live camera interleaved its frames with the camera's: every seq
    went back or jumped by thousands, motion-estimation started a new track on each frame
    and every service downstream counted 186,721 drops in 3 s. The stream now follows one
    publisher until it has been silent SOURCE_SILENT_S; the other's samples are counted,
    not taken, and no drop is counted for them."""
    from vistrack.common import bus

    clock = [0.0]  # time moved on by the test, beside the real clock's few ms
    monkeypatch.setattr(bus, "_monotonic", lambda: time.monotonic() + clock[0])

    def seq_of(item):
        assert item is not None and item[0] == node.keys.frame
        return unpack(item[1])["seq"]

    with MemoryNode("preprocessing") as node:
        node.subscribe(node.keys.frame, latest=True)
        taken = []
        for seq in range(5):  # 30 fps, the replay's frames between the camera's
            node.feed(node.keys.frame, msg(seq), source="camera")
            node.feed(node.keys.frame, msg(2000 + seq), source="replay")
            taken.append(seq_of(node.recv(timeout=1.0)))
            clock[0] += 1 / 30
        assert taken == [0, 1, 2, 3, 4]
        assert (node.status.received, node.status.dropped) == (10, 0)
        assert node.status.extra["other_publishers"] == 5
        # the camera stops: the replay is taken once the camera has been silent long enough
        clock[0] += bus.SOURCE_SILENT_S / 2
        node.feed(node.keys.frame, msg(2005), source="replay")
        assert node.recv(timeout=0.05) is None
        clock[0] += bus.SOURCE_SILENT_S
        node.feed(node.keys.frame, msg(2006), source="replay")
        assert seq_of(node.recv(timeout=1.0)) == 2006
        # the camera back (a restart: another publisher) waits its turn in the same way
        node.feed(node.keys.frame, msg(0), source="camera")
        assert node.recv(timeout=0.05) is None
        # a publisher without a source id (an outside program) is always taken
        node.feed(node.keys.frame, msg(7))
        assert seq_of(node.recv(timeout=1.0)) == 7
        assert node.status.dropped == 0 and node.status.extra["other_publishers"] == 7


# -- MemoryNode: the same semantics ------------------------------------------------------

# (key attribute, payload, reliable subscription?) in arrival order
SCRIPT = [
    ("frame", msg(0)), ("frame", msg(1)), ("params", msg(0)), ("frame", msg(2)),
    ("estimate", msg(0)), ("params", msg(1)), ("params", msg(3)), ("frame", msg(3)),
    ("estimate", msg(1)), ("params", b"garbage"), ("frame", msg(5)),
]


def _subscribe_script(node: Node):
    node.subscribe(node.keys.frame, latest=True)
    node.subscribe(node.keys.estimate, latest=True)
    node.subscribe(node.keys.params, latest=False)


def _outcome(node: Node):
    items = drain(node)
    reliable = [(k, p) for k, p in items if k == node.keys.params]
    latest = {k: p for k, p in items if k != node.keys.params}
    assert items[:len(reliable)] == reliable  # reliable ones come first
    return reliable, latest, (node.status.received, node.status.dropped)


def test_memory_node_behaves_like_zenoh_node(nodes):
    a, b = nodes()
    _subscribe_script(a)
    for attr in ("frame", "estimate", "params"):
        wait_for(lambda attr=attr: b.has_subscribers(getattr(b.keys, attr)), what=attr)
    for attr, payload in SCRIPT:
        b.publish(getattr(b.keys, attr), payload, reliable=True)
    wait_for(lambda: a.status.received == len(SCRIPT), what="the script")
    over_zenoh = _outcome(a)

    with MemoryNode("camera") as mem:
        _subscribe_script(mem)
        for attr, payload in SCRIPT:
            assert mem.feed(getattr(mem.keys, attr), payload)
        in_memory = _outcome(mem)

    assert over_zenoh == in_memory
    reliable, latest, (received, dropped) = in_memory
    assert [p for _, p in reliable] == [msg(0), msg(1), msg(3), b"garbage"]
    assert latest == {a.keys.frame: msg(5), a.keys.estimate: msg(1)}
    # frames: 4 overwritten + seq 4 missing; estimates: 1 overwritten; params: seq 2 missing
    assert (received, dropped) == (len(SCRIPT), 4 + 1 + 1 + 1)


def test_memory_node_publish_feed_and_limits():
    with MemoryNode("preprocessing", "r1", capacity=2) as node:
        assert node.keys.robot == "r1"
        assert not node.feed(node.keys.frame, msg(0))  # nobody subscribed: like Zenoh
        node.subscribe("vistrack/r1/tuner/*", latest=False)
        node.subscribe("vistrack/r1/tuner/*", latest=False)  # same mode: no-op
        with pytest.raises(BusError, match="latest"):
            node.subscribe("vistrack/r1/tuner/*", latest=True)
        assert node.feed(node.keys.params, msg(0))
        assert node.feed(node.keys.report, msg(0))
        with pytest.raises(BusError, match="full"):
            node.feed(node.keys.params, msg(1))
        assert [k for k, _ in drain(node)] == [node.keys.params, node.keys.report]
        node.publish(node.keys.pre_frame, b"x", reliable=False)
        node.publish(node.keys.params, b"y", reliable=True)
        assert node.published[0] == (node.keys.pre_frame, b"x", False)
        assert node.published_on(node.keys.params) == [b"y"]
        assert node.status.published == 2
    with pytest.raises(BusError, match="closed"):
        node.publish(node.keys.params, b"z", reliable=True)
    assert node.recv(timeout=1.0) is None  # closed: returns at once


def test_recv_timeout_and_stop():
    with MemoryNode() as node:
        node.subscribe(node.keys.frame, latest=True)
        t0 = time.monotonic()
        assert node.recv(timeout=0.05) is None
        assert 0.04 <= time.monotonic() - t0 < 1.0
        timer = threading.Timer(0.05, node.stop.set)
        timer.start()
        t0 = time.monotonic()
        assert node.recv(timeout=30.0) is None
        assert time.monotonic() - t0 < 2.0
        timer.join()
        node.feed(node.keys.frame, msg(0))
        assert node.recv(timeout=0.0) is not None  # pending data still come out after stop


def test_recv_wakes_on_arrival_from_another_thread():
    with MemoryNode() as node:
        node.subscribe(node.keys.params, latest=False)
        timer = threading.Timer(0.05, node.feed, args=(node.keys.params, msg(0)))
        timer.start()
        assert node.recv(timeout=5.0) == (node.keys.params, msg(0))
        timer.join()


# -- status and helpers --------------------------------------------------------------------

def test_status_percentiles_window_and_threads():
    status = Status(window=100)
    assert status.as_dict()["p50_ms"] is None
    for ms in range(1000):  # only the last 100 (900..999) count
        status.observe_ms(ms)
    snap = status.as_dict()
    assert snap["samples"] == 100 and 940 <= snap["p50_ms"] <= 960 and snap["p99_ms"] < 1000
    with status.timed():
        pass
    threads = [threading.Thread(target=lambda: [status.count_received() for _ in range(1000)])
               for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert status.as_dict()["received"] == 4000
    assert set(snap) >= {"received", "published", "dropped", "rejected", "last_error",
                         "p50_ms", "p90_ms", "p99_ms", "params", "extra", "started"}


def test_seq_gap_helper():
    gap = SeqGap()
    assert [gap.observe(s) for s in (3, 4, 7, 7, 2, 3)] == [0, 0, 2, 0, 0, 0]
    assert gap.update(b"garbage") == 0 and gap.update(msg(6)) == 2
    assert gap.observe(6 + MAX_SEQ_GAP + 1) == 0  # a new sequence, not a million losses
    assert gap.observe(7 + MAX_SEQ_GAP + 1) == 0 and gap.observe(11 + MAX_SEQ_GAP) == 2


def test_seq_gaps_forget_the_oldest_publisher_of_a_key():
    gaps = SeqGaps()
    assert gaps.update("k", msg(0), "first") == 0
    for i in range(MAX_PUBLISHERS):  # every params set is a new publisher
        assert gaps.update("k", msg(0), f"p{i}") == 0
    assert gaps.update("k", msg(5), "p0") == 4  # still remembered
    assert gaps.update("k", msg(5), "first") == 0  # forgotten: a new sequence


def test_signal_handlers_set_stop():
    stop = threading.Event()
    restore = install_signal_handlers(stop)
    try:
        os.kill(os.getpid(), signal.SIGTERM)
        wait_for(stop.is_set, what="SIGTERM to set stop")
    finally:
        restore()
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL


def test_signal_handlers_off_main_thread_do_nothing():
    result = []
    thread = threading.Thread(target=lambda: result.append(
        install_signal_handlers(threading.Event())))
    before = signal.getsignal(signal.SIGTERM)
    thread.start()
    thread.join()
    assert signal.getsignal(signal.SIGTERM) is before
    result[0]()  # the no-op restore


SLOW_HANDLER_SCRIPT = textwrap.dedent("""
    import signal, threading, time
    from vistrack.common.bus import MemoryNode
    node = MemoryNode("fuzzy_controller")
    node.subscribe(node.keys.estimate, latest=True)
    main = threading.main_thread().ident

    def handler(signum, frame):
        time.sleep(0.2)  # longer than what is left of recv's 50 ms slice of waiting
        threading.Thread(target=node.stop.set, daemon=True).start()

    signal.signal(signal.SIGUSR2, handler)
    threading.Timer(0.3, lambda: signal.pthread_kill(main, signal.SIGUSR2)).start()
    t0 = time.monotonic()
    node.recv(timeout=30.0)
    print(f"{time.monotonic() - t0:.2f}", node.stop.is_set(), flush=True)
""")


def test_recv_ends_once_stop_is_set_even_after_a_slow_signal_handler():
    """A signal handler that runs inside recv's wait, and outlasts it, leaves CPython 3.11's
    queue waiting with a negative timeout: forever, until the next message. A service stopped
    by SIGINT or SIGTERM while nothing came in then hung (4 of 100 here, the flake of
    ``test_service_process_stops_on_signal_and_exits``). Setting ``stop`` wakes the wait: recv
    returns as soon as the handler has set it (0.3 s to the signal + 0.2 s of handler), not at
    its own 30 s timeout nor never."""
    out = subprocess.run([sys.executable, "-c", SLOW_HANDLER_SCRIPT], capture_output=True,
                         text=True, timeout=20)
    assert out.returncode == 0, out.stderr
    seconds, stopped = out.stdout.split()
    assert stopped == "True" and 0.45 <= float(seconds) < 5.0, out.stdout


SERVICE_SCRIPT = textwrap.dedent("""
    import sys
    from vistrack.common.bus import ZenohNode, install_signal_handlers
    from vistrack.common.bus import add_zenoh_args, config_from_args
    import argparse
    parser = argparse.ArgumentParser()
    add_zenoh_args(parser)
    args = parser.parse_args(sys.argv[1:])
    with ZenohNode("fuzzy_controller", config_from_args(args), args.robot) as node:
        install_signal_handlers(node.stop)
        node.subscribe(node.keys.estimate, latest=True)
        node.subscribe(node.keys.params, latest=False)
        print("ready", flush=True)
        while not node.stop.is_set():
            node.recv(timeout=5.0)
    print("closed", flush=True)
""")


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_service_process_stops_on_signal_and_exits(free_port, sig):
    """A service loop with callback subscribers ends on SIGTERM/SIGINT and the interpreter
    exits (an unclosed session would hang it)."""
    endpoint = f"tcp/127.0.0.1:{free_port}"
    proc = subprocess.Popen(
        [sys.executable, "-c", SERVICE_SCRIPT, "-l", endpoint, "--no-multicast-scouting"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
        conf = config_from_args(parse(["-e", endpoint, "--no-multicast-scouting"]))
        with zenoh.open(conf) as session:
            wait_for(lambda: alive_services(session, Keys()) == ["fuzzy_controller"],
                     what="the service token")
            proc.send_signal(sig)
            out, err = proc.communicate(timeout=10)
        assert proc.returncode == 0, err
        assert out.strip() == "closed"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
