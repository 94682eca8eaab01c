"""``vistrack bench ros2``: what speaking ROS 2 costs, against a plain ``camera/frame`` peer.

In one run, through one local Zenoh router, with preprocessing, motion-estimation,
fuzzy-controller, ``vistrack ros2`` and ``vistrack camera --source ros2:/camera/image_raw``
running as processes, this process plays a camera at 30 fps on 256x256 frames of real
texture (RubberWhale, else the built-in sequence), in alternating blocks:

* **plain**: it publishes ``camera/frame`` itself (the peer: what a vistrack camera sends);
* **ros2 mono8 / rgb8**: it publishes ``sensor_msgs/msg/Image`` as ``rmw_zenoh`` does (key,
  CDR, attachment, tokens) on ``/camera/image_raw``; the camera service converts each to a
  ``camera/frame`` (one more process hop: the driver's, then vistrack's camera);
* **direct mono8 / rgb8**: the same Images on ``/camera/direct``, read by a second
  pipeline's preprocessing (robot ``direct``, ``--source ros2:/camera/direct``) with no camera
  process between: the path of ``deploy/ros2-robot.yaml`` and the one the Target is about.
  That pipeline is the first's twin downstream (motion-estimation, fuzzy-controller and
  ``vistrack ros2 --namespace direct``): each estimate wakes as many processes in both, so
  plain is a fair peer for it too.

Latency is from the moment a frame (or image) has been put on the wire to its
``motion/estimate`` arriving here, matched by stamp. The modes take turns in short blocks
(``cycles`` of ``seconds`` each, in a random order each cycle), so a busy spell of the
machine falls on all of them; the added latency of a mode is, per cycle, its median minus
plain's median of the same cycle, and the figure is the median over the cycles. A bare Zenoh
relay process between this process and preprocessing (receiving in Zenoh's callback, as the
ROS 2 camera does, or through a ``RingChannel(1)`` loop) is the least one more hop costs: the
peer of the ROS 2 camera's hop.
Every ``control/cmd_vel`` of the run is then compared with what arrived on the ROS 2
``/cmd_vel``: count, values in order, attachment sequence numbers 1..N.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable
from contextlib import ExitStack

import cv2
import numpy as np
import zenoh

from ...common import groundtruth, synthetic
from ...common import rmw_zenoh as rmw
from ...common import ros2types as r2
from ...common.bus import loopback_config, query_status
from ...common.keys import Keys
from ...common.messages import CmdVel, Frame, peek_int
from ...common.sources import open_files
from ..camera.ros2cam import frame_of_payload
from .pipeline import _free_port, _process, _vistrack, _wait_alive

MODES = ("plain", "relay callback", "relay loop", "ros2 mono8", "ros2 rgb8", "direct mono8",
         "direct rgb8")
#: The robot name and ROS 2 topic of the direct path's pipeline.
DIRECT_ROBOT, DIRECT_TOPIC = "direct", "/camera/direct"

# The bare Zenoh relay peers (plain zenoh, no project code): ``ENDPOINT SRC DST HANDOFF``
# passes every payload of SRC on to DST unchanged, from Zenoh's callback thread or (HANDOFF 1)
# from a loop thread receiving from a RingChannel(1), the latest-only hand-off the camera's
# loop has too: the least that one more process hop costs, without conversion.
RELAY = """
import json, sys, threading, zenoh
endpoint, src, dst, handoff = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4])
c = zenoh.Config()
c.insert_json5("connect/endpoints", json.dumps([endpoint]))
c.insert_json5("scouting/multicast/enabled", "false")
with zenoh.open(c) as s:
    pub = s.declare_publisher(dst)
    if handoff:
        sub = s.declare_subscriber(src, zenoh.handlers.RingChannel(1))
        def loop():
            while True:
                pub.put(sub.recv().payload)
        threading.Thread(target=loop, daemon=True).start()
    else:
        sub = s.declare_subscriber(src, lambda smp: pub.put(smp.payload))
    print("ready", flush=True)
    sys.stdin.read()
