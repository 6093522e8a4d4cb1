"""04 · Record a stereo stream, track it headless, evaluate against ground truth.

What ``trackmeter simulate``, ``trackmeter track`` and ``trackmeter evaluate`` do, through the
library: 3 s of the simulated ESTEC trial are written to a sequence folder (EuRoC layout, with
its rig and ground truth), played back through the pipeline's two threads (acquisition and
tracking, no frame dropped off-line) with 16 automatic targets, and the estimated motion is
compared with the truth after a 2 s settling time, aligning the case-(a) body frame first.
The sequence folder is a temporary one, removed when the example ends (``trackmeter simulate
--duration 3 --out DIR`` writes one to keep).

    python examples/04_record_replay_evaluate.py
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from trackmeter.core.metrics import EvaluateParams, evaluate
from trackmeter.core.transforms import matrix_to_quat_wxyz
from trackmeter.data.config import load_config
from trackmeter.data.evaluation import load_truth
from trackmeter.data.motion_csv import MotionSeries
from trackmeter.data.sequence import SequenceWriter
from trackmeter.pipeline.engine import Engine
from trackmeter.pipeline.pipeline import run_headless
from trackmeter.pipeline.snapshot import SetAuto, Snapshot
from trackmeter.sources import open_source
from trackmeter.sources.sim.simulator import Simulator

SECONDS = 3.0


def main() -> None:
    with tempfile.TemporaryDirectory(prefix="trackmeter-example-") as tmp:  # removed at the end
        record_replay_evaluate(Path(tmp) / "estec")


def record_replay_evaluate(folder: Path) -> None:
    sim = Simulator("estec", render_ahead=False)
    with SequenceWriter(folder, rig=sim.rig) as writer:  # images, data.csv, rig.yaml, groundtruth
        n_frames = round(SECONDS * sim.rate_hz)  # as `trackmeter simulate --duration 3` writes
        for k in range(n_frames):
            writer.write(sim.frame(k))
    print(f"recorded {n_frames} frames to {folder} (removed at the end)")

    source = open_source(f"seq:{folder}")
    assert source.rig is not None  # the folder's rig.yaml, written above
    engine = Engine(load_config(), source.rig, case="a", rate_hz=source.rate_hz, live_errors=False)
    rows: list[tuple[float, np.ndarray, np.ndarray, np.ndarray]] = []  # the valid poses
    first_t: list[float] = []

    def keep(snap: Snapshot) -> None:  # on the tracking thread, one snapshot a frame
        if snap.frame is None:
            return
        first_t[:] = first_t or [snap.frame.t_s]
        p = snap.pose
        if p.valid and (not rows or snap.frame.t_s > rows[-1][0]):
            rows.append((snap.frame.t_s, p.T_cam_body, p.velocity_cam_m_s, p.omega_body_rad_s))

    last, replies = run_headless(source, engine, on_snapshot=keep, commands=[SetAuto(True, 16, "gabor")])
    source.close()
    print(f"{replies[0].message}; {last.timings.frames_processed} frames tracked, {len(rows)} valid poses")

    T = np.array([r[1] for r in rows])
    estimate = MotionSeries(np.array([r[0] for r in rows]), np.ones(len(rows), bool), T[:, :3, 3],
                            matrix_to_quat_wxyz(T[:, :3, :3]), np.array([r[2] for r in rows]),
                            np.array([r[3] for r in rows]))
    truth = load_truth(folder).series
    # The settling time counts from the run's first frame, as for a run directory's states.csv.
    result = evaluate(truth, estimate, EvaluateParams(settle_s=2.0, align="body"), t_start_s=first_t[0])
    s = result.summary
    print(f"after 2 s, {s['matched']} poses: position error rms {1e3 * s['position_m']['norm']['rms']:.2f} mm, "
          f"max {1e3 * s['position_m']['norm']['max']:.2f} mm; attitude max "
          f"{np.degrees(s['attitude_rad']['total']['max']):.3f} deg")


if __name__ == "__main__":
    main()
