"""The select_measurements stage: keep the tag measurements that best localise the focused landmarks."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
import rerun as rr

from pipeline.context import StageContext
from pipeline.errors import StageError
from pipeline.recording import ellipsoids, set_step
from stages.columns import STAMP_NS
from stages.estimation.blas import blas_single
from stages.risk import riskiest_keyframes
from stages.select_landmarks.artifacts import FOCUSED as FOCUSED_JSON
from stages.select_landmarks.artifacts import MAHALANOBIS_FOCUSED, RISK
from stages.select_measurements.artifacts import SELECTED, SELECTION, SelectedMeasurements, selected_table
from stages.select_measurements.config import SelectMeasurementsConfig
from stages.select_measurements.core import (
    MeasurementChoice,
    base_information,
    choose,
    focused_covariances,
    focused_variables,
    linear_system,
    summary_of,
)

if TYPE_CHECKING:
    from stages.graph.load import LoadedGraph

ENTITY = "/select_measurements"
DRIFT_WARN_NATS = 0.05
"""A running entropy this far from the exact one says the greedy's tracked covariance lost precision."""
FOCUSED = [40, 200, 80]
OTHER = [150, 150, 150]
PICK = [255, 40, 200]
KEPT = [255, 170, 0]


def _focused_tags(ctx: StageContext, cfg: SelectMeasurementsConfig, loaded: LoadedGraph) -> list[int] | None:
    if cfg.focus != "selected":
        return None
    if not loaded.landmark_keys:
        raise StageError(
            "the graph has no landmarks (a pose graph): there are no focused landmarks to localise; to keep the K "
            "loop closures that best localise the poses, use --set select_measurements.focus=poses"
        )
    if not ctx.has_input("select_landmarks"):
        raise StageError(
            f"no focused landmarks: select_landmarks has not run in {str(ctx.run.path)!r}; run "
            f"'focusmap select-landmarks {ctx.run.path}' first (or --set select_measurements.focus=all)"
        )
    return FOCUSED_JSON.read(ctx.input("select_landmarks")).tag_ids


def _risky_poses(ctx: StageContext, cfg: SelectMeasurementsConfig, loaded: LoadedGraph) -> list[int]:
    """``focus_poses``: the riskiest keyframes by eq. 20 with the focused landmarks (select_landmarks' risk.parquet)."""
    if cfg.focus_poses <= 0 or cfg.focus == "poses":
        return []
    if not ctx.has_input("select_landmarks"):
        raise StageError(
            "select_measurements.focus_poses needs select_landmarks' risk.parquet: run 'focusmap select-landmarks RUN' "
            "first, or set select_measurements.focus_poses=0"
        )
    sl = ctx.input("select_landmarks")
    risk = RISK.read(sl, columns=[STAMP_NS, MAHALANOBIS_FOCUSED]).to_pydict()
    maha = np.asarray(risk[MAHALANOBIS_FOCUSED], dtype=float)
    if len(maha) != len(loaded.pose_keys) or not np.isfinite(maha).any():
        raise StageError(
            "select_measurements.focus_poses: select_landmarks has no collision risk for this graph's keyframes (no "
            "laser, or it is stale); set select_measurements.focus_poses=0 or re-run 'focusmap select-landmarks RUN'"
        )
    window = FOCUSED_JSON.read(sl).settings.visibility_window_s
    return riskiest_keyframes(maha, np.asarray(risk[STAMP_NS], dtype=np.int64), cfg.focus_poses, window)


