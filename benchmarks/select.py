"""Benchmark ``select``: cost and quality of automatic feature selection (paper section 2.B).

The tracker calls :func:`trackmeter.core.features.select_features` inside its 25 Hz step
whenever automatic targets are missing, so one call must cost a fraction of a frame. All
figures on 726x512 frames of the simulated mock-up (``estec`` scenario, frames 0, 14, ...,
126), wall-time medians over the frames of per-frame medians:

- ``select_ms_4``: 4 points, ``gabor``, with the 12 best points already taken (excluded) — a
  typical top-up; ``select_ms_16`` / ``select_ms_48``: 16 / 48 points on an empty frame (the
  tracker's first fill asks for 3 x 16). ``..._shi_tomasi``: the same calls with the
  Shi-Tomasi baseline, same run; ``select_ratio_vs_shi_tomasi`` = ``select_ms_4`` over it.
- ``select_ms_4_pyramid``: ``select_ms_4`` with ``gabor_pyramid: true`` (the 8 px wavelength at
  half resolution); ``select_ms_4_refine``: with ``stereo_refine: true`` (each point also
  through ``match_epipolar``'s sub-pixel checks). ``select_ms_4_hint``: with ``disparity_range_px`` set to the excluded
  points' disparities (their epipolar matches) /1.5 - 8 .. x1.5 + 8 px, as the tracker can pass.
- ``gabor_score_ms`` / ``gabor_score_ms_2d`` / ``gabor_speedup_vs_2d``: the Gabor score of the
  target's bounding box, ours (separable 1D passes, the same numbers) against the 2D bank
  filtered with ``cv2.filter2D`` (the straightforward implementation), same run.
- ``stereo_check_ms_40`` / ``stereo_check_ms_40_full_line`` / ``stereo_speedup_vs_full_line``:
  the stereo check of the 40 best candidates, ours (ZNCC profile, then ``match_epipolar`` near
  the peak) against ``match_epipolar`` over the whole 1..50 m line, same decisions (tests).
- ``accept_rate_16`` / ``accept_rate_16_pyramid``: share of the points of
  ``select_ms_16``'s calls that a fresh tracker's ``add_target`` accepts (the measurement's
  own checks), without and with the pyramid.
- ``measure_ms_per_candidate_16``: one ``measure_points`` call on those 16 points (as the
  tracker's top-up measures its candidates, most of which the measurement refuses), per point;
  ``measure_ms_per_candidate_16_one_by_one``: the same points one call each (same results, see
  ``tests/test_matching_batch.py``), same run; ``measure_batch_ratio_16`` = the first over it.
"""

from __future__ import annotations

import dataclasses
import statistics
import sys
from typing import TYPE_CHECKING, Callable

import cv2
import numpy as np

from benchmarks import median_ms

if TYPE_CHECKING:
    from trackmeter.core.features import FeatureParams

FRAMES = tuple(range(0, 140, 14))


def _gabor_score_2d(image: np.ndarray, params: FeatureParams) -> np.ndarray:
    """The filter bank as 16 ``cv2.filter2D`` calls with the 2D kernels (the baseline)."""
    from trackmeter.core.features import gabor_bank

    img = np.asarray(image, np.float32)
    bank = gabor_bank(tuple(params.gabor_wavelengths_px), params.gabor_orientations)
    out = np.zeros((len(bank), *img.shape), np.float32)
    for k, scales in enumerate(bank):
        for even, odd in scales:
            np.maximum(out[k], cv2.magnitude(cv2.filter2D(img, cv2.CV_32F, even), cv2.filter2D(img, cv2.CV_32F, odd)), out=out[k])
    return np.sort(out, axis=0)[-params.min_directions]


