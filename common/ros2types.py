"""The contract's messages as ROS 2 messages: types, CDR, schemas and type hashes.

One translation, used wherever vistrack speaks ROS 2: MCAP recordings (``ros2msg`` schemas,
``cdr`` payloads), the Foxglove live view and the ROS 2 bridge over ``rmw_zenoh``. The type
system and the CDR codec are ``rosbags``' (its ROS 2 Jazzy store); nothing here encodes CDR by
hand. vistrack's own types are the ``.msg`` files of ``deploy/ros2/vistrack_msgs/msg`` (a
colcon-buildable package), installed with the project as ``vistrack.ros2_msgs``.

=====================================  ===========================================
contract key                            ROS 2 type
=====================================  ===========================================
``camera/frame``, ``preprocessing/frame``  ``sensor_msgs/msg/Image`` (``mono8``)
``control/cmd_vel``                     ``geometry_msgs/msg/Twist`` (no header: ROS's own type)
``motion/estimate``                     ``vistrack_msgs/msg/Estimate``
``tuner/params``                        ``vistrack_msgs/msg/Params``
``tuner/report``                        ``vistrack_msgs/msg/Report``
=====================================  ===========================================

Header stamps come from the contract's ``stamp_ns``; ``frame_id`` is :data:`FRAME_ID`.

Each estimate is also drawn over its camera frame as two ``visualization_msgs/msg/ImageMarker``
overlays (:data:`OVERLAYS`), which Foxglove's Image panel (and ROS 2's ``rqt_image_overlay``)
draw: the tracked features as points (``camera/features``) and the centroid as a circle whose
radius is the features' mean distance from it (``camera/centroid``). They are derived topics,
not contract keys: nothing publishes them on Zenoh.
"""

from __future__ import annotations

import dataclasses
import functools
import importlib.util
import json
import struct
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import cv2
import msgpack
import numpy as np
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from . import imagelimit
from .messages import (
    MAX_SIDE,
    CmdVel,
    Estimate,
    Frame,
    Message,
    MessageError,
    Params,
    PreFrame,
    Report,
    to_jsonable,
)

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
TWIST = "geometry_msgs/msg/Twist"
ESTIMATE = "vistrack_msgs/msg/Estimate"
PARAMS = "vistrack_msgs/msg/Params"
REPORT = "vistrack_msgs/msg/Report"
IMAGE_MARKER = "visualization_msgs/msg/ImageMarker"

#: ``header.frame_id`` of what vistrack publishes: the camera's optical frame.
FRAME_ID = "camera"

#: Contract key suffix -> the ROS 2 type it is published as.
ROS_TYPES: dict[str, str] = {
    Frame.KEY: IMAGE, PreFrame.KEY: IMAGE, CmdVel.KEY: TWIST, Estimate.KEY: ESTIMATE,
    Params.KEY: PARAMS, Report.KEY: REPORT}


def msg_dir() -> Path:
    """The ``msg`` folder of ``vistrack_msgs``: installed as ``vistrack.ros2_msgs`` (a plain
    folder, no ``__init__.py``: it stays a ROS 2 package as it is in the repository)."""
    spec = importlib.util.find_spec("vistrack.ros2_msgs")
    for location in (spec.submodule_search_locations or []) if spec else []:
        folder = Path(location) / "msg"
        if folder.is_dir():
            return folder
    raise FileNotFoundError("vistrack_msgs/msg not found: reinstall vistrack "
                            "(deploy/ros2/vistrack_msgs is installed as vistrack.ros2_msgs)")


def msg_files() -> dict[str, str]:
    """``vistrack_msgs/msg/NAME`` -> the text of its ``.msg`` file."""
    return {f"vistrack_msgs/msg/{p.stem}": p.read_text(encoding="utf-8")
            for p in sorted(msg_dir().glob("*.msg"))}


@functools.lru_cache(maxsize=1)
def typestore() -> Typestore:
    """rosbags' ROS 2 Jazzy type store with ``vistrack_msgs`` registered (built once)."""
    store = get_typestore(Stores.ROS2_JAZZY)
    types: dict[str, Any] = {}
    for name, text in msg_files().items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


