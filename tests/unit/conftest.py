"""Fixtures for the pure-algorithm tests: real frames from the shared Middlebury data."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vistrack.common import groundtruth, rendered
from vistrack.common.params import TrackerParams
from vistrack.common.vision import to_gray
from vistrack.services.bench.accuracy import run_sequence


def load_pair(sequence: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """frame10, frame11 (grey) and the ground-truth flow of a Middlebury sequence, or skip."""
    folder = groundtruth.middlebury(sequence)
    if folder is None:
        pytest.skip(f"Middlebury {sequence} not found: set VISTRACK_DATA or put the shared "
                    "data at ../shared/data")
    a = to_gray(cv2.imread(str(folder / "frame10.png")))
    b = to_gray(cv2.imread(str(folder / "frame11.png")))
    return a, b, groundtruth.read_flo(folder / "flow10.flo")


@pytest.fixture(scope="session")
def real_image() -> np.ndarray:
    """A real 256x256 grey image (RubberWhale frame10, cropped), or skip."""
    a, _, _ = load_pair("RubberWhale")
    return np.ascontiguousarray(a[60:316, 160:416])


def rendered_sequences(n: int, names: tuple[str, ...]) -> list[rendered.RenderedSequence]:
    """:func:`rendered.middlebury_sequences` of ``n`` frames from ``names``, or skip."""
    seqs = rendered.middlebury_sequences(n, names=names)
    if len(seqs) < len(names):
        pytest.skip("Middlebury frames not found: set VISTRACK_DATA or put the shared data at "
                    "../shared/data")
    return seqs


def against_lk(seq: rendered.RenderedSequence, params: TrackerParams | None = None):
    """(ours, LK) over a rendered sequence, LK started from our features at every step, the
    ground truth its ``map`` (:func:`.accuracy.run_sequence`)."""
    return run_sequence(seq.frames, lambda p, k: seq.map(p, k, k + 1),
                        params if params is not None else TrackerParams(),
                        end_truth=lambda p: seq.map(p, 0, len(seq) - 1))[:2]


def assert_holds_lk(name: str, ours, lk, *, gross: float) -> None:
    """Issue 12's targets against LK on a sequence: median error at most LK's, at most
    ``gross`` of the pairs off by more than 2 px, and at least half LK's survival."""
    assert ours.median_epe <= lk.median_epe, (name, ours, lk)
    assert ours.gross <= gross, (name, ours.gross)
    assert ours.survival >= 0.5 * lk.survival, (name, ours.survival, lk.survival)


def source_image(name: str) -> np.ndarray:
    """The grey frame10 of the Middlebury sequence ``name``, as the rendered sequences start
    from (:func:`rendered.middlebury_sources`), or skip."""
    found = dict(rendered.middlebury_sources((name,)))
    if name not in found:
        pytest.skip(f"Middlebury {name} not found: set VISTRACK_DATA or put the shared data at "
                    "../shared/data")
    return found[name]


@pytest.fixture(scope="session")
def sources() -> list[tuple[str, np.ndarray]]:
    """(name, grey frame10) of every Middlebury sequence the rendered ones start from
    (:data:`rendered.SOURCES`), or skip."""
    found = rendered.middlebury_sources()
    if len(found) < len(rendered.SOURCES):
        pytest.skip("Middlebury frames not found: set VISTRACK_DATA or put the shared data at "
                    "../shared/data")
    return found


def panned_views(name: str, n: int, step: tuple[float, float], seed: int) -> list[np.ndarray]:
    """``n`` uint8 views of the Middlebury frame10 of ``name`` (:func:`source_image`), the
    view moving ``step`` px a frame from (150, 80), each with unit Gaussian noise: the scene
    moves by -``step`` a frame."""
    source = source_image(name)
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        view = view_of(source, 150.0 + step[0] * k, 80.0 + step[1] * k)
        out.append(np.clip(np.rint(view + rng.standard_normal(view.shape)), 0, 255)
                   .astype(np.uint8))
    return out


def view_of(source: np.ndarray, x: float, y: float, size: int = 256) -> np.ndarray:
    """The ``size`` square of ``source`` whose top left corner is at (x, y), float32,
    interpolated (cubic), its edges reflected: a camera's view moved by a sub-pixel amount."""
    shift = np.array([[1.0, 0.0, -x], [0.0, 1.0, -y]])
    return cv2.warpAffine(source.astype(np.float32), shift, (size, size),
                          flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
