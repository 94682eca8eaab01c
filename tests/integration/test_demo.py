"""`vistrack demo`, the README's main job, end to end: the five services and the simulator in
closed loop on an embedded router, its summary and its files."""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys
from pathlib import Path

import cv2
import pytest
from forkcli import vistrack

pytestmark = pytest.mark.integration

CONTRACT = ("frames", "fps", "latency_ms_p50", "latency_ms_p99", "rms_center_error_px",
            "rms_scale_error", "retunes")


def demo(tmp_path, free_port, *flags: str) -> tuple[subprocess.CompletedProcess, dict]:
    out = tmp_path / "out"
    run = subprocess.run([sys.executable, "-m", "vistrack.services.cli", "demo", "--out",
                          str(out), "-l", f"tcp/127.0.0.1:{free_port}", *flags],
                         capture_output=True, text=True, timeout=180)
    assert run.returncode == 0, run.stderr[-3000:]
    return run, json.loads((out / "summary.json").read_text())


def test_demo_runs_the_closed_loop_and_writes_its_summary_and_files(tmp_path, free_port):
    run, summary = demo(tmp_path, free_port, "--duration", "6", "--scenario", "sideways")
    out = tmp_path / "out"
    for key in CONTRACT:
        assert key in summary and math.isfinite(summary[key]), key
    # 30 fps for 6 s, every frame through the five processes
    assert 150 <= summary["frames"] <= 185
    assert 25 <= summary["fps"] <= 31
    assert 0 < summary["latency_ms_p50"] <= summary["latency_ms_p99"]
    assert summary["latency_ms_p50"] <= summary["cmd_latency_ms_p50"]
    assert summary["commands"] >= summary["frames"] - 5, summary
    # no stale stop: the fuzzy controller's watchdog (0.3 s) never found the estimates old, but
    # in the run's first second. In CI on this shared 2-vCPU machine about half of these runs
    # had one gap of 0.31 to 0.49 s in the estimates (1 or 2 stops), where it was recorded at
    # the run's start (once the camera stalled 0.26 s too), while the tuning worker and the
    # demo's plots start beside the pipeline; none in over 40 demos run alone, 1 in 6 runs of
    # CI's first test files. Its cause is not known (README, Known limits); the watchdog's stops
    # for it are right. A stop later, in the run proper, still fails here.
    assert summary["estimate_gap_ms_max"] > 0 and summary["camera_gap_ms_max"] > 0
    # the captures the estimates answer come at least a camera frame apart
    assert summary["estimate_stamp_gap_ms_max"] >= 1e3 / 30 * 0.9
    assert len(summary["stale_at_s"]) == summary["stale_commands"]
    assert all(t < 1.0 for t in summary["stale_at_s"]), diagnosis(summary, out)
    assert summary["npi_mean"] > 20
    # the printed summary is the file's
    printed = json.loads(run.stdout[run.stdout.index("{"):run.stdout.rindex("}") + 1])
    assert {k: summary[k] for k in printed} == printed
    strip = cv2.imread(str(out / "strip.png"))
    assert strip is not None and strip.shape[0] == 256 and strip.shape[1] >= 256 * 4
    for name in ("errors.png", "trajectories.png", "commands.png", "services.log"):
        assert (out / name).stat().st_size > 0, name
    log = (out / "services.log").read_text()
    for service in ("camera", "preprocessing", "motion-estimation", "auto-tuner",
                    "fuzzy-controller"):
        assert f"[{service}]" in log, service
    # what the README shows of a run is what it prints (numbers apart): the report had the
    # README's one wrapped JSON object against the demo's indented one
    printed = {shape(line.replace(str(out), "vistrack-demo").replace("sideways", "default"))
               for line in (run.stdout + run.stderr).splitlines()}
    for line in readme_transcript():
        assert shape(line) in printed, line


def diagnosis(summary: dict, out: Path) -> str:
    """The summary and the services' last log lines: what a failed run left to read."""
    log = (out / "services.log").read_text().splitlines()[-40:]
    return json.dumps(summary, indent=1) + "\n" + "\n".join(log)


README = Path(__file__).resolve().parents[2] / "README.md"


def readme_transcript() -> list[str]:
    """The README's ``$ vistrack demo`` transcript, without the command."""
    block = re.search(r"```\n\$ vistrack demo\n(.*?)```", README.read_text(), flags=re.S)
    assert block, "no $ vistrack demo transcript in the README"
    return block[1].splitlines()


def shape(line: str) -> str:
    """A line with its numbers and runs of blanks made alike."""
    return " ".join(re.sub(r"-?\d+(\.\d+)?", "#", line).split())


def test_demo_with_the_robot_still_does_not_follow_the_target(tmp_path, free_port):
    _, still = demo(tmp_path, free_port, "--duration", "4", "--scenario", "sideways",
                    "--no-control")
    # no command moves the robot, so the target's sideways motion stays in the image
    assert still["rms_center_error_px"] > 5 and still["frames"] > 90


def test_demo_runs_its_services_under_the_robot_id_it_is_given(tmp_path, free_port):
    """--robot was accepted and documented, but the services ran as robot "robot": two demos
    on one network shared keys."""
    run, summary = demo(tmp_path, free_port, "--duration", "3", "--robot", "demo7")
    assert summary["frames"] > 60
    log = (tmp_path / "out" / "services.log").read_text()
    assert "vistrack/demo7/alive/" in log and "vistrack/robot/" not in log


@pytest.mark.parametrize(("flags", "message"), [
    (["--duration", "0"], "--duration 0 is out of range: allowed 1..3600 s"),
    (["--duration", "nan"], "--duration nan is out of range: allowed 1..3600 s"),
    (["--scenario", "nowhere"], "'nowhere' is neither a built-in scenario"),
    (["--out", "FILE"], "exists and is not a folder"),
    # ran the scenario's 20 s and said nothing; a traceback after the start
    (["--duration", "100"], "--duration 100 is out of range: allowed 1..20 s (the length of "
                            "scenario 'default')"),
    (["--out", "/proc/vistrack-demo"], "--out /proc/vistrack-demo: No such file or directory"),
    (["-c", "BAD"], "line 1, column 9: invalid type: integer `1`, expected either 'router', "
                    "'peer' or 'client'"),
    (["-c", "MISSING"], "missing.json5: not found"),
])
def test_demo_bad_flags_are_one_line_and_exit_2(flags, message, tmp_path):
    (tmp_path / "file").write_text("not a folder")
    (tmp_path / "bad.json5").write_text("{ mode: 1 }")
    where = {"FILE": tmp_path / "file", "BAD": tmp_path / "bad.json5",
             "MISSING": tmp_path / "missing.json5"}
    flags = [str(where.get(f, f)) for f in flags]
    if "--out" not in flags:
        flags += ["--out", str(tmp_path / "out")]
    run = vistrack("demo", *flags, timeout=60)
    assert run.returncode == 2
    assert run.stderr.startswith("vistrack demo: error: ") and message in run.stderr
    assert run.stderr.count("\n") == 1, run.stderr
