"""Stage ``select_measurements`` (stage two of focused inference): keep the tag measurements that matter.

Reads ``graph`` and ``select_landmarks`` (``focused.json``; not needed with ``focus: all``); writes
``selected.parquet`` (schema in ``docs/artifacts.md``). All odometry and priors are always kept.

Public API (no run folder needed):
    linear_system(loaded) -> LinearSystem
    choose(loaded, focused_tag_ids, cfg, system=None) -> MeasurementChoice
    MeasurementChoice.keep_factor_indices(loaded) -> list[int]   (for stages.graph.load.build_reduced)
    focused_covariances(system, base, picks, focused_vars, landmark_prior_sigma) -> (blocks, entropy)
    SelectMeasurementsConfig, STAGE
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Final

from pipeline.lazy import lazy_exports
from pipeline.stage import Option, Stage, Summary, lazy, summary_notes
from stages.select_measurements.config import STRATEGIES, SelectMeasurementsConfig

if TYPE_CHECKING:
    from stages.select_measurements.core import (
        MeasurementChoice,
        candidate_factors,
        choose,
        focused_covariances,
        focused_variables,
        linear_system,
    )

__getattr__ = lazy_exports(
    __name__,
    {
        "core": (
            "MeasurementChoice",
            "candidate_factors",
            "choose",
            "focused_covariances",
            "focused_variables",
            "linear_system",
        )
    },
)


def blueprint() -> Any:
    """The layout of ``select_measurements.rrd``: the map, the focused entropy per step, the summary."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="/select_measurements", name="kept measurements"),
            rrb.Vertical(
                rrb.TimeSeriesView(origin="/select_measurements/entropy", name="focused entropy (nats)"),
                rrb.TimeSeriesView(origin="/select_measurements/gain", name="gain per pick (nats)"),
                rrb.TextDocumentView(origin="/select_measurements/summary", name="summary"),
            ),
            column_shares=[3, 2],
        ),
        rrb.TimePanel(play_state="paused", timeline="selection_step"),
    )


def remarks(summary: Summary) -> list[tuple[str, str]]:
    """The notes and a ``warning`` when the greedy's running entropy drifted from the exact one."""
    warnings = summary.get("warnings")
    return summary_notes(summary) + [("warning", str(w)) for w in (warnings if isinstance(warnings, list) else [])]


STAGE: Final = Stage(
    name="select_measurements",
    config_type=SelectMeasurementsConfig,
    run=lazy("stages.select_measurements.stage:run"),
    inputs=("graph",),
    optional_inputs=("select_landmarks",),
    version="1",
    blueprint=blueprint,
    help="Stage two: keep the --budget (K) tag measurements that best localise the focused landmarks (information "
    "| leverage | uniform | random | all).",
    remarks=remarks,
    options=(
        Option("--strategy", "strategy", "Selection strategy (see configs/default.yaml for the choices)."),
        Option("--budget", "budget", "How many to keep.", int, min=0),
        Option("--focus", "focus", "'selected': the focused landmarks of stage one; 'all': every landmark."),
    ),
)

__all__ = [
    "STAGE",
    "STRATEGIES",
    "MeasurementChoice",
    "SelectMeasurementsConfig",
    "blueprint",
    "candidate_factors",
    "choose",
    "focused_covariances",
    "focused_variables",
    "linear_system",
]
