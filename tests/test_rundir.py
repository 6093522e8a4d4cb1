"""The run directory writer: contract columns, coasted poses counted in the summary."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from trackmeter.data.atomic import AppendFile
from trackmeter.data.motion_csv import STATES_COLUMNS, read_motion_csv
from trackmeter.data.rundir import (POSE_COVARIANCE_COLUMNS, RESERVE_NAME, RunWriter, check_run_directory,
                                    read_pose_covariance)
from trackmeter.data.trajectory import read_tum
from trackmeter.errors import TrackmeterError
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


def test_the_summary_says_when_the_poses_were_coasted(tmp_path: Path) -> None:
    # Coasted poses are valid rows like measured ones, and the summary only counted them: a
    # reader of the files could not tell which were coasted (a new user's probe).
    writer = RunWriter(tmp_path / "run", {}, {"spec": "test"})
    for t, coasting in ((0.0, 0.0), (0.04, 0.04), (0.08, 0.08), (0.12, 0.0), (0.16, 0.04), (0.2, -1), (0.24, 0.12)):
        writer.write_frame(t, (), PoseEstimate.invalid("lost") if coasting < 0 else _pose(coasting))
    writer.close("complete")
    summary = yaml.safe_load((tmp_path / "run" / "run.yaml").read_text())["summary"]
    assert summary["coasted_frames"] == 4
    assert summary["coasted_spans_s"] == [[0.04, 0.08], [0.16, 0.16], [0.24, 0.24]]


def test_each_valid_pose_s_covariance_is_written_beside_the_trajectory(tmp_path: Path) -> None:
    # A pose carries its covariance (issue 5), and the console showed it, but a track run
    # folder held none: states.csv's columns are a contract, so it goes to a file of its own,
    # one row per line of trajectory.tum, the 6x6 matrix's upper triangle.
    rng = np.random.default_rng(3)
    covs = []
    writer = RunWriter(tmp_path / "run", {}, {"spec": "test"})
    for k in range(4):
        A = rng.normal(size=(6, 6)) * np.array([1e-3] * 3 + [1e-2] * 3)
        cov = A @ A.T
        pose = _pose(0.0)
        pose = PoseEstimate(True, None, "b", pose.T_cam_body, cov, np.zeros(3), np.zeros(3), 5)
        writer.write_frame(0.04 * k, (), pose if k != 2 else PoseEstimate.invalid("fewer than 3 points"))
        if k != 2:
            covs.append(cov)
    writer.close("complete")
    path = tmp_path / "run" / "pose_covariance.csv"
    assert path.read_text().splitlines()[0] == ",".join(POSE_COVARIANCE_COLUMNS)
    assert POSE_COVARIANCE_COLUMNS[:3] == ("t", "x_x", "x_y") and POSE_COVARIANCE_COLUMNS[-1] == "rz_rz"
    assert len(POSE_COVARIANCE_COLUMNS) == 1 + 21
    t_s, cov = read_pose_covariance(path)
    np.testing.assert_array_equal(t_s, read_tum(tmp_path / "run" / "trajectory.tum").t_s)
    np.testing.assert_allclose(cov, np.array(covs), rtol=1e-8, atol=0)
    np.testing.assert_array_equal(cov, np.transpose(cov, (0, 2, 1)))


@pytest.mark.parametrize("how", ["removed", "replaced"])
def test_a_run_folder_removed_while_writing_is_said_and_not_made_again(tmp_path: Path, how: str) -> None:
    """``rm -rf RUN`` while ``track`` wrote there: the open files went on into the deleted
    folder, the closing run.yaml made a new folder holding only itself with "complete", and the
    run exited 0; every row was lost without a word."""
    import shutil

    out = tmp_path / "run"
    writer = RunWriter(out, {}, {"spec": "test"})
    writer.write_frame(0.00, (), _pose(0.0))
    shutil.rmtree(out)
    if how == "replaced":
        out.mkdir()
    with pytest.raises(TrackmeterError, match=r"run: the run folder was removed or replaced while the run wrote to it; "
                                              r"the 1 frame written there is lost"):
        writer.write_frame(0.04, (), _pose(0.0))
    assert writer.folder_lost
    with pytest.raises(TrackmeterError, match="removed or replaced"):
        writer.close("write failed")
    assert (not out.exists()) if how == "removed" else (list(out.iterdir()) == [])


def test_a_run_folder_removed_before_its_first_frame_says_nothing_was_written(tmp_path: Path) -> None:
    """It said "the 0 frames written there are lost"."""
    import shutil

    out = tmp_path / "run"
    writer = RunWriter(out, {}, {"spec": "test"})
    shutil.rmtree(out)
    with pytest.raises(TrackmeterError) as info:
        writer.write_frame(0.00, (), _pose(0.0))
    assert str(info.value) == (f"{out}: the run folder was removed or replaced while the run wrote to it, before its "
                               "first frame")


def test_a_valid_states_row_has_every_field_and_a_pose_without_rates_stays_in_the_trajectory(tmp_path: Path) -> None:
    """states.csv's valid rows read like groundtruth.csv rows (DESIGN 6: "same meanings"): a pose
    whose rates are not estimated yet is valid 0 there, its pose filled in, and still a line of
    trajectory.tum (valid poses)."""
    import csv

    from dataclasses import replace

    no_rates = replace(_pose(0.0), velocity_cam_m_s=np.full(3, np.nan), omega_body_rad_s=np.full(3, np.nan))
    writer = RunWriter(tmp_path / "run", {}, {"spec": "test"})
    writer.write_frame(0.00, (), PoseEstimate.invalid("fewer than 3 points"))
    writer.write_frame(0.04, (), no_rates, latency_ms=12.0)
    writer.write_frame(0.08, (), _pose(0.0), latency_ms=11.0)
    writer.close("complete")
    with (tmp_path / "run" / "states.csv").open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["valid"] for r in rows] == ["0", "0", "1"]
    assert rows[0]["x"] == "" and rows[0]["vx"] == ""
    assert float(rows[1]["z"]) == 3.5 and rows[1]["vx"] == rows[1]["wz"] == ""
    assert all(math.isfinite(float(rows[2][c])) for c in STATES_COLUMNS)  # every field a number
    tum = [ln for ln in (tmp_path / "run" / "trajectory.tum").read_text().splitlines() if not ln.startswith("#")]
    assert [float(ln.split()[0]) for ln in tum] == [0.04, 0.08]
    summary = yaml.safe_load((tmp_path / "run" / "run.yaml").read_text())["summary"]
    assert summary["valid_frames"] == 2 and summary["rates_pending_frames"] == 1


def test_a_target_id_with_a_comma_or_quote_stays_one_csv_field(tmp_path: Path) -> None:
    """Model ids come from other tools' files; csv readers must get the row's columns back."""
    import csv

    from trackmeter.core.targets import TargetState

    def target(tid: str) -> TargetState:
        return TargetState(tid, "model", "tracking", np.array([10.0, 20.0]), np.array([5.0, 20.0]),
                           np.array([0.1, 0.2, 3.5]), np.eye(3) * 1e-6, 0.97, np.array([10.0, 20.0]),
                           (0.0, 0.0, 1.0, 1.0))

    ids = ["plain", 'wing "north", c0', "a,b"]
    writer = RunWriter(tmp_path / "run", {}, {"spec": "test"})
    writer.write_frame(0.0, tuple(target(i) for i in ids), _pose(0.0))
    writer.close("complete")
    with (tmp_path / "run" / "targets.csv").open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["id"] for r in rows] == ids
    assert all(r["state"] == "tracking" and float(r["z"]) == 3.5 for r in rows)
    first = (tmp_path / "run" / "targets.csv").read_text().splitlines()[1]
    assert first.split(",")[1] == "plain"  # ordinary ids are written as before, unquoted


def test_an_append_lands_whole_or_not_at_all(tmp_path: Path, full_disk) -> None:  # type: ignore[no-untyped-def]
    path = tmp_path / "rows.csv"
    f = AppendFile(path, "a,b\n")
    f.append("1,2\n")
    full_disk(5)  # room for one row and a bit of the next
    f.append("3,4\n")
    with pytest.raises(TrackmeterError, match=r"rows\.csv: cannot write \(No space left on device\)"):
        f.append("5,6\n")
    f.close()
    assert path.read_text() == "a,b\n1,2\n3,4\n"


def test_a_frame_that_cannot_be_written_whole_is_taken_back_from_every_file(tmp_path: Path, full_disk) -> None:  # type: ignore[no-untyped-def]
    """A disk that fills mid-frame: the frame's states row and trajectory line (written before
    its targets' rows failed) come out again, so every file holds the same whole frames."""
    from trackmeter.core.targets import TargetState

    writer = RunWriter(tmp_path / "run", {}, {"spec": "test"})
    target = TargetState("t1", "auto", "tracking", np.array([10.0, 20.0]), np.array([5.0, 20.0]),
                         np.array([0.1, 0.2, 3.5]), np.eye(3) * 1e-6, 0.97, np.array([10.0, 20.0]), (0.0, 0.0, 1.0, 1.0))
    writer.write_frame(0.00, (target,), _pose(0.0))
    before = {name: (tmp_path / "run" / name).read_text()
              for name in ("states.csv", "trajectory.tum", "pose_covariance.csv", "targets.csv")}
    disk = full_disk(0)
    for free in range(0, 900, 7):  # the disk fills at every byte offset of the next frame
        disk.free = free
        try:
            writer.write_frame(0.04, (target,), _pose(0.0))
        except TrackmeterError as exc:
            assert "No space left on device" in str(exc)
            after = {name: (tmp_path / "run" / name).read_text() for name in before}
            assert after == before and writer.frames == 1 and writer.valid_frames == 1
        else:
            break
    else:
        pytest.fail("the frame never fitted")
    disk.free = 10**6
    writer.close("complete")
    states = read_motion_csv(tmp_path / "run" / "states.csv")
    assert len(states) == 2 and len(read_tum(tmp_path / "run" / "trajectory.tum").t_s) == 2
    assert len((tmp_path / "run" / "targets.csv").read_text().splitlines()) == 3
    assert len(read_pose_covariance(tmp_path / "run" / "pose_covariance.csv")[0]) == 2


