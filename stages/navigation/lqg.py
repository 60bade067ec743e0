"""LQG navigation in a case's own map (Mu et al. 2015, Sec. V, eqs. 24-27), with the robot of the risk model.

The robot is the planar unicycle of :mod:`stages.estimation.robot` (the same model, noise and control period as
the risk model of Alg. 2), state ``x = (x, y, θ)``, control ``u = (v, ω)``, white noise on (v, ω).

Frames. The robot *plans and estimates in the case's map*: its nominal trajectory ``x̂^d`` is the case's own
trajectory estimate (the reduced graph's keyframes, resampled every control period), its EKF localises against
the case's landmark positions. The robot *moves in the world*: it starts at the true start pose (the map's origin,
where the first pose's prior pins it), the controls act on its true state, measurements are generated from the
*true* landmarks, and a trial ends at the first collision of its true position with the *true* obstacles. So a map
displaced as a whole (drift from the start) is harmless when the landmarks the robot sees are displaced with the
path it follows, and a map whose path and landmarks disagree locally (or that has no landmark where the path needs
one) steers the robot into a wall.

* Filter: range-bearing measurements of the case's landmarks visible at the step, in a Schmidt-Kalman filter
  whose considered states are the map's landmark errors with the map's *joint* covariance
  (:func:`stages.risk.map_covariances`): eq. 26's ``R + M Σ_L Mᵀ`` is its first update, and the cross-covariance
  it carries keeps the same landmark error, met again, or the drift that several landmarks share, from being
  taken for fresh information (which made the plain eq. 26 filter overconfident).
* LQR: finite horizon on the dynamics linearised along the nominal path (eq. 27),
  ``u_k = u^d_k − L_k (x̂_k − x^d_k)``, ``L_k = (Bᵀ S_{k+1} B + W_u)⁻¹ Bᵀ S_{k+1} A``.
* Random streams: the start, the actuation noise and the measurement noise each have their own stream, and the
  measurement stream draws for every landmark the recording saw at a step whether or not the case's map has it,
  so every case with the same seed meets the same world.
* Consistency: the estimation error ``e = x̂ − x`` (both in the map frame: the world is brought into it by the
  first pose, where the map is anchored); its NEES against the filter's covariance is reported per degree of
  freedom.

Trials run vectorised: all ``N`` trials advance together, one landmark update at a time.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from stages.estimation.blas import single_threaded_blas
from stages.estimation.collision import range_bearing_jacobians
from stages.estimation.robot import PathSteps, RobotModel, resample_path, unicycle_jacobians, unicycle_step
from stages.geometry import wrap_angle
from stages.navigation.stats import wilson_interval
from stages.navigation.walls import Obstacles

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


NominalPath = PathSteps
"""The path to follow, sampled every control period, with the open-loop controls that drive along it."""


def nominal_path(stamps_ns: npt.ArrayLike, poses: FloatArray, dt_s: float = 0.2) -> NominalPath:
    """Resample a recorded path (keyframe stamps and x, y, θ) every ``dt_s`` and derive its controls."""
    return resample_path(stamps_ns, poses, dt_s)


def lqr_gains(path: NominalPath, Wx: FloatArray, Wu: FloatArray) -> FloatArray:
    """Finite-horizon LQR gains ``L_k`` (K-1, 2, 3) along the path (backward Riccati recursion, eq. 27)."""
    A, B = unicycle_jacobians(path.poses[:-1], path.controls, path.dt_s)
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

    def covariance_at(self, keyframes: IntArray, rows: IntArray) -> FloatArray: ...


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

    def covariance_at(self, keyframes: IntArray, rows: IntArray) -> FloatArray:
        """The marginal covariances of ``rows`` (this map has no local ones)."""
        return np.asarray(self.covariances[rows])


def _default_robot() -> RobotModel:
    return RobotModel(robot_radius_m=0.2)


@dataclass(frozen=True)
class NavigationParams:
    """Settings of the Monte Carlo navigation: the robot (radius, motion and sensor noise, start covariance) and
    the trials and LQR settings (see ``EvaluateConfig``)."""

    trials: int = 100
    robot: RobotModel = field(default_factory=_default_robot)
    lqr_position_weight: float = 10.0
    lqr_heading_weight: float = 1.0
    lqr_speed_weight: float = 1.0
    lqr_yaw_rate_weight: float = 1.0
    max_speed_mps: float = 1.0
    max_yaw_rate_radps: float = 1.5
    keep_paths: int = 5

    @property
    def robot_radius_m(self) -> float:
        """The robot's collision radius."""
        return self.robot.robot_radius_m

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
    nees_per_dof: float = float("nan")
    """Mean over the active trials and steps of ``eᵀ P⁻¹ e / 3``, ``e = x̂ − x`` the filter's error: 1 for a
    consistent filter."""


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
    true_path: FloatArray | None = None,
) -> NavigationResult:
    """Run ``params.trials`` LQG trials along ``path`` with ``landmark_map``; count collisions.

    Args:
        path: the nominal trajectory in the case's map frame (the case's own trajectory estimate).
        gains: :func:`lqr_gains` of the path.
        landmark_map: the case's map (only these landmarks are used by the EKF).
        true_landmarks: true (x, y) of every landmark id that may be measured.
        visibility: per step, the landmark ids the robot can see (:func:`visibility_schedule`).
        obstacles: the true walls; None = no collisions (open space).
        params: noise, weights, radius, trials.
        seed: seed of every random draw (the same seed gives the same world to every map).
        true_path: (K, 3) the true path at the steps of ``path`` (where the walls leave room); the robot starts at
            its first pose. None = ``path.poses`` (the map's path is the truth).
    """
    ss = np.random.SeedSequence(seed)
    start_rng, act_rng, meas_rng = (np.random.default_rng(s) for s in ss.spawn(3))
    N, K, dt = params.trials, len(path), path.dt_s
    truth_path = path.poses if true_path is None else np.asarray(true_path, dtype=float)
    index = {int(i): j for j, i in enumerate(landmark_map.tag_ids)}
    truth = {int(i): np.asarray(p, dtype=float)[:2] for i, p in true_landmarks.items()}
    R, Qu, P0 = params.robot.R, params.robot.Qu, params.robot.P0
    x = truth_path[0] + start_rng.standard_normal((N, 3)) * np.sqrt(np.diag(P0))
    xh = np.repeat(path.poses[:1], N, axis=0)
    P = np.repeat(P0[None], N, axis=0)
    Lam = joint_covariance(landmark_map)
    C = np.zeros((N, 3, len(Lam)))  # cross-covariance of the robot's error and the map's landmark errors
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
    stats.step(0, ~collided, x, P, truth_path[0])
    for k in range(K - 1):
        u = _control(xh, path, gains, k, params)
        # the world
        noisy = u + act_rng.standard_normal((N, 2)) * np.sqrt(np.diag(Qu))
        x = np.where(collided[:, None], x, unicycle_step(x, noisy, dt))
        # EKF predict
        A, B = unicycle_jacobians(xh, u, dt)
        xh = unicycle_step(xh, u, dt)
        P = A @ P @ A.transpose(0, 2, 1) + B @ Qu @ B.transpose(0, 2, 1) + 1e-12 * np.eye(3)
        # EKF update, one landmark of the map at a time (eq. 26 noise, the landmark as seen from this keyframe)
        C = A @ C
        seen = visibility[k + 1]
        noise = meas_rng.standard_normal((len(seen), N, 2))  # for every visible landmark: the same world for every map
        used = [(i, index[int(lid)]) for i, lid in enumerate(seen) if int(lid) in index and int(lid) in truth]
        if used:  # every landmark measured at this step in one update
            rows, js = [i for i, _ in used], [j for _, j in used]
            true_xy = np.stack([truth[int(seen[i])] for i in rows])
            z = _measure(x, true_xy, R, noise[rows].transpose(1, 0, 2))
            xh, P, C = schmidt_update(xh, P, C, z, landmark_map.positions[js], js, Lam, R)
        active = ~collided
        if active.any():
            stats.add(active, x, xh, P, truth_path[k + 1])
            stats.step(k + 1, active, x, P, truth_path[k + 1])
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
        nees_per_dof=stats.nees_sum / (3.0 * denom) if stats.n_active else float("nan"),
    )


