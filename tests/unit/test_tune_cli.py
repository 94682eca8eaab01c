"""``vistrack tune``: the CLI contract (json fields, text sections, plots, bad input -> exit 2).

A small buffer (the built-in sequence resized to 96x96, 6 frames, a coarse sweep, one timing
pass) keeps each run to a few seconds; the numbers are checked in test_experiment.py.
"""

from __future__ import annotations

import json

import pytest
from forkcli import vistrack as run_vistrack
from test_experiment import check_report

from vistrack.services import cli
from vistrack.services.auto_tuner.design import paper_design

FAST = ["--resize", "96x96", "--max-frames", "6", "--step", "5", "--repeats", "1"]
PNGS = {"halfnormal.png", "main_effects.png", "interactions.png", "sweep_t1.png",
        "sweep_tf.png", "sweep_ex.png", "sweep_ey.png"}


def vistrack(*args, check=False):
    return run_vistrack(*args, timeout=180, check=check)


def test_json_prints_the_report_fields():
    res = vistrack("tune", "builtin", *FAST, "--seed", "7", "--format", "json", check=True)
    rep = json.loads(res.stdout)
    check_report(rep)
    assert rep["order"] == paper_design().randomized_order(7).tolist()
    assert rep["seed"] == 7 and rep["frames"] == 6 and rep["size"] == [96, 96]
    assert rep["tolerance"] == 0.5 and rep["method"] == "lenth"
    assert rep["search"] == "pruned"  # the default SSD search timed the runs
    assert res.stderr == ""  # no progress line when stderr is not a terminal


def test_the_report_names_the_tracker_it_tuned():
    """A tuning of the paper's tracker and one of the default tracker said nothing of it
    (only the SSD search): the text's second line and the json's tracker field do."""
    reports = {}
    for name, flags in (("default", []), ("paper", ["--paper"]), ("two", ["--levels", "2"])):
        res = vistrack("tune", "builtin", *FAST, "--seed", "7", *flags, "--format", "json",
                       check=True)
        reports[name] = json.loads(res.stdout)["tracker"]
    assert reports == {
        "default": {"name": "default", "levels": 3, "subpixel": True, "refine_size": 21},
        "paper": {"name": "paper", "levels": 1, "subpixel": False, "refine_size": 0},
        "two": {"name": "default", "levels": 2, "subpixel": True, "refine_size": 21}}
    text = vistrack("tune", "builtin", *FAST, "--seed", "7", "--paper", check=True).stdout
    assert text.splitlines()[1] == ("# tracker: paper (no rejection rules); single-level "
                                    "search; sub-pixel off; pruned SSD search; windows: the "
                                    "design's and the sweep's")


def test_text_sections_progress_and_plots(tmp_path):
    out = tmp_path / "plots"
    res = vistrack("tune", *FAST, "--seed", "3", "--out", str(out), "--progress",
                   "--tolerance", "0.75", "--method", "anova", check=True)
    text = res.stdout
    for section in ("## Design", "## Alias structure", "## Effects", "## Table 3",
                    "## Sensitivity sweep"):
        assert section in text, section
    # the choice's heading says whether it met the tolerance
    met = "no swept window within" not in text
    assert ("\n## Optimum\n" in text) == met
    assert ("\n## Closest to the reference (no swept window within the tolerance)\n"
            in text) == (not met)
    table3 = text.split("## Table 3")[1].split("##")[0].splitlines()
    assert [line.split()[0] for line in table3[2:6]] == ["t1", "tf", "ex", "ey"]
    assert "1 = 2345" in text and "34 = 125" in text  # I = ABCDE
    design = text.split("## Design")[1].split("##")[0].splitlines()
    assert sum(1 for line in design if line[:4].strip().isdigit()) == 16
    assert "within 0.75 px" in text or "no swept window within 0.75 px" in text
    assert "vistrack tune: design [" in res.stderr and "vistrack tune: sweep" in res.stderr
    written = {p.name for p in out.iterdir()}
    assert written == PNGS
    for p in out.iterdir():
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and p.stat().st_size > 5000


def test_a_response_that_cannot_be_tested_says_so_in_table_3(tmp_path):
    """A still scene: every run measures no motion, as the reference does, so ex and ey are
    exactly 0 and Lenth's method has no scale (a statistics review). Table 3 showed '-' as for
    a response with no significant effect; it says the response could not be tested."""
    import cv2

    from conftest import source_image

    for i in range(6):
        cv2.imwrite(str(tmp_path / f"f{i}.png"), source_image("RubberWhale"))
    res = vistrack("tune", str(tmp_path), *FAST, "--seed", "3", check=True)
    table3 = res.stdout.split("## Table 3")[1].split("##")[0].splitlines()
    rows = {line.split()[0]: line for line in table3[2:6]}
    for n in ("ex", "ey"):
        assert "not testable: half or more of its effects are exactly 0" in rows[n], rows[n]
    for n in ("t1", "tf"):  # timed: never all equal
        assert "not testable" not in rows[n]


