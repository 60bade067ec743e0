"""Riccati steady state, collision probability, MI greedy vs brute force, leverage, Alg. 2."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from stages.estimation.collision import (
    collision_risk,
    measurement_information,
    planar_range_bearing,
    select_collision,
    stabilised_covariances,
)
from stages.estimation.landmark_selection import (
    landmark_leverage_probabilities,
    select_landmark_leverage,
    select_landmark_random,
    select_landmark_uniform,
    select_mutual_information,
)
from tests.fixtures.planar_problems import random_mi_problem
from tests.oracles.collision import (
    halfplane_collision_probability,
    riccati_iterate,
    riccati_steady_state,
    select_collision_reference,
    stabilised_covariance,
)
from tests.oracles.mutual_information import brute_force_mutual_information, mutual_information

Q = np.diag([0.02, 0.02, 0.005]) ** 2


SIGMAS = (0.02, 0.1)


def _visible_at_pose():
    pose = np.array([1.0, 2.0, 0.3])
    lms = np.array([[4.0, 3.0], [2.0, -1.0]])
    covs = np.stack([0.01 * np.eye(2), 0.04 * np.eye(2)])
    HR = [planar_range_bearing(pose, lms[i], covs[i], SIGMAS) for i in range(2)]
    return pose, lms, covs, HR


def test_riccati_equals_iteration_and_ekf_converges() -> None:
    """Σ* by doubling (production) is the fixed point of eq. 19: DARE, the iterated recursion and an EKF agree."""
    pose, lms, covs, HR = _visible_at_pose()
    H = np.vstack([h for h, _ in HR])
    R = np.block([[HR[0][1], np.zeros((2, 2))], [np.zeros((2, 2)), HR[1][1]]])
    star = stabilised_covariances(Q, measurement_information(pose, lms, covs, SIGMAS)[None], 50)[0]
    np.testing.assert_allclose(star, riccati_steady_state(np.eye(3), Q, H, R), rtol=1e-10)
    np.testing.assert_allclose(star, stabilised_covariance(Q, HR), rtol=1e-10)
    np.testing.assert_allclose(riccati_iterate(np.eye(3), Q, H, R, np.eye(3), 2000), star, rtol=1e-6, atol=1e-12)
    # an EKF held at the pose: predict with Q, update with the landmarks; its prior covariance converges to Σ*
    P = 4.0 * np.eye(3)
    for _ in range(500):
        P = P + Q
        K = P @ H.T @ np.linalg.inv(H @ P @ H.T + R)
        P_post = (np.eye(3) - K @ H) @ P
        P = P_post
    np.testing.assert_allclose(P + Q, star, rtol=1e-6, atol=1e-12)


def test_halfplane_probability_matches_monte_carlo_against_laser_points() -> None:
    rng = np.random.default_rng(0)
    cov = np.array([[0.04, 0.01], [0.01, 0.02]])
    # a wall of laser returns at x = 0.3 (a line of points): the robot collides when it passes it
    wall = np.column_stack([np.full(200, 0.3), np.linspace(-5, 5, 200)])
    n = np.array([1.0, 0.0])
    d = float(np.min(wall @ n))
    p = halfplane_collision_probability(cov, n, d)
    assert collision_risk(cov[None], np.array([d]), n[None], [0, 1])[0] == pytest.approx(p, rel=1e-12)
    x = rng.multivariate_normal(np.zeros(2), cov, size=200_000)
    crossed = x[:, 0] >= wall[:, 0].min()
    mc = crossed.mean()
    se = np.sqrt(p * (1 - p) / len(x))
    assert abs(mc - p) < 4 * se
    assert 0.05 < p < 0.1


def test_mi_greedy_near_brute_force_and_lazy_equals_plain() -> None:
    rng = np.random.default_rng(1)
    ratios = []
    for _ in range(25):
        info0, contrib = random_mi_problem(rng)
        lazy = select_mutual_information(info0, contrib, 5, lazy=True)
        plain = select_mutual_information(info0, contrib, 5, lazy=False)
        assert lazy.picks == plain.picks
        np.testing.assert_allclose(lazy.scores, plain.scores, rtol=1e-9)
        value = mutual_information(info0, contrib, lazy.picks)
        assert value == pytest.approx(sum(lazy.scores), rel=1e-8)
        opt, _ = brute_force_mutual_information(info0, contrib, 5)
        ratios.append(value / opt)
    ratios = np.array(ratios)
    print(f"MI greedy / brute force over {len(ratios)} problems: mean {ratios.mean():.4f}, min {ratios.min():.4f}")
    assert ratios.min() >= 1 - 1 / np.e
    assert ratios.mean() > 0.95


def test_landmark_leverage_probabilities_sum_to_one() -> None:
    info0, contrib = random_mi_problem(np.random.default_rng(2))
    pi = landmark_leverage_probabilities(info0, contrib)
    assert pi.sum() == pytest.approx(1.0, abs=1e-9)
    sel = select_landmark_leverage(info0, contrib, 5, draws=10, seed=4)
    assert sel.picks == select_landmark_leverage(info0, contrib, 5, draws=10, seed=4).picks
    assert len(set(sel.picks)) == 5


def _corridor():
    """A straight path past a narrow door at x = 10 with landmarks along it."""
    T = 41
    poses = np.column_stack([np.linspace(0, 20, T), np.zeros(T), np.zeros(T)])
    landmarks = np.array([[2.0, 2.0], [6.0, -2.0], [10.0, 1.5], [14.0, -2.0], [18.0, 2.0], [10.0, -1.5]])
    covs = np.stack([0.01 * np.eye(2)] * len(landmarks))
    dist = np.linalg.norm(poses[:, None, :2] - landmarks[None], axis=2)
    visible = dist < 5.0
    clearance = np.where(np.abs(poses[:, 0] - 10) < 1.5, 0.25, 2.0)
    normals = np.tile([0.0, 1.0], (T, 1))
    return poses, landmarks, covs, visible, clearance, normals


def test_collision_greedy_picks_the_door_landmarks_first() -> None:
    poses, landmarks, covs, visible, clearance, normals = _corridor()
    sel = select_collision(poses, landmarks, covs, visible, clearance, normals, Q, 2, SIGMAS, 50)
    door = np.flatnonzero(clearance < 1.0)
    assert visible[door, sel.picks[0]].any()  # the first pick serves the probabilistically narrow door
    assert sel.extra["risk_after"].max() < sel.extra["risk_before"].max()
    assert sel.scores == sorted(sel.scores, reverse=True)
    uni = select_landmark_uniform(landmarks, 2)
    rnd = select_landmark_random(len(landmarks), 2, seed=0)
    assert len(uni.picks) == 2 and len(rnd.picks) == 2


def test_landmark_budget_edge_cases() -> None:
    poses, landmarks, covs, visible, clearance, normals = _corridor()
    assert select_collision(poses, landmarks, covs, visible, clearance, normals, Q, 0, SIGMAS, 50).status == (
        "budget_zero"
    )
    over = select_collision(poses, landmarks, covs, visible, clearance, normals, Q, 99, SIGMAS, 50)
    assert over.status == "budget_exceeds_landmarks" and sorted(over.picks) == list(range(6))
    none = select_collision(poses, landmarks[:0], covs[:0], visible[:, :0], clearance, normals, Q, 3, SIGMAS, 50)
    assert none.status == "no_landmarks" and none.picks == []
    info0, contrib = random_mi_problem(np.random.default_rng(0), L=4)
    assert select_mutual_information(info0, contrib, 0).picks == []
    assert sorted(select_mutual_information(info0, contrib, 9).picks) == [0, 1, 2, 3]


@pytest.mark.parametrize("budget", [1, 3, 6, 9])
def test_alg2_equals_the_reference_on_the_corridor(budget: int) -> None:
    """Production Alg. 2 (batched doubling Σ*) picks and scores as the per-pose DARE reference does."""
    poses, landmarks, covs, visible, clearance, normals = _corridor()
    landmarks[5] = [10.7, -1.9]  # no mirror image of landmark 2: no exact tie for the two Σ* solvers to break
    covs[3] *= 4.0
    visible[30:, 4] = False  # a landmark seen from fewer poses, so picks differ in their re-solved poses
    fast = select_collision(poses, landmarks, covs, visible, clearance, normals, Q, budget, SIGMAS, 50)
    ref = select_collision_reference(poses, landmarks, covs, visible, clearance, normals, Q, budget, SIGMAS, 50)
    assert fast.picks == ref.picks and fast.status == ref.status
    np.testing.assert_allclose(fast.scores, ref.scores, rtol=1e-8)
    np.testing.assert_allclose(fast.extra["risk_after"], ref.extra["risk_after"], rtol=1e-8, atol=1e-300)


def _dense_leverage_probabilities(info0, contrib):
    lam = info0.copy()
    for cols, B in contrib:
        lam[np.ix_(cols, cols)] += B
    Sigma = np.linalg.inv(lam)
    base = float(np.trace(Sigma @ info0)) / len(contrib)
    return np.array([base + float(np.sum(Sigma[np.ix_(c, c)] * B)) for c, B in contrib]) / info0.shape[0]


@pytest.mark.parametrize("backend", ["selected", "dense", "sparse"])
@pytest.mark.parametrize("min_block", [1, 96])
def test_sparse_leverage_and_mi_equal_the_dense_formulas(backend, min_block) -> None:
    """The level-block selected inverse gives the dense inverse's numbers (probabilities, draw measures, MI gains).

    ``min_block = 1``: many blocks (one per BFS level); 96: the whole 36-dimensional problem in one block.
    """
    from stages.estimation.landmark_selection import _measure, _measure_information, _scatter

    info0, contrib = random_mi_problem(np.random.default_rng(3), T=12, L=20)
    np.testing.assert_allclose(
        landmark_leverage_probabilities(info0, contrib, min_block),
        _dense_leverage_probabilities(info0, contrib),
        rtol=1e-9,
    )
    lam = info0 + _scatter(info0.shape[0], contrib[:6]).toarray()
    for measure in ("logdet", "trace", "max_eig"):
        dense = _measure(np.linalg.inv(lam), measure)
        assert _measure_information(sp.csc_matrix(lam), measure, min_block=min_block) == pytest.approx(dense, rel=1e-8)
    sel = select_mutual_information(info0, contrib, 6, backend=backend, min_block=min_block)
    assert mutual_information(info0, contrib, sel.picks) == pytest.approx(sum(sel.scores), rel=1e-9)
    assert select_mutual_information(sp.csc_matrix(info0), contrib, 6, backend=backend, min_block=min_block).picks == (
        sel.picks
    )
    ref = select_mutual_information(info0, contrib, 6, backend="dense")
    assert ref.picks == sel.picks
    np.testing.assert_allclose(ref.scores, sel.scores, rtol=1e-9)


@pytest.mark.parametrize("min_block", [1, 4, 10_000])
def test_level_blocks_selected_inverse_on_the_pattern(min_block) -> None:
    """Σ on every nonzero of the pattern and log det, against the dense inverse: a chain with landmarks tying far-apart
    poses (loop closures), a second disconnected chain, and a landmark whose support is not contiguous."""
    from stages.estimation.landmark_selection import _LevelBlocks, _scatter

    rng = np.random.default_rng(7)
    info0, contrib = random_mi_problem(rng, T=30, L=25)
    n = info0.shape[0]
    big = np.zeros((n + 9, n + 9))  # + a separate 3-pose chain (another connected component)
    big[:n, :n] = info0
    for t in range(3):
        idx = np.arange(n + 3 * t, n + 3 * t + 3)
        big[np.ix_(idx, idx)] += (2.0 + t) * np.eye(3)
    far = np.r_[np.arange(0, 3), np.arange(n - 3, n)]  # first and last pose
    J = rng.normal(size=(4, 6))
    contrib.append((far, J.T @ J))
    lam = sp.csc_matrix(big) + _scatter(n + 9, contrib)
    blocks = _LevelBlocks(lam, min_block)
    D, C = blocks.store(lam)
    inv = blocks.factor(D, C)
    dense = np.linalg.inv(lam.toarray())
    coo = sp.coo_matrix(lam)
    np.testing.assert_allclose(
        inv.entries(coo.row.astype(np.int64), coo.col.astype(np.int64)), dense[coo.row, coo.col], rtol=1e-9, atol=1e-14
    )
    np.testing.assert_allclose(inv.block(far), dense[np.ix_(far, far)], rtol=1e-9, atol=1e-14)
    assert inv.logdet == pytest.approx(np.linalg.slogdet(lam.toarray())[1], rel=1e-12)
    assert blocks.logdet(D, C) == pytest.approx(inv.logdet, rel=1e-12)
    assert inv.trace() == pytest.approx(np.trace(dense), rel=1e-10)
    # probabilities with the far-apart support: still the dense formula, still summing to 1
    pi = landmark_leverage_probabilities(big, contrib)
    np.testing.assert_allclose(pi, _dense_leverage_probabilities(big, contrib), rtol=1e-9)
    assert pi.sum() == pytest.approx(1.0, abs=1e-12)
