"""Reference implementations of the collision maths (Mu et al. 2015, eqs. 19-20, Alg. 2), for tests only.

Written as the paper states them, one pose at a time with ``scipy.linalg.solve_discrete_are``; the production
code (:mod:`stages.estimation.collision`) solves Σ* for all poses at once by doubling and must agree with these.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt
import scipy.linalg as sla
from scipy.stats import norm

from stages.estimation.collision import (
    collision_risk,
    dead_reckoning_covariances,
    mahalanobis_to_obstacle,
    planar_range_bearing,
)
from stages.estimation.landmark_selection import LandmarkSelection, _status

FloatArray = npt.NDArray[np.float64]


def riccati_steady_state(A: FloatArray, Q: FloatArray, H: FloatArray, R: FloatArray) -> FloatArray:
    """Fixed point of eq. 19: ``Σ = Q + A(Σ − ΣHᵀ(HΣHᵀ + R)⁻¹HΣ)Aᵀ`` (``scipy.linalg.solve_discrete_are``)."""
    S = sla.solve_discrete_are(A.T, H.T, Q, R)
    return np.asarray(0.5 * (S + S.T))


def riccati_iterate(
    A: FloatArray, Q: FloatArray, H: FloatArray, R: FloatArray, sigma0: FloatArray, steps: int
) -> FloatArray:
    """Iterate the recursion of eq. 19 ``steps`` times from ``sigma0`` (for checking the fixed point)."""
    S = sigma0
    for _ in range(steps):
        K = S @ H.T @ np.linalg.inv(H @ S @ H.T + R)
        S = Q + A @ (S - K @ H @ S) @ A.T
    return S


def stabilised_covariance(
    Q: FloatArray, H_R: Sequence[tuple[FloatArray, FloatArray]], cap_steps: int = 50
) -> FloatArray:
    """``Σ*`` at a pose held still (``A = I``) observing the given landmarks (stacked ``H``, block ``R̄``).

    When the landmarks leave a direction unobservable (e.g. one range-bearing landmark and a
    planar pose), ``A = I`` has no finite fixed point; then ``A = ρ I`` with
    ``ρ = 1 − 1/(2·cap_steps)`` is used, so that unobservable directions saturate at about
    ``cap_steps · Q``, the same cap as the dead-reckoning rule for poses that see no landmark.
    """
    H = np.vstack([h for h, _ in H_R])
    R = sla.block_diag(*[r for _, r in H_R])
    n = Q.shape[0]
    observable = np.linalg.matrix_rank(H) == n  # with A = I the observability matrix has the rank of H
    rho = 1.0 if observable else 1.0 - 0.5 / cap_steps
    return riccati_steady_state(rho * np.eye(n), Q, H, R)


def halfplane_collision_probability(cov_pos: FloatArray, normal: FloatArray, clearance: float) -> float:
    """``P = 1 − Φ(d / sqrt(nᵀΣn))``: probability that the position crosses the obstacle half-plane."""
    s = float(np.sqrt(max(normal @ cov_pos @ normal, 1e-300)))
    return float(norm.sf(clearance / s))


def select_collision_reference(
    poses: FloatArray,
    landmarks: FloatArray,
    landmark_covs: FloatArray,
    visible: npt.NDArray[np.bool_],
    clearance: FloatArray,
    normals: FloatArray,
    Q: FloatArray,
    budget: int,
    bearing_range_sigmas: tuple[float, float] = (0.02, 0.1),
    cap_steps: int = 50,
) -> LandmarkSelection:
    """Mu et al. Alg. 2 for planar poses: pick the landmark seen from the riskiest pose, repeat.

    Args:
        poses: (T, 3) x, y, θ of the keyframes, in time order.
        landmarks: (L, 2) landmark positions; ``landmark_covs`` (L, 2, 2) their marginals.
        visible: (T, L) whether landmark l is visible from pose t.
        clearance: (T,) distance to the nearest laser return; ``normals`` (T, 2) unit vectors from
            the pose towards it (world frame).
        Q: (3, 3) odometry noise per step.
        budget: number of landmarks to pick.
        bearing_range_sigmas: measurement noise (rad, m).
        cap_steps: cap of the dead-reckoning rule for poses that see no selected landmark.

    Returns:
        Picks with, as scores, the maximum collision probability along the path after each pick;
        ``extra`` holds ``risk_before``/``risk_after`` (T,), ``sigma_after`` (T, 3, 3) and
        ``mahalanobis_after`` (T,).
    """
    T, L = visible.shape
    st = _status(budget, L)
    sig = np.zeros((T, 3, 3))
    localised = np.zeros(T, dtype=bool)
    chosen: list[int] = []

    def refresh(ts: npt.NDArray[np.int64]) -> None:
        for t in ts:
            ls = [l_ for l_ in chosen if visible[t, l_]]
            if ls:
                sig[t] = stabilised_covariance(
                    Q,
                    [
                        planar_range_bearing(poses[t], landmarks[l_], landmark_covs[l_], bearing_range_sigmas)
                        for l_ in ls
                    ],
                )
                localised[t] = True

    cov = dead_reckoning_covariances(sig, localised, Q, cap_steps)
    risk0 = collision_risk(cov, clearance, normals, [0, 1])
    if st in ("no_landmarks", "budget_zero"):
        return LandmarkSelection([], [], st, {"risk_before": risk0, "risk_after": risk0})
    budget = min(budget, L)
    risk = risk0
    scores: list[float] = []
    for _ in range(budget):
        available = visible & ~np.isin(np.arange(L), chosen)[None, :]
        cand_poses = np.flatnonzero(available.any(axis=1))
        if len(cand_poses) == 0:  # remaining landmarks are seen from nowhere: append by index
            rest = [l_ for l_ in range(L) if l_ not in chosen]
            chosen.append(rest[0])
            scores.append(float(risk.max()))
            continue
        t = cand_poses[np.argmax(risk[cand_poses])]
        # among the landmarks seen from the riskiest pose, the one that lowers its risk most
        best: tuple[float, int] | None = None
        for l_ in np.flatnonzero(available[t]):
            ls = [x for x in chosen if visible[t, x]] + [int(l_)]
            s = stabilised_covariance(
                Q, [planar_range_bearing(poses[t], landmarks[x], landmark_covs[x], bearing_range_sigmas) for x in ls]
            )
            p = halfplane_collision_probability(s[:2, :2], normals[t], clearance[t])
            if best is None or p < best[0]:
                best = (p, int(l_))
        assert best is not None
        chosen.append(best[1])
        refresh(np.flatnonzero(visible[:, best[1]]))
        cov = dead_reckoning_covariances(sig, localised, Q, cap_steps)
        risk = collision_risk(cov, clearance, normals, [0, 1])
        scores.append(float(risk.max()))
    maha = np.array([mahalanobis_to_obstacle(cov[t, :2, :2], clearance[t] * normals[t]) for t in range(T)])
    return LandmarkSelection(
        chosen,
        scores,
        st or "ok",
        {"risk_before": risk0, "risk_after": risk, "sigma_after": cov, "mahalanobis_after": maha},
    )
