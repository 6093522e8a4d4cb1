"""The type hints hold: mypy, with the settings in pyproject.toml ([tool.mypy]: trackmeter,
console and benchmarks), finds no error.

The package ships ``py.typed``, so its hints are a promise to every program that imports it;
unchecked, they had drifted to 351 errors (2026-12-07), a few of which hid a None that a path
could reach. mypy is in the test extra, so this runs wherever the tests do.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent

pytestmark = pytest.mark.slow


def test_mypy_finds_no_error(tmp_path: Path) -> None:
    # The cache in tmp_path: a checkout's tests write nothing into it.
    run = subprocess.run([sys.executable, "-m", "mypy", "--cache-dir", str(tmp_path / "mypy_cache")],
                         cwd=REPO, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stdout[-6000:] + run.stderr[-2000:]
