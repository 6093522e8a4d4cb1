"""Helpers shared by the subcommands: config loading, argument parsing, progress."""

from __future__ import annotations

import argparse
import math
import sys
import time
from typing import TYPE_CHECKING, Any, Iterable, Iterator, TextIO, TypeVar

from trackmeter.errors import TrackmeterError

if TYPE_CHECKING:
    from trackmeter.core.stereo import StereoRig
    from trackmeter.data.config import Config
    from trackmeter.sources.base import Source

T = TypeVar("T")


def rig_help(default: str, sized_by: str = "the source's frames") -> str:
    """The ``--rig`` option's help, the same in every command: the files it takes; ``default``
    what is used without it, ``sized_by`` what gives a file without the image size its size."""
    return (f"stereo rig file or a preset's name (config/rigs/) ({default}): a rig.yaml (OpenCV FileStorage), "
            "OpenCV's intrinsics.yml or extrinsics.yml (the other beside it), a Kalibr camchain.yaml or a "
            f"Middlebury calib.txt; one without the image size is sized by {sized_by}")


def load_config_from_args(args: argparse.Namespace) -> Config:
    """The configuration: ``config/default.yaml`` with ``--config`` layered over it."""
    from trackmeter.data.config import load_config

    return load_config(getattr(args, "config", None))


def open_source_with_rig(spec: str, rig_path: str | None, realtime: bool = False, loop: bool = False,
                         own_model: bool = True, model_optional: bool = False) -> Source:
    """Open the source SPEC for a command that measures on its frames, with its rig checked.

    The rig is the file ``rig_path`` (``--rig``) when given, else the one the source carries.
    It is read once the source is open, so that a rig file without an image size (OpenCV's
    ``intrinsics.yml``/``extrinsics.yml`` pair) takes the size of the source's frames
    (:attr:`Source.frame_size`, from its first frame). Frames of another size than the rig's
    are refused here, before anything is tracked or written: every pixel of the rig's
    calibration would be wrong for them.

    Args:
        spec: a source SPEC (DESIGN.md section 6).
        rig_path: the ``--rig`` file, or None.
        realtime, loop: as :func:`trackmeter.sources.open_source`.
        own_model: False: the source's own model (a sequence folder's ``model.yaml``) is not
            read (``--model`` given, or a command that needs none). With ``rig_path``, the
            folder's ``rig.yaml`` is not read either: a broken file there stops nothing.
        model_optional: the command may run without the source's model: one that cannot be
            read is warned about and left out.

    Returns:
        The open source, its ``rig`` replaced by ``rig_path``'s when given (may still be None
        when the source carries none: the caller says what is missing).

    Raises:
        TrackmeterError: a bad SPEC or rig file, or frames that do not match the rig (the
            source is closed).
    """
    from trackmeter.data.rigfile import load_rig
    from trackmeter.sources import open_source

    source = open_source(spec, realtime=realtime, loop=loop, own_rig=not rig_path, own_model=own_model,
                         model_optional=model_optional)
    try:
        size = source.frame_size
        problem = getattr(source, "frame_size_problem", None) if size is None else None
        if problem:
            # Refused here, not after reading every pair for nothing (and writing an empty run).
            raise TrackmeterError(f"source {spec!r}: no stereo pair plays (two images that read, of one size); "
                                  f"the first: {problem}")
        if rig_path:
            source.rig = load_rig(rig_path, image_size=size)
            _warn_rig_not_rendered_through(source, rig_path, spec)
        rig = source.rig
        if rig is not None and size is not None and tuple(size) != rig.image_size:
            where = f"--rig {rig_path}" if rig_path else f"the rig {spec} carries; give the right one with --rig"
            raise TrackmeterError(f"frame {size[0]}x{size[1]} does not match the rig's image size "
                                  f"{rig.image_size[0]}x{rig.image_size[1]} ({where})")
        if rig is not None:
            check_rig_side_by_side(rig, rig_path or f"the rig of {spec}")
    except BaseException:
        source.close()
        raise
    return source