def run() -> dict[str, float]:
    from trackmeter.core import features as ft
    from trackmeter.core.matching import measure_points
    from trackmeter.core.patch_tracking import match_epipolar
    from trackmeter.core.tracking import TargetState, Tracker
    from trackmeter.data.config import load_config
    from trackmeter.sources.sim.simulator import Simulator

    cfg = load_config()
    params = cfg.features
    pyramid = dataclasses.replace(params, gabor_pyramid=True)
    refined = dataclasses.replace(params, stereo_refine=True)
    sim = Simulator("estec")
    rig = sim.rig
    rect = rig.rectification
    lo, hi = ft.search_disparities(rig, params)
    span = int(np.ceil(hi - lo))
    frames = []
    for i in FRAMES:
        print(f"  rendering estec frame {i}", file=sys.stderr, flush=True)
        frames.append(sim.frame(i))

    times: dict[str, list[float]] = {}

    def timed(key: str, fn: Callable[[], object]) -> None:
        times.setdefault(key, []).append(median_ms(fn, repeats=7, warmup=1))

    accepted = {"accept_rate_16": [0, 0], "accept_rate_16_pyramid": [0, 0]}
    for f in frames:
        L, R = f.left, f.right
        taken = ft.select_features(L, R, rig, 12, "gabor", params)
        cl = rect.rectify_points(taken, 0)
        m = match_epipolar(
            L, R, rect.maps[0], rect.maps[1], cl, np.full(len(cl), lo), span, params.patch_size,
            min_score=params.stereo_min_score, uniqueness_margin=params.uniqueness_margin, epipolar_tolerance_px=1.0,
        )  # fmt: skip
        d = m.disparity_px[m.ok]
        hint = (float(d.min()) / 1.5 - 8, float(d.max()) * 1.5 + 8)
        for method in ("gabor", "shi_tomasi"):
            sfx = "" if method == "gabor" else "_shi_tomasi"
            timed(f"select_ms_4{sfx}", lambda: ft.select_features(L, R, rig, 4, method, params, taken))
            timed(f"select_ms_16{sfx}", lambda: ft.select_features(L, R, rig, 16, method, params))
            timed(f"select_ms_48{sfx}", lambda: ft.select_features(L, R, rig, 48, method, params))
        timed("select_ms_4_pyramid", lambda: ft.select_features(L, R, rig, 4, "gabor", pyramid, taken))
        timed("select_ms_4_refine", lambda: ft.select_features(L, R, rig, 4, "gabor", refined, taken))
        timed("select_ms_4_hint", lambda: ft.select_features(L, R, rig, 4, "gabor", params, taken, disparity_range_px=hint))

        bx, by, bw, bh = cv2.boundingRect(ft.target_mask(L, params))
        box = L[max(by - 20, 0) : by + bh + 20, max(bx - 20, 0) : bx + bw + 20]
        timed("gabor_score_ms", lambda: ft.gabor_score(box, params))
        timed("gabor_score_ms_2d", lambda: _gabor_score_2d(box, params))

        cand = ft._candidates_gabor(L, ft.target_mask(L, params), params, 40)
        ccl = rect.rectify_points(cand, 0)
        timed("stereo_check_ms_40", lambda: ft.stereo_matchable(L, R, rig, cand, params))
        timed(
            "stereo_check_ms_40_full_line",
            lambda: match_epipolar(
                L, R, rect.maps[0], rect.maps[1], ccl, np.full(len(ccl), lo), span, params.patch_size,
                min_score=params.stereo_min_score, uniqueness_margin=params.uniqueness_margin, epipolar_tolerance_px=1.0,
            ),
        )  # fmt: skip

        for key, p in (("accept_rate_16", params), ("accept_rate_16_pyramid", pyramid)):
            pts = ft.select_features(L, R, rig, 16, "gabor", p)
            if key == "accept_rate_16" and len(pts):
                timed("measure_ms_per_candidate_16", lambda: measure_points(rig, L, R, pts, cfg.measure))
                times["measure_ms_per_candidate_16"][-1] /= len(pts)
                timed(
                    "measure_ms_per_candidate_16_one_by_one",
                    lambda: [measure_points(rig, L, R, p[None], cfg.measure) for p in pts],
                )
                times["measure_ms_per_candidate_16_one_by_one"][-1] /= len(pts)
            tracker = Tracker(rig, dataclasses.replace(cfg.tracker, max_targets=64), cfg.features, cfg.measure)
            accepted[key][0] += sum(isinstance(tracker.add_target(f, (float(u), float(v))), TargetState) for u, v in pts)
            accepted[key][1] += len(pts)
        print(f"  frame {f.index}: select_ms_4 {times['select_ms_4'][-1]:.1f}", file=sys.stderr, flush=True)

    out = {k: float(statistics.median(v)) for k, v in times.items()}
    out["select_ratio_vs_shi_tomasi"] = out["select_ms_4"] / out["select_ms_4_shi_tomasi"]
    out["gabor_speedup_vs_2d"] = out["gabor_score_ms_2d"] / out["gabor_score_ms"]
    out["stereo_speedup_vs_full_line"] = out["stereo_check_ms_40_full_line"] / out["stereo_check_ms_40"]
    out["measure_batch_ratio_16"] = out["measure_ms_per_candidate_16"] / out["measure_ms_per_candidate_16_one_by_one"]
    for key, (n_ok, n_all) in accepted.items():
        out[key] = n_ok / max(n_all, 1)
    return out


if __name__ == "__main__":
    from benchmarks import main_of

    main_of("select", __doc__, run, sort_keys=True)
