"""``vistrack bench pipeline``: the five-process pipeline against one process and raw Zenoh.

In one run, on this machine's loopback, through one local Zenoh router as ``vistrack up`` runs:

1. raw Zenoh round trip: a frame-sized payload (256x256 bytes) between this process and an echo
   peer process (plain zenoh, no project code), back to back; one-way = round trip / 2;
2. in-process: the same stages (pre-processing, tracking, controller) on the same frames, one
   after the other in one process: the throughput ceiling without any messaging;
3. the raw Zenoh skeleton: five plain-zenoh processes (no project code, no work) wired like the
   pipeline, each passing on a payload of the size ours sends (camera 64 KiB -> pre-processing
   75 KiB -> motion-estimation 1 KiB -> controller; the auto-tuner takes every estimate and,
   as ours does between tunings, one frame every 0.2 s, subscribing again for each).
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
   the services);
6. ours unpaced without the auto-tuner: what it costs the whole pipeline (its own process, the
   router's fan-out, the contention for the two cores), against what its own process spends;
7. the CPU a frame of ours unpaced against the skeleton's loops plus the stages in one process,
   in :data:`RATIO_ROUNDS` interleaved rounds of those three runs: the median and the range.

The auto-tuner runs as deployed, and each run is measured once its initial tuning is over:
between tunings (nearly all of a run's life) it takes every estimate and a frame every
``SCENE_SAMPLE_S`` for its scene signal; its experiments, at idle priority in a worker process
whose CPU is not counted, would take a core for seconds.
"""

from __future__ import annotations

import collections
import dataclasses
import math
import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from typing import TextIO

import numpy as np
import zenoh

from ...common import synthetic
from ...common.bus import alive_services, loopback_config, query_status
from ...common.keys import Keys
from ...common.messages import (
    NO_CANDIDATES,
    NO_STRENGTH,
    Estimate,
    Frame,
    PreFrame,
    encode_cmd_vel,
    encode_frame,
    encode_pre_frame,
    peek_int,
)
from ...common.params import TrackerParams
from ...common.sources import GeneratedFrames
from ...common.vision import Preprocessed, Tracker, preprocess, warm_up
from ...common.vision.preprocess import DeferredPreprocessed
from ..fuzzy_controller.control import FuzzyController, FuzzySurface
from ..motion_estimation.service import READ_WINDOW, estimate_payload, wants_candidates
from .messages import pipeline_messages

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
# prescribes for frames (ours: Zenoh's thread queues the sample, the loop takes it in); the
# camera puts frames at FPS, or (FPS 0) with two in flight.
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
        receive(s, "est", lambda payload: None)
        def sample():  # one frame, then none for 0.2 s: the subscription declared for each
            while True:
                got = threading.Event()
                sub = s.declare_subscriber("bench/skel/frame",
                                           lambda smp: (smp.payload.to_bytes(), got.set()))
                got.wait()
                sub.undeclare()
                time.sleep(0.2)
        threading.Thread(target=sample, daemon=True).start()
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
#: The bench process itself: the embedded Zenoh router every message goes through, and the
#: collector of estimates.
ROUTER = "router+collector"
#: The processes of a run, in the pipeline's order (the CPU table's rows).
PROCESSES = ("camera", "preprocessing", "motion-estimation", "fuzzy-controller", "auto-tuner",
             ROUTER)


def _slug(name: str) -> str:
    """A process name as a figure key: ``motion-estimation`` -> ``motion_estimation``."""
    return name.replace("-", "_").replace("+", "_")


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


#: Zenoh's runtime threads by name prefix (zenoh 1.x names its tokio pools): ``rx`` reads the
#: links and runs subscriber callbacks (ours only queue the sample for the loop),
#: ``tx`` writes them; ``net``, ``acc``, ``app`` and the rest are its other pools.
ZENOH_THREADS = ("rx", "tx")
#: Where a process's CPU goes, in the order printed: the Python loop (a service's main thread,
#: a skeleton node's loop threads), Zenoh's receiving and sending threads, everything else.
THREAD_GROUPS = ("loop", "rx", "tx", "other")


