"""Laser scans in the map frame, each beam placed at the robot's pose when it was measured (deskew).

A planar scanner sweeps its beams one after the other: ROS's ``LaserScan`` stamps the first beam, and beam
``i`` is measured at ``stamp + i * time_increment``. While the robot turns at 0.6 rad/s a 0.1 s sweep turns
the last beam 3.4° away from where a single pose at the stamp puts it: 0.47 m at 8 m. :func:`scan_beams`
puts every beam at the trajectory interpolated on SE(2) to the beam's own time
(:func:`stages.geometry.interpolate_planar`), so the obstacles of the collision risk (eq. 20,
:mod:`stages.risk`) and the navigation's occupancy grid (:func:`stages.navigation.walls.ray_cast_grid`)
come from the same returns.

Which ranges count (REP 117): finite with ``range_min <= r < range_max`` is a return (an obstacle at
``r``); ``+inf`` or ``r >= range_max`` is "nothing within range" (free space up to ``range_max``, no
obstacle); NaN, ``-inf`` and ``r < range_min`` say nothing and are dropped.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from itertools import pairwise
from typing import cast

import numpy as np
import numpy.typing as npt
import pyarrow as pa
import pyarrow.compute as pc

from stages.columns import STAMP_NS
from stages.geometry import interpolate_planar
from stages.ingest.artifacts import ANGLE_INCREMENT, ANGLE_MIN, RANGE_MAX, RANGE_MIN, RANGES, TIME_INCREMENT
from stages.limits import MAX_SCAN_SWEEP_S

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True)
class Beams:
    """Laser beams in the map frame (rows are beams, grouped by scan in the order asked for)."""

    scan: IntArray
    """(N,) which of the requested scans each beam belongs to (0-based position in ``rows``)."""
    origins: FloatArray
    """(N, 2) the laser's position when the beam was measured."""
    ends: FloatArray
    """(N, 2) the return's position, or for a beam without one the point at ``range_max``."""
    hit: npt.NDArray[np.bool_]
    """(N,) the beam returned from an obstacle at ``ends`` (False: free up to ``range_max``)."""

    def __len__(self) -> int:
        return len(self.scan)

    def returns(self) -> FloatArray:
        """(M, 2) the obstacle points (the ends of the beams that hit)."""
        return np.asarray(self.ends[self.hit])


def planar_mount(T_base_laser: npt.ArrayLike | None) -> FloatArray:
    """(x, y, yaw) of the laser in the base frame from a 4x4 (identity when None)."""
    if T_base_laser is None:
        return np.zeros(3)
    T = np.asarray(T_base_laser, dtype=float).reshape(4, 4)
    return np.array([T[0, 3], T[1, 3], float(np.arctan2(T[1, 0], T[0, 0]))])


def scan_beams(
    scans: pa.Table,
    stamps_ns: npt.ArrayLike,
    poses: npt.ArrayLike,
    T_base_laser: npt.ArrayLike | None,
    rows: Sequence[int] | npt.ArrayLike | None = None,
    deskew: bool = True,
) -> Beams:
    """The beams of ``scans`` (ingest's ``scans.parquet``) in the map frame.

    Args:
        scans: the scans table (``stamp_ns``, angles, ranges, ``time_increment``).
        stamps_ns: (T,) increasing stamps of the trajectory.
        poses: (T, 3) the base's (x, y, yaw) in the map frame at ``stamps_ns``.
        T_base_laser: 4x4 laser mount in the base frame (identity when None).
        rows: which scans, in this order (default all).
        deskew: place beam ``i`` at the pose of ``stamp + i * time_increment`` (False: every beam at the
            stamp's pose, as a scanner with ``time_increment = 0``).
    """
    idx = np.arange(scans.num_rows) if rows is None else np.asarray(rows, dtype=np.int64).reshape(-1)
    sub = scans.take(pa.array(idx, type=pa.int64())).select(
        [STAMP_NS, ANGLE_MIN, ANGLE_INCREMENT, TIME_INCREMENT, RANGE_MIN, RANGE_MAX, RANGES]
    )
    traj = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
    P = np.asarray(poses, dtype=float).reshape(-1, 3)
    mount = planar_mount(T_base_laser)
    counts = np.asarray(pc.list_value_length(sub.column(RANGES)).fill_null(0).to_numpy(), dtype=np.int64)
    # scans in pieces of about CHUNK_BEAMS beams: every beam's arithmetic is its own, so the pieces give the
    # same numbers as one pass, and the temporaries stay a few MB whatever the recording's length
    ends_at = np.cumsum(counts)
    cuts = [0]
    while cuts[-1] < len(idx):
        nxt = int(np.searchsorted(ends_at, ends_at[cuts[-1]] - counts[cuts[-1]] + CHUNK_BEAMS, side="right"))
        cuts.append(min(max(nxt, cuts[-1] + 1), len(idx)))
    parts = [_chunk_beams(sub.slice(a, b - a), a, traj, P, mount, deskew) for a, b in pairwise(cuts)]
    if not parts:
        return Beams(np.zeros(0, dtype=np.int64), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, dtype=bool))
    # joined field by field, each field's pieces freed once joined: the pieces and the whole are not held together
    pieces = [list(field) for field in zip(*((b.scan, b.origins, b.ends, b.hit) for b in parts), strict=True)]
    del parts
    joined = []
    for field in pieces:
        joined.append(np.concatenate(field))
        field.clear()
    return Beams(*joined)


