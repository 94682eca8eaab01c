"""Effects, Lenth's method and ANOVA against published worked examples and least squares.

Published references (data and results are quoted from the sources, not from this code):

* NIST/SEMATECH e-Handbook of Statistical Methods, Section 5.4.7.1 "Full factorial example"
  (https://www.itl.nist.gov/div898/handbook/pri/section4/pri471.htm): ceramic strength, an
  unreplicated 2^5 with four- and five-factor interactions pooled into error (JMP output).
* Montgomery, D. C. (2012), Design and Analysis of Experiments, 8th ed., Wiley: Solutions
  Manual, Problem 8.1: a 2^(4-1) with I = ABCD (D = ABC) on replicate 1 of Problem 6.7,
  analysed with Design-Expert (effects, sums of squares, Lenth's ME/SME, ANOVA).

The least-squares checks fit the models with numpy.linalg.lstsq and take F statistics as
extra sums of squares of full against reduced fits, independently of the module's formulas.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy import stats

from vistrack.services.auto_tuner.anova import (
    AnovaTable,
    anova,
    effects,
    lenth,
    sums_of_squares,
    table3,
)
from vistrack.services.auto_tuner.design import fractional_factorial, paper_design

# ----------------------------------------------------------------------------- NIST 5.4.7.1

# speed (X1), rate (X2), grit (X3), direction (X4), batch (X5), strength: the published table
# in its standard order (run order column omitted).
NIST_CERAMIC = [
    (-1, -1, -1, -1, -1, 680.45),
    (1, -1, -1, -1, -1, 722.48),
    (-1, 1, -1, -1, -1, 702.14),
    (1, 1, -1, -1, -1, 666.93),
    (-1, -1, 1, -1, -1, 703.67),
    (1, -1, 1, -1, -1, 642.14),
    (-1, 1, 1, -1, -1, 692.98),
    (1, 1, 1, -1, -1, 669.26),
    (-1, -1, -1, 1, -1, 491.58),
    (1, -1, -1, 1, -1, 475.52),
    (-1, 1, -1, 1, -1, 478.76),
    (1, 1, -1, 1, -1, 568.23),
    (-1, -1, 1, 1, -1, 444.72),
    (1, -1, 1, 1, -1, 410.37),
    (-1, 1, 1, 1, -1, 428.51),
    (1, 1, 1, 1, -1, 491.47),
    (-1, -1, -1, -1, 1, 607.34),
    (1, -1, -1, -1, 1, 620.80),
    (-1, 1, -1, -1, 1, 610.55),
    (1, 1, -1, -1, 1, 638.04),
    (-1, -1, 1, -1, 1, 585.19),
    (1, -1, 1, -1, 1, 586.17),
    (-1, 1, 1, -1, 1, 601.67),
    (1, 1, 1, -1, 1, 608.31),
    (-1, -1, -1, 1, 1, 442.90),
    (1, -1, -1, 1, 1, 434.41),
    (-1, 1, -1, 1, 1, 417.66),
    (1, 1, -1, 1, 1, 510.84),
    (-1, -1, 1, 1, 1, 392.11),
    (1, -1, 1, 1, 1, 343.22),
    (-1, 1, 1, 1, 1, 385.52),
    (1, 1, 1, 1, 1, 446.73),
]

# 26-parameter model (all terms up to three-factor interactions; error = the five 4FIs and
# the 5FI, 6 df): term (X1..X5 -> A..E), sum of squares, F ratio, Prob>F ("<.0001" -> None).
NIST_26_TERM = [
    ("A", 894.33, 2.8175, 0.1442),
    ("B", 3497.20, 11.0175, 0.0160),
    ("AB", 4872.57, 15.3505, 0.0078),
    ("C", 12663.96, 39.8964, 0.0007),
    ("AC", 1838.76, 5.7928, 0.0528),
    ("BC", 307.46, 0.9686, 0.3630),
    ("ABC", 357.05, 1.1248, 0.3297),
    ("D", 315132.65, 992.7901, None),
    ("AD", 1637.21, 5.1578, 0.0636),
    ("BD", 1972.71, 6.2148, 0.0470),
    ("ABD", 5895.62, 18.5735, 0.0050),
    ("CD", 3158.34, 9.9500, 0.0197),
    ("ACD", 2.12, 0.0067, 0.9376),
    ("BCD", 44.49, 0.1401, 0.7210),
    ("E", 33653.91, 106.0229, None),
    ("AE", 465.05, 1.4651, 0.2716),
    ("BE", 199.15, 0.6274, 0.4585),
    ("ABE", 144.71, 0.4559, 0.5247),
    ("CE", 29.36, 0.0925, 0.7713),
    ("ACE", 30.36, 0.0957, 0.7676),
    ("BCE", 25.58, 0.0806, 0.7860),
    ("DE", 1328.83, 4.1863, 0.0867),
    ("ADE", 544.58, 1.7156, 0.2382),
    ("BDE", 167.31, 0.5271, 0.4952),
    ("CDE", 32.46, 0.1023, 0.7600),
]

# The 12-term model after stepwise selection (error: the other 19 effects).
NIST_12_TERM = [
    ("A", 894.33, 3.9942, 0.0602),
    ("B", 3497.20, 15.6191, 0.0009),
    ("AB", 4872.57, 21.7618, 0.0002),
    ("C", 12663.96, 56.5595, None),
    ("AC", 1838.76, 8.2122, 0.0099),
    ("D", 315132.65, 1407.4390, None),
    ("AD", 1637.21, 7.3121, 0.0141),
    ("BD", 1972.71, 8.8105, 0.0079),
    ("ABD", 5895.62, 26.3309, None),
    ("CD", 3158.34, 14.1057, 0.0013),
    ("E", 33653.91, 150.3044, None),
    ("DE", 1328.83, 5.9348, 0.0249),
]


def check_published_rows(table: AnovaTable, published) -> None:
    """SS to the published 2 decimals, F to 4 decimals, p to 4 decimals."""
    assert [r.term for r in table.rows] == [term for term, *_ in published]
    for term, ss, f_ratio, p in published:
        row = table.row(term)
        assert row.df == 1
        assert row.ss == pytest.approx(ss, abs=0.005), term
        # JMP prints F to 4 decimals from its own arithmetic; the largest F (1407.4390) is
        # reproduced to 1.1e-7 relative, so a 1e-6 relative bound covers it.
        assert row.F == pytest.approx(f_ratio, abs=5e-5, rel=1e-6), term
        if p is None:
            assert row.p < 1e-4, term
        else:
            assert row.p == pytest.approx(p, abs=5e-5), term


@pytest.fixture(scope="module")
def ceramic():
    data = np.array(NIST_CERAMIC)
    design = fractional_factorial(5, {})
    # The published design columns are the standard (Yates) order this module builds.
    np.testing.assert_array_equal(design.matrix, data[:, :5])
    return design, data[:, 5]


def test_nist_ceramic_26_term_anova_pools_high_order_interactions(ceramic):
    """NIST e-Handbook 5.4.7.1, 'Results from fitting up to and including third-order
    interaction terms': RSquare 0.995127, Root Mean Square Error 17.81632, mean 546.8959."""
    design, y = ceramic
    table = anova(design, y, [t for t, *_ in NIST_26_TERM])
    check_published_rows(table, NIST_26_TERM)
    assert table.error.df == 6
    assert table.root_mse == pytest.approx(17.81632, abs=5e-6)
    assert table.r_squared == pytest.approx(0.995127, abs=5e-7)
    assert np.mean(y) == pytest.approx(546.8959, abs=5e-5)