def test_a_run_that_cannot_even_start_leaves_nothing(tmp_path: Path, full_disk) -> None:  # type: ignore[no-untyped-def]
    full_disk(10)  # run.yaml is written (not through AppendFile), the CSV headers are not
    with pytest.raises(TrackmeterError, match="No space left on device"):
        RunWriter(tmp_path / "run", {}, {"spec": "test"})
    assert not (tmp_path / "run").exists()
    (tmp_path / "mine").mkdir()
    with pytest.raises(TrackmeterError):
        RunWriter(tmp_path / "mine", {}, {"spec": "test"})
    assert (tmp_path / "mine").is_dir() and not any((tmp_path / "mine").iterdir())  # the user's folder stays


def test_a_folder_with_a_runs_files_but_no_run_yaml_is_not_overwritten_silently(tmp_path: Path) -> None:
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "states.csv").write_text("my own\n")
    with pytest.raises(TrackmeterError, match=r"holds states\.csv already .*--overwrite"):
        check_run_directory(tmp_path / "mine")
    assert check_run_directory(tmp_path / "mine", overwrite=True) == tmp_path / "mine"
    with pytest.raises(TrackmeterError, match="name is empty"):
        check_run_directory("")


@pytest.mark.parametrize("where", ["/proc/no-such-run", "/proc/no-such/run"])
def test_a_folder_the_filesystem_refuses_is_told_before_the_run_even_as_root(where: str) -> None:
    # /proc refuses a new folder whoever asks; the permission bits let root (CI runs as root)
    # through, so only asking the filesystem tells it before the source is opened.
    with pytest.raises(TrackmeterError, match=r"cannot create a run folder there \(/proc is not a writable folder\)"):
        check_run_directory(where)


