"""camera: publish 8-bit grey frames from a file camera, a device, or the built-in sequence.

Reads   ``vistrack/<robot>/motion/estimate``  (pacing to the pipeline, and end of file)
        ``vistrack/<robot>/preprocessing/done`` (pacing with ``--fps 0 --in-flight`` > 1)
        ``vistrack/<robot>/control/cmd_vel``  (simulator only: it moves the robot)
Writes  ``vistrack/<robot>/camera/frame``, ``vistrack/<robot>/sim/pose`` (simulator only)

Sources: ``file:PATH`` (video, image folder or glob), ``device:N``, a network stream's URL
(``rtsp://...``, ``http://...``: an IP camera, read as a device is), ``builtin`` (a generated
textured scene), ``sim[:SCENARIO]`` (the robot simulator, see :mod:`.simcam`), ``ros2:TOPIC``
(a ROS 2 camera's ``sensor_msgs/msg/Image`` topic over ``rmw_zenoh``, see :mod:`.ros2cam`).

``--fps F`` paces frames at F per second. ``--fps 0`` (the default for files) runs "as fast as
consumers allow": frame n is sent once motion-estimation has published frame n - ``--in-flight``
and, with more than one in flight, pre-processing has published frame n-1 (it is free again, so
nothing overwrites a frame waiting at its input: ``preprocessing/done``, a few bytes, says so;
an estimate of frame n-1 says so too, for a pre-processing that does not publish it), or after
``--ack-timeout`` s. With the default, 1, a file camera loses no frame however slow the
pipeline: a frame whose estimate does not come within ``--ack-timeout`` s is sent again, the
same bytes (seq and stamp), up to :data:`RESENDS` times, before the camera goes on without it
(status ``extra``: ``resent``,
``ack_timeouts``). Zenoh may lose the one message in flight on a loaded machine, on any hop;
motion-estimation answers a frame it has already tracked with the same estimate again. With 2,
pre-processing works on frame n while motion-estimation tracks frame n-1 (about 1.5x the
frames a second), but a frame can still be overwritten at motion-estimation's latest-only input
when that process is slow to wake (counted in its ``dropped``): a frame waits there for it
while the next is pre-processed. With ``--fps 0`` frames are sent reliable (BLOCK) whatever
``--in-flight``, so nothing else is lost: at most that many queue.
A file camera without ``--loop`` exits 0 after its last frame has been processed.
"""

from __future__ import annotations

import argparse
import collections
import itertools
import logging
import select
import sys
import time
from collections.abc import Iterable, Iterator

import numpy as np

from ...common import rmw_zenoh as rmw
from ...common.bus import Node
from ...common.messages import MAX_SIDE, encode_frame, peek_int
from ...common.sources import (
    BUILTIN,
    MIN_FPS,
    DeviceFrames,
    FileFrames,
    SourceError,
    VideoCutShort,
    device_index,
    is_live,
    is_stream,
    open_device,
    open_files,
    open_stream,
    parse_size,
    redacted,
)
from ..runtime import (
    Faults,
    add_service_args,
    paced,
    ready,
    serve,
    setup_logging,
    wait_for_consumers,
)
from ..usage import add_number, add_path, plural, print_error, say_on_stderr
from .ros2cam import default_domain, is_ros2, run_ros2, topic_of
from .simcam import make_simulator, run_sim

log = logging.getLogger("vistrack.camera")

