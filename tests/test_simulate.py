"""``trackmeter simulate``: every scenario to a sequence folder that the seq source plays back exactly."""

from __future__ import annotations

import re
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from trackmeter.cli.main import main
from trackmeter.data.model import load_model
from trackmeter.data.motion_csv import read_motion_csv
from trackmeter.data.rigfile import load_rig
from trackmeter.data.trajectory import read_tum
from trackmeter.paths import SCENARIOS_DIR
from trackmeter.sources import open_source
from trackmeter.sources.sim.scenario import load_scenario
from trackmeter.sources.sim.simulator import Simulator

SCENARIOS = sorted(p.stem for p in SCENARIOS_DIR.glob("*.yaml"))


@pytest.mark.slow
@pytest.mark.parametrize("name", SCENARIOS)
def test_simulate_every_scenario_reads_back_frame_for_frame(tmp_path, name, capsys):
    out = tmp_path / name
    duration = 0.2
    assert main(["simulate", "--scenario", name, "--duration", str(duration), "--out", str(out)]) == 0
    assert f"to {out}" in capsys.readouterr().out
    assert not (tmp_path / f"{name}.partial").exists()
    for f in ("rig.yaml", "groundtruth.tum", "groundtruth.csv", "model.yaml", "cam0/data.csv", "cam1/data.csv"):
        assert (out / f).is_file(), f
    assert (out / "groundtruth.csv").read_text().splitlines()[0] == "t,x,y,z,qw,qx,qy,qz,vx,vy,vz,wx,wy,wz"

    sim = Simulator(load_scenario(name).with_duration(duration))
    expected = [sim.frame(i) for i in range(sim.n_frames)]
    src = open_source(f"seq:{out}")
    assert src.skipped == 0 and src.warning is None
    assert src.rate_hz == pytest.approx(sim.rate_hz)
    got = list(iter(src.read, None))
    assert len(got) == len(expected) >= 5
    for a, b in zip(expected, got):
        assert b.index == a.index and b.t_s == pytest.approx(a.t_s, abs=1e-9)
        assert np.array_equal(a.left, b.left) and np.array_equal(a.right, b.right)
        assert np.allclose(a.truth.T_cam_body, b.truth.T_cam_body, atol=1e-12)
        assert np.allclose(a.truth.velocity_cam_m_s, b.truth.velocity_cam_m_s, atol=1e-15)
        assert np.allclose(a.truth.omega_body_rad_s, b.truth.omega_body_rad_s, atol=1e-15)
    # The TUM file agrees with the CSV (9 decimals), the rig and model are the scenario's.
    tum = read_tum(out / "groundtruth.tum")
    csv = read_motion_csv(out / "groundtruth.csv")
    assert np.allclose(tum.position_m, csv.position_m, atol=1e-8)
    assert np.allclose(np.abs(np.einsum("ij,ij->i", tum.quat_wxyz, csv.quat_wxyz)), 1.0, atol=1e-8)
    rig = load_rig(out / "rig.yaml")
    assert np.allclose(rig.left.K, sim.true_rig.left.K) and np.allclose(rig.R, sim.true_rig.R)
    model = load_model(out / "model.yaml")
    assert np.allclose(model.points_body, sim.model_points_body)


def test_simulate_refuses_a_used_folder_and_bad_input(tmp_path, capsys):
    used = tmp_path / "used"
    used.mkdir()
    (used / "x").write_text("keep me")
    assert main(["simulate", "--duration", "0.04", "--out", str(used)]) == 2
    assert "not an empty folder" in capsys.readouterr().err
    assert (used / "x").read_text() == "keep me"
    # 1e300 s integrated its whole motion before the first frame, silently, until interrupted
    for duration in ("-1", "inf", "nan", "3600.5", "1e300"):
        assert main(["simulate", "--duration", duration, "--out", str(tmp_path / "a")]) == 2
        err = capsys.readouterr().err
        assert "--duration" in err and len(err.strip().splitlines()) == 1
        assert not (tmp_path / "a").exists()
    endless = tmp_path / "endless.yaml"
    endless.write_text("duration_s: .inf\n")
    assert main(["simulate", "--scenario", str(endless), "--out", str(tmp_path / "a")]) == 2
    assert "'duration_s': expected a finite number" in capsys.readouterr().err
    endless.write_text("duration_s: 1.0e+300\n")
    assert main(["simulate", "--scenario", str(endless), "--out", str(tmp_path / "a")]) == 2
    assert "'duration_s'" in capsys.readouterr().err
    assert main(["simulate", "--scenario", "nope", "--out", str(tmp_path / "b")]) == 2
    assert "no scenario 'nope'" in capsys.readouterr().err
    bad = tmp_path / "bad.yaml"
    bad.write_text("rate_hz: 25\nomega0_body_deg_s: [1, 2, x]\n")
    assert main(["simulate", "--scenario", str(bad), "--out", str(tmp_path / "c")]) == 2
    err = capsys.readouterr().err
    assert "omega0_body_deg_s[2]" in err and len(err.strip().splitlines()) == 1
    behind = tmp_path / "behind.yaml"
    behind.write_text("position0_m: [0, 0, -3.5]\n")  # a sequence of noise only
    assert main(["simulate", "--scenario", str(behind), "--out", str(tmp_path / "d")]) == 2
    err = capsys.readouterr().err
    assert "'position0_m'" in err and "behind the camera" in err and len(err.strip().splitlines()) == 1
    assert not any((tmp_path / name).exists() for name in "acd")


