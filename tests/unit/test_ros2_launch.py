"""Launch files with the ros2 service and a ROS 2 camera: deploy/ros2-robot.yaml is valid,
the default launch stays the five services, and bad ROS 2 flags are refused with their line
before anything starts."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from vistrack.services import cli
from vistrack.services.launch.launchfile import default_launch, load_launch

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"


def test_the_ros2_robot_launch_file_is_valid_and_reads_the_camera_in_preprocessing():
    spec = load_launch(DEPLOY / "ros2-robot.yaml")
    names = {s.name for s in spec.services}
    # no camera service: it would publish camera/frame alongside preprocessing's
    assert names == {"ros2", "preprocessing", "motion_estimation", "auto_tuner",
                     "fuzzy_controller"}
    pre = spec.service("preprocessing")
    assert pre is not None and "ros2:/camera/image_raw" in pre.flags


def test_the_default_launch_has_no_ros2_service():
    assert spec_names(default_launch()) == {"camera", "preprocessing", "motion_estimation",
                                            "auto_tuner", "fuzzy_controller"}


def spec_names(spec) -> set[str]:
    return {s.name for s in spec.services}


@pytest.mark.parametrize(("text", "expected"), [
    ("services:\n  ros2:\n    flags: {--domain: 300}\n",
     r"line 3: services\.ros2\.flags: --domain 300 is out of range: allowed 0\.\.232$"),
    ("services:\n  ros2:\n    flags: [--remap, 'odom:=/odom']\n",
     r"line 3: services\.ros2\.flags: --remap odom:=/odom: 'odom' is none of this "
     r"service's topics"),
    ("services:\n  camera:\n    flags: {--source: 'ros2:/camera//raw'}\n",
     r"line 3: services\.camera\.flags: ROS topic '/camera//raw' is not valid"),
    ("services:\n  preprocessing:\n    flags: {--source: 'ros2:/camera//raw'}\n",
     r"line 3: services\.preprocessing\.flags: ROS topic '/camera//raw' is not valid"),
    ("services:\n  preprocessing:\n    flags: {--source: 'camera'}\n",
     r"line 3: services\.preprocessing\.flags: --source 'camera': expected camera/frame or "
     r"ros2:TOPIC"),
    ("services:\n  bridge:\n", r"line 2: services: unknown service 'bridge'; allowed: "
                               r"camera, .*, fuzzy-controller, ros2"),
])
def test_bad_ros2_launch_entries_are_one_line_errors(text, expected, tmp_path, capsys):
    path = tmp_path / "robot.yaml"
    path.write_text(text)
    assert cli.main(["up", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert re.fullmatch(rf"vistrack up: error: {re.escape(str(path))}, {expected}.*\n", err), err
