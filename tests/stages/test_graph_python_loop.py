"""The Python-driven LM / GN loop (the reference solver of graphs with the shared tag scale) against GTSAM's own
optimisers, and the stage's native solve against it."""

from __future__ import annotations

import itertools

import gtsam
import numpy as np
import pytest

from stages.graph.factors import SCALE_KEY, build_graph, has_python_factors
from stages.graph.problem import VAR_DIMS
from stages.graph.python_loop import optimise_in_python
from stages.graph.solve import optimise
from tests.fixtures.synthetic_runs import synthetic_planar_problem


@pytest.fixture(scope="module")
def scaled():
    problem = synthetic_planar_problem(300, 20, 450, seed=3, tag_scale_sigma=0.005)
    assert has_python_factors(problem.rows)
    return problem, build_graph(problem.rows), {k: VAR_DIMS[t] for k, t in problem.var_types.items()}


def _max_difference(a: gtsam.Values, b: gtsam.Values, problem) -> float:
    diff = 0.0
    for k, t in problem.var_types.items():
        if t == "Pose2":
            diff = max(diff, float(np.abs(a.atPose2(k).localCoordinates(b.atPose2(k))).max()))
        elif t == "Point2":
            diff = max(diff, float(np.abs(a.atPoint2(k) - b.atPoint2(k)).max()))
        else:
            diff = max(diff, abs(a.atDouble(k) - b.atDouble(k)))
    return diff


@pytest.mark.parametrize("method", ["lm", "gn"])
def test_same_minimum_as_gtsam(scaled, method: str) -> None:
    problem, graph, dims = scaled
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-10)
    params.setAbsoluteErrorTol(1e-12)
    ref = gtsam.LevenbergMarquardtOptimizer(graph, problem.initial, params).optimize()
    ours = optimise_in_python(graph, problem.initial, dims, method, relative_tol=1e-10, absolute_tol=1e-12)
    assert ours.values.atDouble(SCALE_KEY) != 1.0  # the scale moved: it is estimated
    assert _max_difference(ours.values, ref, problem) < 1e-6
    np.testing.assert_allclose(graph.error(ours.values), graph.error(ref), rtol=1e-8)


def test_lm_recovers_from_a_bad_start_where_its_error_only_falls(scaled) -> None:
    problem, graph, dims = scaled
    rng = np.random.default_rng(0)
    start = gtsam.Values()
    for k, t in problem.var_types.items():
        if t == "Pose2":
            p = problem.initial.atPose2(k)
            start.insert(k, p.retract(rng.normal(0, [0.3, 0.3, 0.2])))
        elif t == "Point2":
            start.insert(k, problem.initial.atPoint2(k) + rng.normal(0, 0.5, 2))
        else:
            start.insert(k, 1.03)
    errors = []
    for n in (1, 2, 4, 100):
        errors.append(graph.error(optimise_in_python(graph, start, dims, "lm", max_iterations=n).values))
    assert all(b <= a for a, b in itertools.pairwise(errors))
    best = gtsam.LevenbergMarquardtOptimizer(graph, problem.initial, gtsam.LevenbergMarquardtParams()).optimize()
    np.testing.assert_allclose(errors[-1], graph.error(best), rtol=1e-5)


def test_iteration_limit_is_respected(scaled) -> None:
    problem, graph, dims = scaled
    assert optimise_in_python(graph, problem.initial, dims, "lm", max_iterations=1).iterations == 1


def test_stage_optimise_with_the_scale_runs_each_optimizer_natively(scaled) -> None:
    """The stage no longer needs this loop: with the scale it runs the chosen GTSAM optimiser on native factors
    (stages/graph/scale_solve.py), dogleg included, and reaches the minimum this loop reaches."""
    problem, graph, dims = scaled
    lm = optimise(problem, graph, "lm")
    dogleg = optimise(problem, graph, "dogleg")
    assert lm.optimizer == "lm" and dogleg.optimizer == "dogleg"
    np.testing.assert_allclose(lm.final_error, dogleg.final_error, rtol=1e-7)
    assert lm.final_error < lm.initial_error
    loop = optimise_in_python(graph, problem.initial, dims, "lm", relative_tol=1e-12, absolute_tol=1e-12)
    np.testing.assert_allclose(lm.final_error, graph.error(loop.values), rtol=1e-7)
    np.testing.assert_allclose(lm.final_error, graph.error(lm.values), rtol=1e-12)  # the error of the model itself
