"""Pipeline benchmark (deselected by default: ``pytest -m bench``; or ``vistrack bench
pipeline``).

Prints the table: a raw Zenoh round trip, the raw Zenoh skeleton of the five processes (paced
and unpaced, receiving in Zenoh's callbacks and in RingChannel(1) loops), the stages in one
process, and our five processes at 30 fps (256x256 and 1280x720) and unpaced; then where each
process's CPU goes, unpaced, by thread and by part of its loop. Asserts only that every figure
was measured and that the ratios and sums are those of the figures, never a time.
"""

from __future__ import annotations

import io
import math

import pytest

from vistrack.services.bench.pipeline import PROCESSES, THREAD_GROUPS, _slug, bench_pipeline

pytestmark = pytest.mark.bench


def test_bench_pipeline(capsys):
    buf = io.StringIO()
    fig = bench_pipeline(out=buf, seconds=3.0, paced_seconds=6.0, rounds=2)
    with capsys.disabled():
        print("\n" + buf.getvalue())
    for key in ("raw_one_way_ms", "in_process_fps", "skeleton_paced_hop_ms",
                "skeleton_free_rate_hz", "skeleton_free_cpu_us_per_frame",
                "skeleton_loop_rate_hz", "skeleton_loop_cpu_us_per_frame", "paced_lat_p50_ms",
                "paced_lat_p99_ms", "paced_proc_p50_ms", "free_rate_hz",
                "free_cpu_us_per_frame"):
        assert math.isfinite(fig[key]) and fig[key] > 0, key
    assert fig["paced_lat_p99_ms"] >= fig["paced_lat_p50_ms"]
    # 6 s at 30 fps hold three replays of the 60 built-in frames: frames after a jump, and others
    for key in ("paced_lat_p99_steady_ms", "paced_lat_p99_wrap_ms"):
        assert math.isfinite(fig[key]) and fig[key] > 0, key
    assert "p99 of the frames after a jump" in buf.getvalue()
    assert fig["paced_frames"] >= 100 and fig["paced_720_frames"] >= 100  # ~30 fps for 6 s
    assert fig["hop_ratio_skeleton"] == pytest.approx(fig["paced_hop_ms"]
                                                      / fig["skeleton_paced_hop_ms"])
    assert fig["throughput_ratio_in_process"] == pytest.approx(fig["free_rate_hz"]
                                                               / fig["in_process_fps"])
    assert fig["throughput_ratio_skeleton_loop"] == pytest.approx(fig["free_rate_hz"]
                                                                  / fig["skeleton_loop_rate_hz"])
    assert fig["free_dropped"] >= 0
    # the run without the auto-tuner: no tuner process measured, and its cost is the difference
    assert fig["free_no_tuner_rate_hz"] > 0 and "free_no_tuner_cpu_auto_tuner_total" not in fig
    assert fig["free_cpu_auto_tuner_total"] > 0
    assert fig["tuner_cost_us_per_frame"] == pytest.approx(
        fig["free_cpu_us_per_frame"] - fig["free_no_tuner_cpu_us_per_frame"])
    assert "without the auto-tuner" in buf.getvalue()
    assert fig["paced_720_lat_p99_ms"] >= fig["paced_720_lat_p50_ms"] > 0
    assert fig["cpu_ratio_rounds"] == 2
    assert fig["cpu_ratio_min"] <= fig["cpu_ratio_median"] <= fig["cpu_ratio_max"]
    assert fig["cpu_ratio_min"] <= fig["cpu_ratio_skeleton_loop_plus_in_process"] \
        <= fig["cpu_ratio_max"]  # the first round's is one of them
    assert "median of 2 interleaved rounds" in buf.getvalue()
    assert fig["cpu_ratio_skeleton_loop_plus_in_process"] == pytest.approx(
        fig["free_cpu_us_per_frame"] / (fig["skeleton_loop_cpu_us_per_frame"]
                                        + 1e6 / fig["in_process_fps"]))
    # the CPU table: every process measured by thread, adding up to the run's total
    for run in ("free", "skeleton_loop"):
        total = 0.0
        for name in PROCESSES:
            groups = [fig[f"{run}_cpu_{_slug(name)}_{g}"] for g in THREAD_GROUPS]
            assert all(v >= 0 for v in groups), (run, name, groups)
            assert sum(groups) == pytest.approx(fig[f"{run}_cpu_{_slug(name)}_total"])
            total += fig[f"{run}_cpu_{_slug(name)}_total"]
        assert total == pytest.approx(fig[f"{run}_cpu_us_per_frame"])
    for name, parts in (("preprocessing", ("decode", "work", "encode")),
                        ("motion_estimation", ("decode", "work", "encode")),
                        ("fuzzy_controller", ("decode", "work", "encode")),
                        ("camera", ("encode",)), ("auto_tuner", ("decode",))):
        for part in parts:
            assert fig[f"stage_{name}_{part}_us"] > 0, (name, part)
    assert "where the CPU goes" in buf.getvalue()
