"""The evaluate report: Table I layout plus the extra columns, figures as PNG beside it, markdown and HTML."""

from __future__ import annotations

import base64
import html
import math
from collections.abc import Sequence
from concurrent.futures import Executor, Future
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from stages.evaluate import headline_text
from stages.evaluate.analysis import CHI2_2_95
from stages.evaluate.artifacts import LABEL, ORACLE_ERROR_ALL_M, WHY_COLUMNS
from stages.evaluate.cases import HOW_TO_GIVE_WALLS, CaseResult, EvalInputs
from stages.evaluate.figures import (
    MapPanel,
    MapsFigure,
    NavigationFigure,
    NavigationPanel,
    draw_in_worker,
    pyplot,
    save,
)
from stages.evaluate.risk_check import FACTOR, direction

FloatArray = npt.NDArray[np.float64]

TABLE_COLUMNS: tuple[tuple[str, str, str], ...] = (
    ("label", "case", "{}"),
    ("observed_landmarks", "No. observed lms", "{}"),
    ("focused_landmarks", "No. focused lms", "{}"),
    ("focused_entropy_observed", "Entropy on observed focused lms (nats) [unobserved]", "entropy"),
    ("focused_entropy_prior", "+ prior of unobserved (nats)", "{:.2f}"),
    ("error_all_m", "Error on all observed lms (m)", "{:.4f}"),
    ("focused_error_m", "Error on focused lms (m)", "{:.4f}"),
    ("measurements", "measurements", "{}"),
    ("max_collision_probability", "max P(collision)", "{:.2e}"),
    ("mean_collision_probability", "mean P(collision)", "{:.2e}"),
    ("collision_rate", "collision rate [95% CI]", "rate"),
    ("rms_tracking_error_m", "RMS tracking (m)", "{:.3f}"),
    ("selection_s", "selection (s)", "{:.2f}"),
    ("bytes_fraction", "bytes vs full", "{:.3f}"),
)


def _fmt(row: dict[str, Any], key: str, fmt: str) -> str:
    v = row.get(key)
    if fmt == "rate":
        if not row.get("trials"):
            return "not run"
        return f"{row['collision_rate']:.3f} [{row['collision_ci_low']:.3f}, {row['collision_ci_high']:.3f}]"
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    if fmt == "entropy":
        return f"{v:.2f} [{row.get('unobserved_focused_landmarks', '?')}]"
    return fmt.format(v)


def expectation_checks(results: Sequence[CaseResult]) -> list[str]:
    """The issue's expectation, checked: focus,info against focus,DS / full,info / full,DS, and its gap to 1-2."""
    rows = {r.case.name: r.row for r in results}
    if "focus_info" not in rows:
        return []
    fi = rows["focus_info"]
    lines = []
    for metric, name in (
        ("focused_entropy", "focused entropy"),
        ("focused_error_m", "focused error"),
        ("focused_error_aligned_m", "focused error after rigid alignment"),
        ("max_collision_probability", "max collision probability"),
        ("collision_rate", "collision rate"),
    ):
        for other in ("focus_ds", "full_info", "full_ds"):
            if other not in rows:
                continue
            a, b = fi.get(metric, float("nan")), rows[other].get(metric, float("nan"))
            if not (np.isfinite(a) and np.isfinite(b)):
                lines.append(f"- {name}: focus,info vs {other}: not available")
                continue
            if metric == "collision_rate":
                hi_a, lo_b = fi["collision_ci_high"], rows[other]["collision_ci_low"]
                hi_b, lo_a = rows[other]["collision_ci_high"], fi["collision_ci_low"]
                overlap = not (hi_a < lo_b or hi_b < lo_a)
                verdict = (
                    "lower" if a < b and not overlap else ("indistinguishable (CIs overlap)" if overlap else "HIGHER")
                )
            else:
                verdict = "lower (as expected)" if a < b else ("equal" if a == b else "HIGHER (not as expected)")
            lines.append(f"- {name}: focus,info {a:.4g} vs {other} {b:.4g}: {verdict}")
    for ref in ("optimal", "focus_all"):
        if ref in rows:
            lines.append(
                f"- gap to {ref}: entropy {fi['focused_entropy'] - rows[ref]['focused_entropy']:+.2f} nats, "
                f"focused error {fi['focused_error_m'] - rows[ref]['focused_error_m']:+.4f} m"
            )
    return lines


