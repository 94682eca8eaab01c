"""msgpack messages of the contract (common/messages.py): round trips and every rejection."""

from __future__ import annotations

import dataclasses
import itertools
import json
import math

import msgpack
import numpy as np
import pytest

from vistrack.common.messages import (
    MAX_SIDE,
    MESSAGE_TYPES,
    SCHEMA_VERSION,
    CmdVel,
    Demand,
    Estimate,
    Frame,
    MessageError,
    Params,
    Pose,
    PreDone,
    PreFrame,
    Report,
    decode_any,
    pack,
    peek_int,
    peek_seq,
    to_jsonable,
    unpack,
)
from vistrack.common.params import TrackerParams

RNG_SEED = 20240611


def _image(height=6, width=8):
    return np.arange(height * width, dtype=np.uint8).reshape(height, width)


def make(cls):
    """A valid instance of every message class."""
    common = {"seq": 7, "stamp_ns": 1_700_000_000_123_456_789}
    if cls is Frame:
        return Frame(**common, width=8, height=6, data=_image())
    if cls is PreFrame:
        return PreFrame(**common, width=8, height=6, data=_image(),
                        candidates=np.array([[0, 0], [7, 5], [3, 2]], dtype=np.int16),
                        strength=np.array([9.5, 3.0, 1.25], dtype=np.float32), params_id=2)
    if cls is Estimate:
        return Estimate(**common, npi=2, xc=10.5, yc=20.0, xe=3.0, ye=4.5, dx=-1.5, dy=0.25,
                        scale=1.02, t_ms=3.2, first=False,
                        features=[[0, 10.0, 18.0], [4, 11.0, 22.0]], params_id=2, width=64,
                        height=48, cuts=2)
    if cls is Params:
        return Params(**common, max_features=100, thres_percent=2.0, search_size=15,
                      corr_size=9, ungroup_size=5, params_id=3, source="tuner",
                      reason="scene change")
    if cls is Report:
        return Report(**common, design=[[-1, 1], [1, -1]], factors=["search_size", "corr_size"],
                      order=[1, 0], responses={"tf": [1.5, 2.5]},
                      effects={"tf": {"search_size": 0.5}},
                      significant={"tf": {"99": [], "95": ["search_size"]}},
                      optimum={"search_size": 15, "corr_size": 9},
                      sweep={"search_size": [10, 20], "tf": [[1.0, 2.0]]})
    if cls is CmdVel:
        return CmdVel(**common, vx=0.2, vy=0.0, wz=-0.1, stale=False)
    if cls is Demand:
        return Demand(**common, candidates=False)
    if cls is Pose:
        return Pose(**common, x=1.0, y=2.0, theta=0.5, tx=3.0, ty=4.0)
    if cls is PreDone:
        return PreDone(**common)
    raise AssertionError(cls)


ALL = list(MESSAGE_TYPES.values())
ARRAY_FIELDS = {"data", "candidates", "strength"}


def assert_same(a, b):
    assert type(a) is type(b)
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and x.shape == y.shape, f.name
            np.testing.assert_array_equal(x, y, err_msg=f.name)
        else:
            assert x == y, f.name


def raw_map(msg):
    return msgpack.unpackb(msg.encode(), raw=False)


def repack(m):
    return msgpack.packb(m, use_bin_type=True)


def expect_error(cls, payload, field):
    with pytest.raises(MessageError) as info:
        cls.decode(payload)
    assert info.value.field == field, str(info.value)
    if field is not None:
        assert repr(field) in str(info.value)
    return info.value


# -- round trips ----------------------------------------------------------------------------

@pytest.mark.parametrize("cls", ALL, ids=lambda c: c.__name__)
def test_round_trip(cls):
    msg = make(cls)
    back = cls.decode(msg.encode())
    assert_same(msg, back)


@pytest.mark.parametrize("cls", ALL, ids=lambda c: c.__name__)
def test_wire_map_is_versioned_with_string_keys(cls):
    msg = make(cls)
    m = raw_map(msg)
    assert list(m)[:3] == ["v", "seq", "stamp_ns"]
    assert m["v"] == SCHEMA_VERSION == 1
    assert all(isinstance(k, str) for k in m)
    assert set(m) == {"v"} | {f.name for f in dataclasses.fields(msg)}
    assert cls.KEY in MESSAGE_TYPES and MESSAGE_TYPES[cls.KEY] is cls


def test_bins_have_the_contract_layout():
    msg = make(PreFrame)
    m = raw_map(msg)
    assert m["data"] == _image().tobytes()
    assert m["candidates"] == np.array([[0, 0], [7, 5], [3, 2]], "<i2").tobytes()
    assert m["candidates"][4:8] == (7).to_bytes(2, "little") + (5).to_bytes(2, "little")
    assert m["strength"] == np.array([9.5, 3.0, 1.25], "<f4").tobytes()
    assert m["encoding"] == "mono8"


def test_frame_from_image_and_large_frame():
    rng = np.random.default_rng(RNG_SEED)
    image = rng.integers(0, 256, (256, 256), dtype=np.uint8)
    frame = Frame.from_image(image[:, ::-1], seq=1, stamp_ns=2)  # non-contiguous view
    back = Frame.decode(frame.encode())
    np.testing.assert_array_equal(back.data, image[:, ::-1])
    assert (back.width, back.height) == (256, 256)
    assert not back.data.flags.writeable  # a view of the payload, not a copy


def test_empty_candidates_round_trip():
    msg = PreFrame(seq=0, stamp_ns=0, width=2, height=2, data=np.zeros((2, 2), np.uint8),
                   candidates=np.zeros((0, 2), np.int16), strength=np.zeros(0, np.float32),
                   params_id=0)
    back = PreFrame.decode(msg.encode())
    assert back.candidates.shape == (0, 2) and back.strength.shape == (0,)


