"""The auto-tuner's worker process: tuning cycles off the service loop, at idle priority.

:class:`Worker` starts one process ('spawn') that compiles the numba kernels once, then runs one
tuning cycle (:func:`.sensitivity.tune`) per job it is sent and sends back the report and the
optimum. Pure multiprocessing: no Zenoh here (the service loop owns the session).
"""

from __future__ import annotations

import dataclasses
import logging
import multiprocessing
import os
import signal
import threading
from typing import Any

from ..kernels import die_with_parent

log = logging.getLogger("vistrack.auto_tuner")

WORKER_NICE = 10  # where SCHED_IDLE is refused: the experiments yield to the pipeline


def _idle_priority() -> str:
    """Run this process only on CPU time nothing else wants: SCHED_IDLE where Linux allows it
    (no privilege needed), else ``nice +10``. Returns what was set, for the log.

    With nice alone the worker still took its fair share of a core whenever the pipeline's
    processes woke (nice 10 weighs 10 % of nice 0, not zero), and the capture-to-command p99
    of the closed loop went from 6 to 89 ms during a tuning on this 2-core machine. A
    SCHED_IDLE process is preempted at once by any normal one.

    Idempotent: the worker's process inherits it from the thread that starts it
    (:meth:`Worker._spawn`) and sets it again, without adding a second ``nice +10``.
    """
    try:
        if os.sched_getscheduler(0) != os.SCHED_IDLE:
            os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
        return "SCHED_IDLE"
    except (AttributeError, OSError):  # not Linux, or a sandbox that forbids it
        os.nice(max(0, WORKER_NICE - os.nice(0)))
        return f"nice +{WORKER_NICE}"


def _work(conn: Any, parent_pid: int) -> None:
    """The worker process: idle priority, one OpenCV thread, compiled kernels, then one cycle
    per job."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the group: the service stops us
    die_with_parent(parent_pid)
    priority = _idle_priority()
    import cv2

    cv2.setNumThreads(1)  # "bounded CPU": one core at most, and only when it is idle
    from ..kernels import warm_up_kernels
    from ..usage import say_on_stderr
    from .sensitivity import TextureError, tune

    # numba's compile (said on stderr) or cache load, before the first job rather than in it
    warm_up_kernels(say_on_stderr("auto-tuner worker"))
    try:
        conn.send(("ready", priority))
        while True:
            job = conn.recv()
            try:
                result = tune(job["frames"], None, tolerance=job["tolerance"], step=job["step"],
                              base=job["base"], fixed=job.get("fixed"),
                              max_megapixels=job["max_megapixels"])
                if "offered" in job:  # the buffer's frames, of which only these were sent
                    result = dataclasses.replace(result, offered=job["offered"])
                conn.send(("ok", result.to_report(), dict(result.optimum.params),
                           result.keeps(*job["windows"]) if "windows" in job else False))
            except TextureError as e:  # nothing to tune on: not a fault
                conn.send(("skipped", str(e)))
            except Exception as e:  # noqa: BLE001 - a failed cycle is reported, the worker lives
                conn.send(("error", f"{type(e).__name__}: {e}"))
    except (EOFError, BrokenPipeError):
        return  # the service is gone or closed the pipe


class Worker:
    """The tuning cycles in a separate process at lower priority.

    A process, not a thread: a cycle is seconds of Python and numba work holding the GIL, which
    would stall the service loop. Started with 'spawn': a fork of a process with a live Zenoh
    session would copy the locks of its threads in whatever state they were.
    """

    def __init__(self) -> None:
        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_work, args=(child, os.getpid()), name="auto-tuner-worker",
                                 daemon=True)
        self._started = threading.Event()
        self._closing = threading.Event()
        self._error: BaseException | None = None
        threading.Thread(target=self._spawn, name="tuning-worker-spawner", daemon=True).start()
        self._started.wait()
        child.close()
        if self._error is not None:
            raise self._error
        self.ready = False  # a job sent before would block the loop on a full pipe

    def _spawn(self) -> None:
        """Start the worker from this thread, at idle priority from its first instruction.

        A new interpreter's start and imports (numpy, OpenCV, numba, Zenoh: ~1.5 s of CPU) ran
        at normal priority until :func:`_work` set SCHED_IDLE, beside a pipeline that had just
        started: the first half second of a demo is where its stalls were recorded. SCHED_IDLE
        (or nice) is per thread and inherited through fork and exec, so this thread takes it
        and starts the process. It then waits until :meth:`close`: the worker's
        PR_SET_PDEATHSIG fires when the thread that started it exits."""
        try:
            _idle_priority()
            self._proc.start()
        except BaseException as e:  # noqa: BLE001 - raised in __init__, in the caller's thread
            self._error = e
            self._started.set()
            return
        self._started.set()
        self._closing.wait()

    def submit(self, job: dict[str, Any]) -> None:
        """Send ``job`` from a thread of its own: the pipe takes a cycle's frames (26 MiB at
        1280x720) only as fast as the worker, at idle priority, reads them, and a busy machine
        starves it (that is what idle priority is for). Sent from the loop, the loop waited
        12 s and more, its inputs untaken, and the launcher killed the auto-tuner as hung
        (helper review). One job at a time (the service waits for its result); a send that
        fails (the worker died) shows at the next :meth:`poll`."""
        def send() -> None:
            try:
                self._conn.send(job)
            except (OSError, ValueError, TypeError):
                # closed or died meanwhile (a closed connection's handle is None: TypeError
                # from deep in its send, at a stop with the worker starved mid-job): poll()
                # says so, or the service is stopping anyway
                pass
        threading.Thread(target=send, name="tuning-job", daemon=True).start()

    @property
    def pid(self) -> int | None:
        """The worker process's id (None before it started)."""
        return self._proc.pid

    def poll(self) -> tuple | None:
        """The worker's next result, or None; raises EOFError when the worker died."""
        while self._conn.poll():
            msg = self._conn.recv()
            if msg[0] != "ready":
                return msg
            self.ready = True
            log.info("tuning worker ready (pid %d, %s)", self._proc.pid, msg[1])
        return None

    def close(self) -> None:
        self._conn.close()
        self._proc.terminate()  # a cycle in progress is of no use any more
        self._proc.join(0.2)  # the service's own exit must stay prompt (runtime.serve)
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join()
        self._closing.set()  # the spawning thread may end now
