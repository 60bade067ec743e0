"""The robot's belief and collision risk along a path, and the landmark greedy built on them (Mu et al. 2015).

The one home of:

* the planar range-bearing model with the landmark's own uncertainty in the noise (eq. 26),
  :func:`planar_range_bearing`, its information :func:`measurement_information` and, per (pose, landmark) pair,
  :func:`pair_information`;
* the belief along the path: the EKF's covariance recursion with the robot model's unicycle
  (:mod:`stages.estimation.robot`), causal, :func:`forward_covariances` (in place of eq. 19's Σ* of a pose held
  still and a capped dead-reckoning rule);
* the half-plane collision probability, its margin in σ and the eq.-20 Mahalanobis measure,
  :func:`collision_risk`, :func:`margin_sigmas`, :func:`mahalanobis_to_obstacle`;
* Alg. 2 (collision-driven landmark selection), :func:`select_collision`.

Planar throughout: poses ``(x, y, θ)``, landmarks ``(x, y)``; the position block of a pose covariance is
``[0, 1]``. ``stages.risk`` applies these to a run's path; select_landmarks' ``collision`` strategy
runs :func:`select_collision`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from stages.estimation.landmark_selection import LandmarkSelection, SelectionStatus
from stages.estimation.normal import normal_logsf, normal_sf

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


# ------------------------------------------------------------------ the belief along the path (eqs. 19, 26)
def range_bearing_jacobians(poses: FloatArray, positions: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Predicted (bearing, range) (…, 2) of landmarks at ``positions`` (…, 2) from ``poses`` (…, 3), and its
    Jacobians w.r.t. the pose ``H`` (…, 2, 3) and the landmark position ``M`` (…, 2, 2), for any broadcast shape."""
    poses = np.asarray(poses, dtype=float)
    d = np.asarray(positions, dtype=float) - poses[..., :2]
    q = np.maximum((d * d).sum(axis=-1), 1e-12)
    r = np.sqrt(q)
    dx, dy = d[..., 0], d[..., 1]
    z = np.stack([np.arctan2(dy, dx) - poses[..., 2], r], axis=-1)
    H = np.zeros((*q.shape, 2, 3))
    H[..., 0, 0], H[..., 0, 1], H[..., 0, 2] = dy / q, -dx / q, -1.0
    H[..., 1, 0], H[..., 1, 1] = -dx / r, -dy / r
    M = np.zeros((*q.shape, 2, 2))
    M[..., 0, 0], M[..., 0, 1] = -dy / q, dx / q
    M[..., 1, 0], M[..., 1, 1] = dx / r, dy / r
    return z, H, M


def pair_information(
    poses: FloatArray, positions: FloatArray, covariances: FloatArray, sigmas: tuple[float, float]
) -> FloatArray:
    """``Hᵀ R̄⁻¹ H`` (n, 3, 3) of one range-bearing measurement per (pose, landmark) pair, eq. 26 noise.

    ``poses`` (n, 3), ``positions`` (n, 2) and ``covariances`` (n, 2, 2) are paired row by row; the same as
    :func:`measurement_information` of each pair, vectorised.
    """
    _, H, M = range_bearing_jacobians(poses, positions)
    Rbar = np.diag(np.square(sigmas)) + M @ np.asarray(covariances, dtype=float) @ np.swapaxes(M, 1, 2)
    J = np.swapaxes(H, 1, 2) @ np.linalg.solve(Rbar, H)
    return np.asarray(0.5 * (J + np.swapaxes(J, 1, 2)))


@dataclass(frozen=True)
class StepNoise:
    """The robot's covariance propagation along a path: ``P_{k+1} = A_k P_k A_kᵀ + Q_k`` from ``P0``."""

    A: FloatArray
    """(K-1, 3, 3) state transition along the nominal path (:meth:`stages.estimation.robot.PathSteps.transition`)."""
    Q: FloatArray
    """(K-1, 3, 3) process noise per step."""
    P0: FloatArray
    """(3, 3) covariance of the start pose."""

    @property
    def steps(self) -> int:
        """K, the number of steps."""
        return len(self.A) + 1