LOOP_CACHE_BYTES = 256 * 1024 * 1024
#: Frame sides the camera sends, px: a ``camera/frame`` carries at most MAX_SIDE a side.
FRAME_SIDES = (8, MAX_SIDE)
#: Times a file camera in lockstep (``--fps 0 --in-flight 1``) sends a frame again whose
#: estimate has not come within ``--ack-timeout``, before it goes on without it (a service
#: restarted, or is gone): one loss on the way is made good, and a pipeline that stopped
#: answering costs (1 + RESENDS) x ``--ack-timeout`` a frame.
RESENDS = 2


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--source", default=BUILTIN, metavar="SOURCE",
                        help="file:PATH (video, image folder or glob), device:N, a network "
                             "stream's URL (an IP camera's rtsp://..., http://...), builtin (the "
                             "built-in generated sequence, default), or sim[:SCENARIO] (the "
                             "robot simulator; scenarios: default, sideways, approach, steps, "
                             "still, lighting, or a YAML file), or ros2:TOPIC (a ROS 2 camera's "
                             "sensor_msgs/msg/Image topic over rmw_zenoh, e.g. "
                             "ros2:/camera/image_raw; CompressedImage when the topic ends in "
                             "/compressed)")
    add_number(parser, "--fps", lo=MIN_FPS, hi=1000, or_zero=True, default=0.0, metavar="F",
               help="frames per second, %(allowed)s; 0 = as fast as the pipeline takes them "
                    "(default 0; the simulator's 0 is 30, or with --lockstep its simulated "
                    "clock's 30 frames a second, as fast as the pipeline takes them)")
    parser.add_argument("--loop", action="store_true",
                        help="replay a file source forever; with sim, start the scenario "
                             "again when it ends (else the camera exits 0 there)")
    parser.add_argument("--size", metavar="WxH", default=None,
                        help="resize frames, each side 8..4096 (16..4096 for sim), the largest "
                             "camera/frame (default: native size)")
    add_number(parser, "--in-flight", lo=1, hi=16, integer=True, default=1, metavar="N",
               help="with --fps 0, most frames sent and not yet estimated, %(allowed)s "
                    "(default 1: no frame lost; 2: pre-processing and tracking overlap, "
                    "faster, but a frame may be dropped at motion-estimation's input)")
    parser.add_argument("--start-on-stdin", action="store_true",
                        help="say ready and send the first frame only after a line on standard "
                             "input (the launcher starts the camera with the other services "
                             "and releases it once they are ready)")
    add_number(parser, "--ack-timeout", lo=0, hi=3600, lo_open=True, default=1.0, metavar="S",
               help="with --fps 0, longest wait for a frame's estimate, %(allowed)s "
                    f"(default 1 s); with --in-flight 1 the frame is then sent again, up to "
                    f"{RESENDS} times, before the camera goes on")
    sim = parser.add_argument_group("simulator source")
    sim.add_argument("--lockstep", action="store_true",
                     help="render a frame only after the previous frame's command (or, with "
                          "--no-control, its estimate): deterministic runs")
    sim.add_argument("--no-control", action="store_true",
                     help="ignore control/cmd_vel: the robot stands still")
    add_path(sim, "--texture", example="texture.png", metavar="PATH", default=None,
             help="target texture image (default: built-in procedural texture)")
    add_number(sim, "--noise", lo=0, hi=100, default=0.0, metavar="SIGMA",
               help="Gaussian sensor noise, grey levels, %(allowed)s (default 0)")
    add_number(sim, "--seed", lo=0, hi=2**63 - 1, integer=True, default=0, metavar="N",
               help="noise seed, %(allowed)s (default 0)")
    ros = parser.add_argument_group("ROS 2 source")
    add_number(ros, "--domain", lo=rmw.DOMAIN_RANGE[0], hi=rmw.DOMAIN_RANGE[1], integer=True,
               default=default_domain(), metavar="ID",
               help="ROS domain id of ros2:TOPIC, %(allowed)s (default: $ROS_DOMAIN_ID, else 0)")
    add_service_args(parser)


#: The simulator's own flags: (flag, dest, default), refused with another source.
SIM_ONLY = (("--lockstep", "lockstep", False), ("--no-control", "no_control", False),
            ("--texture", "texture", None), ("--noise", "noise", 0.0), ("--seed", "seed", 0))


