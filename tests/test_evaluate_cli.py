"""``trackmeter evaluate`` end to end: files in, exact figures out; bad input -> one line, exit 2."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys

from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from trackmeter.cli.main import main
from trackmeter.data.motion_csv import STATES_COLUMNS, MotionSeries, write_groundtruth_csv, write_states_csv
from trackmeter.data.trajectory import Trajectory, write_tum

from tests.test_metrics import tumbling_truth


# TUM files keep 9 decimals, so figures read through one are exact to ~1e-9.
TUM_EPS = 1e-8


def _tum(path, s: MotionSeries):
    return write_tum(path, Trajectory(s.t_s, s.position_m, s.quat_wxyz))


def _run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture()
def sequence_and_run(tmp_path):
    """A sequence folder with groundtruth.tum/.csv and a run dir whose states.csv has a known
    error: +2 mm in x, 0.5 deg about the viewing axis, +1 mm/s in z, and frame 10 invalid."""
    truth = tumbling_truth()
    seq = tmp_path / "seq"
    _tum(seq / "groundtruth.tum", truth)
    write_groundtruth_csv(seq / "groundtruth.csv", truth)
    n = len(truth)
    r = Rotation.from_rotvec([0, 0, math.radians(0.5)]) * Rotation.from_quat(truth.quat_wxyz, scalar_first=True)
    valid = np.ones(n, bool)
    valid[10] = False
    extra = {"n_tracked": np.full(n, 6.0), "n_lost": np.zeros(n), "latency_ms": np.full(n, 10.0)}
    est = MotionSeries(truth.t_s, valid, truth.position_m + [0.002, 0, 0], r.as_quat(scalar_first=True),
                       truth.velocity_cam_m_s + [0, 0, 0.001], truth.omega_body_rad_s, extra)
    run = tmp_path / "run"
    write_states_csv(run / "states.csv", est)
    return truth, seq, run


def test_run_dir_against_sequence_json_is_exact(capsys, sequence_and_run, tmp_path):
    truth, seq, run = sequence_and_run
    code, out, err = _run(capsys, "evaluate", "--truth", str(seq / "groundtruth.tum"), "--estimate", str(run), "--json")
    assert code == 0, err
    s = json.loads(out)
    assert list(s) == ["matched", "unmatched", "pose_coverage", "position_m", "attitude_rad", "velocity_m_s", "omega_rad_s", "speed_score",
                       "body_offset", "settings"]
    assert s["settings"]["truth"].startswith(str(seq / "groundtruth.tum")) and s["settings"]["estimate"] == str(run / "states.csv")
    assert s["matched"] == 59 and s["unmatched"] == 1  # the invalid frame
    assert s["position_m"]["x"] == pytest.approx({"rms": 0.002, "max": 0.002, "p95": 0.002}, abs=TUM_EPS)
    assert s["position_m"]["y"]["max"] < TUM_EPS
    assert s["attitude_rad"]["z"]["rms"] == pytest.approx(math.radians(0.5), abs=TUM_EPS)
    assert s["attitude_rad"]["total"]["max"] == pytest.approx(math.radians(0.5), abs=TUM_EPS)
    assert s["velocity_m_s"]["z"]["p95"] == pytest.approx(0.001, abs=TUM_EPS)
    assert s["omega_rad_s"]["norm"]["max"] < TUM_EPS
    keep = np.arange(60) != 10
    expected = math.radians(0.5) + np.mean(0.002 / np.linalg.norm(truth.position_m[keep], axis=1))
    assert s["speed_score"] == pytest.approx(expected, abs=TUM_EPS)
    # The sequence folder as --truth (its exact groundtruth.csv) gives the same figures.
    code, out2, _ = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run), "--json")
    assert code == 0
    s2 = json.loads(out2)
    assert s2.pop("settings")["truth"] == str(seq / "groundtruth.csv") and s.pop("settings")
    assert _flat(s2) == pytest.approx(_flat(s), abs=TUM_EPS)


def test_a_run_dir_evaluates_the_poses_of_its_trajectory_tum(capsys, sequence_and_run, tmp_path):
    # A run writes its first poses, before the velocity fit has its window, as valid-0 rows
    # that carry the pose with the rates empty, and as lines of trajectory.tum. Both files of
    # one run must give the same pose figures; the velocity figures come from the valid rows.
    truth, seq, _ = sequence_and_run
    n = len(truth)
    pending = (np.arange(n) >= 20) & (np.arange(n) < 25)  # rates still unknown
    declared_invalid = np.arange(n) == 10  # valid 0 with every field filled in: not a pose
    r = Rotation.from_rotvec([0, 0, math.radians(0.5)]) * Rotation.from_quat(truth.quat_wxyz, scalar_first=True)
    v = np.where(pending[:, None], np.nan, truth.velocity_cam_m_s + [0, 0, 0.001])
    est = MotionSeries(truth.t_s, ~(pending | declared_invalid), truth.position_m + [0.002, 0, 0],
                       r.as_quat(scalar_first=True), v, np.where(pending[:, None], np.nan, truth.omega_body_rad_s))
    run = tmp_path / "run"
    write_states_csv(run / "states.csv", est)
    poses = ~declared_invalid
    write_tum(run / "trajectory.tum", Trajectory(est.t_s[poses], est.position_m[poses], est.quat_wxyz[poses]))
    code, out, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run), "--json")
    assert code == 0 and err == "", err  # the pending rows are valid 0: nothing to warn about
    from_run = json.loads(out)
    code, out, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run / "trajectory.tum"), "--json")
    assert code == 0, err
    from_tum = json.loads(out)
    code, out, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run / "states.csv"), "--json")
    assert code == 0 and err == "", err
    from_csv = json.loads(out)
    assert from_run["matched"] == from_tum["matched"] == from_csv["matched"] == n - 1
    for key in ("position_m", "attitude_rad"):
        assert _flat(from_run[key]) == pytest.approx(_flat(from_tum[key]), abs=TUM_EPS)
        assert _flat(from_csv[key]) == pytest.approx(_flat(from_tum[key]), abs=TUM_EPS)
    assert from_run["velocity_m_s"]["z"]["max"] == pytest.approx(0.001, abs=TUM_EPS)
    assert from_tum["velocity_m_s"] is None and from_tum["omega_rad_s"] is None
    # One shape whatever the estimate: what a TUM file cannot give is null, not missing.
    assert list(from_tum) == list(from_run) == list(from_csv)


@pytest.mark.parametrize("damage", ["cut", "removed", "cut_at_a_line"])
def test_a_track_runs_trajectory_that_cannot_be_read_is_said_to_leave_poses_out(capsys, sequence_and_run, tmp_path,
                                                                               damage: str) -> None:
    """A run folder whose trajectory.tum was cut short (its last line half written) evaluated
    without a word, 10 poses fewer and other figures than the intact folder (an outside probe):
    the poses only that file declares are left out, and now it says so."""
    truth, seq, _ = sequence_and_run
    n = len(truth)
    pending = (np.arange(n) >= 20) & (np.arange(n) < 25)
    v = np.where(pending[:, None], np.nan, truth.velocity_cam_m_s)
    est = MotionSeries(truth.t_s, ~pending, truth.position_m, truth.quat_wxyz, v,
                       np.where(pending[:, None], np.nan, truth.omega_body_rad_s))
    run = tmp_path / "run"
    write_states_csv(run / "states.csv", est)
    tum = write_tum(run / "trajectory.tum", Trajectory(est.t_s, est.position_m, est.quat_wxyz))
    (run / "run.yaml").write_text("status: complete\nsource: {case: b}\n")
    if damage == "cut":
        tum.write_bytes(tum.read_bytes()[:-20])
    elif damage == "cut_at_a_line":  # whole lines, the poses up to t[21] (an outside probe: no word)
        tum.write_text("".join(tum.read_text().splitlines(keepends=True)[:23]))
    else:
        tum.unlink()
    code, out, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run), "--json")
    assert code == 0, err
    if damage == "cut":  # its last line cut mid-way: the poses before it are read, and that is said
        assert json.loads(out)["matched"] == n
        assert "trajectory.tum" in err and "the last line is cut short, left out" in err, err
        return
    left_out = 3 if damage == "cut_at_a_line" else 5
    assert json.loads(out)["matched"] == n - left_out
    assert "trajectory.tum" in err and f"the {left_out} poses logged before the rates were known" in err, err
    assert "left out" in err and len(err.strip().splitlines()) == 1, err


def test_a_states_csv_without_a_trajectory_counts_only_its_valid_rows(capsys, sequence_and_run, tmp_path):
    # Another producer may write a held or predicted pose in its valid-0 rows, with the rates
    # empty: without a trajectory.tum that lists those poses as valid, they are not scored.
    truth, seq, _ = sequence_and_run
    n = len(truth)
    held = (np.arange(n) >= 20) & (np.arange(n) < 30)
    pos = np.where(held[:, None], [9.0, 9.0, 9.0], truth.position_m + [0.002, 0, 0])
    nan3 = np.full((n, 3), np.nan)
    est = MotionSeries(truth.t_s, ~held, pos, truth.quat_wxyz,
                       np.where(held[:, None], nan3, truth.velocity_cam_m_s), np.where(held[:, None], nan3, truth.omega_body_rad_s))
    run = tmp_path / "other"
    write_states_csv(run / "states.csv", est)
    for estimate in (run, run / "states.csv"):
        code, out, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(estimate), "--json")
        # Not a track run (no run.yaml): nothing is missing, but the rows left out are said. A
        # track run's states.csv copied alone scored 10 poses fewer than its folder, unsaid (an
        # outside probe).
        assert code == 0 and err.count("\n") == 1 and "10 rows with a pose but valid 0 left out" in err, err
        s = json.loads(out)
        assert s["matched"] == n - 10
        assert s["position_m"]["x"]["max"] == pytest.approx(0.002, abs=TUM_EPS)


def _flat(tree, prefix=""):
    if isinstance(tree, dict):
        return {k: v for key, sub in tree.items() for k, v in _flat(sub, f"{prefix}{key}.").items()}
    return {prefix: tree}


def test_bare_tum_files_give_pose_metrics_only_and_out_dir(capsys, tmp_path):
    truth = tumbling_truth()
    _tum(tmp_path / "a" / "truth.tum", truth)
    _tum(tmp_path / "b" / "est.tum", MotionSeries.from_trajectory(
        Trajectory(truth.t_s + 0.003, truth.position_m + [0, 0, -0.004], truth.quat_wxyz)))
    out_dir = tmp_path / "report"
    code, out, err = _run(capsys, "evaluate", "--truth", str(tmp_path / "a" / "truth.tum"),
                          "--estimate", str(tmp_path / "b" / "est.tum"), "--out", str(out_dir))
    assert code == 0, err
    assert "position [mm]" in out and "4.000" in out  # human summary in mm
    s = json.loads((out_dir / "summary.json").read_text())
    assert s["velocity_m_s"] is None and s["position_m"]["z"]["max"] == pytest.approx(0.004, abs=1e-9)
    csv = np.loadtxt(out_dir / "errors.csv", delimiter=",", skiprows=1)
    assert csv.shape == (60, 10)
    np.testing.assert_allclose(csv[:, 3], -0.004, atol=1e-9)
    report = (out_dir / "report.md").read_text()
    assert "±5 mm" in report and "viewing" in report
    # summary.json says what was compared and how, so it reads alone (as --json prints it)
    assert s["settings"] == {"truth": str(tmp_path / "a" / "truth.tum"), "estimate": str(tmp_path / "b" / "est.tum"),
                             "align": "none", "settle_s": 0.0, "tolerance_s": 0.01, "case": None}
    assert (out_dir / "position_error.png").stat().st_size > 1000
    assert (out_dir / "attitude_error.png").is_file()


def test_the_report_names_the_body_axes_of_the_angular_velocity(capsys, sequence_and_run, tmp_path):
    """omega is in the body frame (DESIGN.md section 3), whose axes are not the camera's lateral
    and viewing axes: the paper table names them as body axes."""
    truth, seq, run = sequence_and_run
    code, out, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run), "--out", str(tmp_path / "r"))
    assert code == 0, err
    rows = [line for line in (tmp_path / "r" / "report.md").read_text().splitlines() if line.startswith("| angular")]
    assert [row.split("|")[2].strip() for row in rows] == ["x body", "y body", "z body"]
    velocity = [line for line in (tmp_path / "r" / "report.md").read_text().splitlines() if line.startswith("| linear")]
    assert [row.split("|")[2].strip() for row in velocity] == ["x lateral", "y lateral", "z viewing"]


def test_help_says_the_linear_velocity_is_in_the_camera_frame(capsys):
    with pytest.raises(SystemExit):
        main(["evaluate", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "linear velocity errors (camera frame" in text and "angular velocity errors (body frame" in text


def test_an_estimate_mostly_unpaired_is_warned_about_with_both_spans(capsys, tmp_path):
    """Timestamps in nanoseconds against seconds pair only t = 0: the figures then describe one
    pose, so the evaluation says so (one warning line with both time spans); it still runs."""
    truth = tumbling_truth()
    t = truth.t_s - truth.t_s[0]  # from 0, as a recording's clock: t = 0 pairs in both units
    _tum(tmp_path / "truth.tum", MotionSeries.from_trajectory(Trajectory(t, truth.position_m, truth.quat_wxyz)))
    _tum(tmp_path / "est.tum", MotionSeries.from_trajectory(Trajectory(t * 1e9, truth.position_m, truth.quat_wxyz)))
    code, out, err = _run(capsys, "evaluate", "--truth", str(tmp_path / "truth.tum"), "--estimate",
                          str(tmp_path / "est.tum"), "--settle", "0")
    assert code == 0 and "matched 1 pose" in out
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("trackmeter evaluate: warning: the time spans barely overlap"), err
    assert "1 of 60 estimated poses paired" in lines[0] and "units" in lines[0]
    # No such warning for the same clock at other rates, nor for a truth over part of the run
    # (that one only says how many poses fall past the truth's end).
    sub = MotionSeries.from_trajectory(Trajectory(t[::3], truth.position_m[::3], truth.quat_wxyz[::3]))
    _tum(tmp_path / "sparse.tum", sub)
    half = MotionSeries.from_trajectory(Trajectory(t[:30], truth.position_m[:30], truth.quat_wxyz[:30]))
    _tum(tmp_path / "half.tum", half)
    for truth_file in ("truth.tum", "sparse.tum", "half.tum"):
        code, out, err = _run(capsys, "evaluate", "--truth", str(tmp_path / truth_file), "--estimate",
                              str(tmp_path / "truth.tum"))
        assert code == 0 and "barely overlap" not in err, (truth_file, err)
        assert ("30 pose(s) after the truth's end are not evaluated" in err if truth_file == "half.tum"
                else err == ""), (truth_file, err)
    # Nor for a short run (here a single pose) within a long truth, every pose of it paired.
    one = MotionSeries.from_trajectory(Trajectory(t[5:6], truth.position_m[5:6], truth.quat_wxyz[5:6]))
    _tum(tmp_path / "one.tum", one)
    code, out, err = _run(capsys, "evaluate", "--truth", str(tmp_path / "truth.tum"), "--estimate",
                          str(tmp_path / "one.tum"), "--settle", "0")
    assert code == 0 and "matched 1 pose" in out and err == "", err


def test_align_body_recovers_offset_through_the_cli(capsys, tmp_path):
    truth = tumbling_truth()
    R_X = Rotation.from_rotvec([0.3, 2.5, -0.7])
    t_X = np.array([0.1, -0.02, 0.3])
    R = Rotation.from_quat(truth.quat_wxyz, scalar_first=True)
    est = Trajectory(truth.t_s, truth.position_m + R.apply(t_X), (R * R_X).as_quat(scalar_first=True))
    _tum(tmp_path / "t.tum", truth)
    write_tum(tmp_path / "e.tum", est)
    code, out, _ = _run(capsys, "evaluate", "--truth", str(tmp_path / "t.tum"), "--estimate", str(tmp_path / "e.tum"),
                        "--align", "body", "--json")
    s = json.loads(out)
    assert code == 0
    # TUM keeps 9 decimals, so the recovered offset is exact to ~1e-9.
    assert s["position_m"]["norm"]["max"] < 1e-6 and s["attitude_rad"]["total"]["max"] < 1e-6
    # and the offset itself is in the JSON (it was in report.md only: an outside probe)
    offset = s["body_offset"]["T_bodytrue_bodyest"]
    assert offset["translation_m"] == pytest.approx(t_X, abs=1e-6)
    assert offset["rotation_vector_rad"] == pytest.approx(R_X.as_rotvec(), abs=1e-6)
    code, out, _ = _run(capsys, "evaluate", "--truth", str(tmp_path / "t.tum"), "--estimate", str(tmp_path / "e.tum"), "--json")
    assert json.loads(out)["attitude_rad"]["total"]["max"] > 1.0
    assert json.loads(out)["body_offset"] is None  # every key is always there


def _write(path, text):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda d: (_write(d / "t.tum", ""), d / "t.tum"), "no poses"),
        (lambda d: (_write(d / "t.tum", "0 1 2 3\n"), d / "t.tum"), "expected 8 values"),
        (lambda d: (_write(d / "t.tum", "t,x,y\n0,1,2\n"), d / "t.tum"), "header lacks"),
        (lambda d: (_write(d / "t.png", "\x89PNG\r\n\x1a\n\x00\x00garbage"), d / "t.png"), ""),
        (lambda d: (_write(d / "t.tum", "5.0 0 0 3 0 0 0 1\n"), None), "no overlapping timestamps"),
        (lambda d: (d / "missing.tum", None), "no such file"),
        (lambda d: (Path(os.devnull), None), "not a regular file"),
        (lambda d: ((d / "emptydir").mkdir(), d / "emptydir"), "no groundtruth"),
        # a run's states.csv given as the truth, without one valid pose
        (lambda d: (_write(d / "s.csv", ",".join(STATES_COLUMNS) + "\n0.0,0" + "," * (len(STATES_COLUMNS) - 2) + "\n"),
                    d / "s.csv"), "no valid pose"),
    ],
)
def test_bad_truth_is_one_line_and_exit_2(capsys, tmp_path, make, message):
    good = _tum(tmp_path / "good.tum", tumbling_truth())
    made = make(tmp_path)
    truth = made[1] if made[1] is not None else made[0]
    code, out, err = _run(capsys, "evaluate", "--truth", str(truth), "--estimate", str(good))
    assert code == 2
    assert err.count("\n") == 1 and err.startswith("trackmeter evaluate: error:") and message in err
    assert "Traceback" not in err and out == ""


def test_bad_estimate_run_dirs(capsys, tmp_path):
    truth = _tum(tmp_path / "t.tum", tumbling_truth())
    (tmp_path / "run").mkdir()
    code, _, err = _run(capsys, "evaluate", "--truth", str(truth), "--estimate", str(tmp_path / "run"))
    assert code == 2 and "not a run directory" in err
    _write(tmp_path / "run" / "states.csv", ",".join(STATES_COLUMNS) + "\n0.0,0" + "," * (len(STATES_COLUMNS) - 2) + "\n")
    code, _, err = _run(capsys, "evaluate", "--truth", str(truth), "--estimate", str(tmp_path / "run"))
    assert code == 2 and "no valid pose" in err
    code, _, err = _run(capsys, "evaluate", "--truth", str(truth), "--estimate", str(truth), "--tolerance", "-1")
    assert code == 2 and "--tolerance" in err


@pytest.mark.parametrize("option, value", [("--settle", "inf"), ("--settle", "nan"), ("--settle", "-1"),
                                           ("--tolerance", "100"), ("--tolerance", "nan"),
                                           # 0 paired only the poses whose float seconds came out
                                           # equal: 41 of 78 on an outside probe's recording
                                           ("--tolerance", "0")])
def test_options_are_held_to_the_range_their_config_key_has(capsys, sequence_and_run, option, value):
    # --tolerance 100 and --settle inf were taken although evaluate.tolerance_s goes to 10 s and
    # settle_s to 1e6 s (an outside code review): an option is checked as its key in a --config.
    _, seq, run = sequence_and_run
    code, _, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run), option, value)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and f"{option}: expected a value in [" in lines[0], err


def test_a_run_without_a_valid_pose_says_why_its_poses_were_invalid(capsys, tmp_path):
    """An outside probe got "no valid pose in the run" for a case (b) run that bound no model
    point: true, but the reason `track` gave for most of its frames, kept in run.yaml, says what
    to do about it."""
    truth = _tum(tmp_path / "t.tum", tumbling_truth())
    run = tmp_path / "run"
    _write(run / "states.csv", ",".join(STATES_COLUMNS) + "\n0.0,0" + "," * (len(STATES_COLUMNS) - 2) + "\n")
    reasons = {"the first frame": 1, "case (b): binding the model: none is a target yet: target them by id": 4}
    _write(run / "run.yaml", yaml.safe_dump({"source": {"case": "b"}, "summary": {"invalid_reasons": reasons}}))
    code, _, err = _run(capsys, "evaluate", "--truth", str(truth), "--estimate", str(run))
    assert code == 2 and err.count("\n") == 1
    assert err.strip().endswith("no valid pose in the run (4 of its 5 frames: case (b): binding the model: "
                                "none is a target yet: target them by id)"), err
    _write(run / "run.yaml", "summary: [unreadable\n")  # no reasons to give: the plain message
    code, _, err = _run(capsys, "evaluate", "--truth", str(truth), "--estimate", str(run))
    assert code == 2 and err.strip().endswith("no valid pose in the run"), err


def test_an_estimate_that_is_no_regular_file_is_named_as_such(capsys, tmp_path):
    truth = _tum(tmp_path / "t.tum", tumbling_truth())
    code, _, err = _run(capsys, "evaluate", "--truth", str(truth), "--estimate", os.devnull)
    assert code == 2 and err.count("\n") == 1 and "not a regular file" in err


def test_console_script_exit_code(tmp_path):
    """The installed entry point gives exit 2 and one line, not a traceback."""
    proc = subprocess.run([sys.executable, "-m", "trackmeter.cli.main", "evaluate", "--truth", str(tmp_path / "x.tum"),
                           "--estimate", str(tmp_path / "y.tum")], capture_output=True, text=True)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "no such file" in proc.stderr


def test_settle_counts_from_the_start_of_the_run(capsys, tmp_path):
    """A run whose first second has no pose: --settle 2 skips poses before t0 + 2 s of the run,
    not 2 s after the first pose."""
    truth = tumbling_truth()  # t = 2.0, 2.08, ...
    valid = truth.t_s >= 3.0
    p = truth.position_m.copy()
    p[truth.t_s < 4.0] += 0.01  # settling errors until t = 4.0 s = run start + 2 s
    est = MotionSeries(truth.t_s, valid, np.where(valid[:, None], p, np.nan),
                       np.where(valid[:, None], truth.quat_wxyz, np.nan),
                       truth.velocity_cam_m_s, truth.omega_body_rad_s)
    write_states_csv(tmp_path / "run" / "states.csv", est)
    _tum(tmp_path / "truth.tum", truth)
    code, out, err = _run(capsys, "evaluate", "--truth", str(tmp_path / "truth.tum"), "--estimate", str(tmp_path / "run"),
                          "--settle", "2", "--json")
    assert code == 0, err
    s = json.loads(out)
    assert s["matched"] == int(np.count_nonzero(truth.t_s >= 4.0 - 1e-9))
    assert s["position_m"]["norm"]["max"] < TUM_EPS


def test_unwritable_out_is_one_line_and_exit_2(capsys, sequence_and_run):
    """An --out the OS refuses (here: a folder under /proc) is the user's input, not a bug:
    one line naming the path and the reason, exit 2, no traceback."""
    _, seq, run = sequence_and_run
    code, _, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run), "--out", "/proc/nope")
    assert code == 2
    assert err == "trackmeter evaluate: error: /proc/nope: cannot create a report folder there (/proc is not a writable folder)\n"
    assert len(err.strip().splitlines()) == 1


def test_stdout_closed_early_gives_no_traceback(sequence_and_run):
    """``evaluate --json | head -c 10``: the reader goes away before the summary is written;
    the command ends quietly (the docs' recipe: exit 1, nothing on stderr)."""
    _, seq, run = sequence_and_run
    proc = subprocess.Popen([sys.executable, "-m", "trackmeter.cli.main", "evaluate", "--truth", str(seq),
                             "--estimate", str(run), "--json"], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()  # long before the interpreter has even started: every write meets a closed pipe
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 1
    assert err == ""


@pytest.fixture()
def run_in_own_body_frame(tmp_path):
    """A sequence and a run whose poses are the truth's exactly, referred to a body frame of its
    own (rotated 30 deg, origin 0.2 m away), as a case (a) or (c) run's are."""
    truth = tumbling_truth()
    seq = tmp_path / "seq"
    write_groundtruth_csv(seq / "groundtruth.csv", truth)
    R_true_own = Rotation.from_rotvec([0.3, -0.4, 0.2])
    t_true_own = np.array([0.1, -0.15, 0.08])
    R = Rotation.from_quat(truth.quat_wxyz, scalar_first=True)
    est = MotionSeries(truth.t_s, np.ones(len(truth), bool), truth.position_m + R.apply(t_true_own),
                       (R * R_true_own).as_quat(scalar_first=True), np.full((len(truth), 3), np.nan),
                       np.full((len(truth), 3), np.nan), {})
    run = tmp_path / "run"
    write_states_csv(run / "states.csv", est)
    return seq, run


@pytest.mark.parametrize("case", ["a", "c"])
def test_a_case_a_or_c_run_is_aligned_to_the_true_body_by_default(capsys, run_in_own_body_frame, tmp_path, case):
    # Such a run's body frame is its own: compared as it is, its position errors measure where
    # that frame sits (hundreds of mm), which a newcomer takes for the tracking error.
    seq, run = run_in_own_body_frame
    (run / "run.yaml").write_text(f"status: complete\nsource:\n  spec: sim\n  case: {case}\n")
    for estimate in (run, run / "states.csv"):
        code, out, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(estimate), "--json")
        assert code == 0 and err == "", err
        s = json.loads(out)
        assert s["settings"]["align"] == "body" and s["settings"]["case"] == case
        assert s["position_m"]["norm"]["max"] < 1e-6 and s["attitude_rad"]["total"]["max"] < 1e-6
    # Asked for explicitly, "none" is done as asked, with the warning.
    code, out, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run), "--align", "none", "--json")
    assert code == 0 and "--align body" in err, err
    s = json.loads(out)
    assert s["settings"]["align"] == "none" and s["position_m"]["norm"]["max"] > 0.1
    # So is a config's choice.
    config = tmp_path / "evaluate.yaml"
    config.write_text("evaluate:\n  align: none\n")
    code, out, err = _run(capsys, "evaluate", "--config", str(config), "--truth", str(seq), "--estimate", str(run), "--json")
    assert code == 0 and "--align body" in err, err
    assert json.loads(out)["settings"]["align"] == "none"
    code, out, err = _run(capsys, "evaluate", "--config", str(config), "--truth", str(seq), "--estimate", str(run),
                          "--align", "auto", "--json")
    assert code == 0 and err == "" and json.loads(out)["settings"]["align"] == "body", err


