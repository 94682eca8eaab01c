"""Fuzzy rule base of the visual servo: membership functions and rules as data.

The paper moves the robot (a holonomic Nomad XR4000) with a fuzzy logic controller that "cancels
the apparent motion" in the images. It gives neither the variables nor the rules; this module is
our reading, kept as plain data so that it can be reviewed, rendered (:func:`rules_markdown`) and
hashed (the compiled surface cache of ``control.py`` is keyed by :func:`rule_data`).

Conventions
-----------
Robot frame: x forward (along the optical axis, toward the target), y to the left, z up; yaw
``wz`` positive counter-clockwise seen from above. The camera looks along +x with image x to the
right, so image right is robot -y.

Inputs (all clipped to their ranges, exactly as scikit-fuzzy's ``clip_to_bounds`` does):

* ``ex = (xc - x_ref) / (width / 2)``: horizontal image error of the feature centroid (Eq. (2)),
  in half-image-widths, so it is independent of the camera resolution. ``ex > 0``: the target
  appears right of the set point.
* ``ez = ln(scale / scale_ref)``: distance error. The apparent size is inversely proportional to
  the distance, so ``ez ~ -dD / D`` for a small change ``dD`` of the distance ``D``; ``ez > 0``:
  the target looks bigger than at the reference, the robot is too close. The log makes
  approaching and receding symmetric.
* ``dex``, ``dez``: their rates in 1/s (filtered finite differences, see ``control.py``).

Outputs: ``vy`` (lateral, m/s, + = left) cancels ``ex``; ``vx`` (forward, m/s, + = toward the
target) cancels ``ez``. A target on the right (``ex > 0``) is brought back to the centre by moving
right, ``vy < 0``; a target too big (``ez > 0``) by moving back, ``vx < 0``. So both axes follow
"positive error -> negative command" and share one rule table.

``wz`` is always 0: the XR4000 is holonomic, so lateral translation centres the target without
turning, and using yaw as well would make two actuators fight over the same error (yaw also
moves the target in the image, by an amount that depends on the unknown distance). Keeping the
heading fixed also keeps the camera's forward axis, hence the meaning of ``ez``, unchanged.

The two axes are independent rule bases (``AXES``): each output depends on its own (error, rate)
pair only, so each compiles to one 2-D surface.

Rule base: PD-like (MacVicar-Whelan form): output index = ``-(error index + rate index)``,
saturated at the outer terms. The rate terms add damping: an error that is already shrinking
(rate opposite to the error) asks for one step less, an error that grows for one step more.

Inference: scikit-fuzzy's Mamdani defaults (AND = min, implication = min, aggregation = max,
centroid). The surface is monotone (non-increasing) in the error for rates within half their
limit. Beyond that, near saturation, two rules with the same outer consequent and complementary
error terms (``PS & P`` and ``PB & P`` -> ``NB``) dip where their firings cross, so the command
rises again, by at most 0.26 % of the output range from one grid cell to the next and 2.2 %
(0.036 m/s) in all (measured on the compiled grid, and with scikit-fuzzy by a reviewer): a
few cm/s, physically nil. Bounded-sum aggregation removes the dip but roughly doubles the
bilinear interpolation error on the same grid, so we kept the textbook inference.

Membership functions are given on a normalised universe [-1, 1] and scaled by each variable's
limit (:class:`FuzzyLimits`), the usual normalised-gain form of a fuzzy PD controller; tuning the
controller means changing the limits, not the shapes.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from vistrack.common.params import ParamError

if TYPE_CHECKING:  # skfuzzy is imported lazily: a cache hit must not pay for its import
    from skfuzzy.control import ControlSystem

#: Terms of the errors and outputs, most negative first.
ERROR_TERMS: dict[str, tuple[float, ...]] = {
    "NB": (-1.0, -1.0, -0.5),  # left shoulder: inputs are clipped to -1
    "NS": (-1.0, -0.5, 0.0),
    "Z": (-0.5, 0.0, 0.5),
    "PS": (0.0, 0.5, 1.0),
    "PB": (0.5, 1.0, 1.0),  # right shoulder
}

#: Terms of the rates: three are enough for damping and keep the table at 15 rules per axis.
RATE_TERMS: dict[str, tuple[float, ...]] = {
    "N": (-1.0, -1.0, 0.0),
    "Z": (-1.0, 0.0, 1.0),
    "P": (0.0, 1.0, 1.0),
}

#: Terms of the velocity outputs. With centroid defuzzification the outer term alone gives
#: 5/6 of the limit (the centroid of the half triangle), so that is the largest command
#: the controller issues; the limit itself is never exceeded.
OUTPUT_TERMS: dict[str, tuple[float, ...]] = {
    "NB": (-1.0, -1.0, -0.5),
    "NS": (-1.0, -0.5, 0.0),
    "Z": (-0.5, 0.0, 0.5),
    "PS": (0.0, 0.5, 1.0),
    "PB": (0.5, 1.0, 1.0),
}

#: PD rule table shared by both axes: error term -> output term for each rate term in
#: ``RATE_TERMS`` order (N, Z, P).
RULE_TABLE: dict[str, tuple[str, str, str]] = {
    "NB": ("PB", "PB", "PS"),
    "NS": ("PB", "PS", "Z"),
    "Z": ("PS", "Z", "NS"),
    "PS": ("Z", "NS", "NB"),
    "PB": ("NS", "NB", "NB"),
}

#: Output -> (error input, rate input). The axes are independent rule bases.
AXES: dict[str, tuple[str, str]] = {
    "vy": ("ex", "dex"),
    "vx": ("ez", "dez"),
}

#: Variable -> (term set, unit, meaning); the range of each is +-its limit in FuzzyLimits.
VARIABLES: dict[str, tuple[str, str, str]] = {
    "ex": ("error", "half-widths", "horizontal image error (xc - x_ref) / (width / 2); > 0: "
           "target right of the set point"),
    "dex": ("rate", "half-widths/s", "rate of ex"),
    "ez": ("error", "1", "distance error ln(scale / scale_ref); > 0: target too big, too close"),
    "dez": ("rate", "1/s", "rate of ez"),
    "vy": ("output", "m/s", "lateral velocity, + = left (robot frame)"),
    "vx": ("output", "m/s", "forward velocity, + = toward the target (robot frame)"),
}

TERM_SETS: dict[str, dict[str, tuple[float, ...]]] = {
    "error": ERROR_TERMS,
    "rate": RATE_TERMS,
    "output": OUTPUT_TERMS,
}

#: Samples of each scikit-fuzzy universe. The breakpoints above are multiples of 0.5 of the
#: limit, so they fall on samples and the piecewise-linear memberships are represented exactly;
#: 101 leaves room for breakpoints on a 0.02 grid if the shapes are edited.
UNIVERSE_POINTS = 101

# Upper bound of each FuzzyLimits field (the lower bound is 0, excluded).
_LIMIT_BOUNDS = {"ex_max": 1.0, "dex_max": 100.0, "ez_max": 3.0, "dez_max": 100.0,
                 "vy_max": 5.0, "vx_max": 5.0}


def check_number(owner: str, name: str, value: Any, lo: float, hi: float, *,
                 lo_open: bool = False, integer: bool = False) -> float:
    """Validate one configuration number and return it as float (or int).

    Parameters
    ----------
    owner : class name, for the message.
    name : field name, for the message.
    value : the value to check; bool is rejected (True would silently mean 1).
    lo, hi : allowed range, inclusive unless ``lo_open``.
    integer : require an integral value.

    Raises
    ------
    ParamError
        Naming the field, the value and the allowed range.
    """
    bracket = "(" if lo_open else "["
    allowed = f"{bracket}{lo:g}, {hi:g}]"
    kind = "an integer" if integer else "a number"
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ParamError(f"{owner}.{name}={value!r} must be {kind} in {allowed}")
    if integer and not float(value).is_integer():
        raise ParamError(f"{owner}.{name}={value!r} must be {kind} in {allowed}")
    ok = (lo < value if lo_open else lo <= value) and value <= hi  # NaN fails both
    if not ok or not math.isfinite(value):
        raise ParamError(f"{owner}.{name}={value!r} is out of range: allowed {allowed}")
    return int(value) if integer else float(value)


@dataclass(frozen=True)
class FuzzyLimits:
    """Ranges of the fuzzy variables: each variable spans ``[-limit, +limit]``.

    These are the scaling gains of the normalised fuzzy PD controller. At zero rate the
    command is exactly ``-v_max / 4`` at ``e = e_max / 4`` and ``-v_max / 2`` at ``e_max / 2``
    (secant gain ``v_max / e_max``); it is steeper near zero (about ``1.5 v_max / e_max``, the
    usual Mamdani S-shape) and flattens beyond ``e_max / 2`` toward the ``5/6 v_max``
    saturation. A full rate ``de_max`` at zero error gives ``-v_max / 2``: the secant
    derivative gain is ``0.5 v_max / de_max``, a derivative time of ``0.5 e_max / de_max``
    (0.5 s with the defaults).

    Parameters
    ----------
    ex_max : limit of ``ex`` in half-image-widths, (0, 1]; 1 = the image border.
    dex_max : limit of ``dex`` in half-widths/s, (0, 100].
    ez_max : limit of ``ez = ln(scale / scale_ref)``, (0, 3]; 0.5 = a size ratio 0.61..1.65.
    dez_max : limit of ``dez`` in 1/s, (0, 100].
    vy_max : lateral speed limit in m/s, (0, 5].
    vx_max : forward speed limit in m/s, (0, 5].
    """

    ex_max: float = 1.0
    dex_max: float = 1.0
    ez_max: float = 0.5
    dez_max: float = 0.5
    vy_max: float = 0.5
    vx_max: float = 0.5

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = check_number("FuzzyLimits", f.name, getattr(self, f.name), 0.0,
                                 _LIMIT_BOUNDS[f.name], lo_open=True)
            object.__setattr__(self, f.name, value)

    def limit(self, variable: str) -> float:
        """The limit of a variable named in ``VARIABLES`` (``"ex"`` -> ``ex_max``)."""
        if variable not in VARIABLES:
            raise KeyError(f"unknown fuzzy variable {variable!r}: known are "
                           f"{', '.join(VARIABLES)}")
        return float(getattr(self, f"{variable}_max"))

    def as_dict(self) -> dict[str, float]:
        return dataclasses.asdict(self)


def rule_data() -> dict[str, Any]:
    """Everything that defines the normalised fuzzy system, as JSON-serialisable data.

    ``control.py`` hashes this (with the grid) to key the compiled-surface cache, so any edit of
    a shape, a rule or the universe sampling invalidates old surfaces. The limits are not part
    of it: every breakpoint and universe scales with its variable's limit, so the surfaces are
    compiled once on the normalised variables and scaled at run time.
    """
    return {
        "terms": {name: {t: list(p) for t, p in terms.items()} for name, terms in
                  TERM_SETS.items()},
        "rules": {e: list(outs) for e, outs in RULE_TABLE.items()},
        "axes": {out: list(ins) for out, ins in AXES.items()},
        "variables": {v: spec[0] for v, spec in VARIABLES.items()},
        "universe_points": UNIVERSE_POINTS,
        "inference": "mamdani min/max, centroid",
    }


def _membership(universe: Any, points: tuple[float, ...], scale: float) -> Any:
    import skfuzzy as fuzz

    scaled = [p * scale for p in points]
    if len(points) == 3:
        return fuzz.trimf(universe, scaled)
    if len(points) == 4:
        return fuzz.trapmf(universe, scaled)
    raise ValueError(f"membership {points!r}: give 3 (triangle) or 4 (trapezoid) breakpoints")


def _triangle(universe: np.ndarray, points: tuple[float, ...], scale: float) -> np.ndarray:
    """A triangle (a, b, c) sampled on ``universe``, with scikit-fuzzy's ``trimf`` arithmetic."""
    a, b, c = (p * scale for p in points)
    y = np.zeros(len(universe))
    if a != b:
        rising = (a < universe) & (universe < b)
        y[rising] = (universe[rising] - a) / float(b - a)
    if b != c:
        falling = (b < universe) & (universe < c)
        y[falling] = (c - universe[falling]) / float(c - b)
    y[universe == b] = 1
    return y


