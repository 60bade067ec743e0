"""Fast focused-information measurement greedy against a plain dense reference, and the other strategies."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from stages.estimation.linear_system import LinearSystem
from stages.estimation.measurement_selection import (
    default_base,
    focused_entropy,
    leverage_probabilities,
    select_information,
    select_leverage,
    select_random,
    select_uniform,
)
from tests.fixtures.planar_problems import planar_problem

SLAM_GRAPHS = "/work/shared/data/slam-graphs"


def reference_greedy(system, candidates, focused, budget, base, landmark_prior_sigma=100.0):
    """Alg. 1 as written: for every candidate, recompute ½ log det(W Λ⁻¹ Wᵀ) from scratch (dense)."""
    used = sorted({v for f in list(base) + list(candidates) for v in system.factors[f].variables} | set(focused))
    cols = system.columns(used)
    fidx = np.searchsorted(cols, system.columns(focused))
    lms = [v for v in used if system.variables[v].kind == "landmark"]
    lam = (system.information(base) + system.diagonal_prior(lms, landmark_prior_sigma)).toarray()[np.ix_(cols, cols)]
    infos = {c: system.information([c]).toarray()[np.ix_(cols, cols)] for c in candidates}

    def entropy(L):
        cov = np.linalg.inv(L)
        return 0.5 * np.linalg.slogdet(cov[np.ix_(fidx, fidx)])[1]

    picks, gains = [], []
    for _ in range(budget):
        h = entropy(lam)
        best = max(((h - entropy(lam + infos[c]), c) for c in candidates if c not in picks), key=lambda t: t[0])
        picks.append(best[1])
        gains.append(best[0])
        lam = lam + infos[best[1]]
    return picks, np.array(gains)


def _planar(seed: int, n_poses=50, n_lm=8, n_meas=50):
    pp = planar_problem(n_poses, n_lm, n_meas, seed=seed, extent=30.0, sensor_range=12.0)
    system = LinearSystem.from_gtsam(pp.graph, pp.values)
    lms = system.variables_of_kind("landmark")
    return pp, system, lms


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
@pytest.mark.parametrize("refactor_every", [3, 64])
def test_fast_equals_reference_on_random_planar_graphs(seed: int, refactor_every: int) -> None:
    pp, system, lms = _planar(seed)
    focused = lms[:3]
    cand = [f for f in pp.measurement_factors if set(system.factors[f].variables) & set(focused)]
    base = default_base(system, cand)
    budget = min(8, len(cand) - 1)
    fast = select_information(system, cand, focused, budget, base=base, refactor_every=refactor_every)
    picks, gains = reference_greedy(system, cand, focused, budget, base)
    assert fast.picks == picks
    np.testing.assert_allclose(fast.gains, gains, rtol=1e-6, atol=1e-8)
    # the entropy bookkeeping agrees with a fresh computation
    after = focused_entropy(system, base + fast.picks, focused)
    assert fast.entropy_after == pytest.approx(after, abs=1e-6)


def test_fast_equals_reference_all_landmarks_focused() -> None:
    pp, system, lms = _planar(7, n_poses=40, n_lm=6, n_meas=40)
    cand = pp.measurement_factors
    base = default_base(system, cand)
    fast = select_information(system, cand, lms, 10, base=base, refactor_every=4)
    picks, gains = reference_greedy(system, cand, lms, 10, base)
    assert fast.picks == picks
    np.testing.assert_allclose(fast.gains, gains, rtol=1e-6, atol=1e-8)


def _pose_graph(name: str, n_keep: int):
    """A pose graph from slam-graphs: odometry (consecutive) is the base, loop closures the candidates."""
    graph, values = gtsam.load2D(f"{SLAM_GRAPHS}/{name}")
    small = gtsam.NonlinearFactorGraph()
    vals = gtsam.Values()
    for k in range(n_keep):
        vals.insert(k, values.atPose2(k))
    small.add(gtsam.PriorFactorPose2(0, values.atPose2(0), gtsam.noiseModel.Isotropic.Sigma(3, 0.01)))
    for i in range(graph.size()):
        f = graph.at(i)
        keys = f.keys()
        if len(keys) == 2 and max(keys) < n_keep:
            small.add(f)
    system = LinearSystem.from_gtsam(small, vals, is_landmark=lambda k: False)
    odo = [
        i
        for i, f in enumerate(system.factors)
        if len(f.variables) < 2 or abs(system.variables[f.variables[0]].key - system.variables[f.variables[1]].key) == 1
    ]
    loops = [i for i in range(len(system.factors)) if i not in set(odo)]
    return system, odo, loops


@pytest.mark.parametrize(("name", "n_keep"), [("w100.graph", 60), ("w100.graph", 100)])
def test_fast_equals_reference_on_slam_graphs(name: str, n_keep: int) -> None:
    system, odo, loops = _pose_graph(name, n_keep)
    assert len(loops) > 5
    focused = [n_keep - 1, n_keep // 2]  # focus on two poses: W selects their blocks
    budget = min(6, len(loops) - 1)
    fast = select_information(system, loops, focused, budget, base=odo, refactor_every=2)
    picks, gains = reference_greedy(system, loops, focused, budget, odo)
    assert fast.picks == picks
    np.testing.assert_allclose(fast.gains, gains, rtol=1e-6, atol=1e-8)


def test_budget_edge_cases() -> None:
    pp, system, lms = _planar(0)
    cand = [f for f in pp.measurement_factors if set(system.factors[f].variables) & set(lms[:2])]
    zero = select_information(system, cand, lms[:2], 0)
    assert zero.picks == [] and zero.status == "budget_zero"
    assert zero.entropy_after == zero.entropy_before
    over = select_information(system, cand, lms[:2], len(cand) + 5)
    assert sorted(over.picks) == sorted(cand) and over.status == "budget_exceeds_candidates"
    assert over.entropy_after < over.entropy_before
    none = select_information(system, [], lms[:2], 5)
    assert none.status == "no_candidates"
    with pytest.raises(ValueError, match="focused"):
        select_information(system, cand, [], 5)
    for sel in (select_uniform(cand, 0), select_random(cand, 0), select_leverage(system, cand, lms[:2], 0)):
        assert sel.picks == [] and sel.status == "budget_zero"
    for sel in (select_uniform(cand, 99), select_random(cand, 99)):
        assert sorted(sel.picks) == sorted(cand) and sel.status == "budget_exceeds_candidates"


def test_leverage_probabilities_sum_to_one_and_draws_are_seeded() -> None:
    pp, system, lms = _planar(4)
    cand = pp.measurement_factors
    base = default_base(system, cand)
    pi = leverage_probabilities(system, cand, base, lms)
    assert pi.sum() == pytest.approx(1.0, abs=1e-9)
    assert np.all(pi > 0)
    a = select_leverage(system, cand, lms[:3], 10, draws=5, seed=3)
    b = select_leverage(system, cand, lms[:3], 10, draws=5, seed=3)
    assert a.picks == b.picks and len(set(a.picks)) == 10
    greedy = select_information(system, cand, lms[:3], 10)
    # greedy is the best of the strategies on its own objective
    assert greedy.entropy_after <= a.entropy_after + 1e-9


def test_uniform_is_even_in_time() -> None:
    sel = select_uniform(list(range(100, 200)), 5)
    assert sel.picks == [100, 125, 150, 174, 199]


@pytest.mark.parametrize("reduce", [True, False])
@pytest.mark.parametrize("track_focused", [True, False])
def test_fast_equals_reference_through_refactorisations(monkeypatch, track_focused: bool, reduce: bool) -> None:
    """A larger graph (150 poses, 12 landmarks), enough picks for several refactorisations, both ways
    of getting ``Σ Wᵀ p`` (kept at the tracked rows, or a second solve per step), with and without the
    Schur reduction onto the tracked rows."""
    import stages.estimation.measurement_selection as ms

    monkeypatch.setattr(ms, "_TRACKER", "window")  # this test covers the window tracker's paths
    if not track_focused:
        monkeypatch.setattr(ms, "_TRACK_FOCUSED_MAX", 0)
    monkeypatch.setattr(ms, "_REDUCE_BELOW", 1.0 if reduce else 0.0)
    pp = planar_problem(150, 12, 220, seed=11, extent=40.0, sensor_range=12.0)
    system = LinearSystem.from_gtsam(pp.graph, pp.values)
    lms = system.variables_of_kind("landmark")
    assert len(lms) == 12  # the generator measures every landmark
    focused = lms[:3]
    cand = [f for f in pp.measurement_factors if set(system.factors[f].variables) & set(focused)]
    base = default_base(system, cand)
    budget = 14
    fast = select_information(system, cand, focused, budget, base=base, refactor_every=4)
    assert fast.stats["refactorisations"] >= 3
    assert fast.stats["reduced"] == float(reduce)
    picks, gains = reference_greedy(system, cand, focused, budget, base)
    assert fast.picks == picks
    np.testing.assert_allclose(fast.gains, gains, rtol=1e-6, atol=1e-8)
    adaptive = select_information(system, cand, focused, budget, base=base, refactor_every=None)
    assert adaptive.picks == picks
    np.testing.assert_allclose(adaptive.gains, gains, rtol=1e-6, atol=1e-8)


def test_schur_complement_is_the_inverse_of_the_covariance_block() -> None:
    import scipy.sparse as sp

    from stages.estimation.sparse_cov import schur_complement

    rng = np.random.default_rng(1)
    n = 80
    A = sp.random(n, n, density=0.04, random_state=2)
    A = A + A.T + sp.diags(np.full(n, 12.0)) + sp.diags(np.ones(n - 1), 1) + sp.diags(np.ones(n - 1), -1)
    keep = np.sort(rng.choice(n, 25, replace=False))
    S = schur_complement(sp.csc_matrix(A), keep)
    assert S is not None
    ref = np.linalg.inv(np.linalg.inv(A.toarray())[np.ix_(keep, keep)])
    np.testing.assert_allclose(S.toarray(), ref, atol=1e-10)


@pytest.mark.parametrize("first_observation", [False, True])
@pytest.mark.parametrize("case", ["planar", "all_focused", "refactorisations", "w100"])
def test_capacitance_tracker_equals_reference(monkeypatch, case: str, first_observation: bool) -> None:
    """The capacitance-form tracker (two fixed-size solves per step, ``C`` as a bordered Cholesky
    factor) on the cases above, with and without refactorising at a landmark's first observation."""
    import stages.estimation.measurement_selection as ms

    monkeypatch.setattr(ms, "_TRACKER", "capacitance")
    monkeypatch.setattr(ms, "_REFACTOR_ON_FIRST_OBSERVATION", first_observation)
    if case == "planar":
        pp, system, lms = _planar(2)
        focused = lms[:3]
        cand = [f for f in pp.measurement_factors if set(system.factors[f].variables) & set(focused)]
        base, budget, every = default_base(system, cand), min(8, len(cand) - 1), 64
    elif case == "all_focused":
        pp, system, focused = _planar(7, n_poses=40, n_lm=6, n_meas=40)
        cand = pp.measurement_factors
        base, budget, every = default_base(system, cand), 10, 4
    elif case == "refactorisations":
        pp = planar_problem(150, 12, 220, seed=11, extent=40.0, sensor_range=12.0)
        system = LinearSystem.from_gtsam(pp.graph, pp.values)
        focused = system.variables_of_kind("landmark")  # all 12: many first observations in one window
        cand = pp.measurement_factors
        base, budget, every = default_base(system, cand), 24, 64
    else:
        system, base, cand = _pose_graph("w100.graph", 100)
        focused, budget, every = [99, 50], 6, 2
    fast = select_information(system, cand, focused, budget, base=base, refactor_every=every)
    assert fast.stats["capacitance"] == 1.0
    picks, gains = reference_greedy(system, cand, focused, budget, base)
    assert fast.picks == picks
    np.testing.assert_allclose(fast.gains, gains, rtol=1e-6, atol=1e-8)
