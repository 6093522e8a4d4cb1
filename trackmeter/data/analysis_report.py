"""Outputs of ``trackmeter analyze``: JSON, per-range CSV, plots of the paper's Figs. 2-3, report.

Plots (matplotlib, Agg backend, PNG):

- ``sigma_vs_range.png`` (Fig. 3): measured single-point sigma per axis against range, the
  least-squares parabola ``sigma = k z^2`` and the error propagation's prediction;
- ``error_density.png`` (Fig. 2): histogram density of the depth residuals at the range nearest
  3.5 m and of the residuals each over its own point's spread (studentised), with their best normal fits.

Millimetres only at this display edge; the JSON stays in SI units.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from trackmeter.core.error_analysis import DensityFit, ErrorAnalysis
from trackmeter.data.atomic import write_files_atomic
from trackmeter.data.evaluation import check_report_directory, figure_png
from trackmeter.data.jsontext import json_text

if TYPE_CHECKING:  # matplotlib is imported only where a report is drawn
    from matplotlib.axes import Axes

#: The paper's figures (sections 2.F-2.G): sigma_z at 3.5 m, sub-pixel accuracy.
PAPER_SIGMA_Z_3P5_M = 0.004
PAPER_SIGMA_DISPARITY_PX = 0.07


def _shown(value: float | None, scale: float = 1.0) -> str:
    """``value * scale`` to 4 decimals; '-' where it is undefined (a fit over one range has no
    spread: None in the JSON, NaN in the analysis)."""
    return "-" if value is None or value != value else f"{value * scale:.4f}"


def format_analysis(summary: dict) -> str:
    """Human-readable summary (mm, px)."""
    lines = [
        f"{'origin [m]':>10}{'range [m]':>10}{'points':>8}{'samples':>9}{'sx [mm]':>10}{'sy [mm]':>10}{'sz [mm]':>10}"
        f"{'pred sz [mm]':>14}{'sd [px]':>9}{'mism':>6}{'true rms z [mm]':>17}{'bias z [mm]':>13}{'gross':>7}"
    ]
    for r in summary["ranges"]:
        s, p = r["sigma_m"], r["predicted_sigma_m"]
        te = r.get("truth_error")
        truth = (
            f"{te['rms_m']['z'] * 1e3:>17.3f}{te['bias_rms_m']['z'] * 1e3:>13.3f}{te['n_gross']:>4d}/{te['n_points']:<3d}"
            if te else f"{'-':>17}{'-':>13}{'-':>7}"
        )
        origin = r.get("true_range_m", float("nan"))
        lines.append(
            (f"{origin:>10.3f}" if origin == origin else f"{'-':>10}")
            + f"{r['range_m']:>10.3f}{r['n_points']:>8d}{r['n_samples']:>9d}{s['x'] * 1e3:>10.3f}"
            f"{s['y'] * 1e3:>10.3f}{s['z'] * 1e3:>10.3f}{p['z'] * 1e3:>14.3f}{r['sigma_disparity_px']:>9.4f}"
            f"{r['n_outliers']:>6d}" + truth
        )
    lines.append(
        "(origin: the target origin's true range, as the skipped ranges are named, '-' without ground truth; "
        "range: the mean measured depth of the range's points;\n sigma: repeated-measurement standard deviation; "
        "pred: error propagation with the matcher's sigma_d; sd: eq. 2 at that range, point by point;\n mism: samples "
        "left out as mismatches (residuals in units of their own predicted sigma, beyond analyze.max_abs_residual_sigmas robust sigmas, 1.4826 MAD, of them); true rms/bias: against the simulator's surface points, gross mismatches (gross/points) left out)"
    )
    fz = summary["fit"]["z"]
    lines.append(
        f"fit sigma_z = k z^2: k = {fz['k_per_m'] * 1e3:.4f} mm/m^2 (± {_shown(fz['k_std_per_m'], 1e3)}), "
        f"R^2 = {_shown(fz['r2'])} (through the origin); sigma_z at 3.5 m = {summary['sigma_z_at_3p5_m'] * 1e3:.3f} mm "
        f"(paper: {PAPER_SIGMA_Z_3P5_M * 1e3:.0f} mm);\n fitted to each range's k z^2 from its points' own depths "
        "(sd's, eq. 2 point by point), not to sz, which weighs a range spread in depth toward its far points"
    )
    lines.append(
        f"sub-pixel disparity accuracy from k (eq. 2, sigma_d = k f b): {summary['sigma_disparity_px']:.4f} px "
        f"(paper: {PAPER_SIGMA_DISPARITY_PX} px); the matcher's own estimate: "
        f"{summary.get('predicted_sigma_disparity_px', float('nan')):.4f} px; the image noise's limit "
        f"(Cramer-Rao, RMS over points): {summary.get('noise_limited_sigma_disparity_px', float('nan')):.4f} px; "
        f"measured / limit per point (median): {summary.get('measured_over_noise_limit_median', float('nan')):.2f}"
    )
    d = summary["density_normalised"]
    lines.append(
        f"error density (depth residual over its point's spread without it, studentised, {d['n']} samples): normal fit mu = {d['mu']:.3f}, "
        f"sigma = {d['sigma']:.3f}; KS D = {d['ks_statistic']:.4f} (p = {d['ks_pvalue']:.3g}), "
        f"D'Agostino K^2 = {d['k2_statistic']:.2f} (p = {d['k2_pvalue']:.3g})"
    )
    for s in summary.get("skipped_ranges", []):
        lines.append(f"skipped range {s}")
    return "\n".join(lines)


def _plot(analysis: ErrorAnalysis) -> dict[str, bytes]:
    """The two figures as PNG bytes, by file name."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from scipy import stats

    z = np.array([r.range_m for r in analysis.ranges])
    zz = np.linspace(0.0, z.max() * 1.05, 200)
    fig, axes = plt.subplots(1, 3, figsize=(12, 4))
    for i, (ax, axis) in enumerate(zip(axes, "xyz")):
        sig = np.array([r.sigma_m[i] for r in analysis.ranges]) * 1e3
        pred = np.array([r.predicted_sigma_m[i] for r in analysis.ranges]) * 1e3
        k = analysis.fits[axis].k_per_m
        ax.plot(z, sig, "o", label="measured (pooled)")
        if axis == "z":  # what the z fit is fitted to: eq. 2 point by point (ErrorAnalysis.fits)
            ax.plot(z, np.array([r.depth_k_per_m * r.range_m**2 for r in analysis.ranges]) * 1e3, "+", ms=9,
                    label="k z², the points' own depths (fitted)")
        ax.plot(zz, k * zz**2 * 1e3, "-", label=f"fit k z², k = {k * 1e3:.3f} mm/m²")
        if np.any(np.isfinite(pred)):
            ax.plot(z, pred, "x", label="error propagation")
        if axis == "z":
            ax.plot([3.5], [PAPER_SIGMA_Z_3P5_M * 1e3], "s", mfc="none", label="paper, 3.5 m")
        ax.set_xlabel("range z [m]")
        ax.set_ylabel(f"sigma {axis} [mm]")
        ax.set_title(f"{axis}{' (viewing axis)' if axis == 'z' else ''}")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(f"single-point sigma vs range (paper Fig. 3); sigma_d = {analysis.sigma_disparity_px:.4f} px")
    fig.tight_layout()
    sigma_png = figure_png(fig)
    plt.close(fig)

    def panel(ax: Axes, d: DensityFit, scale: float, unit: str, title: str) -> None:
        edges = d.bin_edges * scale
        ax.stairs(d.density / scale, edges, fill=True, alpha=0.5, label="measured")
        x = np.linspace(edges[0], edges[-1], 300)
        ax.plot(x, stats.norm.pdf(x, d.mu * scale, d.sigma * scale), "r-",
                label=f"normal fit mu={d.mu * scale:.3f}, sigma={d.sigma * scale:.3f}")
        ax.set_xlabel(unit)
        ax.set_ylabel("probability density")
        ax.set_title(f"{title}\nKS D={d.ks_statistic:.3f}, K² p={d.k2_pvalue:.2g}", fontsize=9)
        ax.legend(fontsize=7)

    near = analysis.ranges[int(np.argmin([abs(r.range_m - 3.5) for r in analysis.ranges]))]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    panel(axes[0], analysis.density_range, 1e3, "depth error [mm]", f"depth residuals at {near.range_m:.2f} m")
    panel(axes[1], analysis.density, 1.0, "depth residual, studentised", "all points and ranges")
    fig.suptitle("error probability density (paper Fig. 2)")
    fig.tight_layout()
    density_png = figure_png(fig)
    plt.close(fig)
    return {"sigma_vs_range.png": sigma_png, "error_density.png": density_png}


