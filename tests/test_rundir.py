"""The run directory writer: contract columns, coasted poses counted in the summary."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from trackmeter.data.rundir import RunWriter
from trackmeter.data.motion_csv import STATES_COLUMNS
from trackmeter.pipeline.snapshot import PoseEstimate


def _pose(coasting_s: float) -> PoseEstimate:
    T = np.eye(4)
    T[:3, 3] = (0.1, -0.2, 3.5)
    return PoseEstimate(True, "coasting 0.2 s" if coasting_s else None, "b", T, np.eye(6) * 1e-6,
                        np.zeros(3), np.zeros(3), 0 if coasting_s else 5, (), coasting_s)


def test_coasted_poses_are_valid_rows_and_counted_in_the_summary(tmp_path: Path) -> None:
    writer = RunWriter(tmp_path / "run", {}, {"spec": "test"})
    writer.write_frame(0.00, (), _pose(0.0))
    writer.write_frame(0.04, (), _pose(0.04))
    writer.write_frame(0.08, (), _pose(0.08))
    writer.write_frame(0.12, (), PoseEstimate.invalid("fewer than 3 points"))
    writer.close("complete")
    header = (tmp_path / "run" / "states.csv").read_text().splitlines()[0]
    assert header == ",".join(STATES_COLUMNS)  # the contract's columns, nothing added
    summary = yaml.safe_load((tmp_path / "run" / "run.yaml").read_text())["summary"]
    assert summary["frames"] == 4 and summary["valid_frames"] == 3 and summary["coasted_frames"] == 2
    tum = [ln for ln in (tmp_path / "run" / "trajectory.tum").read_text().splitlines() if not ln.startswith("#")]
    assert len(tum) == 3
