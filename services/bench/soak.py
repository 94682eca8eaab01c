"""``vistrack bench soak``: the full pipeline as fast as it goes, for a minute.

A file camera (the built-in 256x256 sequence written as PNG files, looped from memory) at
``--fps 0 --in-flight 2`` feeds preprocessing, motion-estimation, the auto-tuner (tuning as
it would: its first tuning and any scene change) and the fuzzy-controller, each a process on
one local Zenoh router, for 60 s. Measured:

* every service's resident memory (``VmRSS`` from /proc) after 10 s and at the end, and the
  tuning worker's; the target is every service's end within 5 % of its 10 s figure;
* the loss accounting once the camera has stopped and the pipeline has drained: frames the
  camera sent, estimates motion-estimation published, frames counted as dropped (overwritten
  at a latest-only input, or a gap in ``seq``) by preprocessing and motion-estimation; what
  is neither estimated nor counted is lost (target 0), and nothing may be rejected or failed.

The peer, as in ``vistrack bench pipeline``, is the rate: frames a second through the whole
pipeline against the same stages in one process.
"""

from __future__ import annotations

import re
import signal
import subprocess
import sys
import tempfile
import time
from contextlib import ExitStack
from pathlib import Path
from typing import TextIO

import cv2
import zenoh

from ...common import synthetic
from ...common.bus import alive_services, loopback_config, query_status
from ...common.keys import Keys
from .launched import free_port, rss_kib, tuning_worker

SERVICES = ("preprocessing", "motion-estimation", "auto-tuner", "fuzzy-controller")
RSS_TOLERANCE = 0.05
FIRST_SAMPLE_S = 10.0


def _start(name: str, endpoint: str, log: Path, *extra: str) -> subprocess.Popen:
    # the child writes to its own copy of the log's descriptor: ours is closed at once (left
    # open, it was an unclosed file for each service, which pytest -m bench reported)
    with log.open("w") as out:
        return subprocess.Popen([sys.executable, "-m", "vistrack.services.cli", name, "-e",
                                 endpoint, "--no-multicast-scouting", *extra],
                                stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT)


