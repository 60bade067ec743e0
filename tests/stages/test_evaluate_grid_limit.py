"""The laser grid's size is checked before it is allocated (1 µm cells once asked for 883 TiB)."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.errors import ConfigError
from stages.evaluate.cases import _check_grid_size
from stages.limits import MAX_GRID_CELLS


def test_an_office_at_the_default_resolution_fits() -> None:
    _check_grid_size(np.array([[0.0, 0.0], [40.0, 30.0]]), 0.05)


def test_a_grid_too_fine_for_the_area_names_the_key_and_a_resolution_that_fits() -> None:
    endpoints = np.array([[0.0, 0.0], [40.0, 30.0], [np.inf, 0.0]])
    with pytest.raises(ConfigError, match=r"evaluate\.grid_resolution_m=0\.001 .* set it to ([0-9.]+) m") as info:
        _check_grid_size(endpoints, 1e-3)
    suggested = float(str(info.value).rsplit("set it to ", 1)[1].split(" m")[0])
    _check_grid_size(endpoints, suggested)  # the suggestion fits
    span = np.array([42.0, 32.0])
    assert np.prod(np.ceil(span / (0.9 * suggested)) + 1) > MAX_GRID_CELLS / 2  # and is not far too coarse


def test_origins_and_ends_given_apart_are_checked_as_if_stacked() -> None:
    """The beams' origins and ends are checked without stacking them (hundreds of MB on an hour's scans): the same
    message, non-finite rows of either left out."""
    origins = np.array([[0.0, 0.0], [np.nan, 1.0], [10.0, 5.0]])
    ends = np.array([[40.0, 30.0], [np.inf, 0.0], [-2.0, 3.0]])
    messages = []
    for endpoints in (np.vstack([origins, ends]), (origins, ends)):
        with pytest.raises(ConfigError) as info:
            _check_grid_size(endpoints, 1e-3)
        messages.append(str(info.value))
    assert messages[0] == messages[1]
    _check_grid_size((origins, ends[:0]), 0.05)  # an empty part