def _thread_ticks(pid: int) -> dict[int, tuple[str, int]]:
    """tid -> (thread group, user + system clock ticks so far) of every thread of ``pid``."""
    out: dict[int, tuple[str, int]] = {}
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except FileNotFoundError:
        return out
    for tid in tids:
        try:
            with open(f"/proc/{pid}/task/{tid}/stat") as f:
                text = f.read()
        except (FileNotFoundError, ProcessLookupError):
            continue  # the thread ended meanwhile
        comm = text[text.index("(") + 1:text.rindex(")")]
        fields = text.rsplit(")", 1)[1].split()
        zenoh_pool = comm.split("-")[0] in ("rx", "tx", "net", "acc", "app")
        group = next((g for g in ZENOH_THREADS if comm.startswith(g + "-")),
                     "other" if zenoh_pool else "loop")
        out[int(tid)] = (group, int(fields[11]) + int(fields[12]))
    return out


class CpuMeter:
    """CPU of named processes between :meth:`start` and :meth:`stop`, by thread group, read
    from /proc (no instrumentation in the processes measured)."""

    def __init__(self, pids: dict[str, int]) -> None:
        self.pids = pids
        self._t0: dict[str, dict[int, tuple[str, int]]] = {}
        self.seconds: dict[str, dict[str, float]] = {}

    def start(self) -> None:
        self._t0 = {name: _thread_ticks(pid) for name, pid in self.pids.items()}

    def stop(self) -> None:
        tick = 1.0 / os.sysconf("SC_CLK_TCK")
        for name, pid in self.pids.items():
            groups = dict.fromkeys(THREAD_GROUPS, 0.0)
            before = self._t0.get(name, {})
            for tid, (group, ticks) in _thread_ticks(pid).items():
                groups[group] += (ticks - before.get(tid, (group, 0))[1]) * tick
            self.seconds[name] = groups

    def per_frame_us(self, frames: int) -> dict[str, dict[str, float]]:
        """Process -> thread group -> us of CPU a frame (and ``total``)."""
        return {name: {**{g: v / frames * 1e6 for g, v in groups.items()},
                       "total": sum(groups.values()) / frames * 1e6}
                for name, groups in self.seconds.items()}


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


def _wait_tuned(session: zenoh.Session, keys: Keys, timeout: float) -> None:
    """Wait until the auto-tuner's initial tuning is over (done or skipped)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for s in query_status(session, keys, timeout=0.5):
            extra = s.get("extra", {})
            if (s.get("service") == "auto_tuner" and not extra.get("tuning")
                    and extra.get("tunings", 0) + extra.get("skipped", 0) >= 1):
                return
        time.sleep(0.1)
    raise RuntimeError(f"the auto-tuner's initial tuning not over after {timeout} s")


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
    encoded as the services encode them; the pre-processed frame as most go out, deferred
    (without candidates: see ``motion/demand``)."""
    frame, pre, est, cmd = pipeline_messages(frames)
    deferred = dataclasses.replace(pre, candidates=NO_CANDIDATES, strength=NO_STRENGTH,
                                   deferred=True)
    return len(frame.encode()), len(deferred.encode()), len(est.encode()), len(cmd.encode())


#: The parts of a loop's work per frame that :func:`stage_costs` times.
PARTS = ("decode", "work", "encode")


