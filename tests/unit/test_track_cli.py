"""``vistrack track``: the CLI contract, outputs equal to the library, bad input -> exit 2."""

from __future__ import annotations

import csv
import io
import json
import shutil

import cv2
import numpy as np
import pytest
from forkcli import vistrack

from vistrack.common.params import TrackerParams
from vistrack.common.vision import Tracker, to_gray


def test_jsonl_equals_the_library(rubberwhale):
    out = vistrack("track", str(rubberwhale), "--format", "jsonl", "--search-size", "21",
                   "--corr-size", "11", "--subpixel", check=True).stdout
    rows = [json.loads(line) for line in out.splitlines()]
    assert len(rows) == 8
    tracker = Tracker(TrackerParams(search_size=21, corr_size=11, subpixel=True))
    for i, row in enumerate(rows):
        frame = to_gray(cv2.imread(str(rubberwhale / f"frame{7 + i:02d}.png")))
        e = tracker.process(frame).as_dict()
        assert set(row) >= {"seq", "npi", "xc", "yc", "xe", "ye", "dx", "dy", "scale", "t_ms",
                            "features"}
        for k in ("seq", "npi", "xc", "yc", "xe", "ye", "dx", "dy", "scale", "features"):
            assert row[k] == e[k], k
        assert row["npi"] == len(row["features"])
        assert row["t_ms"] > 0


def test_table_and_csv_formats(rubberwhale, tmp_path):
    files = [str(rubberwhale / f"frame{i:02d}.png") for i in (10, 11, 12)]
    table = vistrack("track", *files, check=True).stdout.splitlines()
    body = [line for line in table if not line.startswith("#")]
    assert len(body) == 3 and "NPI" in table[1] and "t1=" in table[-1]
    rows = list(csv.DictReader(io.StringIO(
        vistrack("track", *files, "--format", "csv", "--resize", "256x256",
                 check=True).stdout)))
    assert len(rows) == 3 and float(rows[0]["npi"]) > 0
    # a glob, and a folder with the same files, give the same estimates
    for f in files:
        shutil.copy(f, tmp_path)
    a = vistrack("track", str(tmp_path), "--format", "jsonl", check=True).stdout
    b = vistrack("track", str(tmp_path / "frame1*.png"), "--format", "jsonl", check=True).stdout
    strip = [{k: v for k, v in json.loads(x).items() if k != "t_ms"} for x in a.splitlines()]
    strip_b = [{k: v for k, v in json.loads(x).items() if k != "t_ms"} for x in b.splitlines()]
    assert strip == strip_b and len(strip) == 3


def test_search_flag_changes_the_cost_not_the_estimates(rubberwhale):
    files = [str(rubberwhale / f"frame{i:02d}.png") for i in (10, 11, 12, 13)]
    runs = {}
    for search in ("pruned", "exhaustive"):
        out = vistrack("track", *files, "--format", "jsonl", "--search", search,
                       "--search-size", "31", "--corr-size", "15", check=True).stdout
        runs[search] = [{k: v for k, v in json.loads(x).items() if k != "t_ms"}
                        for x in out.splitlines()]
    assert runs["pruned"] == runs["exhaustive"] and len(runs["pruned"]) == 4
    header = vistrack("track", *files[:2], "--search", "exhaustive", check=True).stdout
    assert "search=exhaustive" in header.splitlines()[0]


def test_levels_paper_and_subpixel_flags(rubberwhale):
    """--levels, --paper (the paper's tracker) and --no-subpixel reach the tracker: jsonl
    equal to the library with those parameters."""
    files = [str(rubberwhale / f"frame{i:02d}.png") for i in (10, 11, 12)]
    frames = [to_gray(cv2.imread(f)) for f in files]
    for flags, params in ((["--levels", "1"], TrackerParams(levels=1)),
                          (["--paper"], TrackerParams.paper()),
                          (["--paper", "--subpixel", "--levels", "2"],
                           TrackerParams.paper(subpixel=True, levels=2)),
                          (["--no-subpixel"], TrackerParams(subpixel=False)),
                          (["--refine-size", "0"], TrackerParams(refine_size=0))):
        out = vistrack("track", *files, "--format", "jsonl", *flags, check=True).stdout
        rows = [json.loads(line) for line in out.splitlines()]
        tracker = Tracker(params)
        for row, frame in zip(rows, frames, strict=True):
            e = tracker.process(frame).as_dict()
            assert row["features"] == e["features"], flags
    table = vistrack("track", *files, "--paper", check=True).stdout
    assert "levels=1" in table and "subpixel=False" in table
    table = vistrack("track", *files, "--refine-size", "13", check=True).stdout
    assert "refine_size=13" in table.splitlines()[0]