def test_the_write_check_leaves_nothing_behind(tmp_path: Path) -> None:
    assert check_run_directory(tmp_path / "new" / "run") == tmp_path / "new" / "run"
    assert check_run_directory(tmp_path) == tmp_path
    assert list(tmp_path.iterdir()) == []


def test_a_written_attitude_keeps_its_quaternion_sign_as_the_body_turns_past_half_a_turn(tmp_path: Path) -> None:
    """q and -q are the same rotation; qw >= 0 on every line would flip all four components where
    a tumble passes 180 deg. Each written quaternion is the sign nearer the one written before (the
    first with qw >= 0), so a plot or a finite difference of the file sees no jump; the rotations
    are unchanged (scipy's)."""
    from dataclasses import replace

    from scipy.spatial.transform import Rotation

    angles = np.radians(np.arange(0.0, 400.0, 10.0))
    R = Rotation.from_rotvec(angles[:, None] * np.array([0.0, 0.6, 0.8])).as_matrix()
    writer = RunWriter(tmp_path / "run", {}, {"spec": "test"})
    for i, R_i in enumerate(R):
        T = np.eye(4)
        T[:3, :3] = R_i
        pose = PoseEstimate.invalid("gap") if i == 20 else replace(_pose(0.0), T_cam_body=T)
        writer.write_frame(0.04 * i, (), pose)
    writer.close("complete")
    traj = read_tum(tmp_path / "run" / "trajectory.tum")
    q = traj.quat_wxyz
    assert q[0, 0] > 0.0
    assert np.all(np.sum(q[1:] * q[:-1], axis=1) > 0.9)  # neighbours on one side, across the gap too
    kept = np.delete(np.arange(len(R)), 20)
    np.testing.assert_allclose(Rotation.from_quat(q, scalar_first=True).as_matrix(), R[kept], atol=1e-9)
    states = read_motion_csv(tmp_path / "run" / "states.csv")
    np.testing.assert_allclose(states.quat_wxyz[kept], q, atol=1e-9)


