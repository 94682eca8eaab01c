"""Closed loop over real processes: simulator camera, tracker services, fuzzy controller.

Ground truth is computed here from ``sim/pose`` with the pinhole model written out (256x256,
60 degree horizontal field of view), independently of the simulator's own projection code.
"""

from __future__ import annotations

import math
import time

import msgpack
import numpy as np
import pytest
import zenoh

from procs import Collector, Proc, router, service, services, zenoh_config

pytestmark = pytest.mark.integration

F_PX = 128.0 / math.tan(math.radians(30.0))
CX = 127.5
TRACKER = ["--subpixel"]


def truth(pose: dict) -> tuple[float, float]:
    """Image x of the target centre (px) and its depth (m) from a sim/pose message."""
    dx, dy, th = pose["tx"] - pose["x"], pose["ty"] - pose["y"], pose["theta"]
    forward = math.cos(th) * dx + math.sin(th) * dy
    left = -math.sin(th) * dx + math.cos(th) * dy
    return CX - F_PX * left / forward, forward


def run(endpoint: str, session: zenoh.Session, scenario: str, control: bool) -> list[dict]:
    """One lockstep run of a built-in scenario; the sim/pose messages in order."""
    poses = Collector(session, "vistrack/robot/sim/pose")
    cam = service("camera", endpoint, "--source", f"sim:{scenario}", "--lockstep",
                  *([] if control else ["--no-control"]))
    try:
        assert cam.p.wait(120) == 0, "\n".join(cam.lines[-20:])
    finally:
        cam.stop()
    # every frame's answer came: none waited out --ack-timeout (on the host's clock, the
    # controller refused the simulated clock's estimates once 1 s ahead: 13 a run)
    assert cam.wait_for("finished after").rstrip().endswith("(0 answered late: --ack-timeout)")
    time.sleep(0.2)  # the last pose is in flight: the run is over, this is not a handshake
    poses.sub.undeclare()
    return [msgpack.unpackb(p) for _, p in poses.items]


def errors(poses: list[dict]) -> tuple[float, float]:
    """RMS centring error (px) and RMS scale error against the start of the run."""
    u, depth = np.array([truth(p) for p in poses]).T
    scale = depth[0] / depth
    return float(np.sqrt(np.mean((u - u[0]) ** 2))), float(np.sqrt(np.mean((scale - 1) ** 2)))


@pytest.fixture(scope="module")
def loop_services(free_port_module):
    with router(free_port_module) as ep, zenoh.open(zenoh_config(ep)) as session, \
            services(ep, names=("preprocessing", "motion-estimation", "fuzzy-controller"),
                     extra={"preprocessing": TRACKER, "motion-estimation": TRACKER,
                            "fuzzy-controller": ["--clock", "camera"]}):
        yield ep, session


@pytest.mark.parametrize("scenario", ["sideways", "approach"])
def test_control_cancels_most_of_the_apparent_motion(loop_services, scenario):
    """RMS centring and scale errors with control on are at most 25 % of those with the robot
    standing still, on the same scenario."""
    ep, session = loop_services
    still = run(ep, session, scenario, control=False)
    moving = run(ep, session, scenario, control=True)
    assert len(still) == len(moving) > 100  # lockstep: no frame lost
    c_still, s_still = errors(still)
    c_move, s_move = errors(moving)
    if scenario == "sideways":
        assert c_still > 10.0  # the scenario does move the target across the image
        assert c_move <= 0.25 * c_still
    else:
        assert s_still > 0.1
        assert s_move <= 0.25 * s_still
        assert c_move < 5.0  # approaching must not throw the centring off


def test_a_step_settles(loop_services):
    """The 'steps' scenario: after each step of the target the centring error is back inside
    a 2 px band within 45 frames (1.5 s at the simulated 30 fps) and stays there."""
    ep, session = loop_services
    poses = run(ep, session, "steps", control=True)
    u = np.array([truth(p)[0] for p in poses])
    err = np.abs(u - u[0])
    jumps = np.flatnonzero(np.abs(np.diff(u)) > 3.0) + 1  # frames where a step lands
    assert len(jumps) >= 2
    ends = list(jumps[1:]) + [len(u)]
    for start, end in zip(jumps, ends, strict=True):
        assert err[start] > 3.0
        settled = np.flatnonzero(err[start:end] > 2.0)
        last_out = int(settled.max()) if len(settled) else 0
        assert last_out < 45, f"step at frame {start} still outside the band at +{last_out}"


def _estimate(seq: int, stamp_ns: int, first: bool) -> bytes:
    """A valid estimate of a target drifting right by 1 px a frame from x = 128."""
    return msgpack.packb({"v": 1, "seq": seq, "stamp_ns": stamp_ns, "npi": 50,
                          "xc": 128.0 + seq, "yc": 128.0, "xe": 900.0, "ye": 900.0,
                          "dx": float(seq), "dy": 0.0, "scale": 1.0, "t_ms": 1.0,
                          "first": first, "features": [], "params_id": 0})


