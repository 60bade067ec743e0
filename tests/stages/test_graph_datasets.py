"""import-graph on the datasets GTSAM ships (its examples/Data, in every gtsam wheel) and the SE-Sync benchmark.

Files GTSAM's readers read import with GTSAM's graph and values; the others are refused with one error line.
"""

from __future__ import annotations

import json
import subprocess
from collections import Counter
from pathlib import Path

import gtsam
import numpy as np
import pytest

from pipeline.errors import InputError
from stages.graph.factors import build_graph
from stages.graph.g2o import read_graph_file
from tests.fixtures.graphs import import_graph
from tests.fixtures.shared_data import need_shared

DATA = Path(gtsam.findExampleDataFile("victoria_park.txt")).parent

IMPORTED = {
    # file: (model, poses, landmarks, factors by kind, GTSAM reader); a prior on the first pose is added
    "victoria_park.txt": ("planar", 6969, 151, {"prior": 1, "odometry": 6968, "tag": 3640}, "gtsam.load2D"),
    "w20000.txt": ("planar", 20061, 0, {"prior": 1, "odometry": 20060, "loop": 6771}, "gtsam.load2D"),
    "example.graph": ("planar", 95, 24, {"prior": 1, "odometry": 94, "tag": 422}, "gtsam.load2D"),
    "w100.graph": ("planar", 100, 0, {"prior": 1, "odometry": 99, "loop": 201}, "gtsam.load2D"),
    "w100_30.g2o": ("planar", 30, 0, {"prior": 1, "odometry": 29, "loop": 30}, "gtsam.load2D"),
    "pose2example.txt": ("planar", 11, 0, {"prior": 1, "odometry": 10, "loop": 2}, "gtsam.readG2o"),
    "noisyToyGraph.txt": ("planar", 4, 0, {"prior": 1, "odometry": 3, "loop": 2}, "gtsam.readG2o"),
    "cityTrees_reduced_1k.g2o": ("planar", 1000, 0, {"prior": 1, "odometry": 999}, "gtsam.readG2o"),
    "sphere2500.txt": ("3d", 2500, 0, {"prior": 1, "odometry": 2499, "loop": 2450}, "gtsam.load3D"),
    "pose3example-grid.txt": ("3d", 27, 0, {"prior": 1, "odometry": 26, "loop": 18}, "gtsam.readG2o"),
    "toyExample.g2o": ("3d", 5, 0, {"prior": 1, "odometry": 4, "loop": 2}, "gtsam.readG2o"),
    "Klaus3.g2o": ("3d", 3, 0, {"prior": 1, "odometry": 2, "loop": 1}, "gtsam.readG2o"),
    "known_landmark_localization_20.g2o": ("3d", 20, 4, {"prior": 1, "odometry": 19, "tag": 80}, "gtsam.readG2o"),
    "edge_se3_trackxyz_example.g2o": ("3d", 1, 1, {"prior": 1, "tag": 1}, "gtsam.readG2o"),
}
REFUSED = {
    # file: what the one error line says
    "sphere_smallnoise.graph": r"sphere_smallnoise\.graph:2201: EDGE3 needs .* \(29 numbers\); the line has 8",
    "T1_city10000_04.txt": r"T1_city10000_04\.txt:1: EDGE2 needs .* \(11 numbers\); the line has 8",
    "edge_se3_trackxyz_missing_vertex.g2o": r"gtsam\.readG2o rejects the file \(EDGE_SE3_TRACKXYZ references a "
    r"missing pose or landmark vertex\)",
    "edge_se3_trackxyz_nonidentity_offset.g2o": r"requires an identity PARAMS_SE3OFFSET",
    "example_with_vertices.g2o": r"holds vertices but no edges GTSAM's readers read",
    "dubrovnik-3-7-pre.txt": r"holds no edges GTSAM's readers read; its lines start with '3'",
    "VO_camera_poses00.txt": r"holds no edges",
    "toy3D.xml": r"toy3D\.xml is a GTSAM XML .* not a pose graph",
    "goats_15.pyfg": r"is a PyFG .* not a pose graph",
    "EqFdata.csv": r"is a CSV table, not a pose graph",
    "HS21.QPS": r"is a QPS quadratic program, not a pose graph",
    "Balbianello.out": r"is a Bundler / BAL .* not a pose graph",
}


def _data(name: str) -> Path:
    path = DATA / name
    if not path.is_file():
        pytest.skip(f"this gtsam wheel ships no {name}")
    return path


def _gtsam_read(path: Path, reader: str, model: str) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    if reader == "gtsam.load2D":
        return gtsam.load2D(str(path))
    if reader == "gtsam.load3D":
        return gtsam.load3D(str(path))
    return gtsam.readG2o(str(path), model == "3d")


@pytest.mark.parametrize("name", sorted(IMPORTED))
def test_gtsam_examples_import_with_gtsams_readers(name: str) -> None:
    model, n_poses, n_lm, kinds, reader = IMPORTED[name]
    p = read_graph_file(_data(name))
    assert (p.model, len(p.pose_keys), len(p.landmark_keys)) == (model, n_poses, n_lm)
    assert dict(Counter(r.kind for r in p.rows)) == kinds
    assert p.info["reader"] == reader
    ref_graph, _ = _gtsam_read(DATA / name, reader, model)
    assert len(p.rows) == ref_graph.size() + 1  # every factor GTSAM's reader returns, and the prior


