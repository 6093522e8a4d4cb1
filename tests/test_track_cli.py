"""trackmeter track: the run directory contract, bad input, and a source failing mid-run."""

from __future__ import annotations

import contextlib
import copy
import csv
import signal
from pathlib import Path

import numpy as np
import pytest
import yaml

from trackmeter.cli.main import main
from trackmeter.cli.track import parse_target
from trackmeter.data.motion_csv import read_motion_csv
from trackmeter.data.trajectory import read_tum
from trackmeter.errors import TrackmeterError
from trackmeter.sources.base import Source, StereoFrame

REPO = Path(__file__).resolve().parent.parent
STATES_HEADER = "t,valid,x,y,z,qw,qx,qy,qz,vx,vy,vz,wx,wy,wz,n_tracked,n_lost,latency_ms"
TARGETS_HEADER = "t,id,state,u,v,u_right,v_right,x,y,z,score"


class TextureSource(Source):
    """Static random texture seen by the paper's rig; raises after ``fail_after`` frames. One
    image in both cameras: ``track`` warns of it once (:data:`SAME_IMAGE`)."""

    def __init__(self, rig, n: int = 6, fail_after: int | None = None, brightness: float = 1.0) -> None:
        self.rig = rig
        self.rate_hz = 25.0
        self.model = None
        self._n, self._k, self._fail = n, 0, fail_after
        rng = np.random.default_rng(0)
        w, h = rig.image_size
        self._img = ((rng.random((h, w)) * 200 + 30) * brightness).astype(np.uint8)

    def __len__(self) -> int:
        return self._n

    def read(self) -> StereoFrame | None:
        if self._fail is not None and self._k >= self._fail:
            raise TrackmeterError("camera unplugged")
        if self._k >= self._n:
            return None
        self._k += 1
        return StereoFrame(self._k - 1, 0.04 * (self._k - 1), self._img, self._img)


#: The warning a source of one image in both cameras gets (TextureSource).
SAME_IMAGE = "the left and right images are one and the same image"


def _other_lines(err: str) -> list[str]:
    """stderr's lines but the warning that TextureSource's one image in both cameras gets."""
    return [line for line in err.strip().splitlines() if SAME_IMAGE not in line]


def fake_source(monkeypatch, rig, **kw) -> None:
    import trackmeter.sources as sources

    monkeypatch.setattr(sources, "open_source", lambda spec, rig_override=None, realtime=False, loop=False, **_:
                        TextureSource(rig_override or rig, **kw))


def test_parse_target() -> None:
    assert parse_target("12.5,40") == (None, (12.5, 40.0))
    assert parse_target("bus_c0=1,2") == ("bus_c0", (1.0, 2.0))
    with pytest.raises(TrackmeterError, match="U,V"):
        parse_target("a=1")
    with pytest.raises(TrackmeterError, match="empty id"):
        parse_target("=1,2")


@pytest.mark.parametrize("text", ["id=", "a=b=1,2", "a=1,2,3", "foo", "nan,1", "a= ,2"])
def test_a_malformed_target_is_quoted_as_given(text: str) -> None:
    """'--target id=' said "expected a pixel as U,V (two finite numbers), got ''" and
    '--target a=b=1,2' "... got 'b=1,2'": the text after the first '=', not what was typed."""
    with pytest.raises(TrackmeterError) as info:
        parse_target(text)
    assert str(info.value) == f"--target {text!r}: expected [ID=]U,V, a pixel's U,V two finite numbers"


def test_run_directory_contract(monkeypatch, tmp_path, estec_rig, capsys) -> None:
    fake_source(monkeypatch, estec_rig, n=6)
    out = tmp_path / "run"
    assert main(["track", "--source", "fake", "--auto", "8", "--out", str(out)]) == 0
    assert (out / "states.csv").read_text().splitlines()[0] == STATES_HEADER
    assert (out / "targets.csv").read_text().splitlines()[0] == TARGETS_HEADER
    states = read_motion_csv(out / "states.csv")
    assert len(states) == 6  # one row per frame, valid or not
    valid = states.valid_only() if hasattr(states, "valid_only") else states
    tum_text = (out / "trajectory.tum").read_text()
    n_tum = sum(1 for line in tum_text.splitlines() if line and not line.startswith("#"))
    assert n_tum == len(valid)
    if n_tum:
        assert len(read_tum(out / "trajectory.tum").t_s) == n_tum
    meta = yaml.safe_load((out / "run.yaml").read_text())
    assert meta["status"] == "complete" and meta["summary"]["frames"] == 6
    assert meta["source"]["spec"] == "fake" and "pose" in meta["config"] and "trackmeter" in meta["versions"]
    rows = list(csv.DictReader((out / "targets.csv").open()))
    assert {r["state"] for r in rows} <= {"tracking", "lost", "recovered"}
    assert "6 frames" in capsys.readouterr().out
    # An existing run is not overwritten by accident.
    assert main(["track", "--source", "fake", "--auto", "8", "--out", str(out)]) == 2
    assert "holds a run already" in capsys.readouterr().err


def test_an_underexposed_source_is_said_with_its_gain(monkeypatch, tmp_path, estec_rig, capsys) -> None:
    fake_source(monkeypatch, estec_rig, n=4, brightness=0.25)  # brightest pixels near 57 grey
    out = tmp_path / "run"
    assert main(["track", "--source", "fake", "--auto", "8", "--out", str(out)]) == 0
    notes = [line for line in capsys.readouterr().err.splitlines() if "underexposed" in line]
    assert len(notes) == 1 and notes[0].startswith("trackmeter track: note: 4 frames underexposed") and "2.2" in notes[0]
    engine = yaml.safe_load((out / "run.yaml").read_text())["summary"]["engine"]
    assert engine["frames_gained"] == 4 and 2.2 < engine["largest_gain"] < 2.3  # 128 / 57
    fake_source(monkeypatch, estec_rig, n=4)
    assert main(["track", "--source", "fake", "--auto", "8", "--out", str(tmp_path / "normal")]) == 0
    assert "underexposed" not in capsys.readouterr().err


def test_targets_given_on_the_command_line_are_in_the_first_frames_rows(tmp_path) -> None:
    """--target acts on frame 0 (after it was processed): its rows must say so, not start at frame 1."""
    out = tmp_path / "run"
    # Two textured points of the estec mock-up in its first frame (automatic selection's picks).
    # Several pixels after one --target, as DESIGN's `[--target [ID=]U,V ...]` reads.
    assert main(["track", "--source", "sim", "--target", "280,331", "303,178", "--max-frames", "3",
                 "--case", "a", "--out", str(out)]) == 0
    rows = list(csv.DictReader((out / "targets.csv").open()))
    first = [r for r in rows if float(r["t"]) == 0.0]
    assert len(first) == 2 and all(r["state"] == "tracking" and r["z"] for r in first)
    assert (float(first[0]["u"]), float(first[0]["v"])) == (280.0, 331.0)
    states = list(csv.DictReader((out / "states.csv").open()))
    assert len(states) == 3 and [r["n_tracked"] for r in states] == ["2", "2", "2"]


