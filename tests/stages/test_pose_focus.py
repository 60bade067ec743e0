"""A pose graph sparsified to K loop closures (``select_measurements.focus: poses``), end to end through the stages,
on GTSAM's own ``w100.graph`` (shipped in every gtsam wheel, so this runs without ``../shared``)."""

from __future__ import annotations

import json
from pathlib import Path

import gtsam
import numpy as np
import pyarrow.parquet as pq
import pytest

from pipeline.config import load_settings
from pipeline.errors import StageError
from pipeline.run_folder import RunFolder
from pipeline.runner import run_stage
from stages import REGISTRY
from tests.fixtures.graphs import import_graph


@pytest.fixture(scope="module")
def w100(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return import_graph(Path(gtsam.findExampleDataFile("w100.graph")), tmp_path_factory.mktemp("pose_focus"))


def _select_and_optimize(run_path: Path, *overrides: str) -> tuple[dict, dict]:
    run = RunFolder(run_path)
    settings = load_settings(REGISTRY.models(), None, ("select_measurements.focus=poses", *overrides))
    sel = run_stage(run, REGISTRY, "select_measurements", settings).summary
    opt = run_stage(run, REGISTRY, "optimize", settings).summary
    return sel, opt


def test_pose_graph_keeps_k_loop_closures(w100: Path) -> None:
    sel, opt = _select_and_optimize(w100, "select_measurements.budget=15")
    factors = pq.read_table(w100 / "graph" / "factors.parquet").to_pydict()
    n_loops = sum(1 for k in factors["kind"] if k == "loop")
    assert sel["candidates"] == n_loops > 15
    assert sel["selected"] == 15 and sel["entropy_after"] < sel["entropy_before"]
    assert opt["loop_closures_kept"] == 15
    assert opt["factors"] == len(factors["kind"]) - (n_loops - 15)
    assert opt["factors_by_kind"]["loop"] == 15
    # the selection's predicted pose entropy after the picks is the reduced graph's (same linearisation point up to
    # the re-optimisation: a loose check) and it lies above the full graph's
    assert opt["pose_entropy"] > opt["pose_entropy_full"]
    assert abs(opt["pose_entropy"] - sel["entropy_after"]) < 0.05 * abs(sel["entropy_after"] - opt["pose_entropy_full"])
    kept = pq.read_table(w100 / "optimize" / "kept.parquet").to_pydict()["full_index"]
    chosen = json.loads((w100 / "select_measurements" / "selection.json").read_text())["factor_indices"]
    assert set(chosen) <= set(kept)


def test_information_beats_uniform_and_random_on_pose_entropy(w100: Path) -> None:
    """Alg. 1 with every pose focused leaves less pose entropy than keeping as many loop closures evenly in time or at
    random (three seeds), on the re-optimised reduced graphs."""
    entropy = {}
    for strategy, seed in [("information", 0), ("uniform", 0), ("random", 0), ("random", 1), ("random", 2)]:
        _, opt = _select_and_optimize(
            w100,
            "select_measurements.budget=12",
            f"select_measurements.strategy={strategy}",
            f"select_measurements.seed={seed}",
        )
        entropy[(strategy, seed)] = opt["pose_entropy"]
    best = entropy[("information", 0)]
    others = [v for k, v in entropy.items() if k[0] != "information"]
    assert best < min(others), entropy
    assert np.isfinite(best)


@pytest.mark.parametrize(
    ("focus", "says"),
    [("all", "focus=poses"), ("selected", "focus=poses")],
)
def test_landmark_focus_on_a_pose_graph_says_what_to_do(w100: Path, focus: str, says: str) -> None:
    run = RunFolder(w100)
    settings = load_settings(REGISTRY.models(), None, (f"select_measurements.focus={focus}",))
    with pytest.raises(StageError, match="no landmarks") as err:
        run_stage(run, REGISTRY, "select_measurements", settings)
    assert says in str(err.value)
