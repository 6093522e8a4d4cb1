"""Benchmark ``render``: stereo frames rendered per second for the ``estec`` geometry, one core.

The ``estec`` scenario (``config/scenarios/estec.yaml``: the paper's 726x512 rig, the ESTEC
mock-up at 3.5 m in free precession): 150 poses spread over its 60 s; each call renders the left
and right images with glints, shadows, auto-iris and sensor noise, exactly as the simulator
source does. (Without the scenario, a built-in tumble at 3.5 m stands in.)
OpenCV is held to one thread; numpy's element-wise work is single-threaded anyway.

Figures:
- ``stereo_fps``: 1000 / ``render_ms_median`` (wall clock), stereo pairs per second.
- ``render_ms_median``: median wall time per stereo pair, ms.
- ``render_cpu_ms_median``, ``stereo_fps_cpu``: the same in process CPU time, which the other
  processes sharing the machine disturb less.
- ``blur3_ms_median``: with 3 motion-blur sub-frames.
- ``remap_pair_ms_median`` and ``render_over_remap``: baseline measured in the same run (two
  full-frame ``cv2.remap`` of float images, the least any distorted stereo renderer must do)
  and the ratio, which cancels the machine's speed.
- ``stream_fps``, ``worker_cpu_ms_per_frame``, ``reader_cpu_ms_per_frame``: the live ``sim``
  source (frames rendered ahead in a worker process, as ``source_alone_fps`` of the ``pipeline``
  benchmark measures it) read as fast as it delivers for ``STREAM_S`` seconds: frames per second
  (wall clock, so it depends on what else runs), and the CPU time per frame of the worker
  process and of the reading process (which, in the live pipeline, is the tracker's).
"""

from __future__ import annotations

import dataclasses
import os
import statistics
import sys
import time
from typing import Callable, Iterable

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from trackmeter.data.rigfile import load_rig
from trackmeter.paths import MODELS_DIR, RIGS_DIR
from trackmeter.sources.sim.mockup import load_mockup
from trackmeter.sources.sim.render import RenderParams, StereoRenderer


def estec_poses(n: int, rate_hz: float = 25.0, range_m: float = 3.5) -> list[np.ndarray]:
    """``T_cam_body`` of a mock-up at ``range_m`` spinning about its z axis at 8 deg/s while that
    axis precesses at 5 deg/s about a tilted axis (a symmetric top's free motion, roughly)."""
    tilt = Rotation.from_rotvec(np.radians([-70.0, 20.0, 0.0]))
    poses = []
    for k in range(n):
        t = k / rate_hz
        R = Rotation.from_rotvec(np.radians(5.0 * t) * np.array([0.3, 0.9, 0.3]) / np.linalg.norm([0.3, 0.9, 0.3]))
        R = R * tilt * Rotation.from_rotvec([0.0, 0.0, np.radians(8.0 * t)])
        T = np.eye(4)
        T[:3, :3] = R.as_matrix()
        T[:3, 3] = (0.05, -0.03, range_m)
        poses.append(T)
    return poses


STREAM_S = 8.0


