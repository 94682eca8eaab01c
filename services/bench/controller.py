"""``vistrack bench controller``: the fuzzy controller against a proportional one.

Both run the same closed loop in one process, in lockstep (render, track, decide, move), on the
same built-in scenarios with the same tracker: the simulator renders a frame, the library
tracker (sub-pixel) estimates it, the controller answers, and the robot moves by that command for
1/30 s. Reported per scenario and controller: RMS centring error (px) and RMS scale error against
the simulator's ground truth, settling time after the target's steps (frames until the centring
error stays inside 2 px), and command effort (mean commanded speed, m/s, and mean change of
command per frame, m/s). Plus the decision time of each controller and of scikit-fuzzy's own
``ControlSystemSimulation.compute()``.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO

import numpy as np

from ...common.params import TrackerParams
from ...common.vision import Tracker, warm_up
from ..camera.sim import Command, Simulator
from ..fuzzy_controller.control import (
    FuzzyController,
    FuzzySurface,
    ProportionalController,
    ProportionalGains,
)
from ..fuzzy_controller.service import LIMITS

SCENARIOS = ("sideways", "approach", "steps", "default")
BAND_PX = 2.0
FPS = 30.0


def make(law: str) -> FuzzyController | ProportionalController:
    """The controller the service runs for ``law`` (same limits and gains)."""
    if law == "fuzzy":
        return FuzzyController(FuzzySurface.compile(LIMITS))
    return ProportionalController(ProportionalGains(
        kx=LIMITS.vy_max / LIMITS.ex_max, kz=LIMITS.vx_max / LIMITS.ez_max,
        vy_max=LIMITS.vy_max, vx_max=LIMITS.vx_max))


def closed_loop(scenario: str, law: str | None) -> dict[str, np.ndarray]:
    """One lockstep run; ``law`` None keeps the robot still. Per-frame traces."""
    sim = Simulator(scenario)
    tracker = Tracker(TrackerParams(subpixel=True))
    ctrl = make(law) if law else None
    u, scale, vx, vy = [], [], [], []
    xc0 = None
    k = 0
    while not sim.done:
        truth = sim.truth()
        u.append(truth["u"])
        scale.append(truth["scale"])
        est = tracker.process(sim.render())
        cmd = Command()
        if ctrl is not None:
            if xc0 is None and est.valid:
                xc0 = est.xc
            c = ctrl.update((est.xc if xc0 is None else xc0) + est.dx, est.scale,
                            k / FPS + 1.0, sim.camera.width, npi=est.npi, valid=est.valid)
            cmd = Command(vx=c.vx, vy=c.vy, wz=c.wz)
        vx.append(cmd.vx)
        vy.append(cmd.vy)
        sim.step(cmd, 1.0 / FPS)
        k += 1
    return {"u": np.array(u), "scale": np.array(scale), "vx": np.array(vx), "vy": np.array(vy)}


def metrics(tr: dict[str, np.ndarray]) -> dict[str, float]:
    err = tr["u"] - tr["u"][0]
    steps = list(np.flatnonzero(np.abs(np.diff(tr["u"])) > 3.0) + 1)
    settle = []
    ends = steps[1:] + [len(err)] if steps else []
    for start, end in zip(steps, ends, strict=True):
        out = np.flatnonzero(np.abs(err[start:end]) > BAND_PX)
        settle.append(int(out.max()) + 1 if len(out) else 0)
    v = np.hypot(tr["vx"], tr["vy"])
    dv = np.hypot(np.diff(tr["vx"]), np.diff(tr["vy"])) if len(v) > 1 else np.zeros(1)
    return {"rms_center_px": float(np.sqrt(np.mean(err ** 2))),
            "rms_scale": float(np.sqrt(np.mean((tr["scale"] / tr["scale"][0] - 1) ** 2))),
            "settle_frames": float(max(settle)) if settle else float("nan"),
            "mean_speed": float(v.mean()), "mean_dv": float(dv.mean())}


def decision_times() -> dict[str, float]:
    """Microseconds per decision: our fuzzy surface, the P law, scikit-fuzzy compute()."""
    from ..fuzzy_controller.rules import build_control_system

    out = {}
    rng = np.random.default_rng(0)
    xs = rng.uniform(100, 156, 2000)
    for law in ("fuzzy", "proportional"):
        ctrl = make(law)
        t0 = time.perf_counter()
        for i, x in enumerate(xs):
            ctrl.update(float(x), 1.0 + 0.01 * (i % 7), 1.0 + i / FPS, 256.0, npi=50)
        out[law] = (time.perf_counter() - t0) / len(xs) * 1e6
    import warnings

    from skfuzzy import control as ctrl_mod

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # skfuzzy 0.5 + numpy 2 deprecation noise
        sim = ctrl_mod.ControlSystemSimulation(build_control_system(LIMITS))
        t0 = time.perf_counter()
        n = 100
        for _ in range(n):
            sim.input["ex"] = float(rng.uniform(-0.1, 0.1))
            sim.input["dex"] = 0.0
            sim.input["ez"] = float(rng.uniform(-0.1, 0.1))
            sim.input["dez"] = 0.0
            sim.compute()
        out["skfuzzy"] = (time.perf_counter() - t0) / n * 1e6
    return out


def bench_controller(out: TextIO = sys.stdout) -> dict[str, float]:
    """Run every scenario with no control, the P law and the fuzzy law; print the table."""
    warm_up()
    fig: dict[str, float] = {}
    print("# vistrack bench controller: lockstep closed loop in one process, 30 fps, "
          "sub-pixel tracker", file=out)
    print(f"{'scenario':10s} {'controller':13s} {'RMS px':>7s} {'RMS scale':>9s} "
          f"{'settle fr':>9s} {'|v| m/s':>8s} {'|dv| m/s':>8s}", file=out)
    for scenario in SCENARIOS:
        for law in (None, "proportional", "fuzzy"):
            m = metrics(closed_loop(scenario, law))
            name = law or "none (still)"
            for k, v in m.items():
                fig[f"{scenario}_{law or 'none'}_{k}"] = v
            print(f"{scenario:10s} {name:13s} {m['rms_center_px']:7.2f} {m['rms_scale']:9.4f} "
                  f"{m['settle_frames']:9.0f} {m['mean_speed']:8.3f} {m['mean_dv']:8.4f}",
                  file=out)
    t = decision_times()
    fig.update({f"decision_us_{k}": v for k, v in t.items()})
    print(f"\ndecision time: fuzzy surface {t['fuzzy']:.1f} us, proportional "
          f"{t['proportional']:.1f} us, scikit-fuzzy compute() {t['skfuzzy']:.0f} us "
          f"({t['skfuzzy'] / t['fuzzy']:.0f}x the surface)", file=out)
    return fig
