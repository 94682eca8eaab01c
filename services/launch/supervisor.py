"""The process supervisor behind ``vistrack up`` and ``vistrack demo``.

:class:`Launcher` starts the services of a :class:`~.launchfile.LaunchSpec` as child
processes (downstream first; the camera with them, but it says ready and sends its first frame
only once its consumers are ready and subscribed), with an
embedded Zenoh router unless it connects to one; it watches their liveliness tokens, prefixes
their output with their names, restarts them by policy with exponential back-off, kills and
restarts (by the same policy) a service that hangs, and stops them all (SIGTERM, then
SIGKILL) leaving no process behind.
"""

from __future__ import annotations

import argparse
import ctypes
import gc
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from types import TracebackType
from typing import IO, Any

import zenoh

from ...common.bus import (
    SUPERVISED_ENV,
    alive_services,
    config_from_args,
    open_session,
    token_names,
)
from ...common.keys import Keys
from ...common.messages import MessageError, unpack
from ...common.sources import is_live
from .launchfile import LaunchError, LaunchSpec, ServiceSpec
from .router import (
    start_router,
)

#: Start order: consumers before producers, the camera last (see ``Launcher.start``).
LAUNCH_ORDER = ("ros2", "fuzzy_controller", "motion_estimation", "preprocessing", "auto_tuner",
                "camera")
#: Services stopped only once the others have exited: the ROS 2 bridge, which passes the
#: controller's last command (a stop) on to the robot's base.
STOPPED_LAST = ("ros2",)
#: The input (a :class:`Keys` attribute) each consumer subscribes to once it can take data.
#: Services declare their liveliness token once warmed up and subscribed (runtime.ready); the
#: camera waits for these subscriptions too, for a service that declares its token at open
#: (ARCHITECTURE.md's table of keys).
CONSUMES = {"preprocessing": "frame", "motion_estimation": "pre_frame", "auto_tuner": "frame",
            "fuzzy_controller": "estimate"}

#: The camera flag that holds its start (its ready, its first frame) until a line on its
#: stdin: the launcher starts the camera's process with the others, so that its own start-up
#: (imports, session, simulator: ~1.4 s) is done when they are ready, and releases it then.
HOLD_FLAG = "--start-on-stdin"
# Seconds between SIGTERM and SIGKILL when stopping (the whole stop stays within 5 s).
TERM_GRACE_S = 3.0
# Seconds to wait for a SIGKILLed child to be reaped, and for an output thread to drain.
KILL_WAIT_S = 1.0
# Period of the supervision loop: how soon an exit is noticed when nothing else wakes it.
TICK_S = 0.1
PR_SET_PDEATHSIG = 1
#: How long the launcher asks the router it joins for services of its robot already there, s
ALIVE_QUERY_S = 1.0
#: How long a launcher that saw another launcher of its robot id, and has the smaller Zenoh
#: id of the two, waits for the other to give way before it asks again, s
#: (:meth:`Supervisor._claim_robot`)
CLAIM_SETTLE_S = 1.0
#: How often each running service is asked for its status (hang detection), s.
STATUS_PERIOD_S = 1.0
#: A gap between two of the launcher's looks at its services longer than this, s, is the
#: launcher's own stall (it looks every TICK_S): the services are judged again after it.
STALLED_S = 2.0

# -- child processes -----------------------------------------------------------------------

def _load_libc() -> ctypes.CDLL | None:
    # loaded once in the parent: loading a library between fork and exec is not safe
    if not sys.platform.startswith("linux"):
        return None
    try:
        return ctypes.CDLL("libc.so.6", use_errno=True)
    except OSError:
        return None


_LIBC = _load_libc()


