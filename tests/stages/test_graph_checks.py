"""The graph's input checks (stages/graph/solve.py check_problem): a bad row anywhere is named, the first one first,
whether the rows are checked one at a time or all of a shape at once."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pipeline.errors import StageError
from stages.graph.solve import check_problem
from tests.fixtures.synthetic_runs import synthetic_planar_problem


def _with(problem, changes: dict[int, dict]):
    rows = list(problem.rows)
    for i, fields in changes.items():
        rows[i] = dataclasses.replace(rows[i], **fields)
    return dataclasses.replace(problem, rows=rows)


@pytest.fixture(scope="module")
def problem():
    return synthetic_planar_problem(60, 6, 80, seed=1, tag_scale_sigma=0.005)


def test_a_fine_problem_passes(problem) -> None:
    check_problem(problem)


def test_each_bad_row_is_named_and_the_first_one_first(problem) -> None:
    tag = next(i for i, r in enumerate(problem.rows) if r.kind == "tag")
    odo = next(i for i, r in enumerate(problem.rows) if r.kind == "odometry")
    nan = np.array(problem.rows[tag].measurement, dtype=float)
    nan[1] = np.nan
    not_pd = -np.eye(3)
    unknown = (*problem.rows[odo + 5].keys[:1], 987654321)
    cases = [
        ({tag: {"measurement": nan}}, f"factor {tag} (tag", "NaN or infinite"),
        ({odo: {"covariance": not_pd}}, f"factor {odo} (odometry", "not positive definite"),
        ({odo + 5: {"keys": unknown}}, f"factor {odo + 5} (odometry", "no initial value"),
        # two bad rows: the first in row order is the one named
        ({tag: {"measurement": nan}, odo: {"covariance": not_pd}}, f"factor {min(tag, odo)} ", ""),
    ]
    for changes, label, why in cases:
        with pytest.raises(StageError) as err:
            check_problem(_with(problem, changes))
        assert str(err.value).startswith(label) and why in str(err.value), str(err.value)
