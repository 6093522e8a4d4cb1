"""The benchmarks' configuration: config/default.yaml, or a YAML layered over it named by
``TRACKMETER_BENCH_CONFIG`` (how the opt-in settings of docs/results.md are measured on the same
chain), never for the README table."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks import CONFIG_ENV, bench_config
from benchmarks.reproduce import Runner
from trackmeter.data.config import Config
from trackmeter.errors import TrackmeterError

REPO = Path(__file__).resolve().parents[1]


def test_without_the_variable_the_benchmarks_run_the_defaults(monkeypatch):
    monkeypatch.delenv(CONFIG_ENV, raising=False)
    assert bench_config() == Config()
    monkeypatch.setenv(CONFIG_ENV, "")
    assert bench_config() == Config()


def test_a_named_file_is_layered_over_the_defaults(monkeypatch, tmp_path):
    f = tmp_path / "smooth.yaml"
    f.write_text("tracker:\n  track_blur_sigma_px: 0.7\npose:\n  relock_stored: true\n")
    monkeypatch.setenv(CONFIG_ENV, str(f))
    c = bench_config()
    assert c.tracker.track_blur_sigma_px == 0.7 and c.pose.relock_stored
    assert c.measure == Config().measure  # what the file does not name stays the default


def test_a_bad_file_is_refused_with_the_variable_named(monkeypatch, tmp_path):
    monkeypatch.setenv(CONFIG_ENV, str(tmp_path / "missing.yaml"))
    with pytest.raises(TrackmeterError, match=CONFIG_ENV):
        bench_config()
    bad = tmp_path / "bad.yaml"
    bad.write_text("tracker:\n  no_such_key: 1\n")
    monkeypatch.setenv(CONFIG_ENV, str(bad))
    with pytest.raises(TrackmeterError, match="no_such_key"):
        bench_config()


@pytest.mark.parametrize("argv", [["-m", "benchmarks", "accuracy"], ["-m", "benchmarks.error_budget"]])
def test_the_command_line_says_so_in_one_line_before_any_work(tmp_path, argv):
    env = {**os.environ, CONFIG_ENV: str(tmp_path / "missing.yaml")}
    proc = subprocess.run([sys.executable, *argv], cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    last = proc.stderr.strip().splitlines()[-1]
    assert "error" in last and CONFIG_ENV in last and "missing.yaml" in last
    assert "Traceback" not in proc.stderr and proc.stdout == ""


def test_the_readme_table_is_always_the_defaults(tmp_path, monkeypatch):
    monkeypatch.setenv(CONFIG_ENV, str(tmp_path / "opt_in.yaml"))
    step = Runner(tmp_path, tmp_path).run("env", [sys.executable, "-c",
                                                  f"import os; print(os.environ.get('{CONFIG_ENV}', 'unset'))"])
    assert step.status == "ok" and step.stdout.strip() == "unset"


def test_a_run_of_benchmarks_that_do_not_read_the_file_says_so(monkeypatch, tmp_path) -> None:
    """`TRACKMETER_BENCH_CONFIG=bad.yaml python -m benchmarks render` ran the defaults, exit 0,
    without a word (an outside probe): the benchmarks that do not read the file are named."""
    from benchmarks import READS_CONFIG, config_note

    assert READS_CONFIG == {"accuracy", "operator", "looks", "error_budget"}
    monkeypatch.setenv(CONFIG_ENV, "smooth.yaml")
    assert config_note(["render", "accuracy", "pipeline"]) == (
        f"{CONFIG_ENV} (smooth.yaml) is read by accuracy, error_budget, looks and operator only: render and "
        "pipeline run config/default.yaml")
    assert config_note(["measure"]).endswith(": measure runs config/default.yaml")  # one: "runs" (a probe)
    assert config_note(["accuracy", "looks"]) is None
    monkeypatch.delenv(CONFIG_ENV)
    assert config_note(["render"]) is None


def test_a_bad_file_is_refused_before_any_benchmark_runs(monkeypatch, tmp_path, capsys) -> None:
    """`benchmarks render operator` with a misspelt file ran render's 20 s first, then failed
    at operator (an outside probe): the file is checked before the first benchmark."""
    import benchmarks.__main__ as entry

    ran: list[str] = []
    monkeypatch.setattr(entry.importlib, "import_module", lambda name: ran.append(name))
    monkeypatch.setenv(CONFIG_ENV, str(tmp_path / "missing.yaml"))
    assert entry.main(["render", "operator"]) == 2
    assert ran == [] and CONFIG_ENV in capsys.readouterr().err