def _child_setup(parent_pid: int) -> Callable[[], None]:
    """The ``preexec_fn`` of a child: its own process group, and SIGTERM when we die."""
    def setup() -> None:
        # its own group: a terminal's Ctrl-C reaches the launcher only, which stops the
        # children in order; and killpg reaches anything a child spawns
        os.setpgid(0, 0)
        if _LIBC is not None:
            _LIBC.prctl(PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
        if os.getppid() != parent_pid:  # the launcher died before prctl took effect
            os._exit(1)
    return setup


def _client_endpoint(endpoint: str) -> str:
    """Where a local process connects to reach a router listening on ``endpoint``."""
    return re.sub(r"^(\w+)/(0\.0\.0\.0|\[::\])(?=:)",
                  lambda m: f"{m[1]}/{'127.0.0.1' if m[2] == '0.0.0.0' else '[::1]'}", endpoint)


@dataclass(frozen=True)
class ChildInfo:
    """What the launcher knows of one service (see :attr:`Launcher.children`)."""

    name: str
    pid: int | None
    restarts: int
    running: bool
    ready: bool
    returncode: int | None


@dataclass
class _Child:
    spec: ServiceSpec
    proc: subprocess.Popen[bytes] | None = None
    reader: threading.Thread | None = None
    started_at: float = 0.0
    restarts: int = 0
    failures: int = 0
    restart_at: float | None = None
    returncode: int | None = None
    ready: bool = False
    held: bool = False

    @property
    def running(self) -> bool:
        return self.proc is not None and self.returncode is None

    @property
    def finished(self) -> bool:
        """Exited for good: not running, no restart pending, not waiting to start."""
        return not self.running and self.restart_at is None and not self.held


@dataclass
class _Watch:
    """What the launcher has seen of one process of a service (hang detection)."""

    pid: int
    since: float  # when it was first seen ready (monotonic)
    asked_at: float = 0.0
    # when the first status query since its last answer was sent: its silence is judged from
    # there, not from the last answer (queried once a second, a service that answered every
    # query at once looked a second silent just before each answer, and hang_timeout 1 killed
    # a healthy motion-estimation 9 times a minute)
    pending_since: float | None = None
    busy_s: float = 0.0
    killed: bool = False


# -- the launcher ----------------------------------------------------------------------------

class Launcher:
    """Start, watch and stop the services of a :class:`LaunchSpec`::

        launch = load_launch("deploy/local.yaml").with_camera(source="sim:default")
        with Launcher(launch) as launcher:     # starts the router and the services
            launcher.wait_ready()              # every liveliness token is up
            launcher.run_until(deadline=time.monotonic() + 30)
        # leaving the block stops everything

    Spawning and supervision (``start``, ``wait_ready``, ``poll``, ``run_until``) must run on
    one long-lived thread, normally the main thread: Linux sends the parent-death signal when
    the *thread* that forked a child exits, not the process.

    Parameters
    ----------
    launch : the validated launch.
    connect : endpoints of an existing router; None starts an embedded router on
        ``launch.listen``.
    router_config : Zenoh config file of the embedded router (with ``connect``: of the
        launcher's own session, which watches the liveliness tokens).
    multicast_scouting : False disables multicast scouting in the embedded router.
    mode : Zenoh mode of the services' sessions (None: their default, peer).
    out : where the children's prefixed output and the launcher's lines go.
    stop_event : setting it makes :meth:`wait_ready` and :meth:`run_until` return (the CLI
        sets it from SIGINT/SIGTERM).
    python : interpreter of the children.
    spare : keep one warmed-up spare process (:mod:`.spare`) that a restarted service
        becomes: a restart then takes a fraction of a second instead of an interpreter's and
        numba's start-up (~2.5 s). It is started once every service is ready.
    """

    def __init__(self, launch: LaunchSpec, *, connect: list[str] | None = None,
                 router_config: str | None = None, multicast_scouting: bool = True,
                 mode: str | None = None, out: IO[str] | None = None,
                 stop_event: threading.Event | None = None,
                 python: str = sys.executable, spare: bool = False) -> None:
        self.launch = launch
        self.keys = Keys(launch.robot)
        self.stop_event = stop_event or threading.Event()
        self._connect = list(connect) if connect else None
        self._router_config = router_config
        self._multicast = multicast_scouting
        self._mode = mode
        self._out = out or sys.stdout
        self._python = python
        self._out_lock = threading.Lock()
        self._cond = threading.Condition()
        self._tokens: dict[str, float] = {}  # service -> when its token appeared (monotonic)
        self._tokens_lost: dict[str, float] = {}  # service -> when its token went (monotonic)
        self._watches: dict[str, _Watch] = {}  # service -> its process's hang watch
        self._router_lost_at: float | None = None  # when the external router went (monotonic)
        self._watched_at: float | None = None  # the last look at the services (monotonic)
        # a warmed-up process a restart becomes (see spare.py), once every service is ready
        self._use_spare = spare and any(s.restart != "never" for s in launch.services)
        self._spare: subprocess.Popen[bytes] | None = None
        order = {name: i for i, name in enumerate(LAUNCH_ORDER)}
        self._children = [_Child(s) for s in sorted(launch.services, key=lambda s: order[s.name])]
        self._session: zenoh.Session | None = None
        self._token_sub: Any = None
        self._claim: Any = None  # this launcher's token on a router it joins
        self._probes: dict[str, zenoh.Publisher] = {}  # never put: matching status only
        self._gate_deadline = 0.0
        self._end_code: int | None = None
        #: services that failed (exit code non-zero) and were not restarted: the run, ended
        #: by its camera's file or its --duration, failed (it said 0)
        self._lost: list[str] = []
        self._started = False
        self._stopped = False

    # -- public API ------------------------------------------------------------------------
    @property
    def endpoints(self) -> list[str]:
        """Endpoints the services (and any local tool) connect to."""
        if self._connect:
            return list(self._connect)
        return [_client_endpoint(e) for e in self.launch.listen]

    @property
    def session(self) -> zenoh.Session | None:
        """The launcher's Zenoh session: the embedded router, or a client of the existing one
        (``connect``); None before :meth:`start`. Tools in-process can use it."""
        return self._session

    @property
    def children(self) -> dict[str, ChildInfo]:
        """Service name (as in keys) -> its pid, restarts and state, in launch order."""
        with self._cond:
            return {c.spec.name: ChildInfo(c.spec.name, c.proc.pid if c.proc else None,
                                           c.restarts, c.running, c.ready, c.returncode)
                    for c in self._children}

    def start(self) -> None:
        """Open the router (or connect to one), then start every service; the camera is held
        (:data:`HOLD_FLAG`: it says ready and sends frames only when released; a live device
        starts only then) until the others are ready and subscribed to their inputs (checked
        by :meth:`wait_ready` and :meth:`poll`), or after ``ready_timeout``.

        Raises
        ------
        BusError
            If the router cannot listen or the existing router cannot be reached.
        """
        if self._started:
            return
        self._started = True
        self.open()
        assert self._session is not None
        self._token_sub = self._session.liveliness().declare_subscriber(
            self.keys.alive_any(), self._on_token, history=True)
        for key in {getattr(self.keys, CONSUMES[c.spec.name]) for c in self._children
                    if c.spec.name in CONSUMES}:
            self._probes[key] = self._session.declare_publisher(key)
        self._gate_deadline = time.monotonic() + self.launch.ready_timeout
        for child in self._children:
            if child.spec.name == "camera" and len(self._children) > 1:
                child.held = True  # released by _release_held once its consumers are up
                if _can_hold(child.spec):
                    self._spawn(child)  # starts now, sends nothing until released
            else:
                self._spawn(child)

    def open(self) -> None:
        """Open the router (or connect to the existing one) without starting any service;
        :meth:`start` does it if it has not been done. Call it first to hold the port (or
        learn it is taken) before long work such as a first run's compile. Idempotent.

        Raises
        ------
        BusError
            As :meth:`start`.
        """
        if self._session is None:
            self._session = self._open_session()

    def wait_ready(self, timeout: float | None = None) -> bool:
        """Block until every service's liveliness token is up; False if ``stop_event`` was set.

        Raises
        ------
        LaunchError
            After ``timeout`` s (default: the launch file's ``ready_timeout``), naming the
            services not ready, or when a service exits before it is ready.
        """
        limit = self.launch.ready_timeout if timeout is None else timeout
        deadline = time.monotonic() + limit
        # the camera's gate counts from here too: a first run's compile may lie since start()
        self._gate_deadline = max(self._gate_deadline, deadline)
        while not self.stop_event.is_set():
            self._step(startup=True)
            if self._end_code is not None or all(c.ready or c.finished for c in self._children):
                return True
            if time.monotonic() > deadline:
                late = [c.spec.cli_name for c in self._children if not (c.ready or c.finished)]
                raise LaunchError(f"not ready after {limit:g} s: {', '.join(late)} (no "
                                  f"liveliness token on {self.keys.alive_any()})")
            self._wait(TICK_S)
        return False

    def poll(self) -> int | None:
        """Reap exited children, apply their restart policies, start what is due.

        Returns
        -------
        code : None while the run goes on; the run's exit code once it should end (0 when
            the camera has finished its file, 1 if a service failed and was not restarted
            meanwhile; 1 when every service has exited and one failed).
        """
        self._step(startup=False)
        return self._end_code

    def run_until(self, stop: threading.Event | None = None,
                  deadline: float | None = None) -> int:
        """Supervise until the run ends, ``stop`` or ``stop_event`` is set, or the monotonic
        ``deadline`` passes; return the exit code (0 for a stop, and for the deadline unless
        a service failed and was not restarted: 1)."""
        while True:
            code = self.poll()
            if code is not None:
                return code
            if self.stop_event.is_set() or (stop is not None and stop.is_set()):
                return 0
            now = time.monotonic()
            if deadline is not None and now >= deadline:
                if self._lost:
                    self._log(f"duration reached; the run lost {', '.join(self._lost)}")
                    return 1
                self._log("duration reached")
                return 0
            self._wait(TICK_S if deadline is None else max(0.0, min(TICK_S, deadline - now)))

    def stop(self) -> None:
        """Stop every child (SIGTERM to its process group, SIGKILL after a grace period) and
        close the router; idempotent, within ~4 s."""
        if self._stopped:
            return
        self._stopped = True
        try:
            self._drop_spare()
            self._terminate_children()
        finally:
            self._kill_children()  # after an interruption too: never leave orphans
            self._close_session()

    def __enter__(self) -> Launcher:
        try:
            self.start()
        except BaseException:
            self.stop()
            raise
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()

    # -- sessions and liveliness -----------------------------------------------------------
    def _open_session(self) -> zenoh.Session:
        if self._connect is None:
            session = start_router(list(self.launch.listen), self._router_config,
                                   multicast_scouting=self._multicast)
            self._log(f"zenoh router listening on {', '.join(self.launch.listen)}")
            return session
        args = argparse.Namespace(mode="client", connect=self._connect, listen=None,
                                  config=self._router_config, no_multicast_scouting=True)
        session = open_session(config_from_args(args))
        self._log(f"connected to {', '.join(self._connect)}")
        try:
            self._claim_robot(session)
        except LaunchError:
            self._claim = None  # its token goes with the session
            session.close()
            raise
        return session

    def _claim_robot(self, session: zenoh.Session) -> None:
        """Declare this launcher's token (:meth:`.Keys.launcher`), then refuse to start where
        the robot id is taken on the router: its services live there
        (:meth:`_check_robot_free`), or another launcher's token is there.

        Two launchers of one robot id started at once both found no service alive (theirs
        start after the kernels' warm-up) and both ran, every key doubled. Each declares its
        token before it looks, and a token reaches the router before the query that follows
        it on the same link: of two, at least the later sees the earlier. One that sees
        another gives way, unless its Zenoh id is the smaller: then the other, which sees it
        too or runs, is given :data:`CLAIM_SETTLE_S` to go, and it starts only if the other
        has gone."""
        me = str(session.info.zid())
        self._claim = session.liveliness().declare_token(self.keys.launcher(me))
        self._check_robot_free(session)
        others = self._launchers(session, me)
        if others and min(others) > me:
            time.sleep(CLAIM_SETTLE_S)  # the other sees this one too and gives way, or runs
            others = self._launchers(session, me)
        if others:
            raise LaunchError(f"robot {self.launch.robot!r} is being launched by another "
                              f"vistrack up at {', '.join(self._connect or [])} (no service "
                              "of it live yet); give another --robot (or robot: in the "
                              "launch file), or stop it first")

    def _launchers(self, session: zenoh.Session, me: str) -> set[str]:
        """The Zenoh ids of the other launchers of this robot id on the router."""
        return token_names(session, self.keys.launcher_any(), ALIVE_QUERY_S) - {me}

    def _check_robot_free(self, session: zenoh.Session) -> None:
        """Refuse to start where services of this robot id already live on the router: a
        second vistrack up with a robot's id doubled its every key (estimates at 118 Hz), and
        each launcher killed the other's services as hung."""
        live = alive_services(session, self.keys, ALIVE_QUERY_S)
        if live:
            raise LaunchError(f"robot {self.launch.robot!r} already has live services at "
                              f"{', '.join(self._connect or [])}: {', '.join(live)}; give "
                              "another --robot (or robot: in the launch file), or stop them "
                              "first")

    def _on_token(self, sample: zenoh.Sample) -> None:
        service = str(sample.key_expr).rsplit("/", 1)[-1]
        with self._cond:
            if sample.kind == zenoh.SampleKind.PUT:
                self._tokens[service] = time.monotonic()
                self._tokens_lost.pop(service, None)
            else:
                self._tokens.pop(service, None)
                self._tokens_lost[service] = time.monotonic()
            self._cond.notify_all()

    def _close_session(self) -> None:
        session, self._session = self._session, None
        if session is None:
            return
        self._drop_probes()
        try:
            if self._token_sub is not None:
                self._token_sub.undeclare()
            if self._claim is not None:
                self._claim.undeclare()
        except zenoh.ZError:
            pass  # the session is closing anyway
        self._claim = None
        session.close()

    # -- supervision -------------------------------------------------------------------------
    def _wait(self, timeout: float) -> None:
        with self._cond:
            self._cond.wait(timeout)

    def _step(self, *, startup: bool) -> None:
        now = time.monotonic()
        with self._cond:
            for child in self._children:
                if not child.ready and child.running and \
                        self._tokens.get(child.spec.name, -1.0) >= child.started_at:
                    child.ready = True
        self._watch_hangs(now)
        for child in self._children:
            if child.running and child.proc is not None and child.proc.poll() is not None:
                self._on_exit(child, child.proc.returncode, now, startup)
            if child.restart_at is not None and now >= child.restart_at:
                child.restart_at = None
                child.restarts += 1
                self._spawn(child)
        self._release_held(now)
        if not startup:
            self._keep_spare()
        if self._end_code is None and all(c.finished for c in self._children):
            failed = [c for c in self._children if c.returncode]
            self._log("every service has exited")
            self._end_code = 1 if failed else 0

    def _release_held(self, now: float) -> None:
        held = [c for c in self._children if c.held]
        if not held:
            return
        others = [c for c in self._children if not c.held]
        waiting = [c for c in others if not c.finished]
        ready = all(c.ready for c in waiting) and self._inputs_subscribed(waiting)
        if not ready:
            if now < self._gate_deadline:
                return
            self._log("starting the camera although not every consumer is ready")
        self._drop_probes()
        for child in held:
            child.held = False
            if child.running and child.proc is not None and child.proc.stdin is not None:
                self._release(child, ready)
            elif not child.running and child.restart_at is None:
                self._spawn(child)
            # else a restart is due: it starts unheld

    def _release(self, child: _Child, ready: bool) -> None:
        """Let a camera started early (:data:`HOLD_FLAG`) say ready and send frames (its
        consumers ``ready``, else the gate's time is up: said so, not "every consumer is
        ready" a line after "not every consumer is ready")."""
        assert child.proc is not None and child.proc.stdin is not None
        try:
            child.proc.stdin.write(b"go\n")
            child.proc.stdin.close()
        except OSError:
            pass  # it exited meanwhile: its exit is handled as any other
        self._log(f"released {child.spec.cli_name} (pid {child.proc.pid}): "
                  + ("every consumer is ready" if ready else "the wait for its consumers is over"))

    def _inputs_subscribed(self, consumers: list[_Child]) -> bool:
        """Whether the input key of each of ``consumers`` has a subscriber somewhere."""
        for child in consumers:
            attr = CONSUMES.get(child.spec.name)
            probe = self._probes.get(getattr(self.keys, attr)) if attr else None
            if probe is None:
                continue
            # the 1.x stub says bool, but the binding returns a MatchingStatus
            status = probe.matching_status
            if not getattr(status, "matching", status):
                return False
        return True

    def _drop_probes(self) -> None:
        probes, self._probes = list(self._probes.values()), {}
        for probe in probes:
            try:
                probe.undeclare()
            except zenoh.ZError:
                pass  # the session is closing

    # -- hang detection ----------------------------------------------------------------------
    def _watch_hangs(self, now: float) -> None:
        """Ask every ready service for its status once a second, and SIGKILL one that has not
        answered for its ``hang_timeout``, answers that its loop has been busy on one input
        that long, or whose liveliness token has been gone that long while its process lives;
        its exit is then handled like any other (restart by policy).

        Not while the launcher has lost the router it joined (``connect``): the services are
        asked through it, and they go on without it (they talk to each other directly). A
        router gone for 3 s or more had every service of every robot on it killed as hung,
        and the runs ended (a camera is not restarted), where the pipelines had kept tracking;
        now the launcher says the router went and came back, and judges again from then."""
        last, self._watched_at = self._watched_at, now
        if last is not None and now - last > STALLED_S:
            # the launcher itself did not run (stopped, starved on a loaded machine): the
            # silence it would see is its own. 7 s of it had every healthy service of the
            # run killed as hung, and the run ended (soak test)
            self._log(f"the launcher did not run for {now - last:.1f} s (stopped, or starved "
                      "of CPU): the services are judged again from now")
            self._judge_from(now)
        if not self._router_reachable(now):
            return
        self._watch_restarts(now)
        for child in self._children:
            timeout = child.spec.hang_timeout
            if not (timeout and child.ready and child.running and child.proc is not None):
                continue
            pid = child.proc.pid
            name = child.spec.name
            with self._cond:
                watch = self._watches.get(name)
                if watch is None or watch.pid != pid:
                    watch = self._watches[name] = _Watch(pid, since=now)
                lost = self._tokens_lost.get(name)
                busy = watch.busy_s
                if not watch.killed and now - watch.asked_at >= STATUS_PERIOD_S:
                    watch.asked_at = now
                    if watch.pending_since is None:
                        watch.pending_since = now
                    ask = True
                else:
                    ask = False
                pending = watch.pending_since
            if watch.killed:
                continue
            if ask:
                self._ask_status(name, pid)
            if pending is not None and now - pending > timeout:
                seen = f"no answer to its status query for {now - pending:.1f} s"
            elif busy > timeout:
                seen = f"its loop has been busy on one input for {busy:.1f} s"
            elif lost is not None and lost >= watch.since and now - lost > timeout:
                seen = f"its liveliness token has been gone for {now - lost:.1f} s"
            else:
                continue
            watch.killed = True
            self._log(f"{child.spec.cli_name} (pid {pid}) is hung: {seen}; killing it")
            try:
                os.killpg(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass  # it exited meanwhile

    def _watch_restarts(self, now: float) -> None:
        """SIGKILL a restarted service that has not become ready within the launch's
        ``ready_timeout`` (its exit is then handled like any other): a restart that never came
        up (the spare stopped, a liveliness token another process held) was never killed,
        since only ready services are asked how they are, and the pipeline stayed down
        (more than 90 s seen). At start-up :meth:`wait_ready` has the same limit."""
        limit = self.launch.ready_timeout
        for child in self._children:
            if not (child.restarts and child.running and not child.ready
                    and child.proc is not None and not child.held
                    and now - child.started_at > limit):
                continue
            pid = child.proc.pid
            with self._cond:
                watch = self._watches.get(child.spec.name)
                if watch is not None and watch.pid == pid and watch.killed:
                    continue
                self._watches[child.spec.name] = _Watch(pid, since=now, killed=True)
            self._log(f"{child.spec.cli_name} (pid {pid}) is not ready {limit:g} s after its "
                      "restart; killing it")
            try:
                os.killpg(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass  # it exited meanwhile

    def _router_reachable(self, now: float) -> bool:
        """Whether the launcher's client session reaches the router it joined (always, for an
        embedded router: it is the launcher's own session); the loss and the return said once,
        and on the return every watch starts again (the outage is no service's silence)."""
        session = self._session
        if not self._connect or session is None:
            return True
        try:
            reached = bool(list(session.info.routers_zid()))
        except zenoh.ZError:
            return True  # the session is closing
        if not reached:
            if self._router_lost_at is None:
                self._router_lost_at = now
                self._log(f"lost the router at {', '.join(self._connect)}: the services "
                          "cannot be asked how they are until it is back, and are not judged "
                          "meanwhile")
            return False
        if self._router_lost_at is not None:
            self._log(f"the router is back after {now - self._router_lost_at:.1f} s")
            self._router_lost_at = None
            self._judge_from(now)
        return True

    def _judge_from(self, now: float) -> None:
        """Start every service's watch again at ``now``: what the launcher saw or missed
        before (queries through a router that went, or while it did not run) says nothing."""
        with self._cond:
            for watch in self._watches.values():
                watch.since = now
                watch.pending_since = None
                watch.busy_s = 0.0

    def _ask_status(self, service: str, pid: int) -> None:
        """Query ``service``'s status; the answer of process ``pid`` updates its watch."""
        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is None:
                return
            try:
                status = unpack(reply.ok.payload.to_bytes())
            except MessageError:
                return  # not a status map: not an answer
            busy = status.get("busy_s", 0.0)
            with self._cond:
                watch = self._watches.get(service)
                if watch is not None and status.get("pid") == pid == watch.pid:
                    watch.pending_since = None
                    watch.busy_s = float(busy) if isinstance(busy, (int, float)) else 0.0

        if self._session is None:
            return
        try:
            # every queryable of the key answers, and the one of process pid counts: by
            # default only the best-matching one did, and where another system's service of
            # the same name was reachable its answer alone came, and a healthy service was
            # killed as hung. Every answer is delivered, too: Zenoh's default consolidation
            # keeps one reply a key, and the two answer on the same key, so one in three
            # runs of the test that has another answer lost the service's own (CI, s53)
            self._session.get(self.keys.status(service), on_reply, timeout=STATUS_PERIOD_S,
                              target=zenoh.QueryTarget.ALL,
                              consolidation=zenoh.ConsolidationMode.NONE)
        except zenoh.ZError:
            pass  # the session is closing: the run is ending

    def _on_exit(self, child: _Child, code: int, now: float, startup: bool) -> None:
        child.returncode = code
        ran = now - child.started_at
        name = child.spec.cli_name
        if startup and not child.ready and code != 0:
            raise LaunchError(f"{name} exited with {code} during start-up "
                              f"(see its [{name}] lines)")
        policy = child.spec.restart
        if policy == "always" or (policy == "on-failure" and code != 0):
            if ran >= child.spec.backoff.reset_after:
                child.failures = 0
            delay = child.spec.backoff.delay(child.failures)
            child.failures += 1
            child.restart_at = now + delay
            self._log(f"{name} exited with {code}, restarting in {delay:g} s")
        elif child.spec.name == "camera" and code == 0:
            self._log("camera finished (exit 0): ending the run"
                      + (f", which lost {', '.join(self._lost)}" if self._lost else ""))
            self._end_code = 1 if self._lost else 0
        elif child.spec.name == "camera" and policy == "never":
            # no frame will come again: a file camera's run that ended in an error (a video
            # cut short, once its frames were out) or a camera that failed ends the run too,
            # as a run failure, rather than leave the other services waiting for frames
            self._log(f"camera exited with {code}, not restarted (restart: never): ending "
                      "the run")
            self._end_code = 1
        else:
            self._log(f"{name} exited with {code}, not restarted (restart: {policy})")
            if code != 0:
                self._lost.append(name)

    def _command(self, spec: ServiceSpec) -> list[str]:
        cmd = [self._python, "-m", "vistrack.services.cli", spec.cli_name, *spec.flags]
        for endpoint in self.endpoints:
            cmd += ["-e", endpoint]
        cmd += ["--no-multicast-scouting", "--robot", self.launch.robot]
        if self._mode is not None:
            cmd += ["-m", self._mode]
        return cmd

    def _spawn(self, child: _Child) -> None:
        child.started_at = time.monotonic()  # before the child can declare its token
        proc = self._from_spare(child.spec) if child.restarts else None
        how = ", from the spare" if proc is not None else ""
        if proc is None and child.held:  # started early: it waits for _release
            proc = self._popen([*self._command(child.spec), HOLD_FLAG], stdin=subprocess.PIPE)
            how = ", held until its consumers are ready"
        elif proc is None:
            proc = self._popen(self._command(child.spec), stdin=subprocess.DEVNULL)
        child.proc, child.returncode, child.ready = proc, None, False
        child.reader = threading.Thread(target=self._pump, args=(child.spec.cli_name, proc),
                                        name=f"out-{child.spec.cli_name}", daemon=True)
        child.reader.start()
        self._log(f"started {child.spec.cli_name} (pid {proc.pid}{how})")

    def _popen(self, command: list[str], stdin: int) -> subprocess.Popen[bytes]:
        # lines as they happen, not per 8 KiB; a stop from outside exits 128 + N (SUPERVISED_ENV)
        env = {**os.environ, "PYTHONUNBUFFERED": "1", SUPERVISED_ENV: "1"}
        return subprocess.Popen(command, stdin=stdin, stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, env=env,
                                preexec_fn=_child_setup(os.getpid()), close_fds=True)

    # -- the spare -----------------------------------------------------------------------------
    def _keep_spare(self) -> None:
        """Start a spare once every service is ready, and again after one was used."""
        if not self._use_spare or self._stopped:
            return
        if self._spare is not None and self._spare.poll() is None:
            return
        if not all(c.ready or c.finished for c in self._children) or \
                any(c.held for c in self._children):
            return
        self._spare = self._popen([self._python, "-m", "vistrack.services.launch.spare"],
                                  stdin=subprocess.PIPE)

    def _from_spare(self, spec: ServiceSpec) -> subprocess.Popen[bytes] | None:
        """The spare, told to become ``spec``'s service; None if there is none alive."""
        spare, self._spare = self._spare, None
        if spare is None or spare.poll() is not None or spare.stdin is None:
            return None
        argv = self._command(spec)[3:]  # what follows `python -m vistrack.services.cli`
        try:
            spare.stdin.write((json.dumps(argv) + "\n").encode())
            spare.stdin.close()
        except OSError:  # it died meanwhile
            return None
        return spare

    def _drop_spare(self) -> None:
        spare, self._spare = self._spare, None
        if spare is None:
            return
        if spare.stdin is not None:
            spare.stdin.close()  # end of input: it exits by itself
        try:
            os.killpg(spare.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        spare.wait()
        if spare.stdout is not None:
            spare.stdout.close()

    def _pump(self, name: str, proc: subprocess.Popen[bytes]) -> None:
        """Copy a child's output line by line, prefixed; drain to the end whatever happens,
        or the child would block on a full pipe."""
        assert proc.stdout is not None
        with proc.stdout:
            for raw in iter(proc.stdout.readline, b""):
                self.emit(f"[{name}] {raw.decode('utf-8', 'replace').rstrip()}")
        with self._cond:
            self._cond.notify_all()  # the child is exiting: let the supervisor look

    def emit(self, line: str) -> None:
        """Write one line to the launcher's output, whole, between the children's lines."""
        with self._out_lock:
            try:
                self._out.write(line + "\n")
                self._out.flush()
            except (OSError, ValueError):
                pass  # stdout closed (e.g. piped into head): keep draining the children

    def _log(self, message: str) -> None:
        # stamped as the services' lines are (runtime.LOG_FORMAT): when the launcher judged
        # a service hung, its line could not be set beside theirs (soak test)
        now = time.time()
        self.emit(f"[launcher] {time.strftime('%H:%M:%S', time.localtime(now))}"
                  f".{int(now % 1 * 1000):03d} {message}")

    # -- stopping ----------------------------------------------------------------------------
    def _signal_all(self, sig: int, children: list[_Child] | None = None) -> list[_Child]:
        live = [c for c in (self._children if children is None else children)
                if c.proc is not None and c.proc.poll() is None]
        for child in live:
            assert child.proc is not None
            try:
                os.killpg(child.proc.pid, sig)
            except ProcessLookupError:
                pass  # exited between poll and kill
        return live

    def _terminate_children(self) -> None:
        """SIGTERM to every service, those of STOPPED_LAST once the others have exited (or
        had their grace): the ROS 2 bridge passes on the fuzzy controller's last command, the
        stop it sends as it exits. Stopped together, the bridge left first in 3 of 5 runs and
        a ROS 2 base was left with a moving Twist (helper review, session 41)."""
        for child in self._children:
            child.held, child.restart_at = False, None
        first = [c for c in self._children if c.spec.name not in STOPPED_LAST]
        last = [c for c in self._children if c.spec.name in STOPPED_LAST]
        for group in (first, last):
            live = self._signal_all(signal.SIGTERM, group)
            if live:
                self._log(f"stopping {', '.join(c.spec.cli_name for c in live)}")
            deadline = time.monotonic() + TERM_GRACE_S
            for child in live:
                assert child.proc is not None
                try:
                    child.proc.wait(max(0.0, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    self._log(f"{child.spec.cli_name} ignored SIGTERM: killing it")

    def _kill_children(self) -> None:
        for child in self._signal_all(signal.SIGKILL):
            assert child.proc is not None
            try:
                child.proc.wait(KILL_WAIT_S)
            except subprocess.TimeoutExpired:
                self._log(f"{child.spec.cli_name} (pid {child.proc.pid}) did not die")
        # the output threads end at EOF, just after their child: one short shared wait
        deadline = time.monotonic() + KILL_WAIT_S
        for child in self._children:
            if child.proc is not None:
                child.returncode = child.proc.poll()
                if child.proc.stdin is not None and not child.proc.stdin.closed:
                    child.proc.stdin.close()  # a camera never released
            if child.reader is not None:
                child.reader.join(max(0.0, deadline - time.monotonic()))


def _can_hold(spec: ServiceSpec) -> bool:
    """Whether the camera of ``spec`` is started early and held: not a live camera (a device or
    a stream, :func:`~vistrack.common.sources.is_live`), whose first frame would be read at
    start-up and sent, stale, once released."""
    flags = list(spec.flags)
    source = ""  # the last --source wins, as in argparse
    for i, flag in enumerate(flags):
        if flag == "--source" and i + 1 < len(flags):
            source = flags[i + 1]
        elif flag.startswith("--source="):
            source = flag.split("=", 1)[1]
    return not is_live(source)


def compile_kernels(command: str = "up", start: Callable[[], None] | None = None) -> None:
    """Compile the tracker's numba kernels into numba's on-disk cache, once, here, saying so
    on stderr (``vistrack COMMAND: compiling ...``) when it happens (a first run).

    On a fresh install the services would otherwise each compile them at start-up, three at
    a time on a small machine (~25 s each alone), and miss the ready timeout; with the cache
    filled they load in under a second. ``start`` (the launcher's) is called once this
    process has the warm-up turn: the services then start while the kernels compile and wait
    for them (services/kernels.py), so their own start-up overlaps the compile.
    """
    from ..kernels import warm_up_kernels
    from ..usage import say_on_stderr

    # it runs no kernel: from the cache, nothing to load (~0.9 s of a core the services'
    # start-up wants)
    warm_up_kernels(say_on_stderr(command), on_turn=start, load=lambda: None)
    # What the compiler leaves behind lives as long as this process (the launcher, the demo's
    # recorder): freeze it out of the garbage collector, whose full collections over it paused
    # the demo's recorder for 100 ms and more (p99 capture-to-command 208 ms on a first run,
    # 9 ms once the kernels came from the cache).
    gc.collect()
    gc.freeze()
