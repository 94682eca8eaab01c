"""Effects, Lenth's method and ANOVA for two-level factorial designs (paper Section 6.1, Table 3).

The paper's 2^(5-1) design has 16 unreplicated runs, so its 5 main effects and 10 two-factor
interactions use all 15 degrees of freedom and leave none for error. Two ways out are offered:

* :func:`lenth` -- Lenth's pseudo standard error (Lenth 1989, *Technometrics* 31(4):469-473),
  which estimates the effects' standard error from the smallest effects (effect sparsity);
* :func:`anova` -- the classical ANOVA with the smallest effects pooled into error (or, when
  every run is replicated, tested against pure error).

Both report significance at 95 % and 99 %; :func:`table3` turns them into the paper's Table 3.

For a two-level design with orthogonal columns, the effect of a term is
mean(y at +1) - mean(y at -1) = 2 * (least-squares coefficient), and its sum of squares is
SS = N * effect^2 / 4 with N the number of observations.

Pure numpy + scipy.stats: no Zenoh, no msgpack.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Protocol, TypeAlias

import numpy as np
from scipy import stats

from vistrack.services.auto_tuner.design import LETTERS, Design, number_label

DesignLike: TypeAlias = Design | np.ndarray


# ----------------------------------------------------------------------------- effects


def effects(
    design: DesignLike, y: np.ndarray | Sequence[float], terms: Sequence[str] | None = None
) -> dict[str, float]:
    """Effect of every term: mean(y at +1) - mean(y at -1) = 2 * least-squares coefficient.

    Parameters
    ----------
    design : Design or numpy.ndarray
        The design, or its (runs, k) matrix of -1/+1 with columns lettered A, B, ...
    y : array_like
        Responses, shape (runs,), or (runs, reps) when every run was replicated `reps` times.
    terms : sequence of str, optional
        Effect words (``"A"``, ``"CD"``) or paper numbers (``"34"``). Default: every main
        effect and two-factor interaction. Terms must not be aliased with each other.

    Returns
    -------
    dict
        Canonical term word -> effect, in the order of `terms`.
    """
    d = _as_design(design)
    responses = _responses(y, d.n_runs)
    labels = _term_labels(d, terms)
    x = _model_matrix(d, labels)
    run_means = responses.mean(axis=1)  # every run has the same number of replicates
    return {
        label: float(run_means[x[:, j] > 0].mean() - run_means[x[:, j] < 0].mean())
        for j, label in enumerate(labels)
    }


def sums_of_squares(
    design: DesignLike, y: np.ndarray | Sequence[float], terms: Sequence[str] | None = None
) -> dict[str, float]:
    """Sum of squares of every term, SS = N * effect^2 / 4 (N = number of observations).

    Parameters are those of :func:`effects`; each SS has one degree of freedom.
    """
    n_obs = _responses(y, _as_design(design).n_runs).size
    return {t: n_obs * e**2 / 4.0 for t, e in effects(design, y, terms).items()}


# ----------------------------------------------------------------------------- Lenth


@dataclass(frozen=True, eq=False)
class LenthResult:
    """Lenth's (1989) analysis of the effects of an unreplicated two-level design.

    Attributes
    ----------
    terms : tuple of str
        Effect labels, in input order.
    effects : numpy.ndarray
        The effects (contrasts) c_j, shape (m,).
    s0 : float
        Initial scale, 1.5 * median |c_j|.
    pse : float
        Pseudo standard error, 1.5 * median{|c_j| : |c_j| < 2.5 * s0}.
    df : float
        Degrees of freedom of the reference t distribution, d = m / 3.
    me : float
        Margin of error at 95 %: t_{0.975, d} * PSE.
    sme : float
        Simultaneous margin of error at 95 %: t_{gamma, d} * PSE, gamma = (1 + 0.95^(1/m)) / 2.
    t : numpy.ndarray
        Lenth t statistics c_j / PSE.
    p : numpy.ndarray
        Two-sided p-values of the t statistics on d degrees of freedom.
    """

    terms: tuple[str, ...]
    effects: np.ndarray
    s0: float
    pse: float
    df: float
    me: float
    sme: float
    t: np.ndarray
    p: np.ndarray

    def margin_of_error(self, level: float = 0.95) -> float:
        """Individual margin of error t_{(1+level)/2, d} * PSE."""
        _check_level(level)
        return float(stats.t.ppf((1.0 + level) / 2.0, self.df) * self.pse)

    def simultaneous_margin_of_error(self, level: float = 0.95) -> float:
        """Simultaneous margin of error t_{gamma, d} * PSE, gamma = (1 + level^(1/m)) / 2."""
        _check_level(level)
        gamma = (1.0 + level ** (1.0 / len(self.terms))) / 2.0
        return float(stats.t.ppf(gamma, self.df) * self.pse)

    def significant(self, level: float = 0.95, *, simultaneous: bool = False) -> list[str]:
        """Terms significant at `level` (e.g. 0.95 or 0.99), in input order.

        Individually: p < 1 - level, i.e. |c_j| > margin of error. With ``simultaneous=True``:
        |c_j| > simultaneous margin of error, which controls the error rate over all m terms.
        """
        if simultaneous:
            bound = self.simultaneous_margin_of_error(level)
            return [t for t, c in zip(self.terms, self.effects, strict=True) if abs(c) > bound]
        _check_level(level)
        return [t for t, p in zip(self.terms, self.p, strict=True) if p < 1.0 - level]


def lenth(effects: Mapping[str, float] | Sequence[float] | np.ndarray) -> LenthResult:
    """Lenth's pseudo standard error, margins of error and t tests for unreplicated effects.

    Parameters
    ----------
    effects : Mapping or sequence of float
        Term -> effect (as returned by :func:`effects`), or bare effects labelled "0", "1", ...
        At least 3 effects; they should be independent with equal variance (orthogonal
        contrasts of a two-level design).

    Returns
    -------
    LenthResult

    Notes
    -----
    s0 = 1.5 median|c|; PSE = 1.5 median{|c| : |c| < 2.5 s0}; d = m/3;
    ME = t_{0.975,d} PSE; SME = t_{gamma,d} PSE with gamma = (1 + 0.95^(1/m)) / 2.
    (Lenth, R. V. (1989). Quick and easy analysis of unreplicated factorials. Technometrics
    31(4), 469-473.)
    """
    if isinstance(effects, Mapping):
        terms = tuple(str(t) for t in effects)
        values = np.asarray(list(effects.values()), dtype=float)
    else:
        values = np.asarray(effects, dtype=float)
        terms = tuple(str(i) for i in range(values.size))
    if values.ndim != 1 or values.size < 3:
        raise ValueError(f"Lenth's method needs at least 3 effects, got shape {values.shape}")
    if not np.all(np.isfinite(values)):
        raise ValueError("effects must be finite")
    m = values.size
    abs_c = np.abs(values)
    s0 = 1.5 * float(np.median(abs_c))
    if s0 == 0.0:
        raise ValueError(
            "Lenth's PSE is zero: at least half of the effects are exactly 0, so there is no "
            "scale to test against"
        )
    # Trimming at 2.5 s0 drops the effects that look active before taking the median again.
    pse = 1.5 * float(np.median(abs_c[abs_c < 2.5 * s0]))
    df = m / 3.0
    t_stat = values / pse
    p = 2.0 * stats.t.sf(np.abs(t_stat), df)
    gamma = (1.0 + 0.95 ** (1.0 / m)) / 2.0
    for array in (values, t_stat, p):
        array.setflags(write=False)
    return LenthResult(
        terms=terms,
        effects=values,
        s0=s0,
        pse=pse,
        df=df,
        me=float(stats.t.ppf(0.975, df) * pse),
        sme=float(stats.t.ppf(gamma, df) * pse),
        t=t_stat,
        p=p,
    )


# ----------------------------------------------------------------------------- ANOVA


@dataclass(frozen=True)
class AnovaRow:
    """One line of an ANOVA table. F and p are NaN for the error line."""

    term: str
    df: int
    ss: float
    ms: float
    F: float
    p: float
    effect: float | None = None


@dataclass(frozen=True)
class AnovaTable:
    """ANOVA of a two-level design.

    Attributes
    ----------
    rows : tuple of AnovaRow
        The tested terms (pooled terms excluded), in the order they were given.
    model : AnovaRow
        All tested terms together.
    error : AnovaRow
        The error line: pure error for replicated runs; otherwise the pooled terms plus any
        variation the terms leave unexplained (effects not in the model).
    lack_of_fit : AnovaRow or None
        Replicated runs only: variation between run means that the terms leave unexplained,
        tested against pure error. None when the model is saturated or runs are unreplicated.
    pooled : tuple of str
        Terms pooled into error.
    total_ss, total_df :
        Corrected total sum of squares and its degrees of freedom (N - 1).
    """

    rows: tuple[AnovaRow, ...]
    model: AnovaRow
    error: AnovaRow
    lack_of_fit: AnovaRow | None
    pooled: tuple[str, ...]
    total_ss: float
    total_df: int

    @property
    def r_squared(self) -> float:
        """Share of the total sum of squares explained by the tested terms."""
        return self.model.ss / self.total_ss if self.total_ss > 0 else float("nan")

    @property
    def root_mse(self) -> float:
        """Square root of the error mean square: the estimated standard deviation of y."""
        return float(np.sqrt(self.error.ms))

    def row(self, term: str) -> AnovaRow:
        """The row of a tested term (canonical word, e.g. ``"CD"``)."""
        for r in self.rows:
            if r.term == term:
                return r
        raise KeyError(f"{term!r} is not a tested term (pooled: {self.pooled})")

    def significant(self, level: float = 0.95) -> list[str]:
        """Tested terms whose F test has p < 1 - level (level 0.95 or 0.99 for Table 3)."""
        _check_level(level)
        return [r.term for r in self.rows if r.p < 1.0 - level]


def anova(
    design: DesignLike,
    y: np.ndarray | Sequence[float],
    terms: Sequence[str] | None = None,
    *,
    pool: int | str | None = None,
) -> AnovaTable:
    """ANOVA table with F tests of main effects and interactions.

    Parameters
    ----------
    design : Design or numpy.ndarray
        The design, or its (runs, k) matrix of -1/+1 with columns lettered A, B, ...
    y : array_like
        Responses, shape (runs,) for an unreplicated design, or (runs, reps) with reps >= 2
        when every run was replicated; then the error is pure error (within-run variation).
    terms : sequence of str, optional
        Terms of the model (default: all main effects and two-factor interactions). Effects
        of the design not named here (e.g. three-factor interactions of a full 2^5) go to
        error in unreplicated designs and to lack of fit in replicated ones.
    pool : int, "auto" or None
        Unreplicated designs only. K: pool the K terms with the smallest sums of squares into
        error. "auto": pool the terms Lenth's method treats as inactive,
        |effect| < 2.5 * 1.5 * median|effect| (the set its PSE is computed from). None: no
        pooling. Pooling chosen from the data makes the error too small, so the F tests are
        optimistic; prefer :func:`lenth` for screening and read pooled ANOVA as a check.

    Returns
    -------
    AnovaTable

    Raises
    ------
    ValueError
        On a y/design size mismatch, aliased terms, a bad `pool`, or when no degrees of
        freedom are left for error (16 runs and 15 terms without pooling).
    """
    d = _as_design(design)
    responses = _responses(y, d.n_runs)
    labels = _term_labels(d, terms)
    eff = np.array(list(effects(d, responses, labels).values()))
    n_runs, reps = responses.shape
    n_obs = responses.size
    ss = n_obs * eff**2 / 4.0
    total_ss = float(((responses - responses.mean()) ** 2).sum())
    unexplained_df = n_runs - 1 - len(labels)
    # A saturated model leaves nothing unexplained; clip rounding noise the same way.
    unexplained_ss = max(total_ss - float(ss.sum()), 0.0) if unexplained_df > 0 else 0.0

    lack_of_fit: AnovaRow | None = None
    if reps > 1:
        if pool not in (None, 0):
            raise ValueError(
                "runs are replicated, so the error is pure error; pooling effects does not apply"
            )
        pooled: list[int] = []
        error_ss = float(((responses - responses.mean(axis=1, keepdims=True)) ** 2).sum())
        error_df = n_runs * (reps - 1)
        lof_ss = max(unexplained_ss - error_ss, 0.0) if unexplained_df > 0 else 0.0
    else:
        pooled = _pooled_indices(eff, ss, pool)
        error_ss = unexplained_ss + float(ss[pooled].sum())
        error_df = unexplained_df + len(pooled)
    if error_df == 0 and pool == "auto":
        raise ValueError(
            "pool='auto' found no inactive effects to pool: half or more of the "
            f"{len(labels)} effects are exactly 0, so Lenth's scale is 0 and there is no error "
            "to test against; replicate runs, or pool=K to pool the K smallest"
        )
    if error_df == 0:
        raise ValueError(
            f"no degrees of freedom left for error: {n_runs} runs, {len(labels)} terms; "
            "pool the smallest effects (pool=K or 'auto'), drop terms, replicate runs, or use "
            "lenth()"
        )
    ms_error = error_ss / error_df

    tested = [j for j in range(len(labels)) if j not in pooled]
    rows = tuple(
        _row(labels[j], 1, float(ss[j]), ms_error, error_df, float(eff[j])) for j in tested
    )
    model = _row("model", len(tested), float(ss[tested].sum()), ms_error, error_df)
    if reps > 1 and unexplained_df > 0:
        lack_of_fit = _row("lack of fit", unexplained_df, lof_ss, ms_error, error_df)
    nan = float("nan")
    error = AnovaRow("error", error_df, error_ss, ms_error, nan, nan)
    return AnovaTable(
        rows=rows,
        model=model,
        error=error,
        lack_of_fit=lack_of_fit,
        pooled=tuple(labels[j] for j in pooled),
        total_ss=total_ss,
        total_df=n_obs - 1,
    )


def _row(
    term: str, df: int, ss: float, ms_error: float, error_df: int, effect: float | None = None
) -> AnovaRow:
    ms = ss / df if df else float("nan")
    with np.errstate(divide="ignore", invalid="ignore"):
        # A perfect fit (ms_error = 0) gives F = inf and p = 0 rather than an exception.
        f_value = float(np.divide(ms, ms_error))
    p = float(stats.f.sf(f_value, df, error_df)) if df else float("nan")
    return AnovaRow(term, df, ss, ms, f_value, p, effect)


def _pooled_indices(eff: np.ndarray, ss: np.ndarray, pool: int | str | None) -> list[int]:
    if pool is None:
        return []
    if pool == "auto":
        s0 = 1.5 * float(np.median(np.abs(eff)))
        return [j for j in range(eff.size) if abs(eff[j]) < 2.5 * s0]
    if isinstance(pool, int | np.integer) and not isinstance(pool, bool):
        if not 0 <= pool < eff.size:
            raise ValueError(f"pool must be in 0..{eff.size - 1} (terms to keep >= 1), got {pool}")
        # Stable sort: ties are pooled in term order, so the result is reproducible.
        return sorted(np.argsort(ss, kind="stable")[: int(pool)].tolist())
    raise ValueError(f"pool must be None, a non-negative int or 'auto', got {pool!r}")


# ----------------------------------------------------------------------------- Table 3


class SupportsSignificance(Protocol):
    """Anything with ``significant(level) -> list of terms``: AnovaTable, LenthResult."""

    def significant(self, level: float = ...) -> list[str]: ...


def table3(
    results_by_response: Mapping[str, SupportsSignificance],
) -> dict[str, dict[str, list[str]]]:
    """Table 3 of the paper: terms significant at 99 %, and at 95 % but not 99 %.

    Parameters
    ----------
    results_by_response : Mapping
        Response name (``"t1"``, ``"tf"``, ``"ex"``, ``"ey"``) -> AnovaTable or LenthResult
        whose terms are factor-letter words.

    Returns
    -------
    dict
        Response -> ``{"99": [...], "95": [...]}`` with terms in the paper's number notation,
        main effects first (``{"99": ["1", "2"], "95": ["12", "13", "23", "34"]}``).
    """
    table: dict[str, dict[str, list[str]]] = {}
    for response, result in results_by_response.items():
        at_99 = set(result.significant(0.99))
        at_95 = set(result.significant(0.95)) - at_99
        table[response] = {"99": _paper_order(at_99), "95": _paper_order(at_95)}
    return table


def _paper_order(terms: set[str]) -> list[str]:
    labels = [number_label(t) for t in terms]
    return sorted(labels, key=lambda label: (len(label), label))


# ----------------------------------------------------------------------------- helpers


def _as_design(design: DesignLike) -> Design:
    if isinstance(design, Design):
        return design
    matrix: np.ndarray = np.asarray(design)
    if matrix.ndim != 2:
        raise ValueError(f"design must be a Design or a 2-D -1/+1 matrix, got shape {matrix.shape}")
    if matrix.shape[1] > len(LETTERS):
        raise ValueError(f"at most {len(LETTERS)} factors, got {matrix.shape[1]}")
    return Design(matrix, tuple(LETTERS[: matrix.shape[1]]))


def _responses(y: np.ndarray | Sequence[float], n_runs: int) -> np.ndarray:
    """y as a float array of shape (runs, reps)."""
    values = np.asarray(y, dtype=float)
    if values.ndim == 1:
        values = values[:, np.newaxis]
    if values.ndim != 2 or values.shape[1] < 1:
        raise ValueError(f"y must have shape (runs,) or (runs, reps), got {values.shape}")
    if values.shape[0] != n_runs:
        raise ValueError(f"y has {values.shape[0]} runs but the design has {n_runs} runs")
    if not np.all(np.isfinite(values)):
        raise ValueError("y must be finite (no NaN or inf)")
    return values


def _term_labels(design: Design, terms: Sequence[str] | None) -> list[str]:
    if terms is None:
        return design.terms(min(2, design.k))
    if isinstance(terms, str):
        terms = [terms]
    labels = [design.term(t) for t in terms]
    if not labels:
        raise ValueError("terms must name at least one effect")
    seen: set[str] = set()
    for label in labels:
        if label in seen:
            raise ValueError(f"term {label} is given twice")
        seen.add(label)
    return labels


def _model_matrix(design: Design, labels: list[str]) -> np.ndarray:
    """Columns of the terms, after checking that each effect is separately estimable."""
    x = design.columns(labels)
    n = design.n_runs
    for j, label in enumerate(labels):
        if x[:, j].sum() != 0:
            what = (
                "is in the defining relation (aliased with the mean)"
                if abs(x[:, j].sum()) == n
                else "is not balanced between -1 and +1"
            )
            raise ValueError(f"term {label} {what}; its effect cannot be estimated")
    gram = x.T @ x
    for i in range(len(labels)):
        for j in range(i + 1, len(labels)):
            if gram[i, j] != 0:
                what = "are aliased" if abs(gram[i, j]) == n else "are not orthogonal"
                raise ValueError(
                    f"terms {labels[i]} and {labels[j]} {what} in this design; keep one of them"
                )
    return x


def _check_level(level: float) -> None:
    if not isinstance(level, float | int) or not 0.0 < level < 1.0:
        raise ValueError(f"level is a confidence level in (0, 1) such as 0.95, got {level!r}")
