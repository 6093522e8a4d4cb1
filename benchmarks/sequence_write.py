"""Sequence-folder writing speed: can a recorder keep up with the live stream?

Figures (726x512 estec stereo frames, rendered once, written repeatedly into a temporary folder):

- ``write_ms``: median time of ``SequenceWriter.write`` for one stereo frame with ground truth
  (two PNGs encoded, written to temporary files and renamed, three CSV/TUM rows flushed).
- ``baseline_png_level3_ms``: median time of encoding the same two images as PNG at zlib level 3
  (libpng's usual default) in memory only, measured in the same run.
- ``ratio_to_baseline``: ``write_ms / baseline_png_level3_ms`` (machine noise cancels).
- ``frames_per_s``: ``1000 / write_ms``; the recorder needs at least the source rate (25 Hz).
- ``bytes_per_frame``: size of the two PNG files.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import cv2

from benchmarks import median_ms


def run() -> dict[str, float]:
    from trackmeter.data.sequence import SequenceWriter
    from trackmeter.sources.base import StereoFrame
    from trackmeter.sources.sim.simulator import Simulator

    sim = Simulator("estec")
    frame = sim.frame(0)
    count = [0]
    with tempfile.TemporaryDirectory() as tmp:
        writer = SequenceWriter(Path(tmp) / "seq", rig=sim.true_rig)

        def write() -> None:
            i = count[0]
            count[0] += 1
            writer.write(StereoFrame(i, i / 25.0, frame.left, frame.right, frame.truth))

        write_ms = median_ms(write, repeats=31)
        writer.close()
        png = Path(tmp) / "seq" / "cam0" / "data" / "0.png"
        size = 2 * png.stat().st_size

    def baseline() -> None:
        level3 = [cv2.IMWRITE_PNG_COMPRESSION, 3]
        cv2.imencode(".png", frame.left, level3)
        cv2.imencode(".png", frame.right, level3)

    base_ms = median_ms(baseline, repeats=31)
    return {
        "write_ms": round(write_ms, 3),
        "baseline_png_level3_ms": round(base_ms, 3),
        "ratio_to_baseline": round(write_ms / base_ms, 3),
        "frames_per_s": round(1000.0 / write_ms, 1),
        "bytes_per_frame": float(size),
    }
