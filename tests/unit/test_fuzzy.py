"""Fuzzy controller: compiled surfaces against scikit-fuzzy, signs, watchdog, P law, config."""

from __future__ import annotations

import math
import subprocess
import sys
import time

import numpy as np
import pytest
from skfuzzy.control import ControlSystemSimulation

from vistrack.common.params import ParamError
from vistrack.services.fuzzy_controller import control, rules
from vistrack.services.fuzzy_controller.control import (
    Command,
    ControllerConfig,
    FuzzyController,
    FuzzySurface,
    ProportionalController,
    ProportionalGains,
    SurfaceConfig,
)
from vistrack.services.fuzzy_controller.rules import AXES, FuzzyLimits, build_control_system

# scikit-fuzzy 0.5 calls np.maximum(a, b, out) positionally, deprecated in NumPy 2.4. Only the
# reference simulations below hit it; the controller itself filters it while compiling.
pytestmark = pytest.mark.filterwarnings(
    "ignore:Passing more than 2 positional arguments:DeprecationWarning")

LIMITS = FuzzyLimits()
WIDTH = 256.0


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("fuzzy-cache")


@pytest.fixture(scope="module")
def surface(cache_dir) -> FuzzySurface:
    # compiled once per module, into an empty cache, so the scikit-fuzzy path really runs
    return FuzzySurface.compile(LIMITS, SurfaceConfig(cache_dir=str(cache_dir)))


def _reference(limits: FuzzyLimits) -> ControlSystemSimulation:
    return ControlSystemSimulation(build_control_system(limits), clip_to_bounds=True)


def _skfuzzy(sim: ControlSystemSimulation, ex: float, dex: float, ez: float,
             dez: float) -> tuple[float, float]:
    sim.input["ex"] = ex
    sim.input["dex"] = dex
    sim.input["ez"] = ez
    sim.input["dez"] = dez
    sim.compute()
    return float(sim.output["vx"]), float(sim.output["vy"])


def _skfuzzy_points(limits: FuzzyLimits, points: np.ndarray) -> np.ndarray:
    """(n, 2) vx, vy of scikit-fuzzy's compute() at (n, 4) points ex, dex, ez, dez, all at
    once (array inputs: the same numbers as one compute() a point, 40 times faster)."""
    sim = _reference(limits)
    for name, column in zip(("ex", "dex", "ez", "dez"), points.T, strict=True):
        sim.input[name] = column
    sim.compute()
    return np.column_stack([sim.output["vx"], sim.output["vy"]])


def _random_inputs(limits: FuzzyLimits, n: int, seed: int) -> np.ndarray:
    """(n, 4) ex, dex, ez, dez drawn over 1.2x the limits, so some are clipped."""
    rng = np.random.default_rng(seed)
    m = np.array([limits.limit(v) for v in ("ex", "dex", "ez", "dez")])
    return rng.uniform(-1.2, 1.2, size=(n, 4)) * m


# -- the surface against scikit-fuzzy ------------------------------------------------------------

def test_surface_matches_skfuzzy(surface):
    points = _random_inputs(LIMITS, 300, seed=1)
    errors = []
    for (ex, dex, ez, dez), (vx_ref, vy_ref) in zip(points, _skfuzzy_points(LIMITS, points),
                                                     strict=True):
        vx, vy = surface.evaluate(ex, dex, ez, dez)
        errors.append((abs(vx - vx_ref) / (2 * LIMITS.vx_max),
                       abs(vy - vy_ref) / (2 * LIMITS.vy_max)))
    worst = np.max(errors, axis=0)
    assert np.all(worst <= 0.01), f"max error (fraction of range) vx, vy: {worst}"


def test_other_limits_scale_without_recompiling(surface):
    # The cache holds the normalised surfaces; new limits must still match scikit-fuzzy
    # built with those limits.
    limits = FuzzyLimits(ex_max=0.6, dex_max=2.0, ez_max=0.3, dez_max=0.2, vy_max=0.8,
                         vx_max=0.25)
    scaled = surface.with_limits(limits)
    points = _random_inputs(limits, 40, seed=2)
    for (ex, dex, ez, dez), (vx_ref, vy_ref) in zip(points, _skfuzzy_points(limits, points),
                                                     strict=True):
        vx, vy = scaled.evaluate(ex, dex, ez, dez)
        assert abs(vx - vx_ref) <= 0.01 * 2 * limits.vx_max
        assert abs(vy - vy_ref) <= 0.01 * 2 * limits.vy_max