def serialize(obj: Any) -> bytes:
    """CDR bytes (little endian, with the 4-byte encapsulation header) of a rosbags message.

    Raises
    ------
    ValueError
        When a value does not fit its field's type (a contract message may hold what a ROS 2
        type cannot: an ``npi`` of 2^32, a stamp past 2038), naming the type; rosbags' own
        ``struct.error`` named neither the field nor the type.
    """
    try:
        return bytes(typestore().serialize_cdr(obj, obj.__msgtype__))
    except (struct.error, OverflowError) as e:
        raise ValueError(f"a value does not fit ROS 2 {obj.__msgtype__}: {e}") from None


def deserialize(data: bytes | bytearray | memoryview, typename: str) -> Any:
    """The rosbags message of CDR ``data`` of ``typename``.

    Raises
    ------
    ValueError
        When ``data`` is not a valid CDR encoding of ``typename`` (rosbags raises assorted
        exceptions on truncated or foreign bytes; they are all reported as one kind here).
    """
    try:
        # a memoryview: rosbags slices off the 4-byte header, which copied a whole image
        return typestore().deserialize_cdr(memoryview(bytes(data)), typename)
    except Exception as e:  # noqa: BLE001 - rosbags' decoder raises struct/index/unicode errors
        raise ValueError(f"not a CDR {typename}: {type(e).__name__}: {e}") from None


@functools.cache
def msgdef(typename: str) -> str:
    """The ``ros2msg`` schema text of ``typename``: its definition followed by those of the
    types it uses, each after a ``====`` line and ``MSG: pkg/Type`` (the format MCAP, Foxglove
    and ``ros2 bag`` read)."""
    text, _ = typestore().generate_msgdef(typename, ros_version=2)
    return text


@functools.cache
def type_hash(typename: str) -> str:
    """``RIHS01_<64 hex>``: the ROS 2 type hash of ``typename`` (REP 2011)."""
    return typestore().hash_rihs01(typename)


def _type(typename: str) -> Any:
    return typestore().types[typename]


#: The seconds ``builtin_interfaces/msg/Time`` holds (int32): 1901-12-13 to 2038-01-19 UTC.
STAMP_SEC_RANGE = (-(2 ** 31), 2 ** 31 - 1)


def stamp(stamp_ns: int) -> Any:
    """``builtin_interfaces/msg/Time`` of ns since the Unix epoch.

    Raises
    ------
    ValueError
        When the time lies outside what the type's int32 seconds hold (:data:`STAMP_SEC_RANGE`).
    """
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    lo, hi = STAMP_SEC_RANGE
    if not lo <= sec <= hi:
        raise ValueError(f"stamp_ns {int(stamp_ns)} lies outside what a ROS 2 "
                         f"builtin_interfaces/msg/Time holds (int32 seconds, {lo} to {hi} s "
                         "since the Unix epoch: 1901-12-13 to 2038-01-19 UTC)")
    return _type("builtin_interfaces/msg/Time")(sec=sec, nanosec=nanosec)


def header(stamp_ns: int, frame_id: str = FRAME_ID) -> Any:
    return _type("std_msgs/msg/Header")(stamp=stamp(stamp_ns), frame_id=frame_id)


def stamp_ns(header_obj: Any) -> int:
    """ns since the Unix epoch of a ``std_msgs/msg/Header``."""
    return int(header_obj.stamp.sec) * 1_000_000_000 + int(header_obj.stamp.nanosec)


# -- contract -> ROS 2 ----------------------------------------------------------------------

def image(msg: Frame | PreFrame, frame_id: str = FRAME_ID) -> Any:
    """``sensor_msgs/msg/Image`` (``mono8``, ``step = width``) of a frame."""
    data = np.ascontiguousarray(msg.data, dtype=np.uint8).reshape(-1)
    return _type(IMAGE)(header=header(msg.stamp_ns, frame_id), height=msg.height,
                        width=msg.width, encoding="mono8", is_bigendian=0, step=msg.width,
                        data=data)


