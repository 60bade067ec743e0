"""focusmap export: the reduced map of a run as g2o, GTSAM, TUM, YAML and CSV, read back by GTSAM's readers."""

from __future__ import annotations

import csv
import json
import subprocess
from pathlib import Path

import gtsam
import numpy as np
import pyarrow.parquet as pq
import pytest
import yaml

from pipeline.config import load_settings
from pipeline.errors import InputError
from pipeline.run_folder import RunFolder
from pipeline.runner import run_stage
from stages import REGISTRY
from stages.export.writers import export_run
from stages.graph.g2o import read_graph_file
from tests.fixtures.graphs import import_graph

EXAMPLE = Path(gtsam.findExampleDataFile("example.graph"))
SETTINGS = ["select_landmarks.strategy=uniform", "select_landmarks.budget=8"]


@pytest.fixture(scope="module")
def reduced_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """GTSAM's example.graph imported, 8 landmarks focused, measurements selected, the reduced map optimised."""
    run_dir = import_graph(EXAMPLE, tmp_path_factory.mktemp("export"), "example")
    settings = load_settings(REGISTRY.models(), None, SETTINGS)
    for stage in ("select_landmarks", "select_measurements", "optimize"):
        run_stage(RunFolder(run_dir), REGISTRY, stage, settings)
    return run_dir


def _summary(run: Path) -> dict:
    return json.loads((run / "optimize" / "summary.json").read_text())


def _files(run: Path) -> set[Path]:
    return {p for p in run.rglob("*") if p.is_file()}


def test_g2o_export_reads_in_gtsam_to_the_same_optimum(reduced_run: Path, tmp_path: Path) -> None:
    before = _files(reduced_run)
    out = tmp_path / "map.g2o"
    assert export_run(reduced_run, "optimize", "g2o", out) == [out, tmp_path / "map.g2o.json"]
    s, meta = _summary(reduced_run), json.loads((tmp_path / "map.g2o.json").read_text())
    graph, values = gtsam.readG2o(str(out), False)
    assert graph.size() == s["factors"] - meta["priors"] == meta["edges_gtsam_reads"]
    assert values.size() == s["poses"] + s["landmarks"]
    back = read_graph_file(out)  # and ours reads it back whole, landmark ids from the side file
    assert (len(back.rows), len(back.landmark_keys)) == (s["factors"], s["landmarks"])
    focused = json.loads((reduced_run / "select_landmarks" / "focused.json").read_text())["tag_ids"]
    assert sorted(back.landmark_keys) == sorted(focused)
    prior = back.rows[0]
    noise = gtsam.noiseModel.Gaussian.Covariance(prior.covariance)
    graph.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(*prior.measurement), noise))
    optimum = graph.error(gtsam.LevenbergMarquardtOptimizer(graph, values).optimize())
    assert optimum == pytest.approx(s["final_error"], rel=1e-6)
    assert _files(reduced_run) == before  # nothing written in the run folder


def test_gtsam_export_is_the_graph_and_values(reduced_run: Path, tmp_path: Path) -> None:
    (out,) = export_run(reduced_run, "optimize", "gtsam", tmp_path / "map.gtsam.json")
    doc = json.loads(out.read_text())
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.deserialize(doc["graph"])
    values.deserialize(doc["values"])
    s = _summary(reduced_run)
    assert graph.size() == doc["factors"] == s["factors"]
    assert graph.error(values) == pytest.approx(s["final_error"], rel=1e-9)


