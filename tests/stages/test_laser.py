"""Laser scans in the map frame: SE(2) interpolation, deskew of a swept scan, the ray-cast occupancy grid."""

from __future__ import annotations

import gtsam
import numpy as np
import pyarrow as pa
import pytest

from sample_data.simulate import (
    SimConfig,
    build_trajectory,
    build_world,
    distance_to_walls,
    laser_scan,
    mount_transforms,
)
from stages.geometry import interpolate_planar, interpolate_pose2
from stages.ingest.artifacts import SCANS
from stages.ingest.convert import scan_row
from stages.laser import scan_beams
from stages.navigation import SegmentWalls, occupancy_grid, ray_cast_grid
from stages.navigation.walls import _cells_crossed
from stages.risk import scan_clearance


def test_interpolate_planar_is_gtsams_geodesic() -> None:
    stamps = np.array([0, 10, 20, 30])
    poses = np.array([[0.0, 0.0, 0.3], [1.0, 0.5, 2.0], [1.2, 0.4, -2.9], [1.2, 0.4, -2.9]])
    query = np.array([-5, 0, 3, 10, 15, 19, 25, 40])
    got = interpolate_planar(stamps, poses, query)
    for q, g in zip(query, got, strict=True):
        i = int(np.clip(np.searchsorted(stamps, q, side="right"), 1, 3))
        alpha = float(np.clip((q - stamps[i - 1]) / (stamps[i] - stamps[i - 1]), 0, 1))
        ref = interpolate_pose2(gtsam.Pose2(*poses[i - 1]), gtsam.Pose2(*poses[i]), alpha)
        np.testing.assert_allclose(g[:2], [ref.x(), ref.y()], atol=1e-12)
        assert np.cos(g[2] - ref.theta()) == pytest.approx(1.0, abs=1e-12)
    # an arc of constant twist is reproduced exactly from its ends (a chord would cut the corner)
    w, v = 1.2, 0.5
    arc = np.array([[v / w * np.sin(w * t), v / w * (1 - np.cos(w * t)), w * t] for t in (0.0, 1.0)])
    mid = interpolate_planar([0.0, 1.0], arc, [0.5])[0]
    np.testing.assert_allclose(mid, [v / w * np.sin(0.6), v / w * (1 - np.cos(0.6)), 0.6], atol=1e-12)


def _clips(u0: np.ndarray, u1: np.ndarray, cell: tuple[int, int]) -> bool:
    """Whether the segment u0 -> u1 meets the closed cell (slab test)."""
    lo, hi = 0.0, 1.0
    for ax in (0, 1):
        d = u1[ax] - u0[ax]
        if d == 0:
            if not cell[ax] <= u0[ax] <= cell[ax] + 1:
                return False
            continue
        t0, t1 = sorted(((cell[ax] - u0[ax]) / d, (cell[ax] + 1 - u0[ax]) / d))
        lo, hi = max(lo, t0), min(hi, t1)
    return lo <= hi + 1e-12


def test_cells_crossed_is_an_exact_traversal() -> None:
    rng = np.random.default_rng(0)
    u0, u1 = rng.uniform(0, 20, (200, 2)), rng.uniform(0, 20, (200, 2))
    u1[:10, 0] = u0[:10, 0]  # vertical
    u1[10:20] = u0[10:20]  # a point
    seg, cells = _cells_crossed(u0, u1)
    for k in range(200):
        got = [(int(c[0]), int(c[1])) for c in cells[seg == k]]
        # every cell a fine walk along the segment visits (a corner it clips for less than the walk's step may
        # be missing from the walk) ...
        p = np.floor(u0[k] + np.linspace(0, 1, 20001)[:, None] * (u1[k] - u0[k])).astype(int)
        assert {(int(a), int(b)) for a, b in p} <= set(got)
        # ... each once, and only cells the segment meets: one for the start and one per border crossed
        assert len(set(got)) == len(got) and all(_clips(u0[k], u1[k], c) for c in got)
        crossed = np.abs(np.floor(u1[k]) - np.floor(u0[k])).sum()
        assert len(got) == 1 + crossed


