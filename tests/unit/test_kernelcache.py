"""Cached kernels stay consistent with the sources: numba keys a kernel's cache on its own
module's stamp only, and would load a caller compiled with the old code of a callee from
another module (:mod:`vistrack.common.vision.kernelcache`)."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

from vistrack.common.vision import kernelcache

INIT = """\
import os
from pathlib import Path
from . import a, b
if os.environ.get("REFRESH") == "1":
    from vistrack.common.vision.kernelcache import refresh
    refresh((a, b), Path(__file__).parent)
"""
CALLER = """\
import numba as nb
from .a import value
@nb.njit(cache=True)
def twice():
    return 2 * value()
"""


def _callee(pkg: Path, value: int) -> None:
    path = pkg / "a.py"
    path.write_text(f"import numba as nb\n@nb.njit(cache=True)\ndef value():\n    return {value}\n")
    # a new stamp for numba even within the file system's time resolution
    stamp = time.time() + value
    os.utime(path, (stamp, stamp))


def _twice(root: Path, refresh: bool) -> int:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(root), *sys.path]),
           "NUMBA_CACHE_DIR": str(root / "cache"), "REFRESH": "1" if refresh else "0"}
    out = subprocess.run([sys.executable, "-c", "import toykernels; print(toykernels.b.twice())"],
                         env=env, capture_output=True, text=True, timeout=120, check=True)
    return int(out.stdout.split()[-1])


def _package(root: Path) -> Path:
    pkg = root / "toykernels"
    pkg.mkdir()
    (pkg / "__init__.py").write_text(INIT)
    (pkg / "b.py").write_text(CALLER)
    return pkg


def _scenario(root: Path, refresh: bool) -> list[int]:
    """``twice()`` with the callee returning 1, then twice with it changed to return 5."""
    root.mkdir()
    pkg = _package(root)
    _callee(pkg, 1)
    first = _twice(root, refresh)
    _callee(pkg, 5)
    return [first, _twice(root, refresh), _twice(root, refresh)]


def test_a_changed_callee_reaches_its_cached_caller(tmp_path):
    # numba alone: the caller's cache still holds the old callee (what refresh is for; if
    # this starts failing, numba tracks callees itself and kernelcache may go)
    assert _scenario(tmp_path / "plain", refresh=False) == [2, 2, 2], \
        "numba now recompiles the caller itself"
    # with refresh at import: the new callee's value, then from the new cache
    assert _scenario(tmp_path / "fresh", refresh=True) == [2, 10, 10]


def test_the_package_stamps_its_cache_and_drops_kernels_of_other_sources(tmp_path):
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    code = ("import sys, vistrack.common.vision as v\n"
            "from vistrack.common.vision.kernelcache import cache_dirs\n"
            "print(*cache_dirs([sys.modules['vistrack.common.vision.ssd']]))")
    run = [sys.executable, "-c", code]
    (directory,) = subprocess.run(run, env=env, capture_output=True, text=True, timeout=120,
                                  check=True).stdout.split()
    directory_path = Path(directory)
    stamp = directory_path / kernelcache.STAMP
    digest = kernelcache.sources_digest(Path(kernelcache.__file__).parent)
    assert stamp.read_text() == digest
    # kernels of other sources (another version of the package), and a file of another
    # module, which stays
    stale = [directory_path / "ssd._refine-1.py311.1.nbc", directory_path / "pyramid.x-2.py311.nbi"]
    other = directory_path / "elsewhere.f-1.py311.nbi"
    for path in (*stale, other):
        path.write_bytes(b"old")
    stamp.write_text("an older version")
    subprocess.run(run, env=env, capture_output=True, text=True, timeout=120, check=True)
    assert not any(p.exists() for p in stale)
    assert other.exists()
    assert stamp.read_text() == digest
    # stamped alike: nothing is removed
    stale[0].write_bytes(b"kept")
    subprocess.run(run, env=env, capture_output=True, text=True, timeout=120, check=True)
    assert stale[0].exists()


TARGET = """\
import os, sys
if sys.argv[1] == "numba-first":
    import numba  # numba imported (its settings read) before the package
import vistrack.common.vision  # noqa: F401
from numba.core.registry import cpu_target
features = cpu_target.target_context.codegen().magic_tuple()[2].split(",")
print("-prefer-256-bit" in features, os.environ.get("NUMBA_CPU_FEATURES") is not None)
"""


def _host_features() -> list[str]:
    import llvmlite.binding as ll

    return ll.get_host_cpu_features().flatten().split(",")


def _target(order: str, **env: str) -> tuple[bool, bool]:
    """In a new interpreter (numba imported before the package if ``order`` says so) with the
    environment less numba's target variables plus ``env``: whether numba's code generator
    has ``prefer-256-bit`` turned off, and whether NUMBA_CPU_FEATURES is set."""
    base = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CPU_FEATURES",
                                                             "NUMBA_CPU_NAME")}
    out = subprocess.run([sys.executable, "-c", TARGET, order], capture_output=True, text=True,
                         timeout=120, env={**base, **env}, check=True).stdout.split()
    return out[0] == "True", out[1] == "True"


def test_kernels_are_compiled_for_the_full_vector_width_of_an_avx512_core():
    """On an AVX-512 core, the code generator numba starts for the package's kernels has LLVM's
    ``prefer-256-bit`` tuning turned off (kernelcache.prefer_full_vectors), whether numba
    was imported before the package or not; elsewhere numba's defaults stay."""
    avx512 = "+avx512bw" in _host_features()
    for order in ("package-first", "numba-first"):
        assert _target(order) == (avx512, avx512), order


def test_a_users_numba_cpu_features_win():
    """``NUMBA_CPU_FEATURES`` set by the user (here the host's own, which keeps 256 bits) is
    left as it is."""
    assert _target("package-first",
                   NUMBA_CPU_FEATURES=",".join(_host_features())) == (False, True)
