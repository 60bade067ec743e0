"""The shared tag scale solved with native GTSAM factors: an exact outer solve over ``s`` around native inner solves.

A tag row with the scale key measures ``e(θ, s)``: planar ``(bearing − b, ρ / s − r)``, 3d ``Log(M⁻¹ (R, t / s))``
(:func:`stages.graph.factors.scaled_bearing_range_error`, :func:`~stages.graph.factors.scaled_between_error`). For a
fixed ``s`` it is exactly a native factor (docs/graph.md, "Tag scale: native solve"): with ``D = diag(1, s)``
(planar) or ``diag(I₃, s I₃)`` (3d), ``e(θ, s) = D⁻¹ e'(θ)`` where ``e'`` is the error of GTSAM's own
``BearingRangeFactor2D`` / ``BetweenFactorPose3`` whose measured range / translation is ``s`` times the row's
(``Log``'s translation part is linear in the translation for a fixed rotation), and whitening ``e'`` with the
covariance ``D Σ D`` gives the same whitened residual as ``e`` with ``Σ``. So:

- *inner*: for a fixed ``s`` the graph is all native (:func:`native_rows`), optimised by GTSAM's own optimiser;
- *outer*: at the inner optimum the native graph is linearised and every tag factor gets a third block, the
  whitened ``∂e/∂s``. Scaling the prediction by ``1 / s`` is moving the landmark along its offset from the pose:
  ``∂e/∂s = −(1/s) ∂e/∂l · w`` with ``w = l − x_t`` (planar, the landmark's offset from the pose in the map frame)
  or ``w = Rᵀ t`` (3d, ``(R, t) = a⁻¹ b``, the landmark's translation block), so the block is the native
  factor's own whitened landmark Jacobian times ``−w / s`` (robust re-weighting included). With the scale prior's
  row, that joint linear system is the Gauss-Newton system of the whole problem; its step updates ``θ`` and
  ``s`` together and is accepted when the error falls (else the inner optimiser runs again at the new ``s``), until
  the error falls by less than the tolerances: ``δs = 0`` with the inner gradient zero is the joint optimum.
- *marginals*: :func:`joint_marginals` takes the marginals of the same joint linear system at the solution,
  i.e. exactly the covariances of the model with ``s`` a variable (every pose and landmark covariance contains the
  scale's uncertainty; the scale's own marginal is one of them).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import gtsam
import numpy as np

from stages.geometry import pose3_from_vector
from stages.graph.factors import FactorRow, build_graph, noise_model, scaled_measurement
from stages.graph.marginals import key_dims, tree_marginals

SCALED_TYPES = ("BearingRangeFactor2D", "BetweenFactorPose3")
"""Row types that carry the scale as a third key."""


def is_scaled(row: FactorRow) -> bool:
    """Whether a row is a tag factor with the shared scale as its third key."""
    return len(row.keys) == 3 and row.type in SCALED_TYPES


def scale_key_of(rows: Sequence[FactorRow]) -> int | None:
    """The scale key the rows use (None when no row carries one)."""
    return next((r.keys[2] for r in rows if is_scaled(r)), None)


def native_rows(rows: Sequence[FactorRow], s: float) -> tuple[list[FactorRow], list[int]]:
    """The rows at a fixed scale ``s`` as native rows (scaled measurement, covariance ``D Σ D``, two keys), without
    the scale's priors; and for each returned row the index of the row it comes from."""
    out: list[FactorRow] = []
    origin: list[int] = []
    for i, row in enumerate(rows):
        if is_scaled(row):
            D = np.diag([1.0, s]) if row.type == "BearingRangeFactor2D" else np.diag([1.0] * 3 + [s] * 3)
            cov = D @ np.asarray(row.covariance, dtype=float).reshape(row.dim, row.dim) @ D
            out.append(replace(row, keys=row.keys[:2], measurement=scaled_measurement(row, s), covariance=cov))
        elif row.type == "PriorFactorDouble":
            continue
        else:
            out.append(row)
        origin.append(i)
    return out, origin


def _scale_priors(rows: Sequence[FactorRow], key: int) -> list[tuple[float, float]]:
    """(mean, sigma) of every prior on the scale."""
    return [
        (float(r.measurement[0]), float(np.sqrt(np.asarray(r.covariance, dtype=float).ravel()[0])))
        for r in rows
        if r.type == "PriorFactorDouble" and r.keys[0] == key
    ]


