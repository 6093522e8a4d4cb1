"""groundtruth.csv / states.csv reader and writers (DESIGN.md section 6)."""

from __future__ import annotations

import io
import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from trackmeter.core.transforms import quat_signs_continuous
from trackmeter.data.motion_csv import (
    GROUNDTRUTH_COLUMNS,
    STATES_COLUMNS,
    MotionCsvWriter,
    MotionSeries,
    read_motion_csv,
    write_groundtruth_csv,
    write_states_csv,
)
from trackmeter.errors import TrackmeterError


def _series(n: int = 7, seed: int = 0) -> MotionSeries:
    rng = np.random.default_rng(seed)
    q = Rotation.random(n, random_state=seed).as_quat(scalar_first=True)
    return MotionSeries(
        np.arange(n) * 0.08 + 1.0, np.ones(n, bool), rng.normal(size=(n, 3)), q,
        rng.normal(size=(n, 3)), rng.normal(size=(n, 3)),
    )


def test_groundtruth_round_trip_is_exact(tmp_path):
    s = _series()
    path = write_groundtruth_csv(tmp_path / "groundtruth.csv", s)
    assert path.read_text().splitlines()[0] == ",".join(GROUNDTRUTH_COLUMNS)
    r = read_motion_csv(path)
    for name in ("t_s", "position_m", "velocity_cam_m_s", "omega_body_rad_s"):
        np.testing.assert_array_equal(getattr(r, name), getattr(s, name))
    # The signs as docs/conventions.md says a written series has them.
    np.testing.assert_allclose(r.quat_wxyz, quat_signs_continuous(s.quat_wxyz), atol=1e-15)
    assert r.valid.all() and r.has_velocity and dict(r.extra) == {}


def test_a_groundtruth_csv_written_with_quotes_reads_as_without(tmp_path):
    # R's write.csv quotes the header's names, Python's csv.QUOTE_ALL every field: "header lacks
    # t,x,y,z,..." refused such a file (an outside probe).
    s = _series()
    plain = write_groundtruth_csv(tmp_path / "groundtruth.csv", s)
    lines = plain.read_text().splitlines()
    quoted = tmp_path / "quoted.csv"
    quoted.write_text("\n".join(",".join(f'"{f}"' for f in line.split(",")) for line in lines) + "\n")
    r = read_motion_csv(quoted)
    for name in ("t_s", "position_m", "quat_wxyz", "velocity_cam_m_s", "omega_body_rad_s"):
        np.testing.assert_array_equal(getattr(r, name), getattr(read_motion_csv(plain), name))


def test_states_writer_streams_whole_rows_and_invalid_rows_read_as_nan(tmp_path):
    path = tmp_path / "run" / "states.csv"
    q = np.array([0.5, 0.5, -0.5, 0.5])
    with MotionCsvWriter(path, STATES_COLUMNS) as w:
        w.write(t=0.0, valid=True, position_m=[1, 2, 3], quat_wxyz=q, velocity_cam_m_s=[0.1, 0, 0],
                omega_body_rad_s=[0, 0, 0.2], n_tracked=6, n_lost=0, latency_ms=12.5)
        # Half-way through, the file already holds the header and one complete row.
        assert read_motion_csv(path).t_s.tolist() == [0.0]
        w.write(t=0.08, valid=False, n_tracked=2, n_lost=4, latency_ms=9.0)
    lines = path.read_text().splitlines()
    assert lines[0] == ",".join(STATES_COLUMNS)
    assert lines[1].split(",")[1] == "1" and lines[1].split(",")[-3:] == ["6", "0", "12.5"]
    r = read_motion_csv(path)
    assert r.valid.tolist() == [True, False]
    np.testing.assert_allclose(r.quat_wxyz[0], q)
    assert np.isnan(r.position_m[1]).all()
    assert r.extra["n_lost"].tolist() == [0.0, 4.0]
    assert len(r.to_trajectory()) == 1
    assert r.has_velocity