def test_a_run_whose_body_frame_started_anew_is_aligned_with_a_warning(capsys, run_in_own_body_frame):
    # A case (a) run starts its body frame anew at a cut in its source (a recorded loop, a
    # restart) and after a total loss; one --align body offset fitted to all of them measures
    # how those frames differ too, which nothing said.
    seq, run = run_in_own_body_frame
    (run / "run.yaml").write_text("status: complete\nsource:\n  spec: sim\n  case: a\n"
                                  "summary:\n  engine:\n    stream_cuts: 2\n    frames_redefined: 1\n")
    code, out, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run), "--json")
    assert code == 0 and json.loads(out)["settings"]["align"] == "body"
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "defined its body frame 4 times" in lines[0] and "one offset" in lines[0], err
    # with the frame defined once, nothing to say; --align none is told otherwise (above)
    (run / "run.yaml").write_text("status: complete\nsource:\n  spec: sim\n  case: a\n"
                                  "summary:\n  engine:\n    stream_cuts: 0\n    frames_redefined: 0\n")
    code, out, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run), "--json")
    assert code == 0 and err == "", err


@pytest.mark.parametrize("run_yaml", ["status: complete\nsource:\n  spec: sim\n  case: b\n", "not: [valid", None])
def test_a_case_b_run_or_one_of_unknown_case_is_compared_as_it_is_by_default(capsys, run_in_own_body_frame, run_yaml):
    # Case (b)'s body frame is the model's, the truth's own: no offset is fitted (nor for a run
    # whose case is unknown: an unreadable run.yaml is no case, not an error).
    seq, run = run_in_own_body_frame
    if run_yaml is not None:
        (run / "run.yaml").write_text(run_yaml)
    code, out, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run), "--json")
    assert code == 0, err
    s = json.loads(out)
    assert s["settings"]["align"] == "none" and s["position_m"]["norm"]["max"] > 0.1
    # The run's own frame (30 deg off) is not taken for the truth's in silence where the case
    # is unknown (a bare trajectory, a lost run.yaml); a case (b) run's frame is the model's.
    if s["settings"]["case"] is None:
        # (and a run.yaml that does not read is named, with why the case is unknown)
        unreadable = run_yaml is not None
        assert "off by 31 deg (RMS)" in err and "--align body" in err and err.count("\n") == 1 + unreadable, err
        assert ("run.yaml: not readable as YAML" in err) == unreadable
    else:
        assert err == "", err