def _warn_rig_not_rendered_through(source: Source, rig_path: str, spec: str) -> None:
    """Warn when ``--rig`` is not the rig a simulator renders through (its ``true_rig``): the
    simulator reports the rig it is given, for a miscalibration on purpose, and its images
    stay those of the scenario's own (measured as the other's, depths a metre off)."""
    import warnings

    import numpy as np

    true_rig = getattr(source, "true_rig", None)
    rig = source.rig
    if true_rig is None or rig is None:
        return

    def close(a: Any, b: Any) -> bool:
        a, b = np.ravel(a), np.ravel(b)
        return a.shape == b.shape and bool(np.allclose(a, b, rtol=1e-9, atol=1e-12))

    pairs = ((rig.left.K, true_rig.left.K), (rig.right.K, true_rig.right.K), (rig.left.dist, true_rig.left.dist),
             (rig.right.dist, true_rig.right.dist), (rig.R, true_rig.R), (rig.T, true_rig.T))
    if all(close(a, b) for a, b in pairs):
        return
    scenario_rig = getattr(getattr(source, "scenario", None), "rig", "its own")
    differ = (f"focal length {rig.left.K[0, 0]:.0f} px where the images' is {true_rig.left.K[0, 0]:.0f} px, baseline "
              f"{np.linalg.norm(rig.T) * 1e3:.1f} mm where theirs is {np.linalg.norm(true_rig.T) * 1e3:.1f} mm")
    warnings.warn(f"source {spec!r} renders through its scenario's rig ({scenario_rig}); --rig {rig_path} is only "
                  f"what it reports ({differ}): a miscalibration on purpose; to render through it, name it as rig: "
                  "in a scenario file (sim:FILE)", stacklevel=3)
    # Also the source's standing warning, which the console's status box shows (the operator
    # sees no terminal); said once here, so a command does not repeat it as news.
    said = f"measured as --rig {rig_path}, rendered through the scenario's rig ({differ})"
    before = getattr(source, "warning", None)
    source.warning = f"{before}; {said}" if before else said  # type: ignore[attr-defined]


def check_rig_side_by_side(rig: StereoRig, named: str) -> None:
    """Refuse a rig whose cameras cannot be matched along rows (swapped, one above the other),
    the message starting with ``named``, the rig's file: the core says what is wrong with the
    rig (:func:`trackmeter.core.stereo.check_side_by_side`) but not which file it came from."""
    from trackmeter.core.stereo import check_side_by_side

    try:
        check_side_by_side(rig)
    except TrackmeterError as exc:
        raise TrackmeterError(f"{named}: {exc}") from None


def source_warning_since(source: object, warning_at_open: str | None) -> str | None:
    """What the source says now (``Source.warning``) beyond what it said when opened, which
    was printed then: a pair skipped while reading, not the opening warning again in front of
    it. None when there is nothing new."""
    warning = getattr(source, "warning", None)
    if not warning or warning == warning_at_open:
        return None
    if warning_at_open and warning.startswith(f"{warning_at_open}; "):
        return warning[len(warning_at_open) + 2:]
    return warning


def parse_uv(text: str) -> tuple[float, float]:
    """``"U,V"`` → ``(u, v)`` in px; raises TrackmeterError with the offending text (also for
    ``nan`` or ``inf``, which ``float`` accepts but no pixel is)."""
    parts = text.split(",")
    try:
        if len(parts) != 2:
            raise ValueError
        u, v = float(parts[0]), float(parts[1])
        if not (math.isfinite(u) and math.isfinite(v)):
            raise ValueError
        return u, v
    except ValueError:
        raise TrackmeterError(f"expected a pixel as U,V (two finite numbers), got {text!r}") from None


#: Seconds between two progress lines when stderr is not a terminal (a log, a pipe).
PLAIN_PROGRESS_S = 30.0


def plain_progress_due(last_s: float, now_s: float) -> bool:
    """Whether a progress line is due on a stream that is not a terminal: one every
    :data:`PLAIN_PROGRESS_S` (a redrawn bar would fill a log), so a long run piped to a file
    still says it is alive."""
    return now_s - last_s >= PLAIN_PROGRESS_S


def progress(items: Iterable[T], total: int | None, label: str, stream: TextIO | None = None) -> Iterator[T]:
    """Yield ``items`` while drawing a one-line progress bar on a terminal; elsewhere (a log,
    a pipe) a plain line every :data:`PLAIN_PROGRESS_S` seconds.

    ``stream`` defaults to the ``sys.stderr`` of the moment of the call (not of import), so
    redirected or captured stderr is honoured.
    """
    if stream is None:
        stream = sys.stderr
    if not stream.isatty():
        start = last = time.monotonic()
        for count, item in enumerate(items, 1):
            yield item
            now = time.monotonic()
            if plain_progress_due(last, now):
                last = now
                stream.write(f"{label}: {count}{f'/{total}' if total else ''} after {now - start:.0f} s\n")
                stream.flush()
        return
    start = time.monotonic()
    first_done = start
    count = 0
    try:
        for count, item in enumerate(items, 1):
            yield item
            now = time.monotonic()
            elapsed = now - start
            if count == 1:
                first_done = now  # the first item carries the start-up: the rate is taken after it
            if total:
                bar = "#" * int(30 * count / total)
                eta = f"{(now - first_done) / (count - 1) * (total - count):5.1f}s" if count > 1 else "    -"
                stream.write(f"\r{label} [{bar:<30}] {count}/{total} {elapsed:5.1f}s eta {eta}")
            else:
                stream.write(f"\r{label} {count} {elapsed:5.1f}s")
            stream.flush()
    finally:
        # Also when the loop is left early (Ctrl-C, an error): the message that follows then
        # starts its own line, not at the end of the bar.
        stream.write("\n")
        stream.flush()