def test_nist_ceramic_12_term_model(ceramic):
    """NIST e-Handbook 5.4.7.1, 'Results from fitting the 12-term model': RSquare 0.989114,
    Root Mean Square Error 14.96346."""
    design, y = ceramic
    table = anova(design, y, [t for t, *_ in NIST_12_TERM])
    check_published_rows(table, NIST_12_TERM)
    assert table.error.df == 32 - 1 - 12
    assert table.root_mse == pytest.approx(14.96346, abs=5e-6)
    assert table.r_squared == pytest.approx(0.989114, abs=5e-7)


# ----------------------------------------------------------------------------- Montgomery 8.1

# Treatment combinations and yields as printed (design column D = ABC, I = ABCD).
MONTGOMERY_8_1 = [
    ("(1)", 90),
    ("ad", 72),
    ("bd", 87),
    ("ab", 83),
    ("cd", 99),
    ("ac", 81),
    ("bc", 88),
    ("abcd", 80),
]
# Design-Expert "Term / Effect / SumSqr / % Contribtn" for the seven estimable effects.
MONTGOMERY_8_1_EFFECTS = [
    ("A", -12, 288, 64.2857),
    ("B", -1, 2, 0.446429),
    ("C", 4, 32, 7.14286),
    ("D", -1, 2, 0.446429),
    ("AB", 6, 72, 16.0714),
    ("AC", -1, 2, 0.446429),
    ("AD", -5, 50, 11.1607),
]