#: What an analyze report folder holds.
ANALYSIS_FILES = ("analysis.json", "ranges.csv", "report.md", "sigma_vs_range.png", "error_density.png")


def check_analysis_directory(directory: str | Path) -> Path:
    """``directory`` as a Path when an analysis report can be written there (new, empty, or an
    earlier analysis report's, which is replaced); nothing is created.

    Raises:
        TrackmeterError: as :func:`check_report_directory`, or the folder holds other files.
    """
    return check_report_directory(directory, ANALYSIS_FILES, "an analysis report", beside_a_run=False)


def write_analysis(analysis: ErrorAnalysis, summary: dict, out_dir: str | Path) -> list[Path]:
    """Write ``analysis.json``, ``ranges.csv``, the two plots and ``report.md`` into ``out_dir``,
    as one piece of work: all of them whole, or (a full disk) none, an earlier report kept.

    Raises:
        TrackmeterError: ``out_dir`` cannot hold a report (:func:`check_analysis_directory`),
            or a file could not be written.
    """
    out = check_analysis_directory(out_dir)
    rows = ["range_m,n_points,n_samples,sigma_x_m,sigma_y_m,sigma_z_m,pred_sigma_x_m,pred_sigma_y_m,pred_sigma_z_m,"
            "true_range_m"]
    for r in summary["ranges"]:  # the table's rows, the origin's true range with them (empty: unknown)
        true_range = r.get("true_range_m")
        rows.append(",".join([repr(float(r["range_m"])), str(int(r["n_points"])), str(int(r["n_samples"])),
                              *(repr(float(r[k][axis])) for k in ("sigma_m", "predicted_sigma_m") for axis in "xyz"),
                              repr(float(true_range)) if true_range is not None and math.isfinite(true_range) else ""]))
    plots = _plot(analysis)
    s = summary
    ok_sigma = s["sigma_z_at_3p5_m"] <= PAPER_SIGMA_Z_3P5_M
    ok_sd = s["sigma_disparity_px"] <= PAPER_SIGMA_DISPARITY_PX
    report = f"""# Error analysis (paper sections 2.F-2.G)

| figure | paper | ours | better |
| --- | --- | --- | --- |
| single-point sigma along the viewing axis at 3.5 m (fit k z²) | {PAPER_SIGMA_Z_3P5_M * 1e3:.0f} mm | {s['sigma_z_at_3p5_m'] * 1e3:.3f} mm | {'yes' if ok_sigma else 'no'} |
| sub-pixel disparity accuracy (eq. 2: sigma_d = k f b) | {PAPER_SIGMA_DISPARITY_PX} px | {s['sigma_disparity_px']:.4f} px | {'yes' if ok_sd else 'no'} |

The viewing axis is our z (the paper's y). f = {s['focal_px']:.1f} px, b = {s['baseline_m'] * 1e3:.1f} mm
(rectified). The matcher's own disparity sigma estimate (median): {s.get('predicted_sigma_disparity_px', math.nan):.4f} px.
The limit the image noise measured over the still frames allows (Cramer-Rao bound of 1-D
registration, RMS over the points): {s.get('noise_limited_sigma_disparity_px', math.nan):.4f} px; point by point,
the measured disparity sigma over that limit has median {s.get('measured_over_noise_limit_median', math.nan):.2f}
(1 = the matcher reaches what the sensor noise allows).

```
{format_analysis(s)}
```

![sigma vs range](sigma_vs_range.png)
![error density](error_density.png)
"""
    files = {out / "analysis.json": (json_text(summary) + "\n").encode(), out / "ranges.csv": ("\n".join(rows) + "\n").encode(),
             **{out / name: png for name, png in plots.items()}, out / "report.md": report.encode("utf-8", "surrogateescape")}
    write_files_atomic(files)
    return list(files)