class _ScaledParts:
    """What does not change with the scale: the native graph of the other rows (built once), the tag rows' numbers
    and the scale's priors. Rebuilding the graph at a new scale then constructs only the tag factors."""

    def __init__(self, rows: Sequence[FactorRow]) -> None:
        key = scale_key_of(rows)
        if key is None:
            raise ValueError("the rows carry no tag scale")
        self.key = key
        fixed = [r for r in rows if not is_scaled(r) and r.type != "PriorFactorDouble"]
        self.fixed = build_graph(fixed)
        self.tags = [r for r in rows if is_scaled(r)]
        self.covs = [np.asarray(r.covariance, dtype=float).reshape(r.dim, r.dim) for r in self.tags]
        self.priors = _scale_priors(rows, key)
        self.ordering: gtsam.Ordering | None = None
        """The elimination ordering of the native linear system (the same structure at every scale)."""

    def graph_at(self, s: float) -> gtsam.NonlinearFactorGraph:
        """The native graph at scale ``s``: the other rows' factors, then one native factor per tag row."""
        graph = gtsam.NonlinearFactorGraph(self.fixed)  # shares the fixed factors
        d2 = np.array([1.0, s])
        d6 = np.array([1.0] * 3 + [s] * 3)
        for row, cov in zip(self.tags, self.covs, strict=True):
            m = row.measurement
            if row.type == "BearingRangeFactor2D":
                noise = noise_model(cov * np.outer(d2, d2), row.robust, row.robust_k)
                graph.add(gtsam.BearingRangeFactor2D(row.keys[0], row.keys[1], gtsam.Rot2(m[0]), s * m[1], noise))
            else:
                noise = noise_model(cov * np.outer(d6, d6), row.robust, row.robust_k)
                graph.add(
                    gtsam.BetweenFactorPose3(
                        row.keys[0], row.keys[1], pose3_from_vector(scaled_measurement(row, s)), noise
                    )
                )
        return graph


