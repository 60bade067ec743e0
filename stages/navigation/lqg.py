"""LQG navigation along a recorded path with a landmark map (Mu et al. 2015, Sec. V, eqs. 24-27).

The robot is a planar unicycle, state ``x = (x, y, θ)``, control ``u = (v, ω)``::

    x_{k+1} = x_k + (v cos θ, v sin θ, ω) dt,   actuation noise on (v, ω)

It follows a nominal trajectory ``x^d`` (the recorded path resampled every ``dt``) with

* an EKF that localises against the case's landmark map: range-bearing measurements of the map's
  landmarks, with the landmark uncertainty folded into the measurement noise,
  ``R̄ = R + M Σ_L Mᵀ`` (eq. 26, ``M`` the Jacobian w.r.t. the landmark), and
* a finite-horizon LQR on the dynamics linearised along ``x^d`` (eq. 27):
  ``u_k = u^d_k − L_k (x̂_k − x^d_k)``, ``L_k = (Bᵀ S_{k+1} B + W_u)⁻¹ Bᵀ S_{k+1} A``.

The world generates measurements from the *true* landmark positions, so a map whose landmarks are
off by more than their stated covariance pulls the estimate, and the robot, off the path. A trial
ends at its first collision (the true position closer than the robot radius to an obstacle).
Trials run vectorised: all ``N`` trials advance together, one landmark update at a time.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import numpy.typing as npt

from stages.geometry import wrap_angle
from stages.navigation.stats import wilson_interval
from stages.navigation.walls import Obstacles

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True)
class NominalPath:
    """The path to follow, sampled every ``dt_s``, with the open-loop controls that drive along it."""

    stamps_ns: IntArray
    poses: FloatArray
    """(K, 3) x, y, θ (θ unwrapped)."""
    controls: FloatArray
    """(K-1, 2) v (m/s), ω (rad/s) from step k to k+1."""
    dt_s: float

    def __len__(self) -> int:
        return len(self.poses)


def nominal_path(stamps_ns: npt.ArrayLike, poses: FloatArray, dt_s: float = 0.2) -> NominalPath:
    """Resample a recorded path (keyframe stamps and x, y, θ) every ``dt_s`` and derive its controls."""
    t = np.asarray(stamps_ns, dtype=np.int64)
    order = np.argsort(t, kind="stable")
    t, p = t[order], np.asarray(poses, dtype=float)[order]
    keep = np.concatenate([[True], np.diff(t) > 0])
    t, p = t[keep], p[keep]
    if len(t) < 2:
        raise ValueError("a nominal path needs at least two poses at distinct stamps")
    step_ns = round(dt_s * 1e9)
    q = np.arange(t[0], t[-1] + 1, step_ns, dtype=np.int64)
    yaw = np.unwrap(p[:, 2])
    tf, qf = (t - t[0]).astype(float), (q - t[0]).astype(float)
    res = np.column_stack([np.interp(qf, tf, p[:, 0]), np.interp(qf, tf, p[:, 1]), np.interp(qf, tf, yaw)])
    d = np.diff(res, axis=0)
    v = (d[:, 0] * np.cos(res[:-1, 2]) + d[:, 1] * np.sin(res[:-1, 2])) / dt_s
    w = d[:, 2] / dt_s
    return NominalPath(q, res, np.column_stack([v, w]), float(dt_s))


def _f(x: FloatArray, u: FloatArray, dt: float) -> FloatArray:
    th = x[..., 2]
    return np.stack(
        [x[..., 0] + u[..., 0] * np.cos(th) * dt, x[..., 1] + u[..., 0] * np.sin(th) * dt, th + u[..., 1] * dt],
        axis=-1,
    )


def _AB(x: FloatArray, u: FloatArray, dt: float) -> tuple[FloatArray, FloatArray]:
    """Jacobians of the unicycle step w.r.t. the state (…, 3, 3) and the control (…, 3, 2)."""
    th = x[..., 2]
    shape = th.shape
    A = np.broadcast_to(np.eye(3), (*shape, 3, 3)).copy()
    A[..., 0, 2] = -u[..., 0] * np.sin(th) * dt
    A[..., 1, 2] = u[..., 0] * np.cos(th) * dt
    B = np.zeros((*shape, 3, 2))
    B[..., 0, 0] = np.cos(th) * dt
    B[..., 1, 0] = np.sin(th) * dt
    B[..., 2, 1] = dt
    return A, B


def lqr_gains(path: NominalPath, Wx: FloatArray, Wu: FloatArray) -> FloatArray:
    """Finite-horizon LQR gains ``L_k`` (K-1, 2, 3) along the path (backward Riccati recursion, eq. 27)."""
    A, B = _AB(path.poses[:-1], path.controls, path.dt_s)
    S = Wx.copy()
    gains = np.zeros((len(path) - 1, 2, 3))
    for k in range(len(path) - 2, -1, -1):
        G = Wu + B[k].T @ S @ B[k]
        L = np.linalg.solve(G, B[k].T @ S @ A[k])
        gains[k] = L
        S = Wx + A[k].T @ S @ (A[k] - B[k] @ L)
        S = 0.5 * (S + S.T)
    return gains


class MapLike(Protocol):
    """A planar landmark map: ``tag_ids`` (L,), ``positions`` (L, 2), ``covariances`` (L, 2, 2)."""

    @property
    def tag_ids(self) -> IntArray: ...

    @property
    def positions(self) -> FloatArray: ...

    @property
    def covariances(self) -> FloatArray: ...


@dataclass(frozen=True)
class NavigationMap:
    """The landmark map a simulated robot navigates with: ids, estimated positions and their covariances (map frame).

    A :class:`MapLike`, as is :class:`stages.risk.LandmarkMap` (the map of a solved graph), so either can be
    passed to :func:`simulate`.
    """

    tag_ids: IntArray
    positions: FloatArray
    """(L, 2) estimated positions."""
    covariances: FloatArray
    """(L, 2, 2) marginal position covariances."""

    def __len__(self) -> int:
        return len(self.tag_ids)


@dataclass(frozen=True)
class NavigationParams:
    """Settings of the Monte Carlo navigation (see ``EvaluateConfig`` for their meaning and defaults)."""

    trials: int = 100
    robot_radius_m: float = 0.2
    bearing_sigma_rad: float = 0.02
    range_sigma_m: float = 0.05
    speed_sigma_mps: float = 0.05
    yaw_rate_sigma_radps: float = 0.05
    initial_sigma_m: float = 0.02
    initial_sigma_rad: float = 0.01
    lqr_position_weight: float = 10.0
    lqr_heading_weight: float = 1.0
    lqr_speed_weight: float = 1.0
    lqr_yaw_rate_weight: float = 1.0
    max_speed_mps: float = 1.0
    max_yaw_rate_radps: float = 1.5
    keep_paths: int = 5

    @property
    def Wx(self) -> FloatArray:
        """LQR state weight."""
        return np.diag([self.lqr_position_weight, self.lqr_position_weight, self.lqr_heading_weight])

    @property
    def Wu(self) -> FloatArray:
        """LQR control weight."""
        return np.diag([self.lqr_speed_weight, self.lqr_yaw_rate_weight])


@dataclass
class NavigationResult:
    """What the Monte Carlo trials of one map gave."""

    trials: int
    collisions: int
    collision_rate: float
    ci_low: float
    ci_high: float
    collision_steps: IntArray
    """(N,) step of each trial's collision, -1 when it reached the end."""
    rms_tracking_error_m: float
    """RMS distance between the true position and the nominal path (steps before any collision)."""
    rms_estimation_error_m: float
    """RMS distance between the EKF's estimate and the true position."""
    sample_paths: FloatArray
    """(keep_paths, K, 2) true positions of the first trials (frozen at their collision)."""
    mean_estimate_sigma_m: float
    """Mean of sqrt(trace of the EKF position covariance) over the active steps."""
    step_rms_deviation_m: FloatArray = field(default_factory=lambda: np.zeros(0))
    """(K,) per step, RMS distance of the active trials' true positions from the nominal pose of that step (NaN once
    every trial has collided)."""
    step_ekf_sigma_m: FloatArray = field(default_factory=lambda: np.zeros(0))
    """(K,) per step, mean over the active trials of the EKF's position σ (sqrt of the largest xy eigenvalue)."""


