"""CPU priority of the live pipeline over interactive programs sharing the machine.

Why: the operator's browser may run on the same computer as the tracker. A browser drawing a
WebGL scene without a GPU takes every core it is given, and on Linux it does not compete with
the tracker thread by thread: with *autogroup* scheduling (``/proc/sys/kernel/sched_autogroup_enabled``,
on by default on desktop kernels) every session is one scheduling group, and groups share the
CPUs equally. Chromium starts in a session of its own, so on two cores it gets one core and the
tracker's whole process (tracking, publishing, and the simulator's renderer) the other, whatever
their ``nice``. Measured (``benchmarks/console.py``'s setup, ``sim`` source, one headless
Chromium): 8-17 Hz tracking at equal priority, 25.0 Hz with the tracker's session at nice -10.
The other side of it: on a slow host a browser beside a tracker at nice -10 may not get the CPU
to open the page at all, so ``trackmeter console`` raises it only when asked (``--cpu-nice``).

:func:`raise_cpu_priority` lowers the nice value of every thread of this process (threads
started later inherit it from the thread that starts them) and of the session's autogroup; a
process that is not allowed to (neither root nor ``CAP_SYS_NICE``) gets a one-line reason and
runs as before. :func:`autogroup_follows_nice` lets a child started in a session of its own
(the simulator's render worker, which stands in for the cameras' own hardware) give that
session the priority it inherited. Linux only; elsewhere both report that nothing was done.

The autogroup belongs to the session (a terminal's, when started from one), not to the
process: :func:`restore_cpu_priority` gives it back, and ``trackmeter console`` does so when it
stops; a process killed outright leaves its session at the raised priority until it ends.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

_TASKS = Path("/proc/self/task")
_AUTOGROUP = Path("/proc/self/autogroup")


@dataclass(frozen=True)
class PriorityChange:
    """What :func:`raise_cpu_priority` did.

    Attributes:
        applied: the threads now run at the requested nice value.
        message: one line for the log: what was set, or why not.
        previous_nice: per thread id, the nice value before (to restore).
        previous_autogroup_nice: the session's autogroup nice before, None when not changed.
    """

    applied: bool
    message: str
    previous_nice: dict[int, int]
    previous_autogroup_nice: int | None


def _thread_ids() -> list[int]:
    try:
        return sorted(int(t) for t in os.listdir(_TASKS))
    except OSError:
        return []


def _read_autogroup_nice() -> int | None:
    """The nice value in ``/proc/self/autogroup`` (``/autogroup-502 nice 0``), None without one."""
    try:
        return int(_AUTOGROUP.read_text().split()[-1])
    except (OSError, ValueError, IndexError):
        return None


def _write_autogroup_nice(nice: int) -> None:
    _AUTOGROUP.write_text(f"{nice}\n")


def raise_cpu_priority(nice: int) -> PriorityChange:
    """Run this process (all its threads) and its session's autogroup at ``nice`` (-20..19;
    lower runs first). Never raises: a refusal (no privilege, not Linux) is reported in
    :attr:`PriorityChange.message` and leaves everything as it was."""
    if not -20 <= nice <= 19:
        return PriorityChange(False, f"nice must be in -20..19, got {nice}", {}, None)
    tids = _thread_ids()
    if not tids or not hasattr(os, "setpriority"):
        return PriorityChange(False, "CPU priority left alone (per-thread priorities need Linux)", {}, None)
    previous: dict[int, int] = {}
    try:
        for tid in tids:
            previous[tid] = os.getpriority(os.PRIO_PROCESS, tid)
            os.setpriority(os.PRIO_PROCESS, tid, nice)
    except OSError as exc:  # PermissionError without CAP_SYS_NICE; a thread that just ended
        _restore_threads(previous)
        return PriorityChange(False, f"CPU priority left alone: cannot set nice {nice} ({exc.strerror or exc}); "
                                     "the tracker shares the CPUs equally with other programs", {}, None)
    group_before = _read_autogroup_nice()
    group_note = ""
    if group_before is not None:
        try:
            _write_autogroup_nice(nice)
        except OSError as exc:
            group_before = None
            group_note = f"; session autogroup left alone ({exc.strerror or exc})"
    else:
        group_note = "; no autogroup scheduling"
    return PriorityChange(True, f"CPU priority raised: nice {nice} for {len(previous)} threads"
                                + ("" if group_note else " and this session's autogroup") + group_note,
                          previous, group_before)


def restore_cpu_priority(change: PriorityChange) -> None:
    """Undo :func:`raise_cpu_priority` for the threads that still exist (best effort)."""
    _restore_threads(change.previous_nice)
    if change.previous_autogroup_nice is not None:
        try:
            _write_autogroup_nice(change.previous_autogroup_nice)
        except OSError:
            pass


def _restore_threads(previous: dict[int, int]) -> None:
    for tid, value in previous.items():
        try:
            os.setpriority(os.PRIO_PROCESS, tid, value)
        except OSError:
            pass  # the thread has ended, or raising nice back is not allowed: nothing to undo


def autogroup_follows_nice() -> bool:
    """Give this process's autogroup (its session's scheduling group) the nice value this
    process was started with, when that is below the group's: for a child started in a new
    session (``start_new_session``) by a process that raised its priority. True when set."""
    if not hasattr(os, "getpriority"):
        return False
    nice = os.getpriority(os.PRIO_PROCESS, 0)
    group = _read_autogroup_nice()
    if group is None or nice >= group:
        return False
    try:
        _write_autogroup_nice(nice)
    except OSError:
        return False
    return True
