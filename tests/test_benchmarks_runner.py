"""``python -m benchmarks`` keeps what it measured: a benchmark that fails (or a Ctrl-C) does not
cost the figures of those that finished, and a benchmark whose needs are missing (the console's
browser) is refused before any runs.

A reproduce run with the project installed without its test extra ran 20 minutes of benchmarks,
then the console benchmark's ``import playwright`` failed and no JSON was written at all."""

from __future__ import annotations

import json
import types
from pathlib import Path

import pytest

import benchmarks.__main__ as entry
from benchmarks.reproduce import Runner, Step, benchmark_rows


def _fake_benchmarks(monkeypatch: pytest.MonkeyPatch, behaviours: dict[str, object]) -> list[str]:
    """Replace the benchmark modules by ``behaviours[name]``: figures to return, an exception to
    raise, or ``("unmet", why)``. Returns the names in the order their ``run`` was called."""
    ran: list[str] = []

    def module(name: str) -> types.SimpleNamespace:
        short = name.removeprefix("benchmarks.")
        behaviour = behaviours[short]

        def run() -> object:
            ran.append(short)
            if isinstance(behaviour, BaseException):
                raise behaviour
            return behaviour

        unmet = (lambda: behaviour[1]) if isinstance(behaviour, tuple) else (lambda: None)
        return types.SimpleNamespace(run=run, unmet=unmet)

    monkeypatch.setattr(entry.importlib, "import_module", module)
    return ran