def _scans_of(messages: list) -> pa.Table:
    rows = [scan_row(m, m.header.stamp_ns) for m in messages]
    return pa.Table.from_pylist(rows, schema=SCANS.schema)


@pytest.mark.parametrize(("path", "t_s"), [("office", 8.0), ("corridor_return", 29.0)])
def test_deskew_puts_a_swept_scan_on_the_walls(path: str, t_s: float) -> None:
    """Scans swept while the robot turns (office corner, 0.5 rad/s; turn in place, 0.6 rad/s), from the
    simulator's geometry: deskewed beams land on the true walls within the range noise, beams placed at the
    stamp's pose do not."""
    cfg = SimConfig(path=path, laser_sweep=True)
    world, traj = build_world(cfg), build_trajectory(cfg)
    rng = np.random.default_rng(1)
    stamps = [cfg.start_time_ns + round((t_s + 0.1 * k) * 1e9) for k in range(5)]
    msgs = [laser_scan(cfg, world.walls, traj, s, rng) for s in stamps]
    assert msgs[0].time_increment * cfg.laser_beams == pytest.approx(0.1)
    scans = _scans_of(msgs)
    # the trajectory as a SLAM back end gives it: poses at 20 Hz (odometry / keyframes)
    traj_ns = np.arange(stamps[0] - 10**8, stamps[-1] + 2 * 10**8, 5 * 10**7)
    x, y, yaw, _, w = traj.sample((traj_ns - cfg.start_time_ns) * 1e-9)
    assert np.abs(w).max() > 0.45  # it turns
    _, T_bl = mount_transforms(cfg)
    err = {}
    for deskew in (True, False):
        beams = scan_beams(scans, traj_ns, np.column_stack([x, y, yaw]), T_bl, deskew=deskew)
        err[deskew] = distance_to_walls(beams.returns(), world.walls)
    assert len(err[True]) > 1000
    sigma = cfg.laser_range_sigma_m
    assert np.percentile(err[True], 99) < 3 * sigma  # on the walls within the range noise
    assert np.percentile(err[False], 99) > 8 * sigma  # off the walls by up to 0.1-0.34 m
    assert err[False].mean() > 3 * err[True].mean()


def test_damaged_time_increment_is_ignored() -> None:
    cfg = SimConfig(path="corridor_return", laser_sweep=True)
    world, traj = build_world(cfg), build_trajectory(cfg)
    stamp = cfg.start_time_ns + 29 * 10**9
    scans = _scans_of([laser_scan(cfg, world.walls, traj, stamp, np.random.default_rng(0))])
    traj_ns = np.arange(stamp - 10**9, stamp + 10**9, 5 * 10**7)
    poses = np.column_stack(traj.sample((traj_ns - cfg.start_time_ns) * 1e-9)[:3])
    _, T_bl = mount_transforms(cfg)
    still = scan_beams(scans, traj_ns, poses, T_bl, deskew=False)
    for bad in (float("nan"), 1.0, float("inf")):  # a 360 s sweep, not a scanner
        damaged = scans.set_column(scans.schema.get_field_index("time_increment"), "time_increment", pa.array([bad]))
        np.testing.assert_array_equal(scan_beams(damaged, traj_ns, poses, T_bl).ends, still.ends)


def _room_with_door() -> SegmentWalls:
    """A 6 x 4 m room whose east wall has a 0.9 m door into the open."""
    return SegmentWalls(
        np.array(
            [[0, 0, 6, 0], [6, 0, 6, 1.55], [6, 2.45, 6, 4], [6, 4, 0, 4], [0, 4, 0, 0], [6, 1.55, 6.1, 1.55]],
            dtype=float,
        )
    )


