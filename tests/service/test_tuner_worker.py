"""The auto-tuner's worker process: a job is handed over without making the loop wait."""

from __future__ import annotations

import os
import signal
import threading
import time

import numpy as np

from vistrack.common.params import TrackerParams
from vistrack.services.auto_tuner.worker import Worker


def test_a_job_is_handed_over_while_the_worker_cannot_read_it():
    """A cycle's frames at 1280x720 are 26 MiB through the pipe, read only as fast as the
    worker at idle priority runs. On a busy machine the loop waited 12 s and more in submit,
    its inputs untaken, and the launcher killed the auto-tuner as hung. Here the worker is
    stopped outright: submit must return at once all the same, and the job be done once the
    worker runs again."""
    worker = Worker()
    try:
        deadline = time.monotonic() + 120  # its kernels load (or compile, on a cold cache)
        while not worker.ready:
            assert worker.poll() is None and time.monotonic() < deadline, "worker not ready"
            time.sleep(0.05)
        frames = [np.zeros((720, 1280), np.uint8) for _ in range(30)]  # textureless: skipped
        os.kill(worker._proc.pid, signal.SIGSTOP)
        try:
            done = threading.Event()
            threading.Thread(target=lambda: (worker.submit({
                "frames": frames, "base": TrackerParams(), "tolerance": 0.5, "step": 5,
                "max_megapixels": 32.0}), done.set()), daemon=True).start()
            assert done.wait(2.0), "submit waited for the worker to read the job"
        finally:
            os.kill(worker._proc.pid, signal.SIGCONT)
        deadline = time.monotonic() + 60
        while (result := worker.poll()) is None:
            assert time.monotonic() < deadline, "no result"
            time.sleep(0.05)
        assert result[0] == "skipped" and "texture" in result[1]
    finally:
        worker.close()
