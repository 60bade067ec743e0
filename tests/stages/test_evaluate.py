"""The evaluate stage produces every case of Table I (and the extra pairs) with the report, on a short synthetic run."""

from __future__ import annotations

import json
import math

import pyarrow.parquet as pq
import pytest

from stages.evaluate.cases import TABLE_I
from tests.fixtures.upstream import evaluated_synthetic_run


@pytest.fixture(scope="module")
def evaluated(tmp_path_factory):
    return evaluated_synthetic_run(
        tmp_path_factory.mktemp("eval"),
        [
            "select_landmarks.budget=5",
            "select_measurements.budget=15",
            "evaluate.trials=6",
            "evaluate.extra_pairs=[random+random]",
        ],
    )


def test_every_case_is_in_the_table(evaluated) -> None:
    table = pq.read_table(evaluated.stage_dir("evaluate") / "cases.parquet").to_pydict()
    assert table["case"] == [c[0] for c in TABLE_I] + ["random+random", "focus_info_poses"]
    for col in (
        "focused_entropy",
        "focused_error_m",
        "max_collision_probability",
        "collision_rate",
        "collision_ci_low",
        "collision_ci_high",
        "observed_landmarks",
        "focused_landmarks",
        "error_all_m",
        "mean_collision_probability",
        "selection_s",
    ):
        assert col in table, col
    rows = {c: {k: v[i] for k, v in table.items()} for i, c in enumerate(table["case"])}
    n_lm = rows["optimal"]["observed_landmarks"]
    assert rows["full_info"]["observed_landmarks"] <= n_lm and rows["focus_info"]["observed_landmarks"] <= 5
    assert rows["focus_info"]["measurements"] <= 15 and rows["full_ds"]["measurements"] <= 15
    assert rows["optimal"]["focused_landmarks"] == 5
    # more information on the same focused landmarks: case 1 <= case 2 <= budgeted cases in entropy
    assert rows["optimal"]["focused_entropy"] <= rows["focus_all"]["focused_entropy"] + 1e-6
    assert rows["focus_all"]["focused_entropy"] <= rows["focus_info"]["focused_entropy"] + 1e-6
    # the greedy maximises exactly this entropy: it beats downsampling on the same landmarks
    assert rows["focus_info"]["focused_entropy"] <= rows["focus_ds"]["focused_entropy"] + 1e-6
    for r in rows.values():
        assert r["trials"] == 6 and 0.0 <= r["collision_ci_low"] <= r["collision_rate"] <= r["collision_ci_high"] <= 1
        assert r["error_reference"] == "ground_truth" and math.isfinite(r["focused_error_m"])
        assert 0.0 <= r["max_collision_probability"] <= 1.0
        # the why-analysis: NEES, rigid-aligned and oracle errors, the navigation margin in sigmas
        for col in ("focused_nees", "focused_error_aligned_m", "oracle_focused_error_m", "kept_tag_nees"):
            if col == "focused_error_aligned_m" and r["focused_landmarks"] < 3:  # a rigid fit needs 3 (random's pick)
                assert r[col] is None  # not computed: null in cases.parquet
                continue
            assert math.isfinite(r[col]), col
        assert r["tight_margin_m"] > 0 and r["margin_sigmas"] > 0 and r["risk_margin_sigmas"] > 0
        # the trials' filter (Schmidt, the map's joint covariance considered) is consistent: NEES per dof near 1
        assert 0.2 < r["navigation_nees"] < 3.0, (r["case"], r["navigation_nees"])


def test_the_entropy_split_and_the_risk_bracket_are_per_case_columns(evaluated) -> None:
    table = pq.read_table(evaluated.stage_dir("evaluate") / "cases.parquet").to_pylist()
    summary = json.loads((evaluated.stage_dir("evaluate") / "summary.json").read_text())
    risk = pq.read_table(evaluated.stage_dir("evaluate") / "path_risk.parquet").to_pydict()
    n_focus = len(summary["focused_tag_ids"])
    assert n_focus == 5
    for row in table:
        assert row["unobserved_focused_landmarks"] == n_focus - row["focused_landmarks"]
        assert row["focused_entropy"] == pytest.approx(row["focused_entropy_observed"] + row["focused_entropy_prior"])
        if row["unobserved_focused_landmarks"] == 0:
            assert row["focused_entropy_prior"] == 0.0
        else:  # the 100 m prior: about 19 nats per unobserved planar landmark
            assert row["focused_entropy_prior"] / row["unobserved_focused_landmarks"] == pytest.approx(
                1 + math.log(2 * math.pi) + 2 * math.log(100.0)
            )
        p = [v for c, v in zip(risk["case"], risk["p_collision"], strict=True) if c == row["case"]]
        assert row["predicted_collision_low"] == max(p)
        assert row["predicted_collision_high"] == pytest.approx(min(1.0, sum(p)))
        assert row["risk_disagrees"] in (True, False)  # trials ran and the run has a laser
    head = summary["headline"]
    assert head["unobserved_focused_landmarks"] == summary["table"]["focus_info"]["unobserved_focused_landmarks"]


