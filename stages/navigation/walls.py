"""The obstacles a simulated robot can hit: wall segments (ground truth) or an occupancy grid from laser scans.

Both expose ``distance(points) -> (N,)``: the distance (m) from each planar point to the nearest
obstacle. A robot of radius ``r`` collides when that distance falls below ``r``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import numpy.typing as npt
from scipy import ndimage

FloatArray = npt.NDArray[np.float64]


class Obstacles(Protocol):
    """Anything with a distance-to-nearest-obstacle query."""

    @property
    def kind(self) -> str:
        """What the obstacles are (e.g. ``ground_truth`` walls or walls rebuilt from the ``laser``)."""
        ...

    def distance(self, points: FloatArray) -> FloatArray:
        """Distance (m) from each (N, 2) point to the nearest obstacle."""
        ...


def distance_to_segments(points: FloatArray, segments: FloatArray) -> FloatArray:
    """Euclidean distance from each (N, 2) point to the nearest of the (W, 4) segments."""
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    a = segments[:, :2]
    e = segments[:, 2:] - a
    rel = pts[:, None, :] - a[None, :, :]
    u = np.clip((rel * e).sum(-1) / np.maximum((e * e).sum(-1), 1e-18), 0.0, 1.0)
    closest = a[None] + u[..., None] * e[None]
    return np.asarray(np.linalg.norm(pts[:, None, :] - closest, axis=-1).min(axis=1))


@dataclass(frozen=True)
class SegmentWalls:
    """Walls as line segments (the simulator's ground truth, brought into the map frame)."""

    segments: FloatArray
    kind: str = "ground_truth"

    def distance(self, points: FloatArray) -> FloatArray:
        """Distance to the nearest segment."""
        return distance_to_segments(points, self.segments)


@dataclass
class OccupancyGrid:
    """Cells hit by laser returns; distances from a Euclidean distance transform of the free cells."""

    occupied: npt.NDArray[np.bool_]
    """(rows, cols), row = y index, col = x index."""
    origin: FloatArray
    """(x, y) of the lower-left corner of cell (0, 0), m."""
    resolution: float
    kind: str = "laser_grid"
    distance_field: FloatArray = field(init=False, repr=False)
    """Distance (m) from each cell centre to the nearest occupied cell centre."""

    def __post_init__(self) -> None:
        occ = self.occupied
        self.distance_field = (
            np.asarray(ndimage.distance_transform_edt(~occ), dtype=float) * self.resolution
            if occ.any()
            else np.full(occ.shape, np.inf)
        )

    def distance(self, points: FloatArray) -> FloatArray:
        """Distance of the cell under each point (points outside the grid take the nearest border cell)."""
        pts = np.asarray(points, dtype=float).reshape(-1, 2)
        ij = np.floor((pts - self.origin) / self.resolution).astype(np.int64)
        rows, cols = self.occupied.shape
        c = np.clip(ij[:, 0], 0, cols - 1)
        r = np.clip(ij[:, 1], 0, rows - 1)
        return np.asarray(self.distance_field[r, c])

    def points(self) -> FloatArray:
        """Centres of the occupied cells, (M, 2)."""
        r, c = np.nonzero(self.occupied)
        return np.column_stack([c + 0.5, r + 0.5]) * self.resolution + self.origin


def scan_endpoints(
    T_map_laser: FloatArray,
    ranges: FloatArray,
    angle_min: float,
    angle_increment: float,
    range_min: float,
    range_max: float,
) -> FloatArray:
    """Map-frame (M, 2) endpoints of the valid returns of one scan (``T_map_laser`` is a 3x3 planar transform)."""
    r = np.asarray(ranges, dtype=float)
    a = angle_min + angle_increment * np.arange(len(r))
    ok = np.isfinite(r) & (r > range_min) & (r < range_max * 0.999)
    local = np.column_stack([r[ok] * np.cos(a[ok]), r[ok] * np.sin(a[ok])])
    return np.asarray(local @ T_map_laser[:2, :2].T + T_map_laser[:2, 2])


def occupancy_grid(
    endpoints: FloatArray, resolution: float = 0.05, min_hits: int = 2, margin_m: float = 1.0
) -> OccupancyGrid:
    """Cells with at least ``min_hits`` laser endpoints (isolated noisy returns are dropped)."""
    pts = np.asarray(endpoints, dtype=float).reshape(-1, 2)
    if len(pts) == 0:
        raise ValueError("no laser returns to build an occupancy grid from")
    origin = pts.min(axis=0) - margin_m
    size = np.ceil((pts.max(axis=0) + margin_m - origin) / resolution).astype(int) + 1
    ij = np.floor((pts - origin) / resolution).astype(np.int64)
    counts = np.zeros((size[1], size[0]), dtype=np.int64)
    np.add.at(counts, (ij[:, 1], ij[:, 0]), 1)
    return OccupancyGrid(counts >= min_hits, origin, float(resolution))
