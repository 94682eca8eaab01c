"""The simulator as the camera service's source (``--source sim[:SCENARIO]``).

Reads   ``vistrack/<robot>/control/cmd_vel``  (reliable: every command moves the robot)
Writes  ``vistrack/<robot>/camera/frame``, ``vistrack/<robot>/sim/pose`` (ground truth)

Real time (default): a frame every 1/fps s of wall time, the robot driven by the latest command.
Lockstep (``--lockstep``): frame k+1 is rendered only once the command answering frame k is in
(the one stamped as frame k: ``stamp_ns`` equal), or, with ``--no-control``, its estimate; the
simulated clock advances 1/fps per frame whatever the wall clock does, so a run is
deterministic.
"""

from __future__ import annotations

import argparse
import logging
import time

from ...common.bus import Node
from ...common.keys import key_suffix
from ...common.messages import CmdVel, Estimate, MessageError, Pose, encode_frame
from ...common.sources import parse_size
from ..runtime import Faults, paced, ready, reject, wait_for_consumers
from .scenarios import ScenarioError, load_scenario
from .sim import CAMERA_SIDES, Camera, Command, Simulator

log = logging.getLogger("vistrack.camera")


def make_simulator(args: argparse.Namespace) -> Simulator:
    """The simulator of ``--source sim[:SCENARIO]``, ``--size``, ``--noise``, ``--texture`` and
    ``--seed``; a ValueError names the flag that is wrong."""
    scenario = args.source.split(":", 1)[1] if ":" in args.source else "default"
    w, h = (parse_size(args.size, "--size", sides=CAMERA_SIDES) if args.size is not None
            else (256, 256))
    try:
        scene = load_scenario(scenario or "default")
    except ScenarioError as e:
        if str(e).startswith(scenario):  # a scenario file: its path already leads the text
            raise
        raise ScenarioError(f"--source {args.source}: {e}") from None
    return Simulator(scene, camera=Camera(width=w, height=h, noise_sigma=args.noise),
                     texture=args.texture, seed=args.seed)


def _wait_answer(node: Node, stamp_ns: int, want_cmd: bool, timeout: float
                 ) -> tuple[bool, CmdVel | None]:
    """Wait for the command (or estimate) of the frame stamped ``stamp_ns``: the one stamped
    exactly so. A command stamped otherwise is not the frame's answer: a controller's
    watchdog stamps its stops on its host's clock, which a lockstep run's simulated clock
    may be behind (taken for the answer, a stop sent before the frame's command had stopped
    the robot for the whole run). Returns whether the answer came (False: ``timeout`` s
    passed, or the node stopped) and the newest command seen meanwhile."""
    deadline = time.monotonic() + timeout
    latest: CmdVel | None = None
    while not node.stop.is_set():
        item = node.recv(timeout=max(0.0, deadline - time.monotonic()))
        if item is None:
            return False, latest
        key, payload = item
        try:
            if key == node.keys.cmd_vel:
                latest = CmdVel.decode(payload)
                if want_cmd and latest.stamp_ns == stamp_ns:
                    return True, latest
            elif not want_cmd and Estimate.decode(payload).stamp_ns == stamp_ns:
                return True, latest
        except MessageError as e:
            reject(node, log, key_suffix(key), e)
    return False, latest


def _drain_commands(node: Node) -> CmdVel | None:
    latest = None
    while (item := node.recv(timeout=0.0)) is not None:
        key, payload = item
        if key != node.keys.cmd_vel:
            continue
        try:
            latest = CmdVel.decode(payload)
        except MessageError as e:
            reject(node, log, "control/cmd_vel", e)
    return latest


def _publish(node: Node, sim: Simulator, seq: int, stamp: int, lockstep: bool,
             cuts: int = 0) -> None:
    """Render the current view and publish it with the ground truth; in lockstep, the frame
    reliable (BLOCK): with one frame in flight that queues no backlog, and a recorder gets
    every frame too (as a file camera's in lockstep, see :mod:`.service`)."""
    frame = sim.render()
    node.publish(node.keys.frame, encode_frame(frame, seq=seq, stamp_ns=stamp, cuts=cuts),
                 reliable=lockstep)
    node.publish(node.keys.pose, Pose(seq=seq, stamp_ns=stamp, **sim.pose()).encode(),
                 reliable=True)


def run_sim(node: Node, args: argparse.Namespace, sim: Simulator) -> int:
    fps = args.fps if args.fps > 0 else 30.0
    dt = 1.0 / fps
    control = not args.no_control
    node.subscribe(node.keys.cmd_vel, latest=False)
    if args.lockstep and not control:
        node.subscribe(node.keys.estimate, latest=True)
    node.advertise(node.keys.frame, reliable=args.lockstep)
    node.advertise(node.keys.pose, reliable=True)
    ready(node)
    # lockstep runs are reproducible from their first frame; in real time the simulator is a
    # camera like any other, rendering for whoever is there
    if args.lockstep and not wait_for_consumers(node, node.keys.frame):
        return 0  # stopped before anyone subscribed
    cmd = Command()
    faults = Faults(node, log)
    t0_ns = time.time_ns()
    next_t = time.perf_counter()
    seq = 0
    cuts = 0  # the scenario's restarts (--loop)
    while not node.stop.is_set():
        if sim.done:
            if not args.loop:
                log.info("scenario %s finished after %d frames (%d answered late: "
                         "--ack-timeout)", sim.scenario.name, seq,
                         node.status.extra.get("ack_timeouts", 0))
                return 0
            sim.reset()
            cuts += 1  # the scenario from its start: the view jumps back there
        # the capture time is when the frame exists, as for a file or device camera: the
        # render (about 2 ms of warpPerspective) is the simulator's cost, not the pipeline's;
        # lockstep stamps run on the simulated clock, so they are reproducible
        stamp = t0_ns + round(seq * dt * 1e9) if args.lockstep else time.time_ns()
        sent = faults.call(node.keys.frame, seq, _publish, node, sim, seq, stamp, args.lockstep,
                           cuts)
        node.status.extra["frames"] = seq + 1
        if args.lockstep and sent:
            answered, got = _wait_answer(node, stamp, control, args.ack_timeout)
            if not answered and not node.stop.is_set():
                extra = node.status.extra
                extra["ack_timeouts"] = extra.get("ack_timeouts", 0) + 1
        elif args.lockstep:
            got = None
        else:
            next_t = paced(node, next_t, dt)
            got = _drain_commands(node)
        if control and got is not None:
            cmd = Command(vx=got.vx, vy=got.vy, wz=got.wz)
        faults.call(node.keys.cmd_vel, seq, sim.step, cmd if control else Command(), dt)
        seq += 1
    return 0
