"""Speed and accuracy benchmarks: ``python -m benchmarks [NAME ...] [--out FILE]``.

Each benchmark is a module ``benchmarks/<name>.py`` with ``run() -> dict[str, float]``
returning its figures: medians over repeats, and ratios against a baseline measured in the
same run so the machine's noise cancels. Progress goes to stderr; the JSON object
``{NAME: {figure: value}}`` to stdout (and ``--out``).
"""

from __future__ import annotations

import statistics
import time
from typing import Callable

#: Benchmarks in the order ``python -m benchmarks`` runs them.
NAMES: tuple[str, ...] = ("measure", "render", "tracker", "accuracy", "pipeline", "soak", "console", "sequence_write")


def median_ms(fn: Callable[[], object], repeats: int = 21, warmup: int = 3) -> float:
    """Median wall time of ``fn()`` in milliseconds over ``repeats`` calls after ``warmup``."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append((time.perf_counter() - start) * 1e3)
    return float(statistics.median(times))