class Skipped:
    """The frames a file source could not give while it ran (an image that does not read,
    one of another size than the first): each left out, said once per file as a warning (a
    looping source meets it every pass) and counted (status ``extra.skipped``, once
    :meth:`attach` gave the node); the frames after it go on. They used to end the camera,
    and the run with it, at the first such frame."""

    def __init__(self) -> None:
        self.node: Node | None = None
        self.count = 0
        self._said: set[str] = set()

    def attach(self, node: Node) -> None:
        self.node = node
        if self.count:
            node.status.extra["skipped"] = self.count

    def add(self, n: int) -> None:
        """Count ``n`` more frames left out (said already)."""
        self.count += n
        if self.node is not None:
            self.node.status.extra["skipped"] = self.count

    def __call__(self, e: SourceError) -> None:
        self.add(1)
        text = str(e)
        if text not in self._said:
            self._said.add(text)
            log.warning("%s: frame skipped, the frames after it go on", text)


def open_source(spec: str, size: tuple[int, int] | None, loop: bool,
                skip: Skipped | None = None) -> Iterator[np.ndarray]:
    """Frames of a SOURCE spec (not ``sim``); raises SourceError naming what is wrong, and
    with ``skip``, a file source's frames that cannot be given mid-run are left to it."""
    if spec.startswith("device:"):
        return open_device(device_index(spec), size)
    if is_stream(spec):
        return open_stream(spec, size)
    if spec == "file:":
        raise SourceError("--source 'file:' names no file: give file:PATH (a video, an image "
                          "folder or a glob)")
    path = spec[len("file:"):] if spec.startswith("file:") else spec
    frames: Iterable[np.ndarray] = open_files([path], size)
    if isinstance(frames, FileFrames):
        frames.size_flag, frames.skip = "--size", skip
    if not loop:
        return iter(frames)
    # a looping source is decoded once and replayed from memory while it fits comfortably,
    # so the camera spends its CPU on publishing, not on decoding the same files again. A
    # video cut short (a recording that lost its end) loops the frames it holds: said once,
    # as a warning, where a single pass ends with the error
    # (frames skipped just before it, frame): the skips are counted again as each pass
    # comes to them, so a frame left out leaves its seq out every pass, as a source read
    # each pass does (counted all at once while caching, before anything was sent, they
    # moved every seq: a pass began at seq 2, with no gap anywhere)
    cached: list[tuple[int, np.ndarray]] = []
    before = seen = skip.count if skip is not None else 0
    total = 0
    try:
        for f in frames:
            now = skip.count if skip is not None else 0
            cached.append((now - seen, f))
            seen = now
            total += f.nbytes
            if total > LOOP_CACHE_BYTES:
                if skip is not None:
                    skip.count = before  # read again from the start: skipped again there
                return Looped(_passes(frames, path))
    except VideoCutShort as e:
        say_on_stderr("camera")(f"warning: {e}; looping the {len(cached)} frames it holds")
    trailing = (skip.count - seen) if skip is not None else 0
    if skip is not None:
        skip.count = before
    return Looped(_replayed(cached, trailing, skip))


class Looped(Iterator[np.ndarray]):
    """A ``--loop`` source's frames, pass after pass, with :attr:`cuts` the cuts before the
    frame last given: one more at each pass after the first whose first frame differs from
    the frame before it (the last of the pass before). Such a frame does not follow that
    frame in the scene, and the camera says so on the wire (``camera/frame``'s ``cuts``) so
    that downstream starts a new track there rather than tracking the jump back to the
    start. One image looped is no cut: the same frame again is a still scene."""

    def __init__(self, passes: Iterator[tuple[np.ndarray, bool]]) -> None:
        self._passes = passes
        self._held: tuple[np.ndarray, bool] | None = None
        self._last: np.ndarray | None = None
        self.cuts = 0

    def __iter__(self) -> Looped:
        return self

    def __next__(self) -> np.ndarray:
        if self._held is not None:
            (frame, starts), self._held = self._held, None
        else:
            frame, starts = next(self._passes)
        if starts and self._last is not None and not np.array_equal(frame, self._last):
            self.cuts += 1
        self._last = frame
        return frame

    def peek(self) -> np.ndarray:
        """The next frame, read now and given again by the next ``next``."""
        if self._held is None:
            self._held = next(self._passes)
        return self._held[0]