"""
RELAY_KEYS = {"relay callback": "bench/ros2/relay_cb", "relay loop": "bench/ros2/relay_loop"}


def frames_256() -> list[np.ndarray]:
    """256x256 grey frames of real texture (RubberWhale resized) or the built-in sequence."""
    folder = groundtruth.middlebury("RubberWhale")
    if folder is not None:
        return list(open_files([str(folder)], (256, 256)))
    return synthetic.builtin_sequence(30)


class _Arrivals:
    """Arrival time (ns) of each estimate by its stamp, and every command in order."""

    def __init__(self, session: zenoh.Session, keys: Keys, direct: Keys) -> None:
        self.estimates: dict[int, int] = {}
        self.commands: list[bytes] = []
        self.ros_commands: list[tuple[bytes, bytes]] = []
        self._lock = threading.Lock()
        twist_key = rmw.topic_key(0, "/cmd_vel", r2.TWIST, r2.type_hash(r2.TWIST))
        self.subs = [session.declare_subscriber(keys.estimate, self._on_estimate),
                     session.declare_subscriber(keys.cmd_vel, self._on_command),
                     session.declare_subscriber(twist_key, self._on_twist),
                     session.declare_subscriber(direct.estimate, self._on_estimate)]

    def _on_estimate(self, sample: zenoh.Sample) -> None:
        t = time.time_ns()
        stamp = peek_int(sample.payload.to_bytes(), "stamp_ns")
        if stamp is not None:
            with self._lock:
                self.estimates[stamp] = t

    def _on_command(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self.commands.append(sample.payload.to_bytes())

    def _on_twist(self, sample: zenoh.Sample) -> None:
        att = sample.attachment.to_bytes() if sample.attachment is not None else b""
        with self._lock:
            self.ros_commands.append((sample.payload.to_bytes(), att))

    def close(self) -> None:
        for sub in self.subs:
            sub.undeclare()


def _play(mode: str, frames: list[np.ndarray], seconds: float, fps: float,
          plain: dict[str, zenoh.Publisher], images: dict[str, rmw.Publisher],
          sent: dict[str, dict[int, int]], seq0: int) -> int:
    """Publish frames at ``fps`` for ``seconds``; note (stamp -> time put) per mode."""
    period = 1.0 / fps
    next_t = time.perf_counter()
    n = int(seconds * fps)
    for i in range(n):
        next_t += period
        delay = next_t - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
        grey = frames[(seq0 + i) % len(frames)]
        stamp = time.time_ns()
        if mode in plain:
            plain[mode].put(Frame.from_image(grey, seq=seq0 + i, stamp_ns=stamp).encode())
        else:
            path, encoding = mode.split()
            images[path].put(_image_cdr(grey, encoding, stamp))
        sent[mode][stamp] = time.time_ns()
    return seq0 + n


def bench_ros2(out=sys.stdout, seconds: float = 2.0, cycles: int = 8, fps: float = 30.0,
               seed: int = 0) -> dict[str, float]:
    """Run the benchmark and print its table; return the figures."""
    frames = frames_256()
    keys = Keys("robot")
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    sent: dict[str, dict[int, int]] = {m: {} for m in MODES}
    blocks: list[dict[str, list[int]]] = []  # per cycle: mode -> stamps sent
    fig: dict[str, float] = {}
    with zenoh.open(loopback_config(endpoint, router=True)), \
            zenoh.open(loopback_config(endpoint)) as session, ExitStack() as stack:
        direct = Keys(DIRECT_ROBOT)
        arrivals = _Arrivals(session, keys, direct)
        stack.callback(arrivals.close)
        driver = stack.enter_context(rmw.Participant(session, rmw.Rmw(node="camera_driver")))
        images = {path: driver.publisher(topic, r2.IMAGE, r2.type_hash(r2.IMAGE),
                                         rmw.QOS_SENSOR)
                  for path, topic in (("ros2", "/camera/image_raw"), ("direct", DIRECT_TOPIC))}
        plain = {"plain": session.declare_publisher(keys.frame),
                 **{m: session.declare_publisher(k) for m, k in RELAY_KEYS.items()}}
        for pub in plain.values():
            stack.callback(pub.undeclare)
        for handoff, key in enumerate(RELAY_KEYS.values()):
            stack.enter_context(_process([sys.executable, "-c", RELAY, endpoint, key,
                                          keys.frame, str(handoff)], stdin=True,
                                         ready_line=True))
        bridge = stack.enter_context(_process(_vistrack("ros2", endpoint, "--domain", "0")))
        _wait_alive(session, keys, {"ros2"}, 60)
        controller = stack.enter_context(_process(_vistrack("fuzzy-controller", endpoint)))
        pids = [bridge.pid, controller.pid]
        for name, extra in (("motion-estimation", ()), ("preprocessing", ()),
                            ("camera", ("--source", "ros2:/camera/image_raw", "--domain",
                                        "0"))):
            pids.append(stack.enter_context(_process(_vistrack(name, endpoint, *extra))).pid)
        direct_services: tuple[tuple[str, tuple[str, ...]], ...] = (
            ("ros2", ("--namespace", DIRECT_ROBOT)), ("fuzzy-controller", ()),
            ("motion-estimation", ()), ("preprocessing", ("--source", f"ros2:{DIRECT_TOPIC}")))
        for name, flags in direct_services:
            pids.append(stack.enter_context(_process(_vistrack(
                name, endpoint, "--robot", DIRECT_ROBOT, *flags))).pid)
        _wait_alive(session, keys, {"fuzzy_controller", "motion_estimation", "preprocessing",
                                    "camera"}, 90)
        _wait_alive(session, direct, {"ros2", "fuzzy_controller", "motion_estimation",
                                      "preprocessing"}, 90)
        deadline = time.monotonic() + 30
        while not (all(i.matched() for i in images.values())
                   and all(_matching(p) for p in plain.values())):
            if time.monotonic() > deadline:
                raise RuntimeError("the camera and the preprocessings did not subscribe in 30 s")
            time.sleep(0.05)
        time.sleep(0.5)
        seq = 0
        for mode in ("plain", "direct mono8"):  # warm-up: each pipeline's first frames
            seq = _play(mode, frames, 1.0, fps, plain, images, sent, seq)
            sent[mode].clear()
        rng = np.random.default_rng(seed)
        for _ in range(cycles):
            blocks.append({})
            # a random order each cycle: a mode that always followed the ROS 2 camera's idle
            # blocks would always meet it cold
            for mode in [MODES[i] for i in rng.permutation(len(MODES))]:
                before = set(sent[mode])
                seq = _play(mode, frames, seconds, fps, plain, images, sent, seq)
                blocks[-1][mode] = [s for s in sent[mode] if s not in before]
                time.sleep(0.2)  # the last estimates of the block arrive
        status = {s["service"]: s for s in query_status(session, keys, timeout=2.0)}
        direct_status = {s["service"]: s for s in query_status(session, direct, timeout=2.0)}
        # the controller stops: its last command goes out; then every one must be on /cmd_vel
        controller.terminate()
        controller.wait(10)
        deadline = time.monotonic() + 10
        while len(arrivals.ros_commands) < len(arrivals.commands) \
                and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.3)
        commands, ros_commands = list(arrivals.commands), list(arrivals.ros_commands)
        estimates = dict(arrivals.estimates)
    for mode in MODES:
        lat = np.array([(estimates[s] - t) * 1e-6 for s, t in sent[mode].items()
                        if s in estimates])
        key = mode.replace(" ", "_")
        fig[f"{key}_frames"] = float(len(sent[mode]))
        fig[f"{key}_estimates"] = float(lat.size)
        fig[f"{key}_p50_ms"] = float(np.median(lat)) if lat.size else float("nan")
        fig[f"{key}_p90_ms"] = float(np.percentile(lat, 90)) if lat.size else float("nan")
    def cycle_median(mode: str, cycle: dict[str, list[int]]) -> float:
        lat = [(estimates[s] - sent[mode][s]) * 1e-6 for s in cycle[mode] if s in estimates]
        return float(np.median(lat)) if lat else float("nan")

    medians = {m: np.array([cycle_median(m, c) for c in blocks]) for m in MODES}
    for mode in MODES[1:]:
        key = mode.replace(" ", "_")
        added = medians[mode] - medians["plain"]
        fig[f"{key}_added_ms"] = float(np.nanmedian(added))
        fig[f"{key}_added_lo_ms"] = float(np.nanmin(added))
        fig[f"{key}_added_hi_ms"] = float(np.nanmax(added))
    for mode in ("ros2 mono8", "ros2 rgb8"):  # against the bare relay with the same hand-off
        key = mode.replace(" ", "_")
        fig[f"{key}_over_relay_ms"] = float(np.nanmedian(medians[mode]
                                                         - medians["relay callback"]))
    fig["camera_p50_ms"] = status.get("camera", {}).get("p50_ms") or float("nan")
    fig["camera_rejected"] = float(status.get("camera", {}).get("rejected", -1))
    fig["direct_rejected"] = float(direct_status.get("preprocessing", {}).get("rejected", -1))
    fig.update(_compare_commands(commands, ros_commands))
    fig.update(_conversion_us(frames[0]))
    _print(fig, out)
    return fig


def _image_cdr(grey: np.ndarray, encoding: str, stamp: int) -> bytes:
    pixels = grey if encoding == "mono8" else np.dstack([grey, grey, grey])
    return r2.serialize(r2.typestore().types[r2.IMAGE](
        header=r2.header(stamp, "camera_optical"), height=grey.shape[0], width=grey.shape[1],
        encoding=encoding, is_bigendian=0, step=pixels.shape[1] * (1 if pixels.ndim == 2 else 3),
        data=np.ascontiguousarray(pixels).reshape(-1)))


def _conversion_us(grey: np.ndarray, rounds: int = 15, n: int = 200) -> dict[str, float]:
    """What preprocessing --source ros2 does per frame that it does not for a camera/frame,
    in this process, the two interleaved: decoding a ``camera/frame`` (plain) against
    converting a ROS 2 Image to one (:func:`frame_of_payload`) and encoding it for the
    ``camera/frame`` it then publishes. Median over ``rounds`` of ``n`` back to back, us;
    OpenCV on one thread, as in the services."""
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        plain = Frame.from_image(grey, seq=0, stamp_ns=1).encode()
        cdr = {enc: _image_cdr(grey, enc, 1) for enc in ("mono8", "rgb8")}
        def convert(payload: bytes) -> Callable[[], object]:
            return lambda: frame_of_payload(payload, r2.IMAGE, 0).encode()

        work: dict[str, Callable[[], object]] = {
            "plain": lambda: Frame.decode(plain), **{e: convert(c) for e, c in cdr.items()}}
        times: dict[str, list[float]] = {k: [] for k in work}
        for _ in range(rounds):
            for name, f in work.items():
                t0 = time.perf_counter()
                for _ in range(n):
                    f()
                times[name].append((time.perf_counter() - t0) / n * 1e6)
    finally:
        cv2.setNumThreads(threads)
    med = {k: float(np.median(v)) for k, v in times.items()}
    return {"convert_plain_us": med["plain"], "convert_mono8_us": med["mono8"],
            "convert_rgb8_us": med["rgb8"]}


def _matching(pub: zenoh.Publisher) -> bool:
    # the 1.x stub says bool, but the binding returns an (always truthy) MatchingStatus
    status = pub.matching_status
    return bool(getattr(status, "matching", status))


def _compare_commands(commands: list[bytes], ros_commands: list[tuple[bytes, bytes]]
                      ) -> dict[str, float]:
    """Every control/cmd_vel against /cmd_vel: counts, in-order matches, sequence numbers."""
    sent = [CmdVel.decode(p) for p in commands]
    seqs = [rmw.Attachment.decode(a).seq for _, a in ros_commands]
    twists = [r2.deserialize(p, r2.TWIST) for p, _ in ros_commands]
    matched = sum(1 for c, t in zip(sent, twists, strict=False)
                  if (t.linear.x, t.linear.y, t.angular.z) == (c.vx, c.vy, c.wz))
    return {"cmd_vel_sent": float(len(sent)), "cmd_vel_ros": float(len(twists)),
            "cmd_vel_in_order": float(matched),
            "cmd_vel_seq_contiguous": float(seqs == list(range(1, len(seqs) + 1)))}


def _print(fig: dict[str, float], out) -> None:
    print("# vistrack bench ros2: 256x256 frames at 30 fps through a local Zenoh router, the "
          "modes in turn; added: median over the cycles of (mode - plain) medians [range]",
          file=out)
    for mode in MODES:
        key = mode.replace(" ", "_")
        added = (f", added {fig[f'{key}_added_ms']:+.3f} ms [{fig[f'{key}_added_lo_ms']:+.2f}"
                 f"..{fig[f'{key}_added_hi_ms']:+.2f}]" if mode != "plain" else "")
        print(f"{mode + ': put -> estimate (median / p90)':48s} "
              f"{fig[f'{key}_p50_ms']:.3f} / {fig[f'{key}_p90_ms']:.3f} ms "
              f"({fig[f'{key}_estimates']:.0f} of {fig[f'{key}_frames']:.0f}){added}", file=out)
    print(f"{'ros2 over a bare relay hop (callback)':48s} "
          f"mono8 {fig['ros2_mono8_over_relay_ms']:+.3f} ms, "
          f"rgb8 {fig['ros2_rgb8_over_relay_ms']:+.3f} ms", file=out)
    print(f"{'camera service: image -> camera/frame (median)':48s} "
          f"{fig['camera_p50_ms']:.3f} ms, {fig['camera_rejected']:.0f} rejected", file=out)
    print(f"{'cmd_vel: pipeline -> /cmd_vel':48s} {fig['cmd_vel_sent']:.0f} sent, "
          f"{fig['cmd_vel_ros']:.0f} on /cmd_vel, {fig['cmd_vel_in_order']:.0f} equal in order, "
          f"attachment seq 1..N: {'yes' if fig['cmd_vel_seq_contiguous'] else 'NO'}", file=out)
    print(f"{'direct: preprocessing rejected':48s} {fig['direct_rejected']:.0f}", file=out)
    base = fig["convert_plain_us"]
    print(f"{'direct: its work a frame, in-process (us)':48s} camera/frame decode {base:.0f}; "
          f"Image convert + camera/frame encode: mono8 {fig['convert_mono8_us']:.0f} "
          f"({fig['convert_mono8_us'] - base:+.0f}), rgb8 {fig['convert_rgb8_us']:.0f} "
          f"({fig['convert_rgb8_us'] - base:+.0f})", file=out)
    # the Target is about the direct path (deploy/ros2-robot.yaml's); the camera's is one
    # process hop more by construction
    met_lat = max(fig["direct_mono8_added_ms"], fig["direct_rgb8_added_ms"]) <= 0.3
    met_cmd = fig["cmd_vel_sent"] == fig["cmd_vel_ros"] == fig["cmd_vel_in_order"] > 0 \
        and fig["cmd_vel_seq_contiguous"]
    print(f"target: direct added <= 0.3 ms a frame: {'met' if met_lat else 'NOT met'}; every "
          f"cmd_vel on /cmd_vel, in order: {'met' if met_cmd else 'NOT met'}", file=out)


if __name__ == "__main__":
    bench_ros2()