def forward_covariances(noise: StepNoise, J: FloatArray) -> FloatArray:
    """The EKF's covariance along the path for a batch of per-step measurement informations ``J`` (B, K, 3, 3).

    Causal: step ``k`` is predicted from step ``k − 1`` with the unicycle's ``A`` and ``Q`` (heading coupled to
    position, no cap), then updated with ``J_k``: ``P⁺ = (P⁻¹ + J_k)⁻¹ = P (I + J_k P)⁻¹``. A pose between two
    localised ones so inherits its past neighbours' information, and dead reckoning grows for as long as it lasts.
    This replaces eq. 19's Σ* of a pose held still (which ignores its neighbours) and the nearest-pose dead-reckoning
    rule; it is what the simulated robot's filter computes along the nominal path. Returns (B, K, 3, 3).
    """
    J = np.asarray(J, dtype=float)
    B, K = J.shape[:2]
    out = np.empty((B, K, 3, 3))
    P = np.broadcast_to(noise.P0, (B, 3, 3)).copy()
    measured = np.abs(J).reshape(B, K, 9).max(axis=2).max(axis=0) > 0
    At = np.swapaxes(noise.A, 1, 2)
    eye = np.eye(3)
    for k in range(K):
        if k:
            P = noise.A[k - 1] @ P @ At[k - 1] + noise.Q[k - 1]
        if measured[k]:
            P = P @ np.linalg.inv(eye + J[:, k] @ P)
            P = 0.5 * (P + np.swapaxes(P, 1, 2))
        out[:, k] = P
    return out


def margin_sigmas(cov: FloatArray, margin: FloatArray, normals: FloatArray) -> FloatArray:
    """``z = m / sqrt(nᵀ Σ_xy n)``: the margin to the obstacle half-plane in standard deviations (eq. 20's measure
    along the normal; ``P = Φ(−z)``). ``cov`` (…, K, 3, 3); ``margin`` (K,) (inf: no obstacle known, z = inf);
    ``normals`` (K, 2). Unlike ``P`` it does not underflow, so greedy comparisons stay meaningful far from walls."""
    var = np.einsum("ki,...kij,kj->...k", normals, cov[..., :2, :2], normals)
    with np.errstate(invalid="ignore"):
        z = margin / np.sqrt(np.maximum(var, 1e-300))
    return np.asarray(np.where(np.isinf(margin), np.inf, z))


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
    return np.asarray(normal_sf(clearance / np.sqrt(np.maximum(var, 1e-300))))


def mahalanobis_to_obstacle(cov_pos: FloatArray, offset: FloatArray) -> float:
    """Eq. 20: ``(x − x_obst)ᵀ Σ⁻¹ (x − x_obst)`` (squared standard deviations to the nearest return)."""
    return float(offset @ np.linalg.solve(cov_pos, offset))


# ------------------------------------------------------------------ Alg. 2
Contribution = tuple[npt.NDArray[np.int64], FloatArray]
"""One landmark's measurement information: the steps that see it (n,) and ``Hᵀ R̄⁻¹ H`` at each (n, 3, 3)."""


def step_information(contributions: Sequence[Contribution], chosen: Sequence[int], K: int) -> FloatArray:
    """Per-step information ``J`` (K, 3, 3) of the ``chosen`` landmarks."""
    J = np.zeros((K, 3, 3))
    for c in chosen:
        steps, info = contributions[c]
        np.add.at(J, steps, info)
    return J