def _ray_cast(walls: SegmentWalls, poses: np.ndarray, range_max: float = 8.0, sigma: float = 0.01):
    """Beams of 360-beam scans from ``poses`` against ``walls`` (exact hits plus noise, +inf beyond range)."""
    from sample_data.simulate import ray_segment_hits

    rng = np.random.default_rng(2)
    o, e, h = [], [], []
    a = np.linspace(-np.pi, np.pi, 360, endpoint=False)
    for x, y, yaw in poses:
        dirs = np.column_stack([np.cos(a + yaw), np.sin(a + yaw)])
        t, _, _ = ray_segment_hits(np.array([x, y]), dirs, walls.segments)
        hit = t < range_max
        r = np.where(hit, t + sigma * rng.standard_normal(len(t)), range_max)
        o.append(np.tile([x, y], (len(a), 1)))
        e.append(np.array([x, y]) + r[:, None] * dirs)
        h.append(hit)
    return np.vstack(o), np.vstack(e), np.concatenate(h)


def test_ray_cast_grid_carves_free_space_and_keeps_the_walls() -> None:
    walls = _room_with_door()
    t = np.linspace(0, 1, 60)
    poses = np.column_stack([1.0 + 4.0 * t, 2.0 + 0.8 * np.sin(6 * t), 0.5 * t])  # a pass along the room
    o, e, h = _ray_cast(walls, poses)
    grid = ray_cast_grid(o, e, h, resolution=0.05, min_hits=2)
    assert grid.free is not None
    # walls occupied: points on the walls are within a cell of an occupied cell
    on_walls = np.vstack([np.linspace(s[:2], s[2:], 50) for s in walls.segments[:5]])
    assert np.percentile(grid.distance(on_walls), 95) < 0.08
    # every occupied cell is on a wall
    assert walls.distance(grid.points()).max() < 0.08
    # the cells the beams crossed are free: the room's inside, well away from the walls
    inside = np.column_stack(
        [np.random.default_rng(3).uniform(0.3, 5.7, 500), np.random.default_rng(4).uniform(0.3, 3.7, 500)]
    )
    ij = np.floor((inside - grid.origin) / grid.resolution).astype(int)
    assert grid.free[ij[:, 1], ij[:, 0]].mean() > 0.99
    # the door stays open: its centre is as far from the grid's obstacles as from the true walls
    door = np.array([[6.0, 2.0]])
    assert grid.distance(door)[0] == pytest.approx(walls.distance(door)[0], abs=0.06)
    # beams through the door without a return carve the outside but mark nothing there
    outside = np.array([[7.0, 2.0], [8.0, 2.0]])
    ij = np.floor((outside - grid.origin) / grid.resolution).astype(int)
    assert grid.free[ij[:, 1], ij[:, 0]].all()
    assert (grid.points()[:, 0] < 6.2).all()


def test_ray_cast_grid_erases_a_passing_obstacle_that_endpoints_keep() -> None:
    """Returns from something that was in the door for a moment (a person) are seen through afterwards:
    the ray-cast grid reopens the door, an endpoint-count grid keeps it shut."""
    walls = _room_with_door()
    blocked = SegmentWalls(np.vstack([walls.segments, [[6.0, 1.55, 6.0, 2.45]]]))
    poses = np.column_stack([np.linspace(1, 5, 40), np.full(40, 2.0), np.zeros(40)])
    o1, e1, h1 = _ray_cast(blocked, poses[:8])
    o2, e2, h2 = _ray_cast(walls, poses[8:])
    o, e, h = np.vstack([o1, o2]), np.vstack([e1, e2]), np.concatenate([h1, h2])
    door = np.array([[6.0, 2.0]])
    assert occupancy_grid(e[h], 0.05, 2).distance(door)[0] < 0.05
    assert ray_cast_grid(o, e, h, 0.05, 2).distance(door)[0] > 0.4


def test_ray_cast_grid_refuses_a_grid_beyond_the_limit() -> None:
    o = np.zeros((2, 2))
    e = np.array([[1e3, 0.0], [0.0, 1e3]])
    with pytest.raises(ValueError, match="cells"):
        ray_cast_grid(o, e, [True, True], resolution=0.01, max_cells=10**6)


