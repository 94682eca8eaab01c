"""``vistrack bench record``: the MCAP recorder and the Foxglove bridge on a live pipeline.

One run on this machine's loopback, through one local Zenoh router: preprocessing,
motion-estimation, fuzzy-controller and auto-tuner (``--no-tune``) processes, and a file camera
publishing ``seconds * fps`` 256x256 frames (the built-in sequence, repeated) at ``fps``, then
ending. Listening to all of it, from before the first frame to after the last, in processes of
their own:

* ``vistrack record run.mcap`` (the writer measured) and, as its peer in the same moment,
  ``vistrack record run.vtr``, which copies the same samples' bytes without converting them;
* ``vistrack foxglove --frame-rate 10`` with a WebSocket client (a thread of this process)
  subscribed to every channel;
* ``vistrack hz '**'``, which counts the samples and the gaps in each key's ``seq``.

Figures: the samples of each key in the MCAP file, the ``.vtr`` file and hz's count, against
the frames the camera published (a gap in the MCAP's frame sequence is a dropped sample); the
CPU each tool used while the camera ran (user + system time from ``/proc/PID/stat``, all
threads, as a percentage of one core); what the Foxglove client received. Targets (issue 16):
no sample dropped, the MCAP writer and the bridge at most 10 % of one core each.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path
from typing import IO, Any

import cv2
import zenoh
from mcap.reader import make_reader
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect
from websockets.typing import Subprotocol

from ...common import synthetic
from ...common.bus import loopback_config
from ...common.keys import Keys
from ..tools.record import Recording
from .pipeline import _cpu_s, _free_port, _vistrack, _wait_alive

SERVICES = ("preprocessing", "motion-estimation", "fuzzy-controller", "auto-tuner")
KEYS = ("camera/frame", "preprocessing/frame", "motion/estimate", "control/cmd_vel",
        "tuner/params")
TARGET_CPU_PCT = 10.0


class _Tool:
    """A vistrack tool process whose stderr goes to a file (read when it has ended)."""

    def __init__(self, args: list[str], log: Path) -> None:
        self.log = log
        self._file: IO[str] = open(log, "w")  # closed by stop()
        self.p = subprocess.Popen(args, stdout=self._file, stderr=subprocess.STDOUT,
                                  stdin=subprocess.DEVNULL, text=True)

    def wait_for(self, needle: str, timeout: float = 60.0) -> None:
        deadline = time.monotonic() + timeout
        while needle not in self.log.read_text():
            if self.p.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"{self.log.name}: no {needle!r}:\n{self.log.read_text()}")
            time.sleep(0.05)

    def stop(self) -> str:
        """Ctrl-C, wait for the exit (a recorder writes its summary then), return the log."""
        if self.p.poll() is None:
            self.p.send_signal(signal.SIGINT)
            try:
                self.p.wait(60)
            except subprocess.TimeoutExpired:
                self.p.kill()
                self.p.wait()
        self._file.close()
        return self.log.read_text()


class _Client(threading.Thread):
    """A Foxglove WebSocket client subscribed to every channel, counting what arrives."""

    def __init__(self, port: int) -> None:
        super().__init__(daemon=True)
        self.port = port
        self.received: Counter[str] = Counter()
        self.subscribed = threading.Event()
        self.stop = threading.Event()

    def run(self) -> None:
        # the subprotocols the Foxglove app offers; the SDK's server takes foxglove.sdk.v1
        offered = [Subprotocol("foxglove.sdk.v1"), Subprotocol("foxglove.websocket.v1")]
        with connect(f"ws://127.0.0.1:{self.port}", max_size=None,
                     subprotocols=offered) as ws:
            topics: dict[int, str] = {}
            while len(topics) < len(KEYS) + 2:  # every key but sim/pose, and the overlays
                msg = json.loads(ws.recv(timeout=30))
                if msg["op"] == "advertise":
                    topics.update({c["id"]: c["topic"] for c in msg["channels"]})
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": cid, "channelId": cid} for cid in topics]}))
            self.subscribed.set()
            while not self.stop.is_set():
                try:
                    data = ws.recv(timeout=0.2)
                except TimeoutError:
                    continue
                except ConnectionClosed:
                    return
                if isinstance(data, bytes) and data[0] == 1:
                    self.received[topics[int.from_bytes(data[1:5], "little")]] += 1


def _frames(folder: Path, n: int) -> None:
    """``n`` 256x256 PNG frames: the built-in sequence, repeated."""
    seq = synthetic.builtin_sequence(60)
    for i in range(n):
        cv2.imwrite(str(folder / f"{i:05d}.png"), seq[i % len(seq)])


def _mcap_counts(path: Path, root: str) -> tuple[Counter[str], Counter[str]]:
    """Messages per key of an MCAP recording, and the gaps in each key's sequence (the
    contract's ``seq``; ``preprocessing/frame`` and ``motion/estimate`` keep the frame's, so
    theirs also count frames the pipeline skipped, not only samples the recorder lost)."""
    counts: Counter[str] = Counter()
    gaps: Counter[str] = Counter()
    last: dict[str, int] = {}
    with open(path, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages(log_time_order=False):
            key = channel.topic[len(root) + 2:]
            counts[key] += 1
            if key in last and message.sequence > last[key] + 1:
                gaps[key] += message.sequence - last[key] - 1
            last[key] = message.sequence
    return counts, gaps


def _hz_counts(text: str) -> dict[str, dict[str, Any]]:
    """The last report of each key in ``vistrack hz --json`` output."""
    last: dict[str, dict[str, Any]] = {}
    for line in text.splitlines():
        if line.startswith("{"):
            report = json.loads(line)
            last[report["key"]] = report
    return last


def bench_record(out=sys.stdout, seconds: float = 60.0, fps: float = 30.0,
                 frame_rate: float = 10.0) -> dict[str, float]:
    """Run it (module docstring), print the table, return the figures."""
    n = round(seconds * fps)
    keys = Keys("robot")
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    work = Path(tempfile.mkdtemp(prefix="vistrack-bench-record-"))
    tools: dict[str, _Tool] = {}
    procs: list[subprocess.Popen] = []
    client: _Client | None = None
    try:
        (work / "frames").mkdir()
        _frames(work / "frames", n)
        with zenoh.open(loopback_config(endpoint, router=True)), \
                zenoh.open(loopback_config(endpoint)) as session:
            for name in SERVICES:
                extra = ("--no-tune",) if name == "auto-tuner" else ()
                procs.append(subprocess.Popen(_vistrack(name, endpoint, *extra),
                                              stdout=subprocess.DEVNULL,
                                              stderr=subprocess.DEVNULL))
            _wait_alive(session, keys, {"preprocessing", "motion_estimation", "auto_tuner",
                                        "fuzzy_controller"}, 90)
            with socket.socket() as sock:
                sock.bind(("127.0.0.1", 0))
                ws_port = sock.getsockname()[1]
            tools["hz"] = _Tool(_vistrack("hz", endpoint, "**", "--json"), work / "hz.log")
            tools["mcap"] = _Tool(_vistrack("record", endpoint, str(work / "run.mcap")),
                                  work / "mcap.log")
            tools["vtr"] = _Tool(_vistrack("record", endpoint, str(work / "run.vtr")),
                                 work / "vtr.log")
            tools["bridge"] = _Tool(_vistrack("foxglove", endpoint, "--port", str(ws_port),
                                              "--frame-rate", f"{frame_rate:g}"),
                                    work / "bridge.log")
            for name in ("mcap", "vtr"):
                tools[name].wait_for("recording")
            tools["bridge"].wait_for("serving")
            client = _Client(ws_port)
            client.start()
            if not client.subscribed.wait(30):
                raise RuntimeError("the Foxglove client did not subscribe")
            time.sleep(1.0)  # hz has no ready line: give its subscription time to settle
            camera = subprocess.Popen(_vistrack("camera", endpoint, "--source",
                                                f"file:{work / 'frames'}", "--fps", f"{fps:g}"),
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            procs.append(camera)
            time.sleep(2.0)  # past the first frames' feature selection: steady state
            pids = {name: t.p.pid for name, t in tools.items()}
            cpu0 = {name: _cpu_s([pid]) for name, pid in pids.items()}
            t0 = time.monotonic()
            if camera.wait(seconds + 120) != 0:
                raise RuntimeError(f"the camera exited with {camera.returncode}")
            window = time.monotonic() - t0
            cpu = {name: _cpu_s([pid]) - cpu0[name] for name, pid in pids.items()}
            time.sleep(2.0)  # hz prints its last report a second after the last sample
            client.stop.set()
            client.join(10)
            logs = {name: t.stop() for name, t in tools.items()}
    finally:
        if client is not None:
            client.stop.set()
        for t in tools.values():
            t.stop()
        for p in procs:
            if p.poll() is None:
                p.terminate()
                p.wait(10)
    try:
        mcap, gaps = _mcap_counts(work / "run.mcap", keys.root)
        vtr = Counter(r.key[len(keys.root) + 1:] for r in Recording(work / "run.vtr").records())
        hz = _hz_counts(logs["hz"])
        mcap_bytes = (work / "run.mcap").stat().st_size
    finally:
        shutil.rmtree(work, ignore_errors=True)
    fig: dict[str, float] = {f"{name}_cpu_pct": 100.0 * c / window for name, c in cpu.items()}
    fig.update(window_s=window, frames_published=n, mcap_mb_per_s=mcap_bytes / 1e6 / seconds)
    print(f"# vistrack bench record: {n} frames 256x256 at {fps:g} fps ({seconds:g} s), "
          "4 services + camera, a local Zenoh router", file=out)
    print(f"{'key':22s} {'mcap':>7s} {'vtr':>7s} {'hz':>7s} {'mcap gaps':>10s} "
          f"{'hz gaps':>8s}", file=out)
    for key in KEYS:
        h = hz.get(f"{keys.root}/{key}", {})
        row = (mcap[key], vtr[key], h.get("samples", 0), gaps[key], h.get("gaps", 0))
        fig.update({f"{key}_mcap": row[0], f"{key}_vtr": row[1], f"{key}_hz": row[2],
                    f"{key}_mcap_gaps": row[3], f"{key}_hz_gaps": row[4]})
        print(f"{key:22s} {row[0]:7d} {row[1]:7d} {row[2]:7d} {row[3]:10d} {row[4]:8d}",
              file=out)
    # the frame-bound keys: every tool listened from before the first frame to after the
    # last, so each must hold exactly what hz counted (commands and parameter reminders also
    # come before and after the frames, when the tools' start and stop times differ)
    missing = sum(abs(mcap[k] - fig[f"{k}_hz"]) + abs(vtr[k] - fig[f"{k}_hz"])
                  for k in KEYS[:3])
    missing += abs(mcap["camera/frame"] - n) + gaps["camera/frame"] + \
        sum(max(0, gaps[k] - fig[f"{k}_hz_gaps"]) for k in KEYS)
    fig["samples_missing"] = missing
    print(f"camera published {n} frames; samples the MCAP lacks against hz, the .vtr and the "
          f"camera: {missing}", file=out)
    print(f"CPU over the {window:.1f} s the camera ran, % of one core: MCAP writer "
          f"{fig['mcap_cpu_pct']:.1f} (its peer, the .vtr writer: {fig['vtr_cpu_pct']:.1f}, "
          f"{fig['mcap_cpu_pct'] / max(fig['vtr_cpu_pct'], 1e-9):.1f}x), Foxglove bridge "
          f"{fig['bridge_cpu_pct']:.1f} (hz on the same keys: {fig['hz_cpu_pct']:.1f})",
          file=out)
    assert client is not None
    got = client.received
    fig["bridge_frames_hz"] = got[f"/{keys.root}/camera/frame"] / window
    fig["bridge_estimates_hz"] = got[f"/{keys.root}/motion/estimate"] / window
    print(f"Foxglove client received: {fig['bridge_frames_hz']:.1f} camera frames/s "
          f"(--frame-rate {frame_rate:g}), {fig['bridge_estimates_hz']:.1f} estimates/s, "
          f"{sum(got.values())} messages on {len(got)} channels; MCAP "
          f"{fig['mcap_mb_per_s']:.2f} MB/s", file=out)
    targets = {"no sample dropped": missing == 0,
               f"MCAP writer <= {TARGET_CPU_PCT:g} % of a core":
                   fig["mcap_cpu_pct"] <= TARGET_CPU_PCT,
               f"bridge <= {TARGET_CPU_PCT:g} % of a core at {frame_rate:g} Hz frames":
                   fig["bridge_cpu_pct"] <= TARGET_CPU_PCT}
    print("targets: " + "; ".join(f"{k}: {'met' if ok else 'NOT met'}"
                                  for k, ok in targets.items()), file=out)
    print(f"(load average during the run: {os.getloadavg()[0]:.2f})", file=out)
    return fig
