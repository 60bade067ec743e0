"""Reference implementations of the collision maths (Mu et al. 2015, eqs. 19-20, Alg. 2), for tests only.

Written plainly: eq. 19 with ``scipy.linalg.solve_discrete_are``; the robot's belief along a path as a Kalman
filter's covariance in the standard (gain) form, one step and one measurement at a time; Alg. 2 one candidate at a
time. The production code (:mod:`stages.estimation.collision`: information form, batched over candidates) must
agree with these.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt
import scipy.linalg as sla
from scipy.stats import norm

from stages.estimation.collision import planar_range_bearing
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


def halfplane_collision_probability(cov_pos: FloatArray, normal: FloatArray, clearance: float) -> float:
    """``P = 1 − Φ(d / sqrt(nᵀΣn))``: probability that the position crosses the obstacle half-plane."""
    s = float(np.sqrt(max(normal @ cov_pos @ normal, 1e-300)))
    return float(norm.sf(clearance / s))


def belief_reference(
    A: FloatArray,
    Q: FloatArray,
    P0: FloatArray,
    measurements: Sequence[Sequence[tuple[FloatArray, FloatArray]]],
) -> FloatArray:
    """Kalman filter covariances along a path: ``P ← A P Aᵀ + Q`` between steps, then at step k one update per
    ``(H, R̄)`` of ``measurements[k]`` in the gain form ``P ← (I − K H) P``. Returns (K, 3, 3)."""
    K = len(measurements)
    out = np.zeros((K, 3, 3))
    P = P0.copy()
    for k in range(K):
        if k:
            P = A[k - 1] @ P @ A[k - 1].T + Q[k - 1]
        for H, R in measurements[k]:
            G = P @ H.T @ np.linalg.inv(H @ P @ H.T + R)
            P = (np.eye(3) - G @ H) @ P
            P = 0.5 * (P + P.T)
        out[k] = P
    return out


def select_collision_reference(
    A: FloatArray,
    Q: FloatArray,
    P0: FloatArray,
    poses: FloatArray,
    landmarks: FloatArray,
    landmark_covs: FloatArray,
    visible: npt.NDArray[np.bool_],
    margin: FloatArray,
    normals: FloatArray,
    budget: int,
    sigmas: tuple[float, float] = (0.02, 0.1),
) -> LandmarkSelection:
    """Alg. 2 on the belief along the path, as :func:`stages.estimation.collision.select_collision` states it.

    Each pick: the step with the smallest margin in σ among those that see an unselected landmark between the last
    localised step and themselves; among those landmarks, the one that gives that step the largest margin, ties by
    the path's smallest margin, then by the sum of log P. Landmark covariances are inflated by the length of the
    run of consecutive steps that see them (as ``stages.risk.landmark_contributions`` does).
    """
    K, L = visible.shape
    st = _status(budget, L)

    def belief(chosen: list[int]) -> FloatArray:
        meas: list[list[tuple[FloatArray, FloatArray]]] = [[] for _ in range(K)]
        for c in chosen:
            ks = np.flatnonzero(visible[:, c])
            runs = np.split(ks, np.flatnonzero(np.diff(ks) > 1) + 1)
            for run in runs:
                for k in run:
                    meas[int(k)].append(
                        planar_range_bearing(poses[k], landmarks[c], len(run) * landmark_covs[c], sigmas)
                    )
        return belief_reference(A, Q, P0, meas)

    def margins(P: FloatArray) -> FloatArray:
        z = np.full(K, np.inf)
        for k in range(K):
            if np.isfinite(margin[k]):
                z[k] = margin[k] / np.sqrt(normals[k] @ P[k, :2, :2] @ normals[k])
        return z

    chosen: list[int] = []
    P = belief(chosen)
    z = margins(P)
    risk0 = norm.sf(z)
    if st in ("no_landmarks", "budget_zero"):
        return LandmarkSelection([], [], st, {"risk_before": risk0, "risk_after": risk0})
    scores: list[float] = []
    for _ in range(min(budget, L)):
        localised = np.array([any(visible[k, c] for c in chosen) for k in range(K)])
        best_step, best_cands = None, []
        for k in np.argsort(z, kind="stable"):
            if not np.isfinite(z[k]):
                break
            last = max([j for j in range(k + 1) if localised[j]], default=0)
            cands = [c for c in range(L) if c not in chosen and visible[last : k + 1, c].any()]
            if cands:
                best_step, best_cands = int(k), cands
                break
        if best_step is None:
            pick = next(c for c in range(L) if c not in chosen)
        else:
            keyed = []
            for c in best_cands:
                zc = margins(belief([*chosen, c]))
                fin = np.isfinite(zc)
                keyed.append(
                    (-round(float(zc[best_step]), 9), -float(zc[fin].min()), float(norm.logsf(zc[fin]).sum()), c)
                )
            pick = min(keyed)[3]
        chosen.append(pick)
        P = belief(chosen)
        z = margins(P)
        scores.append(float(norm.sf(z.min())))
    return LandmarkSelection(chosen, scores, st or "ok", {"risk_before": risk0, "risk_after": norm.sf(z), "z_after": z})