def test_simulate_unwritable_out_is_one_line_and_exit_2(tmp_path, capsys):
    """An --out the OS refuses: one line naming the path the user gave (not the hidden
    DIR.partial it is written into) and the reason, exit 2, no traceback."""
    assert main(["simulate", "--duration", "0.04", "--out", "/proc/nope"]) == 2
    err = capsys.readouterr().err
    assert err == "trackmeter simulate: error: /proc/nope: cannot create a sequence folder there (/proc is not a writable folder)\n"
    (tmp_path / "a_file").write_text("")
    out = tmp_path / "a_file" / "seq"
    assert main(["simulate", "--duration", "0.04", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err == (f"trackmeter simulate: error: {out}: cannot create a sequence folder there "
                   f"({tmp_path / 'a_file'} is not a writable folder)\n")


def test_simulate_reads_its_config(tmp_path, capsys):
    """--config is loaded (and checked) like every other command's, before anything is written."""
    assert main(["simulate", "--config", str(tmp_path / "none.yaml"), "--duration", "0.04", "--out", str(tmp_path / "a")]) == 2
    assert capsys.readouterr().err == f"trackmeter simulate: error: {tmp_path / 'none.yaml'}: no such file\n"
    bad = tmp_path / "bad.yaml"
    bad.write_text("tracker: {no_such_knob: 1}\n")
    assert main(["simulate", "--config", str(bad), "--duration", "0.04", "--out", str(tmp_path / "b")]) == 2
    assert "unknown key 'tracker.no_such_knob'" in capsys.readouterr().err
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()
    good = tmp_path / "good.yaml"
    good.write_text("tracker: {max_targets: 8}\n")
    assert main(["simulate", "--config", str(good), "--scenario", "static_ranges", "--duration", "0.04",
                 "--out", str(tmp_path / "c")]) == 0


def test_simulate_into_an_empty_existing_folder(tmp_path):
    out = tmp_path / "empty"
    out.mkdir()
    assert main(["simulate", "--scenario", "static_ranges", "--duration", "0.04", "--out", str(out)]) == 0
    assert len(open_source(str(out))) == 6  # one frame per range


def test_simulate_into_the_empty_current_folder(tmp_path, monkeypatch):
    # "--out ." has no name to put ".partial" after: a ValueError's traceback (an outside probe).
    out = tmp_path / "here"
    out.mkdir()
    monkeypatch.chdir(out)
    assert main(["simulate", "--scenario", "static_ranges", "--duration", "0.04", "--out", "."]) == 0
    assert len(open_source(str(out))) == 6
    assert sorted(p.name for p in tmp_path.iterdir()) == ["here"]


def test_simulate_refuses_a_link_as_out_before_rendering(tmp_path, capsys, monkeypatch):
    # A link to an empty folder passed as empty, and the rename at the end of the whole render
    # failed on the link ("Not a directory"), throwing the render away (an outside probe).
    import trackmeter.sources.sim.simulator as simulator

    (tmp_path / "target").mkdir()
    (tmp_path / "lnk").symlink_to(tmp_path / "target")
    monkeypatch.setattr(simulator, "Simulator", None)  # refused before any rendering
    assert main(["simulate", "--duration", "0.04", "--out", str(tmp_path / "lnk")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "lnk: is a link; give the folder it leads to" in err[0] and "target" in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["lnk", "target"]


def test_camera_that_cannot_be_opened_exits_2(tmp_path, capsys):
    """A source SPEC naming a missing camera, through a real command that takes --source: one
    clear line on stderr, exit 2, no traceback."""
    proc = subprocess.run([sys.executable, "-m", "trackmeter.cli.main", "analyze", "--source", "camera:99"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.strip() == "trackmeter analyze: error: camera 99 cannot be opened (no such device, or it is busy)"
    for spec, message in [("camera:x", "device numbers"), (f"video:{tmp_path}/l.avi,{tmp_path}/r.avi", "no such video file"),
                          ("nothing_here", "unknown source 'nothing_here'")]:
        assert main(["analyze", "--source", spec]) == 2
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1


def test_a_leftover_partial_is_replaced_only_when_it_is_ours(tmp_path, capsys):
    # A run killed outright leaves OUT.partial behind; the next run replaces it. A folder of
    # that name holding anything else is the user's: refused, untouched.
    theirs = tmp_path / "a.partial"
    theirs.mkdir()
    (theirs / "notes.txt").write_text("keep me")
    assert main(["simulate", "--duration", "0.04", "--out", str(tmp_path / "a")]) == 2
    err = capsys.readouterr().err
    assert "a.partial: exists and is not a sequence this command left unfinished" in err and err.count("\n") == 1
    assert (theirs / "notes.txt").read_text() == "keep me" and not (tmp_path / "a").exists()
    leftover = tmp_path / "b.partial"
    (leftover / "cam0" / "data").mkdir(parents=True)
    (leftover / ".rig.yaml.x1y2").write_text("half")
    assert main(["simulate", "--duration", "0.04", "--out", str(tmp_path / "b")]) == 0
    assert not leftover.exists() and (tmp_path / "b" / "cam0" / "data.csv").is_file()
    # A .partial another simulate is still writing (its writer holds the folder) is not taken.
    from trackmeter.data.sequence import SequenceWriter
    from trackmeter.sources.base import StereoFrame

    with SequenceWriter(tmp_path / "c.partial") as running:
        assert main(["simulate", "--duration", "0.04", "--out", str(tmp_path / "c")]) == 2
        assert "another simulate (or recording) is writing there now" in capsys.readouterr().err
        assert (tmp_path / "c.partial" / "cam0" / "data.csv").is_file() and not (tmp_path / "c").exists()
        img = np.zeros((8, 8), np.uint8)
        running.write(StereoFrame(0, 0.0, img, img))  # its folder still its own


def test_an_interrupted_simulation_says_what_it_removed_and_a_scenario_file_is_named(tmp_path, capsys, monkeypatch):
    """Ctrl-C said only 'interrupted' (an outside probe): the unfinished DIR.partial is removed,
    and that is said. A scenario given as a file printed only its name: key."""
    import shutil

    from trackmeter.data.sequence import SequenceWriter
    from trackmeter.paths import SCENARIOS_DIR

    mine = tmp_path / "my_scen.yaml"
    shutil.copy(SCENARIOS_DIR / "estec.yaml", mine)
    assert main(["simulate", "--scenario", str(mine), "--duration", "0.08", "--out", str(tmp_path / "a")]) == 0
    assert f"of scenario estec ({mine}) to" in capsys.readouterr().out
    real_write = SequenceWriter.write
    calls = []

    def write_then_interrupt(self, frame):  # type: ignore[no-untyped-def]
        calls.append(frame.index)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real_write(self, frame)

    monkeypatch.setattr(SequenceWriter, "write", write_then_interrupt)
    assert main(["simulate", "--duration", "0.2", "--out", str(tmp_path / "b")]) == 130
    err = capsys.readouterr().err
    assert f"the unfinished {tmp_path / 'b.partial'} was removed; nothing was written to {tmp_path / 'b'}" in err
    assert not (tmp_path / "b.partial").exists() and not (tmp_path / "b").exists()


def test_a_simulate_refused_by_another_s_partial_leaves_it_whole(tmp_path, capsys, monkeypatch):
    """Two simulate --out X started together: both find no X.partial, one makes and locks it,
    the other's writer is refused, and its clean-up removed the winner's folder (a code review).
    The loser now takes back nothing: the folder was never its own."""
    from trackmeter.data.sequence import SequenceWriter
    from trackmeter.sources.sim import simulator

    held = []
    real_init = simulator.Simulator.__init__

    def init_then_the_other_starts(self, *args, **kwargs):  # type: ignore[no-untyped-def]
        real_init(self, *args, **kwargs)
        if not held:
            held.append(SequenceWriter(tmp_path / "x.partial"))  # the other simulate, first to its writer

    monkeypatch.setattr(simulator.Simulator, "__init__", init_then_the_other_starts)
    assert main(["simulate", "--duration", "0.04", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert "x.partial" in err and ("already holds a sequence" in err or "is writing there now" in err), err
    assert (tmp_path / "x.partial" / "cam0" / "data.csv").is_file() and not (tmp_path / "x").exists()
    held[0].close()


def test_a_camera_within_the_mock_ups_reach_is_warned_of(tmp_path) -> None:
    # A scenario that put the camera among the mock-up's parts rendered views from inside it
    # (faces seen from behind left out: a black or half-empty image) without a word (a probe).
    from trackmeter.sources.sim.simulator import Simulator

    near = tmp_path / "near.yaml"
    near.write_text("position0_m: [0, 0, 3]\nvelocity_m_s: [0, 0, -0.5]\nduration_s: 5\n")
    with pytest.warns(UserWarning, match=r"the camera comes within 0\.52 m of the body origin at t = 4\.96 s.*"
                                         r"reaches 0\.95 m"):
        Simulator(str(near))
    held = tmp_path / "held.yaml"
    held.write_text("position0_m: [0, 0, 2]\nvelocity_m_s: [0, 0, -0.5]\nduration_s: 5\nrelease_s: 2\n")
    with pytest.warns(UserWarning, match=r"within 0\.52 m of the body origin at t = 4\.96 s"):
        Simulator(str(held))  # released at 2 s: the motion runs 2.96 s (without the hold: 0 m at 4 s)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for name in ("estec", "approach", "static_ranges"):
            Simulator(name)  # 2 m and more away: quiet


@pytest.mark.parametrize("motion", ["approach_to_m: [0, 0, -2]\napproach_s: 0.5\n", "velocity_m_s: [0, 0, -100]\n"])
def test_a_motion_that_takes_the_body_behind_the_camera_is_refused(tmp_path, capsys, motion: str) -> None:
    # A start behind the camera was refused, a motion that went there was not: its truth had
    # the body at z = -2 m (an outside probe).
    scenario = tmp_path / "x.yaml"
    scenario.write_text("duration_s: 1\n" + motion)
    code = main(["simulate", "--scenario", str(scenario), "--out", str(tmp_path / "seq")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert "takes the body origin to z = " in err[0] and "at or behind the camera" in err[0], err
    assert not (tmp_path / "seq").exists()
    # --duration carries a motion on: the same check
    scenario.write_text("duration_s: 1\nvelocity_m_s: [0, 0, -1]\n")
    assert main(["simulate", "--scenario", str(scenario), "--duration", "0.5", "--out", str(tmp_path / "ok")]) == 0
    code = main(["simulate", "--scenario", str(scenario), "--duration", "4", "--out", str(tmp_path / "far")])
    err = capsys.readouterr().err
    assert code == 2 and "at t = 3.52 s" in err and f"--duration 4 with scenario '{scenario}'" in err, err


def test_a_rig_that_track_refuses_is_refused_before_rendering(tmp_path, capsys) -> None:
    """A scenario whose rig has its right camera on the left rendered a sequence with exit 0
    that track and measure then refused (and track --source sim:SCENARIO refused at once; an
    outside probe). Refused here too, before anything is rendered."""
    import dataclasses

    from trackmeter.data.rigfile import save_rig

    rig = load_rig(Path(__file__).resolve().parent.parent / "config" / "rigs" / "estec_12mm.yaml")
    save_rig(dataclasses.replace(rig, T=-rig.T), tmp_path / "swapped.yaml")
    scenario = tmp_path / "s.yaml"
    scenario.write_text(f"rig: {tmp_path / 'swapped.yaml'}\nduration_s: 1\n")
    code = main(["simulate", "--scenario", str(scenario), "--out", str(tmp_path / "seq")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert err[0].startswith(f"trackmeter simulate: error: the rig of scenario '{scenario}' ({tmp_path / 'swapped.yaml'}): "
                             "the right camera lies left of the left one"), err
    assert not (tmp_path / "seq").exists() and not (tmp_path / "seq.partial").exists()


@pytest.mark.parametrize(("position", "said"), [("[10.0, 0.0, 3.5]", "out of the left camera's view in 5 of 5 frames"),
                                               ("[0, 0, 3000]", "under 2 px across in 5 of 5 frames")])
def test_a_mock_up_out_of_view_is_warned_of(tmp_path, position: str, said: str) -> None:
    """10 m to the side (or 3 km away) rendered black frames with exit 0 and nothing said;
    only track noticed, afterwards (an outside probe)."""
    from trackmeter.sources.sim.simulator import Simulator

    scenario = tmp_path / "away.yaml"
    scenario.write_text(f"position0_m: {position}\nduration_s: 0.2\n")
    with pytest.warns(UserWarning, match=rf"scenario 'away': the mock-up is {re.escape(said)} \(t = 0\.00 to 0\.16 s\): "
                                         "those images show no target"):
        Simulator(str(scenario))


def test_a_face_seen_edge_on_renders_without_numpy_warnings(tmp_path) -> None:
    """The body 0.4 m to the side, not turning: a bus face's plane passes through the left
    camera's centre, and numpy's "divide by zero" warnings (four lines and a source line)
    reached the stderr of a run that succeeded (an outside probe). The image is the same as a
    hair beside it."""
    from trackmeter.sources.sim.simulator import Simulator

    frames = []
    for x in (0.4, 0.40001):
        scenario = tmp_path / f"edge{x}.yaml"
        scenario.write_text(f"position0_m: [{x}, 0, 3.5]\nomega0_body_deg_s: [0, 0, 0]\nduration_s: 0.2\n")
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            frames.append(Simulator(str(scenario)).frame(0).left.astype(int))
    assert np.abs(frames[0] - frames[1]).max() <= 2


def test_the_scenario_s_motion_alone_makes_no_renderer() -> None:
    # evaluate --truth sim:X built the renderer (canvases the size of the rig's images) only to
    # read the motion: with a huge rig, 149 GiB asked for (an outside probe).
    from trackmeter.sources.sim.simulator import scenario_truth

    sim = Simulator("estec")
    sim.truth(10)
    assert sim._renderer is None
    assert sim.frame(0).left.shape == (sim.true_rig.image_size[1], sim.true_rig.image_size[0])
    assert sim._renderer is not None
    assert len(scenario_truth("estec")) == sim.n_frames


def test_overwrite_replaces_a_sequence_simulate_wrote_and_nothing_else(tmp_path, capsys) -> None:
    """`simulate` alone had no --overwrite (track and calibrate do): re-rendering a scenario
    meant deleting its folder by hand (an outside probe). It replaces only a sequence this
    command wrote, and only once the new one is complete."""
    out = tmp_path / "seq"
    assert main(["simulate", "--scenario", "static_ranges", "--duration", "0.04", "--out", str(out)]) == 0
    capsys.readouterr()
    assert main(["simulate", "--duration", "0.04", "--out", str(out)]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert main(["simulate", "--duration", "0.08", "--out", str(out), "--overwrite"]) == 0
    assert "name: estec" in (out / "scenario.yaml").read_text()
    assert len(list((out / "cam0" / "data").glob("*.png"))) == 2
    assert [p.name for p in tmp_path.iterdir()] == ["seq"]  # nothing left beside it
    other = tmp_path / "mine"
    other.mkdir()
    (other / "notes.txt").write_text("keep me")
    assert main(["simulate", "--duration", "0.04", "--out", str(other), "--overwrite"]) == 2
    assert "not a sequence simulate wrote" in capsys.readouterr().err
    assert (other / "notes.txt").read_text() == "keep me"


def test_a_render_whose_partial_folder_loses_a_camera_says_nothing_was_kept(tmp_path, monkeypatch, capsys) -> None:
    """`rm -rf OUT.partial/cam1` mid-render: the writer's message said "cam0 keeps its own",
    and simulate then removed the whole unfinished folder (a re-check)."""
    import shutil

    from trackmeter.data.sequence import SequenceWriter

    write = SequenceWriter.write

    def write_then_lose_cam1(self, frame):  # type: ignore[no-untyped-def]
        if self.frames_written == 2:
            shutil.rmtree(self.directory / "cam1")
        return write(self, frame)

    monkeypatch.setattr(SequenceWriter, "write", write_then_lose_cam1)
    out = tmp_path / "seq"
    assert main(["simulate", "--duration", "0.2", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "cam1's files were removed while recording" in err and "keeps its own" not in err, err
    assert f"the unfinished {out}.partial was removed; nothing was written to {out}" in err, err
    assert not out.exists() and not (tmp_path / "seq.partial").exists()


def test_a_warning_about_the_scenarios_rig_is_said_once(tmp_path, capsys, estec_rig):
    """The rig was read twice (checked, then by the simulator), and its warnings (a baseline
    in millimetres) printed twice (an outside probe)."""
    from dataclasses import replace

    from trackmeter.data.rigfile import save_rig

    save_rig(replace(estec_rig, T=estec_rig.T * 1000.0), tmp_path / "rig_mm.yaml")
    scenario = tmp_path / "mm.yaml"
    scenario.write_text("rig: rig_mm.yaml\nduration_s: 0.08\n")
    assert main(["simulate", "--scenario", str(scenario), "--out", str(tmp_path / "out")]) == 0
    err = capsys.readouterr().err
    assert err.count("T must be in metres") == 1, err