CHUNK_BEAMS = 1 << 16
"""Beams placed at once by :func:`scan_beams` (a piece's temporaries: about 100 bytes per beam)."""


def _chunk_beams(
    sub: pa.Table, first: int, traj: npt.NDArray[np.int64], poses: FloatArray, mount: FloatArray, deskew: bool
) -> Beams:
    """:func:`scan_beams` of the scans in ``sub``, which start at position ``first`` of the requested scans."""
    ranges_col = cast(pa.ListArray, sub.column(RANGES).combine_chunks())
    counts = np.asarray(pc.list_value_length(ranges_col).fill_null(0).to_numpy(), dtype=np.int64)
    r = np.asarray(ranges_col.flatten().to_numpy(zero_copy_only=False), dtype=np.float64)
    scan = np.repeat(np.arange(first, first + sub.num_rows, dtype=np.int64), counts)
    beam = np.arange(len(r), dtype=np.int64) - np.repeat(np.cumsum(counts) - counts, counts)

    def per_beam(col: str) -> FloatArray:
        return np.repeat(np.asarray(sub.column(col).to_numpy(), dtype=np.float64), counts)

    r_min, r_max = per_beam(RANGE_MIN), per_beam(RANGE_MAX)
    with np.errstate(invalid="ignore"):
        hit = np.isfinite(r) & (r >= r_min) & (r < r_max)
        free = ~hit & ((r == np.inf) | (np.isfinite(r) & (r >= r_max)))
    keep = hit | free
    scan, beam, r, hit = scan[keep], beam[keep], np.where(hit, r, r_max)[keep], hit[keep]
    stamp = np.repeat(np.asarray(sub.column(STAMP_NS).to_numpy(), dtype=np.int64), counts)[keep]
    angle = per_beam(ANGLE_MIN)[keep] + per_beam(ANGLE_INCREMENT)[keep] * beam
    ref = int(traj[0]) if len(traj) else 0
    t = (stamp - ref).astype(float)  # ns from the trajectory's start: exact in float64
    if deskew:
        inc = np.asarray(sub.column(TIME_INCREMENT).to_numpy(), dtype=float)
        sane = np.isfinite(inc) & (np.abs(inc) * np.maximum(counts - 1, 0) <= MAX_SCAN_SWEEP_S)
        t = t + np.repeat(np.where(sane, inc, 0.0), counts)[keep] * beam * 1e9
    base = interpolate_planar((traj - ref).astype(float), poses, t)
    mx, my, myaw = mount
    c, s = np.cos(base[:, 2]), np.sin(base[:, 2])
    origins = np.column_stack([base[:, 0] + c * mx - s * my, base[:, 1] + s * mx + c * my])
    heading = base[:, 2] + myaw + angle
    ends = origins + r[:, None] * np.column_stack([np.cos(heading), np.sin(heading)])
    return Beams(scan, origins, ends, hit)
