"""Physical bounds of the settings: values beyond them are typing errors, not robots.

Every settings model rejects infinite and NaN numbers (:class:`pipeline.config.SettingsModel`); these
bound the fields where a huge but finite value still broke a stage (a time that overflows nanoseconds,
an information 1/sigma^2 that underflows to zero, a grid of terabytes).
"""

from __future__ import annotations

from typing import Final

MAX_SIGMA_M: Final = 1e3
"""Largest standard deviation in metres (priors, noise floors): 1 km is already "unknown" for any map
here; 1e300 made an information of 0 and a singular graph."""

MAX_TAG_SIZE_M: Final = 5.0
"""Largest printed tag edge, metres (an infinite size aborted Ceres inside the pose solver)."""

MAX_BAG_SECONDS: Final = 1e7
"""Largest time from the bag start, seconds (~116 days; 1e300 overflowed the nanosecond timestamps)."""

MIN_GRID_RESOLUTION_M: Final = 1e-3
"""Smallest occupancy-grid cell, metres (1 µm asked for 883 TiB)."""

MAX_SCAN_SWEEP_S: Final = 1.0
"""Longest sweep of one laser scan, seconds (scanners sweep in 1/5-1/50 s): a ``time_increment`` that spans
more, or is not finite, is damaged, and that scan's beams are all placed at its stamp."""

MAX_GRID_CELLS: Final = 100_000_000
"""Largest occupancy grid, cells (~1 GB of counts): a ~500 m square at the default 5 cm."""

MAX_RATE_SIGMA: Final = 1e3
"""Largest actuation noise of the simulated robot, m/s or rad/s (1e300 overflowed the noise draws)."""

MAX_TRIALS: Final = 100_000
"""Most Monte Carlo navigation trials per case (a billion asked for more than 23 GB and the kernel killed the
process); 1e5 trials resolve a collision rate of 1e-5."""

MAX_ROBOT_RADIUS_M: Final = 100.0
"""Largest robot footprint radius, metres (1e300 overflowed the collision risk's Mahalanobis distance)."""