def test_a_second_run_cannot_write_into_a_folder_a_run_is_writing_even_with_overwrite(tmp_path: Path) -> None:
    """Two `track --overwrite` into one folder at once truncated each other's files (NUL holes,
    rows of both runs, run.yaml saying complete): the folder is locked while a run writes it.
    The lock goes with the writer (closed, or its process gone), so a later run may overwrite."""
    import subprocess
    import sys

    first = RunWriter(tmp_path / "run", {}, {"spec": "first"})
    first.write_frame(0.0, (), _pose(0.0))
    with pytest.raises(TrackmeterError, match="another run is writing"):
        RunWriter(tmp_path / "run", {}, {"spec": "second"}, overwrite=True)
    # Another process is refused too (flock is per open file, not per process).
    code = ("import sys; from trackmeter.data.rundir import RunWriter; from trackmeter.errors import TrackmeterError\n"
            "try:\n    RunWriter(sys.argv[1], {}, {'spec': 'other'}, overwrite=True)\n"
            "except TrackmeterError as e:\n    print(e); sys.exit(3)\n")
    proc = subprocess.run([sys.executable, "-c", code, str(tmp_path / "run")], capture_output=True, text=True)
    assert proc.returncode == 3 and "another run is writing" in proc.stdout, proc.stdout + proc.stderr
    first.write_frame(0.04, (), _pose(0.0))
    first.close("complete")
    assert yaml.safe_load((tmp_path / "run" / "run.yaml").read_text())["source"]["spec"] == "first"
    assert len(read_tum(tmp_path / "run" / "trajectory.tum").t_s) == 2
    RunWriter(tmp_path / "run", {}, {"spec": "third"}, overwrite=True).close("complete")


def test_the_run_folder_s_lock_is_dropped_whatever_closing_or_opening_fails(tmp_path: Path, monkeypatch) -> None:
    """A close whose flush fails, or an open that fails after the lock, must not keep the folder
    locked for the life of the process (the console runs for hours)."""
    import trackmeter.data.rundir as rundir

    writer = RunWriter(tmp_path / "run", {}, {"spec": "first"})

    def failing_close() -> None:
        raise TrackmeterError("flush failed")

    monkeypatch.setattr(writer._states, "close", failing_close)
    with pytest.raises(TrackmeterError, match="flush failed"):
        writer.close("complete")
    RunWriter(tmp_path / "run", {}, {"spec": "second"}, overwrite=True).close("complete")  # not locked

    def failing_open(self, *args) -> None:  # type: ignore[no-untyped-def]
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(rundir.RunWriter, "_open", failing_open)
    with pytest.raises(OSError):
        RunWriter(tmp_path / "new", {}, {"spec": "third"})
    assert not (tmp_path / "new").exists()  # made by it, removed by it
    monkeypatch.undo()
    RunWriter(tmp_path / "new", {}, {"spec": "fourth"}).close("complete")


