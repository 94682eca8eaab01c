"""camera: publish 8-bit grey frames from a file camera, a device, or the built-in sequence.

Reads   ``vistrack/<robot>/motion/estimate``  (pacing to the pipeline, and end of file)
        ``vistrack/<robot>/control/cmd_vel``  (simulator only: it moves the robot)
Writes  ``vistrack/<robot>/camera/frame``, ``vistrack/<robot>/sim/pose`` (simulator only)

Sources: ``file:PATH`` (video, image folder or glob), ``device:N``, ``builtin`` (a generated
textured scene), ``sim[:SCENARIO]`` (the robot simulator, see :mod:`.simcam`).

``--fps F`` paces frames at F per second. ``--fps 0`` (the default for files) runs "as fast as
consumers allow": each frame is sent once the estimate of the previous one is back (or after
``--ack-timeout`` s), so a file camera loses no frame however slow the pipeline. A file camera
without ``--loop`` exits 0 after its last frame has been processed.
"""

from __future__ import annotations

import argparse
import itertools
import logging
import sys
import time
from collections.abc import Iterable, Iterator

import numpy as np

from ...common.bus import Node
from ...common.messages import Estimate, Frame, MessageError
from ..runtime import add_service_args, ready, serve
from .simcam import make_simulator, run_sim
from .sources import BUILTIN, SourceError, open_device, open_files, parse_size

log = logging.getLogger("vistrack.camera")

LOOP_CACHE_BYTES = 256 * 1024 * 1024


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--source", default=BUILTIN, metavar="SOURCE",
                        help="file:PATH (video, image folder or glob), device:N, builtin (the "
                             "built-in generated sequence, default), or sim[:SCENARIO] (the "
                             "robot simulator; scenarios: default, sideways, approach, steps, "
                             "still, lighting, or a YAML file)")
    parser.add_argument("--fps", type=float, default=0.0,
                        help="frames per second; 0 = as fast as the pipeline takes them "
                             "(default 0)")
    parser.add_argument("--loop", action="store_true", help="replay a file source forever")
    parser.add_argument("--size", metavar="WxH", default=None,
                        help="resize frames (default: native size)")
    parser.add_argument("--ack-timeout", type=float, default=1.0, metavar="S",
                        help="with --fps 0, longest wait for a frame's estimate (default 1 s)")
    sim = parser.add_argument_group("simulator source")
    sim.add_argument("--lockstep", action="store_true",
                     help="render a frame only after the previous frame's command (or, with "
                          "--no-control, its estimate): deterministic runs")
    sim.add_argument("--no-control", action="store_true",
                     help="ignore control/cmd_vel: the robot stands still")
    sim.add_argument("--texture", metavar="PATH", default=None,
                     help="target texture image (default: built-in procedural texture)")
    sim.add_argument("--noise", type=float, default=0.0, metavar="SIGMA",
                     help="Gaussian sensor noise, grey levels (default 0)")
    sim.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    add_service_args(parser)


def open_source(spec: str, size: tuple[int, int] | None, loop: bool) -> Iterator[np.ndarray]:
    """Frames of a SOURCE spec; raises SourceError naming what is wrong."""
    if spec.startswith("device:"):
        try:
            index = int(spec.split(":", 1)[1])
        except ValueError:
            raise SourceError(f"{spec!r}: device index must be an integer, e.g. device:0") from None
        return open_device(index, size)
    path = spec[len("file:"):] if spec.startswith("file:") else spec
    frames: Iterable[np.ndarray] = open_files([path] if path else [], size)
    if not loop:
        return iter(frames)
    # a looping source is decoded once and replayed from memory while it fits comfortably,
    # so the camera spends its CPU on publishing, not on decoding the same files again
    cached: list[np.ndarray] = []
    total = 0
    for f in frames:
        cached.append(f)
        total += f.nbytes
        if total > LOOP_CACHE_BYTES:
            return itertools.chain.from_iterable(itertools.repeat(frames))
    return itertools.chain.from_iterable(itertools.repeat(cached))


def _wait_for_estimate(node: Node, stamp_ns: int, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while not node.stop.is_set():
        item = node.recv(timeout=max(0.0, deadline - time.monotonic()))
        if item is None:
            return False
        try:
            if Estimate.decode(item[1]).stamp_ns >= stamp_ns:
                return True
        except MessageError as e:
            node.status.reject(e)
    return False


def loop(node: Node, args: argparse.Namespace) -> int:
    size = parse_size(args.size) if args.size else None
    if args.source.split(":", 1)[0] == "sim":
        return run_sim(node, args, make_simulator(args, size))
    frames = open_source(args.source, size, args.loop)
    paced = args.fps > 0
    # estimates tell when a frame has been through the pipeline: pacing with --fps 0, and the
    # end of a file either way
    node.subscribe(node.keys.estimate, latest=True)
    ready(node)
    period = 1.0 / args.fps if paced else 0.0
    next_t = time.perf_counter()
    try:
        return _run(node, args, frames, paced, period, next_t)
    except SourceError as e:
        log.error("%s", e)
        return 2


def _run(node: Node, args: argparse.Namespace, frames: Iterator[np.ndarray], paced: bool,
         period: float, next_t: float) -> int:
    stamp = 0
    for seq, image in enumerate(frames):
        if node.stop.is_set():
            return 0
        if paced:
            next_t += period
            delay = next_t - time.perf_counter()
            if delay > 0:
                node.stop.wait(delay)
            else:
                next_t = time.perf_counter()  # late: do not burst to catch up
        stamp = time.time_ns()
        node.publish(node.keys.frame, Frame.from_image(image, seq=seq, stamp_ns=stamp).encode(),
                     reliable=False)
        node.status.extra["frames"] = seq + 1
        if paced:
            while node.recv(timeout=0.0) is not None:
                pass  # estimates only matter at the end: consume them, they are no drops
        elif not _wait_for_estimate(node, stamp, args.ack_timeout):
            node.status.extra["ack_timeouts"] = node.status.extra.get("ack_timeouts", 0) + 1
    if stamp and not node.stop.is_set():
        _wait_for_estimate(node, stamp, max(args.ack_timeout, 1.0))
    log.info("end of %s after %d frames", args.source, node.status.extra.get("frames", 0))
    return 0


def main(args: argparse.Namespace) -> int:
    try:
        if args.fps < 0 or args.fps > 1000:
            raise SourceError(f"--fps {args.fps:g} is out of range: allowed 0..1000")
        if args.size:
            parse_size(args.size)
        if args.source.split(":", 1)[0] == "sim":
            make_simulator(args, parse_size(args.size) if args.size else None)
        elif not args.source.startswith("device:"):
            open_source(args.source, None, False)  # fail fast on a bad path, before Zenoh
    except (SourceError, ValueError) as e:
        print(f"vistrack camera: error: {e}", file=sys.stderr)
        return 2
    return serve("camera", args, loop)
