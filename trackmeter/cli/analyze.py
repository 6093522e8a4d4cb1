"""Error analysis of single-point stereo measurements (paper sections 2.F-2.G, Figs. 2-3).

Reads a source of a still target at one or several ranges (default: the simulator's
static_ranges scenario; any sequence folder of a still object works), selects points on the
target at each range (Shi-Tomasi corners on its first frame) and measures them in every frame.
Reports, per range, the standard deviation of a single measurement per camera axis (z = the
viewing axis) beside the error propagation's prediction; the least-squares parabola
sigma_z = k z^2 (Fig. 3); the sub-pixel disparity accuracy k f b it implies (eq. 2); and the
error probability density with its best Gaussian fit and normality statistics (Fig. 2).
Ranges are told apart by the source's ground truth (frames within 1 mm and 0.1 deg of the
range's first true pose, so that a measured truth's jitter stays one range); without ground
truth, by the view: a new range starts where the left image jumps (the target moved).
The true error of each point (its "true rms" and "bias" columns) needs the true 3D point at
that pixel, which only the simulator source knows (its renderer's surface); a sequence
folder's ground truth is the pose alone, so those columns are left empty there. A range where
fewer than 3 points are measured often enough is skipped with its reason (static_ranges' 7
and 10 m with the 12 mm rig). An underexposed range is measured as `measure` and `track` see
it: multiplied by the exposure gain of its first left image (config section exposure; one
gain per range), said on stderr.

--json prints the summary (SI units); --out DIR writes analysis.json, ranges.csv,
sigma_vs_range.png, error_density.png and report.md.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from dataclasses import replace

from trackmeter.cli.common import load_config_from_args, progress, rig_help, source_warning_since


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--source", default="sim:static_ranges", metavar="SPEC",
                        help="frames of a still target (default sim:static_ranges; seq:DIR or a folder)")
    parser.add_argument("--rig", metavar="RIG",
                        help=rig_help("default: the source's own"))
    parser.add_argument("--points", type=int, metavar="N",
                        help="points selected per range (default from config: 30): the best corners the matcher accepts, "
                             "more where some fall short of analyze.min_samples good measurements; a range "
                             "reports the ones that reach it, which may be fewer")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON (SI units)")
    parser.add_argument("--out", metavar="DIR", help="write analysis.json, ranges.csv, plots and report.md here")


def run(args: argparse.Namespace) -> int:
    from trackmeter.cli.common import open_source_with_rig
    from trackmeter.data.analysis_report import format_analysis, write_analysis
    from trackmeter.errors import TrackmeterError
    from trackmeter.pipeline.analysis import run_error_analysis

    config = load_config_from_args(args)
    params = config.analyze
    if args.points is not None:
        from trackmeter.core.error_analysis import AnalyzeParams
        from trackmeter.data.config import check_option

        params = replace(params, points_per_range=check_option(AnalyzeParams, "points_per_range", args.points,
                                                                "--points"))
    if args.out:
        from trackmeter.data.analysis_report import check_analysis_directory

        check_analysis_directory(args.out)  # before the work, which may take a while
    # --rig is read once the source is open: it may take its size from the source's frames.
    with open_source_with_rig(args.source, args.rig, own_model=False) as source:
        rig = source.rig
        if rig is None:
            raise TrackmeterError(f"source {args.source!r} carries no rig: give --rig")
        total = getattr(source, "n_frames", None)
        warning_at_open = getattr(source, "warning", None)  # said by the source already
        try:
            result = run_error_analysis(
                source, rig, config.measure, params,
                progress=lambda frames: progress(frames, total if isinstance(total, int) else None, "analyze"),
                exposure=config.exposure,
            )
        except TrackmeterError as exc:
            skipped = source_warning_since(source, warning_at_open)
            if skipped:  # e.g. every image unreadable: "the source gave no frames" alone does not say why
                raise TrackmeterError(f"{exc}; {skipped}") from None
            raise
        skipped = source_warning_since(source, warning_at_open)
        if skipped:
            warnings.warn(skipped, stacklevel=1)
        for line in result.moving_ranges:
            warnings.warn(line, stacklevel=1)
        if result.frames_without_truth_s:
            warnings.warn(f"{len(result.frames_without_truth_s)} frame(s) without ground truth skipped: they belong to "
                          f"no range (the first at t = {result.frames_without_truth_s[0]:.3f} s)", stacklevel=1)
        gained = [g for g in result.exposure_gains if g != 1.0]
        if gained:
            print(f"trackmeter analyze: note: {len(gained)} of {len(result.exposure_gains)} range(s) underexposed "
                  f"(the left image's brightest pixels below grey {config.exposure.reference_grey:g}), measured at a "
                  f"gain of up to {max(gained):.2f} (config section exposure)", file=sys.stderr)
    summary = result.to_dict()
    summary["source"] = args.source
    if args.out:
        write_analysis(result.analysis, summary, args.out)
    if args.json:
        from trackmeter.data.jsontext import json_text

        print(json_text(summary))
    else:
        print(format_analysis(summary))
        if args.out:
            print(f"wrote {args.out}/report.md, analysis.json, ranges.csv and plots")
    return 0
