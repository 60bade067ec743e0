"""Self-calibrating odometry, before and after, on simulated worlds with systematic wheel errors.

For each world (the office path there and back, and a long corridor out and back; several seeds) the simulator
writes a bag whose wheel odometry has a distance scale error, a yaw-rate scale error and a yaw bias per metre,
with message covariances that grow over the run but do not contain the systematic part. ingest and detect run
once per world through the runner (the detections do not depend on the wheel errors: the images come from their
own random stream). The graph is then built and solved in process for odometry variants made by
``sample_data.simulate.simulate_odometry`` (the same draws): the world's own (``as recorded``), the same with the
covariances 10x too small, all zero, or absent (no covariance column), and the same world without wheel errors
(the control: calibration must not hurt it). Each is solved with the calibration off (``before``) and on
(``after``: ``graph.odometry_calibration``, with the odometry's noise level estimated; ``after_tag_noise``: the
tags' too, ``graph.noise_estimate=odometry_and_tags``), and with the defaults
(``default``: ``odometry_calibration: auto`` decides; the ``auto`` column says what it chose, its statistic and,
when the test did not turn it on, the mean squared shift per dimension of its step against the map's sigma,
``map_shift``, the distance scale's step in its σ, and ``wheel_scale`` where that health check would warn).

Figures per run: landmark RMSE after a rigid 2D alignment of the landmarks to the truth (Umeyama, no scale),
landmark NEES / 2 in the map frame (the truth in the frame of the true first keyframe, where the marginals
live), and for ``after`` the estimated calibration (± σ) and the odometry covariance scale. ``--decompose`` adds
the NEES's radial and tangential parts, the NEES modulo the map's scale and the joint NEES (one χ² over all
landmarks with their joint covariance, over its dimension: the map's scale counts once there, not once per
landmark). ``--print-error-sigma 0.005`` prints each world's tags with an error drawn from the graph's tag-size
prior (one draw per world), as real prints have; with exact tags (the default) the map's scale error is detect's
range bias alone and the radial NEES is small by construction. Nothing is asserted.

    /work/venv/bin/python tests/benchmarks/bench_odometry.py --work /tmp/odom/bench --seeds 1 2 \\
        --paths office corridor_return [--corridor-length 26 --decompose --print-error-sigma 0.005]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from stages.geometry import umeyama_alignment  # noqa: E402

ERRORS = {"odom_distance_scale_error": 0.02, "odom_yaw_scale_error": -0.015, "odom_yaw_bias_rad_per_m": 0.01}
"""Default wheel errors: 2 % long, 1.5 % short in turns, 0.01 rad per metre (0.57°/m)."""


NOMINAL_TAG_M = 0.16
"""The tag size every run is told (``detect.tag_size_m``); the printed size may differ (``--print-error-sigma``)."""


def print_error(path: str, seed: int, sigma: float) -> float:
    """The world's relative tag print error, drawn from N(0, sigma^2) (the graph's tag-size prior when sigma is
    ``graph.tag_scale_sigma``): one number per world, from its own stream (the same for every variant)."""
    if sigma <= 0:
        return 0.0
    rng = np.random.default_rng([seed, sum(map(ord, path))])
    return float(rng.normal(0.0, sigma))


def world_config(
    path: str, seed: int, corridor_length: float, errors: dict[str, float], print_error: float = 0.0
) -> Any:
    from sample_data.simulate import SimConfig

    extra = {"corridor_length_m": corridor_length} if path == "corridor_return" else {}
    size = NOMINAL_TAG_M * (1.0 + print_error)
    return SimConfig(seed=seed, path=path, tag_size_m=size, **extra, **errors)  # type: ignore[arg-type]


def make_world(work: Path, name: str, cfg: Any) -> Path:
    """The world's bag (simulated once) and its ingest + detect run folder (made once)."""
    from pipeline.config import load_settings
    from pipeline.registry import Registry
    from pipeline.run_folder import RunFolder
    from pipeline.runner import run_stage
    from sample_data.simulate import simulate, write_bag
    from stages import detect, ingest

    bag = work / f"{name}.bag"
    if not bag.exists():
        t = time.perf_counter()
        write_bag(simulate(cfg), bag, "ros1", None, overwrite=True)
        print(f"simulated {name} in {time.perf_counter() - t:.0f} s", flush=True)
    run_dir = work / "runs" / name
    if not (run_dir / "detect" / "detections.parquet").exists():
        reg = Registry([ingest.STAGE, detect.STAGE])
        run = RunFolder.create(run_dir, bag)
        settings = load_settings(reg.models(), overrides=[f"detect.tag_size_m={NOMINAL_TAG_M}"])
        for stage in ("ingest", "detect"):
            t = time.perf_counter()
            run_stage(run, reg, stage, settings)
            print(f"{name}: {stage} in {time.perf_counter() - t:.0f} s", flush=True)
    return run_dir


