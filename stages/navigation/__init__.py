"""Simulated navigation on a landmark map (Mu et al. 2015, Sec. V) and what it needs.

Public API:
    nominal_path(stamps_ns, poses, dt_s) -> NominalPath: the recorded path resampled, with controls.
    lqr_gains(path, Wx, Wu) -> (K-1, 2, 3): finite-horizon LQR along the path (eq. 27).
    visibility_schedule(step_stamps_ns, obs_stamps_ns, obs_ids, window_s): landmarks seen per step.
    simulate(path, gains, landmark_map, true_landmarks, visibility, obstacles, params, seed) -> NavigationResult:
        Monte Carlo LQG trials (EKF with eq.-26 noise + LQR), collisions counted, Wilson interval.
    simulate_in_worker(args, kwargs) -> NavigationResult: simulate() on one BLAS thread, for a worker process.
    wilson_interval(successes, trials, confidence) -> (low, high).
    SegmentWalls, OccupancyGrid, occupancy_grid(endpoints, ...), scan_endpoints(...): obstacles.
    ray_cast_grid(origins, ends, hit, ...): log-odds occupancy grid with free space carved along each beam.
    GroundTruth, ground_truth_file(source): the simulator's truth beside a recording, in the map frame.
"""

from __future__ import annotations

from stages.navigation.lqg import (
    MapLike,
    NavigationMap,
    NavigationParams,
    NavigationResult,
    NominalPath,
    lqr_gains,
    nominal_path,
    simulate,
    simulate_in_worker,
    visibility_schedule,
)
from stages.navigation.stats import wilson_interval
from stages.navigation.truth import GroundTruth, MapTruth, ground_truth_file, se2, transform_points
from stages.navigation.walls import (
    Obstacles,
    OccupancyGrid,
    SegmentWalls,
    distance_to_segments,
    occupancy_grid,
    ray_cast_grid,
    scan_endpoints,
)

__all__ = [
    "GroundTruth",
    "MapLike",
    "MapTruth",
    "NavigationMap",
    "NavigationParams",
    "NavigationResult",
    "NominalPath",
    "Obstacles",
    "OccupancyGrid",
    "SegmentWalls",
    "distance_to_segments",
    "ground_truth_file",
    "lqr_gains",
    "nominal_path",
    "occupancy_grid",
    "ray_cast_grid",
    "scan_endpoints",
    "se2",
    "simulate",
    "simulate_in_worker",
    "transform_points",
    "visibility_schedule",
    "wilson_interval",
]