def test_write_states_csv_round_trip(tmp_path):
    s = _series()
    extra = {"n_tracked": np.arange(7.0), "n_lost": np.zeros(7), "latency_ms": np.full(7, 3.25)}
    s = MotionSeries(s.t_s, np.arange(7) % 3 != 0, s.position_m, s.quat_wxyz, s.velocity_cam_m_s, s.omega_body_rad_s, extra)
    r = read_motion_csv(write_states_csv(tmp_path / "states.csv", s))
    np.testing.assert_array_equal(r.valid, s.valid)
    np.testing.assert_array_equal(r.extra["n_tracked"], extra["n_tracked"])
    np.testing.assert_array_equal(r.position_m, s.position_m)


def test_writer_refuses_unknown_column(tmp_path):
    with MotionCsvWriter(tmp_path / "g.csv") as w:
        with pytest.raises(TrackmeterError, match="no column"):
            w.write(t=0.0, bogus=1.0)


@pytest.mark.parametrize(
    "text, message",
    [
        ("", "empty file"),
        ("t,x,y\n0,1,2\n", "header lacks"),
        (",".join(GROUNDTRUTH_COLUMNS) + "\n", "no rows"),
        (",".join(GROUNDTRUTH_COLUMNS) + "\n0,1,2,3,1,0,0,0,0,0,0,0,0\n", "expected 14 values"),
        (",".join(GROUNDTRUTH_COLUMNS) + "\n0,1,2,3,1,0,0,zero,0,0,0,0,0,0\n", "not a number"),
        (",".join(GROUNDTRUTH_COLUMNS) + "\n1,1,2,3,1,0,0,0,0,0,0,0,0,0\n0,1,2,3,1,0,0,0,0,0,0,0,0,0\n", "time order"),
        ("t,valid,x,y,z,qw,qx,qy,qz\n0,1,1,2,3,1,0,0,0\n0.04,1,1,2,3,0,0,0,0\n", "bad.csv:3: a valid .1. row with a zero quaternion"),
        ("1.0 0 0 0 0 0 0 1\n", "header lacks"),  # a TUM file is not a motion CSV
        # TUM's header comment with commas: the file is a TUM trajectory, and the message says so
        ("#,t,tx,ty,tz,qx,qy,qz,qw\n0.04,0,0,3.5,0,0,0,1\n", "TUM trajectory, whose fields are separated by spaces"),
    ],
)
def test_bad_files_raise_one_line(tmp_path, text, message):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(TrackmeterError, match=message) as info:
        read_motion_csv(path)
    assert "\n" not in str(info.value) and str(path) in str(info.value)


def test_timestamps_that_go_backwards_are_named_by_time(tmp_path: Path) -> None:
    """'motion series: timestamps go backwards' did not say where, in a file of thousands of rows."""
    rows = [f"{t},1,2,3,1,0,0,0,0,0,0,0,0,0" for t in (0.0, 0.04, 0.08, 0.06, 0.12)]
    path = tmp_path / "groundtruth.csv"
    path.write_text(",".join(GROUNDTRUTH_COLUMNS) + "\n" + "\n".join(rows) + "\n")
    # and by its line, in the file's words rather than the internal series' (an outside probe)
    with pytest.raises(TrackmeterError, match=r"groundtruth\.csv:5: t = 0\.06 s after 0\.08 s on the line "
                                              r"before: rows must be in time order$"):
        read_motion_csv(path)


def test_tum_comments_anywhere_and_a_bom_read_as_numpy_loadtxt_reads_them(tmp_path: Path) -> None:
    from trackmeter.data.trajectory import read_tum

    text = ("# t tx ty tz qx qy qz qw\n"
            "1.0 0.1 0.2 3.5 0 0 0 1   # first pose\n"
            "\n"
            "1.04 0.1 0.2 3.6 0 0 0.0499792 0.9987503 #\n")
    path = tmp_path / "est.tum"
    path.write_text("\ufeff" + text, encoding="utf-8")
    got = read_tum(path)
    reference = np.loadtxt(io.StringIO(text), comments="#")  # how evo reads a TUM file
    assert np.array_equal(got.t_s, reference[:, 0]) and np.array_equal(got.position_m, reference[:, 1:4])
    q = reference[:, [7, 4, 5, 6]]
    assert np.allclose(got.quat_wxyz, q / np.linalg.norm(q, axis=1, keepdims=True), atol=1e-12)