def test_a_failing_benchmark_costs_only_its_own_figures(monkeypatch: pytest.MonkeyPatch, tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    ran = _fake_benchmarks(monkeypatch, {"measure": {"point_ms_median": 1.5},
                                         "render": ModuleNotFoundError("No module named 'x'"),
                                         "select": {"select_ms_median": 40.0}})
    out = tmp_path / "bench.json"
    assert entry.main(["measure", "render", "select", "--out", str(out)]) == 1
    assert ran == ["measure", "render", "select"]
    captured = capsys.readouterr()
    want = {"measure": {"point_ms_median": 1.5}, "select": {"select_ms_median": 40.0}}
    assert json.loads(out.read_text()) == want and json.loads(captured.out) == want
    last = captured.err.strip().splitlines()[-1]
    assert last == ("python -m benchmarks: error: 1 of 3 failed: render (ModuleNotFoundError: No module named 'x') "
                    "(the others' figures are in the JSON)")
    assert "Traceback" in captured.err  # the failure's own story, for the log


def test_a_ctrl_c_keeps_the_figures_finished_before_it(monkeypatch: pytest.MonkeyPatch, tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    ran = _fake_benchmarks(monkeypatch, {"measure": {"point_ms_median": 1.5}, "render": KeyboardInterrupt(),
                                         "select": {"select_ms_median": 40.0}})
    out = tmp_path / "bench.json"
    assert entry.main(["measure", "render", "select", "--out", str(out)]) == 130
    assert ran == ["measure", "render"]
    assert json.loads(out.read_text()) == {"measure": {"point_ms_median": 1.5}}
    assert "interrupted" in capsys.readouterr().err.strip().splitlines()[-1]


def test_a_benchmark_whose_needs_are_missing_is_refused_before_any_runs(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    ran = _fake_benchmarks(monkeypatch, {"measure": {"point_ms_median": 1.5},
                                         "console": ("unmet", "Playwright (pip install -e '.[test]')")})
    out = tmp_path / "bench.json"
    assert entry.main(["measure", "console", "--out", str(out)]) == 2
    assert ran == [] and not out.exists()
    err = capsys.readouterr().err.strip()
    assert err == ("python -m benchmarks: error: console needs Playwright (pip install -e '.[test]') "
                   "(or name the benchmarks to run without it)")


def test_an_out_that_cannot_be_written_is_refused_before_any_runs(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # An outside probe: --out a folder (or under a file) ran the whole benchmark, printed its
    # figures, then lost the file to a traceback, exit 1.
    ran = _fake_benchmarks(monkeypatch, {"measure": {"point_ms_median": 1.5}})
    (tmp_path / "afile").write_text("x")
    for out, said in ((tmp_path, f"--out {tmp_path}: is a folder; give the JSON file's name, e.g. "
                                 f"{tmp_path / 'benchmarks.json'}"),
                      (tmp_path / "afile" / "new" / "b.json", f"{tmp_path / 'afile'} is a file, not a folder")):
        assert entry.main(["measure", "--out", str(out)]) == 2
        assert ran == []
        err = capsys.readouterr().err.strip()
        assert err.startswith("python -m benchmarks: error: --out ") and err.endswith(said) and "\n" not in err
    # A folder still to be made is made, as before.
    assert entry.main(["measure", "--out", str(tmp_path / "new" / "b.json")]) == 0
    assert json.loads((tmp_path / "new" / "b.json").read_text()) == {"measure": {"point_ms_median": 1.5}}


def test_a_write_that_fails_at_the_end_keeps_the_failures_line_last(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # A code review: the write's error returned before the line that names the failed
    # benchmarks, which benchmarks.reproduce reads as the last one.
    import trackmeter.data.atomic

    def full(path: object, text: str) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(trackmeter.data.atomic, "write_text_atomic", full)
    _fake_benchmarks(monkeypatch, {"measure": {"point_ms_median": 1.5}, "render": RuntimeError("boom")})
    assert entry.main(["measure", "render", "--out", str(tmp_path / "b.json")]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert "cannot write (No space left on device); the figures are above" in lines[-2]
    assert lines[-1].startswith("python -m benchmarks: error: 1 of 2 failed: render (RuntimeError: boom)")


def test_a_usage_error_is_one_line_as_the_commands_give_it(capsys: pytest.CaptureFixture[str]) -> None:
    for argv in (["measure", "--bogus"], ["--out"]):
        with pytest.raises(SystemExit) as info:
            entry.main(argv)
        assert info.value.code == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("python -m benchmarks: error: ") and err.endswith("(see --help)") and "\n" not in err


def test_the_browser_benchmarks_name_what_they_lack(monkeypatch: pytest.MonkeyPatch) -> None:
    import importlib.util
    import shutil

    import benchmarks.console as console_bench
    import benchmarks.soak as soak_bench

    real_find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name == "playwright" else real_find_spec(name, *a))
    assert "Playwright" in (console_bench.unmet() or "")
    monkeypatch.delenv("TRACKMETER_SOAK_CONSOLE", raising=False)
    assert soak_bench.unmet() is None  # the pipeline's soak needs no browser
    monkeypatch.setenv("TRACKMETER_SOAK_CONSOLE", "1")
    assert "Playwright" in (soak_bench.unmet() or "")
    monkeypatch.setattr(importlib.util, "find_spec", real_find_spec)
    monkeypatch.setattr(shutil, "which", lambda name, *a, **k: None)
    assert "apt-get install chromium" in (console_bench.unmet() or "")


def test_reproduce_shows_the_figures_of_a_benchmarks_run_that_failed_in_part(tmp_path: Path) -> None:
    out = tmp_path / "benchmarks.json"
    out.write_text(json.dumps({"measure": {"point_ms_median": 0.5}}))
    step = Step("benchmarks", ["python", "-m", "benchmarks", "measure", "tracker", "--out", str(out)],
                status="failed", reason="exit 1: python -m benchmarks: error: 1 of 2 failed: tracker (boom)")
    r = Runner(tmp_path, tmp_path)
    assert r.json_of(step) is None  # a failed step has no JSON unless the caller asks for what it wrote
    results = r.json_of(step, partial=True)
    rows = benchmark_rows(results, step, ["measure", "tracker"], [])
    assert any("| 15 ms | 0.500 ms |" in row for row in rows)
    tracker_rows = [row for row in rows if "benchmarks tracker" in row]
    assert tracker_rows and all("_failed: benchmarks — exit 1" in row for row in tracker_rows)


def test_reproduce_refuses_before_simulating_when_the_console_rows_cannot_run(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import benchmarks.reproduce as reproduce

    monkeypatch.setattr(reproduce, "browser_unmet", lambda: "Playwright (pip install -e '.[test]')")
    with pytest.raises(SystemExit) as exc:
        reproduce.main(["--out", str(tmp_path / "results"), "--no-readme"])
    assert exc.value.code == 2
    assert "the console benchmarks need Playwright" in capsys.readouterr().err
    assert not (tmp_path / "results").exists()  # nothing simulated, nothing written


def test_the_tracker_benchmark_leaves_out_rubberwhale_without_the_shared_data(monkeypatch: pytest.MonkeyPatch,
                                                                           tmp_path: Path) -> None:
    """Without ``../shared/data`` the real-image figures are left out (README), not the whole
    benchmark lost to cv2.imread's None."""
    import benchmarks.tracker as tracker

    monkeypatch.setattr(tracker, "DATA", tmp_path)
    for name in ("step_time", "drift", "max_speed", "scenario"):
        monkeypatch.setattr(tracker, name, lambda *a, name=name, **k: {f"{name}_figure": 1.0})
    figures = tracker.run()
    assert not any(k.startswith("rubberwhale") for k in figures) and figures["drift_figure"] == 1.0


def test_the_live_window_pools_its_figures_and_gives_each_sub_window_s() -> None:
    """A live rate and dropped fraction are counts over the whole window; its sub-windows'
    median and worst say how steady they were (a single window said nothing of it)."""
    import benchmarks.pipeline as pipeline

    clock = [0.0]
    # 10 s sub-windows: 250 frames read each; 0, 0, 10 and 2 of them dropped.
    counts = iter([(0, 0), (250, 0), (500, 0), (750, 10), (1000, 12)])

    class Pipe:
        def subscribe(self, callback: object) -> None:
            pass

        def latest(self) -> types.SimpleNamespace:
            read, dropped = next(counts)
            timings = types.SimpleNamespace(frames_read=read, frames_dropped=dropped, frames_processed=read - dropped)
            return types.SimpleNamespace(timings=timings)

    def sleep(seconds: float) -> None:
        clock[0] += seconds

    window = pipeline.LiveWindow(Pipe(), clock=lambda: clock[0])
    window.begin()
    window.wait(40.0, 4, sleep=sleep)
    live = window.end()
    assert live["windows"] == 4
    assert live["rate_hz"] == pytest.approx(988 / 40) and live["dropped_fraction"] == pytest.approx(12 / 1000)
    assert live["rate_hz_window_median"] == pytest.approx((24.8 + 25.0) / 2)  # of 25, 25, 24, 24.8 Hz
    assert live["rate_hz_window_min"] == pytest.approx(24.0)
    assert live["dropped_fraction_window_median"] == pytest.approx(1 / 250)
    assert live["dropped_fraction_window_max"] == pytest.approx(10 / 250)
