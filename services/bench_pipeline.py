"""``vistrack bench pipeline``: the five-process pipeline against one process and raw Zenoh.

In one run, on this machine's loopback:

1. raw Zenoh: round trip of a frame-sized payload (256x256 bytes) between this process and an
   echo peer process (plain zenoh, no project code), so one-way = round trip / 2;
2. in-process: the same stages (pre-processing, tracking, controller) on the same frames, one
   after the other in one process: the throughput ceiling;
3. distributed, 30 fps: the camera service paced at 30 fps through preprocessing,
   motion-estimation, auto-tuner and fuzzy-controller processes; latency from capture
   (``stamp_ns``) to ``motion/estimate`` arriving here, median and p99, and the added latency
   per hop (end to end minus the stages' own processing time, over the three hops
   camera -> preprocessing -> motion-estimation -> here);
4. distributed, unpaced: the camera free-running (``--fps 1000``): estimates per second, and the
   frames dropped at the latest-only inputs (counted by the services).
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager

import msgpack
import numpy as np
import zenoh

from ..common import synthetic
from ..common.bus import alive_services, query_status
from ..common.keys import Keys
from ..common.params import TrackerParams
from ..common.vision import Tracker, preprocess, warm_up
from .fuzzy_controller.control import FuzzyController, FuzzySurface

ECHO_PEER = """
import json, sys, time, zenoh
c = zenoh.Config()
c.insert_json5("connect/endpoints", json.dumps([sys.argv[1]]))
c.insert_json5("scouting/multicast/enabled", "false")
with zenoh.open(c) as s:
    pub = s.declare_publisher("bench/pong")
    sub = s.declare_subscriber("bench/ping", lambda smp: pub.put(smp.payload))
    print("ready", flush=True)
    sys.stdin.read()
