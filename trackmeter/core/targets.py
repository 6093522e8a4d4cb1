"""What the tracker reports about each target: the interface between tracking and the rest.

The tracker (:mod:`trackmeter.core.tracking`) owns its mutable state; after every step it
hands out immutable :class:`TargetState` records, which the pose estimator, the pipeline's
snapshots, the run-directory writers and the console read.
"""

from __future__ import annotations

import re
from collections import Counter
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

TargetStatus = Literal["tracking", "lost", "recovered"]
TargetOrigin = Literal["operator", "auto", "model"]


@dataclass(frozen=True, eq=False)
class TargetState:
    """One target after a tracker step.

    Attributes:
        id: stable name (operator-given, model point id, or generated like ``"a7"``).
        origin: who made it: the operator's click, automatic selection, or a model point
            re-locked through the pose (recovery).
        status: ``"tracking"`` (measured this frame), ``"lost"`` (not measured; never a
            guess), ``"recovered"`` (re-locked this frame after a loss; measured).
        uv: (2,) left-image pixel, ORIGINAL (unrectified) image, px. The last good one when lost.
        uv_right: (2,) matched right-image pixel, original image, px (NaN when lost).
        point_cam: (3,) triangulated point, left camera frame, m (NaN when lost).
        cov_cam: (3,3) covariance of ``point_cam``, m² (NaN when lost).
        score: ZNCC in [-1, 1] of the stereo match that gave ``uv_right`` and ``point_cam``
            (NaN when lost).
        predicted_uv: (2,) Kalman-predicted left pixel for this frame, px.
        search_box: ``(u0, v0, u1, v1)`` search window in the left image, px.
        lost_reason: why it was lost (None while tracking).
        age_frames: frames since the target was created.
    """

    id: str
    origin: TargetOrigin
    status: TargetStatus
    uv: NDArray[np.float64]
    uv_right: NDArray[np.float64]
    point_cam: NDArray[np.float64]
    cov_cam: NDArray[np.float64]
    score: float
    predicted_uv: NDArray[np.float64]
    search_box: tuple[float, float, float, float]
    lost_reason: str | None = None
    age_frames: int = 0

    @property
    def measured(self) -> bool:
        """True when the target has a 3D point this frame (tracking or recovered)."""
        return self.status != "lost"


@dataclass(frozen=True)
class Refusal:
    """A point that could not be measured or a target that could not be created, and why."""

    uv: tuple[float, float]
    reason: str


#: A refusal's figures in brackets ("(aperture problem: min gradient eigenvalue 2.2)", "(score
#: 0.61)"): left out when refusals are counted by kind.
_FIGURES = re.compile(r" \([^()]*\d[^()]*\)")


def count_reasons(reasons: Iterable[str] | Mapping[str, int], most: int | None = None) -> list[tuple[str, int]]:
    """Refusal reasons counted by kind, most frequent first: two reasons that differ only in a
    figure in brackets are one kind, said without the figure ("2 textureless patch in one
    direction"); a kind of one text is said whole, figure and all.

    Args:
        reasons: each refusal's reason (:attr:`Refusal.reason`), or reason -> count.
        most: at most this many kinds, or all.
    Returns:
        ``(reason, count)`` pairs.
    """
    counted = reasons if isinstance(reasons, Mapping) else Counter(reasons)
    kinds: Counter[str] = Counter()
    texts: dict[str, set[str]] = {}
    for reason, n in counted.items():
        kind = _FIGURES.sub("", reason)
        kinds[kind] += n
        texts.setdefault(kind, set()).add(reason)
    return [(next(iter(texts[kind])) if len(texts[kind]) == 1 else kind, n) for kind, n in kinds.most_common(most)]
