"""trackmeter measure: 3D points of a stereo pair at given left-image pixels (paper 2.A).

Each --at U,V is a pixel of the ORIGINAL left image (column, row; the centre of the top-left
pixel is 0,0). Its patch (default 8x8) is matched along the epipolar line of the right image
(ZNCC, sub-pixel Gauss-Newton fit), checked (texture, uniqueness, left-right consistency,
range) and triangulated into the left camera frame (x right, y down, z along the viewing
axis), with its standard deviation per axis from the stereo error propagation. A point that
fails a check is refused with its reason rather than given a doubtful number. The checks
cannot see everything: at an occluding contour over untextured background a patch may be
accepted a pixel or more off (measured on the Tsukuba pair, docs/results.md).

--json prints a JSON list, one object per --at, in order:
  {"uv": [u, v], "ok": bool, "reason": str|null, "right_uv": [u, v], "disparity_px": d,
   "xyz_m": [x, y, z], "sigma_m": [sx, sy, sz], "score": s}
(right_uv in the original right image; disparity_px in the RECTIFIED images, d = f b / z plus
the rectification's offset, so not u - right_u where the images are distorted or converge;
a pair rectified already keeps its principal points and its own disparities, u - right_u,
with Middlebury's doffs; null where a refused point has no number).

example (two textured points of the simulated estec trial's first frame):
  trackmeter simulate --scenario estec --duration 1 --out SEQ
  trackmeter measure --rig estec_12mm --left SEQ/cam0/data/0.png \\
      --right SEQ/cam1/data/0.png --at 280,331 --at 435,87 --json
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING, Sequence

from trackmeter.cli.common import rig_help

if TYPE_CHECKING:
    from trackmeter.core.matching import PointMeasurement


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--rig", required=True, metavar="RIG",
                        help=rig_help("required", "the left image"))
    parser.add_argument("--left", required=True, metavar="IMG", help="left image (read as 8-bit grey)")
    parser.add_argument("--right", required=True, metavar="IMG", help="right image (read as 8-bit grey)")
    parser.add_argument(
        "--at", required=True, action="extend", nargs="+", metavar="U,V",
        help="left-image pixels to measure (several may follow one --at, or repeat it; write --at=-5,3 "
        "for a negative u)",
    )
    parser.add_argument("--patch", type=int, metavar="N", help="patch side, px, 3 to 63, odd or even (default: measure.patch_size, 8)")
    parser.add_argument("--json", action="store_true", help="print a JSON list instead of a table")


def run(args: argparse.Namespace) -> int:
    import dataclasses
    import json

    import warnings

    from trackmeter.cli.common import check_rig_side_by_side, parse_uv
    from trackmeter.core.exposure import expose_pair
    from trackmeter.core.matching import REASON_BEYOND_RANGE, measure_points, measurements_to_json
    from trackmeter.core.stereo import swapped_views_problem
    from trackmeter.data.config import load_config
    from trackmeter.data.images import read_grey_pair
    from trackmeter.data.rigfile import load_rig
    from trackmeter.errors import TrackmeterError, counted

    config = load_config(args.config)
    params = config.measure
    if args.patch is not None:
        if not 3 <= args.patch <= 63:
            raise TrackmeterError(f"--patch must be a patch side between 3 and 63 px, got {args.patch}")
        params = dataclasses.replace(params, patch_size=args.patch)
    uv = [parse_uv(text) for text in args.at]
    images = list(read_grey_pair(args.left, args.right))
    # A rig file without an image size (OpenCV's intrinsics.yml/extrinsics.yml) takes the left
    # image's; the size check below then still catches a right image of another size.
    rig = load_rig(args.rig, image_size=(images[0].shape[1], images[0].shape[0]))
    W, H = rig.image_size
    for path, image in zip((args.left, args.right), images):
        if image.shape != (H, W):
            raise TrackmeterError(
                f"{path}: image is {image.shape[1]}x{image.shape[0]} px but the rig {args.rig} is {W}x{H}"
            )
    check_rig_side_by_side(rig, args.rig)

    # An underexposed pair is brought to the grey levels the matcher's gates are set for, as
    # the tracking engine does (config section exposure).
    left, right, _ = expose_pair(images[0], images[1], config.exposure)
    results = measure_points(rig, left, right, uv, params)
    swapped = swapped_views_problem(rig, images[0], images[1])
    if swapped:  # every point refused, or matched to a look-alike: the table alone does not say why
        warnings.warn(swapped, stacklevel=1)
    beyond = sum(m.reason == REASON_BEYOND_RANGE for m in results)
    if beyond:  # the table says "beyond disparity range", not which range nor where it is set
        # Counted from a point at infinity's disparity, as the settings named beside it are.
        offset = rig.rectification.disparity_offset_px
        low, high = (value - offset for value in params.disparity_range_px(rig.rectification))
        near = (f"measure.max_disparity_px ({params.max_disparity_px:g} px)" if params.max_disparity_px
                else f"measure.min_range_m ({params.min_range_m:g} m)")
        past = f" past a point at infinity's ({offset:.4g} px: the principal points apart)" if offset else ""
        warnings.warn(f"{counted(beyond, 'point')} beyond the disparity range searched, {low:g} to {high:.4g} px{past} "
                      f"on this rig: nearer than {near} or farther than measure.min_disparity_px allows; another "
                      f"range goes in a --config file", stacklevel=1)
    if args.json:
        print(json.dumps(measurements_to_json(results), allow_nan=False))
        return 0
    print(format_table(results))
    return 0


def format_table(results: Sequence[PointMeasurement]) -> str:
    """A readable table: one row per point; millimetres for the standard deviations."""
    header = (
        f"{'u':>8} {'v':>8}  {'ok':<3} {'u_right':>8} {'v_right':>8} {'disp_px':>8} "
        f"{'x_m':>8} {'y_m':>8} {'z_m':>8} {'sx_mm':>6} {'sy_mm':>6} {'sz_mm':>6} {'score':>6}  reason"
    )
    lines = [header]
    for m in results:
        score = f"{m.score:6.3f}" if m.score == m.score else f"{'-':>6}"
        head = f"{_pixel(m.uv[0])} {_pixel(m.uv[1])}  {'yes' if m.ok else 'no':<3} "
        if m.ok:
            body = (
                f"{m.right_uv[0]:8.2f} {m.right_uv[1]:8.2f} {m.disparity_px:8.3f} "
                f"{m.xyz_m[0]:8.4f} {m.xyz_m[1]:8.4f} {m.xyz_m[2]:8.4f} "
                f"{m.sigma_m[0] * 1e3:6.2f} {m.sigma_m[1] * 1e3:6.2f} {m.sigma_m[2] * 1e3:6.2f} {score}"
            )
        else:
            body = " ".join(f"{'-':>{w}}" for w in (8, 8, 8, 8, 8, 8, 6, 6, 6)) + f" {score}  {m.reason}"
        lines.append(head + body)
    return "\n".join(lines)


def _pixel(x: float) -> str:
    """A pixel coordinate in the table's 8 columns: one asked for far off any image (1e308,
    refused) in 3 digits, not its 300."""
    return f"{x:8.2f}" if abs(x) < 1e6 else f"{x:8.3g}"