def test_watchdog_stops_the_robot(free_port):
    """Estimates stop: the controller commands zero with stale=true within its 0.3 s bound."""
    with router(free_port) as ep, zenoh.open(zenoh_config(ep)) as session:
        ctrl = Proc(["fuzzy-controller", "-e", ep, "--no-multicast-scouting"])
        try:
            ctrl.wait_for("ready")
            cmds = Collector(session, "vistrack/robot/control/cmd_vel")
            pub = session.declare_publisher("vistrack/robot/motion/estimate",
                                            congestion_control=zenoh.CongestionControl.BLOCK)
            t_last = 0.0
            for k in range(45):  # 1.5 s of estimates with the target drifting right
                pub.put(_estimate(k, time.time_ns(), k == 0))
                t_last = time.time()
                time.sleep(1 / 30)  # the estimate rate being simulated
            items = cmds.wait(lambda it: any(msgpack.unpackb(p)["stale"] for _, p in it),
                              timeout=5.0)
            t_stop = time.time()
            msgs = [msgpack.unpackb(p) for _, p in items]
        finally:
            ctrl.stop()
    moving = [m for m in msgs if not m["stale"]]
    assert moving and any(abs(m["vy"]) > 0.05 for m in moving)  # it was commanding motion
    stops = [m for m in msgs if m["stale"]]
    assert all(m["vx"] == m["vy"] == m["wz"] == 0.0 for m in stops)
    assert t_stop - t_last < 0.3 + 0.3  # the bound plus one repeat period and delivery


@pytest.mark.parametrize("first_lost", [False, True])
def test_a_camera_restarted_on_an_earlier_clock_is_followed(free_port, first_lost):
    """A lockstep simulator's clock runs ahead of the host's, and starts again from the host's
    time when the camera restarts: the second run's stamps are below the first run's last.
    With ``--clock camera`` the controller answers each of the second run's estimates with a
    command stamped as that estimate, and never sends a stale stop while they keep coming;
    also when the run's first estimate (``first: true``) was lost from its latest-only input,
    the camera's restart being told by ``seq`` going back."""
    with router(free_port) as ep, zenoh.open(zenoh_config(ep)) as session:
        ctrl = Proc(["fuzzy-controller", "-e", ep, "--no-multicast-scouting",
                     "--clock", "camera"])
        try:
            ctrl.wait_for("ready")
            cmds = Collector(session, "vistrack/robot/control/cmd_vel")
            pub = session.declare_publisher("vistrack/robot/motion/estimate",
                                            congestion_control=zenoh.CongestionControl.BLOCK)

            def answered(seq: int, stamp: int, first: bool) -> dict:
                pub.put(_estimate(seq, stamp, first))
                items = cmds.wait(lambda it: any(msgpack.unpackb(p)["stamp_ns"] == stamp
                                                 for _, p in it), timeout=5.0)
                return next(m for m in map(msgpack.unpackb, (p for _, p in items))
                            if m["stamp_ns"] == stamp)

            frame_ns = round(1e9 / 30)
            t0 = time.time_ns()
            # 150 frames on a clock 3x as fast as the simulated 30 fps (a simulator in
            # lockstep): 15 s, run in well under that, even on a loaded machine
            for k in range(150):
                answered(k, t0 + k * 3 * frame_ns, k == 0)
            t1 = time.time_ns()  # the camera restarts: its clock from the host's time again
            assert t1 < t0 + 149 * 3 * frame_ns
            start = len(cmds.items)
            second = [answered(k, t1 + k * frame_ns, k == 0 and not first_lost)
                      for k in range(1 if first_lost else 0, 60)]
            during = [msgpack.unpackb(p) for _, p in cmds.items[start:]]
        finally:
            ctrl.stop()
    assert all(not m["stale"] for m in second)
    assert any(abs(m["vy"]) > 0.05 for m in second)  # following the drift
    assert [m for m in during if m["stale"]] == []
    assert "rejected" not in "\n".join(ctrl.lines)


def _drive(endpoint: str, session: zenoh.Session, stops_after: bool) -> list[dict]:
    """A lockstep 'still' run answered from here: each frame's command (vx 0.3 m/s, stamped
    as the frame) and, with ``stops_after``, before it a stop stamped 1 ns after the frame
    (a watchdog's stop sent meanwhile on a clock ahead of the camera's). The poses in order."""
    poses = Collector(session, "vistrack/robot/sim/pose")
    frames = session.declare_subscriber("vistrack/robot/camera/frame")
    pub = session.declare_publisher("vistrack/robot/control/cmd_vel",
                                    congestion_control=zenoh.CongestionControl.BLOCK)
    cam = service("camera", endpoint, "--source", "sim:still", "--lockstep", "--ack-timeout", "5")
    try:
        seq = 0
        while cam.p.poll() is None:
            sample = frames.try_recv()
            if sample is None:
                time.sleep(0.0005)
                continue
            stamp = msgpack.unpackb(sample.payload.to_bytes())["stamp_ns"]
            for vx, at, stale in ([(0.0, stamp + 1, True)] if stops_after else []) \
                    + [(0.3, stamp, False)]:
                pub.put(msgpack.packb({"v": 1, "seq": seq, "stamp_ns": at, "vx": vx,
                                       "vy": 0.0, "wz": 0.0, "stale": stale}))
                seq += 1
        assert cam.p.wait(60) == 0, "\n".join(cam.lines[-20:])
    finally:
        cam.stop()
        frames.undeclare()
    assert cam.wait_for("finished after").rstrip().endswith("(0 answered late: --ack-timeout)")
    time.sleep(0.2)  # the last pose is in flight
    poses.sub.undeclare()
    return [msgpack.unpackb(p) for _, p in poses.items]


def test_in_lockstep_a_frame_is_answered_by_its_own_command_only(free_port):
    """The simulator steps each frame with the command stamped as that frame: a stop that
    comes first, stamped later, is not taken for the answer, so the robot's path is the same
    with and without such stops."""
    with router(free_port) as ep, zenoh.open(zenoh_config(ep)) as session:
        plain = _drive(ep, session, stops_after=False)
        stopped = _drive(ep, session, stops_after=True)
    assert len(plain) == len(stopped) > 100
    x_plain = [p["x"] for p in plain]
    assert x_plain[-1] > 0.5  # the commands did drive the robot
    assert [p["x"] for p in stopped] == x_plain
