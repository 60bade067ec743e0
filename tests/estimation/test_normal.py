"""stages.estimation.normal gives scipy.stats.norm's values bit for bit (it replaces it to save the import)."""

from __future__ import annotations

import numpy as np
from scipy.stats import norm

from stages.estimation.normal import normal_logsf, normal_ppf, normal_sf


def test_tail_and_quantile_equal_scipy_stats_bit_for_bit() -> None:
    x = np.concatenate([np.linspace(-45.0, 45.0, 20001), [np.inf, -np.inf, np.nan, 0.0, -0.0, 1e-300, -1e-300]])
    np.testing.assert_array_equal(normal_sf(x), norm.sf(x))
    np.testing.assert_array_equal(normal_logsf(x), norm.logsf(x))
    q = np.concatenate([np.linspace(0.0, 1.0, 10001), [1e-300, 1.0 - 1e-16, np.nan]])
    np.testing.assert_array_equal(normal_ppf(q), norm.ppf(q))
    assert float(normal_ppf(0.975)) == float(norm.ppf(0.975)) and float(normal_sf(3.0)) == float(norm.sf(3.0))
