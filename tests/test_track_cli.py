"""trackmeter track: the run directory contract, bad input, and a source failing mid-run."""

from __future__ import annotations

import csv
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
    """Static random texture seen by the paper's rig; raises after ``fail_after`` frames."""

    def __init__(self, rig, n: int = 6, fail_after: int | None = None) -> None:
        self.rig = rig
        self.rate_hz = 25.0
        self.model = None
        self._n, self._k, self._fail = n, 0, fail_after
        rng = np.random.default_rng(0)
        w, h = rig.image_size
        self._img = (rng.random((h, w)) * 200 + 30).astype(np.uint8)

    def __len__(self) -> int:
        return self._n

    def read(self) -> StereoFrame | None:
        if self._fail is not None and self._k >= self._fail:
            raise TrackmeterError("camera unplugged")
        if self._k >= self._n:
            return None
        self._k += 1
        return StereoFrame(self._k - 1, 0.04 * (self._k - 1), self._img, self._img)


def fake_source(monkeypatch, rig, **kw) -> None:
    import trackmeter.sources as sources

    monkeypatch.setattr(sources, "open_source", lambda spec, rig_override=None, realtime=False, loop=False:
                        TextureSource(rig_override or rig, **kw))


def test_parse_target() -> None:
    assert parse_target("12.5,40") == (None, (12.5, 40.0))
    assert parse_target("bus_c0=1,2") == ("bus_c0", (1.0, 2.0))
    with pytest.raises(TrackmeterError, match="U,V"):
        parse_target("a=1")
    with pytest.raises(TrackmeterError, match="empty id"):
        parse_target("=1,2")


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


def test_source_failing_mid_run_keeps_what_was_written(monkeypatch, tmp_path, estec_rig, capsys) -> None:
    fake_source(monkeypatch, estec_rig, n=10, fail_after=4)
    out = tmp_path / "run"
    assert main(["track", "--source", "fake", "--auto", "8", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "camera unplugged" in err
    assert len(read_motion_csv(out / "states.csv")) == 4
    meta = yaml.safe_load((out / "run.yaml").read_text())
    assert meta["status"] == "source failed" and meta["summary"]["frames"] == 4


def test_max_frames(monkeypatch, tmp_path, estec_rig) -> None:
    fake_source(monkeypatch, estec_rig, n=10)
    out = tmp_path / "run"
    assert main(["track", "--source", "fake", "--auto", "4", "--max-frames", "3", "--out", str(out)]) == 0
    assert len(read_motion_csv(out / "states.csv")) == 3


def _model(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "model.yaml"
    path.write_text(text)
    return path


@pytest.mark.parametrize(
    ("model_text", "extra", "message"),
    [
        ("points:\n- {id: a, xyz: [0, 0, 0]}\n- {id: b, xyz: [1, 0, 0]}\n", [], "at least 3 points"),
        ("points:\n- {id: a, xyz: [0, 0, 0]}\n- {id: a, xyz: [1, 0, 0]}\n- {id: c, xyz: [0, 1, 0]}\n", [], "twice"),
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


def test_unknown_source_is_one_line(tmp_path, capsys) -> None:
    assert main(["track", "--source", "nope:1", "--auto", "4", "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert "unknown source" in err and len(err.strip().splitlines()) == 1


def test_sigterm_ends_a_run_as_ctrl_c_does(tmp_path) -> None:
    # A service manager stops a run with SIGTERM: the files must be complete, as after Ctrl-C.
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
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 130, err
    assert "interrupted after" in err and "are complete" in err
    meta = yaml.safe_load((out / "run.yaml").read_text())
    assert meta["status"] == "interrupted"
    assert len(read_motion_csv(out / "states.csv")) == meta["summary"]["frames"] >= 3
