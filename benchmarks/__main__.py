"""Run benchmarks and print one JSON object of their figures (see ``benchmarks/__init__``)."""

from __future__ import annotations

import argparse
import contextlib
import importlib
import importlib.util
import json
import math
import numbers
import os
import sys
import time
import traceback
from pathlib import Path
from typing import NoReturn

from benchmarks import NAMES, READS_CONFIG, bench_config, config_note
from trackmeter.errors import TrackmeterError


def figures_for_json(name: str, figures: dict) -> dict[str, float | None]:
    """Benchmark ``name``'s figures as the JSON contract has them: one number per figure (a
    bool or int becomes a float), ``null`` where it is not finite (NaN is not JSON: strict
    readers refuse the whole object). A value that is not a number is left out, with a warning
    naming it: a benchmark's bug must not cost the other figures of a long run."""
    out: dict[str, float | None] = {}
    for key, value in figures.items():
        if isinstance(value, numbers.Real):  # numpy's scalars too
            v = float(value)
            out[key] = v if math.isfinite(v) else None
        else:
            print(f"[benchmarks] {name}: figure {key} is not a number ({type(value).__name__}): left out",
                  file=sys.stderr, flush=True)
    return out


class _Parser(argparse.ArgumentParser):
    """argparse that reports a usage error as one line and exit code 2, as the trackmeter
    commands do (it printed the usage line above it)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


def out_problem(path: Path) -> str | None:
    """Why the JSON could not be written to ``path`` (``--out``), else None: said before any
    benchmark runs, not after a run of up to 40 minutes, whose file was then lost to a
    traceback (a folder given, or a file where a folder must be)."""
    if path.is_dir():
        return f"--out {path}: is a folder; give the JSON file's name, e.g. {path / 'benchmarks.json'}"
    parent = path.parent
    while not parent.exists() and parent != parent.parent:  # the folders --out makes
        parent = parent.parent
    if not parent.is_dir():
        return f"--out {path}: {parent} is a file, not a folder"
    if not os.access(parent, os.W_OK | os.X_OK):
        return f"--out {path}: {parent} is not writable"
    return None


def main(argv: list[str] | None = None) -> int:
    parser = _Parser(
        prog="python -m benchmarks", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="Run from the repository's root (the benchmarks folder is not installed with the package).\n"
               "Long ones: soak runs 10 minutes of live pipeline by design; accuracy took 3-13 minutes on the\n"
               "project's 2-core machines (172 s on 2026-12-02's), looks about 2; console drives a headless\n"
               "Chromium (the Debian package chromium) through Playwright (the test extra), checked before any runs.\n"
               "A benchmark that fails costs only its own figures: the others' are printed and written, exit 1;\n"
               "Ctrl-C keeps those finished before it (exit 130). The figures and their goals: README.md's results table.")
    parser.add_argument("names", nargs="*", metavar="NAME", help=f"benchmarks to run (default: all): {', '.join(NAMES)}")
    parser.add_argument("--out", type=Path, help="also write the JSON to this file")
    args = parser.parse_args(argv)
    if args.out is not None and (problem := out_problem(args.out)):
        print(f"python -m benchmarks: error: {problem}", file=sys.stderr)
        return 2
    names = args.names or [n for n in NAMES if importlib.util.find_spec(f"benchmarks.{n}") is not None]
    unknown = [n for n in names if n not in NAMES]
    if unknown:
        print(f"python -m benchmarks: error: unknown benchmark {', '.join(unknown)} (known: {', '.join(NAMES)})", file=sys.stderr)
        return 2
    note = config_note(names)
    if note:
        print(f"[benchmarks] note: {note}", file=sys.stderr, flush=True)
    if any(n in READS_CONFIG for n in names):
        try:
            bench_config()  # a bad file refused now, not after the benchmarks before its first reader
        except TrackmeterError as exc:
            print(f"python -m benchmarks: error: {exc}", file=sys.stderr)
            return 2
    modules = {}
    for name in names:  # all before the first runs: a missing one is not found an hour in
        try:
            modules[name] = importlib.import_module(f"benchmarks.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"benchmarks.{name}":
                print(f"python -m benchmarks: error: benchmark {name} is not built yet", file=sys.stderr)
                return 2
            raise
    unmet = [(name, why) for name, module in modules.items() if (why := getattr(module, "unmet", lambda: None)())]
    if unmet:
        print(f"python -m benchmarks: error: {'; '.join(f'{name} needs {why}' for name, why in unmet)} "
              f"(or name the benchmarks to run without {'it' if len(unmet) == 1 else 'them'})", file=sys.stderr)
        return 2
    results: dict[str, dict[str, float | None]] = {}
    failed: list[str] = []
    interrupted = False
    for name, module in modules.items():
        print(f"[benchmarks] {name} ...", file=sys.stderr, flush=True)
        start = time.perf_counter()
        # stdout carries the JSON alone: whatever a benchmark's libraries print (viser's banner)
        # goes to stderr with the progress.
        try:
            with contextlib.redirect_stdout(sys.stderr):
                results[name] = figures_for_json(name, module.run())
        except TrackmeterError as exc:  # bad input (e.g. TRACKMETER_BENCH_CONFIG): one line, no traceback
            print(f"python -m benchmarks: error: {name}: {exc}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:  # the figures measured so far are kept (below)
            print(f"[benchmarks] {name} interrupted", file=sys.stderr, flush=True)
            interrupted = True
            break
        except Exception as exc:  # one benchmark's failure must not cost the others' figures
            traceback.print_exc()
            print(f"[benchmarks] {name} failed after {time.perf_counter() - start:.1f} s", file=sys.stderr, flush=True)
            failed.append(f"{name} ({exc.__class__.__name__}: {exc})")
            continue
        print(f"[benchmarks] {name} done in {time.perf_counter() - start:.1f} s", file=sys.stderr, flush=True)
    text = json.dumps(results, indent=2, sort_keys=True, allow_nan=False)
    print(text)
    unwritten = False
    if args.out:
        from trackmeter.data.atomic import write_text_atomic

        try:
            args.out.parent.mkdir(parents=True, exist_ok=True)
            write_text_atomic(args.out, text + "\n")
        except OSError as exc:  # checked before the run; changed since (a full disk, a folder removed)
            # Said before the lines below, which stay last: a caller reads the last one.
            print(f"python -m benchmarks: error: --out {args.out}: cannot write ({exc.strerror or exc}); "
                  "the figures are above", file=sys.stderr)
            unwritten = True
    if interrupted:
        print(f"python -m benchmarks: interrupted: the figures of {len(results)} benchmark(s) finished before it "
              "are above", file=sys.stderr)
        return 130
    if failed:
        # The last line: what a caller (benchmarks.reproduce) shows for the missing figures.
        print(f"python -m benchmarks: error: {len(failed)} of {len(names)} failed: {'; '.join(failed)} "
              "(the others' figures are in the JSON)", file=sys.stderr)
    return 2 if unwritten else 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