def _crossings(universe: np.ndarray, mf: np.ndarray, cut: np.ndarray) -> np.ndarray | None:
    """Where ``mf`` crosses each level of ``cut``: scikit-fuzzy's ``_interp_universe_fast``
    for a whole array of levels.

    Returns
    -------
    (len(cut), 2) the first and last crossing of each level (a universe sample where there is
    none: it is in the upsampled universe anyway), or None if ``mf`` crosses some level more
    than twice (not a convex shape: then this shortcut does not apply).
    """
    above = np.where(cut[:, None] == 0.0, mf[None, :] > 0.0, mf[None, :] >= cut[:, None])
    change = above[:, 1:] != above[:, :-1]  # (G, N - 1): segment i crosses the level
    if change.size and int(change.sum(axis=1).max()) > 2:
        return None
    n = len(universe) - 1
    first = np.argmax(change, axis=1)
    last = n - 1 - np.argmax(change[:, ::-1], axis=1)
    out = np.empty((len(cut), 2))
    for col, idx in enumerate((first, last)):
        dmf = mf[idx + 1] - mf[idx]
        crossing = change[np.arange(len(cut)), idx]
        with np.errstate(divide="ignore", invalid="ignore"):
            x = universe[idx] + (cut - mf[idx]) * (universe[idx + 1] - universe[idx]) / dmf
        out[:, col] = np.where(crossing, x, universe[idx])
    return out


