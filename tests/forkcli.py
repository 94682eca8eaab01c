"""Run ``vistrack`` command lines as real processes, without paying Python's start-up each time.

A command-line test used to start ``python -m vistrack.services.cli ...`` afresh: 1 to 3 s of
interpreter start-up and imports (numpy, OpenCV, Zenoh, scipy, numba's kernels from its cache)
for a few milliseconds of argument checking. Over the suite's ~150 command lines that was a
fifth of the whole run.

:func:`vistrack` instead asks one server process (started on first use, ended when the test
process exits) that has imported every subcommand and loaded the tracker's kernels once. For
each command line it forks a child with stdin from ``/dev/null`` and stdout and stderr (the file
descriptors, so what C libraries write is caught as well) into files. The child runs what the
``vistrack`` command runs, :func:`vistrack.services.cli.entry`, exit included (it ends the
process without the teardown of every module, as the command does). The server replies with
the exit code and both outputs, as :class:`subprocess.CompletedProcess`. What the imports
themselves print would be hidden from the children, so the server checks that they printed
nothing and refuses to start otherwise. It holds no thread when it forks (checked at start):
nothing is left half-locked in the children.

A command line that needs its own environment or start-up (``env``, or the module's import
under test) is run as a plain subprocess: pass ``fresh=True``.
"""

from __future__ import annotations

import atexit
import json
import os
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

_SERVER = r"""
import json, os, sys, tempfile, time
from vistrack.services import threads
threads.configure()
from vistrack.services import cli
cli.build_parser(None)                       # imports every subcommand's module
import cv2
from vistrack.common.vision import warm_up
opencv_threads = cv2.getNumThreads()
cv2.setNumThreads(1)                         # else OpenCV's pool starts its threads here
warm_up()                                    # the kernels, from numba's cache
cv2.setNumThreads(opencv_threads)            # a child starts its own pool, as `vistrack` does
tasks = len(os.listdir("/proc/self/task")) if os.path.isdir("/proc/self/task") else 1
channel = os.fdopen(os.dup(0), "r")          # requests; the children get /dev/null
reply = os.fdopen(os.dup(1), "w")
null = os.open(os.devnull, os.O_RDONLY)
os.dup2(null, 0)
reply.write(json.dumps({"tasks": tasks}) + "\n")
reply.flush()
for line in channel:
    req = json.loads(line)
    out, err = tempfile.TemporaryFile(), tempfile.TemporaryFile()
    sys.stdout.flush()
    sys.stderr.flush()
    pid = os.fork()
    if pid == 0:
        channel.close()
        reply.close()
        os.dup2(out.fileno(), 1)
        os.dup2(err.fileno(), 2)
        if req["cwd"]:
            os.chdir(req["cwd"])
        sys.argv = ["vistrack", *req["argv"]]
        cli.entry(req["argv"])               # the command's whole end, exit code included
    deadline = time.monotonic() + req["timeout"]
    while True:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            break
        if time.monotonic() > deadline:
            os.kill(pid, 9)
            os.waitpid(pid, 0)
            status = None
            break
        time.sleep(0.002)
    outputs = []
    for f in (out, err):
        f.seek(0)
        outputs.append(f.read().decode("utf-8", "replace"))
        f.close()
    rc = None if status is None else os.waitstatus_to_exitcode(status)
    reply.write(json.dumps({"rc": rc, "stdout": outputs[0], "stderr": outputs[1]}) + "\n")
    reply.flush()
"""


class _Server:
    def __init__(self) -> None:
        self.lock = threading.Lock()
        fd, name = tempfile.mkstemp(prefix="vistrack-forkcli-")
        os.close(fd)
        self.stderr = Path(name)
        with self.stderr.open("w") as stderr:  # the child has its own copy
            self.p = subprocess.Popen([sys.executable, "-c", _SERVER], stdin=subprocess.PIPE,
                                      stdout=subprocess.PIPE, stderr=stderr, text=True)
        hello = self.p.stdout.readline() if self.p.stdout else ""
        noise = self.stderr.read_text()
        if not hello or noise:
            raise RuntimeError(f"the vistrack fork server did not start cleanly: {noise!r}")
        if json.loads(hello)["tasks"] != 1:
            raise RuntimeError("the vistrack fork server holds threads: forking it is unsafe")
        atexit.register(self.close)

    def run(self, argv: list[str], timeout: float, cwd: str | None) -> dict:
        assert self.p.stdin is not None and self.p.stdout is not None
        with self.lock:
            self.p.stdin.write(json.dumps({"argv": argv, "timeout": timeout, "cwd": cwd}) + "\n")
            self.p.stdin.flush()
            line = self.p.stdout.readline()
        if not line:
            raise RuntimeError(f"the vistrack fork server died: {self.stderr.read_text()!r}")
        return json.loads(line)

    def close(self) -> None:
        if self.p.stdin:
            self.p.stdin.close()
        try:
            self.p.wait(10)
        except subprocess.TimeoutExpired:
            self.p.kill()
        self.stderr.unlink(missing_ok=True)


_server: _Server | None = None


def vistrack(*args: str, timeout: float = 120, check: bool = False, cwd: str | None = None,
             fresh: bool = False, **popen: object) -> subprocess.CompletedProcess:
    """``vistrack ARGS`` in a real process (a child forked from the server, or with ``fresh``
    or any other ``subprocess.run`` keyword a new interpreter), its outputs as text."""
    global _server
    argv = [str(a) for a in args]
    if fresh or popen:
        return subprocess.run([sys.executable, "-m", "vistrack.services.cli", *argv],
                              capture_output=True, text=True, timeout=timeout, check=check,
                              cwd=cwd, **popen)  # type: ignore[call-overload]
    if _server is None:
        _server = _Server()
    r = _server.run(argv, timeout, cwd)
    if r["rc"] is None:
        raise subprocess.TimeoutExpired(["vistrack", *argv], timeout, r["stdout"], r["stderr"])
    done = subprocess.CompletedProcess(["vistrack", *argv], r["rc"], r["stdout"], r["stderr"])
    if check:
        done.check_returncode()
    return done