def odometry_table(cfg: Any, covariance: str) -> Any:
    """ingest's odometry table for the simulator's odometry of ``cfg`` (covariance: as recorded / small / zero /
    absent)."""
    import pyarrow as pa

    from sample_data.simulate import simulate_odometry

    if covariance == "small":
        cfg = replace(cfg, odom_cov_scale=0.1)
    elif covariance == "zero":
        cfg = replace(cfg, odom_cov_scale=0.0)
    msgs = simulate_odometry(cfg)
    cols: dict[str, list[Any]] = {k: [] for k in ("stamp_ns", "x", "y", "z", "qx", "qy", "qz", "qw")}
    for m in msgs:
        for k, v in zip(
            cols, (m.header.stamp_ns, m.x, m.y, 0.0, 0.0, 0.0, math.sin(m.yaw / 2), math.cos(m.yaw / 2)), strict=True
        ):
            cols[k].append(v)
    if covariance != "absent":
        cols["pose_cov"] = [list(m.pose_covariance) for m in msgs]
    return pa.table(cols)


def evaluate(problem: Any, values: Any, marginals: dict[int, np.ndarray], gt: dict[str, Any]) -> dict[str, float]:
    """Landmark RMSE after a rigid alignment of the landmarks, and landmark NEES / 2 in the map frame."""
    st = np.array([p["stamp_ns"] for p in gt["poses"]], dtype=float)
    xy = np.array([[p["x"], p["y"]] for p in gt["poses"]])
    yaw = np.unwrap([p["yaw"] for p in gt["poses"]])
    s0 = float(problem.pose_stamps_ns[0])
    x0, y0, yaw0 = (float(np.interp(s0, st, a)) for a in (xy[:, 0], xy[:, 1], yaw))
    R0 = np.array([[math.cos(yaw0), -math.sin(yaw0)], [math.sin(yaw0), math.cos(yaw0)]])
    tags = {t["id"]: np.array(t["position"][:2]) for t in gt["tags"]}
    est, true_map, true_w, nees = [], [], [], []
    for tag, key in problem.landmark_keys.items():
        e = np.asarray(values.atPoint2(key))
        t_map = (tags[tag] - [x0, y0]) @ R0
        d = e - t_map
        nees.append(float(d @ np.linalg.solve(marginals[key], d)) / 2)
        est.append(e)
        true_map.append(t_map)
        true_w.append(tags[tag])
    E, T = np.array(est), np.array(true_w)
    R, t, _ = umeyama_alignment(E, T)
    rmse = float(np.sqrt(np.mean(np.sum((E @ R.T + t - T) ** 2, axis=1))))
    return {"rmse_cm": 100 * rmse, "nees": float(np.mean(nees)), "landmarks": len(est)}


