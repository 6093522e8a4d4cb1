"""The direction of imports inside ``trackmeter/`` (DESIGN.md section 2), read from the source.

Bottom to top: core, data, sources (and the simulator), pipeline, cli. A module imports only
from its own layer and the ones below it; the package's top-level helpers sit at the layer
their work belongs to (``errors`` below them all, ``paths`` with data, ``signals`` and
``priority`` with the sources: core does no I/O). Nothing in ``trackmeter`` imports
``console`` or ``viser``, except the one command that starts the console. Imports inside
functions count (a lazy import still ties the layers together), and so do imports under
``if TYPE_CHECKING:``: they never run, but a type hint naming a higher layer's class makes the
lower layer's API depend on it (the core's Tracker took the sources layer's StereoFrame until an
outside review; the frame now lives in ``core.frames``).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "trackmeter"

#: Rank of each layer: a module may import from a rank at most its own.
LAYER_RANK = {"core": 1, "data": 2, "sources": 3, "pipeline": 4, "cli": 5}
#: The package's top-level helpers: the error type (pure) under everything; where the files
#: are, with the data layer; the process's signals and CPU priority (operating-system state,
#: not pure computation) with the sources. Anything else at the top (__init__) under everything.
TOP_LEVEL_RANK = 0
HELPER_RANK = {"errors": 0, "paths": 2, "signals": 3, "priority": 3}
#: ``trackmeter console`` is where the library meets the console: its command module starts it.
MAY_IMPORT_CONSOLE = {"trackmeter.cli.console"}


def rank_of(module: str) -> int | None:
    """Layer rank of a dotted module name inside ``trackmeter``; None for other packages."""
    parts = module.split(".")
    if parts[0] != "trackmeter":
        return None
    if len(parts) == 1:
        return TOP_LEVEL_RANK
    if parts[1] == "__main__":
        return LAYER_RANK["cli"]  # ``python -m trackmeter`` runs the command line
    return LAYER_RANK.get(parts[1], HELPER_RANK.get(parts[1], TOP_LEVEL_RANK))


def module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported_modules(source: str, module: str, is_package: bool = False) -> list[tuple[int, str]]:
    """(line, absolute module name) of every import in ``source``, the text of ``module``
    (lazy ones and type checkers' included); relative imports resolved."""
    package = module if is_package else module.rpartition(".")[0]
    found: list[tuple[int, str]] = []

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.Import):
            found.extend((node.lineno, alias.name) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            found.append((node.lineno, name))
            if name.count(".") <= 1 and name.startswith("trackmeter"):
                # ``from trackmeter import pipeline`` imports the subpackage it names.
                found.extend((node.lineno, f"{name}.{alias.name}") for alias in node.names)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(ast.parse(source))
    return found


def upward_imports(source: str, module: str, is_package: bool = False) -> list[str]:
    own = rank_of(module)
    assert own is not None
    wrong = []
    for line, name in imported_modules(source, module, is_package):
        top = name.split(".")[0]
        if top in ("console", "viser"):
            if module not in MAY_IMPORT_CONSOLE:
                wrong.append(f"line {line}: {name} (trackmeter never imports the console or viser)")
            continue
        rank = rank_of(name)
        if rank is not None and rank > own:
            wrong.append(f"line {line}: {name} (a layer above {module}'s)")
    return wrong


SOURCES = sorted(PACKAGE.rglob("*.py"))


def test_the_package_has_its_layers() -> None:
    names = {module_name(p) for p in SOURCES}
    assert {f"trackmeter.{layer}" for layer in LAYER_RANK} <= names


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(PACKAGE.parent)))
def test_imports_point_down(path: Path) -> None:
    wrong = upward_imports(path.read_text(encoding="utf-8"), module_name(path), path.name == "__init__.py")
    assert not wrong, f"{path.relative_to(PACKAGE.parent)} imports upward:\n" + "\n".join(wrong)


def test_the_check_sees_lazy_relative_and_console_imports() -> None:
    """Without these, the test above could never fail."""
    source = (
        "from typing import TYPE_CHECKING\n"
        "if TYPE_CHECKING:\n    from trackmeter.cli.main import main\n"
        "def f():\n    from ..pipeline import engine\n    import trackmeter.cli.main\n"
        "    from trackmeter import sources\n    import viser\n"
        "from .transforms import absolute_orientation\n")
    wrong = upward_imports(source, "trackmeter.core.pose")
    assert [w.split(":")[1].split()[0] for w in wrong] == [
        "trackmeter.cli.main", "trackmeter.pipeline", "trackmeter.pipeline.engine", "trackmeter.cli.main",
        "trackmeter.sources", "viser"]
    assert imported_modules(source, "trackmeter.core.pose")[-1] == (9, "trackmeter.core.transforms")
    assert upward_imports("import console.server\n", "trackmeter.cli.console") == []
    assert upward_imports("from trackmeter.cli import main\n", "trackmeter.__main__") == []
    assert upward_imports("from trackmeter.priority import raise_cpu_priority\n", "trackmeter.core.pose")
    assert upward_imports("from trackmeter.errors import TrackmeterError\n", "trackmeter.core.pose") == []


#: Modules outside ``trackmeter.pipeline`` that may start a thread, and why. The simulator's
#: render worker sends frames larger than a pipe's buffer: a thread drains its stdout so that it
#: renders ahead instead of stalling after each frame (the thread only copies bytes into a queue).
THREADS_OUTSIDE_PIPELINE = {"trackmeter.sources.sim.render_ahead"}


def thread_starts(source: str) -> list[int]:
    """Lines of ``source`` that make a thread or a pool of them (``threading.Thread(...)``,
    ``Thread(...)``, a ``ThreadPoolExecutor``, ``_thread.start_new_thread``)."""
    names = {"Thread", "ThreadPoolExecutor", "start_new_thread", "Timer"}
    lines = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Call):
            f = node.func
            name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else ""
            if name in names:
                lines.append(node.lineno)
    return lines


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(PACKAGE.parent)))
def test_threads_start_only_in_the_pipeline(path: Path) -> None:
    """The style's rule: threads only in the pipeline (the core and data layers are plain
    functions and objects a caller may use from any thread)."""
    module = module_name(path)
    if module.startswith("trackmeter.pipeline") or module in THREADS_OUTSIDE_PIPELINE:
        return
    lines = thread_starts(path.read_text(encoding="utf-8"))
    assert not lines, f"{path.relative_to(PACKAGE.parent)} starts a thread at line(s) {lines}"


def test_the_thread_check_sees_the_usual_spellings() -> None:
    source = ("import threading\nfrom concurrent.futures import ThreadPoolExecutor\n"
              "threading.Thread(target=print)\nThreadPoolExecutor(2)\nthreading.Timer(1, print)\n")
    assert thread_starts(source) == [3, 4, 5]
    assert thread_starts("import threading\nlock = threading.Lock()\n") == []
