"""The default ``vistrack up`` seen from another host on the robot's network (issue 18).

Two hosts, each a network namespace made by this module (netns.py), on one LAN (10.78.0.0/24
inside the namespaces only)::

    robot     10.78.0.1   vistrack up   (no flags: the default launch file and router), and
                          vistrack echo control/cmd_vel on tcp/127.0.0.1:7447, standing in for
                          the robot's motor driver
    stranger  10.78.0.2   plain zenoh, no credentials: the robot's address with the port of
                          every socket the pipeline listens on, and a stock Zenoh peer

The robot's listening sockets are read from /proc (what ``ss -ltunp`` shows inside its
namespace). From the stranger a plain zenoh client dials each of them on the robot's address,
subscribes to ``vistrack/**`` and publishes forged ``control/cmd_vel`` (vx 0.987654, beyond the
controller's 0.8 m/s limit), and a Zenoh peer with Zenoh's defaults (multicast scouting, listening
on the LAN) scouts and listens for a while: neither opens a session, receives a sample, or gets a
command to the robot. The controls, after the stranger's attempts: the same client on the robot
itself, on 127.0.0.1, opens a session on every TCP socket, receives the pipeline's samples and
its command reaches the motor driver; and the stranger's client does the same through a
``vistrack router -l tcp/0.0.0.0:7450`` on the robot, a deployment that says it wants the network.

The first test needs no root: the sessions of the services' and tools' default flags, opened in
this process, and the sockets they listen on. The other is skipped, with the reason, when not root,
without iproute2's ``ip``, or where network namespaces cannot be created.
"""

from __future__ import annotations

import argparse
import ipaddress
import json
import os
import time
from typing import Any

import netns
import pytest
from netns import NsProc, Stream, listening_sockets, namespace_pids, python

from vistrack.common.bus import ZenohNode, add_zenoh_args, config_from_args, open_session

pytestmark = pytest.mark.integration

ROBOT_IP, STRANGER_IP = "10.78.0.1", "10.78.0.2"
ROBOT_ROUTER = "tcp/127.0.0.1:7447"  # where the default vistrack up's router listens
START_S = 90.0  # one launch importing numpy/numba/OpenCV five times on a small machine
FORGED_VX, LOCAL_VX, TOLD_VX = 0.987654, 0.123456, 0.555555  # the controller's |vx| <= 0.8
TOLD_PORT = 7450  # the control: a router on the robot told to listen on the LAN

# A plain zenoh client (no project code) dialling each endpoint of argv[2:] in turn: a session
# that opens subscribes to vistrack/** for argv[1] s and publishes forged commands meanwhile.
# Prints one JSON object: the endpoints that opened a session, samples received, commands sent.
PROBE = """
import json, sys, threading, time, zenoh
import msgpack
seconds, endpoints, vx = float(sys.argv[1]), sys.argv[3:], float(sys.argv[2])
opened, errors, samples, sent = [], {}, [], 0
for endpoint in endpoints:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("transport/unicast/open_timeout", "2000")
    try:
        session = zenoh.open(conf)
    except zenoh.ZError as e:
        errors[endpoint] = str(e)[:200]
        continue
    with session:
        opened.append(endpoint)
        sub = session.declare_subscriber("vistrack/**",
                                         lambda s: samples.append(str(s.key_expr)))
        pub = session.declare_publisher("vistrack/robot/control/cmd_vel",
                                        congestion_control=zenoh.CongestionControl.BLOCK)
        deadline = time.monotonic() + seconds
        seq = 0
        while time.monotonic() < deadline:
            seq += 1
            pub.put(msgpack.packb({"v": 1, "seq": 10**9 + seq, "stamp_ns": time.time_ns(),
                                   "vx": vx, "vy": 0.0, "wz": 0.0, "stale": False}))
            sent += 1
            time.sleep(0.05)
        sub.undeclare()
        pub.undeclare()
print(json.dumps({"opened": opened, "errors": errors, "samples": len(samples),
                  "keys": sorted(set(samples)), "sent": sent}), flush=True)
"""

