"""House rule: the algorithm modules import neither zenoh nor msgpack."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PURE = sorted((ROOT / "common" / "vision").glob("*.py"))
FORBIDDEN = {"zenoh", "msgpack"}


@pytest.mark.parametrize("path", PURE, ids=lambda p: p.name)
def test_no_forbidden_import_in_source(path):
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
        names = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module:
            names = [node.module]
        for name in names:
            assert name.split(".")[0] not in FORBIDDEN, f"{path.name} imports {name}"


def test_importing_the_vision_package_loads_neither():
    code = ("import sys, vistrack.common.vision, vistrack.common.vision.tracker;"
            "print(','.join(sorted(m for m in ('zenoh', 'msgpack') if m in sys.modules)))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.strip()
    assert out == ""
    assert len(PURE) >= 5
