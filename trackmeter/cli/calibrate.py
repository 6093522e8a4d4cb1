"""trackmeter calibrate: chessboard stereo calibration, written as a rig file.

Finds the chessboard's inner corners in every left/right pair (sub-pixel), calibrates each
camera (linear initialisation, then Levenberg-Marquardt), refines both jointly, drops pairs
whose two images were not taken together where the joint fit is poor (the cameras' own board
poses put the right camera elsewhere than the other pairs do; when most pairs disagree, the
images are not paired as taken and nothing is written), drops outlier views (and says which
and why), and writes the rig (OpenCV FileStorage YAML with rms_px, E, F and the standard
deviations of the parameters).

Pairs match by the number in the file names (left07.png / right07.png) when every name has
one, else by sorted order. Give --square in metres so the rig's T is in metres.

example:
  trackmeter calibrate --left 'calib/left*.png' --right 'calib/right*.png' \\
      --pattern 9x6 --square 0.025 --out rig.yaml
"""

from __future__ import annotations

import argparse
import math
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

if TYPE_CHECKING:
    import numpy as np

    from trackmeter.core.calibration import StereoCalibration


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--left", nargs="+", required=True, metavar="GLOB", help="left images: a glob (quoted) or files")
    parser.add_argument("--right", nargs="+", required=True, metavar="GLOB", help="right images: a glob (quoted) or files")
    parser.add_argument("--pattern", required=True, metavar="COLSxROWS", help="chessboard inner corners, e.g. 9x6")
    parser.add_argument("--square", required=True, type=float, metavar="METRES", help="side of one chessboard square, m")
    parser.add_argument("--out", default="rig.yaml", metavar="RIG",
                        help="rig file to write, OpenCV FileStorage YAML (XML or JSON for a .xml or .json name) "
                        "(default: rig.yaml)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an existing rig file at --out (a file that is not a rig is never replaced)")


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from trackmeter.cli.common import load_config_from_args, progress
    from trackmeter.core.calibration import calibrate_stereo, detect_corners, parse_pattern
    from trackmeter.data.images import expand_globs, pair_stereo_paths, read_grey
    from trackmeter.core.stereo import check_side_by_side
    from trackmeter.data.rigfile import baseline_problem, save_rig, swapped_cameras
    from trackmeter.errors import TrackmeterError

    params = load_config_from_args(args).calibrate
    pattern = parse_pattern(args.pattern)
    if not (MIN_SQUARE_M <= args.square <= MAX_SQUARE_M):  # NaN fails too
        # 1e-300 m passed and underflowed in OpenCV's float32 board points (a cv2.error traceback).
        raise TrackmeterError(f"--square must be a length in metres from {MIN_SQUARE_M:g} to {MAX_SQUARE_M:g}, "
                              f"got {args.square:g}")
    _check_out(args.out, args.overwrite)  # before the work, which takes a while
    lefts, rights = expand_globs(args.left, "left images"), expand_globs(args.right, "right images")
    # Before pairing: a left pattern that also matches the right camera's files (dir/*.jpg) would
    # otherwise be refused for whatever the pairing makes of the mixture.
    on_right = {p.resolve() for p in rights}
    same = [p for p in lefts if p.resolve() in on_right]
    if same:
        raise TrackmeterError(f"{same[0]} is given as both a left and a right image ({len(same)} of the {len(lefts)} left "
                              "images): --left and --right must name the two cameras' images")
    pairs = pair_stereo_paths(lefts, rights)

    size: tuple[int, int] | None = None
    uv_left: list = []
    uv_right: list = []
    for left_path, right_path in progress(pairs, len(pairs), "corners"):
        for path, out in ((left_path, uv_left), (right_path, uv_right)):
            image = read_grey(path)
            image_size = (image.shape[1], image.shape[0])
            if size is None:
                size = image_size
            elif image_size != size:
                raise TrackmeterError(
                    f"{path}: image is {image_size[0]}x{image_size[1]}, the first one was {size[0]}x{size[1]}"
                )
            out.append(detect_corners(image, pattern, params))
    assert size is not None
    if not any(u is not None for u in uv_left + uv_right):
        raise TrackmeterError(
            f"no {pattern[0]}x{pattern[1]} chessboard corners found in any of the {2 * len(pairs)} images "
            "(check --pattern: inner corners, COLSxROWS)"
        )

    result = calibrate_stereo(uv_left, uv_right, pattern, args.square, size, params)
    rig, std = result.rig, result.std
    if rig.baseline_m < MIN_BASELINE_SQUARES * args.square:
        # The same views twice (copies of one camera's images): no stereo rig to write.
        raise TrackmeterError(f"the two cameras came out {rig.baseline_m / args.square:.2g} squares apart, at the same "
                              "place: are --left and --right copies of the same images? (nothing written)")
    extra: dict[str, np.ndarray | float] = {
        "E": result.E,
        "F": result.F,
        "std_K1": np.array([std["fx1"], std["fy1"], std["cx1"], std["cy1"]]),
        "std_K2": np.array([std["fx2"], std["fy2"], std["cx2"], std["cy2"]]),
        "std_D1": np.array([v for k, v in std.items() if k.endswith("_1")]),
        "std_D2": np.array([v for k, v in std.items() if k.endswith("_2")]),
        "std_rvec": np.array([std["rx"], std["ry"], std["rz"]]),
        "std_T": np.array([std["tx"], std["ty"], std["tz"]]),
        "std_baseline": std["baseline"],
        "rectification_vertical_rms_px": result.rectification.rms_px,
    }
    try:
        check_side_by_side(rig)
    except TrackmeterError as exc:  # measure and track refuse such a rig: none is written
        if swapped_cameras(rig):  # the rig reader's advice (negate T) is for a file, not for this
            centre = np.round(-rig.R.T @ rig.T, 3) + 0.0  # + 0.0: no "-0.000"
            raise TrackmeterError(f"the right camera lies left of the left one (its centre "
                                  f"[{', '.join(f'{c:.3f}' for c in centre)}] m in the left camera's "
                                  "frame): --left and --right were given the wrong way round; exchange them. "
                                  "measure and track refuse such a rig, so none was written") from None
        raise TrackmeterError(f"{exc}; measure and track refuse such a rig, so none was written") from None
    out_path = save_rig(rig, args.out, extra)
    print(format_report(result, pairs, args.square, out_path))
    if result.rms_px > HIGH_RMS_PX:
        warnings.warn(f"RMS reprojection error {result.rms_px:.2g} px is high for chessboard corners (0.05-0.5 px "
                      "is usual): check the --pattern, that the board is flat and the images sharp, and the lens "
                      "model (--config with calibrate.distortion_model: rational for a wide lens)", stacklevel=1)
    implausible = baseline_problem(rig)
    if implausible:
        warnings.warn(f"{implausible}: --square is the side of one square in metres (25 mm is 0.025)", stacklevel=1)
    return 0