def twist(msg: CmdVel) -> Any:
    """``geometry_msgs/msg/Twist`` of a command (robot frame: x forward, y left, z up)."""
    vec = _type("geometry_msgs/msg/Vector3")
    return _type(TWIST)(linear=vec(x=msg.vx, y=msg.vy, z=0.0), angular=vec(x=0.0, y=0.0,
                                                                           z=msg.wz))


def estimate(msg: Estimate, frame_id: str = FRAME_ID) -> Any:
    feature = _type("vistrack_msgs/msg/Feature")
    valid = getattr(msg, "valid", msg.npi > 0)
    return _type(ESTIMATE)(
        header=header(msg.stamp_ns, frame_id), seq=msg.seq, valid=bool(valid), npi=msg.npi,
        xc=msg.xc, yc=msg.yc, xe=msg.xe, ye=msg.ye, dx=msg.dx, dy=msg.dy, scale=msg.scale,
        t_ms=msg.t_ms, first=msg.first, params_id=msg.params_id,
        features=[feature(id=int(i), x=float(x), y=float(y)) for i, x, y in msg.features])


def params(msg: Params, frame_id: str = FRAME_ID) -> Any:
    return _type(PARAMS)(
        header=header(msg.stamp_ns, frame_id), seq=msg.seq, max_features=msg.max_features,
        thres_percent=msg.thres_percent, search_size=msg.search_size, corr_size=msg.corr_size,
        ungroup_size=msg.ungroup_size, params_id=msg.params_id, source=msg.source,
        reason=msg.reason)


def _strings(values: Any) -> list[str]:
    return [str(v) for v in values] if isinstance(values, (list, tuple)) else []


def report(msg: Report, frame_id: str = FRAME_ID, whole: Mapping[str, Any] | None = None
           ) -> Any:
    """``vistrack_msgs/msg/Report``: the design, per-response values, effects and significant
    terms as typed fields, and the whole report as JSON in ``json``: ``whole``, the map as
    published (the auto-tuner's ``trigger``, ``changed``, ``params_id``, ... besides the
    contract's fields, which are all ``msg`` holds), else ``msg``."""
    terms: list[str] = []
    for eff in msg.effects.values():
        if isinstance(eff, dict):
            terms += [str(t) for t in eff if str(t) not in terms]
    response = _type("vistrack_msgs/msg/Response")
    responses = []
    for name, values in msg.responses.items():
        eff = msg.effects.get(name, {})
        sig = msg.significant.get(name, {})
        responses.append(response(
            name=str(name),
            values=np.array([float(v) for v in values], np.float64),
            effects=np.array([float(eff.get(t, np.nan)) if isinstance(eff, dict) else np.nan
                              for t in terms], np.float64),
            significant_99=_strings(sig.get("99", [])) if isinstance(sig, dict) else [],
            significant_95=_strings(sig.get("95", [])) if isinstance(sig, dict) else []))
    opt = msg.optimum
    optimum = _type(PARAMS)(
        header=header(msg.stamp_ns, frame_id), seq=msg.seq,
        max_features=int(opt.get("max_features", 0)),
        thres_percent=float(opt.get("thres_percent", 0.0)),
        search_size=int(opt.get("search_size", 0)), corr_size=int(opt.get("corr_size", 0)),
        ungroup_size=int(opt.get("ungroup_size", 0)), params_id=int(opt.get("params_id", 0)),
        source=str(opt.get("source", "tuner")), reason=str(opt.get("reason", "")))
    design = np.array(msg.design, np.int8).reshape(-1)
    return _type(REPORT)(
        header=header(msg.stamp_ns, frame_id), seq=msg.seq, factors=_strings(msg.factors),
        design=design, order=np.array(msg.order, np.uint32), terms=terms,
        responses=responses, optimum=optimum,
        json=json.dumps(to_jsonable(msg if whole is None else whole)))