@pytest.fixture(scope="module")
def montgomery_8_1():
    design = fractional_factorial(4, {"D": "ABC"})
    labels = [
        "".join(f.lower() for f, v in zip(design.factors, run, strict=True) if v > 0) or "(1)"
        for run in design.matrix
    ]
    assert labels == [label for label, _ in MONTGOMERY_8_1]
    return design, np.array([y for _, y in MONTGOMERY_8_1], dtype=float)


def test_montgomery_8_1_effects_and_sums_of_squares(montgomery_8_1):
    """Montgomery (2012), Solutions Manual, Problem 8.1, Design-Expert effect list."""
    design, y = montgomery_8_1
    terms = [t for t, *_ in MONTGOMERY_8_1_EFFECTS]
    eff = effects(design, y, terms)
    ss = sums_of_squares(design, y, terms)
    total = sum(ss.values())
    assert total == pytest.approx(448.0)  # "Cor Total 448.00"
    for term, effect, sum_sq, percent in MONTGOMERY_8_1_EFFECTS:
        assert eff[term] == pytest.approx(effect, abs=1e-12)
        assert ss[term] == pytest.approx(sum_sq, abs=1e-9)
        assert 100 * ss[term] / total == pytest.approx(percent, rel=5e-6)


def test_montgomery_8_1_lenth_margins_of_error(montgomery_8_1):
    """Montgomery (2012), Solutions Manual, Problem 8.1: Lenth's ME 22.5856, SME 54.0516.

    PSE = 1.5 * median(12, 1, 4, 1, 6, 1, 5) = 6 (nothing trimmed). Design-Expert's t
    quantile at the fractional d = 7/3 differs from scipy's in the fifth significant digit
    (ME 22.58474, SME 54.04984 here), so the check is to 1e-4 relative.
    """
    design, y = montgomery_8_1
    result = lenth(effects(design, y, [t for t, *_ in MONTGOMERY_8_1_EFFECTS]))
    assert result.pse == pytest.approx(6.0)
    assert result.df == pytest.approx(7 / 3)
    assert result.me == pytest.approx(22.5856, rel=1e-4)
    assert result.sme == pytest.approx(54.0516, rel=1e-4)
    # |A| = 12 < ME: Design-Expert's half-normal plot flags nothing as significant.
    assert result.significant(0.95) == []


def test_montgomery_8_1_anova_of_the_hierarchical_model(montgomery_8_1):
    """Montgomery (2012), Solutions Manual, Problem 8.1: 'ANOVA for Selected Factorial Model'
    with A, B, D, AB, AD; residual = C and AC (= BD), 2 df."""
    design, y = montgomery_8_1
    table = anova(design, y, ["A", "B", "D", "AB", "AD"])
    published = [  # term, SS, F value, Prob > F
        ("A", 288.00, 16.94, 0.0543),
        ("B", 2.00, 0.12, 0.7643),
        ("D", 2.00, 0.12, 0.7643),
        ("AB", 72.00, 4.24, 0.1758),
        ("AD", 50.00, 2.94, 0.2285),
    ]
    for term, ss, f_value, p in published:
        row = table.row(term)
        assert row.ss == pytest.approx(ss, abs=0.005)
        assert row.F == pytest.approx(f_value, abs=0.005)
        assert row.p == pytest.approx(p, abs=5e-5)
    assert (table.model.df, table.model.ss) == (5, pytest.approx(414.00, abs=0.005))
    assert table.model.ms == pytest.approx(82.80, abs=0.005)
    assert table.model.F == pytest.approx(4.87, abs=0.005)
    assert table.model.p == pytest.approx(0.1791, abs=5e-5)
    assert (table.error.df, table.error.ss, table.error.ms) == (2, 34.0, 17.0)
    assert table.total_ss == pytest.approx(448.00) and table.total_df == 7


# ----------------------------------------------------------------------------- least squares


def lstsq_rss(x: np.ndarray, y: np.ndarray) -> float:
    beta, *_ = np.linalg.lstsq(x, y, rcond=None)
    return float(((y - x @ beta) ** 2).sum())


