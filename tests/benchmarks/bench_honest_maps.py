"""How far a run's landmarks are from the truth, against their own covariance (issue 33's figures).

    python tests/benchmarks/bench_honest_maps.py RUN GROUND_TRUTH.json [RUN GROUND_TRUTH.json ...]

RUN is a run folder whose graph stage has run (planar model); GROUND_TRUTH.json is the truth beside a world from
``sample_data/simulate.py`` (``WORLD.ground_truth.json``, keys ``poses`` and ``tags``) or from the independent
simulator of ``../shared/data/other-sim`` (``robot_poses`` and ``tags``). Printed per run, for the landmarks:

- **map frame**: the truth expressed in the true pose of the first keyframe (the graph's map frame, where its
  marginals live): RMSE (cm) and NEES per dimension (planar, 2), mean and median. This is the consistency test:
  near 1 when the stated covariances are right.
- **aligned**: after a rigid alignment (rotation and translation in the plane) of the landmarks to the truth, the
  same figures (issue 33's table). The alignment removes the map's uncertainty relative to its first pose, which the
  marginals hold, so this NEES sits below the map frame's for an honest map.
- **similarity**: the same with a scale as well, and the scale.

Measured in session seventeen (docs/graph.md, "Honest maps on worlds we did not make").
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq


def _truth(path: Path) -> tuple[np.ndarray, np.ndarray, dict[int, np.ndarray]]:
    """Stamps (ns), planar poses (x, y, yaw; yaw unwrapped) in stamp order, and tag positions (x, y) by id."""
    doc = json.loads(path.read_text())
    poses = doc["robot_poses"] if "robot_poses" in doc else doc["poses"]
    stamps = np.array([p["stamp_ns"] for p in poses], dtype=np.int64)
    xyyaw = np.array([[p["x"], p["y"], p["yaw"]] for p in poses], dtype=float)
    order = np.argsort(stamps, kind="stable")
    stamps, first = np.unique(stamps[order], return_index=True)
    xyyaw = xyyaw[order][first]
    xyyaw[:, 2] = np.unwrap(xyyaw[:, 2])
    tags = {int(t["id"]): np.asarray(t["position"], dtype=float)[:2] for t in doc["tags"]}
    return stamps, xyyaw, tags


def _align(est: np.ndarray, true: np.ndarray, scale: bool) -> tuple[np.ndarray, float]:
    """``est`` moved onto ``true`` by the least-squares rotation, translation (and scale): Umeyama's method."""
    me, mt = est.mean(axis=0), true.mean(axis=0)
    a, b = est - me, true - mt
    U, S, Vt = np.linalg.svd(b.T @ a / len(est))
    D = np.diag([1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / (a**2).sum(axis=1).mean()) if scale else 1.0
    return s * a @ R.T + mt, s


def _figures(err: np.ndarray, covs: np.ndarray) -> str:
    nees = np.array([e @ np.linalg.solve(c, e) / 2 for e, c in zip(err, covs, strict=True)])
    rmse = 100 * float(np.sqrt(np.mean(np.sum(err**2, axis=1))))
    return f"{rmse:6.1f} cm, NEES/dof {np.mean(nees):6.2f} / {np.median(nees):5.2f}"


def measure(run: Path, truth: Path) -> str:
    """The three lines of the module docstring for one run."""
    stamps, xyyaw, tags = _truth(truth)
    graph = run / "graph"
    lm = pq.read_table(graph / "landmarks.parquet").to_pydict()
    first = int(pq.read_table(graph / "poses.parquet", columns=["stamp_ns"]).column(0)[0].as_py())
    x0, y0, yaw0 = (np.interp(first - stamps[0], stamps - stamps[0], xyyaw[:, k]) for k in range(3))
    c, s = np.cos(yaw0), np.sin(yaw0)
    R0 = np.array([[c, -s], [s, c]])
    ids = [i for i in lm["tag_id"] if int(i) in tags]
    rows = [lm["tag_id"].index(i) for i in ids]
    est = np.column_stack([lm["x"], lm["y"]])[rows]
    covs = np.asarray(lm["position_cov"], dtype=float).reshape(-1, 3, 3)[rows][:, :2, :2]
    true_world = np.array([tags[int(i)] for i in ids])
    true_map = (true_world - [x0, y0]) @ R0
    rigid, _ = _align(est, true_world, scale=False)
    similar, scale = _align(est, true_world, scale=True)
    return "\n".join(
        [
            f"{run.name}: {len(ids)} landmarks",
            f"  map frame   {_figures(est - true_map, covs)}",
            f"  aligned     {_figures(rigid - true_world, covs)}",
            f"  similarity  {_figures(similar - true_world, covs)}  (scale {scale:.4f})",
        ]
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("pairs", nargs="+", help="RUN GROUND_TRUTH.json, repeated")
    args = parser.parse_args()
    if len(args.pairs) % 2:
        parser.error("give RUN and GROUND_TRUTH.json in pairs")
    for run, truth in zip(args.pairs[::2], args.pairs[1::2], strict=True):
        print(measure(Path(run), Path(truth)))


if __name__ == "__main__":
    main()
