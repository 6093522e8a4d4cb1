"""Looks benchmark: the whole chain on estec's frames made to look like another camera's.

The chain is tuned on one renderer; other renderers and real cameras blur, compress, expose
and grade their images differently. Here estec's first ``TRACKMETER_LOOKS_S`` seconds (default
20) are rendered once, and each frame is transformed before the engine sees it (its ground
truth kept), then tracked as the accuracy benchmark does (:func:`benchmarks.accuracy.run_chain`:
16 automatic targets, case (b) with the operator's model points, case (a) aligned to the body)
and evaluated after a 2 s settle. The looks (:data:`LOOKS`), each image independently and
reproducibly noised (seeded by the frame's index and camera):

- ``as_rendered``: the images as the simulator renders them (the reference);
- ``blur``: a Gaussian point-spread function of sigma 1 px (optics, focus);
- ``gamma_vignette``: gamma 0.7, a radial vignette darkening the corners to 60 %, and noise of
  sigma 3 grey levels;
- ``jpeg``: JPEG-compressed at quality 70 and decoded;
- ``underexposed``: grey levels times 0.35 plus noise of sigma 2 (the brightest 0.5 % of pixels
  near 67 instead of 190);
- ``gain_mismatch``: the right camera 15 % brighter than the left.

Figures, per look and case (``a``, ``b``): ``looks_<look>_<case>_valid_fraction`` and the
accuracy benchmark's ``pos_lateral_max_mm``, ``pos_depth_max_mm``, ``att_view_max_deg``,
``att_other_max_deg``, ``pos_lateral_rms_mm``, ``pos_depth_rms_mm``. The baseline in the same
run: ``looks_underexposed_<case>_valid_fraction_gain_off``, the underexposed look with the
exposure gain switched off (``exposure.reference_grey: 0``), as the chain was before it.
One noise seed (the scenario's); the engine runs :func:`benchmarks.bench_config`.
"""

from __future__ import annotations

import dataclasses
import os
import sys
from typing import Any, Callable, cast

import cv2
import numpy as np
from numpy.typing import NDArray

from benchmarks import bench_config
from benchmarks.accuracy import figures, run_chain
from trackmeter.sources.base import StereoFrame

KEPT = ("valid_fraction", "pos_lateral_max_mm", "pos_depth_max_mm", "att_view_max_deg", "att_other_max_deg",
        "pos_lateral_rms_mm", "pos_depth_rms_mm")
Image = NDArray[np.uint8]


def log(msg: str) -> None:
    print(f"[looks] {msg}", file=sys.stderr, flush=True)


def _noise(index: int, camera: int, shape: tuple[int, ...], sigma: float) -> NDArray[np.float64]:
    return np.random.default_rng((54, index, camera)).normal(0.0, sigma, shape)


def _to_uint8(values: NDArray[np.floating[Any]]) -> Image:
    return np.clip(np.rint(values), 0, 255).astype(np.uint8)


def _blur(image: Image, index: int, camera: int) -> Image:
    return cast("Image", cv2.GaussianBlur(image, (0, 0), 1.0))


def _gamma_vignette(image: Image, index: int, camera: int) -> Image:
    h, w = image.shape
    y, x = np.mgrid[0:h, 0:w]
    r = np.hypot(x - (w - 1) / 2, y - (h - 1) / 2)
    vignette = 1.0 - 0.4 * (r / r.max()) ** 2
    return _to_uint8(255.0 * (image / 255.0) ** 0.7 * vignette + _noise(index, camera, image.shape, 3.0))


def _jpeg(image: Image, index: int, camera: int) -> Image:
    ok, data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 70])
    assert ok
    return cast("Image", cv2.imdecode(data, cv2.IMREAD_GRAYSCALE))


def _underexposed(image: Image, index: int, camera: int) -> Image:
    return _to_uint8(image * 0.35 + _noise(index, camera, image.shape, 2.0))


def _gain_mismatch(image: Image, index: int, camera: int) -> Image:
    return image if camera == 0 else _to_uint8(image * 1.15)


#: Each look: a function of (image, frame index, camera 0 left / 1 right), None for as rendered.
LOOKS: dict[str, Callable[[Image, int, int], Image] | None] = {
    "as_rendered": None,
    "blur": _blur,
    "gamma_vignette": _gamma_vignette,
    "jpeg": _jpeg,
    "underexposed": _underexposed,
    "gain_mismatch": _gain_mismatch,
}


def looked(fn: Callable[[Image, int, int], Image] | None) -> Callable[[StereoFrame], StereoFrame] | None:
    """The frame transform of a look (both images, truth kept)."""
    if fn is None:
        return None
    return lambda f: dataclasses.replace(f, left=fn(f.left, f.index, 0), right=fn(f.right, f.index, 1))


def run() -> dict[str, float]:
    from trackmeter.sources.sim.simulator import Simulator

    seconds = float(os.environ.get("TRACKMETER_LOOKS_S", "20"))
    sim = Simulator("estec")
    n = min(len(sim), int(round(seconds * (sim.rate_hz or 25.0))) + 1)
    log(f"rendering estec's first {seconds:g} s ({n} frames)")
    frames = [sim.frame(k) for k in range(n)]
    config = bench_config()
    gain_off = dataclasses.replace(config, exposure=dataclasses.replace(config.exposure, reference_grey=0.0))
    out: dict[str, float] = {"looks_duration_s": seconds}
    runs = [(name, fn, config, "") for name, fn in LOOKS.items()]
    runs.append(("underexposed", LOOKS["underexposed"], gain_off, "_gain_off"))
    for name, fn, cfg, suffix in runs:
        for case, align in (("b", "none"), ("a", "body")):
            truth, est, _ = run_chain(case, seconds, frames=frames, look=looked(fn), config=cfg)
            prefix = f"looks_{name}_{case}"
            fig = figures(truth, est, align, prefix)
            if suffix:
                out[f"{prefix}_valid_fraction{suffix}"] = fig[f"{prefix}_valid_fraction"]
            else:
                out.update({f"{prefix}_{k}": fig.get(f"{prefix}_{k}", float("nan")) for k in KEPT})
            log(f"{name}{suffix} case {case}: valid {fig[f'{prefix}_valid_fraction']:.3f}, largest lateral / depth "
                f"{fig.get(f'{prefix}_pos_lateral_max_mm', float('nan')):.2f} / "
                f"{fig.get(f'{prefix}_pos_depth_max_mm', float('nan')):.2f} mm")
    return out


if __name__ == "__main__":
    from benchmarks import main_of

    main_of(__name__, __doc__, run)
