"""The select_landmarks stage: run the chosen strategy, write focused.json and risk.parquet, log the recording."""

from __future__ import annotations

from typing import Any

import numpy as np
import rerun as rr

from pipeline.context import StageContext
from pipeline.recording import colormap, ellipses_2d, ellipsoids, set_stamp, set_step
from stages.risk import path_risk, risk_table
from stages.select_landmarks.artifacts import write_focused
from stages.select_landmarks.config import SelectLandmarksConfig
from stages.select_landmarks.core import LandmarkChoice, LandmarkInputs, choose

ENTITY = "/select_landmarks"
SELECTED = [40, 200, 80]
UNSELECTED = [150, 150, 150]
PICK = [255, 40, 200]


def _finite(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def _log10(p: float) -> float | None:
    return float(np.log10(max(p, 1e-300))) if np.isfinite(p) else None


def run(ctx: StageContext, cfg: SelectLandmarksConfig) -> dict[str, Any]:
    """Select the focused landmarks; write ``focused.json`` and ``risk.parquet``; log ``select_landmarks.rrd``."""
    inputs = LandmarkInputs.load(ctx, cfg)
    choice = choose(inputs, cfg)
    assert choice.risk_all is not None and choice.risk_focused is not None and choice.risk_none is not None
    write_focused(ctx.output, choice, cfg, inputs.geometry)
    z = float(np.median(inputs.landmarks.heights)) if len(inputs.landmarks.heights) else 0.0
    ctx.output.write_table("risk.parquet", risk_table(inputs.geometry, choice.risk_all, choice.risk_focused, 0.0))
    log_recording(ctx, inputs, choice, cfg, z)
    summary: dict[str, Any] = {
        "strategy": choice.strategy,
        "budget": choice.budget,
        "selected": len(choice.tag_ids),
        "landmarks": choice.n_landmarks,
        "keyframes": len(inputs.geometry.stamps_ns),
        "status": choice.status,
        "message": choice.message,
        "laser": inputs.has_laser,
        "select_seconds": round(choice.seconds, 4),
    }
    if inputs.has_laser:
        for name, r in (("none", choice.risk_none), ("all", choice.risk_all), ("focused", choice.risk_focused)):
            summary[f"p_collision_max_{name}"] = _finite(r.max)
            summary[f"p_collision_mean_{name}"] = _finite(r.mean)
            summary[f"log10_p_collision_max_{name}"] = _log10(r.max)
        summary["min_clearance_m"] = _finite(float(np.min(inputs.geometry.clearance_m)))
    else:
        summary["note"] = f"no collision risk: {inputs.laser_note}; only the non-collision strategies can run"
    geo = inputs.geometry
    summary["risk_model"] = {
        "robot_radius_m": inputs.params.robot_radius_m,
        "cap_steps": inputs.params.cap_steps,
        "odometry_sigma_m": float(np.sqrt(geo.Q[0, 0])),
        "odometry_sigma_rad": float(np.sqrt(geo.Q[2, 2])),
        "bearing_sigma_rad": geo.sigmas[0],
        "range_sigma_m": geo.sigmas[1],
        "mean_visible_landmarks": float(geo.visible.sum(axis=1).mean()) if len(geo.visible) else 0.0,
    }
    return summary


def log_recording(
    ctx: StageContext, inputs: LandmarkInputs, choice: LandmarkChoice, cfg: SelectLandmarksConfig, z: float
) -> None:
    """``select_landmarks.rrd``: path coloured by risk, obstacles, Σ* ellipses, landmarks, greedy picks replayed."""
    rec = ctx.rec
    geo, lm, params = inputs.geometry, inputs.landmarks, inputs.params
    assert choice.risk_focused is not None and choice.risk_all is not None
    n_sigma = ctx.n_sigma
    T = len(geo.stamps_ns)
    path = np.column_stack([geo.poses[:, :2], np.zeros(T)])
    rec.log(ENTITY, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    lm_xyz = np.column_stack([lm.positions, np.full(len(lm.tag_ids), z)])
    lm_cov3 = np.zeros((len(lm.tag_ids), 3, 3))
    lm_cov3[:, :2, :2] = lm.covariances
    labels = [str(t) for t in lm.tag_ids]
    picked = set(choice.tag_ids)
    sel_mask = np.array([int(t) in picked for t in lm.tag_ids], dtype=bool)

    def risk_colors(p: np.ndarray) -> np.ndarray:
        logp = np.log10(np.clip(np.nan_to_num(p, nan=0.0), 1e-300, 1.0))
        return colormap(np.clip(logp, -12.0, 0.0), -12.0, 0.0)

    def log_path(sub: str, risk: np.ndarray) -> None:
        if T < 2:
            return
        segs = np.stack([path[:-1], path[1:]], axis=1)
        rec.log(f"{ENTITY}/{sub}", rr.LineStrips3D(segs, colors=risk_colors(np.maximum(risk[:-1], risk[1:]))))

    def log_sigma(sub: str, sigma: np.ndarray, risk: np.ndarray) -> None:
        idx = np.arange(0, T, cfg.ellipse_stride)
        if len(idx):
            rec.log(
                f"{ENTITY}/{sub}",
                ellipses_2d(path[idx], [sigma[i, :2, :2] for i in idx], n_sigma, colors=risk_colors(risk[idx])),
            )

    # static: the final result
    if geo.has_laser:
        ok = np.isfinite(geo.obstacles[:, 0])
        rec.log(
            f"{ENTITY}/obstacles",
            rr.Points3D(np.column_stack([geo.obstacles[ok], np.zeros(ok.sum())]), colors=[[200, 60, 60]], radii=0.02),
            static=True,
        )
        rays = np.stack([path[ok], np.column_stack([geo.obstacles[ok], np.zeros(ok.sum())])], axis=1)
        rec.log(
            f"{ENTITY}/obstacle_rays",
            rr.LineStrips3D(rays[:: cfg.ellipse_stride], colors=[[200, 60, 60, 80]]),
            static=True,
        )
    rec.log(f"{ENTITY}/path_all", rr.LineStrips3D([path], colors=[[120, 120, 120]]), static=True)
    if len(lm.tag_ids):
        rec.log(
            f"{ENTITY}/landmarks/unselected",
            ellipsoids(
                lm_xyz[~sel_mask],
                lm_cov3[~sel_mask],
                n_sigma,
                colors=[UNSELECTED],
                labels=[lab for lab, s in zip(labels, sel_mask, strict=True) if not s],
            ),
            static=True,
        )
    # on the time line: risk along the path
    for t in range(T):
        set_stamp(rec, int(geo.stamps_ns[t]))
        rec.log(f"{ENTITY}/robot", rr.Points3D([path[t]], colors=[PICK], radii=0.05))
    if geo.has_laser and T:
        times = rr.TimeColumn("time", timestamp=geo.stamps_ns.astype("datetime64[ns]"))
        for name, r in (("all", choice.risk_all), ("focused", choice.risk_focused)):
            rec.send_columns(
                f"{ENTITY}/risk/{name}",
                indexes=[times],
                columns=rr.Scalars.columns(scalars=np.log10(np.clip(r.p_collision, 1e-300, 1.0))),
            )
        rec.send_columns(
            f"{ENTITY}/clearance_m",
            indexes=[times],
            columns=rr.Scalars.columns(scalars=np.nan_to_num(geo.clearance_m, posinf=-1.0)),
        )
    rec.reset_time()
    # the greedy picks, replayed on selection_step (step 0: nothing picked)
    n_replay = min(len(choice.tag_ids), cfg.max_replay_steps)
    for k in range(n_replay + 1):
        tags = choice.tag_ids[:k]
        set_step(rec, k)
        risk = path_risk(geo, lm, tags, params, inputs.sigma_cache)
        p = risk.p_collision if geo.has_laser else np.zeros(T)
        log_path("path", p)
        log_sigma("sigma_star", risk.sigma, p)
        mask = np.isin(lm.tag_ids, np.array(tags, dtype=np.int64))
        if mask.any():
            rec.log(
                f"{ENTITY}/landmarks/selected",
                ellipsoids(
                    lm_xyz[mask],
                    lm_cov3[mask],
                    n_sigma,
                    colors=[SELECTED],
                    labels=[lab for lab, s in zip(labels, mask, strict=True) if s],
                ),
            )
        else:
            rec.log(f"{ENTITY}/landmarks/selected", rr.Clear(recursive=False))
        if k:
            i = int(np.flatnonzero(lm.tag_ids == tags[-1])[0])
            rec.log(f"{ENTITY}/pick", rr.Points3D([lm_xyz[i]], colors=[PICK], radii=0.12, labels=[labels[i]]))
            score = choice.scores[k - 1]
            if np.isfinite(score):
                rec.log(f"{ENTITY}/score", rr.Scalars(score))
        if geo.has_laser:
            rec.log(f"{ENTITY}/max_collision_log10", rr.Scalars(np.log10(max(risk.max, 1e-300))))
    rec.reset_time()