def test_comment_lines_among_the_rows_are_skipped(tmp_path: Path) -> None:
    """A '#' line after the header (a note where a recording was resumed) was read as a row:
    'expected 14 values, got 1'. data.csv and TUM files skip such lines; so does a motion CSV,
    Windows line endings and blank lines included."""
    s = _series()
    plain = write_groundtruth_csv(tmp_path / "groundtruth.csv", s).read_text().splitlines()
    lines = [plain[0], plain[1], "# resumed here", "", plain[2], "  #, ,", *plain[3:]]
    path = tmp_path / "commented.csv"
    path.write_bytes(("\r\n".join(lines) + "\r\n").encode())
    got = read_motion_csv(path)
    np.testing.assert_array_equal(got.t_s, s.t_s)
    np.testing.assert_array_equal(got.position_m, s.position_m)
    np.testing.assert_array_equal(got.omega_body_rad_s, s.omega_body_rad_s)


def test_comment_lines_before_the_header_are_skipped(tmp_path: Path) -> None:
    # Another renderer's groundtruth.csv may open with comments; the header is the first line
    # naming the columns (with or without a leading '#', as EuRoC writes its headers).
    s = _series()
    plain = write_groundtruth_csv(tmp_path / "groundtruth.csv", s).read_text()
    for i, prefix in enumerate(("# ground truth from another renderer\n", "#\n# made 2026-11-27, units SI\n\n")):
        for header_hash in ("", "#"):
            path = tmp_path / f"gt_{i}{len(header_hash)}.csv"
            path.write_text(prefix + header_hash + plain)
            got = read_motion_csv(path)
            np.testing.assert_array_equal(got.position_m, s.position_m)
            np.testing.assert_array_equal(got.omega_body_rad_s, s.omega_body_rad_s)
    # a comment that names no columns is still not a header
    path = tmp_path / "only_comment.csv"
    path.write_text("# t x y z\n0 1 2 3\n")
    with pytest.raises(TrackmeterError, match="header lacks"):
        read_motion_csv(path)


def test_a_field_of_thousands_of_nul_bytes_is_quoted_short(tmp_path) -> None:
    """Two writers that clobbered a file left NUL holes; the error quoted the whole field (60 KB
    on one line). It is cut, with its length said."""
    from trackmeter.data.motion_csv import read_motion_csv
    from trackmeter.data.trajectory import read_tum
    from trackmeter.errors import TrackmeterError

    path = tmp_path / "states.csv"
    path.write_text("t,x,y,z,qw,qx,qy,qz\n0.0,0,0,1,1,0,0,0\n" + "\x00" * 20000 + "0.04,0,0,1,1,0,0,0\n")
    with pytest.raises(TrackmeterError) as err:
        read_motion_csv(path)
    assert len(str(err.value)) - len(str(path)) < 120 and "20004 characters" in str(err.value), str(err.value)
    tum = tmp_path / "t.tum"
    tum.write_text("0 0 0 1 0 0 0 1\n" + "x" * 5000 + " 0 0 1 0 0 0 1 0\n")
    with pytest.raises(TrackmeterError) as err:
        read_tum(tum)
    assert len(str(err.value)) - len(str(tum)) < 150, str(err.value)[:300]


def test_tum_poses_repeating_a_timestamp_are_skipped_with_a_warning_whatever_their_order(tmp_path: Path) -> None:
    # Which of two poses at one time paired with the truth depended on the lines' order, and
    # the other was counted unmatched without a word.
    from trackmeter.data.trajectory import read_tum

    lines = ["0 0 0 3 0 0 0 1", "0 0.01 0 3 0 0 0 1", "1 0 0 3 0 0 0 1"]
    for order, kept_x, line in (((0, 1, 2), 0.0, 3), ((2, 1, 0), 0.01, 4)):
        path = tmp_path / "dup.tum"
        path.write_text("# t tx ty tz qx qy qz qw\n" + "\n".join(lines[i] for i in order) + "\n")
        with pytest.warns(UserWarning, match=r"dup\.tum: 1 pose\(s\) skipped that repeat an earlier line's timestamp "
                                             rf"\(the first: line {line}, t = 0 s\); the first pose at each time is kept"):
            got = read_tum(path)
        assert got.t_s.tolist() == [0.0, 1.0]
        assert got.position_m[0, 0] == kept_x


