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
  auto-tuner); the camera starts once their liveliness tokens are up and their inputs have
  subscribers, so no frame is sent before its consumers exist. ``vistrack up: ready (N
  services)`` is printed when every token ``vistrack/<robot>/alive/<service>`` is up.
* Each child's stdout and stderr are printed line by line, prefixed ``[service-name]``.
* A child that exits is restarted by its policy (``never``, ``on-failure``, ``always``) with
  exponential back-off, reset once it has run ``reset_after`` seconds.
* ``--camera SOURCE`` replaces the camera's ``--source`` and drops the launch file's
  ``--loop`` (give ``--loop`` to keep replaying); ``--fps`` and ``--size`` replace the
  camera's. A camera that exits 0 under ``never`` or ``on-failure`` (a file source without
  ``--loop`` has been processed) ends the run, as do ``--duration``, Ctrl-C and SIGTERM.
* Stopping sends SIGTERM to every child's process group, SIGKILL to what is left after
  3 s, and closes the router. Children also get SIGTERM if the launcher dies (Linux
  ``PR_SET_PDEATHSIG``).

Exit codes: 0 clean stop, 1 start-up or run failure, 2 bad command line or launch file.
The library behind it (:func:`load_launch`, :class:`Launcher`) is what ``vistrack demo`` uses.
"""

from __future__ import annotations

import argparse
import ctypes
import dataclasses
import gc
import importlib
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import IO, Any

import yaml
import zenoh

from ...common.bus import (
    BusError,
    add_zenoh_args,
    config_from_args,
    install_signal_handlers,
    open_session,
)
from ...common.keys import SERVICES, Keys, validate_robot_id
from ..usage import FlagError, add_number, check_endpoint, one_line, print_error, run_checks
from .router import (
    DEFAULT_LISTEN,
    listen_endpoints,
    router_config,
    start_router,
)

#: Restart policies of a service.
POLICIES = ("never", "on-failure", "always")
#: Start order: consumers before producers, the camera last (see ``Launcher.start``).
LAUNCH_ORDER = ("fuzzy_controller", "motion_estimation", "preprocessing", "auto_tuner", "camera")
#: The input (a :class:`Keys` attribute) each consumer subscribes to once it can take data.
#: Services declare their liveliness token before warming up and subscribing, so the camera
#: waits for these subscriptions too (ARCHITECTURE.md's table of keys).
CONSUMES = {"preprocessing": "frame", "motion_estimation": "pre_frame", "auto_tuner": "frame",
            "fuzzy_controller": "estimate"}
#: Flags the launcher passes to every service itself; a launch file may not set them.
RESERVED_FLAGS = ("-e", "--connect", "--robot", "--no-multicast-scouting")
#: Where ``vistrack up`` looks for its default launch file (a source checkout).
DEFAULT_LAUNCH_PATH = Path(__file__).resolve().parents[2] / "deploy" / "local.yaml"

# The built-in default launch file, used when deploy/local.yaml is not installed (a wheel);
# a test keeps it identical to deploy/local.yaml.
DEFAULT_LAUNCH = """\
# vistrack launch file: the five services on one machine (`vistrack up` runs this by default).
# Every key is optional but `services`; unknown keys are errors.

# robot id: every key lives under vistrack/<robot>/ (`vistrack up --robot ID` overrides it)
robot: robot

# the Zenoh router embedded in `vistrack up`; services and tools connect to it
# (`-l ENDPOINT` overrides the endpoints; `-e ENDPOINT` uses an existing router instead)
router:
  listen: [tcp/127.0.0.1:7447]

# longest wait, in seconds, for every service's liveliness token at start-up
ready_timeout: 30