def test_a_choice_that_misses_the_tolerance_says_so_in_its_heading():
    # "## Optimum" with a speed-up, and the caveat only on the line below it
    res = vistrack("tune", *FAST, "--seed", "3", "--tolerance", "0", check=True)
    chosen = res.stdout.split("\n## Closest to the reference (no swept window within the "
                              "tolerance)\n")[1]
    assert "## Optimum" not in res.stdout and "no swept window within 0 px" in chosen


@pytest.mark.parametrize("args,message", [
    (["/no/such/file.png"], "no such file"),
    (["--tolerance", "-1"], "--tolerance -1 is out of range: allowed 0..100"),
    (["--tolerance", "nan"], "--tolerance nan is out of range: allowed 0..100"),
    (["--resize", "huge"], "--resize 'huge' is not WIDTHxHEIGHT"),
    (["--resize="], "--resize '' is not WIDTHxHEIGHT"),
    (["--max-frames", "1"], "--max-frames 1 is out of range: allowed 2..1000"),
    (["--repeats", "0"], "--repeats 0 is out of range: allowed 1..20"),
    (["--replicates", "0"], "--replicates 0 is out of range: allowed 1..20"),
    (["--replicates", "21"], "--replicates 21 is out of range: allowed 1..20"),
    (["--replicates", "3", "--method", "anova"], "tested against pure error"),
    (["--step", "0"], "--step 0 is out of range: allowed 1..10"),
    (["--step", "11"], "--step 11 is out of range: allowed 1..10"),
    (["--seed", "-1"], "--seed -1 is out of range: allowed 0..9223372036854775807"),
    (["--seed", "x"], "--seed 'x' is not an integer: allowed 0..9223372036854775807"),
    (["--format", "xml"], "invalid choice"),
    (["--max-megapixels", "0"], "--max-megapixels 0 is out of range: allowed 0.1..1000"),
])
def test_bad_input_is_one_line_and_exit_2(args, message, capsys):
    code = _main(["tune", *args])
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith("vistrack tune: error: ") and message in err
    assert len(err.strip().splitlines()) == 1


def test_search_exhaustive_times_the_papers_search(capsys):
    """Same buffer and seed with either search: the same motion (ex, ey, NPI) and design, but
    the times come from the search asked for (the report says which)."""
    reports = {}
    for search in ("pruned", "exhaustive"):
        assert _main(["tune", "builtin", *FAST, "--seed", "4", "--format", "json",
                      "--search", search]) == 0
        reports[search] = json.loads(capsys.readouterr().out)
    a, b = reports["pruned"], reports["exhaustive"]
    assert a["search"] == "pruned" and b["search"] == "exhaustive"
    for name in ("ex", "ey", "npi_mean"):
        assert a["responses"][name] == b["responses"][name], name
    assert a["order"] == b["order"]
    assert _main(["tune", "--search", "full"]) == 2
    assert "invalid choice: 'full'" in capsys.readouterr().err


def test_replicates_analyse_against_pure_error(capsys):
    """--replicates 2: the report keeps the contract's shapes (responses are the run means)
    and adds every replicate; the text says what the effects were tested against."""
    assert _main(["tune", "builtin", *FAST, "--seed", "4", "--format", "json",
                  "--replicates", "2"]) == 0
    rep = json.loads(capsys.readouterr().out)
    check_report(rep)
    assert rep["replicates"] == 2 and rep["method"] == "pure-error"
    assert [len(row) for row in rep["replicate_responses"]["tf"]] == [2] * 16
    assert rep["pure_error"]["tf"]["df"] == 16
    assert _main(["tune", "builtin", *FAST, "--seed", "4", "--replicates", "2"]) == 0
    text = capsys.readouterr().out
    assert "2 replicates of every design run" in text
    assert "## Table 3: significant terms (pure error)" in text
    assert "tf: ANOVA against pure error, 2 independent timings of each of the 16 runs: 16 df" \
        in text


