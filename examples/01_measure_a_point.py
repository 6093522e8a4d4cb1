"""01 · Measure 3D points with the stereo rig (paper section 2.A).

Renders one stereo pair of the simulated ESTEC trial, measures the 3D points under a few
pixels of the left image (patch match along the rectified epipolar line, sub-pixel,
triangulated, with the covariance of paper eqs. 1-2), and compares them with the renderer's
true surface points. The same measurement is ``trackmeter measure`` on the command line.

    python examples/01_measure_a_point.py
"""

from __future__ import annotations

import numpy as np

from trackmeter.core.matching import measure_points
from trackmeter.sources.sim.simulator import Simulator


def main() -> None:
    sim = Simulator("estec", render_ahead=False)
    frame = sim.frame(0)  # StereoFrame: left/right uint8 images, t_s, truth
    # Two textured pixels, then one on the repetitive solar-cell grid (refused: ambiguous) and
    # one in black space (refused: too dark).
    pixels = np.array([[280.0, 331.0], [435.0, 87.0], [153.0, 283.0], [30.0, 30.0]])

    for m in measure_points(sim.rig, frame.left, frame.right, pixels):
        if not m.ok:
            print(f"({m.uv[0]:6.1f}, {m.uv[1]:6.1f})  refused: {m.reason}")
            continue
        # The renderer's surface under the pixel, in the left camera frame (m).
        T = sim.truth(0).T_cam_body
        truth = sim.surface_points(0, m.uv[None])[0] @ T[:3, :3].T + T[:3, 3]
        error_mm = 1e3 * (m.xyz_m - truth)
        print(f"({m.uv[0]:6.1f}, {m.uv[1]:6.1f})  xyz {np.round(m.xyz_m, 4)} m  "
              f"sigma {np.round(1e3 * m.sigma_m, 2)} mm  error {np.round(error_mm, 2)} mm")


if __name__ == "__main__":
    main()