def _replayed(cached: list[tuple[int, np.ndarray]], trailing: int,
              skip: Skipped | None) -> Iterator[tuple[np.ndarray, bool]]:
    """The cached frames, pass after pass, each after counting the frames skipped before it
    (``trailing``: those after the last) in ``skip``; with each, whether it starts a pass
    after the first."""
    later = False
    while True:
        for i, (gap, frame) in enumerate(cached):
            if gap and skip is not None:
                skip.add(gap)
            yield frame, later and not i
        later = True
        if trailing and skip is not None:
            skip.add(trailing)


def _passes(frames: Iterable[np.ndarray], path: str) -> Iterator[tuple[np.ndarray, bool]]:
    """``frames`` again and again, decoded each pass (a source too large to keep), each with
    whether it starts a pass after the first: a video cut short is played to where it ends
    each time, which the log says once.

    Raises
    ------
    SourceError
        When a pass gives no frame: its files were removed or became unreadable (a USB stick
        or a network share gone). It went round in silence for ever, a core busy."""
    warned = later = False
    while True:
        given = 0
        try:
            for frame in frames:
                given += 1
                yield frame, later and given == 1
        except VideoCutShort as e:
            if not warned:
                log.warning("%s; looping the frames it holds", e)
                warned = True
        if not given:
            raise SourceError(f"{path}: a pass of --loop gave no frame (its files were "
                              "removed or cannot be read any more)")
        later = True


class _Acks:
    """How far the pipeline has got: the newest ``seq`` seen on each watched key.

    An estimate, or pre-processing's ``preprocessing/done``, of frame k acknowledges every
    frame up to k (a frame overwritten at a latest-only input never gets one of its own); an
    estimate of frame k also says that pre-processing is done with it. Only ``seq`` is read
    (:func:`peek_int`: both keep the frame's); a payload without one is counted as rejected.
    Not ``stamp_ns``, as once: after a step of the wall clock back (an NTP correction) every
    frame sent looked acknowledged already, and a run meant to lose no frame went at 17,390
    frames a second.

    Pre-processing's progress once came from ``preprocessing/frame`` itself: the camera
    received every pre-processed frame (64 KiB at 256x256, 900 KiB at 1280x720) to read one
    stamp. Unpaced at 1280x720 the few bytes of ``preprocessing/done`` took the pipeline from
    ~4640 to ~4300 us of CPU a frame (the camera ~940 -> ~750) and ~320 to ~355 estimates a
    second; at 256x256 they changed nothing (the camera still wakes for two messages a frame).
    """

    def __init__(self, node: Node, keys: tuple[str, ...]) -> None:
        self.node = node
        self.newest = dict.fromkeys(keys, -1)
        self.sent = -1  # seq of the newest frame sent: nothing later can be acknowledged
        for key in keys:
            node.subscribe(key, latest=True)

    def wait(self, need: dict[str, int], timeout: float) -> bool:
        """Consume acknowledgements until ``newest[key] >= seq`` for every ``key: seq`` of
        ``need``; False after ``timeout`` s (or on stop). ``timeout`` 0 only consumes what is
        pending."""
        deadline = time.monotonic() + timeout
        while any(self.newest[k] < v for k, v in need.items()) and not self.node.stop.is_set():
            item = self.node.recv(timeout=max(0.0, deadline - time.monotonic()))
            if item is None:
                return False
            self._note(*item)
        return all(self.newest[k] >= v for k, v in need.items())

    def drain(self) -> None:
        """Consume what is pending (paced: acknowledgements only matter at the end, and an
        unread one would count as dropped when the next overwrites it)."""
        while (item := self.node.recv(timeout=0.0)) is not None:
            self._note(*item)

    def consume(self, seconds: float) -> None:
        """Consume acknowledgements as they come for ``seconds`` (or until stop): how a paced
        camera waits for its next frame's slot. Drained once a frame, two estimates that came
        within one period (a frame slow through the pipeline, the next one fast, on a busy
        machine) left the first to be overwritten, counted as dropped (2 at 20 fps in CI)."""
        deadline = time.monotonic() + seconds
        while not self.node.stop.is_set():
            left = deadline - time.monotonic()
            if left <= 0:
                return
            item = self.node.recv(timeout=left)
            if item is not None:
                self._note(*item)

    def _note(self, key: str, payload: bytes) -> None:
        seq = peek_int(payload, "seq")
        if seq is None:
            self.node.status.reject(f"{key}: no valid seq")
        elif seq > self.sent:  # it would stand for every frame still to come
            self.node.status.reject(f"{key}: seq {seq} is after the newest frame sent "
                                    f"({self.sent})")
        else:
            self.newest[key] = max(self.newest[key], seq)
            if key == self.node.keys.estimate and self.node.keys.pre_done in self.newest:
                done = self.node.keys.pre_done  # tracked, so pre-processed
                self.newest[done] = max(self.newest[done], seq)