class NativeScaleGraph:
    """The native graph of ``rows`` at one scale, the scale's priors, and the joint linear system around it."""

    def __init__(self, rows: Sequence[FactorRow] | _ScaledParts, s: float) -> None:
        parts = rows if isinstance(rows, _ScaledParts) else _ScaledParts(rows)
        self.parts = parts
        self.key = parts.key
        self.s = float(s)
        self.graph = parts.graph_at(self.s)
        n_fixed = int(parts.fixed.size())
        self.scaled = list(range(n_fixed, n_fixed + len(parts.tags)))
        self.types = {i: r.type for i, r in zip(self.scaled, parts.tags, strict=True)}
        self.priors = parts.priors

    def at(self, s: float) -> NativeScaleGraph:
        """The same rows at another scale."""
        return NativeScaleGraph(self.parts, s)

    def prior_error(self, s: float) -> float:
        """GTSAM's error (half the whitened square) of the scale's priors at ``s``."""
        return sum(0.5 * ((s - m) / sig) ** 2 for m, sig in self.priors)

    def error(self, values: gtsam.Values) -> float:
        """The error of the model with the scale, at ``values`` (without ``s``) and :attr:`s`."""
        return float(self.graph.error(values)) + self.prior_error(self.s)

    def _scale_columns(self, lin: gtsam.GaussianFactorGraph, values: gtsam.Values) -> list[_ScaledFactors]:
        """The tag factors of the native linearisation ``lin``, by type, with their whitened ``∂e/∂s`` columns
        (vectorised: one Jacobian read per factor, the rest in numpy)."""
        out = []
        for kind in sorted({self.types[i] for i in self.scaled}):
            index = [i for i in self.scaled if self.types[i] == kind]
            factors = [lin.at(i) for i in index]
            keys = np.array([[int(k) for k in f.keys()] for f in factors], dtype=np.int64)  # noqa: SIM118
            jac = [f.jacobian() for f in factors]
            A = np.stack([j[0] for j in jac])
            b = np.stack([j[1] for j in jac])
            if kind == "BearingRangeFactor2D":
                n_a = 3
                poses = _positions(gtsam.utilities.allPose2s(values), gtsam.utilities.extractPose2, keys[:, 0], 2)
                points = {k: values.atPoint2(k) for k in set(keys[:, 1].tolist())}
                w = np.array([points[k] for k in keys[:, 1].tolist()]) - poses  # the landmark's offset, map frame
                col = np.einsum("nij,nj->ni", A[:, :, n_a:], w)
            else:  # w = R_lᵀ (t_l − t_a): the landmark's translation block of a⁻¹ l, in its own frame
                n_a = 6
                matrix = gtsam.utilities.extractPose3(values)
                row = {k: i for i, k in enumerate(gtsam.utilities.allPose3s(values).keys())}
                ra, rl = (np.array([row[k] for k in keys[:, j].tolist()]) for j in (0, 1))
                R_l = matrix[rl, :9].reshape(-1, 3, 3)
                w = np.einsum("nji,nj->ni", R_l, matrix[rl, 9:] - matrix[ra, 9:])
                col = np.einsum("nij,nj->ni", A[:, :, n_a + 3 :], w)
            out.append(_ScaledFactors(keys[:, 0], keys[:, 1], A[:, :, :n_a], A[:, :, n_a:], b, -col / self.s))
        return out

    def joint_system(self, values: gtsam.Values) -> gtsam.GaussianFactorGraph:
        """The model's Gauss-Newton system at ``values`` and :attr:`s`: the native linearisation with the scale's
        column in each tag factor and the priors' rows (see the module docstring)."""
        lin = self.graph.linearize(values)
        joint = gtsam.GaussianFactorGraph()
        scaled = set(self.scaled)
        for i in range(lin.size()):
            if i not in scaled:
                joint.push_back(lin.at(i))
        for f in self._scale_columns(lin, values):
            unit = gtsam.noiseModel.Unit.Create(f.b.shape[1])
            for i in range(len(f.a)):
                joint.push_back(
                    gtsam.JacobianFactor(
                        int(f.a[i]), f.A_a[i], int(f.l[i]), f.A_l[i], self.key, f.c[i].reshape(-1, 1), f.b[i], unit
                    )
                )
        one = gtsam.noiseModel.Unit.Create(1)
        for m, sig in self.priors:
            joint.push_back(
                gtsam.JacobianFactor(self.key, np.array([[1.0 / sig]]), np.array([(m - self.s) / sig]), one)
            )
        return joint

    def joint_step(self, values: gtsam.Values) -> tuple[gtsam.VectorValues, float]:
        """The Gauss-Newton step of :meth:`joint_system`, ``(δθ, δs)``, by its Schur complement on the scale: with
        the native system's ``H = AᵀA`` and ``g = Aᵀb``, the scale's column ``c`` and ``h = Aᵀc``,
        ``δs = (cᵀb + Σ (m − s)/σ² − hᵀH⁻¹g) / (cᵀc + Σ 1/σ² − hᵀH⁻¹h)`` and ``δθ = H⁻¹g − H⁻¹h δs``. One
        elimination of the native system (its ordering computed once for the rows) serves both solves, and no
        factor is rebuilt (the same step as eliminating :meth:`joint_system`, to rounding)."""
        lin = self.graph.linearize(values)
        if self.parts.ordering is None:
            self.parts.ordering = gtsam.Ordering.ColamdGaussianFactorGraph(lin)
        net = lin.eliminateSequential(self.parts.ordering)
        step = net.optimize()
        h: dict[int, np.ndarray] = {}
        ctb = ctc = 0.0
        for f in self._scale_columns(lin, values):
            for keys, A in ((f.a, f.A_a), (f.l, f.A_l)):
                parts = np.einsum("nij,ni->nj", A, f.c)  # each factor's Aᵀc on that key
                unique, at = np.unique(keys, return_inverse=True)
                summed = np.zeros((len(unique), parts.shape[1]))
                np.add.at(summed, at, parts)
                for k, v in zip(unique.tolist(), summed, strict=True):
                    h[k] = h[k] + v if k in h else v
            ctb += float((f.c * f.b).sum())
            ctc += float((f.c * f.c).sum())
        given = gtsam.VectorValues()
        for k, v in h.items():
            given.insert(k, v)
        h_values = gtsam.VectorValues.Zero(step)  # every key (the other keys' entries of h are 0)
        h_values.update(given)
        u = net.backSubstitute(net.backSubstituteTranspose(h_values))  # H⁻¹h
        h_step = sum(float(v @ step.at(k)) for k, v in h.items())
        h_u = sum(float(v @ u.at(k)) for k, v in h.items())
        rhs = ctb + sum((m - self.s) / sig**2 for m, sig in self.priors) - h_step
        ds = rhs / (ctc + sum(1.0 / sig**2 for _, sig in self.priors) - h_u)
        return step.add(u.scale(-ds)), ds


