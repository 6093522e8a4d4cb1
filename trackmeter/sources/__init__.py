"""Where stereo frames come from: the simulator, sequence folders, video files, cameras.

:func:`open_source` turns a SPEC string (DESIGN.md section 6) into a :class:`Source`:

=========================  ===========================================================
``sim``                    the ``estec`` scenario rendered live (with ground truth)
``sim:SCENARIO.yaml``      a scenario file, or a bare name of ``config/scenarios/``
                           (``sim:harsh_light``)
``seq:DIR`` or ``DIR``     a sequence folder (EuRoC layout, also ``DIR/mav0/...``)
``video:LEFT,RIGHT``       two video files
``camera:I,J``             two camera devices, left and right
``camera:I``               one side-by-side stereo device (left half, right half)
=========================  ===========================================================
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

from trackmeter.core.stereo import StereoRig
from trackmeter.errors import TrackmeterError
from trackmeter.sources.base import GroundTruth, Source, StereoFrame

__all__ = ["GroundTruth", "Source", "StereoFrame", "open_source", "DEFAULT_SCENARIO"]

#: The scenario of a bare ``sim`` SPEC.
DEFAULT_SCENARIO = "estec"


def _video_pair(arg: str) -> list[str] | None:
    """``video:``'s LEFT and RIGHT, each stripped of spaces at its ends and its ``~`` expanded:
    split at its one comma; with more (a file name holding one, "Take 1, left.avi"), at the one
    comma whose two sides both name existing files, or else whose one side alone does (so that
    the missing one is named). None when no comma gives two names, or several do alike."""
    commas = [i for i, c in enumerate(arg) if c == ","]
    splits = [[os.path.expanduser(side.strip()) for side in (arg[:i], arg[i + 1:])] for i in commas]
    splits = [pair for pair in splits if all(pair)]
    if len(commas) == 1:
        return splits[0] if splits else None
    for found in (2, 1):  # both sides name files; else one does (the other is said missing)
        matches = [pair for pair in splits if sum(os.path.isfile(side) for side in pair) == found]
        if matches:
            return matches[0] if len(matches) == 1 else None
    return None


def open_source(spec: str, rig_override: StereoRig | None = None, realtime: bool = False, loop: bool = False,
                render_ahead: bool = True, *, own_rig: bool = True, own_model: bool = True,
                model_optional: bool = False) -> Source:
    """Open the source a SPEC string names.

    Args:
        spec: see the module docstring.
        rig_override: use this rig instead of the one the source carries (``--rig``).
        realtime: play recorded and simulated streams at their frame rate (else as fast as
            possible). Cameras are always live.
        loop: start recorded and simulated streams again at their end (else they end).
        render_ahead: the simulator renders its stream in a separate process, ahead of the
            reader (else in the reader's thread); other sources ignore it.
        own_rig, own_model: False: a sequence folder's ``rig.yaml`` (``model.yaml``) is not
            read, its ``rig`` (``model``) None — the caller brings another or needs none, and a
            broken file there must not stop it.
        model_optional: the caller may run without the source's model: a sequence folder's
            ``model.yaml`` that cannot be read is warned about and left out, not an error.

    Raises:
        TrackmeterError: a malformed SPEC, a missing file or folder, a camera that cannot be
            opened; the message names the SPEC's part that failed.
    """
    text = (spec or "").strip()
    if not text:
        raise TrackmeterError("empty source SPEC (expected sim, sim:SCENARIO, seq:DIR, video:LEFT,RIGHT, camera:I[,J])")
    kind, _, arg = text.partition(":")
    # The shell expands a leading '~' only at the start of a word, not after "seq:".
    # (video:'s two files each, where its commas are read: _video_pair)
    arg = arg if kind == "video" else os.path.expanduser(arg)
    # A folder named after a kind ("sim", "seq", ...) is still that kind: say how to play it.
    folder_hint = f" (the folder {text!r} here: give ./{text})" if kind == text and Path(text).is_dir() else ""
    if kind == "sim":
        if folder_hint:
            warnings.warn("source 'sim' is the simulator; to play the folder 'sim' here, give ./sim", stacklevel=2)
        from trackmeter.sources.sim.scenario import load_scenario
        from trackmeter.sources.sim.simulator import Simulator

        scenario = load_scenario(arg or DEFAULT_SCENARIO)
        return Simulator(scenario, rig_override=rig_override, realtime=realtime, loop=loop,
                         render_ahead=render_ahead)
    if kind == "seq":
        if not arg:
            raise TrackmeterError(f"seq: needs a folder, as seq:DIR{folder_hint}")
        return _open_sequence(arg, rig_override, realtime, loop, own_rig, own_model, model_optional)
    if kind == "video":
        parts = _video_pair(arg)
        if parts is None:
            commas = ("; a file name holding a comma is read where exactly one of the splits at its commas "
                      "names two existing files, or one") if arg.count(",") > 1 else ""
            raise TrackmeterError(f"video: needs two files, as video:LEFT,RIGHT, got {spec!r}{commas}{folder_hint}")
        from trackmeter.sources.video import VideoSource

        return VideoSource(parts[0], parts[1], rig=rig_override, realtime=realtime, loop=loop)
    if kind == "camera":
        parts = [p.strip() for p in arg.split(",")]
        try:
            if len(parts) not in (1, 2):
                raise ValueError
            devices = tuple(int(p) for p in parts)
            if any(d < 0 for d in devices):
                raise ValueError
        except ValueError:
            raise TrackmeterError(f"camera: needs one or two device numbers, as camera:0 or camera:0,1, got {spec!r}{folder_hint}") from None
        from trackmeter.sources.video import CameraSource

        return CameraSource(devices, rig=rig_override)
    # A bare folder (DESIGN.md: "seq:DIR or a bare DIR"). Windows drive letters never reach here.
    folder = os.path.expanduser(text)
    if Path(folder).is_dir():
        return _open_sequence(folder, rig_override, realtime, loop, own_rig, own_model, model_optional)
    if ":" not in text and Path(folder).exists():  # a file where a folder would be played
        raise TrackmeterError(f"unknown source {spec!r}: a file, not a sequence folder (two videos play as "
                              "video:LEFT,RIGHT)")
    if ":" not in text:  # no kind given: it can only be meant as a folder, and there is none
        raise TrackmeterError(f"unknown source {spec!r}: no such folder ({Path(folder).absolute()}), and not one of "
                              "sim, sim:SCENARIO, seq:DIR, video:LEFT,RIGHT, camera:I[,J]")
    raise TrackmeterError(
        f"unknown source {spec!r}: expected sim, sim:SCENARIO, seq:DIR, an existing folder, video:LEFT,RIGHT, camera:I[,J]"
    )


def _open_sequence(directory: str, rig: StereoRig | None, realtime: bool, loop: bool, own_rig: bool = True,
                   own_model: bool = True, model_optional: bool = False) -> Source:
    from trackmeter.sources.sequence import SequenceSource

    return SequenceSource(directory, rig=rig, realtime=realtime, loop=loop, read_rig=own_rig, read_model=own_model,
                          model_optional=model_optional)