def test_an_overwrite_that_cannot_start_leaves_the_earlier_run_whole(tmp_path: Path, monkeypatch) -> None:
    """--overwrite whose new run.yaml cannot be written (a full disk) removed the earlier run's
    files, which it had not touched yet, leaving nothing (a code review). Only what the new
    writer began is taken back."""
    import trackmeter.data.rundir as rundir

    first = RunWriter(tmp_path / "run", {}, {"spec": "first"})
    first.write_frame(0.0, (), _pose(0.0))
    first.close("complete")
    (tmp_path / "run" / "notes.txt").write_text("mine")
    before = {p.name: p.read_bytes() for p in (tmp_path / "run").iterdir()}

    def full(self) -> None:  # type: ignore[no-untyped-def]
        raise TrackmeterError("run.yaml: cannot write (No space left on device)")

    monkeypatch.setattr(rundir.RunWriter, "_write_meta", full)
    with pytest.raises(TrackmeterError, match="No space"):
        RunWriter(tmp_path / "run", {}, {"spec": "second"}, overwrite=True)
    assert {p.name: p.read_bytes() for p in (tmp_path / "run").iterdir()} == before


def test_the_final_run_yaml_is_written_in_the_space_held_for_it(tmp_path: Path, monkeypatch) -> None:
    """A disk the rows filled left run.yaml saying "running" (its final write failed too). The
    writer holds a reserve of at least the first run.yaml's size from the start; on ENOSPC it
    is released and run.yaml written in its place; a run that ends well removes it too."""
    import errno

    import trackmeter.data.rundir as rundir

    import os

    writer = RunWriter(tmp_path / "run", {"big": "x" * 5000}, {"spec": "test"})
    reserve = writer._reserve
    assert reserve is not None and reserve.held
    first = (tmp_path / "run" / "run.yaml").stat().st_size
    assert os.fstat(reserve._fd).st_size >= first + 16 * 1024  # type: ignore[arg-type]
    assert not (tmp_path / "run" / rundir.RESERVE_NAME).exists()  # held by a descriptor, not a name
    writer.write_frame(0.0, (), _pose(0.0))
    real = rundir.write_text_atomic
    tries = []

    def full_unless_released(path, text):  # type: ignore[no-untyped-def]
        tries.append(reserve.held)
        if reserve.held:  # the disk is full until the reserve gives its space back
            raise OSError(errno.ENOSPC, "No space left on device")
        real(path, text)

    monkeypatch.setattr(rundir, "write_text_atomic", full_unless_released)
    writer.close("write failed", {"note": "disk full"})
    assert tries == [True, False]
    meta = yaml.safe_load((tmp_path / "run" / "run.yaml").read_text())
    assert meta["status"] == "write failed" and meta["summary"]["frames"] == 1
    assert not reserve.held
    monkeypatch.undo()
    other = RunWriter(tmp_path / "other", {}, {"spec": "test"})
    other.close("complete")
    assert sorted(p.name for p in (tmp_path / "other").iterdir()) == ["pose_covariance.csv", "run.yaml", "states.csv",
                                                                       "targets.csv", "trajectory.tum"]


def test_a_run_killed_outright_leaves_only_its_files(tmp_path: Path) -> None:
    """SIGKILL (the OOM killer, ``kill -9``) gives a run no time to tidy up: the space reserve
    must not be a file left behind in the run folder (it was: a hidden 38 KB
    ``.run.yaml.reserve``), and the frames written before the kill stay readable."""
    import signal
    import subprocess
    import sys

    out = tmp_path / "run"
    child = (
        "import os, signal, sys\n"
        "sys.path[:0] = [sys.argv[2]]\n"
        "from tests.test_rundir import _pose\n"
        "from trackmeter.data.rundir import RunWriter\n"
        "writer = RunWriter(sys.argv[1], {'big': 'x' * 5000}, {'spec': 'test'})\n"
        "for k in range(3):\n"
        "    writer.write_frame(0.04 * k, (), _pose(0.0))\n"
        "os.kill(os.getpid(), signal.SIGKILL)\n"
    )
    root = str(Path(__file__).resolve().parents[1])
    proc = subprocess.run([sys.executable, "-c", child, str(out), root], capture_output=True, text=True, timeout=120)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    assert sorted(p.name for p in out.iterdir()) == ["pose_covariance.csv", "run.yaml", "states.csv", "targets.csv",
                                                     "trajectory.tum"]
    assert yaml.safe_load((out / "run.yaml").read_text())["status"] == "running"
    assert len(read_motion_csv(out / "states.csv")) == 3