def test_out_that_is_a_file_is_an_error_before_any_work(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    code = _main(["tune", *FAST, "--out", str(blocker / "plots")])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("vistrack tune: error: --out ")
    assert len(err.strip().splitlines()) == 1


def test_an_empty_out_is_an_error_not_a_run_without_plots(tmp_path, monkeypatch, capsys):
    # `if args.out:` took '' for "no plots": the run went on and said nothing of them
    monkeypatch.chdir(tmp_path)
    assert _main(["tune", "builtin", *FAST, "--out", ""]) == 2
    captured = capsys.readouterr()
    assert captured.err == ("vistrack tune: error: --out: empty folder name; give a folder, "
                            "e.g. --out tune-report\n")
    assert captured.out == "" and list(tmp_path.iterdir()) == []


def test_a_single_frame_is_not_enough(tmp_path, capsys):
    import cv2
    import numpy as np

    path = tmp_path / "one.png"
    cv2.imwrite(str(path), np.zeros((32, 32), np.uint8))
    assert _main(["tune", str(path)]) == 2
    err = capsys.readouterr().err
    # what was read, and from where: a user with one file sees why, not just the rule
    assert "at least 2 frames" in err and f"{path} gave 1" in err


def test_a_video_cut_short_to_one_frame_says_both(real_image, cut_video_of, capsys):
    """A video whose header announces 16 frames and that holds 1: too few to tune on, and
    why (the cut), in one error."""
    import numpy as np

    image = np.dstack([real_image] * 3)
    # the bytes that hold one frame depend on how it compressed (a cut frame decodes too)
    for k, fraction in enumerate((0.09, 0.07, 0.05, 0.03)):
        cut, held = cut_video_of([image] * 16, name=f"cut{k}.avi", fraction=fraction)
        if len(held) == 1:
            break
    assert len(held) == 1
    assert _main(["tune", str(cut)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "at least 2 frames" in err[0] and "gave 1" in err[0]
    assert "the video ends after 1 of the 16 frames" in err[0]


def _main(argv: list[str]) -> int:
    """The CLI in-process: argparse errors exit (code 2) through SystemExit."""
    try:
        return cli.main(argv)
    except SystemExit as e:
        return int(e.code)


def test_a_video_cut_short_is_tuned_on_then_reported(real_image, cut_video_of, capsys):
    """The frames a cut video still holds are tuned on and the results printed; then the
    one-line error, exit 2, as ``vistrack track`` does (it was the error alone: nothing
    tuned)."""
    import numpy as np

    image = np.dstack([real_image] * 3)
    frames = [np.ascontiguousarray(np.roll(image, (k, 2 * k), axis=(0, 1))) for k in range(16)]
    cut, held = cut_video_of(frames)
    code = _main(["tune", str(cut), "--step", "5", "--repeats", "1", "--seed", "1",
                  "--format", "json"])
    captured = capsys.readouterr()
    assert code == 2
    rep = json.loads(captured.out)
    check_report(rep)
    assert rep["frames"] == len(held)
    assert captured.err.splitlines()[-1] == (
        f"vistrack tune: error: {cut}: the video ends after {len(held)} of the 16 frames its "
        "header announces (cut short or damaged)")


def test_only_the_frames_within_the_work_budget_are_kept_as_they_are_read(tmp_path):
    """The budget picks the latest frames that fit; all --max-frames were read and held
    first (1000 frames of 4096x4096 passed 3 GB in 7 s before the cut)."""
    import argparse

    import cv2
    import numpy as np

    from vistrack.services.offline.tune import read_buffer

    for k in range(10):  # 1 MP each, frame k's pixels all k
        cv2.imwrite(str(tmp_path / f"f{k:02d}.png"), np.full((1000, 1000), k, np.uint8))
    args = argparse.Namespace(frames=[str(tmp_path)], resize=None, max_frames=10, bounce=False,
                              max_megapixels=4.0)
    frames, _, cut, offered = read_buffer(args)
    assert cut is None and offered == 10
    assert [int(f[0, 0]) for f in frames] == [6, 7, 8, 9]
    # played back and forth, the frames are all kept: the bounce needs every one of them
    args.max_frames, args.bounce = 16, True
    frames, _, _, offered = read_buffer(args)
    assert len(frames) == 16 and offered == 16


def test_a_long_tune_says_how_far_it_is_where_no_line_can_be_rewritten():
    """On a log or a pipe a 10-minute tune printed nothing at all; now a plain line every
    30 s (here 0.05) says the phase, how far, and about how long is left; a short run says
    nothing (the JSON test above: stderr empty)."""
    import io
    import time

    from vistrack.services.offline.tune import ProgressNotes

    stream = io.StringIO()
    notes = ProgressNotes(stream, every=0.05)
    for done in range(1, 4):  # faster than every: nothing
        notes("design", done, 100)
    assert stream.getvalue() == ""
    time.sleep(0.06)
    notes("design", 10, 100)
    line = stream.getvalue()
    assert line.startswith("vistrack tune: design 10/100 after 0 s, about ") and \
        line.endswith(" to go in design\n") and line.count("\n") == 1, line


def test_plots_that_cannot_be_written_still_leave_the_report(tmp_path, capsys, monkeypatch):
    """The plots were written before the report was printed: on a full disk a run of many
    minutes ended in one error line and nothing on stdout. The report now comes first."""
    import errno

    from vistrack.services.auto_tuner import plots

    def full(report, out):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(plots, "write_plots", full)
    code = _main(["tune", *FAST, "--seed", "3", "--out", str(tmp_path / "plots")])
    captured = capsys.readouterr()
    assert code == 2
    assert "## Table 3" in captured.out and "Optimum" in captured.out
    err = captured.err.strip().splitlines()
    assert err[-1].startswith("vistrack tune: error: --out ") and "No space left" in err[-1]
    assert "the report above is complete" in err[-1]
