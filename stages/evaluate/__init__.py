"""Stage ``evaluate``: the six cases of Mu et al. Table I and other strategy pairs on one run, Monte Carlo LQG
navigation with each case's map, and a report (``report.md``/``report.html`` with figures).

Public API:
    STAGE, EvaluateConfig.
    EvalInputs; run_case(inputs, case, optimal) -> CaseResult; run_all(inputs, cases).
    cases_table(results) -> pyarrow.Table (``cases.parquet``).
    ``stages.evaluate.cases.cases(cfg) -> list[Case]`` (not re-exported here: its name is its module's).
    report_lines(summary): the report path and headline ``focusmap run`` prints at its end; headline_text(head).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
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


def _number(head: Mapping[str, object], key: str) -> float | None:
    value = head.get(key)
    return float(value) if isinstance(value, int | float) and math.isfinite(value) else None


def headline_text(head: Mapping[str, object], navigation_skipped: str | None = None) -> str:
    """The headline row (focus, info) in one line, each figure that was not computed said in words instead (no
    ``nan``): ``navigation_skipped`` is why the collision rate is missing (``no walls``, ``evaluate.trials=0``)."""
    entropy, observed, prior = (_number(head, k) for k in ("focused_entropy", "focused_entropy_observed",
                                                            "focused_entropy_prior"))  # fmt: skip
    unobserved = head.get("unobserved_focused_landmarks")
    split = (
        f" ({observed:.1f} observed + {prior:.1f} prior of {unobserved} unobserved)"
        if isinstance(unobserved, int) and unobserved > 0 and observed is not None and prior is not None
        else ""
    )
    parts = [
        f"focused entropy {entropy:.1f} nats{split}" if entropy is not None else "focused entropy not computed",
        f"focused error {100 * err:.1f} cm"
        if (err := _number(head, "focused_error_m")) is not None
        else "focused error not computed (no focused landmark observed)",
        f"max P(collision) {p:.2g}"
        if (p := _number(head, "max_collision_probability")) is not None
        else "max P(collision) not computed (no laser clearances)",
    ]
    rate, low, high = (_number(head, k) for k in ("collision_rate", "collision_ci_low", "collision_ci_high"))
    if rate is not None and low is not None and high is not None:
        parts.append(f"collision rate {rate:.3f} [{low:.3f}, {high:.3f}]")
    else:
        parts.append(f"navigation not simulated ({navigation_skipped or 'no trials'})")
    return f"headline ({head.get('case')}): " + ", ".join(parts)


def report_lines(summary: Summary) -> list[str]:
    """The evaluation report's path, its headline row (focus, info), and a line when the full map failed health
    checks, from evaluate's summary."""
    lines = []
    if summary.get("report"):
        lines.append(f"report: {summary['report']}")
    head = summary.get("headline")
    if isinstance(head, dict) and head:
        skipped = summary.get("navigation_skipped")
        lines.append(headline_text(head, skipped if isinstance(skipped, str) else None))
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
    "headline_text",
    "report_lines",
    "run_all",
    "run_case",
]