def markdown_table(results: Sequence[CaseResult]) -> str:
    """The table, Table I columns first."""
    head = "| " + " | ".join(h for _, h, _ in TABLE_COLUMNS) + " |"
    sep = "|" + "|".join("---" for _ in TABLE_COLUMNS) + "|"
    body = ["| " + " | ".join(_fmt(r.row, k, f) for k, _, f in TABLE_COLUMNS) + " |" for r in results]
    return "\n".join([head, sep, *body])


def figures(
    inputs: EvalInputs,
    results: Sequence[CaseResult],
    out_dir: Path,
    n_sigma: float,
    pool: Executor | None = None,
) -> list[str]:
    """Draw maps.png, risk.png, entropy.png (and navigation.png, margin.png) into ``out_dir``; returns their file
    names. With ``pool`` (evaluate's worker process) the two grid figures, maps and navigation, are drawn there while
    this process draws the others."""
    maps, nav = _maps_spec(inputs, results, n_sigma), _navigation_spec(inputs, results)
    futures: list[Future[str] | None] = []
    if pool is not None:
        futures = [None if spec is None else pool.submit(draw_in_worker, spec, out_dir) for spec in (maps, nav)]
    risk = _risk_figure(inputs, results, out_dir)
    entropy = _entropy_figure(results, out_dir)
    margin = margin_figure(inputs, results, out_dir)
    if pool is None:
        grids = [None if spec is None else draw_in_worker(spec, out_dir) for spec in (maps, nav)]
    else:
        grids = [None if f is None else f.result() for f in futures]
    return [name for name in (grids[0], risk, entropy, grids[1], margin) if name is not None]


def _walls_array(inputs: EvalInputs) -> FloatArray | None:
    walls = inputs.truth.walls if inputs.truth is not None else None
    return None if walls is None else np.asarray(walls, dtype=float).reshape(-1, 4)


def _maps_spec(inputs: EvalInputs, results: Sequence[CaseResult], n_sigma: float) -> MapsFigure:
    """What maps.png draws: each case's landmark map with its ellipses, collision-focused landmarks in red."""
    panels = [
        MapPanel(
            r.landmark_map.tag_ids,
            r.landmark_map.positions,
            r.landmark_map.covariances,
            f"{r.row['label']}: H={r.row['focused_entropy']:.1f}, {r.row['measurements']} meas.",
        )
        for r in results
    ]
    geo = inputs.landmarks.geometry
    return MapsFigure(_walls_array(inputs), geo.poses, frozenset(inputs.focus), panels, n_sigma)


def _risk_figure(inputs: EvalInputs, results: Sequence[CaseResult], out_dir: Path) -> str:
    """risk.png: the risk model's margin to the obstacle in σ along the path (P = Φ(−z)), one line per case."""
    geo = inputs.landmarks.geometry
    fig, ax = pyplot().subplots(figsize=(10, 3.8))
    t = (geo.stamps_ns - geo.stamps_ns[0]) / 1e9
    for r in results:
        z = r.risk.z if r.risk.z is not None else np.full(len(t), np.nan)
        ax.plot(t, np.where(np.isfinite(z), z, np.nan), lw=0.9, label=r.row["label"])
    ax.axhline(3.0, color="0.5", lw=0.6, ls="--")
    ax.set_yscale("log")
    ax.set_xlabel("time along the path (s)")
    ax.set_ylabel("margin to the obstacle (σ of the belief)")
    ax.legend(fontsize=7, ncol=3)
    return save(fig, out_dir, "risk.png")


def _entropy_figure(results: Sequence[CaseResult], out_dir: Path) -> str | None:
    """entropy.png: the focused entropy per greedy step of the cases that have one (None: no such case)."""
    greedy = [r for r in results if r.measurement is not None and r.measurement.entropy_per_step() is not None]
    if not greedy:
        return None
    fig, ax = pyplot().subplots(figsize=(7, 3.8))
    for r in greedy:
        assert r.measurement is not None
        steps = r.measurement.entropy_per_step()
        assert steps is not None
        ax.plot(np.arange(len(steps) + 1), [r.measurement.entropy_before, *steps], label=r.row["label"])
    ax.set_xlabel("greedy step (measurements kept)")
    ax.set_ylabel("entropy of the selection's focused set (nats)")
    ax.legend(fontsize=8)
    return save(fig, out_dir, "entropy.png")


