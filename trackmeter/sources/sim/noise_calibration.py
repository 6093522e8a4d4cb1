"""Calibrate the simulator's sensor noise to the paper's single-point depth sigma (4 mm at 3.5 m).

The paper (section 4) measured a static point repeatedly: the standard deviation of its depth
was 4 mm at 3.5 m, growing as z² (sigma_z = z² sigma_d / (f b), paper eq. 2), i.e. a disparity
standard deviation of 0.004 * 1152 * 0.28 / 3.5² ≈ 0.105 px with the ESTEC rig. Giving the
``estec`` scenario the same measurement noise makes our accuracy comparable with the paper's:
same noise in, then the better system wins.

How it is measured (:func:`static_depth_sigma`): the scenario's mock-up is held still at the
scenario's initial attitude at ``range_m``; a grid of left-image pixels on the mock-up is measured
by the project's matcher (:func:`trackmeter.core.matching.measure_points`) in ``n_frames``
renders that differ only in sensor noise. The point set is fixed from the noise-free render
(pixels the matcher accepts there, within 2 cm of the true depth), and the noise-dependent
acceptance tests (``min_score``, ``max_sigma_disparity_px``, the depth-edge and repetitive-texture
checks) are relaxed so that the set does not shrink to the best-textured points as the noise grows
(that would bias sigma low). Per point,
the standard deviation of z over the frames is scaled to 3.5 m by (3.5 / z)²; the figure is the
median over points. Gross mismatches (more than 10 cm off) are dropped and counted.

Run ``python -m trackmeter.sources.sim.noise_calibration`` to search the read noise that gives
4 mm (secant iterations on sigma versus noise) and print the value for ``config/scenarios/``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from dataclasses import dataclass

import numpy as np

from trackmeter.core.matching import MeasureParams, measure_points
from trackmeter.core.transforms import apply_transform
from trackmeter.sources.sim.scenario import Scenario, load_scenario
from trackmeter.sources.sim.simulator import Simulator

PAPER_SIGMA_Z_M = 0.004
PAPER_RANGE_M = 3.5


@dataclass(frozen=True)
class DepthSigmaResult:
    """What :func:`static_depth_sigma` measured.

    Attributes:
        read_noise_grey: the read noise used, grey levels.
        sigma_z_m: median over points of the per-point depth std, scaled to ``range_m``, m.
        sigma_disparity_px: the same as a disparity std, ``sigma_z f b / z²``, px.
        n_points: points in the fixed set.
        n_frames: noisy renders per point.
        outlier_fraction: measurements dropped as gross mismatches (> 10 cm).
        accepted_default_fraction: fraction of the measurements the matcher with its DEFAULT
            parameters accepts at this noise (how much the acceptance tests refuse).
    """

    read_noise_grey: float
    sigma_z_m: float
    sigma_disparity_px: float
    n_points: int
    n_frames: int
    outlier_fraction: float
    accepted_default_fraction: float


def relaxed_params(params: MeasureParams | None = None) -> MeasureParams:
    """The matcher's parameters with the noise-dependent refusals switched off (see module doc):
    the score and disparity-sigma floors, and the depth-edge and repetitive-texture checks
    (at the paper's noise the edge test's shifted windows refuse the noisiest outcomes of
    ordinary points too; the set is already free of edges and repeats, chosen noise-free)."""
    p = params or MeasureParams()
    return dataclasses.replace(
        p, min_score=0.0, max_sigma_disparity_px=1e6, edge_shift_px=0, context_width_px=0
    )


def static_depth_sigma(
    scenario: Scenario,
    read_noise_grey: float | None = None,
    range_m: float = PAPER_RANGE_M,
    n_frames: int = 16,
    grid_step_px: int = 14,
    simulator: Simulator | None = None,
    selection: str = "grid",
) -> DepthSigmaResult:
    """Single-point depth standard deviation at ``range_m`` with the scenario's noise (or ``read_noise_grey``).

    Args:
        scenario: whose rig, mock-up, attitude, light and render parameters are used.
        read_noise_grey: override of ``scenario.render.read_noise_grey``.
        range_m: where the mock-up is held, m (along ``position0_m``'s direction).
        n_frames: noisy renders (same pose) per point.
        grid_step_px: spacing of the candidate pixel grid, px.
        simulator: a simulator of the same scenario to reuse its loaded mock-up.
        selection: ``"grid"`` (the default, the calibration's definition): every grid pixel on
            the target the matcher accepts without noise, i.e. a typical textured point;
            ``"corners"``: Shi-Tomasi corners of the noise-free left image (``cv2.goodFeaturesToTrack``,
            at most 200, 10 px apart), the best-textured points an automatic selector would pick.
    """
    render = scenario.render
    if read_noise_grey is not None:
        render = dataclasses.replace(render, read_noise_grey=float(read_noise_grey))
    held = dataclasses.replace(scenario, static_ranges_m=(float(range_m),), frames_per_range=int(n_frames), render=render)
    sim = Simulator(held, mockup=simulator.mockup if simulator is not None else None)
    rig = sim.true_rig
    W, H = rig.image_size
    T = sim.truth(0).T_cam_body
    clean_left, clean_right = sim.renderer.render(T, sim.sun_dir_cam, np.random.default_rng(0), noise=False)
    if selection == "grid":
        uu, vv = np.meshgrid(np.arange(16, W - 16, grid_step_px), np.arange(16, H - 16, grid_step_px))
        uv = np.column_stack([uu.ravel(), vv.ravel()]).astype(float)
    elif selection == "corners":
        import cv2

        found = cv2.goodFeaturesToTrack(clean_left, maxCorners=200, qualityLevel=0.01, minDistance=10)
        uv = np.zeros((0, 2)) if found is None else found.reshape(-1, 2).astype(float)
        uv = uv[(uv[:, 0] >= 16) & (uv[:, 0] < W - 16) & (uv[:, 1] >= 16) & (uv[:, 1] < H - 16)]
    else:
        raise ValueError(f"selection must be 'grid' or 'corners', got {selection!r}")
    surface = sim.surface_points(0, uv)
    on_target = ~np.isnan(surface[:, 0])
    uv, surface = uv[on_target], surface[on_target]
    z_true = apply_transform(T, surface)[:, 2]
    params = relaxed_params()
    clean = measure_points(rig, clean_left, clean_right, uv, MeasureParams())
    keep = np.array([m.ok and abs(m.xyz_m[2] - z) < 0.02 for m, z in zip(clean, z_true)])
    uv, z_true = uv[keep], z_true[keep]
    Z = np.full((n_frames, len(uv)), np.nan)
    accepted_default = 0
    for i in range(n_frames):
        f = sim.frame(i)
        for k, m in enumerate(measure_points(rig, f.left, f.right, uv, params)):
            if m.ok:
                Z[i, k] = m.xyz_m[2]
        accepted_default += sum(m.ok for m in measure_points(rig, f.left, f.right, uv, MeasureParams()))
    finite = np.isfinite(Z)
    outlier = finite & (np.abs(Z - z_true) > 0.1)
    Z[outlier] = np.nan
    enough = np.isfinite(Z).sum(axis=0) >= max(3, n_frames // 2)
    sigma = np.nanstd(Z[:, enough], axis=0, ddof=1) * (range_m / z_true[enough]) ** 2
    sigma_z = float(np.median(sigma)) if sigma.size else float("nan")
    return DepthSigmaResult(
        read_noise_grey=float(render.read_noise_grey),
        sigma_z_m=sigma_z,
        sigma_disparity_px=sigma_z * rig.rectification.focal_px * rig.rectification.baseline_m / range_m**2,
        n_points=int(enough.sum()),
        n_frames=int(n_frames),
        outlier_fraction=float(outlier.sum() / max(finite.sum(), 1)),
        accepted_default_fraction=float(accepted_default / max(Z.size, 1)),
    )


def calibrate_read_noise(
    scenario: Scenario, target_sigma_z_m: float = PAPER_SIGMA_Z_M, start: tuple[float, float] = (2.0, 6.0),
    iterations: int = 4, **kwargs: object,
) -> list[DepthSigmaResult]:
    """Secant search for the read noise giving ``target_sigma_z_m``; returns every evaluation, last best."""
    sim = Simulator(dataclasses.replace(scenario, static_ranges_m=(PAPER_RANGE_M,), frames_per_range=1))
    results = [static_depth_sigma(scenario, n, simulator=sim, **kwargs) for n in start]  # type: ignore[arg-type]
    for _ in range(iterations):
        a, b = results[-2], results[-1]
        if abs(b.sigma_z_m - target_sigma_z_m) < 0.01 * target_sigma_z_m or b.sigma_z_m == a.sigma_z_m:
            break
        slope = (b.sigma_z_m - a.sigma_z_m) / (b.read_noise_grey - a.read_noise_grey)
        nxt = float(np.clip(b.read_noise_grey + (target_sigma_z_m - b.sigma_z_m) / slope, 0.0, 100.0))
        results.append(static_depth_sigma(scenario, round(nxt, 3), simulator=sim, **kwargs))  # type: ignore[arg-type]
    return results


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m trackmeter.sources.sim.noise_calibration", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenario", default="estec",
                        help="scenario whose noise is calibrated: a bare name of config/scenarios/ or a file "
                             "(default: estec)")
    parser.add_argument("--check", action="store_true", help="only measure the scenario's configured noise")
    parser.add_argument("--selection", choices=("grid", "corners"), default="grid",
                        help="which points: a grid of typical textured points (default) or Shi-Tomasi corners")
    args = parser.parse_args(argv)
    scenario = load_scenario(args.scenario)
    if args.check:
        results = [static_depth_sigma(scenario, selection=args.selection)]
    else:
        results = calibrate_read_noise(scenario, selection=args.selection)
    for r in results:
        print(json.dumps(dataclasses.asdict(r)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