def test_victoria_park_matches_gtsams_graph() -> None:
    """GTSAM's load2D graph at GTSAM's values has the error of ours at the same values (prior aside)."""
    path = _data("victoria_park.txt")
    p = read_graph_file(path)
    ref_graph, ref_values = gtsam.load2D(str(path))
    values = gtsam.Values()
    for k in p.var_types:
        sym = gtsam.Symbol(k)
        ref_key = sym.index() if chr(sym.chr()) == "x" else k
        p.kind(k).insert(values, k, p.kind(k).read(ref_values, ref_key))
    graph = build_graph(p.rows)
    ours = sum(graph.at(i).error(values) for i in range(graph.size()) if p.rows[i].kind != "prior")
    assert ours == pytest.approx(ref_graph.error(ref_values), rel=1e-9)
    assert p.info["poses_placed_by_odometry"] == 0  # load2D already composed the odometry chain


def test_edge_only_3d_graph_starts_on_its_odometry_chain() -> None:
    """sphere2500.txt has no vertices (load3D returns no values): the chain of consecutive edges is composed."""
    p = read_graph_file(_data("sphere2500.txt"))
    assert p.info["poses_placed_by_odometry"] == 2500
    graph = build_graph(p.rows)
    odometry = [graph.at(i).error(p.initial) for i, r in enumerate(p.rows) if r.kind == "odometry"]
    loops = [graph.at(i).error(p.initial) for i, r in enumerate(p.rows) if r.kind == "loop"]
    assert max(odometry) < 1e-12 and max(loops) > 1.0


def _gtsam_optimum(path: Path, reader: str, model: str, prior_cov: np.ndarray) -> float:
    """GTSAM's LM on its reader's graph, from our initial values, with the same prior on the first pose."""
    graph, _ = _gtsam_read(path, reader, model)
    p = read_graph_file(path)
    initial = gtsam.Values()
    for k in p.var_types:
        sym = gtsam.Symbol(k)
        p.kind(k).insert(initial, sym.index() if chr(sym.chr()) == "x" else k, p.kind(k).read(p.initial, k))
    pose0 = gtsam.Symbol(p.pose_keys[0]).index()
    first = p.kind(p.pose_keys[0]).read(p.initial, p.pose_keys[0])
    noise = gtsam.noiseModel.Gaussian.Covariance(prior_cov)
    prior = gtsam.PriorFactorPose2 if model == "planar" else gtsam.PriorFactorPose3
    graph.add(prior(pose0, first, noise))
    return float(graph.error(gtsam.LevenbergMarquardtOptimizer(graph, initial).optimize()))


@pytest.mark.parametrize(
    "name", ["example.graph", "w100.graph", "pose3example-grid.txt", "known_landmark_localization_20.g2o"]
)
def test_import_reaches_gtsams_optimum(tmp_path: Path, name: str) -> None:
    model, n_poses, n_lm, kinds, reader = IMPORTED[name]
    run = import_graph(_data(name), tmp_path)
    s = json.loads((run / "graph" / "summary.json").read_text())
    assert (s["poses"], s["landmarks"], s["factors"]) == (n_poses, n_lm, sum(kinds.values()))
    assert s["reader"] == reader and s["notes"][0] == f"read with {reader}"
    prior = read_graph_file(_data(name)).rows[0]
    assert s["final_error"] == pytest.approx(_gtsam_optimum(DATA / name, reader, model, prior.covariance), rel=1e-4)


def test_se_sync_manhattan_imports(tmp_path: Path) -> None:
    """M3500 (EDGE_SE2 only): readG2o's values, the same optimum as GTSAM's LM."""
    path = need_shared("se-sync-graphs/manhattan.g2o")
    p = read_graph_file(path)
    assert (len(p.pose_keys), len(p.landmark_keys), len(p.rows)) == (3500, 0, 5454)
    assert p.info["reader"] == "gtsam.readG2o"
    run = import_graph(path, tmp_path)
    s = json.loads((run / "graph" / "summary.json").read_text())
    assert s["final_error"] == pytest.approx(_gtsam_optimum(path, "gtsam.readG2o", "planar", p.rows[0].covariance))


@pytest.mark.parametrize("name", sorted(REFUSED))
def test_files_gtsam_cannot_read_are_refused(name: str) -> None:
    with pytest.raises(InputError, match=REFUSED[name]):
        read_graph_file(_data(name))


def test_cli_import_prints_counts_and_one_error_line(tmp_path: Path) -> None:
    ok = subprocess.run(
        ["focusmap", "import-graph", str(_data("example.graph")), "--out", str(tmp_path)],
        capture_output=True,
        text=True,
        check=False,
    )
    assert ok.returncode == 0, ok.stderr
    assert "poses=95  landmarks=24  factors=517" in ok.stdout and "read with gtsam.load2D" in ok.stderr
    for name in ("toy3D.xml", "sphere_smallnoise.graph"):
        bad = subprocess.run(
            ["focusmap", "import-graph", str(_data(name)), "--out", str(tmp_path)],
            capture_output=True,
            text=True,
            check=False,
        )
        assert bad.returncode == 1 and bad.stdout == ""
        assert bad.stderr.count("\n") == 1 and bad.stderr.startswith("error: "), bad.stderr
