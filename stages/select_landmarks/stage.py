"""The select_landmarks stage: run the chosen strategy, write focused.json and risk.parquet, log the recording."""

from __future__ import annotations

from typing import Any

import numpy as np
import rerun as rr

from pipeline.context import StageContext
from pipeline.recording import colormap, ellipses_2d, ellipsoids, set_stamp, set_step
from stages.risk import path_risk
from stages.select_landmarks.artifacts import FOCUSED, RISK, FocusedLandmarks, risk_table
from stages.select_landmarks.config import SelectLandmarksConfig
from stages.select_landmarks.core import LandmarkChoice, LandmarkInputs, auto_strategy, choose

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
    FOCUSED.write(ctx.output, FocusedLandmarks.of(choice, cfg, inputs.geometry))
    z = float(np.median(inputs.landmarks.heights)) if len(inputs.landmarks.heights) else 0.0
    RISK.write(ctx.output, risk_table(inputs.geometry, choice.risk_all, choice.risk_focused, 0.0))
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
    if cfg.strategy == "auto" and choice.strategy != "collision":
        summary["notes"] = [f"select_landmarks.strategy=auto ran {choice.strategy}: {auto_strategy(inputs, cfg)[1]}"]
    geo = inputs.geometry
    summary["risk_model"] = {
        "robot_radius_m": inputs.params.robot_radius_m,
        "control_period_s": geo.robot.control_period_s,
        "speed_sigma_mps": geo.robot.speed_sigma_mps,
        "yaw_rate_sigma_radps": geo.robot.yaw_rate_sigma_radps,
        "bearing_sigma_rad": geo.sigmas[0],
        "range_sigma_m": geo.sigmas[1],
        "mean_visible_landmarks": float(geo.visible.sum(axis=1).mean()) if len(geo.visible) else 0.0,
    }
    return summary