def test_the_table_names_the_tracker_that_ran(rubberwhale):
    """The paper's tracker and the default one on the paper's settings printed the same
    parameter line: it ends with the tracker's name now."""
    files = [str(rubberwhale / f"frame{i:02d}.png") for i in (10, 11)]
    first = {}
    for name, flags in (("paper", ["--paper"]),
                        ("like", ["--levels", "1", "--no-subpixel", "--refine-size", "0"]),
                        ("default", [])):
        first[name] = vistrack("track", *files, *flags, check=True).stdout.splitlines()[0]
    settings = ("max_features=100 thres_percent=2 search_size=15 corr_size=9 ungroup_size=5 "
                "subpixel=False search=pruned levels=1 refine_size=0")
    assert first["paper"].endswith(f"; {settings} tracker=paper")
    assert first["like"].endswith(f"; {settings} tracker=default")
    assert first["default"].endswith("subpixel=True search=pruned levels=3 refine_size=21 "
                                     "tracker=default")


def test_video_file_and_builtin(tmp_path):
    from vistrack.common import synthetic

    frames = synthetic.sequence(6, size=(128, 96), motion=synthetic.Motion(dx=2.0))
    path = str(tmp_path / "clip.avi")
    vw = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*"MJPG"), 10, (128, 96))
    for f in frames:
        vw.write(cv2.cvtColor(f, cv2.COLOR_GRAY2BGR))  # colour in, converted to grey
    vw.release()
    rows = [json.loads(x) for x in vistrack("track", path, "--format", "jsonl",
                                            check=True).stdout.splitlines()]
    assert len(rows) == 6 and abs(rows[-1]["dx"] - 10.0) < 1.0
    out = vistrack("track", "--format", "jsonl", check=True).stdout.splitlines()
    assert len(out) == 60  # the built-in sequence


def test_a_video_whose_index_holds_empty_entries_is_tracked_to_its_end(drop_frame_video):
    # its header announces 20 frames and 10 decode: "cut short", exit 2, was the answer
    path, frames = drop_frame_video
    result = vistrack("track", str(path), "--format", "jsonl")
    assert result.returncode == 0, result.stderr
    assert len(result.stdout.splitlines()) == len(frames) and result.stderr == ""


def test_file_names_that_are_not_utf8(rubberwhale, tmp_path, drop_frame_video):
    """Names in another encoding (Latin-1's e-acute, held by Python as a surrogate escape)
    crashed the process inside OpenCV (SIGSEGV, exit 139): images are read, a video is a
    one-line error."""
    import os

    folder = os.fsencode(tmp_path) + b"/latin"
    os.mkdir(folder)
    sources = [rubberwhale / f"frame{k:02d}.png" for k in (7, 8, 9)]
    for k, src in enumerate(sources):
        with open(folder + b"/frame%d\xe9.png" % k, "wb") as f:
            f.write(src.read_bytes())
    result = vistrack("track", os.fsdecode(folder), "--format", "jsonl")
    assert result.returncode == 0, result.stderr
    rows = [json.loads(x) for x in result.stdout.splitlines()]
    # the same files under their own (UTF-8) names
    ref = [json.loads(x) for x in vistrack("track", *map(str, sources), "--format", "jsonl",
                                           check=True).stdout.splitlines()]
    for r in rows + ref:
        r.pop("t_ms")
    assert len(rows) == 3 and rows == ref
    video = os.fsencode(tmp_path) + b"/clip\xe9.avi"
    os.link(drop_frame_video[0], video)
    result = vistrack("track", os.fsdecode(video))
    assert result.returncode == 2
    assert result.stderr.strip().endswith("OpenCV cannot open a video whose name is not "
                                          "UTF-8: rename it, or link to it under a UTF-8 name")


@pytest.mark.parametrize("args,needle", [
    (["/no/such/file.png"], "no such file"),
    (["--search-size", "500"], "--search-size 500 is out of range: allowed 2..128"),
    (["--thres-percent", "9"], "--thres-percent 9 is out of range: allowed 0.1..5"),
    (["--thres-percent", "nan"], "--thres-percent nan is out of range: allowed 0.1..5"),
    (["--format", "xml"], "invalid choice"),
    (["--resize", "big"], "--resize 'big' is not WIDTHxHEIGHT, e.g. 256x256"),
    (["--resize", ""], "--resize '' is not WIDTHxHEIGHT, e.g. 256x256"),  # was: native size
    (["--resize", "0x0"], "--resize 0x0 is out of range: width and height must be 8..8192"),
    (["--max-features", "many"], "--max-features 'many' is not an integer: allowed 1..2000"),
    (["--max-features", "1e9"], "--max-features '1e9' is not an integer: allowed 1..2000"),
    (["--search", "full"], "invalid choice"),
    (["--levels", "0"], "--levels 0 is out of range: allowed 1..6"),
    (["--levels", "2.5"], "--levels '2.5' is not an integer: allowed 1..6"),
    (["--refine-size", "65"], "--refine-size 65 is out of range: allowed 0..64"),
    (["--refine-size", "-1"], "--refine-size -1 is out of range: allowed 0..64"),
])
def test_bad_input_is_one_line_and_exit_2(args, needle):
    r = vistrack("track", *args)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0] and "Traceback" not in r.stderr


