"""Scripted target motion for the robot simulator: scenarios as YAML, parsed and validated.

A scenario says where the target is at each time ``t`` (s since the start) and how the lighting
changes. It is a YAML mapping::

    name: default
    duration_s: 20
    distance_m: 2.0              # nominal = reference distance of the target, optional (2.0)
    target_size_m: 1.8           # width of the target plane, optional (1.8)
    background_distance_m: 6.0   # distance of the background plane, optional (6.0)
    components:
      - {type: sine, axis: lateral, amplitude_m: 0.3, period_s: 10}
      - {type: profile, axis: distance, points: [[0, 0], [4, 0], [9, -0.6], [16, 0]]}

The target position is the nominal one plus the SUM of the motion components' offsets, per axis:

* ``lateral``: world +y, to the robot's LEFT at the start pose (the target moves to the left of
  the image for a positive offset); the target's ``ty``.
* ``distance``: world +x, away from the robot at the start pose (a negative offset is an
  approach); the target's ``tx = distance_m + offset``.

Component types (``start_s``/``end_s`` default to 0 and "never"):

==========  ====================================================================================
``sine``    ``amplitude_m * sin(2 pi (t - start_s) / period_s + phase_deg)`` for start_s <= t <
            end_s, 0 outside. Keys: axis, amplitude_m, period_s, [phase_deg, start_s, end_s].
``step``    ``offset_m`` from ``at_s`` on, 0 before. Keys: axis, at_s, offset_m.
``ramp``    linear from 0 at ``start_s`` to ``delta_m`` at ``end_s``, held after. Keys: axis,
            start_s, end_s, delta_m.
``profile`` piecewise linear through ``points`` = [[t_s, offset_m], ...] (times increasing), the
            first/last value held before/after. Keys: axis, points.
``lighting`` not a motion: the frame becomes ``gain(t) * frame + offset(t)`` with
            ``gain = 1 + gain_amplitude * s``, ``offset = offset_amplitude * s`` and
            ``s = sin(2 pi (t - start_s) / period_s)`` from start_s on. Keys: period_s,
            [gain_amplitude, offset_amplitude, start_s]. Several lighting components add up.
==========  ====================================================================================

Sensor effects (noise, blur) belong to the camera, not to the scenario: see
:class:`vistrack.services.camera.sim.Camera`.

Built-ins (:data:`BUILTIN_SCENARIOS`, embedded here so they ship with the package): ``default``,
``sideways``, ``approach``, ``steps``, ``still``, ``lighting``. :func:`load_scenario` takes one of
these names or a path to a YAML file. Errors are :class:`ScenarioError` (a ``ValueError``) naming
the source, the key (e.g. ``components[1].type``), the value and what is allowed; malformed YAML
reports its line and column.

Pure Python + numpy + PyYAML: no Zenoh, no msgpack.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import yaml

AXES = ("lateral", "distance")

#: Closest the scripted target may come to the start pose, m: the camera's near limit with a
#: margin, so the target always renders as a whole plane in front of the camera at the start.
MIN_TARGET_DISTANCE_M = 0.3
#: The target must stay this far in front of the background plane, m.
BACKGROUND_CLEARANCE_M = 0.1


class ScenarioError(ValueError):
    """A scenario is malformed or out of range; the message names the source, the key, the
    value and what is allowed (and the line for malformed YAML)."""


# -- components --------------------------------------------------------------------------------

@dataclass(frozen=True)
class Sine:
    """Sinusoidal offset along ``axis``: ``amplitude_m * sin(2 pi (t - start_s)/period_s + phase)``
    on [start_s, end_s), 0 elsewhere (m)."""

    axis: str
    amplitude_m: float
    period_s: float
    phase_deg: float = 0.0
    start_s: float = 0.0
    end_s: float = math.inf

    def offset(self, t: np.ndarray | float) -> np.ndarray:
        """Offset in m at time(s) ``t`` (s); same shape as ``t``."""
        t = np.asarray(t, np.float64)
        phase = 2.0 * np.pi * (t - self.start_s) / self.period_s + np.deg2rad(self.phase_deg)
        active = (t >= self.start_s) & (t < self.end_s)
        return np.where(active, self.amplitude_m * np.sin(phase), 0.0)

    def breakpoints(self) -> tuple[float, ...]:
        return (self.start_s,) + ((self.end_s,) if math.isfinite(self.end_s) else ())


@dataclass(frozen=True)
class Step:
    """``offset_m`` (m) from ``at_s`` (s) on, 0 before."""

    axis: str
    at_s: float
    offset_m: float

    def offset(self, t: np.ndarray | float) -> np.ndarray:
        """Offset in m at time(s) ``t`` (s); same shape as ``t``."""
        return np.where(np.asarray(t, np.float64) >= self.at_s, self.offset_m, 0.0)

    def breakpoints(self) -> tuple[float, ...]:
        return (self.at_s,)


@dataclass(frozen=True)
class Ramp:
    """Linear from 0 at ``start_s`` to ``delta_m`` at ``end_s`` (m), held afterwards."""

    axis: str
    start_s: float
    end_s: float
    delta_m: float

    def offset(self, t: np.ndarray | float) -> np.ndarray:
        """Offset in m at time(s) ``t`` (s); same shape as ``t``."""
        frac = (np.asarray(t, np.float64) - self.start_s) / (self.end_s - self.start_s)
        return self.delta_m * np.clip(frac, 0.0, 1.0)

    def breakpoints(self) -> tuple[float, ...]:
        return (self.start_s, self.end_s)


@dataclass(frozen=True)
class Profile:
    """Piecewise linear through ``points`` ((t_s, offset_m), times increasing); the first and
    last values are held before and after."""

    axis: str
    points: tuple[tuple[float, float], ...]

    def offset(self, t: np.ndarray | float) -> np.ndarray:
        """Offset in m at time(s) ``t`` (s); same shape as ``t``."""
        ts = [p[0] for p in self.points]
        vs = [p[1] for p in self.points]
        return np.asarray(np.interp(np.asarray(t, np.float64), ts, vs))

    def breakpoints(self) -> tuple[float, ...]:
        return tuple(p[0] for p in self.points)


@dataclass(frozen=True)
class Lighting:
    """Sinusoidal gain/offset of the whole frame from ``start_s`` on (see the module doc)."""

    period_s: float
    gain_amplitude: float = 0.0
    offset_amplitude: float = 0.0
    start_s: float = 0.0

    def wave(self, t: float) -> float:
        """The unit sine ``s(t)`` of the module doc (0 before ``start_s``)."""
        if t < self.start_s:
            return 0.0
        return math.sin(2.0 * math.pi * (t - self.start_s) / self.period_s)


Motion = Sine | Step | Ramp | Profile
Component = Sine | Step | Ramp | Profile | Lighting


@dataclass(frozen=True)
class Scenario:
    """A validated scenario: scene geometry and scripted components (see the module doc).

    Build it with :func:`parse_scenario`, :func:`load_scenario` or :meth:`from_mapping`, which
    validate; constructing it directly skips the checks on the components.
    """

    name: str
    duration_s: float
    components: tuple[Component, ...] = ()
    distance_m: float = 2.0
    target_size_m: float = 1.8
    background_distance_m: float = 6.0

    def offsets(self, t: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """Summed (distance, lateral) offsets in m at time(s) ``t`` (s), each shaped like ``t``."""
        t = np.asarray(t, np.float64)
        dist = np.zeros_like(t)
        lat = np.zeros_like(t)
        for c in self.components:
            if isinstance(c, Lighting):
                continue
            if c.axis == "distance":
                dist = dist + c.offset(t)
            else:
                lat = lat + c.offset(t)
        return dist, lat

    def target_position(self, t: float) -> tuple[float, float]:
        """Ground-truth target centre (tx, ty) in the world frame, m, at time ``t`` (s)."""
        dist, lat = self.offsets(t)
        return self.distance_m + float(dist), float(lat)

    def lighting(self, t: float) -> tuple[float, float]:
        """(gain, offset) applied to the frame at time ``t`` (s): ``gain * I + offset``."""
        gain, offset = 1.0, 0.0
        for c in self.components:
            if isinstance(c, Lighting):
                s = c.wave(t)
                gain += c.gain_amplitude * s
                offset += c.offset_amplitude * s
        return gain, offset

    @property
    def has_lighting(self) -> bool:
        return any(isinstance(c, Lighting) for c in self.components)

    @classmethod
    def from_mapping(cls, data: Any, *, source: str = "<scenario>") -> Scenario:
        """Validate a decoded YAML mapping (see the module doc) into a :class:`Scenario`."""
        return _build(data, source)


# -- validation --------------------------------------------------------------------------------

_TOP_REQUIRED = ("name", "duration_s")
_TOP_OPTIONAL = ("components", "distance_m", "target_size_m", "background_distance_m")

# type -> (class, required keys, optional keys); "type" itself is implied
_SCHEMAS: dict[str, tuple[type, tuple[str, ...], tuple[str, ...]]] = {
    "sine": (Sine, ("axis", "amplitude_m", "period_s"), ("phase_deg", "start_s", "end_s")),
    "step": (Step, ("axis", "at_s", "offset_m"), ()),
    "ramp": (Ramp, ("axis", "start_s", "end_s", "delta_m"), ()),
    "profile": (Profile, ("axis", "points"), ()),
    "lighting": (Lighting, ("period_s",), ("gain_amplitude", "offset_amplitude", "start_s")),
}
COMPONENT_TYPES = tuple(_SCHEMAS)

# numeric key -> (low, high, low inclusive); a scenario longer than a day or a target moved by
# more than 10 m is certainly a typo (and would leave the scene anyway)
_RANGES: dict[str, tuple[float, float, bool]] = {
    "duration_s": (0.0, 86400.0, False),
    "distance_m": (MIN_TARGET_DISTANCE_M, 100.0, True),
    "target_size_m": (0.01, 10.0, True),
    "background_distance_m": (0.5, 1000.0, True),
    "amplitude_m": (-10.0, 10.0, True),
    # a period of 5e-324 s made the offsets NaN: the target left the frames and every pose
    # failed; one shorter than 10 ms aliases at any frame rate a camera takes (1000 fps)
    "period_s": (0.01, 86400.0, True),
    "phase_deg": (-360.0, 360.0, True),
    "start_s": (0.0, 86400.0, True),
    "end_s": (0.0, 86400.0, True),
    "at_s": (0.0, 86400.0, True),
    "offset_m": (-10.0, 10.0, True),
    "delta_m": (-10.0, 10.0, True),
    "gain_amplitude": (0.0, 0.9, True),
    "offset_amplitude": (0.0, 100.0, True),
}


def _fail(source: str, key: str, message: str) -> ScenarioError:
    return ScenarioError(f"{source}: {key}: {message}")


def _range_text(name: str) -> str:
    lo, hi, lo_incl = _RANGES[name]
    return f"{'[' if lo_incl else '('}{lo:g}, {hi:g}]"


def _number(source: str, key: str, name: str, value: Any) -> float:
    """``value`` as a float in the range of ``name``, or ScenarioError naming ``key``."""
    # bool is an int subclass: `amplitude_m: yes` must not silently become 1.0
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _fail(source, key, f"{value!r} is not a number: allowed {_range_text(name)}")
    value = float(value)
    lo, hi, lo_incl = _RANGES[name]
    ok = (lo <= value if lo_incl else lo < value) and value <= hi  # also rejects NaN
    if not ok:
        raise _fail(source, key, f"{value!r} is out of range: allowed {_range_text(name)}")
    return value


def _check_keys(source: str, where: str, data: Mapping[str, Any], required: tuple[str, ...],
                optional: tuple[str, ...]) -> None:
    allowed = required + optional
    for key in data:
        if key not in allowed:
            raise _fail(source, f"{where}{key}", f"unknown key: allowed keys are "
                                                 f"{', '.join(allowed)}")
    for key in required:
        if key not in data:
            raise _fail(source, f"{where}{key}", "missing (required)")


def _component(source: str, index: int, data: Any) -> Component:
    where = f"components[{index}]"
    if not isinstance(data, Mapping):
        raise _fail(source, where, f"{data!r} is not a mapping such as "
                                   "{type: sine, axis: lateral, amplitude_m: 0.3, period_s: 6}")
    kind = data.get("type")
    if kind not in _SCHEMAS:
        shown = "missing" if kind is None else f"{kind!r} is not a component type"
        raise _fail(source, f"{where}.type", f"{shown}: allowed types are "
                                             f"{', '.join(COMPONENT_TYPES)}")
    cls, required, optional = _SCHEMAS[kind]
    fields = {k: v for k, v in data.items() if k != "type"}
    _check_keys(source, f"{where}.", fields, required, optional)
    values: dict[str, Any] = {}
    for key, value in fields.items():
        path = f"{where}.{key}"
        if key == "axis":
            if value not in AXES:
                raise _fail(source, path, f"{value!r} is not an axis: allowed "
                                          f"{', '.join(AXES)}")
            values[key] = value
        elif key == "points":
            values[key] = _points(source, path, value)
        else:
            values[key] = _number(source, path, key, value)
    start, end = values.get("start_s", 0.0), values.get("end_s", math.inf)
    if not end > start:
        raise _fail(source, f"{where}.end_s", f"{end!r} must be greater than start_s={start!r}")
    return cls(**values)


def _points(source: str, key: str, value: Any) -> tuple[tuple[float, float], ...]:
    example = "a list of [t_s, offset_m] pairs such as [[0, 0], [5, -0.5]]"
    if not isinstance(value, list) or not value:
        raise _fail(source, key, f"{value!r} is not {example}")
    out: list[tuple[float, float]] = []
    for i, pair in enumerate(value):
        if not isinstance(pair, (list, tuple)) or len(pair) != 2:
            raise _fail(source, f"{key}[{i}]", f"{pair!r} is not a [t_s, offset_m] pair")
        t = _number(source, f"{key}[{i}][0]", "start_s", pair[0])
        v = _number(source, f"{key}[{i}][1]", "offset_m", pair[1])
        if out and not t > out[-1][0]:
            raise _fail(source, f"{key}[{i}][0]", f"time {t!r} must be greater than the "
                                                  f"previous one ({out[-1][0]!r})")
        out.append((t, v))
    return tuple(out)


def _build(data: Any, source: str) -> Scenario:
    if not isinstance(data, Mapping):
        raise ScenarioError(f"{source}: the scenario must be a mapping with keys "
                            f"{', '.join(_TOP_REQUIRED + _TOP_OPTIONAL)}; got {data!r:.80}")
    _check_keys(source, "", data, _TOP_REQUIRED, _TOP_OPTIONAL)
    name = data["name"]
    if not isinstance(name, str) or not name.strip():
        raise _fail(source, "name", f"{name!r} must be a non-empty string")
    numbers = {k: _number(source, k, k, data[k])
               for k in ("duration_s", "distance_m", "target_size_m", "background_distance_m")
               if k in data}
    raw = data.get("components", [])
    if raw is None:
        raw = []
    if not isinstance(raw, list):
        raise _fail(source, "components", f"{raw!r:.80} is not a list of components")
    components = tuple(_component(source, i, c) for i, c in enumerate(raw))
    scenario = Scenario(name=name, components=components, **numbers)
    _check_geometry(scenario, source)
    return scenario


def _check_geometry(s: Scenario, source: str) -> None:
    """The scripted target must stay between the camera's near limit and the background."""
    if not s.background_distance_m > s.distance_m + BACKGROUND_CLEARANCE_M:
        raise _fail(source, "background_distance_m",
                    f"{s.background_distance_m!r} must exceed distance_m + "
                    f"{BACKGROUND_CLEARANCE_M} = {s.distance_m + BACKGROUND_CLEARANCE_M!r}")
    # the offsets are piecewise smooth: a fine grid plus every breakpoint (both sides) finds
    # the extremes to well under a millimetre for any sine slower than the grid
    ts = [np.linspace(0.0, s.duration_s, 4001)]
    for c in s.components:
        if not isinstance(c, Lighting):
            bp = np.array([b for b in c.breakpoints() if 0.0 <= b <= s.duration_s])
            ts.append(np.concatenate([bp, np.maximum(bp - 1e-9, 0.0)]))
    t = np.concatenate(ts)
    dist, _ = s.offsets(t)
    tx = s.distance_m + dist
    lo, hi = MIN_TARGET_DISTANCE_M, s.background_distance_m - BACKGROUND_CLEARANCE_M
    bad = np.flatnonzero((tx < lo) | (tx > hi))
    if bad.size:
        i = int(bad[0])
        raise _fail(source, "components",
                    f"the target distance reaches {tx[i]:.3f} m at t={t[i]:.3f} s: it must "
                    f"stay within [{lo:g}, {hi:g}] m (distance_m plus the distance offsets)")