def visibility_schedule(
    step_stamps_ns: npt.ArrayLike, obs_stamps_ns: npt.ArrayLike, obs_ids: npt.ArrayLike, window_s: float = 0.5
) -> list[IntArray]:
    """Landmark ids seen in the recording within ``window_s`` of each step (the set ``L(x)`` of the paper).

    Visibility comes from the data (which tags the recording robot actually detected near that
    point of the path), so no camera field of view or occlusion model is needed.
    """
    t = np.asarray(obs_stamps_ns, dtype=np.int64)
    ids = np.asarray(obs_ids, dtype=np.int64)
    order = np.argsort(t, kind="stable")
    t, ids = t[order], ids[order]
    w = int(window_s * 1e9)
    out = []
    for s in np.asarray(step_stamps_ns, dtype=np.int64):
        lo, hi = np.searchsorted(t, s - w, "left"), np.searchsorted(t, s + w, "right")
        out.append(np.unique(ids[lo:hi]))
    return out


def simulate(
    path: NominalPath,
    gains: FloatArray,
    landmark_map: MapLike,
    true_landmarks: Mapping[int, FloatArray],
    visibility: Sequence[IntArray],
    obstacles: Obstacles | None,
    params: NavigationParams,
    seed: int = 0,
) -> NavigationResult:
    """Run ``params.trials`` LQG trials along ``path`` with ``landmark_map``; count collisions.

    Args:
        path: the nominal trajectory.
        gains: :func:`lqr_gains` of the path.
        landmark_map: the case's map (only these landmarks are used by the EKF).
        true_landmarks: true (x, y) of every landmark id that may be measured.
        visibility: per step, the landmark ids the robot can see (:func:`visibility_schedule`).
        obstacles: walls; None = no collisions (open space).
        params: noise, weights, radius, trials.
        seed: seed of every random draw (the same seed gives the same noise to every map).
    """
    rng = np.random.default_rng(seed)
    N, K, dt = params.trials, len(path), path.dt_s
    index = {int(i): j for j, i in enumerate(landmark_map.tag_ids)}
    truth = {int(i): np.asarray(p, dtype=float)[:2] for i, p in true_landmarks.items()}
    R = np.diag([params.bearing_sigma_rad**2, params.range_sigma_m**2])
    Qu = np.diag([params.speed_sigma_mps**2, params.yaw_rate_sigma_radps**2])
    P0 = np.diag([params.initial_sigma_m**2] * 2 + [params.initial_sigma_rad**2])
    x = path.poses[0] + rng.standard_normal((N, 3)) * np.sqrt(np.diag(P0))
    xh = np.repeat(path.poses[:1], N, axis=0)
    P = np.repeat(P0[None], N, axis=0)
    collided = np.zeros(N, dtype=bool)
    col_step = np.full(N, -1, dtype=np.int64)
    keep = min(params.keep_paths, N)
    paths = np.zeros((keep, K, 2))
    paths[:, 0] = x[:keep, :2]
    stats = _TrialStats(K)
    if obstacles is not None:
        hit = obstacles.distance(x[:, :2]) < params.robot_radius_m
        collided |= hit
        col_step[hit] = 0
    stats.step(0, ~collided, x, P, path.poses[0])
    for k in range(K - 1):
        u = _control(xh, path, gains, k, params)
        # the world
        noisy = u + rng.standard_normal((N, 2)) * np.sqrt(np.diag(Qu))
        x = np.where(collided[:, None], x, _f(x, noisy, dt))
        # EKF predict
        A, B = _AB(xh, u, dt)
        xh = _f(xh, u, dt)
        P = A @ P @ A.transpose(0, 2, 1) + B @ Qu @ B.transpose(0, 2, 1) + 1e-12 * np.eye(3)
        # EKF update, one landmark of the map at a time (eq. 26 noise)
        for lid in visibility[k + 1]:
            j = index.get(int(lid))
            if j is None or int(lid) not in truth:
                continue
            z = _measure(x, truth[int(lid)], R, rng)
            xh, P = _ekf_update(xh, P, z, landmark_map.positions[j], landmark_map.covariances[j], R)
        active = ~collided
        if active.any():
            stats.add(active, x, xh, P, path.poses[k + 1])
            stats.step(k + 1, active, x, P, path.poses[k + 1])
        if obstacles is not None:
            hit = active & (obstacles.distance(x[:, :2]) < params.robot_radius_m)
            collided |= hit
            col_step[hit] = k + 1
        paths[:, k + 1] = x[:keep, :2]
    n_col = int(collided.sum())
    lo, hi = wilson_interval(n_col, N)
    denom = max(stats.n_active, 1)
    return NavigationResult(
        trials=N,
        collisions=n_col,
        collision_rate=n_col / N if N else float("nan"),
        ci_low=lo,
        ci_high=hi,
        collision_steps=col_step,
        rms_tracking_error_m=float(np.sqrt(stats.se_track / denom)),
        rms_estimation_error_m=float(np.sqrt(stats.se_est / denom)),
        sample_paths=paths,
        mean_estimate_sigma_m=stats.sig_sum / denom,
        step_rms_deviation_m=np.where(stats.step_n > 0, np.sqrt(stats.step_dev / np.maximum(stats.step_n, 1)), np.nan),
        step_ekf_sigma_m=np.where(stats.step_n > 0, stats.step_sig / np.maximum(stats.step_n, 1), np.nan),
    )


