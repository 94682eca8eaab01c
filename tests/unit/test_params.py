"""TrackerParams: Table 4 defaults and validation that names field, value and range."""

from __future__ import annotations

import pytest

from vistrack.common.params import BOUNDS, FACTORS, ParamError, TrackerParams


def test_defaults_are_table4_with_the_papers_optimum():
    p = TrackerParams()
    assert (p.max_features, p.thres_percent, p.ungroup_size) == (100, 2.0, 5)
    assert (p.search_size, p.corr_size) == (15, 9)
    assert FACTORS == ("max_features", "thres_percent", "search_size", "corr_size",
                       "ungroup_size")


@pytest.mark.parametrize("field", sorted(BOUNDS))
def test_out_of_range_names_field_value_and_range(field):
    lo, hi = BOUNDS[field]
    for bad in (lo - 1, hi + 1):
        with pytest.raises(ParamError) as err:
            TrackerParams(**{field: bad})
        text = str(err.value)
        assert text.startswith(f"{field}=") and "allowed" in text
        assert f"{lo:g}" in text and f"{hi:g}" in text


@pytest.mark.parametrize("field,value", [("search_size", "15"), ("max_features", 2.5),
                                         ("corr_size", True), ("thres_percent", "x"),
                                         ("thres_percent", float("nan")),
                                         ("weights", "box"), ("subpixel", 1),
                                         ("strength", "harris"), ("search", "full"),
                                         ("search", None), ("levels", 2.5),
                                         ("reject_border", "yes"), ("guided_retry", 0),
                                         ("max_fb_error", float("inf"))])
def test_wrong_types_are_rejected(field, value):
    with pytest.raises(ParamError, match=field):
        TrackerParams(**{field: value})


def test_replace_and_from_mapping():
    p = TrackerParams().replace(search_size=21, corr_size=11.0)
    assert p.search_size == 21 and p.corr_size == 11 and isinstance(p.corr_size, int)
    with pytest.raises(ParamError, match="unknown parameter serch_size"):
        TrackerParams.from_mapping({"serch_size": 3})
    with pytest.raises(AttributeError):
        p.search_size = 3  # type: ignore[misc]


def test_geometry():
    p = TrackerParams(search_size=15, corr_size=8)
    assert p.corr_half == 4 and p.search_half == 7
    assert TrackerParams(max_features=100).effective_cell_cap == 13


def test_search_is_pruned_by_default_and_names_the_choices():
    assert TrackerParams().search == "pruned"
    assert TrackerParams(search="exhaustive").replace(search_size=21).search == "exhaustive"
    with pytest.raises(ParamError) as err:
        TrackerParams(search="brute")
    assert str(err.value) == "search='brute' is not allowed: use one of pruned, exhaustive"


def test_the_tracker_is_coarse_to_fine_with_its_checks_by_default():
    """Three pyramid levels, sub-pixel refinement, the match tests and a 21 px sub-pixel
    window; the texture floor of a camera with 2 grey levels of noise."""
    p = TrackerParams()
    assert (p.levels, p.subpixel, p.refine_size, p.refine_half) == (3, True, 21, 10)
    assert (p.uniqueness, p.max_fb_error, p.consensus) == (1.25, 1.0, 2.0)
    assert p.reject_border and p.guided_retry
    assert (p.noise_sigma, p.quality_level) == (2.0, 0.01)
    assert TrackerParams(corr_size=25).refine_half == 0  # not wider than the window: none


def test_paper_is_the_papers_single_level_tracker():
    """TrackerParams.paper(): one level, integer positions, no test of a match, no retry; the
    five factors and the other knobs as given."""
    p = TrackerParams.paper(search_size=21, search="exhaustive")
    assert (p.levels, p.subpixel, p.refine_half, p.search_size, p.search) == (
        1, False, 0, 21, "exhaustive")
    assert (p.uniqueness, p.max_fb_error, p.consensus) == (0.0, 0.0, 0.0)
    assert not p.reject_border and not p.guided_retry
    assert p.factors() == TrackerParams(search_size=21).factors()
    with pytest.raises(ParamError, match="levels=0 is out of range: allowed 1..6"):
        TrackerParams.paper(levels=0)


def test_the_tracker_is_named_by_its_rules_not_by_the_flags_both_take():
    """--paper with --levels 3 --subpixel is still the paper's tracker, and the default one
    with --levels 1 --no-subpixel --refine-size 0 is still the default one."""
    paper = TrackerParams.paper()
    like_paper = TrackerParams(levels=1, subpixel=False, refine_size=0)
    assert (paper.tracker, like_paper.tracker) == ("paper", "default")
    assert TrackerParams.paper(levels=3, subpixel=True).tracker == "paper"
    assert TrackerParams(consensus=0.0).tracker == "custom"  # one rule of the paper's only
    assert paper.tracker_said() == ("paper (no rejection rules); single-level search; "
                                    "sub-pixel off; pruned SSD search")
    assert like_paper.tracker_said() == ("default (rejection rules on); single-level search; "
                                         "sub-pixel off; pruned SSD search")
    assert TrackerParams(search="exhaustive", refine_size=13).tracker_said() == (
        "default (rejection rules on); coarse-to-fine search over 3 levels; sub-pixel on, "
        "refine_size 13; exhaustive SSD search")


@pytest.mark.parametrize("paper", [False, True])
def test_an_even_window_width_acts_as_the_next_odd_one(paper):
    """As the help and the README say (and the paper's code does): search_size 16 searches
    as 17 and corr_size 8 correlates as 9, in the default tracker and the paper's; a width
    that rounds to another half-width (15) does not."""
    import numpy as np

    from vistrack.common.synthetic import builtin_sequence
    from vistrack.common.vision import track_frames

    frames = builtin_sequence(12)
    base = TrackerParams.paper() if paper else TrackerParams()

    def run(search: int, corr: int) -> list[tuple]:
        return [(e.npi, e.xc, e.yc, e.dx, e.dy, e.scale, e.points.tobytes())
                for e in track_frames(frames, base.replace(search_size=search, corr_size=corr))]

    odd = run(17, 9)
    assert run(16, 8) == odd
    assert run(15, 9) != odd or run(17, 7) != odd  # the windows matter at all here
    assert np.isfinite([v for row in odd for v in row[1:6]]).all()