def test_a_run_that_fills_a_real_disk_ends_with_its_status(tmp_path: Path, capsys) -> None:
    """On a real full disk (a 160 KB tmpfs; skipped where mounting is not allowed) `track`
    stops at the first frame that does not fit, every row before it whole, and run.yaml says
    "write failed" with the summary (before: "running")."""
    import subprocess

    from trackmeter.cli.main import main

    disk = tmp_path / "disk"
    disk.mkdir()
    try:
        mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=160k", "tmpfs", str(disk)],
                                 capture_output=True).returncode == 0
    except OSError:  # no mount command
        mounted = False
    if not mounted:
        pytest.skip("mounting a tmpfs is not allowed here")
    try:
        out = disk / "run"
        code = main(["track", "--source", "sim", "--auto", "8", "--max-frames", "150", "--out", str(out)])
        err = capsys.readouterr().err
        assert code == 2 and "No space left on device): run stopped; run.yaml says so" in err, err
        meta = yaml.safe_load((out / "run.yaml").read_text())
        assert meta["status"] == "write failed" and 0 < meta["summary"]["frames"] < 150
        assert len(read_motion_csv(out / "states.csv")) == meta["summary"]["frames"]
        assert not (out / RESERVE_NAME).exists()
    finally:
        subprocess.run(["umount", "-l", str(disk)], capture_output=True)


def test_a_reserve_the_disk_cannot_hold_is_refused_and_leaves_nothing(tmp_path: Path, full_disk) -> None:
    from trackmeter.data.atomic import SpaceReserve

    disk = full_disk(1000)
    # The error names the folder and what the bytes are for, not the hidden name they are
    # written under for a moment (the message was ".../.run.yaml.reserve: cannot write").
    with pytest.raises(TrackmeterError, match=rf"^{re.escape(str(tmp_path))}: cannot set aside 4000 bytes for "
                                              r"the last words \(No space left on device\)$"):
        SpaceReserve(tmp_path / ".reserve", 4000, "the last words")
    assert not (tmp_path / ".reserve").exists() and disk.free == 1000  # its part given back
    held = SpaceReserve(tmp_path / ".reserve", 600)
    assert not (tmp_path / ".reserve").exists() and disk.free == 400  # held by a descriptor, not a name
    assert held.release() and not held.release() and disk.free == 1000


def test_a_folder_holding_other_files_is_not_a_run_folder(tmp_path: Path) -> None:
    # track --out / (or --out . in a busy folder) wrote run.yaml and three CSVs among whatever
    # was there; simulate refuses any folder that is not empty.
    busy = tmp_path / "busy"
    (busy / "notes").mkdir(parents=True)
    (busy / "photo.png").write_bytes(b"x")
    for overwrite in (False, True):
        with pytest.raises(TrackmeterError, match=r"busy: holds other files \(notes, photo\.png\); a run folder is "
                                                  r"new, empty or an earlier run's: choose another --out"):
            check_run_directory(busy, overwrite)
    # A folder of run files without run.yaml (a run killed before its first write; an evaluate
    # report), hidden files, and an earlier run's folder with the user's notes beside the run
    # are run folders still.
    run = tmp_path / "run"
    run.mkdir()
    for name in ("states.csv", "report.md", "summary.json", "position_error.png", ".DS_Store"):
        (run / name).write_text("")
    assert check_run_directory(run, overwrite=True) == run
    (run / "run.yaml").write_text("")
    (run / "notes.txt").write_text("mine")
    assert check_run_directory(run, overwrite=True) == run
    # An evaluate report's folder, no run in it, is no run folder: track wrote a run beside
    # the report, and --overwrite deleted the report (an outside probe).
    report = tmp_path / "report"
    report.mkdir()
    for name in ("report.md", "summary.json", "errors.csv"):
        (report / name).write_text("")
    for overwrite in (False, True):
        with pytest.raises(TrackmeterError, match=r"report: holds other files \(errors\.csv, report\.md, summary\.json\)"):
            check_run_directory(report, overwrite)


@pytest.mark.parametrize("status, replaced", [("nothing to track", False), ("no frame", False),
                                              ("complete", True), ("interrupted", True)])
