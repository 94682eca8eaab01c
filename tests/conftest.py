"""Shared pytest fixtures."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from collections.abc import Iterator

import pytest
from hypothesis import settings

# Property-based tests (hypothesis): no per-example deadline (a shared 2-core machine has slow
# moments; time is measured in benchmarks, not here), and in CI the examples are derived from
# each test's name, so a CI run is reproducible; a developer's runs explore new examples.
settings.register_profile("default", deadline=None)
settings.register_profile("ci", deadline=None, derandomize=True, print_blob=True)
settings.load_profile("ci" if os.environ.get("CI") else "default")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Which tests one pytest-xdist worker runs together where it is installed (the dev
    extra; ``-n 4 --dist loadgroup``): a test file's tests, so that its module fixtures (a
    router, a pipeline) are made once; and every benchmark, one after the other on one
    worker, since a benchmark's figures are of a machine that runs nothing else of ours."""
    if not config.pluginmanager.hasplugin("xdist"):
        return
    for item in items:
        group = "bench" if item.get_closest_marker("bench") else item.nodeid.split("::")[0]
        item.add_marker(pytest.mark.xdist_group(group))


#: The kernels of windows whose sub-pixel sums take int64 (a set of their own,
#: ``tracker._kernel_set``), warmed up in a process of their own (the start-up sets it also
#: warms are in the cache by then: it loads them, see :func:`numba_cache`)
_INT64_SET = ("from vistrack.common.params import TrackerParams; "
              "from vistrack.common.vision import tracker; "
              "p = TrackerParams(corr_size=64); "
              "assert tracker._kernel_set(p)[-1] == 'int64'; "
              "tracker.warm_up(params=p)")
#: that process, while it runs
_BACKGROUND: list[subprocess.Popen[bytes]] = []


#: numba's cached versions of each kernel of the tracker's modules (their dispatchers), as the
#: session's warm-up compiled them into an empty cache: before any test or the int64 set's
#: compile added any (empty where the cache was filled before)
START_UP_SIGNATURES: dict[object, set[object]] = {}


@pytest.fixture(scope="session", autouse=True)
def numba_cache() -> Iterator[None]:
    """Compile the tracker's numba kernels into numba's on-disk cache once, before any test.

    The integration tests start several services at once; on a fresh clone each would compile
    the kernels itself and miss its ready timeout. With the cache filled they load in under a
    second. It compiles as a first run does (services/kernels.py: split over two processes,
    52 s against 104 s in one on this 2-core machine, the same 97 kernels' versions alike);
    what it left is kept in :data:`START_UP_SIGNATURES` for test_kernels, which checks that
    the split compiled only versions the tracker runs.

    Then a process at the lowest priority (nice 19: about 1.5 % of a core against a test's
    process that wants it) compiles the int64 set (:data:`_INT64_SET`) in the time the tests
    leave idle, waiting for their processes. The tests that run those kernels
    (:func:`int64_kernels`) then load them: a cold compile of 30 to 85 s inside one test
    took a tenth of the suite's budget. It starts once the start-up kernels are in the cache,
    so that no two processes compile the same kernel's signatures at once (numba's index
    of them is rewritten without a lock).
    """
    from vistrack.services.kernels import warm_up_kernels

    # compiles, or loads, every start-up kernel set; what a compile left is theirs alone (a
    # cache filled by earlier sessions also holds other sets' versions)
    if warm_up_kernels(lambda line: None):
        START_UP_SIGNATURES.update(_cached_signatures())
    _BACKGROUND.append(subprocess.Popen(
        [sys.executable, "-c", _INT64_SET], stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL, preexec_fn=lambda: os.nice(19)))
    yield
    for proc in _BACKGROUND:
        if proc.poll() is None:
            proc.kill()
        proc.wait()


def _cached_signatures() -> dict[object, set[object]]:
    """Every cached kernel of the tracker's modules: its cached versions' argument types."""
    import numba

    from vistrack.services.kernels import cached_signatures

    found: dict[object, set[object]] = {}
    for name, module in list(sys.modules.items()):
        if name.startswith("vistrack.common.vision."):
            for kernel in vars(module).values():
                if isinstance(kernel, numba.core.registry.CPUDispatcher):
                    try:
                        found[kernel] = cached_signatures(kernel)
                    except AttributeError:  # a kernel numba does not cache
                        pass
    return found


#: what the processes a test starts inherit and that says where they read or write: a value a
#: test leaves behind misleads every later test's processes (a NUMBA_CACHE_DIR left set sent
#: them to compile into an empty cache, 45 s in one test, where CI sets none)
_KEPT = ("NUMBA_CACHE_DIR", "HOME", "XDG_CACHE_HOME", "TMPDIR", "VISTRACK_DATA", "PYTHONPATH")


@pytest.fixture(autouse=True)
def environment_kept() -> Iterator[None]:
    """Fail a test that leaves :data:`_KEPT` or the temporary folder changed (torn down after
    ``monkeypatch``, whose undo it checks: a ``delenv(raising=False)`` of a variable that is
    not set records nothing to restore)."""
    import tempfile

    before = ({k: os.environ.get(k) for k in _KEPT}, tempfile.gettempdir())
    yield
    after = ({k: os.environ.get(k) for k in _KEPT}, tempfile.gettempdir())
    assert after == before, f"the test left the environment changed: {before} -> {after}"