def test_an_estimate_of_unknown_case_near_the_truth_is_not_warned_about(capsys, tmp_path):
    truth = tumbling_truth()
    seq, run = tmp_path / "seq", tmp_path / "run"
    write_groundtruth_csv(seq / "groundtruth.csv", truth)
    R = Rotation.from_quat(truth.quat_wxyz, scalar_first=True) * Rotation.from_rotvec([0.0, 0.01, 0.0])
    est = MotionSeries(truth.t_s, np.ones(len(truth), bool), truth.position_m + 0.002,
                       R.as_quat(scalar_first=True), np.full((len(truth), 3), np.nan), np.full((len(truth), 3), np.nan), {})
    write_states_csv(run / "states.csv", est)
    code, out, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run / "states.csv"), "--json")
    assert code == 0 and err == "", err


def test_a_truth_in_integer_nanoseconds_is_read_as_such_with_a_warning(capsys, sequence_and_run, tmp_path):
    truth, seq, run = sequence_and_run
    code, out, err = _run(capsys, "evaluate", "--truth", str(seq / "groundtruth.csv"), "--estimate", str(run), "--json")
    assert code == 0, err
    expected = json.loads(out)
    lines = (seq / "groundtruth.csv").read_text().splitlines()
    rows = [line.split(",") for line in lines[1:]]
    ns_csv = tmp_path / "ns" / "groundtruth.csv"
    ns_csv.parent.mkdir()
    ns_csv.write_text("\n".join([lines[0]] + [",".join([str(round(float(r[0]) * 1e9))] + r[1:]) for r in rows]) + "\n")
    code, out, err = _run(capsys, "evaluate", "--truth", str(ns_csv), "--estimate", str(run), "--json")
    assert code == 0, err
    assert "its times read as integer nanoseconds" in err and len(err.strip().splitlines()) == 1, err
    got = json.loads(out)
    assert got.pop("settings")["truth"] == str(ns_csv) and expected.pop("settings")
    assert _flat(got) == pytest.approx(_flat(expected), abs=1e-9)


