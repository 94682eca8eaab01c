"""What a restarted auto-tuner takes to be in force, asked over real Zenoh on loopback: the
newer of the sets the tracker's two stages report in their status replies (the CONTRACT's
``<service>/status``, answered here by queryables in the test's session)."""

from __future__ import annotations

import types

import pytest
import zenoh

from vistrack.common.keys import Keys
from vistrack.common.messages import pack
from vistrack.services.auto_tuner.service import in_force_of

from procs import router, zenoh_config

pytestmark = pytest.mark.integration


def _params(params_id: int, search_size: int, source: str) -> dict:
    return {"max_features": 100, "thres_percent": 2.0, "search_size": search_size,
            "corr_size": 9, "ungroup_size": 5, "params_id": params_id, "source": source,
            "reason": ""}


@pytest.mark.parametrize(("runs", "expected"), [
    ({"motion_estimation": (0, 15, "tuner"), "preprocessing": (2, 21, "user")}, (2, 21)),
    ({"motion_estimation": (3, 17, "tuner"), "preprocessing": (2, 21, "user")}, (3, 17)),
    ({"preprocessing": (2, 21, "user")}, (2, 21)),  # motion-estimation not there (yet)
    ({}, None),
])
def test_a_restarted_tuner_takes_the_newest_set_either_stage_runs(free_port, runs, expected):
    """Motion-estimation restarted with the tuner (at its flags, params_id 0) while
    pre-processing still ran the user's set 2: the tuner asked motion-estimation alone, took
    its flags on, and its next set reused id 2, which pre-processing refused for good."""
    keys = Keys("robot")
    with router(free_port) as ep, zenoh.open(zenoh_config(ep)) as session:
        answers = []
        for service, (params_id, search, source) in runs.items():
            reply = pack({"service": service, "params": _params(params_id, search, source)})
            answers.append(session.declare_queryable(
                keys.status(service), lambda q, reply=reply: q.reply(q.key_expr, reply)))
        try:
            got = in_force_of(types.SimpleNamespace(session=session, keys=keys))
        finally:
            for q in answers:
                q.undeclare()
    if expected is None:
        assert got is None
    else:
        assert (got["params_id"], got["search_size"]) == expected