@blas_single
def run(ctx: StageContext, cfg: SelectMeasurementsConfig) -> dict[str, Any]:
    """Select the measurements; write ``selected.parquet``; log ``select_measurements.rrd``."""
    from stages.graph.load import load_graph

    loaded = load_graph(ctx.input("graph"))
    tags = _focused_tags(ctx, cfg, loaded)
    system = linear_system(loaded)
    choice = choose(loaded, tags, cfg, system, focus_pose_indices=_risky_poses(ctx, cfg, loaded))
    SELECTED.write(ctx.output, selected_table(choice, loaded))
    SELECTION.write(ctx.output, SelectedMeasurements.of(choice, cfg))
    log_recording(ctx, loaded, system, choice, cfg)
    summary = summary_of(choice)
    summary["factors_kept"] = len(choice.keep_factor_indices(loaded))
    summary["factors_total"] = len(loaded.rows)
    summary["landmark_prior_sigma_m"] = cfg.landmark_prior_sigma_m
    summary["timing_s"] = {k: round(v, 4) for k, v in choice.stats.items() if k != "entropy_drift_nats"}
    drift = choice.stats.get("entropy_drift_nats")
    if drift is not None:
        summary["entropy_drift_nats"] = drift
        if abs(drift) > DRIFT_WARN_NATS:
            summary["warnings"] = [
                f"the fast greedy's running focused entropy drifted {drift:+.3g} nats from the exact one on this graph "
                "(rounding in its tracked covariance: precise measurements against weakly known landmarks); the "
                "entropies reported are exact, but its picks may differ from Alg. 1's exact greedy"
            ]
    return summary