def _check_out(out: str, overwrite: bool = False) -> None:
    """Refuse an ``--out`` the rig file cannot be written to: an empty name, a folder, a file
    that exists (a calibration is not replaced without ``overwrite``), or a place under a file
    or an unwritable folder; nothing is created.

    Raises:
        TrackmeterError: naming the path and why.
    """
    from trackmeter.data.atomic import unwritable_ancestor
    from trackmeter.errors import TrackmeterError

    if not out.strip():
        raise TrackmeterError("--out: the rig file's name is empty")
    path = Path(out)
    if path.is_dir():
        raise TrackmeterError(f"--out {path}: is a folder; give the rig file's name, e.g. {path / 'rig.yaml'}")
    if path.exists() and not overwrite:
        raise TrackmeterError(f"--out {path}: exists (an earlier calibration?); choose another --out or give --overwrite")
    if path.exists() or path.is_symlink():
        from trackmeter.data.rigfile import is_rig_file

        if path.is_symlink() or not path.is_file() or not is_rig_file(path):
            # --overwrite replaces a calibration, not the user's other files (notes.txt, a run's
            # trajectory.tum were rewritten as rigs).
            raise TrackmeterError(f"--out {path}: not a rig file; --overwrite replaces only an earlier calibration: "
                                  "choose another --out")
    blocked = unwritable_ancestor(path.parent)
    if blocked is not None:
        raise TrackmeterError(f"--out {path}: cannot write the rig file there ({blocked} is not a writable folder)")


