"""Key expressions of the contract (common/keys.py)."""

from __future__ import annotations

import pytest
import zenoh

from vistrack.common.keys import (
    CONTRACT_SUFFIXES,
    SERVICES,
    Keys,
    key_suffix,
    validate_robot_id,
)

CONTRACT = {
    "frame": "vistrack/robot/camera/frame",
    "pre_frame": "vistrack/robot/preprocessing/frame",
    "estimate": "vistrack/robot/motion/estimate",
    "params": "vistrack/robot/tuner/params",
    "report": "vistrack/robot/tuner/report",
    "cmd_vel": "vistrack/robot/control/cmd_vel",
    "demand": "vistrack/robot/motion/demand",
    "pose": "vistrack/robot/sim/pose",
    "pre_done": "vistrack/robot/preprocessing/done",
}


@pytest.mark.parametrize("robot", ["robot", "r1", "Robot_2", "a-b", "0"])
def test_valid_robot_ids(robot):
    assert validate_robot_id(robot) == robot
    assert Keys(robot).frame == f"vistrack/{robot}/camera/frame"


@pytest.mark.parametrize("robot", ["", "a/b", "a b", "*", "**", "r$", "r?x", "été", "a#b"])
def test_invalid_robot_ids_name_the_value(robot):
    with pytest.raises(ValueError, match="robot id") as info:
        validate_robot_id(robot)
    assert repr(robot) in str(info.value)
    with pytest.raises(ValueError):
        Keys(robot)


@pytest.mark.parametrize("robot", [None, 5, b"robot"])
def test_non_string_robot_id(robot):
    with pytest.raises(ValueError, match="must be a string"):
        validate_robot_id(robot)


def test_contract_keys_default_robot():
    keys = Keys()
    assert keys.robot == "robot"
    assert keys.root == "vistrack/robot"
    for attr, full in CONTRACT.items():
        assert getattr(keys, attr) == full
    assert set(CONTRACT) == set(CONTRACT_SUFFIXES)


def test_contract_keys_follow_robot_id():
    keys = Keys("scout-7")
    assert keys.estimate == "vistrack/scout-7/motion/estimate"
    assert keys.alive("camera") == "vistrack/scout-7/alive/camera"


@pytest.mark.parametrize("service", SERVICES)
def test_alive_and_status_keys(service):
    keys = Keys()
    assert keys.alive(service) == f"vistrack/robot/alive/{service}"
    assert keys.status(service) == f"vistrack/robot/{service}/status"
    assert zenoh.KeyExpr(keys.alive_any()).intersects(keys.alive(service))
    assert zenoh.KeyExpr(keys.status_any()).intersects(keys.status(service))


def test_service_names_are_the_contract_ones():
    assert SERVICES == ("camera", "preprocessing", "motion_estimation", "auto_tuner",
                        "fuzzy_controller")


@pytest.mark.parametrize("service", ["", "a/b", "*", "x y"])
def test_invalid_service_names(service):
    with pytest.raises(ValueError, match="service name"):
        Keys().alive(service)
    with pytest.raises(ValueError, match="service name"):
        Keys().status(service)


def test_wildcards_do_not_catch_data_keys():
    keys = Keys()
    for full in CONTRACT.values():
        assert not zenoh.KeyExpr(keys.status_any()).intersects(full)
        assert not zenoh.KeyExpr(keys.alive_any()).intersects(full)
    assert not zenoh.KeyExpr(Keys("other").alive_any()).intersects(keys.alive("camera"))


def test_every_key_is_a_canonical_zenoh_key():
    keys = Keys()
    every = [*CONTRACT.values(), keys.alive_any(), keys.status_any(),
             *(keys.alive(s) for s in SERVICES), *(keys.status(s) for s in SERVICES)]
    for key in every:
        assert str(zenoh.KeyExpr(key)) == key


@pytest.mark.parametrize(("short", "full"), [
    ("motion/estimate", "vistrack/robot/motion/estimate"),
    ("camera/frame", "vistrack/robot/camera/frame"),
    ("estimate", "vistrack/robot/motion/estimate"),
    ("cmd_vel", "vistrack/robot/control/cmd_vel"),
    ("camera/status", "vistrack/robot/camera/status"),
    ("**", "vistrack/robot/**"),
    ("vistrack/robot/motion/estimate", "vistrack/robot/motion/estimate"),
    ("vistrack/other/tuner/params", "vistrack/other/tuner/params"),
    ("vistrack/*/alive/*", "vistrack/*/alive/*"),
])
def test_resolve(short, full):
    assert Keys().resolve(short) == full


def test_resolve_uses_the_robot():
    assert Keys("r2").resolve("tuner/params") == "vistrack/r2/tuner/params"


@pytest.mark.parametrize("bad", ["", "/motion/estimate", "motion/estimate/", "motion//estimate",
                                 "motion estimate", "a/$x", None])
def test_resolve_rejects_malformed_keys(bad):
    with pytest.raises(ValueError, match="key"):
        Keys().resolve(bad)


def test_key_suffix():
    assert key_suffix("vistrack/r1/motion/estimate") == "motion/estimate"
    assert key_suffix("motion/estimate") == "motion/estimate"
    assert key_suffix("other/r1/motion/estimate") == "other/r1/motion/estimate"


@pytest.mark.parametrize(("given", "warned"), [
    ("done", True), ("estimates", True), ("camera/frames", True),
    ("pre_done", False), ("preprocessing/done", False), ("motion_estimation/status", True),
    ("alive/camera", True), ("tuner/*", False), ("**", False),
    ("vistrack/r2/motion/estimate", False), ("vistrack/r2/motion/estimat", True)])
def test_a_tool_given_none_of_vistracks_keys_says_so(given, warned, capsys):
    """vistrack echo done listened on vistrack/robot/done in silence for ever: the key is
    preprocessing/done, its short name pre_done."""
    from vistrack.services.tools.shared import resolve_key

    assert resolve_key(Keys("robot"), given, "echo") == Keys("robot").resolve(given)
    err = capsys.readouterr().err
    assert ("listening on" in err) is warned, err
    if warned:
        assert "preprocessing/done (pre_done)" in err
    # a status and a liveliness token are never published: said, with the tool that reads them
    if given.endswith("/status"):
        assert "is a queryable" in err and "vistrack status" in err
    if given.startswith("alive/"):
        assert "is a liveliness token" in err


def test_launcher_tokens_are_apart_from_the_services():
    """A launcher's token (its Zenoh session id) is found by launcher_any, and by none of the
    services' wildcards: `vistrack status` lists no launcher as a service."""
    keys = Keys("scout-7")
    quiet = zenoh.Config.from_json5('{scouting: {multicast: {enabled: false}}}')
    with zenoh.open(quiet) as session:
        zid = str(session.info.zid())
    token = keys.launcher(zid)
    assert token == f"vistrack/scout-7/launcher/{zid}"
    assert str(zenoh.KeyExpr(token)) == token
    assert zenoh.KeyExpr(keys.launcher_any()).intersects(token)
    assert not zenoh.KeyExpr(Keys("other").launcher_any()).intersects(token)
    for wildcard in (keys.alive_any(), keys.status_any()):
        assert not zenoh.KeyExpr(wildcard).intersects(token)
    for service in SERVICES:
        assert not zenoh.KeyExpr(keys.launcher_any()).intersects(keys.alive(service))
