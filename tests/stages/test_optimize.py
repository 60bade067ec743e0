"""The optimize stage: the reduced graph's artifacts and values, on a synthetic run with laser scans and truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from pipeline.artifacts import StageInput, StageOutput
from pipeline.config import load_settings
from pipeline.errors import StageError
from pipeline.registry import Registry
from pipeline.run_folder import RunFolder
from pipeline.runner import run_stage
from stages import graph as graph_stage
from stages import optimize as optimize_stage
from stages.graph.load import landmark_heights, load_graph
from stages.optimize import gaussian_entropy, solve_reduced
from stages.risk import LandmarkMap
from tests.fixtures.room import synthetic_scans, write_ground_truth
from tests.fixtures.synthetic_runs import SyntheticRun, synthetic_run
from tests.fixtures.upstream import seed_upstream, stand_in


def make_graph_run(tmp_path: Path, sim: SyntheticRun, truth: bool = True) -> tuple[RunFolder, Registry]:
    """A run folder with ingest (odometry, scans, extrinsics), detect and a finished graph stage."""
    reg = Registry(
        [
            stand_in("ingest"),
            stand_in("detect", "ingest"),
            graph_stage.STAGE,
            stand_in("select_landmarks", "graph"),
            stand_in("select_measurements", "select_landmarks"),
            optimize_stage.STAGE,
        ]
    )
    source = tmp_path / "run.bag"
    source.write_bytes(b"")
    if truth:
        write_ground_truth(sim, tmp_path / "run.ground_truth.json")
    run = RunFolder.create(tmp_path / "run", source)
    seed_upstream(run, sim, synthetic_scans(sim))
    settings = load_settings(reg.models())
    run_stage(run, reg, "graph", settings)
    return run, reg


def write_selection(run: RunFolder, tag_ids: list[int], factor_indices: list[int], tag: str = "a") -> None:
    """Stand-ins for the two selection stages' artifacts (``focused.json``, ``selected.parquet``, ``selection.json``)
    written through their declarations, with default settings."""
    from stages.select_landmarks import SelectLandmarksConfig
    from stages.select_landmarks.artifacts import FOCUSED, FocusedLandmarks, RiskNoise
    from stages.select_measurements import SelectMeasurementsConfig
    from stages.select_measurements.artifacts import SELECTED, SELECTION, SelectedMeasurements

    for name in ("select_landmarks", "select_measurements"):
        d = run.stage_dir(name)
        d.mkdir(exist_ok=True)
    n = len(factor_indices)
    focused = FocusedLandmarks(
        strategy="test",
        budget=len(tag_ids),
        tag_ids=tag_ids,
        scores=[0.0] * len(tag_ids),
        status="ok",
        message="",
        n_landmarks=len(tag_ids),
        seconds=0.0,
        settings=SelectLandmarksConfig(),
        noise=RiskNoise(bearing_sigma_rad=0.02, range_sigma_m=0.05, speed_sigma_mps=0.05, yaw_rate_sigma_radps=0.05),
    )
    FOCUSED.write(StageOutput(run.stage_dir("select_landmarks")), focused)
    selected = {"factor_index": factor_indices, "step": list(range(n)), "gain": [np.nan] * n, "tag_id": [0] * n}
    SELECTED.write(StageOutput(run.stage_dir("select_measurements")), {**selected, "stamp_ns": [0] * n})
    choice = SelectedMeasurements(
        strategy="test",
        budget=n,
        focus="selected",
        focused_tag_ids=tag_ids,
        factor_indices=factor_indices,
        gains=[np.nan] * n,
        status="ok",
        message="",
        n_candidates=n,
        candidates=[],
        entropy_before=0,
        entropy_after=0,
        seconds=0,
        settings=SelectMeasurementsConfig(),
    )
    SELECTION.write(StageOutput(run.stage_dir("select_measurements")), choice)
    run.record("select_landmarks", {"fingerprint": f"sl-{tag}", "summary": {}})
    run.record("select_measurements", {"fingerprint": f"sm-{tag}", "summary": {}})


@pytest.fixture(scope="module")
def sim() -> SyntheticRun:
    return synthetic_run(seed=4, loops=0.6)


@pytest.fixture(scope="module")
def graph_run(sim, tmp_path_factory):
    run, reg = make_graph_run(tmp_path_factory.mktemp("opt"), sim)
    return run, reg, load_graph(StageInput("graph", run.stage_dir("graph")))


def test_keeping_every_measurement_reproduces_the_full_solution(graph_run) -> None:
    run, _, loaded = graph_run
    tags = sorted(loaded.landmark_keys)
    heights = landmark_heights(pq.read_table(run.stage_dir("graph") / "landmarks.parquet"))
    red = solve_reduced(loaded, tags, loaded.tag_factor_indices.tolist(), heights)
    full = LandmarkMap.from_graph(loaded)
    np.testing.assert_allclose(red.landmark_map.positions, full.positions, atol=1e-6)
    np.testing.assert_allclose(red.landmark_map.covariances, full.covariances, rtol=1e-5, atol=1e-12)
    assert red.observed_tag_ids == tags and red.n_measurements == len(loaded.tag_factor_indices)
    # entropy = ½ log det(2πe Σ) of the full graph's joint landmark marginal
    import gtsam

    marg = gtsam.Marginals(loaded.graph, loaded.values)
    joint = marg.jointMarginalCovariance(gtsam.KeyVector([loaded.landmark_keys[t] for t in tags])).fullMatrix()
    assert red.focused_entropy == pytest.approx(gaussian_entropy(np.asarray(joint)), abs=1e-6)
    assert red.focused_dim == 2 * len(tags)


def test_fewer_measurements_never_lower_the_entropy(graph_run) -> None:
    _, _, loaded = graph_run
    tags = sorted(loaded.landmark_keys)[:6]
    cand = [i for i in loaded.tag_factor_indices.tolist() if loaded.rows[i].tag_id in set(tags)]
    all_ = solve_reduced(loaded, tags, cand)
    half = solve_reduced(loaded, tags, cand[::2])
    few = solve_reduced(loaded, tags, cand[::5])
    assert all_.focused_entropy <= half.focused_entropy + 1e-9 <= few.focused_entropy + 2e-9


def test_stage_outputs_and_values(graph_run) -> None:
    run, reg, loaded = graph_run
    tags = sorted(loaded.landmark_keys)
    focused = tags[:8]
    # focused[-1] is focused but none of its measurements is selected
    by_tag = {t: [i for i in loaded.tag_factor_indices.tolist() if loaded.rows[i].tag_id == t] for t in tags}
    selected = [i for t in focused[:-1] for i in by_tag[t][::2]] + by_tag[tags[-1]][:3]  # some of an unfocused tag
    write_selection(run, focused, selected, "subset")
    settings = load_settings(reg.models())
    res = run_stage(run, reg, "optimize", settings, force=True)
    out = run.stage_dir("optimize")
    for f in (
        "landmarks.parquet",
        "trajectory.tum",
        "poses.parquet",
        "factors.parquet",
        "marginals.npz",
        "kept.parquet",
        "landmark_errors.parquet",
        "risk.parquet",
        "summary.json",
    ):
        assert (out / f).is_file(), f
    assert run.rrd_path("optimize").is_file()
    s = res.summary
    g_lm = pq.read_table(run.stage_dir("graph") / "landmarks.parquet")
    o_lm = pq.read_table(out / "landmarks.parquet")
    assert o_lm.schema.names == g_lm.schema.names
    assert sorted(o_lm.column("tag_id").to_pylist()) == focused[:-1]
    kept = pq.read_table(out / "kept.parquet").column("full_index").to_pylist()
    n_fixed = len(loaded.fixed_factor_indices)
    n_sel_focused = sum(len(by_tag[t][::2]) for t in focused[:-1])
    assert len(kept) == n_fixed + n_sel_focused and s["dropped_unfocused_measurements"] == len(by_tag[tags[-1]][:3])
    assert s["focused_landmarks"] == 8 and s["focused_observed"] == 7 and s["observed_landmarks"] == 7
    # the unobserved focused landmark enters the entropy with the 100 m prior (2 dims)
    extra = 0.5 * 2 * (np.log(100.0**2) + np.log(2 * np.pi * np.e))
    assert s["focused_entropy"] == pytest.approx(s["focused_entropy_observed"] + extra)
    assert s["focused_dim"] == 16
    assert s["reference"] == "ground_truth"
    assert 0 < s["focused_error_m"] < 0.3 and 0 < s["focused_error_vs_full_m"] < 0.3
    size = s["map_size"]
    assert size["landmarks"] == 7 and size["landmarks_full"] == len(tags)
    assert size["measurements"] == n_sel_focused and 0 < size["bytes_fraction"] < 1
    risk = pq.read_table(out / "risk.parquet")
    assert risk.num_rows == len(loaded.pose_keys)
    p = np.asarray(risk.column("p_collision").to_numpy())
    assert np.all((p >= 0) & (p <= 1)) and s["max_collision_probability"] == pytest.approx(p.max())
    assert s["max_collision_probability"] >= s["max_collision_probability_full"]
    err = pq.read_table(out / "landmark_errors.parquet").to_pydict()
    assert all(np.isfinite(err["error_vs_truth_m"])) and err["n_measurements"] == [
        len(by_tag[t][::2]) for t in focused[:-1]
    ]
    # the recording has the reduced map beside the full one
    from rerun.chunk import RrdReader

    paths = {c.entity_path for c in RrdReader(run.rrd_path("optimize")).stream()}
    assert {"/optimize/full/landmarks", "/optimize/reduced/landmarks", "/optimize/path"} <= paths


def test_bad_selections_are_named(graph_run) -> None:
    _, _, loaded = graph_run
    with pytest.raises(StageError, match="outside the graph"):
        solve_reduced(loaded, sorted(loaded.landmark_keys)[:2], [10**7])
    with pytest.raises(StageError, match="not landmarks of the graph"):
        solve_reduced(loaded, [99999], [])