def select_collision(
    noise: StepNoise,
    contributions: Sequence[Contribution],
    margin: FloatArray,
    normals: FloatArray,
    budget: int,
) -> LandmarkSelection:
    """Mu et al. Alg. 2 on the robot's causal belief along the path: pick the landmark that most raises the margin
    (in σ) of the riskiest step, repeat.

    Each pick: the step with the smallest margin ``z`` (:func:`margin_sigmas`) among those that could still be
    helped, i.e. that see an unselected landmark between the last step localised by the selection and themselves;
    among those landmarks, the one whose addition gives that step the largest ``z`` after the whole path's
    covariances are propagated again (:func:`forward_covariances`), ties broken by the path's smallest ``z``, then
    by the sum of ``log P`` (first on remaining ties). Comparing ``z`` instead of ``P = Φ(−z)`` keeps the greedy's
    choices meaningful where ``P`` underflows; a pick changes every later step's covariance, so a step's risk
    accounts for its path neighbours. When no step can be helped, the rest are appended by index.

    Args:
        noise: the robot's propagation along the path.
        contributions: per landmark, the steps that see it and the information of each measurement.
        margin: (K,) distance to the obstacle half-plane (clearance minus the robot radius; inf: none).
        normals: (K, 2) unit vectors towards it.
        budget: number of landmarks to pick.

    Returns:
        Picks with, as scores, the maximum collision probability along the path after each pick; ``extra`` holds
        ``risk_before``/``risk_after`` (K,), ``z_after`` (K,) and ``sigma_after`` (K, 3, 3).
    """
    K, L = noise.steps, len(contributions)
    visible = np.zeros((K, L), dtype=bool)
    for c, (steps, _) in enumerate(contributions):
        visible[steps, c] = True
    J = np.zeros((K, 3, 3))
    cov = forward_covariances(noise, J[None])[0]
    z = margin_sigmas(cov, margin, normals)
    risk0 = normal_sf(z)
    if L == 0:
        return LandmarkSelection([], [], "no_landmarks", {"risk_before": risk0, "risk_after": risk0})
    if budget <= 0:
        return LandmarkSelection([], [], "budget_zero", {"risk_before": risk0, "risk_after": risk0})
    chosen: list[int] = []
    is_chosen = np.zeros(L, dtype=bool)
    scores: list[float] = []
    steps_idx = np.arange(K)
    for _ in range(min(budget, L)):
        localised = np.abs(J).reshape(K, 9).max(axis=1) > 0
        last = np.maximum.accumulate(np.where(localised, steps_idx, 0))
        avail = visible & ~is_chosen[None, :]
        csum = np.vstack([np.zeros((1, L), dtype=np.int64), np.cumsum(avail, axis=0)])
        helpable = (csum[steps_idx + 1] - csum[last]) > 0
        can = helpable.any(axis=1) & np.isfinite(z)
        if not can.any():
            nxt = int(np.flatnonzero(~is_chosen)[0])
        else:
            cand_steps = np.flatnonzero(can)
            k = int(cand_steps[np.argmin(z[cand_steps])])
            cands = np.flatnonzero(helpable[k])
            Js = np.repeat(J[None], len(cands), axis=0)
            for b, cand in enumerate(cands.tolist()):
                steps, info = contributions[cand]
                np.add.at(Js[b], steps, info)
            zc = margin_sigmas(forward_covariances(noise, Js), margin, normals)
            finite = np.where(np.isfinite(zc), zc, np.inf)
            with np.errstate(divide="ignore"):
                logp = np.where(np.isfinite(zc), normal_logsf(np.where(np.isfinite(zc), zc, 0.0)), 0.0).sum(axis=1)
            order = np.lexsort((logp, -finite.min(axis=1), -np.round(zc[:, k], 9)))
            nxt = int(cands[int(order[0])])
        chosen.append(nxt)
        is_chosen[nxt] = True
        steps, info = contributions[nxt]
        np.add.at(J, steps, info)
        cov = forward_covariances(noise, J[None])[0]
        z = margin_sigmas(cov, margin, normals)
        scores.append(float(normal_sf(z.min())) if np.isfinite(z).any() else 0.0)
    status: SelectionStatus = "budget_exceeds_landmarks" if budget > L else "ok"
    extra = {"risk_before": risk0, "risk_after": normal_sf(z), "z_after": z, "sigma_after": cov}
    return LandmarkSelection(chosen, scores, status, extra)
