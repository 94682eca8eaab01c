"""Property-based tests of the decoders (hypothesis): whatever map or bytes arrive, decoding
either gives a valid message, which encodes and decodes to the same again, or raises
MessageError, and nothing else; the seq/stamp peek never raises."""

from __future__ import annotations

import math

import msgpack
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from vistrack.common.messages import (
    MAX_PARAMS_ID,
    MAX_SIDE,
    MESSAGE_TYPES,
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
    peek_int,
    peek_seq,
)

STAMP = 1_700_000_000_123_456_789


def _good_maps() -> dict[str, dict]:
    """One valid wire map of every message type (as a reader receives it)."""
    image = np.arange(48, dtype=np.uint8).reshape(6, 8)
    common = {"seq": 7, "stamp_ns": STAMP}
    messages = [
        Frame(**common, width=8, height=6, data=image),
        PreFrame(**common, width=8, height=6, data=image,
                 candidates=np.array([[0, 0], [7, 5]], np.int16),
                 strength=np.array([2.5, 1.0], np.float32), params_id=2),
        Estimate(**common, npi=1, xc=1.5, yc=2.0, xe=0.0, ye=0.0, dx=0.0, dy=0.0, scale=1.0,
                 t_ms=1.0, first=True, features=[[0, 1.5, 2.0]], params_id=2),
        Params(**common, max_features=100, thres_percent=2.0, search_size=15, corr_size=9,
               ungroup_size=5, params_id=3, source="user", reason="test"),
        Report(**common, design=[[-1, 1]], factors=["a"], order=[0], responses={"tf": [1.0]},
               effects={"tf": {"a": 0.5}}, significant={"tf": {"99": [], "95": []}},
               optimum={"search_size": 15}, sweep={"tf": [[1.0]]}),
        CmdVel(**common, vx=0.1, vy=-0.1, wz=0.0, stale=False),
        Demand(**common, candidates=True),
        Pose(**common, x=0.0, y=1.0, theta=0.5, tx=2.0, ty=3.0),
        PreDone(**common),
    ]
    return {m.KEY: msgpack.unpackb(m.encode()) for m in messages}


GOOD = _good_maps()
KEYS = sorted(GOOD)
EXAMPLES = settings(max_examples=60)  # x 4 tests: a few seconds of the suite

# Any value msgpack can carry, nested a little; ints over msgpack's whole range.
SCALARS = st.one_of(
    st.none(), st.booleans(), st.integers(-2**63, 2**64 - 1),
    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=12),
    st.binary(max_size=64))
VALUES = st.recursive(
    SCALARS, lambda inner: st.lists(inner, max_size=4)
    | st.dictionaries(st.one_of(st.text(max_size=6), st.integers(-3, 3)), inner, max_size=3),
    max_leaves=8)
# Values at and around the contract's limits, valid and not.
EDGES = st.sampled_from([
    0, 1, -1, MAX_SIDE, MAX_SIDE + 1, MAX_PARAMS_ID, MAX_PARAMS_ID + 1, 2**63 - 1, 2**64 - 1,
    -2**63, 0.0, -0.0, 5e-324, 1e-300, 1e300, 1.7976931348623157e308, math.inf, -math.inf,
    math.nan, True, False, "", "mono8", "mono16", "tuner", "user", b"", b"\x00" * 48,
    b"\xff" * 4, [], [[0, 1.0, 2.0]], [[-1, 1.0, 2.0]], [[0, math.nan, 1.0]], {}, None])


@st.composite
def edited_maps(draw) -> tuple[str, bytes]:
    """A valid map of some key with fields deleted, replaced by edge or arbitrary values,
    and unknown fields added; encoded with msgpack (any key type)."""
    key = draw(st.sampled_from(KEYS))
    m = dict(GOOD[key])
    # a few fields edited (often still valid: an edge value within range, a finite number)
    # or any number of them
    names = draw(st.one_of(st.lists(st.sampled_from(sorted(m)), max_size=2),
                           st.just(list(m))))
    for name in names:
        action = draw(st.sampled_from(("drop", "edge", "edge", "any")))
        if action == "drop":
            m.pop(name, None)
        elif action == "edge":
            m[name] = draw(EDGES)
        elif action == "any":
            m[name] = draw(VALUES)
    for _ in range(draw(st.integers(0, 2))):
        m[draw(st.one_of(st.text(max_size=8), st.integers(-5, 5)))] = draw(VALUES)
    return key, msgpack.packb(m, use_bin_type=True)


def _decodes_only_to_a_valid_message_or_message_error(key: str, payload: bytes) -> None:
    cls = MESSAGE_TYPES[key]
    try:
        msg = cls.decode(payload)
    except MessageError:
        return
    again = cls.decode(msg.encode())  # what a reader accepted, a writer can send again
    assert again.seq == msg.seq and again.stamp_ns == msg.stamp_ns


@EXAMPLES
@given(edited_maps())
def test_every_decoder_raises_only_message_error_on_edited_maps(case):
    key, payload = case
    _decodes_only_to_a_valid_message_or_message_error(key, payload)
    try:
        decode_any(f"vistrack/r1/{key}", payload)
    except MessageError:
        pass
    assert peek_seq(payload) is None or peek_seq(payload) >= 0


@EXAMPLES
@given(st.sampled_from(KEYS), st.binary(max_size=300))
def test_every_decoder_raises_only_message_error_on_any_bytes(key, payload):
    _decodes_only_to_a_valid_message_or_message_error(key, payload)
    for name in ("seq", "stamp_ns", "width"):
        value = peek_int(payload, name)
        assert value is None or (type(value) is int and value >= 0)


@EXAMPLES
@given(st.sampled_from(KEYS), VALUES)
def test_every_decoder_raises_only_message_error_on_any_value(key, value):
    _decodes_only_to_a_valid_message_or_message_error(
        key, msgpack.packb(value, use_bin_type=True))


@EXAMPLES
@given(st.sampled_from(KEYS), st.data())
def test_truncated_and_corrupted_payloads_raise_only_message_error(key, data):
    payload = bytearray(msgpack.packb(GOOD[key], use_bin_type=True))
    cut = data.draw(st.integers(0, len(payload)))
    flips = data.draw(st.lists(st.tuples(st.integers(0, max(0, cut - 1)), st.integers(0, 255)),
                               max_size=3))
    payload = payload[:cut]
    for pos, byte in flips:
        if pos < len(payload):
            payload[pos] = byte
    _decodes_only_to_a_valid_message_or_message_error(key, bytes(payload))