def test_an_image_file_that_decodes_to_too_many_pixels_is_refused_from_its_header(tmp_path):
    """140 KB of PNG that decodes to 12000x12000 px: one line naming the file and the limit,
    as the file camera and a simulator texture say it too (was: tracked, 144 MB a frame;
    past OpenCV's own default, 2^30 px, a traceback)."""
    from test_ros2_images import png_of_black

    bomb = tmp_path / "bomb.png"
    bomb.write_bytes(png_of_black(12000, 12000))
    said = (f"{bomb} decodes to more than the 67108864 px (8192x8192) an image may have "
            "(OPENCV_IO_MAX_IMAGE_PIXELS): refused from its header")
    for command, text in ((["track", str(bomb)], said),
                          (["camera", "--source", "sim", "--texture", str(bomb)],
                           f"texture {said}")):
        r = vistrack(*command)
        assert (r.returncode, r.stderr) == (2, f"vistrack {command[0]}: error: {text}\n")


def test_bad_files_are_one_line_and_exit_2(tmp_path):
    (tmp_path / "empty").mkdir()
    (tmp_path / "junk.png").write_bytes(b"not a png")
    a = np.zeros((40, 50), np.uint8)
    cv2.imwrite(str(tmp_path / "a.png"), a)
    cv2.imwrite(str(tmp_path / "b.png"), np.zeros((40, 60), np.uint8))
    video = cv2.VideoWriter(str(tmp_path / "v.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 10,
                            (50, 40))
    video.write(np.zeros((40, 50, 3), np.uint8))
    video.release()
    cases = [([str(tmp_path / "empty")], "folder holds no image"),
             ([str(tmp_path / "v.avi"), str(tmp_path / "a.png")],
              f"{tmp_path / 'v.avi'}: a video among 2 files: give one video alone, or image "
              "files"),
             ([str(tmp_path / "junk.png")], "not a readable image"),
             ([str(tmp_path / "a.png"), str(tmp_path / "b.png")], "60x40 but the first was 50x40"),
             ([str(tmp_path / "nothing*.png")], "matches no image file"),
             ([str(tmp_path / "text.mp4")], "not a readable video")]
    (tmp_path / "text.mp4").write_text("not a video")
    for args, needle in cases:
        r = vistrack("track", *args)
        assert r.returncode == 2, args
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and needle in lines[0], r.stderr
    # a source that gives no frame says so before any output (the table's header came first)
    r = vistrack("track", str(tmp_path / "text.mp4"))
    assert r.stdout == ""


@pytest.mark.parametrize("service", ["preprocessing", "motion-estimation", "auto-tuner"])
def test_services_take_the_search_flag_and_refuse_a_bad_one(service):
    r = vistrack(service, "--help", check=True)
    assert "--search {pruned,exhaustive}" in r.stdout
    r = vistrack(service, "--search", "full", "--no-multicast-scouting")
    assert r.returncode == 2 and "invalid choice: 'full'" in r.stderr


@pytest.mark.parametrize("service", ["preprocessing", "motion-estimation", "auto-tuner"])
def test_services_refuse_bad_parameter_flags_before_starting(service):
    """A service given an out-of-range parameter says so in one line and exits 2, before it
    opens a Zenoh session (no traceback, no half-started process)."""
    r = vistrack(service, "--search-size", "500", "--no-multicast-scouting")
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert lines == [f"vistrack {service}: error: --search-size 500 is out of range: "
                     "allowed 2..128"]


def test_features_left_unsearched_by_the_work_budget_are_said(rubberwhale):
    """The largest windows and feature count in range, the paper's exhaustive search: most
    features are not searched, the frame's work budget reached. The table's NPI and valid
    do not show it; the service warns, and so does track now, once."""
    files = [str(rubberwhale / f"frame{i:02d}.png") for i in (10, 11, 12)]
    res = vistrack("track", *files, "--paper", "--search", "exhaustive", "--search-size",
                   "128", "--corr-size", "64", "--max-features", "2000", "--ungroup-size", "0",
                   "--thres-percent", "5", check=True)
    warnings = [line for line in res.stderr.splitlines() if "warning" in line]
    assert len(warnings) == 1 and "features not searched" in warnings[0], res.stderr
    assert "budget" in res.stdout.splitlines()[-1]


@pytest.mark.skipif(not __import__("os").path.exists("/dev/full"), reason="no /dev/full here")
@pytest.mark.parametrize("fmt", ["table", "csv", "jsonl"])
def test_an_output_that_cannot_be_written_is_one_line_not_a_traceback(rubberwhale, fmt):
    """A full disk (/dev/full: every write fails with ENOSPC) printed a Python traceback; then,
    with the output buffered as it is for a user (no PYTHONUNBUFFERED, which the suite's first
    runs inherited), exit 1 and no line at all: the last writes failed at the interpreter's
    end."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}
    with open("/dev/full", "w") as full:
        run = subprocess.run([sys.executable, "-m", "vistrack.services.cli", "track",
                              str(rubberwhale), "--format", fmt], stdout=full,
                             stderr=subprocess.PIPE, text=True, timeout=300, env=env)
    assert run.returncode == 1, run.stderr
    assert run.stderr == ("vistrack track: error: writing the output: No space left on "
                          "device\n")