def solve(det: Any, odo: Any, extr: Any, overrides: dict[str, Any]) -> tuple[Any, Any, dict, dict, float]:
    """Build and solve as the graph stage does (``stages.graph.solve_all``: with ``odometry_calibration: auto`` it
    decides from the data)."""
    from stages.graph.build import build_problem
    from stages.graph.config import GraphConfig
    from stages.graph.solve_all import _solve

    cfg = GraphConfig(**overrides)
    t = time.perf_counter()
    p = build_problem(det, odo, extr, cfg)
    s = _solve(p, cfg)
    return s.problem, s.solution.values, s.marginals, s.calibration or {}, time.perf_counter() - t


def decompose(det: Any, odo: Any, extr: Any, used: dict[str, Any], gt: dict[str, Any]) -> dict[str, float]:
    """Where the landmark NEES / 2 comes from: its radial part (along each landmark's direction from the first
    keyframe, where the map's scale moves it) and tangential part (NEES / 1 each), and the NEES / 2 modulo the map's
    scale: each landmark's covariance conditioned on the shared tag scale ``s``, and the estimate moved along its
    regression on ``s`` by the one common step that fits the truth best (the scale error taken out of the error as
    it is out of the covariance). From the joint system of the (calibrated or plain) solution with ``s`` and the
    calibration ``c`` as variables."""
    import gtsam

    from stages.graph import calibration as cal
    from stages.graph.build import build_problem
    from stages.graph.config import GraphConfig

    cfg = GraphConfig(**used)
    p0 = build_problem(det, odo, extr, cfg)
    r = cal.calibrate(p0, cfg)
    p, values, summ = r.problem, r.solution.values, r.summary
    base = list(p0.rows)
    odo_rows = [i for i, row in enumerate(base) if row.kind == "odometry"]
    mean, sigma = cal._prior(cfg)
    state = cal._State(
        np.array([summ[k]["value"] for k in cal.PARAMETERS]),
        np.asarray(summ.get("odometry_covariance_scale_by_dimension", [summ["odometry_covariance_scale"]])),
        summ["tag_covariance_scale"],
    )
    joint, _ = cal._joint_system(p, r.graph, values, odo_rows, state, mean, sigma, base)
    marg = gtsam.Marginals(joint, joint.optimize())
    st = np.array([q["stamp_ns"] for q in gt["poses"]], dtype=float)
    xy = np.array([[q["x"], q["y"]] for q in gt["poses"]])
    yaw = np.unwrap([q["yaw"] for q in gt["poses"]])
    x0, y0, yaw0 = (float(np.interp(float(p.pose_stamps_ns[0]), st, a)) for a in (xy[:, 0], xy[:, 1], yaw))
    R0 = np.array([[math.cos(yaw0), -math.sin(yaw0)], [math.sin(yaw0), math.cos(yaw0)]])
    tags = {t["id"]: np.array(t["position"][:2]) for t in gt["tags"]}
    rad, tan, parts = [], [], []
    for tag, key in p.landmark_keys.items():
        e = np.asarray(values.atPoint2(key))
        d = e - (tags[tag] - [x0, y0]) @ R0
        J = np.asarray(marg.jointMarginalCovariance(gtsam.KeyVector([key, p.scale_key])).fullMatrix())
        S = J[:2, :2]
        u = e / np.linalg.norm(e)
        w = np.array([-u[1], u[0]])
        rad.append(float((u @ d) ** 2 / (u @ S @ u)))
        tan.append(float((w @ d) ** 2 / (w @ S @ w)))
        parts.append((d, J[:2, 2] / J[2, 2], S - np.outer(J[:2, 2], J[:2, 2]) / J[2, 2]))
    # the joint NEES of the map (one chi-square over all landmarks, their correlations included: the map's scale
    # is one of its degrees of freedom, not one in each landmark); blocks in the order of the keys given
    keys = list(p.landmark_keys.values())
    full = np.asarray(marg.jointMarginalCovariance(gtsam.KeyVector(keys)).fullMatrix())
    d_all = np.concatenate([d for d, _, _ in parts])
    joint_nees = float(d_all @ np.linalg.solve(full, d_all)) / d_all.size
    num = sum(g @ np.linalg.solve(Sc, d) for d, g, Sc in parts)
    den = sum(g @ np.linalg.solve(Sc, g) for d, g, Sc in parts)
    step = num / den
    mod = [float((d - g * step) @ np.linalg.solve(Sc, d - g * step)) / 2 for d, g, Sc in parts]
    return {
        "nees_radial": float(np.mean(rad)),
        "nees_tangential": float(np.mean(tan)),
        "nees_modulo_scale": float(np.mean(mod)),
        "scale_error": float(step),
        "nees_joint": joint_nees,
    }


