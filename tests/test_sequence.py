"""Sequence folders (EuRoC layout), model files and the file/video/camera sources."""

from __future__ import annotations

import contextlib
import os
from dataclasses import replace
import subprocess
import sys
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from trackmeter.data.model import Model, load_model, save_model
from trackmeter.data.motion_csv import GROUNDTRUTH_COLUMNS, read_motion_csv
from trackmeter.data.sequence import SequenceWriter, index_sequence, pair_by_nearest, seconds_to_ns
from trackmeter.errors import TrackmeterError
from trackmeter.sources import open_source
from trackmeter.sources.base import GroundTruth, StereoFrame
from trackmeter.sources.pacing import Pacer
from trackmeter.sources.sequence import SequenceSource


def _frames(n: int = 6, rate: float = 25.0, truth: bool = True, seed: int = 0) -> list[StereoFrame]:
    rng = np.random.default_rng(seed)
    frames = []
    for i in range(n):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec([0.01 * i, 0.2, -0.1]).as_matrix()
        T[:3, 3] = [0.01 * i, -0.02, 3.5 - 0.001 * i]
        gt = GroundTruth(T, np.array([0.25, 0.0, -0.025]), np.array([0.01, -0.02, 0.03])) if truth else None
        frames.append(StereoFrame(i, i / rate, rng.integers(0, 256, (24, 32), dtype=np.uint8),
                                  rng.integers(0, 256, (24, 32), dtype=np.uint8), gt))
    return frames


def _write(directory: Path, frames, **kwargs) -> Path:
    with SequenceWriter(directory, **kwargs) as w:
        for f in frames:
            w.write(f)
    return directory


def _assert_same(a: StereoFrame, b: StereoFrame) -> None:
    assert a.index == b.index
    assert abs(a.t_s - b.t_s) < 1e-9
    assert np.array_equal(a.left, b.left) and np.array_equal(a.right, b.right)
    assert (a.truth is None) == (b.truth is None)
    if a.truth is not None:
        assert np.allclose(a.truth.T_cam_body, b.truth.T_cam_body, atol=1e-12)
        assert np.allclose(a.truth.velocity_cam_m_s, b.truth.velocity_cam_m_s, atol=1e-12)
        assert np.allclose(a.truth.omega_body_rad_s, b.truth.omega_body_rad_s, atol=1e-12)


# --------------------------------------------------------------------------- round trips


def test_write_then_read_frame_for_frame(tmp_path, estec_rig):
    frames = _frames()
    model = Model(("a", "b", "c"), np.array([[0, 0, 0], [1.0, 0, 0], [0, 0.5, 0.25]]))
    d = _write(tmp_path / "seq", frames, rig=estec_rig, model_points=model)
    # The files of DESIGN.md section 6, with the contract headers.
    assert (d / "cam0" / "data.csv").read_text().splitlines()[0] == "#timestamp [ns],filename"
    assert (d / "cam1" / "data.csv").read_text().splitlines()[1] == "0,0.png"
    assert (d / "cam1" / "data.csv").read_text().splitlines()[2] == "40000000,40000000.png"
    assert (d / "groundtruth.csv").read_text().splitlines()[0] == "t,x,y,z,qw,qx,qy,qz,vx,vy,vz,wx,wy,wz"
    assert ",".join(GROUNDTRUTH_COLUMNS) == "t,x,y,z,qw,qx,qy,qz,vx,vy,vz,wx,wy,wz"
    assert len([x for x in (d / "groundtruth.tum").read_text().splitlines() if not x.startswith("#")]) == len(frames)
    assert not [p for p in d.rglob(".*")], "no temporary files left behind"
    with open_source(f"seq:{d}") as src:
        assert isinstance(src, SequenceSource)
        assert src.frame_size == (32, 24)  # from the first image, before the first read
        assert src.skipped == 0 and src.warning is None
        assert src.n_frames == len(src) == len(frames)
        assert src.rate_hz == pytest.approx(25.0)
        assert src.rig is not None and np.allclose(src.rig.left.K, estec_rig.left.K)
        assert np.allclose(src.rig.R, estec_rig.R) and np.allclose(src.rig.T, estec_rig.T)
        assert src.model is not None and src.model.ids == model.ids
        assert np.array_equal(src.model.points_body, model.points_body)
        read = []
        while (f := src.read()) is not None:
            read.append(f)
    assert len(read) == len(frames)
    for a, b in zip(frames, read):
        _assert_same(a, b)
    # A bare folder is a sequence SPEC too.
    with open_source(str(d)) as src:
        _assert_same(frames[0], src.read())


def test_tum_only_truth_and_no_truth(tmp_path):
    d = _write(tmp_path / "s", _frames(4))
    (d / "groundtruth.csv").unlink()
    src = SequenceSource(d)
    f = src.read()
    assert np.allclose(f.truth.T_cam_body, _frames(4)[0].truth.T_cam_body, atol=1e-8)
    assert np.all(np.isnan(f.truth.velocity_cam_m_s))
    d2 = _write(tmp_path / "n", _frames(3, truth=False))
    assert not (d2 / "groundtruth.csv").exists()
    assert SequenceSource(d2).read().truth is None


def test_loop_and_restart_keep_time_increasing(tmp_path):
    d = _write(tmp_path / "s", _frames(3))
    src = SequenceSource(d, loop=True)
    frames = [src.read() for _ in range(7)]
    ts = [f.t_s for f in frames]
    assert np.all(np.diff(ts) > 0)
    assert np.allclose(np.diff(ts), 0.04)
    assert [f.cut for f in frames] == [False, False, False, True, False, False, True]
    src.restart()
    f = src.read()
    assert f.index == 0 and f.t_s == 0.0 and f.cut and not src.read().cut
    src2 = SequenceSource(d)
    assert [src2.read() is not None for _ in range(4)] == [True, True, True, False]


def test_a_recorded_loop_plays_back_with_its_cuts(tmp_path):
    # A looping source recorded across its new pass (or a restart): the frames after it come
    # with the time carried on, and the scene jumps there. Unmarked, a replay tracked across the
    # jump as if the body had moved (an outside console probe: 16.9 deg median attitude error).
    d = _write(tmp_path / "s", _frames(3))
    src = SequenceSource(d, loop=True)
    looped = [src.read() for _ in range(7)]
    rec = _write(tmp_path / "rec", looped)
    assert (rec / "cuts.csv").read_text().splitlines()[1:] == [str(seconds_to_ns(looped[i].t_s)) for i in (3, 6)]
    index = index_sequence(rec)
    assert index.cuts == (3, 6)
    again = SequenceSource(rec)
    assert [f.cut for f in (again.read() for _ in range(7))] == [False, False, False, True, False, False, True]
    # played in a loop, the folder's own cuts and the loop's both mark the frame they start
    replay = SequenceSource(rec, loop=True)
    assert [f.cut for f in (replay.read() for _ in range(9))] == [False, False, False, True, False, False, True,
                                                                  True, False]
    # a cuts.csv that cannot be read is optional: warned about, not fatal
    (rec / "cuts.csv").write_text("#timestamp [ns]\nnot a number\n")
    index = index_sequence(rec)
    assert index.cuts == () and any("cuts.csv" in w for w in index.warnings), index.warnings


def test_euroc_mav0_layout_with_sensor_yaml(tmp_path):
    """Real EuRoC: mav0/cam0, mav0/cam1, sensor.yaml, no rig.yaml, extra columns absent."""
    root = tmp_path / "MH_01" / "mav0"
    rng = np.random.default_rng(1)
    t0 = 1403636579763555584  # EuRoC-style absolute nanoseconds
    for cam in ("cam0", "cam1"):
        (root / cam / "data").mkdir(parents=True)
        (root / cam / "sensor.yaml").write_text("sensor_type: camera\nrate_hz: 20\n")
        rows = ["#timestamp [ns],filename"]
        for i in range(3):
            ns = t0 + i * 50_000_000
            colour = rng.integers(0, 256, (10, 12, 3), dtype=np.uint8)
            cv2.imwrite(str(root / cam / "data" / f"{ns}.png"), colour)
            rows.append(f"{ns},{ns}.png")
        (root / cam / "data.csv").write_text("\r\n".join(rows) + "\r\n")
    with pytest.warns(UserWarning, match="no key 'intrinsics'"):
        src = open_source(f"seq:{tmp_path / 'MH_01'}")
    assert src.rig is None and src.skipped == 0
    # Seconds since 1970 in a float are resolved to 2.4e-7 s, so a 50 ms interval to ~5e-6.
    assert src.rate_hz == pytest.approx(20.0, rel=1e-5)
    f = src.read()
    assert f.left.dtype == np.uint8 and f.left.shape == (10, 12)
    assert f.t_s == pytest.approx(t0 / 1e9)


def test_mav0_layout_finds_rig_model_and_truth_in_dir_first(tmp_path, estec_rig):
    """DESIGN.md lists rig.yaml, model.yaml and groundtruth.* in DIR; with the images under
    DIR/mav0 they are found there, before DIR/mav0's own, and evaluate --truth agrees."""
    from trackmeter.data.evaluation import load_truth

    frames = _frames(4)
    model = Model(("a", "b", "c"), np.array([[0, 0, 0], [1.0, 0, 0], [0, 0.5, 0.25]]))
    d = tmp_path / "seq"
    _write(d / "mav0", frames, rig=estec_rig, model_points=model)
    for name in ("rig.yaml", "model.yaml", "groundtruth.csv", "groundtruth.tum"):
        (d / "mav0" / name).rename(d / name)
    index = index_sequence(d)
    assert index.root == d / "mav0"
    assert index.rig is not None and np.allclose(index.rig.left.K, estec_rig.left.K)
    assert index.model is not None and index.model.ids == model.ids
    assert index.truth is not None and np.all(index.truth.valid)
    assert load_truth(d).source == str(d / "groundtruth.csv")
    # DIR's files win over DIR/mav0's, for the sequence reader and for evaluate alike.
    save_model(d / "mav0" / "model.yaml", Model(("x", "y", "z"), np.eye(3)))
    (d / "mav0" / "groundtruth.csv").write_text((d / "groundtruth.csv").read_text())
    assert index_sequence(d).model.ids == model.ids
    assert load_truth(d).source == str(d / "groundtruth.csv")
    # DIR is searched before DIR/mav0 (csv before tum within each): DIR's tum beats mav0's csv.
    (d / "groundtruth.csv").unlink()
    assert load_truth(d).source == str(d / "groundtruth.tum")
    # Only in DIR/mav0 (EuRoC's own place): still found.
    for name in ("model.yaml", "groundtruth.tum"):
        (d / name).unlink()
    assert index_sequence(d).model.ids == ("x", "y", "z")
    assert load_truth(d).source == str(d / "mav0" / "groundtruth.csv")


def test_a_folders_rig_without_an_image_size_takes_the_frames(tmp_path, estec_rig):
    """A rig that carries no image size (OpenCV's intrinsics.yml + extrinsics.yml from its
    stereo_calib sample, or a rig.yaml without image_width/height) reads with the size of the
    folder's frames, as ``--rig`` with the same files does."""
    frames = _frames(3)
    K = np.array([[30.0, 0.0, 15.5], [0.0, 30.0, 11.5], [0.0, 0.0, 1.0]])
    rig = replace(estec_rig, left=replace(estec_rig.left, width=32, height=24, K=K),
                  right=replace(estec_rig.right, width=32, height=24, K=K))
    d = _write(tmp_path / "seq", frames, rig=rig)
    text = (d / "rig.yaml").read_text()
    stripped = "\n".join(line for line in text.splitlines() if not line.startswith("image_"))
    (d / "rig.yaml").write_text(stripped + "\n")
    assert index_sequence(d).rig.image_size == (32, 24)
    (d / "rig.yaml").unlink()
    fs = cv2.FileStorage(str(d / "intrinsics.yml"), cv2.FILE_STORAGE_WRITE)
    for key, value in (("M1", rig.left.K), ("D1", rig.left.dist.reshape(1, -1)), ("M2", rig.right.K),
                       ("D2", rig.right.dist.reshape(1, -1))):
        fs.write(key, value)
    fs.release()
    fs = cv2.FileStorage(str(d / "extrinsics.yml"), cv2.FILE_STORAGE_WRITE)
    fs.write("R", rig.R)
    fs.write("T", rig.T.reshape(3, 1))
    fs.release()
    got = index_sequence(d).rig
    assert got is not None and got.image_size == (32, 24)
    np.testing.assert_array_equal(got.left.K, rig.left.K)
    np.testing.assert_array_equal(got.T, rig.T)