def log_recording(
    ctx: StageContext, inputs: LandmarkInputs, choice: LandmarkChoice, cfg: SelectLandmarksConfig, z: float
) -> None:
    """``select_landmarks.rrd``: path coloured by risk, obstacles, Σ* ellipses, landmarks, greedy picks replayed."""
    assert choice.risk_focused is not None and choice.risk_all is not None
    draw = _Drawing(ctx.rec, inputs, z, ctx.n_sigma, cfg.ellipse_stride)
    ctx.rec.log(ENTITY, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    # static: the final result
    if inputs.geometry.has_laser:
        draw.obstacles()
    ctx.rec.log(f"{ENTITY}/path_all", rr.LineStrips3D([draw.path], colors=[[120, 120, 120]]), static=True)
    if len(inputs.landmarks.tag_ids):
        picked = set(choice.tag_ids)
        selected = np.array([int(t) in picked for t in inputs.landmarks.tag_ids], dtype=bool)
        draw.landmarks("landmarks/unselected", ~selected, UNSELECTED, static=True)
    draw.risk_timeline(choice)
    ctx.rec.reset_time()
    # the greedy picks, replayed on selection_step (step 0: nothing picked); every landmark at once: before and after
    n = len(choice.tag_ids)
    at_once = choice.strategy == "all" or n == choice.n_landmarks
    for k in [0, n] if at_once else range(min(n, cfg.max_replay_steps) + 1):
        set_step(ctx.rec, k)
        draw.step(choice, k)
    ctx.rec.reset_time()


def _risk_colors(p: np.ndarray) -> np.ndarray:
    logp = np.log10(np.clip(np.nan_to_num(p, nan=0.0), 1e-300, 1.0))
    return colormap(np.clip(logp, -12.0, 0.0), -12.0, 0.0)


class _Drawing:
    """The parts of ``select_landmarks.rrd``: the path at map height 0, landmarks at height ``z``."""

    def __init__(self, rec: rr.RecordingStream, inputs: LandmarkInputs, z: float, n_sigma: float, stride: int) -> None:
        self.rec, self.inputs, self.n_sigma, self.stride = rec, inputs, n_sigma, stride
        geo, lm = inputs.geometry, inputs.landmarks
        self.T = len(geo.stamps_ns)
        self.path = np.column_stack([geo.poses[:, :2], np.zeros(self.T)])
        self.lm_xyz = np.column_stack([lm.positions, np.full(len(lm.tag_ids), z)])
        self.lm_cov3 = np.zeros((len(lm.tag_ids), 3, 3))
        self.lm_cov3[:, :2, :2] = lm.covariances
        self.labels = [str(t) for t in lm.tag_ids]

    def obstacles(self) -> None:
        """The nearest laser return of each keyframe, and rays to it (a stride), static."""
        geo = self.inputs.geometry
        ok = np.isfinite(geo.obstacles[:, 0])
        points = np.column_stack([geo.obstacles[ok], np.zeros(ok.sum())])
        self.rec.log(f"{ENTITY}/obstacles", rr.Points3D(points, colors=[[200, 60, 60]], radii=0.02), static=True)
        rays = np.stack([self.path[ok], points], axis=1)
        self.rec.log(
            f"{ENTITY}/obstacle_rays", rr.LineStrips3D(rays[:: self.stride], colors=[[200, 60, 60, 80]]), static=True
        )

    def landmarks(self, sub: str, mask: np.ndarray, color: list[int], static: bool = False) -> None:
        """Ellipsoids of the landmarks in ``mask``."""
        labels = [lab for lab, s in zip(self.labels, mask, strict=True) if s]
        ellipses = ellipsoids(self.lm_xyz[mask], self.lm_cov3[mask], self.n_sigma, colors=[color], labels=labels)
        self.rec.log(f"{ENTITY}/{sub}", ellipses, static=static)

    def risk_timeline(self, choice: LandmarkChoice) -> None:
        """The robot on the time line; with laser, the collision risk (all and focused) and the clearance."""
        geo = self.inputs.geometry
        assert choice.risk_focused is not None and choice.risk_all is not None
        for t in range(self.T):
            set_stamp(self.rec, int(geo.stamps_ns[t]))
            self.rec.log(f"{ENTITY}/robot", rr.Points3D([self.path[t]], colors=[PICK], radii=0.05))
        if not (geo.has_laser and self.T):
            return
        times = rr.TimeColumn("time", timestamp=geo.stamps_ns.astype("datetime64[ns]"))
        for name, r in (("all", choice.risk_all), ("focused", choice.risk_focused)):
            log_p = np.log10(np.clip(r.p_collision, 1e-300, 1.0))
            self.rec.send_columns(f"{ENTITY}/risk/{name}", indexes=[times], columns=rr.Scalars.columns(scalars=log_p))
        clearance = np.nan_to_num(geo.clearance_m, posinf=-1.0)
        self.rec.send_columns(f"{ENTITY}/clearance_m", indexes=[times], columns=rr.Scalars.columns(scalars=clearance))

    def step(self, choice: LandmarkChoice, k: int) -> None:
        """Greedy step ``k``: the path coloured by risk and the Σ* ellipses with the first ``k`` picks, the pick."""
        inputs, lm, T = self.inputs, self.inputs.landmarks, self.T
        tags = choice.tag_ids[:k]
        risk = path_risk(inputs.geometry, lm, tags, inputs.params, inputs.sigma_cache)
        p = risk.p_collision if inputs.geometry.has_laser else np.zeros(T)
        if T >= 2:
            segs = np.stack([self.path[:-1], self.path[1:]], axis=1)
            self.rec.log(f"{ENTITY}/path", rr.LineStrips3D(segs, colors=_risk_colors(np.maximum(p[:-1], p[1:]))))
        idx = np.arange(0, T, self.stride)
        if len(idx):
            sigmas = [risk.sigma[i, :2, :2] for i in idx]
            ellipses = ellipses_2d(self.path[idx], sigmas, self.n_sigma, colors=_risk_colors(p[idx]))
            self.rec.log(f"{ENTITY}/sigma_star", ellipses)
        mask = np.isin(lm.tag_ids, np.array(tags, dtype=np.int64))
        if mask.any():
            self.landmarks("landmarks/selected", mask, SELECTED)
        else:
            self.rec.log(f"{ENTITY}/landmarks/selected", rr.Clear(recursive=False))
        if k:
            i = int(np.flatnonzero(lm.tag_ids == tags[-1])[0])
            pick = rr.Points3D([self.lm_xyz[i]], colors=[PICK], radii=0.12, labels=[self.labels[i]])
            self.rec.log(f"{ENTITY}/pick", pick)
            score = choice.scores[k - 1]
            if np.isfinite(score):
                self.rec.log(f"{ENTITY}/score", rr.Scalars(score))
        if inputs.geometry.has_laser:
            self.rec.log(f"{ENTITY}/max_collision_log10", rr.Scalars(np.log10(max(risk.max, 1e-300))))
