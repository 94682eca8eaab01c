"""deploy/foxglove/vistrack.json, the Foxglove layout of a recording and of the live view.

Checked against what is not the layout itself: the panel settings Foxglove defines (the
foxglove-sdk's generated layout classes name every setting of the Image, Plot and Raw Messages
panels), the topics ``vistrack record`` / ``vistrack foxglove`` publish, and the fields of their
ROS 2 types in rosbags' type store.
"""

from __future__ import annotations

import json
from pathlib import Path

import foxglove.layouts as fl
import pytest

from vistrack.common import ros2types as r2

LAYOUT = Path(__file__).resolve().parents[2] / "deploy" / "foxglove" / "vistrack.json"
ROOT = "/vistrack/robot"
#: topic -> ROS 2 type, as the recorder and the bridge publish them for robot ``robot``
TOPICS = {f"{ROOT}/{s}": t for s, t in r2.ROS_TYPES.items()} | \
    {f"{ROOT}/{s}": r2.IMAGE_MARKER for s in r2.OVERLAYS}
NUMERIC = {"bool", "int8", "uint8", "int16", "uint16", "int32", "uint32", "int64", "uint64",
           "float32", "float64"}
# the settings each panel type knows, as Foxglove's layout schema names them
SETTINGS = {
    "Image": set(fl.ImageConfig()._to_dict()),
    "Plot": set(fl.PlotConfig()._to_dict()),
    "RawMessages": set(fl.RawMessagesConfig()._to_dict()),
}


@pytest.fixture(scope="module")
def layout() -> dict:
    return json.loads(LAYOUT.read_text(encoding="utf-8"))


def _leaves(node) -> list[str]:
    if isinstance(node, str):
        return [node]
    assert set(node) <= {"first", "second", "direction", "splitPercentage"}
    assert node["direction"] in ("row", "column")
    return _leaves(node["first"]) + _leaves(node["second"])


def _field_type(typename: str, path: str) -> str:
    """The base type at ``a.b.c`` in ``typename`` (rosbags' field definitions)."""
    store = r2.typestore()
    for name in path.split("."):
        fields = dict(store.fielddefs[typename][1])
        assert name in fields, f"{typename} has no field {name!r}"
        kind, detail = fields[name]
        if kind.name == "NAME":
            typename = detail
        else:
            assert kind.name == "BASE", f"{path}: {name} is not a single value"
            return detail[0]
    raise AssertionError(f"{path} ends at a message, not a value")


def test_every_panel_is_placed_once_and_uses_settings_foxglove_knows(layout):
    panels = layout["configById"]
    assert sorted(_leaves(layout["layout"])) == sorted(panels)
    for panel_id, config in panels.items():
        kind = panel_id.split("!")[0]
        assert set(config) - {"foxglovePanelTitle"} <= SETTINGS[kind], panel_id
        assert config["foxglovePanelTitle"]
    image = next(c for p, c in panels.items() if p.startswith("Image!"))
    assert set(image["imageMode"]) <= set(fl.ImageModeConfig()._to_dict())
    for config in (c for p, c in panels.items() if p.startswith("Plot!")):
        for series in config["paths"]:
            assert set(series) <= set(fl.PlotSeries()._to_dict())
            assert series["timestampMethod"] == "receiveTime"  # a Twist has no header


def test_the_image_shows_the_frame_with_both_overlays(layout):
    (image,) = [c for p, c in layout["configById"].items() if p.startswith("Image!")]
    mode = image["imageMode"]
    assert TOPICS[mode["imageTopic"]] == r2.IMAGE
    assert {t for t, s in mode["annotations"].items() if s["visible"]} == \
        {f"{ROOT}/{s}" for s in r2.OVERLAYS}


def test_every_plotted_path_is_a_number_of_a_published_topic(layout):
    plotted = set()
    for panel_id, config in layout["configById"].items():
        if panel_id.startswith("RawMessages!"):
            assert config["topicPath"] in TOPICS
        for series in config.get("paths", []):
            topic, _, path = series["value"].partition(".")
            assert topic in TOPICS, series["value"]
            assert _field_type(TOPICS[topic], path) in NUMERIC, series["value"]
            plotted.add(series["value"])
    estimate = f"{ROOT}/motion/estimate"
    assert {f"{estimate}.{f}" for f in ("xc", "yc", "xe", "ye", "dx", "dy", "npi")} <= plotted
    assert {f"{ROOT}/control/cmd_vel.linear.x", f"{ROOT}/control/cmd_vel.linear.y"} <= plotted
