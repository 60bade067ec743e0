"""Map realisations: measurements redrawn from the world with their stated noise, the graph re-solved, every case
re-run; the seed streams; the evaluate stage's table and report section."""

from __future__ import annotations

import json

import gtsam
import numpy as np
import pyarrow.parquet as pq
import pytest

from pipeline.errors import StageError
from stages.evaluate.cases import TABLE_I
from stages.evaluate.config import EvaluateConfig
from stages.evaluate.realisations import World, load_run_inputs, redraw_graph, redraw_rows, run_realisations, streams
from stages.graph.factors import make_factor
from tests.fixtures.upstream import evaluated_synthetic_run


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    return evaluated_synthetic_run(
        tmp_path_factory.mktemp("realise"),
        [
            "select_landmarks.budget=5",
            "select_measurements.budget=15",
            "evaluate.trials=4",
            "evaluate.extra_pairs=[random+random]",
            "evaluate.realisations=3",
            "evaluate.plots=false",
        ],
    )


def _values_at(loaded, world: World) -> gtsam.Values:
    vals = gtsam.Values()
    for k, p in zip(loaded.pose_keys, world.poses, strict=True):
        vals.insert(k, gtsam.Pose2(*p))
    for t, k in loaded.landmark_keys.items():
        vals.insert(k, gtsam.Point2(*world.landmarks[t]))
    if loaded.scale_key is not None:
        vals.insert(loaded.scale_key, world.scale)
    return vals


def test_redrawn_measurements_have_their_stated_noise_around_the_world(run_dir) -> None:
    inputs, _ = load_run_inputs(run_dir.path, EvaluateConfig())
    loaded = inputs.loaded
    world = World.of(loaded, inputs.truth)
    assert world.source == "ground_truth" and world.missing_tags == 0
    at_world = _values_at(loaded, world)
    chi2: dict[str, list[float]] = {"odometry": [], "tag": []}
    for seed in range(4):
        rows = redraw_rows(loaded, world, np.random.default_rng(seed))
        assert [(r.kind, r.keys) for r in rows] == [(r.kind, r.keys) for r in loaded.rows]
        for r, old in zip(rows, loaded.rows, strict=True):
            if r.kind in chi2:
                chi2[r.kind].append(2 * make_factor(r).error(at_world))
            else:
                assert r is old  # priors are kept
    # a factor's whitened error at the world is χ² with its dimension: the mean is the dimension
    n_odo, n_tag = len(chi2["odometry"]), len(chi2["tag"])
    assert np.mean(chi2["odometry"]) == pytest.approx(3.0, abs=4 * np.sqrt(6 / n_odo))
    assert np.mean(chi2["tag"]) == pytest.approx(2.0, abs=4 * np.sqrt(4 / n_tag))
    # the bootstrap world is the solution itself: the solved graph's landmarks are where the world puts them
    boot = World.of(loaded)
    assert boot.source == "full_solution"
    k = next(iter(loaded.landmark_keys.values()))
    t = next(iter(loaded.landmark_keys))
    np.testing.assert_allclose(boot.landmarks[t], np.asarray(loaded.values.atPoint2(k)))


def test_the_redrawn_graph_is_solved_with_the_same_structure(run_dir) -> None:
    inputs, _ = load_run_inputs(run_dir.path, EvaluateConfig())
    loaded = inputs.loaded
    world = World.of(loaded, inputs.truth)
    a = redraw_graph(loaded, world, np.random.default_rng(1))
    b = redraw_graph(loaded, world, np.random.default_rng(1))
    c = redraw_graph(loaded, world, np.random.default_rng(2))
    assert a.pose_keys == loaded.pose_keys and a.landmark_keys == loaded.landmark_keys
    assert set(a.marginals) == set(loaded.var_types) and a.factors.num_rows == len(loaded.rows)
    k = next(iter(loaded.landmark_keys.values()))
    pa_, pb, pc = (np.asarray(g.values.atPoint2(k)) for g in (a, b, c))
    np.testing.assert_array_equal(pa_, pb)
    assert not np.allclose(pa_, pc)
    # each solution is within a few marginal σ of the world
    t = {v: q for q, v in loaded.landmark_keys.items()}[k]
    err = pa_ - world.landmarks[t]
    assert float(err @ np.linalg.solve(a.marginals[k], err)) < 30.0


def test_streams_are_separate_and_do_not_depend_on_the_count() -> None:
    few, many = streams(5, 3), streams(5, 10)
    for s, t in zip(few, many[:3], strict=True):
        assert (s.selection_seed, s.navigation_seed) == (t.selection_seed, t.navigation_seed)
        assert s.measurements.entropy == t.measurements.entropy
        assert s.measurements.spawn_key == t.measurements.spawn_key
    assert len({s.navigation_seed for s in many}) == 10
    assert not {s.navigation_seed for s in many} & {s.selection_seed for s in many}
    assert streams(6, 1)[0].navigation_seed != few[0].navigation_seed


def test_realisations_are_reproducible_and_paired(run_dir) -> None:
    inputs, detections = load_run_inputs(run_dir.path, EvaluateConfig(trials=3))
    from stages.evaluate.cases import Case

    todo = [Case(*c) for c in TABLE_I[:3]]
    a = run_realisations(inputs, todo, 2, 3, seed=11, detections=detections)
    b = run_realisations(inputs, todo, 2, 3, seed=11, detections=detections)
    assert a.rows == b.rows and not a.failed and a.world == "ground_truth"
    assert [(r["realisation"], r["case"]) for r in a.rows] == [(i, c.name) for i in range(2) for c in todo]
    # the realisations differ (the measurements were redrawn) and every case ran its trials
    ent = a.values("optimal", "focused_entropy")
    assert ent[0] != ent[1] and all(r["trials"] == 3 for r in a.rows)
    # a longer study starts with the same realisations
    c = run_realisations(inputs, todo[:1], 3, 3, seed=11, detections=detections)
    assert c.values("optimal", "focused_entropy")[:2].tolist() == ent.tolist()


def test_a_3d_graph_is_refused_in_one_line(run_dir) -> None:
    inputs, _ = load_run_inputs(run_dir.path, EvaluateConfig())
    inputs.loaded.model = "3d"
    with pytest.raises(StageError, match="planar graphs only") as err:
        World.of(inputs.loaded)
    assert "\n" not in str(err.value)


def test_the_stage_writes_the_table_and_the_report_section(run_dir) -> None:
    out = run_dir.stage_dir("evaluate")
    t = pq.read_table(out / "realisations.parquet").to_pydict()
    names = [c[0] for c in TABLE_I] + ["random+random", "focus_info_poses"]
    assert t["realisation"] == [r for r in range(3) for _ in names] and t["case"] == names * 3
    assert all(n == 4 for n in t["trials"])
    md = (out / "report.md").read_text()
    assert "## Over map realisations" in md and "3 map realisations × 4 navigation trials" in md
    assert "Wilcoxon p" in md and "ground truth" in md
    summary = json.loads((out / "summary.json").read_text())["realisations"]
    assert summary["realisations"] == 3 and summary["world"] == "ground_truth" and summary["failed"] == 0
    rate = summary["collision_rate"]["focus_info"]
    assert rate["ci"][0] <= rate["mean"] <= rate["ci"][1]
    assert summary["collision_rate"]["optimal"]["vs_focus_info_sign_p"] is not None