def _process_cpu_s(pid: int) -> float:
    """User + system CPU time of a (child) process so far, s (Linux /proc)."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def stream(seconds: float = STREAM_S) -> dict[str, float]:
    """The render-ahead ``sim`` source read as fast as it delivers (see the module doc)."""
    from trackmeter.sources import open_source

    with open_source("sim", realtime=False, loop=True) as source:
        source.read()  # starts the worker and waits for its first frame
        ahead = getattr(source, "_ahead", None)
        pid = ahead._proc.pid if ahead is not None else None
        w0 = _process_cpu_s(pid) if pid is not None else float("nan")
        r0 = time.process_time()
        n, t0 = 0, time.monotonic()
        while time.monotonic() - t0 < seconds:
            source.read()
            n += 1
        wall = time.monotonic() - t0
        w1 = _process_cpu_s(pid) if pid is not None else float("nan")
        r1 = time.process_time()
    return {
        "stream_fps": round(n / wall, 2),
        "worker_cpu_ms_per_frame": round((w1 - w0) * 1e3 / max(n, 1), 2),
        "reader_cpu_ms_per_frame": round((r1 - r0) * 1e3 / max(n, 1), 3),
    }


def _times(fn: Callable[[int], object], items: Iterable[int], clock: Callable[[], float]) -> list[float]:
    out = []
    for item in items:
        start = clock()
        fn(item)
        out.append((clock() - start) * 1e3)
    return out


def _estec_setup() -> tuple[StereoRenderer, StereoRenderer, list[np.ndarray], np.ndarray, str]:
    """(renderer, blur renderer, poses, sun, source) from the ``estec`` scenario (H4's simulator),
    or from the built-in geometry above when the scenario cannot be loaded."""
    try:
        from trackmeter.sources.sim.simulator import Simulator

        sim = Simulator("estec")
        poses = [sim.truth(i).T_cam_body for i in range(0, sim.n_frames, max(1, sim.n_frames // 150))]
        params = sim.scenario.render
        renderer, mockup, rig, sun, source = sim.renderer, sim.mockup, sim.true_rig, sim.sun_dir_cam, "scenario estec"
    except Exception as exc:  # noqa: BLE001 - a benchmark falls back rather than fails
        print(f"[render] estec scenario unavailable ({exc}); using the built-in geometry", file=sys.stderr)
        rig = load_rig(RIGS_DIR / "estec_12mm.yaml")
        mockup = load_mockup(MODELS_DIR / "estec_mockup.yaml")
        params = RenderParams()
        renderer = StereoRenderer(rig, mockup, params)
        poses, sun, source = estec_poses(150), np.array([-0.5, -0.6, -0.6]), "built-in"
    blur = StereoRenderer(rig, mockup, dataclasses.replace(params, motion_blur_subframes=3))
    return renderer, blur, poses, sun, source


def run() -> dict[str, float]:
    # One OpenCV thread while it is timed, and the count put back after: the benchmarks run
    # after it in one process (python -m benchmarks, reproduce) ran with one thread otherwise.
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        return _timed()
    finally:
        cv2.setNumThreads(threads)


def _timed() -> dict[str, float]:
    renderer, blur, poses, sun, source = _estec_setup()
    print(f"[render] {source}: {len(poses)} poses", file=sys.stderr)
    rng = np.random.default_rng(0)
    for T in poses[:5]:
        renderer.render(T, sun, rng)

    wall, cpu = [], []
    for k, T in enumerate(poses):
        w0, c0 = time.perf_counter(), time.process_time()
        renderer.render(T, sun, rng, T_cam_body_prev=poses[k - 1] if k else None)
        cpu.append((time.process_time() - c0) * 1e3)
        wall.append((time.perf_counter() - w0) * 1e3)
        if k % 50 == 0:
            print(f"[render] frame {k}/{len(poses)}", file=sys.stderr, flush=True)
    blur_ms = _times(lambda k: blur.render(poses[k], sun, rng, T_cam_body_prev=poses[k - 1]), range(1, 40), time.perf_counter)

    canvas = np.random.default_rng(1).random((530, 740), dtype=np.float32)
    mx = np.tile(np.linspace(3, 730, 726, dtype=np.float32), (512, 1))
    my = np.tile(np.linspace(3, 520, 512, dtype=np.float32)[:, None], (1, 726))
    remap = _times(lambda _: [cv2.remap(canvas, mx, my, cv2.INTER_LINEAR) for _ in range(2)], range(60), time.perf_counter)

    render_ms = statistics.median(wall)
    cpu_ms = statistics.median(cpu)
    remap_ms = statistics.median(remap)
    print("[render] live sim source (render-ahead worker) ...", file=sys.stderr, flush=True)
    live = stream()
    return {
        **live,
        "stereo_fps": round(1000.0 / render_ms, 2),
        "render_ms_median": round(render_ms, 3),
        "render_cpu_ms_median": round(cpu_ms, 3),
        "stereo_fps_cpu": round(1000.0 / cpu_ms, 2),
        "blur3_ms_median": round(statistics.median(blur_ms), 3),
        "remap_pair_ms_median": round(remap_ms, 3),
        "render_over_remap": round(render_ms / remap_ms, 2),
        "frames": float(len(wall)),
    }


if __name__ == "__main__":
    from benchmarks import main_of

    main_of("render", __doc__, run)
