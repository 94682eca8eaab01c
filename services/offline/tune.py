"""``vistrack tune``: the auto-tuner's experiment over recorded frames, offline (no Zenoh).

Runs the paper's 2^(5-1) design (Table 2 levels, E = ABCD, randomised run order) on a buffer of
frames, analyses it (Table 3: what is significant at 99 % and 95 % for t1, tf, ex, ey), sweeps
SEARCH_SIZE 10..20 x CORR_SIZE 5..15 with Table 4's other values (Figures 5 to 7, as PNG with
``--out``) and picks the optimum: the fastest windows whose errors against the reference
windows (50, 30) stay within ``--tolerance`` px. Exactly the code the auto-tuner service runs.

The buffer is the first ``--max-frames`` frames (default 30, the service's buffer);
``--bounce`` fills it from a shorter sequence by playing it back and forth. Frames keep their
size unless ``--resize`` is given (the paper used 256x256; the time grows with the area).
``--format json`` prints the ``tuner/report`` fields. ``--search exhaustive`` times the paper's
plain SSD search (every displacement scored in full) instead of the default pruned one, so the
times and the optimum are the paper's; the motion, and so ex and ey, are the same either way.
``--replicates N`` (N >= 2) times every design run N times, independently and in a completely
randomised order, and tests the effects against that pure error instead of the paper's
unreplicated analysis (Lenth's method, or ``--method anova``); the responses shown are the
per-run means.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import itertools
import json
import sys
import time
from pathlib import Path
from typing import TextIO

import numpy as np

from ...common.params import FACTORS
from ...common.sources import SourceError, VideoCutShort, open_files, parse_size
from ..auto_tuner.experiment import DEFAULT_REPEATS, METHODS, RESPONSES, bounce
from ..auto_tuner.sensitivity import (
    BUFFER_RANGE,
    DEFAULT_MEGAPIXELS,
    DEFAULT_STEP,
    DEFAULT_TOLERANCE,
    MEGAPIXELS_RANGE,
    MIN_FRAMES,
    STEP_RANGE,
    TOLERANCE_RANGE,
    TuneResult,
    frames_within,
    new_seed,
    tune,
)
from ..kernels import warm_up_kernels
from ..usage import (
    add_number,
    add_path,
    add_search_flag,
    add_tracker_flags,
    params_from_args,
    rewrites_lines,
    say_on_stderr,
)
from .track import offline_main

UNITS = {"t1": "ms", "tf": "ms", "ex": "px", "ey": "px"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("frames", nargs="*", metavar="FRAMES",
                        help="a video file, a folder of images (by name, f2 before f10), a glob, "
                             "or image files in order; none (or 'builtin') runs the built-in "
                             "generated sequence")
    add_number(parser, "--seed", lo=0, hi=2**63 - 1, integer=True, default=None, metavar="N",
               help="seed of the design's run order, %(allowed)s (default: a fresh one, "
                    "printed)")
    add_path(parser, "--out", kind="folder", example="tune-report", metavar="DIR", default=None,
             help="write the plots (half-normal, main effects, interactions, sweep heat "
                  "maps) as PNG into DIR")
    parser.add_argument("--format", choices=("text", "json"), default="text",
                        help="text tables, or the tuner/report fields as JSON (default text)")
    add_number(parser, "--tolerance", lo=TOLERANCE_RANGE[0], hi=TOLERANCE_RANGE[1],
               default=DEFAULT_TOLERANCE, metavar="PX",
               help="largest mean error ex, ey against the reference windows (50, 30) the "
                    f"optimum may have, %(allowed)s px (default {DEFAULT_TOLERANCE})")
    parser.add_argument("--resize", metavar="WxH", default=None,
                        help="resize every frame, each side 8..8192 (default: keep the input "
                             "size)")
    add_number(parser, "--max-frames", lo=BUFFER_RANGE[0], hi=BUFFER_RANGE[1], integer=True,
               default=30, metavar="N",
               help="frames in the buffer, %(allowed)s (default 30, as the service keeps)")
    add_number(parser, "--max-megapixels", lo=MEGAPIXELS_RANGE[0], hi=MEGAPIXELS_RANGE[1],
               default=DEFAULT_MEGAPIXELS, metavar="MP",
               help="work budget: the experiment runs on the latest frames of the buffer whose "
                    f"pixels fit, at least {MIN_FRAMES}; %(allowed)s (default "
                    f"{DEFAULT_MEGAPIXELS:g}: 30 frames of 1280x720, 15 of 1920x1080, as the "
                    "service)")
    parser.add_argument("--bounce", action="store_true",
                        help="fill the buffer by playing a shorter sequence back and forth")
    add_number(parser, "--repeats", lo=1, hi=20, integer=True, default=DEFAULT_REPEATS,
               metavar="N", help="timing passes, %(allowed)s; each frame's least disturbed "
                                 f"time is kept (default {DEFAULT_REPEATS})")
    add_number(parser, "--step", lo=STEP_RANGE[0], hi=STEP_RANGE[1], integer=True,
               default=DEFAULT_STEP, metavar="PX",
               help=f"sweep grid step, %(allowed)s (default {DEFAULT_STEP}: every distinct "
                    "window)")
    add_search_flag(parser)
    add_tracker_flags(parser)
    parser.add_argument("--method", choices=METHODS, default=None,
                        help="significance test of the unreplicated design: Lenth's PSE, or "
                             "ANOVA with the inactive effects pooled (default lenth)")
    add_number(parser, "--replicates", lo=1, hi=20, integer=True, default=1, metavar="N",
               help="independent timings of every design run, %(allowed)s, in a completely "
                    "randomised order; N >= 2 tests the effects against that pure error "
                    "(default 1: the paper's unreplicated design)")
    parser.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                        help="progress line on stderr (default: when stderr is a terminal; "
                             "else a plain line every 30 s of a long run)")


def check_args(args: argparse.Namespace) -> None:
    """The check across flags (the ranges are declared with the flags)."""
    if args.replicates > 1 and args.method is not None:
        raise ValueError(f"--method {args.method} tests the unreplicated design; with "
                         f"--replicates {args.replicates} the effects are tested against pure "
                         "error")


def read_buffer(args: argparse.Namespace
                ) -> tuple[list[np.ndarray], str, VideoCutShort | None, int]:
    """The frames to tune on, per FRAMES, --resize, --max-frames and --bounce, the error
    of a video cut short (its header announces more frames than it holds), or None: the tuning
    runs on the frames it holds, and the error is said once the results are out, as
    ``vistrack track`` says it after its frames; and how many frames the buffer offered.

    Without ``--bounce`` only the latest frames the cycle runs on are kept as they are read
    (those within ``--max-megapixels``, :func:`.frames_within`): all ``--max-frames`` were,
    and the budget cut them afterwards (1000 frames of 4096x4096 passed 3 GB in 7 s)."""
    size = parse_size(args.resize, "--resize") if args.resize is not None else None
    source = open_files(args.frames, size)
    frames: list[np.ndarray] = []
    cut: VideoCutShort | None = None
    kept: collections.deque[np.ndarray] = collections.deque()
    read = 0
    try:
        for frame in itertools.islice(iter(source), args.max_frames):
            if not read and not args.bounce:
                kept = collections.deque(maxlen=frames_within(
                    args.max_frames, frame.shape[:2], args.max_megapixels))
            kept.append(frame)
            read += 1
    except VideoCutShort as e:
        cut = e
    frames = list(kept)
    if not frames:
        raise SourceError("no frame was read")
    what = source.description
    # too few frames: the rule, what the source gave, and why where a video was cut short
    gave = f"{what} gave {read}" + (f" ({cut})" if cut is not None else "")
    if args.bounce and len(frames) < args.max_frames:
        if len(frames) < 2:
            raise SourceError(f"--bounce needs at least 2 frames: {gave}")
        what += f", played back and forth to {args.max_frames} frames"
        frames = bounce(frames, args.max_frames)
    if len(frames) < 2:
        raise SourceError(f"tuning needs at least 2 frames (t1 and tf): {gave}")
    return frames, what, cut, max(read, len(frames))


class ProgressLine:
    """``vistrack tune: design [#####.....] 8/16`` rewritten in place on a stream."""

    def __init__(self, stream: TextIO, width: int = 30) -> None:
        self.stream = stream
        self.width = width
        self.phase = ""

    def __call__(self, phase: str, done: int, total: int) -> None:
        if phase != self.phase and self.phase:
            self.stream.write("\n")
        self.phase = phase
        filled = self.width * done // max(total, 1)
        self.stream.write(f"\rvistrack tune: {phase:6s} [{'#' * filled}"
                          f"{'.' * (self.width - filled)}] {done}/{total}")
        self.stream.flush()

    def close(self) -> None:
        if self.phase:
            self.stream.write("\n")
            self.stream.flush()


class ProgressNotes:
    """Where no line can be rewritten (a log, a pipe): a plain line every ``every`` s of a
    long cycle, ``vistrack tune: design 984/6408 after 60 s, about 6 min to go``. Nothing
    for a cycle shorter than that: a 10-minute tune (the largest windows, 20 replicates)
    printed nothing at all on a non-terminal (range-limits sweep)."""

    def __init__(self, stream: TextIO, every: float = 30.0) -> None:
        self.stream = stream
        self.every = every
        self.start = self.last = time.monotonic()
        self.phase, self.phase_start = "", self.start

    def __call__(self, phase: str, done: int, total: int) -> None:
        now = time.monotonic()
        if phase != self.phase:
            self.phase, self.phase_start = phase, now
        if now - self.last < self.every or done <= 0:
            return
        self.last = now
        left = (now - self.phase_start) / done * (total - done)
        self.stream.write(f"vistrack tune: {phase} {done}/{total} after {now - self.start:.0f}"
                          f" s, about {_duration(left)} to go in {phase}\n")
        self.stream.flush()

    def close(self) -> None:
        pass


def _duration(seconds: float) -> str:
    return f"{seconds:.0f} s" if seconds < 120 else f"{seconds / 60:.0f} min"


def _fmt(v: float) -> str:
    return f"{v:9.3f}"


def print_text(result: TuneResult, what: str, out: TextIO) -> None:
    """The human-readable report: design, aliases, effects, Table 3, sweep and optimum."""
    rep = result.to_report()
    d = result.run.design
    w, h = result.size
    replicates = rep["replicates"]
    frames = (f"{result.frames} frames" if result.frames == result.offered else
              f"the latest {result.frames} of {result.offered} frames (work budget "
              f"{result.max_megapixels:g} MP)")
    print(f"# vistrack tune: {what}; {frames} {w}x{h}; seed {rep['seed']}; "
          f"{result.sweep.base.search} SSD search; timing passes {result.repeats}; "
          + (f"{replicates} replicates of every design run; " if replicates > 1 else "")
          + f"{result.seconds['total']:.1f} s", file=out)
    print(f"# tracker: {result.sweep.base.tracker_said()}; windows: the design's and the "
          "sweep's", file=out)

    gens = ", ".join(f"{k} = {v}" for k, v in d.generators.items())
    order = ("in run order" if replicates == 1 else
             f"in the order the runs first ran; responses: mean of {replicates} replicates")
    print(f"\n## Design: 2^({d.k}-{len(d.generators)}) fractional factorial, {gens}, "
          f"I = {' = '.join(d.defining_relation)}, resolution {d.resolution}; {order}",
          file=out)
    print("factors: " + ", ".join(f"{i + 1} {n}" for i, n in enumerate(rep["factors"])),
          file=out)
    print(" run  std" + "".join(f"{k:>7d}" for k in range(1, d.k + 1))
          + "".join(f"{n:>9s}" for n in ("t1 ms", "tf ms", "ex px", "ey px", "npi")), file=out)
    values = d.with_levels()
    for k, std in enumerate(rep["order"]):
        measured = "".join(_fmt(rep["responses"][n][std]) for n in (*RESPONSES, "npi_mean"))
        print(f"{k + 1:4d} {std + 1:4d}" + "".join(f"{v:7g}" for v in values[std]) + measured,
              file=out)

    print("\n## Alias structure (paper numbers: 1 MAX_FEAT_NUM, 2 THRES_PERCENT, 3 SEARCH_SIZE, "
          "4 CORR_SIZE, 5 UNGROUP_SIZE)", file=out)
    chains = rep["aliases"]
    print("  " + "   ".join(f"{t} = {' = '.join(c)}" for t, c in chains.items()), file=out)

    method = rep["method"] if replicates == 1 else "pure error"
    print(f"\n## Effects (high minus low level; {method} significance: "
          "** 99 %, * 95 %)", file=out)
    print("term" + "".join(f"{n + ' ' + UNITS[n]:>13s}" for n in RESPONSES), file=out)
    for term in rep["effects"]["tf"]:
        cells = []
        for n in RESPONSES:
            sig = rep["significant"][n]
            mark = "**" if term in sig["99"] else "*" if term in sig["95"] else ""
            cells.append(f"{rep['effects'][n][term]:+11.3f}{mark:2s}")
        print(f"{term:>4s}" + "".join(cells), file=out)

    print(f"\n## Table 3: significant terms ({method})", file=out)
    at99 = {n: ", ".join(rep["significant"][n]["99"]) or "-" for n in RESPONSES}
    width = max(24, 2 + max(map(len, at99.values())))  # a replicated tf can list all 15
    print(f"{'output':8s}{'99 %':{width}s}{'95 %'}", file=out)
    for n in RESPONSES:
        if result.analysis.results.get(n) is None:
            # no scale to test against: said, not shown as a response with no effect
            print(f"{n:8s}not testable: half or more of its effects are exactly 0, no scale "
                  "to test them against", file=out)
            continue
        print(f"{n:8s}{at99[n]:{width}s}{', '.join(rep['significant'][n]['95']) or '-'}",
              file=out)
    if replicates > 1:
        _print_pure_error(rep, out)

    sw = result.sweep
    print(f"\n## Sensitivity sweep: {', '.join(f'{k}={v:g}' for k, v in sw.fixed.items())}; "
          "rows SEARCH_SIZE, columns CORR_SIZE", file=out)
    for n in RESPONSES:
        grid = getattr(sw, n)
        print(f"{n} ({UNITS[n]})", file=out)
        print("      " + "".join(f"{c:>8d}" for c in sw.corr_sizes), file=out)
        for s, row in zip(sw.search_sizes, grid, strict=True):
            print(f"{s:6d}" + "".join(f"{v:8.3f}" for v in row), file=out)
    ref = sw.reference
    print(f"reference ({sw.reference_windows[0]}, {sw.reference_windows[1]}): "
          f"t1 {ref.t1:.3f} ms, tf {ref.tf:.3f} ms", file=out)

    opt = result.optimum
    # a choice that misses the tolerance says so in its heading: below it, read first, its
    # speed-up looked like an optimum's
    print("\n## Optimum" if opt.within_tolerance
          else "\n## Closest to the reference (no swept window within the tolerance)", file=out)
    print("  " + " ".join(f"{k}={opt.params[k]:g}" for k in FACTORS), file=out)
    print(f"  t1 {opt.t1:.3f} ms, tf {opt.tf:.3f} ms ({opt.speedup:.1f}x faster than "
          f"the reference), ex {opt.ex:.3f} px, ey {opt.ey:.3f} px", file=out)
    print(f"  {opt.reason}", file=out)


def _print_pure_error(rep: dict, out: TextIO) -> None:
    """Which responses were tested against pure error, on how many degrees of freedom."""
    errors = rep["pure_error"]
    for n in RESPONSES:
        if n in errors:
            e = errors[n]
            print(f"{n}: ANOVA against pure error, {rep['replicates']} independent timings of "
                  f"each of the {len(rep['design'])} runs: {e['df']} df, within-run standard "
                  f"deviation {e['ms'] ** 0.5:.4f} {UNITS[n]}", file=out)
        else:
            print(f"{n}: identical in every replicate (no timing in it), so no pure error: "
                  "Lenth's method on the run means", file=out)


def run(args: argparse.Namespace, out: TextIO | None = None, err: TextIO | None = None) -> int:
    # the streams of the moment (not of import time: pytest swaps them per test)
    out = sys.stdout if out is None else out
    err = sys.stderr if err is None else err
    check_args(args)
    if args.out:
        try:  # fail now rather than after the experiment
            Path(args.out).mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise ValueError(f"--out {args.out}: {e.strerror or e}") from None
    base = params_from_args(args)  # the search every timed run uses
    frames, what, cut, offered = read_buffer(args)
    seed = new_seed() if args.seed is None else args.seed
    # a first run compiles: said, not silent
    warm_up_kernels(say_on_stderr("tune", err), params=base)
    show = rewrites_lines(err) if args.progress is None else args.progress
    progress: ProgressLine | ProgressNotes | None = ProgressLine(err) if show else \
        ProgressNotes(err) if args.progress is None else None
    start = time.perf_counter()
    try:
        result = tune(frames, seed, tolerance=args.tolerance, step=args.step,
                      repeats=args.repeats, method=args.method or "lenth", base=base,
                      progress=progress, replicates=args.replicates,
                      max_megapixels=args.max_megapixels)
    finally:
        if progress is not None:
            progress.close()
    result = dataclasses.replace(result, offered=offered)  # the frames read, not those kept
    report = result.to_report()
    # the report first: plots that cannot be written (a full disk) cost only the plots, not
    # a run of many minutes, whose result was not printed at all
    if args.format == "json":
        print(json.dumps(report, allow_nan=False), file=out, flush=True)
    else:
        print_text(result, what, out)
        out.flush()
    if args.out:
        from ..auto_tuner.plots import write_plots  # matplotlib only when plots are asked for

        try:
            write_plots(report, args.out)
        except OSError as e:
            raise ValueError(f"--out {args.out}: {e.strerror or e} (the report above is "
                             "complete; the plots were not written)") from None
        if args.format != "json":
            print(f"\n# plots in {args.out} ({time.perf_counter() - start:.1f} s in all)",
                  file=out)
    if cut is not None:
        raise cut
    return 0


def main(args: argparse.Namespace) -> int:
    return offline_main("tune", run, args)