def test_an_overwrite_refused_on_its_first_frame_keeps_the_earlier_run(tmp_path: Path, status: str,
                                                                        replaced: bool) -> None:
    """`track --target 1,1 --out run --overwrite` (the pixel refused: nothing to track, exit 2)
    replaced a complete earlier run and its report with one frame (an outside probe). A new run
    that ends without having tracked (nothing to track, no frame) gives the earlier one back,
    report included; one that tracked replaces it, as --overwrite asked."""
    first = RunWriter(tmp_path / "run", {}, {"spec": "first"})
    for k in range(3):
        first.write_frame(0.04 * k, (), _pose(0.0))
    first.close("complete")
    (tmp_path / "run" / "report.md").write_text("the first run's report")
    (tmp_path / "run" / "notes.txt").write_text("mine")
    before = {p.name: p.read_bytes() for p in (tmp_path / "run").iterdir()}
    second = RunWriter(tmp_path / "run", {}, {"spec": "second"}, overwrite=True)
    second.write_frame(0.0, (), _pose(0.0))
    second.close(status)
    after = {p.name: p.read_bytes() for p in (tmp_path / "run").iterdir()}
    if replaced:
        assert "report.md" not in after and after["notes.txt"] == b"mine"
        assert yaml.safe_load(after["run.yaml"])["source"]["spec"] == "second"
        assert len(read_motion_csv(tmp_path / "run" / "states.csv")) == 1
    else:
        assert after == before and second.kept_earlier_run


def test_an_overwrite_stopped_before_its_first_frame_or_killed_keeps_the_earlier_run(tmp_path: Path) -> None:
    """A Ctrl-C before the first frame replaced a complete run with an empty one, and after a
    `kill -9` of an --overwrite run the next --overwrite deleted the earlier run it had set
    aside and gave back the killed, empty one (an outside probe)."""
    first = RunWriter(tmp_path / "run", {}, {"spec": "first"})
    for k in range(3):
        first.write_frame(0.04 * k, (), _pose(0.0))
    first.close("complete")
    before = {p.name: p.read_bytes() for p in (tmp_path / "run").iterdir() if p.is_file()}
    stopped = RunWriter(tmp_path / "run", {}, {"spec": "stopped"}, overwrite=True)
    stopped.close("interrupted")
    assert stopped.kept_earlier_run
    assert {p.name: p.read_bytes() for p in (tmp_path / "run").iterdir() if p.is_file()} == before
    # killed outright: the earlier run waits in .previous-run, run.yaml says running
    killed = RunWriter(tmp_path / "run", {}, {"spec": "killed"}, overwrite=True)
    killed._release_lock()  # its process gone
    assert (tmp_path / "run" / ".previous-run" / "run.yaml").is_file()
    nothing = RunWriter(tmp_path / "run", {}, {"spec": "next"}, overwrite=True)
    nothing.write_frame(0.0, (), _pose(0.0))
    nothing.close("nothing to track")
    assert {p.name: p.read_bytes() for p in (tmp_path / "run").iterdir() if p.is_file()} == before


def test_a_run_folder_moved_while_writing_is_followed(tmp_path: Path) -> None:
    """``mv RUN RUN.moved`` while ``track`` wrote there: its rows went on into the moved folder,
    and the run stopped saying "the 82 frames written there are lost", the moved folder's
    run.yaml left saying "running" (an outside probe). The writer follows the folder: the run
    goes on there, said once, and closes there."""
    import warnings

    out, moved = tmp_path / "run", tmp_path / "run.moved"
    writer = RunWriter(out, {}, {"spec": "test"})
    writer.write_frame(0.00, (), _pose(0.0))
    out.rename(moved)
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        writer.write_frame(0.04, (), _pose(0.0))
        writer.write_frame(0.08, (), _pose(0.0))
    assert [str(w.message) for w in said] == [f"{out}: the run folder was moved to {moved} while the run wrote to it; "
                                              "the run goes on there"]
    writer.close("complete")
    assert writer.directory == moved and not out.exists()
    meta = yaml.safe_load((moved / "run.yaml").read_text())
    assert meta["status"] == "complete" and meta["summary"]["frames"] == 3
    assert len((moved / "states.csv").read_text().splitlines()) == 4