def stage_costs(frames: list[np.ndarray], passes: int = 3) -> dict[str, dict[str, float]]:
    """us a frame of what each process's loop does with a frame, timed here (median over the
    frames, best of ``passes``) rather than inside the services, which would perturb the run:
    process -> ``decode`` (and validate its inputs), ``work`` (its computation), ``encode``
    (build, validate and encode its output). The camera's work (reading its source) is not
    timed; the auto-tuner's is none (its decode: an estimate; between tunings it takes a
    frame only every ``SCENE_SAMPLE_S``, nothing a frame).
    Pre-processing computes the candidates of a frame only when motion-estimation's
    ``motion/demand`` asks for them (as the services do by default), else sends it deferred."""
    warm_up()
    params = TrackerParams()
    ctrl = FuzzyController(FuzzySurface.compile())
    best: dict[str, dict[str, float]] = {}
    times: dict[tuple[str, str], list[float]] = {}

    def lap(proc: str, part: str, t0: float) -> float:
        """Record the time since ``t0`` as ``proc``'s ``part``; the time now."""
        now = time.perf_counter()
        times.setdefault((proc, part), []).append((now - t0) * 1e6)
        return time.perf_counter()

    for p in range(passes):
        tracker = Tracker(params)
        redetected: collections.deque[bool] = collections.deque(maxlen=READ_WINDOW)
        wanted = True
        times.clear()
        for k, f in enumerate(frames):
            stamp = time.time_ns()
            t = time.perf_counter()
            payload = encode_frame(f, seq=k, stamp_ns=stamp)
            t = lap("camera", "encode", t)
            frame = Frame.decode(payload)
            t = lap("preprocessing", "decode", t)
            pre = preprocess(frame.data, params)
            cands = (pre.candidates, pre.strength) if wanted else (NO_CANDIDATES, NO_STRENGTH)
            t = lap("preprocessing", "work", t)
            pre_payload = encode_pre_frame(seq=k, stamp_ns=stamp, data=pre.filtered,
                                           candidates=cands[0], strength=cands[1],
                                           params_id=0, deferred=not wanted)
            t = lap("preprocessing", "encode", t)
            pre_msg = PreFrame.decode(pre_payload)
            t = lap("motion-estimation", "decode", t)
            filtered = np.array(pre_msg.data)
            before = tracker.redetections
            est = tracker.update(
                DeferredPreprocessed(filtered, params) if pre_msg.deferred
                else Preprocessed(filtered, pre_msg.candidates, pre_msg.strength))
            redetected.append(tracker.redetections > before)
            wanted = wants_candidates(est.npi, redetected, params)
            t = lap("motion-estimation", "work", t)
            est_payload = estimate_payload(est, seq=k, stamp_ns=stamp, params_id=0)
            t = lap("motion-estimation", "encode", t)
            e = Estimate.decode(est_payload)
            t = lap("fuzzy-controller", "decode", t)
            ctrl.update(e.xc, e.scale, k / 30.0 + 1.0 + 100 * p, frame.width, npi=e.npi)
            t = lap("fuzzy-controller", "work", t)
            encode_cmd_vel(seq=k, stamp_ns=stamp, vx=0.1, vy=-0.1, wz=0.0)
            t = lap("fuzzy-controller", "encode", t)
            Estimate.decode(est_payload)
            lap("auto-tuner", "decode", t)
        for (proc, part), ts in times.items():
            row = best.setdefault(proc, {})
            row[part] = min(row.get(part, math.inf), float(np.median(ts)))
    return best


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
        pids = {ROUTER: os.getpid()}  # the router and this collector
        for role in (*SERVICES, "camera"):
            pids[role] = stack.enter_context(_process(
                [sys.executable, "-c", SKELETON_NODE, role, endpoint, f"{fps:g}",
                 str(int(handoff)), *size_args],
                stdin=True, ready_line=True)).pid
        time.sleep(1.0)  # steady state
        sub = session.declare_subscriber("bench/skel/est", on)
        meter = CpuMeter(pids)
        meter.start()
        time.sleep(seconds)  # a measurement window, not synchronisation
        meter.stop()
        sub.undeclare()
    if len(stamps) < 10:
        raise RuntimeError(f"raw zenoh skeleton: only {len(stamps)} estimates in {seconds} s")
    lat = np.array([(t - s) * 1e-6 for t, s in stamps])
    per = meter.per_frame_us(len(stamps))
    return {"rate_hz": len(stamps) / seconds, "lat_p50_ms": float(np.median(lat)),
            "lat_p99_ms": float(np.percentile(lat, 99)), "hop_ms": float(np.median(lat)) / 3,
            "cpu_us_per_frame": sum(p["total"] for p in per.values()),
            **{f"cpu_{_slug(n)}_{g}": v for n, groups in per.items() for g, v in groups.items()}}