def test_report_figures_summary_and_recording(evaluated) -> None:
    out = evaluated.stage_dir("evaluate")
    for f in (
        "report.md",
        "report.html",
        "maps.png",
        "risk.png",
        "entropy.png",
        "navigation.png",
        "summary.json",
        "maps.parquet",
        "path_risk.parquet",
        "greedy.parquet",
        "margin.png",
    ):
        assert (out / f).is_file(), f
    md = (out / "report.md").read_text()
    assert "Entropy on observed focused lms" in md and "focus, info" in md and "![maps.png](maps.png)" in md
    # the risk model beside the simulation: one line per case, each with its verdict
    section = md.split("## Risk model against the simulation", 1)[1].split("\n## ", 1)[0]
    lines = [line for line in section.splitlines() if line.startswith("- ")]
    assert len(lines) == len(TABLE_I) + 2
    assert all("predicted P(collision on the path) in [" in line and "simulated " in line for line in lines)
    assert all(("consistent (the interval reaches within 10x" in line) != ("DISAGREE" in line) for line in lines)
    assert "data:image/png;base64," in (out / "report.html").read_text()
    # the full map's health checks head the report: each failed one as a warning line, or that all passed
    from stages.evaluate.report import map_health_lines

    graph_warnings = json.loads((evaluated.stage_dir("graph") / "summary.json").read_text())["health"]["warnings"]
    head = md.split("## ", 1)[0]
    assert "\n".join(map_health_lines(graph_warnings)) in head
    assert ("passed every health check" in head) == (not graph_warnings)
    failed = "\n".join(map_health_lines(["the tag scale is far from its prior", "LM stopped at its cap"]))
    assert "failed 2 health check(s)" in failed and "- warning: LM stopped at its cap" in failed
    summary = json.loads((out / "summary.json").read_text())
    assert summary["headline"]["case"] == "focus_info" and summary["alpha"] == 5 and summary["K"] == 15
    assert "## Why" in md and "oracle" in md and "margin / deviation" in md
    why = summary["why"]
    # the synthetic generator's tag noise is what its covariance says: NEES near the dimension, no range bias
    tag = why["tag_measurements"]
    print("synthetic tag NEES at the truth", tag["mean_nees"], "mean whitened", tag["mean_whitened"])
    assert 1.0 < tag["mean_nees"] < 3.0 and abs(tag["mean_whitened"][1]) < 0.3
    from rerun.chunk import RrdReader

    paths = {c.entity_path for c in RrdReader(evaluated.rrd_path("evaluate")).stream()}
    for case, _, _ in TABLE_I:
        assert f"/evaluate/cases/{case}/landmarks" in paths


def test_the_downstream_stages_write_what_they_declare(evaluated) -> None:
    """Every file of select_*/optimize/evaluate is declared, every required one written, and each reads back."""
    from pipeline.artifacts import StageInput
    from pipeline.contracts import JsonSpec, TableSpec
    from stages.contracts import artifact_sets

    sets = {s.stage: s for s in artifact_sets()}
    for stage in ("select_landmarks", "select_measurements", "optimize", "evaluate"):
        folder = evaluated.stage_dir(stage)
        written = {p.name for p in folder.iterdir()} - {"summary.json"}
        declared = {spec.file for spec in sets[stage].specs}
        required = {spec.file for spec in sets[stage].specs if not spec.optional}
        assert written <= declared, f"{stage} writes undeclared files {sorted(written - declared)}"
        assert required <= written, f"{stage} lacks {sorted(required - written)}"
        inp = StageInput(stage, folder)
        for spec in sets[stage].specs:
            if isinstance(spec, TableSpec):
                assert spec.read(inp).schema == spec.schema
            elif isinstance(spec, JsonSpec):
                assert isinstance(spec.read(inp), spec.model)


def test_the_worker_process_changes_no_number_and_no_picture(evaluated, tmp_path) -> None:
    """evaluate.workers=2 (the default: navigation trials and two figures in a worker process) and 1 (everything in
    the stage's process) write the same cases, bit for bit apart from the timing columns, and the same PNGs."""
    alone = evaluated_synthetic_run(
        tmp_path,
        [
            "select_landmarks.budget=5",
            "select_measurements.budget=15",
            "evaluate.trials=6",
            "evaluate.extra_pairs=[random+random]",
            "evaluate.workers=1",
        ],
    )
    both = pq.read_table(evaluated.stage_dir("evaluate") / "cases.parquet").to_pydict()
    one = pq.read_table(alone.stage_dir("evaluate") / "cases.parquet").to_pydict()
    assert both.keys() == one.keys()
    for column, values in both.items():
        if not column.endswith("_s"):  # the selection and solve timings
            assert [repr(v) for v in values] == [repr(v) for v in one[column]], column
    pictures = sorted(p.name for p in evaluated.stage_dir("evaluate").glob("*.png"))
    assert "navigation.png" in pictures and "maps.png" in pictures
    for name in pictures:
        drawn = (evaluated.stage_dir("evaluate") / name).read_bytes()
        assert drawn == (alone.stage_dir("evaluate") / name).read_bytes(), name