def mamdani_surface(output: str, errors: Any, rates: Any,
                    limits: FuzzyLimits | None = None) -> np.ndarray | None:
    """``output`` of the rule base at every (error, rate) pair, as scikit-fuzzy computes it.

    The arithmetic of ``ControlSystemSimulation(build_control_system(limits),
    clip_to_bounds=True).compute()`` step by step (memberships interpolated on the
    ``UNIVERSE_POINTS`` universes, AND = min, aggregation = max, each output term cut at its
    firing, the output universe upsampled where the terms cross their cuts, the clipped terms'
    max, the piecewise-linear centroid), in numpy over the whole array at once: the 161 x 81
    control surface in well under a second instead of scikit-fuzzy's ~9 s (its loop over the
    points in Python), and without importing scikit-fuzzy (2 to 6 s by itself).

    Parameters
    ----------
    output : an output of ``AXES`` (``"vx"``, ``"vy"``).
    errors, rates : arrays of one shape: the error and rate inputs (clipped to the limits).
    limits : variable ranges; defaults to :class:`FuzzyLimits()`.

    Returns
    -------
    The output, in its unit, in the inputs' shape; None when a membership function is not a
    triangle (the shortcut covers the shapes of this module; use scikit-fuzzy for others).
    """
    limits = limits if limits is not None else FuzzyLimits()
    err, rate = AXES[output]
    errors, rates = np.asarray(errors, dtype=np.float64), np.asarray(rates, dtype=np.float64)
    shape = np.broadcast_shapes(errors.shape, rates.shape)
    inputs = {}
    for name, values in ((err, errors), (rate, rates)):
        m = limits.limit(name)
        inputs[name] = np.clip(np.broadcast_to(values, shape).ravel(), -m, m)
    if any(len(p) != 3 for name in (err, rate, output)
           for p in TERM_SETS[VARIABLES[name][0]].values()):
        return None

    def terms(name: str) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        m = limits.limit(name)
        universe = np.linspace(-m, m, UNIVERSE_POINTS)
        return universe, {t: _triangle(universe, p, m)
                          for t, p in TERM_SETS[VARIABLES[name][0]].items()}

    memberships = {}
    for name in (err, rate):
        universe, mfs = terms(name)
        memberships[name] = {t: np.interp(inputs[name], universe, mf) for t, mf in mfs.items()}
    cuts: dict[str, np.ndarray] = {}  # output term -> its firing (max over its rules)
    for e_term, outs in RULE_TABLE.items():
        for r_term, o_term in zip(RATE_TERMS, outs, strict=True):
            firing = np.fmin(memberships[err][e_term], memberships[rate][r_term])
            cuts[o_term] = firing if o_term not in cuts else np.fmax(firing, cuts[o_term])
    universe, mfs = terms(output)
    points = [np.broadcast_to(universe, (len(inputs[err]), len(universe)))]
    for o_term, cut in cuts.items():
        crossing = _crossings(universe, mfs[o_term], cut)
        if crossing is None:
            return None
        points.append(crossing)
    # duplicates are left in: a segment of zero width adds nothing to the centroid
    x = np.sort(np.concatenate(points, axis=1), axis=1)
    y = np.zeros_like(x)
    for o_term, cut in cuts.items():
        clipped = np.minimum(cut[:, None], np.interp(x, universe, mfs[o_term]))
        np.maximum(y, clipped, out=y)
    return _centroid(x, y).reshape(shape)