def _collect_estimates(session: zenoh.Session, keys: Keys, seconds: float
                       ) -> list[tuple[int, int, int]]:
    """(arrival, capture stamp) in ns, and ``seq``, of every estimate during ``seconds``."""
    out: list[tuple[int, int, int]] = []

    def on(sample: zenoh.Sample) -> None:
        t = time.time_ns()
        payload = sample.payload.to_bytes()
        out.append((t, peek_int(payload, "stamp_ns") or t, peek_int(payload, "seq") or 0))

    sub = session.declare_subscriber(keys.estimate, on)
    time.sleep(seconds)  # a measurement window, not synchronisation
    sub.undeclare()
    return out


def distributed(session: zenoh.Session, endpoint: str, keys: Keys, *, fps: float,
                seconds: float, size: str | None = None, tuner: bool = True
                ) -> dict[str, float]:
    """Run camera + four services for ``seconds``; latency and rate figures. ``size``
    (``WxH``): the built-in frames resized to it, else 256x256. ``tuner=False``: without
    the auto-tuner (what it costs the whole pipeline); with it, the run is measured once its
    initial tuning is over."""
    with ExitStack() as stack:
        pids = {ROUTER: os.getpid()}  # the router and this collector
        names = SERVICES if tuner else tuple(n for n in SERVICES if n != "auto-tuner")
        for name in names:
            pids[name] = stack.enter_context(_process(_vistrack(name, endpoint))).pid
        _wait_alive(session, keys, {n.replace("-", "_") for n in names}, 60)
        pids["camera"] = stack.enter_context(_process(_vistrack(
            "camera", endpoint, "--source", "builtin", "--loop", "--fps", f"{fps:g}",
            "--in-flight", "2", *(("--size", size) if size else ())))).pid
        _wait_alive(session, keys, {"camera"}, 30)
        time.sleep(1.0)  # let the first-frame work (feature selection) pass: steady state
        if tuner:  # and the initial tuning, which takes every frame until it starts
            _wait_tuned(session, keys, 120)
        meter = CpuMeter(pids)
        meter.start()
        samples = _collect_estimates(session, keys, seconds)
        meter.stop()
        status = {s["service"]: s for s in query_status(session, keys, timeout=2.0)}
    if len(samples) < 10:
        raise RuntimeError(f"only {len(samples)} estimates in {seconds} s")
    lat = np.array([(t - stamp) * 1e-6 for t, stamp, _ in samples])
    # the camera replays the built-in sequence: its frames 0 and 1 follow the jump back from
    # its last frame (a scene cut every LOOP_FRAMES / fps s, see LOOP_FRAMES)
    steady = np.array([seq % LOOP_FRAMES > 1 for _, _, seq in samples])
    pre = status.get("preprocessing", {})
    me = status.get("motion_estimation", {})
    proc_ms = (pre.get("p50_ms") or 0.0) + (me.get("p50_ms") or 0.0)
    per = meter.per_frame_us(len(samples))
    return {"rate_hz": len(samples) / seconds, "frames": float(len(samples)),
            "pre_p50_ms": pre.get("p50_ms") or 0.0,
            "me_p50_ms": me.get("p50_ms") or 0.0, "lat_p50_ms": float(np.median(lat)),
            "lat_p99_ms": float(np.percentile(lat, 99)), "proc_p50_ms": proc_ms,
            "lat_p99_steady_ms": float(np.percentile(lat[steady], 99)),
            "lat_p99_wrap_ms": float(np.percentile(lat[~steady], 99)) if (~steady).any()
            else math.nan,
            "hop_ms": (float(np.median(lat)) - proc_ms) / 3.0,
            "dropped": float(pre.get("dropped", 0) + me.get("dropped", 0)),
            "cpu_us_per_frame": sum(p["total"] for p in per.values()),
            **{f"cpu_{_slug(n)}_{g}": v for n, groups in per.items() for g, v in groups.items()}}


