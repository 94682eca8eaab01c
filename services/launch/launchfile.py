"""Launch files: the YAML format of ``vistrack up`` read into a validated :class:`LaunchSpec`.

The format is :data:`DEFAULT_LAUNCH` (identical to ``deploy/local.yaml``): the robot id, the
embedded router's listen endpoints, the ready timeout and, per service, its flags, restart
policy, back-off and hang timeout. :func:`load_launch` validates strictly: every error names
the file, the line, the key and what is allowed, and a service's flags are checked by that
service's own parser (:func:`check_service_flags`) before anything starts.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import json
import math
import re
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
import zenoh

from ...common.bus import BusError, config_from_args
from ...common.keys import LAUNCHABLE, validate_robot_id
from ..usage import FlagError, check_endpoint, one_line, run_checks
from .router import (
    DEFAULT_LISTEN,
)

#: ``vistrack up --camera none``: the launch without its camera.
NO_CAMERA = "none"
#: Restart policies of a service.
POLICIES = ("never", "on-failure", "always")
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

# longest wait, in seconds (0.1..3600), for every service to be ready at start-up (its
# liveliness token: kernels loaded, control surface built, inputs subscribed)
ready_timeout: 60

# one entry per service (camera, preprocessing, motion-estimation, auto-tuner,
# fuzzy-controller), started downstream first and the camera last. Each has:
#   flags:   the service's command-line flags, as a list of strings or a mapping
#            flag -> value (true: the bare flag; false or null: left out; a list: the flag
#            once per value). A flag of two values (the auto-tuner's --scale-band LO HI)
#            takes the list form: [--scale-band, '0.8', '1.25']
#   restart: never | on-failure (non-zero exit or killed) | always (default on-failure)
#   backoff: restart delays in seconds: the first is `initial`, each next one doubles up to
#            `max` (after an `initial` of 0: 0.5, 1, 2, ...), and they start over once the
#            service has run `reset_after` seconds
#            (default {initial: 0.5, max: 10, reset_after: 10}; each 0..3600)
#   hang_timeout: seconds a running service may go without answering its status query, with
#            its loop stuck on one input, or without its liveliness token, before it is
#            killed and restarted by its policy (default 5; 0: never, else 1..3600)
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
    hang_timeout: 5
  auto-tuner:
    restart: on-failure
  fuzzy-controller:
    restart: on-failure
    backoff: {initial: 0.5, max: 10, reset_after: 10}
"""


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
        """Delay before the restart that follows ``failures`` quick exits in a row (0-based).
        With ``initial`` 0 the first restart is at once and the next ones double from
        :data:`FIRST_DOUBLED` (0 doubled stays 0: a service that failed at start-up was
        started again on every tick of the supervisor, ten interpreters a second, for as long
        as the run lasted); ``max`` 0 keeps every restart immediate, as asked."""
        if self.initial > 0:
            return min(self.max, self.initial * 2.0 ** min(failures, 60))
        return 0.0 if failures == 0 else min(self.max, FIRST_DOUBLED * 2.0 ** min(failures - 1, 60))


#: The delay, s, that follows an immediate first restart (``backoff.initial`` 0), doubled after.
FIRST_DOUBLED = 0.5


#: Default ``hang_timeout``, s: a few status queries (one a second) gone unanswered.
DEFAULT_HANG_TIMEOUT = 5.0
#: Allowed ``hang_timeout``: 0 (never) or this range, s (a status query takes up to 1 s).
HANG_TIMEOUT_RANGE = (1.0, 3600.0)


def check_hang_timeout(value: float) -> float:
    """``value`` if it is 0 or within :data:`HANG_TIMEOUT_RANGE`, else LaunchError."""
    lo, hi = HANG_TIMEOUT_RANGE
    if value != 0 and not lo <= value <= hi:
        raise LaunchError(f"{value:g} is out of range: allowed 0 (never) or {lo:g}..{hi:g} s")
    return value


