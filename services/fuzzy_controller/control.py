"""Fuzzy visual-servo controller: compiled control surfaces, set point, rates and watchdog.

Pure code (numpy, scikit-fuzzy at compile time only); ``service.py`` feeds it the
``motion/estimate`` messages and publishes the :class:`Command` on ``control/cmd_vel``.

Why a compiled surface: scikit-fuzzy's ``ControlSystemSimulation.compute`` costs 12 to 18 ms
per call on the development machine (graph look-ups, per-call upsampling and a Python centroid
loop), too slow next to a tracker that runs in a few ms. The two axes are independent rule bases
(``rules.AXES``), so each output is a function of two inputs only; :meth:`FuzzySurface.compile`
evaluates the system once on a uniform grid over each (error, rate) plane and every decision is
then a clipped bilinear interpolation: about 3 us for a whole ``update``. The grid is evaluated
with scikit-fuzzy's own arithmetic vectorised in numpy (``rules.mamdani_surface``: equal to its
``compute()`` to 1e-15, in a fraction of a second where ``compute()`` over the grid took 9 s and
importing scikit-fuzzy 2 to 6 s more), so a first start is quick too.

Grid resolution: the Mamdani surface has kinks along the lines where two memberships are equal
(the min of the AND and the max of the aggregation switch there), and these lines meet at the
breakpoints, so bilinear interpolation converges only to first order near them. On the default
161 x 81 grid the largest difference from scikit-fuzzy found over a 641 x 321 reference grid
was 0.37 % of the output range (2 * v_max; 0.74 % on 81 x 41), inside the 1 % the controller
is held to (``tests/unit/test_fuzzy.py``).

The surfaces are computed on the normalised system (every limit 1; the physical surface is
``v_max * f(e / e_max, r / r_max)`` exactly, because every breakpoint and universe scales with
its limit) and cached on disk keyed by a hash of the rule data: new speed limits or input
ranges never recompile, an edited rule or shape does.

Conventions (see ``rules.py``): robot frame x forward, y left; ``vy < 0`` (move right) when the
target appears right of the set point (``ex > 0``), ``vx < 0`` (back off) when it appears too
big (``ez > 0``); ``wz`` is always 0.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import math
import os
import tempfile
import time
import warnings
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

from vistrack.common.params import ParamError

from .rules import (
    AXES,
    VARIABLES,
    FuzzyLimits,
    build_control_system,
    check_number,
    mamdani_surface,
    rule_data,
)

log = logging.getLogger(__name__)

# Bump when the cache file layout or the way surfaces are computed changes.
_CACHE_FORMAT = 2

#: The normalised system the surfaces are compiled on.
UNIT_LIMITS = FuzzyLimits(ex_max=1.0, dex_max=1.0, ez_max=1.0, dez_max=1.0, vy_max=1.0,
                          vx_max=1.0)


# --------------------------------------------------------------------------------------------
# configuration


@dataclass(frozen=True)
class SurfaceConfig:
    """How the control surfaces are compiled and cached.

    Parameters
    ----------
    grid_error : samples along each error axis, 3..2001. Any 4k + 1 puts a node on every
        breakpoint (multiples of half the limit); 161 keeps the interpolation error under 0.4 %
        of the output range.
    grid_rate : samples along each rate axis, 3..2001. Any odd number puts a node on every
        breakpoint (-1, 0, 1 times the limit).
    cache : read and write compiled surfaces on disk.
    cache_dir : where; ``None`` = ``$XDG_CACHE_HOME/vistrack`` or ``~/.cache/vistrack``.
    """

    grid_error: int = 161
    grid_rate: int = 81
    cache: bool = True
    cache_dir: str | os.PathLike[str] | None = None

    def __post_init__(self) -> None:
        for name in ("grid_error", "grid_rate"):
            value = check_number("SurfaceConfig", name, getattr(self, name), 3, 2001,
                                 integer=True)
            object.__setattr__(self, name, value)
        if not isinstance(self.cache, bool):
            raise ParamError(f"SurfaceConfig.cache={self.cache!r} must be true or false")
        if self.cache_dir is not None and not isinstance(self.cache_dir, (str, os.PathLike)):
            raise ParamError(f"SurfaceConfig.cache_dir={self.cache_dir!r} must be a path or "
                             "None")

    def directory(self) -> Path:
        """The cache directory this configuration uses."""
        if self.cache_dir is not None:
            return Path(self.cache_dir).expanduser()
        base = os.environ.get("XDG_CACHE_HOME") or os.path.join("~", ".cache")
        return Path(base).expanduser() / "vistrack"


#: Allowed values of :class:`ControllerConfig`'s fields (and of the service's flags).
STALE_AFTER_RANGE = (0.0, 10.0)  # s, 0 excluded
MIN_NPI_RANGE = (0, 10000)
X_REF_RANGE = (0.0, 1e5)  # px


@dataclass(frozen=True)
class ControllerConfig:
    """Set point, rate filter and watchdog of :class:`FuzzyController` and
    :class:`ProportionalController`.

    Parameters
    ----------
    stale_after_s : watchdog bound in s, (0, 10]; the age is measured from the capture time of
        the last trusted estimate, so it includes the pipeline latency. Default 0.3 s: 9 frames
        at 30 frames/s, long enough to ride out a dropped or slow frame, short enough that the
        robot (under 0.5 m/s) moves less than 15 cm on stale data.
    min_npi : fewest tracked features (NPI) for an estimate to be trusted, 0..10000 (0 turns
        the check off). Default 5: with fewer, the centroid and scatter of Eq. (2) are
        dominated by which features happen to survive (Table 1b).
    rate_tau_s : time constant of the first-order low-pass filter on the finite-difference
        rates, in s, [0, 10]; 0 = no filtering. Default 0.1 s: a few frames, enough to tame
        pixel-quantisation noise without adding much lag.
    x_ref : set-point centroid x in px, [0, 1e5], or ``None`` to capture the first trusted
        estimate's ``xc``. ``width / 2`` centres the tracked features' centroid, which is
        the target's centre only where every feature lies on the target.
    scale_ref : set-point scale (any positive size measure: the estimate's accumulated
        ``scale`` or the scatter ``xe``), (0, 1e9], or ``None`` to capture the first trusted
        estimate's.
    """

    stale_after_s: float = 0.3
    min_npi: int = 5
    rate_tau_s: float = 0.1
    x_ref: float | None = None
    scale_ref: float | None = None

    def __post_init__(self) -> None:
        obj = "ControllerConfig"
        object.__setattr__(self, "stale_after_s", check_number(
            obj, "stale_after_s", self.stale_after_s, *STALE_AFTER_RANGE, lo_open=True))
        object.__setattr__(self, "min_npi", check_number(
            obj, "min_npi", self.min_npi, *MIN_NPI_RANGE, integer=True))
        object.__setattr__(self, "rate_tau_s", check_number(
            obj, "rate_tau_s", self.rate_tau_s, 0.0, 10.0))
        if self.x_ref is not None:
            object.__setattr__(self, "x_ref", check_number(obj, "x_ref", self.x_ref,
                                                           *X_REF_RANGE))
        if self.scale_ref is not None:
            object.__setattr__(self, "scale_ref", check_number(
                obj, "scale_ref", self.scale_ref, 0.0, 1e9, lo_open=True))


@dataclass(frozen=True)
class ProportionalGains:
    """Gains and saturation of :class:`ProportionalController`.

    The defaults equal the secant gain of the default fuzzy surfaces (``v_max / e_max``: both
    command ``-v_max / 2`` at half the error limit), so the two controllers are compared at
    the same stiffness.

    Parameters
    ----------
    kx : lateral gain in m/s per half-image-width of ``ex``, (0, 100].
    kz : forward gain in m/s per unit of ``ez = ln(scale / scale_ref)``, (0, 100].
    vy_max : lateral saturation in m/s, (0, 5].
    vx_max : forward saturation in m/s, (0, 5].
    """

    kx: float = 0.5
    kz: float = 1.0
    vy_max: float = 0.5
    vx_max: float = 0.5

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            hi = 100.0 if f.name.startswith("k") else 5.0
            object.__setattr__(self, f.name, check_number(
                "ProportionalGains", f.name, getattr(self, f.name), 0.0, hi, lo_open=True))


@dataclass(frozen=True, slots=True)
class Command:
    """One velocity command in the robot frame (the ``control/cmd_vel`` fields).

    Attributes
    ----------
    vx : forward velocity, m/s (+ = toward the target).
    vy : lateral velocity, m/s (+ = left).
    wz : yaw rate, rad/s (+ = counter-clockwise); always 0 here.
    stale : True when the command is a stop because the estimates are too old or untrusted.
    """

    vx: float
    vy: float
    wz: float
    stale: bool


STOP = Command(0.0, 0.0, 0.0, True)


# --------------------------------------------------------------------------------------------
# compiled surfaces


class _Plane:
    """One output's surface over its (error, rate) plane, laid out for scalar lookups.

    Python lists of floats, not numpy: indexing a list and doing float arithmetic is several
    times faster than numpy scalar indexing for a single query.
    """

    __slots__ = ("e_lo", "e_hi", "e_inv", "e_last", "r_lo", "r_hi", "r_inv", "r_last", "rows")

    def __init__(self, e_max: float, r_max: float, table: np.ndarray) -> None:
        """``table`` holds the output, in its unit, on the uniform grid over
        ``[-e_max, e_max] x [-r_max, r_max]``."""
        ne, nr = table.shape
        self.e_lo, self.e_hi = -e_max, e_max
        self.r_lo, self.r_hi = -r_max, r_max
        self.e_inv = (ne - 1) / (2.0 * e_max)
        self.r_inv = (nr - 1) / (2.0 * r_max)
        self.e_last = ne - 2  # last cell index
        self.r_last = nr - 2
        self.rows = table.tolist()

    def __call__(self, e: float, r: float) -> float:
        # clip first, as scikit-fuzzy's clip_to_bounds does
        if e < self.e_lo:
            e = self.e_lo
        elif e > self.e_hi:
            e = self.e_hi
        if r < self.r_lo:
            r = self.r_lo
        elif r > self.r_hi:
            r = self.r_hi
        u = (e - self.e_lo) * self.e_inv
        v = (r - self.r_lo) * self.r_inv
        i = int(u)
        j = int(v)
        if i > self.e_last:  # e == e_hi lands on the last node: use the last cell
            i = self.e_last
        if j > self.r_last:
            j = self.r_last
        fu = u - i
        fv = v - j
        row0 = self.rows[i]
        row1 = self.rows[i + 1]
        a = row0[j] + fv * (row0[j + 1] - row0[j])
        b = row1[j] + fv * (row1[j + 1] - row1[j])
        return a + fu * (b - a)


def _cache_key(config: SurfaceConfig) -> str:
    try:
        skfuzzy_version = metadata.version("scikit-fuzzy")
    except metadata.PackageNotFoundError:  # pragma: no cover - skfuzzy is a dependency
        skfuzzy_version = "unknown"
    data = {"format": _CACHE_FORMAT, "rules": rule_data(),
            "grid": [config.grid_error, config.grid_rate], "skfuzzy": skfuzzy_version}
    text = json.dumps(data, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:20]


def _compute_tables(config: SurfaceConfig) -> dict[str, np.ndarray]:
    """Evaluate the normalised system (every limit 1) on every grid node: scikit-fuzzy's
    inference vectorised in numpy (``rules.mamdani_surface``, a fraction of a second), or
    scikit-fuzzy itself for shapes the vectorised form does not cover (~9 s)."""
    unit_e = np.linspace(-1.0, 1.0, config.grid_error)
    unit_r = np.linspace(-1.0, 1.0, config.grid_rate)
    grid_e, grid_r = np.meshgrid(unit_e, unit_r, indexing="ij")
    tables: dict[str, np.ndarray] = {}
    by_sets: dict[tuple[str, ...], np.ndarray] = {}
    for out, (err, rate) in AXES.items():
        # normalised, two outputs with the same term sets have the same surface
        sets = tuple(VARIABLES[v][0] for v in (err, rate, out))
        table = by_sets.get(sets)
        if table is None:
            table = mamdani_surface(out, grid_e, grid_r, UNIT_LIMITS)
            if table is None:
                return _skfuzzy_tables(grid_e, grid_r)
            by_sets[sets] = table
        tables[out] = table.copy()
    return _checked(tables, grid_e.shape)


def _skfuzzy_tables(grid_e: np.ndarray, grid_r: np.ndarray) -> dict[str, np.ndarray]:
    """The tables from scikit-fuzzy's ``compute()``, with array inputs.

    One array-input ``compute`` fills all outputs: every axis's plane is fed at once, which is
    exact because the axes are independent rule bases.
    """
    from skfuzzy import control as ctrl

    simulation = ctrl.ControlSystemSimulation(build_control_system(UNIT_LIMITS),
                                              clip_to_bounds=True)
    for err, rate in AXES.values():
        simulation.input[err] = grid_e
        simulation.input[rate] = grid_r
    with warnings.catch_warnings():
        # scikit-fuzzy 0.5 passes `out` positionally to np.maximum, deprecated in NumPy 2.4;
        # harmless, and not ours to fix
        warnings.filterwarnings("ignore", message="Passing more than 2 positional arguments",
                                category=DeprecationWarning)
        simulation.compute()
    return _checked({out: np.asarray(simulation.output[out], dtype=np.float64)
                     for out in AXES}, grid_e.shape)


def _checked(tables: dict[str, np.ndarray], shape: tuple[int, ...]) -> dict[str, np.ndarray]:
    for out, table in tables.items():
        if table.shape != shape or not np.all(np.isfinite(table)):
            raise RuntimeError(f"the fuzzy inference gave an unusable surface for {out}")
    return tables


def _load(path: Path, key: str, shape: tuple[int, int]) -> dict[str, np.ndarray] | None:
    try:
        with np.load(path, allow_pickle=False) as data:
            if str(data["key"]) != key:
                raise ValueError("key mismatch")
            tables = {out: np.array(data[out], dtype=np.float64) for out in AXES}
    except FileNotFoundError:
        return None
    except Exception as exc:  # any unreadable cache is just a miss: recompile over it
        log.warning("ignoring unreadable fuzzy surface cache %s: %s", path, exc)
        return None
    for out, table in tables.items():
        if table.shape != shape or not np.all(np.isfinite(table)):
            log.warning("ignoring fuzzy surface cache %s: bad table for %s", path, out)
            return None
    return tables


def _save(path: Path, key: str, tables: dict[str, np.ndarray]) -> None:
    # write to a temporary file and rename, so a concurrent reader never sees half a file
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.stem, suffix=".tmp")
        try:
            arrays: dict[str, Any] = {"key": np.array(key), **tables}
            with os.fdopen(fd, "wb") as f:
                np.savez(f, **arrays)
            os.replace(tmp, path)
        except BaseException:
            os.unlink(tmp)
            raise
    except OSError as exc:  # the cache is an optimisation: a read-only home must not stop us
        log.warning("could not write fuzzy surface cache %s: %s", path, exc)


class FuzzySurface:
    """The fuzzy rule base compiled to one 2-D lookup surface per output.

    Build it with :meth:`compile`. Each output (``rules.AXES``) is sampled on a uniform grid of
    ``grid_error x grid_rate`` nodes over the normalised plane ``[-1, 1] x [-1, 1]``. Every
    breakpoint and universe of ``rules.py`` scales with its variable's limit, so the physical
    surface is ``v_max * f(e / e_max, r / r_max)`` exactly: the normalised tables are compiled
    and cached once, and :meth:`with_limits` applies new limits without recompiling. Queries
    outside the limits are clipped, as scikit-fuzzy does.

    Attributes
    ----------
    limits : the :class:`FuzzyLimits` applied.
    compile_seconds : wall time of :meth:`compile` (cache load or evaluation), s.
    from_cache : whether the tables were read from the disk cache.
    cache_path : the cache file used or written, or None when caching is off.
    """

    def __init__(self, tables: dict[str, np.ndarray], limits: FuzzyLimits | None = None, *,
                 compile_seconds: float = 0.0, from_cache: bool = False,
                 cache_path: Path | None = None) -> None:
        """``tables``: output name -> (Ne, Nr) normalised surface (output / its limit) on the
        uniform grid over [-1, 1]^2 of (error / its limit, rate / its limit)."""
        if set(tables) != set(AXES):
            raise ValueError(f"tables for {sorted(tables)}, expected {sorted(AXES)}")
        self.limits = limits if limits is not None else FuzzyLimits()
        self.compile_seconds = compile_seconds
        self.from_cache = from_cache
        self.cache_path = cache_path
        self._unit: dict[str, np.ndarray] = {}
        for out, table in tables.items():
            table = np.array(table, dtype=np.float64)  # private copy, frozen below
            if table.ndim != 2 or min(table.shape) < 2 or not np.all(np.isfinite(table)):
                raise ValueError(f"table for {out} has shape {table.shape} or non-finite "
                                 "values; expected a finite 2-D table of at least 2 x 2")
            table.setflags(write=False)
            self._unit[out] = table
        self._planes = {}
        for out, (err, rate) in AXES.items():
            lim = self.limits
            self._planes[out] = _Plane(lim.limit(err), lim.limit(rate),
                                       self._unit[out] * lim.limit(out))
        # bound once: evaluate() is on the hot path
        self._vx = self._planes["vx"]
        self._vy = self._planes["vy"]

    @classmethod
    def compile(cls, limits: FuzzyLimits | None = None,
                config: SurfaceConfig | None = None) -> FuzzySurface:
        """Evaluate the scikit-fuzzy system on the grid, or load it from the cache.

        Parameters
        ----------
        limits : variable ranges (default :class:`FuzzyLimits()`); not part of the cache key.
        config : grid and cache settings (default :class:`SurfaceConfig()`).
        """
        config = config if config is not None else SurfaceConfig()
        start = time.perf_counter()
        key = _cache_key(config)
        path = config.directory() / f"fuzzy-surface-{key}.npz" if config.cache else None
        shape = (config.grid_error, config.grid_rate)
        tables = _load(path, key, shape) if path is not None else None
        from_cache = tables is not None
        if tables is None:
            # said whenever it happens, and only then: a first run, or new rules
            log.info("compiling the fuzzy control surfaces (%d x %d grid%s)", *shape,
                     f"; cached in {path.parent}" if path is not None else "")
            tables = _compute_tables(config)
            if path is not None:
                _save(path, key, tables)
        seconds = time.perf_counter() - start
        (log.debug if from_cache else log.info)(
            "fuzzy surfaces %s in %.3f s (%d x %d grid)",
            "loaded" if from_cache else "compiled", seconds, *shape)
        return cls(tables, limits, compile_seconds=seconds, from_cache=from_cache,
                   cache_path=path)

    def with_limits(self, limits: FuzzyLimits) -> FuzzySurface:
        """The same rule base with other limits (no recompilation)."""
        return FuzzySurface(self._unit, limits, compile_seconds=0.0, from_cache=self.from_cache,
                            cache_path=self.cache_path)

    @property
    def outputs(self) -> tuple[str, ...]:
        """Output names, in ``rules.AXES`` order."""
        return tuple(AXES)

    def grid(self, output: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The sampled surface of one output, in physical units.

        Returns
        -------
        errors : (Ne,) error node positions, in the error's unit.
        rates : (Nr,) rate node positions, in the rate's unit.
        table : (Ne, Nr) output values at the nodes, in the output's unit.
        """
        err, rate = AXES[output]
        unit = self._unit[output]
        e_max, r_max = self.limits.limit(err), self.limits.limit(rate)
        return (np.linspace(-e_max, e_max, unit.shape[0]),
                np.linspace(-r_max, r_max, unit.shape[1]), unit * self.limits.limit(output))

    def value(self, output: str, error: float, rate: float) -> float:
        """One output at (error, rate), bilinearly interpolated; inputs are clipped."""
        if error != error or rate != rate:  # NaN: say so rather than fail in int()
            raise ValueError(f"{output}: error={error!r}, rate={rate!r} must not be NaN")
        return self._planes[output](float(error), float(rate))

    def evaluate(self, ex: float, dex: float, ez: float, dez: float) -> tuple[float, float]:
        """Both outputs for one set of inputs: ``(vx, vy)`` in m/s; inputs are clipped.

        The hot path: no checks beyond what float arithmetic does (NaN raises ValueError).
        """
        return self._vx(ez, dez), self._vy(ex, dex)