#: Frames of the built-in sequence the camera replays: each replay starts with a jump back
#: from its last frame (~8 px and a 2 % zoom against the motion predicted), and the frame after
#: the jump follows a prediction the jump made (a full search of every feature, ~10 times a
#: held frame's work); 2 frames in 60, so they alone make the p99 of a run
LOOP_FRAMES = GeneratedFrames().n
#: Seconds of each run at 30 fps: its p99 latency is then that of 600 frames (over 150, the
#: 5 s of the unpaced runs, a p99 was the second-worst frame: at 1280x720 it came out 13.4 or
#: 17.0 ms from one run to the next, wherever the looping sequence's jumps fell).
PACED_S = 20.0


def cpu_ratio(ours_us: float, skeleton_loops_us: float, in_process_s: float) -> float:
    """CPU a frame of ours against what it cannot go below: the bare relay of the same
    messages (receiving from loops) plus the same work in one process (s a frame)."""
    return ours_us / (skeleton_loops_us + 1e6 * in_process_s)


#: Rounds of the CPU ratio's three runs (ours unpaced, the skeleton's loops, the stages in one
#: process), interleaved: on this shared VM one round's ratio came out anywhere from 1.2 to
#: 3.3x within an hour, the peers moving as much as ours; the median of the rounds is the
#: figure, their range beside it.
RATIO_ROUNDS = 3


