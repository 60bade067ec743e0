"""The cache is honest: a stage re-runs exactly when something it uses changed, and its results are then current.

What a stage uses: its own settings, the code it imports, the artifacts of its inputs (whose fingerprints carry
the settings of the stages before it) and the files outside the run folder it reads (the ground truth).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from pipeline.artifacts import StageInput
from pipeline.code import code_digest, package_dirs
from pipeline.config import load_settings
from pipeline.run_folder import RunFolder
from pipeline.runner import run_stage
from stages.select_landmarks.artifacts import FOCUSED
from tests.fixtures.room import synthetic_scans, write_ground_truth
from tests.fixtures.synthetic_runs import SyntheticRun, synthetic_run
from tests.fixtures.upstream import BASE, REG, STAGES, run_all, seed_upstream, summary


@pytest.fixture(scope="module")
def sim() -> SyntheticRun:
    return synthetic_run(seed=7, loops=0.5)


@pytest.fixture
def make_run(sim: SyntheticRun, tmp_path: Path):
    """A synthetic run folder (source ``run.bag``, no ground truth yet) with every stage finished on ``BASE``."""

    def make() -> RunFolder:
        source = tmp_path / "run.bag"
        source.write_bytes(b"")
        run = RunFolder.create(tmp_path / "run", source)
        seed_upstream(run, sim, synthetic_scans(sim))
        assert run_all(run) == dict.fromkeys(STAGES, "done")
        return run

    return make


AFTER_SELECT_LANDMARKS = {
    "graph": "skipped",
    "select_landmarks": "done",
    "select_measurements": "done",
    "optimize": "done",
    "evaluate": "done",
}


def test_landmark_budget_reruns_the_selection_and_what_follows(make_run) -> None:
    run = make_run()
    assert run_all(run) == dict.fromkeys(STAGES, "skipped")
    assert run_all(run, "select_landmarks.budget=3") == AFTER_SELECT_LANDMARKS
    assert summary(run, "evaluate")["alpha"] == 3 and summary(run, "optimize")["alpha"] == 3
    assert len(summary(run, "evaluate")["focused_tag_ids"]) == 3
    assert run_all(run, "select_landmarks.budget=3") == dict.fromkeys(STAGES, "skipped")


def test_a_stage_run_alone_on_stale_inputs_says_which_and_how_to_fix_it(make_run) -> None:
    """select-landmarks with a new budget, then optimize alone: select_measurements still holds the picks made for
    the old focused set, so optimize's result mixes two versions, and the warning names the stage to re-run."""
    run = make_run()
    settings = load_settings(REG.models(), None, [*BASE, "select_landmarks.budget=3"])
    assert run_stage(run, REG, "select_landmarks", settings).warnings == []
    result = run_stage(run, REG, "optimize", settings)
    assert result.status == "done"
    assert result.warnings == [
        f"select_measurements was made from an older select_landmarks; run 'focusmap select-measurements "
        f"{run.path}' (or 'focusmap run') for results from one version"
    ]
    assert run_stage(run, REG, "select_measurements", settings).status == "done"
    assert run_stage(run, REG, "optimize", settings).warnings == []  # one version again (evaluate stays behind)


def test_measurement_budget_reruns_from_select_measurements(make_run) -> None:
    run = make_run()
    statuses = run_all(run, "select_measurements.budget=7")
    assert statuses == {**AFTER_SELECT_LANDMARKS, "select_landmarks": "skipped"}
    assert summary(run, "evaluate")["K"] == 7 and summary(run, "optimize")["K"] == 7
    assert summary(run, "optimize")["tag_measurements"] <= 7


def test_robot_radius_reaches_optimize_and_evaluate(make_run) -> None:
    run = make_run()
    p_before = summary(run, "optimize")["max_collision_probability"]
    # a robot almost as wide as the path's clearance: collisions become likely
    radius = round(summary(run, "select_landmarks")["min_clearance_m"] - 0.05, 3)
    assert run_all(run, f"select_landmarks.robot_radius_m={radius}") == AFTER_SELECT_LANDMARKS
    focused = FOCUSED.read(StageInput("select_landmarks", run.stage_dir("select_landmarks")))
    assert focused.risk_params.robot_radius_m == radius
    # optimize and evaluate recomputed the risk with the new radius, taken from select_landmarks' artifact
    p_after = summary(run, "optimize")["max_collision_probability"]
    assert p_after > max(p_before, 1e-6)
    # the same map read back from optimize's artifacts: the same risk up to the float round trip
    assert summary(run, "evaluate")["table"]["focus_info"]["max_collision_probability"] == pytest.approx(p_after)


def test_evaluate_reuses_the_upstream_case_and_reports_its_numbers(make_run) -> None:
    run = make_run()
    ev, opt = summary(run, "evaluate"), summary(run, "optimize")
    assert ev["from_upstream"]["focus_info"] == ["landmarks", "measurements", "reduced map"]
    assert "optimal" not in ev["from_upstream"]
    assert ev["table"]["focus_info"]["focused_entropy"] == opt["focused_entropy"]