def with_intercept(columns: np.ndarray) -> np.ndarray:
    return np.column_stack([np.ones(columns.shape[0]), columns])


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_effects_are_twice_the_least_squares_coefficients(seed):
    design = paper_design()
    terms = design.terms(2)
    y = np.random.default_rng(seed).normal(10.0, 3.0, design.n_runs)
    beta, *_ = np.linalg.lstsq(with_intercept(design.columns(terms)), y, rcond=None)
    eff = effects(design, y)
    assert list(eff) == terms
    np.testing.assert_allclose(list(eff.values()), 2 * beta[1:], rtol=1e-10, atol=1e-12)
    ss = sums_of_squares(design, y)
    np.testing.assert_allclose(list(ss.values()), 16 * beta[1:] ** 2, rtol=1e-10)


@pytest.mark.parametrize(("seed", "pool"), [(4, 3), (5, 6), (6, 10)])
def test_pooled_anova_f_equals_extra_sum_of_squares_f(seed, pool):
    design = paper_design()
    terms = design.terms(2)
    x = design.columns(terms)
    rng = np.random.default_rng(seed)
    y = x @ rng.normal(0.0, 2.0, 15) + rng.normal(0.0, 1.0, 16)
    table = anova(design, y, terms, pool=pool)

    # The pooled terms are the `pool` smallest |effects| (SS = 16 beta^2 is monotone in |beta|).
    beta, *_ = np.linalg.lstsq(with_intercept(x), y, rcond=None)
    smallest = {terms[j] for j in np.argsort(np.abs(beta[1:]))[:pool]}
    assert set(table.pooled) == smallest
    kept = [j for j, t in enumerate(terms) if t not in smallest]
    assert [r.term for r in table.rows] == [terms[j] for j in kept]

    full = with_intercept(x[:, kept])
    rss_full = lstsq_rss(full, y)
    df_error = 16 - 1 - len(kept)
    assert table.error.df == df_error == pool
    assert table.error.ss == pytest.approx(rss_full, rel=1e-9)
    for col, j in enumerate(kept):
        reduced = np.delete(full, col + 1, axis=1)
        f_ref = (lstsq_rss(reduced, y) - rss_full) / (rss_full / df_error)
        row = table.row(terms[j])
        assert row.F == pytest.approx(f_ref, rel=1e-8)
        assert row.p == pytest.approx(stats.f.sf(f_ref, 1, df_error), rel=1e-8)


@pytest.mark.parametrize("seed", [7, 8])
def test_unpooled_residual_of_a_full_factorial_equals_least_squares(seed):
    design = fractional_factorial(5, {})
    terms = design.terms(2)
    y = np.random.default_rng(seed).normal(0.0, 1.0, 32)
    table = anova(design, y)
    full = with_intercept(design.columns(terms))
    rss_full = lstsq_rss(full, y)
    assert table.pooled == ()
    assert table.error.df == 32 - 1 - 15
    assert table.error.ss == pytest.approx(rss_full, rel=1e-9)
    assert table.r_squared == pytest.approx(1 - rss_full / ((y - y.mean()) ** 2).sum())
    for col, term in enumerate(terms):
        f_ref = (lstsq_rss(np.delete(full, col + 1, axis=1), y) - rss_full) / (rss_full / 16)
        assert table.row(term).F == pytest.approx(f_ref, rel=1e-8)


@pytest.mark.parametrize("seed", [9, 10])
def test_replicated_anova_tests_against_pure_error(seed):
    design = fractional_factorial(3, {})
    terms = ["A", "B", "C", "AB"]
    reps = 3
    rng = np.random.default_rng(seed)
    y = (design.columns(terms) @ rng.normal(0, 2, 4))[:, None] + rng.normal(0, 1, (8, reps))
    table = anova(design, y, terms)

    # Stack the observations; the cell-means model (one dummy per run) leaves pure error.
    obs = y.ravel()
    x = np.repeat(design.columns(terms), reps, axis=0)
    cells = np.repeat(np.eye(8), reps, axis=0)
    rss_cells = lstsq_rss(cells, obs)
    ms_pure = rss_cells / (8 * (reps - 1))
    full = with_intercept(x)
    rss_model = lstsq_rss(full, obs)
    assert table.error.df == 16
    assert table.error.ss == pytest.approx(rss_cells, rel=1e-9)
    assert table.lack_of_fit is not None
    assert table.lack_of_fit.df == 8 - 1 - 4
    assert table.lack_of_fit.ss == pytest.approx(rss_model - rss_cells, rel=1e-9)
    assert table.lack_of_fit.F == pytest.approx((rss_model - rss_cells) / 3 / ms_pure, rel=1e-8)
    for col, term in enumerate(terms):
        extra = lstsq_rss(np.delete(full, col + 1, axis=1), obs) - rss_model
        assert table.row(term).F == pytest.approx(extra / ms_pure, rel=1e-8)
    # Effects of replicated runs are those of the run means.
    np.testing.assert_allclose(
        list(effects(design, y, terms).values()),
        list(effects(design, y.mean(axis=1), terms).values()),
    )