def test_constructor_normalises_numpy_scalars():
    est = Estimate(seq=np.int64(1), stamp_ns=2, npi=np.int32(1), xc=np.float32(1.5), yc=2,
                   xe=0, ye=0, dx=0, dy=0, scale=1, t_ms=0.5, first=np.bool_(True),
                   features=[(np.int64(3), np.float32(1.5), 2.5)], params_id=0)
    assert type(est.seq) is int and type(est.xc) is float and est.first is True
    assert est.features == [[3, 1.5, 2.5]] and type(est.features[0][0]) is int
    assert Estimate.decode(est.encode()) == est


def test_params_conversion_with_tracker_params():
    tp = TrackerParams(search_size=17, corr_size=7)
    msg = Params.from_tracker_params(tp, seq=1, stamp_ns=2, params_id=5, source="user",
                                     reason="set by hand")
    assert msg.factors() == tp.factors()
    assert msg.tracker_params() == TrackerParams(search_size=17, corr_size=7)
    assert Params.decode(msg.encode()) == msg


def test_params_integral_floats_are_normalised():
    m = raw_map(make(Params))
    m["search_size"] = 15.0
    assert Params.decode(repack(m)).search_size == 15
    assert type(Params.decode(repack(m)).search_size) is int


def test_unknown_fields_are_ignored():
    for cls in ALL:
        m = raw_map(make(cls))
        m["future_field"] = {"anything": [1, 2, 3]}
        m["zz"] = b"\x00" * 10
        assert_same(cls.decode(repack(m)), make(cls))


def test_decode_accepts_bytearray_and_memoryview():
    payload = make(CmdVel).encode()
    assert CmdVel.decode(bytearray(payload)) == make(CmdVel)
    assert CmdVel.decode(memoryview(payload)) == make(CmdVel)


# -- rejections ---------------------------------------------------------------------------

# fields added to the contract later: a message from an older publisher lacks them
OPTIONAL = {(Estimate, "valid"), (Estimate, "width"), (Estimate, "height"), (Estimate, "cuts"),
            (PreFrame, "deferred"), (Frame, "cuts"), (PreFrame, "cuts")}


@pytest.mark.parametrize(("cls", "name"), [
    (cls, f.name) for cls in ALL for f in dataclasses.fields(cls)
    if (cls, f.name) not in OPTIONAL
], ids=lambda x: x if isinstance(x, str) else x.__name__)
def test_missing_field_is_named(cls, name):
    m = raw_map(make(cls))
    del m[name]
    err = expect_error(cls, repack(m), name)
    assert "missing" in str(err)


def test_an_estimates_frame_size_is_optional_and_checked():
    """``width`` and ``height`` came later: without them an estimate decodes with None (not
    said), and is encoded without them; given, each is a side of 1..MAX_SIDE px."""
    m = raw_map(make(Estimate))
    assert (m["width"], m["height"]) == (64, 48)
    del m["width"], m["height"]
    old = Estimate.decode(repack(m))
    assert (old.width, old.height) == (None, None)
    assert "width" not in raw_map(old) and "height" not in raw_map(old)
    for bad in (0, MAX_SIDE + 1, None, 64.0, True):
        expect_error(Estimate, repack({**m, "width": bad, "height": 48}), "width")


def test_an_estimates_cuts_are_optional_and_checked():
    """``cuts`` came later: an estimate without it (an older publisher's, or one of a source
    with no cut yet) decodes with 0 and is encoded without it; the fast encoder writes it as
    the message does; a count below 0 or not an integer is refused, naming it."""
    from vistrack.common.messages import encode_estimate

    m = raw_map(make(Estimate))
    assert m["cuts"] == 2
    del m["cuts"]
    old = Estimate.decode(repack(m))
    assert old.cuts == 0 and "cuts" not in raw_map(old)
    for cuts in (0, 3):
        msg = dataclasses.replace(make(Estimate), cuts=cuts)
        fast = encode_estimate(**{k: getattr(msg, k) for k in (
            "seq", "stamp_ns", "npi", "xc", "yc", "xe", "ye", "dx", "dy", "scale", "t_ms",
            "first", "params_id", "valid", "width", "height", "cuts")},
            ids=np.array([f[0] for f in msg.features]),
            points=np.array([f[1:] for f in msg.features]))
        assert fast == msg.encode() and Estimate.decode(fast).cuts == cuts
    for bad in (-1, 1.5, None, "2"):
        expect_error(Estimate, repack({**m, "cuts": bad}), "cuts")


@pytest.mark.parametrize(("npi", "valid"), [(0, False), (2, False), (3, True), (40, True)])
def test_an_estimate_without_valid_from_an_older_publisher_decodes(npi, valid):
    """``valid`` came later: a message without it decodes, valid when NPI reaches 3."""
    m = raw_map(make(Estimate))
    del m["valid"]
    m["npi"] = npi
    assert Estimate.decode(repack(m)).valid is valid


def test_a_pre_frame_without_deferred_from_an_older_publisher_has_its_candidates():
    m = raw_map(make(PreFrame))
    assert m["deferred"] is False
    del m["deferred"]
    for decode in (PreFrame.decode, lambda p: PreFrame._from_map(unpack(p))):
        msg = decode(repack(m))
        assert msg.deferred is False and len(msg.candidates) == 3