def test_the_ground_truth_file_appearing_or_changing_reruns_its_readers(make_run, sim, tmp_path: Path) -> None:
    run = make_run()
    assert summary(run, "evaluate")["reference"] == "optimal"
    truth_key = str((tmp_path / "run.ground_truth.json").resolve())
    yaml_key = str((tmp_path / "run.truth.yaml").resolve())
    assert run.stage_entry("evaluate")["outside_files"] == {truth_key: None, yaml_key: None}  # looked for, absent
    truth = tmp_path / "run.ground_truth.json"
    readers = {**dict.fromkeys(STAGES, "skipped"), "optimize": "done", "evaluate": "done"}
    write_ground_truth(sim, truth)
    assert run_all(run) == readers
    assert summary(run, "evaluate")["reference"] == "ground_truth"
    assert summary(run, "optimize")["reference"] == "ground_truth"
    assert list(run.stage_entry("optimize")["outside_files"]) == [truth_key]
    assert run.stage_entry("optimize")["outside_files"][truth_key] is not None
    assert run_all(run) == dict.fromkeys(STAGES, "skipped")
    doc = json.loads(truth.read_text())
    doc["tags"] = doc["tags"][1:]  # one tag fewer in the truth
    truth.write_text(json.dumps(doc))
    assert run_all(run) == readers
    truth.unlink()
    assert run_all(run) == readers
    assert summary(run, "evaluate")["reference"] == "optimal"


def _stage_digests(root: Path) -> dict[str, str]:
    dirs = {"stages": root / "stages", "pipeline": root / "pipeline"}
    return {s: code_digest([f"stages.{s}"], dirs) for s in ("ingest", "detect", *STAGES)}


def _edited(tree: Path, dest: Path, module: str) -> Path:
    """A copy of ``tree`` with a comment appended to ``module`` (a fresh folder: digests are cached per folder)."""
    shutil.copytree(tree, dest)
    with (dest / module).open("a") as f:
        f.write("\n# an edit\n")
    return dest


def test_editing_a_module_changes_the_code_of_its_users_only(tmp_path: Path) -> None:
    """The real digest over copies of the source tree: an edit reaches the stages that import the module."""
    v0 = tmp_path / "v0"
    for pkg, src in package_dirs(["stages", "pipeline"]).items():
        shutil.copytree(src, v0 / pkg, ignore=shutil.ignore_patterns("__pycache__"))
    before = _stage_digests(v0)
    assert len(set(before.values())) == len(before)

    v1 = _edited(v0, tmp_path / "v1", "stages/evaluate/report.py")
    after = _stage_digests(v1)
    assert {s for s in before if before[s] != after[s]} == {"evaluate"}

    v2 = _edited(v1, tmp_path / "v2", "stages/select_landmarks/core.py")
    again = _stage_digests(v2)
    changed = {s for s in after if after[s] != again[s]}
    assert "select_landmarks" in changed and "evaluate" in changed
    assert not changed & {"ingest", "detect", "graph"}

    # graph imports the g2o reader only inside a function: it counts
    v3 = _edited(v2, tmp_path / "v3", "stages/graph/g2o.py")
    assert _stage_digests(v3)["graph"] != again["graph"]
    # a module nobody imports: no stage changes
    (v3 / "stages" / "estimation" / "unused.py").write_text("x = 1\n")
    v4 = _edited(v3, tmp_path / "v4", "stages/estimation/unused.py")
    assert _stage_digests(v4) == _stage_digests(v3)


def test_lazy_and_relative_imports_are_followed(tmp_path: Path) -> None:
    from pipeline.code import reachable_modules

    pkg = tmp_path / "proj"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "sub" / "a.py").write_text("import os\n\ndef f():\n    from . import b\n    return b\n")
    (pkg / "sub" / "b.py").write_text("try:\n    from ..c import x\nexcept ImportError:\n    pass\n")
    (pkg / "c.py").write_text("x = 1\n")
    (pkg / "d.py").write_text("y = 2\n")
    # 'from . import b' names the package proj.sub too; proj (a parent only) and d (not imported) stay out
    assert set(reachable_modules(["proj.sub.a"], {"proj": pkg})) == {"proj.sub", "proj.sub.a", "proj.sub.b", "proj.c"}
    # a package root takes in every module below it
    assert set(reachable_modules(["proj.sub"], {"proj": pkg})) == {"proj.sub", "proj.sub.a", "proj.sub.b", "proj.c"}


@pytest.mark.parametrize("limit", ["select_landmarks.max_trajectory_dim", "evaluate.extra_max_trajectory_dim"])
def test_an_extra_case_that_cannot_run_is_skipped_with_a_warning(make_run, limit: str) -> None:
    """Mutual information on a trajectory above its limit (a long recording): the extra case is left out with one
    warning line naming the setting, and the Table I cases still run."""
    run = make_run()
    sets = (f"{limit}=10", "evaluate.extra_pairs=[mutual-information+information]")
    assert run_all(run, *sets)["evaluate"] == "done"
    ev = summary(run, "evaluate")
    assert "mutual-information+information" not in ev["cases"] and "focus_info" in ev["cases"]
    assert len(ev["warnings"]) == 1 and limit.split(".")[1] in ev["warnings"][0], ev["warnings"]
    assert "case mutual-information+information skipped" in (run.stage_dir("evaluate") / "report.md").read_text()