def test_an_overwrite_whose_writes_failed_keeps_the_earlier_run_beside_it(tmp_path: Path) -> None:
    """`track --overwrite` onto a nearly full disk: the new run stopped after 29 frames ("write
    failed") and the complete earlier run was deleted, unsaid (an outside probe). A run whose
    writes failed is no replacement asked for: the earlier one stays in PREVIOUS_RUN, and the
    writer says where."""
    from trackmeter.data.rundir import PREVIOUS_RUN

    first = RunWriter(tmp_path / "run", {}, {"spec": "first"})
    for k in range(3):
        first.write_frame(0.04 * k, (), _pose(0.0))
    first.close("complete")
    second = RunWriter(tmp_path / "run", {}, {"spec": "second"}, overwrite=True)
    second.write_frame(0.0, (), _pose(0.0))
    second.close("write failed")
    kept = tmp_path / "run" / PREVIOUS_RUN
    assert second.earlier_run_kept_in == kept
    assert yaml.safe_load((kept / "run.yaml").read_text())["status"] == "complete"
    assert len(read_motion_csv(kept / "states.csv")) == 3
    assert yaml.safe_load((tmp_path / "run" / "run.yaml").read_text())["status"] == "write failed"


def test_a_covariance_that_is_no_number_is_written_empty_and_read_as_nan(tmp_path: Path) -> None:
    # The writer gives a value that is not a number as an empty field (as in states.csv); the
    # reader refused the whole file for it (an outside probe).
    writer = RunWriter(tmp_path / "run", {}, {"spec": "test"})
    cov = np.eye(6) * 1e-6
    cov[0, 0] = np.nan
    for k, c in enumerate((np.eye(6) * 1e-6, cov)):
        pose = _pose(0.0)
        writer.write_frame(0.04 * k, (), PoseEstimate(True, None, "b", pose.T_cam_body, c, np.zeros(3), np.zeros(3), 5))
    writer.close("complete")
    t_s, read = read_pose_covariance(tmp_path / "run" / "pose_covariance.csv")
    assert len(t_s) == 2 and np.isnan(read[1, 0, 0]) and read[1, 1, 1] == 1e-6
    np.testing.assert_array_equal(read[0], np.eye(6) * 1e-6)


def _old_report(folder: Path) -> dict[Path, bytes]:
    files = {folder / "summary.json": b"old summary\n", folder / "errors.csv": b"old errors\n"}
    for path, data in files.items():
        path.write_bytes(data)
    return files


def test_several_files_written_as_one_are_left_as_they_were_when_a_target_is_a_folder(tmp_path: Path) -> None:
    # A report folder whose report.md had become a folder: the files renamed before it were
    # replaced, its temporary file was left behind, and os.replace's error escaped (an outside
    # code review).
    from trackmeter.data.atomic import write_files_atomic

    old = _old_report(tmp_path)
    (tmp_path / "report.md").mkdir()
    new = {path: b"new\n" for path in [*old, tmp_path / "report.md", tmp_path / "z.csv"]}
    with pytest.raises(TrackmeterError, match=r"report\.md: cannot write: it is a folder"):
        write_files_atomic(new)
    assert {p: p.read_bytes() for p in old} == old
    assert sorted(p.name for p in tmp_path.iterdir()) == ["errors.csv", "report.md", "summary.json"]


def test_several_files_written_as_one_are_put_back_when_a_rename_fails(tmp_path: Path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    import os

    import trackmeter.data.atomic as atomic

    old = _old_report(tmp_path)
    renames = []

    def replace_failing_third(src, dst):  # type: ignore[no-untyped-def]
        renames.append(dst)
        if len(renames) == 3:
            raise OSError(5, "Input/output error")
        os.rename(src, dst)

    monkeypatch.setattr(atomic.os, "replace", replace_failing_third)
    new = {tmp_path / "summary.json": b"new\n", tmp_path / "new.png": b"new\n", tmp_path / "errors.csv": b"new\n"}
    with pytest.raises(TrackmeterError, match=r"errors\.csv: cannot write: Input/output error"):
        atomic.write_files_atomic(new)
    monkeypatch.undo()
    assert {p: p.read_bytes() for p in old} == old
    assert sorted(p.name for p in tmp_path.iterdir()) == ["errors.csv", "summary.json"]
    atomic.write_files_atomic(new)
    assert all(p.read_bytes() == b"new\n" for p in new) and len(list(tmp_path.iterdir())) == 3
