"""Every string in the project's sources is text that UTF-8 can hold.

A docstring spelling a surrogate escape (``\\udce9``, as a file name in another encoding is
held) compiles on Python 3.11 and 3.12, but 3.13 encodes docstrings to UTF-8 when it cleans
them at compile time: the import failed with "surrogates not allowed", and with it every
command (vistrack demo: exit 2) and 12 test modules, on a fresh machine with Python 3.13."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SOURCES = sorted(p for top in ("common", "services", "tests") for p in (ROOT / top).rglob("*.py"))


def test_the_sources_are_found():
    assert len(SOURCES) > 100 and ROOT / "common" / "sources.py" in SOURCES


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_string_constant_encodes_as_utf8(path):
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            try:
                node.value.encode("utf-8")
            except UnicodeEncodeError as e:
                pytest.fail(f"{path.relative_to(ROOT)}:{node.lineno}: a string Python 3.13 "
                            f"cannot compile ({e.reason}: {node.value[e.start:e.end]!r}); "
                            "escape the backslash")