def test_both_trajectories_in_epoch_nanoseconds_are_read_as_such(capsys, sequence_and_run, tmp_path):
    # EuRoC-style TUM files on both sides (integer nanoseconds since the epoch): nothing pairs
    # them as seconds against the other, yet --settle and --tolerance are in seconds, so each
    # is told by its own numbers (an outside evaluator's probe: --settle 2 was read as 2 ns).
    truth, seq, run = sequence_and_run
    code, out, err = _run(capsys, "evaluate", "--truth", str(seq / "groundtruth.tum"), "--estimate", str(run),
                          "--settle", "0.5", "--json")
    assert code == 0, err
    expected = json.loads(out)
    epoch_ns = 1_403_636_579_763_555_584
    files = []
    for name, source in (("truth.tum", seq / "groundtruth.tum"), ("est.tum", run / "trajectory.tum")):
        if name == "est.tum":  # the run's valid poses, as trajectory.tum holds them
            lines = [" ".join([f"{float(r[0]):.9f}", *r[2:5], r[6], r[7], r[8], r[5]])
                     for r in (line.split(",") for line in (run / "states.csv").read_text().splitlines()[1:])
                     if r[1] == "1"]
        else:
            lines = [line for line in source.read_text().splitlines() if line and not line.startswith("#")]
        rows = [line.split() for line in lines]
        path = tmp_path / "ns" / name
        path.parent.mkdir(exist_ok=True)
        path.write_text("".join(" ".join([str(epoch_ns + round(float(r[0]) * 1e9))] + r[1:]) + "\n" for r in rows))
        files.append(path)
    code, out, err = _run(capsys, "evaluate", "--truth", str(files[0]), "--estimate", str(files[1]),
                          "--settle", "0.5", "--json")
    assert code == 0, err
    assert err.count("its times read as integer nanoseconds") == 2, err
    got = json.loads(out)
    assert got["matched"] == expected["matched"] < 59  # the settle counted in seconds
    for group in ("position_m", "attitude_rad"):
        assert _flat(got[group]) == pytest.approx(_flat(expected[group]), abs=1e-6)


def _report_files(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def test_a_disk_that_fills_leaves_the_earlier_report_whole_and_no_part_of_the_new(capsys, sequence_and_run, full_disk):
    _, seq, run = sequence_and_run
    out = run.parent / "report"
    assert _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run), "--out", str(out))[0] == 0
    before = _report_files(out)
    assert {"summary.json", "errors.csv", "report.md", "position_error.png"} <= set(before)
    full_disk(20_000)  # room for the text files, not for the plots as well
    code, _, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run), "--align", "body",
                        "--out", str(out))
    assert code == 2 and len(err.strip().splitlines()) == 1 and "No space left on device" in err, err
    assert str(out) in err
    assert _report_files(out) == before  # every file the earlier report's, nothing beside them


def test_a_report_folder_the_full_disk_left_empty_is_not_left_behind(capsys, sequence_and_run, full_disk):
    """A new --out folder (and the folders made to reach it) stayed behind, empty, when the
    disk filled while the report was written."""
    _, seq, run = sequence_and_run
    parent = run.parent / "reports"
    full_disk(20_000)
    code, _, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run), "--out",
                        str(parent / "new" / "report"))
    assert code == 2 and len(err.strip().splitlines()) == 1 and "No space left on device" in err, err
    assert not parent.exists()


def test_out_refuses_a_sequence_folder_and_a_file(capsys, sequence_and_run):
    _, seq, run = sequence_and_run
    recording = run.parent / "recording"
    for cam in ("cam0", "cam1"):
        (recording / cam).mkdir(parents=True)
        (recording / cam / "data.csv").write_text("#timestamp [ns],filename\n")
    a_file = run.parent / "file.txt"
    a_file.write_text("x")
    for out, message in ((recording, "a sequence folder"), (a_file, "not a folder")):
        code, _, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run), "--out", str(out))
        assert code == 2 and message in err and len(err.strip().splitlines()) == 1, err
    assert sorted(p.name for p in recording.iterdir()) == ["cam0", "cam1"]


def test_out_refuses_a_folder_of_other_files_and_replaces_a_report_or_joins_a_run(capsys, sequence_and_run):
    # --out . (or a folder of notes) wrote eight report files among the user's (an outside probe).
    _, seq, run = sequence_and_run
    busy = run.parent / "busy"
    busy.mkdir()
    (busy / "notes.txt").write_text("mine")
    (busy / ".hidden").write_text("x")
    code, _, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run), "--out", str(busy))
    assert code == 2 and len(err.strip().splitlines()) == 1 and "holds other files (notes.txt)" in err, err
    assert sorted(p.name for p in busy.iterdir()) == [".hidden", "notes.txt"]
    # an earlier report is replaced (it is made again from the same files), a run's folder joined
    report = run.parent / "report"
    for out in (report, report, run):
        assert _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run), "--out", str(out))[0] == 0
    assert (run / "report.md").is_file() and (run / "states.csv").is_file()
    # the user's notes beside an earlier report (or a run: its run.yaml) stay welcome
    (report / "notes.txt").write_text("mine")
    assert _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run), "--out", str(report))[0] == 0
    assert (report / "notes.txt").read_text() == "mine"


def test_out_takes_no_lone_report_file_and_no_other_run_s_folder(capsys, sequence_and_run, tmp_path) -> None:
    # A folder holding only the user's errors.csv was taken for a report's (names alone), and
    # another run's folder took this run's report over its own (an outside probe).
    _, seq, run = sequence_and_run
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "errors.csv").write_text("my own")
    code, _, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run), "--out", str(mine))
    assert code == 2 and "holds other files (errors.csv)" in err, err
    assert (mine / "errors.csv").read_text() == "my own"
    other = tmp_path / "other_run"
    other.mkdir()
    (other / "run.yaml").write_text("status: complete\n")
    code, _, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run), "--out", str(other))
    assert code == 2 and len(err.strip().splitlines()) == 1 and "another run's folder" in err, err
    assert sorted(p.name for p in other.iterdir()) == ["run.yaml"]
    (run / "run.yaml").write_text("status: complete\n")  # its own run's folder: welcome
    assert _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run / "states.csv"), "--out", str(run))[0] == 0


def test_a_run_replaced_with_overwrite_loses_its_old_evaluation(capsys, tmp_path):
    seq = tmp_path / "seq"
    assert main(["simulate", "--duration", "0.25", "--out", str(seq)]) == 0
    run = tmp_path / "run"
    assert main(["track", "--source", str(seq), "--select-model-points", "--out", str(run)]) == 0
    assert main(["evaluate", "--truth", str(seq), "--estimate", str(run), "--out", str(run)]) == 0
    assert (run / "report.md").is_file() and (run / "position_error.png").is_file()
    assert main(["track", "--source", str(seq), "--auto", "4", "--out", str(run), "--overwrite"]) == 0
    capsys.readouterr()
    assert not any((run / name).exists() for name in ("report.md", "summary.json", "errors.csv", "position_error.png"))
    assert (run / "states.csv").is_file() and (run / "run.yaml").is_file()


@pytest.mark.parametrize("status", ["running", "interrupted", "complete", "write failed", "source failed"])
def test_a_run_its_writer_never_closed_is_warned_about(capsys, run_in_own_body_frame, status):
    # After a kill -9 run.yaml keeps "status: running" and its summary is missing; it was
    # evaluated without a word (an outside CLI probe). An interrupted run's files are complete.
    # A run whose writes failed (a full disk) ended early: it was evaluated without a word too
    # (a re-check).
    seq, run = run_in_own_body_frame
    (run / "run.yaml").write_text(f"status: {status}\nsource:\n  spec: sim\n  case: a\n")
    code, out, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run), "--json")
    assert code == 0
    assert ("still running: it was killed, its disk filled" in err) == (status == "running"), err
    assert ("its writes failed (a full disk?), so it ended early" in err) == (status == "write failed"), err
    assert ("its source failed, so it ended early" in err) == (status == "source failed"), err  # a second re-check
    assert len(err.strip().splitlines()) == (status in ("running", "write failed", "source failed"))


def test_a_killed_overwrite_run_names_the_earlier_run_it_set_aside(capsys, run_in_own_body_frame):
    # A `track --overwrite` killed outright keeps the run it was replacing in .previous-run, a
    # hidden folder: nothing told the user the complete earlier run was still there.
    seq, run = run_in_own_body_frame
    (run / ".previous-run").mkdir()
    (run / ".previous-run" / "run.yaml").write_text("status: complete\n")
    (run / "run.yaml").write_text("status: running\nsource:\n  spec: sim\n  case: a\n")
    code, out, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run), "--json")
    assert code == 0 and len(err.strip().splitlines()) == 1, err
    assert f"the earlier run it was replacing (--overwrite) is kept in {run / '.previous-run'}" in err, err
    # Killed before its first frame: its states.csv is a header alone, refused, and the
    # earlier run went unnamed (a README walk-through).
    (run / "states.csv").write_text((run / "states.csv").read_text().splitlines()[0] + "\n")
    code, out, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run), "--json")
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert "no rows after the header" in err, err
    assert f"the earlier run it was replacing (--overwrite) is kept in {run / '.previous-run'}" in err, err


