"""Plots of a tuning cycle: the design's effects and the sweep's surfaces (Figures 5 to 7).

Everything is drawn from a ``tuner/report`` dict (:meth:`.sensitivity.TuneResult.to_report`),
so a report received over the bus or saved as JSON can be plotted too. Figures are built with
``matplotlib.figure.Figure`` and written with the Agg canvas: no pyplot, no display, no global
backend state.

Files written by :func:`write_plots`:

``halfnormal.png``
    half-normal plot of |effect| per response; the terms significant at 95 % or 99 % labelled
    (in the paper's numbers: 3 = SEARCH_SIZE, 34 = SEARCH_SIZE x CORR_SIZE).
``main_effects.png``
    mean response at each factor's low and high level, one row per response.
``interactions.png``
    SEARCH_SIZE x CORR_SIZE (34) and, per response, its largest other two-factor interaction.
``sweep_t1.png``, ``sweep_tf.png``, ``sweep_ex.png``, ``sweep_ey.png``
    heat maps over SEARCH_SIZE x CORR_SIZE, the optimum marked: Figures 5 to 7 of the paper
    (which shows t1, ex and ey) plus tf, the time the optimum minimises.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from scipy import stats

UNITS = {"t1": "ms", "tf": "ms", "ex": "px", "ey": "px"}
TITLES = {"t1": "t1: first frame", "tf": "tf: following frames", "ex": "ex: X error",
          "ey": "ey: Y error"}


def _save(fig: Figure, path: Path) -> Path:
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=100)
    return path


def _responses(report: Mapping[str, Any]) -> list[str]:
    return [r for r in ("t1", "tf", "ex", "ey") if r in report["effects"]]


def halfnormal(report: Mapping[str, Any], path: str | os.PathLike[str]) -> Path:
    """Half-normal plot of every response's effects, significant terms labelled.

    Sorted |effects| against the half-normal quantiles Phi^-1(0.5 + 0.5 (i - 0.5) / m): inactive
    effects fall on a line through the origin, active ones stand off it.
    """
    names = _responses(report)
    fig = Figure(figsize=(10, 8), layout="constrained")
    axes = fig.subplots(2, 2).ravel()
    for ax, name in zip(axes, names, strict=False):
        eff = report["effects"][name]
        terms = list(eff)
        values = np.abs(np.array([eff[t] for t in terms], float))
        order = np.argsort(values)
        m = len(values)
        q = stats.norm.ppf(0.5 + 0.5 * (np.arange(1, m + 1) - 0.5) / m)
        sig = report["significant"].get(name, {})
        at99, at95 = set(sig.get("99", [])), set(sig.get("95", []))
        colours = ["tab:red" if terms[k] in at99 else "tab:orange" if terms[k] in at95
                   else "tab:blue" for k in order]
        ax.scatter(q, values[order], c=colours, zorder=3)
        for x, k in zip(q, order, strict=True):
            if terms[k] in at99 | at95:
                ax.annotate(terms[k], (x, values[k]), xytext=(4, 2), textcoords="offset points")
        ax.set_title(f"{TITLES[name]} (red 99 %, orange 95 %)")
        ax.set_xlabel("half-normal quantile")
        ax.set_ylabel(f"|effect| ({UNITS[name]})")
        ax.grid(alpha=0.3)
    for ax in axes[len(names):]:
        ax.set_visible(False)
    return _save(fig, Path(path))


def _level_means(report: Mapping[str, Any], name: str, columns: Sequence[int]
                 ) -> dict[tuple[int, ...], float]:
    """Mean response at every combination of levels of the given design columns."""
    design = np.asarray(report["design"])
    y = np.asarray(report["responses"][name], float)
    keys = [tuple(int(v) for v in row) for row in design[:, list(columns)]]
    return {k: float(np.mean([y[i] for i in range(len(y)) if keys[i] == k]))
            for k in sorted(set(keys))}


def main_effects(report: Mapping[str, Any], path: str | os.PathLike[str]) -> Path:
    """Mean response at each factor's low (-1) and high (+1) level, one row per response."""
    names = _responses(report)
    factors = list(report["factors"])
    levels = report.get("levels", {})
    fig = Figure(figsize=(2.4 * len(factors), 2.2 * len(names)), layout="constrained")
    axes = np.atleast_2d(fig.subplots(len(names), len(factors), sharey="row", squeeze=False))
    for r, name in enumerate(names):
        for c, factor in enumerate(factors):
            ax = axes[r, c]
            means = _level_means(report, name, [c])
            ax.plot([-1, 1], [means[(-1,)], means[(1,)]], "o-")
            lo_hi = levels.get(factor)
            ax.set_xticks([-1, 1], [f"{v:g}" for v in lo_hi] if lo_hi else ["-", "+"])
            if r == 0:
                ax.set_title(f"{c + 1}: {factor}", fontsize=9)
            if c == 0:
                ax.set_ylabel(f"{name} ({UNITS[name]})")
            ax.grid(alpha=0.3)
    return _save(fig, Path(path))