# --------------------------------------------------------------------------------------------
# controllers


def _finite(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{name}={value!r} must be a number")
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"{name}={value!r} must be finite")
    return value


class _ImageServo:
    """Set point, errors, filtered rates and the watchdog shared by the controllers.

    Subclasses implement :meth:`_law`, mapping (ex, dex, ez, dez) to (vx, vy).
    """

    def __init__(self, config: ControllerConfig | None) -> None:
        self.config = config if config is not None else ControllerConfig()
        self.reset()

    # -- state -------------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget everything: set point back to the configured one, rates, watchdog."""
        self._x_ref = self.config.x_ref
        self._scale_ref = self.config.scale_ref
        self._t: float | None = None  # time of the last trusted estimate
        self._ex = self._ez = 0.0
        self._dex = self._dez = 0.0
        self._collapsed = False  # the last estimate had too few features
        self._restart_rates = True
        self._command = STOP

    def restart_timing(self) -> None:
        """Forget the time of the last trusted estimate (and so the rates measured over it),
        keeping the set point: the next estimate starts the timing again, whatever its time
        (the camera's clock was set back)."""
        self._t = None
        self._dex = self._dez = 0.0
        self._restart_rates = True

    def set_point(self, x_ref: float | None = None, scale_ref: float | None = None) -> None:
        """Set the reference centroid x (px) and/or scale explicitly; None leaves it as is."""
        if x_ref is not None:
            self._x_ref = _finite("x_ref", x_ref)
        if scale_ref is not None:
            scale_ref = _finite("scale_ref", scale_ref)
            if scale_ref <= 0.0:
                raise ValueError(f"scale_ref={scale_ref!r} must be > 0")
            self._scale_ref = scale_ref
        # the errors jump with the set point; a rate across the jump would be a kick
        self._restart_rates = True

    @property
    def x_ref(self) -> float | None:
        """Set-point centroid x in px (None until captured)."""
        return self._x_ref

    @property
    def scale_ref(self) -> float | None:
        """Set-point scale (None until captured)."""
        return self._scale_ref

    @property
    def errors(self) -> tuple[float, float, float, float]:
        """The last trusted ``(ex, dex, ez, dez)`` fed to the law (for status and plots)."""
        return self._ex, self._dex, self._ez, self._dez

    # -- the loop ----------------------------------------------------------------------------
    def update(self, xc: float, scale: float, t: float, width: float, *,
               npi: int | None = None, valid: bool = True) -> Command:
        """Take one motion estimate and return the command for it.

        Parameters
        ----------
        xc : centroid x of the tracked features, px (Eq. (2)).
        scale : apparent size of the target, any positive measure proportional to it (the
            estimate's accumulated ``scale``, or the scatter ``xe``).
        t : capture time of the frame, s (any monotonic clock, the same as :meth:`command_at`).
        width : image width, px.
        npi : number of tracked features; below ``config.min_npi`` the estimate is not trusted
            and the command is a stale stop. None skips the check.
        valid : the estimate's ``valid``; False (too few features for a meaningful centroid
            and scatter, see ``motion/estimate``) is not trusted either: a stale stop.

        Returns
        -------
        Command
            ``stale=False`` unless the estimate was not trusted.

        Raises
        ------
        ValueError
            Non-finite inputs, ``scale <= 0``, ``width <= 0``, or ``t`` not after the last
            trusted estimate's (out of order or duplicate). The controller state is unchanged.
        """
        xc = _finite("xc", xc)
        scale = _finite("scale", scale)
        t = _finite("t", t)
        width = _finite("width", width)
        if scale <= 0.0:
            raise ValueError(f"scale={scale!r} must be > 0")
        if width <= 0.0:
            raise ValueError(f"width={width!r} must be > 0")
        if self._t is not None and t <= self._t:
            raise ValueError(f"t={t!r} is not after the previous estimate's t={self._t!r}")
        if not valid or (npi is not None and npi < self.config.min_npi):
            # Too few features: the centroid and scatter are not the target's any more. Stop,
            # and restart the rates afterwards, because re-detected features have a different
            # centroid and a difference across the gap would kick the rate terms.
            self._collapsed = True
            self._restart_rates = True
            self._command = STOP
            return STOP

        # everything computed before anything is kept: a finite but extreme input (a scale of
        # 5e-324 as a track's first, two stamps 1e-300 s apart) made an infinite error or
        # rate, then NaN, and jammed the track: every later estimate refused
        x_ref = xc if self._x_ref is None else self._x_ref
        scale_ref = scale if self._scale_ref is None else self._scale_ref
        ex = (xc - x_ref) / (0.5 * width)
        ratio = scale / scale_ref
        if not (math.isfinite(ex) and 0.0 < ratio < math.inf):
            raise ValueError(f"xc={xc!r}, scale={scale!r} give no finite error against the "
                             f"track's set point (xc {x_ref!r}, scale {scale_ref!r}): the "
                             "ratio of the scales must be finite and > 0")
        ez = math.log(ratio)

        cfg = self.config
        if self._restart_rates or self._t is None or t - self._t > cfg.stale_after_s:
            # after a gap the finite difference would span stale data: start from rest
            dex = dez = 0.0
        else:
            dt = t - self._t
            alpha = 1.0 if cfg.rate_tau_s == 0.0 else -math.expm1(-dt / cfg.rate_tau_s)
            dex = self._dex + alpha * ((ex - self._ex) / dt - self._dex)
            dez = self._dez + alpha * ((ez - self._ez) / dt - self._dez)
            if not (math.isfinite(dex) and math.isfinite(dez)):
                raise ValueError(f"t={t!r} is {dt!r} s after the previous estimate's: the "
                                 "error's rate over it is not finite")
        self._x_ref, self._scale_ref = x_ref, scale_ref
        self._dex, self._dez = dex, dez
        self._ex, self._ez, self._t = ex, ez, t
        self._restart_rates = False
        self._collapsed = False
        vx, vy = self._law(ex, self._dex, ez, self._dez)
        self._command = Command(vx, vy, 0.0, False)
        return self._command

    def command_at(self, t: float) -> Command:
        """The command to send at time ``t``: the last one, or a stale stop.

        Stops (all zero, ``stale=True``) before the first trusted estimate, after an untrusted
        one (``npi < min_npi``), and when the last trusted estimate is older than
        ``config.stale_after_s``.
        """
        if self._t is None or self._collapsed or t - self._t > self.config.stale_after_s:
            return STOP
        return self._command

    def _law(self, ex: float, dex: float, ez: float, dez: float) -> tuple[float, float]:
        raise NotImplementedError