def test_errors_csv_leaves_an_unknown_value_empty_as_the_run_files_do(capsys, tmp_path):
    # errors.csv wrote Python's "nan" where states.csv and targets.csv leave a field empty (an
    # outside evaluator's reading): a frame whose rates were not estimated yet.
    truth = tumbling_truth()
    seq, run = tmp_path / "seq", tmp_path / "run"
    write_groundtruth_csv(seq / "groundtruth.csv", truth)
    v, w = truth.velocity_cam_m_s.copy(), truth.omega_body_rad_s.copy()
    v[:5], w[:5] = np.nan, np.nan
    est = MotionSeries(truth.t_s, np.ones(len(truth), bool), truth.position_m, truth.quat_wxyz, v, w, {})
    write_states_csv(run / "states.csv", est)
    code, _, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run / "states.csv"),
                        "--out", str(tmp_path / "report"))
    assert code == 0, err
    text = (tmp_path / "report" / "errors.csv").read_text()
    assert "nan" not in text.lower()
    rows = [line.split(",") for line in text.splitlines()[1:]]
    header = text.splitlines()[0].split(",")
    assert all(len(r) == len(header) for r in rows)
    assert any(r[header.index("evx_m_s")] == "" for r in rows) and rows[-1][header.index("evx_m_s")] != ""
    # each column names its unit (DESIGN.md 3; "ax" could be radians or degrees: an outside probe)
    assert header == ["t_s", "ex_m", "ey_m", "ez_m", "e_norm_m", "ax_rad", "ay_rad", "az_rad", "a_total_rad",
                      "evx_m_s", "evy_m_s", "evz_m_s", "ewx_rad_s", "ewy_rad_s", "ewz_rad_s", "speed_score"]


def test_frames_of_the_run_without_a_pose_count_as_unmatched_and_say_the_share_covered(capsys, tmp_path):
    """A run that had no pose for long stretches (harsh_light case (b) before its model binds)
    read "unmatched 0": only truth frames inside the span of the estimate's poses were counted.
    A run folder knows its own span (its states.csv rows): every truth frame in it after the
    settle without a pose is unmatched, and the share of them with one is said."""
    truth = tumbling_truth()  # t = 2.0, 2.08, ...
    valid = (truth.t_s >= 3.0 - 1e-9) & (truth.t_s <= 4.0 + 1e-9)
    est = MotionSeries(truth.t_s, valid, np.where(valid[:, None], truth.position_m, np.nan),
                       np.where(valid[:, None], truth.quat_wxyz, np.nan),
                       truth.velocity_cam_m_s, truth.omega_body_rad_s)
    write_states_csv(tmp_path / "run" / "states.csv", est)
    write_groundtruth_csv(tmp_path / "gt.csv", truth)
    args = ("evaluate", "--truth", str(tmp_path / "gt.csv"), "--estimate", str(tmp_path / "run"), "--settle", "0.5")
    code, out, err = _run(capsys, *args, "--json")
    assert code == 0, err
    s = json.loads(out)
    after = truth.t_s >= 2.5 - 1e-9
    assert s["matched"] == int(np.count_nonzero(valid & after))
    assert s["unmatched"] == int(np.count_nonzero(~valid & after))
    assert s["pose_coverage"] == pytest.approx(np.count_nonzero(valid & after) / np.count_nonzero(after))
    code, out, err = _run(capsys, *args)
    assert f"{100 * s['pose_coverage']:.1f} % of the run's frames after the settle (in the truth's span) have a pose" in out


def test_a_run_of_the_simulator_is_evaluated_against_its_scenario_s_motion(capsys, tmp_path):
    """`track --source sim` saves no ground truth: `--truth sim[:SCENARIO]` takes the scenario's
    motion at its frame times (no rendering), the same truth `simulate` writes."""
    from trackmeter.sources.sim.simulator import Simulator

    run = tmp_path / "run"
    assert main(["track", "--source", "sim", "--auto", "12", "--max-frames", "40", "--out", str(run)]) == 0
    capsys.readouterr()
    assert yaml.safe_load((run / "run.yaml").read_text())["source"]["scenario"] == "estec"  # for the check below
    sim = Simulator("estec")
    n = 40
    truth = MotionSeries(np.array([sim.time_of(i) for i in range(n)]), np.ones(n, bool),
                         np.array([sim.truth(i).T_cam_body[:3, 3] for i in range(n)]),
                         Rotation.from_matrix([sim.truth(i).T_cam_body[:3, :3] for i in range(n)]).as_quat(scalar_first=True),
                         np.array([sim.truth(i).velocity_cam_m_s for i in range(n)]),
                         np.array([sim.truth(i).omega_body_rad_s for i in range(n)]))
    write_groundtruth_csv(tmp_path / "gt.csv", truth)
    code, out_sim, err = _run(capsys, "evaluate", "--truth", "sim", "--estimate", str(run), "--json")
    assert code == 0 and "may not be of the sequence the run was tracked on" not in err, err
    code, out_file, err = _run(capsys, "evaluate", "--truth", str(tmp_path / "gt.csv"), "--estimate", str(run), "--json")
    assert code == 0, err
    a, b = json.loads(out_sim), json.loads(out_file)
    assert a["matched"] == b["matched"] > 0
    assert a["position_m"]["norm"]["max"] == pytest.approx(b["position_m"]["norm"]["max"], abs=1e-8)
    assert a["omega_rad_s"]["norm"]["rms"] == pytest.approx(b["omega_rad_s"]["norm"]["rms"], abs=1e-8)
    code, out, err = _run(capsys, "evaluate", "--truth", "sim:no_such_scenario", "--estimate", str(run))
    assert code == 2 and "no_such_scenario" in err


def test_a_truth_of_another_sequence_than_the_run_s_is_warned_about(capsys, tmp_path):
    """evaluate --truth harsh_light's folder on a run tracked on estec's gave plausible figures
    (7.8 mm, 6 deg) without a word. A run's run.yaml names the folder (and the scenario) it was
    tracked on; a truth from elsewhere is warned about, the same scenario rendered twice is not."""
    truth = tumbling_truth()
    seqs = {}
    for name, scenario in (("estec_seq", "estec"), ("harsh_seq", "harsh_light"), ("estec_again", "estec")):
        folder = tmp_path / name
        write_groundtruth_csv(folder / "groundtruth.csv", truth)
        (folder / "scenario.yaml").write_text(f"name: {scenario}\n")
        for cam in ("cam0", "cam1"):  # what makes it a sequence folder (images left out)
            (folder / cam).mkdir()
            (folder / cam / "data.csv").write_text("#timestamp [ns],filename\n")
        seqs[name] = folder
    run = tmp_path / "run"
    write_states_csv(run / "states.csv", truth)
    (run / "run.yaml").write_text(yaml.safe_dump({"status": "complete", "source": {
        "spec": "estec_seq", "case": "b", "folder": str(seqs["estec_seq"]), "scenario": "estec"}}))
    for name, warned in (("estec_seq", False), ("estec_again", False), ("harsh_seq", True)):
        code, out, err = _run(capsys, "evaluate", "--truth", str(seqs[name]), "--estimate", str(run))
        assert code == 0, err
        assert ("may not be of the sequence the run was tracked on" in err) == warned, (name, err)
    (seqs["harsh_seq"] / "scenario.yaml").unlink()  # a real sequence: folders differ, no scenario to tell
    code, out, err = _run(capsys, "evaluate", "--truth", str(seqs["harsh_seq"]), "--estimate", str(run))
    assert code == 0 and "may not be of the sequence the run was tracked on" in err and str(seqs["estec_seq"]) in err
    code, out, err = _run(capsys, "evaluate", "--truth", "sim:harsh_light", "--estimate", str(run))
    assert "may not be of the sequence the run was tracked on" in err
    # The forms that name the same scenario, and a truth file kept outside any sequence folder.
    from trackmeter.paths import SCENARIOS_DIR

    for spec in ("sim", "sim:estec", f"sim:{SCENARIOS_DIR / 'estec.yaml'}"):
        code, out, err = _run(capsys, "evaluate", "--truth", spec, "--estimate", str(run))
        assert "may not be" not in err, (spec, err)
    elsewhere = tmp_path / "elsewhere"
    write_groundtruth_csv(elsewhere / "reference.csv", truth)
    code, out, err = _run(capsys, "evaluate", "--truth", str(elsewhere / "reference.csv"), "--estimate", str(run))
    assert code == 0 and "may not be" not in err, err


def test_a_settle_time_longer_than_the_run_says_how_long_the_run_is(capsys, tmp_path):
    truth = tumbling_truth()
    _tum(tmp_path / "truth.tum", truth)
    _tum(tmp_path / "est.tum", truth)
    code, out, err = _run(capsys, "evaluate", "--truth", str(tmp_path / "truth.tum"), "--estimate", str(tmp_path / "est.tum"),
                          "--settle", "1000")
    span = truth.t_s[-1] - truth.t_s[0]
    assert code == 2 and f"the paired poses end {span:.3g} s after the start" in err, err


def test_valid_rows_some_without_rates_are_warned_about(capsys, sequence_and_run):
    # README: a states.csv row is valid when every field is a number. A valid row with a rate
    # edited to nan was read without a word: its pose counted, its rates left out.
    truth, seq, run = sequence_and_run
    path = run / "states.csv"
    lines = path.read_text().splitlines()
    header = lines[0].split(",")
    for row in (3, 7):
        fields = lines[row].split(",")
        fields[header.index("vx" if row == 3 else "wz")] = "nan" if row == 3 else ""
        lines[row] = ",".join(fields)
    path.write_text("\n".join(lines) + "\n")
    code, out, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run), "--json")
    assert code == 0
    assert f"warning: 2 rows with a pose of {path} have a rate that is not a number" in err, err
    assert json.loads(out)["matched"] == 59  # the poses still count


def test_a_report_over_an_earlier_one_leaves_none_of_its_plots(capsys, sequence_and_run, tmp_path):
    # A run folder's report has velocity plots, a TUM pair's has none: written into the same
    # --out, the second left the first's velocity plots beside a report that has no velocities.
    truth, seq, run = sequence_and_run
    out = tmp_path / "report"
    assert _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run), "--out", str(out))[0] == 0
    assert (out / "velocity_error.png").is_file() and (out / "omega_error.png").is_file()
    (out / "my_notes.txt").write_text("mine")  # not the report's: stays
    (out / "my_plot.png").write_bytes(b"mine")
    code, _, err = _run(capsys, "evaluate", "--truth", str(seq / "groundtruth.tum"), "--estimate",
                        str(run / "states.csv"), "--out", str(out))
    assert code == 0, err
    code, _, err = _run(capsys, "evaluate", "--truth", str(seq / "groundtruth.tum"), "--estimate",
                        str(seq / "groundtruth.tum"), "--out", str(out))
    assert code == 0, err
    assert sorted(p.name for p in out.iterdir()) == ["attitude_error.png", "errors.csv", "my_notes.txt", "my_plot.png",
                                                     "position_error.png", "report.md", "summary.json"]


