"""``vistrack bench pipeline``: the five-process pipeline against one process and raw Zenoh.

In one run, on this machine's loopback, through one local Zenoh router as ``vistrack up`` runs:

1. raw Zenoh round trip: a frame-sized payload (256x256 bytes) between this process and an echo
   peer process (plain zenoh, no project code), back to back; one-way = round trip / 2;
2. in-process: the same stages (pre-processing, tracking, controller) on the same frames, one
   after the other in one process: the throughput ceiling without any messaging;
3. the raw Zenoh skeleton: five plain-zenoh processes (no project code, no work) wired like the
   pipeline, each passing on a payload of the size ours sends (camera 64 KiB -> pre-processing
   75 KiB -> motion-estimation 1 KiB -> controller; the auto-tuner takes frames and estimates).
   At 30 fps its capture-to-estimate latency / 3 is a raw hop under the same pacing, process
   count and wake-ups as ours; unpaced (two frames in flight) its rate is what Zenoh-Python
   itself allows this machine for that message pattern. Run unpaced once more with every node
   receiving in a loop thread from a zenoh ``RingChannel(1)`` (latest only, as the contract
   prescribes for frames) instead of in Zenoh's callback: the cost of that structure alone;
4. ours at 30 fps: the camera service paced at 30 fps through preprocessing,
   motion-estimation, auto-tuner and fuzzy-controller processes; latency from capture
   (``stamp_ns``) to ``motion/estimate`` arriving here, median and p99, and the added latency
   per hop (end to end minus the stages' own processing time, over the three hops
   camera -> preprocessing -> motion-estimation -> here);
5. ours unpaced: the camera with ``--fps 0 --in-flight 2`` (pre-processing and tracking
   overlap): estimates per second, and the frames dropped at the latest-only inputs (counted by
   the services).

The auto-tuner runs with ``--no-tune``: it buffers every frame and watches every estimate, but
its experiments, which would take a core for seconds, are left out of the measurement.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager

import numpy as np
import zenoh

from ...common import synthetic
from ...common.bus import alive_services, loopback_config, query_status
from ...common.keys import Keys
from ...common.messages import CmdVel, Frame, PreFrame, peek_int
from ...common.params import TrackerParams
from ...common.vision import Tracker, preprocess, warm_up
from ..fuzzy_controller.control import FuzzyController, FuzzySurface
from ..motion_estimation.service import estimate_message

ECHO_PEER = """
import json, sys, time, zenoh
c = zenoh.Config()
c.insert_json5("connect/endpoints", json.dumps([sys.argv[1]]))
c.insert_json5("listen/endpoints", json.dumps(["tcp/127.0.0.1:0"]))
c.insert_json5("scouting/multicast/enabled", "false")
with zenoh.open(c) as s:
    pub = s.declare_publisher("bench/pong")
    sub = s.declare_subscriber("bench/ping", lambda smp: pub.put(smp.payload))
    print("ready", flush=True)
    sys.stdin.read()
"""

# One node of the raw skeleton (plain zenoh, no project code): ``ROLE ENDPOINT FPS HANDOFF
# SIZES...``. Like our services it listens on loopback only, where the others connect to it
# directly. A relay answers each sample with a payload of its output size whose first 8 bytes
# are the input's (the capture stamp), from Zenoh's callback thread, or (HANDOFF 1) from a loop
# thread that receives from a zenoh RingChannel(1), the latest-only reception the contract
# prescribes for frames (and the cheapest hand-off: ours is a Python inbox); the camera puts
# frames at FPS, or (FPS 0) with two in flight.
SKELETON_NODE = """
import json, os, sys, threading, time, zenoh
role, endpoint, fps, handoff, frame, pre, est, cmd = sys.argv[1], sys.argv[2], \
    float(sys.argv[3]), *map(int, sys.argv[4:9])
