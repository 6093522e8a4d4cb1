"""Patch stereo matching and 3D point measurement (paper section 2.A).

(Work in progress: the matcher lands here.)
"""

from __future__ import annotations

from dataclasses import dataclass

from trackmeter.core.params import param


@dataclass(frozen=True)
class MeasureParams:
    """Tunables of a single 3D point measurement."""

    patch_size: int = param(8, "side of the square patch matched between the images, px", min=3, max=63)