def test_saturated_replicated_model_has_no_lack_of_fit():
    design = fractional_factorial(2, {})
    y = np.array([[1.0, 2.0], [3.0, 5.0], [2.0, 2.5], [7.0, 6.0]])
    table = anova(design, y, ["A", "B", "AB"])
    assert table.lack_of_fit is None
    assert table.error.df == 4


# ----------------------------------------------------------------------------- Lenth


def test_lenth_trims_active_effects_before_the_second_median():
    # median|c| = 1.5, s0 = 2.25, so 30 and 40 (> 2.5 s0 = 5.625) are left out:
    # median(0.5, 1, 1, 1.5, 2) = 1, PSE = 1.5.
    c = {"A": 0.5, "B": -1.0, "C": 1.0, "D": 1.5, "E": -2.0, "AB": 30.0, "AC": 40.0}
    result = lenth(c)
    assert result.s0 == pytest.approx(2.25)
    assert result.pse == pytest.approx(1.5)
    assert result.df == pytest.approx(7 / 3)
    np.testing.assert_allclose(result.t, np.array(list(c.values())) / 1.5)
    np.testing.assert_allclose(result.p, 2 * stats.t.sf(np.abs(result.t), 7 / 3))
    assert result.significant(0.95) == ["AB", "AC"]
    assert result.me == pytest.approx(result.margin_of_error(0.95))
    assert result.sme == pytest.approx(result.simultaneous_margin_of_error(0.95))
    assert result.sme > result.me


def test_lenth_is_robust_to_the_size_of_the_active_effects():
    base = np.array([0.3, -0.8, 1.1, -0.2, 0.6, 0.9, -1.4, 0.4, 5.0, -7.0])
    inflated = base.copy()
    inflated[-2:] *= 100
    assert lenth(inflated).pse == pytest.approx(lenth(base).pse)


@pytest.mark.parametrize("level", [0.95, 0.99])
def test_lenth_significance_matches_the_margin_of_error(level):
    c = np.random.default_rng(11).normal(0, 1, 15)
    c[:3] = [8.0, -6.0, 3.5]
    result = lenth(c)
    expected = [
        t for t, v in zip(result.terms, c, strict=True) if abs(v) > result.margin_of_error(level)
    ]
    assert result.significant(level) == expected
    simultaneous = [
        t
        for t, v in zip(result.terms, c, strict=True)
        if abs(v) > result.simultaneous_margin_of_error(level)
    ]
    assert result.significant(level, simultaneous=True) == simultaneous


@pytest.mark.parametrize(
    ("values", "message"),
    [([1.0, 2.0], "at least 3"), ([0.0, 0.0, 0.0, 1.0], "zero"), ([1.0, np.nan, 2.0], "finite")],
)
def test_lenth_rejects_unusable_effects(values, message):
    with pytest.raises(ValueError, match=message):
        lenth(values)


# ----------------------------------------------------------------------------- pooling


def test_auto_pooling_keeps_the_active_effects():
    design = paper_design()
    rng = np.random.default_rng(12)
    y = 10 * design.columns("A")[:, 0] + 6 * design.columns("CD")[:, 0] + rng.normal(0, 0.5, 16)
    table = anova(design, y, pool="auto")
    assert [r.term for r in table.rows] == ["A", "CD"]
    assert table.error.df == 13
    assert table.significant(0.99) == ["A", "CD"]


def test_pool_zero_equals_no_pooling():
    design = fractional_factorial(5, {})
    y = np.random.default_rng(13).normal(0, 1, 32)
    assert anova(design, y, pool=0).error.ss == pytest.approx(anova(design, y).error.ss)


# ----------------------------------------------------------------------------- Table 3