BEFORE: dict[str, Any] = {"odometry_calibration": False, "noise_estimate": "off"}
AFTER: dict[str, Any] = {"odometry_calibration": True}
"""The calibration forced on (with ``noise_estimate: auto``: the odometry's noise level)."""
AFTER_TAG_NOISE: dict[str, Any] = {"odometry_calibration": True, "noise_estimate": "odometry_and_tags"}
"""The calibration with the odometry's and the tags' noise levels estimated."""
AFTER_YAW: dict[str, Any] = {"odometry_calibration": True, "odometry_scale_sigma": 0.0}
"""The yaw-rate scale and yaw bias only (the distance scale left to the tag scale)."""
DEFAULT: dict[str, Any] = {}
"""The defaults: ``odometry_calibration: auto`` (on when the data reject uncalibrated odometry)."""
CONFIGS = {
    "before": BEFORE,
    "after": AFTER,
    "after_tag_noise": AFTER_TAG_NOISE,
    "after_yaw": AFTER_YAW,
    "default": DEFAULT,
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/focusmap_odometry"))
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--paths", nargs="+", default=["office", "corridor_return"])
    ap.add_argument("--corridor-length", type=float, default=16.0)
    ap.add_argument("--variants", nargs="+", default=["recorded", "small", "zero", "absent", "no_errors"])
    ap.add_argument("--configs", nargs="+", default=["before", "after", "default"], choices=sorted(CONFIGS))
    ap.add_argument(
        "--errors",
        type=float,
        nargs=3,
        metavar=("DISTANCE_SCALE", "YAW_SCALE", "YAW_BIAS"),
        default=[ERRORS[k] for k in ERRORS],
        help="the wheel errors of the worlds (default: %(default)s; the held-out worlds' milder 0.015 -0.01 0.004 "
        "are what the calibration test must still catch)",
    )
    ap.add_argument("--worlds-only", action="store_true", help="make the bags and run folders, then stop")
    ap.add_argument(
        "--decompose",
        action="store_true",
        help="also split each NEES into its radial and tangential parts and give it modulo the map's scale",
    )
    ap.add_argument(
        "--print-error-sigma",
        type=float,
        default=0.0,
        help="print each world's tags (1 + e) times the size detect is told, e ~ N(0, this^2) per world (0: exact "
        "tags; 0.005 = graph.tag_scale_sigma, the tolerance the graph assumes of a real print)",
    )
    args = ap.parse_args()

    import pyarrow.parquet as pq

    from stages.detect.artifacts import DETECTIONS
    from stages.graph.calibration import shift_warning
    from stages.graph.config import GraphConfig
    from stages.ingest.artifacts import EXTRINSICS, Extrinsics

    args.work.mkdir(parents=True, exist_ok=True)
    rows = []
    for path in args.paths:
        for seed in args.seeds:
            eps = print_error(path, seed, args.print_error_sigma)
            name = f"{path}_seed{seed}" + (f"_print{args.print_error_sigma:g}" if args.print_error_sigma > 0 else "")
            if list(args.errors) != list(ERRORS.values()):
                name += "_errors" + "_".join(f"{e:g}" for e in args.errors)
            errors = dict(zip(ERRORS, args.errors, strict=True))
            cfg = world_config(path, seed, args.corridor_length, errors, eps)
            run_dir = make_world(args.work, name, cfg)
            if args.worlds_only:
                continue
            gt = json.loads((args.work / f"{name}.ground_truth.json").read_text())
            det = pq.read_table(run_dir / "detect" / DETECTIONS.file)
            extr = Extrinsics.model_validate_json((run_dir / "ingest" / EXTRINSICS.file).read_text())
            for variant in args.variants:
                vcfg = world_config(path, seed, args.corridor_length, {}, eps) if variant == "no_errors" else cfg
                odo = odometry_table(vcfg, "recorded" if variant == "no_errors" else variant)
                for label in args.configs:
                    over = CONFIGS[label]
                    p, values, marg, summ, secs = solve(det, odo, extr, over)
                    res = {"world": name, "odometry": variant, "graph": label, **evaluate(p, values, marg, gt)}
                    res["print_error"] = round(eps, 5)
                    res["seconds"] = round(secs, 1)
                    if "decision" in summ:
                        dec = summ["decision"]
                        shift = dec.get("map_shift", {}).get("mean_d2_per_dim")
                        moved = ""
                        if shift is not None:  # the wheel_scale check's figures (without the tag_scale check's veto)
                            z = (dec["step"]["distance_scale"] - 1) / dec["sigma"]["distance_scale"]
                            warned = shift_warning(dec, GraphConfig(**CONFIGS[label])) is not None
                            moved = f"; shift {shift:.2f}, k_d {z:+.1f} σ" + ("; wheel_scale" if warned else "")
                        res["auto"] = f"{'on' if dec['applied'] else 'off'} ({dec['statistic']:.1f}{moved})"
                    if args.decompose:
                        calibrated = "distance_scale" in summ
                        used = {"odometry_calibration": calibrated, "noise_estimate": summ.get("noise_estimate", "off")}
                        parts = decompose(det, odo, extr, used, gt)
                        res.update({k: round(v, 4) for k, v in parts.items()})
                    if "distance_scale" in summ:
                        for k in ("distance_scale", "yaw_rate_scale", "yaw_bias_rad_per_m"):
                            res[k] = f"{summ[k]['value']:.4f} ± {summ[k]['sigma']:.4f}"
                        res["odo_cov_scale"] = round(summ["odometry_covariance_scale"], 3)
                        res["tag_cov_scale"] = round(summ["tag_covariance_scale"], 3)
                    rows.append(res)
                    print(json.dumps(res), flush=True)
    if rows:
        table(rows)


def table(rows: list[dict[str, Any]]) -> None:
    cols = [
        "world",
        "odometry",
        "graph",
        "rmse_cm",
        "nees",
        "distance_scale",
        "yaw_rate_scale",
        "yaw_bias_rad_per_m",
        "odo_cov_scale",
        "tag_cov_scale",
        "auto",
        "nees_radial",
        "nees_tangential",
        "nees_modulo_scale",
        "nees_joint",
        "print_error",
    ]
    print("| " + " | ".join(cols) + " |")
    print("|" + " --- |" * len(cols))
    for r in rows:
        cells = [f"{r[c]:.2f}" if isinstance(r.get(c), float) else str(r.get(c, "–")) for c in cols]
        print("| " + " | ".join(cells) + " |")
    for label in CONFIGS:
        for variant in sorted({r["odometry"] for r in rows}):
            sel = [r for r in rows if r["graph"] == label and r["odometry"] == variant]
            if sel:
                print(
                    f"mean {label:6s} {variant:9s}: RMSE {np.mean([r['rmse_cm'] for r in sel]):.1f} cm, "
                    f"NEES/2 {np.mean([r['nees'] for r in sel]):.2f} over {len(sel)} worlds"
                )


if __name__ == "__main__":
    main()