# one entry per service (camera, preprocessing, motion-estimation, auto-tuner,
# fuzzy-controller), started downstream first and the camera last. Each has:
#   flags:   the service's command-line flags, as a list of strings or a mapping
#            flag -> value (true: the bare flag; false or null: left out)
#   restart: never | on-failure (non-zero exit or killed) | always (default on-failure)
#   backoff: restart delays in seconds: the first is `initial`, each next one doubles up to
#            `max`, and they start over once the service has run `reset_after` seconds
#            (default {initial: 0.5, max: 10, reset_after: 10})
services:
  camera:
    # the built-in generated sequence, replayed forever at 30 frames per second
    # (`vistrack up --camera SOURCE --fps F --size WxH` overrides these)
    flags: {--source: builtin, --fps: 30, --loop: true}
    # never: when a file camera ends (exit 0) the run ends; a crash is not hidden
    restart: never
  preprocessing:
    restart: on-failure
  motion-estimation:
    restart: on-failure
  auto-tuner:
    restart: on-failure
  fuzzy-controller:
    restart: on-failure
    backoff: {initial: 0.5, max: 10, reset_after: 10}
"""

# Seconds between SIGTERM and SIGKILL when stopping (the whole stop stays within 5 s).
TERM_GRACE_S = 3.0
# Seconds to wait for a SIGKILLed child to be reaped, and for an output thread to drain.
KILL_WAIT_S = 1.0
# Period of the supervision loop: how soon an exit is noticed when nothing else wakes it.
TICK_S = 0.1
PR_SET_PDEATHSIG = 1


class LaunchError(ValueError):
    """A launch file or launch that cannot work: bad YAML or schema, a service not ready.

    ``line`` is the 1-based line of the launch file the error is about, when there is one.
    """

    def __init__(self, message: str, line: int | None = None) -> None:
        super().__init__(message)
        self.line = line


# -- the launch specification --------------------------------------------------------------

@dataclass(frozen=True)
class Backoff:
    """Restart delays: ``initial`` s, doubling up to ``max`` s, reset after ``reset_after`` s
    of stable running."""

    initial: float = 0.5
    max: float = 10.0
    reset_after: float = 10.0

    def __post_init__(self) -> None:
        if not 0 <= self.initial <= self.max:
            raise LaunchError(f"backoff initial {self.initial:g} s must be >= 0 and <= max "
                              f"{self.max:g} s")
        if self.reset_after < 0:
            raise LaunchError(f"backoff reset_after {self.reset_after:g} s must be >= 0")

    def delay(self, failures: int) -> float:
        """Delay before the restart that follows ``failures`` quick exits in a row (0-based)."""
        return min(self.max, self.initial * 2.0 ** min(failures, 60))


@dataclass(frozen=True)
class ServiceSpec:
    """One service of a launch: its name (as in keys), flags, restart policy and back-off."""

    name: str
    flags: tuple[str, ...] = ()
    restart: str = "on-failure"
    backoff: Backoff = field(default_factory=Backoff)

    def __post_init__(self) -> None:
        if self.name not in SERVICES:
            raise LaunchError(f"unknown service {self.name!r}; allowed: {', '.join(SERVICES)}")
        if self.restart not in POLICIES:
            raise LaunchError(f"{self.cli_name}: unknown restart policy {self.restart!r}; "
                              f"allowed: {', '.join(POLICIES)}")

    @property
    def cli_name(self) -> str:
        """The ``vistrack`` subcommand, e.g. ``motion-estimation``."""
        return self.name.replace("_", "-")


@dataclass(frozen=True)
class LaunchSpec:
    """A validated launch file (see :data:`DEFAULT_LAUNCH` for the format)."""

    services: tuple[ServiceSpec, ...]
    robot: str = "robot"
    listen: tuple[str, ...] = DEFAULT_LISTEN
    ready_timeout: float = 30.0
    source: str = "<launch>"

    def __post_init__(self) -> None:
        try:
            validate_robot_id(self.robot)
        except ValueError as e:
            raise LaunchError(str(e)) from None
        names = [s.name for s in self.services]
        if not names or len(set(names)) != len(names):
            raise LaunchError(f"services {names}: expected at least one, each at most once")
        if not self.listen or self.ready_timeout <= 0:
            raise LaunchError("a launch needs listen endpoints and a positive ready_timeout")

    def service(self, name: str) -> ServiceSpec | None:
        """The spec of ``name`` (key or CLI spelling), None if not launched."""
        name = name.replace("-", "_")
        return next((s for s in self.services if s.name == name), None)

    def with_camera(self, *, source: str | None = None, fps: float | None = None,
                    size: str | None = None, loop: bool = False) -> LaunchSpec:
        """A copy whose camera flags are overridden (``vistrack up --camera/--fps/--size``).

        A new ``source`` drops the launch file's ``--loop`` unless ``loop`` is true. Later
        flags win in argparse, so overrides are appended.

        Raises
        ------
        LaunchError
            If there is something to override but the launch starts no camera.
        """
        camera = self.service("camera")
        extra: list[str] = []
        for flag, value in (("--source", source), ("--fps", fps), ("--size", size)):
            if value is not None:
                extra += [flag, f"{value:g}" if isinstance(value, float) else str(value)]
        if loop:
            extra.append("--loop")
        if not extra:
            return self
        if camera is None:
            raise LaunchError(f"{self.source}: --camera/--fps/--size/--loop given but the "
                              "launch starts no camera")
        flags = list(camera.flags)
        if source is not None:
            flags = [f for f in flags if f != "--loop"]
        new = dataclasses.replace(camera, flags=(*flags, *extra))
        services = tuple(new if s is camera else s for s in self.services)
        return dataclasses.replace(self, services=services)


# -- launch file parsing: YAML nodes carry the line numbers errors need -------------------

class _Reader:
    """Walks a composed YAML document, turning nodes into checked values.

    Working on nodes (``yaml.compose``) rather than loaded data keeps every value's line
    number for error messages, and sees duplicate keys, which loading silently merges.
    """

    def __init__(self, text: str, source: str) -> None:
        self.source = source
        self._loader = yaml.SafeLoader(text)

    def document(self) -> yaml.Node | None:
        try:
            return self._loader.get_single_node()
        except yaml.MarkedYAMLError as e:
            mark = e.problem_mark or e.context_mark
            where = (f"line {mark.line + 1}, column {mark.column + 1}" if mark is not None
                     else "somewhere")
            problem = " ".join(str(p) for p in (e.context, e.problem) if p)
            raise LaunchError(f"{self.source}, {where}: malformed YAML: {problem}",
                              mark.line + 1 if mark is not None else None) from None
        except yaml.YAMLError as e:
            raise LaunchError(f"{self.source}: malformed YAML: {e}") from None
        finally:
            self._loader.dispose()

    def error(self, node: yaml.Node, path: str, message: str) -> LaunchError:
        line = node.start_mark.line + 1
        return LaunchError(f"{self.source}, line {line}: {path}: {message}", line)

    def value(self, node: yaml.Node) -> Any:
        """The Python value of a scalar node (YAML's own typing: 30 is an int, true a bool)."""
        return self._loader.construct_object(node, deep=True)

    def mapping(self, node: yaml.Node, path: str,
                allowed: Iterable[str]) -> dict[str, tuple[yaml.Node, yaml.Node]]:
        """``{key: (key node, value node)}`` of a mapping whose keys are all in ``allowed``."""
        allowed = tuple(allowed)
        if not isinstance(node, yaml.MappingNode):
            raise self.error(node, path, f"expected a mapping with keys {', '.join(allowed)}")
        out: dict[str, tuple[yaml.Node, yaml.Node]] = {}
        for key_node, value_node in node.value:
            key = self.value(key_node) if isinstance(key_node, yaml.ScalarNode) else None
            if not isinstance(key, str):
                raise self.error(key_node, path, "keys must be strings")
            if key not in allowed:
                raise self.error(key_node, f"{path}.{key}" if path else key,
                                 f"unknown key; allowed: {', '.join(allowed)}")
            if key in out:
                raise self.error(key_node, f"{path}.{key}" if path else key,
                                 f"duplicate key (first on line {out[key][0].start_mark.line + 1})")
            out[key] = (key_node, value_node)
        return out

    def scalar(self, node: yaml.Node, path: str, kinds: tuple[type, ...], what: str) -> Any:
        """A scalar of one of ``kinds`` (a bool is not a number here)."""
        value = self.value(node) if isinstance(node, yaml.ScalarNode) else None
        if (not isinstance(node, yaml.ScalarNode) or not isinstance(value, kinds)
                or (isinstance(value, bool) and bool not in kinds)):
            shown = repr(value) if isinstance(node, yaml.ScalarNode) else f"a {node.id}"
            raise self.error(node, path, f"expected {what}, got {shown}")
        return value

    def number(self, node: yaml.Node, path: str, lo: float, hi: float) -> float:
        value = float(self.scalar(node, path, (int, float), "a number of seconds"))
        if not lo <= value <= hi:
            raise self.error(node, path, f"{value:g} is out of range: allowed {lo:g}..{hi:g}")
        return value

    def sequence(self, node: yaml.Node, path: str, what: str) -> list[yaml.Node]:
        if not isinstance(node, yaml.SequenceNode):
            raise self.error(node, path, f"expected a list of {what}")
        return list(node.value)


def _parse_launch(reader: _Reader, root: yaml.Node | None) -> LaunchSpec:
    if root is None:
        raise LaunchError(f"{reader.source}: empty launch file: expected a mapping with "
                          "'services'")
    top = reader.mapping(root, "", ("robot", "router", "ready_timeout", "services"))
    spec: dict[str, Any] = {"source": reader.source}
    if "robot" in top:
        node = top["robot"][1]
        try:
            spec["robot"] = validate_robot_id(reader.scalar(node, "robot", (str,), "a string"))
        except ValueError as e:
            raise reader.error(node, "robot", str(e)) from None
    if "router" in top:
        router = reader.mapping(top["router"][1], "router", ("listen",))
        if "listen" in router:
            spec["listen"] = _endpoints(reader, router["listen"][1], "router.listen")
    if "ready_timeout" in top:
        spec["ready_timeout"] = reader.number(top["ready_timeout"][1], "ready_timeout", 0.1, 3600)
    if "services" not in top:
        raise reader.error(root, "services", "missing: list the services to start")
    spec["services"] = _services(reader, top["services"][1])
    return LaunchSpec(**spec)


def _endpoints(reader: _Reader, node: yaml.Node, path: str) -> tuple[str, ...]:
    """A non-empty list of Zenoh endpoints, checked by Zenoh's own parser."""
    items = reader.sequence(node, path, "endpoints such as tcp/127.0.0.1:7447")
    if not items:
        raise reader.error(node, path, "empty: give at least one endpoint")
    out = []
    for item in items:
        endpoint = reader.scalar(item, path, (str,), "an endpoint such as tcp/127.0.0.1:7447")
        try:
            zenoh.Config().insert_json5("listen/endpoints", json.dumps([endpoint]))
            check_endpoint(path, endpoint)
        except (zenoh.ZError, FlagError):
            raise reader.error(item, path, f"{endpoint!r} is not a Zenoh endpoint: "
                               "<protocol>/<address>, e.g. tcp/127.0.0.1:7447") from None
        out.append(endpoint)
    return tuple(out)


def _service_name(reader: _Reader, node: yaml.Node, path: str) -> str:
    allowed = ", ".join(s.replace("_", "-") for s in SERVICES)
    name = reader.scalar(node, path, (str,), f"a service name ({allowed})")
    if name.replace("-", "_") not in SERVICES:
        raise reader.error(node, path, f"unknown service {name!r}; allowed: {allowed}")
    return name.replace("-", "_")


def _services(reader: _Reader, node: yaml.Node) -> tuple[ServiceSpec, ...]:
    """The ``services`` entry: a mapping name -> settings, or a list of settings with a name."""
    # (name, node naming it, settings node or None, path for messages, extra allowed keys)
    entries: list[tuple[str, yaml.Node, yaml.Node | None, str, tuple[str, ...]]] = []
    if isinstance(node, yaml.MappingNode):
        for key_node, value_node in node.value:
            name = _service_name(reader, key_node, "services")
            body = None if _is_null(value_node) else value_node
            entries.append((name, key_node, body, f"services.{name.replace('_', '-')}", ()))
    else:
        for i, item in enumerate(reader.sequence(node, "services", "service settings")):
            fields = reader.mapping(item, f"services[{i}]", ("name", *_SERVICE_KEYS))
            if "name" not in fields:
                raise reader.error(item, f"services[{i}]", "missing 'name'")
            name = _service_name(reader, fields["name"][1], f"services[{i}].name")
            entries.append((name, fields["name"][1], item, f"services[{i}]", ("name",)))
    if not entries:
        raise reader.error(node, "services", "no service to start")
    seen: dict[str, int] = {}
    specs = []
    for name, name_node, body, path, extra in entries:
        if name in seen:
            raise reader.error(name_node, path, f"service listed twice (first on line "
                               f"{seen[name]})")
        seen[name] = name_node.start_mark.line + 1
        specs.append(_service(reader, name, body, path, extra))
    return tuple(specs)


_SERVICE_KEYS = ("flags", "restart", "backoff")


def _is_null(node: yaml.Node) -> bool:
    return isinstance(node, yaml.ScalarNode) and node.tag == "tag:yaml.org,2002:null"


def _service(reader: _Reader, name: str, node: yaml.Node | None, path: str,
             extra: tuple[str, ...]) -> ServiceSpec:
    if node is None:
        return ServiceSpec(name)
    fields = reader.mapping(node, path, (*extra, *_SERVICE_KEYS))
    spec: dict[str, Any] = {"name": name}
    if "restart" in fields:
        value_node = fields["restart"][1]
        policy = reader.scalar(value_node, f"{path}.restart", (str,),
                               f"a restart policy ({', '.join(POLICIES)})")
        if policy not in POLICIES:
            raise reader.error(value_node, f"{path}.restart", f"unknown restart policy "
                               f"{policy!r}; allowed: {', '.join(POLICIES)}")
        spec["restart"] = policy
    if "backoff" in fields:
        spec["backoff"] = _backoff(reader, fields["backoff"][1], f"{path}.backoff")
    if "flags" in fields:
        spec["flags"] = _flags(reader, name, fields["flags"][1], f"{path}.flags")
    return ServiceSpec(**spec)


def _backoff(reader: _Reader, node: yaml.Node, path: str) -> Backoff:
    fields = reader.mapping(node, path, ("initial", "max", "reset_after"))
    values = {key: reader.number(value, f"{path}.{key}", 0.0, 3600.0)
              for key, (_, value) in fields.items()}
    try:
        return Backoff(**values)
    except LaunchError as e:
        raise reader.error(node, path, str(e)) from None


def _flags(reader: _Reader, service: str, node: yaml.Node, path: str) -> tuple[str, ...]:
    """Command-line flags from a list of strings or a mapping flag -> value, checked against
    the service's own argument parser."""
    argv: list[str] = []
    if isinstance(node, yaml.MappingNode):
        for key_node, value_node in node.value:
            flag = reader.scalar(key_node, path, (str,), "a flag name such as --fps")
            flag = flag if flag.startswith("-") else f"--{flag}"
            argv += _flag_values(reader, flag, value_node, f"{path}.{flag}")
    elif isinstance(node, yaml.SequenceNode):
        for item in node.value:
            argv.append(str(reader.scalar(item, path, (str, int, float),
                                          "a string (a flag or its value)")))
    else:
        raise reader.error(node, path, "expected a list of strings or a mapping flag -> value")
    for arg in argv:
        if arg.split("=", 1)[0] in RESERVED_FLAGS:
            raise reader.error(node, path, f"{arg} is set by the launcher (from robot and the "
                               f"router); reserved: {', '.join(RESERVED_FLAGS)}")
    problem = check_service_flags(service, argv)
    if problem:
        raise reader.error(node, path, problem)
    return tuple(argv)


def _flag_values(reader: _Reader, flag: str, node: yaml.Node, path: str) -> list[str]:
    """``--flag value``, ``--flag`` (true), nothing (false/null), or one pair per list item."""
    if isinstance(node, yaml.SequenceNode):
        return [a for item in node.value for a in _flag_values(reader, flag, item, path)]
    value = reader.scalar(node, path, (str, int, float, bool, type(None)),
                          "a string, number, true/false, null or a list of them")
    if value is True:
        return [flag]
    if value is False or value is None:
        return []
    return [flag, str(value)]


class _FlagsError(Exception):
    pass


class _CheckingParser(argparse.ArgumentParser):
    """argparse that raises instead of printing and exiting."""

    def error(self, message: str) -> None:  # type: ignore[override]
        raise _FlagsError(message)

    def exit(self, status: int = 0, message: str | None = None) -> None:  # type: ignore[override]
        raise _FlagsError(message or "a flag that exits (such as --help) is not allowed")


def check_service_flags(service: str, argv: list[str]) -> str | None:
    """Why ``argv`` (plus the launcher's own flags) would not be accepted by ``service``, or
    None.

    Parses them with the service's own ``add_arguments`` (unknown flags, values out of their
    declared ranges) and runs its ``check_args`` (a camera source that does not exist, ...),
    so what ``vistrack <service>`` would refuse is found before anything starts rather than as
    a crash loop.
    """
    from ..cli import COMMANDS  # here, not at the top: cli imports this module

    module = importlib.import_module(f"vistrack.services.{COMMANDS[service.replace('_', '-')][0]}")
    parser = _CheckingParser(prog=f"vistrack {service}", add_help=False)
    module.add_arguments(parser)
    try:
        args = parser.parse_args([*argv, "-e", DEFAULT_LISTEN[0], "--no-multicast-scouting"])
        run_checks(module, args)
    except (_FlagsError, ValueError) as e:
        return one_line(e)
    return None


def load_launch(path_or_text: str | Path) -> LaunchSpec:
    """Read and validate a launch file: a path, or YAML text (a string with a newline).

    Raises
    ------
    LaunchError
        Naming the file, the line (and column for malformed YAML), the key and what is allowed.
    """
    if isinstance(path_or_text, str) and "\n" in path_or_text:
        text, source = path_or_text, "<launch text>"
    else:
        path = Path(path_or_text)
        try:
            text = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as e:
            raise LaunchError(f"{path}: cannot read launch file: "
                              f"{getattr(e, 'strerror', None) or e}") from None
        source = str(path)
    reader = _Reader(text, source)
    return _parse_launch(reader, reader.document())


def default_launch() -> LaunchSpec:
    """``deploy/local.yaml`` of the source checkout, else the identical built-in default."""
    if DEFAULT_LAUNCH_PATH.is_file():
        return load_launch(DEFAULT_LAUNCH_PATH)
    return dataclasses.replace(load_launch(DEFAULT_LAUNCH), source="<built-in local.yaml>")


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
    """

    def __init__(self, launch: LaunchSpec, *, connect: list[str] | None = None,
                 router_config: str | None = None, multicast_scouting: bool = True,
                 mode: str | None = None, out: IO[str] | None = None,
                 stop_event: threading.Event | None = None,
                 python: str = sys.executable) -> None:
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
        order = {name: i for i, name in enumerate(LAUNCH_ORDER)}
        self._children = [_Child(s) for s in sorted(launch.services, key=lambda s: order[s.name])]
        self._session: zenoh.Session | None = None
        self._token_sub: Any = None
        self._probes: dict[str, zenoh.Publisher] = {}  # never put: matching status only
        self._gate_deadline = 0.0
        self._end_code: int | None = None
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
        """Open the router (or connect to one), then start every service but the camera; the
        camera follows once the others are ready and subscribed to their inputs (checked by
        :meth:`wait_ready` and :meth:`poll`), or after ``ready_timeout``.

        Raises
        ------
        BusError
            If the router cannot listen or the existing router cannot be reached.
        """
        if self._started:
            return
        self._started = True
        self._session = self._open_session()
        self._token_sub = self._session.liveliness().declare_subscriber(
            self.keys.alive_any(), self._on_token, history=True)
        for key in {getattr(self.keys, CONSUMES[c.spec.name]) for c in self._children
                    if c.spec.name in CONSUMES}:
            self._probes[key] = self._session.declare_publisher(key)
        self._gate_deadline = time.monotonic() + self.launch.ready_timeout
        for child in self._children:
            if child.spec.name == "camera" and len(self._children) > 1:
                child.held = True  # started by _release_held once its consumers are up
            else:
                self._spawn(child)

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
            the camera has finished its file; 1 when every service has exited and one failed).
        """
        self._step(startup=False)
        return self._end_code

    def run_until(self, stop: threading.Event | None = None,
                  deadline: float | None = None) -> int:
        """Supervise until the run ends, ``stop`` or ``stop_event`` is set, or the monotonic
        ``deadline`` passes; return the exit code (0 for a stop or the deadline)."""
        while True:
            code = self.poll()
            if code is not None:
                return code
            if self.stop_event.is_set() or (stop is not None and stop.is_set()):
                return 0
            now = time.monotonic()
            if deadline is not None and now >= deadline:
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
        return session

    def _on_token(self, sample: zenoh.Sample) -> None:
        service = str(sample.key_expr).rsplit("/", 1)[-1]
        with self._cond:
            if sample.kind == zenoh.SampleKind.PUT:
                self._tokens[service] = time.monotonic()
            else:
                self._tokens.pop(service, None)
            self._cond.notify_all()

    def _close_session(self) -> None:
        session, self._session = self._session, None
        if session is None:
            return
        self._drop_probes()
        try:
            if self._token_sub is not None:
                self._token_sub.undeclare()
        except zenoh.ZError:
            pass  # the session is closing anyway
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
        for child in self._children:
            if child.running and child.proc is not None and child.proc.poll() is not None:
                self._on_exit(child, child.proc.returncode, now, startup)
            if child.restart_at is not None and now >= child.restart_at:
                child.restart_at = None
                child.restarts += 1
                self._spawn(child)
        self._release_held(now)
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
        if not (all(c.ready for c in waiting) and self._inputs_subscribed(waiting)):
            if now < self._gate_deadline:
                return
            self._log("starting the camera although not every consumer is ready")
        self._drop_probes()
        for child in held:
            child.held = False
            self._spawn(child)

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
            self._log("camera finished (exit 0): ending the run")
            self._end_code = 0
        else:
            self._log(f"{name} exited with {code}, not restarted (restart: {policy})")

    def _command(self, spec: ServiceSpec) -> list[str]:
        cmd = [self._python, "-m", "vistrack.services.cli", spec.cli_name, *spec.flags]
        for endpoint in self.endpoints:
            cmd += ["-e", endpoint]
        cmd += ["--no-multicast-scouting", "--robot", self.launch.robot]
        if self._mode is not None:
            cmd += ["-m", self._mode]
        return cmd

    def _spawn(self, child: _Child) -> None:
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}  # lines as they happen, not per 8 KiB
        child.started_at = time.monotonic()  # before the child can declare its token
        proc = subprocess.Popen(self._command(child.spec), stdin=subprocess.DEVNULL,
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env,
                                preexec_fn=_child_setup(os.getpid()), close_fds=True)
        child.proc, child.returncode, child.ready = proc, None, False
        child.reader = threading.Thread(target=self._pump, args=(child.spec.cli_name, proc),
                                        name=f"out-{child.spec.cli_name}", daemon=True)
        child.reader.start()
        self._log(f"started {child.spec.cli_name} (pid {proc.pid})")

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
        self.emit(f"[launcher] {message}")

    # -- stopping ----------------------------------------------------------------------------
    def _signal_all(self, sig: int) -> list[_Child]:
        live = [c for c in self._children
                if c.proc is not None and c.proc.poll() is None]
        for child in live:
            assert child.proc is not None
            try:
                os.killpg(child.proc.pid, sig)
            except ProcessLookupError:
                pass  # exited between poll and kill
        return live

    def _terminate_children(self) -> None:
        for child in self._children:
            child.held, child.restart_at = False, None
        live = self._signal_all(signal.SIGTERM)
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
            if child.reader is not None:
                child.reader.join(max(0.0, deadline - time.monotonic()))