class FuzzyController(_ImageServo):
    """The fuzzy PD visual servo of ``rules.py``, evaluated through a :class:`FuzzySurface`.

    Parameters
    ----------
    surface : the compiled surfaces (``FuzzySurface.compile()``).
    config : set point, rate filter and watchdog settings.
    """

    def __init__(self, surface: FuzzySurface, config: ControllerConfig | None = None) -> None:
        self.surface = surface
        super().__init__(config)

    def _law(self, ex: float, dex: float, ez: float, dez: float) -> tuple[float, float]:
        return self.surface.evaluate(ex, dex, ez, dez)


class ProportionalController(_ImageServo):
    """Plain proportional law, for comparison with the fuzzy controller.

    ``vy = clip(-kx * ex, -vy_max, vy_max)``, ``vx = clip(-kz * ez, -vx_max, vx_max)``,
    ``wz = 0``; the rates are estimated (see :attr:`errors`) but not used.

    Parameters
    ----------
    gains : gains and saturation.
    config : set point, rate filter and watchdog settings.
    """

    def __init__(self, gains: ProportionalGains | None = None,
                 config: ControllerConfig | None = None) -> None:
        self.gains = gains if gains is not None else ProportionalGains()
        super().__init__(config)

    def _law(self, ex: float, dex: float, ez: float, dez: float) -> tuple[float, float]:
        g = self.gains
        vy = min(g.vy_max, max(-g.vy_max, -g.kx * ex))
        vx = min(g.vx_max, max(-g.vx_max, -g.kz * ez))
        return vx, vy