def _navigation_spec(inputs: EvalInputs, results: Sequence[CaseResult]) -> NavigationFigure | None:
    """What navigation.png draws: sample navigation trials of each case (None: navigation did not run)."""
    if inputs.navigation is None or not any(r.navigation is not None for r in results):
        return None
    panels = [
        NavigationPanel(None, None)
        if r.navigation is None
        else NavigationPanel(
            r.navigation.sample_paths,
            f"{r.row['label']}: {r.navigation.collisions}/{r.navigation.trials} collisions",
        )
        for r in results
    ]
    return NavigationFigure(_walls_array(inputs), inputs.navigation.path.poses, panels)


def markdown_report(
    inputs: EvalInputs,
    results: Sequence[CaseResult],
    images: Sequence[str],
    notes: Sequence[str],
    map_warnings: Sequence[str] = (),
    headline_warnings: Sequence[str] = (),
) -> str:
    """``report.md``. ``map_warnings``: the full graph's failed health checks, shown before any figure, since every
    case is cut from that map; ``headline_warnings``: lines that make the headline doubtful (a reduced map far worse
    than its own covariance), shown under it."""
    ref = results[0].row["error_reference"] if results else "?"
    nav = inputs.navigation
    lines = [
        "# focusmap evaluation: Mu et al. Table I on this run",
        "",
        *map_health_lines(map_warnings),
        f"Navigation regime: {inputs.cfg.regime}.",
        "",
        f"Budgets: alpha = {inputs.alpha} landmarks, K = {inputs.K} measurements. "
        f"Focused landmarks (entropy and focused error): the {len(inputs.focus)} collision-focused landmarks "
        "(Alg. 2) for every case. Entropy: ½ log det(2πe Σ_F) nats over the focused landmarks the case observes, "
        "with the number it does not observe in brackets; each of those enters Table I's entropy with a fixed "
        "term of its weak prior (optimize.unobserved_sigma_m per dimension), shown separately (Table I's figure, "
        "`focused_entropy` in cases.parquet, is the sum of the two columns). Errors: mean planar distance to "
        f"{'the ground truth' if ref == 'ground_truth' else 'case 1 (optimal)'}.",
        "",
        markdown_table(results),
        "",
    ]
    skipped = inputs.navigation_skipped
    if results:
        head = next((r.row for r in results if r.case.name == "focus_info"), results[0].row)
        lines += [f"**{headline_text(head, skipped.reason if skipped is not None else None)}**", ""]
        lines += [*(f"- warning: {w}" for w in headline_warnings), *([""] if headline_warnings else [])]
    if nav is None:
        reason = skipped.reason if skipped is not None else "no trials"
        why = (
            f"the run has no walls for the robot to collide with ({skipped.why}); {HOW_TO_GIVE_WALLS}"
            if skipped is not None and skipped.why
            else "the trials were switched off"
        )
        lines += [
            f"Navigation not simulated ({reason}): {why}. Not computed, so shown as – or 'not run' here and null "
            "in cases.parquet: the collision rate and its interval, the collisions, the RMS tracking and estimation "
            "errors, the filter NEES and the navigation margin columns.",
            "",
        ]
    else:
        p = nav.params.robot
        world = (
            "the ground truth"
            if nav.world == "ground_truth"
            else "no ground truth: the full map stands in for it, its path, landmarks and laser grid"
        )
        lines += [
            f"Navigation: {nav.params.trials} seeded LQG trials per case. Each case's robot plans along its own "
            "trajectory estimate and localises against its own landmarks (its map frame); it moves in the world "
            f"({world}"
            f"; {len(nav.path)} steps of {nav.path.dt_s} s), walls: {nav.obstacles.kind}, robot radius "
            f"{p.robot_radius_m} m (true path clearance {nav.min_clearance_m:.3f} m). The robot is the risk model's: "
            f"motion noise {p.speed_sigma_mps:.4f} m/s, {p.yaw_rate_sigma_radps:.4f} rad/s per control period, "
            f"measurement noise {p.bearing_sigma_rad:.4f} rad / {p.range_sigma_m:.4f} m. "
            "Collision rate with a 95 % Wilson interval; filter NEES per dof in the margin table.",
            "",
        ]
    lines += ["## Expectation (focus,info best of the budgeted cases)", "", *expectation_checks(results), ""]
    lines += risk_check_section(results)
    lines += why_section(inputs, results)
    if notes:
        lines += ["## Notes", "", *notes, ""]
    lines += ["## Figures", ""] + [f"![{name}]({name})" for name in images]
    return "\n".join(lines) + "\n"


