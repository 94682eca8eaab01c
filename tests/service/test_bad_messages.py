"""Messages of the right shape but bad content, fed to the service code in-process through
the MemoryNode seam: each is refused, counted and logged, what was in force stays, and the
service goes on (the malformed ones are in tests/integration/test_tools.py)."""

from __future__ import annotations

import logging

import msgpack
import pytest

from vistrack.common.bus import MemoryNode
from vistrack.common.messages import (
    MAX_PARAMS_ID,
    MessageError,
    Params,
    next_params_id,
)
from vistrack.common.params import TrackerParams
from vistrack.services import cli
from vistrack.services.runtime import ParamsInForce

log = logging.getLogger("test")


def parse(command: str, *argv: str):
    return cli.build_parser(command).parse_args([command, *argv])


def params_payload(params_id: int, **factors) -> bytes:
    """A tuner/params built with plain msgpack, so out-of-range values get through."""
    return msgpack.packb({"v": 1, "seq": 1, "stamp_ns": 1, "max_features": 100,
                          "thres_percent": 2.0, "search_size": 15, "corr_size": 9,
                          "ungroup_size": 5, "params_id": params_id, "source": "user",
                          "reason": "test", **factors})


@pytest.mark.parametrize(("factor", "value", "problem"), [
    ("search_size", 500, "search_size=500 is out of range: allowed 2..128"),
    ("thres_percent", 0.0, "thres_percent=0.0 is out of range: allowed 0.1..5.0"),
    ("corr_size", 1, "corr_size=1 is out of range: allowed 2..64"),
])
def test_params_out_of_range_are_refused_and_the_old_ones_stay(factor, value, problem):
    with MemoryNode("preprocessing") as node:
        state = ParamsInForce(TrackerParams(), params_id=3)
        assert not state.apply(params_payload(4, **{factor: value}), node, log)
        assert (state.params, state.params_id) == (TrackerParams(), 3)
        assert node.status.rejected == 1
        assert node.status.last_error == f"tuner/params: field '{factor}': {problem}"
        # the next good set is applied as usual
        assert state.apply(params_payload(4, search_size=21), node, log)
        assert (state.params.search_size, state.params_id) == (21, 4)


def test_a_params_id_beyond_the_largest_is_refused():
    """2**64 - 1 was accepted, and "one above the largest" could then not be encoded: the
    params tool died with a traceback and a tuning would have killed the auto-tuner."""
    with MemoryNode("motion_estimation") as node:
        state = ParamsInForce(TrackerParams(), params_id=3)
        assert not state.apply(params_payload(MAX_PARAMS_ID + 1, search_size=21), node, log)
        assert state.params_id == 3 and node.status.rejected == 1
        assert "'params_id' must be in 0..9007199254740991" in node.status.last_error
        assert state.apply(params_payload(MAX_PARAMS_ID, search_size=21), node, log)
    assert next_params_id(MAX_PARAMS_ID - 1) == MAX_PARAMS_ID
    with pytest.raises(MessageError, match="largest a message may carry"):
        next_params_id(MAX_PARAMS_ID)
    with pytest.raises(MessageError, match="params_id"):
        Params.from_tracker_params(TrackerParams(), seq=0, stamp_ns=0,
                                   params_id=MAX_PARAMS_ID + 1, source="user")


def test_the_tuner_at_the_largest_params_id_keeps_what_is_in_force():
    from vistrack.services.auto_tuner.service import AutoTuner, check_flags

    args = parse("auto-tuner", "--no-tune")
    with MemoryNode("auto_tuner") as node:
        tuner = AutoTuner(node, args, check_flags(args))
        tuner.seen_id = MAX_PARAMS_ID  # an estimate carried the largest id
        assert not tuner.announce("scene change")
        assert node.published_on(node.keys.params) == []
        assert tuner.state.params_id == 0
        assert "largest a message may carry" in node.status.last_error
        assert tuner.announce()  # the reminder of what is in force still goes out
        assert Params.decode(node.published_on(node.keys.params)[0]).params_id == 0
