"""Belief stabilisation and collision risk along a path, and the landmark greedy built on them (Mu et al. 2015).

The one home of:

* the planar range-bearing model with the landmark's own uncertainty in the noise (eq. 26),
  :func:`planar_range_bearing` and its information :func:`measurement_information`;
* Σ*, the steady state of belief stabilisation (eq. 19), :func:`stabilised_covariances`;
* the dead-reckoning rule for poses that see no selected landmark, :func:`dead_reckoning_covariances`;
* the half-plane collision probability and the eq.-20 Mahalanobis measure, :func:`collision_risk`,
  :func:`mahalanobis_to_obstacle`;
* Alg. 2 (collision-driven landmark selection), :func:`select_collision`.

Planar throughout: poses ``(x, y, θ)``, landmarks ``(x, y)``; the position block of a pose covariance is
``[0, 1]``. ``stages.risk`` applies these to a run's keyframes; select_landmarks' ``collision`` strategy
runs :func:`select_collision`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt
from scipy.stats import norm

from stages.estimation.landmark_selection import LandmarkSelection, SelectionStatus

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


# ------------------------------------------------------------------ measurement model (eq. 26)
def planar_range_bearing(
    pose: FloatArray, landmark: FloatArray, landmark_cov: FloatArray, sigmas: tuple[float, float]
) -> tuple[FloatArray, FloatArray]:
    """Jacobian w.r.t. the pose (2×3) of (bearing, range) and the noise of eq. 26 ``R + M R_L Mᵀ``."""
    dx, dy = landmark[0] - pose[0], landmark[1] - pose[1]
    q = max(dx * dx + dy * dy, 1e-12)
    r = np.sqrt(q)
    H = np.array([[dy / q, -dx / q, -1.0], [-dx / r, -dy / r, 0.0]])
    M = np.array([[-dy / q, dx / q], [dx / r, dy / r]])  # w.r.t. the landmark position
    R = np.diag(np.square(sigmas)) + M @ landmark_cov @ M.T
    return H, R


def measurement_information(
    pose: FloatArray, positions: FloatArray, covariances: FloatArray, sigmas: tuple[float, float]
) -> FloatArray:
    """``J = Σ_l Hᵀ R̄⁻¹ H`` (3×3) of range-bearing measurements from ``pose`` of the landmarks ``positions`` (L, 2)
    with marginal ``covariances`` (L, 2, 2) (eq. 26 noise).

    The Riccati recursion of eq. 19 sees the measurements only through ``Σ⁻¹ + J``, so ``J`` replaces the
    stacked ``H`` and block-diagonal ``R̄`` without changing Σ*.
    """
    J = np.zeros((3, 3))
    for p, c in zip(positions, covariances, strict=True):
        H, R = planar_range_bearing(pose, p, c, sigmas)
        J += H.T @ np.linalg.solve(R, H)
    return 0.5 * (J + J.T)


# ------------------------------------------------------------------ belief stabilisation (eq. 19)
def stabilised_covariances(Q: FloatArray, J: FloatArray, cap_steps: int, max_iter: int = 100) -> FloatArray:
    """Σ* of eq. 19 at poses held still, for a batch of measurement informations ``J`` (B, 3, 3).

    Σ* is the fixed point of ``Σ = Q + A(Σ⁻¹ + J)⁻¹Aᵀ`` with ``A = I``. When ``J`` is rank deficient (e.g. one
    range-bearing landmark and a planar pose), ``A = I`` has no finite fixed point; then ``A = ρI`` with
    ``ρ = 1 − 1/(2·cap_steps)`` is used, so that unobservable directions saturate at about ``cap_steps · Q``,
    the same cap as :func:`dead_reckoning_covariances`.

    Solved for every pose at once by the structured doubling algorithm, with 3×3 batched numpy:
    ``A ← A W⁻¹ A``, ``G ← G + A W⁻¹ G Aᵀ``, ``X ← X + Aᵀ X W⁻¹ A`` with ``W = I + G X``, from ``(A, J, Q)``;
    ``X → Σ*`` quadratically (agrees with ``scipy.linalg.solve_discrete_are`` to ~1e-13; tested).
    """
    J = np.asarray(J, dtype=float).reshape(-1, 3, 3)
    B = len(J)
    if B == 0:
        return np.zeros((0, 3, 3))
    w = np.linalg.eigvalsh(J)
    observable = (w > 1e-10 * np.maximum(w[:, -1:], 1e-300)).sum(axis=1) == 3
    rho = np.where(observable, 1.0, 1.0 - 0.5 / cap_steps)
    eye = np.eye(3)
    A = rho[:, None, None] * eye
    G = J.copy()
    X = np.broadcast_to(Q, (B, 3, 3)).copy()
    for _ in range(max_iter):
        Winv = np.linalg.inv(eye + G @ X)
        AW = A @ Winv
        X_new = X + np.swapaxes(A, 1, 2) @ X @ Winv @ A
        G = G + AW @ G @ np.swapaxes(A, 1, 2)
        A = AW @ A
        done = np.abs(X_new - X).max() <= 1e-15 * np.abs(X_new).max()
        X = X_new
        if done:
            break
    return np.asarray(0.5 * (X + np.swapaxes(X, 1, 2)))


def dead_reckoning_covariances(sigmas: FloatArray, localised: BoolArray, Q: FloatArray, cap_steps: int) -> FloatArray:
    """Covariance of every pose: ``sigmas`` where ``localised``, dead reckoning elsewhere.

    Rule: ``Σ(t) = Σ*(s) + min(|t − s|, cap_steps) · Q`` with ``s`` the nearest pose along the path
    that does see a landmark (dead reckoning from there, one odometry step of noise ``Q`` per pose);
    if no pose is localised, ``cap_steps · Q``.
    """
    T = len(localised)
    out = sigmas.copy()
    idx = np.flatnonzero(localised)
    if len(idx) == 0:
        out[:] = cap_steps * Q
        return out
    t = np.arange(T)
    pos = np.searchsorted(idx, t)
    left = idx[np.clip(pos - 1, 0, len(idx) - 1)]
    right = idx[np.clip(pos, 0, len(idx) - 1)]
    nearest = np.where(np.abs(t - left) <= np.abs(right - t), left, right)
    steps = np.minimum(np.abs(t - nearest), cap_steps)
    un = ~localised
    out[un] = sigmas[nearest[un]] + steps[un, None, None] * Q
    return out


# ------------------------------------------------------------------ collision risk (half-plane, eq. 20)
def collision_risk(
    poses_cov: FloatArray, clearance: FloatArray, normals: FloatArray, pos_idx: Sequence[int]
) -> FloatArray:
    """``P_t = 1 − Φ(d_t / sqrt(n_tᵀ Σ_t n_t))``: probability that pose ``t`` crosses its obstacle half-plane.

    ``poses_cov`` (T, k, k); ``pos_idx`` its position rows; ``clearance`` (T,) the distance ``d_t`` to the
    half-plane and ``normals`` (T, 2) the unit normal towards it.
    """
    P = poses_cov[:, pos_idx][:, :, pos_idx]
    var = np.einsum("ti,tij,tj->t", normals, P, normals)
    return np.asarray(norm.sf(clearance / np.sqrt(np.maximum(var, 1e-300))))


def mahalanobis_to_obstacle(cov_pos: FloatArray, offset: FloatArray) -> float:
    """Eq. 20: ``(x − x_obst)ᵀ Σ⁻¹ (x − x_obst)`` (squared standard deviations to the nearest return)."""
    return float(offset @ np.linalg.solve(cov_pos, offset))


# ------------------------------------------------------------------ Alg. 2
def select_collision(
    poses: FloatArray,
    positions: FloatArray,
    covariances: FloatArray,
    visible: BoolArray,
    margin: FloatArray,
    normals: FloatArray,
    Q: FloatArray,
    budget: int,
    sigmas: tuple[float, float],
    cap_steps: int,
) -> LandmarkSelection:
    """Mu et al. Alg. 2: pick the landmark seen from the riskiest pose that lowers that pose's risk most, repeat.

    Each step: the riskiest pose that sees an unselected landmark; among the unselected landmarks it sees, the
    one whose Σ* (with the selected ones it sees) gives it the lowest collision probability (first on ties);
    then Σ* of every pose that sees the pick is re-solved and the rest dead-reckon
    (:func:`dead_reckoning_covariances`). When no pose sees an unselected landmark, the rest are appended by index.

    Args:
        poses: (T, 3) x, y, θ of the keyframes, in time order.
        positions: (L, 2) landmark positions; ``covariances`` (L, 2, 2) their marginals.
        visible: (T, L) whether landmark l is visible from pose t.
        margin: (T,) distance to the obstacle half-plane (clearance minus the robot radius; inf: none);
            ``normals`` (T, 2) unit vectors from the pose towards it (world frame).
        Q: (3, 3) odometry noise per step.
        budget: number of landmarks to pick.
        sigmas: bearing (rad) and range (m) noise.
        cap_steps: cap of the dead-reckoning rule.

    Returns:
        Picks with, as scores, the maximum collision probability along the path after each pick; ``extra``
        holds ``risk_before``/``risk_after`` (T,) and ``sigma_after`` (T, 3, 3).
    """
    T, L = visible.shape
    sig = np.zeros((T, 3, 3))
    localised = np.zeros(T, dtype=bool)
    chosen: list[int] = []
    is_chosen = np.zeros(L, dtype=bool)

    def info(t: int, rows: list[int]) -> FloatArray:
        return measurement_information(poses[t], positions[rows], covariances[rows], sigmas)

    def risk_now() -> tuple[FloatArray, FloatArray]:
        cov = dead_reckoning_covariances(sig, localised, Q, cap_steps)
        return cov, np.asarray(collision_risk(cov, margin, normals, [0, 1]))

    cov, risk = risk_now()
    if L == 0:
        return LandmarkSelection([], [], "no_landmarks", {"risk_before": risk, "risk_after": risk})
    if budget <= 0:
        return LandmarkSelection([], [], "budget_zero", {"risk_before": risk, "risk_after": risk})
    risk0 = risk
    scores: list[float] = []
    for _ in range(min(budget, L)):
        available = visible & ~is_chosen[None, :]
        cand_poses = np.flatnonzero(available.any(axis=1))
        if len(cand_poses) == 0:  # the rest are seen from nowhere: by index
            nxt = int(np.flatnonzero(~is_chosen)[0])
            chosen.append(nxt)
            is_chosen[nxt] = True
            scores.append(float(risk.max()))
            continue
        t = int(cand_poses[np.argmax(risk[cand_poses])])
        base = [x for x in chosen if visible[t, x]]
        cands = np.flatnonzero(available[t])
        S = stabilised_covariances(Q, np.array([info(t, [*base, int(c)]) for c in cands]), cap_steps)
        var = np.einsum("i,bij,j->b", normals[t], S[:, :2, :2], normals[t])
        p = norm.sf(margin[t] / np.sqrt(np.maximum(var, 1e-300)))
        best = int(cands[int(np.argmin(p))])
        chosen.append(best)
        is_chosen[best] = True
        ts = np.flatnonzero(visible[:, best])
        J = np.array([info(int(u), [x for x in chosen if visible[u, x]]) for u in ts])
        sig[ts] = stabilised_covariances(Q, J, cap_steps)
        localised[ts] = True
        cov, risk = risk_now()
        scores.append(float(risk.max()))
    status: SelectionStatus = "budget_exceeds_landmarks" if budget > L else "ok"
    return LandmarkSelection(chosen, scores, status, {"risk_before": risk0, "risk_after": risk, "sigma_after": cov})