def map_health_lines(warnings: Sequence[str]) -> list[str]:
    """The report's paragraph on the full map's health checks (the graph stage's; docs/graph.md "Health checks")."""
    if not warnings:
        return ["The full map passed every health check of the graph stage.", ""]
    return [
        f"**The full map failed {len(warnings)} health check(s) of the graph stage: every case below is cut from it, "
        "so read its figures with these in mind.**",
        "",
        *(f"- warning: {w}" for w in warnings),
        "",
    ]


def risk_check_line(row: dict[str, Any]) -> str:
    """One case: the risk model's path collision probability beside the simulated rate, flagged where they
    disagree by more than :data:`~stages.evaluate.risk_check.FACTOR` (rule: :mod:`stages.evaluate.risk_check`)."""
    low, high = row.get("predicted_collision_low", math.nan), row.get("predicted_collision_high", math.nan)
    predicted = (
        f"predicted P(collision on the path) in [{low:.2g}, {high:.2g}] (riskiest keyframe, union bound)"
        if math.isfinite(low) and math.isfinite(high)
        else "no predicted P(collision) (no laser)"
    )
    if not row.get("trials"):
        return f"- {row[LABEL]}: {predicted}; not simulated"
    rate = f"simulated {row['collision_rate']:.3f} [{row['collision_ci_low']:.3f}, {row['collision_ci_high']:.3f}]"
    flag = row.get("risk_disagrees")
    if flag is None:
        verdict = "not comparable"
    elif flag:
        side = direction(low, high, row["collision_ci_low"], row["collision_ci_high"])
        verdict = f"**DISAGREE**: the simulated rate is more than {FACTOR:g}x {side} the prediction"
    else:
        verdict = f"consistent (the interval reaches within {FACTOR:g}x of the bracket)"
    return f"- {row[LABEL]}: {predicted}; {rate}: {verdict}"


def risk_check_section(results: Sequence[CaseResult]) -> list[str]:
    """Markdown: per case, the risk model against the simulated collision rate."""
    if not results:
        return []
    return [
        "## Risk model against the simulation",
        "",
        "Per case, the risk model's probability that the robot collides somewhere on the path, bracketed by the "
        "riskiest keyframe's P (lower bound) and min(1, the sum over keyframes) (union bound), beside the "
        f"simulated collision rate with its 95 % Wilson interval. Flagged where the interval lies more than "
        f"{FACTOR:g}x outside the bracket.",
        "",
        *(risk_check_line(r.row) for r in results),
        "",
    ]


def html_report(markdown_text: str, out_dir: Path) -> str:
    """``report.html``: the markdown's table and text, images embedded (base64)."""
    body: list[str] = []
    in_table = False
    for line in markdown_text.splitlines():
        if line.startswith("|"):
            cells = [c.strip() for c in line.strip("|").split("|")]
            if set("".join(cells)) <= set("-"):
                continue
            tag = "th" if not in_table else "td"
            if not in_table:
                body.append("<table>")
                in_table = True
            body.append("<tr>" + "".join(f"<{tag}>{html.escape(c)}</{tag}>" for c in cells) + "</tr>")
            continue
        if in_table:
            body.append("</table>")
            in_table = False
        if line.startswith("!["):
            name = line[line.index("(") + 1 : line.index(")")]
            data = base64.b64encode((out_dir / name).read_bytes()).decode()
            body.append(
                f'<p><img alt="{html.escape(name)}" src="data:image/png;base64,{data}" style="max-width:100%"></p>'
            )
        elif line.startswith("## "):
            body.append(f"<h2>{html.escape(line[3:])}</h2>")
        elif line.startswith("# "):
            body.append(f"<h1>{html.escape(line[2:])}</h1>")
        elif line.startswith("- "):
            body.append(f"<li>{html.escape(line[2:])}</li>")
        elif line.strip():
            body.append(f"<p>{html.escape(line)}</p>")
    if in_table:
        body.append("</table>")
    style = (
        "body{font-family:sans-serif;max-width:1400px;margin:2em auto}table{border-collapse:collapse;font-size:13px}"
        "td,th{border:1px solid #bbb;padding:3px 6px;text-align:right}th{background:#eee}"
    )
    head = f"<head><meta charset='utf-8'><title>focusmap evaluation</title><style>{style}</style></head>"
    return f"<!doctype html><html>{head}<body>{''.join(body)}</body></html>\n"


