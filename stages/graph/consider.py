"""The odometry calibration's uncertainty in a graph of its corrected rows: a consider covariance.

With the odometry calibration applied, the graph stage writes the odometry rows corrected at the estimated
calibration ``ĉ = (k_d, k_w, b)`` (:mod:`stages.graph.calibration`), and takes its marginals from the joint system of
the map and ``c``, so they hold ``c``'s uncertainty. A graph rebuilt from those rows treats ``ĉ`` as exact: every
reduced graph of optimize and evaluate, and the full graph's own information, from which the risk model takes its
cross covariances. With ``c`` *considered* (not estimated again: its estimate and covariance ``Σ_c`` are the full
graph's), the covariance of the solution ``x̂`` is

    Σ_x + S Σ_c Sᵀ,   S = ∂x̂/∂c = −H⁻¹ Jᵀ A_c,

``J`` the graph's whitened Jacobian at the solution, ``H = JᵀJ``, and ``A_c`` the odometry rows' whitened Jacobian
for ``c``. For the full graph this is its joint marginal exactly (the Schur complement of ``c``); for a reduced graph
it is the uncertainty of the map a robot carries with the calibrated odometry, as uncertain as the whole recording
left the calibration. (The reduced graph's rows also took part in estimating ``ĉ``; the term ignores that
correlation, so it errs towards a larger covariance.)

```python
cal = OdometryCalibration.read(graph_input)          # None: the run was not calibrated
term = consider_term(rows, graph.linearize(values), key_dims(values), cal, full_index)
marginals = term.add_to_marginals(marginals)          # each variable's marginal, with c's uncertainty
```
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import gtsam
import numpy as np

from pipeline.artifacts import StageInput, StageOutput
from stages.estimation.sparse_cov import SPDSolver
from stages.graph.artifacts import CALIBRATION
from stages.graph.factors import FactorRow
from stages.graph.marginals import whitened_system


@dataclass(frozen=True)
class OdometryCalibration:
    """The applied calibration, its covariance, and how each corrected odometry factor's error depends on it."""

    value: np.ndarray
    """(3,) k_d, k_w, b."""
    covariance: np.ndarray
    """(3, 3) from the joint system of the map and the calibration."""
    factor_index: np.ndarray
    """(N,) the corrected odometry rows' indices in the full graph."""
    jacobian: np.ndarray
    """(N, dim, 3) ``∂ error / ∂c`` of each of those factors, in the factor's tangent, unwhitened."""

    def write(self, out: StageOutput) -> None:
        """Write ``calibration.npz``."""
        out.write_npz(
            CALIBRATION.file,
            value=self.value,
            covariance=self.covariance,
            factor_index=self.factor_index,
            jacobian=self.jacobian,
        )

    @classmethod
    def read(cls, inp: StageInput) -> OdometryCalibration | None:
        """``calibration.npz`` of a finished graph stage, or None when it has none (not calibrated)."""
        if not inp.exists(CALIBRATION.file):
            return None
        a = inp.read_npz(CALIBRATION.file)
        return cls(
            value=np.asarray(a["value"], dtype=float),
            covariance=np.asarray(a["covariance"], dtype=float),
            factor_index=np.asarray(a["factor_index"], dtype=np.int64),
            jacobian=np.asarray(a["jacobian"], dtype=float),
        )

    def by_factor(self) -> dict[int, np.ndarray]:
        """Each corrected factor's ``∂ error / ∂c`` by its full-graph index."""
        return {int(i): J for i, J in zip(self.factor_index.tolist(), self.jacobian, strict=True)}


@dataclass(frozen=True)
class ConsiderTerm:
    """``S Σ_c Sᵀ`` of one graph, by variable: what its covariances lack for the calibration's uncertainty."""

    sensitivity: dict[int, np.ndarray]
    """Key to ``S_k = ∂x̂_k/∂c`` (dim x 3), in the variable's tangent."""
    covariance: np.ndarray
    """Σ_c (3 x 3)."""

    def block(self, a: int, b: int) -> np.ndarray:
        """The term's block of keys ``a`` and ``b``: ``S_a Σ_c S_bᵀ``."""
        return self.sensitivity[a] @ self.covariance @ self.sensitivity[b].T

    def joint(self, keys: Sequence[int]) -> np.ndarray:
        """The term's joint block of ``keys`` (in their order)."""
        S = np.concatenate([self.sensitivity[k] for k in keys]) if keys else np.zeros((0, 3))
        return S @ self.covariance @ S.T

    def add_to_marginals(self, marginals: Mapping[int, np.ndarray]) -> dict[int, np.ndarray]:
        """Every marginal with its block of the term added."""
        return {k: np.asarray(m) + self.block(k, k) if k in self.sensitivity else m for k, m in marginals.items()}


def consider_term(
    rows: Sequence[FactorRow],
    linear: gtsam.GaussianFactorGraph,
    dims: Mapping[int, int],
    calibration: OdometryCalibration | None,
    full_index: Sequence[int] | np.ndarray | None = None,
) -> ConsiderTerm | None:
    """The calibration's consider term of a graph built from (some of) the full graph's rows.

    Args:
        rows: the graph's rows; factor ``i`` of ``linear`` is ``rows[i]``.
        linear: the graph linearised at its solution.
        dims: each variable's tangent dimension.
        calibration: the full graph's (None: the run was not calibrated, and there is no term).
        full_index: row ``i``'s index in the full graph (None: the rows are the full graph's, in order).

    Returns:
        None when no row is a corrected odometry factor.
    """
    if calibration is None:
        return None
    index = np.arange(len(rows)) if full_index is None else np.asarray(full_index, dtype=np.int64)
    jac = calibration.by_factor()
    J, _ = whitened_system(linear)
    A_c = np.zeros((J.shape[0], 3))
    offset, hit = 0, False
    for row, i in zip(rows, index.tolist(), strict=True):
        G = jac.get(int(i))
        if G is not None and row.kind == "odometry":
            R = np.asarray(gtsam.noiseModel.Gaussian.Covariance(np.asarray(row.covariance, dtype=float)).R())
            A_c[offset : offset + row.dim] = R @ G
            hit = True
        offset += row.dim
    if not hit:
        return None
    if offset != J.shape[0]:
        raise ValueError(f"the rows hold {offset} residuals, the linearised graph {J.shape[0]}")
    S = -SPDSolver((J.T @ J).tocsc()).solve(np.asarray(J.T @ A_c))
    keys = sorted(int(k) for k in linear.keyVector())
    sensitivity: dict[int, np.ndarray] = {}
    o = 0
    for k in keys:
        sensitivity[k] = S[o : o + dims[k]]
        o += dims[k]
    return ConsiderTerm(sensitivity, np.asarray(calibration.covariance, dtype=float))
