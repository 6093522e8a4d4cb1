"""Shared test fixtures: paths to the real data in ../shared/data and the paper's rig."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
SHARED_DATA = (REPO / ".." / "shared" / "data").resolve()


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data not found at {SHARED_DATA}")
    return SHARED_DATA


@pytest.fixture(scope="session")
def estec_rig():  # type: ignore[no-untyped-def]
    from trackmeter.data.rigfile import load_rig

    return load_rig(REPO / "config" / "rigs" / "estec_12mm.yaml")


@pytest.fixture(scope="session")
def estec_sim_frames():  # type: ignore[no-untyped-def]
    """(rig, the first 60 frames of the default ``sim`` source: the estec scenario), rendered
    once per test session for the tests that run the tracker or the engine over real frames."""
    from trackmeter.sources import open_source

    source = open_source("sim", render_ahead=False)
    try:
        frames = [source.read() for _ in range(60)]
    finally:
        source.close()
    return source.rig, frames