def _centroid(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The centroid of each row of the piecewise-linear ``(x, y)``, as scikit-fuzzy's
    ``centroid`` integrates it (segment by segment, exactly), to rounding."""
    dx = x[:, 1:] - x[:, :-1]
    y1, y2 = y[:, :-1], y[:, 1:]
    area = 0.5 * dx * (y1 + y2)  # a segment's trapezoid, and its first moment about 0
    moment = dx * (dx * (y1 + 2.0 * y2) / 6.0 + x[:, :-1] * (y1 + y2) / 2.0)
    return moment.sum(axis=1) / np.fmax(area.sum(axis=1), np.finfo(float).eps)


def build_control_system(limits: FuzzyLimits | None = None) -> ControlSystem:
    """Build the scikit-fuzzy Mamdani system from the data above.

    Parameters
    ----------
    limits : variable ranges; defaults to :class:`FuzzyLimits()`.

    Returns
    -------
    skfuzzy.control.ControlSystem
        Antecedents ``ex, dex, ez, dez``, consequents ``vx, vy`` (centroid defuzzification),
        ``len(AXES) * len(ERROR_TERMS) * len(RATE_TERMS)`` rules labelled
        ``"<output>: <error term> & <rate term>"``. Simulate it with
        ``ControlSystemSimulation(system, clip_to_bounds=True)`` so that out-of-range inputs
        are clipped as in ``control.FuzzySurface``.
    """
    from skfuzzy import control as ctrl

    limits = limits if limits is not None else FuzzyLimits()
    variables: dict[str, Any] = {}
    for name, (term_set, _unit, _meaning) in VARIABLES.items():
        m = limits.limit(name)
        universe = np.linspace(-m, m, UNIVERSE_POINTS)
        if term_set == "output":
            var = ctrl.Consequent(universe, name, defuzzify_method="centroid")
        else:
            var = ctrl.Antecedent(universe, name)
        for term, points in TERM_SETS[term_set].items():
            var[term] = _membership(universe, points, m)
        variables[name] = var

    rules = []
    for out, (err, rate) in AXES.items():
        for e_term, outs in RULE_TABLE.items():
            for r_term, o_term in zip(RATE_TERMS, outs, strict=True):
                rules.append(ctrl.Rule(variables[err][e_term] & variables[rate][r_term],
                                       variables[out][o_term],
                                       label=f"{out}: {e_term} & {r_term}"))
    return ctrl.ControlSystem(rules)


def _shape(points: tuple[float, ...]) -> str:
    if len(points) == 3:
        if points[0] == points[1]:
            return "left shoulder"
        if points[1] == points[2]:
            return "right shoulder"
        return "triangle"
    return "trapezoid"


def rules_markdown(limits: FuzzyLimits | None = None) -> str:
    """The variables, membership functions and rule table as Markdown (for the README).

    Parameters
    ----------
    limits : ranges to print; defaults to :class:`FuzzyLimits()`.
    """
    limits = limits if limits is not None else FuzzyLimits()
    lines = ["| variable | meaning | range | unit | terms |", "| --- | --- | --- | --- | --- |"]
    for name, (term_set, unit, meaning) in VARIABLES.items():
        m = limits.limit(name)
        names = " ".join(TERM_SETS[term_set])
        lines.append(f"| `{name}` | {meaning} | [{-m:g}, {m:g}] | {unit} | {names} |")
    lines += ["", "Membership functions on the normalised universe [-1, 1] (multiply by the "
              "variable's limit): triangle (a, b, c), trapezoid (a, b, c, d).", "",
              "| term set | term | shape | breakpoints |", "| --- | --- | --- | --- |"]
    for set_name, terms in TERM_SETS.items():
        for term, points in terms.items():
            text = ", ".join(f"{p:g}" for p in points)
            lines.append(f"| {set_name} | {term} | {_shape(points)} | {text} |")
    axes = "; ".join(f"`{out}` from (`{e}`, `{r}`)" for out, (e, r) in AXES.items())
    lines += ["", f"Rules (Mamdani min/max, centroid), one table for both axes: {axes}; "
              "`wz` = 0.", "",
              "| error \\ rate | " + " | ".join(RATE_TERMS) + " |",
              "| --- |" + " --- |" * len(RATE_TERMS)]
    for e_term, outs in RULE_TABLE.items():
        lines.append(f"| {e_term} | " + " | ".join(outs) + " |")
    return "\n".join(lines) + "\n"