def _g(v: Any, fmt: str = "{:.4f}") -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–" if not (isinstance(v, float) and math.isinf(v)) else "inf"
    return fmt.format(v)


def _order(rows: dict[str, dict[str, Any]], key: str, names: Sequence[str]) -> str:
    have = [n for n in names if n in rows and math.isfinite(rows[n].get(key, float("nan")))]
    have.sort(key=lambda n: rows[n][key])
    return " < ".join(f"{n} {rows[n][key]:.4f}" for n in have)


def why_findings(inputs: EvalInputs, results: Sequence[CaseResult]) -> dict[str, Any]:
    """The computed part of the "why" analysis, for summary.json and the report's sentences."""
    rows = {r.case.name: r.row for r in results}
    out: dict[str, Any] = {}
    tag = inputs.consistency.get("tag")
    odo = inputs.consistency.get("odometry")
    if tag is not None:
        out["tag_measurements"] = tag.as_dict()
    if odo is not None:
        out["odometry"] = odo.as_dict()
    if inputs.by_range:
        out["tag_residuals_by_range"] = inputs.by_range
    budgeted = ["focus_all", "focus_info", "focus_ds", "full_info", "full_ds"]
    for key in (
        "focused_error_m",
        "focused_error_aligned_m",
        "oracle_focused_error_m",
        "oracle_focused_error_aligned_m",
    ):
        out[f"order_{key}"] = _order(rows, key, budgeted)
    out["order_focused_entropy"] = _order(rows, "focused_entropy", budgeted)
    out["cases"] = {
        n: {
            k: row.get(k)
            for k in (
                "focused_error_m",
                *(c for c in WHY_COLUMNS if c != ORACLE_ERROR_ALL_M),
                "risk_margin_sigmas",
                "margin_sigmas",
                "tight_margin_m",
                "tight_deviation_m",
                "tight_ekf_sigma_m",
                "min_margin_m",
            )
        }
        for n, row in rows.items()
    }
    return out