def test_frame_times_are_the_nanoseconds_correctly_rounded(tmp_path):
    """t = ns / 1e9, not ns * 1e-9 (120000000 ns -> 0.12000000000000001 s): a frame's time in
    the index, in groundtruth.* and as written by the simulator are the same float."""
    frames = _frames(10)
    index = index_sequence(_write(tmp_path / "s", frames))
    assert index.t_s.tolist() == [f.t_s for f in frames]  # i / 25, exactly
    assert index.truth is not None and np.all(index.truth.valid)
    assert index.tolerance_s == 0.25 * 0.04


EUROC_CAM0 = """# General sensor definitions.
sensor_type: camera
comment: VI-Sensor cam0 (MT9M034)

# Sensor extrinsics wrt. the body-frame.
T_BS:
  cols: 4
  rows: 4
  data: [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975,
         0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768,
        -0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949,
         0.0, 0.0, 0.0, 1.0]

# Camera specific definitions.
rate_hz: 20
resolution: [752, 480]
camera_model: pinhole
intrinsics: [458.654, 457.296, 367.215, 248.375] #fu, fv, cu, cv
distortion_model: radial-tangential
distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
"""


def test_euroc_sensor_yaml_gives_the_rig(tmp_path):
    """cam1 mounted 0.11 m along cam0's +x and turned 1 deg about its y axis: the rig says so."""
    _write(tmp_path / "seq" / "mav0", _frames(2, truth=False))
    T_BS0 = np.array(yaml.safe_load(EUROC_CAM0)["T_BS"]["data"]).reshape(4, 4)
    T_c0_c1 = np.eye(4)
    T_c0_c1[:3, :3] = Rotation.from_euler("y", 1.0, degrees=True).as_matrix()
    T_c0_c1[:3, 3] = [0.11, 0.0, 0.0]
    T_BS1 = T_BS0 @ T_c0_c1
    cam1 = EUROC_CAM0.replace("VI-Sensor cam0", "VI-Sensor cam1")
    old = EUROC_CAM0[EUROC_CAM0.index("  data: ["):EUROC_CAM0.index("# Camera specific")]
    cam1 = cam1.replace(old, "  data: [" + ", ".join(repr(float(x)) for x in T_BS1.ravel()) + "]\n\n")
    (tmp_path / "seq" / "mav0" / "cam0" / "sensor.yaml").write_text("%YAML:1.0\n" + EUROC_CAM0)
    (tmp_path / "seq" / "mav0" / "cam1" / "sensor.yaml").write_text(cam1)
    src = open_source(f"seq:{tmp_path / 'seq'}")
    rig = src.rig
    assert rig is not None and src.warning is None
    assert rig.image_size == (752, 480)
    assert np.allclose(rig.left.K, [[458.654, 0, 367.215], [0, 457.296, 248.375], [0, 0, 1]])
    assert np.allclose(rig.left.dist[:4], [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05])
    # p_cam1 = R p_cam0 + T with (R, T) = inv(T_c0_c1).
    assert np.allclose(rig.R, T_c0_c1[:3, :3].T, atol=1e-12)
    assert np.allclose(rig.T, -T_c0_c1[:3, :3].T @ [0.11, 0, 0], atol=1e-12)
    assert rig.baseline_m == pytest.approx(0.11)
    assert src.index.rig_file == tmp_path / "seq" / "mav0" / "cam0" / "sensor.yaml"  # what run.yaml names
    # An unsupported model: played, rig unknown, and said so.
    (tmp_path / "seq" / "mav0" / "cam1" / "sensor.yaml").write_text(cam1.replace("radial-tangential", "equidistant"))
    with pytest.warns(UserWarning, match="not supported"):
        src = open_source(f"seq:{tmp_path / 'seq'}")
    assert src.rig is None and "not supported" in src.warning and src.skipped == 0
    assert src.index.rig_file is None


# --------------------------------------------------------------------------- bad input


def test_rows_repeated_in_data_csv_are_said_to_be_repeats_not_images_without_a_partner(tmp_path):
    frames = _frames(4)
    d = _write(tmp_path / "s", frames)
    for cam in ("cam0", "cam1"):  # data.csv appended to twice: every row but the header repeated
        text = (d / cam / "data.csv").read_text()
        header, rows = text.split("\n", 1)
        (d / cam / "data.csv").write_text(header + "\n" + rows + rows)
    with pytest.warns(UserWarning, match="repeating an earlier timestamp"):
        src = SequenceSource(d)
    assert len(src) == 4 and src.skipped == 8
    assert "8 data.csv row(s) repeating an earlier timestamp skipped (cam0: 4, cam1: 4)" in src.warning
    assert "without a partner" not in src.warning


def test_cameras_offset_in_time_are_refused_with_the_offset(tmp_path):
    # Every right image 25 ms after its left one at 25 Hz was refused as "no stereo pair (left
    # and right timestamps within 10 ms)", with nothing of how far apart the cameras are or
    # what to do (an outside probe).
    d = _write(tmp_path / "s", _frames(6))
    csv1 = (d / "cam1" / "data.csv").read_text().splitlines()
    rows = [csv1[0]]
    for row in csv1[1:]:
        t, name = row.split(",")
        late = int(t) + 25_000_000
        os.replace(d / "cam1" / "data" / name, d / "cam1" / "data" / f"{late}.png")
        rows.append(f"{late},{late}.png")
    (d / "cam1" / "data.csv").write_text("\n".join(rows) + "\n")
    with pytest.raises(TrackmeterError) as info:
        SequenceSource(d)
    text = str(info.value)
    assert text.startswith(f"{d}: no stereo pair (left and right timestamps within 10 ms): "), text
    assert "each left image's nearest right one is a median 15 ms away (right minus left: -15 ms)" in text, text
    assert "triggered together" in text, text


@pytest.mark.parametrize("cameras", [("cam0", "cam1"), ("cam1",)])
def test_timestamps_that_go_back_in_data_csv_are_said_with_their_line(tmp_path, cameras):
    # A camera clock reset half-way (the second half restarting at 5 ms) played the two halves
    # interleaved with only a wrong "gaps" warning, and one row stamped early played out of
    # order with nothing said (an outside probe); groundtruth.csv's rows are refused so.
    d = _write(tmp_path / "s", _frames(8))
    for cam in cameras:
        rows = (d / cam / "data.csv").read_text().splitlines()
        reset = rows[:6]
        for row in rows[6:]:
            t, name = row.split(",")
            reset.append(f"{int(t) - 195_000_000},{name}")  # 200 ms -> 5 ms
        (d / cam / "data.csv").write_text("\n".join(reset) + "\n")
    with pytest.warns(UserWarning, match="back in time"):
        src = SequenceSource(d)
    for cam in cameras:
        assert (f"{cam}/data.csv: 1 row(s) back in time from the row above (the first on line 7, "
                "0.155 s back): played in time order") in src.warning, src.warning
    assert len(src) == (8 if len(cameras) == 2 else 5)


def test_rows_in_time_order_say_nothing_of_time_going_back(tmp_path):
    src = SequenceSource(_write(tmp_path / "s", _frames(4)))
    assert src.warning is None


def _retime_right(d: Path, shift_ns) -> None:
    """Give cam1's images the times ``shift_ns(t)`` (renamed to match)."""
    rows = (d / "cam1" / "data.csv").read_text().splitlines()
    out = [rows[0]]
    for row in rows[1:]:
        t, name = row.split(",")
        moved = shift_ns(int(t))
        os.replace(d / "cam1" / "data" / name, d / "cam1" / "data" / f"t{moved}.png")
        out.append(f"{moved},t{moved}.png")
    (d / "cam1" / "data.csv").write_text("\n".join(out) + "\n")


def test_cameras_paired_a_constant_few_milliseconds_apart_are_said_to_be(tmp_path):
    # Right images 8 ms after the left ones (within the 10 ms window) were paired with nothing
    # said, while a moving target is then measured from two instants (an outside probe).
    d = _write(tmp_path / "s", _frames(6))
    _retime_right(d, lambda t: t + 8_000_000)
    with pytest.warns(UserWarning, match="8 ms apart"):
        src = SequenceSource(d)
    assert len(src) == 6 and src.skipped == 0
    assert ("left and right images paired a median 8 ms apart (right minus left: +8 ms): a moving target is seen "
            "at two instants; if the cameras were triggered together, shift cam1/data.csv's timestamps by -8 ms") in src.warning


def test_clocks_that_drift_apart_are_said_to_where_pairs_are_lost(tmp_path):
    # The right clock 1 % fast: only the first half paired, said as "images without a partner"
    # alone (an outside probe).
    d = _write(tmp_path / "s", _frames(50))
    _retime_right(d, lambda t: int(t * 1.01))
    with pytest.warns(UserWarning, match="without a partner"):
        src = SequenceSource(d)
    assert 20 <= len(src) < 50
    assert "the cameras' clocks drift apart" in src.warning, src.warning
    assert "shift cam1" not in src.warning, src.warning  # no one shift mends a drift


@pytest.mark.parametrize("late_start", [True, False])
def test_a_camera_that_starts_late_or_ends_early_is_no_clock_drift(tmp_path, late_start):
    # cam1 starting 1 s late was said to be "clocks drifting apart" (+520 ms over the first
    # quarter, +0 over the last): its first quarter's nearest images were far only because it
    # had none there (an outside re-check).
    d = _write(tmp_path / "s", _frames(50))
    rows = (d / "cam1" / "data.csv").read_text().splitlines()
    kept = rows[1:][25:] if late_start else rows[1:][:25]
    (d / "cam1" / "data.csv").write_text("\n".join([rows[0], *kept]) + "\n")
    with pytest.warns(UserWarning, match="25 image\\(s\\) without a partner"):
        src = SequenceSource(d)
    assert len(src) == 25 and "drift" not in src.warning, src.warning


def test_jittered_but_simultaneous_cameras_say_nothing_of_an_offset(tmp_path):
    rng = np.random.default_rng(3)
    d = _write(tmp_path / "s", _frames(20))
    _retime_right(d, lambda t: t + int(rng.integers(-3_000_000, 3_000_000)))
    src = SequenceSource(d)
    assert src.warning is None or "apart" not in src.warning, src.warning


def test_missing_images_and_unpaired_timestamps_are_skipped_counted_and_reported(tmp_path):
    frames = _frames(8)
    d = _write(tmp_path / "s", frames)
    # 1. A left image missing from disk.
    (d / "cam0" / "data" / "80000000.png").unlink()
    # 2. The right image of frame 5 recorded 15 ms late: pairs by nearest time (tolerance 10 ms).
    late = 200_000_000 + 15_000_000
    os.replace(d / "cam1" / "data" / "200000000.png", d / "cam1" / "data" / f"{late}.png")
    # 3. A right image 3 ms off: still paired.
    off = 280_000_000 - 3_000_000
    os.replace(d / "cam1" / "data" / "280000000.png", d / "cam1" / "data" / f"{off}.png")
    csv1 = (d / "cam1" / "data.csv").read_text()
    csv1 = csv1.replace("200000000,200000000.png", f"{late},{late}.png").replace("280000000,280000000.png", f"{off},{off}.png")
    (d / "cam1" / "data.csv").write_text(csv1 + "32000")  # 4. a row cut short by a crash
    with pytest.warns(UserWarning, match="skipped"):
        src = SequenceSource(d)
    # Left 2 (missing) leaves right 2 alone; left 5 and right 5 (15 ms) both unpaired; one cut row.
    assert len(src) == 6
    assert src.skipped == 1 + 1 + 2 + 1
    assert "missing" in src.warning and "without a partner" in src.warning and "cut-short" in src.warning
    got = []
    while (f := src.read()) is not None:
        got.append(f)
    kept = [0, 1, 3, 4, 6, 7]
    assert [round(f.t_s * 25) for f in got] == kept
    for f, k in zip(got, kept):
        assert np.array_equal(f.left, frames[k].left)
        assert np.array_equal(f.right, frames[k].right)
        assert np.allclose(f.truth.T_cam_body, frames[k].truth.T_cam_body)


def test_data_csv_of_other_tools_extra_columns_and_a_bom_are_read(tmp_path):
    frames = _frames(3)
    d = _write(tmp_path / "s", frames)
    for cam in ("cam0", "cam1"):
        rows = (d / cam / "data.csv").read_text().splitlines()
        extended = [rows[0] + ",exposure_us"] + [r + ",1200" for r in rows[1:]]
        (d / cam / "data.csv").write_text("\ufeff" + "\n".join(extended) + "\n", encoding="utf-8")
    src = SequenceSource(d)
    assert src.warning is None and len(src) == 3
    got = [src.read() for _ in range(3)]
    assert [round(f.t_s * 25) for f in got] == [0, 1, 2]
    assert all(np.array_equal(f.left, ref.left) for f, ref in zip(got, frames))


