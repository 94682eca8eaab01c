"""Tracker parameters: the paper's five factors plus the knobs the paper leaves implicit.

The five factors of the factorial design (Table 2 of the paper) keep their paper names in the
docs and snake_case names in code:

=============  ================  ===========================================  =======
paper          field             meaning                                      default
=============  ================  ===========================================  =======
MAX_FEAT_NUM   max_features      maximum number of feature points             100
THRES_PERCENT  thres_percent     % of pixels (strongest gradient) kept        2.0
SEARCH_SIZE    search_size       search window width, px                      15
CORR_SIZE      corr_size         correlation window width, px                 9
UNGROUP_SIZE   ungroup_size      minimum distance between feature points, px  5
=============  ================  ===========================================  =======

Defaults are Table 4's fixed values (100, 2, 5) with the optimum the paper picked (15, 9).

Window geometry: the correlation window is ``2 * (corr_size // 2) + 1`` pixels wide and the
search covers every displacement within ``search_size // 2`` of the predicted position, so an
even width behaves like the next odd one, as in the paper's C implementation.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

WEIGHT_KINDS = ("uniform", "gaussian")
STRENGTH_KINDS = ("min_eigen", "gradient")
#: How the SSD search of Eq. (1) finds its argmin: the same positions, different costs.
SEARCH_KINDS = ("pruned", "exhaustive")


class ParamError(ValueError):
    """A parameter value is out of range or of the wrong type. The message names the field,
    the value and what is allowed."""


# field -> (low, high) inclusive bounds for numeric fields
BOUNDS: dict[str, tuple[float, float]] = {
    "max_features": (1, 2000),
    "thres_percent": (0.1, 5.0),
    "search_size": (2, 128),
    "corr_size": (2, 64),
    "ungroup_size": (0, 100),
    "blur_sigma": (0.0, 10.0),
    "grid_rows": (1, 32),
    "grid_cols": (1, 32),
    "cell_cap": (0, 2000),
    "max_residual": (1.0, 255.0),
    "redetect_fraction": (0.0, 1.0),
    "levels": (1, 6),
    "uniqueness": (0.0, 10.0),
    "noise_sigma": (0.0, 50.0),
    "max_fb_error": (0.0, 100.0),
    "consensus": (0.0, 100.0),
    "refine_size": (0, 64),
    "quality_level": (0.0, 1.0),
}

#: Fewest features for a meaningful estimate (``valid`` of ``motion/estimate``): the centroid
#: and scatter of one or two points are those points, not the target's, and the robust motion's
#: outlier rejection needs three pairs to outvote one mismatch.
MIN_VALID_NPI = 3

#: What turns the tracker into the paper's: the single-level search of Eq. (1), integer
#: positions, and no test of a match beyond the paper's losses (:meth:`TrackerParams.paper`).
PAPER_TRACKER: dict[str, Any] = {"levels": 1, "subpixel": False, "uniqueness": 0.0,
                                 "max_fb_error": 0.0, "consensus": 0.0,
                                 "reject_border": False,
                                 "guided_retry": False, "refine_size": 0, "follow": False,
                                 "exposure": False}

#: What tells the paper's tracker from the default one, whatever ``--levels``, ``--subpixel``
#: and ``--refine-size`` (flags of both) set: its tests of a match and what finds a match
#: again (:meth:`TrackerParams.tracker`).
_TRACKER_RULES = tuple(k for k in PAPER_TRACKER if k not in ("levels", "subpixel",
                                                            "refine_size"))

#: The paper's five factors, in Table 2's order (A..E of the 2^(5-1) design).
FACTORS = ("max_features", "thres_percent", "search_size", "corr_size", "ungroup_size")

_INT_FIELDS = {"max_features", "search_size", "corr_size", "ungroup_size", "grid_rows",
               "grid_cols", "cell_cap", "levels", "refine_size"}
_BOOL_FIELDS = {"subpixel", "reject_border", "guided_retry", "follow", "exposure"}


@dataclass(frozen=True)
class TrackerParams:
    """Validated, immutable tracker configuration.

    Parameters
    ----------
    max_features : MAX_FEAT_NUM, 1..2000.
    thres_percent : THRES_PERCENT, 0.1..5.0 (% of the image's pixels kept as candidates).
    search_size : SEARCH_SIZE, 2..128 px.
    corr_size : CORR_SIZE, 2..64 px.
    ungroup_size : UNGROUP_SIZE, 0..100 px.
    blur_sigma : Gaussian pre-filter sigma in px, 0 disables the filter.
    grid_rows, grid_cols : feature-bucketing grid.
    cell_cap : most features chosen per grid cell; 0 picks ``ceil(2 * max_features / cells)``
        so that buckets spread the features and the overall cap then trims the weakest.
    weights : ``"uniform"`` or ``"gaussian"`` correlation-window weights W(i, j) of Eq. (1).
    strength : how candidates are ranked: ``"min_eigen"`` (smaller eigenvalue of the gradient
        structure tensor, default) or ``"gradient"`` (Sobel magnitude, the paper's literal
        measure); see :mod:`vistrack.common.vision.preprocess`.
    subpixel : refine each SSD minimum to sub-pixel precision (Gauss-Newton on Eq. (1), a
        parabola through the minimum and its neighbours where that cannot run); on by default.
    search : how the SSD search of Eq. (1) finds its argmin, see
        :func:`vistrack.common.vision.ssd.track_ssd`: ``"pruned"`` (default: exact, skips the
        displacements a bound rules out, so its cost barely grows with CORR_SIZE) or
        ``"exhaustive"`` (the paper's plain Eq. (1): every displacement scored in full, cost
        proportional to SEARCH_SIZE^2 x CORR_SIZE^2). Both give the same positions.
    max_residual : loss bound: a feature is lost when the RMS grey-level difference over its
        correlation window at the best match exceeds this.
    redetect_fraction : re-detect features when fewer than this fraction of ``max_features``
        survive.
    levels : pyramid levels of the coarse-to-fine search (1..6): Eq. (1) is searched at the
        coarsest level that holds a feature's template and refined level by level, so a search
        of SEARCH_SIZE // 2 px reaches 2^(levels - 1) times as far; 1 is the paper's
        single-level search. See :mod:`vistrack.common.vision.pyramid`.
    uniqueness : a match fails when a displacement outside its minimum's 3x3 neighbourhood
        has S <= uniqueness * S_min + 2 noise_sigma^2 sum W (repetitive texture); 0 turns the
        test off.
    noise_sigma : the camera's noise, grey levels: what noise alone adds to S at a perfect
        match (the uniqueness test), and the texture floor a candidate's strength must clear
        (what a uniform patch with this noise reaches, or with the noise the frame shows
        where that is more: :func:`vistrack.common.vision.preprocess.frame_noise`).
    max_fb_error : forward-backward bound, px: a match tracked back from frame t+1 must
        return to within this of where it started; 0 turns the check off.
    consensus : a match whose displacement departs from the median of its 6 nearest tracked
        neighbours' by more than this, px (or by more than three robust sigmas of theirs,
        where they disagree more), is rejected; 0 turns the check off.
    reject_border : a match whose minimum lies on the border of the search window fails (the
        true minimum may lie outside it).
    guided_retry : a feature that found no trustworthy minimum around its own prediction is
        searched again around the frame's dominant motion (the median displacement of the
        features found); a frame in which fewer than half were found is tracked again around
        the frame-wide shift (phase correlation, :func:`.vision.pyramid.frame_shift`).
    refine_size : width of the wide sub-pixel window, px: its estimate is taken where it
        agrees with the correlation window's; 0 (or not wider than CORR_SIZE) refines over the
        correlation window only.
    quality_level : a candidate's strength must also reach this fraction of the frame's
        strongest (OpenCV's ``goodFeaturesToTrack`` qualityLevel).
    follow : a feature tracked in the frame before is first refined by Gauss-Newton from its
        prediction at the frame's own level and taken when that converges within a pixel and
        its way back returns within ``max_fb_error``; only the others are searched coarse to
        fine (needs ``subpixel`` and ``max_fb_error`` > 0). See
        :mod:`vistrack.common.vision.pyramid`.
    exposure : compensate a change of exposure of the whole frame (auto-exposure, a light):
        frame t's pyramid is mapped by the gain and offset that take its brightness to frame
        t+1's before the coarse-to-fine search, when that moves its grey levels by more than
        ``2 noise_sigma``. See :mod:`vistrack.common.vision.exposure`.
    """

    max_features: int = 100
    thres_percent: float = 2.0
    search_size: int = 15
    corr_size: int = 9
    ungroup_size: int = 5
    blur_sigma: float = 0.5
    grid_rows: int = 4
    grid_cols: int = 4
    cell_cap: int = 0
    weights: str = "uniform"
    strength: str = "min_eigen"
    subpixel: bool = True
    search: str = "pruned"
    max_residual: float = 40.0
    redetect_fraction: float = 0.5
    levels: int = 3
    uniqueness: float = 1.25
    noise_sigma: float = 2.0
    max_fb_error: float = 1.0
    consensus: float = 2.0
    reject_border: bool = True
    guided_retry: bool = True
    refine_size: int = 21
    quality_level: float = 0.01
    follow: bool = True
    exposure: bool = True

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            name = f.name
            value = getattr(self, name)
            if name == "weights":
                if value not in WEIGHT_KINDS:
                    raise ParamError(f"weights={value!r} is not allowed: use one of "
                                     f"{', '.join(WEIGHT_KINDS)}")
                continue
            if name == "strength":
                if value not in STRENGTH_KINDS:
                    raise ParamError(f"strength={value!r} is not allowed: use one of "
                                     f"{', '.join(STRENGTH_KINDS)}")
                continue
            if name == "search":
                if value not in SEARCH_KINDS:
                    raise ParamError(f"search={value!r} is not allowed: use one of "
                                     f"{', '.join(SEARCH_KINDS)}")
                continue
            if name in _BOOL_FIELDS:
                if not isinstance(value, bool):
                    raise ParamError(f"{name}={value!r} must be true or false")
                continue
            lo, hi = BOUNDS[name]
            if name in _INT_FIELDS:
                # bool is an int subclass; reject it (True would silently mean 1)
                if isinstance(value, bool) or not isinstance(value, int):
                    if isinstance(value, float) and value.is_integer():
                        object.__setattr__(self, name, int(value))
                        value = int(value)
                    else:
                        raise ParamError(f"{name}={value!r} must be an integer in {lo}..{hi}")
                range_text = f"{int(lo)}..{int(hi)}"
            else:
                if isinstance(value, bool) or not isinstance(value, (int, float)):
                    raise ParamError(f"{name}={value!r} must be a number in {lo}..{hi}")
                value = float(value)
                object.__setattr__(self, name, value)
                range_text = f"{lo}..{hi}"
            if not lo <= value <= hi:  # also rejects NaN
                raise ParamError(f"{name}={value!r} is out of range: allowed {range_text}")

    # -- derived geometry -------------------------------------------------------------------
    @property
    def corr_half(self) -> int:
        """n of Eq. (1): the correlation window is (2n+1) x (2n+1)."""
        return self.corr_size // 2

    @property
    def search_half(self) -> int:
        """Half-width of the search window around the predicted position."""
        return self.search_size // 2

    @property
    def refine_half(self) -> int:
        """Half-width of the wide sub-pixel window (0: none)."""
        return self.refine_size // 2 if self.refine_size // 2 > self.corr_half else 0

    @property
    def effective_cell_cap(self) -> int:
        if self.cell_cap:
            return self.cell_cap
        cells = self.grid_rows * self.grid_cols
        return max(1, -(-2 * self.max_features // cells))

    # -- construction helpers ---------------------------------------------------------------
    def replace(self, **changes: Any) -> TrackerParams:
        """A copy with ``changes`` applied and validated (unknown names raise ParamError)."""
        return TrackerParams.from_mapping(changes, base=self)

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any], *,
                     base: TrackerParams | None = None) -> TrackerParams:
        """Build from a mapping such as a decoded message or a launch file section.

        Unknown names raise :class:`ParamError` listing the known ones, so a typo in a launch
        file or a ``params set`` is reported instead of silently ignored.
        """
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ParamError(f"unknown parameter {', '.join(unknown)}: known are "
                             f"{', '.join(sorted(known))}")
        merged = dataclasses.asdict(base if base is not None else cls())
        merged.update(values)
        return cls(**merged)

    @classmethod
    def paper(cls, **changes: Any) -> TrackerParams:
        """The paper's tracker (:data:`PAPER_TRACKER`: one level, integer positions, no test
        of a match), with ``changes`` applied: what the factorial design of the paper timed."""
        return cls.from_mapping({**PAPER_TRACKER, **changes})

    @property
    def tracker(self) -> str:
        """Which tracker these parameters run: ``"paper"`` where the tests of a match and the
        retries are the paper's (:data:`PAPER_TRACKER`: none), ``"default"`` where they are
        this class's defaults, else ``"custom"``. The pyramid, sub-pixel refinement and the
        windows are said apart (:meth:`tracker_said`): flags set them on either tracker."""
        if all(getattr(self, k) == PAPER_TRACKER[k] for k in _TRACKER_RULES):
            return "paper"
        defaults = TrackerParams()
        if all(getattr(self, k) == getattr(defaults, k) for k in _TRACKER_RULES):
            return "default"
        return "custom"

    def tracker_said(self) -> str:
        """The tracker in words for a report, so that two reports tell their trackers apart:
        which one (:attr:`tracker`), its search (single level or coarse to fine over
        ``levels``), sub-pixel refinement and the SSD search, e.g. ``default (rejection rules
        on); coarse-to-fine search over 3 levels; sub-pixel on, refine_size 21; pruned SSD
        search``. Not the windows: a tuning varies them."""
        kind = {"paper": "paper (no rejection rules)", "default": "default (rejection rules "
                "on)", "custom": "custom (rejection rules as set)"}[self.tracker]
        search = ("single-level search" if self.levels == 1 else
                  f"coarse-to-fine search over {self.levels} levels")
        subpixel = (f"sub-pixel on, refine_size {self.refine_size}" if self.subpixel
                    else "sub-pixel off")
        return f"{kind}; {search}; {subpixel}; {self.search} SSD search"

    def factors(self) -> dict[str, float]:
        """The five design factors as a dict (the fields of ``tuner/params``)."""
        return {name: getattr(self, name) for name in FACTORS}

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def describe_bounds() -> str:
    """One line per numeric field with its allowed range, for help texts."""
    return "\n".join(f"  {k}: {lo}..{hi}" for k, (lo, hi) in BOUNDS.items())