@pytest.mark.parametrize("cls", [Frame, PreFrame], ids=lambda c: c.__name__)
def test_a_frame_without_cuts_from_an_older_publisher_has_none(cls):
    """``cuts`` came later: absent, it is 0 (the frame follows the one before it), on the
    fast path and by the checks alike; present, an integer >= 0."""
    m = raw_map(make(cls))
    assert m["cuts"] == 0
    del m["cuts"]
    for decode in (cls.decode, lambda p: cls._from_map(unpack(p))):
        assert decode(repack(m)).cuts == 0
    m["cuts"] = 3
    assert cls.decode(repack(m)).cuts == 3
    for wrong, words in ((-1, "must be >= 0"), (True, "must be an integer"),
                         ("2", "must be an integer"), (1.5, "must be an integer")):
        m["cuts"] = wrong
        err = expect_error(cls, repack(m), "cuts")
        assert words in str(err)


def test_a_deferred_pre_frame_has_no_candidates():
    """``deferred``: the candidates were left out; a message that says so and still carries
    some contradicts itself and is refused, on the fast path and by the checks alike."""
    fields = {k: v for k, v in dataclasses.asdict(make(PreFrame)).items()}
    empty = {**fields, "candidates": np.empty((0, 2), np.int16),
             "strength": np.empty(0, np.float32), "deferred": True}
    msg = PreFrame.decode(PreFrame(**empty).encode())
    assert msg.deferred is True and msg.candidates.shape == (0, 2) and msg.strength.size == 0
    with pytest.raises(MessageError, match="must be empty when deferred") as info:
        PreFrame(**{**fields, "deferred": True})
    assert info.value.field == "candidates"
    m = raw_map(make(PreFrame))
    m["deferred"] = True
    err = expect_error(PreFrame, repack(m), "candidates")
    assert "must be empty when deferred" in str(err)
    m["deferred"] = 1
    expect_error(PreFrame, repack(m), "deferred")


def test_estimate_valid_is_sent_and_checked():
    m = raw_map(make(Estimate))
    assert m["valid"] is False  # npi 2: too few for a centroid and scatter that mean anything
    m["valid"] = True  # what the publisher says is taken as said
    assert Estimate.decode(repack(m)).valid is True
    for bad in (None, 1, "yes"):
        m["valid"] = bad
        expect_error(Estimate, repack(m), "valid")
    fields = {k: v for k, v in dataclasses.asdict(make(Estimate)).items() if k != "valid"}
    assert Estimate(**{**fields, "npi": 3}).valid is True  # derived when not given
    assert Estimate(**{**fields, "npi": 3}, valid=False).valid is False


@pytest.mark.parametrize("cls", ALL, ids=lambda c: c.__name__)
@pytest.mark.parametrize("version", [2, 0, True, "1", 1.0, None])
def test_wrong_version(cls, version):
    m = raw_map(make(cls))
    m["v"] = version
    expect_error(cls, repack(m), "v")


@pytest.mark.parametrize("cls", ALL, ids=lambda c: c.__name__)
def test_missing_version(cls):
    m = raw_map(make(cls))
    del m["v"]
    expect_error(cls, repack(m), "v")


NAN, INF = float("nan"), float("inf")

BAD_VALUES = [
    # (class, field, bad value, words expected in the message)
    (Frame, "seq", -1, ">= 0"),
    (Frame, "seq", True, "integer"),
    (Frame, "seq", 1.5, "integer"),
    (Frame, "stamp_ns", "now", "integer"),
    (Frame, "width", -3, "in 1..4096"),
    (Frame, "width", 0, "in 1..4096"),
    (Frame, "width", 4097, "in 1..4096"),
    (Frame, "height", True, "integer"),
    (Frame, "height", None, "integer"),
    (Frame, "encoding", "rgb8", "mono8"),
    (Frame, "encoding", 8, "string"),
    (Frame, "data", b"\x00" * 47, "48 bytes"),
    (Frame, "data", b"", "48 bytes"),
    (Frame, "data", "not bytes", "bin"),
    (Frame, "data", [0] * 48, "bin"),
    (PreFrame, "data", b"\x00" * 49, "48 bytes"),
    (PreFrame, "candidates", b"\x00" * 5, "pairs"),
    (PreFrame, "candidates", b"\x00" * 6, "pairs"),
    (PreFrame, "candidates", [[0, 0]], "bin"),
    (PreFrame, "candidates", np.array([[8, 0]], "<i2").tobytes(), "inside"),
    (PreFrame, "candidates", np.array([[0, 6]], "<i2").tobytes(), "inside"),
    (PreFrame, "candidates", np.array([[-1, 0]], "<i2").tobytes(), "inside"),
    (PreFrame, "strength", b"\x00" * 7, "float32"),
    (PreFrame, "strength", np.zeros(2, "<f4").tobytes(), "one value per candidate"),
    (PreFrame, "strength", np.array([1, NAN, 2], "<f4").tobytes(), "finite"),
    (PreFrame, "strength", np.array([1, INF, 2], "<f4").tobytes(), "finite"),
    (PreFrame, "params_id", -1, "in 0..9007199254740991"),
    (Estimate, "npi", True, "integer"),
    (Estimate, "npi", -1, ">= 0"),
    (Estimate, "xc", NAN, "finite"),
    (Estimate, "yc", INF, "finite"),
    (Estimate, "xc", "1.0", "number"),
    (Estimate, "xc", True, "number"),
    (Estimate, "xe", -0.5, ">= 0"),
    (Estimate, "dx", -INF, "finite"),
    (Estimate, "scale", 0.0, "> 0"),
    (Estimate, "scale", -1.0, "> 0"),
    (Estimate, "t_ms", -1.0, ">= 0"),
    (Estimate, "first", 1, "true or false"),
    (Estimate, "first", None, "true or false"),
    (Estimate, "features", {"0": [1, 2]}, "list"),
    (Estimate, "features", [[1, 2.0]], "item 0 must be [id, x, y]"),
    (Estimate, "features", [1, 2.0, 3.0], "item 0 must be [id, x, y]"),
    (Estimate, "features", [[0, 1.0, 2.0], [True, 1.0, 2.0]], "item 1: id must be an integer"),
    (Estimate, "features", [[-1, 1.0, 2.0]], "id must be >= 0"),
    (Estimate, "features", [[1, NAN, 2.0]], "finite"),
    (Estimate, "features", [[1, 1.0, "2"]], "finite numbers"),
    (Estimate, "params_id", 1.5, "integer"),
    (Estimate, "params_id", 2**53, "in 0..9007199254740991"),
    (Params, "max_features", 0, "out of range"),
    (Params, "max_features", True, "integer"),
    (Params, "thres_percent", 9.0, "out of range"),
    (Params, "thres_percent", NAN, "out of range"),
    (Params, "thres_percent", False, "number"),
    (Params, "search_size", 1000, "out of range"),
    (Params, "search_size", 15.5, "integer"),
    (Params, "corr_size", "9", "integer"),
    (Params, "ungroup_size", -1, "out of range"),
    (Params, "params_id", -1, "in 0..9007199254740991"),
    (Params, "params_id", 2**64 - 1, "in 0..9007199254740991"),
    (Params, "source", "robot", "'tuner', 'user'"),
    (Params, "source", None, "string"),
    (Params, "reason", 5, "string"),
    (Params, "reason", "x" * 5000, "longer"),
    (Report, "design", {"a": 1}, "list"),
    (Report, "factors", "abc", "list"),
    (Report, "order", 3, "list"),
    (Report, "responses", [1, 2], "map"),
    (Report, "effects", None, "map"),
    (Report, "significant", "99", "map"),
    (Report, "optimum", [], "map"),
    (Report, "sweep", 1.0, "map"),
    (CmdVel, "vx", NAN, "finite"),
    (CmdVel, "vy", None, "number"),
    (CmdVel, "wz", INF, "finite"),
    (CmdVel, "stale", 0, "true or false"),
    (CmdVel, "stale", "yes", "true or false"),
    (Pose, "x", NAN, "finite"),
    (Pose, "theta", None, "number"),
    (Pose, "tx", [1.0], "number"),
    (Pose, "ty", True, "number"),
]