c = zenoh.Config()
c.insert_json5("connect/endpoints", json.dumps([endpoint]))
c.insert_json5("listen/endpoints", json.dumps(["tcp/127.0.0.1:0"]))
c.insert_json5("scouting/multicast/enabled", "false")
def receive(s, src, act):
    if not handoff:
        s.declare_subscriber("bench/skel/" + src, lambda smp: act(smp.payload.to_bytes()))
        return
    sub = s.declare_subscriber("bench/skel/" + src, zenoh.handlers.RingChannel(1))
    def loop():
        while True:
            act(sub.recv().payload.to_bytes())
    threading.Thread(target=loop, daemon=True).start()
def relay(s, src, dst, size):
    pub = s.declare_publisher("bench/skel/" + dst)
    tail = os.urandom(size - 8)
    receive(s, src, lambda payload: pub.put(payload[:8] + tail))
with zenoh.open(c) as s:
    if role == "preprocessing":
        relay(s, "frame", "pre", pre)
    elif role == "motion-estimation":
        relay(s, "pre", "est", est)
    elif role == "fuzzy-controller":
        relay(s, "est", "cmd", cmd)
    elif role == "auto-tuner":
        for key in ("frame", "est"):
            receive(s, key, lambda payload: None)
    if role != "camera":
        print("ready", flush=True)
        sys.stdin.read()
        sys.exit(0)
    credit = threading.Semaphore(2)
    s.declare_subscriber("bench/skel/est", lambda smp: credit.release())
    pub = s.declare_publisher("bench/skel/frame")
    tail = os.urandom(frame - 8)
    print("ready", flush=True)
    threading.Thread(target=lambda: (sys.stdin.read(), os._exit(0)), daemon=True).start()
    next_t = time.perf_counter()
    while True:
        if fps:
            next_t += 1.0 / fps
            time.sleep(max(0.0, next_t - time.perf_counter()))
        elif not credit.acquire(timeout=1.0):
            credit = threading.Semaphore(2)  # a sample was lost: start over
        pub.put(time.time_ns().to_bytes(8, "little") + tail)
"""

SERVICES = ("fuzzy-controller", "motion-estimation", "preprocessing", "auto-tuner")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _cpu_s(pids: list[int]) -> float:
    """User + system CPU seconds used so far by these processes (all their threads)."""
    total = 0
    for pid in pids:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        total += int(fields[11]) + int(fields[12])
    return total / os.sysconf("SC_CLK_TCK")


@contextmanager
def _process(args: list[str], *, stdin: bool = False,
             ready_line: bool = False) -> Iterator[subprocess.Popen]:
    """A child process, stopped on exit; ``ready_line``: wait for its first stdout line."""
    p = subprocess.Popen(args, stdin=subprocess.PIPE if stdin else subprocess.DEVNULL,
                         stdout=subprocess.PIPE if ready_line else subprocess.DEVNULL,
                         stderr=subprocess.DEVNULL, text=True)
    try:
        if ready_line and p.stdout is not None and not p.stdout.readline():
            raise RuntimeError(f"{args[-1]!r} exited before it was ready")
        yield p
    finally:
        if p.poll() is None:
            p.terminate()
            try:
                p.wait(5)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        for pipe in (p.stdin, p.stdout):
            if pipe is not None:
                pipe.close()


def _vistrack(name: str, endpoint: str, *extra: str) -> list[str]:
    return [sys.executable, "-m", "vistrack.services.cli", name, "-e", endpoint,
            "--no-multicast-scouting", *extra]


def _wait_alive(session: zenoh.Session, keys: Keys, names: set[str], timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if names <= set(alive_services(session, keys, timeout=0.5)):
            return
        time.sleep(0.1)
    raise RuntimeError(f"services not alive after {timeout} s: "
                       f"{sorted(names - set(alive_services(session, keys)))}")


def raw_round_trip(session: zenoh.Session, endpoint: str, size: int, n: int = 300) -> np.ndarray:
    """Round-trip times (s) of ``size``-byte payloads through a plain-zenoh echo process."""
    got = threading.Event()
    sub = session.declare_subscriber("bench/pong", lambda s: got.set())
    pub = session.declare_publisher("bench/ping",
                                    congestion_control=zenoh.CongestionControl.BLOCK)
    payload = os.urandom(size)
    times = []
    with _process([sys.executable, "-c", ECHO_PEER, endpoint], stdin=True):
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:  # until the echo peer answers
            got.clear()
            pub.put(payload)
            if got.wait(0.2):
                break
        for _ in range(n):
            got.clear()
            t0 = time.perf_counter()
            pub.put(payload)
            if not got.wait(2.0):
                raise RuntimeError("raw zenoh echo did not answer within 2 s")
            times.append(time.perf_counter() - t0)
    sub.undeclare()
    pub.undeclare()
    return np.array(times)


def in_process(frames: list[np.ndarray]) -> float:
    """Seconds per frame for the pipeline's stages in one process (best of 3 passes)."""
    warm_up()
    ctrl = FuzzyController(FuzzySurface.compile())
    best = float("inf")
    for _ in range(3):
        tracker = Tracker(TrackerParams())
        t0 = time.perf_counter()
        for k, f in enumerate(frames):
            est = tracker.update(preprocess(f, tracker.params))
            ctrl.update(est.xc, est.scale, k / 30.0 + 1.0 + _ * 100, f.shape[1], npi=est.npi,
                        valid=est.valid)
        best = min(best, (time.perf_counter() - t0) / len(frames))
    return best


