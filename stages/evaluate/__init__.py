"""Stage ``evaluate``: the six cases of Mu et al. Table I and other strategy pairs on one run, Monte Carlo LQG
navigation with each case's map, and a report (``report.md``/``report.html`` with figures).

Public API:
    STAGE, EvaluateConfig.
    cases(cfg) -> list[Case]; EvalInputs; run_case(inputs, case, optimal) -> CaseResult; run_all(inputs, cases).
    cases_table(results) -> pyarrow.Table (``cases.parquet``).
"""

from __future__ import annotations

from typing import Any, Final

from pipeline.stage import Stage
from stages.evaluate.cases import TABLE_I, Case, CaseResult, EvalInputs, cases, cases_table, run_all, run_case
from stages.evaluate.config import EvaluateConfig
from stages.evaluate.stage import run


def blueprint() -> Any:
    """The layout of ``evaluate.rrd``: the case maps from above (toggle the case entities) and the summary."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="/evaluate", name="cases"),
            rrb.TextDocumentView(origin="/evaluate/summary", name="summary"),
            column_shares=[3, 1],
        ),
    )


STAGE: Final = Stage(
    name="evaluate",
    config_type=EvaluateConfig,
    run=run,
    inputs=("graph", "select_landmarks", "select_measurements"),
    optional_inputs=("ingest", "detect", "optimize"),
    version="1",
    blueprint=blueprint,
    help="Compare the six cases of Mu et al. Table I (and other strategy pairs), navigate on each map, report.",
)

__all__ = [
    "STAGE",
    "TABLE_I",
    "Case",
    "CaseResult",
    "EvalInputs",
    "EvaluateConfig",
    "blueprint",
    "cases",
    "cases_table",
    "run_all",
    "run_case",
]