def _is_sim(args: argparse.Namespace) -> bool:
    return args.source.split(":", 1)[0] == "sim"


def _size(args: argparse.Namespace) -> tuple[int, int] | None:
    return (parse_size(args.size, "--size", sides=FRAME_SIDES) if args.size is not None
            else None)


def released(node: Node, args: argparse.Namespace) -> bool:
    """With ``--start-on-stdin``, wait for a line on stdin: True once it came (or without the
    flag); False if stdin ends first (the launcher is gone) or the node is stopped."""
    if not getattr(args, "start_on_stdin", False):
        return True
    while not node.stop.is_set():
        if select.select([sys.stdin], [], [], 0.1)[0]:
            if sys.stdin.readline():
                return True
            # the launcher is gone, or a unit file gave /dev/null: it only said "stopped"
            log.warning("--start-on-stdin: standard input ended before the line that starts "
                        "the frames (run by hand or from a unit file, leave the flag out)")
            return False
    return False


def loop(node: Node, args: argparse.Namespace, frames: Iterator[np.ndarray] | None = None,
         skipped: Skipped | None = None) -> int:
    """Publish the frames of ``--source`` (``frames``, already opened by :func:`main`, the
    frames it leaves out counted by ``skipped``), once :func:`released`."""
    if frames is None:
        if _is_sim(args):
            sim = make_simulator(args)
            return run_sim(node, args, sim) if released(node, args) else 0
        if is_ros2(args.source):
            return run_ros2(node, args, _size(args)) if released(node, args) else 0
        frames = open_source(args.source, _size(args), args.loop)
        if isinstance(frames, DeviceFrames):  # opened here: let go here (main's are its own)
            try:
                return loop(node, args, frames, skipped)
            finally:
                frames.close()
    if not released(node, args):
        return 0
    # estimates tell when a frame has been through the pipeline (pacing with --fps 0, and the
    # end of a file either way); preprocessing/done when pre-processing is free again
    window = 1 if args.fps > 0 else args.in_flight
    acks = _Acks(node, (node.keys.estimate,) if window == 1
                 else (node.keys.estimate, node.keys.pre_done))
    node.advertise(node.keys.frame, reliable=_reliable(args))
    ready(node)
    # a recording loses its first frames if it plays before anyone listens; a live device
    # is like any camera: its frames are for whoever is there
    if not is_live(args.source) and not wait_for_consumers(node, node.keys.frame):
        return 0  # stopped before anyone subscribed
    try:
        return _run(node, args, frames, acks, window, skipped)
    except SourceError as e:
        log.error("%s", e)
        return 2


