"""The laser occupancy grid against the true walls, on a run of a simulated recording (issue #14 item 6).

    python -m sample_data.simulate --out bags --name office_s1_sweep --seed 1 --laser-sweep --force
    focusmap run bags/office_s1_sweep.bag --out runs --config configs/office.yaml --until graph
    python tests/benchmarks/bench_laser_grid.py runs/office_s1_sweep bags/office_s1_sweep.ground_truth.json

Builds three grids from the run's scans (every ``--stride``-th, as evaluate does), each from the true and from the
estimated keyframe poses: the endpoint grid evaluate used before (each scan at the pose of its stamp, cells with
>= 2 returns), the ray-cast grid without deskew, and the ray-cast grid with deskew (evaluate's now). Per grid:
the clearance it gives along the path (the estimated path for estimated poses, as evaluate without ground truth)
against the true walls' clearance along the true path, at the door passages and overall, and the share of its
occupied cells farther than 0.10 m from any true wall (phantom obstacles).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

from stages.ingest.artifacts import ANGLE_INCREMENT, ANGLE_MIN, RANGE_MAX, RANGE_MIN, RANGES, STAMP_NS
from stages.laser import planar_mount, scan_beams
from stages.navigation import (
    GroundTruth,
    OccupancyGrid,
    SegmentWalls,
    nominal_path,
    occupancy_grid,
    ray_cast_grid,
    scan_endpoints,
    se2,
    transform_points,
)

DOOR_WORLD = (8.0, 3.0)
"""Centre of the simulated office's door (sample_data/README.md)."""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path)
    parser.add_argument("truth", type=Path)
    parser.add_argument("--stride", type=int, default=2)
    parser.add_argument("--resolution", type=float, default=0.05)
    args = parser.parse_args()
    scans = pq.read_table(args.run / "ingest" / "scans.parquet")
    kf = pq.read_table(args.run / "graph" / "poses.parquet").to_pydict()
    ks = np.asarray(kf[STAMP_NS], dtype=np.int64)
    estimated = np.column_stack([kf["x"], kf["y"], kf["yaw"]])
    sensors = json.loads((args.run / "ingest" / "extrinsics.json").read_text())["sensors"]
    T_bl = np.asarray(sensors["laser"]["T_base_sensor"], dtype=float)
    gt = GroundTruth.load(args.truth)
    truth = gt.in_map(int(ks[0]))
    walls = SegmentWalls(truth.walls)
    door = transform_points(np.linalg.inv(gt.T_world_map(int(ks[0]))), [DOOR_WORLD])[0]
    stamps = np.asarray(scans.column(STAMP_NS).to_numpy(), dtype=np.int64)
    rows = np.arange(0, scans.num_rows, args.stride)
    rows = rows[(stamps[rows] >= ks[0]) & (stamps[rows] <= ks[-1])]
    print(f"{args.run}: {len(rows)} scans, time_increment up to {np.max(scans.column('time_increment')):.2e} s")

    def endpoint_grid(poses: np.ndarray) -> OccupancyGrid:
        kt, yaw = ks.astype(float), np.unwrap(poses[:, 2])
        mount = se2(*planar_mount(T_bl))
        cols = scans.select([STAMP_NS, ANGLE_MIN, ANGLE_INCREMENT, RANGE_MIN, RANGE_MAX, RANGES]).to_pydict()
        pts = []
        for j in rows:
            s = float(cols[STAMP_NS][j])
            pose = se2(np.interp(s, kt, poses[:, 0]), np.interp(s, kt, poses[:, 1]), np.interp(s, kt, yaw))
            ranges = np.asarray(cols[RANGES][j], dtype=float)
            limits = (cols[ANGLE_MIN][j], cols[ANGLE_INCREMENT][j], cols[RANGE_MIN][j], cols[RANGE_MAX][j])
            pts.append(scan_endpoints(pose @ mount, ranges, *limits))
        return occupancy_grid(np.vstack(pts), args.resolution, 2)

    def carved_grid(poses: np.ndarray, deskew: bool) -> OccupancyGrid:
        b = scan_beams(scans, ks, poses, T_bl, rows, deskew=deskew)
        return ray_cast_grid(b.origins, b.ends, b.hit, args.resolution, 2)

    true_path = nominal_path(ks, truth.pose_at(ks), 0.2).poses[:, :2]
    d_true = walls.distance(true_path)
    at_door = np.linalg.norm(true_path - door, axis=1) < 0.5
    print(
        f"true walls: clearance along the true path min {d_true.min():.3f} m, at the door {d_true[at_door].min():.3f} m"
    )
    header = "poses      grid                        door   min    (true there)  under>0.10  worst under  phantom cells"
    print(header)
    for label, poses in (("true", truth.pose_at(ks)), ("estimated", estimated)):
        path = nominal_path(ks, poses, 0.2).poses[:, :2]
        grids = (
            ("endpoints (before)", endpoint_grid(poses)),
            ("ray cast, no deskew", carved_grid(poses, False)),
            ("ray cast + deskew (now)", carved_grid(poses, True)),
        )
        for name, grid in grids:
            d = grid.distance(path)
            k = int(np.argmin(d))
            phantom = float(np.mean(walls.distance(grid.points()) > 0.10))
            print(
                f"{label:10s} {name:26s} {d[at_door].min():.3f}  {d.min():.3f}  ({d_true[k]:.3f})      "
                f"{np.mean(d < d_true - 0.10):8.3f}  {np.max(d_true - d):9.3f}    {phantom:.3f} of {len(grid.points())}"
            )


if __name__ == "__main__":
    main()
