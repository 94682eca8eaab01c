"""Which recorded samples ``vistrack replay`` publishes again: the recorded moves on
``control/cmd_vel`` only where a KEY names them."""

from __future__ import annotations

from vistrack.common.keys import Keys
from vistrack.services import cli
from vistrack.services.tools.replay import _key_filter, _Selection, names_commands


def selection(*keys: str) -> _Selection:
    args = cli.build_parser("replay").parse_args(["replay", "rec.vtr", *keys])
    exprs = [_key_filter(Keys(args.robot), k) for k in args.keys]
    return _Selection(exprs, commands=names_commands(args.keys, exprs))


def test_a_replay_publishes_recorded_commands_only_where_a_key_names_them():
    """Replayed with the rest, a recording's commands reached the ROS 2 bridge of a robot of
    that id, which drove its base with them (29 moving commands in a 1 s replay)."""
    cmd, frame = "vistrack/robot/control/cmd_vel", "vistrack/robot/camera/frame"
    every = selection()
    assert every(frame) and not every(cmd) and every.held_back
    wild = selection("**")
    assert wild(frame) and not wild(cmd)
    for named in ("control/cmd_vel", "cmd_vel", "vistrack/robot/control/cmd_vel",
                  "control/**"):
        chosen = selection(named, "camera/frame")
        assert chosen(cmd) and chosen(frame) and not chosen.held_back, named
    frames_only = selection("camera/frame")  # not asked for: nothing held back, no note
    assert frames_only(frame) and not frames_only(cmd) and not frames_only.held_back
