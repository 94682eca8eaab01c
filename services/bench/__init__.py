"""``vistrack bench``: measured figures against a peer run in the same process and moment.

One module a benchmark, each also run under pytest by ``tests/bench`` (``-m bench``):

* :mod:`.tracker`: the SSD tracker against ``cv2.matchTemplate`` and pyramidal LK (speed);
* :mod:`.accuracy`: the tracker against pyramidal LK on the scoreboard sequences (accuracy);
* :mod:`.pipeline`: the five-process pipeline against its stages in one process and a raw
  Zenoh skeleton of the same processes;
* :mod:`.net`: latency and throughput over loopback, TCP, mutual TLS and the multi-host chain;
* :mod:`.tuner`: one tuning cycle of the auto-tuner;
* :mod:`.messages`: decoding and encoding the hot-path messages, msgspec against the checks;
* :mod:`.controller`: the fuzzy controller against a proportional one and scikit-fuzzy;
* :mod:`.idle`: the CPU each process of ``vistrack up`` takes at 30 fps, from /proc;
* :mod:`.faults`: hostile and extreme input on the live system, crash and hang to a new
  process ready, and the cost of the per-message fault isolation;
* :mod:`.soak`: the full pipeline unpaced for a minute: memory, drops, nothing else lost;
* :mod:`.record`: the MCAP recorder and the Foxglove bridge on a live pipeline, against the
  ``.vtr`` recorder and ``vistrack hz`` listening to the same samples;
* :mod:`.ros2`: a ROS 2 camera topic against a plain ``camera/frame``, and ``/cmd_vel``.

Each is imported only when it runs (the pipeline one starts processes, the net one makes
network namespaces).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable

from ...common.groundtruth import DataError


def _tracker(out=sys.stdout) -> dict[str, float]:
    from .tracker import bench_tracker

    return bench_tracker(out)


def _accuracy(out=sys.stdout) -> dict[str, float]:
    from .accuracy import bench_accuracy

    return bench_accuracy(out)


def _pipeline(out=sys.stdout) -> dict[str, float]:
    from .pipeline import bench_pipeline  # starts processes: imported only when run

    return bench_pipeline(out)


def _tuner(out=sys.stdout) -> dict[str, float]:
    from .tuner import bench_tuner

    return bench_tuner(out=out)


def _messages(out=sys.stdout) -> dict[str, float]:
    from .messages import bench_messages

    return bench_messages(out=out)


def _controller(out=sys.stdout) -> dict[str, float]:
    from .controller import bench_controller

    return bench_controller(out=out)


def _net(out=sys.stdout) -> dict[str, float]:
    from .net import bench_net  # makes network namespaces when root

    return bench_net(out)


def _idle(out=sys.stdout) -> dict[str, float]:
    from .idle import bench_idle  # starts vistrack up

    return bench_idle(out)


def _faults(out=sys.stdout) -> dict[str, float]:
    from .faults import bench_faults  # starts vistrack up

    return bench_faults(out)


def _soak(out=sys.stdout) -> dict[str, float]:
    from .soak import bench_soak  # starts the five services

    return bench_soak(out)


def _record(out=sys.stdout) -> dict[str, float]:
    try:
        from .record import bench_record  # starts processes; its client needs websockets
    except ImportError as e:
        raise SystemExit(f"vistrack bench: error: record needs {e.name}: pip install "
                         "'vistrack[test]'") from None
    return bench_record(out)


def _ros2(out=sys.stdout) -> dict[str, float]:
    from .ros2 import bench_ros2  # starts processes: imported only when run

    return bench_ros2(out)


BENCHES: dict[str, Callable[..., dict[str, float]]] = {"tracker": _tracker,
                                                       "accuracy": _accuracy,
                                                       "net": _net,
                                                       "pipeline": _pipeline,
                                                       "tuner": _tuner,
                                                       "messages": _messages,
                                                       "controller": _controller,
                                                       "idle": _idle,
                                                       "faults": _faults,
                                                       "soak": _soak,
                                                       "record": _record,
                                                       "ros2": _ros2}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("which", nargs="?", default="tracker", choices=sorted(BENCHES),
                        metavar="BENCHMARK",  # its name in errors too, not "which"
                        help=f"which benchmark: {', '.join(sorted(BENCHES))} (default "
                             "tracker)")


def main(args: argparse.Namespace) -> int:
    try:
        BENCHES[args.which]()
    except DataError as e:  # the data given to score on (a user's own sequence)
        print(f"vistrack bench {args.which}: {e}", file=sys.stderr)
        return 2
    return 0
