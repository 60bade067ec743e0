"""Stage ``graph``: the full SLAM factor graph of the run (odometry + every tag measurement), optimised,
with the marginal covariance of every pose and landmark; and ``import_run`` for existing graph files.

Public API:
    STAGE: the stage value for the registry.
    GraphConfig: its settings.
    import_run(path, out_dir, name) -> RunFolder: a run folder whose graph stage reads a g2o / GTSAM file.
    load_graph(graph_input) -> LoadedGraph and build_reduced(loaded, keep_factor_indices) (in ``stages.graph.load``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Final

from pipeline.lazy import lazy_exports
from pipeline.stage import Option, Stage, Summary, lazy, summary_notes
from stages.graph.config import GRAPH_SOURCE, GraphConfig

if TYPE_CHECKING:
    from stages.graph.imports import import_run
    from stages.graph.load import LoadedGraph, build_reduced, load_graph

__getattr__ = lazy_exports(
    __name__, {"imports": ("import_run",), "load": ("LoadedGraph", "build_reduced", "load_graph")}
)


def blueprint() -> Any:
    """The layout of ``graph.rrd``: the map from above, and the summary."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="/graph", name="full graph"),
            rrb.TextDocumentView(origin="/graph/summary", name="summary"),
            column_shares=[3, 1],
        ),
        rrb.TimePanel(play_state="paused", timeline="time"),
    )


STRICT: Final = Option(
    "--strict",
    "strict",
    "Stop with an error when a health check fails (fit far outside the noise models, tag scale off its prior, "
    "iteration cap, moved tags, trajectory against dead reckoning, wheel scale).",
    kind=bool,
)
"""The ``--strict`` option of the graph and optimize commands (their ``strict`` setting)."""


def remarks(summary: Summary) -> list[tuple[str, str]]:
    """The notes, the model ``auto`` chose (and why), the odometry calibration ``auto`` turned on (and why), and one
    ``warning`` per failed health check."""
    out = summary_notes(summary)
    choice = summary.get("model_choice")
    if isinstance(choice, dict) and choice.get("setting") == "auto":
        out.append(("note", f"graph model {choice.get('model')} (graph.model=auto): {choice.get('reason')}"))
    calibration = summary.get("odometry_calibration")
    decision = calibration.get("decision") if isinstance(calibration, dict) else None
    if isinstance(decision, dict) and decision.get("applied"):
        out.append(("note", f"odometry calibration on (graph.odometry_calibration=auto): {decision.get('reason')}"))
    if isinstance(decision, dict) and decision.get("skipped"):
        out.append(("note", f"odometry calibration off (graph.odometry_calibration=auto): {decision.get('reason')}"))
    growth = summary.get("odometry_covariance_growth")
    if isinstance(growth, dict) and growth.get("model") == "added":
        out.append(
            (
                "note",
                "the odometry's pose covariances grow by plain addition, without the position-heading terms a "
                "propagation through the motion has (propagated, they would be indefinite: median "
                f"{growth.get('indefinite_median_propagated')}): each odometry factor's noise is their difference",
            )
        )
    block = calibration if isinstance(calibration, dict) else {}
    scale = block.get("odometry_covariance_scale_by_dimension")
    if summary.get("odometry_noise") == "settings" and isinstance(scale, list) and not block.get("estimated"):
        dims = ("x", "y", "θ") if len(scale) == 3 else ("all",)
        scaled = ", ".join(f"{v:.3g} ({d})" for v, d in zip(scale, dims, strict=True) if isinstance(v, float))
        out.append(
            (
                "note",
                "the odometry has no covariances, so its noise is the settings' (graph.odometry_sigma_*) scaled to "
                f"the data (graph.noise_estimate=auto): its variances scaled by {scaled}",
            )
        )
    from stages.graph.rig import rig_remarks  # gtsam: loaded only once the stage has run

    out += rig_remarks(summary.get("rig_calibration"))
    health = summary.get("health")
    warnings = health.get("warnings") if isinstance(health, dict) else None
    if isinstance(warnings, list):
        out += [("warning", str(w)) for w in warnings]
    return out


STAGE: Final = Stage(
    name="graph",
    config_type=GraphConfig,
    run=lazy("stages.graph.stage:run"),
    inputs=("ingest", "detect"),
    source_kinds=(GRAPH_SOURCE,),
    version="1",
    blueprint=blueprint,
    help="Build the full factor graph (odometry + every tag), optimise it and compute every marginal.",
    options=(STRICT,),
    remarks=remarks,
)

__all__ = ["STAGE", "GraphConfig", "LoadedGraph", "blueprint", "build_reduced", "import_run", "load_graph"]