@pytest.mark.parametrize(("cls", "name", "value", "words"), BAD_VALUES,
                         ids=[f"{c.__name__}-{n}-{i}" for i, (c, n, _, _) in
                              enumerate(BAD_VALUES)])
def test_bad_field_is_rejected_and_named(cls, name, value, words):
    m = raw_map(make(cls))
    m[name] = value
    err = expect_error(cls, repack(m), name)
    assert words in str(err)


def test_params_error_keeps_the_param_error_text():
    m = raw_map(make(Params))
    m["search_size"] = 1000
    err = expect_error(Params, repack(m), "search_size")
    assert "search_size=1000 is out of range: allowed 2..128" in str(err)


def test_report_map_keys_must_be_strings():
    m = raw_map(make(Report))
    m["responses"] = {b"tf": [1.0]}
    expect_error(Report, repack(m), "responses")


@pytest.mark.parametrize("payload", [
    b"", b"\xc1", b"\x92\x01\x02", b"\xa5hello", b"\x01", b"\xc0",
    msgpack.packb({"v": 1}) + b"\x00",  # trailing data
    msgpack.packb({1: 2}),  # non-string map key
    msgpack.packb(msgpack.ExtType(1, b"x")),
    b"\x91" * 5000,  # deep nesting
    b"\xc6\xff\xff\xff\xff",  # bin claiming 4 GiB
    b"\xdd\xff\xff\xff\xff",  # array claiming 4 G items
])
def test_not_a_versioned_map(payload):
    for cls in ALL:
        expect_error(cls, payload, None)


@pytest.mark.parametrize(("obj", "message", "field"), [
    ({1: 2, "v": 1}, "payload: map keys must be strings, got int key 1", None),
    ({"v": 1, None: 0}, "payload: map keys must be strings, got nil key None", None),
    ({"v": 1, (1, 2): 0}, "payload: map keys must be strings, got array key [1, 2]", None),
    ({"v": 1, "seq": 0, "features": [{2.5: 0}]},
     "payload: map keys must be strings, got float key 2.5 in field 'features'", "features"),
])
def test_a_map_key_that_is_not_a_string_is_said_not_called_invalid_msgpack(obj, message, field):
    payload = msgpack.packb(obj)
    msgpack.unpackb(payload, strict_map_key=False, use_list=False)  # valid msgpack it is
    for cls in ALL:
        assert str(expect_error(cls, payload, field)) == message, cls.__name__
    # a map as a key: Python cannot even hold it in a dict
    err = expect_error(Frame, b"\x82\xa1v\x01\x81\x81\xa1a\x01\x02\x03", None)
    assert str(err) == "payload: map keys must be strings, got a key holding a map"


def test_non_bytes_payload():
    with pytest.raises(MessageError):
        Frame.decode("a string")  # type: ignore[arg-type]


def test_limits_reject_oversized_fields():
    m = raw_map(make(Params))
    m["reason"] = "x" * (2 << 20)
    expect_error(Params, repack(m), None)  # over max_str_len: rejected by the unpacker


@pytest.mark.parametrize(("cls", "kwargs", "name"), [
    (Frame, {"data": np.zeros((6, 8), np.float32)}, "data"),
    (Frame, {"data": np.zeros((8, 6), np.uint8)}, "data"),
    (Frame, {"data": b"\x00" * 48}, "data"),
    (PreFrame, {"candidates": np.zeros((3, 3), np.int16)}, "candidates"),
    (PreFrame, {"candidates": np.zeros((3, 2), np.float32)}, "candidates"),
    (PreFrame, {"strength": np.zeros((3, 1), np.float32)}, "strength"),
    (Estimate, {"features": [[0, 1.0]]}, "features"),
    (Params, {"corr_size": 65}, "corr_size"),
    (CmdVel, {"vx": float("nan")}, "vx"),
])
def test_constructor_rejects_what_decode_rejects(cls, kwargs, name):
    with pytest.raises(MessageError) as info:
        dataclasses.replace(make(cls), **kwargs)
    assert info.value.field == name and repr(name) in str(info.value)