def bench_pipeline(out: TextIO = sys.stdout, seconds: float = 5.0,
                   paced_seconds: float = PACED_S,
                   rounds: int = RATIO_ROUNDS) -> dict[str, float]:
    """Run every part and print the table; return the figures. ``seconds``: each unpaced
    run; ``paced_seconds``: each run at 30 fps (its latency percentiles); ``rounds``: of the
    CPU ratio's runs (the first round's are the figures of the table)."""
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
        skel_paced = skeleton(session, endpoint, sizes, fps=30, seconds=paced_seconds)
        skel_free = skeleton(session, endpoint, sizes, fps=0, seconds=seconds)
        skel_loop = skeleton(session, endpoint, sizes, fps=0, seconds=seconds, handoff=True)
        paced = distributed(session, endpoint, keys, fps=30, seconds=paced_seconds)
        paced_720 = distributed(session, endpoint, keys, fps=30, seconds=paced_seconds,
                                size="1280x720")
        free = distributed(session, endpoint, keys, fps=0, seconds=seconds)
        free_alone = distributed(session, endpoint, keys, fps=0, seconds=seconds, tuner=False)
        ratios = [cpu_ratio(free["cpu_us_per_frame"], skel_loop["cpu_us_per_frame"],
                            1.0 / fig["in_process_fps"])]
        for _ in range(rounds - 1):
            mine = distributed(session, endpoint, keys, fps=0, seconds=seconds)["cpu_us_per_frame"]
            peer = skeleton(session, endpoint, sizes, fps=0, seconds=seconds,
                            handoff=True)["cpu_us_per_frame"]
            ratios.append(cpu_ratio(mine, peer, in_process(frames)))
    fig.update({f"skeleton_paced_{k}": v for k, v in skel_paced.items()})
    fig.update({f"skeleton_free_{k}": v for k, v in skel_free.items()})
    fig.update({f"skeleton_loop_{k}": v for k, v in skel_loop.items()})
    fig.update({f"paced_{k}": v for k, v in paced.items()})
    fig.update({f"paced_720_{k}": v for k, v in paced_720.items()})
    fig.update({f"free_{k}": v for k, v in free.items()})
    fig.update({f"free_no_tuner_{k}": v for k, v in free_alone.items()})
    # what the auto-tuner costs the whole pipeline between tunings (its process, the
    # router's fan-out, the other processes' share of two cores), beside what its own process
    # spends
    fig["tuner_cost_us_per_frame"] = (free["cpu_us_per_frame"]
                                      - free_alone["cpu_us_per_frame"])
    fig["hop_ratio_raw"] = paced["hop_ms"] / fig["raw_one_way_ms"]
    fig["hop_ratio_skeleton"] = paced["hop_ms"] / skel_paced["hop_ms"]
    fig["throughput_ratio_in_process"] = free["rate_hz"] / fig["in_process_fps"]
    fig["throughput_ratio_skeleton"] = free["rate_hz"] / skel_free["rate_hz"]
    fig["throughput_ratio_skeleton_loop"] = free["rate_hz"] / skel_loop["rate_hz"]
    fig["cpu_ratio_skeleton_loop_plus_in_process"] = ratios[0]  # the table's round
    fig["cpu_ratio_rounds"] = float(len(ratios))
    fig["cpu_ratio_median"] = float(np.median(ratios))
    fig["cpu_ratio_min"], fig["cpu_ratio_max"] = float(min(ratios)), float(max(ratios))
    print("# vistrack bench pipeline: 256x256 built-in frames, 5 processes over a local "
          "Zenoh router", file=out)
    print(f"# message sizes: frame {sizes[0]}, pre-processed {sizes[1]} (deferred, as most go "
          f"out), estimate {sizes[2]}, command {sizes[3]} bytes", file=out)
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
         f"{paced['lat_p50_ms']:.2f} / {paced['lat_p99_ms']:.2f} ms "
         f"({paced['frames']:.0f} frames)"),
        ("ours 30 fps: p99 of the frames after a jump / of the others",
         f"{paced['lat_p99_wrap_ms']:.2f} / {paced['lat_p99_steady_ms']:.2f} ms (the replay's "
         f"wrap, 2 frames in {LOOP_FRAMES}: 1280x720 {paced_720['lat_p99_wrap_ms']:.2f} / "
         f"{paced_720['lat_p99_steady_ms']:.2f} ms)"),
        ("ours 30 fps, 1280x720: capture -> estimate (median / p99)",
         f"{paced_720['lat_p50_ms']:.2f} / {paced_720['lat_p99_ms']:.2f} ms "
         f"({paced_720['frames']:.0f} frames; stages' own processing "
         f"{paced_720['proc_p50_ms']:.2f} ms)"),
        ("ours 30 fps: stages' own processing (median)",
         f"{paced['proc_p50_ms']:.2f} ms (preprocessing {paced['pre_p50_ms']:.2f}, "
         f"motion-estimation {paced['me_p50_ms']:.2f})"),
        ("ours 30 fps: added latency per hop (median)",
         f"{paced['hop_ms']:.3f} ms = {fig['hop_ratio_skeleton']:.2f}x raw skeleton hop, "
         f"{fig['hop_ratio_raw']:.2f}x back-to-back one-way"),
        ("ours 30 fps: median = stages' medians + the rest",
         f"256x256 {paced['proc_p50_ms']:.2f} {3 * paced['hop_ms']:+.2f} ms, 1280x720 "
         f"{paced_720['proc_p50_ms']:.2f} {3 * paced_720['hop_ms']:+.2f} ms (the rest: "
         f"messaging and wake-ups; raw skeleton's, no work: {skel_paced['lat_p50_ms']:.2f})"),
        ("ours unpaced (2 in flight): throughput",
         f"{free['rate_hz']:.0f} fps = {100 * fig['throughput_ratio_in_process']:.0f} % of "
         f"in-process, {100 * fig['throughput_ratio_skeleton']:.0f} % / "
         f"{100 * fig['throughput_ratio_skeleton_loop']:.0f} % of raw skeleton (callback / "
         f"loop), {free['cpu_us_per_frame']:.0f} us of CPU a frame"),
        ("ours unpaced: frames dropped at latest-only inputs", f"{free['dropped']:.0f}"),
        ("ours unpaced without the auto-tuner",
         f"{free_alone['rate_hz']:.0f} fps, {free_alone['cpu_us_per_frame']:.0f} us of CPU a "
         f"frame: the auto-tuner (between tunings) costs the pipeline "
         f"{fig['tuner_cost_us_per_frame']:+.0f} us a frame, its own process "
         f"{free['cpu_auto_tuner_total']:.0f}"),
        ("ours unpaced: CPU a frame / (skeleton loops + in-process)",
         f"{free['cpu_us_per_frame']:.0f} / ({skel_loop['cpu_us_per_frame']:.0f} + "
         f"{1e6 / fig['in_process_fps']:.0f}) us = "
         f"{fig['cpu_ratio_skeleton_loop_plus_in_process']:.2f}x"),
        (f"the same ratio, median of {len(ratios)} interleaved rounds",
         f"{fig['cpu_ratio_median']:.2f}x (rounds {', '.join(f'{r:.2f}' for r in ratios)})"),
    ]
    for label, value in rows:
        print(f"{label:56s} {value}", file=out)
    costs = stage_costs(frames)
    fig.update({f"stage_{_slug(n)}_{k}_us": v for n, parts in costs.items()
                for k, v in parts.items()})
    print_cpu_table(fig, costs, out)
    return fig


