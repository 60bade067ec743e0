"""Stage ``select_landmarks`` (stage one of focused inference): keep the landmarks that matter for the task.

Reads ``graph`` (required), ``ingest`` (laser scans, extrinsics) and ``detect`` (detections) when present;
writes ``focused.json`` and ``risk.parquet`` (schemas in ``docs/artifacts.md``).

Public API (no run folder needed):
    LandmarkInputs.load(ctx, cfg) / LandmarkInputs.from_pieces(loaded, scans, T_base_laser, detections, cfg)
    choose(inputs, cfg, with_risk=True) -> LandmarkChoice
    SelectLandmarksConfig, STAGE
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Final

from pipeline.lazy import lazy_exports
from pipeline.stage import Option, Stage, lazy
from stages.select_landmarks.config import STRATEGIES, SelectLandmarksConfig

if TYPE_CHECKING:
    from stages.select_landmarks.core import LandmarkChoice, LandmarkInputs, choose

__getattr__ = lazy_exports(__name__, {"core": ("LandmarkChoice", "LandmarkInputs", "choose")})


def blueprint() -> Any:
    """The layout of ``select_landmarks.rrd``: the map from above, risk along the path, picks, summary."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="/select_landmarks", name="focused landmarks and risk"),
            rrb.Vertical(
                rrb.TimeSeriesView(origin="/select_landmarks/risk", name="log10 collision probability"),
                rrb.TimeSeriesView(origin="/select_landmarks/max_collision_log10", name="max log10 P per pick"),
                rrb.TextDocumentView(origin="/select_landmarks/summary", name="summary"),
            ),
            column_shares=[3, 2],
        ),
        rrb.TimePanel(play_state="paused", timeline="selection_step"),
    )


STAGE: Final = Stage(
    name="select_landmarks",
    config_type=SelectLandmarksConfig,
    run=lazy("stages.select_landmarks.stage:run"),
    inputs=("graph",),
    optional_inputs=("ingest", "detect"),
    version="1",
    blueprint=blueprint,
    help="Stage one: keep the --budget (alpha) landmarks that matter most (collision | mutual-information | "
    "leverage | uniform | random | all).",
    options=(
        Option("--strategy", "strategy", "Selection strategy (see configs/default.yaml for the choices)."),
        Option("--budget", "budget", "How many to keep.", int, min=0),
    ),
)

__all__ = ["STAGE", "STRATEGIES", "LandmarkChoice", "LandmarkInputs", "SelectLandmarksConfig", "blueprint", "choose"]