def test_a_groundtruth_row_without_a_whole_pose_is_unknown_truth_at_that_time_only(tmp_path: Path) -> None:
    # "Empty fields are unknown" (README): one blank row of a groundtruth.csv refused the whole
    # file ("a valid row has a non-finite pose"), and track and evaluate lost all the truth.
    rows = ["0,0,0,3,1,0,0,0,0,0,0,0,0,0", "0.04,,,,,,,,,,,,,", "0.08,0,0,3,nan,0,0,0,0,0,0,0,0,0",
            "0.12,0,0,3,1,0,0,0,,,,,,"]
    path = tmp_path / "groundtruth.csv"
    path.write_text(",".join(GROUNDTRUTH_COLUMNS) + "\n" + "\n".join(rows) + "\n")
    with pytest.warns(UserWarning, match=r"groundtruth\.csv:3: 2 row\(s\) without a whole pose \(.*\) read as "
                                         r"no pose at their time \(the first on this line\)"):
        got = read_motion_csv(path)
    assert got.valid.tolist() == [True, False, False, True]
    assert np.isnan(got.velocity_cam_m_s[3]).all()  # a pose without rates is still a pose
    # A states.csv says which rows are valid; one that says 1 over an empty pose contradicts it.
    states = tmp_path / "states.csv"
    states.write_text("t,valid,x,y,z,qw,qx,qy,qz\n0,1,0,0,3,1,0,0,0\n0.04,1,,,,,,,\n")
    with pytest.raises(TrackmeterError, match=r"states\.csv:3: a valid \(1\) row without a whole pose"):
        read_motion_csv(states)