def test_source_failing_mid_run_keeps_what_was_written(monkeypatch, tmp_path, estec_rig, capsys) -> None:
    fake_source(monkeypatch, estec_rig, n=10, fail_after=4)
    out = tmp_path / "run"
    assert main(["track", "--source", "fake", "--auto", "8", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "camera unplugged" in err
    assert len(read_motion_csv(out / "states.csv")) == 4
    meta = yaml.safe_load((out / "run.yaml").read_text())
    assert meta["status"] == "source failed" and meta["summary"]["frames"] == 4


def test_a_source_that_delivers_no_frame_is_one_line_not_a_hang(monkeypatch, tmp_path, estec_rig, capsys) -> None:
    # All images unreadable, an empty video: --auto and --target wait for a first frame that
    # never comes; the run must still end, with one line and exit code 2.
    fake_source(monkeypatch, estec_rig, n=0)
    out = tmp_path / "run"
    assert main(["track", "--source", "fake", "--auto", "4", "--target", "10,10", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "delivered no frame" in err and len(err.strip().splitlines()) == 1
    assert yaml.safe_load((out / "run.yaml").read_text())["status"] == "no frame"


def test_when_every_target_is_refused_and_nothing_else_can_start_one_the_run_ends_at_once(
        monkeypatch, tmp_path, estec_rig, capsys) -> None:
    """--target pixels the tracker refuses on frame 0 (here too near the border for a patch),
    without --auto: nothing could ever be tracked, so the run stops there rather than playing
    the whole source for nothing — each refusal said, one line why it stopped, exit code 2,
    and the run directory complete for the frames it holds."""
    fake_source(monkeypatch, estec_rig, n=500)
    out = tmp_path / "run"
    code = main(["track", "--source", "fake", "--target", "1,1", "--target", "5,-0.4", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2, err
    lines = err.strip().splitlines()
    assert sum("refused at (1.0, 1.0): patch not inside image" in line for line in lines) == 1, err
    assert sum("refused at (5.0, -0.4): patch not inside image" in line for line in lines) == 1, err
    assert "nothing to track: every --target was refused" in lines[-1], err
    meta = yaml.safe_load((out / "run.yaml").read_text())
    assert meta["status"] == "nothing to track"
    frames = meta["summary"]["frames"]
    assert 1 <= frames < 50 and len(read_motion_csv(out / "states.csv")) == frames


@pytest.mark.parametrize("pixel", ["{w},10", "100000,5", "5,-300", "-0.6,3", "p1=5,{h}", "{w1}.5001,10",
                                   "p2=3,-0.50001"])
def test_a_target_off_the_image_is_one_line_before_the_run(monkeypatch, tmp_path, estec_rig, capsys,
                                                             pixel) -> None:
    """A pixel off the image is a slip in typing it: one error line (exit 2) once the rig gives
    the image's size, no run folder, and not the case's note or a refusal before it (it was
    refused after the first frame, with two lines before the error; a README walk-through)."""
    fake_source(monkeypatch, estec_rig, n=50)
    width, height = estec_rig.image_size
    pixel = pixel.format(w=width, h=height, w1=width - 1)  # past the last column or row
    out = tmp_path / "run"
    code = main(["track", "--source", "fake", f"--target={pixel}", "--target", "280,331", "--out", str(out)])
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2, lines
    assert lines == [f"trackmeter track: error: --target {pixel}: outside the {width}x{height} image "
                     f"(U from -0.5 to {width - 0.5:g}, V from -0.5 to {height - 0.5:g}: pixel centres are whole "
                     "numbers, 0 the first)"], lines
    assert not out.exists()


def test_select_model_points_alone_is_something_to_track_unless_the_source_has_no_truth(
        monkeypatch, tmp_path, estec_rig, capsys) -> None:
    """--select-model-points starts targets by itself (no --target or --auto needed); on a
    source without ground truth it never can, so the run stops at once and says why."""
    fake_source(monkeypatch, estec_rig, n=500)  # its frames carry no truth
    model = _model(tmp_path, THREE_POINTS)
    out = tmp_path / "run"
    code = main(["track", "--source", "fake", "--model", str(model), "--case", "b", "--select-model-points",
                 "--out", str(out)])
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2, lines
    assert "nothing to track" in lines[-1] and "ground truth" in lines[-1], lines
    meta = yaml.safe_load((out / "run.yaml").read_text())
    assert meta["status"] == "nothing to track" and meta["summary"]["frames"] < 50
    # A source whose truth starts later (a recording's ground truth may begin after frame 0):
    # the repeating selection may still succeed, so the run goes on.
    monkeypatch.setattr(TextureSource, "has_truth", True, raising=False)
    fake_source(monkeypatch, estec_rig, n=20)
    out = tmp_path / "run2"
    capsys.readouterr()
    main(["track", "--source", "fake", "--model", str(model), "--case", "b", "--select-model-points", "--out", str(out)])
    meta = yaml.safe_load((out / "run.yaml").read_text())
    assert meta["status"] == "complete" and meta["summary"]["frames"] == 20
    # ... and says so, not that the selection needs what the source has
    err = capsys.readouterr().err
    assert "--select-model-points: the first frame has no ground truth: the model points are selected " \
           "at the first frame that has it" in err and "needs a frame with ground truth" not in err, err
    # ... and, none of the run's frames having any (its truth starting after them), says that
    # no model point was selected at all (the run ended on the note alone: a probe)
    assert "warning: --select-model-points: no frame of the run had ground truth: no model point was selected" \
           in err, err
    # run.yaml says how its targets came (it held "targets: []" and nothing else; an outside probe)
    assert meta["source"]["select_model_points"] is True and meta["source"]["targets"] == []


def test_a_refused_target_is_said_while_the_run_goes_on_with_the_others(tmp_path, capsys) -> None:
    out = tmp_path / "run"
    # 280,331: a textured point of the estec mock-up in its first frame (as above).
    assert main(["track", "--source", "sim", "--target", "1,1", "--target", "280,331", "--max-frames", "4",
                 "--case", "a", "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert sum("refused at (1.0, 1.0): patch not inside image" in line for line in err.splitlines()) == 1, err
    meta = yaml.safe_load((out / "run.yaml").read_text())
    assert meta["status"] == "complete" and meta["summary"]["frames"] == 4


def test_a_target_put_on_a_corner_near_the_pixel_given_is_said(tmp_path, capsys) -> None:
    # 434,84 on estec's first frame: refused where it is (disparity too uncertain), trackable
    # 3.2 px away (tracker.click_snap_px); the run tracks it, and says where it was put.
    out = tmp_path / "run"
    assert main(["track", "--source", "sim", "--target", "434,84", "--max-frames", "2", "--case", "a",
                 "--out", str(out)]) == 0
    notes = [line for line in capsys.readouterr().err.splitlines() if "--target 434,84" in line]
    assert len(notes) == 1 and notes[0].startswith("trackmeter track: note: --target 434,84: target p1 at "), notes
    assert "px to a trackable corner (where asked: " in notes[0]


def test_max_frames(monkeypatch, tmp_path, estec_rig) -> None:
    fake_source(monkeypatch, estec_rig, n=10)
    out = tmp_path / "run"
    assert main(["track", "--source", "fake", "--auto", "4", "--max-frames", "3", "--out", str(out)]) == 0
    assert len(read_motion_csv(out / "states.csv")) == 3


def test_max_frames_wrapper_delegates_what_only_some_sources_have(estec_rig) -> None:
    """``--max-frames`` wraps the source: what the pipeline asks of some sources only (a
    sequence's model, a camera's warning, resume after a pause) is the wrapped source's."""
    from trackmeter.cli.track import _Limited

    source = TextureSource(estec_rig, n=10)
    source.warning = "a camera's note"
    source.resume = lambda: "resumed"
    limited = _Limited(source, 2)
    assert limited.model is None and limited.warning == "a camera's note" and limited.resume() == "resumed"
    assert [limited.read() is not None for _ in range(3)] == [True, True, False]
    with pytest.raises(AttributeError):
        limited.no_such_thing  # noqa: B018 - what the source itself would raise
    assert copy.copy(limited).model is None  # copied before __init__ ran: no recursion on _source
    source.__deepcopy__ = lambda memo: source  # dunders are the wrapper's: a deep copy keeps the limit
    assert isinstance(copy.deepcopy(limited), _Limited)


def _model(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "model.yaml"
    path.write_text(text)
    return path


@pytest.mark.parametrize(
    ("model_text", "extra", "message"),
    [
        ("points:\n- {id: a, xyz: [0, 0, 0]}\n- {id: b, xyz: [1, 0, 0]}\n", [], "at least 3 points"),
        ("points:\n- {id: a, xyz: [0, 0, 0]}\n- {id: a, xyz: [1, 0, 0]}\n- {id: c, xyz: [0, 1, 0]}\n", [], "twice"),
        # no attitude about their line: case (b)'s pose is undefined
        ("points:\n- {id: a, xyz: [0, 0, 0]}\n- {id: b, xyz: [1, 0, 0]}\n- {id: c, xyz: [2, 0, 0]}\n", [], "collinear"),
        ("points:\n- {id: a, xyz: [1, 2, 3]}\n- {id: b, xyz: [1, 2, 3]}\n- {id: c, xyz: [1, 2, 3]}\n", [], "collinear"),
        # 0.1 mm off a 0.2 m line: the attitude about it is the noise's
        ("points:\n- {id: a, xyz: [0, 0, 0]}\n- {id: b, xyz: [0.2, 0, 0]}\n- {id: c, xyz: [0.1, 0.0001, 0]}\n", [],
         "collinear"),
        ("points:\n- {id: a, xyz: [0, 0, 0]}\n- {id: b, xyz: [1, 0, 0]}\n- {id: c, xyz: [0, 1, 0]}\n",
         ["--target", "zz=100,100"], "'zz' is not in the model"),
    ],
)
def test_bad_models_and_targets(monkeypatch, tmp_path, estec_rig, capsys, model_text, extra, message) -> None:
    fake_source(monkeypatch, estec_rig)
    model = _model(tmp_path, model_text)
    code = main(["track", "--source", "fake", "--model", str(model), "--case", "b", "--auto", "4", *extra,
                 "--out", str(tmp_path / "run")])
    err = capsys.readouterr().err
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "run").exists()


def test_bad_arguments(monkeypatch, tmp_path, estec_rig, capsys) -> None:
    fake_source(monkeypatch, estec_rig)
    assert main(["track", "--source", "fake", "--out", str(tmp_path / "r")]) == 2
    assert "nothing to track" in capsys.readouterr().err
    assert main(["track", "--source", "fake", "--case", "b", "--auto", "4", "--out", str(tmp_path / "r")]) == 2
    assert "needs a model" in capsys.readouterr().err
    assert main(["track", "--source", "fake", "--target", "1,x", "--out", str(tmp_path / "r")]) == 2
    assert "U,V" in capsys.readouterr().err
    assert main(["track", "--source", "fake", "--target", "a=nan,5", "--out", str(tmp_path / "r")]) == 2
    assert "finite" in capsys.readouterr().err


def test_a_search_range_empty_on_the_source_s_rig_is_one_line_before_the_run(monkeypatch, tmp_path, estec_rig,
                                                                            capsys) -> None:
    # measure.min_disparity_px 400 on a rig whose search reaches 326 px (min_range_m's): the run
    # went on, every frame "tracking failed", and ended exit 0 with no pose (a re-check).
    fake_source(monkeypatch, estec_rig)
    config = tmp_path / "c.yaml"
    config.write_text("measure:\n  min_disparity_px: 400\n")
    code = main(["track", "--config", str(config), "--source", "fake", "--auto", "4", "--out", str(tmp_path / "r")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert err[0].startswith("trackmeter track: error: min_disparity_px (400) must be below the largest disparity "
                             "searched, 326.5 px on this rig"), err
    assert not (tmp_path / "r").exists()


def test_a_bad_out_or_auto_is_refused_before_the_source_is_opened(monkeypatch, tmp_path, capsys) -> None:
    # Opening a source can print notes (a model it carries, frames it skipped): a bad --out
    # or --auto must be the one line the user sees, and no folder may be made.
    import trackmeter.sources as sources

    def never(*args, **kwargs):  # type: ignore[no-untyped-def]
        raise AssertionError("the source was opened")

    monkeypatch.setattr(sources, "open_source", never)
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    used = tmp_path / "used"
    used.mkdir()
    (used / "run.yaml").write_text("status: complete\n")
    sequence = tmp_path / "seq"  # a recording: its folder is no place for a run's files
    for cam in ("cam0", "cam1"):
        (sequence / cam).mkdir(parents=True)
        (sequence / cam / "data.csv").write_text("#timestamp [ns],filename\n")
    for extra, message in ((["--auto", "4", "--out", str(a_file)], "not a folder"),
                           (["--auto", "4", "--out", str(sequence)], "a sequence folder"),
                           (["--auto", "4", "--out", str(sequence / "cam0" / "data")], "inside a sequence's cam0/"),
                           (["--auto", "4", "--out", str(used)], "holds a run already"),
                           (["--auto", "4", "--out", str(a_file / "sub")], "not a writable folder"),
                           (["--auto", "33", "--out", str(tmp_path / "r")], "--auto must be in [1, 32]")):
        assert main(["track", "--source", "fake", *extra]) == 2
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "r").exists()


def test_unknown_source_is_one_line(tmp_path, capsys) -> None:
    assert main(["track", "--source", "nope:1", "--auto", "4", "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert "unknown source" in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("signals", [("SIGTERM",), ("SIGTERM", "SIGTERM", "SIGINT"), ("SIGHUP", "SIGTERM")])
def test_sigterm_ends_a_run_as_ctrl_c_does(tmp_path, signals) -> None:
    # A service manager stops a run with SIGTERM: the files must be complete, as after Ctrl-C,
    # also when the signal comes again while the run winds down (a wrapper passing it on).
    # A closed terminal or a dropped ssh session (SIGHUP) ends it the same way.
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "trackmeter.cli.main", "track", "--source", "sim", "--auto", "4",
                             "--out", str(out)], stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while not (out / "states.csv").exists() or len((out / "states.csv").read_text().splitlines()) < 4:
            assert proc.poll() is None and time.monotonic() < deadline, "track ended or never wrote a frame"
            time.sleep(0.2)
        for name in signals:
            proc.send_signal(getattr(signal, name))
            time.sleep(0.01)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 130, err
    assert "interrupted after" in err and "are complete" in err
    assert [line for line in err.splitlines() if "interrupted" in line] == [  # one line, not two
        f"trackmeter track: interrupted after {len(read_motion_csv(out / 'states.csv'))} frames; files in {out} are complete"]
    meta = yaml.safe_load((out / "run.yaml").read_text())
    assert meta["status"] == "interrupted"
    assert len(read_motion_csv(out / "states.csv")) == meta["summary"]["frames"] >= 3


#: ``python -c`` this, then ``FILE`` and the command's arguments: the command line, with every
#: thread's stack written to FILE on SIGUSR1 (a hung child's terminal is gone, so not there),
#: and SIGHUP's default action, as a shell on a terminal starts a command: run under ``nohup``,
#: pytest passes on SIGHUP ignored, which the command rightly leaves ignored (it ran on, found
#: by the stacks).
_WITH_STACK_DUMP = (
    "import faulthandler, signal, sys\n"
    "signal.signal(signal.SIGHUP, signal.SIG_DFL)\n"
    "dump = open(sys.argv.pop(1), 'w')\n"
    "faulthandler.register(signal.SIGUSR1, file=dump, all_threads=True)\n"
    "from trackmeter.cli.main import main\n"
    "sys.exit(main())\n"
)


def test_a_run_whose_terminal_closed_stops_cleanly(tmp_path) -> None:
    # An ssh session drops: the terminal goes away (writes to it fail) and SIGHUP comes. The
    # run must complete its files and exit as interrupted, its last lines lost, not an error.
    import os
    import pty
    import signal
    import subprocess
    import sys
    import threading
    import time

    out = tmp_path / "run"
    stacks = tmp_path / "stacks.txt"  # where the run's threads are dumped if it does not stop
    terminal, its_other_end = pty.openpty()
    proc = subprocess.Popen([sys.executable, "-c", _WITH_STACK_DUMP, str(stacks), "track", "--source", "sim", "--auto", "4",
                             "--out", str(out)], stdin=its_other_end, stdout=its_other_end, stderr=its_other_end,
                            start_new_session=True)
    os.close(its_other_end)
    shown: list[bytes] = []

    def read_the_terminal() -> None:  # a terminal reads what it is given, or the run would block on it
        with contextlib.suppress(OSError):
            while chunk := os.read(terminal, 4096):
                shown.append(chunk)

    reader = threading.Thread(target=read_the_terminal, daemon=True)
    reader.start()
    try:
        deadline = time.monotonic() + 120
        while not (out / "states.csv").exists() or len((out / "states.csv").read_text().splitlines()) < 4:
            assert proc.poll() is None and time.monotonic() < deadline, b"".join(shown).decode(errors="replace")
            time.sleep(0.2)
        os.close(terminal)
        proc.send_signal(signal.SIGHUP)
        try:
            code = proc.wait(timeout=60)
        except subprocess.TimeoutExpired:  # say where it hangs: every thread's stack
            proc.send_signal(signal.SIGUSR1)
            time.sleep(2)
            pytest.fail("no exit 60 s after the hang-up; its threads:\n" + stacks.read_text(errors="replace"))
        assert code == 130
    finally:
        proc.kill()
    meta = yaml.safe_load((out / "run.yaml").read_text())
    assert meta["status"] == "interrupted"
    assert len(read_motion_csv(out / "states.csv")) == meta["summary"]["frames"] >= 3


def test_a_run_under_nohup_keeps_ignoring_sighup(tmp_path) -> None:
    # nohup starts a command with SIGHUP ignored so that it outlives its terminal: the stop
    # handler must not take that over.
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "trackmeter.cli.main", "track", "--source", "sim", "--auto", "4",
                             "--out", str(out)], stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGHUP, signal.SIG_IGN))
    try:
        deadline = time.monotonic() + 120

        def frames_written() -> int:
            return len((out / "states.csv").read_text().splitlines()) if (out / "states.csv").exists() else 0

        while frames_written() < 4:
            assert proc.poll() is None and time.monotonic() < deadline, "track ended or never wrote a frame"
            time.sleep(0.2)
        proc.send_signal(signal.SIGHUP)
        after_hup = frames_written()
        while frames_written() < after_hup + 5:
            assert proc.poll() is None and time.monotonic() < deadline, "SIGHUP stopped a run started under nohup"
            time.sleep(0.2)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 130 and "interrupted after" in err, err


# --------------------------------------------------------------------------- rig and frame size


@pytest.fixture(scope="module")
def sequence_with_wrong_rig(opencv_sample_sequence: Path, estec_rig, tmp_path_factory) -> Path:
    """OpenCV's 640x480 sample pairs in a sequence folder whose rig.yaml is the 726x512 estec rig."""
    from trackmeter.data.sequence import SequenceWriter
    from trackmeter.sources import open_source

    folder = tmp_path_factory.mktemp("wrong_rig") / "seq"
    with open_source(f"seq:{opencv_sample_sequence}") as source, SequenceWriter(folder, rig=estec_rig) as writer:
        while (frame := source.read()) is not None:
            writer.write(frame)
    return folder


def test_an_opencv_pair_rig_takes_the_size_of_the_source_frames(opencv_sample_rig, opencv_sample_sequence,
                                                                 tmp_path, capsys) -> None:
    out = tmp_path / "run"
    code = main(["track", "--source", f"seq:{opencv_sample_sequence}", "--rig", str(opencv_sample_rig / "intrinsics.yml"),
                 "--auto", "4", "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    meta = yaml.safe_load((out / "run.yaml").read_text())
    assert meta["status"] == "complete" and meta["summary"]["frames"] == 3
    assert len(read_motion_csv(out / "states.csv")) == 3
    # run.yaml names the rig file as given (it said "intrinsics", the file's stem)
    assert meta["source"]["rig"] == str(opencv_sample_rig / "intrinsics.yml")


def test_run_yaml_says_the_rig_came_with_the_source(opencv_sample_rig, opencv_sample_sequence, tmp_path, capsys) -> None:
    import shutil

    folder = tmp_path / "seq"
    shutil.copytree(opencv_sample_sequence, folder)
    for name in ("intrinsics.yml", "extrinsics.yml"):
        shutil.copy(opencv_sample_rig / name, folder / name)
    out = tmp_path / "run"
    code = main(["track", "--source", f"seq:{folder}", "--auto", "4", "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    # its file: a folder with both DIR/rig.yaml and DIR/mav0/rig.yaml said only which was not
    # used by its silence (an outside probe)
    assert yaml.safe_load((out / "run.yaml").read_text())["source"]["rig"] == f"the source's ({folder / 'intrinsics.yml'})"


def test_a_rate_from_nanosecond_timestamps_is_written_as_the_rate_it_is(opencv_sample_rig, shared_data, tmp_path,
                                                                      capsys) -> None:
    """50 frames at 25 Hz have a median interval that computes as 24.99999999999998 Hz: the
    source's rate is the mean regular interval to the nanosecond, 25 Hz, and run.yaml says so."""
    from trackmeter.data.images import read_grey
    from trackmeter.data.sequence import SequenceWriter
    from trackmeter.sources.base import StereoFrame
    from trackmeter.sources.sequence import SequenceSource

    left, right = (read_grey(shared_data / "stereo_calib_opencv" / f"{side}01.jpg") for side in ("left", "right"))
    with SequenceWriter(tmp_path / "seq") as writer:
        for i in range(50):
            writer.write(StereoFrame(i, 100.0 + i / 25.0, left, right))
    assert SequenceSource(tmp_path / "seq").rate_hz == 25.0
    out = tmp_path / "run"
    code = main(["track", "--source", str(tmp_path / "seq"), "--rig", str(opencv_sample_rig / "intrinsics.yml"),
                 "--auto", "4", "--max-frames", "2", "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    assert "rate_hz: 25.0\n" in (out / "run.yaml").read_text()


def test_an_image_unreadable_mid_sequence_is_reported_at_the_end_and_in_run_yaml(opencv_sample_rig, opencv_sample_sequence,
                                                                                   tmp_path, capsys) -> None:
    import shutil

    folder = tmp_path / "seq"
    shutil.copytree(opencv_sample_sequence, folder)
    broken = sorted((folder / "cam1" / "data").iterdir())[1]
    broken.write_bytes(b"not an image")  # found at open (the file exists), unreadable at play
    out = tmp_path / "run"
    code = main(["track", "--source", f"seq:{folder}", "--rig", str(opencv_sample_rig / "intrinsics.yml"),
                 "--auto", "4", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 0, err
    warning = [line for line in err.splitlines() if "warning" in line]
    assert len(warning) == 1 and "unreadable" in warning[0] and broken.name in warning[0]
    meta = yaml.safe_load((out / "run.yaml").read_text())
    assert meta["summary"]["frames"] == 2 and "unreadable" in meta["summary"]["source_warning"]


def test_a_source_failing_mid_run_is_said_once(estec_rig, tmp_path) -> None:
    """As a user runs it (a process of its own, logging as it is by default): the failure is
    one line of track's, not also the pipeline's log line; the frames before it are kept."""
    import subprocess
    import sys

    out = tmp_path / "run"
    code = f"""
import trackmeter.sources as sources
from trackmeter.cli.main import main
from trackmeter.data.rigfile import load_rig
from tests.test_track_cli import TextureSource
rig = load_rig({str(REPO / "config" / "rigs" / "estec_12mm.yaml")!r})
sources.open_source = lambda spec, rig_override=None, **_: TextureSource(rig, n=10, fail_after=2)
raise SystemExit(main(["track", "--source", "fake", "--auto", "4", "--out", {str(out)!r}]))
"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=REPO)
    assert done.returncode == 2, done.stderr
    said = [line for line in done.stderr.splitlines() if "camera unplugged" in line]
    assert len(said) == 1 and said[0].startswith("trackmeter track: source stopped: source failed:"), done.stderr
    assert yaml.safe_load((out / "run.yaml").read_text())["status"] == "source failed"
    assert len(read_motion_csv(out / "states.csv")) == 2


def test_a_pair_of_another_size_mid_sequence_is_skipped_and_said_once(opencv_sample_rig, opencv_sample_sequence,
                                                                      tmp_path) -> None:
    """Another camera's frame (or a truncated one) in a recording: skipped and named at the
    end, the run goes on and completes (it ended the run with 'source failed' before)."""
    import shutil
    import subprocess
    import sys

    import cv2

    folder = tmp_path / "seq"
    shutil.copytree(opencv_sample_sequence, folder)
    for cam in ("cam0", "cam1"):
        second = sorted((folder / cam / "data").iterdir())[1]
        cv2.imwrite(str(second), cv2.resize(cv2.imread(str(second)), (320, 240)))  # another camera's frame
    out = tmp_path / "run"
    done = subprocess.run([sys.executable, "-m", "trackmeter.cli.main", "track", "--source", f"seq:{folder}",
                           "--rig", str(opencv_sample_rig / "intrinsics.yml"), "--auto", "4", "--out", str(out)],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    said = [line for line in done.stderr.splitlines() if "320x240" in line]
    assert len(said) == 1 and said[0].startswith("trackmeter track: warning: 1 pair(s) of another image size skipped"), done.stderr
    meta = yaml.safe_load((out / "run.yaml").read_text())
    assert meta["status"] == "complete" and "another image size" in meta["summary"]["source_warning"]
    assert len(read_motion_csv(out / "states.csv")) == 2  # the folder's 3 pairs but the skipped one


@pytest.mark.parametrize("rig_from", ["--rig", "rig.yaml"])
@pytest.mark.parametrize("targets", [["--auto", "4"], ["--target", "100,100"]])
def test_frames_that_do_not_match_the_rig_are_refused_before_the_run(opencv_sample_sequence, sequence_with_wrong_rig,
                                                                     tmp_path, capsys, rig_from, targets) -> None:
    if rig_from == "--rig":
        source, rig = [f"seq:{opencv_sample_sequence}"], ["--rig", str(REPO / "config" / "rigs" / "estec_12mm.yaml")]
    else:
        source, rig = [str(sequence_with_wrong_rig)], []
    out = tmp_path / "run"
    code = main(["track", "--source", *source, *rig, *targets, "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert "frame 640x480 does not match the rig's image size 726x512" in err[0]
    assert ("estec_12mm.yaml" if rig_from == "--rig" else "give the right one with --rig") in err[0]
    assert not out.exists()  # nothing misleading written


# --------------------------------------------------------------------------- model case


THREE_POINTS = "points:\n- {id: a, xyz: [0, 0, 0]}\n- {id: b, xyz: [0.1, 0, 0]}\n- {id: c, xyz: [0, 0.1, 0]}\n"


def test_a_broken_rig_or_model_in_the_folder_stops_nothing_the_user_replaced(opencv_sample_rig, opencv_sample_sequence,
                                                                            tmp_path, capsys) -> None:
    """DESIGN.md section 6: the folder's rig.yaml is used unless --rig is given, its model.yaml
    for case (b) unless --model is given; a broken one the user replaced (or case a, which
    needs none, also when (a) is the default because no target is bound) must not stop the
    run, and one that would be used is still one clear line."""
    import shutil

    folder = tmp_path / "seq"
    shutil.copytree(opencv_sample_sequence, folder)
    (folder / "rig.yaml").write_text("%YAML:1.0\n---\nimage_width: 640\n")
    (folder / "model.yaml").write_text("points: [oops\n")
    (tmp_path / "model.yaml").write_text(THREE_POINTS)
    rig = ["--rig", str(opencv_sample_rig / "intrinsics.yml")]
    for k, extra in enumerate([["--model", str(tmp_path / "model.yaml")], ["--case", "a"]]):
        out = tmp_path / f"run{k}"
        code = main(["track", "--source", f"seq:{folder}", *rig, *extra, "--auto", "4", "--out", str(out)])
        assert code == 0, capsys.readouterr().err
        assert yaml.safe_load((out / "run.yaml").read_text())["status"] == "complete"
    capsys.readouterr()
    # The default case with no target bound to a model point is (a): the model is not needed.
    out = tmp_path / "run_default"
    assert main(["track", "--source", f"seq:{folder}", *rig, "--auto", "4", "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "model.yaml" in err and "malformed YAML" in err and "model not used" in err and "Traceback" not in err
    meta = yaml.safe_load((out / "run.yaml").read_text())
    assert meta["status"] == "complete" and meta["source"]["case"] == "a"
    for k, args in enumerate([[*rig, "--case", "b"], [*rig, "--target", "p1=300,200"],
                              ["--model", str(tmp_path / "model.yaml")]]):
        code = main(["track", "--source", f"seq:{folder}", *args, "--auto", "4", "--out", str(tmp_path / f"bad{k}")])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(err) == 1 and ("model.yaml" if k < 2 else "rig.yaml") in err[0], err
        assert not (tmp_path / f"bad{k}").exists()


def test_case_help_says_when_b_is_chosen(capsys) -> None:
    with pytest.raises(SystemExit):
        main(["track", "--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    assert "--target ID=U,V or --select-model-points" in help_text


@pytest.mark.parametrize("model_from", ["--model", "source"])
def test_a_model_without_bound_targets_runs_case_a_and_says_so(monkeypatch, tmp_path, estec_rig, capsys,
                                                              model_from) -> None:
    import trackmeter.sources as sources
    from trackmeter.data.model import load_model

    model_path = _model(tmp_path, THREE_POINTS)

    def open_fake(spec, rig_override=None, realtime=False, loop=False, **_):  # type: ignore[no-untyped-def]
        source = TextureSource(rig_override or estec_rig, n=3)
        source.model = load_model(model_path) if model_from == "source" else None
        return source

    monkeypatch.setattr(sources, "open_source", open_fake)
    extra = ["--model", str(model_path)] if model_from == "--model" else []
    out = tmp_path / "run"
    assert main(["track", "--source", "fake", *extra, "--auto", "4", "--out", str(out)]) == 0
    # (the fake source's one image in both cameras gives --auto nothing: that is said too, and
    # the one image, once)
    captured = capsys.readouterr().err
    assert captured.count(SAME_IMAGE) == 1, captured
    err = [line for line in _other_lines(captured) if "--auto started no target" not in line]
    assert len(err) == 1 and "case (a)" in err[0], err
    assert "--target ID=U,V" in err[0] and "--select-model-points" in err[0] and "--case b" in err[0]
    meta = yaml.safe_load((out / "run.yaml").read_text())["source"]
    assert meta["case"] == "a" and meta["model"] is None  # no model was used
    assert meta["model_available"] == (str(model_path) if model_from == "--model" else "source")
    assert "no target bound" in meta["case_reason"]

    # A target bound to a model point: case (b) with that model, and no note.
    out = tmp_path / "run_b"
    assert main(["track", "--source", "fake", *extra, "--target", "a=100,100", "--auto", "4", "--out", str(out)]) == 0
    assert "case (a)" not in capsys.readouterr().err
    meta = yaml.safe_load((out / "run.yaml").read_text())["source"]
    assert meta["case"] == "b" and meta["model"] == (str(model_path) if model_from == "--model" else "source")


def test_the_first_frame_is_summarised_as_the_frame_its_targets_start_on(tmp_path, capsys) -> None:
    # The commands act on frame 0 after its pose was estimated, so its own reason ("none is a
    # target yet: target them by id") would ask for what --select-model-points did next.
    out = tmp_path / "run"
    assert main(["track", "--source", "sim", "--select-model-points", "--case", "b", "--max-frames", "3",
                 "--out", str(out)]) == 0
    summary = capsys.readouterr().out
    assert "target them by id" not in summary
    assert "invalid in 1 frame: the first frame (the targets set on it are tracked from the next frame)" in summary
    reasons = yaml.safe_load((out / "run.yaml").read_text())["summary"]["invalid_reasons"]
    assert not any("target them by id" in r for r in reasons)
    # The 2 valid poses have no rates yet (states.csv valid 0): the line says so, not only "2 valid".
    states = read_motion_csv(out / "states.csv")
    pending = int(np.sum(~states.valid & np.isfinite(states.position_m[:, 0])))
    assert pending == 2 and f"2 valid poses, {pending} of them before the rates were known" in summary


def test_a_refusal_is_said_with_the_option_it_came_from(tmp_path, capsys) -> None:
    out = tmp_path / "run"
    assert main(["track", "--source", "sim", "--target", "p1=1,1", "--target", "280,331", "--max-frames", "2",
                 "--case", "a", "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "warning: --target p1=1,1: refused at (1.0, 1.0)" in err, err
    assert "SelectPoint" not in err


def test_a_disk_that_fills_stops_the_run_with_whole_rows_and_says_so(monkeypatch, tmp_path, estec_rig, capsys,
                                                                     full_disk) -> None:
    """A full disk used to print a traceback per frame, leave half rows that evaluate refused
    and run.yaml at "running"; now the run stops at the first frame that does not fit."""
    import trackmeter.data.rundir as rundir

    fake_source(monkeypatch, estec_rig, n=40)
    out = tmp_path / "run"
    disk = full_disk(900)  # the headers and about 20 rows

    class HeldOnTheDisk(rundir.SpaceReserve):  # the run's reserve for run.yaml comes on top
        def __init__(self, path, size: int, purpose: str) -> None:  # type: ignore[no-untyped-def]
            disk.free += size
            super().__init__(path, size, purpose)

    monkeypatch.setattr(rundir, "SpaceReserve", HeldOnTheDisk)
    assert main(["track", "--source", "fake", "--auto", "8", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert len(_other_lines(err)) == 1, err
    assert "targets.csv: cannot write (No space left on device): run stopped; run.yaml says so" in err or \
        "states.csv: cannot write (No space left on device): run stopped; run.yaml says so" in err, err
    meta = yaml.safe_load((out / "run.yaml").read_text())
    frames = meta["summary"]["frames"]
    assert meta["status"] == "write failed" and 0 < frames < 40
    assert len(read_motion_csv(out / "states.csv")) == frames
    tum = [line for line in (out / "trajectory.tum").read_text().splitlines() if not line.startswith("#")]
    assert len(tum) == meta["summary"]["valid_frames"]


def test_a_run_folder_removed_mid_run_stops_the_run_and_says_the_rows_are_lost(monkeypatch, tmp_path, estec_rig,
                                                                              capsys) -> None:
    """The run went on into the deleted folder, printed "-> RUN" and exited 0 with a new RUN
    holding only a run.yaml that said "complete"."""
    import shutil

    import trackmeter.data.rundir as rundir

    fake_source(monkeypatch, estec_rig, n=40)
    out = tmp_path / "run"
    write_frame = rundir.RunWriter.write_frame

    def remove_at_frame_10(self, *args, **kwargs):  # type: ignore[no-untyped-def]
        if self.frames == 10 and out.exists():
            shutil.rmtree(out)
        return write_frame(self, *args, **kwargs)

    monkeypatch.setattr(rundir.RunWriter, "write_frame", remove_at_frame_10)
    assert main(["track", "--source", "fake", "--auto", "8", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert len(_other_lines(err)) == 1, err
    assert "the run folder was removed or replaced while the run wrote to it; the 10 frames written there are lost" in err
    assert "run stopped" in err and "whole in" not in err, err
    assert not out.exists()


def test_auto_that_never_starts_a_target_says_why(monkeypatch, tmp_path, estec_rig, capsys) -> None:
    """A renderer's too-dark sequence ran 'complete' with 0 valid poses and only "0 points
    tracked" as the reason: the candidates' refusals are now named. (The fake source shows the
    same image to both cameras: no candidate has a unique stereo match.)"""
    fake_source(monkeypatch, estec_rig, n=12)
    assert main(["track", "--source", "fake", "--auto", "8", "--out", str(tmp_path / "run")]) == 0
    err = capsys.readouterr().err
    assert ("trackmeter track: warning: --auto started no target: its candidates were refused: no candidate point "
            "(black space, no texture, or no unique stereo match) (") in err, err
    meta = yaml.safe_load((tmp_path / "run" / "run.yaml").read_text())
    assert meta["summary"]["tracker"]["auto_added"] == 0


def test_auto_that_starts_fewer_targets_than_asked_says_how_many_and_why(monkeypatch, tmp_path, estec_rig,
                                                                        capsys) -> None:
    """--auto 16 on small images started 1-3 targets and the run ended "waiting for 3 points"
    with no word of the shortfall, which was said only when none started (an outside probe).
    Here a 15 x 12 cm plate at 3.5 m holds room for 3 of the 8 asked."""
    import trackmeter.sources as sources
    from trackmeter.sources import plane

    scene = plane.PlaneScene(estec_rig, plane.pose_translating(3.5, (0, 0, 0)), size_m=(0.15, 0.12), n_frames=8)
    monkeypatch.setattr(sources, "open_source", lambda spec, rig_override=None, realtime=False, loop=False, **_: scene)
    assert main(["track", "--source", "plate", "--auto", "8", "--out", str(tmp_path / "run")]) == 0
    err = capsys.readouterr().err
    said = [line for line in err.splitlines() if "--auto 8" in line]
    assert len(said) == 1, err
    assert said[0].startswith("trackmeter track: warning: --auto 8: at most 3 automatic targets at once; its other "
                              "candidates were refused: "), said
    # A run that reaches the count says nothing of it.
    scene = plane.PlaneScene(estec_rig, plane.pose_translating(3.5, (0, 0, 0)), n_frames=4)
    monkeypatch.setattr(sources, "open_source", lambda spec, rig_override=None, realtime=False, loop=False, **_: scene)
    assert main(["track", "--source", "plate", "--auto", "8", "--out", str(tmp_path / "run2")]) == 0
    assert "--auto" not in capsys.readouterr().err


def test_track_says_when_the_left_and_right_images_look_swapped(monkeypatch, tmp_path, estec_sim_frames,
                                                              capsys) -> None:
    """cam0 and cam1 exchanged under a rig in order ran 'complete' with no valid pose and a
    false match at a made-up depth, and nothing said why (an outside probe)."""
    import dataclasses

    import trackmeter.sources as sources

    rig, frames = estec_sim_frames

    class Frames(Source):
        def __init__(self, swap: bool) -> None:
            self.rig, self.rate_hz, self.model = rig, 25.0, None
            self._frames = [dataclasses.replace(f, left=f.right, right=f.left, truth=None) if swap else f
                            for f in frames[:6]]

        def read(self):  # type: ignore[no-untyped-def]
            return self._frames.pop(0) if self._frames else None

    for swap in (True, False):
        monkeypatch.setattr(sources, "open_source", lambda spec, rig_override=None, realtime=False, loop=False, **_:
                            Frames(swap))
        assert main(["track", "--source", "frames", "--auto", "8", "--out", str(tmp_path / f"run{swap}")]) == 0
        said = [line for line in capsys.readouterr().err.splitlines() if "look swapped" in line]
        assert len(said) == swap, said
        if swap:
            assert said[0].startswith("trackmeter track: warning: the left and right images look swapped: "), said


def test_a_countdown_is_one_reason_in_the_summary(tmp_path, capsys, monkeypatch) -> None:
    """Case (c)'s "hold still (1.9 s left)" was counted as a reason of its own at every tenth of
    a second (23 entries in run.yaml; the five printed covered 16 of 56 invalid frames)."""
    from trackmeter.cli.track import summary_reason

    assert summary_reason("acquiring a model: hold still (1.9 s left)") == \
        summary_reason("acquiring a model: hold still (0.1 s left)") == "acquiring a model: hold still (counting down)"
    assert summary_reason("case (b): binding the model: 2 of its points located") == \
        "case (b): binding the model: 2 of its points located"
    import trackmeter.cli.track as track_cli

    monkeypatch.setattr(track_cli, "SUMMARY_REASONS", 1)  # the reasons not printed are counted
    out = tmp_path / "run"
    code = main(["track", "--source", "sim:hold_release", "--case", "c", "--auto", "16", "--max-frames", "40",
                 "--out", str(out)])
    printed = capsys.readouterr().out
    assert code == 0
    reasons = yaml.safe_load((out / "run.yaml").read_text())["summary"]["invalid_reasons"]
    countdowns = [r for r in reasons if "hold still" in r]
    assert countdowns == ["acquiring a model: hold still (counting down)"], reasons
    assert reasons[countdowns[0]] >= 20
    assert "s left" not in printed
    others = len(reasons) - 1
    rest = sum(sorted(reasons.values())[:-1])
    assert others >= 1 and f"invalid in {rest} more frame{'s' if rest != 1 else ''} for {others} other reason{'s' if others != 1 else ''}" in printed, printed


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--source", "{tmp}/no_such_folder"], "no_such_folder"),
        (["--rig", "{tmp}/no_such_rig.yaml"], "no_such_rig.yaml"),
        (["--model", "{tmp}/no_such_model.yaml", "--case", "b"], "no_such_model.yaml"),
    ],
)
def test_a_missing_input_is_named_before_nothing_to_track(tmp_path, capsys, opencv_sample_sequence,
                                                          extra, message) -> None:  # type: ignore[no-untyped-def]
    # An outside probe forgot --auto and gave a wrong path: it was told "nothing to track", and
    # only after adding --auto that the path does not exist.
    args = ["track", "--source", str(opencv_sample_sequence), *[a.format(tmp=tmp_path) for a in extra],
            "--out", str(tmp_path / "run")]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert message in err and "nothing to track" not in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "run").exists()


def test_an_interrupt_while_starting_says_nothing_was_written(monkeypatch, tmp_path, capsys) -> None:
    # The source's opening (or a model's reading, the fits' loading) takes seconds: a Ctrl-C then
    # left no folder and said only "interrupted", and the user went looking for the files.
    import trackmeter.cli.common as common

    def interrupted(*args, **kwargs):  # type: ignore[no-untyped-def]
        raise KeyboardInterrupt

    monkeypatch.setattr(common, "open_source_with_rig", interrupted)
    out = tmp_path / "run"
    assert main(["track", "--source", "sim", "--auto", "4", "--out", str(out)]) == 130
    err = capsys.readouterr().err
    assert err == f"trackmeter track: interrupted while starting; nothing was written to {out}\n"
    assert not out.exists()


def test_a_target_id_given_twice_is_refused_before_the_run(tmp_path, capsys) -> None:
    # It was a warning after the first frame and a run that went on (an outside CLI probe).
    out = tmp_path / "run"
    assert main(["track", "--source", "sim", "--target", "p1=329.5,159.8", "p1=385.1,348.6", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err == "trackmeter track: error: --target id 'p1' given twice: each target's id names one point\n"
    assert not out.exists()


def test_an_unnamed_target_does_not_take_a_name_given_later(tmp_path, capsys) -> None:
    # The unnamed target was made first and took p1, and the later p1=... was refused after
    # the first frame as "a target named 'p1' exists" (a code review).
    out = tmp_path / "run"
    assert main(["track", "--source", "sim", "--case", "a", "--target", "329.5,159.8", "p1=385.1,348.6",
                 "--max-frames", "2", "--out", str(out)]) == 0
    assert "exists" not in capsys.readouterr().err
    ids = {row["id"] for row in csv.DictReader((out / "targets.csv").open())}
    assert "p1" in ids and len(ids) == 2


def test_targets_on_a_later_first_frame_are_said_to_be_there(tmp_path, capsys) -> None:
    """The first pair unreadable, --target pixels "of the first frame" went on the second,
    t = 0.04 s, without a word (an outside probe): a target the pixel was chosen for may not
    be there then."""
    from benchmarks.measure import estec_plane
    from trackmeter.data.sequence import SequenceWriter
    from trackmeter.sources.base import StereoFrame

    rig, left, right, _ = estec_plane(seed=5)
    folder = tmp_path / "seq"
    with SequenceWriter(folder, rig=rig) as writer:
        for i in range(4):
            writer.write(StereoFrame(i, i / 25.0, left, right))
    sorted((folder / "cam0" / "data").iterdir())[0].write_bytes(b"")
    code = main(["track", "--source", str(folder), "--target", "300,250", "--out", str(tmp_path / "run")])
    err = capsys.readouterr().err
    assert code == 0, err
    assert ("note: --target: the pixels were placed on the first frame that played, t = 0.040 s; the pair(s) "
            "before it were skipped") in err, err


def test_an_overwrite_with_nothing_to_track_keeps_the_earlier_run(tmp_path, capsys, monkeypatch, estec_rig) -> None:
    """`--target 1,1 --overwrite` (refused: nothing to track) destroyed a complete earlier run
    (an outside probe); the earlier run is now kept, and the message says so."""
    fake_source(monkeypatch, estec_rig, n=12)
    out = tmp_path / "run"
    assert main(["track", "--source", "fake", "--auto", "4", "--out", str(out)]) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    capsys.readouterr()
    assert main(["track", "--source", "fake", "--target", "1,1", "--out", str(out), "--overwrite"]) == 2
    err = capsys.readouterr().err
    assert f"the earlier run in {out} is kept" in err, err
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_the_closing_source_warning_says_only_what_is_new(tmp_path) -> None:
    """A sequence warned at open (an image listed but missing) that then skips an unreadable
    pair: the closing warning repeated the opening one in front of the new skip (an outside probe)."""
    import subprocess
    import sys

    seq = tmp_path / "seq"
    assert subprocess.run([sys.executable, "-m", "trackmeter", "simulate", "--duration", "0.6", "--out", str(seq)],
                          capture_output=True, timeout=300).returncode == 0
    images = {cam: sorted((seq / cam / "data").iterdir(), key=lambda p: int(p.stem)) for cam in ("cam0", "cam1")}
    images["cam1"][3].unlink()  # listed in data.csv, missing: said at open
    images["cam0"][10].write_bytes(b"not a png")  # found when read: said at the end
    done = subprocess.run([sys.executable, "-m", "trackmeter", "track", "--source", str(seq), "--auto", "4",
                           "--out", str(tmp_path / "run")], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    warned = [line for line in done.stderr.splitlines() if line.startswith("trackmeter track: warning:")]
    assert len(warned) == 2, done.stderr
    assert "listed in data.csv are missing" in warned[0] and "unreadable" not in warned[0], warned
    assert "unreadable image skipped" in warned[1] and "listed in data.csv" not in warned[1], warned


def _compile_that_swallows_a_stop(fails: bool):  # type: ignore[no-untyped-def]
    """A warm-up as numba's compile behaves when a stop signal lands in it: the handler's
    KeyboardInterrupt raised inside a ctypes callback is reported ("Exception ignored") and
    dropped, and the compile goes on, or fails ("RuntimeError: no compiled object yet")."""

    def warm_up() -> None:
        try:
            signal.raise_signal(signal.SIGTERM)
        except KeyboardInterrupt:
            pass
        if fails:
            raise RuntimeError("no compiled object yet for <Library 'lk_translation'>")

    return warm_up


@pytest.mark.parametrize("fails", [True, False])
def test_a_stop_signal_swallowed_by_the_compile_still_stops_the_run(monkeypatch, tmp_path, capsys, fails) -> None:
    """SIGTERM while the fits compiled (a cold numba cache) gave a traceback, exit 1 and a run
    folder saying "running"; once the stop was lost, and the run went on to its end with
    exit 0 (an outside probe). Either way it is an interrupt now."""
    import trackmeter.pipeline.pipeline as pipeline_module

    monkeypatch.setattr(pipeline_module, "warm_up", _compile_that_swallows_a_stop(fails))
    before = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    out = tmp_path / "run"
    try:
        signal.signal(signal.SIGINT, signal.default_int_handler)  # a process's own, whatever earlier tests left
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        code = main(["track", "--source", "sim", "--auto", "4", "--max-frames", "50", "--out", str(out)])
    finally:
        for sig, handler in before.items():
            signal.signal(sig, handler)
    err = capsys.readouterr().err
    assert code == 130 and "Traceback" not in err, err
    assert err.strip().splitlines()[-1].startswith("trackmeter track: interrupted"), err
    if out.exists():  # no folder left saying "running"
        assert yaml.safe_load((out / "run.yaml").read_text())["status"] == "interrupted"


def test_a_run_whose_final_run_yaml_cannot_be_written_says_the_frames_are_whole(monkeypatch, tmp_path, capsys) -> None:
    """The folder made read-only (chattr +i) mid-run: all frames written, then only
    "run.yaml: cannot write (Operation not permitted)", no word of the frames (an outside
    probe). Said as a write failure at the end is elsewhere: what is whole, and where."""
    import trackmeter.data.rundir as rundir

    write_meta = rundir.RunWriter._write_meta

    def refused_at_the_end(self):  # type: ignore[no-untyped-def]
        if self._meta.get("status") != "running":
            raise TrackmeterError(f"{self.directory / 'run.yaml'}: cannot write (Operation not permitted)")
        return write_meta(self)

    monkeypatch.setattr(rundir.RunWriter, "_write_meta", refused_at_the_end)
    out = tmp_path / "run"
    assert main(["track", "--source", "sim", "--auto", "4", "--max-frames", "5", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == (f"trackmeter track: error: {out / 'run.yaml'}: cannot write (Operation not permitted): "
                       f"run.yaml could not be updated (it says running); the 5 frames are whole in {out}"), err


def test_an_overwrite_cut_short_by_a_full_disk_says_where_the_earlier_run_is(monkeypatch, tmp_path, estec_rig, capsys,
                                                                             full_disk) -> None:
    """The complete earlier run was deleted when the new one filled the disk, unsaid (an
    outside probe): it is kept, and the one line says where."""
    import trackmeter.data.rundir as rundir

    fake_source(monkeypatch, estec_rig, n=40)
    out = tmp_path / "run"
    assert main(["track", "--source", "fake", "--auto", "8", "--max-frames", "5", "--out", str(out)]) == 0
    capsys.readouterr()
    disk = full_disk(900)

    class HeldOnTheDisk(rundir.SpaceReserve):
        def __init__(self, path, size: int, purpose: str) -> None:  # type: ignore[no-untyped-def]
            disk.free += size
            super().__init__(path, size, purpose)

    monkeypatch.setattr(rundir, "SpaceReserve", HeldOnTheDisk)
    assert main(["track", "--source", "fake", "--auto", "8", "--out", str(out), "--overwrite"]) == 2
    err = capsys.readouterr().err
    assert err.strip().endswith(f"; the earlier run it was to replace is kept in {out / rundir.PREVIOUS_RUN}"), err
    assert yaml.safe_load((out / rundir.PREVIOUS_RUN / "run.yaml").read_text())["summary"]["frames"] == 5


def test_the_help_s_case_b_example_clicks_only_corners_estec_s_first_frame_shows() -> None:
    """The help's example bound bus_mxpymz=385.1,348.6, a corner behind the bus in estec's first
    frame: measured there, the bus face in front of it, 1.03 m nearer (an outside probe). Each
    example target measured at its pixel lies within 30 mm of its model point (the simulated
    operator's own test of a hidden point)."""
    import re

    from trackmeter.cli import track
    from trackmeter.core.matching import measure_points
    from trackmeter.core.transforms import apply_transform
    from trackmeter.sources import open_source

    example = re.findall(r"(\w+)=([\d.]+),([\d.]+)", track.__doc__ or "")
    assert len(example) >= 3, track.__doc__
    source = open_source("sim")
    frame = source.read()
    assert frame is not None and frame.truth is not None and source.model is not None
    where = dict(zip(source.model.ids, source.model.points_body))
    got = measure_points(source.rig, frame.left, frame.right, [(float(u), float(v)) for _, u, v in example])
    for (point_id, _, _), measured in zip(example, got):
        true_cam = apply_transform(frame.truth.T_cam_body, where[point_id])
        assert measured.ok and np.linalg.norm(measured.xyz_m - true_cam) < 0.03, (point_id, measured.xyz_m, true_cam)


def test_tracker_auto_in_a_config_starts_automatic_selection_as_in_the_console(tmp_path, capsys) -> None:
    # `tracker.auto: true` in a --config (default.yaml: "Automatic feature selection on at
    # start") was refused by track as "nothing to track: give ... --auto N", and beside a
    # --target the automatic targets ran while run.yaml said auto: null (an outside review).
    config = tmp_path / "c.yaml"
    config.write_text("tracker:\n  auto: true\nfeatures:\n  count: 5\n")
    out = tmp_path / "r"
    code = main(["track", "--config", str(config), "--source", "sim", "--max-frames", "8", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 0, err
    assert "--auto" not in err, err  # its notes name tracker.auto, not an option the user did not type
    meta = yaml.safe_load((out / "run.yaml").read_text())
    assert meta["source"]["auto"] == 5, meta["source"]
    with open(out / "targets.csv", newline="") as f:
        ids = {row["id"] for row in csv.DictReader(f)}
    assert ids and all(i.startswith("a") for i in ids), ids
    # --auto N still says how many
    code = main(["track", "--config", str(config), "--source", "sim", "--max-frames", "2", "--auto", "3", "--out", str(tmp_path / "r3")])
    assert code == 0, capsys.readouterr().err
    assert yaml.safe_load((tmp_path / "r3" / "run.yaml").read_text())["source"]["auto"] == 3
    # More than the tracker holds: capped, and said (an outside probe found it silent).
    config.write_text("tracker:\n  auto: true\nfeatures:\n  count: 40\n")
    code = main(["track", "--config", str(config), "--source", "sim", "--max-frames", "2", "--out", str(tmp_path / "r40")])
    err = capsys.readouterr().err
    assert code == 0, err
    assert "note: tracker.auto keeps 32 targets: features.count (40) is more than tracker.max_targets holds" in err, err
    assert "--auto" not in err, err  # no option the user did not type
    assert yaml.safe_load((tmp_path / "r40" / "run.yaml").read_text())["source"]["auto"] == 32
