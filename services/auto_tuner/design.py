"""Factorial designs: the general full factorial and regular two-level fractional factorials.

The paper (Section 2) counts a general full factorial as N = L^V runs, or l1 x l2 x ... x ln
for mixed levels, and (Section 6.1) screens its five tracker parameters with an unreplicated
2^(5-1) fractional factorial in random run order. We build that design from the generator
E = ABCD, so its defining relation is I = ABCDE and its resolution is V: every main effect is
aliased only with a four-factor interaction and every two-factor interaction with a
three-factor one. The paper does not name its generator; ABCD is the only one that gives a
resolution V half fraction of five factors.

Conventions
-----------
* Factors are letters A, B, C, ... in column order. The letter I is skipped because it denotes
  the identity in a defining relation (as in Montgomery, *Design and Analysis of Experiments*).
* A *word* such as ``"ABD"`` names the interaction column A*B*D. The paper's Table 3 numbers the
  factors 1..5 instead and writes the SEARCH_SIZE x CORR_SIZE interaction as ``"34"``:
  :func:`number_label` and :func:`letter_term` convert between the two.
* Two-level designs are coded -1 (low) / +1 (high) and listed in standard (Yates) order: the
  first base factor alternates fastest.

Pure numpy: no Zenoh, no msgpack.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from types import MappingProxyType

import numpy as np

from vistrack.common.params import FACTORS as PAPER_FACTORS

#: Factor letters in column order; I is left out (it is the identity of a defining relation).
LETTERS = "ABCDEFGHJKLMNOPQRSTUVWXYZ"

#: The paper's generator for its 2^(5-1) design: E = ABCD, so I = ABCDE (resolution V).
PAPER_GENERATORS: Mapping[str, str] = MappingProxyType({"E": "ABCD"})

#: Table 2 of the paper: (low, high) level of each factor, in PAPER_FACTORS order.
PAPER_LEVELS: Mapping[str, tuple[float, float]] = MappingProxyType(
    {
        "max_features": (50, 200),
        "thres_percent": (0.1, 5.0),
        "search_size": (10, 30),
        "corr_size": (5, 15),
        "ungroup_size": (5, 20),
    }
)

# Guards against a typo such as full_factorial(10, 10) allocating 10^10 rows.
MAX_RUNS = 1 << 20

CODINGS = ("centred", "index")

# A signed word: (+1 or -1, set of factor letters). Multiplying two words is the symmetric
# difference of their letter sets because every coded column squares to the identity.
_Word = tuple[int, frozenset[str]]


def full_factorial(
    levels: Sequence[int] | int, n_factors: int | None = None, *, coding: str = "centred"
) -> np.ndarray:
    """Every combination of factor levels: the l1 x l2 x ... x ln design of Section 2.

    Parameters
    ----------
    levels : int or sequence of int
        Number of levels of every factor (with `n_factors`), or one count per factor.
        Each count must be at least 2.
    n_factors : int, optional
        Number of factors when `levels` is a single count (3 levels, 4 factors: 3^4 = 81 runs).
    coding : {"centred", "index"}
        ``"centred"`` (default) spreads the levels of each factor evenly over [-1, +1]: two
        levels are -1/+1 as in two-level designs, three are -1/0/+1, four are -1, -1/3, 1/3, 1.
        ``"index"`` gives the level numbers 0 .. L-1 as integers.

    Returns
    -------
    numpy.ndarray
        Shape (runs, factors), runs = prod(levels), in standard order: the first factor changes
        fastest. float64 for ``"centred"``, int64 for ``"index"``.
    """
    counts = _level_counts(levels, n_factors)
    if coding not in CODINGS:
        raise ValueError(f"coding must be one of {CODINGS}, got {coding!r}")
    grids = np.meshgrid(*[np.arange(c) for c in counts], indexing="ij")
    # Fortran order makes the first index vary fastest: standard (Yates) order.
    index = np.stack([g.ravel(order="F") for g in grids], axis=1).astype(np.int64)
    if coding == "index":
        return index
    return 2.0 * index / (np.asarray(counts, dtype=float) - 1.0) - 1.0


def _level_counts(levels: Sequence[int] | int, n_factors: int | None) -> list[int]:
    if _is_int(levels):
        if n_factors is None or not _is_int(n_factors) or n_factors < 1:
            raise ValueError(
                f"n_factors must be a positive int when levels is one count, got {n_factors!r}"
            )
        counts = [int(levels)] * int(n_factors)  # type: ignore[arg-type]
    else:
        counts = list(levels)  # type: ignore[arg-type]
        if not counts:
            raise ValueError("levels must name at least one factor")
        if n_factors is not None and n_factors != len(counts):
            raise ValueError(f"n_factors={n_factors} but levels gives {len(counts)} factors")
    for i, c in enumerate(counts):
        if not _is_int(c) or c < 2:
            raise ValueError(f"factor {i} needs an int number of levels >= 2, got {c!r}")
    runs = int(np.prod(counts, dtype=object))
    if runs > MAX_RUNS:
        raise ValueError(f"{' x '.join(map(str, counts))} = {runs} runs exceeds {MAX_RUNS}")
    return [int(c) for c in counts]


def _is_int(value: object) -> bool:
    return isinstance(value, int | np.integer) and not isinstance(value, bool)


@dataclass(frozen=True, eq=False)
class Design:
    """A regular two-level factorial or fractional factorial design.

    Attributes
    ----------
    matrix : numpy.ndarray
        Shape (runs, k), int64 entries -1/+1, read-only; runs in standard (Yates) order.
    factors : tuple of str
        The factor letters, one per column (A, B, C, ...).
    generators : Mapping[str, str]
        Generated factor -> word of base factors, e.g. ``{"E": "ABCD"}`` (``"-ABCD"`` for the
        other half). Empty for a full 2^k factorial.
    names : tuple of str, optional
        A human name per factor (``"search_size"``), used by :meth:`with_levels`.
    levels : tuple of (low, high), optional
        Actual values of the -1 and +1 levels per factor, used by :meth:`with_levels`.
    """

    matrix: np.ndarray
    factors: tuple[str, ...]
    generators: Mapping[str, str] = field(default_factory=dict)
    names: tuple[str, ...] | None = None
    levels: tuple[tuple[float, float], ...] | None = None
    _generator_words: dict[str, _Word] = field(init=False, repr=False, default_factory=dict)

    def __post_init__(self) -> None:
        raw = np.asarray(self.matrix)
        if raw.ndim != 2 or raw.shape[0] < 2 or raw.shape[1] < 1:
            raise ValueError(f"design matrix must be 2-D, runs >= 2, factors >= 1; got {raw.shape}")
        if not np.all((raw == -1) | (raw == 1)):
            raise ValueError("a two-level design matrix must contain only -1 and +1")
        matrix = raw.astype(np.int64)  # a copy: callers cannot change the design under us
        matrix.setflags(write=False)
        object.__setattr__(self, "matrix", matrix)

        factors = tuple(self.factors)
        if factors != tuple(LETTERS[: len(factors)]) or len(factors) != matrix.shape[1]:
            raise ValueError(
                f"factors must be {tuple(LETTERS[: matrix.shape[1]])} for {matrix.shape[1]} "
                f"columns, got {factors}"
            )
        object.__setattr__(self, "factors", factors)

        generators = _parse_generators(dict(self.generators), factors)
        for letter, (sign, word) in generators.items():
            expected = sign * np.prod(matrix[:, [factors.index(f) for f in word]], axis=1)
            if not np.array_equal(matrix[:, factors.index(letter)], expected):
                raise ValueError(f"column {letter} does not follow its generator")
        object.__setattr__(
            self,
            "generators",
            MappingProxyType({k: _format(s, w) for k, (s, w) in generators.items()}),
        )
        object.__setattr__(self, "_generator_words", generators)

        if self.names is not None:
            names = tuple(self.names)
            if len(names) != len(factors) or len(set(names)) != len(names):
                raise ValueError(f"names must be {len(factors)} distinct strings, got {names}")
            for letter, name in zip(factors, names, strict=True):
                # "B" naming factor A would make with_levels({"B": ...}) ambiguous.
                if name in factors and name != letter:
                    raise ValueError(f"name {name!r} of factor {letter} is another factor's letter")
            object.__setattr__(self, "names", names)
        if self.levels is not None:
            object.__setattr__(self, "levels", _check_levels(self.levels, factors))

    @property
    def n_runs(self) -> int:
        """Number of runs (rows)."""
        return int(self.matrix.shape[0])

    @property
    def k(self) -> int:
        """Number of factors (columns)."""
        return int(self.matrix.shape[1])

    @cached_property
    def _relation(self) -> list[_Word]:
        # Each generator E = ABCD gives the word ABCDE (E * E = I); the defining relation is
        # every product of a non-empty subset of those words: 2^p - 1 words for p generators.
        words: list[_Word] = [(s, w | {g}) for g, (s, w) in self._generator_words.items()]
        relation: list[_Word] = []
        for size in range(1, len(words) + 1):
            for subset in itertools.combinations(words, size):
                sign, letters = 1, frozenset[str]()
                for s, w in subset:
                    sign, letters = sign * s, letters ^ w
                relation.append((sign, letters))
        return sorted(relation, key=self._word_key)

    @property
    def defining_relation(self) -> list[str]:
        """The words equal to the identity I, shortest first, e.g. ``["ABCDE"]``.

        A negative word (``"-ABCDE"``) means its column is -1 in every run.
        """
        return [_format(sign, word) for sign, word in self._relation]

    @property
    def resolution(self) -> int | None:
        """Length of the shortest word of the defining relation (5 for I = ABCDE).

        None for a full factorial, whose defining relation is empty: no effect is aliased.
        """
        return min((len(w) for _, w in self._relation), default=None)

    def terms(self, max_order: int = 2) -> list[str]:
        """All effect words up to `max_order` letters: main effects, then 2FIs, ...

        Within an order words are in factor order: A, B, ..., AB, AC, ..., DE.
        """
        if not _is_int(max_order) or not 1 <= max_order <= self.k:
            raise ValueError(f"max_order must be an int in 1..{self.k}, got {max_order!r}")
        return [
            "".join(combo)
            for order in range(1, max_order + 1)
            for combo in itertools.combinations(self.factors, order)
        ]

    def aliases(self, max_order: int = 2) -> dict[str, list[str]]:
        """Alias chains of every effect up to `max_order` letters (main effects and 2FIs).

        Returns
        -------
        dict
            Effect word -> the words it is aliased with (effect times each word of the
            defining relation), shortest first. In the 2^(5-1) with I = ABCDE,
            ``{"A": ["BCDE"], ..., "AB": ["CDE"], ...}``. Empty lists for a full factorial.
        """
        chains: dict[str, list[str]] = {}
        for term in self.terms(max_order):
            effect = frozenset(term)
            products = [(sign, effect ^ word) for sign, word in self._relation]
            chains[term] = [_format(s, w) for s, w in sorted(products, key=self._word_key)]
        return chains

    def term(self, label: str) -> str:
        """Canonical word for a term label: letters in factor order (``"DC"`` -> ``"CD"``).

        Number labels in the paper's notation are accepted too (``"34"`` -> ``"CD"``).
        """
        if not isinstance(label, str) or not label:
            raise ValueError(f"a term is a non-empty string such as 'A' or 'CD', got {label!r}")
        letters = letter_term(label) if label.isdigit() else label
        unknown = [c for c in letters if c not in self.factors]
        if unknown:
            raise ValueError(
                f"term {label!r} names unknown factor(s) {''.join(unknown)}; "
                f"factors are {''.join(self.factors)}"
            )
        if len(set(letters)) != len(letters):
            raise ValueError(f"term {label!r} repeats a factor")
        return "".join(sorted(letters, key=self.factors.index))

    def columns(self, terms: str | Iterable[str]) -> np.ndarray:
        """Model matrix of the given terms: the column of ``"AB"`` is A*B, run by run.

        Parameters
        ----------
        terms : str or iterable of str
            Effect words (``"A"``, ``"CD"``, ``"ABD"``) or paper numbers (``"34"``).

        Returns
        -------
        numpy.ndarray
            Shape (runs, len(terms)), float64 entries -1/+1 (no intercept column).
        """
        labels = [terms] if isinstance(terms, str) else list(terms)
        if not labels:
            raise ValueError("columns needs at least one term")
        idx = [[self.factors.index(c) for c in self.term(t)] for t in labels]
        return np.stack([np.prod(self.matrix[:, i], axis=1) for i in idx], axis=1).astype(float)

    def randomized_order(self, seed: int | None = None) -> np.ndarray:
        """A random run order: a permutation of 0 .. runs-1 from ``numpy.random.default_rng(seed)``.

        The same seed gives the same order, so a recorded experiment can be replayed.
        """
        return np.random.default_rng(seed).permutation(self.n_runs)

    def with_levels(self, low_high: Mapping[str, tuple[float, float]] | None = None) -> np.ndarray:
        """Actual factor values of every run: -1 -> low, +1 -> high.

        Parameters
        ----------
        low_high : Mapping, optional
            Factor (letter or name) -> (low, high) for every factor. Defaults to the levels
            the design was built with (Table 2 for :func:`paper_design`).

        Returns
        -------
        numpy.ndarray
            Shape (runs, k), float64, columns in factor order.
        """
        if low_high is None:
            if self.levels is None:
                raise ValueError("this design has no levels; pass low_high for every factor")
            levels = self.levels
        else:
            levels = self._levels_from_mapping(low_high)
        low, high = np.asarray(levels, dtype=float).T
        return low + (self.matrix + 1) / 2.0 * (high - low)

    def _levels_from_mapping(
        self, low_high: Mapping[str, tuple[float, float]]
    ) -> tuple[tuple[float, float], ...]:
        keys = {f: f for f in self.factors}
        if self.names is not None:
            keys.update(zip(self.names, self.factors, strict=True))
        unknown = sorted(set(low_high) - set(keys))
        if unknown:
            raise ValueError(f"unknown factor(s) {unknown}; use letters or names {sorted(keys)}")
        by_letter = {keys[key]: value for key, value in low_high.items()}
        missing = [f for f in self.factors if f not in by_letter]
        if missing:
            raise ValueError(f"low_high gives no levels for factor(s) {missing}")
        return _check_levels([by_letter[f] for f in self.factors], self.factors)

    def _word_key(self, word: _Word) -> tuple[int, list[int], int]:
        sign, letters = word
        return len(letters), sorted(self.factors.index(c) for c in letters), -sign


def fractional_factorial(
    k: int,
    generators: Mapping[str, str] | Sequence[str],
    *,
    names: Sequence[str] | None = None,
    levels: Sequence[tuple[float, float]] | Mapping[str, tuple[float, float]] | None = None,
) -> Design:
    """A regular two-level 2^(k-p) design built from its p generators.

    Parameters
    ----------
    k : int
        Number of factors, lettered A, B, ... (I skipped).
    generators : Mapping or sequence of str
        ``{"E": "ABCD"}``, or ``["E=ABCD"]``, or bare words ``["ABCD"]`` which generate the
        last p factors in order. A leading ``-`` (``"-ABCD"``) selects the other fraction.
        Words may only use base factors (those not generated). Empty for a full 2^k.
    names : sequence of str, optional
        A name per factor, e.g. the tracker parameter names.
    levels : optional
        (low, high) per factor, as a sequence in factor order or a mapping keyed by letter or
        name; used by :meth:`Design.with_levels`.

    Returns
    -------
    Design
        2^(k-p) runs; the base factors form a full factorial in standard (Yates) order.
    """
    if not _is_int(k) or not 1 <= k <= len(LETTERS):
        raise ValueError(f"k must be an int in 1..{len(LETTERS)}, got {k!r}")
    factors = tuple(LETTERS[:k])
    parsed = _parse_generators(generators, factors)
    base = [f for f in factors if f not in parsed]
    if len(base) > MAX_RUNS.bit_length() - 1:
        raise ValueError(f"2^{len(base)} runs exceeds {MAX_RUNS}")
    base_matrix = full_factorial(2, len(base)).astype(np.int64)
    columns = {f: base_matrix[:, i] for i, f in enumerate(base)}
    for letter, (sign, word) in parsed.items():
        columns[letter] = sign * np.prod(np.stack([columns[f] for f in word], axis=1), axis=1)
    matrix = np.stack([columns[f] for f in factors], axis=1)
    design = Design(
        matrix,
        factors,
        {g: _format(s, w) for g, (s, w) in parsed.items()},
        tuple(names) if names is not None else None,
    )
    if levels is None:
        return design
    if isinstance(levels, Mapping):
        level_tuple = design._levels_from_mapping(levels)
    else:
        level_tuple = _check_levels(levels, factors)
    return Design(design.matrix, factors, design.generators, design.names, level_tuple)


def paper_design() -> Design:
    """The paper's 2^(5-1) design: E = ABCD (I = ABCDE, resolution V), Table 2 levels.

    Factors A..E are MAX_FEAT_NUM (1), THRES_PERCENT (2), SEARCH_SIZE (3), CORR_SIZE (4) and
    UNGROUP_SIZE (5), named as in :mod:`vistrack.common.params`. Runs are in standard order;
    use :meth:`Design.randomized_order` for the order in which to run them.
    """
    return fractional_factorial(
        5,
        PAPER_GENERATORS,
        names=PAPER_FACTORS,
        levels=[PAPER_LEVELS[name] for name in PAPER_FACTORS],
    )


def number_label(term: str) -> str:
    """The paper's number notation for an effect word: ``"CD"`` -> ``"34"``, ``"A"`` -> ``"1"``.

    Digits are factor positions 1..9 in factor order, as in Table 3 of the paper.
    """
    if not isinstance(term, str) or not term:
        raise ValueError(f"a term is a non-empty string of factor letters, got {term!r}")
    if len(set(term)) != len(term) or any(c not in LETTERS[:9] for c in term):
        raise ValueError(
            f"term {term!r} must use distinct factor letters from {LETTERS[:9]} "
            "(number labels exist for at most 9 factors)"
        )
    return "".join(str(LETTERS.index(c) + 1) for c in sorted(term, key=LETTERS.index))


def letter_term(label: str) -> str:
    """The effect word for a paper number label: ``"34"`` -> ``"CD"``, ``"1"`` -> ``"A"``."""
    if not isinstance(label, str) or not label or any(c not in "123456789" for c in label):
        raise ValueError(f"a number label is a string of digits 1..9 such as '34', got {label!r}")
    if len(set(label)) != len(label):
        raise ValueError(f"number label {label!r} repeats a factor")
    return "".join(LETTERS[int(c) - 1] for c in sorted(label))


def _parse_generators(
    generators: Mapping[str, str] | Sequence[str], factors: tuple[str, ...]
) -> dict[str, _Word]:
    """Generated factor -> (sign, set of base letters), validated against `factors`."""
    if isinstance(generators, Mapping):
        pairs = [
            (_check_str(g, "generated factor"), _check_str(w, "generator").replace(" ", ""))
            for g, w in generators.items()
        ]
    else:
        items = [generators] if isinstance(generators, str) else list(generators)
        items = [_check_str(item, "generator").replace(" ", "") for item in items]
        explicit = ["=" in item for item in items]
        if all(explicit):
            pairs = [(item.split("=", 1)[0], item.split("=", 1)[1]) for item in items]
        elif not any(explicit):
            # Bare words generate the last p factors, as in E = ABCD for 2^(5-1).
            pairs = list(zip(factors[len(factors) - len(items) :], items, strict=True))
        else:
            raise ValueError("write either all generators as 'E=ABCD' or all as bare words")
        if len(items) > len(factors):
            raise ValueError(f"{len(items)} generators for only {len(factors)} factors")

    parsed: dict[str, _Word] = {}
    for letter, text in pairs:
        if letter not in factors:
            raise ValueError(
                f"generator {letter}={text} defines {letter!r}, which is not one of the "
                f"factors {''.join(factors)}"
            )
        if letter in parsed:
            raise ValueError(f"factor {letter} has two generators")
        sign = -1 if text.startswith("-") else 1
        word = text.lstrip("+-")
        if not word:
            raise ValueError(f"generator for {letter} is empty")
        unknown = [c for c in word if c not in factors]
        if unknown:
            raise ValueError(
                f"generator {letter}={text} names unknown factor(s) {''.join(unknown)}; "
                f"factors are {''.join(factors)}"
            )
        if len(set(word)) != len(word):
            raise ValueError(f"generator {letter}={text} repeats a factor")
        if len(word) < 2:
            raise ValueError(
                f"generator {letter}={text} needs at least two base factors; one would make "
                f"{letter} a copy of {word}"
            )
        parsed[letter] = (sign, frozenset(word))
    for letter, (_, letters) in parsed.items():
        generated = sorted(letters & parsed.keys())
        if generated:
            raise ValueError(
                f"generator for {letter} uses generated factor(s) {''.join(generated)}; "
                "write every generator in base factors only"
            )
    if len(parsed) >= len(factors):
        raise ValueError("at least one factor must be a base factor (not generated)")
    return parsed


def _check_str(value: object, what: str) -> str:
    if not isinstance(value, str):
        raise ValueError(f"{what} must be a string, got {value!r}")
    return value


def _check_levels(
    levels: Sequence[tuple[float, float]], factors: Sequence[str]
) -> tuple[tuple[float, float], ...]:
    pairs = list(levels)
    if len(pairs) != len(factors):
        raise ValueError(f"need (low, high) for {len(factors)} factors, got {len(pairs)}")
    checked = []
    for factor, pair in zip(factors, pairs, strict=True):
        try:
            low, high = (float(v) for v in pair)
        except (TypeError, ValueError):
            raise ValueError(f"levels of {factor} must be (low, high), got {pair!r}") from None
        if not (np.isfinite(low) and np.isfinite(high)) or low == high:
            raise ValueError(f"levels of {factor} must be finite and differ, got {pair!r}")
        checked.append((low, high))
    return tuple(checked)


def _format(sign: int, word: frozenset[str] | Iterable[str]) -> str:
    letters = "".join(sorted(word, key=LETTERS.index))
    return ("-" if sign < 0 else "") + letters
