"""The rendered long sequences (:mod:`vistrack.common.rendered`): their ground truth is exact,
their views stay inside the source, their motion is what it says, and they are deterministic."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vistrack.common import groundtruth, rendered


def test_rendered_ground_truth_is_exact():
    """A frame rendered with the homographies puts a point of the source exactly where the
    ground truth says: a bright dot, found by its centre of mass, within 0.05 px in every
    frame; the views stay inside the source, and the fastest step is 12 px."""
    source = np.zeros((300, 400), np.uint8)
    cv2.circle(source, (200, 150), 6, 255, -1, lineType=cv2.LINE_AA)
    hs = rendered.homographies((400, 300), (160, 120), 40, max_step=12.0, seed=3)
    frames = rendered.render(source, hs, (160, 120), noise=0.0)
    seq = rendered.RenderedSequence("dot", frames, hs)
    for k, f in enumerate(frames):
        h = hs[k] @ [200.0, 150.0, 1.0]  # where the source's dot centre lands
        expect = h[:2] / h[2]
        if not (10 < expect[0] < 150 and 10 < expect[1] < 110):
            continue  # the dot is out of view
        m = cv2.moments(f.astype(np.float32))
        found = (m["m10"] / m["m00"], m["m01"] / m["m00"])
        assert np.hypot(found[0] - expect[0], found[1] - expect[1]) < 0.05, k
    corners = np.array([[0, 0], [159, 0], [159, 119], [0, 119]], float)
    for k in range(len(hs)):
        src = seq.map(corners, k, k)  # identity check of map
        np.testing.assert_allclose(src, corners, atol=1e-9)
        q = np.hstack([corners, np.ones((4, 1))]) @ np.linalg.inv(hs[k]).T
        q = q[:, :2] / q[:, 2:]
        assert q.min() >= 2 and q[:, 0].max() <= 397 and q[:, 1].max() <= 297
    centre = np.array([[79.5, 59.5]])
    steps = [np.hypot(*(seq.map(centre, k, k + 1) - centre)[0]) for k in range(len(hs) - 1)]
    assert abs(max(steps) - 12.0) < 0.05 and min(steps) < 6.0


def test_rendered_sequences_are_deterministic():
    folder = groundtruth.middlebury("Venus")
    if folder is None:
        pytest.skip("Middlebury Venus not found: set VISTRACK_DATA or put the shared data at "
                    "../shared/data")
    a = rendered.middlebury_sequences(5, names=("Venus",))[0]
    b = rendered.middlebury_sequences(5, names=("Venus",))[0]
    for fa, fb in zip(a.frames, b.frames, strict=True):
        np.testing.assert_array_equal(fa, fb)
    np.testing.assert_array_equal(a.homographies, b.homographies)
