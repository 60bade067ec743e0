"""Stage ``optimize``: the reduced graph (odometry + prior + the selected measurements of the focused landmarks),
re-optimised with Levenberg-Marquardt, with marginals, the focused entropy, errors against the full graph and the
ground truth, the collision risk recomputed with the reduced map, and the size of the map against the full one.

Public API:
    STAGE, OptimizeConfig.
    solve_reduced(loaded, focused_tag_ids, selected_factor_indices, ...) -> ReducedMap (``stages.optimize.core``).
    landmark_errors(estimate, reference, tag_ids), mean_or_nan(values), map_size(loaded, reduced),
    gaussian_entropy(cov), solve_settings(cfg).
    read_reduced(optimize_input, full_graph, focused_tag_ids) -> ReducedMap: optimize's result read back.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any, Final

from pipeline.errors import InputError
from pipeline.lazy import lazy_exports
from pipeline.stage import Option, Stage, lazy
from stages.graph import STRICT, remarks
from stages.optimize.config import OptimizeConfig

if TYPE_CHECKING:
    from stages.optimize.artifacts import read_reduced
    from stages.optimize.core import (
        ReducedMap,
        gaussian_entropy,
        landmark_errors,
        local_map,
        map_size,
        mean_or_nan,
        solve_reduced,
        solve_settings,
    )

__getattr__ = lazy_exports(
    __name__,
    {
        "artifacts": ("read_reduced",),
        "core": (
            "ReducedMap",
            "gaussian_entropy",
            "landmark_errors",
            "local_map",
            "map_size",
            "mean_or_nan",
            "solve_settings",
            "solve_reduced",
        ),
    },
)


def _truth_file(path: Path) -> str:
    """``--truth``: an existing file, as an absolute path (a run folder keeps working from any directory)."""
    if not path.is_file():
        raise InputError(
            f"ground truth {str(path)!r} not found; pass an existing truth YAML (docs/evaluate.md, 'Ground truth "
            "file') or .ground_truth.json to --truth"
        )
    return json.dumps(str(path.resolve()))


TRUTH: Final = Option(
    "--truth",
    "truth_file",
    "Ground truth of the recording: a truth YAML (tags, poses as TUM, walls; docs/evaluate.md) or a simulator "
    ".ground_truth.json; default: <name>.ground_truth.json or <name>.truth.yaml beside the recording.",
    Path,
    value=_truth_file,
    on_run=True,
)
"""The ``--truth`` option of optimize, evaluate, run and batch (their ``truth_file`` setting)."""


def blueprint() -> Any:
    """The layout of ``optimize.rrd``: the maps from above, risk along the path, the summary."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="/optimize", name="reduced vs full map"),
            rrb.Vertical(
                rrb.TimeSeriesView(origin="/optimize/risk", name="collision probability"),
                rrb.TextDocumentView(origin="/optimize/summary", name="summary"),
            ),
            column_shares=[3, 1],
        ),
        rrb.TimePanel(play_state="paused", timeline="time"),
    )


STAGE: Final = Stage(
    name="optimize",
    config_type=OptimizeConfig,
    run=lazy("stages.optimize.stage:run"),
    inputs=("graph", "select_measurements"),
    optional_inputs=("select_landmarks", "ingest", "detect"),
    version="1",
    blueprint=blueprint,
    help="Re-optimise the reduced graph (focused landmarks, selected measurements); entropy, errors, risk, size.",
    options=(STRICT, TRUTH),
    remarks=remarks,
)

__all__ = [
    "STAGE",
    "TRUTH",
    "OptimizeConfig",
    "ReducedMap",
    "blueprint",
    "gaussian_entropy",
    "landmark_errors",
    "local_map",
    "map_size",
    "mean_or_nan",
    "read_reduced",
    "solve_reduced",
    "solve_settings",
]