def test_grid_nodes_equal_skfuzzy(surface):
    # at the nodes there is nothing to interpolate: the tables are scikit-fuzzy's own values
    sim = _reference(LIMITS)
    errors, rates, table = surface.grid("vy")
    for i, j in [(0, 0), (17, 63), (80, 40), (121, 5), (160, 80)]:
        _, vy_ref = _skfuzzy(sim, errors[i], rates[j], 0.0, 0.0)
        assert table[i, j] == pytest.approx(vy_ref, abs=1e-9)


def _skfuzzy_arrays(limits: FuzzyLimits, output: str, errors: np.ndarray,
                    rates: np.ndarray) -> np.ndarray:
    """scikit-fuzzy's own compute() of one output, with array inputs."""
    sim = _reference(limits)
    for err, rate in AXES.values():
        sim.input[err] = errors
        sim.input[rate] = rates
    sim.compute()
    return np.asarray(sim.output[output], dtype=np.float64)


@pytest.mark.parametrize("limits", [FuzzyLimits(), FuzzyLimits(
    ex_max=0.6, dex_max=2.0, ez_max=0.3, dez_max=0.2, vy_max=0.8, vx_max=0.25)])
@pytest.mark.parametrize("output", list(AXES))
def test_vectorised_inference_is_skfuzzys(limits, output):
    # the surface is compiled without scikit-fuzzy: the same numbers as its compute(), at
    # random points (some outside the limits, so clipped), on the breakpoints and at the
    # corners, where the cuts are 0 or 1 and the crossings fall on universe samples
    err, rate = AXES[output]
    e_max, r_max = limits.limit(err), limits.limit(rate)
    rng = np.random.default_rng(7)
    e = np.concatenate([rng.uniform(-1.2, 1.2, 150), np.repeat([-1, -0.5, 0, 0.5, 1], 3)])
    r = np.concatenate([rng.uniform(-1.2, 1.2, 150), np.tile([-1, 0, 1], 5)])
    errors, rates = e * e_max, r * r_max
    expected = _skfuzzy_arrays(limits, output, errors, rates)
    got = rules.mamdani_surface(output, errors, rates, limits)
    assert got is not None and got.shape == errors.shape
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-9)


def test_compiled_tables_equal_skfuzzy_on_the_grid(tmp_path):
    # a small grid, compiled for real into an empty cache, against compute() at every node
    config = SurfaceConfig(grid_error=21, grid_rate=11, cache_dir=str(tmp_path))
    compiled = FuzzySurface.compile(UNIT := control.UNIT_LIMITS, config)
    assert not compiled.from_cache
    for out in AXES:
        errors, rates, table = compiled.grid(out)
        grid_e, grid_r = np.meshgrid(errors, rates, indexing="ij")
        np.testing.assert_allclose(table, _skfuzzy_arrays(UNIT, out, grid_e, grid_r),
                                   rtol=0, atol=1e-9)


def test_crossings_refuse_a_shape_that_is_not_convex():
    # the shortcut assumes each term crosses a level at most twice; a shape that does not is
    # left to scikit-fuzzy (mamdani_surface returns None) rather than computed wrongly
    universe = np.linspace(-1.0, 1.0, 5)
    two_humps = np.array([0.0, 1.0, 0.0, 1.0, 0.0])
    assert rules._crossings(universe, two_humps, np.array([0.5])) is None
    triangle = np.array([0.0, 0.5, 1.0, 0.5, 0.0])
    np.testing.assert_allclose(rules._crossings(universe, triangle, np.array([0.5])),
                               [[-0.5, 0.5]])


