"""The why-analysis of evaluate (consistency against the truth, rigid alignment, margin) and the seed summary."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from stages.evaluate.analysis import (
    NavigationMargin,
    aligned_error,
    landmark_consistency,
    predicted_bearing_range,
)
from stages.evaluate.seeds import report


def test_aligned_error_removes_a_rigid_motion_only() -> None:
    rng = np.random.default_rng(0)
    truth = rng.uniform(-5, 5, size=(12, 2))
    c, s = np.cos(0.3), np.sin(0.3)
    moved = truth @ np.array([[c, -s], [s, c]]).T + [0.4, -0.2]
    ids = np.arange(12)
    ref = dict(enumerate(truth))
    assert aligned_error(ids, moved, ref, ids) == pytest.approx(0.0, abs=1e-12)
    noisy = moved + rng.normal(scale=0.01, size=moved.shape)
    assert 0.003 < aligned_error(ids, noisy, ref, ids) < 0.02
    assert np.isnan(aligned_error(ids[:2], moved[:2], ref, ids[:2]))


def test_landmark_nees_is_two_for_consistent_maps_and_grows_with_a_bias() -> None:
    rng = np.random.default_rng(1)
    n = 4000
    covs = np.array([np.diag(rng.uniform(0.01, 0.05, 2) ** 2) for _ in range(n)])
    err = np.array([rng.multivariate_normal(np.zeros(2), C) for C in covs])
    truth = rng.uniform(-5, 5, size=(n, 2))
    ids = np.arange(n)
    ok = landmark_consistency(ids, truth + err, covs, dict(enumerate(truth)))
    assert ok.mean_nees == pytest.approx(2.0, rel=0.08) and ok.share_outside_95 == pytest.approx(0.05, abs=0.015)
    biased = landmark_consistency(ids, truth + err + [0.05, 0.0], covs, dict(enumerate(truth)))
    assert biased.mean_nees > 4 and biased.mean_error_m > ok.mean_error_m


def test_bearing_range_and_margin_summary() -> None:
    np.testing.assert_allclose(predicted_bearing_range(np.array([1.0, 1.0, np.pi / 2]), np.array([1.0, 3.0])), [0, 2])
    m = NavigationMargin(np.array([1.0, 0.2, 0.5]), np.array([0.1, 0.05, 0.5]), np.array([0.01, 0.02, 0.03]))
    s = m.summary()
    assert s["margin_sigmas"] == pytest.approx(1.0) and s["tight_margin_m"] == 0.5 and s["min_margin_m"] == 0.2


def test_seed_summary_counts_wins(tmp_path) -> None:
    def write(name: str, info: float, ds: float) -> None:
        rows = {
            "case": ["focus_info", "focus_ds"],
            "label": ["focus, info", "focus, DS"],
            "focused_entropy": [info, ds],
            "collision_rate": [0.0, 0.1],
        }
        pq.write_table(pa.table(rows), tmp_path / f"{name}.parquet")

    write("s1", -10.0, -5.0)
    write("s2", -3.0, -5.0)
    md = report([tmp_path / "s1.parquet", tmp_path / "s2.parquet"])
    assert "mean ± sd over 2 runs" in md and "-6.5 ± 4.9" in md
    head = next(x for x in md.splitlines() if x.startswith("| focus_info lower than |"))
    line = next(x for x in md.splitlines() if x.startswith("| focus_ds |"))
    cells = dict(zip([c.strip() for c in head.split("|")], [c.strip() for c in line.split("|")], strict=True))
    assert cells["focused_entropy"] == "1/2" and cells["collision_rate"] == "2/2"
    assert cells["max_collision_probability"] == "0/0"  # not in these tables


def test_rigid_alignment_recovers_the_motion() -> None:
    from stages.evaluate.analysis import rigid_alignment

    rng = np.random.default_rng(2)
    truth = rng.uniform(-5, 5, size=(8, 2))
    c, s = np.cos(-0.2), np.sin(-0.2)
    R0 = np.array([[c, -s], [s, c]])
    est = (truth - [1.0, 2.0]) @ R0  # truth = R0 est + [1, 2]
    fit = rigid_alignment(np.arange(8), est, dict(enumerate(truth)))
    assert fit is not None
    np.testing.assert_allclose(fit[0], R0, atol=1e-12)
    np.testing.assert_allclose(est @ fit[0].T + fit[1], truth, atol=1e-12)
    assert rigid_alignment(np.arange(2), est[:2], dict(enumerate(truth))) is None


def test_seed_summary_names_a_missing_run_in_one_line(tmp_path, capsys) -> None:
    from stages.evaluate.seeds import main

    assert main([str(tmp_path / "no_such_run")]) == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "no_such_run/evaluate/cases.parquet does not exist" in err
