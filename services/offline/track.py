"""``vistrack track``: the tracker over recorded frames, offline (no Zenoh).

Runs exactly the library code the services run (:class:`vistrack.common.vision.Tracker`) and
prints one row per frame: Table 1's columns (``table``), JSON lines with every field of
``motion/estimate`` (``jsonl``), or CSV without the feature list (``csv``).
"""

from __future__ import annotations

import argparse
import csv
import itertools
import json
import sys
from collections.abc import Callable
from typing import TextIO

from ...common.params import ParamError
from ...common.sources import SourceError, open_files, parse_size
from ...common.vision import Estimate, Tracker
from ...common.vision.tracker import over_budget_said
from ..kernels import warm_up_kernels
from ..usage import add_param_flags, params_from_args, print_error, say_on_stderr

CSV_FIELDS = ["seq", "npi", "xc", "yc", "xe", "ye", "dx", "dy", "scale", "t_ms", "valid"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("frames", nargs="*", metavar="FRAMES",
                        help="a video file, a folder of images (by name, f2 before f10), a glob, "
                             "or image files in order; none (or 'builtin') runs the built-in "
                             "generated sequence")
    add_param_flags(parser)
    parser.add_argument("--resize", metavar="WxH", default=None,
                        help="resize every frame, each side 8..8192 (default: keep the input "
                             "size)")
    parser.add_argument("--format", choices=("table", "jsonl", "csv"), default="table",
                        help="output: Table 1 columns, JSON lines, or CSV (default table)")


def _table_row(e: Estimate) -> str:
    valid = "yes" if e.valid else "no"
    return (f"{e.seq:5d} {e.npi:4d} {e.xc:8.2f} {e.yc:8.2f} {e.xe:9.1f} {e.ye:9.1f} "
            f"{e.dx:8.2f} {e.dy:8.2f} {e.scale:7.4f} {e.t_ms:8.3f} {valid:>5s}")


def run(args: argparse.Namespace, out: TextIO | None = None) -> int:
    out = sys.stdout if out is None else out  # the stream of the moment, not of import time
    params = params_from_args(args)
    size = parse_size(args.resize, "--resize") if args.resize is not None else None
    source = open_files(args.frames, size)
    # the first frame before any output: a source that gives none (a file that is no video)
    # is one line on stderr, not a table's header on stdout and then the error; and before
    # the kernels' compile, which a bad source need not wait for
    frames = iter(source)
    first = next(frames, None)
    if first is None:
        raise SourceError("no frame was read")
    # numba compile (said on stderr) or cache load, so t1 measures the tracker, not the JIT
    warm_up_kernels(say_on_stderr("track"), params=params)
    tracker = Tracker(params)
    # the count and the paper's t1 and tf, not every estimate: held with its features, the
    # estimates of a 12000-frame video took 653 MB, growing with the video's length
    frames_read, t1, tf_sum = 0, float("nan"), 0.0
    writer = None
    if args.format == "table":
        print(f"# {source.description}; max_features={params.max_features} "
              f"thres_percent={params.thres_percent:g} search_size={params.search_size} "
              f"corr_size={params.corr_size} ungroup_size={params.ungroup_size} "
              f"subpixel={params.subpixel} search={params.search} levels={params.levels} "
              f"refine_size={params.refine_size} tracker={params.tracker}",
              file=out)
        print("#   seq  NPI       xc       yc        xe        ye       dx       dy   scale"
              "     t_ms valid", file=out)
    elif args.format == "csv":
        writer = csv.writer(out, lineterminator="\n")
        writer.writerow(CSV_FIELDS)
    warned = False
    for frame in itertools.chain([first], frames):
        e = tracker.process(frame)
        if frames_read == 0:
            t1 = e.t_ms
        else:
            tf_sum += e.t_ms
        frames_read += 1
        if tracker.over_budget and not warned:
            # said as the service says it: the table's NPI and valid do not show it
            warned = True
            print(f"vistrack track: warning: {over_budget_said(e.seq, tracker.over_budget)} "
                  "(said once; the summary counts them as budget)", file=sys.stderr, flush=True)
        if args.format == "table":
            print(_table_row(e), file=out)
        elif args.format == "jsonl":
            print(json.dumps(e.as_dict(), allow_nan=False), file=out)
        else:
            assert writer is not None
            writer.writerow([getattr(e, k) for k in CSV_FIELDS])
    if not frames_read:
        raise SourceError("no frame was read")
    if args.format == "table":
        tf_text = f"{tf_sum / (frames_read - 1):.3f} ms" if frames_read > 1 else "- (one frame)"
        reasons = ", ".join(f"{k} {v}" for k, v in tracker.lost_by.items()
                            if v and k not in ("left", "cut"))
        print(f"# frames={frames_read} t1={t1:.3f} ms tf={tf_text} "
              f"lost={tracker.lost_total} (rejected {tracker.rejected_total}"
              + (f": {reasons}" if reasons else "")
              + f") redetections={tracker.redetections} followed={tracker.followed} "
              f"exposure_steps={tracker.exposure_steps} zoom_warps={tracker.zoom_warps}",
              file=out)
    return 0


def offline_main(name: str, run: Callable[[argparse.Namespace], int],
                 args: argparse.Namespace) -> int:
    """Run an offline command: bad input is one line ``vistrack NAME: error: ...`` and exit
    code 2; a closed pipe (``vistrack NAME ... | head``) is a normal end; an output that cannot
    be written (a full disk, /dev/full) is one line and exit 1 (it was a traceback)."""
    try:
        code = run(args)
        # a buffered output's last writes fail only when flushed (a full disk: ENOSPC), which
        # the interpreter's end did in silence, exit 1 and no line (tested with
        # PYTHONUNBUFFERED=1, where each write fails at once, it passed)
        sys.stdout.flush()
        return code
    except (SourceError, ParamError, ValueError) as e:
        print_error(name, e)
        return 2
    except BrokenPipeError:
        return 0
    except OSError as e:  # with a file name: that file's; without: the output stream's
        said = e.strerror or str(e)
        print_error(name, f"{e.filename}: {said}" if e.filename else
                    f"writing the output: {said}")
        return 1


def main(args: argparse.Namespace) -> int:
    return offline_main("track", run, args)