def test_eq20_obstacles_are_the_deskewed_returns() -> None:
    """Alg. 2's nearest return per keyframe (risk.scan_clearance) from scans swept while the robot turns at an
    office corner: on the true walls, at the true clearance. (Unswept, the nearest return moves by up to
    r * w * 0.1 s, a few cm at these ranges: the grid's far returns are where the sweep matters.)"""
    cfg = SimConfig(path="office", laser_sweep=True)
    world, traj = build_world(cfg), build_trajectory(cfg)
    rng = np.random.default_rng(5)
    scan_ns = [cfg.start_time_ns + round((6.5 + 0.1 * k) * 1e9) for k in range(20)]
    scans = _scans_of([laser_scan(cfg, world.walls, traj, s, rng) for s in scan_ns])
    key_ns = np.array(scan_ns[:-1]) + 5 * 10**7  # keyframes half a sweep after each scan's first beam
    poses = np.column_stack(traj.sample((key_ns - cfg.start_time_ns) * 1e-9)[:3])
    _, T_bl = mount_transforms(cfg)
    clearance, normals, points = scan_clearance(poses, key_ns, scans, T_bl, max_gap_s=0.06)
    assert np.isfinite(clearance).all()
    true_clearance = distance_to_walls(poses[:, :2], world.walls)
    assert np.abs(clearance - true_clearance).max() < 0.04  # the nearest of many noisy returns: biased by ~-2 sigma
    assert distance_to_walls(points, world.walls).max() < 0.04
    np.testing.assert_allclose(points, poses[:, :2] + clearance[:, None] * normals, atol=1e-9)


def test_beams_and_clearance_in_pieces_are_the_same_numbers(monkeypatch: pytest.MonkeyPatch) -> None:
    """scan_beams and scan_clearance work a piece of the scans at a time (memory bounded on long recordings): any
    piece size gives the same beams and clearances, bit for bit, as one piece, including a scan larger than a
    piece and keyframes sharing a scan."""
    import stages.laser
    import stages.risk

    cfg = SimConfig(path="office", laser_sweep=True)
    world, traj = build_world(cfg), build_trajectory(cfg)
    rng = np.random.default_rng(7)
    scan_ns = [cfg.start_time_ns + round((6.0 + 0.1 * k) * 1e9) for k in range(23)]
    scans = _scans_of([laser_scan(cfg, world.walls, traj, s, rng) for s in scan_ns])
    key_ns = np.sort(np.r_[np.array(scan_ns) + 3 * 10**7, np.array(scan_ns[::4]) + 4 * 10**7])
    poses = np.column_stack(traj.sample((key_ns - cfg.start_time_ns) * 1e-9)[:3])
    _, T_bl = mount_transforms(cfg)
    rows = [5, 2, 2, 17, 9, 0, 22]
    whole = scan_beams(scans, key_ns, poses, T_bl, rows)
    clear = scan_clearance(poses, key_ns, scans, T_bl, max_gap_s=0.06)
    assert len(whole) > 1000 and np.isfinite(clear[0]).all()
    for beams, scans_at_once in ((cfg.laser_beams // 3, 1), (cfg.laser_beams + 1, 4), (5 * cfg.laser_beams, 7)):
        monkeypatch.setattr(stages.laser, "CHUNK_BEAMS", beams)
        monkeypatch.setattr(stages.risk, "CLEARANCE_SCANS", scans_at_once)
        part = scan_beams(scans, key_ns, poses, T_bl, rows)
        for field in ("scan", "origins", "ends", "hit"):
            np.testing.assert_array_equal(getattr(part, field), getattr(whole, field))
        for a, b in zip(scan_clearance(poses, key_ns, scans, T_bl, max_gap_s=0.06), clear, strict=True):
            np.testing.assert_array_equal(a, b)
    empty = scan_beams(scans, key_ns, poses, T_bl, [])
    assert empty.origins.shape == (0, 2) and empty.hit.dtype == bool