def message_sizes(frames: list[np.ndarray]) -> tuple[int, int, int, int]:
    """Bytes of our camera frame, pre-processed frame, estimate and command for these frames,
    encoded as the services encode them."""
    params = TrackerParams()
    tracker = Tracker(params)
    for f in frames[:2]:
        pre = preprocess(f, params)
        est = tracker.update(pre)
    frame = Frame.from_image(frames[1], seq=1, stamp_ns=time.time_ns())
    pre_msg = PreFrame(seq=1, stamp_ns=frame.stamp_ns, width=frame.width, height=frame.height,
                       data=pre.filtered, candidates=pre.candidates, strength=pre.strength,
                       params_id=0)
    est_msg = estimate_message(est, seq=1, stamp_ns=frame.stamp_ns, params_id=0)
    cmd = CmdVel(seq=1, stamp_ns=frame.stamp_ns, vx=0.1, vy=-0.1, wz=0.0)
    return (len(frame.encode()), len(pre_msg.encode()), len(est_msg.encode()),
            len(cmd.encode()))


def skeleton(session: zenoh.Session, endpoint: str, sizes: tuple[int, ...], *, fps: float,
             seconds: float, handoff: bool = False) -> dict[str, float]:
    """Run the raw Zenoh skeleton for ``seconds``: estimates per second and the latency from
    the camera's put to an estimate-sized payload arriving here, ms. ``handoff``: each node
    receives in a loop thread from a RingChannel(1), as the contract prescribes for frames,
    instead of in Zenoh's callback."""
    size_args = [str(n) for n in sizes]
    stamps: list[tuple[int, int]] = []

    def on(sample: zenoh.Sample) -> None:
        stamps.append((time.time_ns(), int.from_bytes(sample.payload.to_bytes()[:8], "little")))

    with ExitStack() as stack:
        pids = [os.getpid()]  # the router and this collector
        for role in (*SERVICES, "camera"):
            pids.append(stack.enter_context(_process(
                [sys.executable, "-c", SKELETON_NODE, role, endpoint, f"{fps:g}",
                 str(int(handoff)), *size_args],
                stdin=True, ready_line=True)).pid)
        time.sleep(1.0)  # steady state
        sub = session.declare_subscriber("bench/skel/est", on)
        cpu0 = _cpu_s(pids)
        time.sleep(seconds)  # a measurement window, not synchronisation
        cpu = _cpu_s(pids) - cpu0
        sub.undeclare()
    if len(stamps) < 10:
        raise RuntimeError(f"raw zenoh skeleton: only {len(stamps)} estimates in {seconds} s")
    lat = np.array([(t - s) * 1e-6 for t, s in stamps])
    return {"rate_hz": len(stamps) / seconds, "lat_p50_ms": float(np.median(lat)),
            "lat_p99_ms": float(np.percentile(lat, 99)), "hop_ms": float(np.median(lat)) / 3,
            "cpu_us_per_frame": cpu / len(stamps) * 1e6}


