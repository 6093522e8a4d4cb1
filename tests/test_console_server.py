"""Starting the console: exact port or a clear error, a failing source reported in the UI.

No browser here (see ``tests/browser``); viser's server runs in-process on a free port.
"""

from __future__ import annotations

import contextlib
import errno
import functools
import logging
import os
import re
import socket
import threading
import time
import types
import urllib.request
from concurrent.futures import Future
from typing import Any, Iterator

import numpy as np
import pytest

pytest.importorskip("viser")

from console.server import check_port_free, console_url, start_console  # noqa: E402
from tests.browser.conftest import free_port  # noqa: E402
from tests.test_pipeline import CountingSource, RecordingEngine  # noqa: E402
from trackmeter.cli.main import main  # noqa: E402
from trackmeter.errors import TrackmeterError  # noqa: E402


def _listening_socket() -> tuple[socket.socket, int]:
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    s.listen()
    return s, s.getsockname()[1]


def test_busy_port_is_a_clear_error_not_a_move_to_the_next_port(capsys: pytest.CaptureFixture[str]) -> None:
    s, port = _listening_socket()
    with s:
        with pytest.raises(TrackmeterError, match=f"port {port} on 127.0.0.1 is already in use"):
            check_port_free("127.0.0.1", port)
        assert main(["console", "--port", str(port)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err == [f"trackmeter console: error: port {port} on 127.0.0.1 is already in use; choose another with --port"]
    check_port_free("127.0.0.1", port)  # free again once nobody listens
    with pytest.raises(TrackmeterError, match="port must be 1-65535"):
        check_port_free("127.0.0.1", 70000)


@pytest.mark.parametrize(("host", "url"), [
    ("127.0.0.1", "http://127.0.0.1:8080"), ("0.0.0.0", "http://127.0.0.1:8080"), ("", "http://127.0.0.1:8080"),
    ("::1", "http://[::1]:8080"), ("::", "http://[::1]:8080"), ("fe80::1%eth0", "http://[fe80::1%25eth0]:8080"),
    ("localhost", "http://localhost:8080")])
def test_the_console_s_address_is_one_a_browser_opens_ipv6_in_brackets(host: str, url: str) -> None:
    # --host ::1 printed http://::1:8080, and --host :: http://:::8080: no browser opens either
    # (an outside code review).
    assert console_url(host, 8080) == url


def test_a_console_on_every_ipv6_interface_answers_at_the_address_it_gives() -> None:
    if not socket.has_ipv6:
        pytest.skip("no IPv6 here")
    port = free_port()
    try:
        running = start_console(CountingSource(100_000, delay_s=0.02), RecordingEngine(), host="::",  # type: ignore[arg-type]
                                port=port)
    except TrackmeterError as exc:
        pytest.skip(f"cannot listen on IPv6 here: {exc}")
    try:
        assert running.url == f"http://[::1]:{port}"  # urllib opened "http://:::PORT" too; a browser does not
        with urllib.request.urlopen(running.url, timeout=10) as response:
            assert response.status == 200
    finally:
        running.stop()


def test_an_out_of_range_cpu_priority_is_a_clear_error(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["console", "--cpu-nice", "-21"]) == 2
    assert capsys.readouterr().err.strip() == "trackmeter console: error: --cpu-nice must be -20..19, got -21"


def test_the_cpu_priority_is_left_alone_unless_asked_for(tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A raised priority starves a browser on the same machine when the host is slow (the
    console benchmark's Chromium, in the console's session, did not open its websocket within
    60 s in 3 runs of 4 at nice -10; one in its own session took 3-19 s a screenshot,
    docs/results.md), so raising it is the operator's choice (--cpu-nice N), not the default."""
    import trackmeter.priority as priority

    asked: list[int] = []

    def fake_raise(nice: int) -> priority.PriorityChange:
        asked.append(nice)
        return priority.PriorityChange(False, "left alone (test)", {}, None)

    monkeypatch.setattr(priority, "raise_cpu_priority", fake_raise)
    missing = tmp_path / "nonexistent"  # the source fails once the priority is decided
    assert main(["console", "--source", str(missing), "--port", str(free_port())]) == 2
    assert asked == []
    assert main(["console", "--source", str(missing), "--port", str(free_port()), "--cpu-nice", "-10"]) == 2
    assert asked == [-10]


def test_the_console_draws_the_configured_patch_size(tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    # tracker.patch_size from --config: the boxes were drawn 8 px whatever it said (an outside
    # code review).
    import console.server as server_mod
    from trackmeter.errors import TrackmeterError

    seen: dict[str, object] = {}

    def fake_start(source, engine, **kwargs):  # type: ignore[no-untyped-def]
        seen.update(kwargs)
        raise TrackmeterError("stop here (test)")

    monkeypatch.setattr(server_mod, "start_console", fake_start)
    config = tmp_path / "c.yaml"
    config.write_text("tracker:\n  patch_size: 12\n")
    assert main(["console", "--source", "sim", "--config", str(config), "--port", str(free_port())]) == 2
    assert seen["patch_px"] == 12


def _wait_for_status(running, text: str, timeout_s: float = 20.0) -> None:  # type: ignore[no-untyped-def]
    """Wait until the console's status box shows ``text``; fail with what it shows instead."""
    deadline = time.monotonic() + timeout_s
    while text not in running.console.status_html.content:
        assert time.monotonic() < deadline, running.console.status_html.content
        time.sleep(0.05)


def test_a_lost_operator_box_leaves_the_image_a_while_after_the_loss() -> None:
    """A target lost for good (its uv the last good pixel) is not marked there for ever: after
    LOST_SHOWN_S of frame time its box is parked (console.overlay.LostTargets)."""
    from console.overlay import LOST_SHOWN_S
    from trackmeter.core.targets import TargetState

    nan2 = np.full(2, np.nan)
    engine = RecordingEngine()
    engine.targets = [TargetState("p1", "operator", "lost", np.array([3.0, 2.0]), nan2, np.full(3, np.nan),
                                  np.full((3, 3), np.nan), float("nan"), nan2, (0, 0, 1, 1), "test")]
    frames = int(25 * (LOST_SHOWN_S + 1.0))  # CountingSource: 25 frames a second
    running = start_console(CountingSource(frames, delay_s=0.02), engine, port=free_port())  # type: ignore[arg-type]
    try:
        marks = running.console.operator_marks
        deadline = time.monotonic() + 20.0
        while "p1" not in marks.of_target and len(engine.processed) < frames:
            time.sleep(0.005)
        assert "p1" in marks.of_target, "the lost box was never shown"  # just after the loss it is
        _wait_for_status(running, "ended")
        time.sleep(0.3)  # the last push
        assert "p1" not in marks.of_target and time.monotonic() < deadline
        # ... and a shift-click there does not remove what the operator cannot see.
        assert running.console._hidden_ids == {"p1"}
    finally:
        running.stop()


def test_after_a_restart_the_dropped_share_counts_from_it() -> None:
    from trackmeter.pipeline.snapshot import RestartSource

    running = start_console(CountingSource(100_000, delay_s=0.005), RecordingEngine(), port=free_port())  # type: ignore[arg-type]
    try:
        _wait_for_status(running, "running")
        assert "since Restart" not in running.console.status_html.content
        running.console.submit(RestartSource()).result(10)
        _wait_for_status(running, "since Restart")
        import re

        since, total = (int(x) for x in re.search(r"dropped (\d+) \([\d.]+ %\) since Restart · (\d+) in all",
                                                   running.console.status_html.content).groups())
        assert 0 <= since <= total
    finally:
        running.stop()


def test_a_failing_source_is_shown_and_the_console_stays_up() -> None:
    port = free_port()
    img_source = CountingSource(40, fail_at=25)
    running = start_console(img_source, RecordingEngine(), port=port)  # type: ignore[arg-type]
    try:
        assert running.url == f"http://127.0.0.1:{port}"
        _wait_for_status(running, "source failed: camera unplugged")
        assert running.pipeline.running
        with urllib.request.urlopen(running.url, timeout=10) as response:
            assert response.status == 200
    finally:
        running.stop()
    assert not running.pipeline.running and img_source.closed


def test_a_stopped_console_says_so_on_the_page() -> None:
    # The page kept its last status ("running · frame N · REC") after the server stopped, with
    # only viser's small disconnected icon to tell (an outside console probe).
    running = start_console(CountingSource(100_000, delay_s=0.02), RecordingEngine(), port=free_port())  # type: ignore[arg-type]
    try:
        _wait_for_status(running, "running")
    finally:
        running.stop()
    assert "stopped" in running.console.status_html.content and "running" not in running.console.status_html.content


def test_frames_that_do_not_match_the_rig_are_a_clear_error(opencv_sample_sequence, capsys: pytest.CaptureFixture[str]) -> None:
    from pathlib import Path

    rig = Path(__file__).resolve().parent.parent / "config" / "rigs" / "estec_12mm.yaml"
    port = free_port()
    code = main(["console", "--source", f"seq:{opencv_sample_sequence}", "--rig", str(rig), "--port", str(port),
                 "--cpu-nice", "0"])
    err = [line for line in capsys.readouterr().err.strip().splitlines() if "opening" not in line]
    assert code == 2 and err == [f"trackmeter console: error: frame 640x480 does not match the rig's image size "
                                 f"726x512 (--rig {rig})"], err


def test_a_broken_model_in_the_folder_is_warned_and_left_out_unless_case_b_is_asked_for(
        opencv_sample_sequence, opencv_sample_rig, tmp_path, monkeypatch, capsys: pytest.CaptureFixture[str]) -> None:
    """The console runs cases (a) and (c) without a model: a folder's broken model.yaml is a
    warning then (the operator can still track), and one clear line with --case b."""
    import shutil

    import console.server

    folder = tmp_path / "seq"
    shutil.copytree(opencv_sample_sequence, folder)
    (folder / "model.yaml").write_text("points: [oops\n")
    served: list[Any] = []

    def serve_briefly(running: Any) -> None:
        served.append(running.pipeline.engine.case)
        running.stop()

    monkeypatch.setattr(console.server, "serve_forever", serve_briefly)
    rig = ["--rig", str(opencv_sample_rig / "intrinsics.yml")]
    assert main(["console", "--source", str(folder), *rig, "--port", str(free_port()), "--cpu-nice", "0"]) == 0
    err = capsys.readouterr().err
    assert served == ["a"] and "model.yaml: malformed YAML" in err and "model not used" in err, err
    code = main(["console", "--source", str(folder), *rig, "--case", "b", "--port", str(free_port()), "--cpu-nice", "0"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "model.yaml" in err[0], err


def test_the_console_takes_a_model_file_and_starts_automatic_selection_as_track_does(
        opencv_sample_sequence, opencv_sample_rig, tmp_path, monkeypatch, capsys: pytest.CaptureFixture[str]) -> None:
    """``track`` has --model and --auto; the console had neither: case (b) on a folder without a
    model.yaml was refused with no word of how to give one, and the README's case (c) example
    sat acquiring "0 measured points" until the operator found the automatic selection (a new
    user's probe)."""
    import console.server
    from trackmeter.data.model import save_model

    model_file = tmp_path / "m.yaml"
    save_model(model_file, [("p1", [0.0, 0.0, 0.0]), ("p2", [0.1, 0.0, 0.0]), ("p3", [0.0, 0.1, 0.0])])
    served: list[Any] = []

    def serve_briefly(running: Any) -> None:
        deadline = time.monotonic() + 20
        while not running.pipeline.latest().auto_enabled and time.monotonic() < deadline:
            time.sleep(0.05)
        snap = running.pipeline.latest()
        engine = running.pipeline.engine
        served.append((engine.case, None if engine.model is None else list(engine.model.ids), snap.auto_enabled,
                       snap.auto_count))
        running.stop()

    monkeypatch.setattr(console.server, "serve_forever", serve_briefly)
    rig = ["--rig", str(opencv_sample_rig / "intrinsics.yml")]
    common = ["--source", str(opencv_sample_sequence), *rig, "--port", str(free_port()), "--cpu-nice", "0"]
    assert main(["console", *common, "--case", "b", "--model", str(model_file), "--auto", "7"]) == 0
    assert served == [("b", ["p1", "p2", "p3"], True, 7)], served
    capsys.readouterr()
    for bad, said in ((["--auto", "0"], "--auto must be in [1, "), (["--model", str(tmp_path / "none.yaml")], "none.yaml")):
        assert main(["console", *common, *bad]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and said in err[0], err


def test_a_bad_source_is_one_line_on_stderr(tmp_path, capsys: pytest.CaptureFixture[str]) -> None:
    """Bad input is one line on stderr (DESIGN.md section 6): the CPU priority's and the
    "opening" notes came first. "opening" is progress, shown on a terminal only; the priority
    is said once the source is open (it is raised before, so the source's threads inherit it)."""
    missing = tmp_path / "nonexistent"
    code = main(["console", "--source", str(missing), "--port", str(free_port()), "--cpu-nice", "-1"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and err[0].startswith(f"trackmeter console: error: unknown source '{missing}'"), err


class _NamingEngine(RecordingEngine):
    """The test double, plus the model point id each SelectPoint named (None: none)."""

    def __init__(self) -> None:
        super().__init__()
        self.named: list[str | None] = []

    def handle(self, command, frame):  # type: ignore[no-untyped-def]
        from trackmeter.pipeline.snapshot import SelectPoint

        if isinstance(command, SelectPoint):
            self.named.append(command.target_id)
        return super().handle(command, frame)


def _wait_for_pushes(con, n: int) -> None:  # type: ignore[no-untyped-def]
    """Wait until the console has pushed ``n`` more images to the browser (20 s at most)."""
    target = con.images_pushed + n
    deadline = time.monotonic() + 20
    while con.images_pushed < target:
        assert time.monotonic() < deadline, "no pushes"
        time.sleep(0.02)


class _AutoEngine(RecordingEngine):
    """The test double, plus automatic selection: on with a count of 1 or more, refused with 0."""

    auto_enabled = False

    def handle(self, command, frame):  # type: ignore[no-untyped-def]
        from trackmeter.pipeline.snapshot import CommandReply, SetAuto

        if isinstance(command, SetAuto):
            if command.enabled and not command.count:
                return CommandReply(False, "count must be 1 or more")
            self.auto_enabled = command.enabled
            return CommandReply(True, "ok")
        return super().handle(command, frame)


def test_a_toggle_from_the_browser_is_not_undone_before_its_callback_runs() -> None:
    """viser stores the browser's new value, then runs the callback in a worker thread: a push
    in between must not put the tracker's old state back (the callback would send it)."""
    from trackmeter.pipeline.snapshot import SetAuto

    running = start_console(CountingSource(100_000, delay_s=0.02), _AutoEngine(), port=free_port())  # type: ignore[arg-type]
    con = running.console
    pushes = functools.partial(_wait_for_pushes, con)

    try:
        pushes(3)
        assert con.auto_checkbox.value is False
        con.auto_checkbox.value = True  # what viser does on the browser's message, before the callback
        pushes(5)
        assert con.auto_checkbox.value is True
        con.submit(con._auto_command()).result(10)  # the callback
        pushes(3)
        assert running.pipeline.latest().auto_enabled and con.auto_checkbox.value is True
        # A change made elsewhere (another client, the command line) shows on the widget.
        running.pipeline.submit(SetAuto(False)).result(10)
        pushes(5)
        assert con.auto_checkbox.value is False
        # A refused toggle snaps back to the tracker's state.
        con.auto_checkbox.value = True
        assert not con.submit(SetAuto(True, 0), None, "SetAuto").result(10).ok
        pushes(5)
        assert con.auto_checkbox.value is False
    finally:
        running.stop()


class _LimitsEngine(_AutoEngine):
    """The double with the real engine's limits: at most ``max_targets`` automatic targets, and
    an output-filter cutoff in (0, ``max_filter_cutoff_hz``]."""

    max_targets = 20
    auto_count = 6
    filter_cutoff_hz = 2.0
    max_filter_cutoff_hz = 11.875

    def handle(self, command, frame):  # type: ignore[no-untyped-def]
        from trackmeter.pipeline.snapshot import CommandReply, SetAuto, SetFilterCutoff

        if isinstance(command, SetFilterCutoff):
            if not 0 < command.cutoff_hz <= self.max_filter_cutoff_hz:
                return CommandReply(False, "out of range")
            self.filter_cutoff_hz = command.cutoff_hz
            return CommandReply(True, "ok")
        if isinstance(command, SetAuto) and command.count:
            self.auto_count = command.count
        return super().handle(command, frame)


class _SentEngine(_LimitsEngine):
    """:class:`_LimitsEngine` that also lists what each command of one kind carried, in order
    (``sent``): ``field`` of every ``kind`` handled."""

    def __init__(self, kind: str = "SetFilterCutoff", field: str = "cutoff_hz") -> None:
        super().__init__()
        self.kind, self.field = kind, field
        self.sent: list[Any] = []

    def handle(self, command, frame):  # type: ignore[no-untyped-def]
        if type(command).__name__ == self.kind:
            self.sent.append(getattr(command, self.field))
        return super().handle(command, frame)


def test_the_method_widget_shows_the_configured_method_and_a_toggle_keeps_it() -> None:
    # features.method from --config (centroid, shi_tomasi) was shown as "gabor", and the first
    # tick of "Automatic selection" sent "gabor", replacing it (an outside code review).
    from trackmeter.pipeline.snapshot import SetAuto

    class _MethodEngine(_LimitsEngine):
        auto_method = "shi_tomasi"

        def handle(self, command, frame):  # type: ignore[no-untyped-def]
            if isinstance(command, SetAuto):
                self.sent_method = command.method
                if command.method:
                    self.auto_method = command.method
            return super().handle(command, frame)

    engine = _MethodEngine()
    running = start_console(CountingSource(100_000, delay_s=0.02), engine, port=free_port())  # type: ignore[arg-type]
    con = running.console
    try:
        assert con.auto_method.value == "shi_tomasi" and "shi_tomasi" in con.auto_method.options
        assert con._auto_command().method == "shi_tomasi"
        running.pipeline.submit(SetAuto(True, 6, "centroid")).result(10)  # changed elsewhere
        _wait_for_pushes(con, 4)
        assert con.auto_method.value == "centroid"
    finally:
        running.stop()


def test_the_count_and_cutoff_widgets_follow_the_tracker_and_its_limits() -> None:
    """The Count field takes up to the tracker's max_targets (a larger value was refused while
    the field kept showing it), the cutoff field up to the filter's limit, and both show the
    tracker's value again after a refusal or a change made elsewhere."""
    from trackmeter.pipeline.snapshot import SetAuto, SetFilterCutoff

    running = start_console(CountingSource(100_000, delay_s=0.02), _LimitsEngine(), port=free_port())  # type: ignore[arg-type]
    con = running.console
    pushes = functools.partial(_wait_for_pushes, con)

    try:
        assert con.auto_count_max == 20 and con.cutoff_range_hz[1] == pytest.approx(11.875)
        pushes(3)
        assert con.auto_count.value == "6" and con.cutoff.value == "2"
        running.pipeline.submit(SetAuto(True, 9)).result(10)  # elsewhere
        pushes(5)
        assert con.auto_count.value == "9"
        con.cutoff.value = "0"  # typed by the operator, refused by the tracker
        assert not con.submit(SetFilterCutoff(0.0), None, "SetFilterCutoff").result(10).ok
        pushes(5)
        assert con.cutoff.value == "2"
    finally:
        running.stop()


@contextlib.contextmanager
def _sending_console() -> Iterator[tuple[Any, _SentEngine]]:
    """A console on :class:`_SentEngine`, pushing; yields (console, engine)."""
    engine = _SentEngine()
    running = start_console(CountingSource(100_000, delay_s=0.02), engine, port=free_port())  # type: ignore[arg-type]
    try:
        _wait_for_pushes(running.console, 3)
        yield running.console, engine
    finally:
        running.stop()


def _type_cutoff(con: Any, text: str, said: list[tuple[str, str]] | None = None) -> None:
    """What viser does with a keystroke in the cutoff field: the value, then the callback, with
    the browser's pop-ups going to ``said``."""
    def notify(title: str, body: str, **_: Any) -> None:
        if said is not None:
            said.append((title, body))

    con.cutoff.value = text
    con.edit_callbacks["cutoff"](types.SimpleNamespace(client=types.SimpleNamespace(client_id=0, add_notification=notify)))


def _wait_until(condition: Any, what: str, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, what
        time.sleep(0.05)


def test_a_typed_cutoff_is_sent_once_the_field_holds_it() -> None:
    """viser sends every keystroke of a field: typing "0.5" passed 0 (refused, and the
    refusal put the old value back while the operator was still typing), and every accepted
    keystroke rebuilt the output filter. The value is sent once the field has held it."""
    with _sending_console() as (con, engine):
        for typed in ("0", "0.", "0.5"):  # a keystroke every 0.1 s
            _type_cutoff(con, typed)
            time.sleep(0.1)
            assert con.cutoff.value == typed  # nothing put back while typing
        _wait_until(lambda: engine.filter_cutoff_hz == 0.5, f"0.5 Hz set: {engine.sent}")
        assert engine.sent == [0.5]
        _wait_for_pushes(con, 5)
        assert con.cutoff.value == "0.5"


@pytest.mark.parametrize(("typed", "sent"), [("0,5", 0.5), (" 0.25 ", 0.25), ("3", 3.0)])
def test_a_cutoff_typed_with_a_decimal_comma_is_taken_as_its_value(typed: str, sent: float) -> None:
    """viser's number field dropped a pasted comma: "0,5", the decimal point of much of
    Europe, reached the filter as 5 Hz, ten times the cutoff meant (an outside console probe).
    The field is text, read with either decimal mark."""
    with _sending_console() as (con, engine):
        _type_cutoff(con, typed)
        _wait_until(lambda: engine.sent, "nothing sent")
        assert engine.sent == [pytest.approx(sent)]


def test_the_cutoff_field_shows_what_the_filter_holds_at_both_ends_and_after_it_is_emptied() -> None:
    """The field's range was 0.05 Hz up, the filter's 0.01: 0.02 typed was taken and shown as
    0.05; the top, 11.875, was shown as 11.88, which typed back was refused; and an emptied
    field stayed empty while the filter kept its cutoff (a re-check)."""
    with _sending_console() as (con, engine):
        assert con.cutoff_range_hz == (0.01, 11.875)
        for typed, shown in (("0,02", "0.02"), ("1.2345678", "1.2345678"), ("11.875", "11.875")):
            _type_cutoff(con, typed)
            _wait_until(lambda: engine.filter_cutoff_hz == float(shown), f"{shown} Hz set: {engine.sent}")
            _wait_for_pushes(con, 5)
            assert con.cutoff.value == shown
        _type_cutoff(con, "  ")
        _wait_until(lambda: con.cutoff.value == "11.875", f"the field shows the tracker's cutoff, not {con.cutoff.value!r}")
        assert engine.sent == [0.02, 1.2345678, 11.875]


@pytest.mark.parametrize("typed", ["0,5,1", "fast", "nan", "1.5.", "0.5 Hz x"])
def test_a_cutoff_that_is_no_number_is_refused_with_the_reason_and_the_tracker_s_value_shown(typed: str) -> None:
    said: list[tuple[str, str]] = []
    with _sending_console() as (con, engine):
        _type_cutoff(con, typed, said)
        _wait_until(lambda: said, "nothing said")
        assert said[0][0] == "Filter cutoff: refused" and repr(typed.strip()) in said[0][1], said
        _wait_for_pushes(con, 5)
        assert engine.sent == [] and con.cutoff.value == "2"


def _type_count(con: Any, text: str, said: list[tuple[str, str]] | None = None) -> None:
    """A keystroke in the Count field, as :func:`_type_cutoff`."""
    def notify(title: str, body: str, **_: Any) -> None:
        if said is not None:
            said.append((title, body))

    con.auto_count.value = text
    con.edit_callbacks["auto_count"](types.SimpleNamespace(client=types.SimpleNamespace(client_id=0, add_notification=notify)))


@pytest.mark.parametrize("typed", ["1e9", "0,5", "abc", "nan", "0", "21", "2.5", "-3"])
def test_a_count_that_is_no_whole_number_in_range_is_refused_with_the_reason_and_the_tracker_s_shown(typed: str) -> None:
    """Count was viser's number field, which mangled what was typed and said nothing (an
    outside monkey probe): "1e9" became 19 and the tracker topped up to 19 targets, "0,5"
    became 5, and "abc", "nan" or an emptied field left it blank while the tracker kept its
    count. Anything but a whole number from 1 to max_targets is refused with the reason and
    the tracker's count shown again."""
    from trackmeter.pipeline.snapshot import SetAuto

    said: list[tuple[str, str]] = []
    with _sending_console() as (con, engine):
        engine.kind, engine.field = "SetAuto", "count"
        assert con.submit(SetAuto(True, 6), None, "SetAuto").result(10).ok
        engine.sent.clear()
        _wait_for_pushes(con, 5)
        con.auto_checkbox.value = True
        _type_count(con, typed, said)
        _wait_until(lambda: said, "nothing said")
        assert said[0][0] == "Automatic selection: refused" and repr(typed) in said[0][1], said
        assert "1 to 20" in said[0][1]
        _wait_for_pushes(con, 5)
        assert engine.sent == [] and con.auto_count.value == "6"


def test_an_emptied_count_shows_the_tracker_s_again_and_a_padded_one_is_read() -> None:
    from trackmeter.pipeline.snapshot import SetAuto

    with _sending_console() as (con, engine):
        engine.kind, engine.field = "SetAuto", "count"
        assert con.submit(SetAuto(True, 6), None, "SetAuto").result(10).ok
        engine.sent.clear()
        con.auto_checkbox.value = True
        _type_count(con, "  ")
        _wait_until(lambda: con.auto_count.value == "6", f"the field shows the tracker's count, not {con.auto_count.value!r}")
        _type_count(con, " 12 ")
        _wait_until(lambda: engine.sent == [12], f"12 sent: {engine.sent}")


def _pause(con: Any) -> None:
    """Pause the console's source and wait until the page shows the paused snapshot."""
    from trackmeter.pipeline.snapshot import SetPaused

    assert con.pipeline.call(SetPaused(True)).ok
    _wait_until(lambda: con.pipeline.latest().paused and con.last_pushed_sequence == con.pipeline.latest().sequence,
                "the paused snapshot pushed")


def test_a_refused_count_or_cutoff_shows_the_tracker_s_value_again_while_paused() -> None:
    # Paused, "abc" in Count and "fast" in Filter cutoff were refused but stayed in their fields,
    # as did 0 Hz refused by the filter: the tracker's value was put back only by the push of a
    # new snapshot, and none comes while paused (an outside code review).
    said: list[tuple[str, str]] = []
    with _sending_console() as (con, engine):
        _pause(con)
        _type_count(con, "abc", said)
        _type_cutoff(con, "fast", said)
        _wait_until(lambda: len(said) == 2, f"two refusals said: {said}")
        _wait_until(lambda: (con.auto_count.value, con.cutoff.value) == ("6", "2"),
                    f"the tracker's values shown, not {(con.auto_count.value, con.cutoff.value)}")
        _type_cutoff(con, "0", said)
        _wait_until(lambda: engine.sent == [0.0] and len(said) == 3, f"0 Hz sent and refused: {engine.sent}, {said}")
        assert said[-1][0] == "Filter cutoff: refused", said
        _wait_until(lambda: con.cutoff.value == "2", f"the tracker's cutoff shown, not {con.cutoff.value!r}")


def test_a_typed_count_is_sent_once_the_field_holds_it() -> None:
    """Typing 16 into Count sent 1 and then 16 (an outside probe: eleven refusals for one long
    number typed): like the cutoff, the count is sent once the field holds it."""
    import types

    from trackmeter.pipeline.snapshot import SetAuto

    engine = _SentEngine("SetAuto", "count")
    running = start_console(CountingSource(100_000, delay_s=0.02), engine, port=free_port())  # type: ignore[arg-type]
    con = running.console
    browser = types.SimpleNamespace(add_notification=lambda *a, **k: None)
    try:
        _wait_for_pushes(con, 3)
        assert con.submit(SetAuto(True, 6), None, "SetAuto").result(10).ok
        engine.sent.clear()
        con.auto_checkbox.value = True
        for typed in ("1", "16"):
            con.auto_count.value = typed
            con.edit_callbacks["auto_count"](types.SimpleNamespace(client=browser))
            time.sleep(0.1)
            assert con.auto_count.value == typed
        deadline = time.monotonic() + 10
        while engine.auto_count != 16:
            assert time.monotonic() < deadline, engine.sent
            time.sleep(0.05)
        assert engine.sent == [16]
    finally:
        running.stop()


class _HeldExecutor:
    """Stands in for viser's callback thread pool: runs nothing until :meth:`release`, as a
    pool whose workers are all busy would (a loaded 2-core machine)."""

    def __init__(self) -> None:
        self.held: list[tuple[Any, tuple[Any, ...]]] = []

    def submit(self, fn, *args):  # type: ignore[no-untyped-def]
        self.held.append((fn, args))
        future: Future[Any] = Future()
        return future

    @classmethod
    def installed_in(cls, running) -> "_HeldExecutor":  # type: ignore[no-untyped-def]
        """One in place of ``running``'s viser pool, with a stand-in browser (client id 7)."""
        import types

        held = cls()
        running.server.gui._thread_executor = held
        running.server._connected_clients[7] = types.SimpleNamespace(add_notification=lambda *a, **k: None)
        return held

    def release(self) -> None:
        for fn, args in self.held:
            fn(*args)
        self.held.clear()


@contextlib.contextmanager
def _console_with_held_pool(engine) -> Iterator[tuple[Any, _HeldExecutor]]:  # type: ignore[no-untyped-def]
    """A console on ``engine`` whose viser callback pool runs nothing until released, after
    its first pushes; stopped on leaving."""
    running = start_console(CountingSource(100_000, delay_s=0.02), engine, port=free_port())
    try:
        held = _HeldExecutor.installed_in(running)
        _wait_for_pushes(running.console, 3)
        yield running, held
    finally:
        running.stop()


def _browser_sets(running, handle, value) -> None:  # type: ignore[no-untyped-def]
    """What viser does with a browser's new value: its own message handler, on its event loop."""
    import asyncio

    from viser._messages import GuiUpdateMessage

    gui = running.server.gui
    message = GuiUpdateMessage(handle._impl.uuid, {"value": value})
    asyncio.run_coroutine_threadsafe(gui._handle_gui_updates(7, message), gui._event_loop).result(10)


def test_a_value_typed_as_a_refusal_puts_the_old_one_back_is_the_value_sent() -> None:
    """A refusal shows the tracker's value on the widget again. The operator's next value,
    typed just then, arrived while viser's callback for it waited for a worker thread; the push
    put the old value on the widget and the callback, reading the widget, sent that: the typed
    value was silently lost (an outside console probe: "3.3 after a run of bad values was not
    applied"). The value is the one that arrived, and a field being edited is not reset."""
    engine = _SentEngine()
    with _console_with_held_pool(engine) as (running, held):
        con = running.console
        assert con.cutoff.value == "2"
        _browser_sets(running, con.cutoff, "3.3")
        con._mirrored.pop("cutoff", None)  # what a refusal of the value before it does
        _wait_for_pushes(con, 5)
        held.release()
        deadline = time.monotonic() + 10
        while not engine.sent:
            assert time.monotonic() < deadline, "nothing sent"
            time.sleep(0.05)
        time.sleep(0.3)
        assert engine.sent == [pytest.approx(3.3)]
        _wait_for_pushes(con, 5)
        assert engine.filter_cutoff_hz == pytest.approx(3.3) and con.cutoff.value == "3.3"


def test_a_toggle_is_sent_in_the_order_it_came_without_waiting_for_a_worker_thread() -> None:
    """The switches' callbacks run on viser's event loop as their messages arrive: with every
    worker thread busy, "Automatic selection" on, then off, reaches the tracker at once and in
    that order (from the pool, two quick toggles could also run in either order)."""
    engine = _AutoEngine()
    with _console_with_held_pool(engine) as (running, held):
        con = running.console
        _browser_sets(running, con.auto_checkbox, True)
        _wait_for_pushes(con, 3)
        assert engine.auto_enabled and running.pipeline.latest().auto_enabled
        _browser_sets(running, con.auto_checkbox, False)
        _wait_for_pushes(con, 3)
        assert not engine.auto_enabled and con.auto_checkbox.value is False
        assert not held.held  # nothing waited for the pool


def _browser_clicks(running, uv, modifier=None) -> None:  # type: ignore[no-untyped-def]
    """What viser does with a click on the left image at pixel ``uv``: its own message handler,
    with a ray straight onto the image plane."""
    import asyncio

    import numpy as np
    from scipy.spatial.transform import Rotation
    from viser._messages import SceneNodeClickMessage

    from console.overlay import pixel_to_plane

    con = running.console
    R = Rotation.from_quat(np.asarray(con.left_image.wxyz, dtype=float), scalar_first=True).as_matrix()
    x, y = pixel_to_plane([uv], con._image_size, con.render_size)[0]
    origin = R @ np.array([x, y, -1.0]) + np.asarray(con.left_image.position, dtype=float)
    message = SceneNodeClickMessage("/left", None, tuple(origin), tuple(R @ np.array([0.0, 0.0, 1.0])), (0.5, 0.5),
                                    modifier)
    scene = running.server.scene
    asyncio.run_coroutine_threadsafe(scene._handle_node_click_updates(7, message), scene._event_loop).result(10)


def test_a_click_and_a_remove_click_reach_the_tracker_in_the_order_they_came() -> None:
    """Clicks on the image are handled on viser's event loop as they arrive (viser's own advice
    for stateful gestures): from its thread pool, a click and a shift-click right after it
    could reach the tracker the other way round, removing before adding."""
    engine = RecordingEngine()
    with _console_with_held_pool(engine) as (running, held):
        running.server.scene._thread_executor = held  # type: ignore[assignment]
        _browser_clicks(running, (3.0, 2.0))  # the test source's frames are 6 x 4 px
        _browser_clicks(running, (3.0, 2.0), "shift")
        deadline = time.monotonic() + 10
        while sum(name in ("SelectPoint", "RemoveNearest") for name, _ in engine.commands) < 2:
            assert time.monotonic() < deadline and not held.held, engine.commands
            time.sleep(0.05)
        assert [name for name, _ in engine.commands if name in ("SelectPoint", "RemoveNearest")] == [
            "SelectPoint", "RemoveNearest"]


def test_a_remove_click_goes_to_the_tracker_even_when_the_last_frame_showed_no_target() -> None:
    """The console answered a shift-click itself ("Nothing to remove") when the last published
    frame had no target: a click's target not yet made there (the tracker a frame behind, a
    loaded machine) made the remove that followed it vanish (this file's ordering test failed
    so once in a full run). The tracker, which has every command in order, answers it."""
    engine = RecordingEngine()
    with _console_with_held_pool(engine) as (running, held):
        running.server.scene._thread_executor = held  # type: ignore[assignment]
        assert not running.pipeline.latest().targets
        _browser_clicks(running, (3.0, 2.0), "shift")
        deadline = time.monotonic() + 10
        while not any(name == "RemoveNearest" for name, _ in engine.commands):
            assert time.monotonic() < deadline and not held.held, engine.commands
            time.sleep(0.05)


def test_a_refused_click_keeps_the_model_point_chosen_for_the_next_one() -> None:
    """"Next click is" names the next target after a model point; a refused click (common on a
    turning body) must not use the choice up, or the retry makes an unnamed target."""
    import types

    from console.app import NEW_TARGET

    running = start_console(CountingSource(100_000, delay_s=0.02), RecordingEngine(), port=free_port())  # type: ignore[arg-type]
    con = running.console
    browser = types.SimpleNamespace(add_notification=lambda *a, **k: None)
    try:
        _wait_for_pushes(con, 3)
        con.model_point_dropdown.options = (NEW_TARGET, "m1")
        con.model_point_dropdown.value = "m1"
        assert not con._click_at((-5.0, 10.0), browser).result(10).ok  # refused: outside the image
        _wait_for_pushes(con, 3)
        assert con.model_point_dropdown.value == "m1"
        assert con._click_at((50.0, 10.0), browser).result(10).ok
        deadline = time.monotonic() + 10
        while con.model_point_dropdown.value != NEW_TARGET:
            assert time.monotonic() < deadline, "the choice stays after the target was made"
            time.sleep(0.05)
    finally:
        running.stop()


def test_a_model_point_named_like_the_new_target_choice_leaves_every_option_distinct() -> None:
    """A model point with the id "a new target" put that option twice in "Next click is":
    the browser's dropdown refuses duplicate options, and every page went blank until the
    console was restarted (an outside probe)."""
    import types

    from console.app import NEW_TARGET

    engine = _NamingEngine()
    # The engine's own model, so every snapshot the console syncs from carries these ids (a
    # snapshot made up by the test was undone by the next real one: flaky in CI)
    engine.model = types.SimpleNamespace(ids=(NEW_TARGET, "m2", "m3"))
    running = start_console(CountingSource(100_000, delay_s=0.02), engine, port=free_port())  # type: ignore[arg-type]
    con = running.console
    try:
        deadline = time.monotonic() + 10
        while len(con.model_point_dropdown.options) < 4:
            assert time.monotonic() < deadline, "the model's ids never reached 'Next click is'"
            time.sleep(0.02)
        options = con.model_point_dropdown.options
        assert len(set(options)) == len(options) == 4, options
        assert NEW_TARGET in options[1:]  # the model point keeps its id
        new_target = con.model_point_dropdown.value
        assert new_target == options[0] and new_target != NEW_TARGET
        # a click with the (renamed) new-target choice makes an unnamed target, the model
        # point's choice a named one
        browser = types.SimpleNamespace(add_notification=lambda *a, **k: None, client_id=1)
        assert con._click_at((50.0, 10.0), browser).result(10).ok
        con.model_point_dropdown.value = NEW_TARGET
        assert con._click_at((60.0, 10.0), browser).result(10).ok
        assert engine.named == [None, NEW_TARGET]
    finally:
        running.stop()


def test_what_the_source_skipped_is_shown_while_it_plays() -> None:
    """A sequence folder's unreadable image is skipped while it plays (``Source.warning``):
    the operator sees it in the status box, not only ``track``'s user at the end."""

    class SkippingSource(CountingSource):
        warning = None

        def read(self):  # type: ignore[no-untyped-def]
            frame = super().read()
            if self.i == 20:
                self.warning = "1 pair(s) with an unreadable image skipped (cam0/data/123.png: not an image)"
            return frame

    running = start_console(SkippingSource(100_000, delay_s=0.01), RecordingEngine(), port=free_port())  # type: ignore[arg-type]
    try:
        _wait_for_status(running, "unreadable image skipped")
        assert "123.png" in running.console.status_html.content
    finally:
        running.stop()


def test_the_console_starts_when_the_filter_cutoff_lies_beyond_the_field_s_range() -> None:
    """A slow source (4 Hz: the filter takes at most 1.9 Hz) with the default 2 Hz cutoff, which
    the filter clips: viser refuses a number field whose start value is out of its range."""

    class SlowSourceEngine(_LimitsEngine):
        max_filter_cutoff_hz = 1.9

    running = start_console(CountingSource(100_000, delay_s=0.02), SlowSourceEngine(), port=free_port())  # type: ignore[arg-type]
    try:
        assert running.console.cutoff_range_hz[1] == pytest.approx(1.9) and running.console.cutoff.value == "1.9"
    finally:
        running.stop()


@pytest.mark.parametrize("burst_s", [(0.0, 0.0, 0.001, 0.01, 0.05, 0.2, 0.5)])
def test_signals_repeated_while_stopping_end_cleanly_with_the_recording_whole(tmp_path, burst_s) -> None:
    """A SIGTERM sent twice (a wrapper and a service manager) or Ctrl-C pressed again while the
    console winds down: one clean stop, its summary, the recording complete; no traceback. The
    first is a SIGHUP: a closed terminal or a dropped ssh session stops it as cleanly."""
    import re
    import signal
    import subprocess
    import sys

    from trackmeter.data.sequence import index_sequence

    port, record = free_port(), tmp_path / "rec"
    proc = subprocess.Popen([sys.executable, "-m", "trackmeter.cli.main", "console", "--port", str(port), "--cpu-nice", "0",
                             "--record", str(record)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        csv = record / "cam0" / "data.csv"
        while not csv.exists() or len(csv.read_text().splitlines()) < 10:
            assert proc.poll() is None and time.monotonic() < deadline, "the console ended or never recorded"
            time.sleep(0.2)
        for i, pause_s in enumerate(burst_s):
            time.sleep(pause_s)
            proc.send_signal((signal.SIGHUP, signal.SIGTERM, signal.SIGINT)[i % 3])
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 0 and "Traceback" not in err, err
    assert "trackmeter console: stopped after" in err
    recorded = re.search(r"recorded (\d+) frames", err)
    assert recorded, err
    index = index_sequence(record)
    assert len(index.t_s) == int(recorded.group(1)) >= 10 and index.skipped == 0


def test_the_fits_are_compiled_before_a_browser_can_connect(monkeypatch) -> None:
    # The first console after an install compiled the fits for ~15 s with the server already
    # listening; a page opened then (the README's first command) stayed black: viser's client
    # cancels an image still loading when the next arrives, and the starved page never caught up.
    import console.server as server_module

    calls: list[str] = []
    real_start_server = server_module.start_server
    monkeypatch.setattr(server_module, "warm_up", lambda: calls.append("warm_up"), raising=False)
    monkeypatch.setattr(server_module, "start_server", lambda *a, **k: (calls.append("listen"), real_start_server(*a, **k))[1])
    running = start_console(CountingSource(100_000, delay_s=0.02), RecordingEngine(), port=free_port())  # type: ignore[arg-type]
    try:
        assert calls[:2] == ["warm_up", "listen"], calls
    finally:
        running.stop()


def test_a_recording_folder_name_the_file_system_refuses_is_answered_not_a_traceback(tmp_path) -> None:
    # An outside probe typed a 300-letter folder name and ticked Record: OSError in the
    # callback (a traceback in the log), no answer, and the box stayed ticked.
    from trackmeter.pipeline.snapshot import SetRecording

    running = start_console(CountingSource(100_000, delay_s=0.02), RecordingEngine(), port=free_port())  # type: ignore[arg-type]
    con = running.console
    try:
        con.record_dir.value = str(tmp_path / ("L" * 300))
        folder = con._fresh_record_dir()
        assert folder == con.record_dir.value
        reply = con.submit(SetRecording(folder), None, "SetRecording").result(10)
        assert not reply.ok and "too long" in reply.message, reply.message
        _wait_for_pushes(con, 3)
        assert con.record_checkbox.value is False
    finally:
        running.stop()


def test_a_record_folder_in_a_home_the_server_cannot_find_is_refused_and_the_box_unticked() -> None:
    # Record ticked with the Folder "~nosuchuser/rec": Path.expanduser's RuntimeError escaped the
    # callback on viser's event loop: nothing recorded, no word of why, and the box stayed
    # ticked (an outside code review). Paused here, where no new snapshot comes to untick it.
    said: list[tuple[str, str]] = []
    running = start_console(CountingSource(100_000, delay_s=0.02), RecordingEngine(), port=free_port())  # type: ignore[arg-type]
    con = running.console
    try:
        running.server._connected_clients[7] = types.SimpleNamespace(
            client_id=7, add_notification=lambda title, body, **k: said.append((title, body)))
        _wait_for_pushes(con, 3)
        _pause(con)
        con.record_dir.value = "~nosuchuser_tm/rec"
        _browser_sets(running, con.record_checkbox, True)
        _wait_until(lambda: said, "nothing said")
        assert said == [("Record: refused", "'~nosuchuser_tm/rec': the server finds no home folder for "
                                            "'~nosuchuser_tm' (no such user there)")], said
        _wait_until(lambda: con.record_checkbox.value is False, "the box unticked")
        assert not running.pipeline.latest().recording
    finally:
        running.stop()


def test_a_recording_folder_name_with_a_nul_is_answered_in_words(tmp_path, caplog) -> None:
    # "rec<NUL>nul" answered "SetRecording failed: ValueError: embedded null byte" with a
    # traceback on stderr, where every other bad name gets its reason (an outside probe).
    from trackmeter.pipeline.snapshot import SetRecording

    running = start_console(CountingSource(100_000, delay_s=0.02), RecordingEngine(), port=free_port())  # type: ignore[arg-type]
    con = running.console
    try:
        reply = con.submit(SetRecording(str(tmp_path / "rec\x00nul")), None, "SetRecording").result(10)
        assert not reply.ok and "NUL" in reply.message and "ValueError" not in reply.message, reply.message
        # a byte that is not UTF-8 beside it is quoted as the console shows it elsewhere (\xfe),
        # not as Python holds it (\udcfe)
        reply = con.submit(SetRecording(str(tmp_path / "rec\udcfe\x00")), None, "SetRecording").result(10)
        assert "rec\\xfe\\x00'" in reply.message and "udc" not in reply.message, reply.message
        assert not any(r.exc_info for r in caplog.records)
    finally:
        running.stop()


def test_a_click_on_the_right_image_is_answered() -> None:
    # The README: every click that arrives is answered. One on the right image got nothing (an
    # outside console probe); targets are set on the left image, and the answer says so.
    import types

    running = start_console(CountingSource(100_000, delay_s=0.02), RecordingEngine(), port=free_port())  # type: ignore[arg-type]
    con = running.console
    shown: list[tuple[str, str]] = []
    browser = types.SimpleNamespace(client_id=7, add_notification=lambda title, body, **k: shown.append((title, body)))
    try:
        con._on_right_click(types.SimpleNamespace(client=browser))
        assert shown and "left image" in shown[0][1], shown
        assert con.notifications[-1] == shown[0]
    finally:
        running.stop()


def test_the_right_image_shown_while_paused_is_the_paused_frame_s_and_nothing_is_added_twice() -> None:
    # "Show right image" ticked while paused (or with the source ended) showed it black or
    # stale: it was drawn only on the push of a new snapshot, and none comes while paused (an
    # outside code review). The paused snapshot is pushed again, once, and the trails and plots
    # take nothing from it twice.
    from trackmeter.pipeline.snapshot import SelectPoint

    running = start_console(CountingSource(100_000, delay_s=0.02), RecordingEngine(), port=free_port())  # type: ignore[arg-type]
    con = running.console
    try:
        assert running.pipeline.call(SelectPoint(3.0, 2.0)).ok
        _wait_for_pushes(con, 5)
        _pause(con)
        paused = running.pipeline.latest()
        assert paused.frame is not None and paused.frame.right[0, 0] != 0  # not black itself
        pushed, trail = con.images_pushed, list(con._trails.points["t0"])
        plotted = {name: len(window) for name, window in con.plots.windows.items()}
        con.right_checkbox.value = True  # viser runs the callback as for a browser's tick
        _wait_until(lambda: con.right_image.image.shape[:2] == paused.frame.right.shape
                    and con.right_image.image[0, 0, 0] == paused.frame.right[0, 0],
                    f"the paused frame's right image shown, not {con.right_image.image[0, 0]}")
        time.sleep(0.5)  # the publisher's ticks
        settled = con.images_pushed
        # Pushed again (a snapshot the pause published after it may have been pushed too, under load)
        assert settled >= pushed + 1 and con.last_pushed_sequence == running.pipeline.latest().sequence
        time.sleep(0.5)
        assert con.images_pushed == settled  # once: not again on every tick
        assert list(con._trails.points["t0"]) == trail
        assert {name: len(window) for name, window in con.plots.windows.items()} == plotted
    finally:
        running.stop()


def _boxed_as_before(rgb: np.ndarray, uv: tuple[int, int], half: int) -> None:
    """The right image's match box as the console drew it before (numpy slices): right for a box
    inside the image."""
    u, v = uv
    rgb[max(v - half, 0):v + half + 1, [max(u - half, 0), min(u + half, rgb.shape[1] - 1)]] = (60, 230, 60)
    rgb[[max(v - half, 0), min(v + half, rgb.shape[0] - 1)], max(u - half, 0):u + half + 1] = (60, 230, 60)


def test_a_match_box_off_the_right_image_is_left_out_and_one_inside_drawn_as_before() -> None:
    # A match above and left of the right image (uv_right is the unrectified pixel of a
    # rectified match) was drawn with negative numpy indices, which wrapped round: a full-height
    # line at the left and a line at the far right (an outside code review); one a few pixels
    # below or right of it raised IndexError, and no image was pushed while it lasted.
    from trackmeter.core.targets import TargetState
    from trackmeter.sources.base import StereoFrame

    class _GreySource(CountingSource):
        def read(self):  # type: ignore[no-untyped-def]
            frame = super().read()
            grey = np.full((120, 160), 40, np.uint8)
            return None if frame is None else StereoFrame(frame.index, frame.t_s, grey, grey.copy(), cut=frame.cut)

    inside = [(80, 60), (4, 4), (155, 115)]  # the last two touch the edges
    nan2 = np.full(2, np.nan)
    engine = RecordingEngine()
    engine.targets = [TargetState(f"a{i}", "auto", "tracking", np.array([80.0, 60.0]), np.array(uv, float),
                                  np.array([0.0, 0.0, 3.0]), np.eye(3) * 1e-6, 0.9, nan2, (70, 50, 90, 70))
                      for i, uv in enumerate([(-7, -7), (-30, 500), (1e12, -1e12), *inside])]
    running = start_console(_GreySource(100_000, delay_s=0.02), engine, port=free_port())  # type: ignore[arg-type]
    con = running.console
    try:
        con.right_checkbox.value = True
        _wait_until(lambda: con.right_image.image.shape == (120, 160, 3), "the right image shown")
        _wait_for_pushes(con, 2)
        expected = np.full((120, 160, 3), 40, np.uint8)
        for uv in inside:
            _boxed_as_before(expected, uv, con.patch_px // 2)
        shown = con.right_image.image
        assert np.array_equal(shown, expected), np.argwhere(np.any(shown != expected, axis=2))[:10]
    finally:
        running.stop()


def test_a_recording_that_lost_frames_ends_the_console_with_exit_code_1(tmp_path, monkeypatch,
                                                                        capsys: pytest.CaptureFixture[str]) -> None:
    """A script that records with the console must be able to tell a cut-short recording: the
    console said so on stderr but exited 0 (an outside probe, on a full tmpfs)."""
    import console.server
    from trackmeter.data.sequence import SequenceWriter

    def full_disk(self, path, image):  # type: ignore[no-untyped-def]
        # Under write(), as a full disk fails it (a writer that never saw a frame keeps nothing).
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    def serve_until_failed(running: Any) -> None:
        deadline = time.monotonic() + 30.0
        while running.pipeline.recording_stats().error is None and time.monotonic() < deadline:
            time.sleep(0.05)
        running.stop()

    monkeypatch.setattr(SequenceWriter, "_write_image", full_disk)
    monkeypatch.setattr(console.server, "serve_forever", serve_until_failed)
    code = main(["console", "--source", "sim", "--port", str(free_port()), "--cpu-nice", "0",
                 "--record", str(tmp_path / "rec")])
    err = capsys.readouterr().err
    assert code == 1 and "NOT recorded" in err, err


def test_the_server_loop_says_on_stderr_when_the_source_ends_fails_or_warns(capsys: pytest.CaptureFixture[str]) -> None:
    """A sequence deleted under a running console: it went idle and printed nothing; only the
    browser's status line could tell. Each new source status and warning is now one line."""
    import threading
    from types import SimpleNamespace

    from console.server import serve_forever
    from trackmeter.pipeline.snapshot import PoseEstimate, Snapshot, Timings

    news = [(None, None), (None, "3 pair(s) with an unreadable image skipped (x.png: no such image file)"),
            ("ended", "3 pair(s) with an unreadable image skipped (x.png: no such image file)"),
            ("ended", "3 pair(s) with an unreadable image skipped (x.png: no such image file)"),
            ("source failed: x: gone", None)]
    stop = threading.Event()
    polled: list[int] = []

    def latest() -> Any:
        k = min(len(polled), len(news) - 1)
        polled.append(k)
        if len(polled) > len(news):
            stop.set()
        return Snapshot(None, (), PoseEstimate.invalid("x"), None, Timings(), source_status=news[k][0],
                        source_warning=news[k][1])

    stopped: list[bool] = []
    running = SimpleNamespace(pipeline=SimpleNamespace(latest=latest), warning_at_open=None,
                              stop=lambda: stopped.append(True))
    serve_forever(running, stop, poll_s=0.01)  # type: ignore[arg-type]
    assert stopped == [True]
    assert capsys.readouterr().err.splitlines() == [
        "trackmeter console: warning: 3 pair(s) with an unreadable image skipped (x.png: no such image file)",
        "trackmeter console: source ended",
        "trackmeter console: source failed: x: gone",
    ]
    # The warning the source gave when it opened was said then (naming its folder): not again,
    # bare (an outside probe saw every sequence warning twice).
    polled.clear()
    stop.clear()
    news = news[1:]  # the snapshots carry the source's warning from the first frame on
    at_open = news[0][1]
    running = SimpleNamespace(pipeline=SimpleNamespace(latest=latest), warning_at_open=at_open,
                              stop=lambda: stopped.append(True))
    serve_forever(running, stop, poll_s=0.01)  # type: ignore[arg-type]
    assert capsys.readouterr().err.splitlines() == ["trackmeter console: source ended",
                                                    "trackmeter console: source failed: x: gone"]


def test_a_sequence_whose_first_image_does_not_decode_is_said_on_stderr(tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    """The skip was found by the pipeline's first read, before serve_forever looked, and taken
    for the warning said when the source opened: the console said nothing, where `track` and a
    later bad image warn (an outside probe)."""
    from console.server import serve_forever
    from tests.test_sequence import _frames, _write
    from trackmeter.sources.sequence import SequenceSource

    folder = _write(tmp_path / "seq", _frames(8))
    first = sorted((folder / "cam0" / "data").iterdir(), key=lambda p: int(p.stem))[0]
    first.write_bytes(b"junk")
    running = start_console(SequenceSource(folder, realtime=True, loop=True), RecordingEngine(), port=free_port())
    _wait_for_pushes(running.console, 2)
    stop = threading.Event()
    threading.Timer(1.0, stop.set).start()
    serve_forever(running, stop, poll_s=0.05)
    err = capsys.readouterr().err
    assert f"trackmeter console: warning: 1 pair(s) with an unreadable image skipped ({first}: " in err, err


def test_a_source_failure_is_said_once_on_stderr(capsys) -> None:  # type: ignore[no-untyped-def]
    """The pipeline's log said "error: source failed: ..." and the server loop "source failed:
    ...", the same line twice (a re-check). The command serves within source_said_by_caller,
    as this test does."""
    from console.server import serve_forever
    from trackmeter.cli.main import PROJECT_LOGGERS, _LogPrinter
    from trackmeter.pipeline.pipeline import source_said_by_caller

    printer = _LogPrinter("console")
    for name in PROJECT_LOGGERS:
        logging.getLogger(name).addHandler(printer)
    try:
        with source_said_by_caller():
            running = start_console(CountingSource(100_000, fail_at=20, delay_s=0.01), RecordingEngine(),
                                    port=free_port())
            stop = threading.Event()
            threading.Timer(2.0, stop.set).start()
            serve_forever(running, stop, poll_s=0.05)
    finally:
        for name in PROJECT_LOGGERS:
            logging.getLogger(name).removeHandler(printer)
    said = [line for line in capsys.readouterr().err.splitlines() if "camera unplugged" in line]
    assert said == ["trackmeter console: source failed: camera unplugged"], said


def test_a_model_point_chosen_in_one_browser_names_only_that_browser_s_click() -> None:
    """"Next click is" is one widget for every browser: one operator's choice named another
    operator's click, meant as a new target, after that model point."""
    import types

    from console.app import NEW_TARGET

    engine = _NamingEngine()
    running = start_console(CountingSource(100_000, delay_s=0.02), engine, port=free_port())  # type: ignore[arg-type]
    con = running.console
    tab_a, tab_b = (types.SimpleNamespace(client_id=i, add_notification=lambda *a, **k: None) for i in (1, 2))
    try:
        _wait_for_pushes(con, 3)
        con.model_point_dropdown.options = (NEW_TARGET, "m1")
        con.model_point_dropdown.value = "m1"
        con._own_next_click(types.SimpleNamespace(client=tab_a))  # chosen in tab A's panel
        assert con._click_at((40.0, 10.0), tab_b).result(10).ok  # tab B's click: a new target
        assert con.model_point_dropdown.value == "m1"
        assert con._click_at((50.0, 10.0), tab_a).result(10).ok  # tab A's: the model point
        assert engine.named == [None, "m1"]
        # Chosen by the console itself (no browser's), any click may use it, as before.
        con.model_point_dropdown.value = "m1"
        con._own_next_click(types.SimpleNamespace(client=None))
        assert con._click_at((60.0, 10.0), tab_b).result(10).ok
        assert engine.named == [None, "m1", "m1"]
        # The chooser gone, its click will never come: the choice is dropped.
        con.model_point_dropdown.value = "m1"
        con._own_next_click(types.SimpleNamespace(client=tab_a))
        con._on_disconnect(tab_a)  # type: ignore[arg-type]
        assert con.model_point_dropdown.value == NEW_TARGET
    finally:
        running.stop()


class _CaseEngine(_NamingEngine):
    """The naming double, plus the model case: SetCase switches the case its poses carry."""

    case = "b"

    def handle(self, command, frame):  # type: ignore[no-untyped-def]
        from trackmeter.pipeline.snapshot import CommandReply, SetCase

        if isinstance(command, SetCase):
            self.case = command.case
            return CommandReply(True, f"case ({command.case})")
        return super().handle(command, frame)

    def process(self, frame):  # type: ignore[no-untyped-def]
        from trackmeter.pipeline.snapshot import PoseEstimate

        targets, _, extra = super().process(frame)
        return targets, PoseEstimate.invalid("test double", self.case), extra  # type: ignore[arg-type]


def test_a_case_switch_drops_the_model_point_chosen_for_the_next_click() -> None:
    """"Next click is" stayed on dish_centre through case (b) -> (c) -> (b) for 15 minutes: a
    plain click in case (c), and later ones, were taken as that model point (an outside probe)."""
    import types

    from console.app import NEW_TARGET
    from trackmeter.pipeline.snapshot import SetCase

    engine = _CaseEngine()
    running = start_console(CountingSource(100_000, delay_s=0.02), engine, port=free_port())  # type: ignore[arg-type]
    con = running.console
    tab = types.SimpleNamespace(client_id=1, add_notification=lambda *a, **k: None)
    try:
        _wait_for_pushes(con, 3)
        con.model_point_dropdown.options = (NEW_TARGET, "m1")
        con.model_point_dropdown.value = "m1"
        con._own_next_click(types.SimpleNamespace(client=tab))
        _wait_for_pushes(con, 3)
        assert con.model_point_dropdown.value == "m1"  # kept while the case stays
        assert running.pipeline.call(SetCase("c")).ok
        deadline = time.monotonic() + 10
        while con.model_point_dropdown.value != NEW_TARGET:
            assert time.monotonic() < deadline, "the choice outlived the case switch"
            time.sleep(0.05)
        assert con._click_at((50.0, 10.0), tab).result(10).ok
        assert engine.named == [None]
    finally:
        running.stop()


@pytest.mark.parametrize("aspect", [700 / 768, 476 / 600, 576 / 900, 390 / 844, 16 / 9])
def test_the_both_preset_holds_the_scene_and_the_image_in_views_of_every_shape(aspect: float) -> None:
    """A desktop window's view beside the docked panel, taller than wide (1024x768: 700x768),
    was given the framing made for a wide view: the image ran under the panel, the scene off
    the left edge. Seen from the browser's camera, the scene's left edge and the image's right
    one must lie inside the view."""
    import contextlib
    import types

    from console.app import SCENE3D_OFFSET

    running = start_console(CountingSource(100_000, delay_s=0.02), RecordingEngine(), port=free_port())  # type: ignore[arg-type]
    con = running.console
    try:
        camera = types.SimpleNamespace(aspect=aspect)
        client = types.SimpleNamespace(camera=camera, atomic=contextlib.nullcontext)
        con._apply_view(client, "both")
        (px, _, pz), (lx, _, lz) = camera.position, camera.look_at
        assert px == pytest.approx(lx) and pz < 0.0 == lz  # facing +z onto the image plane z = 0
        half_width = -pz * np.tan(camera.fov / 2.0) * aspect
        rw, _ = con.render_size
        left, right = SCENE3D_OFFSET[0] - 1.5, rw / 2  # the scene's left edge, the left image's right edge
        assert px - half_width <= left and right <= px + half_width, (aspect, px - half_width, left, right, px + half_width)
    finally:
        running.stop()


def test_the_exit_lines_name_every_recording_and_the_folder_field_the_one_going_on(
        tmp_path, monkeypatch, capsys: pytest.CaptureFixture[str]) -> None:
    # An outside console probe: with --record DIR the panel's Folder field read "runs/recording";
    # a recording started from the panel then went to runs/recording-2 (relative to wherever the
    # server was started), and the exit line named only the last of them.
    import console.server
    from trackmeter.pipeline.snapshot import SetRecording

    seen: dict[str, Any] = {}

    def serve_two_recordings(running: Any) -> None:
        con = running.console
        deadline = time.monotonic() + 30.0
        while running.pipeline.recording_stats().frames_written < 3 and time.monotonic() < deadline:
            time.sleep(0.05)
        _wait_for_pushes(con, 2)
        seen["field"] = con.record_dir.value
        assert running.pipeline.call(SetRecording(None)).ok
        con.record_dir.value = "second"
        folder = con._fresh_record_dir()
        seen["second"] = folder
        assert running.pipeline.call(SetRecording(folder)).ok
        while running.pipeline.recording_stats().frames_written < 3 and time.monotonic() < deadline:
            time.sleep(0.05)
        running.stop()
        seen["image_bytes"] = running.pipeline.recording_stats().image_bytes_written

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(console.server, "serve_forever", serve_two_recordings)
    first = tmp_path / "rec"
    code = main(["console", "--source", "sim", "--port", str(free_port()), "--cpu-nice", "0", "--record", str(first)])
    err = capsys.readouterr().err
    assert code == 0, err
    assert seen["field"] == str(first) and seen["second"] == str(tmp_path / "second")
    # what the panel's recording line shows as the recording's size: its image files
    assert seen["image_bytes"] == sum(p.stat().st_size for p in (tmp_path / "second").glob("cam*/data/*.png")) > 0
    assert re.search(rf"recorded \d+ frames to {re.escape(str(first))}\n", err), err
    assert re.search(rf"recorded \d+ frames to {re.escape(str(tmp_path / 'second'))}\n", err), err


def test_a_looping_source_s_new_pass_is_said_once_and_counted() -> None:
    # A sequence of 100 frames played in a loop: every 4 s its targets, model points and pose
    # went without a word, the status still "source delivering" (an outside console probe).
    from trackmeter.pipeline.snapshot import PoseEstimate, Snapshot, Timings
    from trackmeter.sources.base import StereoFrame

    running = start_console(CountingSource(3), RecordingEngine(), port=free_port())  # type: ignore[arg-type]
    con = running.console
    img = np.zeros((8, 8), np.uint8)
    deadline = time.monotonic() + 10
    while running.pipeline.latest().source_status != "ended":  # no snapshot of its own comes between
        assert time.monotonic() < deadline
        time.sleep(0.02)
    time.sleep(0.5)  # its last snapshot published

    def push(index: int, source_pass: int) -> None:
        con._push(Snapshot(StereoFrame(index, index / 25.0, img, img), (), PoseEstimate.invalid("x"), None, Timings(),
                           source_pass=source_pass), plots=False)

    try:
        for index, source_pass in ((100, 2), (250, 3)):  # the publisher may skip a pass's first frame
            push(index, source_pass)
            assert f"pass {source_pass} (it loops" in con.status_html.content, con.status_html.content
        push(5, 1)  # an operator's Restart: pass 1 again
        assert "pass" not in con.status_html.content
        push(120, 2)
        said = [body for title, body in con.notifications if "starts over" in body]
        assert len(said) == 2 and "loops" in said[0], con.notifications  # once, and once after the Restart
    finally:
        running.stop()


def test_why_automatic_selection_started_none_pops_up_once_whole() -> None:
    # The reason on the targets line is cut to two lines of the panel, its cause (a setting's
    # name) at the end, and a phone has no hover for the whole (an outside console probe): it
    # pops up whole, once, until selection starts a target or is switched off and on.
    from trackmeter.pipeline.snapshot import PoseEstimate, Snapshot, Timings
    from trackmeter.sources.base import StereoFrame

    running = start_console(CountingSource(3), RecordingEngine(), port=free_port())  # type: ignore[arg-type]
    con = running.console
    img = np.zeros((8, 8), np.uint8)
    deadline = time.monotonic() + 10
    while running.pipeline.latest().source_status != "ended":
        assert time.monotonic() < deadline
        time.sleep(0.02)
    time.sleep(0.5)

    def push(index: int, auto: bool, why: str | None) -> None:
        con._push(Snapshot(StereoFrame(index, index / 25.0, img, img), (), PoseEstimate.invalid("x"), None, Timings(),
                           auto_enabled=auto, auto_shortfall=why), plots=False)

    reason = "no room for a patch: features.target_margin_px or features.border_px leave no pixel of the lit target"
    try:
        for index, (auto, why) in enumerate([(True, reason), (True, reason), (True, "another"), (True, None),
                                             (True, reason), (False, reason), (True, reason)]):
            push(index, auto, why)
        said = [(title, body) for title, body in con.notifications if title == "Automatic selection"]
        assert said == [("Automatic selection", f"started no target: {reason}")] * 3, said
    finally:
        running.stop()


def test_left_and_right_images_that_look_swapped_pop_up_once(estec_sim_frames) -> None:
    # cam0 and cam1 exchanged: the operator saw every click refused and no word of why (an
    # outside probe; track and measure say it on stderr).
    import dataclasses

    from trackmeter.pipeline.snapshot import PoseEstimate, Snapshot, Timings

    rig, frames = estec_sim_frames
    running = start_console(CountingSource(3), RecordingEngine(), port=free_port(), rig=rig)  # type: ignore[arg-type]
    con = running.console
    deadline = time.monotonic() + 10
    while running.pipeline.latest().source_status != "ended":
        assert time.monotonic() < deadline
        time.sleep(0.02)
    time.sleep(0.5)
    try:
        for f in frames[:3]:
            swapped = dataclasses.replace(f, left=f.right, right=f.left)
            con._push(Snapshot(swapped, (), PoseEstimate.invalid("x"), None, Timings()), plots=False)
        said = [(title, body) for title, body in con.notifications if title == "Stereo pair"]
        assert len(said) == 1 and said[0][1].startswith("the left and right images look swapped"), con.notifications
    finally:
        running.stop()


def test_a_toggle_s_reply_with_something_to_say_is_shown() -> None:
    # Choosing the centroid method answered nothing in the browser: a toggle's success is
    # shown by the widget, and its note (one point a bright region) went with the pop-up.
    from trackmeter.pipeline.snapshot import CommandReply

    running = start_console(CountingSource(3), RecordingEngine(), port=free_port())  # type: ignore[arg-type]
    con = running.console
    try:
        for reply in (CommandReply(True, "automatic selection on (10 targets, gabor)"),
                      CommandReply(True, "automatic selection on (10 targets, centroid: one a bright region, its "
                                         "centroid)", notable=True)):
            future: Future[CommandReply] = Future()
            future.set_result(reply)
            with con._pending_lock:
                con._pending.append((future, None, "SetAuto"))
            con._flush_replies()
        shown = [body for _, body in con.notifications if "automatic selection" in body]
        assert shown == ["automatic selection on (10 targets, centroid: one a bright region, its centroid)"], shown
        # A selection of model points too few for a pose is partly done, not "refused" (one was
        # made: an outside console probe).
        for reply in (CommandReply(False, "1 model point selected (m0); 16 refused", partial=True),
                      CommandReply(False, "0 model points selected; 17 refused")):
            future = Future()
            future.set_result(reply)
            with con._pending_lock:
                con._pending.append((future, None, "SelectModelPoints"))
            con._flush_replies()
        titles = [title for title, _ in con.notifications if title.startswith("Click the model points")]
        assert titles == ["Click the model points: partly done", "Click the model points: refused"], titles
    finally:
        running.stop()


def test_a_record_folder_expands_home_and_numbers_on_from_a_numbered_one(tmp_path, monkeypatch) -> None:
    # "~/rec" made a folder named "~" where the server runs; with the Folder field showing the
    # last recording (rec-2), the next went to rec-2-2 (an outside console probe).
    monkeypatch.setenv("HOME", str(tmp_path))
    running = start_console(CountingSource(3), RecordingEngine(), port=free_port())  # type: ignore[arg-type]
    con = running.console
    try:
        con.record_dir.value = "~/rec"
        assert con._fresh_record_dir() == str(tmp_path / "rec")
        for name in ("rec", "rec-2"):
            (tmp_path / name / "cam0").mkdir(parents=True)
            (tmp_path / name / "cam0" / "data.csv").write_text("#timestamp [ns],filename\n")
        assert con._fresh_record_dir() == str(tmp_path / "rec-3")
        con.record_dir.value = str(tmp_path / "rec-2")
        assert con._fresh_record_dir() == str(tmp_path / "rec-3")
    finally:
        running.stop()


def test_a_recording_folder_whose_name_is_not_utf8_is_shown_escaped_and_the_page_stays_up(tmp_path) -> None:
    """`--record` to a folder whose name has the bytes ff fe (or Record in a server folder so
    named): every message to the browser failed to encode (lone surrogates), 800 tracebacks
    a minute, and no page could connect (an outside probe). The name is shown with its bytes
    escaped; the recording still goes to the folder so named, and the next one numbers on
    from it."""
    from trackmeter.pipeline.snapshot import SetRecording

    folder = tmp_path / os.fsdecode(b"rec_\xff\xfe")
    running = start_console(CountingSource(100_000, delay_s=0.02), RecordingEngine(), port=free_port())  # type: ignore[arg-type]
    con = running.console
    shown: list[tuple[str, str]] = []
    browser = types.SimpleNamespace(client_id=1, add_notification=lambda title, body, **k: shown.append((title, body)))
    try:
        reply = con.submit(SetRecording(str(folder)), browser, "SetRecording").result(10)
        assert reply.ok, reply.message
        _wait_for_pushes(con, 5)
        before = con.images_pushed
        _wait_for_pushes(con, 5)  # the publisher goes on
        assert con.images_pushed > before
        for text in (con.record_md.content, con.record_dir.value, con.status_html.content, *shown[-1]):
            text.encode("utf-8")  # what viser's msgpack needs: no lone surrogate
        assert "rec_\\xff\\xfe" in con.record_dir.value and "rec_\\xff\\xfe" in shown[-1][1]
        stop = con.submit(SetRecording(None), browser, "SetRecording").result(10)
        assert stop.ok, stop.message
        assert (folder / "cam0" / "data.csv").is_file()
        # the field's escaped text means the folder itself, which holds a recording now
        assert con._fresh_record_dir() == str(folder.with_name(folder.name + "-2"))
        # and edited, the escapes still stand for the bytes (not a folder named with backslashes)
        con.record_dir.value = con.record_dir.value + "/take2"
        assert con._fresh_record_dir() == str(folder / "take2")
    finally:
        running.stop()


def _popup_browser(client_id: int, removed: list[tuple[int, str]]) -> Any:
    """A browser double whose pop-ups, when removed, append ``(client_id, title)`` to ``removed``."""
    def add(title: str, body: str, **kwargs: Any) -> Any:
        return types.SimpleNamespace(remove=lambda: removed.append((client_id, title)))
    return types.SimpleNamespace(client_id=client_id, add_notification=add)


def _console_with_two_browsers(removed: list[tuple[int, str]]) -> tuple[Any, Any, Any]:
    """A running console (stop it) and two browser doubles connected to it (:func:`_popup_browser`)."""
    running = start_console(CountingSource(3), RecordingEngine(), port=free_port())  # type: ignore[arg-type]
    browsers = _popup_browser(1, removed), _popup_browser(2, removed)
    for client in browsers:
        running.console._on_connect(client)
    return running, *browsers


def test_a_pop_up_for_a_browser_gone_before_its_answer_is_not_kept() -> None:
    # A browser closed while its answer was pending (a refusal settling, a command's reply) left
    # its pop-up in Console._popups for good, one entry per such browser (an outside code review).
    removed: list[tuple[int, str]] = []
    running, staying, gone = _console_with_two_browsers(removed)
    con = running.console
    try:
        con._on_disconnect(gone)
        for _ in range(2):
            con._notify(staying, "Automatic selection: refused", "'abc' is not a whole number", False)
            con._notify(gone, "Automatic selection: refused", "'abc' is not a whole number", False)
        assert list(con._popups) == [1]
        assert [cid for cid, _ in removed] == [1]  # the staying browser's first pop-up gave way to its second
    finally:
        running.stop()


def test_viser_s_warning_of_a_pop_up_for_a_closed_browser_is_left_out_and_no_other() -> None:
    """A reply's pop-up to a browser that had just reloaded reached the server's terminal as
    viser's 'Queued a NotificationShowMessage on a closed connection' warning (an outside monkey
    probe): left out; any other warning still shows."""
    import warnings

    from console.server import quiet_dead_client_warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        quiet_dead_client_warnings()
        warnings.warn("Queued a NotificationShowMessage on a closed connection (e.g. via a handle owned by a "
                      "disconnected client, or after the server stopped); it will never be delivered.", UserWarning)
        warnings.warn("something else", UserWarning)
    assert [str(w.message) for w in caught] == ["something else"]


def test_a_pop_up_is_closed_by_the_console_when_its_time_is_up(monkeypatch: pytest.MonkeyPatch) -> None:
    """The browser's own timer stops while the pointer rests on a pop-up, and they stack at the
    image's top-left, where the operator clicks: a refusal stayed over the image 30 s, catching
    those clicks (an outside console probe). The console closes each itself once its time is
    up; one still in its time stays."""
    import console.app

    removed: list[tuple[int, str]] = []
    running, quick, slow = _console_with_two_browsers(removed)
    con = running.console
    try:
        monkeypatch.setattr(console.app, "POPUP_REFUSED_S", 0.0)
        monkeypatch.setattr(console.app, "POPUP_GRACE_S", 0.0)
        con._notify(quick, "Remove target near (40, 40): refused", "no target within 20 px", False)
        monkeypatch.setattr(console.app, "POPUP_OK_S", 60.0)
        con._notify(slow, "Target a1", "measured", True)
        deadline = time.monotonic() + 5.0
        while not removed and time.monotonic() < deadline:  # the publisher closes it within 0.1 s
            time.sleep(0.02)
        assert removed == [(1, "Remove target near (40, 40): refused")]
        assert list(con._popups) == [2] and list(con._popup_close_at) == [2]
    finally:
        running.stop()
