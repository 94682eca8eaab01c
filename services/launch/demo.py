"""``vistrack demo``: the whole system on the built-in default, in closed loop.

Starts an embedded Zenoh router and the five services with the robot simulator as the camera
(a scenario in which the target moves sideways and approaches and recedes; the robot follows),
shows a live status line, stops after ``--duration`` (default: the scenario's length) and writes
to ``--out``:

* ``summary.json``: frames, fps, latency_ms_p50/p99 (capture to estimate), cmd_latency_ms_p50/p99
  (capture to velocity command), rms_center_error_px
  and rms_scale_error (against the simulator's ground truth), retunes, and more;
* ``strip.png``: frames through the run with the tracked features and their centroid;
* ``errors.png``, ``trajectories.png``, ``commands.png``: image and distance error over time,
  robot and target paths, velocity commands;
* ``services.log``: every service's log, prefixed with its name.

``--no-control`` runs the same scenario with the robot standing still, for comparison.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import dataclasses
import json
import math
import os
import sys
import threading
import time
from pathlib import Path
from typing import Any

import cv2
import msgpack
import numpy as np
import zenoh

from ...common.bus import BusError, add_zenoh_args
from ..camera.scenarios import ScenarioError, load_scenario
from ..camera.sim import Camera, image_truth
from ..fuzzy_controller.control import ControllerConfig
from ..usage import add_number, add_path, print_error, rewrites_lines
from .launchfile import LaunchError, LaunchSpec, default_launch
from .router import listen_endpoints, router_config
from .supervisor import Launcher, compile_kernels

TRACKER_FLAGS = ("--subpixel",)  # closed loop needs sub-pixel motion (see README)
STRIP_FRAMES = 8


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_number(parser, "--duration", lo=1, hi=3600, unit="s", default=None, metavar="S",
               help="seconds to run, %(allowed)s, at most the scenario's duration (its "
                    "default)")
    parser.add_argument("--scenario", default="default",
                        help="built-in scenario (default, sideways, approach, steps, still, "
                             "lighting) or a scenario YAML file")
    parser.add_argument("--no-control", action="store_true",
                        help="the robot stands still: the same run without the controller")
    add_path(parser, "--out", kind="folder", example="vistrack-demo", default="vistrack-demo",
             metavar="DIR", help="output folder (default ./vistrack-demo)")
    add_zenoh_args(parser)


def check_args(args: argparse.Namespace) -> None:
    """Before anything starts: the output folder can be made, the scenario and a Zenoh config
    file can be read (ValueError names what is wrong)."""
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {args.out}: exists and is not a folder")
    try:
        # made now: a folder that cannot be made (a read-only working directory, /proc) was
        # a traceback, after the start
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ValueError(f"--out {args.out}: {e.strerror or e}") from None
    try:
        scenario = load_scenario(args.scenario)
    except ScenarioError as e:
        raise ValueError(str(e)) from None
    if args.duration is not None and args.duration > scenario.duration_s:
        # it ran the scenario's length and said nothing (its strip then held 2 frames of 8)
        raise ValueError(f"--duration {args.duration:g} is out of range: allowed "
                         f"1..{scenario.duration_s:g} s (the length of scenario "
                         f"{args.scenario!r})")
    if args.config is not None:
        try:
            router_config(None, args.config)
        except BusError as e:
            raise ValueError(str(e)) from None


def _with_flags(launch: LaunchSpec, service: str, *flags: str) -> LaunchSpec:
    spec = launch.service(service)
    if spec is None:
        return launch
    new = dataclasses.replace(spec, flags=(*spec.flags, *flags))
    return dataclasses.replace(launch, services=tuple(new if s is spec else s
                                                      for s in launch.services))


class Recorder:
    """Collects what the demo reports, from Zenoh callbacks (thread-safe)."""

    def __init__(self, session: zenoh.Session, keys: Any, duration: float) -> None:
        self.lock = threading.Lock()
        self.estimates: list[tuple[int, dict]] = []  # (arrival ns, message)
        self.poses: list[dict] = []
        self.cmds: list[dict] = []
        self.params: dict = {}
        self.params_ids: set[int] = set()
        self.params_arrivals: list[int] = []  # when each new params_id of the tuner came
        self.frames: collections.OrderedDict[int, np.ndarray] = collections.OrderedDict()
        self.strip: list[tuple[np.ndarray, dict]] = []
        self._next_strip = 0.0
        self._strip_every = duration / STRIP_FRAMES
        self._t0 = time.monotonic()
        self._session, self._keys = session, keys
        self._frame_sub: zenoh.Subscriber | None = None
        self.subs = [session.declare_subscriber(keys.estimate, self._on_estimate),
                     session.declare_subscriber(keys.pose, self._on(self.poses)),
                     session.declare_subscriber(keys.cmd_vel, self._on_cmd),
                     session.declare_subscriber(keys.params, self._on_params)]

    def watch_frames(self) -> None:
        """Subscribe to camera frames only around the strip's next frame (call it from the
        main loop): every frame is 64 KiB delivered into this process, which also measures
        the latency, and only eight are kept."""
        with self.lock:
            due = (len(self.strip) < STRIP_FRAMES
                   and time.monotonic() - self._t0 >= self._next_strip - 0.3)
        if due and self._frame_sub is None:
            self._frame_sub = self._session.declare_subscriber(self._keys.frame,
                                                               self._on_frame)
        elif not due and self._frame_sub is not None:
            self._frame_sub.undeclare()
            self._frame_sub = None

    def _on(self, store: list) -> Any:
        def on(sample: zenoh.Sample) -> None:
            m = msgpack.unpackb(sample.payload.to_bytes())
            with self.lock:
                store.append(m)
        return on

    def _on_cmd(self, sample: zenoh.Sample) -> None:
        t = time.time_ns()
        m = msgpack.unpackb(sample.payload.to_bytes())
        m["_arrival_ns"] = t  # camera-to-command latency = arrival - stamp_ns (capture)
        with self.lock:
            self.cmds.append(m)

    def _on_params(self, sample: zenoh.Sample) -> None:
        m = msgpack.unpackb(sample.payload.to_bytes())
        with self.lock:
            self.params = m
            if m.get("source") == "tuner" and m["params_id"] not in self.params_ids:
                self.params_ids.add(m["params_id"])
                self.params_arrivals.append(time.time_ns())

    def _on_frame(self, sample: zenoh.Sample) -> None:
        if time.monotonic() - self._t0 < self._next_strip:
            return  # only frames that may go into the strip are kept
        m = msgpack.unpackb(sample.payload.to_bytes())
        img = np.frombuffer(m["data"], np.uint8).reshape(m["height"], m["width"])
        with self.lock:
            self.frames[m["stamp_ns"]] = img
            while len(self.frames) > 8:
                self.frames.popitem(last=False)

    def _on_estimate(self, sample: zenoh.Sample) -> None:
        t = time.time_ns()
        m = msgpack.unpackb(sample.payload.to_bytes())
        with self.lock:
            self.estimates.append((t, m))
            frame = self.frames.pop(m["stamp_ns"], None)
            if frame is not None and len(self.strip) < STRIP_FRAMES:
                self.strip.append((frame, m))
                self._next_strip += self._strip_every

    def close(self) -> None:
        for s in [*self.subs, *([self._frame_sub] if self._frame_sub is not None else [])]:
            s.undeclare()
        self._frame_sub = None


def _annotate(frame: np.ndarray, est: dict) -> np.ndarray:
    img = cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR)
    for _, x, y in est["features"]:
        cv2.rectangle(img, (int(x) - 2, int(y) - 2), (int(x) + 2, int(y) + 2), (0, 200, 0), 1)
    if math.isfinite(est["xc"]):
        c = (int(round(est["xc"])), int(round(est["yc"])))
        cv2.drawMarker(img, c, (0, 0, 255), cv2.MARKER_CROSS, 14, 2)
    cv2.putText(img, f"seq {est['seq']} NPI {est['npi']}", (4, 14), cv2.FONT_HERSHEY_SIMPLEX,
                0.4, (0, 255, 255), 1, cv2.LINE_AA)
    return img


def start_truth(scenario: Any, cam: Camera) -> tuple[float, float]:
    """Where the target is in the image at the start (the robot at the origin), and its scale:
    the errors' reference. The first ``sim/pose`` received was, but it missed frame 0 now and
    then (its subscriber is declared as the camera starts) and measured the error from frame 1
    or 2 (+0.13 to 0.73 px on the default scenario)."""
    tx0, ty0 = scenario.target_position(0.0)
    return image_truth({"x": 0.0, "y": 0.0, "theta": 0.0, "tx": tx0, "ty": ty0}, cam,
                       scenario.distance_m)


def summarise(rec: Recorder, scenario: Any, wall_s: float) -> dict[str, Any]:
    """summary.json: the contract's fields and a few more."""
    with rec.lock:
        est = list(rec.estimates)
        poses = list(rec.poses)
        cmds = list(rec.cmds)
        retuned = list(rec.params_arrivals[1:])
    lat = np.array([(t - m["stamp_ns"]) * 1e-6 for t, m in est]) if est else np.array([np.nan])
    # the longest the loop went without an estimate (arrivals), and the camera without a
    # frame (capture stamps): a gap over the fuzzy controller's watchdog bound (0.3 s) makes
    # its stale stops; when the camera's gap is as long, the machine stalled, not the pipeline
    arrivals = np.array([t for t, _ in est], np.int64)
    gap = np.diff(arrivals) * 1e-6 if len(est) > 1 else np.zeros(1)
    # when the longest gap began, s after the first estimate
    gap_at = (arrivals[int(np.argmax(gap))] - arrivals[0]) * 1e-9 if len(est) > 1 else 0.0
    cam_gap = np.diff([p["stamp_ns"] for p in poses]) * 1e-6 if len(poses) > 1 \
        else np.zeros(1)
    # the same between the captures the estimates answer: a pipeline that stalls skips
    # frames (latest only), while a gap in arrivals alone is this process's, late to take
    # them in (its plots' import, its log forwarding), not the pipeline's
    stamp_gap = np.diff([m["stamp_ns"] for _, m in est]) * 1e-6 if len(est) > 1 \
        else np.zeros(1)
    cam = Camera()
    truth = np.array([image_truth(p, cam, scenario.distance_m) for p in poses]) \
        if poses else np.full((1, 2), np.nan)
    u, scale = truth[:, 0], truth[:, 1]
    u0, scale0 = start_truth(scenario, cam)
    effort = [math.hypot(c["vx"], c["vy"]) for c in cmds if not c["stale"]]
    cmd_lat = np.array([(c["_arrival_ns"] - c["stamp_ns"]) * 1e-6 for c in cmds
                        if not c["stale"]]) if cmds else np.array([np.nan])
    return {
        "scenario": scenario.name, "frames": len(est), "wall_s": round(wall_s, 3),
        # rounded to what the measurement resolves (10 us, 1/1000 px): read by people
        "fps": round(len(est) / wall_s, 2) if wall_s > 0 else 0.0,
        "latency_ms_p50": round(float(np.nanmedian(lat)), 2),
        "latency_ms_p99": round(float(np.nanpercentile(lat, 99)), 2),
        "cmd_latency_ms_p50": round(float(np.nanmedian(cmd_lat)), 2),
        "cmd_latency_ms_p99": round(float(np.nanpercentile(cmd_lat, 99)), 2),
        "rms_center_error_px": round(float(np.sqrt(np.nanmean((u - u0) ** 2))), 3),
        "rms_scale_error": round(float(np.sqrt(np.nanmean((scale / scale0 - 1) ** 2))), 5),
        "retunes": max(0, len(rec.params_ids) - 1),
        "npi_mean": round(float(np.mean([m["npi"] for _, m in est])), 1) if est else 0.0,
        "commands": len(cmds), "stale_commands": sum(1 for c in cmds if c["stale"]),
        # when each stale stop came, s after the first estimate
        "stale_at_s": [round((c["_arrival_ns"] - int(arrivals[0])) * 1e-9, 3)
                       for c in cmds if c["stale"]] if len(est) else [],
        "estimate_gap_ms_max": round(float(np.max(gap)), 2),
        "estimate_gap_at_s": round(float(gap_at), 3),
        # gaps over the fuzzy controller's default watchdog bound: each makes stale stops
        "estimate_gaps_over_watchdog": int(np.sum(gap > 1e3 * ControllerConfig().stale_after_s)),
        # when each retune's parameters came, s after the first estimate
        "retunes_at_s": [round((t - int(arrivals[0])) * 1e-9, 3)
                         for t in retuned] if len(est) else [],
        "camera_gap_ms_max": round(float(np.max(cam_gap)), 2),
        "estimate_stamp_gap_ms_max": round(float(np.max(stamp_gap)), 2),
        "mean_speed_cmd_m_s": round(float(np.mean(effort)), 4) if effort else 0.0,
        "params": {k: rec.params.get(k) for k in ("max_features", "thres_percent",
                                                 "search_size", "corr_size", "ungroup_size",
                                                 "params_id", "source", "reason")},
    }


