"""numba's on-disk kernels kept consistent with the code that made them.

numba caches each ``cache=True`` kernel under its module's source stamp (the file's time and
size) alone, but a kernel's compiled code holds the code of every kernel it calls, inlined or
linked in. When a callee's module changes and the caller's does not (an upgrade that changed
only :mod:`.ssd`), numba loads the caller with the old callee inside it: the tracker runs the
old refinement without a word (seen here: a change to ``ssd._refine`` left every kernel of
:mod:`.pyramid` as it was, and a change that did not even compile went unnoticed). So the
package stamps the cache directories its kernels use with a digest of all its sources (and of
numba and Python); at import, a directory stamped otherwise loses this package's cached
kernels, which then compile afresh (~30 s once, as on a first run).
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import sys
import types
from collections.abc import Iterable, Iterator
from pathlib import Path

#: The stamp file in each cache directory: the digest of the sources its kernels came from.
STAMP = "vistrack-kernels.stamp"
#: LLVM's tuning flag that keeps loops on AVX-512 cores to 256-bit vectors (see
#: :func:`prefer_full_vectors`)
PREFER_256 = "prefer-256-bit"


def prefer_full_vectors() -> str | None:
    """Let numba vectorise the kernels' loops 512 bits wide on a core with AVX-512; returns
    the feature string set, or None where nothing was changed.

    LLVM tunes every AVX-512 core of Intel's since Skylake-SP to prefer 256-bit vectors (its
    ``prefer-256-bit`` tuning flag): the kernels' integer sums then take 8 lanes a vector,
    not 16. numba compiles for the host's features, or for ``NUMBA_CPU_FEATURES`` where set:
    this sets that to the host's features less the flag, before numba's code generator starts
    (at the first compile or cache load). The default tracker's frames whose features were
    held took 233 us against 253 (the wide sub-pixel window 81 us against 102; the bench's
    frames, interleaved, best of 40 rounds, 2026-12-05); the integer sums are exact and no
    kernel uses fastmath, so every output is the same bit for bit. Nothing is changed where
    the core has no AVX-512BW or where ``NUMBA_CPU_FEATURES`` or ``NUMBA_CPU_NAME`` is set
    (yours wins: ``NUMBA_CPU_FEATURES`` set to the host's features keeps 256 bits). Where
    numba's code generator already started (numba compiled something before this package was
    imported), its target stays as it was in this process; processes started from it get the
    setting."""
    if "NUMBA_CPU_FEATURES" in os.environ or "NUMBA_CPU_NAME" in os.environ:
        return None
    try:
        import llvmlite.binding as ll

        features = ll.get_host_cpu_features().flatten()
    except (RuntimeError, ImportError):  # a host LLVM cannot describe: numba's defaults
        return None
    if "+avx512bw" not in features.split(","):
        return None
    wanted = f"{features},-{PREFER_256}"
    os.environ["NUMBA_CPU_FEATURES"] = wanted
    numba = sys.modules.get("numba")
    if numba is not None:  # imported before: its settings read again (they are at compile)
        numba.core.config.reload_config()
    return wanted


def sources_digest(package_dir: Path) -> str:
    """A digest of every ``.py`` file of ``package_dir`` (names and contents), numba's version
    and Python's."""
    import numba

    h = hashlib.sha256(f"{numba.__version__} {sys.version}".encode())
    for path in sorted(package_dir.glob("*.py")):
        h.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()


def cache_dirs(modules: Iterable[types.ModuleType]) -> set[Path]:
    """The directories numba caches the ``cache=True`` kernels of ``modules`` in."""
    from numba.core.dispatcher import Dispatcher

    dirs = set()
    for module in modules:
        for obj in vars(module).values():
            if isinstance(obj, Dispatcher) and obj.__module__ == module.__name__:
                path = getattr(getattr(obj, "_cache", None), "_cache_path", None)
                if path:
                    dirs.add(Path(path))
    return dirs


@contextlib.contextmanager
def _locked(directory: Path) -> Iterator[None]:
    """An exclusive lock on ``directory``'s stamp (processes starting together: one clears,
    the others then find the new stamp)."""
    try:
        import fcntl
    except ImportError:  # not POSIX: no lock
        yield
        return
    with open(directory / (STAMP + ".lock"), "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def refresh(modules: Iterable[types.ModuleType], package_dir: Path) -> list[Path]:
    """Remove the cached kernels of ``modules`` (all of ``package_dir``) from each of their
    cache directories stamped with another digest than :func:`sources_digest`'s, and stamp
    it; returns the files removed. Call it after the modules are imported and before any
    kernel runs: a dispatcher reads its cache at its first call. A directory that cannot be
    written is left alone (numba cannot cache there either)."""
    modules = list(modules)
    digest = sources_digest(package_dir)
    names = {m.__name__.rsplit(".", 1)[-1] for m in modules}
    removed: list[Path] = []
    for directory in sorted(cache_dirs(modules)):
        stamp = directory / STAMP
        try:
            if stamp.read_text() == digest:
                continue
        except OSError:
            pass
        try:
            directory.mkdir(parents=True, exist_ok=True)
            with _locked(directory):
                with contextlib.suppress(OSError):
                    if stamp.read_text() == digest:
                        continue  # another process refreshed it meanwhile
                for path in directory.iterdir():
                    if (path.suffix in (".nbi", ".nbc")
                            and path.name.split(".", 1)[0] in names):
                        path.unlink(missing_ok=True)
                        removed.append(path)
                tmp = directory / f"{STAMP}.{os.getpid()}"
                tmp.write_text(digest)
                os.replace(tmp, stamp)
        except OSError:
            continue
    return removed