class _TrialStats:
    """Running sums over the trials still moving: tracking and estimation errors, EKF sigma, per step."""

    def __init__(self, K: int) -> None:
        self.se_track = self.se_est = self.sig_sum = 0.0
        self.n_active = 0
        self.step_dev = np.zeros(K)
        self.step_sig = np.zeros(K)
        self.step_n = np.zeros(K)

    def add(
        self, active: npt.NDArray[np.bool_], x: FloatArray, xh: FloatArray, P: FloatArray, nominal: FloatArray
    ) -> None:
        """One step's squared errors (true from nominal, estimate from true) and position sigmas."""
        self.se_track += float((np.square(x[active, :2] - nominal[:2])).sum())
        self.se_est += float((np.square(xh[active, :2] - x[active, :2])).sum())
        self.sig_sum += float(np.sqrt(np.maximum(P[active, 0, 0] + P[active, 1, 1], 0.0)).sum())
        self.n_active += int(active.sum())

    def step(self, k: int, active: npt.NDArray[np.bool_], x: FloatArray, P: FloatArray, nominal: FloatArray) -> None:
        """Step ``k``'s squared deviation from the nominal path and the sum of the EKF's largest position sigmas."""
        if not active.any():
            return
        self.step_dev[k] = float(np.square(x[active, :2] - nominal[:2]).sum())
        Pxy = P[active, :2, :2]
        tr, det = Pxy[:, 0, 0] + Pxy[:, 1, 1], Pxy[:, 0, 0] * Pxy[:, 1, 1] - Pxy[:, 0, 1] * Pxy[:, 1, 0]
        lam = 0.5 * tr + np.sqrt(np.maximum(0.25 * tr * tr - det, 0.0))
        self.step_sig[k] = float(np.sqrt(np.maximum(lam, 0.0)).sum())
        self.step_n[k] = float(active.sum())


