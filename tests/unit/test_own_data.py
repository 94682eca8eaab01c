"""A user's own sequences on the scoreboard: any folder of Middlebury's files (frame10.png,
frame11.png, flow10.flo) under ``$VISTRACK_DATA/middlebury/`` is scored beside the shared
data's pairs; files that do not fit together give a one-line error naming them."""

from __future__ import annotations

import subprocess
import sys

import cv2
import numpy as np
import pytest

from vistrack.common import groundtruth
from vistrack.services.bench.accuracy import PAIRS, scoreboard


def _write_flo(path, flow: np.ndarray) -> None:
    h, w = flow.shape[:2]
    with open(path, "wb") as f:
        np.array([groundtruth.FLO_MAGIC], np.float32).tofile(f)
        np.array([w, h], np.int32).tofile(f)
        flow.astype(np.float32).tofile(f)


def _own_pair(folder, image: np.ndarray, shift: tuple[int, int]) -> None:
    """frame11 = frame10 moved by ``shift`` (x, y) px; the flow says so (unknown where the
    moved frame has no source: the border)."""
    folder.mkdir(parents=True)
    dx, dy = shift
    moved = np.roll(image, (dy, dx), axis=(0, 1))
    cv2.imwrite(str(folder / "frame10.png"), image)
    cv2.imwrite(str(folder / "frame11.png"), moved)
    flow = np.empty(image.shape + (2,), np.float32)
    flow[..., 0], flow[..., 1] = dx, dy
    flow[-dy:, :] = flow[:, -dx:] = 1e10  # rolled round from the other side: unknown
    _write_flo(folder / "flow10.flo", flow)


@pytest.fixture
def own_data(tmp_path, monkeypatch, real_image):
    monkeypatch.setenv("VISTRACK_DATA", str(tmp_path))
    _own_pair(tmp_path / "middlebury" / "MyCorridor", real_image, (3, 2))
    (tmp_path / "middlebury" / "notes").mkdir()  # not a pair: skipped
    return tmp_path


def test_a_users_own_pair_is_found_and_scored(own_data):
    assert groundtruth.middlebury_pairs(PAIRS) == ["MyCorridor"]
    rows = scoreboard(n_frames=4)
    assert [r.sequence for r in rows] == ["MyCorridor (pair)"]
    ours, lk = rows[0].ours, rows[0].lk
    assert ours.pairs >= 50 and lk.pairs >= 50
    assert ours.median_epe < 0.05 and ours.gross == 0.0  # a whole-pixel shift, found


def test_shared_pairs_come_first_then_the_others_by_name(tmp_path, monkeypatch, real_image):
    monkeypatch.setenv("VISTRACK_DATA", str(tmp_path))
    for name in ("Zed", "Venus", "Alpha", "Dimetrodon"):
        _own_pair(tmp_path / "middlebury" / name, real_image[:64, :64], (1, 1))
    assert groundtruth.middlebury_pairs(PAIRS) == ["Dimetrodon", "Venus", "Alpha", "Zed"]


def test_a_flow_of_another_size_is_a_one_line_error(own_data):
    folder = own_data / "middlebury" / "MyCorridor"
    _write_flo(folder / "flow10.flo", np.zeros((10, 12, 2), np.float32))
    assert _bench_error() == (f"vistrack bench accuracy: {folder}: frame11.png is 256x256 and "
                              "flow10.flo 12x10: expected frame10.png's 256x256")


