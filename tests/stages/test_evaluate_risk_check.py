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
