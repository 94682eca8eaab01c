"""Benchmark of the tuning cycle: ``python -m vistrack.services.auto_tuner.bench``.

On a 30-frame 256x256 buffer, on one core (OpenCV's threads set to 1; the numba kernels are
single-threaded), it times one whole tuning cycle (the 2^(5-1) design with its reference runs,
then the SEARCH_SIZE x CORR_SIZE sweep) and reports the optimum it chose: its tf, the tf of the
reference windows (50, 30) measured in the same passes, the speed-up, and the optimum's ex and
ey; and, for comparison, the paper's choice (15, 9). Buffers: RubberWhale frames 07-14 cropped
to 256x256 and played back and forth (when the shared data is there) and the built-in generated
sequence. Prints a table and returns the figures; asserts nothing about time.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO

import cv2
import numpy as np

from vistrack.common import groundtruth, synthetic
from vistrack.common.vision import to_gray
from vistrack.services.auto_tuner.experiment import bounce
from vistrack.services.auto_tuner.sensitivity import TuneResult, tune

BUFFER = 30


def buffers() -> list[tuple[str, list[np.ndarray]]]:
    """(name, 30 frames of 256x256 uint8) for every buffer the benchmark runs on."""
    out = []
    folder = groundtruth.middlebury("RubberWhale")
    if folder is not None:
        frames = [np.ascontiguousarray(to_gray(cv2.imread(str(folder / f"frame{i:02d}.png")))
                                       [60:316, 160:416]) for i in range(7, 15)]
        out.append(("RubberWhale 07-14 bounced", bounce(frames, BUFFER)))
    out.append(("built-in sequence", synthetic.builtin_sequence(2 * BUFFER)[:BUFFER]))
    return out


def _paper_point(result: TuneResult) -> tuple[float, float, float] | None:
    """(tf, ex, ey) of the paper's (15, 9), or of the swept point with the same geometry."""
    sw = result.sweep
    for i, s in enumerate(sw.search_sizes):
        for j, c in enumerate(sw.corr_sizes):
            if s // 2 == 15 // 2 and c // 2 == 9 // 2:
                return float(sw.tf[i, j]), float(sw.ex[i, j]), float(sw.ey[i, j])
    return None


def bench_tuner(out: TextIO = sys.stdout, *, seed: int = 0) -> dict[str, float]:
    """Run the tuning-cycle benchmark, print its table, return the figures.

    Keys per buffer ``b`` (``rubberwhale``, ``builtin``): ``{b}_cycle_s``, ``{b}_design_s``,
    ``{b}_sweep_s``, ``{b}_tf_ms`` (optimum), ``{b}_ref_tf_ms``, ``{b}_speedup``,
    ``{b}_ex_px``, ``{b}_ey_px``, ``{b}_search_size``, ``{b}_corr_size``.
    """
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        rows = []
        fig: dict[str, float] = {}
        for name, frames in buffers():
            t0 = time.perf_counter()
            result = tune(frames, seed)
            cycle = time.perf_counter() - t0
            key = "rubberwhale" if name.startswith("RubberWhale") else "builtin"
            opt = result.optimum
            fig.update({
                f"{key}_cycle_s": cycle,
                f"{key}_design_s": result.seconds["design"],
                f"{key}_sweep_s": result.seconds["sweep"],
                f"{key}_tf_ms": opt.tf,
                f"{key}_ref_tf_ms": result.sweep.reference.tf,
                f"{key}_speedup": opt.speedup,
                f"{key}_ex_px": opt.ex,
                f"{key}_ey_px": opt.ey,
                f"{key}_search_size": float(opt.params["search_size"]),
                f"{key}_corr_size": float(opt.params["corr_size"]),
            })
            rows.append((name, fig, key, result, _paper_point(result)))
    finally:
        cv2.setNumThreads(threads)

    print(f"Tuning cycle on a {BUFFER}-frame 256x256 buffer, one core, default settings "
          "(3 timing passes, sweep step 2, tolerance 0.5 px), seed "
          f"{seed}", file=out)
    print(f"{'buffer':28s}{'cycle s':>8s}{'design':>8s}{'sweep':>8s}  {'optimum':>9s}"
          f"{'tf ms':>8s}{'(50,30)':>9s}{'speed-up':>9s}{'ex px':>7s}{'ey px':>7s}"
          f"   {'(15,9): tf ms':>13s}{'ex':>6s}{'ey':>6s}", file=out)
    for name, f, key, _, paper in rows:
        opt = f"({f[f'{key}_search_size']:.0f},{f[f'{key}_corr_size']:.0f})"
        cells = (f"{name:28s}{f[f'{key}_cycle_s']:8.2f}{f[f'{key}_design_s']:8.2f}"
                 f"{f[f'{key}_sweep_s']:8.2f}  {opt:>9s}{f[f'{key}_tf_ms']:8.3f}"
                 f"{f[f'{key}_ref_tf_ms']:9.3f}{f[f'{key}_speedup']:8.1f}x"
                 f"{f[f'{key}_ex_px']:7.2f}{f[f'{key}_ey_px']:7.2f}")
        if paper is not None:
            cells += f"   {paper[0]:13.3f}{paper[1]:6.2f}{paper[2]:6.2f}"
        print(cells, file=out)
    for name, _, _, result, _ in rows:
        sig = result.analysis.significant
        print(f"{name}: Table 3 ({result.analysis.method}) "
              + "; ".join(f"{r} 99 % [{', '.join(s['99'])}] 95 % [{', '.join(s['95'])}]"
                          for r, s in sig.items()), file=out)
    return fig


if __name__ == "__main__":
    bench_tuner()
