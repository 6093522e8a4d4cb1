"""Helpers shared by the subcommands: config loading, argument parsing, progress."""

from __future__ import annotations

import argparse
import sys
import time
from typing import Iterable, Iterator, TypeVar

from trackmeter.errors import TrackmeterError

T = TypeVar("T")


def not_built_yet(name: str) -> int:
    """A subcommand whose engine has not landed yet: say so and exit 2."""
    print(f"trackmeter {name}: not built yet", file=sys.stderr)
    return 2


def load_config_from_args(args: argparse.Namespace):  # type: ignore[no-untyped-def]
    from trackmeter.data.config import load_config

    return load_config(getattr(args, "config", None))


def parse_uv(text: str) -> tuple[float, float]:
    """``"U,V"`` → ``(u, v)`` in px; raises TrackmeterError with the offending text."""
    parts = text.split(",")
    try:
        if len(parts) != 2:
            raise ValueError
        return float(parts[0]), float(parts[1])
    except ValueError:
        raise TrackmeterError(f"expected a pixel as U,V (two numbers), got {text!r}") from None


def progress(items: Iterable[T], total: int | None, label: str, stream=None) -> Iterator[T]:  # type: ignore[no-untyped-def]
    """Yield ``items`` while drawing a one-line progress bar on a terminal (silent otherwise).

    ``stream`` defaults to the ``sys.stderr`` of the moment of the call (not of import), so
    redirected or captured stderr is honoured.
    """
    if stream is None:
        stream = sys.stderr
    if not stream.isatty():
        yield from items
        return
    start = time.monotonic()
    count = 0
    for count, item in enumerate(items, 1):
        yield item
        elapsed = time.monotonic() - start
        if total:
            frac = count / total
            bar = "#" * int(30 * frac)
            eta = elapsed / frac - elapsed if frac > 0 else 0.0
            stream.write(f"\r{label} [{bar:<30}] {count}/{total} {elapsed:5.1f}s eta {eta:5.1f}s")
        else:
            stream.write(f"\r{label} {count} {elapsed:5.1f}s")
        stream.flush()
    stream.write("\n")
    stream.flush()
