"""The risk model's path bracket against the simulated rate, and the entropy split (stages/evaluate/risk_check.py)."""

from __future__ import annotations

import math

import pytest

from stages.evaluate.risk_check import direction, disagrees, entropy_split, predicted_path_probability


def test_the_bracket_is_the_riskiest_keyframe_and_the_capped_union_bound() -> None:
    assert predicted_path_probability([1e-3, 2e-3, float("nan"), 5e-4]) == pytest.approx((2e-3, 3.5e-3))
    assert predicted_path_probability([0.6, 0.7]) == (0.7, 1.0)
    low, high = predicted_path_probability([float("nan")] * 3)  # no laser: no prediction
    assert math.isnan(low) and math.isnan(high)


@pytest.mark.parametrize(
    ("bracket", "interval", "flag", "side"),
    [
        ((2.9e-21, 1e-20), (0.96, 1.0), True, "above"),  # the sample's 2.9e-21 next to a rate of 1.000
        ((1e-3, 5e-3), (0.04, 0.2), False, ""),  # 8x above the union bound: within a factor 10
        ((1e-3, 5e-3), (0.06, 0.2), True, "above"),
        ((0.5, 1.0), (0.0, 0.037), True, "below"),  # 0 of 100 where the model says at least one half
        ((0.3, 1.0), (0.0, 0.037), False, ""),
        ((0.0, 0.0), (0.0, 0.037), False, ""),
    ],
)
def test_a_simulated_rate_more_than_10x_outside_the_bracket_is_flagged(
    bracket: tuple[float, float], interval: tuple[float, float], flag: bool, side: str
) -> None:
    assert disagrees(*bracket, *interval) is flag
    assert direction(*bracket, *interval) == side


def test_without_trials_or_risk_there_is_no_verdict() -> None:
    assert disagrees(1e-3, 1e-2, float("nan"), float("nan")) is None
    assert disagrees(float("nan"), float("nan"), 0.1, 0.2) is None


def test_the_entropy_split_counts_the_unobserved_and_the_priors_part() -> None:
    assert entropy_split(-10.0, -48.0, 5, 3) == (2, 38.0)
    assert entropy_split(-48.0, -48.0, 5, 5) == (0, 0.0)


def test_risk_disagreements_become_warning_lines_the_cli_prints() -> None:
    """A case that collides in every trial where the model predicts ~0 (an hour's corridor with 90 measurements) and
    one that never collides where the model predicts certain collision each give a warning; a consistent case none."""
    from types import SimpleNamespace

    from stages.evaluate import STAGE
    from stages.evaluate.stage import risk_warnings

    def case(name: str, rate: float, lo: float, hi: float, high_pred: float) -> SimpleNamespace:
        row = {"collision_rate": rate, "collision_ci_low": lo, "collision_ci_high": hi, "rms_tracking_error_m": 0.11}
        row |= {"case": name, "predicted_collision_low": high_pred / 10, "predicted_collision_high": high_pred}
        row["risk_disagrees"] = disagrees(high_pred / 10, high_pred, lo, hi)
        return SimpleNamespace(row=row)

    results = [
        case("optimal", 0.0, 0.0, 0.037, 0.0),  # no prediction at all: not comparable
        case("focus_info", 1.0, 0.963, 1.0, 3.6e-14),
        case("full_ds", 0.02, 0.006, 0.07, 0.05),
        case("focus_ds", 0.01, 0.002, 0.054, 1e-19),  # flagged in the report; one collision in 100: no warning
        case("random+random", 0.0, 0.0, 0.005, 1.0),
    ]
    lines = risk_warnings(results)
    assert len(lines) == 2
    assert "more often" in lines[0] and "focus_info" in lines[0]
    assert "full_ds" not in lines[0] and "focus_ds" not in lines[0]
    assert "3.6e-14" in lines[0] and "0.11 m" in lines[0]
    assert "less often" in lines[1] and "random+random" in lines[1]
    remarks = STAGE.remarks({"warnings": [*lines, "case x skipped: why"], "notes": ["n"]})
    assert [label for label, _ in remarks] == ["note", "warning", "warning", "warning"]
    assert risk_warnings(results[2:3]) == []
