"""Figures of the graph stage: timing against a single GTSAM optimise, accuracy and NEES against ground truth.

Commands (each prints what it measured in this run; nothing is asserted)::

    # build + optimise + marginals on a Victoria-Park-sized synthetic graph, as a ratio to one GTSAM optimise
    /work/venv/bin/python tests/benchmarks/bench_graph.py timing --poses 7000 --landmarks 150 --measurements 10000

    # ingest + detect + graph on simulated office runs (the sample = seed 0), ATE / landmark RMSE / NEES
    /work/venv/bin/python tests/benchmarks/bench_graph.py accuracy --bag sample_data/office/office.bag
    /work/venv/bin/python tests/benchmarks/bench_graph.py accuracy --simulate-seeds 1 2 3 4 --work /tmp/focusmap_sims

    # the same statistics on the image-free synthetic runs of stages/graph/synthetic.py
    /work/venv/bin/python tests/benchmarks/bench_graph.py synthetic --seeds 0 1 2 3 4 5 6 7 8 9
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from stages.geometry import umeyama_alignment  # noqa: E402


def timing(args: argparse.Namespace) -> None:
    """Time check + build + optimise + marginals (and the whole stage tail with writing) vs one GTSAM optimise."""
    import gtsam

    from pipeline.artifacts import StageOutput
    from stages.graph.config import GraphConfig
    from stages.graph.factors import build_graph
    from stages.graph.solve import check_problem, marginal_covariances, optimise
    from stages.graph.solve_all import solve_and_write
    from stages.graph.synthetic import synthetic_planar_problem

    t = time.perf_counter()
    problem = synthetic_planar_problem(args.poses, args.landmarks, args.measurements, seed=args.seed)
    gen = time.perf_counter() - t
    print(
        f"graph: {len(problem.pose_keys)} poses, {len(problem.landmark_keys)} landmarks, "
        f"{sum(r.kind == 'tag' for r in problem.rows)} landmark measurements, {len(problem.rows)} factors "
        f"(generated in {gen:.2f} s)"
    )
    # reference: one GTSAM optimise of the same graph (graph built beforehand, default LM parameters)
    ref_graph = build_graph(problem.rows)
    ref = []
    for _ in range(args.repeat):
        t = time.perf_counter()
        gtsam.LevenbergMarquardtOptimizer(ref_graph, problem.initial, gtsam.LevenbergMarquardtParams()).optimize()
        ref.append(time.perf_counter() - t)
    ours = {"check": [], "build": [], "optimise": [], "marginals": [], "total": []}
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        check_problem(problem)
        t1 = time.perf_counter()
        graph = build_graph(problem.rows)
        t2 = time.perf_counter()
        sol = optimise(problem, graph)
        t3 = time.perf_counter()
        marginal_covariances(problem, graph, sol.values, list(problem.var_types))
        t4 = time.perf_counter()
        for k, v in zip(ours, (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t4 - t0), strict=True):
            ours[k].append(v)
    t_ref = float(np.median(ref))
    print(f"single GTSAM LM optimise: {t_ref:.3f} s (median of {args.repeat})")
    for k, v in ours.items():
        print(f"  {k:10s} {np.median(v):8.3f} s   ratio to one optimise {np.median(v) / t_ref:6.2f}")
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        solve_and_write(problem, GraphConfig(), StageOutput(Path(tmp)), None, 3.0)
        whole = time.perf_counter() - t
    print(f"  stage tail (check+build+optimise+marginals+write artifacts) {whole:.3f} s   ratio {whole / t_ref:.2f}")


def _stats(est_xy: np.ndarray, true_xy: np.ndarray, lm_est: np.ndarray, lm_true: np.ndarray) -> tuple[float, float]:
    R, t, _ = umeyama_alignment(est_xy, true_xy)
    ate = float(np.sqrt(np.mean(np.sum((est_xy @ R.T + t - true_xy) ** 2, axis=1))))
    lm = float(np.sqrt(np.mean(np.sum((lm_est @ R.T + t - lm_true) ** 2, axis=1)))) if len(lm_est) else float("nan")
    return ate, lm


def _nees(est: np.ndarray, cov: np.ndarray, truth: np.ndarray) -> np.ndarray:
    e = est - truth
    return np.array([ei @ np.linalg.solve(ci, ei) / len(ei) for ei, ci in zip(e, cov, strict=True)])


def _evaluate_run(run_dir: Path, gt: dict, dims: int) -> dict[str, float]:
    """ATE, landmark RMSE (after rigid alignment of the trajectory) and landmark NEES/d (in the map frame)."""
    import pyarrow.parquet as pq

    poses = pq.read_table(run_dir / "graph" / "poses.parquet").to_pydict()
    lms = pq.read_table(run_dir / "graph" / "landmarks.parquet").to_pydict()
    gt_st = np.array([p["stamp_ns"] for p in gt["poses"]], dtype=float)
    gt_xy = np.array([[p["x"], p["y"]] for p in gt["poses"]])
    gt_yaw = np.unwrap([p["yaw"] for p in gt["poses"]])
    st = np.array(poses["stamp_ns"], dtype=float)
    true_xy = np.column_stack([np.interp(st, gt_st, gt_xy[:, 0]), np.interp(st, gt_st, gt_xy[:, 1])])
    yaw0 = float(np.interp(st[0], gt_st, gt_yaw))
    est_xy = np.column_stack([poses["x"], poses["y"]])
    tags = {t["id"]: np.array(t["position"]) for t in gt["tags"]}
    ids = [t for t in lms["tag_id"] if t in tags]
    idx = [lms["tag_id"].index(t) for t in ids]
    lm_est = np.column_stack([lms["x"], lms["y"], lms["z"]])[idx]
    lm_true_w = np.array([tags[t] for t in ids])
    ate, lm_rmse = _stats(est_xy, true_xy, lm_est[:, :2], lm_true_w[:, :2])
    # truth in the map frame (the true pose of the first keyframe), where the marginals live
    c, s = np.cos(yaw0), np.sin(yaw0)
    Rw0 = np.array([[c, -s], [s, c]])
    lm_true_map = (lm_true_w[:, :2] - true_xy[0]) @ Rw0
    covs = np.array(lms["position_cov"]).reshape(-1, 3, 3)[idx]
    nees = _nees(lm_est[:, :2], covs[:, :2, :2], lm_true_map) if dims == 2 else None
    if dims == 3:
        lm_true_map3 = np.column_stack([lm_true_map, lm_true_w[:, 2]])
        nees = _nees(lm_est, covs, lm_true_map3)
    return {
        "ate_cm": 100 * ate,
        "landmark_rmse_cm": 100 * lm_rmse,
        "nees_per_dim": float(np.mean(nees)),
        "landmarks": len(ids),
        "poses": len(st),
    }


def accuracy(args: argparse.Namespace) -> None:
    """Run ingest, detect and graph on simulated bags and compare with their ground truth."""
    from pipeline.config import load_settings
    from pipeline.registry import Registry
    from pipeline.run_folder import RunFolder
    from pipeline.runner import run_stage
    from sample_data.simulate import SimConfig, ground_truth_path, simulate, write_bag
    from stages import detect, graph, ingest

    reg = Registry([ingest.STAGE, detect.STAGE, graph.STAGE])
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    bags: list[tuple[str, Path]] = [(Path(b).stem, Path(b).resolve()) for b in args.bag]
    for seed in args.simulate_seeds:
        bag = work / f"office_seed{seed}.bag"
        if not bag.exists():
            t = time.perf_counter()
            write_bag(simulate(SimConfig(seed=seed)), bag, "ros1", None, overwrite=True)
            print(f"simulated seed {seed} in {time.perf_counter() - t:.1f} s")
        bags.append((f"seed{seed}", bag))
    rows = []
    for name, bag in bags:
        gt = json.loads(ground_truth_path(bag).read_text())
        for model in args.models:
            run = RunFolder.create(work / "runs" / name, bag)
            settings = load_settings(reg.models(), overrides=[f"graph.model={model}", *args.set])
            times = {}
            for stage in ("ingest", "detect", "graph"):
                t = time.perf_counter()
                run_stage(run, reg, stage, settings, force=stage == "graph")
                times[stage] = time.perf_counter() - t
            res = _evaluate_run(run.path, gt, 2 if model == "planar" else 3)
            summ = json.loads((run.path / "graph" / "summary.json").read_text())
            res.update(
                {
                    "run": name,
                    "model": model,
                    "graph_s": round(times["graph"], 2),
                    "tag_measurements": summ["tag_measurements"],
                }
            )
            rows.append(res)
            print(json.dumps(res))
    _table(rows)


def synthetic(args: argparse.Namespace) -> None:
    """The same statistics on image-free synthetic runs (detections drawn from their reported covariance)."""
    from stages.graph.build import build_problem
    from stages.graph.config import GraphConfig
    from stages.graph.factors import build_graph
    from stages.graph.solve import marginal_covariances, optimise
    from stages.graph.synthetic import synthetic_run

    rows = []
    for model in args.models:
        for seed in args.seeds:
            sim = synthetic_run(seed=seed, loops=args.loops)
            cfg = GraphConfig(model=model, tag_sigma_floor_m=args.floor, tag_sigma_floor_rad=args.floor)
            p = build_problem(sim.detections, sim.odometry, sim.extrinsics, cfg)
            g = build_graph(p.rows)
            sol = optimise(p, g)
            marg = marginal_covariances(p, g, sol.values, list(p.var_types))
            true = sim.true_pose_at(np.array(p.pose_stamps_ns))
            if model == "planar":
                est_xy = np.array([[sol.values.atPose2(k).x(), sol.values.atPose2(k).y()] for k in p.pose_keys])
                lm = np.array([sol.values.atPoint2(k) for k in p.landmark_keys.values()])
                covs = np.array([marg[k] for k in p.landmark_keys.values()])
            else:
                est_xy = np.array([np.asarray(sol.values.atPose3(k).translation())[:2] for k in p.pose_keys])
                lmp = [sol.values.atPose3(k) for k in p.landmark_keys.values()]
                lm = np.array([np.asarray(q.translation())[:2] for q in lmp])
                covs = np.array(
                    [
                        (np.asarray(q.rotation().matrix()) @ marg[k][3:, 3:] @ np.asarray(q.rotation().matrix()).T)[
                            :2, :2
                        ]
                        for q, k in zip(lmp, p.landmark_keys.values(), strict=True)
                    ]
                )
            lm_w = np.array([sim.tags_world[t][:2, 3] for t in p.landmark_keys])
            ate, lm_rmse = _stats(est_xy, true[:, :2], lm, lm_w)
            c, s = np.cos(true[0, 2]), np.sin(true[0, 2])
            lm_map = (lm_w - true[0, :2]) @ np.array([[c, -s], [s, c]])
            nees = _nees(lm, covs, lm_map)
            rows.append(
                {
                    "run": f"synthetic seed {seed}",
                    "model": model,
                    "ate_cm": 100 * ate,
                    "landmark_rmse_cm": 100 * lm_rmse,
                    "nees_per_dim": float(np.mean(nees)),
                    "landmarks": len(lm),
                    "poses": len(p.pose_keys),
                }
            )
    _table(rows)


def _table(rows: list[dict]) -> None:
    print("\n| run | model | poses | landmarks | ATE (cm) | landmark RMSE (cm) | landmark NEES / dim |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        print(
            f"| {r['run']} | {r['model']} | {r['poses']} | {r['landmarks']} | {r['ate_cm']:.1f} | "
            f"{r['landmark_rmse_cm']:.1f} | {r['nees_per_dim']:.2f} |"
        )
    for model in sorted({r["model"] for r in rows}):
        sel = [r for r in rows if r["model"] == model]
        print(
            f"{model}: mean ATE {np.mean([r['ate_cm'] for r in sel]):.1f} cm, mean landmark RMSE "
            f"{np.mean([r['landmark_rmse_cm'] for r in sel]):.1f} cm, mean NEES/dim "
            f"{np.mean([r['nees_per_dim'] for r in sel]):.2f} over {len(sel)} runs"
        )


def main() -> None:
    """Command line."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("timing")
    p.add_argument("--poses", type=int, default=7000)
    p.add_argument("--landmarks", type=int, default=150)
    p.add_argument("--measurements", type=int, default=10000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--repeat", type=int, default=3)
    p = sub.add_parser("accuracy")
    p.add_argument("--bag", nargs="*", default=[])
    p.add_argument("--simulate-seeds", nargs="*", type=int, default=[])
    p.add_argument("--work", default="/tmp/focusmap_graph_bench")
    p.add_argument("--models", nargs="*", default=["planar", "3d"])
    p.add_argument("--set", nargs="*", default=[], help="extra SECTION.KEY=VALUE settings")
    p = sub.add_parser("synthetic")
    p.add_argument("--seeds", nargs="*", type=int, default=list(range(10)))
    p.add_argument("--models", nargs="*", default=["planar", "3d"])
    p.add_argument("--loops", type=float, default=1.5)
    p.add_argument("--floor", type=float, default=0.0, help="tag sigma floor (m and rad)")
    args = parser.parse_args()
    {"timing": timing, "accuracy": accuracy, "synthetic": synthetic}[args.cmd](args)


if __name__ == "__main__":
    main()