@dataclass(frozen=True)
class ServiceSpec:
    """One service of a launch: its name (as in keys), flags, restart policy, back-off and
    hang timeout (s; 0: never judged hung)."""

    name: str
    flags: tuple[str, ...] = ()
    restart: str = "on-failure"
    backoff: Backoff = field(default_factory=Backoff)
    hang_timeout: float = DEFAULT_HANG_TIMEOUT

    def __post_init__(self) -> None:
        if self.name not in LAUNCHABLE:
            raise LaunchError(f"unknown service {self.name!r}; allowed: "
                              f"{', '.join(LAUNCHABLE)}")
        if self.restart not in POLICIES:
            raise LaunchError(f"{self.cli_name}: unknown restart policy {self.restart!r}; "
                              f"allowed: {', '.join(POLICIES)}")
        try:
            check_hang_timeout(self.hang_timeout)
        except LaunchError as e:
            raise LaunchError(f"{self.cli_name}: hang_timeout {e}") from None

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
    ready_timeout: float = 60.0
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

        A new ``source`` drops the launch file's ``--loop`` unless ``loop`` is true, and one
        other than the simulator its simulator flags (``--noise``, ``--lockstep``, ...). Each
        flag given takes the place of the launch file's (``--fps 30`` and ``--fps=30`` alike),
        so that the camera's command line, in ``ps`` and the log, says each once.
        ``source="none"`` leaves the camera
        out: the pipeline waits for frames from elsewhere (``vistrack replay``, a camera of
        your own publishing ``camera/frame``).

        Raises
        ------
        LaunchError
            If there is something to override but the launch starts no camera.
        """
        camera = self.service("camera")
        if source == NO_CAMERA:
            if fps is not None or size is not None or loop:
                raise LaunchError("--camera none starts no camera: --fps, --size and --loop "
                                  "have nothing to apply to")
            services = tuple(s for s in self.services if s.name != "camera")
            if not services:
                raise LaunchError(f"{self.source}: --camera none leaves no service to start")
            return dataclasses.replace(self, services=services)
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
        if source is not None or loop:
            flags = [f for f in flags if f != "--loop"]
        if source is not None and not source.startswith("sim"):
            # the simulator's own flags go with it (a sim launch file run with --camera
            # builtin was refused for its --noise and --lockstep)
            from ..camera.service import SIM_ONLY  # here: the camera imports OpenCV

            for flag, _, default in SIM_ONLY:
                flags = ([f for f in flags if f != flag] if default is False
                         else _without(flags, flag))
        for flag in (f for f in extra if f.startswith("--") and f != "--loop"):
            flags = _without(flags, flag)
        new = dataclasses.replace(camera, flags=(*flags, *extra))
        services = tuple(new if s is camera else s for s in self.services)
        return dataclasses.replace(self, services=services)


def _without(flags: list[str], flag: str) -> list[str]:
    """``flags`` without ``flag`` and its value, in either form (``--fps 30``, ``--fps=30``)."""
    out: list[str] = []
    skip = False
    for f in flags:
        if skip:
            skip = False
        elif f == flag:
            skip = True
        elif not f.startswith(flag + "="):
            out.append(f)
    return out


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
        """The error at ``node``, naming the file, its line and the key ``path`` ("": the
        document itself)."""
        line = node.start_mark.line + 1
        where = f"{path}: " if path else "the launch file: "
        return LaunchError(f"{self.source}, line {line}: {where}{message}", line)

    def value(self, node: yaml.Node, path: str) -> Any:
        """The Python value of a scalar node (YAML's own typing: 30 is an int, true a bool).

        A merge key (``<<: *defaults``), a tag the safe loader does not know (``!foo``) or a
        value its tag does not fit (``!!int abc``) is an error naming its line: each was a
        Python traceback, exit 1."""
        if node.tag == "tag:yaml.org,2002:merge":
            raise self.error(node, path, "YAML merge keys (<<) are not taken: write the keys "
                                         "out")
        try:
            return self._loader.construct_object(node, deep=True)
        except (yaml.YAMLError, ValueError, TypeError) as e:
            problem = getattr(e, "problem", None) or str(e)
            raise self.error(node, path, f"{node.value!r} tagged {node.tag}: cannot be "
                                         f"read ({problem})") from None

    def mapping(self, node: yaml.Node, path: str,
                allowed: Iterable[str]) -> dict[str, tuple[yaml.Node, yaml.Node]]:
        """``{key: (key node, value node)}`` of a mapping whose keys are all in ``allowed``."""
        allowed = tuple(allowed)
        if not isinstance(node, yaml.MappingNode):
            raise self.error(node, path, f"expected a mapping with keys {', '.join(allowed)}")
        out: dict[str, tuple[yaml.Node, yaml.Node]] = {}
        for key_node, value_node in node.value:
            key = self.value(key_node, path) if isinstance(key_node, yaml.ScalarNode) else None
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
        value = self.value(node, path) if isinstance(node, yaml.ScalarNode) else None
        if (not isinstance(node, yaml.ScalarNode) or not isinstance(value, kinds)
                or (isinstance(value, bool) and bool not in kinds)):
            shown = repr(value) if isinstance(node, yaml.ScalarNode) else f"a {node.id}"
            raise self.error(node, path, f"expected {what}, got {shown}")
        return value

    def number(self, node: yaml.Node, path: str, lo: float, hi: float,
               allowed: str | None = None) -> float:
        """A number of seconds within ``lo..hi`` (``allowed``: the range as errors say it).
        A plain (unquoted) scalar in exponent form is one too: YAML 1.1 reads ``1e3`` as a
        string."""
        allowed = allowed or f"{lo:g}..{hi:g} s"
        value = self.value(node, path) if isinstance(node, yaml.ScalarNode) else None
        if isinstance(value, str) and node.style is None:
            try:
                value = float(value)
            except ValueError:
                pass
        if (not isinstance(value, (int, float)) or isinstance(value, bool)
                or math.isnan(value)):
            shown = repr(value) if isinstance(node, yaml.ScalarNode) else f"a {node.id}"
            raise self.error(node, path, f"expected a number of seconds, {allowed}, got {shown}")
        if not lo <= value <= hi:
            raise self.error(node, path, f"{node.value} is out of range: allowed {allowed}")
        return float(value)

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
        robot = reader.scalar(node, "robot", (str,), "a string")
        try:
            spec["robot"] = validate_robot_id(robot)
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
        if any_port(endpoint):
            raise reader.error(item, path, f"{endpoint!r}: the services connect to the "
                               "router's endpoints, so give it a port of its own, not 0")
        if endpoint in out:
            raise reader.error(item, path, f"{endpoint!r} is given twice: give each endpoint "
                               "once")
        out.append(endpoint)
    return tuple(out)


def any_port(endpoint: str) -> bool:
    """Whether ``endpoint`` asks for any free port (``:0``): fine for a process nobody
    connects to, not for the router the services are told to connect to."""
    return re.search(r":0(?:[?#].*)?$", endpoint.partition("/")[2]) is not None


def _service_name(reader: _Reader, node: yaml.Node, path: str) -> str:
    allowed = ", ".join(s.replace("_", "-") for s in LAUNCHABLE)
    name = reader.scalar(node, path, (str,), f"a service name ({allowed})")
    if name.replace("-", "_") not in LAUNCHABLE:
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


_SERVICE_KEYS = ("flags", "restart", "backoff", "hang_timeout")


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
    if "hang_timeout" in fields:
        value_node = fields["hang_timeout"][1]
        lo, hi = HANG_TIMEOUT_RANGE
        value = reader.number(value_node, f"{path}.hang_timeout", 0.0, hi,
                              f"0 (never) or {lo:g}..{hi:g} s")
        try:
            spec["hang_timeout"] = check_hang_timeout(value)
        except LaunchError as e:
            raise reader.error(value_node, f"{path}.hang_timeout", str(e)) from None
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
        # -eENDPOINT too (argparse's attached short form): it got past as one word, and the
        # service joined a second router
        if arg.split("=", 1)[0] in RESERVED_FLAGS or (
                arg.startswith("-e") and not arg.startswith("--")):
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
    parser = _CheckingParser(prog=f"vistrack {service}", add_help=False,
                             allow_abbrev=False)
    module.add_arguments(parser)
    own = ["-e", DEFAULT_LISTEN[0], "--no-multicast-scouting"]  # the launcher adds these
    try:
        args = parser.parse_args([*argv, *own])
        run_checks(module, args)
        if getattr(args, "mode", None) == "router":
            # as `vistrack up -m router` is: each such service listens on 7447, the default
            return ("-m router: a service of vistrack up connects to its router: allowed "
                    "peer (the default) or client")
        if getattr(args, "config", None) is not None:
            config_from_args(args)  # a -c file missing or malformed: said now, not at start
    except (_FlagsError, ValueError, BusError) as e:
        # the launcher's own flags are not the user's (an empty flag name quoted them)
        return one_line(str(e).replace(" " + " ".join(own), ""))
    return None


def camera_source(launch: LaunchSpec) -> str | None:
    """The camera's ``--source`` as the camera service will read its flags (None: the launch
    starts no camera). Call it on a launch whose flags have been checked."""
    camera = launch.service("camera")
    if camera is None:
        return None
    from ..camera.service import add_arguments  # here: the camera imports OpenCV

    parser = _CheckingParser(prog="vistrack camera", add_help=False, allow_abbrev=False)
    add_arguments(parser)
    args = parser.parse_args([*camera.flags, "-e", DEFAULT_LISTEN[0], "--no-multicast-scouting"])
    return str(args.source)


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
