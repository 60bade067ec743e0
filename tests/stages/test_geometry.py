"""The one angle wrap."""

from __future__ import annotations

import numpy as np

from stages.geometry import wrap_angle


def test_wrap_angle_lands_in_the_half_open_interval_and_keeps_the_direction() -> None:
    a = np.linspace(-20.0, 20.0, 4001)
    w = np.asarray(wrap_angle(a))
    assert np.all(w >= -np.pi) and np.all(w < np.pi)
    np.testing.assert_allclose(np.cos(w), np.cos(a), atol=1e-12)
    np.testing.assert_allclose(np.sin(w), np.sin(a), atol=1e-12)
    assert float(wrap_angle(np.pi)) == -np.pi
    assert float(wrap_angle(0.25)) == 0.25
