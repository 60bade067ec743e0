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

from stages.limits import MAX_GRID_CELLS

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
    free: npt.NDArray[np.bool_] | None = None
    """(rows, cols) cells that beams crossed more than they hit (None: not known, endpoints only)."""
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


def _cells_crossed(u0: FloatArray, u1: FloatArray) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """The cells each segment ``u0 -> u1`` (grid units: cell ``(i, j)`` spans ``[i, i+1) x [j, j+1)``) passes
    through, each once: (segment index, (M, 2) cell), in no particular order.

    An exact grid traversal (as Amanatides-Woo's DDA) for all segments at once, without a loop or a sort: a
    segment's cells are its start cell and, for every vertical or horizontal cell border it crosses, the cell
    it enters there (the border fixes one index, the segment's position at the crossing the other).
    """
    n = len(u0)
    d = u1 - u0
    f0 = np.floor(u0).astype(np.int64)
    steps = np.abs(np.floor(u1).astype(np.int64) - f0)
    seg, cells = [np.arange(n, dtype=np.int64)], [f0]
    for axis in (0, 1):
        other = 1 - axis
        k = steps[:, axis]
        s_ax = np.repeat(np.arange(n, dtype=np.int64), k)
        j = np.arange(len(s_ax), dtype=np.int64) - np.repeat(np.cumsum(k) - k, k)
        forward = d[s_ax, axis] > 0
        border = f0[s_ax, axis] + np.where(forward, j + 1, -j)
        t = (border - u0[s_ax, axis]) / d[s_ax, axis]
        entered = np.empty((len(s_ax), 2), dtype=np.int64)
        entered[:, axis] = np.where(forward, border, border - 1)
        entered[:, other] = np.floor(u0[s_ax, other] + t * d[s_ax, other]).astype(np.int64)
        seg.append(s_ax)
        cells.append(entered)
    return np.concatenate(seg), np.concatenate(cells)


def _add_counts(counter: npt.NDArray[np.int32], flat: npt.NDArray[np.int64]) -> None:
    """Add one to ``counter`` at every index in ``flat`` (a histogram when the grid is small next to the list,
    else scattered adds: no grid-sized temporary for a few beams on a large grid)."""
    if len(counter) <= 4 * len(flat):
        counter += np.bincount(flat, minlength=len(counter)).astype(np.int32)
    else:
        np.add.at(counter, flat, 1)


def ray_cast_grid(
    origins: FloatArray,
    ends: FloatArray,
    hit: npt.ArrayLike,
    resolution: float = 0.05,
    min_hits: int = 2,
    margin_m: float = 1.0,
    log_odds_hit: float = 0.85,
    log_odds_miss: float = -0.4,
    max_cells: int = MAX_GRID_CELLS,
    chunk_cells: int = 500_000,
) -> OccupancyGrid:
    """A log-odds occupancy grid from laser beams, free space carved along every beam.

    Each beam ``origins[k] -> ends[k]`` lowers the log-odds of the cells it crosses by ``log_odds_miss``; a
    beam that ``hit`` raises its end cell by ``log_odds_hit`` and carves only up to one cell short of it (a
    return's own cell and its neighbour along the beam stay with the hits). A beam without a return carves
    its whole length (``range_max``) and marks nothing. A cell is occupied when it has at least
    ``min_hits`` hits and a positive log-odds: a passing return (a moving person, a noisy range) is erased
    by the beams that later see through it, and a door that beams cross stays open.

    Vectorised: the traversal of all beams at once (:func:`_cells_crossed`), in chunks of about
    ``chunk_cells`` crossed cells; the grid itself is refused beyond ``max_cells`` cells (ValueError).
    """
    o = np.asarray(origins, dtype=float).reshape(-1, 2)
    e = np.asarray(ends, dtype=float).reshape(-1, 2)
    h = np.asarray(hit, dtype=bool).reshape(-1)
    ok = np.isfinite(o).all(axis=1) & np.isfinite(e).all(axis=1)
    if not ok.all():  # (an hour's beams are hundreds of MB: no copy when every beam is finite)
        o, e, h = o[ok], e[ok], h[ok]
    del ok
    if not h.any():
        raise ValueError("no laser returns to build an occupancy grid from")
    origin = np.minimum(o.min(axis=0), e.min(axis=0)) - margin_m  # the corners of the origins and ends, not stacked
    size = np.ceil((np.maximum(o.max(axis=0), e.max(axis=0)) + margin_m - origin) / resolution).astype(np.int64) + 1
    if int(size[0]) * int(size[1]) > max_cells:
        raise ValueError(f"a laser grid of {size[0]} x {size[1]} cells is more than {max_cells:.0e}")
    cols = int(size[0])
    n_cells = int(size[0]) * int(size[1])
    u0 = (o - origin) / resolution
    ue = (e - origin) / resolution
    del o, e
    length = np.linalg.norm(ue - u0, axis=1)
    # a return's beam stops one cell short of the return; a beam without one carves all of its length
    keep = np.where(h, np.maximum(length - 1.0, 0.0), length)
    u1 = u0 + (ue - u0) * np.divide(keep, length, out=np.zeros_like(length), where=length > 0)[:, None]
    del keep, length
    hit_cells = np.floor(ue[h]).astype(np.int64)
    del ue
    hits = np.zeros(n_cells, dtype=np.int32)
    misses = np.zeros(n_cells, dtype=np.int32)
    _add_counts(hits, hit_cells[:, 1] * cols + hit_cells[:, 0])
    del hit_cells
    # the cells each beam crosses, an axis at a time (the sum of two terms, as over the rows of an (N, 2) array)
    cost = np.abs(np.floor(u1[:, 0]) - np.floor(u0[:, 0]))
    cost += np.abs(np.floor(u1[:, 1]) - np.floor(u0[:, 1]))
    cost += 1
    np.cumsum(cost, out=cost)
    start = 0
    while start < len(u0):
        stop = max(int(np.searchsorted(cost, cost[start] - 1 + chunk_cells, side="right")), start + 1)
        _, cells = _cells_crossed(u0[start:stop], u1[start:stop])
        _add_counts(misses, cells[:, 1] * cols + cells[:, 0])
        start = stop
    log_odds = hits.astype(np.float32)
    log_odds *= np.float32(log_odds_hit)
    log_odds += misses * np.float32(log_odds_miss)
    del misses
    shape = (int(size[1]), cols)
    occupied = (hits >= min_hits) & (log_odds > 0)
    return OccupancyGrid(occupied.reshape(shape), origin, float(resolution), free=(log_odds < 0).reshape(shape))