def test_frame_from_image_rejects_3d():
    with pytest.raises(MessageError, match="'data'"):
        Frame.from_image(np.zeros((4, 4, 3), np.uint8), seq=0, stamp_ns=0)


# -- fuzzing: decode raises MessageError and nothing else ---------------------------------

def _decode_all(payload):
    for cls in ALL:
        try:
            cls.decode(payload)
        except MessageError:
            pass


def test_fuzz_random_bytes():
    rng = np.random.default_rng(RNG_SEED)
    for _ in range(3000):
        n = int(rng.integers(0, 120))
        payload = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        _decode_all(payload)
        # random bytes behind a valid map prefix reach the field checks more often
        _decode_all(b"\x8f\xa1v\x01" + payload)


def test_fuzz_mutated_valid_messages():
    rng = np.random.default_rng(RNG_SEED + 1)
    originals = [make(cls).encode() for cls in ALL]
    for _ in range(3000):
        payload = bytearray(originals[int(rng.integers(len(originals)))])
        op = int(rng.integers(4))
        if op == 0:  # flip bytes
            for _ in range(int(rng.integers(1, 4))):
                payload[int(rng.integers(len(payload)))] = int(rng.integers(256))
        elif op == 1:  # truncate
            payload = payload[:int(rng.integers(len(payload)))]
        elif op == 2:  # insert bytes
            pos = int(rng.integers(len(payload)))
            payload[pos:pos] = rng.integers(0, 256, int(rng.integers(1, 6)),
                                            dtype=np.uint8).tobytes()
        else:  # delete a range
            pos = int(rng.integers(len(payload)))
            del payload[pos:pos + int(rng.integers(1, 6))]
        _decode_all(bytes(payload))
        try:
            decode_any(ALL[int(rng.integers(len(ALL)))].KEY, bytes(payload))
        except MessageError:
            pass


# a value valid on its own may break a cross-field rule reported on the other field
RELATED = {("PreFrame", "candidates"): {"candidates", "strength"},
           ("PreFrame", "deferred"): {"deferred", "candidates"}}  # deferred: none sent

TYPE_CONFUSION = [None, True, False, -1, 0, 2**63, -2**63, 1.5, NAN, INF, "", "x", b"",
                  b"\x00" * 4, [], [1], [[1, 2, 3]], {}, {"a": 1}]


@pytest.mark.parametrize("cls", ALL, ids=lambda c: c.__name__)
def test_fuzz_type_confusion_names_the_field(cls):
    """Every field replaced by values of every msgpack type: either accepted or rejected
    with an error naming exactly that field."""
    for f in dataclasses.fields(cls):
        for value in TYPE_CONFUSION:
            m = raw_map(make(cls))
            m[f.name] = value
            try:
                cls.decode(repack(m))
            except MessageError as err:
                allowed = RELATED.get((cls.__name__, f.name), {f.name})
                assert err.field in allowed, (f.name, value, str(err))


# -- helpers ------------------------------------------------------------------------------

@pytest.mark.parametrize("cls", ALL, ids=lambda c: c.__name__)
def test_decode_any_by_suffix_and_full_key(cls):
    payload = make(cls).encode()
    assert_same(decode_any(cls.KEY, payload), make(cls))
    assert_same(decode_any(f"vistrack/r7/{cls.KEY}", payload), make(cls))


def test_decode_any_unknown_key():
    with pytest.raises(MessageError, match="no message type"):
        decode_any("camera/status", make(Frame).encode())


def test_decode_any_wrong_type_for_key():
    with pytest.raises(MessageError) as info:
        decode_any("camera/frame", make(Pose).encode())
    assert info.value.field == "width"


@pytest.mark.parametrize("cls", ALL, ids=lambda c: c.__name__)
def test_to_jsonable_is_strict_json(cls):
    out = to_jsonable(make(cls))
    text = json.dumps(out, allow_nan=False)
    assert out["v"] == 1 and out["seq"] == 7
    assert len(text) < 2000  # arrays summarised, never dumped


def test_to_jsonable_summarises_frames():
    image = np.full((256, 256), 10, np.uint8)
    out = to_jsonable(Frame.from_image(image, seq=1, stamp_ns=2))
    assert out["data"] == {"width": 256, "height": 256, "mean": 10.0, "nbytes": 65536}
    out = to_jsonable(make(PreFrame))
    assert out["candidates"]["shape"] == [3, 2] and out["candidates"]["nbytes"] == 12
    assert out["strength"]["mean"] == pytest.approx((9.5 + 3.0 + 1.25) / 3)


def test_to_jsonable_maps_non_finite_to_none():
    report = dataclasses.replace(make(Report), responses={"tf": [1.0, NAN],
                                                          "raw": np.array([INF])})
    out = to_jsonable(report)
    assert out["responses"] == {"tf": [1.0, None],
                                "raw": {"shape": [1], "dtype": "float64", "mean": None,
                                        "nbytes": 8}}
    assert to_jsonable({"v": 1, "blob": b"abc", "x": np.float32(2.0)}) == \
        {"v": 1, "blob": {"nbytes": 3}, "x": 2.0}


def test_report_encodes_numpy_contents():
    report = dataclasses.replace(make(Report), responses={"tf": np.array([1.0, 2.0])},
                                 optimum={"search_size": np.int64(15)})
    back = Report.decode(report.encode())
    assert back.responses == {"tf": [1.0, 2.0]} and back.optimum == {"search_size": 15}