def to_ros(msg: Message, frame_id: str = FRAME_ID, payload: bytes | None = None) -> Any:
    """The ROS 2 message of a contract message (see the table above); ``payload``: the bytes it
    was decoded from, whose fields beyond the contract's a report's ``json`` keeps.

    Raises
    ------
    TypeError
        For ``sim/pose``, which has no ROS 2 counterpart here.
    """
    if isinstance(msg, (Frame, PreFrame)):
        return image(msg, frame_id)
    if isinstance(msg, CmdVel):
        return twist(msg)
    if isinstance(msg, Estimate):
        return estimate(msg, frame_id)
    if isinstance(msg, Params):
        return params(msg, frame_id)
    if isinstance(msg, Report):
        whole = msgpack.unpackb(payload, raw=False) if payload is not None else None
        return report(msg, frame_id, whole if isinstance(whole, dict) else None)
    raise TypeError(f"{type(msg).__name__} has no ROS 2 type")


# -- ROS 2 -> contract ----------------------------------------------------------------------

def frame_of_image(obj: Any, *, seq: int) -> Frame:
    """The ``camera/frame`` of a ``sensor_msgs/msg/Image`` in any encoding the ROS 2 camera
    source takes (:func:`grey_of_image`: colour to grey, 16-bit by its high byte; ``mono8``
    as it is). Only ``mono8`` was taken: a recording of a colour camera (a valid rosbag2
    file) was refused as damaged at its first frame."""
    return Frame.from_image(grey_of_image(obj), seq=seq, stamp_ns=stamp_ns(obj.header))


def cmd_vel_of_twist(obj: Any, *, seq: int, stamp_ns_: int, stale: bool = False) -> CmdVel:
    return CmdVel(seq=seq, stamp_ns=stamp_ns_, vx=obj.linear.x, vy=obj.linear.y,
                  wz=obj.angular.z, stale=stale)


def estimate_of_ros(obj: Any) -> Estimate:
    fields = {f.name for f in dataclasses.fields(Estimate)}
    values: dict[str, Any] = dict(
        seq=obj.seq, stamp_ns=stamp_ns(obj.header), npi=obj.npi, xc=obj.xc, yc=obj.yc,
        xe=obj.xe, ye=obj.ye, dx=obj.dx, dy=obj.dy, scale=obj.scale, t_ms=obj.t_ms,
        first=obj.first, params_id=obj.params_id,
        features=[[int(f.id), float(f.x), float(f.y)] for f in obj.features])
    if "valid" in fields:
        values["valid"] = bool(obj.valid)
    return Estimate(**values)


def params_of_ros(obj: Any) -> Params:
    return Params(seq=obj.seq, stamp_ns=stamp_ns(obj.header), max_features=obj.max_features,
                  thres_percent=obj.thres_percent, search_size=obj.search_size,
                  corr_size=obj.corr_size, ungroup_size=obj.ungroup_size,
                  params_id=obj.params_id, source=obj.source, reason=obj.reason)


def report_of_ros(obj: Any) -> Report:
    """The ``tuner/report`` carried whole in the message's ``json`` field."""
    m = json.loads(obj.json)
    names = [f.name for f in dataclasses.fields(Report)]
    return Report(**{n: m[n] for n in names if n in m})


def of_ros(suffix: str, obj: Any, *, seq: int, stamp_ns_: int) -> Message:
    """The contract message of key ``suffix`` rebuilt from its ROS 2 message ``obj``.

    ``seq`` and ``stamp_ns_`` fill what the ROS 2 type does not carry: an Image has no
    sequence number, a Twist neither a stamp nor ``stale`` (rebuilt as False).

    Raises
    ------
    TypeError
        For a key whose ROS 2 type does not carry the contract message whole
        (``preprocessing/frame``: an Image has no candidates) or has no ROS 2 type.
    ValueError
        When ``obj`` is not a valid message of that key (:class:`MessageError` is one).
    """
    if suffix == Frame.KEY:
        return frame_of_image(obj, seq=seq)
    if suffix == CmdVel.KEY:
        return cmd_vel_of_twist(obj, seq=seq, stamp_ns_=stamp_ns_)
    if suffix == Estimate.KEY:
        return estimate_of_ros(obj)
    if suffix == Params.KEY:
        return params_of_ros(obj)
    if suffix == Report.KEY:
        try:
            return report_of_ros(obj)
        except (json.JSONDecodeError, TypeError) as e:  # a json field that is no report
            raise MessageError(f"{Report.KEY}: field 'json' is not a report ({e})") from None
    raise TypeError(f"{suffix} cannot be rebuilt from its ROS 2 message")


