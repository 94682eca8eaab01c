"""Ground truth for scoring: the Middlebury optical-flow data and its ``.flo`` files.

Baker, Scharstein, Lewis, Roth, Black, Szeliski, "A Database and Evaluation Methodology for
Optical Flow", IJCV 92(1), 2011. The data is not part of the project: it is found through the
``VISTRACK_DATA`` environment variable, else ``../shared/data`` beside the checkout.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

FLO_MAGIC = 202021.25
UNKNOWN = 1e9  # flow components at or above this magnitude are "unknown"


def data_dir() -> Path | None:
    """The shared data folder, or None when neither VISTRACK_DATA nor ../shared/data exists."""
    env = os.environ.get("VISTRACK_DATA")
    if env:
        p = Path(env)
        return p if p.is_dir() else None
    here = Path(__file__).resolve().parent.parent  # the checkout
    for cand in (here.parent / "shared" / "data", Path.cwd().parent / "shared" / "data"):
        if cand.is_dir():
            return cand
    return None


def middlebury(sequence: str) -> Path | None:
    """Folder of one Middlebury sequence (e.g. "RubberWhale"), or None if absent."""
    root = data_dir()
    if root is None:
        return None
    p = root / "middlebury" / sequence
    return p if p.is_dir() else None


class DataError(ValueError):
    """A data file that does not read, or files that do not fit together; the text names the
    file and what was wrong."""


#: What makes a folder under ``<data>/middlebury`` a scored pair: Middlebury's file names.
PAIR_FILES = ("frame10.png", "frame11.png", "flow10.flo")


def middlebury_pairs(first: tuple[str, ...] = ()) -> list[str]:
    """The Middlebury-format pairs in the data folder: every folder under ``middlebury/``
    holding :data:`PAIR_FILES` (the shared data's five, or a user's own sequences put beside
    them), those named in ``first`` first, in that order, then the others by name; empty
    when there is no data folder."""
    root = data_dir()
    top = root / "middlebury" if root is not None else None
    if top is None or not top.is_dir():
        return []
    found = sorted(p.name for p in top.iterdir()
                   if p.is_dir() and all((p / f).is_file() for f in PAIR_FILES))
    return [n for n in first if n in found] + [n for n in found if n not in first]


def read_flo(path: str | os.PathLike[str]) -> np.ndarray:
    """Read a Middlebury ``.flo`` file.

    Returns
    -------
    (H, W, 2) float32 flow (u, v) in px; unknown entries are set to NaN.
    """
    with open(path, "rb") as f:
        magic = np.fromfile(f, np.float32, 1)
        if magic.size != 1 or magic[0] != FLO_MAGIC:
            raise DataError(f"{path}: not a .flo file (bad magic number)")
        dims = np.fromfile(f, np.int32, 2)
        if dims.size != 2 or dims.min() <= 0 or dims.max() > 100_000:
            raise DataError(f"{path}: bad .flo dimensions {dims.tolist()}")
        w, h = int(dims[0]), int(dims[1])
        data = np.fromfile(f, np.float32, w * h * 2)
    if data.size != w * h * 2:
        raise DataError(f"{path}: truncated .flo file ({data.size} of {w * h * 2} values)")
    flow = data.reshape(h, w, 2).copy()
    flow[np.abs(flow).max(axis=2) >= UNKNOWN] = np.nan
    return flow


def endpoint_errors(start: np.ndarray, end: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """End-point errors of tracked points against a ground-truth flow.

    Parameters
    ----------
    start, end : (N, 2) x, y of each point in the first and second frame.
    flow : (H, W, 2) ground truth, NaN where unknown; sampled at the rounded start position.

    Returns
    -------
    (M,) px errors, M <= N: points whose flow is unknown or that are NaN are left out.
    """
    start = np.asarray(start, np.float64).reshape(-1, 2)
    end = np.asarray(end, np.float64).reshape(-1, 2)
    h, w = flow.shape[:2]
    ix = np.clip(np.rint(start[:, 0]).astype(int), 0, w - 1)
    iy = np.clip(np.rint(start[:, 1]).astype(int), 0, h - 1)
    gt = flow[iy, ix].astype(np.float64)
    err = np.hypot(*(end - start - gt).T)
    return err[np.isfinite(err)]