def _import_pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def preload_plots() -> threading.Thread:
    """Import matplotlib in a thread: started as the run begins, its import (~2 s on a first
    run, which also builds matplotlib's font cache) overlaps the run, whose 20 s leave a core
    idle, instead of adding to the time after it."""
    thread = threading.Thread(target=_import_pyplot_aside, name="preload-matplotlib",
                              daemon=True)
    thread.start()
    return thread


def _import_pyplot_aside() -> None:
    """:func:`_import_pyplot` at the lowest priority, this thread only (Linux nice is per
    thread): its ~0.5 s of CPU comes as the pipeline starts, and in a run's first half second
    the pipeline stalled now and then in CI (README, Known limits)."""
    with contextlib.suppress(AttributeError, OSError):  # not Linux: at the process's priority
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 19)
    _import_pyplot()


def write_outputs(out: Path, rec: Recorder, scenario: Any, summary: dict) -> list[str]:
    plt = _import_pyplot()

    out.mkdir(parents=True, exist_ok=True)
    written = ["summary.json"]
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    with rec.lock:
        strip = list(rec.strip)
        poses, cmds = list(rec.poses), list(rec.cmds)
    if strip:
        # encoded here and written by Python: cv2.imwrite crashed on an --out whose name is
        # not UTF-8 (see sources.utf8_name)
        ok, png = cv2.imencode(".png", np.hstack([_annotate(f, m) for f, m in strip]))
        (out / "strip.png").write_bytes(png.tobytes())
        written.append("strip.png")
    if poses:
        cam = Camera()
        t = np.array([(p["stamp_ns"] - poses[0]["stamp_ns"]) * 1e-9 for p in poses])
        truth = np.array([image_truth(p, cam, scenario.distance_m) for p in poses])
        fig, ax = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
        u0, scale0 = start_truth(scenario, cam)
        ax[0].plot(t, truth[:, 0] - u0)
        ax[0].set_ylabel("centring error, px")
        ax[1].plot(t, truth[:, 1] / scale0 - 1)
        ax[1].set_ylabel("scale error")
        ax[1].set_xlabel("time, s")
        fig.suptitle(f"{scenario.name}: error against ground truth")
        fig.tight_layout()
        fig.savefig(out / "errors.png", dpi=90)
        fig, ax = plt.subplots(figsize=(6, 5))
        ax.plot([p["y"] for p in poses], [p["x"] for p in poses], label="robot")
        ax.plot([p["ty"] for p in poses], [p["tx"] for p in poses], label="target")
        ax.set_xlabel("y (left), m")
        ax.set_ylabel("x (forward), m")
        ax.invert_xaxis()
        ax.legend()
        ax.set_title("trajectories (top view)")
        fig.tight_layout()
        fig.savefig(out / "trajectories.png", dpi=90)
        written += ["errors.png", "trajectories.png"]
    if cmds:
        tc = np.array([(c["stamp_ns"] - cmds[0]["stamp_ns"]) * 1e-9 for c in cmds])
        fig, ax = plt.subplots(figsize=(8, 3))
        ax.plot(tc, [c["vx"] for c in cmds], label="vx (forward)")
        ax.plot(tc, [c["vy"] for c in cmds], label="vy (left)")
        ax.set_xlabel("time, s")
        ax.set_ylabel("m/s")
        ax.legend()
        fig.tight_layout()
        fig.savefig(out / "commands.png", dpi=90)
        written.append("commands.png")
    plt.close("all")
    return written