#: Contract keys :func:`of_ros` rebuilds whole from their ROS 2 message.
REBUILT = (Frame.KEY, CmdVel.KEY, Estimate.KEY, Params.KEY, Report.KEY)


def schema_problem(typename: str, text: str) -> str | None:
    """Why the ``ros2msg`` schema ``text`` of ``typename`` (as recorded in a file) does not
    describe the same messages as ours, or None when it does.

    Field names, types and order count; comments, constants' layout and formatting do not, so
    a schema written by ``ros2 bag`` from the installed ``.msg`` files matches too.
    """
    try:
        theirs = get_types_from_msg(text, typename)
    except Exception as e:  # noqa: BLE001 - rosbags' parser raises its own error kinds
        return f"its schema does not parse as ros2msg ({type(e).__name__}: {e})"
    ours = typestore().fielddefs
    for name, (_, fields) in theirs.items():
        if name in ours and ours[name][1] != fields:
            theirs_, ours_ = _field_list(fields), _field_list(ours[name][1])
            if theirs_ == ours_:
                return f"the field types of its {name} differ from this vistrack's"
            return f"its {name} has the fields ({theirs_}), this vistrack's ({ours_})"
    if typename not in theirs:
        return f"its schema does not define {typename}"
    return None


def _field_list(fields: Any) -> str:
    return ", ".join(f"{name}" for name, _ in fields)


# -- overlays: an estimate drawn over its frame -------------------------------------------

def _color(r: float, g: float, b: float, a: float = 1.0) -> Any:
    return _type("std_msgs/msg/ColorRGBA")(r=r, g=g, b=b, a=a)


def _point(x: float, y: float) -> Any:
    return _type("geometry_msgs/msg/Point")(x=float(x), y=float(y), z=0.0)


#: Colours of the overlays (RGBA, 0..1): features green, centroid orange.
FEATURE_COLOR = (0.2, 1.0, 0.2, 1.0)
CENTROID_COLOR = (1.0, 0.5, 0.0, 1.0)
#: Diameter of a feature's dot, px.
FEATURE_DOT_PX = 3.0


def _marker(msg: Estimate, frame_id: str, *, ns: str, kind: int, position: Any, scale: float,
            color: tuple[float, ...], points: list[Any]) -> Any:
    duration = _type("builtin_interfaces/msg/Duration")
    return _type(IMAGE_MARKER)(
        header=header(msg.stamp_ns, frame_id), ns=ns, id=0, type=kind, action=0,
        position=position, scale=scale, outline_color=_color(*color), filled=0,
        fill_color=_color(0.0, 0.0, 0.0, 0.0), lifetime=duration(sec=0, nanosec=0),
        points=points, outline_colors=[])


def feature_marker(msg: Estimate, frame_id: str = FRAME_ID) -> Any:
    """``ImageMarker`` ``POINTS``: the tracked features of an estimate, in the pixel
    coordinates of its frame (pixel centres at integers, as OpenCV and ROS's image tools
    draw), stamped with the frame's ``stamp_ns`` so a viewer can match it to its image."""
    return _marker(msg, frame_id, ns="features", kind=4, position=_point(0.0, 0.0),
                   scale=FEATURE_DOT_PX, color=FEATURE_COLOR,
                   points=[_point(x, y) for _, x, y in msg.features])


def centroid_marker(msg: Estimate, frame_id: str = FRAME_ID) -> Any:
    """``ImageMarker`` ``CIRCLE`` at the centroid (xc, yc) of Eq. 2, of radius the mean
    absolute deviation of the features about it, (xe + ye) / (2 NPI) px (at least 1 px);
    transparent when the estimate is not valid (too few features: nothing to act on)."""
    npi = max(msg.npi, 1)
    radius = max((msg.xe + msg.ye) / (2.0 * npi), 1.0)
    valid = getattr(msg, "valid", msg.npi > 0)
    color = CENTROID_COLOR if valid else (0.0, 0.0, 0.0, 0.0)
    return _marker(msg, frame_id, ns="centroid", kind=0, position=_point(msg.xc, msg.yc),
                   scale=radius, color=color, points=[])


