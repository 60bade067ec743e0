"""Reference for the Schmidt-Kalman update, for tests only: the textbook Kalman update of the augmented state.

The production update (:func:`stages.navigation.lqg.schmidt_update`) carries the robot's error ``δ`` and its
cross-covariance ``C`` with the map's landmark errors ``λ``, which it never estimates (considered states). For one
update the robot part of that is exactly the augmented filter's on ``[δ; λ]``: the same gain for ``δ``, the same
``P`` and ``C`` after it; only ``λ``'s own estimate and covariance, which the Schmidt filter leaves alone, differ.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from stages.geometry import wrap_angle

FloatArray = npt.NDArray[np.float64]


def augmented_update(
    xh: FloatArray,
    P: FloatArray,
    C: FloatArray,
    z: FloatArray,
    lh: FloatArray,
    js: list[int],
    Lam: FloatArray,
    R: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """One trial at a time: stack ``[δ; λ]`` with covariance ``[[P, C], [Cᵀ, Λ]]``, the measurement Jacobian
    ``[H, M_J]``, and apply ``K = Σ Jᵀ (J Σ Jᵀ + R)⁻¹``, ``Σ ← (I − K J) Σ``. Returns the robot's estimate, ``P`` and
    ``C`` after it."""
    N, m, n_l = len(xh), len(js), Lam.shape[0]
    out_x, out_P, out_C = xh.copy(), P.copy(), C.copy()
    for n in range(N):
        Sig = np.block([[P[n], C[n]], [C[n].T, Lam]])
        J = np.zeros((2 * m, 3 + n_l))
        nu = np.zeros(2 * m)
        for i, j in enumerate(js):
            dx, dy = lh[i] - xh[n, :2]
            q = dx * dx + dy * dy
            r = np.sqrt(q)
            J[2 * i : 2 * i + 2, :3] = [[dy / q, -dx / q, -1.0], [-dx / r, -dy / r, 0.0]]
            J[2 * i : 2 * i + 2, 3 + 2 * j : 5 + 2 * j] = [[-dy / q, dx / q], [dx / r, dy / r]]
            nu[2 * i] = wrap_angle(z[n, i, 0] - (np.arctan2(dy, dx) - xh[n, 2]))
            nu[2 * i + 1] = z[n, i, 1] - r
        S = J @ Sig @ J.T + np.kron(np.eye(m), R)
        K = Sig @ J.T @ np.linalg.inv(S)
        post = (np.eye(3 + n_l) - K @ J) @ Sig
        out_x[n] = xh[n] + (K @ nu)[:3]
        out_P[n] = post[:3, :3]
        out_C[n] = post[:3, 3:]
    return out_x, out_P, out_C