# A Zenoh peer with Zenoh's defaults (multicast scouting on, listening on every interface), as
# any Zenoh application on the robot's network runs: it scouts, subscribes to vistrack/** and
# publishes forged commands for argv[1] s. Prints what others advertised in their hellos, which
# sessions it has and what it received from others (its own hellos and commands left out).
STRANGER_PEER = """
import json, sys, time, zenoh
import msgpack
seconds, vx = float(sys.argv[1]), float(sys.argv[2])
MINE = 2 * 10**9  # the seq of the commands published here start above it
hellos = []
scout = zenoh.scout(lambda h: hellos.append({"zid": str(h.zid), "whatami": str(h.whatami),
                                             "locators": [str(l) for l in h.locators]}),
                    what="peer|router")
samples = []
def on_sample(s):
    if msgpack.unpackb(s.payload.to_bytes()).get("seq", 0) < MINE:
        samples.append(str(s.key_expr))
with zenoh.open(zenoh.Config()) as session:
    me = str(session.info.zid())
    sub = session.declare_subscriber("vistrack/**", on_sample)
    pub = session.declare_publisher("vistrack/robot/control/cmd_vel")
    deadline = time.monotonic() + seconds
    seq = 0
    while time.monotonic() < deadline:
        seq += 1
        pub.put(msgpack.packb({"v": 1, "seq": MINE + seq, "stamp_ns": time.time_ns(),
                               "vx": vx, "vy": 0.0, "wz": 0.0, "stale": False}))
        time.sleep(0.05)
    peers = [str(z) for z in session.info.peers_zid()]
    routers = [str(z) for z in session.info.routers_zid()]
    sub.undeclare()
    pub.undeclare()
scout.stop()
hellos = [h for h in hellos if h["zid"] != me]
print(json.dumps({"hellos": hellos, "peers": peers, "routers": routers,
                  "samples": len(samples), "sent": seq}), flush=True)
"""


def endpoint_host(locator: str) -> str:
    """The host of ``proto/host:port`` (options after ? or # dropped), brackets removed."""
    address = locator.partition("/")[2].split("?")[0].split("#")[0]
    return address.rsplit(":", 1)[0].strip("[]")


def run_json(ns: str, code: str, *args: str, timeout: float = 60.0) -> dict[str, Any]:
    proc = python(ns, code, *args, timeout=timeout)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


# -- the default flags' sessions, in this process (no root needed) ---------------------------

def test_default_flags_open_loopback_listeners_only():
    parser = argparse.ArgumentParser()
    add_zenoh_args(parser)
    # multicast scouting off: it may not work in a sandbox, and it is not where a session
    # listens; everything else as a service or tool started without flags
    args = parser.parse_args(["--no-multicast-scouting"])
    already = set(listening_sockets([os.getpid()]))  # anything this process had open before
    with ZenohNode("camera", config_from_args(args)) as a, \
            ZenohNode("preprocessing", config_from_args(args)) as b:
        mine = [s for s in listening_sockets([os.getpid()]) if s not in already]
        # each peer listens, both on loopback ...
        tcp = [s for s in mine if s.proto == "tcp"]
        assert len(tcp) == 2, [str(s) for s in mine]
        assert all(s.loopback for s in mine), [str(s) for s in mine if not s.loopback]
        # ... and there a third connects to both directly, as the services do through their
        # router's gossip (here: named on the command line)
        ports = [s.port for s in tcp]
        third = parser.parse_args(["--no-multicast-scouting",
                                   *(f"--connect=tcp/127.0.0.1:{p}" for p in ports)])
        with open_session(config_from_args(third)) as c:
            deadline = time.monotonic() + 5
            while len(list(c.info.peers_zid())) < 2:
                assert time.monotonic() < deadline, "the peers' loopback endpoints refused"
                time.sleep(0.01)
            assert {str(z) for z in c.info.peers_zid()} == {str(a.session.info.zid()),
                                                            str(b.session.info.zid())}


# -- the default vistrack up, from another host ------------------------------------------------

@pytest.fixture(scope="module")
def lan():
    with netns.lan_or_skip(netns.Lan({"robot": ROBOT_IP, "stranger": STRANGER_IP})) as net:
        yield net


@pytest.fixture(scope="module")
def robot(lan):
    """The default ``vistrack up`` on the robot, and the robot's view of control/cmd_vel."""
    up = NsProc(lan.ns["robot"], "up")
    commands = None
    try:
        up.wait_line(r"^vistrack up: ready \(5 services\)$", START_S)
        commands = Stream(lan.ns["robot"], "control/cmd_vel", ROBOT_ROUTER)
        commands.wait(lambda got: len(got) >= 3, 0.0, 30, "the controller's commands")
        yield up, commands
    finally:
        if commands is not None:
            commands.stop()
        up.stop()