def test_a_header_with_some_of_the_rates_is_warned_about(tmp_path: Path) -> None:
    """A states.csv without its wx,wy,wz columns read without a word, and evaluate then
    compared no velocity at all, the linear one there included (an outside probe). A
    pose-only file (no rate column) is a file of poses, not warned about."""
    path = tmp_path / "states.csv"
    path.write_text("t,valid,x,y,z,qw,qx,qy,qz,vx,vy,vz,n_tracked\n0,1,0,0,3,1,0,0,0,0.1,0,0,5\n")
    with pytest.warns(UserWarning, match=r"states\.csv:1: the header has vx,vy,vz but not wx,wy,wz: those read as "
                                         r"unknown, and no velocity is compared without both"):
        got = read_motion_csv(path)
    assert got.velocity_cam_m_s[0].tolist() == [0.1, 0.0, 0.0] and np.isnan(got.omega_body_rad_s).all()
    path.write_text("t,valid,x,y,z,qw,qx,qy,qz\n0,1,0,0,3,1,0,0,0\n")
    truth = tmp_path / "data.csv"  # EuRoC's ground truth: a linear velocity, no angular one
    truth.write_text("#timestamp,p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z [],"
                     "v_RS_R_x [m s^-1],v_RS_R_y [m s^-1],v_RS_R_z [m s^-1]\n0,0,0,3,1,0,0,0,0.1,0,0\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_motion_csv(path)
        assert read_motion_csv(truth).velocity_cam_m_s[0].tolist() == [0.1, 0.0, 0.0]


@pytest.mark.parametrize(
    "bad_line, message",
    [
        ("0.08 0 0 3.5 0 0 0 0", "zero quaternion"),
        ("0.08 0 nan 3.5 0 0 0 1", r"ty is not finite \(nan\)"),
        ("0.08 0 0 3.5 0 0 0 inf", r"qw is not finite \(inf\)"),
        ("inf 0 0 3.5 0 0 0 1", "not finite"),
    ],
)
def test_a_bad_tum_pose_is_named_by_its_line(tmp_path: Path, bad_line: str, message: str) -> None:
    """'trajectory has a zero quaternion' did not say where, in a file of thousands of poses
    (an outside probe). The line is named, as for every other bad TUM line."""
    from trackmeter.data.trajectory import read_tum

    path = tmp_path / "est.tum"
    path.write_text("# t tx ty tz qx qy qz qw\n0.0 0 0 3.5 0 0 0 1\n0.04 0 0 3.5 0 0 0 1\n"
                    f"{bad_line}\n0.12 0 0 3.5 0 0 0 1\n")
    with pytest.raises(TrackmeterError, match=rf"est\.tum:4: .*{message}") as info:
        read_tum(path)
    assert "\n" not in str(info.value)


def test_a_groundtruth_row_with_a_zero_quaternion_is_no_truth_at_its_time_named_by_line(tmp_path: Path) -> None:
    """One such row threw the whole ground truth away ("motion series: a valid row has a zero
    quaternion", no line; track then said the recording had no truth): it is a time without
    truth, like a row with a NaN, and the line is named (an outside probe)."""
    rows = [f"{t},1,2,3,1,0,0,0,0,0,0,0,0,0" for t in (0.0, 0.04, 0.08, 0.12)]
    rows[2] = "0.08,1,2,3,0,0,0,0,0,0,0,0,0,0"
    path = tmp_path / "groundtruth.csv"
    path.write_text(",".join(GROUNDTRUTH_COLUMNS) + "\n" + "\n".join(rows) + "\n")
    with pytest.warns(UserWarning, match=r"groundtruth\.csv:4: 1 row\(s\) without a whole pose .*zero quaternion"):
        s = read_motion_csv(path)
    assert s.valid.tolist() == [True, True, False, True]


@pytest.mark.parametrize("reader", ["tum", "csv"])
def test_a_binary_file_is_said_not_to_be_text_with_what_is_expected(tmp_path: Path, reader: str) -> None:
    """`evaluate --truth cam0/data/0.png` said "cannot read as text: UnicodeDecodeError" (an
    outside probe): the exception's name, not what the file should have been."""
    from trackmeter.data.trajectory import read_tum

    path = tmp_path / "0.png"
    path.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR\xff\xfe")
    with pytest.raises(TrackmeterError) as info:
        (read_tum if reader == "tum" else read_motion_csv)(path)
    text = str(info.value)
    assert text.startswith(f"{path}: not a text file") and "UnicodeDecodeError" not in text
    assert ("TUM trajectory" if reader == "tum" else "CSV") in text


def test_a_last_line_cut_short_is_left_out_with_a_warning(tmp_path: Path) -> None:
    """A states.csv whose last line was cut by a full disk or a kill was refused whole
    ("expected 18 values, got 15"), while data.csv's cut rows are skipped (an outside probe):
    the rows before it are whole. A short line elsewhere is still an error."""
    rows = [f"{t},1,2,3,1,0,0,0,0,0,0,0,0,0" for t in (0.0, 0.04, 0.08)]
    path = tmp_path / "groundtruth.csv"
    path.write_text(",".join(GROUNDTRUTH_COLUMNS) + "\n" + "\n".join(rows) + "\n0.12,1,2,3,1,0")
    with pytest.warns(UserWarning, match=r"groundtruth\.csv:5: the last line is cut short \(6 of 14 values\)"):
        s = read_motion_csv(path)
    assert len(s) == 3
    path.write_text(",".join(GROUNDTRUTH_COLUMNS) + "\n" + rows[0] + "\n0.02,1,2\n" + "\n".join(rows[1:]) + "\n")
    with pytest.raises(TrackmeterError, match=r"groundtruth\.csv:3: expected 14 values, got 3"):
        read_motion_csv(path)


def test_a_tum_file_whose_last_line_is_cut_short_is_read_without_it(tmp_path: Path) -> None:
    """A trajectory.tum cut mid-line (a full disk, a kill) was refused whole, while a motion
    CSV's cut last line is left out with a warning (an outside probe)."""
    from trackmeter.data.trajectory import read_tum

    path = tmp_path / "cut.tum"
    path.write_text("# t tx ty tz qx qy qz qw\n0.0 0 0 3.5 0 0 0 1\n0.04 0 0 3.5 0 0 0 1\n0.08 0 0 3.")
    with pytest.warns(UserWarning, match=r"cut\.tum:4: the last line is cut short, left out"):
        assert len(read_tum(path)) == 2
    path.write_text("# t tx ty tz qx qy qz qw\n0.0 0 0 3.5 0 0 0 1\n0.04 0 0\n0.08 0 0 3.5 0 0 0 1\n")
    with pytest.raises(TrackmeterError, match=r"cut\.tum:3: expected 8 values"):
        read_tum(path)
    # cut to its first field, no newline after it (an outside probe: refused whole)
    path.write_text("# t tx ty tz qx qy qz qw\n0.0 0 0 3.5 0 0 0 1\n0.04 0 0 3.5 0 0 0 1\n1.92")
    with pytest.warns(UserWarning, match=r"cut\.tum:4: the last line is cut short"):
        assert len(read_tum(path)) == 2
    path.write_text("# t tx ty tz qx qy qz qw\n0.0 0 0 3.5 0 0 0 1\n0.04 0 0 3.5 0 0 0 1\n1.92\n")
    with pytest.raises(TrackmeterError, match=r"cut\.tum:4: expected 8 values .*, got 1"):
        read_tum(path)  # a whole line of one value is no cut


def test_a_header_written_as_a_comment_is_pointed_at(tmp_path: Path) -> None:
    # A "#stamp [ns],x,..." header was skipped as a comment, and the refusal named line 2, the
    # first row of numbers, as the header (an outside probe).
    path = tmp_path / "groundtruth.csv"
    path.write_text("#stamp [ns],x,y,z,qw,qx,qy,qz\n0,0,0,3.5,1,0,0,0\n")
    with pytest.raises(TrackmeterError) as info:
        read_motion_csv(path)
    assert str(info.value).startswith(f"{path}:2: not a motion CSV: header lacks t,x,y,z,qw,qx,qy,qz")
    assert "; line 1 above it is a comment ('#stamp [ns],x,y,z" in str(info.value), info.value
    # EuRoC's names, its frame letters left out, are a header (its ground truth's, read as ours)
    path.write_text("#timestamp [ns],p_x [m],p_y [m],p_z [m],q_w [],q_x [],q_y [],q_z []\n0,0,0,3.5,1,0,0,0\n")
    series = read_motion_csv(path)
    assert series.position_m.tolist() == [[0.0, 0.0, 3.5]] and series.quat_wxyz.tolist() == [[1.0, 0.0, 0.0, 0.0]]
    path.write_text("# written by hand\nt;x;y\n0;0;0\n")  # a comment that is no header is not named
    with pytest.raises(TrackmeterError) as info:
        read_motion_csv(path)
    assert "comment" not in str(info.value)


def test_a_tum_line_cut_inside_its_last_field_is_left_out(tmp_path: Path) -> None:
    """A writer killed inside a line's last field (qw) leaves 8 values without a newline:
    read as a pose, its quaternion was silently another one (qw 0.70710 cut to 0.7, 0.6 deg
    off, renormalised without a word), or the whole file refused ("not a number" for a cut
    "-" or "1e"). Such a line is left out with the cut-line warning when every line before
    holds a unit quaternion; a file whose quaternions are all unnormalised is read as before."""
    from trackmeter.data.trajectory import read_tum

    whole = "0.0 0 0 3.5 0 0 0.707106781 0.707106781\n0.04 0 0 3.5 0 0 0.707106781 0.707106781\n"
    path = tmp_path / "cut.tum"
    for last in ("0.08 0 0 3.5 0 0 0.707106781 0.7", "0.08 0 0 3.5 0 0 0.707106781 -", "0.08 0 0 3.5 0 0 0.7 1e"):
        path.write_text(whole + last)
        with pytest.warns(UserWarning, match=r"cut\.tum:3: the last line is cut short, left out"):
            assert len(read_tum(path)) == 2
    path.write_text(whole + "0.08 0 0 3.5 0 0 0.707106781 0.707106781")  # whole, only its newline missing
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert len(read_tum(path)) == 3
    path.write_text("0.0 0 0 3.5 0 0 2 2\n0.04 0 0 3.5 0 0 2 2\n0.08 0 0 3.5 0 0 2 3")  # a producer's unnormalised q
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        assert len(read_tum(path)) == 3  # not cut: normalised, and said as such
    assert [str(w.message).split(": ", 1)[1][:45] for w in said] == ["3 line(s) whose quaternion's norm is far from"]


def test_rows_repeating_a_timestamp_are_skipped_with_a_warning_as_in_a_tum_file(tmp_path: Path) -> None:
    """A groundtruth.csv row repeating the time before was taken silently (an unmatched pose
    more in evaluate), where a TUM file's repeat is warned and skipped (an outside probe)."""
    rows = [f"{t},{x},2,3,1,0,0,0,0,0,0,0,0,0" for t, x in ((0.0, 1), (0.04, 1), (0.04, 9), (0.08, 1))]
    path = tmp_path / "groundtruth.csv"
    path.write_text(",".join(GROUNDTRUTH_COLUMNS) + "\n" + "\n".join(rows) + "\n")
    with pytest.warns(UserWarning, match=r"groundtruth\.csv:4: 1 row\(s\) repeating the timestamp of the row before "
                                         r"skipped \(the first on this line\); the first row at each time is kept"):
        s = read_motion_csv(path)
    assert s.t_s.tolist() == [0.0, 0.04, 0.08] and s.position_m[:, 0].tolist() == [1.0, 1.0, 1.0]
    # and in a file without the rate columns (the rows' count sizes the missing ones)
    path.write_text("t,x,y,z,qw,qx,qy,qz\n0,1,2,3,1,0,0,0\n0.04,1,2,3,1,0,0,0\n0.04,9,2,3,1,0,0,0\n")
    with pytest.warns(UserWarning, match="repeating the timestamp"):
        assert len(read_motion_csv(path).velocity_cam_m_s) == 2


def test_quaternions_far_from_unit_norm_are_said_with_their_line(tmp_path) -> None:
    """A groundtruth.csv whose quaternion columns held norm 2 (or angles: roll, pitch, yaw, 0)
    was normalised without a word into some attitude (an outside probe). Rounding (six
    decimals) says nothing."""
    from trackmeter.data.trajectory import read_tum

    path = tmp_path / "groundtruth.csv"
    path.write_text("t,x,y,z,qw,qx,qy,qz\n0,0,0,3,0.707107,0,0.707107,0\n0.04,0,0,3,2,0,0,0\n"
                    "0.08,0,0,3,0.3,0.1,-0.2,0\n")
    with pytest.warns(UserWarning, match=r"groundtruth.csv:3: 2 row\(s\) whose quaternion's norm is far from 1 "
                                         r"\(2 on this line\)"):
        series = read_motion_csv(path)
    assert np.allclose(np.linalg.norm(series.quat_wxyz, axis=1), 1.0)
    tum = tmp_path / "t.tum"
    tum.write_text("0 0 0 3 0 0.707107 0 0.707107\n0.04 0 0 3 0 0 0 2\n")
    with pytest.warns(UserWarning, match=r"t.tum:2: 1 line\(s\) whose quaternion's norm is far from 1"):
        read_tum(tum)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tum.write_text("0 0 0 3 0 0.707107 0 0.707107\n")
        read_tum(tum)


def test_a_time_is_the_same_text_in_states_csv_as_in_the_tum_files_and_targets_csv() -> None:
    """A run's files are joined on their time column: states.csv wrote the shortest round trip
    (``0.12000000000000001``, an epoch time's 17 digits) where trajectory.tum and targets.csv
    write nine decimals (``0.120000000``)."""
    from trackmeter.data.motion_csv import format_csv_value
    from trackmeter.data.trajectory import format_tum_line

    for t_s in (0.04 * 3, 1733570000.123456789, 0.0, 12.5):
        tum_text = format_tum_line(t_s, np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0])).split()[0]
        assert format_csv_value("t", t_s) == tum_text == f"{t_s:.9f}"
    assert format_csv_value("x", 0.04 * 3) == repr(0.04 * 3)  # other columns keep every digit
    assert format_csv_value("t", float("nan")) == ""
