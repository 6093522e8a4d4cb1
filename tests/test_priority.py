"""CPU priority of the live pipeline (trackmeter.priority): set, refused, restored."""

from __future__ import annotations

import os
import threading

import pytest

from trackmeter import priority as pr


class _FakeOS:
    """Per-thread nice values as the kernel keeps them; lowering below ``floor`` is refused."""

    def __init__(self, tids: list[int], floor: int = -20, refuse_tid: int | None = None) -> None:
        self.nice = {t: 0 for t in tids}
        self.floor = floor
        self.refuse_tid = refuse_tid

    def getpriority(self, which: int, who: int) -> int:
        return self.nice[who]

    def setpriority(self, which: int, who: int, value: int) -> None:
        if value < self.floor or who == self.refuse_tid:
            raise PermissionError(1, "Operation not permitted")
        self.nice[who] = value


@pytest.fixture
def fake(monkeypatch, tmp_path):
    def make(floor: int = -20, refuse_tid: int | None = None, autogroup: str | None = "/autogroup-7 nice 0\n"):
        fake_os = _FakeOS([11, 12, 13], floor, refuse_tid)
        monkeypatch.setattr(pr, "_thread_ids", lambda: [11, 12, 13])
        monkeypatch.setattr(pr.os, "getpriority", fake_os.getpriority)
        monkeypatch.setattr(pr.os, "setpriority", fake_os.setpriority)
        group = tmp_path / "autogroup"
        if autogroup is not None:
            group.write_text(autogroup)
        monkeypatch.setattr(pr, "_AUTOGROUP", group)
        return fake_os, group

    return make


def test_every_thread_and_the_session_autogroup_get_the_priority_and_get_it_back(fake):
    fake_os, group = fake()
    change = pr.raise_cpu_priority(-10)
    assert change.applied and "nice -10 for 3 threads and this session's autogroup" in change.message
    assert fake_os.nice == {11: -10, 12: -10, 13: -10}
    assert group.read_text().strip() == "-10"
    group.write_text("/autogroup-7 nice -10\n")  # what the kernel shows after the write
    pr.restore_cpu_priority(change)
    assert fake_os.nice == {11: 0, 12: 0, 13: 0}
    assert group.read_text().strip() == "0"


def test_without_the_privilege_nothing_changes_and_it_says_why(fake):
    fake_os, group = fake(floor=0)
    change = pr.raise_cpu_priority(-10)
    assert not change.applied and "left alone" in change.message and "not permitted" in change.message
    assert fake_os.nice == {11: 0, 12: 0, 13: 0}
    assert group.read_text() == "/autogroup-7 nice 0\n"


def test_a_refusal_halfway_undoes_the_threads_already_set(fake):
    fake_os, _ = fake(refuse_tid=13)
    change = pr.raise_cpu_priority(-5)
    assert not change.applied
    assert fake_os.nice == {11: 0, 12: 0, 13: 0}


def test_without_autogroup_scheduling_the_threads_are_still_set(fake):
    fake_os, _ = fake(autogroup=None)
    change = pr.raise_cpu_priority(-4)
    assert change.applied and "no autogroup" in change.message and change.previous_autogroup_nice is None
    assert set(fake_os.nice.values()) == {-4}


def test_out_of_range_is_refused():
    change = pr.raise_cpu_priority(-21)
    assert not change.applied and "-20..19" in change.message


def test_a_child_in_its_own_session_takes_its_inherited_nice_to_its_autogroup(fake, monkeypatch):
    _, group = fake()
    monkeypatch.setattr(pr.os, "getpriority", lambda which, who: -10)
    assert pr.autogroup_follows_nice()
    assert group.read_text().strip() == "-10"
    group.write_text("/autogroup-7 nice -10\n")
    assert not pr.autogroup_follows_nice()  # already there


@pytest.mark.skipif(not os.path.exists("/proc/self/task"), reason="per-thread priorities need Linux")
def test_on_this_system_a_higher_nice_is_always_allowed_and_restored():
    # Raising nice (lower priority) needs no privilege: the real system calls, both ways.
    stop = threading.Event()
    worker = threading.Thread(target=stop.wait)
    worker.start()
    try:
        before = os.getpriority(os.PRIO_PROCESS, worker.native_id)
        target = min(before + 2, 19)
        change = pr.raise_cpu_priority(target)
        assert change.applied, change.message
        assert os.getpriority(os.PRIO_PROCESS, worker.native_id) == target
        assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == target
        pr.restore_cpu_priority(change)
        if os.geteuid() == 0:  # lowering it back needs the privilege
            assert os.getpriority(os.PRIO_PROCESS, worker.native_id) == before
    finally:
        stop.set()
        worker.join()
