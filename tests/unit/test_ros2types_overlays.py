"""What ros2types adds for recordings and the live view: the ImageMarker overlays of an
estimate, the contract messages rebuilt by key (``of_ros``), and the check of a recorded
schema against ours (``schema_problem``). Decoded with mcap-ros2-support, not rosbags."""

from __future__ import annotations

import numpy as np
import pytest
from test_ros2types import _decode_with_mcap_ros2 as _decode

from vistrack.common import ros2types as r2
from vistrack.common.messages import CmdVel, Estimate, Frame, MessageError, PreFrame


def _estimate(npi: int = 3) -> Estimate:
    feats = [[1, 10.0, 20.0], [2, 14.0, 20.0], [5, 12.0, 23.0]][:npi]
    xs, ys = [f[1] for f in feats], [f[2] for f in feats]
    xc, yc = (float(np.mean(xs)), float(np.mean(ys))) if feats else (0.0, 0.0)
    return Estimate(seq=7, stamp_ns=1_700_000_000_123_456_789, npi=npi, xc=xc, yc=yc,
                    xe=float(sum(abs(x - xc) for x in xs)),
                    ye=float(sum(abs(y - yc) for y in ys)), dx=0.0, dy=0.0, scale=1.0,
                    t_ms=0.3, first=False, features=feats, params_id=4)


def test_features_are_points_at_their_pixels_with_the_frame_stamp():
    est = _estimate()
    m = _decode(r2.IMAGE_MARKER, r2.serialize(r2.feature_marker(est)))
    assert m.type == 4 and m.action == 0  # POINTS, ADD (visualization_msgs/ImageMarker)
    assert [(p.x, p.y, p.z) for p in m.points] == [(10.0, 20.0, 0.0), (14.0, 20.0, 0.0),
                                                   (12.0, 23.0, 0.0)]
    assert (m.header.stamp.sec, m.header.stamp.nanosec) == (1_700_000_000, 123_456_789)
    assert m.scale == r2.FEATURE_DOT_PX and m.outline_color.a == 1.0


def test_the_centroid_circle_has_the_mean_distance_as_its_radius():
    est = _estimate()
    m = _decode(r2.IMAGE_MARKER, r2.serialize(r2.centroid_marker(est)))
    assert m.type == 0 and (m.position.x, m.position.y) == (est.xc, est.yc)
    # |10-12|+|14-12|+|12-12| = 4 and |20-21|*2+|23-21| = 4: (4 + 4) / (2 * 3)
    assert m.scale == pytest.approx(8 / 6, rel=1e-6)
    empty = _decode(r2.IMAGE_MARKER, r2.serialize(r2.centroid_marker(_estimate(0))))
    assert empty.outline_color.a == 0.0 and empty.scale == 1.0  # nothing to draw, but stamped
    two = _estimate(2)  # a centroid of two points is theirs, not the target's: not valid
    assert not two.valid
    assert _decode(r2.IMAGE_MARKER, r2.serialize(r2.centroid_marker(two))).outline_color.a \
        == 0.0
    assert _decode(r2.IMAGE_MARKER, r2.serialize(r2.feature_marker(_estimate(0)))).points == []


def test_of_ros_rebuilds_by_key_with_what_the_ros_type_lacks():
    frame = Frame.from_image(np.arange(6, dtype=np.uint8).reshape(2, 3), seq=0, stamp_ns=5)
    back = r2.of_ros(Frame.KEY, r2.image(frame), seq=41, stamp_ns_=0)
    assert back.seq == 41 and back.stamp_ns == 5 and np.array_equal(back.data, frame.data)
    cmd = CmdVel(seq=3, stamp_ns=9, vx=0.5, vy=0.25, wz=-0.1, stale=True)
    assert r2.of_ros(CmdVel.KEY, r2.twist(cmd), seq=3, stamp_ns_=9) == \
        CmdVel(seq=3, stamp_ns=9, vx=0.5, vy=0.25, wz=-0.1, stale=False)
    est = _estimate()
    assert r2.of_ros(Estimate.KEY, r2.estimate(est), seq=0, stamp_ns_=0) == est
    pre = PreFrame(seq=0, stamp_ns=0, width=3, height=2, data=frame.data,
                   candidates=np.zeros((0, 2), np.int16), strength=np.zeros(0, np.float32),
                   params_id=0)
    with pytest.raises(TypeError, match="preprocessing/frame"):
        r2.of_ros(PreFrame.KEY, r2.image(pre), seq=0, stamp_ns_=0)
    bad = r2.estimate(est)
    bad.scale = -1.0  # valid CDR, not a valid motion/estimate
    with pytest.raises(MessageError, match="scale"):
        r2.of_ros(Estimate.KEY, bad, seq=0, stamp_ns_=0)


def test_schema_problem_accepts_our_msg_files_and_names_a_difference():
    text = (r2.msg_dir() / "Estimate.msg").read_text()  # comments and all, as ros2 bag writes
    assert r2.schema_problem(r2.ESTIMATE, text) is None
    assert r2.schema_problem(r2.IMAGE, r2.msgdef(r2.IMAGE)) is None
    older = r2.msgdef(r2.ESTIMATE).replace("bool valid\n", "")
    assert "(header, seq, npi," in r2.schema_problem(r2.ESTIMATE, older)
    retyped = r2.msgdef(r2.ESTIMATE).replace("uint32 npi", "int64 npi")
    assert "field types" in r2.schema_problem(r2.ESTIMATE, retyped)
    assert "Image has the fields (linear, angular), this vistrack's (header, " in \
        r2.schema_problem(r2.IMAGE, r2.msgdef(r2.TWIST))