def test_twelve_bit_images_in_sixteen_bit_files_play_scaled_alike_in_every_frame(tmp_path):
    """A camera's 12-bit samples stored as they are in 16-bit PNGs: every frame reads as its top
    8 bits, a dark frame among bright ones too (the depth is the sequence's, not the frame's)."""
    frames = _frames(5)
    d = _write(tmp_path / "s", frames)
    for cam, side in (("cam0", "left"), ("cam1", "right")):
        for k, path in enumerate(sorted((d / cam / "data").glob("*.png"), key=lambda q: int(q.stem))):
            img8 = getattr(frames[k], side) // (8 if k == 2 else 1)  # frame 2 is dark
            cv2.imwrite(str(path), img8.astype(np.uint16) << 4 | np.uint16(9))
    src = SequenceSource(d)
    assert src.image_bits == (12, 12)
    got = [src.read() for _ in range(5)]
    for k, (f, ref) in enumerate(zip(got, frames)):
        scale = 8 if k == 2 else 1
        assert np.array_equal(f.left, ref.left // scale) and np.array_equal(f.right, ref.right // scale)
    assert SequenceSource(_write(tmp_path / "eight", frames)).image_bits == (8, 8)


def test_a_deeper_image_among_eight_bit_ones_is_read_at_its_own_depth_and_said(tmp_path):
    """A full-range 16-bit PNG among a sequence's 8-bit ones (whose depth is decided from its
    first, middle and last pairs) was clipped at 255: 90 % of the frame white, its targets lost,
    nothing said. It now reads as its own top 8 bits, counted in the source's warning."""
    frames = _frames(7)
    d = _write(tmp_path / "s", frames)
    lefts = sorted((d / "cam0" / "data").glob("*.png"), key=lambda q: int(q.stem))
    for k in (1, 4):  # not among the pairs the depth is decided from (0, 3, 6)
        cv2.imwrite(str(lefts[k]), frames[k].left.astype(np.uint16) * 257)
    src = SequenceSource(d)
    assert src.image_bits == (8, 8)
    got = list(iter(src.read, None))
    assert len(got) == 7
    assert all(np.array_equal(f.left, ref.left) for f, ref in zip(got, frames))
    assert src.warning is not None
    assert f"2 image(s) deeper than their camera's 8 bits read at their own depth ({lefts[4]} is 16-bit)" in src.warning


def test_a_sequence_whose_cameras_store_different_sample_depths_is_warned_about(tmp_path):
    # 12-bit left beside full 16-bit right, scaled alike: the left reads black (at most 15 grey
    # levels), and every point is refused as black sky with nothing said.
    frames = _frames(3)
    d = _write(tmp_path / "s", frames)
    for cam, side, shift in (("cam0", "left", 4), ("cam1", "right", 8)):
        for k, path in enumerate(sorted((d / cam / "data").glob("*.png"), key=lambda q: int(q.stem))):
            cv2.imwrite(str(path), getattr(frames[k], side).astype(np.uint16) << shift)
    with pytest.warns(UserWarning, match="cam0's images look 12-bit and cam1's 16-bit"):
        src = SequenceSource(d)
        assert src.image_bits == (12, 16)
    f = src.read()
    assert np.array_equal(f.left, frames[0].left) and np.array_equal(f.right, frames[0].right)


@pytest.mark.parametrize("left_bits, right_bits", [(10, 12), (14, 12)])
def test_cameras_two_bits_apart_are_each_read_at_their_own_depth(tmp_path, left_bits, right_bits):
    # A 10-bit left camera beside a 12-bit right one: read alike, the left was 4x darker with
    # 2 bits lost, nothing said, and the run found no valid pose (an outside probe). The depth
    # is each camera's, decided over the pairs sampled from the sequence, and said.
    frames = _frames(4)
    d = _write(tmp_path / "s", frames)
    for cam, side, bits in (("cam0", "left", left_bits), ("cam1", "right", right_bits)):
        for k, path in enumerate(sorted((d / cam / "data").glob("*.png"), key=lambda q: int(q.stem))):
            cv2.imwrite(str(path), getattr(frames[k], side).astype(np.uint16) << (bits - 8))
    with pytest.warns(UserWarning, match=f"cam0's images look {left_bits}-bit and cam1's {right_bits}-bit"):
        src = SequenceSource(d)
        assert src.image_bits == (left_bits, right_bits)
    got = list(iter(src.read, None))
    assert len(got) == 4
    assert all(np.array_equal(f.left, ref.left) and np.array_equal(f.right, ref.right) for f, ref in zip(got, frames))


def test_data_csv_with_no_usable_row_says_what_a_row_must_be(tmp_path):
    d = _write(tmp_path / "s", _frames(3))
    rows = (d / "cam0" / "data.csv").read_text().splitlines()
    seconds = [rows[0]] + [f"{int(r.split(',')[0]) * 1e-9:.3f},{r.split(',')[1]}" for r in rows[1:]]
    (d / "cam0" / "data.csv").write_text("\n".join(seconds) + "\n")
    with pytest.raises(TrackmeterError, match=r"cam0.data\.csv: no usable row: expected 'timestamp_ns,filename'.*'0\.000,"):
        SequenceSource(d)


def test_a_header_without_its_hash_is_a_header_not_a_bad_row(tmp_path):
    d = _write(tmp_path / "s", _frames(3))
    for cam in ("cam0", "cam1"):
        rows = (d / cam / "data.csv").read_text().splitlines()
        (d / cam / "data.csv").write_text("\n".join(["timestamp,filename"] + rows[1:]) + "\n")
    index = index_sequence(d)
    assert len(index) == 3 and index.warnings == () and index.skipped == 0


def test_a_data_csv_without_rows_says_so(tmp_path):
    d = _write(tmp_path / "s", _frames(3))
    (d / "cam1" / "data.csv").write_text("#timestamp [ns],filename\n")
    with pytest.raises(TrackmeterError, match=r"cam1.data\.csv: lists no image"):
        index_sequence(d)


@pytest.mark.parametrize("unit_ns, what", [(1000, "are these microseconds (25 Hz then)?"),
                                           (1_000_000, "are these milliseconds (25 Hz then)?"),
                                           (40_000_000, "are these frame numbers?")])
def test_timestamps_in_another_unit_than_nanoseconds_are_warned(tmp_path, unit_ns, what):
    # microseconds (25 kHz read as ns) or frame numbers (1 GHz): the motion model would be
    # given intervals a thousand times too short and tracking fails without saying why.
    d = _write(tmp_path / "s", _frames(4))
    for cam in ("cam0", "cam1"):
        rows = (d / cam / "data.csv").read_text().splitlines()
        scaled = [rows[0]] + [f"{int(r.split(',')[0]) // unit_ns},{r.split(',')[1]}" for r in rows[1:]]
        (d / cam / "data.csv").write_text("\n".join(scaled) + "\n")
    index = index_sequence(d)
    assert len(index) == 4
    (warning,) = [w for w in index.warnings if "nanoseconds" in w]
    assert what in warning  # milliseconds were asked about as "microseconds or frame numbers" (an outside probe)
    assert index_sequence(_write(tmp_path / "ns", _frames(4))).warnings == ()


def test_an_unfinished_simulation_is_warned_about(tmp_path):
    # After a kill -9, `simulate`'s OUT.partial (66 of 250 frames) was tracked as a complete
    # sequence without a word (an outside CLI probe).
    index = index_sequence(_write(tmp_path / "sim.partial", _frames(3)))
    assert len(index) == 3
    assert [w for w in index.warnings if "unfinished simulation" in w and "may end early" in w]
    assert index_sequence(_write(tmp_path / "sim", _frames(3))).warnings == ()


def test_unreadable_image_skipped_at_read(tmp_path):
    d = _write(tmp_path / "s", _frames(3))
    (d / "cam1" / "data" / "40000000.png").write_bytes(b"not a png")
    src = SequenceSource(d)
    got = [f.t_s for f in iter(src.read, None)]
    assert got == [0.0, 0.08]
    assert src.skipped == 1 and "unreadable" in src.warning


def test_a_pair_of_another_size_mid_sequence_is_skipped_and_named(tmp_path):
    """The rig's calibration holds for one image size (checked against the sequence's frames when
    the source opens); a later pair of another size, or whose left and right images differ,
    is no frame of this rig. One such file in a long recording must not end the run (it did:
    the source failed there): it is skipped like an unreadable image, counted and named in
    the source's warning, and the frames after it play."""
    d = _write(tmp_path / "s", _frames(5))
    small = np.zeros((12, 16), np.uint8)
    for cam in ("cam0", "cam1"):
        cv2.imwrite(str(d / cam / "data" / "40000000.png"), small)
    cv2.imwrite(str(d / "cam1" / "data" / "120000000.png"), small)  # the right one only
    src = SequenceSource(d)
    assert src.frame_size == (32, 24)
    got = [f.t_s for f in iter(src.read, None)]
    assert got == [0.0, 0.08, 0.16]
    assert src.skipped == 2
    assert src.warning is not None and src.warning.startswith("2 pair(s) of another image size skipped (")
    assert "120000000.png 16x12 px" in src.warning  # the last one, named
    src.restart()  # a second pass counts nothing twice
    assert len([f for f in iter(src.read, None)]) == 3 and src.skipped == 2


def test_a_first_pair_whose_images_differ_in_size_is_skipped_not_taken_for_the_sequences_size(tmp_path):
    # A 640x480 left image in the first pair (its right one of the sequence's size) set the
    # sequence's frame size: track then refused the whole run, blaming the rig.
    d = _write(tmp_path / "s", _frames(4))
    cv2.imwrite(str(d / "cam0" / "data" / "0.png"), np.zeros((12, 16), np.uint8))
    src = SequenceSource(d)
    assert src.frame_size == (32, 24)
    assert [f.t_s for f in iter(src.read, None)] == [0.04, 0.08, 0.12]
    assert src.skipped == 1 and "0.png is 16x12 px" in src.warning


def test_a_first_pair_of_another_size_in_both_cameras_is_skipped_too(tmp_path):
    # Both images of the first pair 16x12 (a re-exported first frame): they set the sequence's
    # size, and track refused the run blaming the rig, whose size the other pairs have.
    d = _write(tmp_path / "s", _frames(5))
    for cam in ("cam0", "cam1"):
        cv2.imwrite(str(d / cam / "data" / "0.png"), np.zeros((12, 16), np.uint8))
    src = SequenceSource(d)
    assert src.frame_size == (32, 24)
    assert [f.t_s for f in iter(src.read, None)] == [0.04, 0.08, 0.12, 0.16]
    assert src.skipped == 1 and "the sequence's 32x24 px" in src.warning


@pytest.mark.parametrize("removed", ["folder", "cam1", "cam1's images"])
def test_a_sequence_folder_removed_while_it_plays_fails_the_source_rather_than_ending_it(tmp_path, removed):
    # Every pair after it was skipped as unreadable, and `track` ended "complete", exit 0, with
    # a warning of the pairs skipped (left from the last stop; the images alone, a re-check).
    import shutil

    d = _write(tmp_path / "s", _frames(5))
    src = SequenceSource(d)
    assert [src.read().t_s for _ in range(2)] == [0.0, 0.04]
    if removed == "cam1's images":
        for image in (d / "cam1" / "data").iterdir():
            image.unlink()
    else:
        shutil.rmtree(d if removed == "folder" else d / "cam1")
    with pytest.raises(TrackmeterError) as info:
        src.read()
    gone = {"folder": f"{d}: removed or moved", "cam1": f"{d / 'cam1'}: removed or moved",
            "cam1's images": f"{d / 'cam1' / 'data'}: emptied of its images"}[removed]
    assert str(info.value) == f"{gone} while the sequence played, after 2 pairs"


def test_a_looping_folder_with_no_playable_pair_ends_instead_of_spinning(tmp_path):
    d = _write(tmp_path / "s", _frames(3))
    for path in (d / "cam0" / "data").iterdir():
        path.write_bytes(b"not a png")
    src = SequenceSource(d, loop=True)
    assert src.read() is None
    assert src.skipped == 3 and "3 pair(s) with an unreadable image skipped" in src.warning


def test_writer_refuses_existing_sequence_and_bad_images(tmp_path):
    d = _write(tmp_path / "s", _frames(2))
    with pytest.raises(TrackmeterError, match="already holds a sequence"):
        SequenceWriter(d)
    w = SequenceWriter(tmp_path / "t")
    with pytest.raises(TrackmeterError, match="uint8"):
        w.write(StereoFrame(0, 0.0, np.zeros((4, 4), np.float32), np.zeros((4, 4), np.float32)))
    w.write(_frames(1)[0])
    with pytest.raises(TrackmeterError, match="does not come after"):
        w.write(_frames(1)[0])
    w.close()


def test_crash_mid_recording_leaves_complete_files(tmp_path):
    """Kill a writer process mid-stream: every listed image decodes, every row is whole."""
    out = tmp_path / "rec"
    code = f"""
import numpy as np, sys
from trackmeter.data.sequence import SequenceWriter
from trackmeter.sources.base import StereoFrame, GroundTruth
w = SequenceWriter({str(out)!r})
rng = np.random.default_rng(0)
i = 0
while True:
    img = rng.integers(0, 256, (240, 320), dtype=np.uint8)
    w.write(StereoFrame(i, i / 25, img, img, GroundTruth(np.eye(4), np.zeros(3), np.zeros(3))))
    if i == 5:
        print("ready", flush=True)
    i += 1
"""
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
    finally:
        proc.kill()
        proc.wait()
    index = index_sequence(out)
    assert len(index) >= 5
    assert any("not closed" in w for w in index.warnings)  # killed: told when read
    with pytest.warns(UserWarning, match="not closed"):
        src = SequenceSource(out)
    n = sum(1 for _ in iter(src.read, None))
    assert n == len(index) and src._skipped_on_read == 0
    assert index.truth is not None and np.all(index.truth.valid[:-1])


def test_a_folder_named_like_a_scheme_is_pointed_to(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "seq").mkdir()
    with pytest.raises(TrackmeterError, match=r"seq: needs a folder, as seq:DIR \(the folder 'seq' here: give ./seq\)"):
        open_source("seq")
    for kind in ("video", "camera"):
        (tmp_path / kind).mkdir()
        with pytest.raises(TrackmeterError, match=rf"the folder '{kind}' here: give ./{kind}"):
            open_source(kind)
    # "sim" is the simulator even with a folder of that name here (a recording called sim/):
    # the run goes on, but not silently on other data than the user meant.
    (tmp_path / "sim").mkdir()
    with pytest.warns(UserWarning, match=r"source 'sim' is the simulator; to play the folder 'sim' here, give ./sim"):
        open_source("sim", render_ahead=False).close()


def test_not_a_sequence_and_bad_specs(tmp_path):
    (tmp_path / "empty").mkdir()
    (tmp_path / "a_file.avi").write_bytes(b"not a folder")
    for spec, match in [
        (f"seq:{tmp_path / 'nothing'}", "no such sequence folder"),
        (f"seq:{tmp_path / 'empty'}", "not a sequence folder"),
        ("seq:", "needs a folder"),
        ("", "empty source"),
        ("bogus:1", "unknown source 'bogus:1': expected sim"),
        ("nosuchdir", "unknown source 'nosuchdir': no such folder"),
        (str(tmp_path / "a_file.avi"), "a file, not a sequence folder"),
        ("video:only_one.avi", "two files"),
        (f"video:{tmp_path / 'a.avi'},{tmp_path / 'b.avi'}", "no such video"),
        ("camera:x", "device numbers"),
        ("camera:1,2,3", "device numbers"),
        ("camera:99", "camera 99 cannot be opened"),
        ("camera:98,99", "cannot be opened"),
    ]:
        with pytest.raises(TrackmeterError, match=match):
            open_source(spec)


def test_pair_by_nearest_is_mutual_and_within_tolerance():
    a = [0.0, 0.04, 0.08, 0.12]
    b = [0.001, 0.05, 0.052, 0.2]
    assert pair_by_nearest(a, b, 0.013) == [(0, 0), (1, 1)]
    assert pair_by_nearest(a, [], 0.01) == []
    assert pair_by_nearest([0.5], [0.5], 0.0) == [(0, 0)]


# --------------------------------------------------------------------------- video


def test_video_source_reads_two_files(tmp_path):
    paths = [tmp_path / "left.avi", tmp_path / "right.avi"]
    rng = np.random.default_rng(3)
    frames = [rng.integers(0, 256, (48, 64), dtype=np.uint8) for _ in range(5)]
    for k, p in enumerate(paths):
        vw = cv2.VideoWriter(str(p), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (64, 48), isColor=True)
        if not vw.isOpened():
            pytest.skip("this OpenCV build cannot write MJPG")
        for img in frames:
            vw.write(cv2.cvtColor(np.roll(img, k, axis=1), cv2.COLOR_GRAY2BGR))
        vw.release()
    src = open_source(f"video:{paths[0]},{paths[1]}")
    assert src.rate_hz == pytest.approx(10.0)
    assert src.frame_size == (64, 48)  # known before the first read, which still gets frame 0
    got = list(iter(src.read, None))
    assert len(got) == 5
    assert [f.t_s for f in got] == pytest.approx([0.0, 0.1, 0.2, 0.3, 0.4])
    for f, img in zip(got, frames):
        assert f.left.shape == (48, 64) and f.left.dtype == np.uint8
        assert np.mean(np.abs(f.left.astype(float) - img)) < 12  # MJPG is lossy
    src.restart()
    first = src.read()
    assert first.index == 0 and first.cut and not src.read().cut
    src.close()
    looped = open_source(f"video:{paths[0]},{paths[1]}", loop=True)
    frames = [looped.read() for _ in range(8)]
    assert np.all(np.diff([f.t_s for f in frames]) > 0)
    assert [f.cut for f in frames] == [False] * 5 + [True, False, False]


def test_a_video_without_a_frame_rate_is_stamped_as_the_rest_assumes(tmp_path, monkeypatch):
    # Without a rate in its metadata a video's frames were a second apart, while its loop,
    # the engine and track took 0.04 s: speeds 25 times too small (an outside review).
    import math

    import trackmeter.sources.video as video
    from trackmeter.sources.base import NO_RATE_INTERVAL_S

    paths = [_video(tmp_path / "left.avi", 3), _video(tmp_path / "right.avi", 3)]
    real_capture = cv2.VideoCapture

    class NoRate:  # a wrapper, not a subclass: OpenCV's binding crashes collecting one
        def __init__(self, *args):  # type: ignore[no-untyped-def]
            self._capture = real_capture(*args)

        def get(self, prop):  # type: ignore[no-untyped-def]
            return math.nan if prop == cv2.CAP_PROP_FPS else self._capture.get(prop)

        def __getattr__(self, name):  # type: ignore[no-untyped-def]
            return getattr(self._capture, name)

    monkeypatch.setattr(video.cv2, "VideoCapture", NoRate)
    src = open_source(f"video:{paths[0]},{paths[1]}", loop=True)
    assert src.rate_hz is None
    times = [src.read().t_s for _ in range(5)]
    src.close()
    assert np.diff(times) == pytest.approx([NO_RATE_INTERVAL_S] * 4)


def test_videos_of_different_lengths_are_warned_at_open(tmp_path):
    paths = [tmp_path / "left.avi", tmp_path / "right.avi"]
    img = np.random.default_rng(4).integers(0, 256, (48, 64), dtype=np.uint8)
    for p, n in zip(paths, (5, 3)):
        vw = cv2.VideoWriter(str(p), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (64, 48), isColor=True)
        if not vw.isOpened():
            pytest.skip("this OpenCV build cannot write MJPG")
        for _ in range(n):
            vw.write(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
        vw.release()
    with pytest.warns(UserWarning, match=r"differ in length \(left.avi: 5 frames, right.avi: 3\)"):
        src = open_source(f"video:{paths[0]},{paths[1]}")
    assert len(list(iter(src.read, None))) == 3
    src.close()


def test_pacer_sleeps_to_media_time():
    now = [0.0]
    slept = []

    def sleep(d):
        slept.append(d)
        now[0] += d

    p = Pacer(clock=lambda: now[0], sleep=sleep)
    p.wait(10.0)
    p.wait(10.04)
    now[0] += 0.01  # consumer took 10 ms
    p.wait(10.08)
    assert slept == pytest.approx([0.04, 0.03])


# --------------------------------------------------------------------------- model files


def test_model_round_trip(tmp_path):
    m = Model.from_pairs([("c1", [0.5, 0.5, 0.5]), ("2", [-0.5, 0.5, 0.5]), ("tip", [0.0, 0.0, 1.2 + 1e-9])])
    path = save_model(tmp_path / "model.yaml", m)
    back = load_model(path)
    assert back.ids == ("c1", "2", "tip")
    assert np.array_equal(back.points_body, m.points_body)
    assert np.array_equal(back.point("tip"), m.points_body[2])


def test_model_ids_that_look_like_numbers_are_read_as_written(tmp_path):
    # YAML 1.1 reads 010 as octal 8 and 0x1f as 31: an id is a name, so it is its text, and
    # --target 010=U,V must find it.
    path = tmp_path / "model.yaml"
    path.write_text("points:\n- {id: 010, xyz: [0, 0, 0]}\n- {id: 0x1f, xyz: [0.1, 0, 0]}\n"
                    "- {id: 1.50, xyz: [0, 0.1, 0]}\n- {id: 7, xyz: [0, 0, 0.1]}\n")
    model = load_model(path)
    assert model.ids == ("010", "0x1f", "1.50", "7")
    assert np.allclose(model.point("010"), 0.0) and np.allclose(model.points_body[1], [0.1, 0, 0])


@pytest.mark.parametrize(
    "text, match",
    [
        ("points: [{id: a, xyz: [0, 0, 0]}, {id: b, xyz: [1, 0, 0]}]", "at least 3 points"),
        ("points: [{id: a, xyz: [0,0,0]}, {id: a, xyz: [1,0,0]}, {id: c, xyz: [0,1,0]}]", "'a' appears twice"),
        ("points: [{id: a, xyz: [0,0,0]}, {id: b, xyz: [1,zero,0]}, {id: c, xyz: [0,1,0]}]", r"points\[1\]\.xyz\[1\]"),
        ("points: [{id: a, xyz: [0,0,0]}, {id: b, xyz: [1,0]}, {id: c, xyz: [0,1,0]}]", r"points\[1\]\.xyz"),
        ("points: [{id: a, xyz: [0,0,0]}, {xyz: [1,0,0]}, {id: c, xyz: [0,1,0]}]", r"points\[1\]': missing key 'id'"),
        ("pts: []", "missing key 'points'"),
        ("points: [{id: '', xyz: [0,0,0]}, {id: b, xyz: [1,0,0]}, {id: c, xyz: [0,1,0]}]", r"points\[0\]\.id: empty"),
        ("points: [{id: a, xyz: [0,0,0]}, {id: b=c, xyz: [1,0,0]}, {id: c, xyz: [0,1,0]}]",
         r"points\[1\]\.id 'b=c'.*'='"),
        ("name: estec_mockup\nmaterials: []\nparts: []", "missing key 'points'.*simulator mock-up's geometry, not a model"),
        ("points: [{id: a, xyz: [0,0,0]}, {id: b, xyz: [1,0,.inf]}, {id: c, xyz: [0,1,0]}]", r"xyz\[2\]': expected a finite number"),
        ("points: [a, b, c]", r"points\[0\]"),
        ("points: [{id: a, xyz: [0,0,0]", "malformed YAML"),
        # A stereo rig given as the model said "malformed YAML at line 5" (an outside console probe).
        ("%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\nK1: !!opencv-matrix\n   rows: 3\n   cols: 3\n"
         "   dt: d\n   data: [ 800., 0., 320., 0., 800., 240., 0., 0., 1. ]\n",
         "an OpenCV FileStorage file \\(a stereo rig\\?\\), not a model file"),
        ("image_width: 640\nimage_height: 480\nK1: [[800, 0, 320], [0, 800, 240], [0, 0, 1]]\nT: [-0.2, 0, 0]\n",
         "a stereo rig file \\(its camera matrices K1, K2\\), not a model file"),
    ],
)
def test_bad_model_files_name_the_problem(tmp_path, text, match):
    path = tmp_path / "model.yaml"
    path.write_text(text)
    with pytest.raises(TrackmeterError, match=match):
        load_model(path)


def test_a_model_path_that_is_a_pipe_or_too_large_is_refused_without_reading_it(tmp_path):
    """The console loads a model on its tracking thread: a pipe without a writer blocked it for
    ever (the image froze, Pause did nothing) and /dev/zero filled the memory (12 GB in 5 s)."""
    import threading

    fifo = tmp_path / "model.yaml"
    os.mkfifo(fifo)
    outcome: list[BaseException] = []

    def load() -> None:
        try:
            load_model(fifo)
        except BaseException as exc:  # noqa: BLE001 (handed to the test's thread)
            outcome.append(exc)

    reader = threading.Thread(target=load, daemon=True)
    reader.start()
    reader.join(timeout=10.0)
    if reader.is_alive():  # the old code: unblock its open() so that the thread can end
        os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
    assert not reader.is_alive() and len(outcome) == 1
    assert isinstance(outcome[0], TrackmeterError)
    assert str(outcome[0]) == f"{fifo}: not a regular file (a device, a pipe or a socket): YAML is read from a file"
    with pytest.raises(TrackmeterError, match="not a regular file"):
        load_model("/dev/zero")
    huge = tmp_path / "huge.yaml"
    with open(huge, "wb") as f:  # sparse: no disk used
        f.truncate(17 * 2**20)
    with pytest.raises(TrackmeterError, match=r"huge\.yaml: 17 MiB, too large for a YAML file \(at most 16 MiB\)"):
        load_model(huge)


def test_model_file_keys_of_other_tools_are_ignored_with_a_warning(tmp_path):
    """DESIGN.md's format is ``points: [{id, xyz}, ...]``; a file from another tool may carry
    more (``units``, a point's ``note``): read, with one warning naming what was ignored."""
    path = tmp_path / "model.yaml"
    path.write_text("units: m\nname: mock-up\npoints:\n  - {id: a, xyz: [0, 0, 0], note: corner}\n"
                    "  - {id: b, xyz: [1, 0, 0], note: edge}\n  - {id: c, xyz: [0, 1, 0]}\n")
    with pytest.warns(UserWarning, match=r"ignoring key\(s\) that are not part of a model file: units, points\[\]\.note$"):
        model = load_model(path)
    assert model.ids == ("a", "b", "c")
    np.testing.assert_array_equal(model.points_body, [[0, 0, 0], [1, 0, 0], [0, 1, 0]])
    # The extra keys do not weaken the other checks.
    path.write_text("units: m\npoints: [{id: a, xyz: [0,0,0], note: x}, {id: a, xyz: [1,0,0]}, {id: c, xyz: [0,1,0]}]\n")
    with pytest.warns(UserWarning), pytest.raises(TrackmeterError, match="'a' appears twice"):
        load_model(path)


def test_a_model_written_in_millimetres_is_warned_about(tmp_path):
    # An outside probe's model of a 0.7 m box in mm: no pose ever, and nothing said (a rig's T in
    # mm is warned about). No satellite's points lie 100 m apart; a metre-sized one in mm does.
    path = tmp_path / "model.yaml"
    path.write_text("points:\n  - {id: a, xyz: [0, 0, 0]}\n  - {id: b, xyz: [700, 0, 0]}\n"
                    "  - {id: c, xyz: [0, 600, 0]}\n")
    with pytest.warns(UserWarning, match="metres.*millimetres"):
        load_model(path)
    path.write_text("points:\n  - {id: a, xyz: [0, 0, 0]}\n  - {id: b, xyz: [30, 0, 0]}\n"
                    "  - {id: c, xyz: [0, 2, 0]}\n")  # a 30 m solar array: metres
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_model(path)


def test_videos_of_different_frame_sizes_are_refused_when_opened(tmp_path):
    """Left and right frames of different sizes are no stereo pair: said when the source is
    opened for a command (its frame size is asked before anything is written), not as a
    failure of the first read."""
    from trackmeter.cli.common import open_source_with_rig

    paths = [tmp_path / "left.avi", tmp_path / "right.avi"]
    img = np.random.default_rng(5).integers(0, 256, (48, 64), dtype=np.uint8)
    for p, size in zip(paths, ((64, 48), (32, 24))):
        vw = cv2.VideoWriter(str(p), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, size, isColor=True)
        if not vw.isOpened():
            pytest.skip("this OpenCV build cannot write MJPG")
        for _ in range(3):
            vw.write(cv2.cvtColor(cv2.resize(img, size), cv2.COLOR_GRAY2BGR))
        vw.release()
    with pytest.raises(TrackmeterError, match=r"differ in frame size: left.avi is 64x48 px, right.avi is 32x24 px"):
        open_source_with_rig(f"video:{paths[0]},{paths[1]}", None)


def test_a_sequence_has_truth_when_its_folder_gives_some(tmp_path):
    assert SequenceSource(_write(tmp_path / "a", _frames(3))).has_truth
    assert not SequenceSource(_write(tmp_path / "b", _frames(3, truth=False))).has_truth


@pytest.mark.parametrize("t0_s", [0.0, 1403636579.7635555])
def test_a_groundtruth_csv_in_integer_nanoseconds_is_read_as_such(tmp_path, t0_s):
    # DESIGN.md: "integer nanoseconds only in EuRoC-style CSV files"; another renderer may take
    # its groundtruth.csv for one. Read in seconds, its times would pair with no frame (or only
    # with frame 0 at t = 0): the truth, and --select-model-points, silently gone.
    frames = [replace(f, t_s=t0_s + f.t_s) for f in _frames(5)]
    d = _write(tmp_path / "s", frames)
    (d / "groundtruth.tum").unlink()
    lines = (d / "groundtruth.csv").read_text().splitlines()
    rows = [line.split(",") for line in lines[1:]]
    ns = [str(int(round(float(r[0]) * 1e9))) for r in rows]
    (d / "groundtruth.csv").write_text("\n".join([lines[0]] + [",".join([t] + r[1:]) for t, r in zip(ns, rows)]) + "\n")
    with pytest.warns(UserWarning, match=rf"{d / 'groundtruth.csv'}: its times read as integer nanoseconds"):
        src = SequenceSource(d)
    for f in frames:
        got = src.read()
        assert got.truth is not None, f.index
        np.testing.assert_allclose(got.truth.T_cam_body, f.truth.T_cam_body, atol=1e-12)
        np.testing.assert_allclose(got.truth.omega_body_rad_s, f.truth.omega_body_rad_s, atol=1e-12)


def test_a_recording_refuses_a_folder_that_holds_anything(tmp_path):
    """A recording never overwrites or mixes with what a folder holds (an old groundtruth.csv
    and images without their data.csv were overwritten and mixed before)."""
    from trackmeter.data.sequence import check_record_directory

    (tmp_path / "old" / "cam0" / "data").mkdir(parents=True)
    (tmp_path / "old" / "groundtruth.csv").write_text("t,x\n")
    with pytest.raises(TrackmeterError, match=r"cannot record to .*old: it already holds files; record into a new or empty"):
        SequenceWriter(tmp_path / "old")
    assert (tmp_path / "old" / "groundtruth.csv").read_text() == "t,x\n"
    (tmp_path / "empty").mkdir()
    assert check_record_directory(tmp_path / "empty") == tmp_path / "empty"
    with pytest.raises(TrackmeterError, match="name is empty"):
        check_record_directory("")
    # A name longer than the file system takes (an outside console probe typed 300 letters:
    # OSError from deep inside, a traceback in the console's log and a ticked Record box).
    with pytest.raises(TrackmeterError, match="cannot record to .*too long"):
        check_record_directory(tmp_path / ("L" * 300))


def test_a_frame_the_disk_cannot_take_is_not_recorded_at_all(tmp_path, full_disk):
    """A disk that fills mid-frame: neither camera's data.csv lists the frame, nor the truth
    files, and its images are gone, so the folder plays back as the frames before."""
    frames = _frames(3)
    w = SequenceWriter(tmp_path / "rec")
    w.write(frames[0])
    disk = full_disk(0)
    for free in range(0, 600, 11):
        disk.free = free
        try:
            w.write(frames[1])
            break
        except TrackmeterError as exc:
            assert "No space left on device" in str(exc)
            assert sorted(p.name for p in (tmp_path / "rec").rglob("*.png")) == [f"{seconds_to_ns(frames[0].t_s)}.png"] * 2
            assert not list((tmp_path / "rec").rglob("*.tmp"))
            with pytest.warns(UserWarning, match="not closed"):  # still being written
                src = SequenceSource(tmp_path / "rec")
            assert len(src) == 1 and len(read_motion_csv(tmp_path / "rec" / "groundtruth.csv")) == 1
            src.close()
    else:
        pytest.fail("the frame never fitted")
    disk.free = 10**6
    w.write(frames[2])
    w.close()
    assert len(SequenceSource(tmp_path / "rec")) == 3


def test_a_timestamp_beyond_64_bits_or_a_stray_byte_is_a_bad_row_not_a_crash(tmp_path):
    d = _write(tmp_path / "s", _frames(4))
    for cam in ("cam0", "cam1"):
        text = (d / cam / "data.csv").read_text()
        text = text.replace("40000000,40000000.png", "9223372036854775808,40000000.png")  # 2^63
        (d / cam / "data.csv").write_bytes(text.encode() + b"\xff\xfe,junk\n")  # not UTF-8
    with pytest.warns(UserWarning, match=r"4 malformed or cut-short data.csv row\(s\) ignored"):
        src = SequenceSource(d)
    assert len(src) == 3


def test_a_video_ffmpeg_cannot_open_is_our_one_line_not_also_ffmpeg_s(tmp_path):
    """A truncated mp4 (its index, the moov atom, never written): FFmpeg's own "moov atom not
    found" used to be printed above the error line."""
    good = tmp_path / "good.mp4"
    vw = cv2.VideoWriter(str(good), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (64, 48), isColor=True)
    if not vw.isOpened():
        pytest.skip("this OpenCV build cannot write mp4v")
    for k in range(5):
        vw.write(np.full((48, 64, 3), 40 * k, np.uint8))
    vw.release()
    data = good.read_bytes()
    cut = tmp_path / "cut.mp4"
    cut.write_bytes(data[: data.find(b"moov") - 4] if b"moov" in data else data[: len(data) // 2])
    env = {k: v for k, v in os.environ.items() if k != "OPENCV_FFMPEG_LOGLEVEL"}
    proc = subprocess.run([sys.executable, "-m", "trackmeter.cli.main", "track", "--source", f"video:{cut},{good}",
                           "--auto", "3", "--out", str(tmp_path / "run")], capture_output=True, text=True, env=env, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [f"trackmeter track: error: {cut}: OpenCV cannot open this video file"], proc.stderr


def test_a_broken_optional_ground_truth_is_warned_and_left_out(tmp_path):
    """groundtruth.* is optional: one that cannot be read stops nothing that does not need it
    (as a folder's broken rig.yaml stops nothing given --rig); it is named, with its line."""
    d = _write(tmp_path / "s", _frames(4))
    (d / "groundtruth.csv").write_text("x,y\n")
    with pytest.warns(UserWarning, match=r"groundtruth\.csv:1: not a motion CSV.*; ground truth not used"):
        src = SequenceSource(d)
    f = src.read()
    assert f is not None and f.truth is None
    (d / "groundtruth.csv").unlink()
    tum = (d / "groundtruth.tum").read_text().splitlines()
    (d / "groundtruth.tum").write_text("\n".join(tum[:2] + ["0.2 1 2"] + tum[2:]) + "\n")
    with pytest.warns(UserWarning, match=r"groundtruth\.tum:\d+: .*; ground truth not used"):
        assert SequenceSource(d).read().truth is None


def test_a_home_folder_in_a_spec_is_expanded(tmp_path, monkeypatch):
    """The shell does not expand '~' after 'seq:' or 'video:'; the source does."""
    monkeypatch.setenv("HOME", str(tmp_path))
    _write(tmp_path / "s", _frames(3))
    assert len(open_source("seq:~/s")) == 3
    assert len(open_source("~/s")) == 3
    with pytest.raises(TrackmeterError, match=rf"{tmp_path}/a\.avi: no such video file"):
        open_source("video:~/a.avi,~/b.avi")


def _video(path: Path, n: int, fps: float = 10.0) -> Path:
    img = np.random.default_rng(4).integers(0, 256, (48, 64), dtype=np.uint8)
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (64, 48), isColor=True)
    if not vw.isOpened():
        pytest.skip("this OpenCV build cannot write MJPG")
    for _ in range(n):
        vw.write(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
    vw.release()
    return path


def test_a_video_pair_that_cannot_be_a_stereo_pair_is_told(tmp_path):
    left = _video(tmp_path / "left.avi", 3)
    with pytest.raises(TrackmeterError, match=r"video: LEFT and RIGHT are the same file"):
        open_source(f"video:{left},{left}")
    os.link(left, tmp_path / "linked.avi")  # one file under two names: it was read as both views
    with pytest.raises(TrackmeterError, match=r"video: LEFT and RIGHT are the same file"):
        open_source(f"video:{left},{tmp_path / 'linked.avi'}")
    (tmp_path / "folder").mkdir()
    with pytest.raises(TrackmeterError, match=r"folder: a folder, not a video file"):
        open_source(f"video:{left},{tmp_path / 'folder'}")
    slow = _video(tmp_path / "slow.avi", 3, fps=5.0)
    with pytest.warns(UserWarning, match=r"frame rates differ \(left\.avi: 10 Hz, slow\.avi: 5 Hz\)"):
        open_source(f"video:{left},{slow}").close()


def test_a_data_csv_whose_images_are_all_missing_names_the_path_it_looked_for(tmp_path):
    """A filename column written relative to the camera folder ('data/<ns>.png') is looked for
    one folder too deep: the message shows where, so the cause is plain."""
    d = _write(tmp_path / "s", _frames(3))
    for cam in ("cam0", "cam1"):
        csv = d / cam / "data.csv"
        lines = csv.read_text().splitlines()
        csv.write_text("\n".join([lines[0]] + [row.replace(",", ",data/") for row in lines[1:]]) + "\n")
    with pytest.raises(TrackmeterError, match=r"none of the 3 image\(s\) it lists exists "
                                              rf"\(the first looked for: {d}/cam0/data/data/\d+\.png\)"):
        SequenceSource(d)


def test_a_written_ground_truth_keeps_its_quaternion_sign_past_half_a_turn(tmp_path):
    """As trajectory.tum (test_rundir): each truth quaternion takes the sign nearer the one before,
    so groundtruth.csv/.tum have no flip where the tumble passes 180 deg; rotations unchanged."""
    frames = _frames(40)
    angles = np.radians(np.arange(40) * 10.0)
    R = Rotation.from_rotvec(angles[:, None] * np.array([0.6, 0.0, 0.8])).as_matrix()
    for f, R_i in zip(frames, R):
        f.truth.T_cam_body[:3, :3] = R_i
    d = _write(tmp_path / "seq", frames)
    q = read_motion_csv(d / "groundtruth.csv").quat_wxyz
    assert q[0, 0] > 0.0 and np.all(np.sum(q[1:] * q[:-1], axis=1) > 0.9)
    np.testing.assert_allclose(Rotation.from_quat(q, scalar_first=True).as_matrix(), R, atol=1e-9)
    tum = np.loadtxt(d / "groundtruth.tum")
    np.testing.assert_allclose(tum[:, [7, 4, 5, 6]], q, atol=1e-9)


def test_two_recordings_into_one_new_folder_at_once_do_not_mix(tmp_path, monkeypatch):
    """Both pass the empty-folder check before either writes: the second is refused by the
    folder's lock, and the first's recording stays whole."""
    import trackmeter.data.sequence as sequence

    frames = _frames(4)
    real_check = sequence.check_record_directory
    with SequenceWriter(tmp_path / "rec") as first:
        first.write(frames[0])
        checks = iter([lambda d: Path(d)])  # the second's first check ran before the first wrote
        monkeypatch.setattr(sequence, "check_record_directory", lambda d: next(checks, real_check)(d))
        with pytest.raises(TrackmeterError, match="another recording is writing"):
            SequenceWriter(tmp_path / "rec")
        monkeypatch.setattr(sequence, "check_record_directory", real_check)
        for f in frames[1:]:
            first.write(f)
    src, read = SequenceSource(tmp_path / "rec"), []
    while (f := src.read()) is not None:
        read.append(f)
    for a, b in zip(read, frames, strict=True):
        _assert_same(a, b)


def test_a_recording_never_closed_is_told_from_a_complete_one_when_read(tmp_path):
    """A recording killed mid-way holds whole frames up to the last and read as complete (an
    outside probe: console --record, kill -9). Its writer's mark stays; reading warns."""
    frames = _frames(3)
    writer = SequenceWriter(tmp_path / "killed")
    for f in frames:
        writer.write(f)  # never closed, as under kill -9
    with pytest.warns(UserWarning, match="not closed"):
        warning = SequenceSource(tmp_path / "killed").warning
    assert warning is not None and "not closed" in warning
    writer.close()
    assert SequenceSource(tmp_path / "killed").warning is None
    d = _write(tmp_path / "closed", frames)
    assert SequenceSource(d).warning is None and not any(p.name.startswith(".") for p in d.iterdir())


def test_a_writer_that_fails_after_taking_the_folder_leaves_nothing_and_no_lock(tmp_path):
    """A bad model (or a full disk) after the lock left cam0/, cam1/, the mark and a held lock:
    the console's next Record into that folder was refused for the life of the process."""
    for folder, existed in ((tmp_path / "new", False), (tmp_path / "empty", True)):
        if existed:
            folder.mkdir()
        with pytest.raises(Exception):
            SequenceWriter(folder, model_points=[("a", [1.0, 2.0])])  # a point of two coordinates
        assert (folder.exists() and not any(folder.iterdir())) if existed else not folder.exists()
        with SequenceWriter(folder) as again:  # not refused: nothing held, nothing left
            again.write(_frames(1)[0])


def _spoil_video_frame(path: Path, k: int) -> None:
    """Zero frame ``k``'s whole JPEG in an MJPG AVI (its bytes from its start-of-image marker
    to the next frame's chunk): FFmpeg then fails on that frame alone and decodes the rest."""
    data = bytearray(path.read_bytes())
    starts = [i for i in range(len(data) - 1) if data[i] == 0xFF and data[i + 1] == 0xD8]
    end = starts[k + 1] - 8 if k + 1 < len(starts) else len(data)
    data[starts[k]:end] = bytes(end - starts[k])
    path.write_bytes(bytes(data))


def test_a_video_frame_that_does_not_decode_is_skipped_and_said_not_the_end(tmp_path):
    """One bad frame ended the whole stream without a word (exit 0, "complete", the rest of
    the video never tracked); OpenCV itself decodes every frame after it."""
    left, right = _video(tmp_path / "left.avi", 20), _video(tmp_path / "right.avi", 20)
    _spoil_video_frame(left, 10)
    src = open_source(f"video:{left},{right}")
    frames = list(iter(src.read, None))
    src.close()
    assert len(frames) == 19
    times = [f.t_s for f in frames]
    assert times[9] == pytest.approx(0.9) and times[10] == pytest.approx(1.1)  # frame 10's time is skipped too
    assert [f.index for f in frames] == list(range(19))
    assert src.warning is not None and "1 frame pair skipped: left.avi's frame 10 did not decode" in src.warning


def test_a_video_cut_short_says_it_ended_before_its_frame_count(tmp_path):
    """A file cut in half (its header still counting every frame) ended the stream at the cut,
    status complete, no warning."""
    left, right = _video(tmp_path / "left.avi", 20), _video(tmp_path / "right.avi", 20)
    data = left.read_bytes()
    left.write_bytes(data[: len(data) // 2])
    src = open_source(f"video:{left},{right}")
    frames = list(iter(src.read, None))
    src.close()
    assert 5 <= len(frames) < 15
    assert src.warning is not None and f"the stream ended after {len(frames)} of the 20 frame pairs the files count" in src.warning


def test_a_recording_killed_before_its_first_frame_is_named_as_such(tmp_path):
    """A console recording killed after its rig.yaml but before data.csv read as 'not a
    sequence folder', with its unfinished mark sitting there unmentioned."""
    from trackmeter.data.sequence import UNFINISHED_MARK, find_sequence_root

    d = tmp_path / "rec"
    (d / "cam0" / "data").mkdir(parents=True)
    (d / "rig.yaml").write_text("%YAML:1.0\n")
    (d / UNFINISHED_MARK).write_text("")
    with pytest.raises(TrackmeterError, match=r"rec: a recording stopped before its first frame was written"):
        find_sequence_root(d)
    (d / UNFINISHED_MARK).unlink()
    with pytest.raises(TrackmeterError, match=r"rec: not a sequence folder"):
        find_sequence_root(d)


def test_a_bad_video_frame_is_counted_once_when_the_stream_restarts(tmp_path):
    """The console restarts a stream (its Restart button): a bad frame met again before the
    first pass ended was counted again."""
    left, right = _video(tmp_path / "left.avi", 12), _video(tmp_path / "right.avi", 12)
    _spoil_video_frame(left, 3)
    src = open_source(f"video:{left},{right}")
    for _ in range(5):
        src.read()
    src.restart()
    frames = list(iter(src.read, None))
    src.close()
    assert len(frames) == 11
    assert src.warning is not None and src.warning.startswith("1 frame pair skipped: left.avi's frame 3 did not decode")


def test_the_rate_of_nanosecond_timestamps_is_the_rate_they_say() -> None:
    # 40 000 000 ns apart gave 24.99999999999998 Hz (seconds' round-off): the console then
    # refused a filter cutoff of 11.875 Hz, "must be in (0, 11.875] Hz".
    from trackmeter.data.sequence import SequenceIndex

    # 15, 30 and 60 Hz read 14.9999999, 30.0000003 and 59.9999988 from whole nanoseconds (a
    # probe): the filter then warned "7.125 Hz is above the 7.125 Hz" it takes at 15 Hz.
    for rate in (25.0, 20.0, 15.0, 30.0, 60.0, 12.5, 30000 / 1001):
        ns = np.round(np.arange(300) * 1e9 / rate).astype(np.int64)
        ns = np.delete(ns, [100, 101, 200])  # dropped frames are no interval
        assert SequenceIndex(Path("."), ns / 1e9, (), ()).rate_hz == pytest.approx(rate, rel=2e-8)
        if rate == round(rate, 3):
            assert SequenceIndex(Path("."), ns / 1e9, (), ()).rate_hz == rate
        # EuRoC's absolute timestamps (1.4e18 ns): seconds keep them to 0.2 us
        absolute = SequenceIndex(Path("."), (ns + 1_403_636_579_763_555_584) / 1e9, (), ()).rate_hz
        assert absolute == pytest.approx(rate, rel=1e-7)


@pytest.mark.parametrize("damage, said", [
    ("right_size", "cam1/data/0.png 16x12 px"),
    ("left_unreadable", "cam0/data/0.png: "),
])
def test_a_sequence_with_no_playable_pair_is_refused_at_open(tmp_path, capsys, damage: str, said: str) -> None:
    """Every right image of another size (or every left one unreadable) passed the open: track
    read the whole folder, then said it delivered no frame and left an empty run folder that a
    re-run must --overwrite; the console listened and showed nothing (an outside probe)."""
    from trackmeter.cli.main import main

    d = _write(tmp_path / "s", _frames(4))
    for path in sorted((d / ("cam1" if damage == "right_size" else "cam0") / "data").iterdir()):
        if damage == "right_size":
            cv2.imwrite(str(path), np.zeros((12, 16), np.uint8))
        else:
            path.write_bytes(b"not a png")
    out = tmp_path / "run"
    code = main(["track", "--source", str(d), "--rig", "config/rigs/estec_12mm.yaml", "--auto", "4", "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and not out.exists(), err
    assert err[-1].startswith(f"trackmeter track: error: source {str(d)!r}: no stereo pair plays"), err
    assert said in err[-1], err


def test_ground_truth_whose_times_meet_no_frame_is_said_so(tmp_path) -> None:
    """A groundtruth.csv of 0-0.12 s beside frames timed from the epoch paired with none:
    track then said --select-model-points "needs a frame with ground truth" of a folder that
    has one (an outside probe). Its times and the frames' are named."""
    from trackmeter.data.motion_csv import read_motion_csv, write_groundtruth_csv

    d = _write(tmp_path / "s", _frames(4))
    truth = read_motion_csv(d / "groundtruth.csv")
    write_groundtruth_csv(d / "groundtruth.csv", replace(truth, t_s=truth.t_s + 1000.0))
    with pytest.warns(UserWarning, match=r"groundtruth\.csv: its times \(from 1000\.000 s to 1000\.120 s\) meet none "
                                         r"of the frames' \(from 0\.000 s to 0\.120 s\) within .*; ground truth not used"):
        src = SequenceSource(d)
    assert not src.has_truth and src.truth_problem


def test_a_gap_in_the_frame_times_is_said(tmp_path) -> None:
    """A second of frames cut out of both streams (data.csv rows and images) was tracked
    straight through without a word (an outside probe); the gap is named by where it is."""
    frames = _frames(12)
    d = _write(tmp_path / "s", [f for f in frames if not 4 <= f.index <= 8])
    with pytest.warns(UserWarning, match=r"1 gap\(s\) in the frame times longer than 3 frame intervals \(the "
                                         r"longest 0\.240 s, after t = 0\.120 s\)"):
        src = SequenceSource(d)
    assert len(src) == 7
    d2 = _write(tmp_path / "whole", frames)
    assert "gap" not in (SequenceSource(d2).warning or "")


@pytest.mark.parametrize("name", [b"bad\xe9dir", "cam\u00e9ra".encode()])
def test_a_video_named_outside_utf8_is_refused_or_read_not_a_crash(tmp_path, name):
    # OpenCV's VideoCapture crashed the process (a segmentation fault) on a name holding
    # Python's surrogate escapes: a byte that is not UTF-8, or any non-ASCII name under a C
    # locale without UTF-8 mode (an outside probe). The latter is read; the former refused.
    import os
    import shutil
    import subprocess
    import sys

    folder = os.fsdecode(bytes(tmp_path) + b"/" + name)
    os.mkdir(folder)
    for side in ("l", "r"):
        shutil.copy(_video(tmp_path / f"{side}.avi", 3), os.path.join(folder, f"{side}.avi"))
    code = ("from trackmeter.sources import open_source\nfrom trackmeter.errors import TrackmeterError\n"
            "import os, sys\nf = os.fsdecode(sys.argv[1].encode('utf-8', 'surrogateescape'))\n"
            "try:\n    print(len(list(iter(open_source(f'video:{f}/l.avi,{f}/r.avi').read, None))))\n"
            "except TrackmeterError as exc:\n    print('refused:', exc)\n")
    env = {**os.environ, "LC_ALL": "C", "PYTHONUTF8": "0", "PYTHONCOERCECLOCALE": "0"}
    arg = bytes(tmp_path).decode("ascii") + "/" + name.decode("utf-8", "surrogateescape")
    done = subprocess.run([sys.executable, "-c", code, arg], capture_output=True, env=env, timeout=120)
    assert done.returncode == 0, (done.returncode, done.stderr)
    out = done.stdout.decode("utf-8", "replace")
    if b"\xe9" in name:
        assert out.startswith("refused:") and "not UTF-8" in out, out
    else:
        assert out.strip() == "3", out


@pytest.mark.parametrize("damage", ["bytes", "one frame", "same names"])
def test_a_video_that_lost_frames_inside_warns_that_the_pairs_may_be_out_of_step(tmp_path, damage):
    """Bytes overwritten in the middle of an MJPG file: OpenCV skips the broken frames without
    a failed read, so every left frame after them pairs with an earlier right one (6 frames
    apart in an outside probe's run: ten times the error), and all that was said was that the
    stream ended early, "a file cut short?". The file that ran out while the other still had
    frames is named, with what that means for the pairs: also when it lost one frame (a broken
    chunk marker; one frame short was said of nothing), and by its path when both files have
    one name (that ended the run with "source failed: StopIteration", a re-check)."""
    rng = np.random.default_rng(0)
    paths = []
    for name in (("L/cam.avi", "R/cam.avi") if damage == "same names" else ("left.avi", "right.avi")):
        (tmp_path / name).parent.mkdir(exist_ok=True)
        vw = cv2.VideoWriter(str(tmp_path / name), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (64, 48), isColor=False)
        if not vw.isOpened():
            pytest.skip("this OpenCV build cannot write MJPG")
        for _ in range(30):
            vw.write(rng.integers(0, 256, (48, 64), dtype=np.uint8))
        vw.release()
        paths.append(tmp_path / name)
    data = bytearray(paths[0].read_bytes())
    if damage == "one frame":
        marker = [i for i in range(len(data) - 3) if data[i:i + 4] == b"00dc"][10]  # frame 10's chunk
        data[marker:marker + 4] = b"xxxx"
    else:
        middle = len(data) * 3 // 10
        data[middle:middle + 6000] = rng.integers(0, 256, 6000, dtype=np.uint8).tobytes()
    paths[0].write_bytes(bytes(data))
    src = open_source(f"video:{paths[0]},{paths[1]}")
    frames = list(iter(src.read, None))
    src.close()
    assert len(frames) == 29 if damage == "one frame" else len(frames) < 29
    shown = str(paths[0]) if damage == "same names" else "left.avi"
    assert src.warning is not None and f"{shown} ran out" in src.warning and "out of step" in src.warning, src.warning


@pytest.mark.parametrize("how", ["moved", "removed"])
def test_a_recording_folder_moved_or_removed_while_recording_is_followed_or_said(tmp_path, how):
    """Renamed mid-recording, the writer failed on a hidden temporary file's path ("cam0/data/
    .760000000.png.tmp: cannot write (No such file or directory)") and left the moved folder
    marked unfinished; removed, it said the same (an outside probe). A moved folder is followed
    (said once) and closed whole; a removed one is said to be."""
    import shutil
    import warnings

    from trackmeter.data.sequence import UNFINISHED_MARK

    frames = _frames(4)
    out, moved = tmp_path / "rec", tmp_path / "rec.moved"
    writer = SequenceWriter(out)
    writer.write(frames[0])
    writer.write(frames[1])
    if how == "moved":
        out.rename(moved)
        with warnings.catch_warnings(record=True) as said:
            warnings.simplefilter("always")
            writer.write(frames[2])
            writer.write(frames[3])
        writer.close()
        assert [str(w.message) for w in said] == [
            f"{out}: the recording folder was moved to {moved} while recording; the recording goes on there"]
        assert writer.directory == moved and not (moved / UNFINISHED_MARK).exists()
        assert len(open_source(f"seq:{moved}")) == 4
    else:
        shutil.rmtree(out)
        with pytest.raises(TrackmeterError) as info:
            writer.write(frames[2])
        writer.close()
        assert str(info.value) == (f"{out}: the recording folder was removed while recording; the 2 frames written "
                                   "there went with it")


def test_a_recording_whose_files_are_removed_while_its_folder_stays_is_said_so(tmp_path):
    # `mv` to another file system copies, then removes the files while the folder is still
    # there: the writer failed on a hidden temporary file's name (a re-check).
    import shutil

    frames = _frames(3)
    out = tmp_path / "rec"
    writer = SequenceWriter(out)
    writer.write(frames[0])
    writer.write(frames[1])
    for cam in ("cam0", "cam1"):
        shutil.rmtree(out / cam)
    with pytest.raises(TrackmeterError) as info:
        writer.write(frames[2])
    with contextlib.suppress(TrackmeterError):
        writer.close()
    assert str(info.value) == (f"{out}: the recording's files were removed while recording (deleted, or moved to "
                               "another file system); the 2 frames written there went with them")


@pytest.mark.parametrize("removed", ["cam0", "cam1"])
def test_a_recording_that_loses_one_camera_says_which_and_what_is_left(tmp_path, removed):
    # Only cam1 removed was told that every frame "went with them", though cam0 kept its
    # images (a probe).
    import shutil

    frames = _frames(3)
    out = tmp_path / "rec"
    writer = SequenceWriter(out)
    writer.write(frames[0])
    writer.write(frames[1])
    shutil.rmtree(out / removed)
    with pytest.raises(TrackmeterError) as info:
        writer.write(frames[2])
    with contextlib.suppress(TrackmeterError):
        writer.close()
    kept = "cam1" if removed == "cam0" else "cam0"
    assert str(info.value) == (f"{out}: {removed}'s files were removed while recording (deleted, or moved to another "
                               f"file system); the 2 frames written there lost their {removed} images, {kept} keeps "
                               "its own")


@pytest.mark.parametrize("cam", ["cam0", "cam1"])
def test_a_camera_index_deleted_while_recording_is_written_again_and_said(tmp_path, cam):
    # data.csv deleted mid-recording: the writer went on appending to the unlinked file, and the
    # folder played as "no frames" after it closed, every image kept but none listed (a probe).
    frames = _frames(5)
    out = tmp_path / "rec"
    writer = SequenceWriter(out)
    for frame in frames[:3]:
        writer.write(frame)
    (out / cam / "data.csv").unlink()
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        for frame in frames[3:]:
            writer.write(frame)
    writer.close()
    assert [str(w.message) for w in said] == [
        f"{out / cam / 'data.csv'}: removed while recording; written again from the recorder's own copy "
        "(the 3 frames before kept)"]
    index = index_sequence(out)
    assert len(index) == 5 and not index.warnings
    np.testing.assert_allclose(index.t_s, [f.t_s for f in frames], atol=1e-9)


@pytest.mark.parametrize("name", ["cam0/data.csv", "cam1/data.csv", "groundtruth.csv", "groundtruth.tum"])
def test_a_file_deleted_after_the_last_frame_is_written_again_at_the_close(tmp_path, name):
    # Record, pause, delete cam0/data.csv, stop: "recorded 38 frames", and the folder was no
    # sequence; the ground truth deleted while recording went without a word (a re-check).
    frames = _frames(4)
    out = tmp_path / "rec"
    writer = SequenceWriter(out)
    for frame in frames:
        writer.write(frame)
    (out / name).unlink()
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        writer.close()
    assert [str(w.message) for w in said] == [
        f"{out / name}: removed while recording; written again from the recorder's own copy (the 4 frames before kept)"]
    index = index_sequence(out)
    assert len(index) == 4 and not index.warnings and index.truth is not None and bool(np.all(index.truth.valid))


def test_at_the_close_every_deleted_file_that_can_be_is_written_again_and_the_rest_said(tmp_path):
    # One file that could not be written again (a folder where cam0/data.csv was) stopped the
    # close's restoring there: cam1's index and the ground truth were lost too (a re-check).
    from trackmeter.data.sequence import UNFINISHED_MARK

    out = tmp_path / "rec"
    writer = SequenceWriter(out)
    for frame in _frames(3):
        writer.write(frame)
    for name in ("cam0/data.csv", "cam1/data.csv", "groundtruth.csv", "groundtruth.tum"):
        (out / name).unlink()
    (out / "cam0" / "data.csv").mkdir()
    with warnings.catch_warnings(record=True) as said, pytest.raises(TrackmeterError, match="cam0/data.csv: removed, and "
                                                                                             "cannot be written again"):
        warnings.simplefilter("always")
        writer.close()
    assert sorted(Path(str(w.message).split(":")[0]).name for w in said) == ["data.csv", "groundtruth.csv",
                                                                             "groundtruth.tum"]
    assert (out / "cam1" / "data.csv").read_text().count("\n") == 4 and (out / UNFINISHED_MARK).exists()


@pytest.mark.parametrize("how", ["cam1 removed", "moved"])
def test_a_recording_folder_changed_after_the_last_frame_is_said_at_the_close(tmp_path, how):
    # After the last frame the close said nothing: a camera's folder removed left a folder that
    # was no sequence, marked whole; a folder moved kept its unfinished mark (a re-check).
    import shutil

    from trackmeter.data.sequence import UNFINISHED_MARK

    out, moved = tmp_path / "rec", tmp_path / "rec.moved"
    writer = SequenceWriter(out)
    for frame in _frames(4):
        writer.write(frame)
    if how == "moved":
        out.rename(moved)
        with pytest.warns(UserWarning, match="the recording folder was moved to"):
            writer.close()
        assert not (moved / UNFINISHED_MARK).exists() and len(index_sequence(moved)) == 4
    else:
        shutil.rmtree(out / "cam1")
        with pytest.raises(TrackmeterError, match="cam1's files were removed while recording .* the 4 frames written "
                                                  "there lost their cam1 images, cam0 keeps its own"):
            writer.close()
        assert (out / UNFINISHED_MARK).exists()


def test_the_rig_and_model_deleted_while_recording_are_written_again(tmp_path, estec_rig):
    # rig.yaml and model.yaml deleted while simulate rendered: "wrote 150 frames", then track
    # said the folder carries no stereo rig (a re-check).
    model = Model(("a", "b", "c"), np.array([[0.0, 0, 0], [0.1, 0, 0], [0, 0.1, 0]]))
    out = tmp_path / "rec"
    writer = SequenceWriter(out, rig=estec_rig, model_points=model)
    frames = _frames(3)
    writer.write(frames[0])
    (out / "rig.yaml").unlink()
    with pytest.warns(UserWarning, match="rig.yaml: removed while recording; written again"):
        writer.write(frames[1])
    writer.write(frames[2])
    (out / "model.yaml").unlink()  # after the last frame
    with pytest.warns(UserWarning, match="model.yaml: removed while recording; written again"):
        writer.close()
    index = index_sequence(out)
    assert index.rig is not None and index.model is not None and index.model.ids == ("a", "b", "c")


def test_a_camera_folder_replaced_by_a_file_while_recording_is_refused_in_words(tmp_path):
    # cam1/data replaced by a file: the frame's clean-up raised NotADirectoryError past the
    # recorder, where the write's own error was the one to tell (a probe).
    import shutil

    frames = _frames(3)
    out = tmp_path / "rec"
    writer = SequenceWriter(out)
    writer.write(frames[0])
    writer.write(frames[1])
    shutil.rmtree(out / "cam1" / "data")
    (out / "cam1" / "data").write_text("not a folder\n")
    with pytest.raises(TrackmeterError, match="Not a directory"):
        writer.write(frames[2])
    with contextlib.suppress(TrackmeterError):
        writer.close()
    assert (out / "cam0" / "data.csv").read_text().count("\n") == 3  # the header, two frames: whole


def test_a_recording_removed_before_its_first_frame_says_nothing_was_lost(tmp_path):
    import shutil

    out = tmp_path / "rec"
    writer = SequenceWriter(out)
    shutil.rmtree(out)
    with pytest.raises(TrackmeterError) as info:
        writer.write(_frames(1)[0])
    writer.close()
    assert str(info.value) == f"{out}: the recording folder was removed while recording, before its first frame"


def test_a_recording_whose_unfinished_mark_cannot_be_removed_says_so_in_words(tmp_path):
    # An immutable folder (chattr +i) at the close: "[Errno 1] Operation not permitted:
    # '.../.trackmeter-unfinished'" (an outside probe).
    from trackmeter.data.sequence import UNFINISHED_MARK

    writer = SequenceWriter(tmp_path / "rec")
    writer.write(_frames(1)[0])
    mark = tmp_path / "rec" / UNFINISHED_MARK
    mark.unlink()
    mark.mkdir()  # what cannot be unlinked, as a file in an immutable folder cannot
    (mark / "x").write_text("")
    with pytest.raises(TrackmeterError) as info:
        writer.close()
    assert str(info.value).startswith(f"{mark}: cannot remove (")
    assert str(info.value).endswith("the 1 frame recorded is whole, but the folder stays marked unfinished")


def test_videos_of_one_name_are_told_apart_in_every_message(tmp_path):
    # "the videos differ in length (cam.avi: 30 frames, cam.avi: 25)" (a second re-check).
    (tmp_path / "L").mkdir()
    (tmp_path / "R").mkdir()
    left, right = _video(tmp_path / "L" / "cam.avi", 6), _video(tmp_path / "R" / "cam.avi", 4)
    with pytest.warns(UserWarning, match="differ in length"):
        src = open_source(f"video:{left},{right}")
    src.close()
    assert src.warning is not None and f"({left}: 6 frames, {right}: 4)" in src.warning, src.warning


def test_a_writer_closed_without_a_frame_keeps_nothing(tmp_path: Path, estec_rig) -> None:  # type: ignore[no-untyped-def]
    """A folder of csv headers is no sequence (the reader refuses it: "lists no image"): a
    writer closed before its first frame removes what it made, and the folder where it made it."""
    from trackmeter.data.sequence import SequenceWriter

    with SequenceWriter(tmp_path / "new", rig=estec_rig) as writer:
        assert (tmp_path / "new" / "cam0" / "data.csv").is_file()
    assert writer.discarded and not (tmp_path / "new").exists()
    (tmp_path / "given").mkdir()
    with SequenceWriter(tmp_path / "given", rig=estec_rig) as writer:
        pass
    assert writer.discarded and list((tmp_path / "given").iterdir()) == []


# --------------------------------------------------------------------------- an outside code review (2026-12-07)


def test_a_one_pair_sequence_looped_keeps_its_time_increasing(tmp_path):
    """One pair has no rate: each pass was shifted by 0 s, so every frame had the same time and
    a recording refused the second ("does not come after the previous one")."""
    d = _write(tmp_path / "one", _frames(1))
    src = SequenceSource(d, loop=True)
    frames = [src.read() for _ in range(4)]
    assert np.all(np.diff([f.t_s for f in frames]) > 0) and np.all(np.diff([f.stamp_ns for f in frames]) > 0)
    assert [f.cut for f in frames] == [False, True, True, True]
    _write(tmp_path / "copy", frames)  # a recording of it takes every frame
    assert len(index_sequence(tmp_path / "copy")) == 4


def test_a_data_csv_appended_to_twice_still_pairs_within_a_quarter_interval(tmp_path):
    """Every row twice made half the gaps 0: the default tolerance, a quarter of the median gap,
    was 0, and a right camera 0.1 ms off paired with nothing (the folder was refused)."""
    d = _write(tmp_path / "s", _frames(6))
    _retime_right(d, lambda t: t + 100_000)
    csv = d / "cam0" / "data.csv"
    lines = csv.read_text().splitlines()
    csv.write_text("\n".join(lines + lines[1:]) + "\n")
    index = index_sequence(d)
    assert len(index) == 6 and index.tolerance_s == pytest.approx(0.25 / 25.0)
    assert any("repeating an earlier timestamp" in w for w in index.warnings), index.warnings


@pytest.mark.skipif(sys.platform == "win32", reason="file names are bytes on POSIX only")
def test_images_named_in_latin_1_are_found(tmp_path):
    """data.csv was read with errors="replace": caf\\xe9.png became caf\\ufffd.png, "missing"."""
    d = _write(tmp_path / "s", _frames(2))
    for cam in ("cam0", "cam1"):
        rows = (d / cam / "data.csv").read_bytes().splitlines()
        out = [rows[0]]
        for k, row in enumerate(rows[1:]):
            t, name = row.split(b",")
            new = b"caf\xe9_%d.png" % k
            os.replace(os.fsencode(d / cam / "data") + b"/" + name, os.fsencode(d / cam / "data") + b"/" + new)
            out.append(t + b"," + new)
        (d / cam / "data.csv").write_bytes(b"\n".join(out) + b"\n")
    src = SequenceSource(d)
    assert len(src.index) == 2 and src.read() is not None and src.read() is not None


def test_a_truth_file_that_cannot_be_made_leaves_no_half_frame_after_it(tmp_path):
    """groundtruth.csv made and groundtruth.tum not: the next frame with truth failed on an
    assertion its rollback did not catch, and its images and data.csv rows stayed."""
    frames = _frames(3)
    out = tmp_path / "rec"
    writer = SequenceWriter(out)
    writer.write(replace(frames[0], truth=None))
    (out / "groundtruth.tum").mkdir()  # stands in for a file the system will not make
    for f in frames[1:]:
        with pytest.raises(TrackmeterError, match="groundtruth.tum: cannot create"):
            writer.write(f)
    assert writer.frames_written == 1
    assert len((out / "cam0" / "data.csv").read_text().splitlines()) == 2
    assert sorted(p.name for p in (out / "cam0" / "data").iterdir()) == [f"{seconds_to_ns(frames[0].t_s)}.png"]
    assert not (out / "groundtruth.csv").exists()
    writer.close()


def test_a_cut_on_a_pair_that_cannot_be_read_marks_the_next_frame(tmp_path):
    """cuts.csv's jump at a pair skipped as unreadable was lost: the frame after it, which
    follows the jump, was not marked, and the tracker took the jump for motion."""
    frames = _frames(5)
    d = _write(tmp_path / "s", frames)
    (d / "cuts.csv").write_text(f"#timestamp [ns]\n{seconds_to_ns(frames[2].t_s)}\n")
    assert index_sequence(d).cuts == (2,)
    (d / "cam0" / "data" / f"{seconds_to_ns(frames[2].t_s)}.png").write_bytes(b"not a png")
    src = SequenceSource(d)
    played = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        while (f := src.read()) is not None:
            played.append(f)
    assert [round(f.t_s * 25) for f in played] == [0, 1, 3, 4]
    assert [f.cut for f in played] == [False, False, True, False]


@pytest.mark.parametrize("n_frames", [1, 4])
def test_a_whole_last_row_without_its_newline_is_played(tmp_path, n_frames):
    """Another tool's data.csv may end its last row without a newline (RFC 4180 allows it):
    that frame was dropped as cut short, and a one-frame sequence refused as listing no image.
    A last row cut short by a crash (its file name unfinished) is still counted, not played."""
    d = _write(tmp_path / "s", _frames(n_frames))
    for cam in ("cam0", "cam1"):
        csv = d / cam / "data.csv"
        csv.write_text(csv.read_text().rstrip("\n"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        src = SequenceSource(d)
    assert len(src) == n_frames and src.skipped == 0
    if n_frames == 1:  # its one row cut short: said so, not "lists no image" alone
        csv = d / "cam0" / "data.csv"
        csv.write_text(csv.read_text()[:-2])
        with pytest.raises(TrackmeterError, match=r"cam0/data.csv: lists no image but 1 row malformed or cut short$"):
            SequenceSource(d)
        return
    cut = d / "cam1" / "data.csv"
    cut.write_text(cut.read_text()[:-2])  # "...png" -> "...p": a name cut short
    with pytest.warns(UserWarning, match=r"1 malformed or cut-short data.csv row\(s\) ignored \(cam0: 0, cam1: 1\)"):
        src = SequenceSource(d)
    assert len(src) == n_frames - 1


def test_a_video_whose_first_frame_does_not_decode_is_still_checked_against_the_rig(tmp_path, estec_rig):
    """The frame size was read from the left file's first frame only: spoilt, the size was
    unknown, the rig's size went unchecked, and every frame then failed in the tracker (a
    traceback a frame, exit 0, run "complete"). The first frame that decodes gives it."""
    from trackmeter.cli.common import open_source_with_rig
    from trackmeter.data.rigfile import save_rig

    left, right = _video(tmp_path / "left.avi", 6), _video(tmp_path / "right.avi", 6)
    _spoil_video_frame(left, 0)
    src = open_source(f"video:{left},{right}")
    try:
        assert src.frame_size == (64, 48)
    finally:
        src.close()
    # A left file none of whose frames decodes: the right's size (a code review).
    dead = _video(tmp_path / "dead.avi", 6)
    for k in (5, 4, 3, 2, 1, 0):  # from the last: a spoilt frame's start is gone from the next count
        _spoil_video_frame(dead, k)
    src = open_source(f"video:{dead},{right}")
    try:
        assert src.frame_size == (64, 48)
    finally:
        src.close()
    K = np.array([[30.0, 0.0, 15.5], [0.0, 30.0, 11.5], [0.0, 0.0, 1.0]])
    rig = replace(estec_rig, left=replace(estec_rig.left, width=32, height=24, K=K),
                  right=replace(estec_rig.right, width=32, height=24, K=K))
    path = save_rig(rig, tmp_path / "rig.yaml")
    with pytest.raises(TrackmeterError, match=r"frame 64x48 does not match the rig's image size 32x24"):
        open_source_with_rig(f"video:{left},{right}", str(path))


def test_a_video_file_name_holding_a_comma_is_read_where_one_split_names_two_files(tmp_path):
    """video:LEFT,RIGHT split at every comma: a file named "left,1.avi" could not be given, and
    the message did not say why."""
    left, right = _video(tmp_path / "left,1.avi", 3), _video(tmp_path / "right,1.avi", 3)
    src = open_source(f"video:{left},{right}")
    try:
        assert src.paths == (left, right) and len(list(iter(src.read, None))) == 3
    finally:
        src.close()
    # A space beside the comma, as commas in file names mostly have (a code review): kept.
    spaced = [_video(tmp_path / "Take 1, left.avi", 3), _video(tmp_path / "Take 1, right.avi", 3)]
    src = open_source(f"video:{spaced[0]}, {spaced[1]}")
    try:
        assert src.paths == tuple(spaced)
    finally:
        src.close()
    # One side found: the other is named as missing, not the split rule.
    with pytest.raises(TrackmeterError, match=rf"^{tmp_path / 'gone,2.avi'}: no such video file$"):
        open_source(f"video:{left},{tmp_path / 'gone,2.avi'}")
    with pytest.raises(TrackmeterError, match=r"video: needs two files, as video:LEFT,RIGHT, got .*; a file name "
                                              r"holding a comma is read where exactly one of the splits"):
        open_source(f"video:{tmp_path / 'a,b.avi'},{tmp_path / 'c,d.avi'}")


def test_a_rig_the_simulator_does_not_render_through_is_warned_about(recwarn):
    """``--rig`` with the ``sim`` source is the rig the simulator *reports* (a miscalibration on
    purpose), its images rendered through the scenario's own: `analyze --source
    sim:static_ranges --rig estec_8mm` measured the 12 mm rig's images as the 8 mm one's (depth
    errors of a metre) without a word (an outside probe). It is said; the scenario's own rig
    named again is not."""
    from trackmeter.cli.common import open_source_with_rig
    from trackmeter.paths import RIGS_DIR

    src = open_source_with_rig("sim", str(RIGS_DIR / "estec_8mm.yaml"))
    try:
        assert src.rig.left.K[0, 0] == 768.0
        # The source's standing warning too: the console's status box shows it (a console probe).
        assert src.warning.startswith("measured as --rig ") and "focal length 768 px where the images' is 1152 px" \
            in src.warning, src.warning
    finally:
        src.close()
    said = [str(w.message) for w in recwarn]
    assert any("renders through its scenario's rig" in m and "estec_12mm.yaml" in m and "focal length 768 px "
               "where the images' is 1152 px" in m and "rig: in a scenario file" in m for m in said), said
    recwarn.clear()
    src = open_source_with_rig("sim", str(RIGS_DIR / "estec_12mm.yaml"))
    src.close()
    assert not [w for w in recwarn if "renders through" in str(w.message)]