def _collect_estimates(session: zenoh.Session, keys: Keys, seconds: float
                       ) -> list[tuple[int, int]]:
    """(arrival, capture stamp) in ns of every estimate during ``seconds``."""
    out: list[tuple[int, int]] = []

    def on(sample: zenoh.Sample) -> None:
        t = time.time_ns()
        out.append((t, peek_int(sample.payload.to_bytes(), "stamp_ns") or t))

    sub = session.declare_subscriber(keys.estimate, on)
    time.sleep(seconds)  # a measurement window, not synchronisation
    sub.undeclare()
    return out


def distributed(session: zenoh.Session, endpoint: str, keys: Keys, *, fps: float,
                seconds: float) -> dict[str, float]:
    """Run camera + four services for ``seconds``; latency and rate figures."""
    with ExitStack() as stack:
        pids = [os.getpid()]  # the router and this collector
        for name in SERVICES:
            # the tuner buffers every frame but runs no experiment: its worker would take the
            # CPU the pipeline is being measured on
            extra = ("--no-tune",) if name == "auto-tuner" else ()
            pids.append(stack.enter_context(_process(_vistrack(name, endpoint, *extra))).pid)
        _wait_alive(session, keys, {"preprocessing", "motion_estimation", "auto_tuner",
                                    "fuzzy_controller"}, 60)
        pids.append(stack.enter_context(_process(_vistrack(
            "camera", endpoint, "--source", "builtin", "--loop", "--fps", f"{fps:g}",
            "--in-flight", "2"))).pid)
        _wait_alive(session, keys, {"camera"}, 30)
        time.sleep(1.0)  # let the first-frame work (feature selection) pass: steady state
        cpu0 = _cpu_s(pids)
        samples = _collect_estimates(session, keys, seconds)
        cpu = _cpu_s(pids) - cpu0
        status = {s["service"]: s for s in query_status(session, keys, timeout=2.0)}
    if len(samples) < 10:
        raise RuntimeError(f"only {len(samples)} estimates in {seconds} s")
    lat = np.array([(t - stamp) * 1e-6 for t, stamp in samples])
    pre = status.get("preprocessing", {})
    me = status.get("motion_estimation", {})
    proc_ms = (pre.get("p50_ms") or 0.0) + (me.get("p50_ms") or 0.0)
    return {"rate_hz": len(samples) / seconds, "pre_p50_ms": pre.get("p50_ms") or 0.0,
            "me_p50_ms": me.get("p50_ms") or 0.0, "lat_p50_ms": float(np.median(lat)),
            "lat_p99_ms": float(np.percentile(lat, 99)), "proc_p50_ms": proc_ms,
            "hop_ms": (float(np.median(lat)) - proc_ms) / 3.0,
            "dropped": float(pre.get("dropped", 0) + me.get("dropped", 0)),
            "cpu_us_per_frame": cpu / len(samples) * 1e6}


