"""Speed and accuracy benchmarks: ``python -m benchmarks [NAME ...] [--out FILE]``.

Each benchmark is a module ``benchmarks/<name>.py`` with ``run() -> dict[str, float]``
returning its figures: medians over repeats, and ratios against a baseline measured in the
same run so the machine's noise cancels. Progress goes to stderr; the JSON object
``{NAME: {figure: value}}`` to stdout (and ``--out``): every value one number, ``null`` where
it is not finite (strict JSON: no NaN), a per-seed or per-bin series as numbered figures
(``..._seed0``, ``..._bin0_...``).

The benchmarks that run the tracking engine (``accuracy``, ``looks``, ``operator``, ``error_budget``) use
config/default.yaml, or a YAML file layered over it (as ``--config`` does for the commands)
named by the environment variable ``TRACKMETER_BENCH_CONFIG``: how an opt-in setting of
docs/results.md is measured on the same chain, e.g.
``TRACKMETER_BENCH_CONFIG=smooth.yaml TRACKMETER_ACCURACY_SEEDS=7 python -m benchmarks accuracy``.
``benchmarks.reproduce`` (the README table) always runs the defaults.
"""

from __future__ import annotations

import os
import statistics
import time
from typing import TYPE_CHECKING, Callable

if TYPE_CHECKING:
    from trackmeter.data.config import Config

#: Benchmarks in the order ``python -m benchmarks`` runs them.
NAMES: tuple[str, ...] = ("measure", "render", "select", "tracker", "operator", "accuracy", "looks", "pipeline", "soak", "console", "sequence_write")


#: Environment variable naming a YAML file layered over config/default.yaml for the benchmarks
#: that run the engine (:func:`bench_config`).
CONFIG_ENV = "TRACKMETER_BENCH_CONFIG"


#: The benchmarks that run the engine with :func:`bench_config` (the others, speed figures of
#: the code paths themselves, always run the defaults).
READS_CONFIG = frozenset({"accuracy", "operator", "looks", "error_budget"})


def config_note(names: list[str]) -> str | None:
    """One line when :data:`CONFIG_ENV` is set and some of ``names`` do not read it, naming
    them (the variable would otherwise seem to have been applied); None otherwise."""
    path = os.environ.get(CONFIG_ENV, "")
    others = [n for n in names if n not in READS_CONFIG]
    if not path or not others:
        return None
    readers = sorted(READS_CONFIG)
    return (f"{CONFIG_ENV} ({path}) is read by {', '.join(readers[:-1])} and {readers[-1]} only: "
            f"{', '.join(others[:-1]) + ' and ' if len(others) > 1 else ''}{others[-1]} "
            f"{'run' if len(others) > 1 else 'runs'} config/default.yaml")


def browser_unmet() -> str | None:
    """What a benchmark that drives the console in a headless browser lacks, said as the fix
    (Playwright, from the project's test extra, and the Debian package chromium), or None.

    Checked before any benchmark runs (a module's ``unmet()``): the console benchmark comes
    after 20 minutes of others, and its missing browser cost them all (no JSON was written)."""
    import importlib.util
    import shutil

    if importlib.util.find_spec("playwright") is None:
        return "Playwright (pip install -e '.[test]'; never 'playwright install')"
    if shutil.which("chromium") is None:
        return "the Debian package chromium (apt-get install chromium)"
    return None


def bench_config() -> Config:
    """The configuration a benchmark runs the engine with: the defaults, or the file named by
    :data:`CONFIG_ENV` layered over them.

    Raises:
        TrackmeterError: the file cannot be read or holds a bad key or value (the message
            names the variable).
    """
    from trackmeter.data.config import Config, load_config
    from trackmeter.errors import TrackmeterError

    path = os.environ.get(CONFIG_ENV, "")
    if not path:
        return Config()
    try:
        return load_config(path)
    except TrackmeterError as exc:
        raise TrackmeterError(f"{CONFIG_ENV}: {exc}") from exc


def median_ms(
    fn: Callable[[], object], repeats: int = 21, warmup: int = 3, clock: Callable[[], float] = time.perf_counter
) -> float:
    """Median time of ``fn()`` in milliseconds over ``repeats`` calls after ``warmup``.

    ``clock`` is wall time by default; :func:`median_cpu_ms` passes this thread's CPU time,
    which other processes on a shared machine do not inflate.
    """
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        start = clock()
        fn()
        times.append((clock() - start) * 1e3)
    return float(statistics.median(times))


def median_cpu_ms(fn: Callable[[], object], repeats: int = 101, warmup: int = 5) -> float:
    """Median CPU time of this thread per ``fn()`` call, ms (``time.thread_time``)."""
    return median_ms(fn, repeats, warmup, clock=time.thread_time)


def main_of(module: str, doc: str | None, run: Callable[[], dict[str, float]], sort_keys: bool = False) -> None:
    """``python -m benchmarks.<module>``: ``--help`` prints the module's docstring (a benchmark
    may take minutes, so asking must not start it); otherwise run it and print its figures as
    JSON."""
    import argparse
    import json
    import sys

    from trackmeter.errors import TrackmeterError

    argparse.ArgumentParser(prog=f"python -m benchmarks.{module}", description=doc,
                            formatter_class=argparse.RawDescriptionHelpFormatter).parse_args()
    try:
        figures = run()
    except TrackmeterError as exc:  # bad input (e.g. TRACKMETER_BENCH_CONFIG): one line, no traceback
        print(f"python -m benchmarks.{module}: error: {exc}", file=sys.stderr)
        sys.exit(2)
    print(json.dumps(figures, indent=1, sort_keys=sort_keys))