@pytest.fixture
def start_up_signatures() -> dict[object, set[object]] | None:
    """:data:`START_UP_SIGNATURES`: each cached kernel's versions, as the session's warm-up
    compiled them; None where it compiled nothing (a cache filled before: CI's is cold)."""
    return START_UP_SIGNATURES or None


@pytest.fixture
def int64_kernels() -> None:
    """Wait for the int64 set's compile (:func:`numba_cache`), if it still runs: a test that
    runs those kernels, or reads numba's index of them, then finds it whole."""
    for proc in _BACKGROUND:
        assert proc.wait(timeout=900) == 0, \
            f"the int64 set's compile failed (exit {proc.returncode}): python -c \"{_INT64_SET}\""


@pytest.fixture
def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago (bind to port 0, then release)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.fixture(scope="module")
def free_port_module() -> int:
    """Like ``free_port``, for module-scoped fixtures (one router shared by a test module)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.fixture(scope="module")
def rubberwhale():
    """The Middlebury RubberWhale folder of the shared data; the test skips, saying where the
    data is looked for, when it is absent."""
    from vistrack.common import groundtruth

    folder = groundtruth.middlebury("RubberWhale")
    if folder is None:
        pytest.skip("Middlebury RubberWhale not found: set VISTRACK_DATA or put the shared "
                    "data at ../shared/data")
    return folder


def _decoded(path) -> list:
    """Every frame of the video at ``path`` (BGR), read with OpenCV alone."""
    import cv2

    cap = cv2.VideoCapture(str(path))
    held = []
    while True:
        ok, img = cap.read()
        if not ok:
            break
        held.append(img)
    cap.release()
    return held


@pytest.fixture
def cut_video_of(tmp_path):
    """Make a video cut short, as a recording that lost its end: ``make(frames)`` writes the
    (H, W, 3) uint8 ``frames`` (MJPG, 10 fps), keeps ``fraction`` of the file's bytes (half),
    and returns (its path, the BGR frames it still holds, read with OpenCV alone); its header
    still announces them all."""
    import cv2

    def make(frames, name: str = "cut.avi", fraction: float = 0.5):
        h, w = frames[0].shape[:2]
        full = tmp_path / f"full-{name}"
        writer = cv2.VideoWriter(str(full), cv2.VideoWriter_fourcc(*"MJPG"), 10, (w, h))
        for f in frames:
            writer.write(f)
        writer.release()
        cut = tmp_path / name
        data = full.read_bytes()
        cut.write_bytes(data[:int(len(data) * fraction)])
        held = _decoded(cut)
        assert 0 < len(held) < len(frames)
        return cut, held
    return make


@pytest.fixture
def cut_video(cut_video_of):
    """:func:`cut_video_of` of 10 random 64x48 frames."""
    import numpy as np

    rng = np.random.default_rng(7)
    return cut_video_of([rng.integers(0, 256, (48, 64, 3), dtype=np.uint8) for _ in range(10)])


@pytest.fixture
def drop_frame_video(tmp_path):
    """A complete MJPG AVI of 10 random 64x48 frames at 10 fps stored at 20: each picture's
    index entry followed by an empty one (an AVI's "repeat the last frame", as in OpenCV's own
    ``vtest.avi``), so its header announces 20 frames and 10 decode, 0 to 0.9 s of 1 s.
    Written here, chunk by chunk (``cv2.VideoWriter`` writes no empty entry). Returns (its
    path, the BGR frames it holds, read with OpenCV alone)."""
    import struct

    import cv2
    import numpy as np

    def chunk(fourcc: bytes, data: bytes) -> bytes:
        return fourcc + struct.pack("<I", len(data)) + data + b"\0" * (len(data) % 2)

    def listed(kind: bytes, body: bytes) -> bytes:
        return chunk(b"LIST", kind + body)

    rng = np.random.default_rng(3)
    frames = [rng.integers(0, 256, (48, 64, 3), dtype=np.uint8) for _ in range(10)]
    pictures = [cv2.imencode(".jpg", f, [cv2.IMWRITE_JPEG_QUALITY, 100])[1].tobytes()
                for f in frames]
    entries = [e for p in pictures for e in (p, b"")]
    n, fps, biggest = len(entries), 20, max(map(len, pictures))
    avih = struct.pack("<14I", 1_000_000 // fps, 0, 0, 0x10, n, 0, 1, biggest, 64, 48,
                       0, 0, 0, 0)
    strh = b"vidsMJPG" + struct.pack("<IHHIIIIIIII4h", 0, 0, 0, 0, 1, fps, 0, n, biggest,
                                     0xFFFFFFFF, 0, 0, 0, 64, 48)
    strf = struct.pack("<IiiHH4sIiiII", 40, 64, 48, 1, 24, b"MJPG", 64 * 48 * 3, 0, 0, 0, 0)
    movi, index, offset = b"", b"", 4
    for e in entries:
        c = chunk(b"00dc", e)
        index += b"00dc" + struct.pack("<III", 0x10 if e else 0, offset, len(e))
        movi += c
        offset += len(c)
    body = (b"AVI " + listed(b"hdrl", chunk(b"avih", avih) + listed(
        b"strl", chunk(b"strh", strh) + chunk(b"strf", strf)))
        + listed(b"movi", movi) + chunk(b"idx1", index))
    path = tmp_path / "drop.avi"
    path.write_bytes(chunk(b"RIFF", body))
    cap = cv2.VideoCapture(str(path))
    assert cap.get(cv2.CAP_PROP_FRAME_COUNT) == 20  # what made it "cut short"
    cap.release()
    held = _decoded(path)
    assert len(held) == len(frames)
    return path, held
