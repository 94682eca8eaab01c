"""up: start the five services as supervised child processes, with an embedded Zenoh router.

``vistrack up [LAUNCH.yaml] [--camera SOURCE] [--fps F] [--size WxH] [--loop] [--duration S]``
plus the Zenoh flags. The launch file (default ``deploy/local.yaml``) names the robot, the
router's listen endpoints and, per service, its flags and restart policy; it is validated
strictly and every error names the file, the line, the key and what is allowed.

* Unless ``-e/--connect`` names an existing router, a Zenoh router runs inside this process,
  listening on ``tcp/127.0.0.1:7447`` (``-l`` to change); every service connects to it with
  ``-e ENDPOINT --no-multicast-scouting --robot ID``, and so can any tool.
  ``-c`` configures the embedded router (with ``-e``: the launcher's own session);
  ``-m`` sets the services' session mode.
* Start-up is downstream first (fuzzy-controller, motion-estimation, preprocessing,
  auto-tuner); a service declares its liveliness token ``vistrack/<robot>/alive/<service>``
  once it is ready (kernels and control surface loaded or compiled, inputs subscribed), and
  the camera starts once every other token is up and their inputs have subscribers, so no
  frame is sent before its consumers can take it. ``vistrack up: ready (N services)`` is
  printed when all N tokens are up. On a first run the tracker's kernels are compiled here
  first (said on stderr, then every 15 s until done; half a minute to two minutes), the
  services starting meanwhile and loading them from the cache once they are compiled.
* Each child's stdout and stderr are printed line by line, prefixed ``[service-name]``.
* A child that exits is restarted by its policy (``never``, ``on-failure``, ``always``) with
  exponential back-off, reset once it has run ``reset_after`` seconds. A service that hangs
  (no answer to its status query, its loop busy on one input, or its liveliness token gone,
  for its ``hang_timeout``) is killed and restarted the same way. Once every service is
  ready, one warmed-up spare process waits: a restarted service becomes it, ready in about a
  second rather than the ~2.5 s of a new interpreter's imports and numba's first load.
* ``--camera SOURCE`` replaces the camera's ``--source`` and drops the launch file's
  ``--loop`` (give ``--loop`` to keep replaying); ``--fps`` and ``--size`` replace the
  camera's. ``--camera none`` starts the other services without the camera, for frames
  from elsewhere (``vistrack replay`` of a recorded ``camera/frame`` stream). A ``device:N``
  camera is opened once before anything starts: a missing one is an error (exit 1). A
  camera that exits 0 under ``never`` or ``on-failure`` (a file source without ``--loop``
  has been processed, a simulator's scenario ended) ends the run, as do ``--duration``,
  Ctrl-C and SIGTERM; one that exits with an error under ``never`` (a video cut short, a
  failed device) ends it as a run failure (exit 1).
* Stopping sends SIGTERM to every child's process group (the ``ros2`` bridge's once the
  others have exited: it passes on the controller's last command, a stop), SIGKILL to what
  is left after 3 s, and closes the router. Children also get SIGTERM if the launcher dies (Linux
  ``PR_SET_PDEATHSIG``).

Exit codes: 0 clean stop, 1 start-up or run failure, 2 bad command line or launch file.
The library behind it (:func:`~.launchfile.load_launch`, :class:`~.supervisor.Launcher`) is
what ``vistrack demo`` uses.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import signal
import sys
import threading
import time
from collections.abc import Iterator
from types import FrameType
from typing import Any

from ...common.bus import (
    STOP_SIGNALS,
    BusError,
    add_zenoh_args,
    install_signal_handlers,
)
from ...common.sources import MIN_FPS, SourceError, is_live, probe_device
from ..usage import add_number, add_path, plural, print_error
from .launchfile import (
    LaunchError,
    LaunchSpec,
    any_port,
    camera_source,
    check_service_flags,
    default_launch,
    load_launch,
)
from .router import (
    listen_endpoints,
    router_config,
)
from .supervisor import Launcher, compile_kernels

# -- the command line ------------------------------------------------------------------------

def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_path(parser, "launch", example="deploy/local.yaml", nargs="?", metavar="LAUNCH.yaml",
             help="launch file (default: deploy/local.yaml)")
    parser.add_argument("--camera", metavar="SOURCE",
                        help="the camera's source: file:PATH, device:N, a stream's URL "
                             "(rtsp://..., http://...), builtin, sim[:SCENARIO] or "
                             "ros2:TOPIC; drops the launch file's --loop. 'none': no "
                             "camera (frames come from elsewhere, e.g. vistrack replay)")
    add_number(parser, "--fps", lo=MIN_FPS, hi=1000, or_zero=True, metavar="F",
               help="the camera's frames per second (its --fps), %(allowed)s")
    parser.add_argument("--size", metavar="WxH",
                        help="the camera's frame size (its --size: each side 8..4096, "
                             "16..4096 for sim)")
    parser.add_argument("--loop", action="store_true",
                        help="with --camera: replay a file source forever, start a sim "
                             "scenario again when it ends (else either ends the run)")
    add_number(parser, "--duration", lo=0, hi=1e6, lo_open=True, unit="s", metavar="S",
               help="end the run after S seconds, %(allowed)s")
    # the launch file's range (0.1 .. 3600): 0.05 here was taken, then failed "not ready"
    add_number(parser, "--ready-timeout", lo=0.1, hi=3600, unit="s", metavar="S",
               help="longest wait for the services at start-up, %(allowed)s (default: the "
                    "launch file's ready_timeout)")
    add_zenoh_args(parser)
    # None = not given: the launch file's robot then applies
    parser.set_defaults(robot=None)


def launch_from_args(args: argparse.Namespace) -> LaunchSpec:
    """The launch file of ``args`` with the command line's overrides applied.

    Raises
    ------
    LaunchError, BusError
        A bad launch file or flag combination (exit code 2).
    """
    launch = load_launch(args.launch) if args.launch else default_launch()
    overridden = launch.with_camera(source=args.camera, fps=args.fps, size=args.size,
                                    loop=args.loop)
    if overridden is not launch and overridden.service("camera") is not None:
        # the camera's flags with --camera/--fps/--size applied
        camera = overridden.service("camera")
        assert camera is not None
        problem = check_service_flags("camera", list(camera.flags))
        if problem and args.camera is not None and problem.startswith("--source "):
            # the camera's flag, given as up's: name the one the user typed
            problem = "--camera " + problem.removeprefix("--source ")
        if problem:
            raise LaunchError(problem)
    launch = overridden
    changes: dict[str, Any] = {}
    if args.robot is not None:
        changes["robot"] = args.robot
    if args.mode == "router":
        # each service then tried to listen on 7447 (a router's default), and all but the
        # first found it taken: a start-up failure
        raise LaunchError("-m router: the services cannot all be routers (the embedded "
                          "router, or -e ROUTER, routes for them): allowed peer (the "
                          "default) or client")
    if args.listen:
        if args.connect:
            raise LaunchError("-l/--listen sets the embedded router's endpoints, and "
                              "-e/--connect replaces that router: give one of them")
        for k, endpoint in enumerate(args.listen):
            if endpoint in args.listen[:k]:
                # Zenoh tried to listen there twice: "another process listens there", exit 1
                raise LaunchError(f"-l {endpoint} is given twice: give each endpoint once")
            if any_port(endpoint):
                # the services were told to connect to port 0: 'nothing answers there'
                raise LaunchError(f"-l {endpoint}: the services connect to the router's "
                                  "endpoints, so give it a port of its own, not 0")
        changes["listen"] = tuple(args.listen)
        router_config(list(args.listen))  # a malformed endpoint is a usage error
    if args.ready_timeout is not None:
        changes["ready_timeout"] = args.ready_timeout
    if args.config is not None:
        router_config(None, args.config)  # a missing or invalid file is a usage error
    if args.config is not None and not args.listen and not args.connect:
        # the config file decides where the router listens
        changes["listen"] = tuple(listen_endpoints(router_config(None, args.config)))
    return dataclasses.replace(launch, **changes)


def check_camera(launch: LaunchSpec) -> None:
    """A ``device:N`` camera, or a network stream's URL, is opened (and let go) before any
    service starts: a missing camera is one line and exit 1 now, not a crash loop once
    everything else runs.

    Raises
    ------
    SourceError
        Naming the device.
    """
    source = camera_source(launch)
    if source is not None and is_live(source):
        probe_device(source)


def main(args: argparse.Namespace) -> int:
    try:
        launch = launch_from_args(args)
    except (LaunchError, BusError) as e:
        print_error("up", e)
        return 2
    try:
        check_camera(launch)
    except SourceError as e:  # no such camera: a start-up failure, not a bad command line
        print_error("up", e)
        return 1
    stop = threading.Event()
    restore = install_signal_handlers(stop)
    try:
        return _run(launch, args, stop)
    except (LaunchError, BusError) as e:
        print_error("up", e)
        return 1
    finally:
        restore()


@contextlib.contextmanager
def _interrupting() -> Iterator[None]:
    """SIGINT, SIGTERM and SIGHUP raise KeyboardInterrupt within: a first run's compile of the
    kernels (a long call in this thread) ends at once. The handlers that only set the stop
    event were run between the compiler's bytecodes and nothing looked at the event: Ctrl-C
    or SIGTERM took effect 45 to 50 s later, when the compile was done (systemd's
    TimeoutStopSec of the shipped unit is 15 s)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum: int, frame: FrameType | None) -> None:
        raise KeyboardInterrupt

    previous = {sig: signal.signal(sig, interrupt) for sig in STOP_SIGNALS}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _run(launch: LaunchSpec, args: argparse.Namespace, stop: threading.Event) -> int:
    launcher = Launcher(launch, connect=args.connect, router_config=args.config,
                        multicast_scouting=not args.no_multicast_scouting, mode=args.mode,
                        stop_event=stop, spare=True)
    try:
        # the router first: tools can connect (and a taken port is said) at once, not after
        # a first run's half minute of compiling; the services start during the compile
        launcher.open()
        with _interrupting():
            compile_kernels("up", start=launcher.start)
    except KeyboardInterrupt:  # a stop request during the compile: stopped, as at start-up
        launcher.stop()
        print("vistrack up: stopped while compiling the tracker's kernels (exit 0)",
              file=sys.stderr, flush=True)
        return 0
    except BaseException:
        launcher.stop()
        raise
    with launcher:
        if launcher.wait_ready():
            launcher.emit(f"vistrack up: ready ({plural(len(launch.services), 'service')})")
            deadline = time.monotonic() + args.duration if args.duration else None
            code = launcher.run_until(deadline=deadline)
        else:  # Ctrl-C during start-up: said as any other stop (it ended on "stopping ...")
            code = 0
    try:
        print(f"vistrack up: stopped (exit {code})", flush=True)
    except OSError:
        pass  # stdout closed (piped into head): the exit code still tells
    return code
