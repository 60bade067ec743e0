"""Every marginal from one elimination down the Bayes tree (stages/graph/marginals.py) against GTSAM's own
per-key queries, on graphs of every shape the stages make: planar and 3D, a shared tag scale, disconnected parts."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from stages.graph.factors import build_graph
from stages.graph.marginals import (
    key_dims,
    selected_inverse,
    sparse_joint_covariance,
    tree_marginals,
    whitened_system,
)
from stages.graph.scale_solve import NativeScaleGraph, scale_key_of, without_key
from stages.graph.solve import optimise
from tests.fixtures.synthetic_runs import synthetic_planar_problem


def _gtsam(linear: gtsam.GaussianFactorGraph, values: gtsam.Values, keys: list[int]) -> dict[int, np.ndarray]:
    marginals = gtsam.Marginals(linear, values)
    return {k: np.asarray(marginals.marginalCovariance(k)) for k in keys}


def _assert_same(ours: dict[int, np.ndarray], theirs: dict[int, np.ndarray]) -> None:
    assert ours.keys() == theirs.keys()
    for k, cov in theirs.items():
        assert np.allclose(ours[k], cov, rtol=1e-8, atol=1e-12 * np.abs(cov).max()), k
        assert np.array_equal(ours[k], ours[k].T)


@pytest.mark.parametrize("sigma", [0.0, 0.005])
def test_planar_graphs_with_and_without_the_shared_scale(sigma: float) -> None:
    problem = synthetic_planar_problem(300, 25, 500, seed=3, tag_scale_sigma=sigma)
    graph = build_graph(problem.rows)
    values = optimise(problem, graph).values
    keys = list(problem.var_types)
    if sigma:  # the joint system of native factors and the scale's column
        key = scale_key_of(problem.rows)
        assert key is not None
        linear = NativeScaleGraph(problem.rows, float(values.atDouble(key))).joint_system(without_key(values, key))
    else:
        linear = graph.linearize(values)
    _assert_same(tree_marginals(linear, key_dims(values), keys), _gtsam(linear, values, keys))


def test_a_3d_graph_in_two_disconnected_parts() -> None:
    """Pose3 chains with loop closures and Point3 landmarks, as two separate parts (two roots)."""
    rng = np.random.default_rng(4)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.02, 0.02, 0.02, 0.1, 0.1, 0.1]))
    for part in range(2):
        base = 1000 * part
        graph.add(gtsam.PriorFactorPose3(base, gtsam.Pose3(), noise))
        pose = gtsam.Pose3()
        for i in range(40):
            step = gtsam.Pose3(gtsam.Rot3.Rodrigues(*rng.normal(0, 0.1, 3)), rng.normal([1, 0, 0], 0.1))
            values.insert(base + i, pose)
            if i:
                graph.add(gtsam.BetweenFactorPose3(base + i - 1, base + i, step, noise))
            pose = pose.compose(step)
            if i >= 5 and i % 7 == 0:  # a loop closure to five poses back
                graph.add(gtsam.BetweenFactorPose3(base + i - 5, base + i, gtsam.Pose3(), noise))
        for j in range(5):
            lm = base + 500 + j
            values.insert(lm, rng.normal(0, 3, 3))
            for i in rng.choice(40, 4, replace=False):
                bearing = gtsam.Unit3(rng.normal(0, 1, 3))
                noise_br = gtsam.noiseModel.Isotropic.Sigma(3, 0.05)
                graph.add(gtsam.BearingRangeFactor3D(base + int(i), lm, bearing, float(rng.uniform(1, 4)), noise_br))
    linear = graph.linearize(values)
    keys = [int(k) for k in values.keys()]  # noqa: SIM118 (a gtsam KeyVector)
    ours = tree_marginals(linear, key_dims(values), keys)
    assert {len(c) for c in ours.values()} == {3, 6}
    _assert_same(ours, _gtsam(linear, values, keys))


def test_an_indeterminant_graph_raises_as_gtsam_does() -> None:
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    noise = gtsam.noiseModel.Isotropic.Sigma(3, 0.1)
    graph.add(gtsam.BetweenFactorPose2(0, 1, gtsam.Pose2(1, 0, 0), noise))  # no prior: free to move
    values.insert(0, gtsam.Pose2())
    values.insert(1, gtsam.Pose2(1, 0, 0))
    with pytest.raises(RuntimeError) as theirs:
        _gtsam(graph.linearize(values), values, [0, 1])
    with pytest.raises(RuntimeError) as ours:
        tree_marginals(graph.linearize(values), key_dims(values), [0, 1])
    assert type(ours.value) is type(theirs.value)


class _ColamdStops(gtsam.GaussianFactorGraph):
    """A linear graph whose default elimination stops as GTSAM's COLAMD ordering did on TagSLAM's test_14 reduced to
    30 landmarks (a pivot lost to rounding in a positive definite system); any other ordering eliminates it."""

    def eliminateMultifrontal(self, *args):  # type: ignore[no-untyped-def]
        if not args:
            raise RuntimeError("Indeterminate linear system detected while working near variable l70")
        return super().eliminateMultifrontal(*args)


def _planar_scaled() -> tuple[gtsam.GaussianFactorGraph, gtsam.Values, list[int], list[int]]:
    problem = synthetic_planar_problem(300, 25, 500, seed=3, tag_scale_sigma=0.0)
    graph = build_graph(problem.rows)
    values = optimise(problem, graph).values
    return graph.linearize(values), values, list(problem.var_types), list(problem.landmark_keys.values())


def test_the_landmarks_last_ordering_takes_over_when_the_default_one_stops() -> None:
    linear, values, keys, landmarks = _planar_scaled()
    stops = _ColamdStops()
    for i in range(linear.size()):
        stops.push_back(linear.at(i))
    with pytest.raises(RuntimeError, match="Indeterminate"):
        tree_marginals(stops, key_dims(values), keys)  # no landmarks named: nothing to fall back to
    _assert_same(tree_marginals(stops, key_dims(values), keys, last=landmarks), _gtsam(linear, values, keys))


def test_the_sparse_joint_covariance_is_gtsams() -> None:
    linear, values, keys, landmarks = _planar_scaled()
    pick = landmarks[::4] + [k for k in keys if k not in set(landmarks)][:3]  # landmarks and poses, each once
    theirs = np.asarray(gtsam.Marginals(linear, values).jointMarginalCovariance(gtsam.KeyVector(pick)).fullMatrix())
    ours = sparse_joint_covariance(linear, key_dims(values), pick)
    assert ours.shape == theirs.shape
    assert np.allclose(ours, theirs, rtol=1e-7, atol=1e-10 * np.abs(theirs).max())


@pytest.mark.parametrize("sigma", [0.0, 0.005])
def test_the_selected_inverse_is_the_dense_inverse_on_every_factors_blocks(sigma: float) -> None:
    """``selected_inverse`` gives ``H⁻¹`` on the blocks of every factor's keys (both ways) and zero elsewhere, equal
    to the dense inverse of ``JᵀJ``; each factor's leverage ``tr(H⁻¹ J_fᵀ J_f)`` from it sums to the number of
    unknowns, as the hat matrix's trace must. With the shared scale, one key is in every tag factor's group."""
    problem = synthetic_planar_problem(120, 15, 200, seed=5, tag_scale_sigma=sigma)
    graph = build_graph(problem.rows)
    values = optimise(problem, graph).values
    linear = graph.linearize(values)
    groups = [[int(k) for k in linear.at(i).keys()] for i in range(linear.size())]  # noqa: SIM118 (a KeyVector)
    dims = key_dims(values)
    Z = selected_inverse(linear, dims, groups)
    J, _ = whitened_system(linear)
    dense = np.linalg.inv((J.T @ J).toarray())
    ordered = sorted(dims)
    start = dict(zip(ordered, np.cumsum([0] + [dims[k] for k in ordered[:-1]]).tolist(), strict=True))
    mask = np.zeros(dense.shape, dtype=bool)
    for g in groups:
        idx = np.concatenate([np.arange(start[k], start[k] + dims[k]) for k in g])
        mask[np.ix_(idx, idx)] = True
    Zd = Z.toarray()
    assert np.allclose(Zd[mask], dense[mask], rtol=1e-8, atol=1e-10 * np.abs(dense).max())
    assert not Zd[~mask].any()
    leverage = float((J.T @ J).multiply(Z).sum())
    assert leverage == pytest.approx(J.shape[1], rel=1e-9)
    with pytest.raises(RuntimeError, match="share no clique"):  # the first and last poses are no factor's keys
        selected_inverse(linear, dims, [[ordered[0], ordered[-1]], *groups])
