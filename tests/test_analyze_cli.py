"""``trackmeter analyze`` end to end on a small static-ranges simulation (real matcher, real renderer)."""

from __future__ import annotations

import json

import pytest

from trackmeter.cli.main import main

pytest.importorskip("trackmeter.sources.sim.simulator")

SCENARIO = """
name: static_small
rig: estec_12mm.yaml
mockup: estec_mockup.yaml
attitude0_wxyz: [0.541675, 0.664463, 0.454519, -0.241845]
position0_m: [0.0, 0.0, 1.0]
static_ranges_m: [2.5, 3.5, 5.0]
frames_per_range: 8
sun_dir_cam: [-0.45, -0.6, -0.66]
rate_hz: 25.0
seed: 5
"""


@pytest.mark.slow
def test_analyze_static_ranges_recovers_the_parabola(tmp_path, capsys):
    scenario = tmp_path / "static_small.yaml"
    scenario.write_text(SCENARIO)
    out = tmp_path / "out"
    code = main(["analyze", "--source", f"sim:{scenario}", "--json", "--out", str(out)])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    s = json.loads(captured.out)
    ranges = s["ranges"]
    assert [r["true_range_m"] for r in ranges] == [2.5, 3.5, 5.0]
    sz = [r["sigma_m"]["z"] for r in ranges]
    assert sz == sorted(sz)  # grows with range
    # The parabola: a one-parameter fit explains the depth sigma over the ranges ...
    assert s["fit"]["z"]["r2"] > 0.9
    # ... and eq. 2 at each range alone gives the same sub-pixel accuracy within a factor 2.5.
    for r in ranges:
        assert 0.4 < r["sigma_disparity_px"] / s["sigma_disparity_px"] < 2.5
    # Sub-pixel, and consistent with the scenario's sensor noise: point by point, the disparity
    # sigma measured over the still frames (eq. 2) is what the Cramer-Rao limit of the noise
    # measured in the same frames allows that patch (median ratio within 40 % of 1 overall; per
    # range, over 5-12 points, from 0.3: the bound's central differences overstate it for fine
    # texture, and the slanted sub-pixel fit does not scatter with where the texture's energy
    # falls in each frame: measured 0.38, 0.86 and 0.80 at 2.5, 3.5 and 5 m, 0.81 overall;
    # 0.60, 0.95, 0.90 and 0.89 with the shift fit alone).
    assert 0.005 < s["sigma_disparity_px"] < 0.2
    assert 0.6 < s["measured_over_noise_limit_median"] < 1.4
    for r in ranges:
        assert 0.3 < r["measured_over_noise_limit_median"] < 1.4
    # The depth residuals, normalised per range, are unit Gaussian by construction of sigma.
    assert s["density_normalised"]["sigma"] == pytest.approx(1.0, abs=0.1)
    for name in ("analysis.json", "ranges.csv", "sigma_vs_range.png", "error_density.png", "report.md"):
        assert (out / name).stat().st_size > 100
    report = (out / "report.md").read_text()
    assert "0.07 px" in report
    # Each row names the range as the skipped ones are named (the target origin's true range),
    # beside the measured depth of its points (the table showed only the latter).
    rows = report[report.index("origin [m]"):].splitlines()[1:4]
    assert [float(row.split()[0]) for row in rows] == [2.5, 3.5, 5.0]
    # ranges.csv as the table: counts as whole numbers (they read 6.0, 62.0), the origin's true
    # range too (an outside probe), unknowns empty as in the run files.
    import csv

    table = list(csv.DictReader((out / "ranges.csv").read_text().splitlines()))
    assert [float(r["true_range_m"]) for r in table] == [2.5, 3.5, 5.0]
    assert [int(r["n_points"]) for r in table] == [r["n_points"] for r in ranges]
    assert [float(r["sigma_z_m"]) for r in table] == sz
    assert [float(row.split()[1]) for row in rows] == pytest.approx([r["range_m"] for r in ranges], abs=1e-3)