def simulate_in_worker(args: tuple[Any, ...], kwargs: dict[str, Any]) -> NavigationResult:
    """``simulate(*args, **kwargs)`` with numpy's BLAS on one thread, as a worker process runs it (evaluate runs
    each case's trials in one while it selects and solves the next case; the same inputs give the same numbers)."""
    with single_threaded_blas():
        return simulate(*args, **kwargs)


class _TrialStats:
    """Running sums over the trials still moving: tracking and estimation errors, EKF sigma, per step."""

    def __init__(self, K: int) -> None:
        self.se_track = self.se_est = self.sig_sum = self.nees_sum = 0.0
        self.n_active = 0
        self.step_dev = np.zeros(K)
        self.step_sig = np.zeros(K)
        self.step_n = np.zeros(K)

    def add(
        self,
        active: npt.NDArray[np.bool_],
        x: FloatArray,
        xh: FloatArray,
        P: FloatArray,
        true_nominal: FloatArray,
    ) -> None:
        """One step's squared errors (true deviation from the true path; estimation error in the map frame),
        position sigmas and NEES."""
        e = xh[active] - x[active]
        e[:, 2] = wrap_angle(e[:, 2])
        self.se_track += float((np.square(x[active, :2] - true_nominal[:2])).sum())
        self.se_est += float((np.square(e[:, :2])).sum())
        self.sig_sum += float(np.sqrt(np.maximum(P[active, 0, 0] + P[active, 1, 1], 0.0)).sum())
        Pa = P[active] + 1e-12 * np.eye(3)  # a noise-free trial has P = 0
        self.nees_sum += float(np.einsum("ni,ni->", e, np.linalg.solve(Pa, e[:, :, None])[:, :, 0]))
        self.n_active += int(active.sum())

    def step(self, k: int, active: npt.NDArray[np.bool_], x: FloatArray, P: FloatArray, nominal: FloatArray) -> None:
        """Step ``k``'s squared deviation from the true path and the sum of the EKF's largest position sigmas."""
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