#: Derived topic suffix (under ``vistrack/<robot>/``) -> how it is drawn from an estimate.
OVERLAYS = {"camera/features": feature_marker, "camera/centroid": centroid_marker}


# -- ROS 2 cameras -> 8-bit grey ---------------------------------------------------------------

#: ``sensor_msgs/msg/Image`` encodings a ROS 2 camera source takes: bytes a pixel and the
#: OpenCV conversion to grey (None: already one channel, or one of :data:`_BYTE_OF_PIXEL`'s).
#: Raw Bayer, as machine-vision cameras send it, is demosaiced by OpenCV, whose pattern names
#: are those of the second row (ROS's ``bayer_rggb8`` is OpenCV's BayerBG, as ``cv_bridge``
#: maps them). YUV 4:2:2 (USB cameras' YUYV, ``usb_cam``'s ``yuv422_yuy2`` or ``yuyv``, and
#: UYVY, ``yuv422`` or ``uyvy``, the names ``sensor_msgs`` gives the same layouts) is its luma
#: byte: grey as the camera made it. The generic ``8UC3`` and ``8UC4`` are OpenCV's BGR and
#: BGRA, as ``cv_bridge`` reads them.
IMAGE_ENCODINGS: dict[str, tuple[int, int | None]] = {
    "mono8": (1, None), "8UC1": (1, None), "mono16": (2, None), "16UC1": (2, None),
    "rgb8": (3, cv2.COLOR_RGB2GRAY), "bgr8": (3, cv2.COLOR_BGR2GRAY),
    "8UC3": (3, cv2.COLOR_BGR2GRAY),
    "rgba8": (4, cv2.COLOR_RGBA2GRAY), "bgra8": (4, cv2.COLOR_BGRA2GRAY),
    "8UC4": (4, cv2.COLOR_BGRA2GRAY),
    "bayer_rggb8": (1, cv2.COLOR_BayerBG2GRAY), "bayer_bggr8": (1, cv2.COLOR_BayerRG2GRAY),
    "bayer_gbrg8": (1, cv2.COLOR_BayerGR2GRAY), "bayer_grbg8": (1, cv2.COLOR_BayerGB2GRAY),
    "yuv422_yuy2": (2, None), "yuyv": (2, None), "yuv422": (2, None), "uyvy": (2, None),
}
#: The two-byte encodings that carry the grey level in one byte of each pixel's two: which.
_BYTE_OF_PIXEL = {"yuv422_yuy2": 0, "yuyv": 0,  # Y0 U Y1 V
                  "yuv422": 1, "uyvy": 1}  # U Y0 V Y1