def test_analyze_bad_source_is_one_line(tmp_path, capsys):
    code = main(["analyze", "--source", f"seq:{tmp_path / 'missing'}"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "Traceback" not in err


@pytest.mark.parametrize("points, expected", [("2", "[3, 1000], got 2"), ("5000", "[3, 1000], got 5000")])
def test_points_is_held_to_the_range_of_its_config_key(tmp_path, capsys, points, expected):
    # --points 5000 was taken although analyze.points_per_range goes to 1000 (an outside review).
    code = main(["analyze", "--source", str(tmp_path / "nowhere"), "--points", points])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and err == [f"trackmeter analyze: error: --points: expected a value in {expected}"], err


def test_split_ranges_groups_frames_by_true_pose():
    import numpy as np

    from trackmeter.pipeline.analysis import split_ranges
    from trackmeter.sources.base import GroundTruth, StereoFrame

    def frame(i, z):
        T = np.eye(4)
        T[2, 3] = z
        truth = None if z is None else GroundTruth(T, np.zeros(3), np.zeros(3))
        img = np.zeros((4, 4), np.uint8)
        return StereoFrame(i, 0.1 * i, img, img, truth)

    groups = list(split_ranges([frame(0, 2.0), frame(1, 2.0), frame(2, 3.5), frame(3, 3.5), frame(4, 3.5), frame(5, 2.0)]))
    assert [[f.index for f in g] for g in groups] == [[0, 1], [2, 3, 4], [5]]
    assert [len(g) for g in split_ranges([frame(i, None) for i in range(4)])] == [4]  # no truth, one view: one range
    # Frames without truth among frames with it belong to no range: skipped, their times kept
    # (they refused the whole analysis: 'ground truth present on some frames only').
    skipped: list[float] = []
    groups = list(split_ranges([frame(0, None), frame(1, 2.0), frame(2, None), frame(3, 2.0), frame(4, 3.5),
                                frame(5, None)], skipped=skipped))
    assert [[f.index for f in g] for g in groups] == [[1, 3], [4]]
    assert skipped == pytest.approx([0.0, 0.2, 0.5])
    skipped.clear()
    assert [len(g) for g in split_ranges([frame(i, None) for i in range(4)], skipped=skipped)] == [4] and not skipped


def test_a_measured_truth_that_jitters_about_a_still_target_is_one_range():
    # Ranges were split wherever any entry of the true pose changed by 1e-6: a measured ground
    # truth (motion capture: hundredths of a millimetre) made every frame its own range and
    # analyze refused the source (an outside probe). A range now holds the frames within 1 mm
    # and 0.1 deg of its first; a slow drift still splits, measured from that first pose.
    import numpy as np
    from scipy.spatial.transform import Rotation

    from trackmeter.pipeline.analysis import split_ranges
    from trackmeter.sources.base import GroundTruth, StereoFrame

    rng = np.random.default_rng(4)
    img = np.zeros((4, 4), np.uint8)

    def frame(i, z, jitter_m=5e-5, jitter_rad=1e-4, angle_rad=0.0):
        T = np.eye(4)
        T[:3, :3] = (Rotation.from_rotvec([0.0, angle_rad, 0.0])
                     * Rotation.from_rotvec(rng.normal(0, jitter_rad, 3))).as_matrix()
        T[:3, 3] = [0.0, 0.0, z] + rng.normal(0, jitter_m, 3)
        return StereoFrame(i, 0.1 * i, img, img, GroundTruth(T, np.zeros(3), np.zeros(3)))

    frames = [frame(i, 2.0) for i in range(10)] + [frame(10 + i, 3.5) for i in range(10)]
    assert [len(g) for g in split_ranges(frames)] == [10, 10]
    turned = [frame(i, 2.0) for i in range(5)] + [frame(5 + i, 2.0, angle_rad=0.01) for i in range(5)]
    assert [len(g) for g in split_ranges(turned)] == [5, 5]  # turned 0.57 deg, not moved
    drift = [frame(i, 2.0 + 4e-4 * i, jitter_m=0.0, jitter_rad=0.0) for i in range(8)]
    assert [len(g) for g in split_ranges(drift)] == [3, 3, 2]  # 1 mm from each range's first


def test_range_details_follow_their_range_not_its_depth():
    # Per-range details were attached by the range's mean depth rounded to 1 um: two ranges
    # measured at the same depth both showed the last one's true range and frame count.
    import numpy as np

    from trackmeter.core.error_analysis import analyze_ranges, range_statistics
    from trackmeter.pipeline.analysis import AnalysisRun, RangeMeasurements

    rng = np.random.default_rng(0)
    xyz = (np.array([0.1, 0.0, 3.5]) + rng.normal(0, [0.001, 0.001, 0.004], (10, 6, 3))
           + np.arange(6)[None, :, None] * [0.02, 0.01, 0])
    sig = np.full_like(xyz, 0.004)

    def measured(x, s, true_range_m):
        return RangeMeasurements(np.arange(len(x)) * 0.04, np.zeros((x.shape[1], 2)), x, s,
                                 np.full(x.shape[:2], 0.07), {}, true_range_m)

    ranges = (measured(xyz, sig, 3.5), measured(np.concatenate([xyz, xyz]), np.concatenate([sig, sig]), 3.6))
    stats = tuple(range_statistics(m.xyz_m, m.sigma_m, 5) for m in ranges)
    assert stats[0].range_m == stats[1].range_m
    entries = AnalysisRun(analyze_ranges(stats, 1000.0, 0.2), ranges, stats, 0.07).to_dict()["ranges"]
    assert [(e["true_range_m"], e["n_frames"]) for e in entries] == [(3.5, 10), (3.6, 20)]


def test_without_truth_the_ranges_are_where_the_image_jumps():
    # Without ground truth the whole source was one range: a still target recorded at several
    # ranges gave one range of all of them, a sub-pixel accuracy of 0.02 px against a noise
    # limit of 0.48 px and a parabola fitted to one point (an outside probe). The view of a
    # still target changes by its noise from frame to frame, and at once when it is moved.
    import numpy as np

    from trackmeter.pipeline.analysis import split_ranges
    from trackmeter.sources.base import StereoFrame

    rng = np.random.default_rng(3)
    views = [rng.integers(0, 255, (48, 64)).astype(float) for _ in range(3)]

    def frame(i, view):
        img = np.clip(views[view] + rng.normal(0, 2.0, views[view].shape), 0, 255).astype(np.uint8)
        return StereoFrame(i, 0.1 * i, img, img, None)

    which = [0, 0, 0, 0, 1, 1, 1, 2, 2, 2, 2, 2]
    groups = list(split_ranges([frame(i, v) for i, v in enumerate(which)]))
    assert [[f.index for f in g] for g in groups] == [[0, 1, 2, 3], [4, 5, 6], [7, 8, 9, 10, 11]]


@pytest.mark.slow
def test_analyze_without_truth_finds_the_ranges_the_truth_gives(tmp_path, capsys):
    import shutil

    scenario = tmp_path / "static_small.yaml"
    scenario.write_text(SCENARIO)
    seq = tmp_path / "seq"
    assert main(["simulate", "--scenario", str(scenario), "--out", str(seq)]) == 0
    capsys.readouterr()
    code = main(["analyze", "--source", f"seq:{seq}", "--json"])
    with_truth = json.loads(capsys.readouterr().out)
    assert code == 0
    bare = tmp_path / "bare"
    shutil.copytree(seq, bare)
    (bare / "groundtruth.csv").unlink()
    (bare / "groundtruth.tum").unlink()
    code = main(["analyze", "--source", f"seq:{bare}", "--json"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    without = json.loads(captured.out)
    assert [r["n_samples"] for r in without["ranges"]] == [r["n_samples"] for r in with_truth["ranges"]]
    assert [r["range_m"] for r in without["ranges"]] == pytest.approx([r["range_m"] for r in with_truth["ranges"]],
                                                                     abs=0.05)
    assert without["sigma_disparity_px"] == pytest.approx(with_truth["sigma_disparity_px"], rel=0.3)


def test_a_moving_source_is_refused_in_one_short_line(estec_rig):
    # Every frame of a moving object is a range of its own: the refusal must say why in one
    # line, not repeat a reason per frame (a 60 s sequence made a 2.8 KB message).
    import numpy as np

    from trackmeter.core.matching import MeasureParams
    from trackmeter.core.error_analysis import AnalyzeParams
    from trackmeter.errors import TrackmeterError
    from trackmeter.pipeline.analysis import run_error_analysis
    from trackmeter.sources.base import GroundTruth, Source, StereoFrame

    class Moving(Source):
        def __init__(self) -> None:
            self.i = 0

        def read(self):  # type: ignore[no-untyped-def]
            if self.i == 40:
                return None
            T = np.eye(4)
            T[2, 3] = 3.5 + 0.01 * self.i
            img = np.full((estec_rig.image_size[1], estec_rig.image_size[0]), 128, np.uint8)
            self.i += 1
            return StereoFrame(self.i - 1, 0.04 * self.i, img, img, GroundTruth(T, np.zeros(3), np.zeros(3)))

    with pytest.raises(TrackmeterError, match="40 ranges of 1.0 frames .* the analysis needs a still target") as info:
        run_error_analysis(Moving(), estec_rig, MeasureParams(), AnalyzeParams())
    assert len(str(info.value)) < 300


def test_analyze_refuses_frames_that_do_not_match_the_rig(opencv_sample_sequence, tmp_path, capsys):
    from pathlib import Path

    rig = Path(__file__).resolve().parent.parent / "config" / "rigs" / "estec_12mm.yaml"
    code = main(["analyze", "--source", f"seq:{opencv_sample_sequence}", "--rig", str(rig), "--out", str(tmp_path / "a")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert "frame 640x480 does not match the rig's image size 726x512" in err[0]
    assert not (tmp_path / "a").exists()


def test_analyze_takes_the_frame_size_for_an_opencv_pair_rig(opencv_sample_sequence, opencv_sample_rig, capsys):
    code = main(["analyze", "--source", f"seq:{opencv_sample_sequence}", "--rig",
                 str(opencv_sample_rig / "extrinsics.yml"), "--json"])
    captured = capsys.readouterr()
    # The rig is read (sized by the frames); the three pairs are three different scenes, not a
    # still target, so the analysis itself then finds no range: that is the one line it says.
    assert code == 2 and captured.err.strip().splitlines() == [
        "trackmeter analyze: error: no usable range for the error analysis (frames from t=0.000 s: "
        "no point has 5 good measurements at this range)"], captured.err


@pytest.fixture(scope="module")
def still_sequence(tmp_path_factory):
    """8 noisy frames of one textured plane at 3.8 m (no ground truth: one range); analyze
    runs on it in about a second."""
    import numpy as np

    from benchmarks.measure import estec_plane
    from trackmeter.data.sequence import SequenceWriter
    from trackmeter.sources.base import StereoFrame

    rig, left, right, _ = estec_plane(seed=5)
    folder = tmp_path_factory.mktemp("still") / "seq"
    rng = np.random.default_rng(0)

    def noisy(image):  # type: ignore[no-untyped-def]
        return np.clip(image + rng.normal(0, 2.5, image.shape), 0, 255).astype(np.uint8)

    with SequenceWriter(folder, rig=rig) as writer:
        for i in range(8):
            writer.write(StereoFrame(i, i / 25.0, noisy(left), noisy(right)))
    return folder


@pytest.mark.parametrize("kind", ["file", "sequence", "under_a_file"])
def test_an_out_that_cannot_hold_the_report_is_refused_before_the_work(still_sequence, tmp_path, monkeypatch,
                                                                       capsys, kind):
    """--out was first tried after the whole analysis: a file gave 'X: File exists', a place
    under a file 'Not a directory', and a sequence folder took the report among its images
    (evaluate refuses all three up front)."""
    import trackmeter.pipeline.analysis as analysis

    def no_work(*args, **kwargs):  # type: ignore[no-untyped-def]
        raise AssertionError("the analysis ran before --out was checked")

    monkeypatch.setattr(analysis, "run_error_analysis", no_work)
    (tmp_path / "notes.txt").write_text("x")
    out, words = {"file": (tmp_path / "notes.txt", ("notes.txt", "not a folder")),
                  "sequence": (still_sequence, ("a sequence folder",)),
                  "under_a_file": (tmp_path / "notes.txt" / "report", ("notes.txt", "not a writable folder"))}[kind]
    code = main(["analyze", "--source", str(still_sequence), "--points", "5", "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert err[0].startswith("trackmeter analyze: error: ")
    for word in words:
        assert word in err[0], err[0]
    assert not any(p.name.endswith((".json", ".md")) for p in still_sequence.iterdir())


def test_out_takes_an_earlier_analysis_report_but_no_folder_of_other_files(still_sequence, tmp_path, capsys,
                                                                            monkeypatch) -> None:
    import trackmeter.pipeline.analysis as analysis

    def no_work(*args, **kwargs):  # type: ignore[no-untyped-def]
        raise AssertionError("the analysis ran before --out was checked")

    monkeypatch.setattr(analysis, "run_error_analysis", no_work)
    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "notes.txt").write_text("x")
    (busy / "report.md").write_text("x")  # an evaluate report's: not an analysis report's folder
    code = main(["analyze", "--source", str(still_sequence), "--points", "5", "--out", str(busy)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "holds other files (notes.txt, report.md)" in err[0], err
    assert sorted(p.name for p in busy.iterdir()) == ["notes.txt", "report.md"]
    lone = tmp_path / "lone"
    lone.mkdir()
    (lone / "report.md").write_text("my own report")  # no analysis.json: the user's, not a report's
    code = main(["analyze", "--source", str(still_sequence), "--points", "5", "--out", str(lone)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and "holds other files (report.md)" in err[0], err
    # an earlier analysis report's folder, the user's notes beside it: replaced (the notes stay)
    (busy / "analysis.json").write_text("x")
    with pytest.raises(AssertionError, match="the analysis ran"):
        main(["analyze", "--source", str(still_sequence), "--points", "5", "--out", str(busy)])


def test_a_report_is_written_whole_or_not_at_all(still_sequence, tmp_path, full_disk, capsys):
    """On a full disk analysis.json and ranges.csv were left in --out without the plots and
    report.md they go with (seen on a full tmpfs)."""
    out = tmp_path / "report"
    out.mkdir()
    (out / "analysis.json").write_text('{"earlier": true}\n')
    full_disk(3000)
    code = main(["analyze", "--source", str(still_sequence), "--points", "5", "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert "No space left on device" in err[0]
    assert sorted(p.name for p in out.iterdir()) == ["analysis.json"]  # the earlier report's file, as it was
    assert (out / "analysis.json").read_text() == '{"earlier": true}\n'


def test_unreadable_frames_are_said(still_sequence, tmp_path, capsys):
    """Frames skipped for an unreadable image were not mentioned: with all of them unreadable
    the one line said only 'no usable range ... (the source gave no frames)'."""
    import shutil

    folder = tmp_path / "seq"
    shutil.copytree(still_sequence, folder)
    images = sorted((folder / "cam0" / "data").glob("*.png"))
    images[3].write_bytes(b"")
    code = main(["analyze", "--source", str(folder), "--points", "5"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 0
    assert err == [f"trackmeter analyze: warning: 1 pair(s) with an unreadable image skipped ({images[3]}: not an image "
                   "file OpenCV can decode)"]
    for image in images:
        image.write_bytes(b"")
    code = main(["analyze", "--source", str(folder), "--points", "5"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    # refused at open, before reading every pair for nothing
    assert err[0].startswith(f"trackmeter analyze: error: source {str(folder)!r}: no stereo pair plays") and (
        f"the first: {images[0]}: not an image file OpenCV can decode" in err[0]), err


def test_a_target_that_moves_without_ground_truth_is_warned_about(still_sequence, tmp_path, capsys):
    """Without ground truth the whole source is one range, so a moving target was analysed
    silently: the surface under each fixed pixel changes, and its motion was reported as
    measurement noise (a tumbling simulation: sigma_z 16.5 mm against 1.8 predicted). The
    points' image motion between the range's first and last frames (pyramidal Lucas-Kanade)
    says so; the still sequence says nothing."""
    import numpy as np

    from trackmeter.data.images import read_grey
    from trackmeter.data.sequence import SequenceWriter, index_sequence
    from trackmeter.sources.base import StereoFrame

    code = main(["analyze", "--source", str(still_sequence), "--points", "5", "--json"])
    assert code == 0 and capsys.readouterr().err == ""
    index = index_sequence(still_sequence)
    folder = tmp_path / "moving"
    with SequenceWriter(folder, rig=index.rig) as writer:
        for i, (left, right) in enumerate(zip(index.left_paths, index.right_paths)):
            shift = (i, i // 2)  # rows, columns: 7 px down and 3 px right by the last frame
            writer.write(StereoFrame(i, i / 25.0, np.roll(read_grey(left), shift, axis=(0, 1)),
                                     np.roll(read_grey(right), shift, axis=(0, 1))))
    code = main(["analyze", "--source", str(folder), "--points", "5", "--json"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 0 and len(err) == 1, err
    assert err[0].startswith("trackmeter analyze: warning: frames from t=0.000 s: the points moved 7.") and \
        "needs a still target" in err[0], err


def test_an_underexposed_still_target_is_measured_at_the_engines_gain(still_sequence, tmp_path, capsys):
    """The still sequence at 12 % of its brightness: `measure` and the tracking engine multiply
    such a pair by the exposure gain (config section exposure), `analyze` refused every point
    ("no usable range"). It now measures each range at one gain (its first left image's), says
    so, and finds the points a sigma like the bright sequence's."""
    import json

    import numpy as np

    from trackmeter.data.images import read_grey
    from trackmeter.data.sequence import SequenceWriter, index_sequence
    from trackmeter.sources.base import StereoFrame

    index = index_sequence(still_sequence)
    folder = tmp_path / "dark"
    with SequenceWriter(folder, rig=index.rig) as writer:
        for i, (left, right) in enumerate(zip(index.left_paths, index.right_paths)):
            dark = [np.round(read_grey(p) * 0.12).astype(np.uint8) for p in (left, right)]
            writer.write(StereoFrame(i, i / 25.0, dark[0], dark[1]))
    assert main(["analyze", "--source", str(still_sequence), "--points", "5", "--json"]) == 0
    bright = json.loads(capsys.readouterr().out)
    code = main(["analyze", "--source", str(folder), "--points", "5", "--json"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("trackmeter analyze: note: 1 of 1 range(s) underexposed"), err
    dark = json.loads(captured.out)
    (entry,) = dark["ranges"]
    assert entry["n_points"] == 5 and entry["exposure_gain"] == 4.0  # max_gain: 0.12 x 4 is still dim
    assert bright["ranges"][0]["exposure_gain"] == 1.0
    z_dark, z_bright = entry["sigma_m"]["z"], bright["ranges"][0]["sigma_m"]["z"]
    assert 0.3 < z_dark / z_bright < 3.0, (z_dark, z_bright)


def test_the_points_asked_for_are_found_past_corners_the_matcher_refuses(still_sequence, monkeypatch) -> None:
    # Only the 4 N strongest corners were tried: where the matcher refused them (a repetitive
    # texture, one camera's view) --points 3 measured 1 point, or none, on the simulator's ranges.
    from dataclasses import replace

    import numpy as np

    import trackmeter.pipeline.analysis as analysis
    from trackmeter.core.error_analysis import AnalyzeParams
    from trackmeter.core.matching import MeasureParams
    from trackmeter.sources import open_source

    params = AnalyzeParams(points_per_range=3)
    with open_source(f"seq:{still_sequence}") as source:
        frames = [source.read() for _ in range(3)]
        rig = source.rig
    strongest = analysis.select_points(frames[0].left, params, MeasureParams().min_mean_grey, 12)
    real = analysis.measure_points

    def refusing(rig, left, right, uv, params, *args):  # type: ignore[no-untyped-def]
        out = real(rig, left, right, uv, params, *args)
        refused = [any(np.allclose(p, q) for q in strongest) for p in np.asarray(uv).reshape(-1, 2)]
        return tuple(replace(m, ok=False, reason="refused here") if r else m for m, r in zip(out, refused))

    monkeypatch.setattr(analysis, "measure_points", refusing)
    m = analysis.measure_range(frames, rig, MeasureParams(), params)
    assert len(m.uv) == 3 and np.isfinite(m.xyz_m).all()
    assert not any(np.allclose(p, q) for p in m.uv for q in strongest)


def test_a_border_wider_than_the_image_says_no_point_could_be_selected(still_sequence, tmp_path, capsys) -> None:
    # border_px: 100000 in --config: a traceback (a 40 GB kernel); at 1000: "no point has 5
    # good measurements", which blamed the measurements for a selection that found nothing.
    config = tmp_path / "c.yaml"
    config.write_text("analyze:\n  border_px: 100000\n")
    code = main(["analyze", "--source", str(still_sequence), "--config", str(config)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert "no point selectable on its first frame: no corner 100000 px inside the lit target" in err[0], err


def test_a_still_motion_threshold_of_zero_is_refused(still_sequence, tmp_path, capsys) -> None:
    # 0 warned that points moving 0.0 px made the range's scatter (an outside probe): the
    # threshold is a motion the LK tracker can tell, not nothing.
    config = tmp_path / "c.yaml"
    config.write_text("analyze:\n  max_still_motion_px: 0\n")
    code = main(["analyze", "--source", str(still_sequence), "--config", str(config)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "max_still_motion_px" in err[0], err


def test_points_that_fall_short_of_their_samples_are_made_up_for(still_sequence, monkeypatch) -> None:
    # --points 3 on a small range: 3 selected, 2 measured often enough, and the range dropped
    # while the target had more points to measure (a re-check probe).
    import numpy as np

    import trackmeter.pipeline.analysis as analysis
    from trackmeter.core.error_analysis import AnalyzeParams
    from trackmeter.core.matching import MeasureParams
    from trackmeter.sources import open_source

    params = AnalyzeParams(points_per_range=3)
    with open_source(f"seq:{still_sequence}") as source:
        frames = [source.read() for _ in range(8)]
        rig = source.rig
    plain = analysis.measure_range(frames, rig, MeasureParams(), params)
    assert len(plain.uv) == 3  # all three measured often enough: nothing to make up for
    flaky = plain.uv[1]
    real = analysis.measure_points

    def refusing_later(rig, left, right, uv, params, *args):  # type: ignore[no-untyped-def]
        out = real(rig, left, right, uv, params, *args)
        later = left is not frames[0].left
        return tuple(replace(m, ok=False, reason="refused later") if later and np.allclose(p, flaky) else m
                     for m, p in zip(out, np.asarray(uv).reshape(-1, 2)))

    from dataclasses import replace

    monkeypatch.setattr(analysis, "measure_points", refusing_later)
    m = analysis.measure_range(frames, rig, MeasureParams(), params)
    good = np.sum(np.isfinite(m.xyz_m[..., 2]), axis=0) >= params.min_samples
    assert len(m.uv) == 4 and good.sum() == 3 and not good[1], good
    assert np.allclose(m.uv[:3], plain.uv) and m.refusals.get("refused later") == 7


def _with_truth(still_sequence, tmp_path, rows: int | None, text: str | None = None):  # type: ignore[no-untyped-def]
    """A copy of ``still_sequence`` with a groundtruth.csv: the plane still at 3.8 m on its
    first ``rows`` frames, or ``text``."""
    import shutil

    from trackmeter.data.motion_csv import GROUNDTRUTH_COLUMNS

    folder = tmp_path / "seq"
    shutil.copytree(still_sequence, folder)
    if text is None:
        lines = [f"{i / 25.0:.6f},0,0,3.8,1,0,0,0,0,0,0,0,0,0" for i in range(rows or 0)]
        text = ",".join(GROUNDTRUTH_COLUMNS) + "\n" + "\n".join(lines) + "\n"
    (folder / "groundtruth.csv").write_text(text)
    return folder


def test_frames_without_ground_truth_among_frames_with_it_are_skipped_and_said(still_sequence, tmp_path, capsys):
    """Truth on 6 of 8 frames refused the whole analysis ('ground truth present on some frames
    only: cannot split the source into ranges', no file, no time) although its rows warned
    they would be read as no truth at their time (an outside probe)."""
    folder = _with_truth(still_sequence, tmp_path, rows=6)
    code = main(["analyze", "--source", str(folder), "--points", "5", "--json"])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert "2 frame(s) without ground truth skipped: they belong to no range (the first at t = 0.240 s)" in err, err
    report = json.loads(out)
    assert [r["n_frames"] for r in report["ranges"]] == [6]


def test_a_ground_truth_file_that_does_not_read_stops_analyze(still_sequence, tmp_path, capsys):
    """One garbage line made the truth unread ('ground truth not used', a warning) and analyze
    went on as if the source had none: six ranges taken for one, k 0.19 instead of 0.08 and
    exit 0 (an outside probe). The ranges come from the truth: analyze stops, naming it."""
    from trackmeter.data.motion_csv import GROUNDTRUTH_COLUMNS

    text = ",".join(GROUNDTRUTH_COLUMNS) + "\n0,0,0,3.8,1,0,0,0,0,0,0,0,0,0\ngarbage\n"
    folder = _with_truth(still_sequence, tmp_path, rows=None, text=text)
    code = main(["analyze", "--source", str(folder), "--points", "5"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 2, err
    # (the file is named once: the folder's name no longer stands in front of its own file's)
    assert err[0].startswith(f"trackmeter analyze: warning: {folder / 'groundtruth.csv'}:3: expected 14 values")
    assert err[1].startswith("trackmeter analyze: error: analyze splits the source into its still ranges by the "
                             f"ground truth, and {folder / 'groundtruth.csv'}:3: expected 14 values")


def test_a_ground_truth_without_a_whole_pose_stops_analyze(still_sequence, tmp_path, capsys):
    """Every row's x NaN: each warned, then analyze went on as if there were no truth, six
    ranges taken for one, exit 0 (an outside probe, a variant of the unreadable file)."""
    from trackmeter.data.motion_csv import GROUNDTRUTH_COLUMNS

    rows = [f"{i / 25.0:.6f},nan,0,3.8,1,0,0,0,0,0,0,0,0,0" for i in range(8)]
    folder = _with_truth(still_sequence, tmp_path, rows=None,
                         text=",".join(GROUNDTRUTH_COLUMNS) + "\n" + "\n".join(rows) + "\n")
    code = main(["analyze", "--source", str(folder), "--points", "5"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2, err
    assert err[-1].startswith("trackmeter analyze: error: analyze splits the source into its still ranges by the "
                              "ground truth"), err
    assert f"{folder / 'groundtruth.csv'}: no row gives a whole pose" in err[-1], err