def _control(xh: FloatArray, path: NominalPath, gains: FloatArray, k: int, params: NavigationParams) -> FloatArray:
    """The LQR control of step ``k`` from the estimates, clipped to the speed and yaw-rate limits."""
    e = xh - path.poses[k]
    e[:, 2] = wrap_angle(e[:, 2])
    u = path.controls[k] - e @ gains[k].T
    u[:, 0] = np.clip(u[:, 0], -params.max_speed_mps, params.max_speed_mps)
    u[:, 1] = np.clip(u[:, 1], -params.max_yaw_rate_radps, params.max_yaw_rate_radps)
    return u


def _measure(x: FloatArray, landmark: FloatArray, R: FloatArray, rng: np.random.Generator) -> FloatArray:
    """Noisy bearing and range of the true ``landmark`` from each true pose."""
    d = landmark - x[:, :2]
    z = np.column_stack([wrap_angle(np.arctan2(d[:, 1], d[:, 0]) - x[:, 2]), np.hypot(d[:, 0], d[:, 1])])
    return z + rng.standard_normal((len(x), 2)) * np.sqrt(np.diag(R))


def _ekf_update(
    xh: FloatArray, P: FloatArray, z: FloatArray, lh: FloatArray, SL: FloatArray, R: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """EKF update of every trial with one bearing-range measurement of a map landmark at ``lh`` with covariance
    ``SL``: the landmark's uncertainty enters as measurement noise (eq. 26), Joseph form."""
    N = len(xh)
    d = lh - xh[:, :2]
    q = np.maximum((d * d).sum(1), 1e-12)
    r = np.sqrt(q)
    zh = np.column_stack([np.arctan2(d[:, 1], d[:, 0]) - xh[:, 2], r])
    H = np.zeros((N, 2, 3))
    H[:, 0, 0], H[:, 0, 1], H[:, 0, 2] = d[:, 1] / q, -d[:, 0] / q, -1.0
    H[:, 1, 0], H[:, 1, 1] = -d[:, 0] / r, -d[:, 1] / r
    M = np.zeros((N, 2, 2))
    M[:, 0, 0], M[:, 0, 1] = -d[:, 1] / q, d[:, 0] / q
    M[:, 1, 0], M[:, 1, 1] = d[:, 0] / r, d[:, 1] / r
    Rbar = R + M @ SL @ M.transpose(0, 2, 1)
    PHt = P @ H.transpose(0, 2, 1)
    S = H @ PHt + Rbar
    Kg = PHt @ np.linalg.inv(S)
    nu = z - zh
    nu[:, 0] = wrap_angle(nu[:, 0])
    IKH = np.eye(3) - Kg @ H
    return xh + np.einsum("nij,nj->ni", Kg, nu), IKH @ P @ IKH.transpose(0, 2, 1) + Kg @ Rbar @ Kg.transpose(0, 2, 1)