def test_pack_unpack():
    payload = pack({"seq": 3, "x": np.float64(1.5)})
    assert unpack(payload) == {"v": 1, "seq": 3, "x": 1.5}


def test_peek_seq():
    for cls in ALL:
        assert peek_seq(make(cls).encode()) == 7
    # seq after a large bin (another encoder's key order): found by skipping
    late = msgpack.packb({"v": 1, "data": b"\x00" * 100_000, "seq": 42}, use_bin_type=True)
    assert peek_seq(late) == 42
    for bad in [b"", b"\xc1", b"\x92\x01\x02", msgpack.packb({"v": 1}),
                msgpack.packb({"seq": -1}), msgpack.packb({"seq": True}),
                msgpack.packb({"seq": "1"}), b"\x81\xa3seq"]:
        assert peek_seq(bad) is None
    rng = np.random.default_rng(RNG_SEED + 2)
    for _ in range(2000):
        result = peek_seq(rng.integers(0, 256, int(rng.integers(0, 80)),
                                       dtype=np.uint8).tobytes())
        assert result is None or (isinstance(result, int) and result >= 0)


def test_peek_int_reads_stamp_ns_of_every_message():
    for cls in ALL:
        msg = make(cls)
        assert peek_int(msg.encode(), "stamp_ns") == msg.stamp_ns
    late = msgpack.packb({"v": 1, "data": b"\x00" * 100_000, "stamp_ns": 2**62}, use_bin_type=True)
    assert peek_int(late, "stamp_ns") == 2**62
    assert peek_int(msgpack.packb({"v": 1, "seq": 3}), "stamp_ns") is None
    assert peek_int(msgpack.packb({"stamp_ns": 1.5}), "stamp_ns") is None


def test_peek_int_fast_and_slow_agree():
    """seq and stamp_ns are peeked by msgspec, anything msgspec refuses by the unpacker: both
    give the same answer on valid, mutated and foreign payloads."""
    from vistrack.common.messages import _peek_int_unpacker

    rng = np.random.default_rng(RNG_SEED + 3)
    payloads = [msgpack.packb({"stamp_ns": 5, 1: 2}), msgpack.packb({"seq": [1], "v": 1}),
                msgpack.packb({"seq": 2**64 - 1}), msgpack.packb([1, 2])]
    for cls in ALL:
        good = make(cls).encode()
        payloads.append(good)
        for _ in range(200):
            mutated = bytearray(good)
            for _ in range(rng.integers(1, 4)):
                mutated[rng.integers(min(len(mutated), 40))] = rng.integers(256)
            payloads.append(bytes(mutated[:len(mutated) - rng.integers(0, 3)]))
    answers = set()
    for p in payloads:
        for name in ("seq", "stamp_ns"):
            fast, slow = peek_int(p, name), _peek_int_unpacker(p, name)
            answers.add(fast)
            if fast != slow:
                # the one difference (as in decoding): msgspec skips a field it does not
                # know without reading its name, so a name that is not UTF-8 does not hide
                # the field asked for
                with pytest.raises(UnicodeDecodeError):
                    msgpack.unpackb(p, raw=False)
                lenient = msgpack.unpackb(p, raw=False, unicode_errors="surrogateescape")
                assert slow is None and fast == lenient[name], (p[:40], name)
    assert len(answers) > 10  # found, not found, and other values


def test_error_is_a_value_error():
    assert issubclass(MessageError, ValueError)
    assert math.isnan(NAN)


# -- the msgspec fast path of the hot messages ---------------------------------------------

HOT = [Frame, PreFrame, Estimate]


def slow_decode(cls, payload):
    """The hand-written checks alone, as before msgspec: what the fast path must equal."""
    return cls._from_map(unpack(payload))


@pytest.mark.parametrize("cls", ALL, ids=lambda c: c.__name__)
def test_encoding_writes_the_bytes_msgpack_writes(cls):
    """The wire format (the CONTRACT) is unchanged by encoding through msgspec."""
    msg = make(cls)
    assert msg.encode() == msgpack.packb({"v": 1, **msg._wire_fields()}, use_bin_type=True)


@pytest.mark.parametrize("cls", HOT, ids=lambda c: c.__name__)
def test_the_fast_path_mirrors_every_field(cls):
    """Its msgspec type holds every field of the message (a field added to one and not the
    other would be lost, or refused, on the hot path)."""
    wire = cls._FAST.decode(make(cls).encode())
    assert set(type(wire).__struct_fields__) == {"v"} | {f.name for f in
                                                         dataclasses.fields(cls)}


@pytest.mark.parametrize("cls", HOT, ids=lambda c: c.__name__)
def test_the_fast_path_decodes_as_the_checks_do_and_views_the_payload(cls):
    payload = make(cls).encode()
    fast = cls.decode(payload)
    assert_same(fast, slow_decode(cls, payload))
    assert_same(fast, make(cls))
    for name in ARRAY_FIELDS & {f.name for f in dataclasses.fields(cls)}:
        array = getattr(fast, name)
        # the image is a view (no 64 KiB copy); every array is aligned, as numba's kernels
        # were compiled for (an unaligned one is compiled anew, seconds on the first frame)
        assert np.shares_memory(array, np.frombuffer(payload, np.uint8)) == (name == "data")
        assert array.flags.aligned and not array.flags.writeable, name
    mutable = bytearray(payload)  # a view of a bytearray must not write into it either
    for name in ARRAY_FIELDS & {f.name for f in dataclasses.fields(cls)}:
        assert not getattr(cls.decode(mutable), name).flags.writeable