def test_a_body_alignment_fitted_to_one_pose_is_warned_about(capsys, tmp_path):
    # The offset fitted to a single pose makes every error zero: reported as a perfect run.
    truth, est = tmp_path / "truth.tum", tmp_path / "est.tum"
    truth.write_text("0 0 0 3 0 0 0 1\n1 0 0 3 0 0 0 1\n")
    est.write_text("0 0.01 0.02 3.03 0.1 0 0 0.995\n")
    code, out, err = _run(capsys, "evaluate", "--truth", str(truth), "--estimate", str(est), "--align", "body", "--json")
    assert code == 0 and json.loads(out)["position_m"]["norm"]["max"] < 1e-9
    assert "warning: --align body fitted the body-frame offset to 1 pose(s)" in err, err
    code, _, err = _run(capsys, "evaluate", "--truth", str(truth), "--estimate", str(est), "--json")
    assert code == 0 and "fitted the body-frame offset" not in err  # no alignment, nothing absorbed


def test_a_motion_csv_whose_time_column_is_renamed_is_told_so_not_read_as_tum(capsys, sequence_and_run):
    # The header "time,x,y,..." was read as a TUM line: "expected 8 values 't tx ty tz qx qy qz qw', got 14".
    truth, seq, run = sequence_and_run
    path = seq / "groundtruth.csv"
    path.write_text(path.read_text().replace("t,x,y,z", "time,x,y,z", 1))
    code, _, err = _run(capsys, "evaluate", "--truth", str(path), "--estimate", str(run))
    assert code == 2 and "not a motion CSV: header lacks t (expected t,x,y,z" in err and "TUM" not in err, err


@pytest.mark.parametrize("separator, named, hashed", [("\t", "tabs", False), (";", "semicolons", False),
                                                      ("\t", "tabs", True)])
def test_a_motion_csv_separated_by_tabs_is_told_so_not_read_as_tum(capsys, sequence_and_run, separator, named, hashed):
    # A tab-separated groundtruth.csv was refused as a TUM file: "expected 8 values 't tx ty
    # tz qx qy qz qw', got 14" (an outside probe); with its header as a '#' line too.
    truth, seq, run = sequence_and_run
    path = seq / "groundtruth.csv"
    path.write_text(("# a note; not a header\n#" if hashed else "") + path.read_text().replace(",", separator))
    code, _, err = _run(capsys, "evaluate", "--truth", str(path), "--estimate", str(run))
    assert code == 2 and f"a header of names separated by {named}" in err and "commas" in err, err
    assert "expected 8 values" not in err and len(err.strip().splitlines()) == 1, err


def test_a_headerless_comma_file_is_read_as_tum_and_said_so(capsys, tmp_path) -> None:
    # groundtruth.csv's rows without their header (t,x,y,z,qw,qx,qy,qz) were read as TUM
    # (qx qy qz qw) without a word: 128 deg of attitude error (an outside probe).
    truth, est = tmp_path / "truth.txt", tmp_path / "est.tum"
    truth.write_text("0,0,0,3,0,0,0,1\n1,0,0,3,0,0,0,1\n")
    est.write_text("0 0 0 3 0 0 0 1\n1 0 0 3 0 0 0 1\n")
    code, out, err = _run(capsys, "evaluate", "--truth", str(truth), "--estimate", str(est), "--json")
    assert code == 0 and json.loads(out)["position_m"]["norm"]["max"] == 0.0
    assert "separated by commas" in err and "read as TUM (t tx ty tz qx qy qz qw" in err, err
    code, out, err = _run(capsys, "evaluate", "--truth", str(est), "--estimate", str(est), "--json")
    assert code == 0 and "commas" not in err


def test_two_scenarios_of_one_name_are_told_apart_by_their_motion(capsys, tmp_path) -> None:
    # Two scenario files both called "t", the body at 3.5 m and at 2.5 m: evaluate --truth
    # sim:the_other gave 1000 mm of error without a word (the names agreed; an outside probe).
    near, far = tmp_path / "near.yaml", tmp_path / "far.yaml"
    near.write_text("name: t\nposition0_m: [0, 0, 2.5]\nduration_s: 2\n")
    far.write_text("name: t\nposition0_m: [0, 0, 3.5]\nduration_s: 2\n")
    renamed = tmp_path / "renamed.yaml"
    renamed.write_text("name: other\nposition0_m: [0, 0, 3.5]\nduration_s: 2\ndescription: the same motion\n")
    faster = tmp_path / "faster.yaml"  # the same motion sampled at 50 Hz: its truth is the same
    faster.write_text("name: t\nposition0_m: [0, 0, 3.5]\nduration_s: 2\nrate_hz: 50\n")
    run = tmp_path / "run"
    assert main(["track", "--source", f"sim:{far}", "--auto", "8", "--max-frames", "40", "--out", str(run)]) == 0
    for truth, warned in ((far, False), (near, True), (renamed, False), (faster, False)):
        code, _, err = _run(capsys, "evaluate", "--truth", f"sim:{truth}", "--estimate", str(run), "--settle", "0")
        assert code == 0 and ("may not be of the sequence the run was tracked on" in err) == warned, (truth, err)
    assert "their motions differ" in _run(capsys, "evaluate", "--truth", f"sim:{near}", "--estimate", str(run),
                                          "--settle", "0")[2]
    # a sequence simulated from it (its scenario.yaml as run) is the same motion
    seq = tmp_path / "seq"
    assert main(["simulate", "--scenario", str(far), "--out", str(seq)]) == 0
    run2 = tmp_path / "run2"
    assert main(["track", "--source", str(seq), "--auto", "8", "--max-frames", "40", "--out", str(run2)]) == 0
    for truth, warned in ((f"sim:{far}", False), (str(seq), False), (f"sim:{near}", True)):
        code, _, err = _run(capsys, "evaluate", "--truth", truth, "--estimate", str(run2), "--settle", "0")
        assert ("may not be of the sequence the run was tracked on" in err) == warned, (truth, err)


def test_a_sim_truth_carries_the_motion_on_over_a_longer_run(capsys, tmp_path) -> None:
    # A sequence simulated with --duration past its scenario's own: --truth sim:SCENARIO ended
    # at the scenario's duration and half the run went unevaluated without a word (a probe).
    short = tmp_path / "short.yaml"
    short.write_text("name: short\nduration_s: 1.0\n")
    seq, run = tmp_path / "seq", tmp_path / "run"
    assert main(["simulate", "--scenario", str(short), "--duration", "2", "--out", str(seq)]) == 0
    assert main(["track", "--source", str(seq), "--auto", "8", "--out", str(run)]) == 0
    capsys.readouterr()
    code, out_sim, err = _run(capsys, "evaluate", "--truth", f"sim:{short}", "--estimate", str(run), "--json")
    assert code == 0, err
    code, out_seq, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run), "--json")
    a, b = json.loads(out_sim), json.loads(out_seq)
    assert a["matched"] == b["matched"] > 30 and a["unmatched"] == b["unmatched"]
    assert a["position_m"]["norm"]["max"] == pytest.approx(b["position_m"]["norm"]["max"], abs=1e-9)


@pytest.mark.parametrize("text, said", [
    ("status: [unclosed\n", "not readable as YAML"),
    ("", "not a run's record (an empty file)"),
    ("- a\n", "not a run's record"),
    ("status: complete\nsource: {case: z}\n", "an unknown pose case 'z' (a, b or c)"),
    ("status: complete\n", r"no pose case recorded (source.case)"),
    (None, "not a file"),
])
def test_a_run_yaml_that_says_no_case_is_warned_about(capsys, sequence_and_run, text: str, said: str) -> None:
    """A broken run.yaml was ignored without a word: --align auto then compared a case-(a)
    run without aligning and reported a 117 deg attitude error (an outside probe)."""
    truth, seq, run = sequence_and_run
    if text is None:
        (run / "run.yaml").mkdir()
    else:
        (run / "run.yaml").write_text(text)
    code, out, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run), "--json")
    assert code == 0, err
    assert f"{run / 'run.yaml'}: {said}" in err and "--align body" in err, err
    assert json.loads(out)["settings"]["align"] == "none"
    if text is None:
        (run / "run.yaml").rmdir()
    (run / "run.yaml").write_text("status: complete\nsource: {case: b}\n")
    code, out, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run), "--json")
    assert code == 0 and "run.yaml" not in err, err


def test_a_truth_that_ends_before_the_run_is_said_so(capsys, sequence_and_run, tmp_path) -> None:
    """A groundtruth.csv cut to its first 30 rows evaluated 11 of 75 poses without a word but
    the coverage line (an outside probe): the poses past the truth's end are counted."""
    from trackmeter.data.motion_csv import read_motion_csv, write_groundtruth_csv

    truth, seq, run = sequence_and_run
    short = tmp_path / "short"
    cut = read_motion_csv(seq / "groundtruth.csv")
    keep = cut.t_s <= cut.t_s[len(cut) // 2]
    write_groundtruth_csv(short / "groundtruth.csv", MotionSeries(cut.t_s[keep], cut.valid[keep], cut.position_m[keep],
                                                                   cut.quat_wxyz[keep], cut.velocity_cam_m_s[keep],
                                                                   cut.omega_body_rad_s[keep]))
    code, out, err = _run(capsys, "evaluate", "--truth", str(short), "--estimate", str(run))
    assert code == 0, err
    n_after = int(np.count_nonzero(truth.t_s > cut.t_s[keep][-1]))
    assert (f"warning: the truth ends at {cut.t_s[keep][-1]:.3f} s, the estimate at {truth.t_s[-1]:.3f} s: its "
            f"{n_after} pose(s) after the truth's end are not evaluated") in err, err
    code, out, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run))
    assert code == 0 and "not evaluated" not in err, err


@pytest.mark.parametrize("name", [b"s\xe9q", "s\u00e9q".encode()])
def test_a_path_that_is_not_utf8_is_written_and_printed_by_its_own_bytes(run_in_own_body_frame, tmp_path, name):
    # report.md's text was encoded strictly, and so was stdout: a path holding Python's
    # surrogate escapes (a byte that is not UTF-8, or any non-ASCII name under a C locale, the
    # second case here) failed with a traceback after the work was done (an outside probe).
    import shutil

    seq, run = run_in_own_body_frame
    odd = tmp_path / os.fsdecode(name)
    shutil.copytree(seq, odd)
    out = tmp_path / "report"
    env = dict(os.environ, **({"LC_ALL": "C", "PYTHONUTF8": "0", "PYTHONCOERCECLOCALE": "0"} if name.isascii() is False
                              and b"\xe9" not in name else {}))
    done = subprocess.run([sys.executable, "-m", "trackmeter", "evaluate", "--truth", os.fsencode(odd), "--estimate",
                           str(run), "--align", "body", "--out", str(out)], capture_output=True, env=env, timeout=300)
    assert done.returncode == 0, done.stderr.decode("utf-8", "replace")
    assert name in (out / "report.md").read_bytes()
    assert name in done.stdout


