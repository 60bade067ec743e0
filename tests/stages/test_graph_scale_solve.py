"""The shared tag scale solved with native factors (stages/graph/scale_solve.py) against the model with the scale as a
variable (the CustomFactor graph of stages/graph/factors.py): the same errors, linear system, optimum and marginals."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from stages.graph.build import build_problem
from stages.graph.config import GraphConfig
from stages.graph.factors import SCALE_KEY, build_graph
from stages.graph.problem import VAR_DIMS
from stages.graph.python_loop import optimise_in_python
from stages.graph.scale_solve import NativeScaleGraph, with_scale, without_key
from stages.graph.solve import marginal_covariances, optimise
from tests.fixtures.synthetic_runs import synthetic_run


@pytest.fixture(scope="module", params=[("planar", "none"), ("3d", "none"), ("planar", "huber")])
def problem(request):
    model, robust = request.param
    sim = synthetic_run(seed=2)
    return build_problem(sim.detections, sim.odometry, sim.extrinsics, GraphConfig(model=model, robust_kernel=robust))


def _perturbed(problem, seed: int = 0) -> gtsam.Values:
    """The initial values moved off the dead reckoning, the scale off 1 (a generic point, not a minimum)."""
    rng = np.random.default_rng(seed)
    out = gtsam.Values()
    for k, t in problem.var_types.items():
        if t == "Pose2":
            out.insert(k, problem.initial.atPose2(k).retract(rng.normal(0, 0.05, 3)))
        elif t == "Pose3":
            out.insert(k, problem.initial.atPose3(k).retract(rng.normal(0, 0.05, 6)))
        elif t == "Point2":
            out.insert(k, problem.initial.atPoint2(k) + rng.normal(0, 0.05, 2))
        else:
            out.insert(k, 1.013)
    return out


def test_native_graph_has_the_error_of_the_scaled_model(problem) -> None:
    values = _perturbed(problem)
    native = NativeScaleGraph(problem.rows, values.atDouble(SCALE_KEY))
    np.testing.assert_allclose(
        native.error(without_key(values, SCALE_KEY)), build_graph(problem.rows).error(values), rtol=1e-12
    )


def test_joint_system_is_the_linearisation_of_the_scaled_model(problem) -> None:
    values = _perturbed(problem, 1)
    native = NativeScaleGraph(problem.rows, values.atDouble(SCALE_KEY))
    ours = native.joint_system(without_key(values, SCALE_KEY))
    ref = build_graph(problem.rows).linearize(values)
    ordering = gtsam.Ordering()
    for k in [*sorted(set(problem.var_types) - {SCALE_KEY}), SCALE_KEY]:
        ordering.push_back(k)
    H, eta = ours.hessian(ordering)
    H_ref, eta_ref = ref.hessian(ordering)
    scale = np.abs(H_ref).max()
    assert np.abs(H - H_ref).max() < 1e-9 * scale
    np.testing.assert_allclose(eta, eta_ref, atol=1e-9 * np.abs(eta_ref).max())
    assert np.abs(H_ref[:, -1]).max() > 0  # the scale's column is there (and is compared)


def test_the_schur_step_is_the_joint_systems_step(problem) -> None:
    """joint_step (one native elimination, the scale by its Schur complement) gives the Gauss-Newton step of the
    joint system, poses, landmarks and scale, at a generic point (planar, 3d, with a robust kernel)."""
    values = _perturbed(problem, 2)
    native = NativeScaleGraph(problem.rows, values.atDouble(SCALE_KEY))
    theta = without_key(values, SCALE_KEY)
    ref = native.joint_system(theta).optimize()
    for _ in range(2):  # the second time with the ordering kept from the first
        step, ds = native.joint_step(theta)
        assert ds == pytest.approx(float(ref.at(SCALE_KEY)[0]), rel=1e-8) and abs(ds) > 1e-6
        for k in problem.var_types:
            if k != SCALE_KEY:
                np.testing.assert_allclose(step.at(k), ref.at(k), rtol=1e-7, atol=1e-10)


def test_optimum_and_marginals_match_the_scaled_model(problem) -> None:
    graph = build_graph(problem.rows)
    dims = {k: VAR_DIMS[t] for k, t in problem.var_types.items()}
    ref = optimise_in_python(graph, problem.initial, dims, "lm", 100, 1e-12, 1e-12).values
    sol = optimise(problem, graph)
    assert sol.values.atDouble(SCALE_KEY) != 1.0
    np.testing.assert_allclose(sol.final_error, graph.error(ref), rtol=1e-7)
    np.testing.assert_allclose(sol.final_error, graph.error(sol.values), rtol=1e-12)
    keys = list(problem.var_types)
    span = np.ptp([problem.position(ref, k) for k in problem.pose_keys], axis=0).max()
    for k in keys:
        if k != SCALE_KEY:
            assert np.linalg.norm(problem.position(sol.values, k) - problem.position(ref, k)) < 2e-5 * span
    assert abs(sol.values.atDouble(SCALE_KEY) - ref.atDouble(SCALE_KEY)) < 1e-5
    # marginals at the same point: the joint system's equal GTSAM's of the scaled model to rounding
    ours = marginal_covariances(problem, graph, ref, keys)
    marginals = gtsam.Marginals(graph, ref)
    for k in keys:
        expected = np.asarray(marginals.marginalCovariance(k))
        np.testing.assert_allclose(ours[k], expected, rtol=1e-7, atol=1e-9 * np.abs(expected).max())
    assert with_scale(without_key(ref, SCALE_KEY), SCALE_KEY, 1.0).atDouble(SCALE_KEY) == 1.0
