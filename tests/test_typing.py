"""The type hints hold: mypy, with the settings in pyproject.toml ([tool.mypy]: trackmeter,
console, benchmarks and examples), finds no error.

The package ships ``py.typed``, so its hints are a promise to every program that imports it;
unchecked, they had drifted to 351 errors (2026-12-07), a few of which hid a None that a path
could reach. mypy is in the test extra (pinned), so this runs wherever the tests do, except
where numpy, OpenCV or viser is older than the versions whose type stubs it was checked against:
their stubs judge the same lines differently (numpy 2.0's finds 19 errors the current one does
not), which says nothing of this code.
"""

from __future__ import annotations

import re
import subprocess
import sys
from importlib.metadata import version
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent

pytestmark = pytest.mark.slow

#: The distributions whose stubs the check was made with, and their versions (major, minor).
CHECKED_WITH = {"numpy": (2, 4), "opencv-python-headless": (5, 1), "viser": (1, 1)}


def _older_stubs() -> list[str]:
    older = []
    for name, wanted in CHECKED_WITH.items():
        have = version(name)
        if tuple(int(x) for x in re.findall(r"\d+", have)[:2]) < wanted:
            older.append(f"{name} {have} (checked with {wanted[0]}.{wanted[1]})")
    return older


def test_mypy_finds_no_error(tmp_path: Path) -> None:
    if older := _older_stubs():
        pytest.skip("type stubs older than those checked against: " + ", ".join(older))
    # The cache in tmp_path: a checkout's tests write nothing into it.
    run = subprocess.run([sys.executable, "-m", "mypy", "--cache-dir", str(tmp_path / "mypy_cache")],
                         cwd=REPO, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stdout[-6000:] + run.stderr[-2000:]