def test_tum_yaml_and_csv_hold_the_reduced_map(reduced_run: Path, tmp_path: Path) -> None:
    s = _summary(reduced_run)
    (tum,) = export_run(reduced_run, "optimize", "tum", tmp_path / "t.tum")
    rows = np.loadtxt(tum)
    poses = pq.read_table(reduced_run / "optimize" / "poses.parquet").to_pydict()
    assert rows.shape == (s["poses"], 8)
    np.testing.assert_allclose(rows[:, 1], poses["x"], atol=1e-8)
    np.testing.assert_allclose(rows[:, 7], poses["qw"], atol=1e-8)

    landmarks = pq.read_table(reduced_run / "optimize" / "landmarks.parquet").to_pydict()
    focused = set(json.loads((reduced_run / "select_landmarks" / "focused.json").read_text())["tag_ids"])
    (y,) = export_run(reduced_run, "optimize", "yaml", tmp_path / "tags.yaml")
    doc = yaml.safe_load(y.read_text())
    tags = doc["bodies"][0]["map"]["tags"]
    assert [t["id"] for t in tags] == landmarks["tag_id"] and all(t["focused"] == (t["id"] in focused) for t in tags)
    for t, x, cov in zip(tags, landmarks["x"], landmarks["position_cov"], strict=True):
        assert t["pose"]["position"]["x"] == pytest.approx(x)
        np.testing.assert_allclose(t["pose"]["covariance"], cov)
        assert t["pose"]["position_noise"]["y"] == pytest.approx(np.sqrt(cov[4]))

    lm_csv, pose_csv = export_run(reduced_run, "optimize", "csv", tmp_path / "tables")
    with lm_csv.open() as f:
        table = list(csv.DictReader(f))
    assert [int(r["tag_id"]) for r in table] == landmarks["tag_id"]
    assert [float(r["cov_yy"]) for r in table] == pytest.approx([c[4] for c in landmarks["position_cov"]])
    with pose_csv.open() as f:
        assert sum(1 for _ in csv.DictReader(f)) == s["poses"]


def test_graph_stage_export_is_the_full_graph(reduced_run: Path, tmp_path: Path) -> None:
    (out, _) = export_run(reduced_run, "graph", "g2o", tmp_path / "full.g2o")
    graph, _ = gtsam.readG2o(str(out), False)
    full = json.loads((reduced_run / "graph" / "summary.json").read_text())
    assert graph.size() == full["factors"] - 1  # every factor but the prior on the first pose


def test_stage_graph_g2o_reads_in_gtsam(reduced_run: Path) -> None:
    """The graph stage's own graph.g2o (no comment lines any more): readG2o reads every factor but the prior."""
    for stage in ("graph", "optimize"):
        graph, _ = gtsam.readG2o(str(reduced_run / stage / "graph.g2o"), False)
        meta = json.loads((reduced_run / stage / "graph.g2o.json").read_text())
        assert graph.size() == meta["edges_gtsam_reads"] == meta["edges"] - 1 > 0


def test_bad_exports_are_one_error_line(reduced_run: Path, tmp_path: Path) -> None:
    with pytest.raises(InputError, match="unknown export format 'xyz'"):
        export_run(reduced_run, "optimize", "xyz", tmp_path / "x")
    with pytest.raises(InputError, match="inside the run's optimize stage folder"):
        export_run(reduced_run, "optimize", "g2o", reduced_run / "optimize" / "graph.g2o")
    graph_only = import_graph(EXAMPLE, tmp_path, "graph_only")
    with pytest.raises(InputError, match="has no finished optimize stage"):
        export_run(graph_only, "optimize", "yaml", tmp_path / "x.yaml")
    for args in (
        [str(graph_only), "--format", "yaml"],
        [str(reduced_run), "--format", "xyz"],
        [str(tmp_path / "missing"), "--format", "g2o"],
        [str(reduced_run), "--format", "g2o", "--stage", "detect"],
    ):
        r = subprocess.run(["focusmap", "export", *args], capture_output=True, text=True, cwd=tmp_path, check=False)
        assert r.returncode == 1 and r.stdout == "", r.stdout
        assert r.stderr.startswith("error: ") and r.stderr.count("\n") == 1, r.stderr
    ok = subprocess.run(
        ["focusmap", "export", str(reduced_run), "-f", "tum"], capture_output=True, text=True, cwd=tmp_path, check=False
    )
    assert ok.returncode == 0 and (tmp_path / "example_optimize.tum").is_file(), ok.stderr