def grey_of_image(obj: Any, grey: Callable[[np.ndarray], np.ndarray] | None = None
                  ) -> np.ndarray:
    """The 8-bit grey image, shape (height, width) uint8, of a ``sensor_msgs/msg/Image`` in
    one of :data:`IMAGE_ENCODINGS`: colour (raw Bayer demosaiced first) through OpenCV's luma
    weights, YUV 4:2:2 by its luma byte, 16-bit (either byte order as ``is_bigendian`` says)
    by ``grey`` (a stream's :class:`~vistrack.common.vision.preprocess.Grey`, which scales
    by the depth of the camera's samples), else by its high byte (value // 256). Row padding
    (``step`` > width * bytes a pixel) is dropped.

    Raises
    ------
    ValueError
        For another encoding, an empty image, a ``step`` shorter than a row, or ``data`` whose
        size is not ``step * height``; the text names the value and what was expected.
    """
    encoding = str(obj.encoding)
    if encoding not in IMAGE_ENCODINGS:
        raise ValueError(f"image encoding {encoding!r} is not supported: allowed "
                         f"{', '.join(IMAGE_ENCODINGS)}")
    channels, conversion = IMAGE_ENCODINGS[encoding]
    width, height, step = int(obj.width), int(obj.height), int(obj.step)
    if width < 1 or height < 1:
        raise ValueError(f"image is {width}x{height}: expected at least 1x1")
    row = width * channels
    data = np.asarray(obj.data, np.uint8).reshape(-1)
    if step < row or data.size != step * height:
        raise ValueError(f"{encoding} image data is {data.size} bytes: expected step * height "
                         f"= {step} * {height} with step >= {row} (step >= width * "
                         f"bytes a pixel = {width} * {channels})")
    rows = data.reshape(height, step)[:, :row]
    if channels == 2:
        pixels = rows.reshape(height, width, 2)
        if encoding in _BYTE_OF_PIXEL:
            return np.ascontiguousarray(pixels[:, :, _BYTE_OF_PIXEL[encoding]])
        samples = np.ascontiguousarray(pixels).view(">u2" if obj.is_bigendian else "<u2")
        return _grey_of(samples.reshape(height, width).astype(np.uint16), grey)
    if conversion is None:
        return np.ascontiguousarray(rows)
    return cv2.cvtColor(np.ascontiguousarray(rows).reshape(height, width, channels),
                        conversion)


def grey_of_compressed(obj: Any, grey: Callable[[np.ndarray], np.ndarray] | None = None
                       ) -> np.ndarray:
    """The 8-bit grey image of a ``sensor_msgs/msg/CompressedImage`` (JPEG, PNG, any format
    OpenCV's ``imdecode`` reads), made grey exactly as the file camera makes an image file
    grey (``grey``, a stream's ``vision.preprocess.Grey``; else ``to_gray``). ValueError if it
    does not decode, or its header says more pixels than an image may have
    (:mod:`.imagelimit`: a few KB can claim 30000x30000 px, which OpenCV then allocated)."""
    data = np.asarray(obj.data, np.uint8).reshape(-1)
    what = f"compressed image ({obj.format or 'no format'}, {data.size} bytes)"
    image = imagelimit.decode(what, lambda: cv2.imdecode(data, cv2.IMREAD_UNCHANGED)) \
        if data.size else None
    if image is None:
        raise ValueError(f"{what} does not decode")
    return _grey_of(image, grey)


def _grey_of(image: np.ndarray, grey: Callable[[np.ndarray], np.ndarray] | None) -> np.ndarray:
    """``grey(image)``, else ``vision.preprocess.to_gray(image)`` (16-bit: the high byte)."""
    if grey is not None:
        return grey(image)
    # here, not at the top: the vision package loads numba, which MCAP tools need not pay for
    from .vision.preprocess import to_gray
    return to_gray(image)


def frame_of_camera(obj: Any, *, seq: int,
                    grey: Callable[[np.ndarray], np.ndarray] | None = None,
                    resize: Callable[[np.ndarray], np.ndarray] | None = None) -> Frame:
    """The ``camera/frame`` of an ``Image`` or ``CompressedImage`` from a ROS 2 camera (see
    :func:`grey_of_image`, :func:`grey_of_compressed`; ``grey``: the camera's
    ``vision.preprocess.Grey``), ``resize`` d if given (before the size check: a 5472 px
    wide camera with ``--size`` was refused as wider than a ``camera/frame`` carries),
    stamped with the header's stamp.

    Raises
    ------
    ValueError
        For an image that cannot be converted, or one larger than a ``camera/frame`` carries.
    """
    image = (grey_of_compressed(obj, grey) if obj.__msgtype__ == COMPRESSED_IMAGE
             else grey_of_image(obj, grey))
    if resize is not None:
        image = resize(image)
    try:
        return Frame.from_image(image, seq=seq, stamp_ns=stamp_ns(obj.header))
    except MessageError as e:
        if image.ndim == 2 and max(image.shape) > MAX_SIDE:
            raise ValueError(f"{e} (a camera/frame carries at most {MAX_SIDE} px a side: "
                             "give --size WxH to scale the images)") from None
        raise ValueError(str(e)) from None