#: A calibrated baseline shorter than this many squares is no stereo rig: the same views twice.
MIN_BASELINE_SQUARES = 1e-3

#: A joint RMS reprojection error above this, px, is warned about: sub-pixel chessboard corners
#: fit to 0.05-0.5 px (OpenCV's sample pairs 0.22 px, rendered boards 0.05-0.07 px).
HIGH_RMS_PX = 1.0

#: Per-camera RMS this many times the joint one is said in the report (a fit that stopped).
STALLED_RATIO = 3.0

#: The --square sizes accepted, m (a 0.1 mm square to a 100 m one: anything else is a typo; a
#: size in millimetres, 25 for 0.025, passes and is warned about by the baseline it gives).
MIN_SQUARE_M, MAX_SQUARE_M = 1e-4, 100.0


def format_report(result: StereoCalibration, pairs: Sequence[tuple[Path, Path]], square: float, out_path: Path) -> str:
    """The human-readable summary printed by the command."""
    import numpy as np

    rig, std = result.rig, result.std
    lines = []
    lines.append(f"views: {len(result.used_views)} used of {len(pairs)} pairs")
    lines.append(f"RMS reprojection error: {result.rms_px:.4f} px (joint, both images)")
    alone = f"  per camera alone: left {result.left.rms_px:.4f} px, right {result.right.rms_px:.4f} px"
    if max(result.left.rms_px, result.right.rms_px) > STALLED_RATIO * result.rms_px:
        # A wide lens (an outside probe's k1 -0.3 at f 500 px): OpenCV's start for one camera
        # is far off, its fit stops in a poorer solution, and the joint one climbs out of it.
        alone += (" (far above the joint fit: a camera's own fit stopped in a poorer solution, which the joint "
                  "refinement, held by both cameras, left; the joint one is written)")
    lines.append(alone)
    b = rig.baseline_m
    lines.append(f"baseline: {b:.6g} ± {std['baseline']:.2g} m ({b / square:.4f} squares)")
    lines.append("T: [" + ", ".join(f"{t:.6g}" for t in rig.T) + f"] m, ± [{std['tx']:.2g}, {std['ty']:.2g}, {std['tz']:.2g}]")
    rvec_deg = np.degrees(_rodrigues(rig.R))
    lines.append(
        "R (rotation vector): [" + ", ".join(f"{r:.4f}" for r in rvec_deg) + "] deg, ± ["
        + ", ".join(f"{math.degrees(std[k]):.2g}" for k in ("rx", "ry", "rz")) + "]"
    )
    for side, cam, idx in (("left", rig.left, 1), ("right", rig.right, 2)):
        K = cam.K
        lines.append(
            f"{side}: fx {K[0, 0]:.3f} ± {std[f'fx{idx}']:.2g}, fy {K[1, 1]:.3f} ± {std[f'fy{idx}']:.2g}, "
            f"cx {K[0, 2]:.3f} ± {std[f'cx{idx}']:.2g}, cy {K[1, 2]:.3f} ± {std[f'cy{idx}']:.2g} px"
        )
        dist = [f"{k.split('_')[0]} {cam.dist[i]:.5f} ± {v:.2g}" for i, (k, v) in enumerate((k, v) for k, v in std.items() if k.endswith(f"_{idx}"))]
        lines.append(f"  distortion: {', '.join(dist)}")
    rc = result.rectification
    lines.append(
        f"rectification check: vertical disparity of rectified corners RMS {rc.rms_px:.4f} px, max {rc.max_abs_px:.4f} px"
    )
    if result.rejected:
        lines.append(f"rejected views: {len(result.rejected)}")
        for rv in result.rejected:
            left, right = pairs[rv.index]
            lines.append(f"  {left.name} / {right.name}: {rv.reason}")
    else:
        lines.append("rejected views: none")
    lines.append("per-view RMS, px (left, right, rectified vertical disparity):")
    for k, i in enumerate(result.used_views):
        left, right = pairs[i]
        e = result.per_view_rms_px[k]
        lines.append(f"  {left.name} / {right.name}: {e[0]:.4f} {e[1]:.4f} {rc.per_view_rms_px[k]:.4f}")
    lines.append(f"wrote {out_path}")
    return "\n".join(lines)


def _rodrigues(R: "np.ndarray") -> "np.ndarray":
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_rotvec()