# -- the command line ------------------------------------------------------------------------

def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("launch", nargs="?", metavar="LAUNCH.yaml",
                        help="launch file (default: deploy/local.yaml)")
    parser.add_argument("--camera", metavar="SOURCE",
                        help="the camera's source: file:PATH, device:N, builtin or "
                             "sim[:SCENARIO]; drops the launch file's --loop")
    parser.add_argument("--fps", type=float, metavar="F",
                        help="the camera's frames per second (its --fps)")
    parser.add_argument("--size", metavar="WxH", help="the camera's frame size (its --size)")
    parser.add_argument("--loop", action="store_true",
                        help="with --camera: replay a file source forever")
    add_number(parser, "--duration", lo=0, hi=1e6, lo_open=True, unit="s", metavar="S",
               help="end the run after S seconds, %(allowed)s")
    add_number(parser, "--ready-timeout", lo=0, hi=3600, lo_open=True, unit="s", metavar="S",
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
    if overridden is not launch:  # the camera's flags with --camera/--fps/--size applied
        camera = overridden.service("camera")
        assert camera is not None
        problem = check_service_flags("camera", list(camera.flags))
        if problem:
            raise LaunchError(problem)
    launch = overridden
    changes: dict[str, Any] = {}
    if args.robot is not None:
        changes["robot"] = args.robot
    if args.listen:
        if args.connect:
            raise LaunchError("-l/--listen sets the embedded router's endpoints, and "
                              "-e/--connect replaces that router: give one of them")
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


def main(args: argparse.Namespace) -> int:
    try:
        launch = launch_from_args(args)
    except (LaunchError, BusError) as e:
        print_error("up", e)
        return 2
    stop = threading.Event()
    restore = install_signal_handlers(stop)
    try:
        return _run(launch, args, stop)
    except (LaunchError, BusError) as e:
        print_error("up", e)
        return 1
    finally:
        restore()


def compile_kernels(out: IO[str] = sys.stderr) -> None:
    """Compile the tracker's numba kernels into numba's on-disk cache, once, here.

    On a fresh install the services would otherwise each compile them at start-up, three at
    a time on a small machine (~25 s each alone), and miss the ready timeout; with the cache
    filled they load in under a second.
    """
    from ...common.vision import warm_up

    t0 = time.monotonic()
    warm_up()
    # What the compiler leaves behind lives as long as this process (the launcher, the demo's
    # recorder): freeze it out of the garbage collector, whose full collections over it paused
    # the demo's recorder for 100 ms and more (p99 capture-to-command 208 ms on a first run,
    # 9 ms once the kernels came from the cache).
    gc.collect()
    gc.freeze()
    if time.monotonic() - t0 > 3.0:
        print(f"vistrack: compiled the tracker's kernels in {time.monotonic() - t0:.0f} s "
              "(first run only; cached from now on)", file=out)


def _run(launch: LaunchSpec, args: argparse.Namespace, stop: threading.Event) -> int:
    compile_kernels()
    with Launcher(launch, connect=args.connect, router_config=args.config,
                  multicast_scouting=not args.no_multicast_scouting, mode=args.mode,
                  stop_event=stop) as launcher:
        if not launcher.wait_ready():
            return 0  # Ctrl-C during start-up
        launcher.emit(f"vistrack up: ready ({len(launch.services)} services)")
        deadline = time.monotonic() + args.duration if args.duration else None
        code = launcher.run_until(deadline=deadline)
    try:
        print(f"vistrack up: stopped (exit {code})", flush=True)
    except OSError:
        pass  # stdout closed (piped into head): the exit code still tells
    return code