def print_cpu_table(fig: dict[str, float], costs: dict[str, dict[str, float]],
                    out: TextIO) -> None:
    """Where each process's CPU goes, unpaced: ours against the skeleton's same process."""
    print("\n# where the CPU goes, unpaced, us a frame (per estimate delivered); from /proc, by "
          "thread: loop = the Python loop (a service's main thread; the skeleton's loop "
          "threads), rx = Zenoh's link readers, which run the subscriber callbacks (our "
          "queuing of each sample for the loop), tx = its writers, other = its other pools; "
          "decode / work / encode = the loop's parts timed in this process on the same "
          "frames, rest = loop minus those (taking samples in, publishing, status "
          "counting, the loop itself)", file=out)
    print(f"{'process':18s}{'ours':>7s}{'skeleton':>9s}{'extra':>7s}  |{'loop':>6s}{'decode':>8s}"
          f"{'work':>7s}{'encode':>8s}{'rest':>7s}  |{'rx':>6s}{'tx':>6s}{'other':>7s}  "
          f"| skeleton:{'loop':>6s}{'rx':>6s}{'tx':>6s}{'other':>7s}", file=out)
    sums = dict.fromkeys(("ours", "skel", "decode", "work", "encode"), 0.0)
    for name in PROCESSES:
        ours = {g: fig.get(f"free_cpu_{_slug(name)}_{g}", 0.0) for g in (*THREAD_GROUPS, "total")}
        skel = {g: fig.get(f"skeleton_loop_cpu_{_slug(name)}_{g}", 0.0)
                for g in (*THREAD_GROUPS, "total")}
        part = {k: costs.get(name, {}).get(k, 0.0) for k in PARTS}
        rest = ours["loop"] - sum(part.values())
        for k in PARTS:
            sums[k] += part[k]
        sums["ours"] += ours["total"]
        sums["skel"] += skel["total"]
        timed = costs.get(name, {})
        cells = "".join(f"{part[k]:{w}.0f}" if k in timed else f"{'-':>{w}s}"
                        for k, w in (("decode", 8), ("work", 7), ("encode", 8)))
        print(f"{name:18s}{ours['total']:7.0f}{skel['total']:9.0f}"
              f"{ours['total'] - skel['total']:+7.0f}  |{ours['loop']:6.0f}{cells}"
              f"{rest:7.0f}  |{ours['rx']:6.0f}{ours['tx']:6.0f}{ours['other']:7.0f}  "
              f"|          {skel['loop']:6.0f}{skel['rx']:6.0f}{skel['tx']:6.0f}"
              f"{skel['other']:7.0f}", file=out)
    print(f"{'all processes':18s}{sums['ours']:7.0f}{sums['skel']:9.0f}"
          f"{sums['ours'] - sums['skel']:+7.0f}  |{'':6s}{sums['decode']:8.0f}"
          f"{sums['work']:7.0f}{sums['encode']:8.0f}", file=out)