def _measure(x: FloatArray, landmarks: FloatArray, R: FloatArray, noise: FloatArray) -> FloatArray:
    """Noisy bearing and range (N, m, 2) of the true ``landmarks`` (m, 2) from each true pose (``noise`` standard
    normal (N, m, 2))."""
    d = landmarks[None] - x[:, None, :2]
    bearing = wrap_angle(np.arctan2(d[..., 1], d[..., 0]) - x[:, None, 2])
    z = np.stack([bearing, np.hypot(d[..., 0], d[..., 1])], axis=-1)
    return z + noise * np.sqrt(np.diag(R))


GATE_CHI2 = 13.82
"""Innovation gate: χ² with 2 degrees of freedom at 99.9 %."""


def joint_covariance(landmark_map: MapLike) -> FloatArray:
    """(2L, 2L) joint covariance of the map's landmark positions: the map's own when it has one (``joint``), else
    its marginals as independent blocks."""
    joint = getattr(landmark_map, "joint", None)
    if joint is not None:
        return np.asarray(joint, dtype=float)
    L = len(landmark_map.tag_ids)
    out = np.zeros((2 * L, 2 * L))
    for j in range(L):
        out[2 * j : 2 * j + 2, 2 * j : 2 * j + 2] = landmark_map.covariances[j]
    return out