class Preset:
    """A result whose significant terms are fixed, to test Table 3's bookkeeping alone."""

    def __init__(self, at_99, at_95):
        self.lists = {0.99: at_99, 0.95: at_95}

    def significant(self, level=0.95):
        return self.lists[level]


def test_table3_uses_paper_numbers_and_separates_95_from_99():
    # Table 3 of the paper, row t1: 99 % -> 1, 2; 95 % -> 12, 13, 23, 34.
    result = Preset(["B", "A"], ["A", "AB", "B", "CD", "AC", "BC"])
    assert table3({"t1": result}) == {"t1": {"99": ["1", "2"], "95": ["12", "13", "23", "34"]}}


def test_table3_from_real_analyses():
    design = paper_design()
    rng = np.random.default_rng(14)
    y = 8 * design.columns("C")[:, 0] + 5 * design.columns("CD")[:, 0] + rng.normal(0, 0.3, 16)
    both = {"tf": anova(design, y, pool="auto"), "tf_lenth": lenth(effects(design, y))}
    table = table3(both)
    for response in both:
        assert table[response]["99"] == ["3", "34"]
        assert set(table[response]["95"]).isdisjoint(table[response]["99"])


# ----------------------------------------------------------------------------- bad input


@pytest.fixture(scope="module")
def paper():
    return paper_design()


@pytest.mark.parametrize(
    ("y", "terms", "kwargs", "message"),
    [
        (np.zeros(15), None, {}, "15 runs but the design has 16"),
        (np.r_[np.nan, np.zeros(15)], None, {}, "finite"),
        (np.zeros((16, 2, 2)), None, {}, "shape"),
        (np.arange(16.0), ["A", "BCDE"], {}, "aliased"),
        (np.arange(16.0), ["ABCDE"], {}, "defining relation"),
        (np.arange(16.0), ["A", "A"], {}, "twice"),
        (np.arange(16.0), ["AX"], {}, "unknown factor"),
        (np.arange(16.0), None, {}, "no degrees of freedom"),
        (np.arange(16.0), None, {"pool": 15}, "pool must be in"),
        (np.arange(16.0), None, {"pool": "most"}, "pool must be"),
        (np.arange(16.0), None, {"pool": True}, "pool must be"),
        (np.ones((16, 2)), None, {"pool": 3}, "pure error"),
    ],
)
def test_anova_rejects_bad_input(paper, y, terms, kwargs, message):
    with pytest.raises(ValueError, match=message):
        anova(paper, y, terms, **kwargs)


def test_effects_accept_a_bare_matrix(paper):
    y = np.random.default_rng(15).normal(0, 1, 16)
    assert effects(paper.matrix, y) == pytest.approx(effects(paper, y))
    with pytest.raises(ValueError, match="-1 and \\+1"):
        effects(paper.matrix * 2, y)


def test_terms_accept_paper_numbers(paper):
    y = np.random.default_rng(16).normal(0, 1, 16)
    assert list(effects(paper, y, ["3", "34"])) == ["C", "CD"]


@pytest.mark.parametrize("level", [0.0, 1.0, 95, -0.5])
def test_significance_level_must_be_a_probability(paper, level):
    table = anova(paper, np.random.default_rng(17).normal(0, 1, 16), pool=5)
    with pytest.raises(ValueError, match="level"):
        table.significant(level)


def test_all_terms_are_estimable_in_every_two_level_full_factorial():
    # Every word of a 2^4 is estimable and orthogonal to every other one.
    design = fractional_factorial(4, {})
    words = ["".join(w) for r in range(1, 5) for w in itertools.combinations("ABCD", r)]
    y = np.random.default_rng(18).normal(0, 1, 16)
    assert len(effects(design, y, words)) == 15


def test_auto_pooling_says_why_it_found_nothing_to_pool(paper):
    # one exact effect (CORR_SIZE low -> 1) and fourteen exactly 0: Lenth's scale is 0, so
    # pool='auto' pools nothing; the error must say so, not advise pool='auto' again
    y = np.where(paper.matrix[:, 3] < 0, 1.0, 0.0)
    with pytest.raises(ValueError, match="pool='auto' found no inactive effects") as err:
        anova(paper, y, pool="auto")
    assert "(pool=K or 'auto')" not in str(err.value)
    # pooling the 14 zeros by count still tests the one effect, exactly
    table = anova(paper, y, pool=14)
    assert [r.term for r in table.rows] == ["D"] and table.rows[0].effect == -1.0