@pytest.mark.parametrize("cls", HOT, ids=lambda c: c.__name__)
def test_the_fast_path_accepts_and_refuses_exactly_what_the_checks_do(cls):
    """Corrupt a valid payload at random (bytes changed, cut, or fields replaced by values of
    other types and ranges): whatever the fast path accepts, the checks accept and decode to
    the same message; whatever it refuses, the checks refuse with the same error. (But for
    an unknown field whose name is not UTF-8: ignored, as unknown fields are, not refused.)"""
    rng = np.random.default_rng(RNG_SEED)
    good = raw_map(make(cls))
    odd = [None, True, -1, 0, 4096, 4097, 2**53, 2**53 - 1, 2**64 - 1, -0.0, 1e308, NAN, INF,
           "", "mono16", b"", b"\x00" * 48, [], [[0, 1.0]], [[-1, 1.0, 2.0]], [[0, NAN, 1.0]],
           {}]
    outcomes = {"ok": 0, "error": 0}
    for trial in range(600):
        if trial % 2:
            m = dict(good)
            name = list(m)[rng.integers(len(m))]
            m[name] = odd[rng.integers(len(odd))]
            payload = repack(m)
        else:
            payload = bytearray(make(cls).encode())
            for _ in range(rng.integers(1, 4)):
                payload[rng.integers(len(payload))] = rng.integers(256)
            payload = bytes(payload[:len(payload) - rng.integers(0, 3)])
        try:
            expected = slow_decode(cls, payload)
        except MessageError as e:
            try:
                fast = cls.decode(payload)
            except MessageError as info:
                assert str(info) == str(e) and info.field == e.field
                outcomes["error"] += 1
                continue
            # the one difference: msgspec skips a field it does not know without reading its
            # name, so a name that is not UTF-8 is ignored where msgpack refused the payload
            assert "UnicodeDecodeError" in str(e), e
            lenient = msgpack.unpackb(payload, raw=False, unicode_errors="surrogateescape")
            assert_same(fast, cls._from_map(lenient))
        else:
            assert_same(cls.decode(payload), expected)
            outcomes["ok"] += 1
    assert outcomes["ok"] > 30 and outcomes["error"] > 200, outcomes  # both sides exercised


# -- the motion-estimation hot path: an estimate encoded from the tracker's arrays ---------

def test_encode_estimate_writes_what_the_message_writes():
    """For the tracker's own estimates (first frame, tracking, none left), byte for byte."""
    from vistrack.common import synthetic
    from vistrack.common.messages import encode_estimate
    from vistrack.common.vision import Tracker

    tracker = Tracker(TrackerParams())
    estimates = [tracker.process(f) for f in synthetic.builtin_sequence(4)]
    tracker.reset()
    estimates.append(tracker.process(np.full((8, 8), 7, np.uint8)))  # no feature
    for e in estimates:
        fields = dict(seq=e.seq, stamp_ns=123, npi=e.npi, xc=e.xc, yc=e.yc, xe=e.xe,
                      ye=e.ye, dx=e.dx, dy=e.dy, scale=e.scale, t_ms=e.t_ms, first=e.first,
                      params_id=4, valid=e.valid)
        expected = Estimate(**fields, features=e.features()).encode()
        assert encode_estimate(**fields, ids=e.ids, points=e.points) == expected
        del fields["valid"]  # derived from npi, as the constructor does
        assert encode_estimate(**fields, ids=e.ids, points=e.points) == \
            Estimate(**fields, features=e.features()).encode()


@pytest.mark.parametrize(("change", "name", "words"), [
    ({"points": np.array([[1.0, np.nan]])}, "features", "finite"),
    ({"ids": np.array([-1])}, "features", ">= 0"),
    ({"ids": np.array([0, 1])}, "features", "one per point"),
    ({"ids": np.array([0.5])}, "features", "integers"),
    ({"scale": 0.0}, "scale", "> 0"),
    ({"xc": math.inf}, "xc", "finite"),
    ({"params_id": -1}, "params_id", "in 0.."),
])
def test_encode_estimate_refuses_what_the_constructor_refuses(change, name, words):
    from vistrack.common.messages import encode_estimate

    fields = dict(seq=1, stamp_ns=2, npi=1, xc=1.0, yc=2.0, xe=0.0, ye=0.0, dx=0.0, dy=0.0,
                  scale=1.0, t_ms=0.5, first=True, params_id=0, ids=np.array([3]),
                  points=np.array([[1.0, 2.0]]))
    with pytest.raises(MessageError) as info:
        encode_estimate(**{**fields, **change})
    assert info.value.field == name and words in str(info.value)


# -- the other hot paths: frames, pre-processed frames and commands without message objects --

