"""A reduced map further off than its own covariance allows gets a warning line (issue 34 item 6: a 4-camera rig's
headline said `focused error 82.5 cm` and nothing else); an honest map, however large its error, does not."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from stages.evaluate import artifacts as art
from stages.evaluate.analysis import OVERCONFIDENCE_FALSE_ALARM, overconfidence
from stages.evaluate.stage import overconfidence_warnings

N = 30


def _map(seed: int, sigma_m: float, stated_sigma_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """N landmarks off the reference by errors of ``sigma_m`` per axis, stating a σ of ``stated_sigma_m``."""
    rng = np.random.default_rng(seed)
    ids = np.arange(N)
    truth = rng.uniform(-10, 10, size=(N, 2))
    covs = np.tile(np.eye(2) * stated_sigma_m**2, (N, 1, 1))
    positions = truth + rng.normal(0.0, sigma_m, size=(N, 2))
    return ids, positions, covs, dict(zip(ids.tolist(), truth, strict=True))


def test_an_honest_map_passes_and_an_overconfident_one_fails() -> None:
    ids, pos, covs, ref = _map(0, 0.5, 0.5)  # large errors, and says so
    honest = overconfidence(ids, pos, covs, ref, ids)
    assert honest.count == N and honest.fails is False
    assert honest.limit == -2 * np.log(OVERCONFIDENCE_FALSE_ALARM / N)
    ids, pos, covs, ref = _map(0, 0.5, 0.05)  # the same errors stated ten times smaller
    over = overconfidence(ids, pos, covs, ref, ids)
    assert over.fails is True and over.sigmas > np.sqrt(over.limit)
    assert over.error_m / over.sigma_m == pytest.approx(np.sqrt(over.nees))
    # only the focused landmarks count, and none tested is no verdict
    assert overconfidence(ids, pos, covs, ref, []).fails is None


def test_a_right_covariance_is_flagged_as_rarely_as_the_test_size_says() -> None:
    flagged = sum(bool(overconfidence(*_map(seed, 0.2, 0.2), range(N)).fails) for seed in range(400))
    assert flagged <= 3  # expected at most 0.4 at p = 0.001; the test is Bonferroni's, so below that


def _result(name: str, measurements: int, check: Any, error_m: float = 0.825) -> SimpleNamespace:
    row = {
        art.CASE: name,
        art.LABEL: name,
        art.MEASUREMENTS: measurements,
        art.FOCUSED_ERROR_M: error_m,
        art.ERROR_REFERENCE: "optimal",
    }
    return SimpleNamespace(case=SimpleNamespace(name=name), overconfidence=check, row=row)


def _inputs(kinds: list[str], K: int = 90) -> SimpleNamespace:
    return SimpleNamespace(loaded=SimpleNamespace(rows=[SimpleNamespace(kind=k) for k in kinds]), K=K)


def test_the_warning_names_the_camera_only_cause_and_the_budget_that_holds() -> None:
    ids, pos, covs, ref = _map(1, 0.5, 0.05)
    bad = overconfidence(ids, pos, covs, ref, ids)
    good = overconfidence(*_map(1, 0.02, 0.02), ids)
    results = [
        _result("optimal", 3000, None, 0.0),
        _result("focus_all", 1600, good, 0.01),
        _result("focus_info", 90, bad),
        _result("focus_ds", 90, bad),
    ]
    camera_only = _inputs(["motion_prior", "tag", "tag"])
    (line,) = overconfidence_warnings(camera_only, results)  # type: ignore[arg-type]
    assert "focused error 82.5 cm" in line and "far worse than its own covariance" in line
    assert "camera-only run (no odometry)" in line and "K = 90" in line
    assert "raise select_measurements.budget" in line and "towards 1600" in line
    with_odometry = overconfidence_warnings(_inputs(["odometry", "tag"]), results)  # type: ignore[arg-type]
    assert len(with_odometry) == 1 and "camera-only" not in with_odometry[0]


def test_an_honest_reduced_map_gets_no_warning() -> None:
    ids, pos, covs, ref = _map(1, 0.8, 0.8)  # 80 cm off, and its covariance says so
    honest = overconfidence(ids, pos, covs, ref, ids)
    results = [_result("optimal", 3000, None, 0.0), _result("focus_info", 90, honest)]
    assert overconfidence_warnings(_inputs(["motion_prior", "tag"]), results) == []  # type: ignore[arg-type]


def test_measurements_noisier_than_stated_are_named_instead_of_the_budget() -> None:
    """The full graph's tag χ² per dof says the stated variance is that many times too small: when that factor
    explains the reduced map's worst NEES, the line blames the measurement model, not K."""
    ids, pos, covs, ref = _map(1, 0.5, 0.05)  # 100x in variance
    bad = overconfidence(ids, pos, covs, ref, ids)
    results = [_result("optimal", 3000, None, 0.0), _result("focus_info", 90, bad)]
    camera_only = _inputs(["motion_prior", "tag"])
    (line,) = overconfidence_warnings(camera_only, results, tag_variance=100.0)  # type: ignore[arg-type]
    assert "stated noise, 10x too small" in line and "graph.tag_covariance_scale" in line
    assert "camera-only" not in line
    (line,) = overconfidence_warnings(camera_only, results, tag_variance=1.2)  # type: ignore[arg-type]
    assert "camera-only run" in line  # a variance factor near 1 does not explain 10x


def test_the_variance_factor_is_the_graph_health_checks_tag_chi2() -> None:
    from stages.evaluate.stage import tag_variance_factor

    chi2 = {"by_kind": {"tag": {"chi2_per_dof": 6827.0}, "motion_prior": {"chi2_per_dof": 0.16}}}
    assert tag_variance_factor({"health": {"checks": {"chi2": chi2}}}) == 6827.0
    assert tag_variance_factor({}) is None  # an imported graph's summary, or an older one
    nan_tag = {"by_kind": {"tag": {"chi2_per_dof": float("nan")}}}
    assert tag_variance_factor({"health": {"checks": {"chi2": nan_tag}}}) is None
