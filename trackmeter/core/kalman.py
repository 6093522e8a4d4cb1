"""Image-plane Kalman filter of one target: constant-acceleration (2nd order) kinematic model.

The paper's section 2.B predicts each target's position with a kinematic Kalman filter of second
order so that the search window follows fast targets. State, left-image pixels of the ORIGINAL
image:

    x = (u, v, u', v', u'', v'')          px, px/s, px/s²

Transition over ``dt`` (constant acceleration), measurement ``z = (u, v)``:

    F = [[I, dt I, dt²/2 I], [0, I, dt I], [0, 0, I]],   H = [I 0 0]

Process noise: the discrete white-noise acceleration-increment model,
``filterpy.common.Q_discrete_white_noise(dim=3, block_size=2, order_by_dim=False)``
(Bar-Shalom, Li & Kirubarajan, *Estimation with Applications to Tracking and Navigation*,
6.3.3): the acceleration changes by a random ``w`` each frame, ``Q = Gamma Gamma^T var`` with
``Gamma = (dt²/2, dt, 1)`` per axis and ``var = accel_step_sigma_px_s2²``.

The filter itself is filterpy's :class:`~filterpy.kalman.KalmanFilter`; this module only builds
its matrices, sizes the search window from the predicted covariance and gates measurements by
their Mahalanobis distance (chi-square with 2 degrees of freedom).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from filterpy.common import Q_discrete_white_noise
from filterpy.kalman import KalmanFilter
from numpy.typing import ArrayLike, NDArray
from scipy.stats import chi2

from trackmeter.core.params import check_params, param

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class KalmanParams:
    """Tunables of the per-target image-plane filter (part of ``TrackerParams``)."""

    accel_step_sigma_px_s2: float = param(
        500.0, "std of the random change of image acceleration per frame (discrete white noise), px/s^2", min=0.0
    )
    measurement_sigma_px: float = param(0.1, "std of one left-image patch match, px", min=1e-4)
    initial_velocity_sigma_px_s: float = param(
        50.0, "std of a new target's unknown image velocity (no other target to copy it from), px/s", min=0.0
    )
    initial_accel_sigma_px_s2: float = param(
        1000.0, "std of a new target's unknown image acceleration, px/s^2", min=0.0
    )
    gate_probability: float = param(
        0.9999, "chi-square gate on the innovation: a measurement outside it is a rejected jump", min=0.5, max=0.9999999
    )
    window_sigmas: float = param(4.0, "search window half-size in predicted standard deviations", min=1.0)

    def __post_init__(self) -> None:
        check_params(self)  # declared ranges and choices, as the config loader checks them


@lru_cache(maxsize=64)
def _cached_fq(dt_s: float, accel_step_sigma_px_s2: float) -> tuple[FloatArray, FloatArray]:
    return transition_matrix(dt_s), process_noise(dt_s, accel_step_sigma_px_s2)


def transition_matrix(dt_s: float) -> FloatArray:
    """The 6x6 constant-acceleration transition ``F`` for the state order (u, v, u', v', u'', v'')."""
    I2 = np.eye(2)
    F = np.eye(6)
    F[0:2, 2:4] = dt_s * I2
    F[0:2, 4:6] = 0.5 * dt_s * dt_s * I2
    F[2:4, 4:6] = dt_s * I2
    return F


def process_noise(dt_s: float, accel_step_sigma_px_s2: float) -> FloatArray:
    """6x6 process noise ``Q`` (filterpy's discrete white-noise model; the acceleration changes by
    a random increment of std ``accel_step_sigma_px_s2`` per step)."""
    return Q_discrete_white_noise(
        dim=3, dt=dt_s, var=accel_step_sigma_px_s2**2, block_size=2, order_by_dim=False
    )


def make_filter(
    uv: ArrayLike,
    params: KalmanParams,
    velocity_px_s: ArrayLike = (0.0, 0.0),
    velocity_sigma_px_s: float | None = None,
) -> KalmanFilter:
    """A filterpy filter started at pixel ``uv`` (2,) with an optional velocity guess (2,), px/s."""
    kf = KalmanFilter(dim_x=6, dim_z=2)
    kf.x = np.array([*np.asarray(uv, float)[:2], *np.asarray(velocity_px_s, float)[:2], 0.0, 0.0])
    sv = params.initial_velocity_sigma_px_s if velocity_sigma_px_s is None else velocity_sigma_px_s
    kf.P = np.diag(
        [params.measurement_sigma_px**2] * 2 + [sv**2] * 2 + [params.initial_accel_sigma_px_s2**2] * 2
    )
    kf.H = np.hstack([np.eye(2), np.zeros((2, 4))])
    kf.R = np.eye(2) * params.measurement_sigma_px**2
    kf.F = transition_matrix(0.04)
    kf.Q = process_noise(0.04, params.accel_step_sigma_px_s2)
    return kf


def predict(kf: KalmanFilter, dt_s: float, params: KalmanParams) -> None:
    """Propagate ``kf`` by ``dt_s`` seconds (in place; filterpy's predict with this step's F, Q)."""
    dt = round(max(float(dt_s), 1e-6), 9)  # frame intervals repeat: F and Q are cached
    F, Q = _cached_fq(dt, float(params.accel_step_sigma_px_s2))
    kf.predict(F=F, Q=Q)


def innovation_covariance(kf: KalmanFilter) -> FloatArray:
    """2x2 covariance of the predicted measurement, ``S = H P H^T + R``, px²."""
    return kf.H @ kf.P @ kf.H.T + kf.R


@lru_cache(maxsize=16)
def gate_threshold(probability: float) -> float:
    """Squared Mahalanobis distance that contains ``probability`` of 2-DoF Gaussian innovations."""
    return float(chi2.ppf(probability, df=2))


def mahalanobis_sq(kf: KalmanFilter, z: ArrayLike) -> float:
    """Squared Mahalanobis distance ``y^T S^-1 y`` of measurement ``z`` (2,) from the prediction."""
    y = np.asarray(z, float)[:2] - kf.H @ kf.x
    return float(y @ np.linalg.solve(innovation_covariance(kf), y))


def search_half_size(kf: KalmanFilter, params: KalmanParams, min_px: float, max_px: float) -> FloatArray:
    """Half-size (2,) of the search window around the prediction: ``window_sigmas * sqrt(diag S)``,
    clipped to ``[min_px, max_px]``, px."""
    s = np.sqrt(np.diag(innovation_covariance(kf)))
    return np.clip(params.window_sigmas * s, min_px, max_px)


def update(kf: KalmanFilter, z: ArrayLike, params: KalmanParams) -> tuple[bool, float]:
    """Gate and fuse a measurement ``z`` (2,) px; returns ``(accepted, d²)``.

    A measurement whose squared Mahalanobis distance exceeds the chi-square gate is NOT fused
    (the filter keeps its prediction) and reported as rejected: the target jumped. So is one
    that is not finite (its distance NaN), as :func:`update_many` rejects it.
    """
    d2 = mahalanobis_sq(kf, z)
    if not d2 <= gate_threshold(params.gate_probability):  # NaN > gate is False: NaN passed
        return False, d2
    kf.update(np.asarray(z, float)[:2])
    return True, d2


# ---------------------------------------------------------------------------- batched forms
#
# A tracker steps dozens of filters per frame; filterpy's per-object predict/update costs tens of
# microseconds of Python each. These functions apply the SAME equations as filterpy's
# ``KalmanFilter.predict`` / ``update`` (Joseph-form covariance update) to many filters at once,
# reading and writing their ``x`` and ``P``; ``tests/test_kalman.py`` pins them to filterpy.


def predict_many(kfs: list[KalmanFilter], dts_s: ArrayLike, params: KalmanParams) -> None:
    """:func:`predict` for many filters (in place), each by its own ``dt`` (grouped by value)."""
    if not kfs:
        return
    dts = np.round(np.maximum(np.asarray(dts_s, dtype=float).reshape(-1), 0.0), 9)
    for dt in np.unique(dts):
        idx = np.flatnonzero(dts == dt)
        if dt <= 0:
            continue
        F, Q = _cached_fq(float(dt), float(params.accel_step_sigma_px_s2))
        X = np.stack([kfs[i].x for i in idx])
        P = np.stack([kfs[i].P for i in idx])
        X = X @ F.T
        P = F @ P @ F.T + Q
        for j, i in enumerate(idx):
            kfs[i].x = X[j]
            kfs[i].P = P[j]


def innovation_covariances(kfs: list[KalmanFilter]) -> FloatArray:
    """(N,2,2) ``S = H P H^T + R`` of many filters (H selects (u, v))."""
    return np.stack([kf.P[:2, :2] + kf.R for kf in kfs]) if kfs else np.zeros((0, 2, 2))


def search_half_sizes(kfs: list[KalmanFilter], params: KalmanParams, min_px: float, max_px: float) -> FloatArray:
    """(N,2) :func:`search_half_size` of many filters."""
    S = innovation_covariances(kfs)
    s = np.sqrt(np.stack([S[:, 0, 0], S[:, 1, 1]], axis=1))
    return np.clip(params.window_sigmas * s, min_px, max_px)


def update_many(kfs: list[KalmanFilter], z: ArrayLike, params: KalmanParams) -> tuple[NDArray[np.bool_], FloatArray]:
    """:func:`update` for many filters: gate each measurement (N,2) and fuse the accepted ones.

    Returns ``(accepted (N,), d² (N,))``.
    """
    n = len(kfs)
    if n == 0:
        return np.zeros(0, bool), np.zeros(0)
    Z = np.asarray(z, dtype=float).reshape(n, 2)
    X = np.stack([kf.x for kf in kfs])
    P = np.stack([kf.P for kf in kfs])
    R = np.stack([kf.R for kf in kfs])
    S = P[:, :2, :2] + R
    Sinv = np.linalg.inv(S)
    y = Z - X[:, :2]
    d2 = np.einsum("ni,nij,nj->n", y, Sinv, y)
    accepted = d2 <= gate_threshold(params.gate_probability)
    K = P[:, :, :2] @ Sinv  # P H^T S^-1
    X = X + np.einsum("nij,nj->ni", K, y)
    IKH = np.repeat(np.eye(6)[None], n, 0)
    IKH[:, :, :2] -= K
    P = IKH @ P @ np.transpose(IKH, (0, 2, 1)) + K @ R @ np.transpose(K, (0, 2, 1))  # Joseph form
    for i in np.flatnonzero(accepted):
        kfs[i].x = X[i]
        kfs[i].P = P[i]
    return accepted, d2