def why_section(inputs: EvalInputs, results: Sequence[CaseResult]) -> list[str]:
    """Markdown: measurement consistency at the truth, NEES per case, the oracle re-solve, margin against σ."""
    rows = {r.case.name: r.row for r in results}
    lines = ["## Why: consistency against the ground truth and the navigation margin", ""]
    tag = inputs.consistency.get("tag")
    if tag is None:
        lines += [
            "No ground truth with poses and tags (or a 3-D graph): the consistency analysis needs the true poses and "
            "tag positions, so only the navigation margin below is computed.",
            "",
        ]
    else:
        lines += [
            "Every measurement of the full graph, its residual at the *true* poses and tags, whitened by its stated "
            "covariance (consistent: mean whitened 0, NEES = dimension):",
            "",
            "| measurements | count | mean residual | RMS residual | stated σ (RMS) | mean residual / σ | mean NEES "
            "(expected) |",
            "|---|---|---|---|---|---|---|",
        ]
        units = {"tag": ("rad", "m"), "odometry": ("m", "m", "rad")}
        for c in inputs.consistency.values():
            u = units.get(c.kind, ("",) * c.dim)

            def fmt(v: Any, u: tuple[str, ...] = u) -> str:
                return ", ".join(f"{x:.2e} {w}" for x, w in zip(v, u, strict=False))

            lines.append(
                f"| {c.kind} ({'bearing, range' if c.kind == 'tag' else 'x, y, yaw'}) | {c.count} | "
                f"{fmt(c.mean_residual)} | {fmt(c.rms_residual)} | {fmt(c.stated_sigma)} | "
                f"{', '.join(f'{x:+.2f}' for x in c.mean_whitened)} | {c.mean_nees:.2f} ({c.dim}) |"
            )
        lines.append("")
        if inputs.by_range:
            lines += [
                "Tag residuals by measured range:",
                "",
                "| range (m) | count | mean range residual (m) | stated range σ (m) | mean range residual / σ | "
                "mean NEES |",
                "|---|---|---|---|---|---|",
            ]
            for b in inputs.by_range:
                lines.append(
                    f"| {b['range_lo_m']:g}–{b['range_hi_m']:g} | {b['count']} | {b['mean_range_residual_m']:+.4f} | "
                    f"{b['range_sigma_m']:.4f} | {b['mean_whitened_range']:+.2f} | {b['mean_nees']:.2f} |"
                )
            lines.append("")
        lines += [
            "Per case, the collision-focused landmarks against the truth: error in the first-pose frame and after the "
            "best rigid planar alignment (removes the path's drift between the start and the landmarks, common to all "
            "of them), mean marginal σ per axis, NEES eᵀΣ⁻¹e (2 if the map's covariance is right) and the share of "
            "landmarks outside its 95 % bound (0.05 if right); NEES of the case's kept tag measurements at the truth "
            "and their mean range residual; and the same selection re-solved with ground-truth-consistent "
            "measurements (truth + noise drawn from the stated covariance, the 'oracle').",
            "",
            "| case | error (m) | aligned error (m) | σ (m) | NEES | outside 95 % | kept meas. NEES | kept range "
            "residual (m) | oracle error (m) | oracle aligned (m) | oracle NEES | entropy (nats) |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for r in results:
            w = r.row
            lines.append(
                f"| {w['label']} | {_g(w['focused_error_m'])} | {_g(w['focused_error_aligned_m'])} | "
                f"{_g(w['focused_sigma_m'])} | {_g(w['focused_nees'], '{:.2f}')} | "
                f"{_g(w['focused_outside_95'], '{:.2f}')} | {_g(w['kept_tag_nees'], '{:.2f}')} | "
                f"{_g(w['kept_range_bias_m'], '{:+.4f}')} | {_g(w['oracle_focused_error_m'])} | "
                f"{_g(w['oracle_focused_error_aligned_m'])} | {_g(w['oracle_focused_nees'], '{:.2f}')} | "
                f"{_g(w['focused_entropy'], '{:.1f}')} |"
            )
        lines.append("")
        lines += _findings(inputs, rows)
    lines += _margin_lines(inputs, results)
    return lines


def _findings(inputs: EvalInputs, rows: dict[str, dict[str, Any]]) -> list[str]:
    tag = inputs.consistency["tag"]
    budgeted = ["focus_all", "focus_info", "focus_ds", "full_info", "full_ds"]
    out = ["Findings (computed from the tables above):", ""]
    bias_sigmas = float(tag.mean_whitened[1])
    out.append(
        f"- Tag measurements: mean NEES {tag.mean_nees:.2f} against {tag.dim} expected, so their stated covariance "
        f"is {'larger' if tag.mean_nees < tag.dim else 'smaller'} than their scatter; but the range residual has a "
        f"mean of {tag.mean_residual[1]:+.4f} m ({bias_sigmas:+.2f} σ) shared by the detections: a bias, which "
        "fusing more measurements does not average away."
    )
    opt = rows.get("optimal")
    if opt is not None and math.isfinite(opt.get("focused_nees", float("nan"))):
        nees, o_nees = opt["focused_nees"], opt.get("oracle_focused_nees", float("nan"))
        facts = (
            f"its focused landmarks have NEES {nees:.1f} (expected 2) and error {opt['focused_error_m']:.4f} m against "
            f"σ {opt['focused_sigma_m']:.4f} m; with oracle measurements error {_g(opt['oracle_focused_error_m'])} m "
            f"and NEES {_g(o_nees, '{:.2f}')}"
        )
        if nees > CHI2_2_95 and not (o_nees > CHI2_2_95):
            verdict = (
                "with many measurements the error is set by a bias shared by the measurements, not by the variance "
                "the entropy measures."
            )
        elif nees > CHI2_2_95:
            verdict = "inconsistent with the real and with the oracle measurements: the model, not only the data."
        else:
            verdict = "consistent (the graph's model absorbs what bias the measurements have, or there is none)."
        out.append(f"- The full graph (optimal) fuses all of them: {facts}: {verdict}")
    fi = rows.get("focus_info", {})
    if math.isfinite(fi.get("focused_sigma_m", float("nan"))):
        out.append(
            f"- The focus cases' focused landmarks have marginal σ ≈ {fi['focused_sigma_m']:.3f} m (focus,info; "
            f"NEES {fi['focused_nees']:.2f}): without the unfocused landmarks the path's drift between the start "
            "(the map frame) and the focused landmarks is constrained by odometry only, and it moves all focused "
            "landmarks together. One recording draws that drift once, so the first-pose-frame error differences "
            "between focus cases are well inside one σ; the aligned error removes the common motion."
        )
    for key, name in (
        ("focused_entropy", "entropy"),
        ("focused_error_m", "error (first-pose frame, real measurements)"),
        ("focused_error_aligned_m", "aligned error (real measurements)"),
        ("oracle_focused_error_m", "error with oracle measurements"),
        ("oracle_focused_error_aligned_m", "aligned error with oracle measurements"),
    ):
        o = _order(rows, key, budgeted)
        if o:
            out.append(f"- Order by {name}: {o}.")
    out.append("")
    return out


def _margin_lines(inputs: EvalInputs, results: Sequence[CaseResult]) -> list[str]:
    nav = inputs.navigation
    lines = [
        "Navigation margin: the risk model's smallest margin along the path in σ of the robot's belief (z, "
        "P = Φ(−z); the robot model's filter covariance propagated along the path), and from the simulated trials "
        "the tightest step (smallest clearance − radius over the RMS distance of the robots from the true path), "
        "with the filter's σ there and its NEES per degree of freedom (1 = consistent):",
        "",
        "| case | risk model margin (σ) | tightest: margin (m) | RMS deviation (m) | filter σ (m) | "
        "margin / deviation | min margin on the path (m) | collision rate | filter NEES / dof |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        w = r.row
        rate = f"{w['collision_rate']:.3f}" if w.get("trials") else "not run"
        lines.append(
            f"| {w['label']} | {_g(w.get('risk_margin_sigmas'), '{:.1f}')} | {_g(w.get('tight_margin_m'), '{:.3f}')} | "
            f"{_g(w.get('tight_deviation_m'), '{:.3f}')} | {_g(w.get('tight_ekf_sigma_m'), '{:.3f}')} | "
            f"{_g(w.get('margin_sigmas'), '{:.2f}')} | {_g(w.get('min_margin_m'), '{:.3f}')} | {rate} | "
            f"{_g(w.get('navigation_nees'), '{:.2f}')} |"
        )
    lines.append("")
    if nav is not None:
        lines.append(
            "- Each case's robot follows its own map: a map displaced as a whole (drift from the start) is harmless "
            "when the landmarks it sees are displaced with the path; what collides is a map whose path and landmarks "
            "disagree near an obstacle, or that has no landmark where the path needs one. The filter's eq. 26 uses "
            "each landmark's covariance as seen from the keyframe the robot is at (docs/evaluate.md)."
        )
        if nav.world != "ground_truth":
            lines.append(
                "- Without a ground truth the world is the full map: each case's errors are measured against a map "
                "whose own errors it largely shares, so its filter NEES comes out below 1 by construction."
            )
        lines.append("")
    return lines


def margin_figure(inputs: EvalInputs, results: Sequence[CaseResult], out_dir: Path) -> str | None:
    """``margin.png``: clearance − radius along the path against 3 × the trials' RMS deviation, per case."""
    nav = inputs.navigation
    have = [(r, r.margin) for r in results if r.margin is not None]
    if nav is None or not have:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = (nav.path.stamps_ns - nav.path.stamps_ns[0]) / 1e9
    fig, ax = plt.subplots(figsize=(10, 3.8))
    ax.semilogy(t, np.maximum(have[0][1].margin_m, 1e-4), color="k", lw=1.5, label="clearance − radius")
    for r, margin in have:
        ax.semilogy(t, 3 * margin.deviation_m, lw=0.8, label=f"3 × RMS dev. {r.row[LABEL]}")
    ax.set_ylim(bottom=1e-2)
    ax.set_xlabel("time along the path (s)")
    ax.set_ylabel("m")
    ax.set_title("margin vs 3 × RMS deviation of the trials (a line ends when all its trials collided)", fontsize=9)
    ax.legend(fontsize=6, ncol=3)
    fig.tight_layout()
    fig.savefig(out_dir / "margin.png", dpi=110)
    plt.close(fig)
    return "margin.png"