#: the shortest run of estimates the status line gives a rate for, s
RATE_SPAN_S = 0.5


def _status_line(rec: Recorder, t0: float) -> str:
    with rec.lock:
        est = rec.estimates[-60:]
        params = rec.params
        n = len(rec.estimates)
    if len(est) < 2:
        return f"waiting for estimates... ({time.monotonic() - t0:.0f} s)"
    span = (est[-1][0] - est[0][0]) * 1e-9
    # a rate over less than RATE_SPAN_S is none: the first line read 407.5 fps over 3 frames
    rate = f"{(len(est) - 1) / span:5.1f}" if span >= RATE_SPAN_S else "    -"
    lat = np.median([(t - m["stamp_ns"]) * 1e-6 for t, m in est])
    last = est[-1][1]
    return (f"{time.monotonic() - t0:5.1f} s  frames {n:5d}  {rate} fps  latency "
            f"{lat:5.1f} ms  NPI {last['npi']:3d}  search {params.get('search_size', '?')} "
            f"corr {params.get('corr_size', '?')} (params_id {params.get('params_id', '?')})")


def main(args: argparse.Namespace) -> int:
    try:
        check_args(args)  # again, for callers that did not come through the CLI
        scenario = load_scenario(args.scenario)
        duration = args.duration if args.duration is not None else scenario.duration_s
        launch = default_launch().with_camera(source=f"sim:{args.scenario}", fps=30.0)
        # --robot, as vistrack up takes it (the services ran as robot "robot", whatever it said)
        launch = dataclasses.replace(launch, robot=getattr(args, "robot", launch.robot))
        if args.no_control:
            launch = _with_flags(launch, "camera", "--no-control")
        for name in ("preprocessing", "motion-estimation", "auto-tuner"):
            launch = _with_flags(launch, name, *TRACKER_FLAGS)
        if args.listen:
            launch = dataclasses.replace(launch, listen=tuple(args.listen))
        elif args.config is not None and not args.connect:
            # the config file decides where the router listens, as for vistrack up
            launch = dataclasses.replace(launch, listen=tuple(listen_endpoints(
                router_config(None, args.config))))
    except (ScenarioError, LaunchError, ValueError) as e:
        print_error("demo", e)
        return 2
    out = Path(args.out)
    try:
        return _run(args, launch, scenario, duration, out)
    except (BusError, LaunchError) as e:  # a port in use, no router at -e, a service down
        print_error("demo", e)
        return 1
    except KeyboardInterrupt:
        # the status line ends, and what was written is said (the services stopped with the
        # launcher); nothing else is: a run cut short is no demo
        print(f"\nvistrack demo: interrupted; only {out / 'services.log'} was written",
              file=sys.stderr, flush=True)
        return 130