def _run(node: Node, args: argparse.Namespace, frames: Iterator[np.ndarray], acks: _Acks,
         window: int, skipped: Skipped | None = None) -> int:
    """Publish every frame: at ``--fps``, or (``--fps 0``) frame n once pre-processing has
    published frame n-1 and motion-estimation frame n-window. A frame the source left out
    (``skipped``) takes its ``seq`` with it: the gap says a frame is missing there, as a
    drop does, and the tracker predicts over it (the frame after one that was left out was
    sent as its ``seq``, and tracked as one step where two had passed)."""
    keys = node.keys
    period = 1.0 / args.fps if args.fps > 0 else 0.0
    next_t = time.perf_counter()
    sent: collections.deque[int] = collections.deque(maxlen=window)  # seqs of the last sent
    lockstep = _lockstep(args, window)
    reliable = _reliable(args)
    last: list[bytes] = []
    faults = Faults(node, log)
    device = frames if isinstance(frames, DeviceFrames) else None
    if device is not None:
        device.stop_with = node.stop  # a stop ends a wait for a frame that does not come
    looped = frames if isinstance(frames, Looped) else None
    try:
        for sent_before, image in enumerate(frames):
            seq = sent_before + (skipped.count if skipped is not None else 0)
            if node.stop.is_set():
                log.info("stopped after %s", plural(sent_before, "frame"))
                return 0
            if period:
                if sent_before:  # the first frame goes at once (it waited a whole period)
                    next_t = paced(node, next_t, period, acks.consume)
                if node.stop.is_set():  # stopped while it waited: no frame more
                    log.info("stopped after %s", plural(sent_before, "frame"))
                    return 0
            elif sent:
                need = {keys.estimate: sent[0]} if len(sent) == window else {}
                if window > 1:
                    need[keys.pre_done] = sent[-1]
                if not _wait(node, acks, need, args.ack_timeout, last if lockstep else []):
                    sent.clear()  # lost downstream (a service restarted): go on
            # a device's frame: when it was read from the device (its newest, not when sent)
            stamp = device.capture_ns if device is not None else time.time_ns()
            node.status.extra["frames"] = sent_before + 1
            cuts = looped.cuts if looped is not None else 0
            if not faults.call(keys.frame, seq, _publish, node, image, seq, stamp, last, reliable,
                               cuts):
                continue  # skipped (counted in failed): nothing to wait for
            acks.sent = seq
            sent.append(seq)
            if period:
                acks.drain()
    except VideoCutShort:
        # the frames a video cut short holds are out: their estimates are waited for, as
        # at a file's end, before the error that ends the camera
        _last_estimate(node, args, acks, last if lockstep else [])
        raise
    _last_estimate(node, args, acks, last if lockstep else [])
    log.info("end of %s after %s", redacted(args.source),
             plural(node.status.extra.get("frames", 0), "frame"))
    return 0


def _last_estimate(node: Node, args: argparse.Namespace, acks: _Acks, last: list[bytes]
                   ) -> None:
    """Wait for the estimate of the last frame sent (a file's end), if one was sent."""
    if acks.sent >= 0 and not node.stop.is_set():
        _wait(node, acks, {node.keys.estimate: acks.sent}, max(args.ack_timeout, 1.0), last)


def _wait(node: Node, acks: _Acks, need: dict[str, int], timeout: float,
          last: list[bytes]) -> bool:
    """:meth:`_Acks.wait`, and while ``need`` is not met, ``last`` (the frame in flight, in
    lockstep) sent again up to :data:`RESENDS` times, ``timeout`` s apart. False (counted in
    ``ack_timeouts``) if it still is not met."""
    extra = node.status.extra
    for attempt in range(RESENDS + 1):
        if attempt:
            node.publish(node.keys.frame, last[0], reliable=True)  # only in lockstep
            extra["resent"] = extra.get("resent", 0) + 1
            log.info("no estimate of frame %s within %g s: sent again",
                     extra.get("frames", 0) - 1, timeout)
        if acks.wait(need, timeout):
            return True
        if not last or node.stop.is_set():
            break
    extra["ack_timeouts"] = extra.get("ack_timeouts", 0) + 1
    return False


def _lockstep(args: argparse.Namespace, window: int) -> bool:
    """Whether the camera runs in lockstep: ``--fps 0 --in-flight 1``, not a live device.

    In lockstep the frame in flight is sent again should its estimate not come (a live
    device's next frame is worth more than the one lost), and frames are published reliable
    (BLOCK, as with more in flight, :func:`_reliable`): with one frame in flight that never
    queues a backlog, and every subscriber gets every frame, a recorder or a viewer too.
    Latest-only (BLOCK_FIRST) dropped the second
    frame of a run at a recorder now and then: the first large messages a new subscriber
    receives by shared memory took 4 to 10 ms here (the segment being mapped), and a frame
    that finds its predecessor still in flight on a link for 1 ms is dropped.
    """
    return window == 1 and _reliable(args)


