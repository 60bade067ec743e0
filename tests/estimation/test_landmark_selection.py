"""The robot's belief along a path, collision probability, MI greedy vs brute force, leverage, Alg. 2."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from stages.estimation.collision import (
    StepNoise,
    collision_risk,
    forward_covariances,
    margin_sigmas,
    measurement_information,
    pair_information,
    planar_range_bearing,
    select_collision,
)
from stages.estimation.landmark_selection import (
    landmark_leverage_probabilities,
    select_landmark_leverage,
    select_landmark_random,
    select_landmark_uniform,
    select_mutual_information,
)
from stages.estimation.robot import RobotModel, resample_path
from tests.fixtures.planar_problems import random_mi_problem
from tests.oracles.collision import (
    belief_reference,
    halfplane_collision_probability,
    riccati_iterate,
    riccati_steady_state,
    select_collision_reference,
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


def test_belief_held_still_converges_to_the_riccati_steady_state() -> None:
    """A robot held still (A = I) that keeps measuring the same landmarks: the belief recursion (information form,
    production) converges to eq. 19's Σ* (DARE), the posterior of its fixed point."""
    pose, lms, covs, HR = _visible_at_pose()
    H = np.vstack([h for h, _ in HR])
    R = np.block([[HR[0][1], np.zeros((2, 2))], [np.zeros((2, 2)), HR[1][1]]])
    K = 600
    noise = StepNoise(np.repeat(np.eye(3)[None], K - 1, axis=0), np.repeat(Q[None], K - 1, axis=0), 4.0 * np.eye(3))
    J = np.repeat(measurement_information(pose, lms, covs, SIGMAS)[None, None], K, axis=1)
    P = forward_covariances(noise, J)[0]
    star = riccati_steady_state(np.eye(3), Q, H, R)  # the predicted (prior) covariance of the fixed point
    np.testing.assert_allclose(P[-2] + Q, star, rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(riccati_iterate(np.eye(3), Q, H, R, np.eye(3), 2000), star, rtol=1e-6, atol=1e-12)


def _path_problem(seed: int, K: int = 60, L: int = 6):
    """A curving path resampled by the robot model, landmarks beside it, random visibility runs, walls."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 20, 41)
    poses = np.column_stack([t, 2.0 * np.sin(t / 5.0), np.arctan2(0.4 * np.cos(t / 5.0), 1.0)])
    steps = resample_path((t * 1e9).astype(np.int64), poses, 20.0 / (K - 1))
    robot = RobotModel(speed_sigma_mps=0.05, yaw_rate_sigma_radps=0.03)
    A, Qs = steps.transition(robot)
    noise = StepNoise(A, Qs, robot.P0)
    K = len(steps)
    lms = np.column_stack([rng.uniform(0, 20, L), rng.choice([-1.5, 3.5], L)])
    covs = np.stack([np.diag(rng.uniform(0.0005, 0.01, 2)) for _ in range(L)])
    visible = np.zeros((K, L), dtype=bool)
    for c in range(L):
        for _ in range(2):
            k0 = int(rng.integers(0, K - 8))
            visible[k0 : k0 + int(rng.integers(2, 8)), c] = True
    margin = np.where(rng.random(K) < 0.3, rng.uniform(0.05, 0.4, K), np.inf)
    normals = np.tile([0.0, 1.0], (K, 1))
    return steps, noise, robot, lms, covs, visible, margin, normals


def _contributions(steps, robot, lms, covs, visible):
    from stages.risk import _run_lengths

    out = []
    for c in range(len(lms)):
        ks = np.flatnonzero(visible[:, c])
        inflated = covs[c][None] * _run_lengths(ks)[:, None, None]
        out.append((ks, pair_information(steps.poses[ks], np.repeat(lms[c][None], len(ks), 0), inflated, robot.sigmas)))
    return out


def test_belief_along_a_path_equals_a_kalman_filter() -> None:
    """The batched information-form recursion equals a Kalman filter run step by step in the gain form, with the
    unicycle's A (heading coupled to position) and process noise, for several landmark sets at once."""
    steps, noise, robot, lms, covs, visible, _, _ = _path_problem(3)
    K = len(steps)
    sets = [[], [0], [1, 3], list(range(len(lms)))]
    J = np.zeros((len(sets), K, 3, 3))
    meas_all = []
    for b, chosen in enumerate(sets):
        meas = [[] for _ in range(K)]
        for c in chosen:
            for k in np.flatnonzero(visible[:, c]):
                H, Rb = planar_range_bearing(steps.poses[k], lms[c], covs[c], robot.sigmas)
                meas[k].append((H, Rb))
                J[b, k] += H.T @ np.linalg.solve(Rb, H)
        meas_all.append(meas)
    P = forward_covariances(noise, J)
    for b in range(len(sets)):
        ref = belief_reference(noise.A, noise.Q, noise.P0, meas_all[b])
        np.testing.assert_allclose(P[b], ref, rtol=1e-8, atol=1e-14)
    # dead reckoning grows without a cap, and heading error turns into cross-track error
    assert np.all(np.diff(P[0][:, 1, 1]) > 0) and P[0][-1, 1, 1] > 10 * P[0][1, 1, 1]


def test_adding_a_landmark_never_raises_any_steps_risk() -> None:
    """Monotone: more information never widens the belief (the issue's saturating Alg. 2 could raise a pose's risk
    by adding a landmark, since a localised pose ignored its path neighbours)."""
    steps, noise, robot, lms, covs, visible, margin, normals = _path_problem(5)
    contrib = _contributions(steps, robot, lms, covs, visible)
    K = len(steps)
    J = np.zeros((1, K, 3, 3))
    z_prev = margin_sigmas(forward_covariances(noise, J)[0], margin, normals)
    for ks, info in contrib:
        np.add.at(J[0], ks, info)
        z = margin_sigmas(forward_covariances(noise, J)[0], margin, normals)
        fin = np.isfinite(z)
        assert np.all(z[fin] >= z_prev[fin] - 1e-9)
        z_prev = z


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
    """A straight path past a narrow door at x = 10 with landmarks along it (a step every 0.5 m)."""
    K = 41
    poses = np.column_stack([np.linspace(0, 20, K), np.zeros(K), np.zeros(K)])
    steps = resample_path((np.arange(K) * 1e9).astype(np.int64), poses, 1.0)
    robot = RobotModel(speed_sigma_mps=0.02, yaw_rate_sigma_radps=0.01, bearing_sigma_rad=0.02, range_sigma_m=0.1)
    A, Qs = steps.transition(robot)
    noise = StepNoise(A, Qs, robot.P0)
    landmarks = np.array([[2.0, 2.0], [6.0, -2.0], [10.0, 1.5], [14.0, -2.0], [18.0, 2.0], [10.0, -1.5]])
    covs = np.stack([0.01 * np.eye(2)] * len(landmarks))
    dist = np.linalg.norm(poses[:, None, :2] - landmarks[None], axis=2)
    visible = dist < 5.0
    margin = np.where(np.abs(poses[:, 0] - 10) < 1.5, 0.25, 2.0)
    normals = np.tile([0.0, 1.0], (K, 1))
    return steps, noise, robot, landmarks, covs, visible, margin, normals


def test_collision_greedy_picks_the_door_landmarks_first() -> None:
    steps, noise, robot, landmarks, covs, visible, margin, normals = _corridor()
    contrib = _contributions(steps, robot, landmarks, covs, visible)
    sel = select_collision(noise, contrib, margin, normals, 2)
    door = np.flatnonzero(margin < 1.0)
    assert visible[door, sel.picks[0]].any()  # the first pick serves the probabilistically narrow door
    assert sel.extra["risk_after"].max() < sel.extra["risk_before"].max()
    assert sel.scores == sorted(sel.scores, reverse=True)
    uni = select_landmark_uniform(landmarks, 2)
    rnd = select_landmark_random(len(landmarks), 2, seed=0)
    assert len(uni.picks) == 2 and len(rnd.picks) == 2


def test_landmark_budget_edge_cases() -> None:
    steps, noise, robot, landmarks, covs, visible, margin, normals = _corridor()
    contrib = _contributions(steps, robot, landmarks, covs, visible)
    assert select_collision(noise, contrib, margin, normals, 0).status == "budget_zero"
    over = select_collision(noise, contrib, margin, normals, 99)
    assert over.status == "budget_exceeds_landmarks" and sorted(over.picks) == list(range(6))
    none = select_collision(noise, [], margin, normals, 3)
    assert none.status == "no_landmarks" and none.picks == []
    info0, contrib_mi = random_mi_problem(np.random.default_rng(0), L=4)
    assert select_mutual_information(info0, contrib_mi, 0).picks == []
    assert sorted(select_mutual_information(info0, contrib_mi, 9).picks) == [0, 1, 2, 3]


@pytest.mark.parametrize("budget", [1, 3, 6, 9])
def test_alg2_equals_the_reference_on_the_corridor(budget: int) -> None:
    """Production Alg. 2 (batched information-form belief) picks and scores as the one-candidate-at-a-time Kalman
    reference does."""
    steps, noise, robot, landmarks, covs, visible, margin, normals = _corridor()
    landmarks[5] = [10.7, -1.9]  # no mirror image of landmark 2: no exact tie for the two solvers to break
    covs[3] *= 4.0
    visible[30:, 4] = False
    contrib = _contributions(steps, robot, landmarks, covs, visible)
    fast = select_collision(noise, contrib, margin, normals, budget)
    ref = select_collision_reference(
        noise.A, noise.Q, noise.P0, steps.poses, landmarks, covs, visible, margin, normals, budget, robot.sigmas
    )
    assert fast.picks == ref.picks and fast.status == ref.status
    np.testing.assert_allclose(fast.scores, ref.scores, rtol=1e-6, atol=1e-300)
    np.testing.assert_allclose(fast.extra["z_after"], ref.extra["z_after"], rtol=1e-6)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_alg2_equals_the_reference_on_random_curved_paths(seed: int) -> None:
    steps, noise, robot, lms, covs, visible, margin, normals = _path_problem(seed)
    contrib = _contributions(steps, robot, lms, covs, visible)
    fast = select_collision(noise, contrib, margin, normals, 4)
    ref = select_collision_reference(
        noise.A, noise.Q, noise.P0, steps.poses, lms, covs, visible, margin, normals, 4, robot.sigmas
    )
    assert fast.picks == ref.picks
    np.testing.assert_allclose(fast.extra["z_after"], ref.extra["z_after"], rtol=1e-6)


def test_alg2_still_chooses_where_the_collision_probability_underflows() -> None:
    """Far from walls every P is 0.0 in floating point; the margin in σ still tells the candidates apart, so the
    greedy picks the landmark that helps the riskiest step most, not the first index (the saturation found)."""
    steps, noise, robot, landmarks, covs, visible, margin, normals = _corridor()
    wide = np.where(np.isfinite(margin), margin * 100.0, margin)
    contrib = _contributions(steps, robot, landmarks, covs, visible)
    sel = select_collision(noise, contrib, wide, normals, 3)
    assert sel.extra["risk_before"].max() == 0.0  # every probability underflows
    narrow = select_collision(noise, contrib, margin, normals, 3)
    assert sel.picks == narrow.picks  # scaling every margin does not change which landmark helps most
    assert sel.picks[0] != 0


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
def test_level_blocks_selected_inverse_on_the_pattern(min_block, monkeypatch) -> None:
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
    # the flat store placed a few entries at a time (as large matrices are) is the store placed at once
    monkeypatch.setattr(_LevelBlocks, "STORE_CHUNK", 5)
    D5, C5 = blocks.store(lam)
    assert lam.nnz > 50
    np.testing.assert_array_equal(D5, D)
    np.testing.assert_array_equal(C5, C)
    # probabilities with the far-apart support: still the dense formula, still summing to 1
    pi = landmark_leverage_probabilities(big, contrib)
    np.testing.assert_allclose(pi, _dense_leverage_probabilities(big, contrib), rtol=1e-9)
    assert pi.sum() == pytest.approx(1.0, abs=1e-12)