def _run(args: argparse.Namespace, launch: LaunchSpec, scenario: Any, duration: float,
         out: Path) -> int:
    tty = rewrites_lines(sys.stderr)
    with open(out / "services.log", "w") as log:
        launcher = Launcher(launch, connect=args.connect, router_config=args.config,
                            multicast_scouting=not args.no_multicast_scouting, mode=args.mode,
                            out=log)
        try:
            launcher.open()  # the router first: a taken port is said before any compiling
            # says so on stderr when it compiles (a first run); the services start meanwhile
            compile_kernels("demo", start=launcher.start)
        except BaseException:
            launcher.stop()
            raise
        return _closed_loop(args, launcher, scenario, duration, out, tty)


def _closed_loop(args: argparse.Namespace, launcher: Launcher, scenario: Any,
                 duration: float, out: Path, tty: bool) -> int:
    with launcher:
        print(f"vistrack demo: starting the five services (scenario {scenario.name}, "
              f"{'robot still' if args.no_control else 'closed loop'}); logs in "
              f"{out / 'services.log'}", file=sys.stderr)
        launcher.wait_ready()
        assert launcher.session is not None
        rec = Recorder(launcher.session, launcher.keys, duration)
        preload = preload_plots()
        t0 = time.monotonic()
        last_print = 0.0
        code = None
        while time.monotonic() - t0 < duration and code is None:
            code = launcher.poll()
            rec.watch_frames()
            time.sleep(0.1)
            if time.monotonic() - last_print >= (0.25 if tty else 2.0):
                line = _status_line(rec, t0)
                print(f"\r{line}\033[K" if tty else line, end="" if tty else "\n",
                      file=sys.stderr, flush=True)
                last_print = time.monotonic()
        wall = time.monotonic() - t0
        rec.close()
        # the services stop (up to a few seconds of waiting on their exits) while the
        # figures are drawn; leaving the block waits for the stop
        stopper = threading.Thread(target=launcher.stop, name="stop-services")
        stopper.start()
        try:
            if tty:
                print(file=sys.stderr)
            summary = summarise(rec, scenario, wall)
            preload.join()
            written = write_outputs(out, rec, scenario, summary)
        finally:
            stopper.join()
    print(json.dumps({k: summary[k] for k in ("frames", "fps", "latency_ms_p50",
                                                "latency_ms_p99", "cmd_latency_ms_p99",
                                                "rms_center_error_px",
                                                "rms_scale_error", "retunes")}, indent=2))
    print(f"vistrack demo: wrote {', '.join(written)} to {out}/", file=sys.stderr)
    return 0 if summary["frames"] > 0 else 1
