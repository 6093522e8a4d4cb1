"""Matching on real pairs through a real calibration that the rectification crops hard.

OpenCV's stereo calibration sample (``../shared/data/stereo_calib_opencv``) calibrated with
the 8-coefficient rational model: ``stereoRectify`` (alpha 0) then zooms in by about 10 %,
and the leftmost chessboard corners' true matches fall beyond the rectified right image's
left edge. The best peak the search can still see is then a look-alike square two squares
away (score 0.98), which the second-peak rule cannot refuse because the true peak is never
compared. Every accepted corner must be the right-image corner OpenCV finds.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from trackmeter.core import matching as M
from trackmeter.core.stereo import Camera, StereoRig
from trackmeter.data.images import read_grey

PATTERN = (9, 6)
PAIRS = ("01", "02", "03", "04", "05", "06", "07", "08", "09", "11", "12", "13", "14")


def _corners(image: np.ndarray) -> np.ndarray | None:
    found, c = cv2.findChessboardCorners(image, PATTERN)
    if not found:
        return None
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.01)
    return cv2.cornerSubPix(image, c, (5, 5), (-1, -1), criteria).reshape(-1, 2)


@pytest.fixture(scope="module")
def board_views(shared_data: Path) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """(left image, right image, left corners, right corners in the left's order) per pair."""
    folder = shared_data / "stereo_calib_opencv"
    views = []
    for n in PAIRS:
        left, right = read_grey(folder / f"left{n}.jpg"), read_grey(folder / f"right{n}.jpg")
        cl, cr = _corners(left), _corners(right)
        if cl is None or cr is None:
            continue
        if np.var(cl - cr[::-1], axis=0).sum() < np.var(cl - cr, axis=0).sum():
            cr = cr[::-1]  # OpenCV may report a board from its other end
        views.append((left, right, cl, cr))
    return views


@pytest.fixture(scope="module")
def rational_rig(board_views: list) -> StereoRig:
    board = np.zeros((PATTERN[0] * PATTERN[1], 3), np.float32)
    board[:, :2] = np.mgrid[0 : PATTERN[0], 0 : PATTERN[1]].T.reshape(-1, 2)  # squares of 1
    h, w = board_views[0][0].shape
    rms, K1, D1, K2, D2, R, T, _, _ = cv2.stereoCalibrate(
        [board] * len(board_views), [v[2] for v in board_views], [v[3] for v in board_views],
        None, None, None, None, (w, h), flags=cv2.CALIB_RATIONAL_MODEL,
    )
    assert rms < 0.5
    return StereoRig(Camera(w, h, K1, D1.ravel()[:8]), Camera(w, h, K2, D2.ravel()[:8]), R, T.ravel())


def test_the_rational_rigs_rectification_crops_the_corners_true_matches(rational_rig: StereoRig) -> None:
    # the premise: a zoom of several per cent, so matches near the left edge leave the image
    rect = rational_rig.rectification
    assert rect.focal_px > 1.05 * rational_rig.left.K[0, 0]


def test_no_accepted_corner_is_matched_to_a_look_alike(board_views: list, rational_rig: StereoRig) -> None:
    accepted = wrong = unseen = 0
    for left, right, cl, cr in board_views:
        for m, truth in zip(M.measure_points(rational_rig, left, right, cl), cr):
            if m.ok:
                accepted += 1
                wrong += int(np.linalg.norm(m.right_uv - truth) > 2.0)
            unseen += int(m.reason == M.REASON_UNSEEN_RIVAL)
    assert wrong == 0
    assert unseen > 0  # the corners whose true match the rectification cropped are refused, named
    assert accepted > 0.6 * sum(len(v[2]) for v in board_views)


def test_a_patch_in_the_border_the_rectification_crops_says_so(board_views: list, rational_rig: StereoRig) -> None:
    # "patch not inside image" for a pixel 10 px inside the image the user sees read as a wrong
    # claim (an outside probe's --at 10,10): the zoomed rectification has cropped it.
    left, right = board_views[0][:2]
    h, w = left.shape
    m = M.measure_points(rational_rig, left, right, [(10.0, 10.0), (12.0, h / 2), (1.0, 1.0)])
    assert [x.reason for x in m] == [M.REASON_PATCH_CROPPED, M.REASON_PATCH_CROPPED, M.REASON_PATCH_OUTSIDE]