def _reliable(args: argparse.Namespace) -> bool:
    """Whether the frames are published reliable (BLOCK): with ``--fps 0``, whatever
    ``--in-flight``, but not from a live device. The camera sends frame n only once the
    pipeline has answered frame n - ``--in-flight``, so BLOCK queues at most that many; and
    every subscriber gets every frame of a file's run, and every estimate (the stages answer
    a frame sent BLOCK with BLOCK). With two in flight and latest-only (BLOCK_FIRST) frames,
    a frame that found its predecessor still on a link was lost uncounted now and then (a CI
    run lost a run's last estimate: no later ``seq`` showed the gap)."""
    return not args.fps and not is_live(args.source)


def _publish(node: Node, image: np.ndarray, seq: int, stamp: int, last: list[bytes],
             reliable: bool, cuts: int = 0) -> None:
    last[:] = [encode_frame(image, seq=seq, stamp_ns=stamp, cuts=cuts)]
    node.publish(node.keys.frame, last[0], reliable=reliable)


def check_args(args: argparse.Namespace) -> None:
    """``--size`` and ``--source`` (a file source's first frame is read: a text file named
    .avi or a damaged first image is found here, where ``vistrack up`` used to start every
    service and then end the run on the camera's exit; no device is opened), so
    ``vistrack camera`` and a launch file's camera flags fail before anything starts."""
    if _is_sim(args):
        make_simulator(args)
        return
    given = [flag for flag, dest, default in SIM_ONLY if getattr(args, dest) != default]
    if given:  # they were ignored in silence: --texture /nonexistent with a file source ran
        raise SourceError(f"{', '.join(given)}: for --source sim only (the robot simulator), "
                          f"not {redacted(args.source)}")
    size = _size(args)
    if is_ros2(args.source):
        topic_of(args.source)
        return
    if args.source.startswith("device:"):
        device_index(args.source)
        return
    if is_stream(args.source):
        return
    frames = open_source(args.source, size, False)
    try:
        _first_frame_read(frames)
    finally:
        close = getattr(frames, "close", None)  # a generator: a video's capture let go now
        if close is not None:
            close()


def _first_frame_read(frames: Iterator[np.ndarray]) -> Iterator[np.ndarray]:
    """``frames`` with its first frame read now: a video that does not decode, a device that
    does not open, or frames too large for a ``camera/frame`` are a one-line error before the
    service starts, not a log line."""
    # a loop is kept as it is, its first frame read ahead: it counts the camera's cuts
    first = frames.peek() if isinstance(frames, Looped) else next(frames)
    h, w = first.shape
    if max(w, h) > MAX_SIDE:
        raise SourceError(f"frames are {w}x{h}: a camera/frame carries at most {MAX_SIDE} px "
                          f"a side; give --size to scale them")
    return frames if isinstance(frames, Looped) else itertools.chain([first], frames)


def main(args: argparse.Namespace) -> int:
    if _is_sim(args) or is_ros2(args.source):
        return serve("camera", args, loop, publishes_frames=True)
    skipped = Skipped()
    # the source is read before the service starts (its first frame; a --loop source kept
    # in memory whole): its grey depth and float range decisions are logged from here on,
    # where they were lost before serve() set the log up
    setup_logging(args.log_level)
    try:
        source = open_source(args.source, _size(args), args.loop, skipped)
        frames = _first_frame_read(source)
        if isinstance(source, DeviceFrames):
            # a live camera's first frame is stale once the pipeline is up: the device
            # delivers a fresh one then
            frames = source
    except SourceError as e:
        print_error("camera", e)
        # no such camera is a start-up failure (1); a file that cannot be read, bad input (2)
        return 1 if is_live(args.source) else 2
    try:
        def run(node: Node, a: argparse.Namespace) -> int:
            skipped.attach(node)
            return loop(node, a, frames, skipped)

        return serve("camera", args, run, publishes_frames=True)
    finally:
        if isinstance(source, DeviceFrames):
            source.close()  # its reading thread lets the device go