def test_encode_frame_pre_frame_and_cmd_vel_write_what_the_messages_write():
    """For the services' own outputs (a camera image, a filtered frame with and without its
    candidates, a command, pre-processing's done), and for inputs the fast path hands to the
    message (a view, numpy scalars), byte for byte."""
    from vistrack.common import synthetic
    from vistrack.common.messages import (
        encode_cmd_vel,
        encode_frame,
        encode_pre_done,
        encode_pre_frame,
    )
    from vistrack.common.vision import preprocess

    image = synthetic.builtin_sequence(3)[1]
    for img, seq in ((image, 7), (image[10:50, 3:99], 8), (image, np.int64(9))):
        assert encode_frame(img, seq=seq, stamp_ns=123) == \
            Frame.from_image(img, seq=seq, stamp_ns=123).encode()
        for cuts in (0, 2, np.int64(5)):
            assert encode_frame(img, seq=seq, stamp_ns=123, cuts=cuts) == \
                Frame.from_image(img, seq=seq, stamp_ns=123, cuts=cuts).encode()
    assert Frame.decode(encode_frame(image, seq=1, stamp_ns=2, cuts=7)).cuts == 7
    pre = preprocess(image, TrackerParams())
    assert len(pre.candidates) > 100
    none = dict(candidates=np.empty((0, 2), np.int16), strength=np.empty(0, np.float32))
    for (arrays, deferred), cuts in itertools.product(
            ((dict(candidates=pre.candidates, strength=pre.strength), False),
             (none, True), (none, False),
             (dict(candidates=pre.candidates.astype(np.int32),
                   strength=pre.strength.astype(np.float64)), False)), (0, 4)):
        fields = dict(seq=5, stamp_ns=6, data=pre.filtered, params_id=3, deferred=deferred,
                      cuts=cuts, **arrays)
        assert encode_pre_frame(**fields) == PreFrame(width=256, height=256, **fields).encode()
        assert PreFrame.decode(encode_pre_frame(**fields)).cuts == cuts
    for stale in (False, True):
        fields = dict(seq=4, stamp_ns=5, vx=0.25, vy=-0.5, wz=0.0, stale=stale)
        assert encode_cmd_vel(**fields) == CmdVel(**fields).encode()
    assert encode_cmd_vel(seq=4, stamp_ns=5, vx=np.float32(0.5), vy=1, wz=0.0) == \
        CmdVel(seq=4, stamp_ns=5, vx=np.float32(0.5), vy=1, wz=0.0).encode()
    for seq, stamp in ((0, 1), (np.int64(7), 1_700_000_000_123_456_789)):
        assert encode_pre_done(seq=seq, stamp_ns=stamp) == \
            PreDone(seq=seq, stamp_ns=stamp).encode()


@pytest.mark.parametrize(("encoder", "change", "name", "words"), [
    ("frame", {"seq": -1}, "seq", ">= 0"),
    ("frame", {"stamp_ns": True}, "stamp_ns", "integer"),
    ("frame", {"image": np.zeros((4, 4), np.float32)}, "data", "uint8"),
    ("frame", {"image": np.zeros(4, np.uint8)}, "data", "2-D"),
    ("frame", {"image": np.zeros((1, 4097), np.uint8)}, "width", "1..4096"),
    ("frame", {"cuts": -1}, "cuts", ">= 0"),
    ("frame", {"cuts": True}, "cuts", "integer"),
    ("pre", {"cuts": "1"}, "cuts", "integer"),
    ("pre", {"candidates": np.array([[0, 256]], np.int16)}, "candidates", "inside"),
    ("pre", {"candidates": np.array([[-1, 0]], np.int16)}, "candidates", "inside"),
    ("pre", {"strength": np.array([np.nan], np.float32)}, "strength", "finite"),
    ("pre", {"strength": np.zeros(2, np.float32)}, "strength", "one value per candidate"),
    ("pre", {"deferred": True}, "candidates", "empty when deferred"),
    ("pre", {"params_id": -1}, "params_id", "in 0.."),
    ("pre", {"data": np.zeros((4, 4, 3), np.uint8)}, "data", "2-D"),
    ("cmd", {"vx": math.nan}, "vx", "finite"),
    ("cmd", {"stale": 1}, "stale", "true or false"),
    ("cmd", {"seq": 1.5}, "seq", "integer"),
    ("done", {"seq": -2}, "seq", ">= 0"),
    ("done", {"stamp_ns": "now"}, "stamp_ns", "integer"),
])
def test_the_fast_encoders_refuse_what_the_constructors_refuse(encoder, change, name, words):
    from vistrack.common.messages import (
        encode_cmd_vel,
        encode_frame,
        encode_pre_done,
        encode_pre_frame,
    )

    fields: dict = {
        "frame": dict(image=np.zeros((8, 6), np.uint8), seq=1, stamp_ns=2),
        "pre": dict(seq=1, stamp_ns=2, data=np.zeros((256, 256), np.uint8),
                    candidates=np.array([[3, 4]], np.int16),
                    strength=np.array([1.5], np.float32), params_id=0),
        "cmd": dict(seq=1, stamp_ns=2, vx=0.0, vy=0.0, wz=0.0),
        "done": dict(seq=1, stamp_ns=2),
    }[encoder]
    encode = {"frame": encode_frame, "pre": encode_pre_frame, "cmd": encode_cmd_vel,
              "done": encode_pre_done}[encoder]
    with pytest.raises(MessageError) as info:
        encode(**{**fields, **change})
    assert info.value.field == name and words in str(info.value)


def test_a_decoded_estimate_makes_its_features_lists_when_they_are_read():
    """A reader that never reads them (the controller) does not pay for 100 lists; to one
    that does, the estimate is what the message decoded the slow way is, item by item."""
    import copy
    import pickle

    fields = dict(seq=1, stamp_ns=2, npi=3, xc=1.0, yc=2.0, xe=0.5, ye=0.5, dx=0.0, dy=0.0,
                  scale=1.0, t_ms=0.5, first=False, params_id=0)
    features = [[7, 10.5, 20.25], [9, 30.0, 40.0], [12, 0.0, 255.0]]
    payload = Estimate(**fields, features=features).encode()
    est = Estimate.decode(payload)
    assert "features" not in vars(est)  # not made yet
    assert est.xc == 1.0 and est.npi == 3
    assert est.features == features and all(type(f) is list for f in est.features)
    assert est.features is est.features  # made once
    for other in (Estimate.decode(payload), copy.copy(Estimate.decode(payload)),
                  pickle.loads(pickle.dumps(Estimate.decode(payload))),
                  dataclasses.replace(Estimate.decode(payload))):
        assert other == est == Estimate._from_map(unpack(payload))
    assert to_jsonable(Estimate.decode(payload))["features"] == features
    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        est.nothing  # noqa: B018