def test_default_up_is_closed_to_another_host(lan, robot):
    up, commands = robot
    robot_ns, stranger_ns = lan.ns["robot"], lan.ns["stranger"]
    t0 = time.monotonic()
    sockets = listening_sockets(namespace_pids(robot_ns))
    tcp = [s for s in sockets if s.proto == "tcp"]
    outside = [s for s in sockets if not s.loopback]
    # every socket, dialled on the robot's address from the stranger
    targets = [f"{s.proto}/{ROBOT_IP}:{s.port}" for s in sockets]
    probe = run_json(stranger_ns, PROBE, "1", str(FORGED_VX), *targets)
    # a stock Zenoh peer on the stranger, scouting and listening on the LAN
    peer = run_json(stranger_ns, STRANGER_PEER, "3", str(FORGED_VX))
    advertised = [loc for h in peer["hellos"] for loc in h["locators"]]
    # the controls, after the stranger's attempts: the same client on the robot reaches every
    # TCP socket on loopback, gets the pipeline's samples, and its command reaches the motor
    # driver; and from the stranger it does all that through a router told to listen on the
    # network (-l), so the LAN and the client work
    t_local = time.monotonic()
    local = run_json(robot_ns, PROBE, "0.5", str(LOCAL_VX),
                     *(f"tcp/127.0.0.1:{s.port}" for s in tcp))
    commands.wait(lambda got: any(m["vx"] == LOCAL_VX for m in got), t_local, 10,
                  "the command published on the robot itself")
    exposed = NsProc(robot_ns, "router", "-l", f"tcp/0.0.0.0:{TOLD_PORT}", "-e", ROBOT_ROUTER,
                     "--no-multicast-scouting")
    try:
        exposed.wait_line(r"vistrack router: ready", 30)
        t_told = time.monotonic()
        told = run_json(stranger_ns, PROBE, "1", str(TOLD_VX), f"tcp/{ROBOT_IP}:{TOLD_PORT}")
        commands.wait(lambda got: any(m["vx"] == TOLD_VX for m in got), t_told, 10,
                      "the stranger's command through the router told to listen on the LAN")
    finally:
        exposed.stop()
    forged = [m for _, m in commands.samples(t0) if m["vx"] == FORGED_VX]
    report = "\n".join(str(s) for s in sockets)
    print(f"\nrobot's sockets: {len(tcp)} TCP listeners, {len(sockets) - len(tcp)} UDP; "
          f"beyond loopback: {sum(s.proto == 'tcp' for s in outside)} TCP, "
          f"{sum(s.proto == 'udp' for s in outside)} UDP\n{report}\n"
          f"stranger's client: {len(probe['opened'])} sessions of {len(targets)} sockets, "
          f"{probe['samples']} samples, {probe['sent']} forged commands sent\n"
          f"stranger's peer: {len(peer['hellos'])} hellos advertising {sorted(set(advertised))}, "
          f"{len(peer['peers']) + len(peer['routers'])} sessions, {peer['samples']} samples, "
          f"{peer['sent']} forged commands sent\n"
          f"robot's own client: {len(local['opened'])} sessions, {local['samples']} samples\n"
          f"stranger's client via a router told -l tcp/0.0.0.0:{TOLD_PORT}: "
          f"{len(told['opened'])} session, {told['samples']} samples\n"
          f"forged commands delivered to the robot: {len(forged)}")

    # found: the router, the five services and the echo tool each listen (peers do)
    assert len({s.pid for s in tcp}) >= 6, report
    assert not [s for s in outside if s.proto == "tcp"], report
    # a UDP socket beyond loopback may only be the router's multicast scouting (the
    # 224.0.0.224:7446 group and its reply socket), which advertises loopback only
    assert all("up" in s.command.split() for s in outside), report
    assert all(ipaddress.ip_address(endpoint_host(loc)).is_loopback for loc in advertised), peer
    assert probe["opened"] == [] and probe["samples"] == 0, probe
    assert set(probe["errors"]) == set(targets), probe
    assert peer["peers"] == [] and peer["routers"] == [] and peer["samples"] == 0, peer
    assert not forged, f"{len(forged)} forged commands reached the robot"
    assert len(local["opened"]) == len(tcp) and local["samples"] > 0, local
    assert told["opened"] and told["samples"] > 0, told
    assert up.proc.poll() is None, up.tail