def _bench_error() -> str:
    """``vistrack bench accuracy``'s one line of error, having checked that it exits 2 with
    nothing more on stderr."""
    out = subprocess.run([sys.executable, "-m", "vistrack.services.cli", "bench", "accuracy"],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 2, out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1, out.stderr
    return lines[0]


def test_a_pair_with_no_ground_truth_where_the_features_are_is_shown_not_counted(own_data,
                                                                                real_image):
    """Sparse ground truth (KITTI's: known on a quarter of the pixels) can leave a pair with no
    tracked feature to score: its row shows '-' where there is nothing to compare, and the
    totals and targets are those of the other rows, not NaN."""
    folder = own_data / "middlebury" / "Sparse"
    _own_pair(folder, real_image, (3, 2))
    _write_flo(folder / "flow10.flo", np.full((256, 256, 2), 1e10, np.float32))  # all unknown
    out = subprocess.run([sys.executable, "-m", "vistrack.services.cli", "bench", "accuracy"],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    sparse, = (line for line in lines if line.startswith("Sparse (pair)"))
    # pairs, median, >2px, survival, drift, rejected | the same, LK | verdict | the pairs
    # both tracked: pairs, ours, LK, verdict
    cols = sparse.split()
    assert cols[4:9] == ["0", "-", "-", "-", "-"] and cols[11:] == [
        "0", "-", "-", "-", "-", "|", "-", "|", "0", "-", "-", "-"], sparse
    mine, = (line for line in lines if line.startswith("MyCorridor (pair)"))
    assert mine.split()[-6:-4] == ["yes", "|"] and mine.split()[-1] == "yes", mine
    total, = (line for line in lines if line.startswith("all sequences:"))
    assert "nan" not in total and "0.00 % off" in total, total
    targets, = (line for line in lines if line.startswith("targets:"))
    assert targets.startswith("targets: median <= LK's on every sequence: met (1 without pairs "
                              "on one side, not counted); on the pairs both tracked: met; pairs "
                              "off by > 2 px <= 2 % on every sequence: met (worst 0.00 %), over "
                              "all: met"), targets


def _own_run(folder, image: np.ndarray, step: tuple[int, int], first: int) -> None:
    """frame<first> to frame11, each the one before moved by ``step`` (x, y) px (whole
    pixels, rolled), and flow10.flo saying so for frame10 to frame11 (unknown at the rolled
    border)."""
    folder.mkdir(parents=True)
    dx, dy = step
    for k in range(first, 12):
        moved = np.roll(image, ((k - first) * dy, (k - first) * dx), axis=(0, 1))
        cv2.imwrite(str(folder / f"frame{k:02d}.png"), moved)
    flow = np.empty(image.shape + (2,), np.float32)
    flow[..., 0], flow[..., 1] = dx, dy
    flow[-dy:, :] = flow[:, -dx:] = 1e10  # rolled round from the other side: unknown
    _write_flo(folder / "flow10.flo", flow)


def test_a_folder_with_the_frames_before_is_also_scored_in_a_running_track(tmp_path,
                                                                         monkeypatch,
                                                                         real_image):
    """Middlebury's "other" sequences hold frame07 to frame14: the pair frame10 to frame11 is
    also scored at the end of a running track from the frames before it (held features
    followed from their velocity, as on a robot), only its step counted; a folder with the
    pair alone has no such row."""
    monkeypatch.setenv("VISTRACK_DATA", str(tmp_path))
    _own_run(tmp_path / "middlebury" / "Hall", real_image, (3, 2), first=8)
    _own_pair(tmp_path / "middlebury" / "Kitchen", real_image, (1, 1))
    rows = scoreboard(n_frames=4)
    assert [(r.sequence, r.frames) for r in rows] == [
        ("Hall (pair)", 2), ("Kitchen (pair)", 2), ("Hall (pair, running from frame08)", 4)]
    pair, running = rows[0], rows[2]
    # one step scored: no more pairs than the features held into frame10, found by both
    assert 50 <= running.ours.pairs <= 100 and 50 <= running.lk.pairs <= 100
    assert running.ours.median_epe < 0.05 and running.ours.gross == 0.0
    assert running.ours.gross_one_motion == 0.0
    assert pair.ours.median_epe < 0.05


def test_an_earlier_frame_of_another_size_is_a_one_line_error(tmp_path, monkeypatch,
                                                               real_image):
    monkeypatch.setenv("VISTRACK_DATA", str(tmp_path))
    folder = tmp_path / "middlebury" / "Hall"
    _own_run(folder, real_image, (3, 2), first=8)
    cv2.imwrite(str(folder / "frame09.png"), real_image[:100, :120])
    assert _bench_error() == (f"vistrack bench accuracy: {folder / 'frame09.png'}: 120x100, "
                              "expected frame10.png's 256x256")
