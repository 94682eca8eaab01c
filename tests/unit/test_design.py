"""Factorial designs: the paper's 2^(5-1) against the textbook construction, and general designs.

Reference constructions are built here independently of the module (itertools products and
explicit column products), so a wrong generator, sign or run order shows up as a difference.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from vistrack.services.auto_tuner.design import (
    PAPER_FACTORS,
    Design,
    fractional_factorial,
    full_factorial,
    letter_term,
    number_label,
    paper_design,
)

FIVE = "ABCDE"
MAINS_AND_2FI = [*FIVE, *("".join(c) for c in itertools.combinations(FIVE, 2))]


def product_column(matrix: np.ndarray, word: str, letters: str = FIVE) -> np.ndarray:
    """The interaction column of `word`, computed from the factor columns."""
    return np.prod(matrix[:, [letters.index(c) for c in word]], axis=1)


def textbook_half_fraction(sign: int = 1) -> set[tuple[int, ...]]:
    """The principal fraction I = +ABCDE: the runs of the 2^5 with A*B*C*D*E = +1
    (Montgomery, Design and Analysis of Experiments, Section 8.2). sign=-1: I = -ABCDE."""
    return {run for run in itertools.product((-1, 1), repeat=5) if np.prod(run) == sign}


@pytest.fixture(scope="module")
def half() -> Design:
    return fractional_factorial(5, {"E": "ABCD"})


# ----------------------------------------------------------------------------- 2^(5-1)


def test_half_fraction_has_16_distinct_balanced_runs(half):
    assert half.matrix.shape == (16, 5)
    assert len({tuple(r) for r in half.matrix}) == 16
    assert np.all(half.matrix.sum(axis=0) == 0)


def test_main_effect_and_2fi_columns_are_orthogonal(half):
    x = np.stack([product_column(half.matrix, w) for w in MAINS_AND_2FI], axis=1)
    np.testing.assert_array_equal(x.T @ x, 16 * np.eye(15))
    np.testing.assert_array_equal(half.columns(MAINS_AND_2FI), x)


def test_e_column_is_the_product_abcd(half):
    np.testing.assert_array_equal(half.matrix[:, 4], product_column(half.matrix, "ABCD"))


def test_same_runs_as_the_textbook_half_fraction(half):
    assert {tuple(int(v) for v in r) for r in half.matrix} == textbook_half_fraction()


def test_base_factors_are_in_yates_order(half):
    # Standard order: factor j alternates in blocks of 2^j runs, A fastest.
    expected = np.array([[1 if (run >> j) & 1 else -1 for j in range(4)] for run in range(16)])
    np.testing.assert_array_equal(half.matrix[:, :4], expected)


def test_defining_relation_and_resolution_five(half):
    assert half.defining_relation == ["ABCDE"]
    assert half.resolution == 5
    # Independently: ABCDE is the only word whose column is +1 in every run.
    constant = [
        "".join(w)
        for r in range(1, 6)
        for w in itertools.combinations(FIVE, r)
        if np.all(product_column(half.matrix, "".join(w)) == 1)
    ]
    assert constant == ["ABCDE"]


def test_main_effects_alias_four_factor_and_2fi_alias_three_factor_interactions(half):
    chains = half.aliases(max_order=2)
    assert sorted(chains) == sorted(MAINS_AND_2FI)
    for term, aliases in chains.items():
        complement = "".join(c for c in FIVE if c not in term)
        assert aliases == [complement]
        assert len(aliases[0]) == 5 - len(term)
        # Aliased effects share a column.
        np.testing.assert_array_equal(
            product_column(half.matrix, term), product_column(half.matrix, complement)
        )


def test_negative_generator_gives_the_other_half():
    other = fractional_factorial(5, {"E": "-ABCD"})
    assert {tuple(int(v) for v in r) for r in other.matrix} == textbook_half_fraction(-1)
    assert other.defining_relation == ["-ABCDE"]
    assert other.aliases(1)["A"] == ["-BCDE"]


@pytest.mark.parametrize(
    "generators",
    [{"E": "ABCD"}, ["E=ABCD"], ["ABCD"], "E=ABCD", {"E": " ABCD "}],
    ids=["mapping", "explicit", "bare", "single-string", "spaces"],
)
def test_generator_spellings_build_the_same_design(half, generators):
    np.testing.assert_array_equal(fractional_factorial(5, generators).matrix, half.matrix)


# ----------------------------------------------------------------------------- other fractions


def test_quarter_fraction_2_6_2_defining_relation_includes_the_product_of_generators():
    # Montgomery, DAE, Table 8.14: 2^(6-2)_IV with E = ABC, F = BCD: I = ABCE = BCDF = ADEF.
    d = fractional_factorial(6, {"E": "ABC", "F": "BCD"})
    assert d.matrix.shape == (16, 6)
    assert set(d.defining_relation) == {"ABCE", "BCDF", "ADEF"}
    assert d.resolution == 4
    letters = "ABCDEF"
    constant = {
        "".join(w)
        for r in range(1, 7)
        for w in itertools.combinations(letters, r)
        if np.all(product_column(d.matrix, "".join(w), letters) == 1)
    }
    assert constant == {"ABCE", "BCDF", "ADEF"}
    # Resolution IV: 2FIs alias other 2FIs (AB = CE), main effects do not alias each other.
    assert "CE" in d.aliases()["AB"]


def test_saturated_2_7_4_is_resolution_three():
    d = fractional_factorial(7, {"D": "AB", "E": "AC", "F": "BC", "G": "ABC"})
    assert d.matrix.shape == (8, 7)
    assert len(d.defining_relation) == 2**4 - 1
    assert d.resolution == 3
    assert "BD" in d.aliases()["A"]  # D = AB, so A = BD


def test_full_two_level_factorial_has_no_aliases():
    d = fractional_factorial(3, {})
    assert d.matrix.shape == (8, 3)
    assert d.defining_relation == []
    assert d.resolution is None
    assert all(chain == [] for chain in d.aliases(3).values())


# ----------------------------------------------------------------------------- bad generators


@pytest.mark.parametrize(
    ("k", "generators", "message"),
    [
        (5, {"E": "ABCX"}, "unknown factor"),
        (5, {"F": "ABCD"}, "not one of the factors"),
        (5, {"E": "ABCE"}, "uses generated factor"),
        (6, {"E": "ABC", "F": "ABE"}, "uses generated factor"),
        (5, {"E": "A"}, "at least two base factors"),
        (5, {"E": ""}, "empty"),
        (5, {"E": "ABBC"}, "repeats"),
        (5, ["E=ABCD", "ABC"], "either all"),
        (5, {"E": 3}, "must be a string"),
        (2, {"A": "AB", "B": "AB"}, "generated factor|base factor"),
    ],
)
def test_bad_generators_raise_value_error(k, generators, message):
    with pytest.raises(ValueError, match=message):
        fractional_factorial(k, generators)


@pytest.mark.parametrize("k", [0, 26, 2.0, True])
def test_bad_number_of_factors_raises(k):
    with pytest.raises(ValueError, match="k must be"):
        fractional_factorial(k, {})


def test_design_rejects_a_matrix_that_is_not_two_level():
    with pytest.raises(ValueError, match="-1 and \\+1"):
        Design(np.array([[0, 1], [1, -1]]), ("A", "B"))


def test_design_rejects_a_column_that_breaks_its_generator(half):
    broken = half.matrix.copy()
    broken[0, 4] *= -1
    with pytest.raises(ValueError, match="does not follow its generator"):
        Design(broken, half.factors, {"E": "ABCD"})


def test_design_matrix_is_read_only(half):
    with pytest.raises(ValueError):
        half.matrix[0, 0] = 1


# ----------------------------------------------------------------------------- full factorial


def test_full_3_to_the_4_has_81_distinct_runs():
    # The paper's Section 2 example: four parameters, three levels: 3^4 = 81 runs.
    x = full_factorial(3, 4)
    assert x.shape == (81, 4)
    assert len({tuple(r) for r in x}) == 81
    assert set(np.unique(x)) == {-1.0, 0.0, 1.0}
    index = full_factorial(3, 4, coding="index")
    assert index.dtype.kind == "i"
    assert {tuple(r) for r in index} == set(itertools.product(range(3), repeat=4))


def test_mixed_level_factorial_is_every_combination_first_factor_fastest():
    x = full_factorial([2, 3, 4], coding="index")
    assert x.shape == (24, 3)
    expected = [tuple(reversed(r)) for r in itertools.product(range(4), range(3), range(2))]
    assert [tuple(r) for r in x] == expected
    centred = full_factorial([2, 3, 4])
    np.testing.assert_allclose(np.unique(centred[:, 2]), [-1, -1 / 3, 1 / 3, 1])


def test_two_level_full_factorial_matches_fractional_factorial_with_no_generators():
    np.testing.assert_array_equal(full_factorial(2, 4), fractional_factorial(4, {}).matrix)


@pytest.mark.parametrize(
    ("levels", "n_factors", "message"),
    [
        (1, 3, "levels >= 2"),
        (3, None, "n_factors"),
        ([2, 3], 3, "n_factors=3"),
        ([], None, "at least one"),
        ([2, 2.5], None, "levels >= 2"),
        (10, 10, "exceeds"),
    ],
)
def test_full_factorial_rejects_bad_levels(levels, n_factors, message):
    with pytest.raises(ValueError, match=message):
        full_factorial(levels, n_factors)


def test_full_factorial_rejects_unknown_coding():
    with pytest.raises(ValueError, match="coding"):
        full_factorial(2, 2, coding="orthogonal")


# ----------------------------------------------------------------------------- run order


@pytest.mark.parametrize("seed", [0, 1, 12345])
def test_randomized_order_is_a_reproducible_permutation(half, seed):
    order = half.randomized_order(seed)
    assert sorted(order.tolist()) == list(range(16))
    np.testing.assert_array_equal(order, half.randomized_order(seed))
    np.testing.assert_array_equal(order, np.random.default_rng(seed).permutation(16))


def test_randomized_order_differs_between_seeds(half):
    assert not np.array_equal(half.randomized_order(0), half.randomized_order(1))


# ----------------------------------------------------------------------------- paper design


def test_paper_design_is_the_half_fraction_with_table_2_levels(half):
    d = paper_design()
    np.testing.assert_array_equal(d.matrix, half.matrix)
    assert dict(d.generators) == {"E": "ABCD"}
    assert (
        d.names
        == PAPER_FACTORS
        == (
            "max_features",
            "thres_percent",
            "search_size",
            "corr_size",
            "ungroup_size",
        )
    )
    values = d.with_levels()
    table_2 = [(50, 200), (0.1, 5.0), (10, 30), (5, 15), (5, 20)]
    for j, (low, high) in enumerate(table_2):
        np.testing.assert_allclose(values[:, j], np.where(d.matrix[:, j] < 0, low, high))


def test_with_levels_accepts_letters_or_names_and_interpolates(half):
    by_letter = half.with_levels({f: (0.0, 10.0) for f in FIVE})
    np.testing.assert_allclose(by_letter, (half.matrix + 1) * 5.0)
    named = paper_design().with_levels(
        {"max_features": (1, 3), "B": (0, 1), "C": (0, 1), "D": (0, 1), "ungroup_size": (2, 4)}
    )
    np.testing.assert_allclose(named[:, 0], np.where(half.matrix[:, 0] < 0, 1, 3))
    np.testing.assert_allclose(named[:, 4], np.where(half.matrix[:, 4] < 0, 2, 4))


@pytest.mark.parametrize(
    ("low_high", "message"),
    [
        ({"A": (0, 1)}, "no levels for factor"),
        ({**{f: (0, 1) for f in FIVE}, "Z": (0, 1)}, "unknown factor"),
        ({**{f: (0, 1) for f in FIVE}, "A": (1, 1)}, "differ"),
        ({**{f: (0, 1) for f in FIVE}, "A": (0,)}, "low, high"),
    ],
)
def test_with_levels_rejects_bad_levels(half, low_high, message):
    with pytest.raises(ValueError, match=message):
        half.with_levels(low_high)


def test_with_levels_without_levels_needs_a_mapping(half):
    with pytest.raises(ValueError, match="no levels"):
        half.with_levels()


# ----------------------------------------------------------------------------- term labels


@pytest.mark.parametrize(
    ("term", "label"),
    [("A", "1"), ("E", "5"), ("AB", "12"), ("CD", "34"), ("DE", "45"), ("DC", "34")],
)
def test_number_labels_follow_the_papers_table_3(term, label):
    assert number_label(term) == label
    assert letter_term(label) == "".join(sorted(term))


def test_number_labels_round_trip_every_effect(half):
    for term in half.terms(5):
        assert letter_term(number_label(term)) == term


def test_columns_accept_paper_numbers(half):
    np.testing.assert_array_equal(half.columns(["34", "1"]), half.columns(["CD", "A"]))


@pytest.mark.parametrize("bad", ["", "AA", "AX", "ABCDEFGHJK", 3])
def test_number_label_rejects_bad_terms(bad):
    with pytest.raises(ValueError):
        number_label(bad)


@pytest.mark.parametrize("bad", ["", "0", "33", "3a", "A"])
def test_letter_term_rejects_bad_labels(bad):
    with pytest.raises(ValueError):
        letter_term(bad)


@pytest.mark.parametrize(
    ("term", "message"), [("AF", "unknown factor"), ("AA", "repeats"), ("", "non-empty")]
)
def test_columns_reject_bad_terms(half, term, message):
    with pytest.raises(ValueError, match=message):
        half.columns([term])


def test_terms_lists_mains_then_interactions(half):
    assert half.terms(2) == MAINS_AND_2FI
    assert len(half.terms(5)) == 31
    with pytest.raises(ValueError, match="max_order"):
        half.terms(6)