def log_recording(
    ctx: StageContext, loaded: LoadedGraph, system: Any, choice: MeasurementChoice, cfg: SelectMeasurementsConfig
) -> None:
    """``select_measurements.rrd``: picks on ``selection_step`` (edge highlighted, focused ellipsoids, entropy)."""
    rec = ctx.rec
    rec.log(ENTITY, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    _log_map(rec, loaded, choice)
    ent = _log_entropy(rec, choice)
    for k, i in enumerate(choice.factor_indices, start=1):
        set_step(rec, k)
        rec.log(f"{ENTITY}/pick", rr.LineStrips3D([_edge(loaded, i)], colors=[PICK], radii=0.02))
    _log_replay(rec, loaded, system, choice, cfg, ctx.n_sigma, log_entropy=ent is None)
    rec.reset_time()


def _xyz(loaded: LoadedGraph, key: int) -> np.ndarray:
    return loaded.position(loaded.values, key)


def _edge(loaded: LoadedGraph, i: int) -> list[np.ndarray]:
    keys = loaded.rows[i].keys
    return [_xyz(loaded, keys[0]), _xyz(loaded, keys[1])]


def _log_map(rec: rr.RecordingStream, loaded: LoadedGraph, choice: MeasurementChoice) -> None:
    """The path, the landmarks outside the focused set and every candidate measurement, static."""
    path = np.array([_xyz(loaded, k) for k in loaded.pose_keys]).reshape(-1, 3)
    rec.log(f"{ENTITY}/path", rr.LineStrips3D([path], colors=[[120, 120, 120]]), static=True)
    focused_set = set(choice.focused_tag_ids)
    others = [t for t in sorted(loaded.landmark_keys) if t not in focused_set]
    if others:
        rec.log(
            f"{ENTITY}/landmarks/other",
            rr.Points3D(
                [_xyz(loaded, loaded.landmark_keys[t]) for t in others],
                colors=[OTHER],
                radii=0.04,
                labels=[str(t) for t in others],
            ),
            static=True,
        )
    if choice.candidates:
        rec.log(
            f"{ENTITY}/candidates",
            rr.LineStrips3D([_edge(loaded, i) for i in choice.candidates], colors=[[200, 200, 60, 60]], radii=0.002),
            static=True,
        )


def _log_entropy(rec: rr.RecordingStream, choice: MeasurementChoice) -> np.ndarray | None:
    """The focused entropy per step (every step for information, from the gains) and the gains; None when the
    strategy gives no per-step entropy (then the replay logs it at its steps)."""
    ent = choice.entropy_per_step()
    set_step(rec, 0)
    rec.log(f"{ENTITY}/entropy", rr.Scalars(choice.entropy_before))
    if ent is not None:
        steps = rr.TimeColumn("selection_step", sequence=np.arange(1, len(ent) + 1))
        rec.send_columns(f"{ENTITY}/entropy", indexes=[steps], columns=rr.Scalars.columns(scalars=ent))
        rec.send_columns(
            f"{ENTITY}/gain", indexes=[steps], columns=rr.Scalars.columns(scalars=np.asarray(choice.gains))
        )
    return ent


def _log_replay(
    rec: rr.RecordingStream,
    loaded: LoadedGraph,
    system: Any,
    choice: MeasurementChoice,
    cfg: SelectMeasurementsConfig,
    n_sigma: float,
    log_entropy: bool,
) -> None:
    """The focused ellipsoids and the kept edges at evenly spaced steps (one sparse factorisation each)."""
    if choice.focus == "poses":  # the focused set is every pose: the kept loop closures only
        _log_kept_steps(rec, loaded, choice, cfg)
        return
    f_keys = [loaded.landmark_keys[t] for t in choice.focused_tag_ids]
    f_xyz = np.array([_xyz(loaded, k) for k in f_keys]).reshape(-1, 3)
    f_labels = [str(t) for t in choice.focused_tag_ids]
    replay = _replay_steps(len(choice.factor_indices), cfg.max_replay_steps)
    focused_vars = focused_variables(loaded, system, choice.focused_tag_ids)
    base = [int(i) for i in loaded.fixed_factor_indices]
    base_info = base_information(system, base, cfg.landmark_prior_sigma_m)  # once: the odometry chain of every step
    for k in replay:
        picks = choice.factor_indices[:k]
        set_step(rec, k)
        blocks, entropy = focused_covariances(
            system, base, picks, focused_vars, cfg.landmark_prior_sigma_m, base_info=base_info
        )
        covs = []
        for key, block in zip(f_keys, blocks, strict=True):
            kind = loaded.kind(key)
            covs.append(kind.position_cov(kind.read(loaded.values, key), block))
        seen = {loaded.rows[i].tag_id for i in picks}
        observed = np.array([tag in seen for tag in choice.focused_tag_ids], dtype=bool)
        _log_focused(rec, f_xyz, covs, f_labels, observed, n_sigma)
        if picks:
            kept = rr.LineStrips3D([_edge(loaded, i) for i in picks], colors=[KEPT], radii=0.006)
            rec.log(f"{ENTITY}/kept", kept)
        if log_entropy:
            rec.log(f"{ENTITY}/entropy", rr.Scalars(entropy))


def _replay_steps(picks: int, max_steps: int) -> list[int]:
    """The steps replayed on ``selection_step``: 0, the last pick and at most ``max_steps`` evenly spaced between."""
    n = min(picks, max_steps)
    return sorted({0, picks, *np.round(np.linspace(0, picks, n + 1)).astype(int).tolist()}) if n else [0]


def _log_kept_steps(
    rec: rr.RecordingStream, loaded: LoadedGraph, choice: MeasurementChoice, cfg: SelectMeasurementsConfig
) -> None:
    """The kept edges at evenly spaced steps (no covariance replay)."""
    K = len(choice.factor_indices)
    for k in sorted({*_replay_steps(K, cfg.max_replay_steps), K}):
        if k:
            set_step(rec, k)
            rec.log(
                f"{ENTITY}/kept",
                rr.LineStrips3D([_edge(loaded, i) for i in choice.factor_indices[:k]], colors=[KEPT], radii=0.006),
            )


def _log_focused(
    rec: rr.RecordingStream,
    xyz: np.ndarray,
    covs: list[np.ndarray],
    labels: list[str],
    observed: np.ndarray,
    n_sigma: float,
) -> None:
    """Focused landmarks: ellipsoids where a kept measurement sees them, points where only the weak prior does."""
    if observed.any():
        rec.log(
            f"{ENTITY}/landmarks/focused",
            ellipsoids(
                xyz[observed],
                [c for c, o in zip(covs, observed, strict=True) if o],
                n_sigma,
                colors=[FOCUSED],
                labels=[lab for lab, o in zip(labels, observed, strict=True) if o],
            ),
        )
    else:
        rec.log(f"{ENTITY}/landmarks/focused", rr.Clear(recursive=False))
    if (~observed).any():
        rec.log(
            f"{ENTITY}/landmarks/unobserved",
            rr.Points3D(
                xyz[~observed],
                colors=[FOCUSED],
                radii=0.06,
                labels=[lab for lab, o in zip(labels, observed, strict=True) if not o],
            ),
        )
    else:
        rec.log(f"{ENTITY}/landmarks/unobserved", rr.Clear(recursive=False))