def bench_pipeline(out=sys.stdout, seconds: float = 5.0) -> dict[str, float]:
    """Run every part and print the table; return the figures."""
    frames = synthetic.builtin_sequence(60)
    keys = Keys("robot")
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    fig: dict[str, float] = {}
    sizes = message_sizes(frames)
    with zenoh.open(loopback_config(endpoint, router=True)), \
            zenoh.open(loopback_config(endpoint)) as session:
        rtt = raw_round_trip(session, endpoint, 256 * 256)
        fig["raw_one_way_ms"] = float(np.median(rtt)) / 2 * 1e3
        fig["raw_one_way_p99_ms"] = float(np.percentile(rtt, 99)) / 2 * 1e3
        fig["in_process_fps"] = 1.0 / in_process(frames)
        skel_paced = skeleton(session, endpoint, sizes, fps=30, seconds=seconds)
        skel_free = skeleton(session, endpoint, sizes, fps=0, seconds=seconds)
        skel_loop = skeleton(session, endpoint, sizes, fps=0, seconds=seconds, handoff=True)
        paced = distributed(session, endpoint, keys, fps=30, seconds=seconds)
        free = distributed(session, endpoint, keys, fps=0, seconds=seconds)
    fig.update({f"skeleton_paced_{k}": v for k, v in skel_paced.items()})
    fig.update({f"skeleton_free_{k}": v for k, v in skel_free.items()})
    fig.update({f"skeleton_loop_{k}": v for k, v in skel_loop.items()})
    fig.update({f"paced_{k}": v for k, v in paced.items()})
    fig.update({f"free_{k}": v for k, v in free.items()})
    fig["hop_ratio_raw"] = paced["hop_ms"] / fig["raw_one_way_ms"]
    fig["hop_ratio_skeleton"] = paced["hop_ms"] / skel_paced["hop_ms"]
    fig["throughput_ratio_in_process"] = free["rate_hz"] / fig["in_process_fps"]
    fig["throughput_ratio_skeleton"] = free["rate_hz"] / skel_free["rate_hz"]
    fig["throughput_ratio_skeleton_loop"] = free["rate_hz"] / skel_loop["rate_hz"]
    print("# vistrack bench pipeline: 256x256 built-in frames, 5 processes over a local "
          "Zenoh router", file=out)
    print(f"# message sizes: frame {sizes[0]}, pre-processed {sizes[1]}, estimate {sizes[2]}, "
          f"command {sizes[3]} bytes", file=out)
    rows = [
        ("raw zenoh one-way, 64 KiB, back to back (median / p99)",
         f"{fig['raw_one_way_ms']:.3f} / {fig['raw_one_way_p99_ms']:.3f} ms"),
        ("raw skeleton 30 fps: capture -> estimate (median / p99)",
         f"{skel_paced['lat_p50_ms']:.2f} / {skel_paced['lat_p99_ms']:.2f} ms = "
         f"{skel_paced['hop_ms']:.3f} ms a hop"),
        ("raw skeleton unpaced: throughput",
         f"{skel_free['rate_hz']:.0f} fps, {skel_free['cpu_us_per_frame']:.0f} us of CPU a frame"),
        ("raw skeleton unpaced, RingChannel(1) loops",
         f"{skel_loop['rate_hz']:.0f} fps, {skel_loop['cpu_us_per_frame']:.0f} us of CPU a frame"),
        ("in-process stages: throughput",
         f"{fig['in_process_fps']:.0f} fps, {1e6 / fig['in_process_fps']:.0f} us of CPU a frame"),
        ("ours 30 fps: capture -> estimate (median / p99)",
         f"{paced['lat_p50_ms']:.2f} / {paced['lat_p99_ms']:.2f} ms"),
        ("ours 30 fps: stages' own processing (median)",
         f"{paced['proc_p50_ms']:.2f} ms (preprocessing {paced['pre_p50_ms']:.2f}, "
         f"motion-estimation {paced['me_p50_ms']:.2f})"),
        ("ours 30 fps: added latency per hop (median)",
         f"{paced['hop_ms']:.3f} ms = {fig['hop_ratio_skeleton']:.2f}x raw skeleton hop, "
         f"{fig['hop_ratio_raw']:.2f}x back-to-back one-way"),
        ("ours unpaced (2 in flight): throughput",
         f"{free['rate_hz']:.0f} fps = {100 * fig['throughput_ratio_in_process']:.0f} % of "
         f"in-process, {100 * fig['throughput_ratio_skeleton']:.0f} % / "
         f"{100 * fig['throughput_ratio_skeleton_loop']:.0f} % of raw skeleton (callback / "
         f"loop), {free['cpu_us_per_frame']:.0f} us of CPU a frame"),
        ("ours unpaced: frames dropped at latest-only inputs", f"{free['dropped']:.0f}"),
    ]
    for label, value in rows:
        print(f"{label:56s} {value}", file=out)
    return fig