"""

SERVICES = ("fuzzy-controller", "motion-estimation", "preprocessing", "auto-tuner")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _conf(endpoint: str, *, router: bool = False) -> zenoh.Config:
    c = zenoh.Config()
    if router:
        c.insert_json5("mode", '"router"')
        c.insert_json5("listen/endpoints", json.dumps([endpoint]))
    else:
        c.insert_json5("connect/endpoints", json.dumps([endpoint]))
    c.insert_json5("scouting/multicast/enabled", "false")
    return c


@contextmanager
def _process(args: list[str], *, stdin: bool = False) -> Iterator[subprocess.Popen]:
    p = subprocess.Popen(args, stdin=subprocess.PIPE if stdin else subprocess.DEVNULL,
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, text=True)
    try:
        yield p
    finally:
        if p.poll() is None:
            p.terminate()
            try:
                p.wait(5)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


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
            ctrl.update(est.xc, est.scale, k / 30.0 + 1.0 + _ * 100, f.shape[1], npi=est.npi)
        best = min(best, (time.perf_counter() - t0) / len(frames))
    return best


def _collect_estimates(session: zenoh.Session, keys: Keys, seconds: float
                       ) -> list[tuple[float, dict]]:
    out: list[tuple[float, dict]] = []
    lock = threading.Lock()

    def on(sample: zenoh.Sample) -> None:
        t = time.time_ns()
        with lock:
            out.append((t, msgpack.unpackb(sample.payload.to_bytes())))

    sub = session.declare_subscriber(keys.estimate, on)
    time.sleep(seconds)  # a measurement window, not synchronisation
    sub.undeclare()
    return out


def distributed(session: zenoh.Session, endpoint: str, keys: Keys, *, fps: float,
                seconds: float) -> dict[str, float]:
    """Run camera + four services for ``seconds``; latency and rate figures."""
    with ExitStack() as stack:
        for name in SERVICES:
            # the tuner buffers every frame but runs no experiment: its worker would take the
            # CPU the pipeline is being measured on
            extra = ("--no-tune",) if name == "auto-tuner" else ()
            stack.enter_context(_process(_vistrack(name, endpoint, *extra)))
        _wait_alive(session, keys, {"preprocessing", "motion_estimation", "auto_tuner",
                                    "fuzzy_controller"}, 60)
        stack.enter_context(_process(_vistrack("camera", endpoint, "--source", "builtin",
                                               "--loop", "--fps", f"{fps:g}")))
        _wait_alive(session, keys, {"camera"}, 30)
        time.sleep(1.0)  # let the first-frame work (feature selection) pass: steady state
        samples = _collect_estimates(session, keys, seconds)
        status = {s["service"]: s for s in query_status(session, keys, timeout=2.0)}
    if len(samples) < 10:
        raise RuntimeError(f"only {len(samples)} estimates in {seconds} s")
    lat = np.array([(t - m["stamp_ns"]) * 1e-6 for t, m in samples])
    pre = status.get("preprocessing", {})
    me = status.get("motion_estimation", {})
    proc_ms = (pre.get("p50_ms") or 0.0) + (me.get("p50_ms") or 0.0)
    return {"rate_hz": len(samples) / seconds, "pre_p50_ms": pre.get("p50_ms") or 0.0,
            "me_p50_ms": me.get("p50_ms") or 0.0, "lat_p50_ms": float(np.median(lat)),
            "lat_p99_ms": float(np.percentile(lat, 99)), "proc_p50_ms": proc_ms,
            "hop_ms": (float(np.median(lat)) - proc_ms) / 3.0,
            "dropped": float(pre.get("dropped", 0) + me.get("dropped", 0))}


def bench_pipeline(out=sys.stdout, seconds: float = 5.0) -> dict[str, float]:
    """Run every part and print the table; return the figures."""
    frames = synthetic.builtin_sequence(60)
    keys = Keys("robot")
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    fig: dict[str, float] = {}
    with zenoh.open(_conf(endpoint, router=True)), zenoh.open(_conf(endpoint)) as session:
        rtt = raw_round_trip(session, endpoint, 256 * 256)
        fig["raw_one_way_ms"] = float(np.median(rtt)) / 2 * 1e3
        fig["raw_one_way_p99_ms"] = float(np.percentile(rtt, 99)) / 2 * 1e3
        fig["in_process_fps"] = 1.0 / in_process(frames)
        paced = distributed(session, endpoint, keys, fps=30, seconds=seconds)
        free = distributed(session, endpoint, keys, fps=1000, seconds=seconds)
    fig.update({f"paced_{k}": v for k, v in paced.items()})
    fig.update({f"free_{k}": v for k, v in free.items()})
    print("# vistrack bench pipeline: 256x256 built-in frames, 5 processes over a local "
          "Zenoh router", file=out)
    rows = [
        ("raw zenoh one-way, 64 KiB (median / p99)",
         f"{fig['raw_one_way_ms']:.3f} / {fig['raw_one_way_p99_ms']:.3f} ms"),
        ("in-process stages: throughput", f"{fig['in_process_fps']:.0f} fps"),
        ("30 fps: capture -> estimate (median / p99)",
         f"{paced['lat_p50_ms']:.2f} / {paced['lat_p99_ms']:.2f} ms"),
        ("30 fps: stages' own processing (median)",
         f"{paced['proc_p50_ms']:.2f} ms (preprocessing {paced['pre_p50_ms']:.2f}, "
         f"motion-estimation {paced['me_p50_ms']:.2f})"),
        ("30 fps: added latency per hop (median)",
         f"{paced['hop_ms']:.3f} ms = {paced['hop_ms'] / fig['raw_one_way_ms']:.2f}x raw"),
        ("unpaced: distributed throughput", f"{free['rate_hz']:.0f} fps = "
         f"{free['rate_hz'] / fig['in_process_fps'] * 100:.0f} % of in-process"),
        ("unpaced: frames dropped at latest-only inputs", f"{free['dropped']:.0f}"),
    ]
    for label, value in rows:
        print(f"{label:48s} {value}", file=out)
    return fig
