"""``vistrack bench idle``: the CPU the whole system takes at 30 fps, per process, from /proc.

A plain ``vistrack up`` (the default launch: the built-in 256x256 sequence at 30 fps, all five
services, the auto-tuner tuning) is started; once the auto-tuner's first tuning is over (the
tuner idle between tunings, as it is most of the time), the CPU time of every process is read
from ``/proc/<pid>/stat`` over a window: each service, the tuning worker, and the launcher with
its embedded Zenoh router, and the launcher's warmed-up spare (waiting). Shares are in % of
one core.

Peers, in the same run:

* the same system with ``VISTRACK_NUMERIC_THREADS`` at the number of cores, which is what the
  bundled OpenBLAS libraries pick by themselves (how every service ran before they were limited
  to one thread): the spinning BLAS threads are the difference;
* the raw Zenoh skeleton of ``vistrack bench pipeline`` at 30 fps: five plain-zenoh processes
  passing payloads of our sizes, no work, and its router: what the messaging alone costs.

The issue's target (the whole system at most 25 % of one core) is marked met or not.
"""

from __future__ import annotations

import os
import sys
import time
from typing import TextIO

import zenoh

from ...common import synthetic
from ...common.bus import loopback_config
from .launched import UpRun, children, cpu_s, free_port, tuning_worker

TARGET_PERCENT = 25.0
FIRST_TUNING_S = 180.0  # the buffer fills in 1 s; the cycle runs at idle priority


def _wait_first_tuning(up: UpRun, timeout: float = FIRST_TUNING_S) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        tuner = up.statuses().get("auto_tuner", {}).get("extra", {})
        if tuner.get("tunings", 0) >= 1 and not tuner.get("tuning"):
            return tuner
        time.sleep(0.5)
    raise RuntimeError(f"the auto-tuner did not finish its first tuning within {timeout} s")


def measure_system(seconds: float, threads: int | None = None) -> dict[str, float]:
    """% of one core of every process of ``vistrack up`` at 30 fps over ``seconds``, the
    tuner idle; ``threads`` sets VISTRACK_NUMERIC_THREADS (None: the default, 1)."""
    env = {"VISTRACK_NUMERIC_THREADS": str(threads)} if threads else {}
    with UpRun(env=env) as up:
        pids = up.pids()
        before = _wait_first_tuning(up)
        time.sleep(1.0)  # the cycle's result handed over, the worker back to waiting
        procs = {name.replace("_", "-"): pid for name, pid in pids.items()}
        worker = tuning_worker(pids["auto_tuner"])
        if worker:
            procs["tuning worker"] = worker
        procs["launcher + router"] = up.proc.pid
        for pid in children(up.proc.pid):
            if pid not in pids.values():
                procs["spare (waiting)"] = pid  # the warmed-up process a restart becomes
        estimates = 0

        def count(_sample: zenoh.Sample) -> None:
            nonlocal estimates
            estimates += 1

        assert up.session is not None
        sub = up.session.declare_subscriber(up.keys.estimate, count)
        c0 = {name: cpu_s(pid) for name, pid in procs.items()}
        t0 = time.monotonic()
        time.sleep(seconds)  # a measurement window, not synchronisation
        c1 = {name: cpu_s(pid) for name, pid in procs.items()}
        elapsed = time.monotonic() - t0
        sub.undeclare()
        after = up.statuses()["auto_tuner"]["extra"]
    fig = {name: (c1[name] - c0[name]) / elapsed * 100 for name in procs}
    fig["services"] = sum(v for k, v in fig.items()
                          if k not in ("launcher + router", "spare (waiting)"))
    fig["total"] = fig["services"] + fig["launcher + router"] + fig.get("spare (waiting)", 0.0)
    fig["fps"] = estimates / elapsed
    fig["tuned_in_window"] = float(after.get("tunings", 0) != before.get("tunings", 0)
                                   or bool(after.get("tuning")))
    return fig


def measure_skeleton(seconds: float) -> float:
    """% of one core of the raw Zenoh skeleton at 30 fps (five processes and the router)."""
    from .pipeline import message_sizes, skeleton

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    sizes = message_sizes(synthetic.builtin_sequence(4))
    with zenoh.open(loopback_config(endpoint, router=True)), \
            zenoh.open(loopback_config(endpoint)) as session:
        fig = skeleton(session, endpoint, sizes, fps=30, seconds=seconds)
    return fig["cpu_us_per_frame"] * fig["rate_hz"] / 1e4


def bench_idle(out: TextIO = sys.stdout, seconds: float = 10.0) -> dict[str, float]:
    """Run the three measurements and print the table; return the figures."""
    cores = os.cpu_count() or 1
    ours = measure_system(seconds)
    spinning = measure_system(seconds, threads=cores)
    skeleton_percent = measure_skeleton(seconds)
    print(f"# vistrack bench idle: vistrack up, built-in 256x256 at 30 fps, tuner idle; "
          f"% of one core over {seconds:g} s from /proc", file=out)
    print(f"{'process':24s} {'1 thread':>10s} {f'{cores} threads':>10s}", file=out)
    for name in ours:
        if name in ("fps", "tuned_in_window", "services", "total"):
            continue
        print(f"{name:24s} {ours[name]:9.1f}% {spinning.get(name, float('nan')):9.1f}%",
              file=out)
    for name in ("services", "total"):
        print(f"{name:24s} {ours[name]:9.1f}% {spinning[name]:9.1f}%", file=out)
    print(f"{'estimates a second':24s} {ours['fps']:10.1f} {spinning['fps']:10.1f}", file=out)
    print(f"raw zenoh skeleton at 30 fps (5 processes + router): {skeleton_percent:.1f}% of one "
          f"core", file=out)
    met = "met" if ours["total"] <= TARGET_PERCENT else "NOT met"
    print(f"target: whole system <= {TARGET_PERCENT:g}% of one core: {ours['total']:.1f}% "
          f"({met}); {ours['total'] / skeleton_percent:.1f}x the raw skeleton", file=out)
    for label, fig in (("1 thread", ours), (f"{cores} threads", spinning)):
        if fig["tuned_in_window"]:
            print(f"note: a tuning ran during the {label} window", file=out)
    fig = {f"ours_{k}": v for k, v in ours.items()}
    fig.update({f"spinning_{k}": v for k, v in spinning.items()})
    fig["skeleton_percent"] = skeleton_percent
    fig["ratio_skeleton"] = ours["total"] / skeleton_percent
    return fig