@dataclass(frozen=True)
class _ScaledFactors:
    """Tag factors of one type, whitened and linearised: ``A_a δa + A_l δl + c δs = b`` (pose ``a``, landmark
    ``l``), stacked along the first axis."""

    a: np.ndarray
    l: np.ndarray  # noqa: E741
    A_a: np.ndarray
    A_l: np.ndarray
    b: np.ndarray
    c: np.ndarray


def _positions(of_type: gtsam.Values, extract: object, keys: np.ndarray, n: int) -> np.ndarray:
    """The first ``n`` columns of ``extract(of_type)`` (one row per variable, in key order) for each of ``keys``."""
    matrix = extract(of_type)  # type: ignore[operator]
    row = {k: i for i, k in enumerate(of_type.keys())}
    return np.asarray(matrix)[[row[k] for k in keys.tolist()], :n]


def without_key(values: gtsam.Values, key: int) -> gtsam.Values:
    """A copy of ``values`` without ``key``."""
    out = gtsam.Values(values)
    if out.exists(key):
        out.erase(key)
    return out


def with_scale(values: gtsam.Values, key: int, s: float) -> gtsam.Values:
    """A copy of ``values`` with the scale ``key`` at ``s``."""
    out = gtsam.Values(values)
    out.insert(key, float(s))
    return out


@dataclass
class ScaleSolution:
    """Result of :func:`optimise_with_scale`: the values with ``s``, their error and what it took."""

    values: gtsam.Values
    initial_error: float
    final_error: float
    iterations: int
    """Inner optimiser iterations plus outer rounds."""
    rounds: int
    """Joint Gauss-Newton steps taken on ``(θ, s)``."""


def _converged(old: float, new: float, relative_tol: float, absolute_tol: float) -> bool:
    decrease = old - new
    return new <= 0.0 or decrease < absolute_tol or (old > 0 and decrease / old < relative_tol)


def optimise_with_scale(
    rows: Sequence[FactorRow],
    initial: gtsam.Values,
    inner: object,
    max_rounds: int = 50,
    relative_tol: float = 1e-6,
    absolute_tol: float = 1e-9,
) -> ScaleSolution:
    """Minimise the model with the shared scale (module docstring). ``inner(graph, values) -> (values, iterations)``
    optimises a native graph (GTSAM's LM, GN or Dogleg with the stage's limits)."""
    key = scale_key_of(rows)
    if key is None:
        raise ValueError("the rows carry no tag scale")
    s = float(initial.atDouble(key))
    native = NativeScaleGraph(rows, s)
    theta = without_key(initial, key)
    initial_error = native.error(theta)
    theta, iterations = inner(native.graph, theta)  # type: ignore[operator]
    error = native.error(theta)
    rounds = 0
    while rounds < max_rounds:
        rounds += 1
        step, ds = native.joint_step(theta)
        cand_theta, cand = theta.retract(step), native.at(s + ds)
        cand_error = cand.error(cand_theta)
        if not cand_error <= error:  # the joint step overshot: optimise the native graph at the new scale
            cand_theta, more = inner(cand.graph, theta)  # type: ignore[operator]
            iterations += more
            cand_error = cand.error(cand_theta)
            if not cand_error <= error:  # neither falls: at the minimum (to the linearisation's accuracy)
                break
        done = _converged(error, cand_error, relative_tol, absolute_tol)
        theta, native, s, error = cand_theta, cand, s + ds, cand_error
        if done:
            break
    return ScaleSolution(with_scale(theta, key, s), initial_error, error, iterations + rounds, rounds)


def joint_marginals(
    rows: Sequence[FactorRow], values: gtsam.Values, keys: Sequence[int], last: Sequence[int] = ()
) -> dict[int, np.ndarray]:
    """Marginal covariance of each key of the model with the shared scale at ``values`` (which hold ``s``), from one
    elimination of its joint linear system (:func:`stages.graph.marginals.tree_marginals`): the same system GTSAM
    linearises the scaled factors to."""
    key = scale_key_of(rows)
    if key is None:
        raise ValueError("the rows carry no tag scale")
    native = NativeScaleGraph(rows, float(values.atDouble(key)))
    joint = native.joint_system(without_key(values, key))
    return tree_marginals(joint, key_dims(values), keys, last=last)