# -- parsing and loading -----------------------------------------------------------------------

def parse_scenario(text: str, *, source: str = "<string>") -> Scenario:
    """Parse and validate scenario YAML ``text``; ``source`` names it in error messages.

    Raises
    ------
    ScenarioError
        Malformed YAML (with line and column) or an invalid scenario (naming the key).
    """
    try:
        data = yaml.safe_load(text)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark else ""
        problem = exc.problem or exc.context or "invalid YAML"
        raise ScenarioError(f"{source}: malformed YAML: {where}{problem}") from None
    except yaml.YAMLError as exc:
        raise ScenarioError(f"{source}: malformed YAML: {exc}") from None
    return _build(data, source)


BUILTIN_SCENARIOS: dict[str, str] = {
    # the demo's main job: a slow sideways sweep with an approach and a recede on top
    "default": """\
name: default
duration_s: 20
components:
  - {type: sine, axis: lateral, amplitude_m: 0.3, period_s: 10}
  - {type: profile, axis: distance, points: [[0, 0], [4, 0], [9, -0.6], [11, -0.6], [16, 0]]}
""",
    # 0.3 m at 2 m is +-45 px at 256x256; peak speed 0.24 m/s ~ 1 px per frame at 30 fps
    "sideways": """\
name: sideways
duration_s: 20
components:
  - {type: sine, axis: lateral, amplitude_m: 0.3, period_s: 8}
""",
    # 2.0 m -> 1.2 m -> 2.0 m: apparent scale 1 -> 1.67 -> 1
    "approach": """\
name: approach
duration_s: 16
components:
  - {type: profile, axis: distance, points: [[0, 0], [2, 0], [7, -0.8], [9, -0.8], [14, 0]]}
""",
    # 5 cm lateral steps (~5.5 px at 2 m) stay inside SEARCH_SIZE 15's +-7 px, so the step
    # response of the closed loop can be measured without the tracker losing every feature
    "steps": """\
name: steps
duration_s: 16
components:
  - {type: step, axis: lateral, at_s: 2, offset_m: 0.05}
  - {type: step, axis: lateral, at_s: 5, offset_m: -0.05}
  - {type: step, axis: lateral, at_s: 8, offset_m: -0.05}
  - {type: step, axis: distance, at_s: 11, offset_m: -0.1}
""",
    # nothing moves: noise floor and drift of the tracker and controller
    "still": """\
name: still
duration_s: 10
components: []
""",
    "lighting": """\
name: lighting
duration_s: 20
components:
  - {type: sine, axis: lateral, amplitude_m: 0.3, period_s: 8}
  - {type: lighting, period_s: 5, gain_amplitude: 0.25, offset_amplitude: 15}
""",
}


def scenario_names() -> tuple[str, ...]:
    """Names of the built-in scenarios."""
    return tuple(BUILTIN_SCENARIOS)


def load_scenario(name_or_path: str | os.PathLike[str]) -> Scenario:
    """A built-in scenario by name, or a scenario YAML file by path.

    Raises
    ------
    ScenarioError
        Unknown name and no such file (listing the built-ins), unreadable file, or invalid
        content.
    """
    text = os.fspath(name_or_path)
    if text in BUILTIN_SCENARIOS:
        return parse_scenario(BUILTIN_SCENARIOS[text], source=f"built-in scenario {text!r}")
    if not os.path.exists(text):
        raise ScenarioError(f"{text!r} is neither a built-in scenario (allowed: "
                            f"{', '.join(BUILTIN_SCENARIOS)}) nor an existing YAML file")
    if os.path.isdir(text):
        raise ScenarioError(f"{text}: is a folder, expected a scenario YAML file")
    try:
        with open(text, encoding="utf-8") as f:
            content = f.read()
    except (OSError, UnicodeDecodeError) as exc:
        raise ScenarioError(f"{text}: cannot read the scenario: {exc}") from None
    return parse_scenario(content, source=text)