def schmidt_update(
    xh: FloatArray,
    P: FloatArray,
    C: FloatArray,
    z: FloatArray,
    lh: FloatArray,
    js: Sequence[int],
    Lam: FloatArray,
    R: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Schmidt (consider) update of every trial with bearing-range measurements ``z`` (N, m, 2) of the map landmarks
    ``js`` (rows of the map) at ``lh`` (m, 2), all at once.

    The map's landmark errors ``λ`` (joint covariance ``Lam``) are considered states: not estimated, but their
    cross-covariance ``C`` with the robot's error is carried, so the same landmark error, met again, or the drift
    that several landmarks share, is not taken for fresh information (eq. 26 applied independently per measurement
    would be). With ``δ = x − x̂``, ``ν = z − h(x̂, l̂) ≈ H δ + M λ_J + v``:
    ``S = H P Hᵀ + H C_J Mᵀ + M C_Jᵀ Hᵀ + M Λ_JJ Mᵀ + R``, ``K = (P Hᵀ + C_J Mᵀ) S⁻¹``, ``P ← P − K S Kᵀ``,
    ``C ← C − K (H C + M Λ_J·)``. A measurement whose own innovation fails the χ² gate (:data:`GATE_CHI2`, on its
    block of ``S``) is left out for that trial (its noise is made uninformative), as a real filter rejects a
    measurement it cannot explain.
    """
    N, m = z.shape[0], len(js)
    # (N, m, ·): every trial's estimate against each measured landmark; M w.r.t. each landmark's own position
    zh, H, M = range_bearing_jacobians(xh[:, None, :], np.asarray(lh, dtype=float)[None])
    cols = np.stack([2 * np.asarray(js), 2 * np.asarray(js) + 1], axis=1).ravel()
    diag = np.arange(m)
    # the measurement Jacobian of the robot's error and the measured landmarks' errors, J = [H, blockdiag(M_i)],
    # and their joint covariance Σ = [[P, C_J], [C_Jᵀ, Λ_JJ]]: every per-trial product below is (N, ·, 3 + 2m)
    J = np.zeros((N, 2 * m, 3 + 2 * m))
    J[:, :, :3] = H.reshape(N, 2 * m, 3)
    J[:, :, 3:].reshape(N, m, 2, m, 2)[:, diag, :, diag, :] = M.transpose(1, 0, 2, 3)
    LamJ = Lam[cols]  # Λ_J· (2m, 2L), the same for every trial
    Sig = np.empty((N, 3 + 2 * m, 3 + 2 * m))
    Sig[:, :3, :3] = P
    Sig[:, :3, 3:] = C[:, :, cols]
    Sig[:, 3:, :3] = Sig[:, :3, 3:].transpose(0, 2, 1)
    Sig[:, 3:, 3:] = LamJ[:, cols]
    SigJt = Sig @ J.transpose(0, 2, 1)
    S = J @ SigJt
    S.reshape(N, m, 2, m, 2)[:, diag, :, diag, :] += R
    nu = (z - zh).reshape(N, 2 * m)
    nu[:, 0::2] = wrap_angle(nu[:, 0::2])
    # innovation gate, per measurement on its own 2x2 block of S (inverted in closed form)
    b = S.reshape(N, m, 2, m, 2)[:, diag, :, diag, :]  # (m, N, 2, 2)
    n0, n1 = nu[:, 0::2].T, nu[:, 1::2].T
    det = b[..., 0, 0] * b[..., 1, 1] - b[..., 0, 1] * b[..., 1, 0]
    nis = (b[..., 1, 1] * n0 * n0 - (b[..., 0, 1] + b[..., 1, 0]) * n0 * n1 + b[..., 0, 0] * n1 * n1) / det
    rejected = (nis > GATE_CHI2).T  # (N, m)
    if rejected.any():
        big = np.repeat(rejected, 2, axis=1)
        nu[big] = 0.0
        idx = np.flatnonzero(big.any(axis=0))
        for c in idx:
            S[big[:, c], c, c] += 1e12
    G = SigJt[:, :3]  # P Hᵀ + C_J Mᵀ
    Kg = np.linalg.solve(S, G.transpose(0, 2, 1)).transpose(0, 2, 1)  # G S⁻¹ (S symmetric)
    xh = xh + np.einsum("nij,nj->ni", Kg, nu)
    P = P - Kg @ G.transpose(0, 2, 1)  # K S Kᵀ
    P = 0.5 * (P + P.transpose(0, 2, 1))
    # C ← C − K (H C + M Λ_J·); K M Λ_J· is one (3N, 2m) x (2m, 2L) product, Λ_J· being the same for every trial
    KJ = Kg @ J
    KM = np.ascontiguousarray(KJ[:, :, 3:]).reshape(3 * N, 2 * m)  # a strided view would miss BLAS (10x slower)
    C = C - KJ[:, :, :3] @ C - (KM @ LamJ).reshape(N, 3, -1)
    return xh, P, C
