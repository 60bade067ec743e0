"""Figures of the graph stage: timing against a single GTSAM optimise, accuracy and NEES against ground truth.

Commands (each prints what it measured in this run; nothing is asserted)::

    # build + optimise + marginals on a Victoria-Park-sized synthetic graph, as a ratio to one GTSAM optimise
    # (with the default shared tag scale; --tag-scale-sigma 0 for the graph without it)
    /work/venv/bin/python tests/benchmarks/bench_graph.py timing --poses 7000 --landmarks 150 --measurements 10000

    # ingest + detect + graph on simulated office runs (the sample = seed 0), ATE / landmark RMSE / NEES
    /work/venv/bin/python tests/benchmarks/bench_graph.py accuracy --bag sample_data/office/office.bag
    /work/venv/bin/python tests/benchmarks/bench_graph.py accuracy --simulate-seeds 1 2 3 4 --work /tmp/focusmap_sims

    # where the landmark NEES comes from (on the run folders 'accuracy' left in --work; docs/graph.md)
    /work/venv/bin/python tests/benchmarks/bench_graph.py diagnose --bag sample_data/office/office.bag \\
        /tmp/g4/office_seed1.bag /tmp/g4/office_seed2.bag /tmp/g4/office_seed3.bag --work /tmp/g4/work --estimator-mc

    # the same statistics on the image-free synthetic runs of tests/fixtures/synthetic_runs.py
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
    from tests.fixtures.synthetic_runs import synthetic_planar_problem

    t = time.perf_counter()
    sigma = GraphConfig().tag_scale_sigma if args.tag_scale_sigma is None else args.tag_scale_sigma
    problem = synthetic_planar_problem(
        args.poses, args.landmarks, args.measurements, seed=args.seed, tag_scale_sigma=sigma
    )
    gen = time.perf_counter() - t
    print(
        f"graph: {len(problem.pose_keys)} poses, {len(problem.landmark_keys)} landmarks, "
        f"{sum(r.kind == 'tag' for r in problem.rows)} landmark measurements, {len(problem.rows)} factors, "
        f"tag scale sigma {sigma} (generated in {gen:.2f} s)"
    )
    # references, graphs built beforehand, default LM parameters: one GTSAM optimise of the same graph, and of the
    # graph without the scale (native factors only). GTSAM's own optimisers copy every variable for each call of a
    # Python factor, so with the scale the first reference is slow (the stage drives LM from Python instead).
    references: dict[str, list[float]] = {}
    cases = [("the same graph, GTSAM LM", problem)] if sigma == 0 or args.gtsam_same_graph else []
    if sigma > 0:
        plain = synthetic_planar_problem(args.poses, args.landmarks, args.measurements, seed=args.seed)
        cases.append(("the graph without the scale, GTSAM LM", plain))
    for label, prob in cases:
        ref_graph = build_graph(prob.rows)
        slow = sigma > 0 and prob is problem  # GTSAM's LM on Python factors: minutes, run once
        for _ in range(1 if slow else args.repeat):
            t = time.perf_counter()
            gtsam.LevenbergMarquardtOptimizer(ref_graph, prob.initial, gtsam.LevenbergMarquardtParams()).optimize()
            references.setdefault(label, []).append(time.perf_counter() - t)
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
    refs = {label: float(np.median(v)) for label, v in references.items()}
    for label, t_ref in refs.items():
        print(f"one optimise of {label}: {t_ref:.3f} s (median of {len(references[label])})")
    print("| ours | s | " + " | ".join(f"ratio to {label}" for label in refs) + " |")
    print("| --- | --- |" + " --- |" * len(refs))
    rows = {k: float(np.median(v)) for k, v in ours.items()}
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        solve_and_write(problem, GraphConfig(tag_scale_sigma=sigma), StageOutput(Path(tmp)), None, 3.0)
        rows["stage tail (total + writing artifacts)"] = time.perf_counter() - t
    for k, v in rows.items():
        print(f"| {k} | {v:.3f} | " + " | ".join(f"{v / t_ref:.2f}" for t_ref in refs.values()) + " |")


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
                    "tag_scale": (summ.get("tag_scale") or {}).get("value", float("nan")),
                    "tag_scale_sigma": (summ.get("tag_scale") or {}).get("sigma", float("nan")),
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
    from tests.fixtures.synthetic_runs import synthetic_run

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


def _truth_tables(gt: dict) -> tuple[dict, np.ndarray, np.ndarray, dict]:
    """Ground truth: T_camera_tag by (frame, tag id), pose stamps, poses (x, y, yaw), tag positions (world)."""
    truth = {(f["index"], t["id"]): np.array(t["T_camera_tag"]) for f in gt["frames"] for t in f["visible_tags"]}
    st = np.array([p["stamp_ns"] for p in gt["poses"]], dtype=float)
    xyyaw = np.array([[p["x"], p["y"], p["yaw"]] for p in gt["poses"]])
    xyyaw[:, 2] = np.unwrap(xyyaw[:, 2])
    tags = {t["id"]: np.array(t["position"]) for t in gt["tags"]}
    return truth, st, xyyaw, tags


def _depth_errors(det: dict, truth: dict) -> dict[str, np.ndarray]:
    """Per detection matched to the truth: range, relative depth error (along the true line of sight), view angle."""
    out: dict[str, list] = {"i": [], "range": [], "rel_depth": [], "view_deg": [], "p_alt": [], "rel_depth_alt": []}
    for i in range(len(det["frame"])):
        key = (int(det["frame"][i]), int(det["tag_id"][i]))
        if key not in truth or det["ambiguous"][i]:
            continue
        T = np.reshape(det["T_camera_tag"][i], (4, 4))
        Ta = np.reshape(det["alt_T_camera_tag"][i], (4, 4))
        Tt = truth[key]
        tt = Tt[:3, 3]
        z = float(np.linalg.norm(tt))
        u = tt / z
        ta = Ta[:3, 3] if np.all(np.isfinite(Ta)) else T[:3, 3]
        out["i"].append(i)
        out["range"].append(z)
        out["rel_depth"].append(float((T[:3, 3] - tt) @ u) / z)
        out["rel_depth_alt"].append(float((ta - tt) @ u) / z)
        out["view_deg"].append(float(np.degrees(np.arccos(min(1.0, abs(Tt[:3, 2] @ u))))))
        out["p_alt"].append(float(det["alt_probability"][i]) if "alt_probability" in det else 0.0)
    return {k: np.asarray(v) for k, v in out.items()}


def _edit_detections(table, truth: dict, how: str, k: float = 0.0):
    """A copy of the detection table with the tag translations edited against the truth.

    ``depth``: the depth error (along the true line of sight) removed, the lateral error kept;
    ``scale``: every translation multiplied by ``1 + k``; ``mixture_mean``: the translation replaced by
    ``(1 - p) t + p t_alt`` (the mixture mean of both planar solutions' centres).
    """
    import pyarrow as pa

    det = table.to_pydict()
    Ts = [list(v) for v in det["T_camera_tag"]]
    for i in range(len(Ts)):
        T = np.reshape(Ts[i], (4, 4)).copy()
        t = T[:3, 3]
        if how == "scale":
            T[:3, 3] = t * (1.0 + k)
        elif how == "mixture_mean":
            Ta = np.reshape(det["alt_T_camera_tag"][i], (4, 4))
            p = float(det["alt_probability"][i])
            if np.all(np.isfinite(Ta)):
                T[:3, 3] = (1 - p) * t + p * Ta[:3, 3]
        elif how == "depth":
            key = (int(det["frame"][i]), int(det["tag_id"][i]))
            if key in truth:
                tt = truth[key][:3, 3]
                u = tt / np.linalg.norm(tt)
                T[:3, 3] = t - ((t - tt) @ u) * u
        Ts[i] = T.ravel().tolist()
    idx = table.column_names.index("T_camera_tag")
    return table.set_column(idx, "T_camera_tag", pa.array(Ts, type=table.schema.field("T_camera_tag").type))


def _solve_nees(detections, odometry, extrinsics, cfg, gt: dict) -> dict:
    """Build and solve the stage's problem in process; landmark NEES/dim in the map frame, per landmark too."""
    import gtsam

    from stages.graph.build import build_problem
    from stages.graph.factors import build_graph
    from stages.graph.solve import marginal_covariances, optimise

    _, gst, gxy, tags = _truth_tables(gt)
    p = build_problem(detections, odometry, extrinsics, cfg)
    g = build_graph(p.rows)
    sol = optimise(p, g)
    marg = marginal_covariances(p, g, sol.values, [*p.landmark_keys.values(), p.pose_keys[0]])
    st = np.asarray(p.pose_stamps_ns, dtype=float)
    x0, y0, yaw0 = (float(np.interp(st[0], gst, gxy[:, j])) for j in range(3))
    c, s = np.cos(yaw0), np.sin(yaw0)
    R0 = np.array([[c, -s], [s, c]])
    ids, nees, sig = [], [], []
    for tag, key in p.landmark_keys.items():
        if tag not in tags:
            continue
        true = (tags[tag][:2] - [x0, y0]) @ R0
        if p.model == "planar":
            est = np.asarray(sol.values.atPoint2(key))
            cov = marg[key]
        else:
            q = sol.values.atPose3(key)
            est = np.asarray(q.translation())[:2]
            R = np.asarray(q.rotation().matrix())
            cov = (R @ marg[key][3:, 3:] @ R.T)[:2, :2]
        e = est - true
        ids.append(tag)
        nees.append(float(e @ np.linalg.solve(cov, e)) / 2)
        sig.append(float(np.sqrt(np.trace(cov) / 2)))
    # odometry factors' chi^2 per dimension at the true poses (planar only)
    chi = []
    if p.model == "planar":
        tp = [gtsam.Pose2(*(float(np.interp(t, gst, gxy[:, j])) for j in range(3))) for t in st]
        pidx = {k: i for i, k in enumerate(p.pose_keys)}
        for r in p.rows:
            if r.kind == "odometry":
                i, j = pidx[r.keys[0]], pidx[r.keys[1]]
                meas = gtsam.Pose2(*r.measurement)
                e = gtsam.Pose2.Logmap(meas.between(tp[i].between(tp[j])))
                chi.append(float(e @ np.linalg.solve(r.covariance, e)) / 3)
    return {
        "nees_per_dim": float(np.mean(nees)),
        "per_landmark": dict(zip(ids, nees, strict=True)),
        "sigma_cm": float(100 * np.mean(sig)),
        "odometry_chi2_per_dim": float(np.mean(chi)) if chi else float("nan"),
        "problem": p,
    }


def _estimator_bias(gt: dict, sigma_px: float, draws: int, stride: int, seed: int = 0) -> None:
    """Monte Carlo of detect's pose estimator alone: the true corners plus white noise of ``sigma_px``.

    No image, no JPEG, no detector: what remains of the range bias is the estimator's own (the planar
    tilt folded away from frontal, which the range pays for).
    """
    from stages.camera import colmap_camera
    from stages.detect.pose import estimate_tag_pose

    cam = gt["camera"]
    camera = colmap_camera(
        {"width": cam["width"], "height": cam["height"], "K": cam["K"], "D": cam["D"], "distortion_model": "plumb_bob"}
    )
    size = float(gt["config"]["tag_size_m"])
    rng = np.random.default_rng(seed)
    res = []
    for f in gt["frames"][::stride]:
        for t in f["visible_tags"]:
            T = np.array(t["T_camera_tag"])
            c = np.array(t["corners_px"]).reshape(4, 2)
            if min(np.linalg.norm(np.roll(c, -1, 0) - c, axis=1)) < 10:
                continue
            z = float(np.linalg.norm(T[:3, 3]))
            u = T[:3, 3] / z
            errs = []
            for _ in range(draws):
                est = estimate_tag_pose(c + rng.normal(0, sigma_px, c.shape), size, camera)
                if est is not None:
                    errs.append(float((est.T_camera_tag[:3, 3] - T[:3, 3]) @ u) / z)
            view = float(np.degrees(np.arccos(min(1.0, abs(T[:3, 2] @ u)))))
            res.append((z, view, np.mean(errs)))
    A = np.array(res)
    print(
        f"\nestimator alone (true corners + N(0, {sigma_px} px), {draws} draws, {len(A)} tag views): "
        f"mean relative depth error {100 * A[:, 2].mean():+.3f} %"
    )
    print("| range (m) | n | rel. depth error (%) |  | view angle (deg) | n | rel. depth error (%) |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    rb = [(0, 1.5), (1.5, 2), (2, 3), (3, 5), (5, 99), (None, None)]
    vb = [(0, 10), (10, 20), (20, 30), (30, 45), (45, 60), (60, 91)]
    for (a, b), (c0, c1) in zip(rb, vb, strict=True):
        left = "|  |  |  |"
        if a is not None:
            m = (A[:, 0] >= a) & (A[:, 0] < b)
            left = f"| {a}-{b} | {m.sum()} | {100 * A[m, 2].mean():+.3f} |"
        m = (A[:, 1] >= c0) & (A[:, 1] < c1)
        print(f"{left}  | {c0}-{c1} | {m.sum()} | {100 * A[m, 2].mean():+.3f} |")


def diagnose(args: argparse.Namespace) -> None:
    """Where the landmark NEES comes from: detect's range errors, the prior, far-only landmarks, odometry.

    Works on run folders made by ``accuracy`` (same --work): per-detection depth errors against the truth,
    then in-process rebuilds of the planar problem with the detections edited against the truth.
    """
    import pyarrow.parquet as pq

    from stages.graph.config import GraphConfig
    from stages.ingest.artifacts import Extrinsics

    work = Path(args.work)
    cfg0 = GraphConfig(model="planar")
    summary: dict[str, list[float]] = {}
    for bag in args.bag:
        bag = Path(bag)
        name = bag.stem
        run = work / "runs" / name
        gt = json.loads(bag.with_name(bag.stem + ".ground_truth.json").read_text())
        truth = _truth_tables(gt)[0]
        detections = pq.read_table(run / "detect" / "detections.parquet")
        odometry = pq.read_table(run / "ingest" / "odometry.parquet")
        extrinsics = Extrinsics.model_validate_json((run / "ingest" / "extrinsics.json").read_text())
        de = _depth_errors(detections.to_pydict(), truth)
        k = -float(np.mean(de["rel_depth"]))
        print(f"\n## {name}: {len(de['i'])} detections matched, mean relative depth error {-100 * k:+.3f} %")
        print("| range (m) | n | rel. depth error (%) | other solution (%) |")
        print("| --- | --- | --- | --- |")
        for a, b in [(0, 1), (1, 2), (2, 3), (3, 5), (5, 99)]:
            m = (de["range"] >= a) & (de["range"] < b)
            rel, alt = 100 * de["rel_depth"][m].mean(), 100 * de["rel_depth_alt"][m].mean()
            print(f"| {a}-{b} | {m.sum()} | {rel:+.3f} | {alt:+.3f} |")
        print("| view angle (deg) | n | rel. depth error (%) | other solution (%) |")
        print("| --- | --- | --- | --- |")
        for a, b in [(0, 10), (10, 20), (20, 30), (30, 45), (45, 60), (60, 91)]:
            m = (de["view_deg"] >= a) & (de["view_deg"] < b)
            rel, alt = 100 * de["rel_depth"][m].mean(), 100 * de["rel_depth_alt"][m].mean()
            print(f"| {a}-{b} | {m.sum()} | {rel:+.3f} | {alt:+.3f} |")
        # corners outwards of the truth along their diagonals (a scale error of the quad), by shortest side
        corners = {
            (f["index"], t["id"]): np.array(t["corners_px"]).reshape(4, 2)
            for f in gt["frames"]
            for t in f["visible_tags"]
        }
        dd = detections.to_pydict()
        rows = []
        for j, i in enumerate(de["i"]):
            ct = corners[(int(dd["frame"][i]), int(dd["tag_id"][i]))]
            c = np.reshape(dd["corners"][i], (4, 2))
            radial = ct - ct.mean(axis=0)
            r = np.linalg.norm(radial, axis=1)
            side = float(min(np.linalg.norm(np.roll(ct, -1, 0) - ct, axis=1)))
            rows.append(
                (side, float(((c - ct) * radial / r[:, None]).sum(1).mean()), float(r.mean()), de["rel_depth"][j])
            )
        C = np.array(rows)
        print("| shortest side (px) | n | corners outwards (px) | share of half-diagonal (%) | rel. depth (%) |")
        print("| --- | --- | --- | --- | --- |")
        for a, b in [(0, 15), (15, 20), (20, 30), (30, 45), (45, 70), (70, 999)]:
            m = (C[:, 0] >= a) & (C[:, 0] < b)
            print(
                f"| {a}-{b} | {m.sum()} | {C[m, 1].mean():+.4f} | {100 * (C[m, 1] / C[m, 2]).mean():+.3f} | "
                f"{100 * C[m, 3].mean():+.3f} |"
            )
        variants = [
            ("as detected", detections, cfg0),
            ("mixture mean of both solutions' centres", _edit_detections(detections, truth, "mixture_mean"), cfg0),
            ("depth error removed (truth), lateral kept", _edit_detections(detections, truth, "depth"), cfg0),
            (
                "every range x (1 - mean relative depth error), one number",
                _edit_detections(detections, truth, "scale", k),
                cfg0,
            ),
            ("prior 1e-4", detections, cfg0.model_copy(update={"prior_sigma_m": 1e-4, "prior_sigma_rad": 1e-4})),
            ("prior 1e-2", detections, cfg0.model_copy(update={"prior_sigma_m": 1e-2, "prior_sigma_rad": 1e-2})),
            ("tag floor 0", detections, cfg0.model_copy(update={"tag_sigma_floor_m": 0.0})),
            ("odometry noise from settings", detections, cfg0.model_copy(update={"odometry_noise": "settings"})),
        ]
        print("| planar problem | landmark NEES/2 | mean landmark σ (cm) | odometry χ²/dim at truth |")
        print("| --- | --- | --- | --- |")
        base = None
        for label, table, cfg in variants:
            r = _solve_nees(table, odometry, extrinsics, cfg, gt)
            base = base or r
            summary.setdefault(label, []).append(r["nees_per_dim"])
            print(f"| {label} | {r['nees_per_dim']:.2f} | {r['sigma_cm']:.2f} | {r['odometry_chi2_per_dim']:.2f} |")
        # (b) landmarks by their nearest sighting
        near = {}
        for i in de["i"]:
            t = int(detections.column("tag_id")[int(i)].as_py())
            near[t] = min(near.get(t, 99.0), float(de["range"][list(de["i"]).index(i)]))
        print("| nearest sighting (m) | landmarks | NEES/2 as detected |")
        print("| --- | --- | --- |")
        for a, b in [(0, 1.5), (1.5, 2.5), (2.5, 99)]:
            v = [n for t, n in base["per_landmark"].items() if a <= near.get(t, 99) < b]
            print(f"| {a}-{b} | {len(v)} | {np.mean(v) if v else float('nan'):.2f} |")
    if args.estimator_mc:
        gt = json.loads(Path(args.bag[0]).with_name(Path(args.bag[0]).stem + ".ground_truth.json").read_text())
        _estimator_bias(gt, args.mc_sigma_px, args.mc_draws, args.mc_stride)
    print("\n| planar problem | mean landmark NEES/2 over the runs |")
    print("| --- | --- |")
    for label, v in summary.items():
        print(f"| {label} | {np.mean(v):.2f} ({', '.join(f'{x:.2f}' for x in v)}) |")


def _table(rows: list[dict]) -> None:
    print(
        "\n| run | model | poses | landmarks | ATE (cm) | landmark RMSE (cm) | landmark NEES / dim | tag scale s (σ) |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        sc = r.get("tag_scale", float("nan"))
        scale = "-" if not np.isfinite(sc) else f"{sc:.5f} ({r.get('tag_scale_sigma', float('nan')):.5f})"
        print(
            f"| {r['run']} | {r['model']} | {r['poses']} | {r['landmarks']} | {r['ate_cm']:.1f} | "
            f"{r['landmark_rmse_cm']:.1f} | {r['nees_per_dim']:.2f} | {scale} |"
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
    p.add_argument(
        "--tag-scale-sigma", type=float, default=None, help="the shared tag scale's prior (default: the setting's)"
    )
    p.add_argument(
        "--gtsam-same-graph", action="store_true", help="with the scale, also time GTSAM's LM on it (slow, once)"
    )
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
    p = sub.add_parser("diagnose")
    p.add_argument("--bag", nargs="*", default=[], help="bags already run by 'accuracy' with the same --work")
    p.add_argument("--work", default="/tmp/focusmap_graph_bench")
    p.add_argument("--estimator-mc", action="store_true", help="also the estimator-only Monte Carlo (first bag)")
    p.add_argument("--mc-sigma-px", type=float, default=0.14, help="corner noise of the Monte Carlo (detect's pooled)")
    p.add_argument("--mc-draws", type=int, default=8)
    p.add_argument("--mc-stride", type=int, default=4, help="every n-th frame of the ground truth")
    args = parser.parse_args()
    {"timing": timing, "accuracy": accuracy, "synthetic": synthetic, "diagnose": diagnose}[args.cmd](args)


if __name__ == "__main__":
    main()