@pytest.mark.parametrize("with_run_yaml", [True, False])
def test_a_run_folder_without_its_states_csv_says_the_rates_are_not_evaluated(capsys, sequence_and_run, tmp_path,
                                                                              with_run_yaml):
    # A run's folder whose states.csv is gone fell back on trajectory.tum without a word, and
    # its velocity figures were simply missing (an outside probe). A folder of a TUM file alone
    # is no run's: nothing to say.
    truth, seq, _ = sequence_and_run
    run = tmp_path / "tum_run"
    run.mkdir()
    _tum(run / "trajectory.tum", truth)
    if with_run_yaml:
        (run / "run.yaml").write_text("status: complete\nsource:\n  spec: sim\n  case: b\n")
    code, out, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run), "--json")
    assert code == 0 and json.loads(out)["matched"] == len(truth)
    said = [line for line in err.splitlines() if "states.csv" in line]
    assert len(said) == with_run_yaml, err
    if with_run_yaml:
        assert said[0] == (f"trackmeter evaluate: warning: {run / 'states.csv'}: missing: the poses of "
                           f"{run / 'trajectory.tum'} are evaluated, without rates"), err
        (run / "states.csv").mkdir()  # said "missing" of a folder by that name
        code, out, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run), "--json")
        assert code == 0 and f"{run / 'states.csv'}: not a file: the poses of" in err, err


@pytest.mark.parametrize("columns", ["pose", "state", "upper case"])
def test_a_euroc_ground_truth_csv_is_read_by_its_header(capsys, sequence_and_run, tmp_path, columns):
    """EuRoC's ground truth (``#timestamp, p_RS_R_x [m], ..., q_RS_w [], ...``, nanoseconds,
    scalar-first) was taken for a TUM file with commas: its header a comment, the quaternion
    read scalar-last, 126 deg of attitude error and exit 0 (an outside probe). Read by its
    header, it evaluates as the same poses in groundtruth.csv do; its gyro-bias columns
    (``b_w_RS_S_x``) are no angular velocity."""
    truth, seq, run = sequence_and_run
    names = ["#timestamp [ns]", "p_RS_R_x [m]", "p_RS_R_y [m]", "p_RS_R_z [m]", "q_RS_w []", "q_RS_x []",
             "q_RS_y []", "q_RS_z []"]
    if columns == "state":
        names += [f"v_RS_R_{a} [m s^-1]" for a in "xyz"] + [f"b_w_RS_S_{a} [rad s^-1]" for a in "xyz"] + \
            [f"b_a_RS_S_{a} [m s^-2]" for a in "xyz"]
    rows = [",".join(names).upper() if columns == "upper case" else ",".join(names)]  # read alike (a re-check)
    for k in range(len(truth)):
        values = [f"{round(truth.t_s[k] * 1e9)}"] + [f"{x:.12g}" for x in truth.position_m[k]] + \
            [f"{x:.12g}" for x in truth.quat_wxyz[k]]
        if columns == "state":
            values += [f"{x:.12g}" for x in truth.velocity_cam_m_s[k]] + ["0.5"] * 6
        rows.append(",".join(values))
    gt = tmp_path / "euroc" / "data.csv"
    gt.parent.mkdir()
    gt.write_text("\n".join(rows) + "\n")
    code, out, err = _run(capsys, "evaluate", "--truth", str(gt), "--estimate", str(run / "states.csv"), "--json")
    assert code == 0 and "scalar last" not in err, err
    s = json.loads(out)
    assert s["matched"] == len(truth) - 1
    assert s["position_m"]["x"]["max"] == pytest.approx(0.002, abs=1e-6)
    assert s["attitude_rad"]["z"]["max"] == pytest.approx(math.radians(0.5), abs=1e-6)
    # the gyro biases are not read as omega; without one, the linear velocity is not scored either
    assert s["omega_rad_s"] is None and s["velocity_m_s"] is None


@pytest.mark.parametrize("mixup", ["inverted", "scalar_first", "millimetres", "body_frame", "conjugated",
                                   "centimetres"])
def test_an_estimate_written_in_another_convention_is_named(capsys, tmp_path, mixup):
    """A TUM estimate of T_body_cam, one written scalar-first, or one in millimetres gave
    errors of metres and 126 deg with only "compare with --align body" said, or, in mm, nothing
    at all (an outside probe, checking against evo). Each is now named; a case (a) frame of its
    own still gets the --align body hint, and only it."""
    truth = tumbling_truth()
    R = Rotation.from_quat(truth.quat_wxyz, scalar_first=True)
    p, q = np.array(truth.position_m), np.array(truth.quat_wxyz)
    lines = []
    if mixup == "inverted":
        p, q = -(R.inv().apply(p)), R.inv().as_quat(scalar_first=True)
    elif mixup == "millimetres":
        p = 1000 * p
    elif mixup == "centimetres":  # and a JPL quaternion, or R_body_cam beside T_cam_body's position (a re-check)
        p = 100 * p
    elif mixup == "conjugated":
        q = R.inv().as_quat(scalar_first=True)
    elif mixup == "body_frame":
        Rb = R * Rotation.from_rotvec([0.3, 2.5, -0.7])
        p, q = p + R.apply([0.1, -0.02, 0.3]), Rb.as_quat(scalar_first=True)
    for t, pos, quat in zip(truth.t_s, p, q):
        order = quat if mixup == "scalar_first" else quat[[1, 2, 3, 0]]
        lines.append(" ".join(f"{x:.9f}" for x in (t, *pos, *order)))
    (tmp_path / "e.tum").write_text("\n".join(lines) + "\n")
    _tum(tmp_path / "t.tum", truth)
    code, out, err = _run(capsys, "evaluate", "--truth", str(tmp_path / "t.tum"), "--estimate", str(tmp_path / "e.tum"))
    assert code == 0
    said = {"inverted": "inverted (T_body_cam", "scalar_first": "scalar first", "millimetres": "1000x the",
            "body_frame": "--align body", "conjugated": "its rotation inverted", "centimetres": "100x the"}
    assert said[mixup] in err, err
    assert sum(word in err for word in said.values()) == 1, err  # the one that fits, not every guess
    # the table keeps its columns apart however large the figures
    row = next(line for line in out.splitlines() if line.startswith("position [mm]") and " norm " in f" {line} ")
    assert len(row.split()) == 6, row


def test_the_error_plots_name_the_axes_their_panels_are_in():
    from trackmeter.data.evaluation import error_plot_title

    assert error_plot_title("omega_rad_s").startswith("angular velocity (body frame) error (estimate - truth), body axes\n")
    for group in ("position_m", "attitude_rad", "velocity_m_s"):
        assert "camera axes, z = the viewing axis\n" in error_plot_title(group)


def test_a_tum_estimate_is_never_said_to_be_read_scalar_first(capsys, tmp_path):
    """A TUM estimate whose quaternions fit the truth far better rolled the other way (each
    row's qw column holding the truth's qx, ...) was told it had been "written scalar last
    (x y z w) where scalar first is read": TUM is read scalar last (an outside probe). The
    hint names only the order that the file's format was not read in; a CSV still gets it."""
    truth = tumbling_truth()
    q = np.array(truth.quat_wxyz)
    lines = [" ".join(f"{x:.9f}" for x in (t, *pos, *np.roll(quat, -1)[[1, 2, 3, 0]]))
             for t, pos, quat in zip(truth.t_s, truth.position_m, q)]
    (tmp_path / "e.tum").write_text("\n".join(lines) + "\n")
    _tum(tmp_path / "t.tum", truth)
    code, out, err = _run(capsys, "evaluate", "--truth", str(tmp_path / "t.tum"), "--estimate", str(tmp_path / "e.tum"))
    assert code == 0 and "where scalar first is read" not in err, err
    rows = ["t,x,y,z,qw,qx,qy,qz"] + [",".join(f"{x:.9f}" for x in (t, *pos, *np.roll(quat, -1)))
                                      for t, pos, quat in zip(truth.t_s, truth.position_m, q)]
    (tmp_path / "e.csv").write_text("\n".join(rows) + "\n")
    code, out, err = _run(capsys, "evaluate", "--truth", str(tmp_path / "t.tum"), "--estimate", str(tmp_path / "e.csv"))
    assert code == 0 and "written scalar last (x y z w) where scalar first is read" in err, err


def test_warnings_about_an_estimate_without_a_valid_column_call_it_neither_truth_nor_valid(capsys, sequence_and_run,
                                                                                          tmp_path):
    # A states.csv without its valid column, given as --estimate, was warned about as "read as
    # no ground truth at their time" and as having "valid (1) rows" (an outside probe).
    truth, seq, run = sequence_and_run
    lines = (run / "states.csv").read_text().splitlines()
    header = lines[0].split(",")
    keep = [i for i, name in enumerate(header) if name != "valid"]
    rows = [",".join(line.split(",")[i] for i in keep) for line in lines]
    fields = rows[5].split(",")
    fields[header.index("vx") - 1] = ""  # a pose without its rate
    rows[5] = ",".join(fields)
    rows[8] = rows[8].split(",")[0] + "," * (len(keep) - 1)  # a row without a pose
    (tmp_path / "novalid.csv").write_text("\n".join(rows) + "\n")
    code, out, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(tmp_path / "novalid.csv"))
    assert code == 0 and "row(s) without a whole pose" in err and "rate that is not a number" in err, err
    assert "ground truth" not in err and "valid (1) rows" not in err, err


