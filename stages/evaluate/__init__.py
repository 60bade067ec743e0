"""Stage ``evaluate``: the six cases of Mu et al. Table I and other strategy pairs on one run, Monte Carlo LQG
navigation with each case's map, and a report (``report.md``/``report.html`` with figures).

Public API:
    STAGE, EvaluateConfig.
    EvalInputs; run_case(inputs, case, optimal) -> CaseResult; run_all(inputs, cases).
    cases_table(results) -> pyarrow.Table (``cases.parquet``).
    ``stages.evaluate.cases.cases(cfg) -> list[Case]`` (not re-exported here: its name is its module's).
    report_lines(summary): the report path and headline ``focusmap run`` prints at its end.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Final

from pipeline.lazy import lazy_exports
from pipeline.stage import Stage, Summary, lazy, summary_notes
from stages.evaluate.config import EvaluateConfig
from stages.optimize import TRUTH

if TYPE_CHECKING:
    from stages.evaluate.cases import TABLE_I, Case, CaseResult, EvalInputs, cases_table, run_all, run_case

__getattr__ = lazy_exports(
    __name__, {"cases": ("TABLE_I", "Case", "CaseResult", "EvalInputs", "cases_table", "run_all", "run_case")}
)


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


def remarks(summary: Summary) -> list[tuple[str, str]]:
    """The notes, then one ``warning`` per line of the summary's ``warnings`` (cases skipped, risk model against the
    simulation)."""
    warnings = summary.get("warnings")
    return summary_notes(summary) + ([("warning", str(w)) for w in warnings] if isinstance(warnings, list) else [])


def report_lines(summary: Summary) -> list[str]:
    """The evaluation report's path, its headline row (focus, info), and a line when the full map failed health
    checks, from evaluate's summary."""
    lines = []
    if summary.get("report"):
        lines.append(f"report: {summary['report']}")
    head = summary.get("headline")
    if isinstance(head, dict) and head:

        def num(key: str) -> float:
            value = head.get(key)
            return float(value) if isinstance(value, int | float) else float("nan")

        unobserved = head.get("unobserved_focused_landmarks")
        split = (
            f" ({num('focused_entropy_observed'):.1f} observed + {num('focused_entropy_prior'):.1f} prior of "
            f"{unobserved} unobserved)"
            if isinstance(unobserved, int) and unobserved > 0
            else ""
        )
        lines.append(
            f"headline ({head.get('case')}): focused entropy {num('focused_entropy'):.1f} nats{split}, "
            f"focused error {100 * num('focused_error_m'):.1f} cm, "
            f"max P(collision) {num('max_collision_probability'):.2g}, "
            f"collision rate {num('collision_rate'):.3f} "
            f"[{num('collision_ci_low'):.3f}, {num('collision_ci_high'):.3f}]"
        )
    failed = summary.get("map_health_warnings")
    if isinstance(failed, int) and failed > 0:
        lines.append(
            f"the full map failed {failed} health check(s) of the graph stage (its warning lines above, and at the "
            "top of the report): its figures are doubtful"
        )
    return lines


STAGE: Final = Stage(
    name="evaluate",
    config_type=EvaluateConfig,
    run=lazy("stages.evaluate.stage:run"),
    inputs=("graph", "select_landmarks", "select_measurements"),
    optional_inputs=("ingest", "detect", "optimize"),
    version="1",
    blueprint=blueprint,
    help="Compare the six cases of Mu et al. Table I (and other strategy pairs), navigate on each map, report.",
    report_lines=report_lines,
    remarks=remarks,
    options=(TRUTH,),
)

__all__ = [
    "STAGE",
    "TABLE_I",
    "Case",
    "CaseResult",
    "EvalInputs",
    "EvaluateConfig",
    "blueprint",
    "cases_table",
    "report_lines",
    "run_all",
    "run_case",
]