def _wait_alive(session: zenoh.Session, keys: Keys, names: set[str], timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while not names <= set(alive_services(session, keys, timeout=0.5)):
        if time.monotonic() > deadline:
            raise RuntimeError(f"not alive after {timeout} s: {sorted(names)}")
        time.sleep(0.2)


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def bench_soak(out: TextIO = sys.stdout, seconds: float = 60.0) -> dict[str, float]:
    """Run the soak and print the table; return the figures."""
    keys = Keys("robot")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with tempfile.TemporaryDirectory() as tmp, ExitStack() as stack:
        frames = Path(tmp) / "frames"
        frames.mkdir()
        for i, image in enumerate(synthetic.builtin_sequence(60)):
            cv2.imwrite(str(frames / f"{i:03d}.png"), image)
        logs = {name: Path(tmp) / f"{name}.log" for name in (*SERVICES, "camera")}
        stack.enter_context(zenoh.open(loopback_config(endpoint, router=True)))
        session = stack.enter_context(zenoh.open(loopback_config(endpoint)))
        procs = {name: _start(name, endpoint, logs[name]) for name in SERVICES}
        for proc in procs.values():
            stack.callback(_stop, proc)
        _wait_alive(session, keys, {n.replace("-", "_") for n in SERVICES}, 120)
        time.sleep(2.0)  # subscribed after their liveliness tokens: let them warm up
        camera = _start("camera", endpoint, logs["camera"], "--source", f"file:{frames}",
                        "--loop", "--fps", "0", "--in-flight", "2")
        stack.callback(_stop, camera)
        _wait_alive(session, keys, {"camera"}, 60)
        t0 = time.monotonic()
        worker: int | None = None
        samples: dict[str, list[tuple[float, int]]] = {n: [] for n in SERVICES}
        while time.monotonic() - t0 < seconds:
            now = time.monotonic() - t0
            for name, proc in procs.items():
                if proc.poll() is None:
                    samples[name].append((now, rss_kib(proc.pid)))
            worker = worker or tuning_worker(procs["auto-tuner"].pid)
            if worker:
                samples.setdefault("tuning worker", []).append((now, rss_kib(worker)))
            time.sleep(1.0)  # the sampling period of a measurement, not synchronisation
        exits = {name: proc.poll() for name, proc in procs.items()}
        _stop(camera)
        # drained when motion-estimation's count stops moving
        last, stable_since = -1, time.monotonic()
        while time.monotonic() - stable_since < 1.0:
            status = {s["service"]: s for s in query_status(session, keys, timeout=2.0)}
            published = status["motion_estimation"]["published"]
            if published != last:
                last, stable_since = published, time.monotonic()
            time.sleep(0.2)
        camera_log = logs["camera"].read_text()
    m = re.search(r"stopped after (\d+) frames", camera_log)
    if m is None:
        raise RuntimeError(f"the camera did not say how many frames it sent:\n{camera_log}")
    sent = int(m[1])
    fig: dict[str, float] = {"sent": sent, "seconds": seconds, "rate_hz": sent / seconds,
                             "exits": float(sum(code is not None for code in exits.values()))}
    pre, me = status["preprocessing"], status["motion_estimation"]
    fig["estimates"] = me["published"]
    fig["dropped"] = pre["dropped"] + me["dropped"]
    fig["uncounted"] = sent - fig["estimates"] - fig["dropped"]
    fig["rejected_failed"] = float(sum(s["rejected"] + s["failed"] for s in status.values()))
    for name, s in status.items():
        fig[f"{name}_dropped"] = s["dropped"]
    for name, points in samples.items():
        at_10 = next((kib for t, kib in points if t >= FIRST_SAMPLE_S), points[0][1])
        fig[f"{name}_rss10_mib"] = at_10 / 1024
        fig[f"{name}_rss_end_mib"] = points[-1][1] / 1024
        fig[f"{name}_rss_max_mib"] = max(kib for _, kib in points) / 1024
        fig[f"{name}_rss_change"] = points[-1][1] / at_10 - 1
    _print(out, fig, samples, status)
    return fig


def _print(out: TextIO, fig: dict[str, float], samples: dict, status: dict) -> None:
    print(f"# vistrack bench soak: file camera --fps 0 --in-flight 2, built-in 256x256, "
          f"{fig['seconds']:g} s, five processes on a local Zenoh router", file=out)
    print(f"{'process':18s} {'RSS at 10 s':>12s} {'at the end':>11s} {'max':>8s} "
          f"{'change':>7s}", file=out)
    ok = True
    for name in samples:
        change = fig[f"{name}_rss_change"]
        if name in SERVICES:
            ok = ok and abs(change) <= RSS_TOLERANCE
        print(f"{name:18s} {fig[name + '_rss10_mib']:9.1f} MiB {fig[name + '_rss_end_mib']:7.1f}"
              f" MiB {fig[name + '_rss_max_mib']:5.1f} MiB {100 * change:+6.1f}%", file=out)
    print(f"frames sent {fig['sent']:.0f} ({fig['rate_hz']:.0f} a second), estimates "
          f"{fig['estimates']:.0f}, counted as dropped {fig['dropped']:.0f} (preprocessing "
          f"{status['preprocessing']['dropped']}, motion-estimation "
          f"{status['motion_estimation']['dropped']}), lost uncounted {fig['uncounted']:.0f}",
          file=out)
    others = ", ".join(f"{n} {status[n]['dropped']}" for n in ("auto_tuner", "fuzzy_controller"))
    print(f"also dropped at latest-only inputs: {others}; rejected + failed everywhere: "
          f"{fig['rejected_failed']:.0f}; services that exited: {fig['exits']:.0f}", file=out)
    print(f"target: every service's RSS at the end within {100 * RSS_TOLERANCE:g} % of 10 s: "
          f"{'met' if ok else 'NOT met'}; nothing lost but the counted drops: "
          f"{'met' if fig['uncounted'] == 0 and fig['rejected_failed'] == 0 else 'NOT met'}",
          file=out)
