"""msgpack encoding and validated decoding of every message of the key contract.

Wire format (ARCHITECTURE.md, "CONTRACT: keys and messages"): each payload is a msgpack map with
string keys, ``"v": 1`` first, then ``"seq"`` and ``"stamp_ns"``, then the message's own fields.
Array data travel as msgpack ``bin``:

* ``data``: the 8-bit grey image, ``width * height`` bytes, row-major;
* ``candidates``: int16 little-endian ``x, y`` pairs (4 bytes per candidate);
* ``strength``: float32 little-endian, one per candidate.

Readers ignore unknown fields. Anything else that is wrong (not msgpack, not a map, wrong
version, missing field, wrong type -- ``bool`` is not an int --, non-finite number, size
mismatch, over-long field) raises :class:`MessageError`, whose text names the field. Decoding
never raises anything else, whatever the bytes, so a service can count and log the rejection
and go on. The same checks run in each message's constructor, so a producer cannot encode a
message its consumers would reject.

The messages of the hot path (``camera/frame``, ``preprocessing/frame``, ``motion/estimate``)
are decoded first by msgspec, which parses and type-checks the map in C against a
:class:`msgspec.Struct` holding the same rules (types, ranges, finiteness), with the images
taken as zero-copy views of the payload (candidates and strengths are copied: aligned, as
numba wants them); the cross-field checks follow in numpy. Only a
payload msgspec refuses goes through the checks above, which name the field and the allowed
range: so the accepted messages and the errors are exactly those of the checks, at C speed for
valid messages. One difference: msgspec skips a field it does not know without reading its
name, so an unknown field whose name is not UTF-8 is ignored, as unknown fields are, where
msgpack refused the whole payload. Encoding goes through msgspec's encoder, which writes the
same bytes as msgpack.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import sys
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Annotated, Any, ClassVar, Literal, TypeVar

import msgpack
import msgspec
import numpy as np

from vistrack.common.keys import key_suffix
from vistrack.common.params import FACTORS, MIN_VALID_NPI, ParamError, TrackerParams

SCHEMA_VERSION = 1

#: Largest frame side in pixels a reader accepts.
MAX_SIDE = 4096
MAX_PIXELS = MAX_SIDE * MAX_SIDE
MAX_TEXT = 4096  # longest free-text field (``reason``), characters
#: Largest ``params_id`` a reader accepts: exact in JSON (and float64), and far from msgpack's
#: 2**64 limit, so that "one above the largest seen" can always be encoded. A publisher at
#: the limit has no newer id to give (see ``next_params_id``).
MAX_PARAMS_ID = 2**53 - 1

# Explicit msgpack limits: a hostile or corrupt length prefix must not make the reader
# allocate more than a full-size frame's worth of candidates (4 bytes per pixel).
_UNPACK_LIMITS = {
    "max_bin_len": MAX_PIXELS * 4,
    "max_str_len": 1 << 20,
    "max_array_len": 1 << 20,
    "max_map_len": 1 << 16,
    "max_ext_len": 0,
}
# Everything msgpack.unpackb raises on bad input: ValueError covers ExtraData, FormatError,
# StackError, UnicodeDecodeError and the limit checks; TypeError covers unhashable map keys.
_UNPACK_ERRORS = (ValueError, TypeError, msgpack.UnpackException)


class MessageError(ValueError):
    """A payload or a message field is invalid.

    Parameters
    ----------
    message : what was wrong, naming the field.
    field : name of the offending top-level field, or None when the payload as a whole is bad
        (not msgpack, not a map).
    """

    def __init__(self, message: str, *, field: str | None = None) -> None:
        super().__init__(message)
        self.field = field


# -- field checks ---------------------------------------------------------------------------
# A check takes (message key, field name, value) and returns the normalised value (plain
# Python int/float/bool/str, so msgpack can encode what numpy code produced) or raises.

_Check = Callable[[str, str, Any], Any]


def _short(value: Any) -> str:
    """A bounded description of a bad value for error texts (payloads can be megabytes)."""
    if isinstance(value, (bytes, bytearray, memoryview)):
        return f"<{len(value)} bytes>"
    if isinstance(value, np.ndarray):
        return f"<array shape={value.shape} dtype={value.dtype}>"
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _error(where: str, name: str, problem: str, value: Any = dataclasses.MISSING) -> MessageError:
    got = "" if value is dataclasses.MISSING else f", got {_short(value)}"
    return MessageError(f"{where}: field {name!r} {problem}{got}", field=name.split("[")[0])


def _is_bool(value: Any) -> bool:
    return isinstance(value, (bool, np.bool_))


def _int(lo: int | None = 0, hi: int | None = None) -> _Check:
    def check(where: str, name: str, value: Any) -> int:
        if type(value) is not int:  # exact int (what msgpack gives) skips the abc checks
            if _is_bool(value) or not isinstance(value, numbers.Integral):
                raise _error(where, name, "must be an integer", value)
            value = int(value)
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            allowed = f">= {lo}" if hi is None else f"in {lo}..{hi}"
            raise _error(where, name, f"must be {allowed}", value)
        return value
    return check


def _float(lo: float | None = None, *, positive: bool = False) -> _Check:
    def check(where: str, name: str, value: Any) -> float:
        if type(value) is not float:  # exact float (what msgpack gives) skips the abc checks
            if _is_bool(value) or not isinstance(value, numbers.Real):
                raise _error(where, name, "must be a number", value)
            try:
                value = float(value)
            except OverflowError:
                raise _error(where, name, "is too large for a float", value) from None
        if not math.isfinite(value):
            raise _error(where, name, "must be finite", value)
        if positive and value <= 0:
            raise _error(where, name, "must be > 0", value)
        if lo is not None and value < lo:
            raise _error(where, name, f"must be >= {lo}", value)
        return value
    return check


def _bool(where: str, name: str, value: Any) -> bool:
    if not _is_bool(value):
        raise _error(where, name, "must be true or false", value)
    return bool(value)


def _str(choices: tuple[str, ...] | None = None, max_len: int = MAX_TEXT) -> _Check:
    def check(where: str, name: str, value: Any) -> str:
        if not isinstance(value, str):
            raise _error(where, name, "must be a string", value)
        if choices is not None and value not in choices:
            raise _error(where, name, f"must be one of {', '.join(map(repr, choices))}", value)
        if len(value) > max_len:
            raise _error(where, name, f"is longer than {max_len} characters", value)
        return value
    return check


def _list(where: str, name: str, value: Any) -> list:
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if not isinstance(value, (list, tuple)):
        raise _error(where, name, "must be a list", value)
    return list(value)


def _map(where: str, name: str, value: Any) -> dict:
    if not isinstance(value, Mapping):
        raise _error(where, name, "must be a map", value)
    for k in value:
        if not isinstance(k, str):
            raise _error(where, name, "must have string keys", k)
    return dict(value)


def _finite_float(value: Any) -> float | None:
    """``value`` as a finite float, or None if it is not a finite real number."""
    if _is_bool(value) or not isinstance(value, numbers.Real):
        return None
    try:
        value = float(value)
    except OverflowError:
        return None
    return value if math.isfinite(value) else None


def _features(where: str, name: str, value: Any) -> list[list]:
    """``[[id, x, y], ...]`` with an integer id >= 0 and finite pixel coordinates."""
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if not isinstance(value, (list, tuple)):
        raise _error(where, name, "must be a list of [id, x, y]", value)
    isfinite = math.isfinite
    for item in value:  # fast path: exactly what msgpack and Estimate.features() produce
        if type(item) is not list or len(item) != 3:
            break
        fid, x, y = item
        if not (type(fid) is int and fid >= 0 and type(x) is float and type(y) is float
                and isfinite(x) and isfinite(y)):
            break
    else:
        return value if type(value) is list else list(value)
    out = []
    for i, item in enumerate(value):
        if not isinstance(item, (list, tuple)) or len(item) != 3:
            raise _error(where, name, f"item {i} must be [id, x, y]", item)
        fid, x, y = item  # the slow path: numpy scalars or tuples, or an error to name
        if _is_bool(fid) or not isinstance(fid, numbers.Integral):
            raise _error(where, name, f"item {i}: id must be an integer", fid)
        fid = int(fid)
        x, y = _finite_float(x), _finite_float(y)
        if x is None or y is None:
            raise _error(where, name, f"item {i}: x, y must be finite numbers", item)
        if fid < 0:
            raise _error(where, name, f"item {i}: id must be >= 0", fid)
        out.append([fid, x, y])
    return out


# -- wire helpers -----------------------------------------------------------------------------

def _np_default(obj: Any) -> Any:
    """msgpack ``default`` hook: numpy scalars and arrays inside maps (reports, status)."""
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"cannot encode {type(obj).__name__} in a message")


_ENCODER = msgspec.msgpack.Encoder(enc_hook=_np_default)


def pack(values: Mapping[str, Any]) -> bytes:
    """Encode a map as a versioned payload (``"v": 1`` first), numpy values allowed."""
    try:
        return _ENCODER.encode({"v": SCHEMA_VERSION, **values})
    except (TypeError, OverflowError):
        # what msgspec cannot write (a dict with non-str keys in a report, an int beyond
        # 64 bits) raises as msgpack does, with msgpack's own message
        return msgpack.packb({"v": SCHEMA_VERSION, **values}, use_bin_type=True,
                             default=_np_default)


def unpack(payload: bytes | bytearray | memoryview) -> dict[str, Any]:
    """Decode a payload into a map and check its schema version.

    Raises
    ------
    MessageError
        If the payload is not msgpack within the size limits, not a map, or ``v`` is not 1.
    """
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        raise MessageError(f"payload must be bytes, got {type(payload).__name__}")
    try:
        obj = msgpack.unpackb(payload, raw=False, strict_map_key=True, **_UNPACK_LIMITS)
    except _UNPACK_ERRORS as err:
        raise _key_error(payload) or MessageError(
            f"payload is not valid msgpack ({len(payload)} bytes): {type(err).__name__} "
            f"{err}") from None
    if not isinstance(obj, dict):
        raise MessageError(f"payload must be a msgpack map, got {type(obj).__name__}")
    if "v" not in obj:
        raise MessageError("payload: missing field 'v' (schema version)", field="v")
    version = obj["v"]
    if type(version) is not int or version != SCHEMA_VERSION:
        raise MessageError(f"payload: field 'v' is schema version {_short(version)}, this "
                           f"reader supports {SCHEMA_VERSION}", field="v")
    return obj


#: msgpack's types by their Python types as msgpack decodes them (arrays as tuples, below).
_MSGPACK_TYPES = {bool: "bool", int: "int", float: "float", type(None): "nil", tuple: "array"}


def _key_error(payload: bytes | bytearray | memoryview) -> MessageError | None:
    """Why msgpack refused ``payload`` where the reason is a map key that is not a string
    (the contract's maps have string keys: ``strict_map_key``), naming the key, its type and
    the top-level field it is in; None when the payload is not valid msgpack anyway.

    msgpack says only ``int is not allowed for map key when strict_map_key=True``, which
    :func:`unpack` reported as "not valid msgpack", and valid msgpack it is. Run on a refused
    payload only: a second decode, without the key rule (arrays as tuples, so that an array
    key is hashable), tells the two apart without reading msgpack's wording.
    """
    try:
        obj = msgpack.unpackb(payload, raw=False, strict_map_key=False, use_list=False,
                              **_UNPACK_LIMITS)
    except TypeError:  # unhashable, so not a string: a map, or an array holding one
        return MessageError("payload: map keys must be strings, got a key holding a map")
    except _UNPACK_ERRORS:
        return None
    found = _non_string_key(obj)
    if found is None:  # not the keys after all (cannot happen): the decoder's own words
        return None
    key, field = found
    kind = _MSGPACK_TYPES.get(type(key), type(key).__name__)
    shown = list(key) if isinstance(key, tuple) else key  # an array, as msgpack has it
    where = "" if field is None else f" in field {field!r}"
    return MessageError(f"payload: map keys must be strings, got {kind} key {_short(shown)}"
                        f"{where}", field=field)


def _non_string_key(obj: Any) -> tuple[Any, str | None] | None:
    """The first map key in ``obj`` (decoded msgpack) that is neither str nor bytes, in the
    order msgpack reads them, with the top-level field it lies in (None: a top-level key)."""
    # depth first with a stack of generators, not recursion: msgpack nests deeper than
    # Python's recursion limit
    stack = [_entries(obj, None, top=True)]
    while stack:
        entry = next(stack[-1], None)
        if entry is None:
            stack.pop()
            continue
        is_key, key, value, field = entry
        if is_key and not isinstance(key, (str, bytes)):
            return key, field
        if isinstance(value, (dict, tuple)):
            stack.append(_entries(value, field, top=False))
    return None


def _entries(value: Any, field: str | None, *, top: bool
             ) -> Iterator[tuple[bool, Any, Any, str | None]]:
    """``(is a map entry, key, value, field)`` of a map's entries or an array's items; the
    entries of the top-level map are in their own field."""
    if isinstance(value, dict):
        for k, v in value.items():
            yield True, k, v, (k if top and isinstance(k, str) else field)
    else:
        for v in value:
            yield False, None, v, field


def peek_seq(payload: bytes | bytearray | memoryview) -> int | None:
    """The ``seq`` field of a payload without decoding the rest, or None if there is none.

    Cheap for our own messages, which put ``v``, ``seq`` and ``stamp_ns`` first: only the first
    bytes are parsed; other key orders fall back to skipping values one by one. Never raises.
    """
    return peek_int(payload, "seq")


class _Peek(msgspec.Struct):
    """The fields :func:`peek_int` reads fast: msgspec skips every other field (a bin by its
    length, without reading it)."""

    seq: Any = None
    stamp_ns: Any = None


_PEEK = msgspec.msgpack.Decoder(_Peek)


def peek_int(payload: bytes | bytearray | memoryview, name: str) -> int | None:
    """The non-negative integer field ``name`` of a payload map, without decoding the rest.

    Returns None if the payload is not a map, has no such field, or it is not an int >= 0.
    Never raises. See :func:`peek_seq`.

    ``seq`` and ``stamp_ns`` are read by msgspec (0.4 us for a 64 KiB frame, against 3 to 5 us
    for msgpack's incremental unpacker, on every message's arrival); a payload msgspec does
    not take (not a map of string keys, malformed past the field) goes the slow way below,
    which gives the same answer.
    """
    if name in ("seq", "stamp_ns"):
        try:
            value = getattr(_PEEK.decode(payload), name)
        except (msgspec.DecodeError, TypeError, RecursionError):  # maps nested 1000 deep
            pass
        else:
            return value if type(value) is int and value >= 0 else None
    return _peek_int_unpacker(payload, name)


def _peek_int_unpacker(payload: bytes | bytearray | memoryview, name: str) -> int | None:
    """:func:`peek_int` with msgpack's incremental unpacker: any field, any payload."""
    view = memoryview(payload)
    for chunk in (view[:64], view):
        unpacker = msgpack.Unpacker(raw=False, strict_map_key=False, **_UNPACK_LIMITS)
        try:
            unpacker.feed(chunk)
            for _ in range(unpacker.read_map_header()):
                if unpacker.unpack() == name:
                    value = unpacker.unpack()
                    return value if type(value) is int and value >= 0 else None
                unpacker.skip()
            return None
        except msgpack.OutOfData:
            if len(chunk) == len(view):
                return None
        except _UNPACK_ERRORS:
            return None
    return None


def _bin_of(array: np.ndarray, dtype: str) -> memoryview:
    """Zero-copy bytes view of ``array`` as ``dtype`` (copies only if layout/dtype differ)."""
    flat = np.ascontiguousarray(array, dtype=dtype).reshape(-1)
    return flat.view(np.uint8).data


def _bin_field(where: str, name: str, m: Mapping[str, Any]) -> bytes:
    value = m[name]
    if not isinstance(value, bytes):
        raise _error(where, name, "must be bin (bytes)", value)
    return value


# -- messages -------------------------------------------------------------------------------

_M = TypeVar("_M", bound="_Message")
_FIELD_NAMES: dict[type, tuple[str, ...]] = {}  # message class -> its field names, in order


class _Message:
    """Shared encode/decode/validation. Subclasses are frozen keyword-only dataclasses whose
    first two fields are ``seq`` and ``stamp_ns``; ``_CHECKS`` validates the scalar fields,
    ``_validate`` the arrays and cross-field rules."""

    KEY: ClassVar[str]
    _CHECKS: ClassVar[dict[str, _Check]]

    def __post_init__(self) -> None:
        for name, check in self._CHECKS.items():
            object.__setattr__(self, name, check(self.KEY, name, getattr(self, name)))
        self._validate()

    def _validate(self) -> None:
        """Array and cross-field checks (none by default)."""

    def _wire_fields(self) -> dict[str, Any]:
        """Field name -> value as sent; array fields override this."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}  # type: ignore[arg-type]

    def encode(self) -> bytes:
        """The msgpack payload: a map with ``"v": 1`` and every field."""
        return pack(self._wire_fields())

    #: The msgspec decoder of the hot-path messages (see the module notes), else None.
    _FAST: ClassVar[msgspec.msgpack.Decoder | None] = None

    @classmethod
    def decode(cls: type[_M], payload: bytes | bytearray | memoryview) -> _M:
        """Parse and validate a payload.

        Raises
        ------
        MessageError
            For any invalid payload (and nothing else), naming the field.
        """
        if cls._FAST is not None and isinstance(payload, (bytes, bytearray, memoryview)):
            try:
                values = cls._from_wire(cls._FAST.decode(payload))
            except (msgspec.DecodeError, RecursionError):  # ValidationError too: the checks
                values = None  # below name it; nesting beyond msgspec's stack, unpack's limit
            if values is not None:
                msg = object.__new__(cls)  # valid: the checks would change nothing
                msg.__dict__.update(values)
                return msg
        return cls._from_map(unpack(payload))

    @classmethod
    def _from_wire(cls, wire: Any) -> dict[str, Any] | None:
        """Every field's value from a message msgspec decoded, arrays made, or None when a
        cross-field check fails (the full checks then name it)."""
        return {name: getattr(wire, name) for name in cls._field_names()}

    @classmethod
    def _field_names(cls) -> tuple[str, ...]:
        names = _FIELD_NAMES.get(cls)
        if names is None:
            names = _FIELD_NAMES[cls] = tuple(
                f.name for f in dataclasses.fields(cls))  # type: ignore[arg-type]
        return names

    @classmethod
    def _from_map(cls: type[_M], m: dict[str, Any]) -> _M:
        values = {}
        for f in dataclasses.fields(cls):  # type: ignore[arg-type]
            if f.name not in m:
                raise MessageError(f"{cls.KEY}: missing field {f.name!r}", field=f.name)
            values[f.name] = m[f.name]
        return cls(**cls._arrays_from_wire(values))

    @classmethod
    def _arrays_from_wire(cls, values: dict[str, Any]) -> dict[str, Any]:
        """Turn bin fields into arrays (after checking their sizes); identity by default."""
        return values


_SEQ = {"seq": _int(), "stamp_ns": _int()}
_PARAMS_ID = _int(0, MAX_PARAMS_ID)
_SIDE = _int(1, MAX_SIDE)
_IMAGE = {"width": _SIDE, "height": _SIDE, "encoding": _str(("mono8",))}


def _check_image(where: str, msg: Any) -> None:
    data = msg.data
    if not isinstance(data, np.ndarray) or data.dtype != np.uint8:
        raise _error(where, "data", "must be a uint8 array", data)
    if data.shape != (msg.height, msg.width):
        raise _error(where, "data", f"must have shape (height, width) = "
                                    f"({msg.height}, {msg.width})", data)


def _image_from_wire(where: str, values: dict[str, Any]) -> None:
    width = _SIDE(where, "width", values["width"])
    height = _SIDE(where, "height", values["height"])
    data = _bin_field(where, "data", values)
    if len(data) != width * height:
        raise _error(where, "data", f"must be width*height = {width * height} bytes", data)
    values["data"] = np.frombuffer(data, dtype=np.uint8).reshape(height, width)


# -- msgspec types of the hot-path messages: the checks above, as msgspec constraints -------

_BIG = sys.float_info.max  # NaN and the infinities fail -max <= x <= max: "must be finite"
_Count = Annotated[int, msgspec.Meta(ge=0)]
_Finite = Annotated[float, msgspec.Meta(ge=-_BIG, le=_BIG)]
_FiniteNonNeg = Annotated[float, msgspec.Meta(ge=0.0, le=_BIG)]
_FinitePos = Annotated[float, msgspec.Meta(gt=0.0, le=_BIG)]
_Side = Annotated[int, msgspec.Meta(ge=1, le=MAX_SIDE)]
_ParamsId = Annotated[int, msgspec.Meta(ge=0, le=MAX_PARAMS_ID)]


class _FrameWire(msgspec.Struct, kw_only=True):
    v: Literal[1]
    seq: _Count
    stamp_ns: _Count
    width: _Side
    height: _Side
    encoding: Literal["mono8"]
    data: memoryview  # a view of the payload, not a copy
    cuts: _Count = 0  # absent: an older publisher's


class _PreFrameWire(_FrameWire, kw_only=True):
    candidates: memoryview
    strength: memoryview
    params_id: _ParamsId
    deferred: bool = False  # absent: an older publisher's


class _EstimateWire(msgspec.Struct):
    v: Literal[1]
    seq: _Count
    stamp_ns: _Count
    npi: _Count
    xc: _Finite
    yc: _Finite
    xe: _FiniteNonNeg
    ye: _FiniteNonNeg
    dx: _Finite
    dy: _Finite
    scale: _FinitePos
    t_ms: _FiniteNonNeg
    first: bool
    features: list[tuple[_Count, _Finite, _Finite]]
    params_id: _ParamsId
    valid: bool | msgspec.UnsetType = msgspec.UNSET  # absent: an older publisher's
    width: _Side | msgspec.UnsetType = msgspec.UNSET  # absent: an older publisher's
    height: _Side | msgspec.UnsetType = msgspec.UNSET
    cuts: _Count = 0  # absent: 0 (no cut yet, or an older publisher's)


def _image_view(wire: Any) -> np.ndarray | None:
    """The (height, width) uint8 view of a decoded image's data, or None if its size is off."""
    if len(wire.data) != wire.width * wire.height:
        return None
    image = np.frombuffer(wire.data, np.uint8).reshape(wire.height, wire.width)
    # a view of bytes (what Zenoh hands over) is read-only already: a call less on the
    # frame's path, which in a service at 30 fps runs from cold caches
    return image if wire.data.readonly else _read_only(image)


def _read_only(array: np.ndarray) -> np.ndarray:
    """``array`` made read-only: a view of a payload that may be a bytearray must not write
    into it."""
    array.flags.writeable = False
    return array


@dataclass(frozen=True, kw_only=True, eq=False)
class Frame(_Message):
    """A camera image (``camera/frame``).

    Parameters
    ----------
    seq : per-publisher sequence number, increasing.
    stamp_ns : capture time, ns since the Unix epoch.
    width, height : image size in px, 1..4096.
    data : (height, width) uint8 array, 8-bit grey, row-major on the wire. Decoded frames hold
        a read-only view of the payload.
    encoding : ``"mono8"`` (the only encoding).
    cuts : how many cuts the source has made before this frame, >= 0: a frame whose
        ``cuts`` differs from the frame before it does not follow that frame in the scene
        (the first frame of a ``--loop`` source's next pass, a simulator's scenario started
        again). Readers that track across frames start again there. A count, not a flag, so
        that a cut frame dropped on the way still shows in the frame after it. Absent (a
        publisher that predates the field): 0.
    """

    KEY: ClassVar[str] = "camera/frame"
    _CHECKS: ClassVar[dict[str, _Check]] = {**_SEQ, **_IMAGE, "cuts": _int()}

    seq: int
    stamp_ns: int
    width: int
    height: int
    encoding: str = "mono8"
    data: np.ndarray
    cuts: int = 0

    @classmethod
    def from_image(cls, image: np.ndarray, *, seq: int, stamp_ns: int,
                   cuts: int = 0) -> Frame:
        """A frame of a (height, width) uint8 image."""
        if not isinstance(image, np.ndarray) or image.ndim != 2:
            raise _error(cls.KEY, "data", "must be a 2-D (height, width) array", image)
        return cls(seq=seq, stamp_ns=stamp_ns, width=image.shape[1], height=image.shape[0],
                   data=image, cuts=cuts)

    def _validate(self) -> None:
        _check_image(self.KEY, self)

    def _wire_fields(self) -> dict[str, Any]:
        return {"seq": self.seq, "stamp_ns": self.stamp_ns, "width": self.width,
                "height": self.height, "encoding": self.encoding,
                "data": _bin_of(self.data, "u1"), "cuts": self.cuts}

    @classmethod
    def _from_map(cls, m: dict[str, Any]) -> Frame:
        return super()._from_map(_cuts_default(m))

    @classmethod
    def _arrays_from_wire(cls, values: dict[str, Any]) -> dict[str, Any]:
        _image_from_wire(cls.KEY, values)
        return values

    @classmethod
    def _from_wire(cls, wire: Any) -> dict[str, Any] | None:
        data = _image_view(wire)
        if data is None:
            return None
        return {"seq": wire.seq, "stamp_ns": wire.stamp_ns, "width": wire.width,
                "height": wire.height, "encoding": wire.encoding, "data": data,
                "cuts": wire.cuts}


def _cuts_default(m: dict[str, Any]) -> dict[str, Any]:
    """A received map with ``cuts`` 0 where it is absent (a publisher that predates it)."""
    return m if "cuts" in m else {**m, "cuts": 0}


Frame._FAST = msgspec.msgpack.Decoder(_FrameWire)


@dataclass(frozen=True, kw_only=True, eq=False)
class PreFrame(_Message):
    """A pre-processed frame with its feature candidates (``preprocessing/frame``).

    Parameters
    ----------
    seq, stamp_ns, width, height, encoding : as in :class:`Frame` (``stamp_ns`` of the camera
        frame it derives from).
    data : (height, width) uint8 array, the filtered frame.
    candidates : (N, 2) int16 array of ``x, y`` pixel coordinates inside the image, strongest
        gradient first.
    strength : (N,) float32 array, finite gradient magnitude of each candidate.
    params_id : ``params_id`` of the parameters used (THRES_PERCENT).
    deferred : True when the candidates were not computed (``candidates`` and ``strength``
        are then empty) because motion-estimation said on ``motion/demand`` that it would not
        read them; a reader that needs them computes them from ``data``. Absent (a publisher
        that predates the field): False.
    cuts : the camera frame's :attr:`Frame.cuts`, passed on (absent: 0).
    """

    KEY: ClassVar[str] = "preprocessing/frame"
    _CHECKS: ClassVar[dict[str, _Check]] = {**_SEQ, **_IMAGE, "params_id": _PARAMS_ID,
                                            "deferred": _bool, "cuts": _int()}

    seq: int
    stamp_ns: int
    width: int
    height: int
    encoding: str = "mono8"
    data: np.ndarray
    candidates: np.ndarray
    strength: np.ndarray
    params_id: int
    deferred: bool = False
    cuts: int = 0

    def _validate(self) -> None:
        _check_image(self.KEY, self)
        cand = self.candidates
        if not isinstance(cand, np.ndarray) or cand.ndim != 2 or cand.shape[1] != 2 \
                or not np.issubdtype(cand.dtype, np.integer):
            raise _error(self.KEY, "candidates", "must be an (N, 2) integer array", cand)
        if cand.size and (cand.min() < 0 or cand[:, 0].max() >= self.width
                          or cand[:, 1].max() >= self.height):
            raise _error(self.KEY, "candidates", f"must lie inside the {self.width}x"
                                                 f"{self.height} image", cand)
        strength = self.strength
        if not isinstance(strength, np.ndarray) or strength.ndim != 1 \
                or strength.dtype.kind not in "fiu":
            raise _error(self.KEY, "strength", "must be an (N,) float array", strength)
        if len(strength) != len(cand):
            raise _error(self.KEY, "strength", f"must have one value per candidate "
                                               f"({len(cand)})", strength)
        if self.deferred and len(cand):
            raise _error(self.KEY, "candidates", "must be empty when deferred is true", cand)
        strength = strength.astype("<f4", copy=False)
        if not np.isfinite(strength).all():
            raise _error(self.KEY, "strength", "must be finite", strength)
        object.__setattr__(self, "candidates", cand.astype("<i2", copy=False))
        object.__setattr__(self, "strength", strength)

    def _wire_fields(self) -> dict[str, Any]:
        return {"seq": self.seq, "stamp_ns": self.stamp_ns, "width": self.width,
                "height": self.height, "encoding": self.encoding,
                "data": _bin_of(self.data, "u1"),
                "candidates": _bin_of(self.candidates, "<i2"),
                "strength": _bin_of(self.strength, "<f4"), "params_id": self.params_id,
                "deferred": self.deferred, "cuts": self.cuts}

    @classmethod
    def _from_map(cls, m: dict[str, Any]) -> PreFrame:
        if "deferred" not in m:  # an older publisher's: its candidates are all there
            m = {**m, "deferred": False}
        return super()._from_map(_cuts_default(m))

    @classmethod
    def _arrays_from_wire(cls, values: dict[str, Any]) -> dict[str, Any]:
        _image_from_wire(cls.KEY, values)
        cand = _bin_field(cls.KEY, "candidates", values)
        if len(cand) % 4:
            raise _error(cls.KEY, "candidates", "length must be a whole number of int16 x,y "
                                                "pairs (4 bytes each)", cand)
        strength = _bin_field(cls.KEY, "strength", values)
        if len(strength) % 4:
            raise _error(cls.KEY, "strength", "length must be a whole number of float32 "
                                              "values (4 bytes each)", strength)
        values["candidates"] = np.frombuffer(cand, dtype="<i2").reshape(-1, 2)
        values["strength"] = np.frombuffer(strength, dtype="<f4")
        return values

    @classmethod
    def _from_wire(cls, wire: Any) -> dict[str, Any] | None:
        data = _image_view(wire)
        n = len(wire.candidates)
        if data is None or n % 4 or len(wire.strength) != n or (wire.deferred and n):
            return None
        if not n:  # a deferred frame (most are): nothing to read, nor to check
            cand, strength = NO_CANDIDATES, NO_STRENGTH
        else:
            # copied (5 KiB each), not viewed: at their offsets in the payload they are
            # unaligned, and numba compiles (seconds, on the first frame) and runs other code
            # for unaligned arrays than for the aligned ones it was warmed up with
            cand = _read_only(np.frombuffer(wire.candidates, "<i2").reshape(-1, 2).copy())
            strength = _read_only(np.frombuffer(wire.strength, "<f4").copy())
            # as unsigned, a negative coordinate is >= 32768, beyond any side: one test a
            # coordinate, each over a 1-D view (a reduction along axis 0 cost 6 times more)
            xy = cand.view("<u2").reshape(-1)
            if xy[0::2].max() >= wire.width or xy[1::2].max() >= wire.height:
                return None
            if not np.isfinite(strength).all():
                return None
        return {"seq": wire.seq, "stamp_ns": wire.stamp_ns, "width": wire.width,
                "height": wire.height, "encoding": wire.encoding, "data": data,
                "candidates": cand, "strength": strength, "params_id": wire.params_id,
                "deferred": wire.deferred, "cuts": wire.cuts}


PreFrame._FAST = msgspec.msgpack.Decoder(_PreFrameWire)
#: The candidates and strengths of every frame that goes or comes without them (read-only,
#: shared by pre-processing, which sends them, and the decoder): two arrays fewer to make on a
#: deferred frame's path, ~75 us of a service's cold start on each frame at 30 fps
NO_CANDIDATES = _read_only(np.empty((0, 2), "<i2"))
NO_STRENGTH = _read_only(np.empty(0, "<f4"))


@dataclass(frozen=True, kw_only=True)
class Estimate(_Message):
    """The tracker's result for one frame (``motion/estimate``).

    Parameters
    ----------
    seq, stamp_ns : as in :class:`Frame` (``stamp_ns`` of the frame it derives from).
    npi : number of tracked features (NPI).
    xc, yc : centroid of the features, px (Eq. (2)).
    xe, ye : scatter, sum of absolute deviations from the centroid, px (Eq. (2)), >= 0.
    dx, dy : accumulated robust incremental motion, px.
    scale : accumulated ratio of the matched features' dispersion, > 0.
    t_ms : processing time of this frame, ms, >= 0.
    first : True for the first frame of a run (the t1 frame).
    features : ``[[id, x, y], ...]``, pixel coordinates in this frame; an id is kept while the
        feature is tracked.
    params_id : ``params_id`` of the parameters used.
    valid : False when NPI is below :data:`~vistrack.common.params.MIN_VALID_NPI`, too few
        features for a meaningful centroid and scatter: nothing should act on the estimate.
        Its numbers are finite all the same (see the README's CONTRACT). None (the default,
        and a message from a publisher that predates the field) derives it from ``npi``.
    width, height : the size of the frame the estimate is of, px (1..MAX_SIDE); None (the
        default, and a message from a publisher that predates the fields): not said. The
        controller normalises the centring error by ``width``.
    cuts : the frame's :attr:`Frame.cuts` (>= 0; absent on the wire: 0): a track's ``first``
        where it changed is the source starting again (a ``--loop`` file's next pass), not
        features lost in the scene.
    """

    KEY: ClassVar[str] = "motion/estimate"
    _CHECKS: ClassVar[dict[str, _Check]] = {
        **_SEQ, "npi": _int(), "xc": _float(), "yc": _float(), "xe": _float(0.0),
        "ye": _float(0.0), "dx": _float(), "dy": _float(), "scale": _float(positive=True),
        "t_ms": _float(0.0), "first": _bool, "features": _features, "params_id": _PARAMS_ID,
        "cuts": _int()}

    seq: int
    stamp_ns: int
    npi: int
    xc: float
    yc: float
    xe: float
    ye: float
    dx: float
    dy: float
    scale: float
    t_ms: float
    first: bool
    features: list = field(default_factory=list)
    params_id: int
    valid: bool | None = None
    width: int | None = None
    height: int | None = None
    cuts: int = 0

    def _validate(self) -> None:
        valid = self.npi >= MIN_VALID_NPI if self.valid is None else self.valid
        object.__setattr__(self, "valid", _bool(self.KEY, "valid", valid))
        for name in ("width", "height"):
            if getattr(self, name) is not None:
                object.__setattr__(self, name, _SIDE(self.KEY, name, getattr(self, name)))

    def _wire_fields(self) -> dict[str, Any]:
        values = super()._wire_fields()
        for name in ("width", "height"):  # not said: left out, as an older publisher's
            if values[name] is None:
                del values[name]
        if not values["cuts"]:  # absent is 0: an estimate of a source with no cut is as before
            del values["cuts"]
        return values

    @classmethod
    def _from_map(cls, m: dict[str, Any]) -> Estimate:
        if "valid" not in m:  # an older publisher's: derived from npi in _validate
            m = {**m, "valid": None}
        elif m["valid"] is None:  # None means "derive" to the constructor only
            raise _error(cls.KEY, "valid", "must be true or false", None)
        for name in ("width", "height"):
            if name not in m:
                m = {**m, name: None}
            elif m[name] is None:  # absent is "not said", nil is a wrong type
                raise _error(cls.KEY, name, f"must be an integer in 1..{MAX_SIDE}", None)
        return super()._from_map(_cuts_default(m))

    @classmethod
    def _from_wire(cls, wire: Any) -> dict[str, Any] | None:
        values = {name: getattr(wire, name) for name in cls._field_names()
                  if name != "features"}
        # checked by msgspec; made [id, x, y] lists when first read (__getattr__)
        values["_wire_features"] = wire.features
        if wire.valid is msgspec.UNSET:  # derived from npi, as the constructor does
            values["valid"] = wire.npi >= MIN_VALID_NPI
        for name in ("width", "height"):
            if values[name] is msgspec.UNSET:
                values[name] = None
        return values

    def __getattr__(self, name: str) -> Any:
        # Only called for what the instance does not hold: the features of an estimate the
        # fast path decoded, turned from msgspec's (id, x, y) tuples into lists when first
        # read. A reader that never looks at them (the controller) saves 12 us an estimate
        # of 100 features; to the others the estimate is the same.
        if name == "features":
            wire = self.__dict__.get("_wire_features")
            if wire is not None:
                features = list(map(list, wire))
                object.__setattr__(self, "features", features)
                return features
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")


Estimate._FAST = msgspec.msgpack.Decoder(_EstimateWire)


def encode_estimate(*, seq: int, stamp_ns: int, npi: int, xc: float, yc: float, xe: float,
                    ye: float, dx: float, dy: float, scale: float, t_ms: float, first: bool,
                    ids: np.ndarray, points: np.ndarray, params_id: int,
                    valid: bool | None = None, width: int | None = None,
                    height: int | None = None, cuts: int = 0) -> bytes:
    """``Estimate(...).encode()`` byte for byte, with the features given as arrays: ``ids``
    (N,) integers >= 0 and ``points`` (N, 2) finite x, y.

    The hot path of motion-estimation: the same checks as the constructor's, the features'
    with numpy over the arrays rather than item by item, and no message object (the
    features go to the encoder as tuples, which it writes as the arrays lists are written).
    About a third of building and encoding an :class:`Estimate` of 100 features.

    Raises
    ------
    MessageError
        As the constructor would, naming the field.
    """
    key = Estimate.KEY
    checks = Estimate._CHECKS
    ids = np.asarray(ids)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if ids.ndim != 1 or len(ids) != len(pts) or (ids.size and ids.dtype.kind not in "iu"):
        raise _error(key, "features", "ids must be (N,) integers, one per point", ids)
    if ids.size and ids.min() < 0:
        raise _error(key, "features", "ids must be >= 0", ids)
    if not np.isfinite(pts).all():
        raise _error(key, "features", "x, y must be finite numbers", pts)
    values: dict[str, Any] = {
        "seq": seq, "stamp_ns": stamp_ns, "npi": npi, "xc": xc, "yc": yc, "xe": xe, "ye": ye,
        "dx": dx, "dy": dy, "scale": scale, "t_ms": t_ms, "first": first}
    for name, value in values.items():
        values[name] = checks[name](key, name, value)
    values["features"] = list(zip(ids.tolist(), pts[:, 0].tolist(), pts[:, 1].tolist(),
                                  strict=True))
    values["params_id"] = checks["params_id"](key, "params_id", params_id)
    values["valid"] = _bool(key, "valid", values["npi"] >= MIN_VALID_NPI if valid is None
                            else valid)
    if width is not None:
        values["width"] = _SIDE(key, "width", width)
    if height is not None:
        values["height"] = _SIDE(key, "height", height)
    if cuts:
        values["cuts"] = checks["cuts"](key, "cuts", cuts)
    return pack(values)


def _exact_scalars(values: dict[str, Any], kinds: Mapping[str, type]) -> bool:
    """Whether every value of ``values`` named in ``kinds`` has exactly that type (an int or
    float as Python makes it, not a numpy scalar or a bool): then the checks of the hot-path
    encoders below return it as it is."""
    for name, kind in kinds.items():
        if type(values[name]) is not kind:
            return False
    return True


_FRAME_SCALARS = {"seq": int, "stamp_ns": int, "cuts": int}
_PRE_FRAME_SCALARS = {"seq": int, "stamp_ns": int, "params_id": int, "deferred": bool,
                      "cuts": int}


def _plain_image(data: Any) -> bool:
    """A (height, width) uint8 C-contiguous array of a size a frame may have."""
    return (type(data) is np.ndarray and data.dtype == np.uint8 and data.ndim == 2
            and data.flags.c_contiguous and 1 <= data.shape[0] <= MAX_SIDE
            and 1 <= data.shape[1] <= MAX_SIDE)


def encode_frame(image: np.ndarray, *, seq: int, stamp_ns: int, cuts: int = 0) -> bytes:
    """``Frame.from_image(image, seq=seq, stamp_ns=stamp_ns, cuts=cuts).encode()``, byte for
    byte.

    The camera's hot path: for what a camera produces (a C-contiguous uint8 image, plain
    ints) the checks are a few type and range tests and no message object is built (13 to
    5 us a 64 KiB frame); anything else goes through the message, which names what is wrong.

    Raises
    ------
    MessageError
        As :meth:`Frame.from_image` would, naming the field.
    """
    values = {"seq": seq, "stamp_ns": stamp_ns, "cuts": cuts}
    if not (_plain_image(image) and _exact_scalars(values, _FRAME_SCALARS)
            and seq >= 0 and stamp_ns >= 0 and cuts >= 0):
        return Frame.from_image(image, seq=seq, stamp_ns=stamp_ns, cuts=cuts).encode()
    height, width = image.shape
    return _ENCODER.encode({"v": SCHEMA_VERSION, "seq": seq, "stamp_ns": stamp_ns,
                            "width": width, "height": height, "encoding": "mono8",
                            "data": image.data, "cuts": cuts})


def encode_pre_frame(*, seq: int, stamp_ns: int, data: np.ndarray, candidates: np.ndarray,
                     strength: np.ndarray, params_id: int, deferred: bool = False,
                     cuts: int = 0) -> bytes:
    """``PreFrame(...).encode()`` of a (height, width) ``data``, byte for byte.

    Pre-processing's hot path: for what it produces (a C-contiguous uint8 image, ``(N, 2)``
    int16 candidates inside it and ``(N,)`` finite float32 strengths, plain ints) the checks
    are type tests and, when there are candidates, their bounds and finiteness in numpy; no
    message object is built (38 to 6 us a deferred 64 KiB frame). Anything else goes through
    the message, which names what is wrong.

    Raises
    ------
    MessageError
        As the constructor would, naming the field.
    """
    values = {"seq": seq, "stamp_ns": stamp_ns, "params_id": params_id, "deferred": deferred,
              "cuts": cuts}
    plain = (_plain_image(data) and _exact_scalars(values, _PRE_FRAME_SCALARS)
             and seq >= 0 and stamp_ns >= 0 and cuts >= 0 and 0 <= params_id <= MAX_PARAMS_ID
             and type(candidates) is np.ndarray and candidates.dtype == np.int16
             and candidates.ndim == 2 and candidates.shape[1] == 2
             and candidates.flags.c_contiguous and type(strength) is np.ndarray
             and strength.dtype == np.float32 and strength.shape == (len(candidates),)
             and strength.flags.c_contiguous and not (deferred and len(candidates)))
    if plain and len(candidates):
        height, width = data.shape
        xy = candidates.reshape(-1)
        plain = (xy.min() >= 0 and xy[0::2].max() < width and xy[1::2].max() < height
                 and bool(np.isfinite(strength).all()))
    if not plain:
        if not isinstance(data, np.ndarray) or data.ndim != 2:
            raise _error(PreFrame.KEY, "data", "must be a 2-D (height, width) array", data)
        return PreFrame(seq=seq, stamp_ns=stamp_ns, width=data.shape[1],
                        height=data.shape[0], data=data, candidates=candidates,
                        strength=strength, params_id=params_id, deferred=deferred,
                        cuts=cuts).encode()
    height, width = data.shape
    return _ENCODER.encode({
        "v": SCHEMA_VERSION, "seq": seq, "stamp_ns": stamp_ns, "width": width,
        "height": height, "encoding": "mono8", "data": data.data,
        "candidates": _bin_of(candidates, "<i2"), "strength": _bin_of(strength, "<f4"),
        "params_id": params_id, "deferred": deferred, "cuts": cuts})


def _pack_checked(cls: type[_Message], values: dict[str, Any]) -> bytes:
    """``cls(**values).encode()``, byte for byte, for a message of scalar fields only: each
    value through the constructor's check (which raises as it would), then packed."""
    key, checks = cls.KEY, cls._CHECKS
    for name, value in values.items():
        values[name] = checks[name](key, name, value)
    return pack(values)


def encode_pre_done(*, seq: int, stamp_ns: int) -> bytes:
    """``PreDone(...).encode()``, byte for byte, with the constructor's checks and no message
    object: pre-processing's hot path.

    Raises
    ------
    MessageError
        As the constructor would, naming the field.
    """
    return _pack_checked(PreDone, {"seq": seq, "stamp_ns": stamp_ns})


def encode_cmd_vel(*, seq: int, stamp_ns: int, vx: float, vy: float, wz: float,
                   stale: bool = False) -> bytes:
    """``CmdVel(...).encode()``, byte for byte, with the constructor's checks and no message
    object (22 to 3 us): the fuzzy controller's hot path.

    Raises
    ------
    MessageError
        As the constructor would, naming the field.
    """
    return _pack_checked(CmdVel, {"seq": seq, "stamp_ns": stamp_ns, "vx": vx, "vy": vy,
                                  "wz": wz, "stale": stale})


@dataclass(frozen=True, kw_only=True)
class Params(_Message):
    """The tracker parameters in force (``tuner/params``).

    Parameters
    ----------
    seq, stamp_ns : as in :class:`Frame`.
    max_features, thres_percent, search_size, corr_size, ungroup_size : the paper's five
        factors, validated like :class:`vistrack.common.params.TrackerParams`.
    params_id : identifier of this parameter set, increasing.
    source : ``"tuner"`` or ``"user"``.
    reason : why they changed (free text).
    """

    KEY: ClassVar[str] = "tuner/params"
    _CHECKS: ClassVar[dict[str, _Check]] = {
        **_SEQ, "params_id": _PARAMS_ID, "source": _str(("tuner", "user")), "reason": _str()}

    seq: int
    stamp_ns: int
    max_features: int
    thres_percent: float
    search_size: int
    corr_size: int
    ungroup_size: int
    params_id: int
    source: str
    reason: str = ""

    def _validate(self) -> None:
        for name in FACTORS:  # one at a time, so the error names the field
            try:
                value = getattr(TrackerParams().replace(**{name: getattr(self, name)}), name)
            except ParamError as err:
                raise MessageError(f"{self.KEY}: field {name!r}: {err}", field=name) from None
            object.__setattr__(self, name, value)

    def factors(self) -> dict[str, Any]:
        """The five factors as a dict."""
        return {name: getattr(self, name) for name in FACTORS}

    def tracker_params(self, base: TrackerParams | None = None) -> TrackerParams:
        """``base`` (default: TrackerParams()) with these five factors applied."""
        return (base if base is not None else TrackerParams()).replace(**self.factors())

    @classmethod
    def from_tracker_params(cls, params: TrackerParams, *, seq: int, stamp_ns: int,
                            params_id: int, source: str, reason: str = "") -> Params:
        """The message announcing ``params``."""
        return cls(seq=seq, stamp_ns=stamp_ns, params_id=params_id, source=source,
                   reason=reason, **params.factors())


def next_params_id(largest: int) -> int:
    """The ``params_id`` of a new parameter set: one above ``largest``, the largest in force.

    Raises
    ------
    MessageError
        If that is beyond :data:`MAX_PARAMS_ID` (a publisher sent the largest id there is).
    """
    if largest >= MAX_PARAMS_ID:
        raise MessageError(f"params_id {largest} in force is the largest a message may carry "
                           f"({MAX_PARAMS_ID}): no newer parameters can be announced",
                           field="params_id")
    return largest + 1


@dataclass(frozen=True, kw_only=True)
class Report(_Message):
    """The auto-tuner's design, ANOVA and sweep (``tuner/report``); validated shallowly.

    Parameters
    ----------
    seq, stamp_ns : as in :class:`Frame`.
    design : rows of -1/+1 levels, one per run.
    factors : factor names, column order of ``design``.
    order : run order (indices into ``design``).
    responses : response name -> list of values, one per run.
    effects : response name -> effect estimates.
    significant : response name -> ``{"99": [...], "95": [...]}``.
    optimum : the chosen parameters.
    sweep : the sensitivity grid and its responses.
    """

    KEY: ClassVar[str] = "tuner/report"
    _CHECKS: ClassVar[dict[str, _Check]] = {
        **_SEQ, "design": _list, "factors": _list, "order": _list, "responses": _map,
        "effects": _map, "significant": _map, "optimum": _map, "sweep": _map}

    seq: int
    stamp_ns: int
    design: list
    factors: list
    order: list
    responses: dict
    effects: dict
    significant: dict
    optimum: dict
    sweep: dict


@dataclass(frozen=True, kw_only=True)
class CmdVel(_Message):
    """A velocity command (``control/cmd_vel``).

    Parameters
    ----------
    seq, stamp_ns : as in :class:`Frame` (``stamp_ns`` of the estimate it answers).
    vx, vy : linear velocity in the robot frame, m/s.
    wz : angular velocity, rad/s.
    stale : True when the estimates are stale and the robot is being stopped.
    """

    KEY: ClassVar[str] = "control/cmd_vel"
    _CHECKS: ClassVar[dict[str, _Check]] = {
        **_SEQ, "vx": _float(), "vy": _float(), "wz": _float(), "stale": _bool}

    seq: int
    stamp_ns: int
    vx: float
    vy: float
    wz: float
    stale: bool = False


@dataclass(frozen=True, kw_only=True)
class Demand(_Message):
    """What motion-estimation will read of the pre-processed frames (``motion/demand``).

    Parameters
    ----------
    seq, stamp_ns : as in :class:`Frame` (``stamp_ns`` of the estimate it follows).
    candidates : whether the next frames need their candidates (the tracker selects or
        re-detects features); pre-processing leaves them out (``deferred``) while False.
    """

    KEY: ClassVar[str] = "motion/demand"
    _CHECKS: ClassVar[dict[str, _Check]] = {**_SEQ, "candidates": _bool}

    seq: int
    stamp_ns: int
    candidates: bool


@dataclass(frozen=True, kw_only=True)
class PreDone(_Message):
    """Pre-processing is done with a frame (``preprocessing/done``): published after its
    ``preprocessing/frame`` while anything subscribes to it.

    A file camera with more than one frame in flight sends the next frame once pre-processing
    is free again; it learns that from these few bytes instead of receiving every
    pre-processed frame (64 KiB at 256x256, 900 KiB at 1280x720) to read one stamp.

    Parameters
    ----------
    seq, stamp_ns : those of the camera frame (and of its ``preprocessing/frame``).
    """

    KEY: ClassVar[str] = "preprocessing/done"
    _CHECKS: ClassVar[dict[str, _Check]] = {**_SEQ}

    seq: int
    stamp_ns: int


@dataclass(frozen=True, kw_only=True)
class Pose(_Message):
    """Simulator ground truth (``sim/pose``).

    Parameters
    ----------
    seq, stamp_ns : as in :class:`Frame` (``stamp_ns`` of the rendered frame).
    x, y : robot position, m; theta : robot heading, rad.
    tx, ty : target position, m.
    """

    KEY: ClassVar[str] = "sim/pose"
    _CHECKS: ClassVar[dict[str, _Check]] = {
        **_SEQ, "x": _float(), "y": _float(), "theta": _float(), "tx": _float(),
        "ty": _float()}

    seq: int
    stamp_ns: int
    x: float
    y: float
    theta: float
    tx: float
    ty: float


Message = Frame | PreFrame | Estimate | Params | Report | CmdVel | Demand | Pose | PreDone

#: Contract key suffix -> message class.
MESSAGE_TYPES: dict[str, type[_Message]] = {
    cls.KEY: cls for cls in (Frame, PreFrame, Estimate, Params, Report, CmdVel, Demand, Pose,
                             PreDone)}


def decode_any(key: str, payload: bytes | bytearray | memoryview) -> Message:
    """Decode ``payload`` as the message of ``key``.

    Parameters
    ----------
    key : a contract key suffix (``"motion/estimate"``) or a full key
        (``"vistrack/<robot>/motion/estimate"``).

    Raises
    ------
    MessageError
        If the key has no message type (``field`` None) or the payload is invalid.
    """
    cls = MESSAGE_TYPES.get(key_suffix(key))
    if cls is None:
        raise MessageError(f"no message type for key {key!r}: known are "
                           f"{', '.join(MESSAGE_TYPES)}")
    return cls.decode(payload)  # type: ignore[return-value]


def to_jsonable(msg: Message | Mapping[str, Any]) -> dict[str, Any]:
    """A JSON-friendly dict of a message (or of a decoded map such as a status reply).

    Arrays and bins are summarised, not dumped: an image becomes ``{"width", "height",
    "mean", "nbytes"}``, other arrays ``{"shape", "dtype", "mean", "nbytes"}``, bytes
    ``{"nbytes"}``. Non-finite floats become None (strict JSON has no NaN).
    """
    if isinstance(msg, _Message):
        out: dict[str, Any] = {"v": SCHEMA_VERSION}
        out.update({f.name: _jsonable(getattr(msg, f.name))
                    for f in dataclasses.fields(msg)})  # type: ignore[arg-type]
        return out
    return _jsonable(dict(msg))


def _jsonable(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        mean = _jsonable(float(value.mean())) \
            if value.size and value.dtype.kind in "fiub" else None
        if value.ndim == 2 and value.dtype == np.uint8:
            return {"width": value.shape[1], "height": value.shape[0], "mean": mean,
                    "nbytes": value.nbytes}
        return {"shape": list(value.shape), "dtype": str(value.dtype), "mean": mean,
                "nbytes": value.nbytes}
    if isinstance(value, (bytes, bytearray, memoryview)):
        return {"nbytes": len(value)}
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    return value