def test_compiling_does_not_import_skfuzzy(tmp_path):
    # importing scikit-fuzzy alone took 2 to 6 s of the fuzzy-controller's start
    code = ("import sys; from vistrack.services.fuzzy_controller.control import FuzzySurface, "
            "SurfaceConfig; s = FuzzySurface.compile(config=SurfaceConfig(cache_dir="
            f"{str(tmp_path)!r})); assert not s.from_cache; "
            "print(sorted(m for m in sys.modules if 'skfuzzy' in m))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert out.strip() == "[]"


# -- signs and shape -----------------------------------------------------------------------------

@pytest.mark.parametrize("ex", [0.02, 0.3, 0.7, 1.0, 3.0])
def test_target_right_moves_right(surface, ex):
    _, vy = surface.evaluate(ex, 0.0, 0.0, 0.0)
    assert vy < 0.0
    _, vy_mirror = surface.evaluate(-ex, 0.0, 0.0, 0.0)
    assert vy_mirror > 0.0


@pytest.mark.parametrize("ez", [0.01, 0.2, 0.5, 2.0])
def test_target_too_big_backs_off(surface, ez):
    vx, _ = surface.evaluate(0.0, 0.0, ez, 0.0)
    assert vx < 0.0
    vx_mirror, _ = surface.evaluate(0.0, 0.0, -ez, 0.0)
    assert vx_mirror > 0.0


def test_zero_error_zero_command(surface):
    vx, vy = surface.evaluate(0.0, 0.0, 0.0, 0.0)
    assert abs(vx) < 1e-9 and abs(vy) < 1e-9


def test_outputs_saturate_within_range(surface):
    inputs = _random_inputs(LIMITS, 500, seed=3) * 10.0  # mostly far outside the limits
    for ex, dex, ez, dez in inputs:
        vx, vy = surface.evaluate(ex, dex, ez, dez)
        assert abs(vx) <= LIMITS.vx_max and abs(vy) <= LIMITS.vy_max
    # Full error and full rate fire only the outer output term, a right-angled triangle from
    # half the limit to the limit: its centroid is 5/6 of the limit.
    vx, vy = surface.evaluate(10.0, 10.0, 10.0, 10.0)
    assert vy == pytest.approx(-5 / 6 * LIMITS.vy_max, abs=1e-3)
    assert vx == pytest.approx(-5 / 6 * LIMITS.vx_max, abs=1e-3)
    # beyond the limits the inputs are clipped, not extrapolated
    assert surface.evaluate(5.0, 0.0, 5.0, 0.0) == surface.evaluate(LIMITS.ex_max, 0.0,
                                                                    LIMITS.ez_max, 0.0)


@pytest.mark.parametrize("output", list(AXES))
@pytest.mark.parametrize("rate_fraction", [0.0, -0.5, -0.25, 0.25, 0.5])
def test_monotone_in_error(surface, output, rate_fraction):
    err, rate = AXES[output]
    e_max, r_max = LIMITS.limit(err), LIMITS.limit(rate)
    sweep = np.linspace(-1.2 * e_max, 1.2 * e_max, 1201)
    values = np.array([surface.value(output, e, rate_fraction * r_max) for e in sweep])
    assert np.all(np.diff(values) <= 1e-12), "command rises with the error somewhere"
    assert values[0] > 0.1 * LIMITS.limit(output) and values[-1] < -0.1 * LIMITS.limit(output)


def test_rate_adds_damping(surface):
    # PD: an error that is already shrinking asks for less, one that grows for more
    _, still = surface.evaluate(0.4, 0.0, 0.0, 0.0)
    _, shrinking = surface.evaluate(0.4, -0.5, 0.0, 0.0)
    _, growing = surface.evaluate(0.4, 0.5, 0.0, 0.0)
    assert growing < still < shrinking


def test_rule_table_is_pd_form():
    # output index = -(error index + rate index), saturated; NB..PB = -2..2, N..P = -1..1
    e_index = {t: i - 2 for i, t in enumerate(rules.ERROR_TERMS)}
    r_index = {t: i - 1 for i, t in enumerate(rules.RATE_TERMS)}
    o_terms = list(rules.OUTPUT_TERMS)
    for e_term, outs in rules.RULE_TABLE.items():
        for r_term, o_term in zip(rules.RATE_TERMS, outs, strict=True):
            expected = max(-2, min(2, -(e_index[e_term] + r_index[r_term])))
            assert o_terms.index(o_term) - 2 == expected, (e_term, r_term, o_term)


def test_rules_markdown_lists_every_rule():
    text = rules.rules_markdown()
    for e_term, outs in rules.RULE_TABLE.items():
        assert f"| {e_term} | " + " | ".join(outs) + " |" in text
    for name in rules.VARIABLES:
        assert f"`{name}`" in text


# -- the cache -----------------------------------------------------------------------------------

def _fail_compile(config):
    raise AssertionError("scikit-fuzzy was run although the cache should have answered")


def test_cache_round_trip(surface, cache_dir, monkeypatch):
    assert not surface.from_cache and surface.cache_path is not None
    assert surface.cache_path.parent == cache_dir and surface.cache_path.exists()
    monkeypatch.setattr(control, "_compute_tables", _fail_compile)
    loaded = FuzzySurface.compile(LIMITS, SurfaceConfig(cache_dir=str(cache_dir)))
    assert loaded.from_cache
    for out in AXES:
        np.testing.assert_array_equal(loaded.grid(out)[2], surface.grid(out)[2])


def test_corrupt_cache_is_recompiled(surface, tmp_path, monkeypatch):
    path = tmp_path / surface.cache_path.name
    path.write_bytes(b"not an npz file")
    calls = []

    def fake_compile(config):
        calls.append(config)
        return {out: surface.grid(out)[2] / LIMITS.limit(out) for out in AXES}

    monkeypatch.setattr(control, "_compute_tables", fake_compile)
    first = FuzzySurface.compile(LIMITS, SurfaceConfig(cache_dir=str(tmp_path)))
    assert len(calls) == 1 and not first.from_cache
    second = FuzzySurface.compile(LIMITS, SurfaceConfig(cache_dir=str(tmp_path)))
    assert len(calls) == 1 and second.from_cache  # the bad file was replaced


def test_cache_key_follows_rule_data(surface, tmp_path, monkeypatch):
    tables = {out: surface.grid(out)[2] / LIMITS.limit(out) for out in AXES}
    monkeypatch.setattr(control, "_compute_tables", lambda config: tables)
    config = SurfaceConfig(cache_dir=str(tmp_path))
    before = FuzzySurface.compile(LIMITS, config).cache_path
    assert FuzzySurface.compile(FuzzyLimits(vx_max=1.0), config).cache_path == before
    monkeypatch.setitem(rules.RULE_TABLE, "Z", ("PS", "Z", "Z"))
    assert FuzzySurface.compile(LIMITS, config).cache_path != before


# -- the controllers -----------------------------------------------------------------------------

def _fuzzy(surface, **config):
    return FuzzyController(surface, ControllerConfig(**config))


def _proportional(surface, **config):
    return ProportionalController(ProportionalGains(), ControllerConfig(**config))


CONTROLLERS = [_fuzzy, _proportional]


@pytest.mark.parametrize("make", CONTROLLERS)
def test_controller_signs(surface, make):
    c = make(surface, x_ref=WIDTH / 2, scale_ref=1.0)
    right = c.update(WIDTH * 0.75, 1.0, 0.0, WIDTH, npi=50)
    assert right.vy < 0 and abs(right.vx) < 1e-9 and right.wz == 0.0 and not right.stale
    c.reset()
    close = c.update(WIDTH / 2, 1.3, 0.0, WIDTH, npi=50)
    assert close.vx < 0 and abs(close.vy) < 1e-9
    c.reset()
    far_left = c.update(WIDTH * 0.2, 0.8, 0.0, WIDTH, npi=50)
    assert far_left.vx > 0 and far_left.vy > 0


@pytest.mark.parametrize("make", CONTROLLERS)
def test_set_point_captured_from_first_estimate(surface, make):
    c = make(surface)
    first = c.update(97.0, 3.5, 0.0, WIDTH, npi=40)
    assert (c.x_ref, c.scale_ref) == (97.0, 3.5)
    assert abs(first.vx) < 1e-9 and abs(first.vy) < 1e-9 and not first.stale
    c.update(97.0 + 32.0, 3.5 * math.exp(0.1), 0.05, WIDTH, npi=40)
    ex, _, ez, _ = c.errors
    assert ex == pytest.approx(32.0 / 128.0) and ez == pytest.approx(0.1)


def test_explicit_set_point(surface):
    c = _fuzzy(surface)
    c.set_point(x_ref=128.0, scale_ref=2.0)
    c.update(160.0, 1.0, 0.0, WIDTH)
    ex, _, ez, _ = c.errors
    assert ex == pytest.approx(0.25) and ez == pytest.approx(math.log(0.5))


def test_rates_from_filtered_differences(surface):
    c = _fuzzy(surface, x_ref=128.0, scale_ref=1.0, rate_tau_s=0.1)
    slope = 0.3  # ex per second
    dt = 1 / 30
    rates = []
    for k in range(40):
        t = k * dt
        c.update(128.0 + 128.0 * slope * t, 1.0, t, WIDTH)
        rates.append(c.errors[1])
    assert rates[0] == 0.0  # no difference yet: start from rest
    assert 0.0 < rates[1] < slope  # low-passed, not the raw difference
    assert rates[-1] == pytest.approx(slope, rel=1e-3)
    assert c.errors[3] == 0.0  # constant scale, no distance rate


def test_rates_restart_after_gap(surface):
    c = _fuzzy(surface, x_ref=128.0, scale_ref=1.0, stale_after_s=0.3)
    for k in range(10):
        c.update(128.0 + 4.0 * k, 1.0, k * 0.03, WIDTH)
    assert c.errors[1] > 0.0
    c.update(200.0, 1.0, 5.0, WIDTH)  # after a long gap the difference would be meaningless
    assert c.errors[1] == 0.0


@pytest.mark.parametrize("make", CONTROLLERS)
def test_watchdog_stops_after_bound(surface, make):
    c = make(surface, x_ref=128.0, scale_ref=1.0, stale_after_s=0.3)
    assert c.command_at(0.0).stale  # nothing received yet
    cmd = c.update(200.0, 1.2, 10.0, WIDTH, npi=30)
    assert not cmd.stale and cmd.vy < 0
    assert c.command_at(10.29) == cmd
    late = c.command_at(10.31)
    assert late == Command(0.0, 0.0, 0.0, True)


@pytest.mark.parametrize("make", CONTROLLERS)
def test_watchdog_stops_on_npi_collapse(surface, make):
    c = make(surface, x_ref=128.0, scale_ref=1.0, min_npi=5)
    assert not c.update(200.0, 1.2, 0.0, WIDTH, npi=5).stale
    lost = c.update(190.0, 1.2, 0.03, WIDTH, npi=4)
    assert lost == Command(0.0, 0.0, 0.0, True)
    assert c.command_at(0.04).stale  # well within the time bound
    back = c.update(180.0, 1.2, 0.06, WIDTH, npi=20)
    assert not back.stale and back.vy < 0
    assert c.errors[1] == 0.0  # the rate restarted across the collapse


@pytest.mark.parametrize("make", CONTROLLERS)
def test_an_invalid_estimate_does_not_move_the_robot(surface, make):
    """``valid: false`` (too few features for a meaningful centroid) stops the robot, even
    with the NPI check off, until a valid estimate comes."""
    c = make(surface, x_ref=128.0, scale_ref=1.0, min_npi=0)
    assert not c.update(200.0, 1.2, 0.0, WIDTH, npi=40).stale
    stop = c.update(200.0, 1.2, 0.03, WIDTH, npi=0, valid=False)
    assert stop == Command(0.0, 0.0, 0.0, True)
    assert c.command_at(0.04).stale
    back = c.update(200.0, 1.2, 0.06, WIDTH, npi=40)
    assert not back.stale and back.vy < 0 and c.errors[1] == 0.0


def test_bad_estimates_rejected(surface):
    c = _fuzzy(surface)
    c.update(128.0, 1.0, 1.0, WIDTH)
    for args in [(math.nan, 1.0, 2.0, WIDTH), (128.0, 0.0, 2.0, WIDTH),
                 (128.0, 1.0, 2.0, 0.0), (128.0, 1.0, 1.0, WIDTH), (128.0, 1.0, 0.5, WIDTH)]:
        with pytest.raises(ValueError):
            c.update(*args)
    # nothing above touched the state: the next estimate is differenced against t = 1.0
    cmd = c.update(128.0 + 12.8, 1.0, 1.1, WIDTH)
    assert not cmd.stale and c.errors[1] > 0.0


def test_an_extreme_scale_is_refused_without_touching_the_state(surface):
    """Finite, positive, but 1 / 5e-324 overflows: the scale error would be infinite and the
    rate NaN, which jammed the track (every later estimate refused as NaN)."""
    c = _fuzzy(surface)
    c.update(128.0, 5e-324, 1.0, WIDTH, npi=50)
    before = c.errors
    with pytest.raises(ValueError, match="no finite error"):
        c.update(128.0, 1.0, 1.1, WIDTH, npi=50)
    assert c.errors == before and all(math.isfinite(v) for v in c.errors)
    # the stamp it carried was not taken: one between the two is still in order
    c.update(128.0, 5e-324, 1.05, WIDTH, npi=50)
    c.reset()  # a new track starts from a sane set point
    cmd = c.update(128.0 + 12.8, 1.0, 2.0, WIDTH, npi=50)
    assert not cmd.stale and all(math.isfinite(v) for v in (cmd.vx, cmd.vy))


@pytest.mark.parametrize(("xc", "scale", "vy", "vx"), [
    (160.0, 1.1, -0.8 * 0.25, -1.5 * math.log(1.1)),   # linear range
    (96.0, 0.95, 0.8 * 0.25, 1.5 * math.log(1 / 0.95)),
    (256.0, 3.0, -0.3, -0.4),                          # saturated
    (0.0, 0.2, 0.3, 0.4),
])
def test_proportional_law(xc, scale, vy, vx):
    gains = ProportionalGains(kx=0.8, kz=1.5, vy_max=0.3, vx_max=0.4)
    c = ProportionalController(gains, ControllerConfig(x_ref=128.0, scale_ref=1.0))
    cmd = c.update(xc, scale, 0.0, WIDTH)
    assert cmd.vy == pytest.approx(vy) and cmd.vx == pytest.approx(vx)
    assert cmd.wz == 0.0 and not cmd.stale


# -- configuration -------------------------------------------------------------------------------

@pytest.mark.parametrize(("cls", "field", "value"), [
    (FuzzyLimits, "vy_max", 0.0),
    (FuzzyLimits, "ex_max", 2.0),
    (FuzzyLimits, "dez_max", math.nan),
    (FuzzyLimits, "vx_max", True),
    (ControllerConfig, "stale_after_s", -1.0),
    (ControllerConfig, "min_npi", 2.5),
    (ControllerConfig, "rate_tau_s", 11.0),
    (ControllerConfig, "scale_ref", 0.0),
    (ProportionalGains, "kx", -0.1),
    (ProportionalGains, "vx_max", 6.0),
    (SurfaceConfig, "grid_error", 2),
    (SurfaceConfig, "grid_rate", "81"),
])
def test_config_validation_names_field_value_and_range(cls, field, value):
    with pytest.raises(ParamError) as info:
        cls(**{field: value})
    message = str(info.value)
    assert field in message and repr(value) in message
    assert "[" in message or "(" in message  # the allowed range


# -- speed (deselected by default: -m bench) ----------------------------------------------------

@pytest.mark.bench
def test_decision_time(surface):
    c = FuzzyController(surface, ControllerConfig(x_ref=128.0, scale_ref=1.0))
    n = 20000
    start = time.perf_counter()
    for k in range(n):
        c.update(128.0 + (k % 50), 1.0 + 0.001 * (k % 30), k * 0.033, WIDTH, npi=50)
    per_decision = (time.perf_counter() - start) / n
    sim = _reference(LIMITS)
    m = 30
    start = time.perf_counter()
    for ex, dex, ez, dez in _random_inputs(LIMITS, m, seed=4):
        _skfuzzy(sim, ex, dex, ez, dez)
    per_compute = (time.perf_counter() - start) / m
    print(f"decision {per_decision * 1e6:.2f} us, skfuzzy compute {per_compute * 1e6:.0f} us, "
          f"{per_compute / per_decision:.0f}x, compile {surface.compile_seconds:.2f} s")
    assert per_decision < 50e-6
    assert per_compute / per_decision >= 100
