"""Position estimation: centroid and scatter of Eq. (2), and robust incremental motion.

Eq. (2) of the paper, over the N feature points (x_i, y_i) with centroid (xbar, ybar):

    x_e = sum_i |xbar - x_i|        y_e = sum_i |ybar - y_i|

Image motion along X is read from the centroid and along Z (approach / recede) from the scatter.
The paper uses the raw sums, which jump when features are lost (its Table 1b: 379 -> 40 as NPI
goes 19 -> 8), so we also estimate the motion from the features matched in two consecutive
frames only (:func:`incremental_motion`), which a lost feature cannot disturb.
"""

from __future__ import annotations

import numpy as np


def centroid_scatter(points: np.ndarray) -> tuple[float, float, float, float]:
    """Eq. (2): centroid (xc, yc) and scatter (xe, ye), all in px.

    Parameters
    ----------
    points : (N, 2) x, y feature positions.

    Returns
    -------
    xc, yc, xe, ye ; NaN centroid and zero scatter when there are no points.
    """
    pts = np.asarray(points, np.float64).reshape(-1, 2)
    if len(pts) == 0:
        return float("nan"), float("nan"), 0.0, 0.0
    xc, yc = pts.mean(axis=0)
    xe = float(np.abs(xc - pts[:, 0]).sum())
    ye = float(np.abs(yc - pts[:, 1]).sum())
    return float(xc), float(yc), xe, ye


def _similarity_inliers(a: np.ndarray, b: np.ndarray, rounds: int = 3) -> np.ndarray:
    """Mask of point pairs that agree with one translation + isotropic scale.

    Least-squares fit of ``b - mean(b) = s (a - mean(a))``, then pairs whose residual exceeds
    3 robust sigmas (MAD, at least 0.5 px) are left out and the fit repeated. A plain median
    of the displacements would reject the genuine outer points of a scale change.
    """
    keep = np.ones(len(a), bool)
    for _ in range(rounds):
        if keep.sum() < 3:
            break
        ca, cb = a[keep].mean(axis=0), b[keep].mean(axis=0)
        da = a - ca
        denom = float((da[keep] ** 2).sum())
        s = float((da[keep] * (b[keep] - cb)).sum()) / denom if denom > 1e-12 else 1.0
        r = np.hypot(*(b - cb - s * da).T)
        mad = 1.4826 * float(np.median(r[keep]))
        new = r <= max(3.0 * mad, 0.5)
        if (new == keep).all():
            break
        keep = new
    return keep


def incremental_motion(before: np.ndarray, after: np.ndarray) -> tuple[float, float, float]:
    """Image motion between two frames from the same features seen in both.

    Parameters
    ----------
    before, after : (N, 2) x, y of the matched features in frames t and t+1.

    Returns
    -------
    dx, dy : mean displacement of the inliers, px. Inliers are the pairs consistent with one
        translation and scale (:func:`_similarity_inliers`), so mismatches cannot drag it.
    scale : ratio of the inliers' mean distance to their centroid, after / before (> 1 when the
        target grows: the camera approaches it); 1 when fewer than 3 inliers.
    """
    a = np.asarray(before, np.float64).reshape(-1, 2)
    b = np.asarray(after, np.float64).reshape(-1, 2)
    if a.shape != b.shape:
        raise ValueError(f"before {a.shape} and after {b.shape} must have one shape")
    if len(a) == 0:
        return 0.0, 0.0, 1.0
    keep = _similarity_inliers(a, b) if len(a) >= 3 else np.ones(len(a), bool)
    dx, dy = (b[keep] - a[keep]).mean(axis=0)
    scale = 1.0
    if keep.sum() >= 3:
        a_in, b_in = a[keep], b[keep]
        spread_a = np.hypot(*(a_in - a_in.mean(axis=0)).T).mean()
        spread_b = np.hypot(*(b_in - b_in.mean(axis=0)).T).mean()
        if spread_a > 1e-9:
            scale = float(spread_b / spread_a)
    return float(dx), float(dy), scale