def interactions(report: Mapping[str, Any], path: str | os.PathLike[str]) -> Path:
    """Interaction plots: 34 (SEARCH_SIZE x CORR_SIZE) and each response's largest other 2FI."""
    names = _responses(report)
    factors = list(report["factors"])
    fig = Figure(figsize=(9, 2.6 * len(names)), layout="constrained")
    axes = fig.subplots(len(names), 2, squeeze=False)
    for r, name in enumerate(names):
        eff = report["effects"][name]
        others = [t for t in eff if len(t) == 2 and t != "34"]
        largest = max(others, key=lambda t: abs(eff[t])) if others else None
        for ax, term in zip(axes[r], ["34", largest], strict=True):
            if term is None or term not in eff:
                ax.set_visible(False)
                continue
            a, b = (int(ch) - 1 for ch in term)
            means = _level_means(report, name, [a, b])
            for lb, style in ((-1, "o--"), (1, "s-")):
                ax.plot([-1, 1], [means[(-1, lb)], means[(1, lb)]], style,
                        label=f"{factors[b]} {'low' if lb < 0 else 'high'}")
            ax.set_xticks([-1, 1], [f"{factors[a]} low", "high"])
            ax.set_title(f"{name}: interaction {term} (effect {eff[term]:+.3g} "
                         f"{UNITS[name]})", fontsize=9)
            ax.set_ylabel(f"{name} ({UNITS[name]})")
            ax.legend(fontsize=8)
            ax.grid(alpha=0.3)
    return _save(fig, Path(path))


def sweep_heatmap(report: Mapping[str, Any], name: str, path: str | os.PathLike[str]) -> Path:
    """One response over the SEARCH_SIZE x CORR_SIZE sweep, the optimum starred."""
    sweep = report["sweep"]
    values = np.asarray(sweep[name], float)
    ss, cs = sweep["search_size"], sweep["corr_size"]
    fig = Figure(figsize=(6, 5), layout="constrained")
    ax = fig.subplots()
    im = ax.imshow(values, origin="lower", aspect="auto", cmap="viridis")
    ax.set_xticks(range(len(cs)), [str(c) for c in cs])
    ax.set_yticks(range(len(ss)), [str(s) for s in ss])
    ax.set_xlabel("CORR_SIZE (px)")
    ax.set_ylabel("SEARCH_SIZE (px)")
    fixed = ", ".join(f"{k}={v:g}" for k, v in sweep.get("fixed", {}).items())
    ax.set_title(f"{TITLES[name]} ({UNITS[name]}); {fixed}", fontsize=9)
    fig.colorbar(im, ax=ax, label=f"{name} ({UNITS[name]})")
    opt = report.get("optimum", {})
    if opt.get("search_size") in ss and opt.get("corr_size") in cs:
        ax.plot(cs.index(opt["corr_size"]), ss.index(opt["search_size"]), "r*", ms=16,
                label="optimum")
        ax.legend(loc="upper left", fontsize=8)
    return _save(fig, Path(path))


def write_plots(report: Mapping[str, Any], out_dir: str | os.PathLike[str]) -> list[Path]:
    """Write every plot of the module docstring into ``out_dir`` (created if needed).

    Returns the paths written.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = [halfnormal(report, out / "halfnormal.png"),
             main_effects(report, out / "main_effects.png"),
             interactions(report, out / "interactions.png")]
    paths += [sweep_heatmap(report, name, out / f"sweep_{name}.png")
              for name in ("t1", "tf", "ex", "ey")]
    return paths
