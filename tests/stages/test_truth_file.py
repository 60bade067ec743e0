"""The hand-written ground-truth format (``--truth``): it reads as the simulator's JSON does, parts may be missing,
bad files are one line, and the stages that read it re-run when it (or a file it names) changes."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from pipeline.errors import InputError
from pipeline.run_folder import RunFolder
from sample_data.simulate import SimConfig, simulate, truth_yaml_paths, write_bag
from stages.navigation.truth import MISSING, read_truth, read_tum
from tests.fixtures.room import room_walls, synthetic_scans
from tests.fixtures.synthetic_runs import SyntheticRun, synthetic_run
from tests.fixtures.upstream import STAGES, run_all, seed_upstream, summary


@pytest.fixture(scope="module")
def simulated(tmp_path_factory) -> Path:
    """A small simulated recording with both truth files beside it."""
    out = tmp_path_factory.mktemp("sim")
    rec = simulate(SimConfig(seed=2, duration_s=1.5, image_width=160, image_height=120))
    return write_bag(rec, out / "small.bag", "ros1")


def test_the_simulators_truth_yaml_reads_as_its_json(simulated: Path) -> None:
    yaml_path, tum_path = truth_yaml_paths(simulated)
    assert yaml_path.is_file() and tum_path.is_file()
    from_json = read_truth(simulated.with_name("small.ground_truth.json"))
    from_yaml = read_truth(yaml_path)
    assert from_yaml.missing == () and from_json.missing == ()
    first = int(from_json.pose_stamps_ns[5])  # a first keyframe that is not the first true pose
    a, b = from_json.in_map(first), from_yaml.in_map(first)
    assert np.array_equal(a.pose_stamps_ns, b.pose_stamps_ns)
    np.testing.assert_allclose(b.poses, a.poses, atol=1e-12)
    np.testing.assert_allclose(b.walls, a.walls, atol=1e-12)
    assert sorted(a.tags) == sorted(b.tags) and len(a.tags) > 3
    for t in a.tags:
        np.testing.assert_allclose(b.tags[t], a.tags[t], atol=1e-12)
    assert b.placed_by == "poses"


def test_the_json_reads_the_same_without_its_frames(simulated: Path) -> None:
    """GroundTruth drops the simulator's per-frame entries as the JSON is parsed (memory on long recordings): walls,
    tags and poses are those of the whole file."""
    path = simulated.with_name("small.ground_truth.json")
    data = json.loads(path.read_text())
    assert data["frames"] and any(f["visible_tags"] for f in data["frames"])
    truth = read_truth(path)
    np.testing.assert_array_equal(truth.walls_world, np.asarray(data["world"]["walls"], float).reshape(-1, 4))
    assert sorted(truth.tags_world) == sorted(int(t["id"]) for t in data["tags"])
    for t in data["tags"]:
        np.testing.assert_array_equal(truth.tags_world[int(t["id"])], t["position"])
    np.testing.assert_array_equal(truth.pose_stamps_ns, [p["stamp_ns"] for p in data["poses"]])
    np.testing.assert_array_equal(truth.poses_world, [[p["x"], p["y"], p["yaw"]] for p in data["poses"]])


def _write(folder: Path, text: str, **files: str) -> Path:
    for name, content in files.items():
        (folder / name.replace("_", ".")).write_text(content)
    path = folder / "truth.yaml"
    path.write_text(text)
    return path


def test_csv_parts_relative_paths_and_optional_z(tmp_path: Path) -> None:
    sub = tmp_path / "parts"
    sub.mkdir()
    (sub / "tags.csv").write_text("id,x,y,z\n3, 1.0, 2.0, 0.4\n# a comment\n4 5.0 6.0\n")
    (sub / "walls.csv").write_text("0 0 4 0  # south wall\n4,0,4,3\n")
    (sub / "run.tum").write_text(
        "# stamp x y z qx qy qz qw\n10.5 1 1 0 0 0 0 1\n11.000000001 2 1 0 0 0 0.7071067811865476 0.7071067811865476\n"
    )
    truth = read_truth(_write(tmp_path, "tags: parts/tags.csv\nwalls: parts/walls.csv\nposes: parts/run.tum\n"))
    assert sorted(truth.tags_world) == [3, 4]
    np.testing.assert_allclose(truth.tags_world[4], [5.0, 6.0, 0.0])
    np.testing.assert_allclose(truth.walls_world, [[0, 0, 4, 0], [4, 0, 4, 3]])
    assert truth.pose_stamps_ns.tolist() == [10_500_000_000, 11_000_000_001]
    np.testing.assert_allclose(truth.poses_world[1], [2.0, 1.0, math.pi / 2])
    # in the map frame of the first pose: the robot's start is the origin, facing +x
    m = truth.in_map(10_500_000_000)
    np.testing.assert_allclose(m.tags[3], [0.0, 1.0], atol=1e-12)


def test_a_missing_part_is_named_and_tags_place_a_truth_without_poses(tmp_path: Path) -> None:
    path = _write(tmp_path, "tags: [[1, 1.0, 0.0], [2, 1.0, 2.0], [3, 3.0, 2.0]]\nwalls: [[0, 0, 0, 5]]\n")
    truth = read_truth(path)
    assert truth.missing == ("poses",)
    # the graph's map is the world turned by 90° and moved by (1, 1)
    turn = np.array([[0.0, -1.0], [1.0, 0.0]])
    estimates = {t: turn @ p[:2] + [1.0, 1.0] for t, p in truth.tags_world.items()}
    m = truth.in_map(0, estimates)
    assert m.placed_by == "tags" and not m.has_poses and m.has_tags and m.has_walls
    for t in estimates:
        np.testing.assert_allclose(m.tags[t], estimates[t], atol=1e-12)
    np.testing.assert_allclose(m.walls[0], [1.0, 1.0, -4.0, 1.0], atol=1e-12)
    assert m.missing_notes() == [f"ground truth: {MISSING['poses']}"]
    with pytest.raises(InputError, match="cannot be placed in the map"):
        truth.in_map(0, {1: [0.0, 0.0]})  # one shared tag does not fix a frame
    walls_only = read_truth(_write(tmp_path, "frame: map\nwalls: [[0, 0, 0, 5]]\n")).in_map(0)
    assert walls_only.missing == ("tags", "poses") and walls_only.placed_by == "map"
    np.testing.assert_allclose(walls_only.walls, [[0, 0, 0, 5]])


@pytest.mark.parametrize(
    ("text", "files", "says"),
    [
        ("tags: [[1, 2]]\n", {}, "tags entry 1: expected id x y [z], got 2 values"),
        ("tags: [[1, 2, x]]\n", {}, "tags entry 1: expected an integer id and numbers"),
        ("tags: [[1, 2, 3], [1, 4, 5]]\n", {}, "tag 1 is listed twice"),
        ("walls: walls.csv\n", {"walls_csv": "0 0 1\n"}, "walls.csv line 1: expected x0 y0 x1 y1, got 3 values"),
        ("walls: nowhere.csv\n", {}, "walls file"),
        ("poses: p.tum\n", {"p_tum": "1 0 0 0 0 0 1\n"}, "a TUM pose is 8 values"),
        ("poses: p.tum\n", {"p_tum": "2 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n"}, "stamps must increase"),
        ("poses: p.tum\n", {"p_tum": "1 0 0 0 0 0 0 0\n"}, "quaternion"),
        ("poses: p.tum\n", {"p_tum": "1 nan 0 0 0 0 0 1\n"}, "expected 8 numbers"),
        ("frame: odom\ntags: [[1, 2, 3]]\n", {}, "frame 'odom' is not one of world, map"),
        ("tag: [[1, 2, 3]]\n", {}, "unknown key 'tag'; the keys are frame, tags, poses, walls"),
        ("frame: world\n", {}, "it has none of tags, poses, walls"),
        ("- 1\n- 2\n", {}, "expected a mapping"),
        ("tags: [1, 2\n", {}, "not valid YAML"),
    ],
)
def test_a_bad_truth_file_is_one_line_saying_what_is_wrong(
    tmp_path: Path, text: str, files: dict[str, str], says: str
) -> None:
    with pytest.raises(InputError) as err:
        read_truth(_write(tmp_path, text, **files))
    message = str(err.value)
    assert says in message and "\n" not in message and "docs/evaluate.md" in message


def test_read_tum_keeps_nanosecond_stamps(tmp_path: Path) -> None:
    (tmp_path / "t.tum").write_text("1700000000.000000001 0 0 0 0 0 0 1\n1700000000.5 0 0 0 0 0 0 1\n")
    stamps, _ = read_tum(tmp_path / "t.tum")
    assert stamps.tolist() == [1_700_000_000_000_000_001, 1_700_000_000_500_000_000]


def _truth_files(sim: SyntheticRun, folder: Path, walls: bool = True) -> Path:
    """``sim``'s truth in the YAML format: tags inline, poses as TUM, the room's walls (or none)."""
    tum = [
        f"{s // 10**9}.{s % 10**9:09d} {float(p[0])!r} {float(p[1])!r} 0 "
        f"0 0 {math.sin(p[2] / 2)!r} {math.cos(p[2] / 2)!r}"
        for s, p in zip(sim.true_stamps_ns.tolist(), sim.true_poses, strict=True)
    ]
    (folder / "path.tum").write_text("\n".join(tum) + "\n")
    tags = [[int(t), *T[:3, 3].tolist()] for t, T in sim.tags_world.items()]
    text = f"poses: path.tum\ntags: {json.dumps(tags)}\n"
    if walls:
        text += f"walls: {json.dumps(room_walls().tolist())}\n"
    (folder / "mine.yaml").write_text(text)
    return folder / "mine.yaml"


def test_truth_file_is_read_by_optimize_and_evaluate_and_a_change_reruns_them(tmp_path: Path) -> None:
    sim = synthetic_run(seed=7, loops=0.5)
    source = tmp_path / "run.bag"
    source.write_bytes(b"")
    run = RunFolder.create(tmp_path / "run", source)
    seed_upstream(run, sim, synthetic_scans(sim))
    folder = tmp_path / "truth"
    folder.mkdir()
    path = _truth_files(sim, folder)
    sets = (f"optimize.truth_file={path}", f"evaluate.truth_file={path}")
    assert run_all(run, *sets) == dict.fromkeys(STAGES, "done")
    assert summary(run, "optimize")["reference"] == "ground_truth"
    assert summary(run, "evaluate")["reference"] == "ground_truth"
    assert "notes" not in summary(run, "evaluate")
    declared = set(run.stage_entry("evaluate")["outside_files"])
    assert {str(path.resolve()), str((folder / "path.tum").resolve())} <= declared
    assert run_all(run, *sets) == dict.fromkeys(STAGES, "skipped")
    tum = folder / "path.tum"
    tum.write_text(tum.read_text().replace(" 0 0 0 ", " 0 0.0 0 ", 1))  # the same poses, another file
    readers = {**dict.fromkeys(STAGES, "skipped"), "optimize": "done", "evaluate": "done"}
    assert run_all(run, *sets) == readers
    _truth_files(sim, folder, walls=False)
    assert run_all(run, *sets, "evaluate.trials=2") == readers
    ev = summary(run, "evaluate")
    assert ev["notes"] == [f"ground truth: {MISSING['walls']}"] and ev["walls"] == "laser_grid"
    # the settings of a truth that is not there: one error line
    (folder / "gone.yaml").write_text("tags: [[1, 0, 0]]\n")
    gone = folder / "gone.yaml"
    gone.unlink()
    with pytest.raises(InputError, match="not found"):
        run_all(run, f"evaluate.truth_file={gone}")


def test_truth_option_on_the_command_line(tmp_path: Path) -> None:
    """``--truth`` on a stage command and on run: a missing file is one ``error:`` line before anything runs."""
    from typer.testing import CliRunner

    from cli.app import app

    missing = tmp_path / "nope.yaml"
    for args in (["evaluate", tmp_path, "--truth", missing], ["run", tmp_path / "x.bag", "--truth", missing]):
        result = CliRunner().invoke(app, [str(a) for a in args])
        assert result.exit_code == 1, result.stderr
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: ground truth"), result.stderr
        assert "nope.yaml" in lines[0] and "--truth" in lines[0]


def test_one_truth_flag_sets_optimize_and_evaluate(tmp_path: Path) -> None:
    from cli.app import _overrides, _registry
    from pipeline.stage import run_options

    path = tmp_path / "t.yaml"
    path.write_text("walls: [[0, 0, 1, 1]]\n")
    value = json.dumps(str(path.resolve()))
    assert _overrides(run_options(_registry()), {"truth": path}) == [
        f"optimize.truth_file={value}",
        f"evaluate.truth_file={value}",
    ]


def test_a_batch_file_entry_names_its_own_truth_relative_to_the_batch_file(tmp_path: Path) -> None:
    from pipeline.batch_file import read_batch_file
    from pipeline.config import load_settings
    from stages import REGISTRY

    (tmp_path / "a.bag").write_bytes(b"")
    (tmp_path / "a.truth").mkdir()
    (tmp_path / "a.truth" / "t.yaml").write_text("walls: [[0, 0, 1, 1]]\n")
    (tmp_path / "fleet.yaml").write_text(
        "- {recording: a.bag, truth: a.truth/t.yaml}\n- {recording: a.bag, name: b, truth: no.yaml}\n"
    )
    entries, problems = read_batch_file(tmp_path / "fleet.yaml", REGISTRY, load_settings(REGISTRY.models()))
    settings = entries[0].settings
    assert settings is not None
    want = str((tmp_path / "a.truth" / "t.yaml").resolve())
    values = settings.dump()
    assert values["optimize"]["truth_file"] == want == values["evaluate"]["truth_file"]
    assert len(problems) == 1 and "entry 2" in problems[0] and "no.yaml" in problems[0] and "not found" in problems[0]