@pytest.mark.parametrize("shift_m", [0.0, 0.5])
def test_a_tum_truth_takes_velocities_from_a_groundtruth_csv_beside_only_of_the_same_poses(capsys, sequence_and_run,
                                                                                           tmp_path, shift_m):
    """A groundtruth.tum with a groundtruth.csv beside it takes the csv's velocities; they were
    taken when the two disagreed too (a TUM shifted 0.5 m), unsaid (an outside probe)."""
    truth, seq, run = sequence_and_run
    mix = tmp_path / "mix"
    write_groundtruth_csv(mix / "groundtruth.csv", truth)
    _tum(mix / "groundtruth.tum", MotionSeries(truth.t_s, truth.valid, truth.position_m + [shift_m, 0, 0],
                                               truth.quat_wxyz, truth.velocity_cam_m_s, truth.omega_body_rad_s))
    code, out, err = _run(capsys, "evaluate", "--truth", str(mix / "groundtruth.tum"), "--estimate", str(run),
                          "--json")
    assert code == 0
    s = json.loads(out)
    if shift_m == 0.0:
        assert s["velocity_m_s"]["z"]["max"] == pytest.approx(0.001, abs=1e-6) and err == "", err
    else:
        assert s["velocity_m_s"] is None
        assert "groundtruth.csv" in err and "500.000 mm" in err and "velocities are not used" in err, err


def test_a_command_started_with_its_stdout_closed_ends_without_a_traceback(sequence_and_run, tmp_path):
    # `trackmeter track ... >&-`: Python then has no sys.stdout (None), and the flush after the
    # command's work gave "AttributeError: 'NoneType' object has no attribute 'flush'", exit 1
    # (an outside probe).
    truth, seq, run = sequence_and_run
    command = [sys.executable, "-m", "trackmeter.cli.main", "evaluate", "--truth", str(seq), "--estimate", str(run),
               "--out", str(tmp_path / "report")]
    for closed in (">&-", "2>&-", ">&- 2>&-"):  # stderr too: track asked it isatty()
        proc = subprocess.run(["sh", "-c", f'"$@" {closed}', "sh", *command], capture_output=True, text=True)
        assert proc.returncode == 0 and "Traceback" not in proc.stdout + proc.stderr, (closed, proc.stdout, proc.stderr)
        assert (tmp_path / "report" / "summary.json").is_file()
    track = [sys.executable, "-m", "trackmeter.cli.main", "track", "--source", "sim", "--auto", "4", "--max-frames", "3",
             "--out", str(tmp_path / "tracked")]  # its progress asks stderr isatty()
    proc = subprocess.run(["sh", "-c", '"$@" 2>&-', "sh", *track], capture_output=True, text=True)
    assert proc.returncode == 0 and "Traceback" not in proc.stdout, proc.stdout
    assert (tmp_path / "tracked" / "run.yaml").is_file()


def test_a_run_s_pose_covariance_is_judged_against_the_truth(capsys, sequence_and_run) -> None:
    # track writes each pose's covariance (pose_covariance.csv): evaluate says how honest it
    # is, the normalised estimation error squared (NEES, chi-square with 6 dof when honest:
    # Bar-Shalom, Li and Kirubarajan 2001, 5.4.2). Errors of 2 mm along x and 0.5 deg about z
    # against 1-sigmas of 1 mm and 0.5 deg give NEES 2^2 + 1^2 = 5 at every pose.
    from trackmeter.data.rundir import POSE_COVARIANCE_COLUMNS

    truth, seq, run = sequence_and_run
    cov = np.diag([1e-3**2] * 3 + [math.radians(0.5) ** 2] * 3)
    upper = cov[np.triu_indices(6)]
    rows = [",".join([f"{t:.9f}", *(f"{c:.9e}" for c in upper)]) for k, t in enumerate(truth.t_s) if k != 10]
    (run / "pose_covariance.csv").write_text(",".join(POSE_COVARIANCE_COLUMNS) + "\n" + "\n".join(rows) + "\n")
    (run / "run.yaml").write_text(yaml.safe_dump({"status": "complete", "source": {"case": "b"}}))  # a track run's
    code, out, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run), "--json")
    assert code == 0, err
    s = json.loads(out)
    assert s["pose_nees"]["poses"] == 59
    assert s["pose_nees"]["median"] == pytest.approx(5.0, rel=1e-6)
    assert s["pose_nees"]["within_95"] == 1.0
    code, out, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run))
    assert "pose covariance: NEES median 5.00 over 59 poses (5.35 when honest), 100.0 % within" in out, out
    # Aligned to the truth's body, the errors are no longer the ones the covariance describes.
    code, out, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run), "--align", "body", "--json")
    assert code == 0 and "pose_nees" not in json.loads(out)


def _covariance_file(run, truth, rows_cov) -> None:
    """A pose_covariance.csv for ``run`` at the truth's times but frame 10 (the run's invalid
    one): ``rows_cov(k)`` gives row k's (6,6) matrix, or None for empty fields (as track writes
    a non-finite covariance)."""
    from trackmeter.data.rundir import POSE_COVARIANCE_COLUMNS

    lines = [",".join(POSE_COVARIANCE_COLUMNS)]
    for k, t in enumerate(truth.t_s):
        if k == 10:
            continue
        cov = rows_cov(k)
        fields = [""] * 21 if cov is None else [f"{c:.9e}" for c in cov[np.triu_indices(6)]]
        lines.append(",".join([f"{t:.9f}", *fields]))
    (run / "pose_covariance.csv").write_text("\n".join(lines) + "\n")
    (run / "run.yaml").write_text(yaml.safe_dump({"status": "complete", "source": {"case": "b"}}))  # a track run's


def test_a_covariance_that_is_no_covariance_is_left_out_and_said(capsys, sequence_and_run) -> None:
    # An outside probe: a zero (singular) matrix crashed evaluate (LinAlgError), negative
    # variances gave a NEES median of -6.56 "100 % within the bound", and poses left without a
    # covariance were dropped without a word.
    truth, seq, run = sequence_and_run
    good = np.diag([1e-3**2] * 3 + [math.radians(0.5) ** 2] * 3)
    bad = {3: np.zeros((6, 6)), 4: -good, 5: None}
    _covariance_file(run, truth, lambda k: bad.get(k, good))
    code, out, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run), "--json")
    assert code == 0 and "Traceback" not in err, err
    s = json.loads(out)
    assert s["pose_nees"]["poses"] == 56 and s["pose_nees"]["median"] == pytest.approx(5.0, rel=1e-6)
    assert ("warning: 3 of the 59 paired poses have no usable covariance in " in err
            and "(1 not finite, 2 not positive definite or beyond what doubles can weigh): the NEES is over the "
                "other 56" in err), err
    # Every one unusable, or another run's file (no time in common): said, not judged.
    _covariance_file(run, truth, lambda k: -good)
    code, out, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run), "--json")
    assert code == 0 and "pose_nees" not in json.loads(out)
    assert "warning: none of the 59 paired poses has a usable covariance in " in err, err
    truth_later = MotionSeries(truth.t_s + 1000.0, truth.valid, truth.position_m, truth.quat_wxyz,
                               truth.velocity_cam_m_s, truth.omega_body_rad_s)
    _covariance_file(run, truth_later, lambda k: good)
    code, out, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run), "--json")
    assert "pose_nees" not in json.loads(out) and "none of the 59 paired poses" in err, err


def test_only_the_run_s_own_poses_are_judged_with_its_covariance(capsys, sequence_and_run, tmp_path) -> None:
    # Another tracker's trajectory put in a run folder was judged against the run's covariance
    # (NEES 131), and so was a bare TUM file with a pose_covariance.csv beside it.
    truth, seq, run = sequence_and_run
    good = np.diag([1e-3**2] * 3 + [math.radians(0.5) ** 2] * 3)
    _covariance_file(run, truth, lambda k: good)
    _tum(run / "other_tracker.tum", truth)
    code, out, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run / "other_tracker.tum"), "--json")
    assert code == 0 and "pose_nees" not in json.loads(out), out
    code, out, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run / "states.csv"), "--json")
    assert json.loads(out)["pose_nees"]["poses"] == 59
    (run / "run.yaml").unlink()  # not a track run's folder
    code, out, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run), "--json")
    assert code == 0 and "pose_nees" not in json.loads(out), out


def test_covariances_beyond_what_doubles_can_weigh_and_ambiguous_rows_are_left_out(capsys, sequence_and_run) -> None:
    # A second outside probe: matrices of 1e-310 passed the check and gave negative NEES counted
    # "within the bound"; a time given twice was resolved silently; a row cut off at the end
    # (no final newline) threw the whole file away or was read as a shorter number; a gap and
    # an infinity were both called "not a number".
    truth, seq, run = sequence_and_run
    good = np.diag([1e-3**2] * 3 + [math.radians(0.5) ** 2] * 3)
    rows = {3: good * 1e-307, 4: good * 1e300}
    _covariance_file(run, truth, lambda k: rows.get(k, good))
    text = (run / "pose_covariance.csv").read_text().splitlines()
    inf_row = text[7].split(",")
    inf_row[5] = "inf"
    text[7] = ",".join(inf_row)
    text.insert(9, text[9].replace(f"{good[0, 0]:.9e}", f"{2 * good[0, 0]:.9e}", 1))  # its time twice, unlike
    del text[12]  # a pose without a row
    cut = text[-1][:-4]  # cut off inside its last number, no newline after it
    (run / "pose_covariance.csv").write_text("\ufeff" + "\n".join(text[:-1] + [cut]))  # and a byte order mark
    code, out, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run), "--json")
    assert code == 0 and "Traceback" not in err, err
    s = json.loads(out)
    assert s["pose_nees"]["median"] == pytest.approx(5.0, rel=1e-6)
    assert s["pose_nees"]["poses"] == 59 - 6, s["pose_nees"]
    assert "its last line is cut off (no line end): left out" in err, err
    assert "1 time given twice with different values: left out" in err, err
    assert ("6 of the 59 paired poses have no usable covariance in " in err and "3 without a row at their time (" in err
            and "1 not finite" in err and "2 not positive definite or beyond what doubles can weigh" in err), err


def test_no_covariance_is_judged_for_a_run_whose_body_frame_is_its_own(capsys, sequence_and_run) -> None:
    # Case (a) or (c), compared without alignment: the errors are of the frame's placement, not
    # what the covariance describes (a NEES of 8e7 was printed beside the warning saying so).
    truth, seq, run = sequence_and_run
    good = np.diag([1e-3**2] * 3 + [math.radians(0.5) ** 2] * 3)
    _covariance_file(run, truth, lambda k: good)
    (run / "run.yaml").write_text(yaml.safe_dump({"status": "complete", "source": {"case": "a"}}))
    code, out, err = _run(capsys, "evaluate", "--truth", str(seq), "--estimate", str(run), "--align", "none", "--json")
    assert code == 0 and "pose_nees" not in json.loads(out), out
