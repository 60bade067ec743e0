"""LinearSystem's assembly: the Jacobian stacked by shape groups is the one stacked factor by factor."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from stages.estimation.linear_system import LinearSystem, information_from_gtsam


def _one_by_one(system: LinearSystem, ids: list[int]) -> sp.csr_matrix:
    """The reference: each factor's block written at its rows and columns, in the given order."""
    blocks = [system.factors[f] for f in ids if system.factors[f].rows]
    J = np.zeros((sum(f.rows for f in blocks), system.dim))
    r = 0
    for f in blocks:
        J[r : r + f.rows, system.columns(f.variables)] = f.jacobian
        r += f.rows
    return sp.csr_matrix(J)


def _mixed_system(rng: np.random.Generator) -> LinearSystem:
    """Poses of 3 dims, landmarks of 2 and a 1-dim variable; priors, odometry, measurements of 2 and 3 rows, a
    three-variable factor and an empty one."""
    dims = [3] * 6 + [2] * 3 + [1]
    kinds = ["pose"] * 6 + ["landmark"] * 3 + ["pose"]
    factors: list[tuple[list[int], np.ndarray]] = [([0], rng.standard_normal((3, 3)))]
    factors += [([i, i + 1], rng.standard_normal((3, 6))) for i in range(5)]
    factors += [([i, 6 + i % 3], rng.standard_normal((2, 5))) for i in range(6)]
    factors += [([6 + i % 3, i], rng.standard_normal((3, 5))) for i in range(3)]
    factors += [([2, 7, 9], rng.standard_normal((2, 6))), ([4], np.zeros((0, 3)))]
    return LinearSystem.from_blocks(dims, kinds, factors)  # type: ignore[arg-type]


def test_jacobian_grouped_by_shape_equals_stacking_factor_by_factor() -> None:
    rng = np.random.default_rng(3)
    system = _mixed_system(rng)
    for ids in (list(range(len(system.factors))), [int(i) for i in rng.permutation(len(system.factors))], [15, 2, 7]):
        got = system.jacobian(ids)
        want = _one_by_one(system, ids)
        assert got.shape == want.shape
        np.testing.assert_array_equal(got.toarray(), want.toarray())
    info = system.information()
    J = _one_by_one(system, list(range(len(system.factors)))).toarray()
    np.testing.assert_allclose(info.toarray(), J.T @ J, rtol=1e-12, atol=1e-12)
    assert system.jacobian([]).shape == (0, system.dim)
    assert system.jacobian([16]).shape == (0, system.dim)  # the empty factor only


def test_factor_columns_are_cached_and_right() -> None:
    system = _mixed_system(np.random.default_rng(4))
    for f, fac in enumerate(system.factors):
        np.testing.assert_array_equal(system.factor_columns(f), system.columns(fac.variables))
    assert system.factor_columns(15) is system.factor_columns(15)


def test_information_from_gtsams_sparse_jacobian_equals_the_per_factor_assembly() -> None:
    """``information_from_gtsam`` (one C++ call) gives the same Λ, keys and columns as stacking every factor's
    whitened Jacobian, on a graph of mixed dimensions (Pose2, Point2, Pose3) whose keys are not in insertion order."""
    import gtsam

    rng = np.random.default_rng(5)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    X, L, P = (lambda i: gtsam.symbol("x", i)), (lambda i: gtsam.symbol("l", i)), (lambda i: gtsam.symbol("p", i))
    odo = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.05, 0.02, 0.01]))
    br = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.02, 0.1]))
    graph.add(gtsam.PriorFactorPose2(X(0), gtsam.Pose2(), odo))
    for i in range(8):
        values.insert(X(i), gtsam.Pose2(i + 0.1 * rng.standard_normal(), 0.1 * rng.standard_normal(), 0.05 * i))
        if i:
            graph.add(gtsam.BetweenFactorPose2(X(i - 1), X(i), gtsam.Pose2(1.0, 0.0, 0.05), odo))
    for j in (7, 2, 4):
        values.insert(L(j), gtsam.Point2(float(j), 2.0 + 0.1 * j))
        for i in range(0, 8, 2):
            graph.add(gtsam.BearingRangeFactor2D(X(i), L(j), gtsam.Rot2(0.3), 2.0, br))
    values.insert(P(1), gtsam.Pose3())
    graph.add(gtsam.PriorFactorPose3(P(1), gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 0.3)))
    got = information_from_gtsam(graph, values)
    want = LinearSystem.from_gtsam(graph, values)
    assert got.keys == [v.key for v in want.variables]
    np.testing.assert_array_equal(got.offsets, want.offsets)
    np.testing.assert_allclose(got.information.toarray(), want.information().toarray(), rtol=1e-12, atol=1e-9)
    assert got.index_of_key(L(4)) == want.index_of_key(L(4))
