"""focusmap batch: planning, the summary, local vs Dask on generated bags, resuming after a kill.

The end-to-end tests run ``--until detect`` (ingest and detect only) on 2-second simulated
recordings at 320x240, so the whole file stays well under a minute and a half on two cores; the
machinery they check (tasks, run folders, manifests, resuming) is the same for every stage.

The batches run in subprocesses on a snapshot of ``pipeline/``, ``stages/`` and ``cli/`` taken when
the module starts: the runner's fingerprints hash the stage code, so an edit to a stage while the
test runs would otherwise make every stage look out of date.
"""

from __future__ import annotations

import fcntl
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq
import pytest

from pipeline.batch import (
    SUMMARY_FILE,
    Outcome,
    collect_recordings,
    plan_tasks,
    run_name,
    run_names,
    summary_table,
)
from pipeline.batch_file import BatchEntry, BatchFileError, load_batch_file
from pipeline.config import load_settings
from pipeline.errors import InputError
from pipeline.registry import Headline, Registry
from pipeline.run_folder import LOCK_FILE

ROOT = Path(__file__).resolve().parents[2]
UNTIL = "detect"
FORMATS = (("s1.bag", "ros1"), ("s2", "ros2-sqlite"), ("s3", "ros2-mcap"))
TIMING = re.compile(r"seconds|timing|per_second|_s$")
# One detect process per recording: these tests are about the batch's own workers. detect's default pool would
# spawn two more interpreters per recording (4-8 s of imports on two cores) to detect tags in ten frames; the pool
# itself is tested in tests/stages/test_detect.py.
SETS = ("--set", "detect.workers=1")


# --- helpers -----------------------------------------------------------------------------------------
def _stable(value: Any) -> Any:
    """A stage summary without its timings (which differ from run to run)."""
    if isinstance(value, dict):
        return {k: _stable(v) for k, v in value.items() if not TIMING.search(k)}
    if isinstance(value, list):
        return [_stable(v) for v in value]
    return value


def _manifests(out: Path) -> dict[str, dict[str, Any]]:
    """Per run folder: per stage, its fingerprint and summary without timings."""
    result = {}
    for manifest in sorted(out.glob("*/manifest.json")):
        stages = json.loads(manifest.read_text())["stages"]
        result[manifest.parent.name] = {
            name: {"fingerprint": e["fingerprint"], "summary": _stable(e["summary"])} for name, e in stages.items()
        }
    return result


def _rows(out: Path) -> list[dict[str, Any]]:
    """The summary rows without timings and the worker's host."""
    table = pq.read_table(out / SUMMARY_FILE)
    return [{k: v for k, v in r.items() if not k.startswith("seconds") and k != "host"} for r in table.to_pylist()]


def _registry() -> Any:
    from stages import REGISTRY

    return REGISTRY


def _cli(*args: str) -> list[str]:
    """The command line of ``focusmap ARGS`` run with the interpreter of the tests."""
    return [sys.executable, "-c", "from cli.app import main; main()", *args]


DASK_SCRIPT = """
import json, os, sys
from pathlib import Path
from distributed import LocalCluster
from pipeline.batch import collect_recordings, plan_tasks, run_batch, summary_table, write_summary
from pipeline.config import load_settings
from stages import REGISTRY

out, until, sets, *bags = sys.argv[1:]
stages = [s.name for s in REGISTRY.between(None, until)]
tasks = plan_tasks(collect_recordings(bags), Path(out), stages, load_settings(REGISTRY.models(), None, [sets]),
                   preflight="stages.ingest.bags:detect_format")
with LocalCluster(n_workers=2, threads_per_worker=1, host="127.0.0.1", processes=True, dashboard_address=None) as c:
    result = run_batch(tasks, scheduler=c.scheduler_address, progress=False)
write_summary(summary_table(result.outcomes, stages, REGISTRY), Path(out))
print(json.dumps({"client_pid": os.getpid(), "hosts": [o.host for o in result.outcomes]}))
"""


# --- fixtures --------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Three short recordings (seeds 1-3; ROS 1, ROS 2 SQLite, ROS 2 MCAP) and one truncated ROS 1 bag."""
    from sample_data.simulate import SimConfig, simulate, write_bag

    root = tmp_path_factory.mktemp("bags")
    paths = []
    for seed, (name, fmt) in enumerate(FORMATS, start=1):
        rec = simulate(SimConfig(seed=seed, path="corridor", duration_s=2.0, image_width=320, image_height=240))
        paths.append(write_bag(rec, root / name, fmt))  # type: ignore[arg-type]
    broken = root / "broken.bag"
    broken.write_bytes(paths[0].read_bytes()[:3000])  # cut inside the first chunk
    return [*paths, broken]


@pytest.fixture(scope="module")
def env(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    """Environment whose PYTHONPATH puts a snapshot of the code first (fingerprints stay put)."""
    root = tmp_path_factory.mktemp("code")
    for package in ("pipeline", "stages", "cli"):
        shutil.copytree(ROOT / package, root / package, ignore=shutil.ignore_patterns("__pycache__"))
    # Subprocesses run with the snapshot as working directory too: ``python -c`` puts it first on sys.path.
    return {**os.environ, "PYTHONPATH": str(root), "COLUMNS": "200"}


@pytest.fixture(scope="module")
def local_out(
    bags: list[Path], env: dict[str, str], tmp_path_factory: pytest.TempPathFactory
) -> tuple[Path, subprocess.CompletedProcess[str]]:
    """``focusmap batch`` (local pool, 2 workers) over the bags; returns OUT and the finished process."""
    out = tmp_path_factory.mktemp("local") / "runs"
    cmd = _cli("batch", *map(str, bags), "--out", str(out), "--until", UNTIL, "--workers", "2", *SETS)
    return out, subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300, cwd=env["PYTHONPATH"])


# --- planning ----------------------------------------------------------------------------------------------
def test_collect_recordings_globs_dedupes_and_names_the_missing(tmp_path: Path) -> None:
    (tmp_path / "a.bag").write_bytes(b"x")
    (tmp_path / "b.bag").write_bytes(b"x")
    (tmp_path / "ros2").mkdir()
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "c.mcap").write_bytes(b"x")
    found = collect_recordings([str(tmp_path / "*.bag"), str(tmp_path / "a.bag"), str(tmp_path / "**" / "*.mcap")])
    assert [p.name for p in found] == ["a.bag", "b.bag", "c.mcap"]
    assert [run_name(p) for p in collect_recordings([str(tmp_path / "ros2")])] == ["ros2"]
    with pytest.raises(InputError, match="does not exist"):
        collect_recordings([str(tmp_path / "nope.bag")])
    with pytest.raises(InputError, match="no recording matches"):
        collect_recordings([str(tmp_path / "*.db3")])


def test_recordings_sharing_a_name_get_the_shortest_path_suffix_that_tells_them_apart(tmp_path: Path) -> None:
    for folder in ("a/run_bag", "b/run_bag", "x/a/run_bag"):
        (tmp_path / folder).mkdir(parents=True)
    for file in ("x/a/day.bag", "y/a/day.bag", "z/b/day.bag", "solo.bag"):
        (tmp_path / file).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / file).write_bytes(b"x")
    recs = [tmp_path / p for p in ("a/run_bag", "x/a/run_bag", "b/run_bag", "x/a/day.bag", "y/a/day.bag")]
    recs += [tmp_path / p for p in ("z/b/day.bag", "solo.bag")]
    names = run_names(recs)
    # T/a/run_bag ends like T/x/a/run_bag up to 'a': the folder above it (T itself) tells them apart
    top = f"{tmp_path.name}_a_run_bag"
    assert names == [top, "x_a_run_bag", "b_run_bag", "x_a_day", "y_a_day", "b_day", "solo"]
    assert run_names(recs[::-1]) == names[::-1]  # a recording's name does not depend on the order
    assert run_names([tmp_path / "a" / "run_bag", tmp_path / "a" / "run_bag"]) == [None, None]

    settings = load_settings(_registry().models())
    tasks = plan_tasks(recs[:3], tmp_path / "runs", ["ingest"], settings)
    assert [Path(t.run_dir).name for t in tasks] == [top, "x_a_run_bag", "b_run_bag"]
    assert not (tmp_path / "runs").exists()


def test_names_that_still_clash_are_one_error_line_each_before_anything_runs(tmp_path: Path) -> None:
    for d in ("x", "y"):
        (tmp_path / d).mkdir()
        (tmp_path / d / "day.bag").write_bytes(b"x")
    (tmp_path / "x_day.bag").write_bytes(b"x")
    settings = load_settings(_registry().models())
    x, y = tmp_path / "x" / "day.bag", tmp_path / "y" / "day.bag"
    entries = [BatchEntry(x), BatchEntry(x), BatchEntry(y, name="x_day"), tmp_path / "x_day.bag"]
    with pytest.raises(BatchFileError) as info:
        plan_tasks(entries, tmp_path / "runs", ["ingest"], settings, problems=["earlier problem"])
    problems = info.value.problems
    assert len(problems) == 3, problems
    assert problems[0] == "earlier problem"
    assert "listed twice" in problems[1] and str(x) in problems[1]
    assert problems[2].startswith("duplicate name 'x_day': ") and str(y) in problems[2]
    assert str(info.value).count("\nerror: ") == 2  # the CLI prints one error: line per problem
    assert not (tmp_path / "runs").exists()


def test_batch_file_entries_layer_their_settings_over_the_batch(tmp_path: Path) -> None:
    for d in ("a", "b"):
        (tmp_path / d / "run_bag").mkdir(parents=True)
    (tmp_path / "cams").mkdir()
    (tmp_path / "cams" / "b.yaml").write_text("x")
    (tmp_path / "rig_b.yaml").write_text("detect:\n  tag_size_m: 0.3\n  workers: 2\n")
    yaml_file = tmp_path / "fleet.yaml"
    yaml_file.write_text(
        "recordings:\n"
        "  - recording: a/run_bag\n"
        "  - {recording: b/run_bag, name: rig_b, config: rig_b.yaml, camera: cams/b.yaml, stride: 3,\n"
        "     detect: {tag_size_m: 0.2}, ingest.image_topic: /cam}\n"
    )
    csv_file = tmp_path / "fleet.csv"
    csv_file.write_text(
        "# one row per recording\nrecording,name,config,camera,stride,detect.tag_size_m,ingest.image_topic\n"
        "a/run_bag,,,,,,\nb/run_bag,rig_b,rig_b.yaml,cams/b.yaml,3,0.2,/cam\n"
    )
    registry = _registry()
    base = load_settings(registry.models(), None, ["detect.tag_size_m=0.1", "detect.workers=1"])
    for path in (yaml_file, csv_file):
        a, b = load_batch_file(path, registry, base)
        assert (a.recording, a.name, a.settings) == (tmp_path / "a" / "run_bag", None, None)  # the batch's
        assert (b.recording, b.name) == (tmp_path / "b" / "run_bag", "rig_b")
        assert b.settings is not None
        detect, ingest = b.settings["detect"].model_dump(), b.settings["ingest"].model_dump()
        assert detect["tag_size_m"] == 0.2  # the entry's key over its config file over the batch's --set
        assert detect["workers"] == 2  # the entry's config file over the batch's --set
        assert ingest["camera_file"] == str(tmp_path / "cams" / "b.yaml")  # relative to the batch file
        assert (ingest["frame_stride"], ingest["image_topic"]) == (3, "/cam")
        tasks = plan_tasks([a, b], tmp_path / "runs", ["ingest"], base)
        assert [Path(t.run_dir).name for t in tasks] == ["run_bag", "rig_b"]
        assert tasks[0].settings is base and tasks[1].settings is b.settings


def test_every_problem_of_a_batch_file_is_one_line(tmp_path: Path) -> None:
    (tmp_path / "a").mkdir()
    bad = tmp_path / "bad.yaml"
    bad.write_text(
        "- {recording: a, detect.tag_sise_m: 0.16, tagsize: 3}\n"
        "- {recording: missing, name: x}\n"
        "- {recording: a, name: x, stride: 0, detect.tag_size_m: -1, camera: nope.yaml}\n"
        "- {name: y}\n"
    )
    registry = _registry()
    base = load_settings(registry.models())
    with pytest.raises(BatchFileError) as info:
        load_batch_file(bad, registry, base)
    problems = info.value.problems
    expected = [
        ("bad.yaml entry 1 (a): ", "unknown setting 'detect.tag_sise_m' (did you mean 'tag_size_m'?)"),
        ("bad.yaml entry 1 (a): ", "unknown key 'tagsize'"),
        ("bad.yaml entry 2 (missing): ", "recording '" + str(tmp_path / "missing") + "' does not exist"),
        ("bad.yaml entry 3 (a): ", "stride: must be at least 1"),
        ("bad.yaml entry 3 (a): ", "detect.tag_size_m: Input should be greater than 0"),
        ("bad.yaml entry 3 (a): ", "camera: camera file '" + str(tmp_path / "nope.yaml") + "' not found"),
        ("bad.yaml entry 4: ", "no 'recording'"),
    ]
    assert len(problems) == len(expected), problems
    for problem, (where, what) in zip(problems, expected, strict=True):
        assert problem.startswith(where + what), problem
    csv_file = tmp_path / "bad.csv"
    csv_file.write_text("name,bogus,detect.nope,detect.tag_size_m,name\nx,1,2,3,y\n")
    with pytest.raises(BatchFileError) as info:
        load_batch_file(csv_file, registry, base)
    problems = info.value.problems
    assert [p.removeprefix(f"{csv_file}: ").split(";")[0] for p in problems] == [
        "column 'name' appears more than once",
        "no 'recording' column",
        "column 'bogus': unknown key 'bogus'",
        "column 'detect.nope': unknown setting 'detect.nope'",
    ]


def test_summary_reads_headlines_from_stage_summaries_and_leaves_nulls() -> None:
    registry = _registry()
    stages = ["graph", "select_landmarks", "evaluate"]
    full = Outcome(
        recording="/r/a.bag",
        run="a",
        run_dir="/o/a",
        status="done",
        stages_run=["graph"],
        stages={
            "graph": {"seconds": 1.5, "summary": {"landmarks": 24, "health": {"warnings": ["a", "b"]}}},
            "select_landmarks": {"seconds": 0.5, "summary": {"selected": 3, "p_collision_max_focused": 0.02}},
            "evaluate": {"seconds": 2.0, "summary": {"headline": {"collision_rate": 0.1}, "focused_entropy": -3.5}},
        },
    )
    failed = Outcome(
        recording="/r/b.bag", run="b", run_dir="/o/b", status="failed", reason="broken", failed_stage="graph"
    )
    rows = summary_table([full, failed], stages, registry).to_pylist()
    assert rows[0]["landmarks"] == 24
    assert rows[0]["focused_landmarks"] == 3
    assert rows[0]["max_collision_probability"] == pytest.approx(0.02)
    assert rows[0]["collision_rate"] == pytest.approx(0.1)  # a dotted place reaches into "headline"
    assert rows[0]["focused_entropy"] == pytest.approx(-3.5)  # found by the column's own name
    assert rows[0]["graph_warnings"] == 2  # the graph's health warnings, counted
    assert rows[0]["measurements_kept"] is None
    assert rows[0]["seconds_graph"] == 1.5
    assert rows[1] | {"recording": None} == {
        "recording": None,
        "run": "b",
        "run_dir": "/o/b",
        "status": "failed",
        "reason": "broken",
        "failed_stage": "graph",
        "seconds": 0.0,
        "stages_run": [],
        "host": None,
        **{f"seconds_{s}": None for s in stages},
        **dict.fromkeys(registry.headlines),
    }


def test_headlines_count_lists_and_skip_non_numbers_without_any_stage_names() -> None:
    registry = Registry([], {"n": Headline("int64"), "x": Headline("float64", short="X")})
    out = Outcome(
        recording="/r/a.bag",
        run="a",
        run_dir="/o/a",
        status="done",
        stages={"a": {"summary": {"n": [1, 2, 3], "x": "text"}}, "b": {"summary": {"x": 2}}},
    )
    row = summary_table([out], [], registry).to_pylist()[0]
    assert row["n"] == 3 and row["x"] == 2.0  # a list counts; a string is no figure, the next stage's is
    with pytest.raises(ValueError, match="headline 'n' reads unknown stage 'graph'"):
        Registry([], {"n": Headline("int64", (("graph", "landmarks"),))})


# --- end to end ----------------------------------------------------------------------------------------------
def test_local_batch_runs_the_good_recordings_and_reports_the_broken_one(
    local_out: tuple[Path, subprocess.CompletedProcess[str]],
) -> None:
    out, result = local_out
    assert result.returncode == 1, result.stderr
    assert "1 of 4 recordings failed" in result.stderr
    assert "broken" in result.stdout and "failed (ingest)" in result.stdout
    rows = {r["run"]: r for r in pq.read_table(out / SUMMARY_FILE).to_pylist()}
    assert set(rows) == {"s1", "s2", "s3", "broken"}
    for name in ("s1", "s2", "s3"):
        assert rows[name]["status"] == "done" and rows[name]["reason"] is None
        assert rows[name]["stages_run"] == ["ingest", "detect"]
        assert rows[name]["seconds_ingest"] > 0 and rows[name]["seconds_detect"] > 0
        manifest = json.loads((out / name / "manifest.json").read_text())
        assert list(manifest["stages"]) == ["ingest", "detect"]
        assert manifest["stages"]["detect"]["summary"]["detections"] > 0
        assert not (out / name / ".partial").exists()
    broken = rows["broken"]
    assert broken["status"] == "failed" and broken["failed_stage"] == "ingest"
    assert "truncated or damaged" in broken["reason"] and "\n" not in broken["reason"]
    assert broken["seconds_ingest"] is None and broken["landmarks"] is None


def test_dask_cluster_gives_the_same_run_folders_and_summary(
    bags: list[Path], env: dict[str, str], local_out: tuple[Path, Any], tmp_path: Path
) -> None:
    out, _ = local_out
    dask_out = tmp_path / "runs"
    cmd = [sys.executable, "-c", DASK_SCRIPT, str(dask_out), UNTIL, SETS[1], *map(str, bags)]
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300, cwd=env["PYTHONPATH"])
    assert done.returncode == 0, done.stderr[-3000:]
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert str(report["client_pid"]) not in {h.split(":")[1] for h in report["hosts"]}  # ran on the workers
    assert sorted(p.name for p in dask_out.iterdir()) == sorted(p.name for p in out.iterdir())
    assert _manifests(dask_out) == _manifests(out)
    local_rows, dask_rows = _rows(out), _rows(dask_out)
    for row in (*local_rows, *dask_rows):
        row.pop("run_dir")
    assert dask_rows == local_rows


def test_second_call_skips_what_is_up_to_date(
    bags: list[Path], env: dict[str, str], local_out: tuple[Path, Any]
) -> None:
    out, _ = local_out
    before = {p.parent.name: p.read_text() for p in out.glob("*/manifest.json")}
    cmd = _cli("batch", *map(str, bags), "--out", str(out), "--until", UNTIL, "--workers", "2", *SETS)
    result = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300, cwd=env["PYTHONPATH"])
    assert result.returncode == 1, result.stderr
    status = {r["run"]: (r["status"], r["stages_run"]) for r in pq.read_table(out / SUMMARY_FILE).to_pylist()}
    assert status == {"s1": ("skipped", []), "s2": ("skipped", []), "s3": ("skipped", []), "broken": ("failed", [])}
    assert {p.parent.name: p.read_text() for p in out.glob("*/manifest.json")} == before


def test_killed_batch_loses_nothing_and_resumes_without_redoing_stages(
    bags: list[Path], env: dict[str, str], tmp_path: Path
) -> None:
    good = [str(b) for b in bags[:2]]
    out = tmp_path / "runs"
    cmd = _cli("batch", *good, "--out", str(out), "--until", UNTIL, "--workers", "1", *SETS)
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=env["PYTHONPATH"])
    finished: dict[tuple[str, str], tuple[str, str, int]] = {}
    deadline = time.monotonic() + 60
    while not finished and time.monotonic() < deadline and proc.poll() is None:
        for manifest in out.glob("*/manifest.json"):
            try:
                stages = json.loads(manifest.read_text())["stages"]
            except (json.JSONDecodeError, FileNotFoundError):
                continue
            for name in stages:
                finished[(manifest.parent.name, name)] = ("", "", 0)
        time.sleep(0.02)
    assert proc.poll() is None, "the batch ended before any stage finished; the test needs slower recordings"
    assert finished, "no stage finished within 60 s"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    # What the kill left: every finished stage whole; record what the second call must not redo.
    finished.clear()
    for manifest in out.glob("*/manifest.json"):
        for name, entry in json.loads(manifest.read_text())["stages"].items():
            folder = manifest.parent / name
            assert (folder / "summary.json").is_file()
            finished[(manifest.parent.name, name)] = (entry["fingerprint"], entry["finished"], folder.stat().st_ino)
    assert len(finished) < 2 * len(good), "the batch finished before the kill"
    # The batch's worker died with it: its run folder lock is free again (within a moment).
    for lock in out.glob(f"*/{LOCK_FILE}"):
        fd = os.open(lock, os.O_RDWR)
        try:
            for _ in range(50):
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except BlockingIOError:
                    time.sleep(0.1)
            else:
                pytest.fail(f"{lock} is still held after the batch was killed: an orphaned worker is running")
        finally:
            os.close(fd)

    again = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=env["PYTHONPATH"], timeout=300)
    assert again.returncode == 0, again.stderr
    rows = {r["run"]: r for r in pq.read_table(out / SUMMARY_FILE).to_pylist()}
    for (run, stage), (fingerprint, when, inode) in finished.items():
        entry = json.loads((out / run / "manifest.json").read_text())["stages"][stage]
        assert (entry["fingerprint"], entry["finished"]) == (fingerprint, when), f"{run}/{stage} was re-run"
        assert (out / run / stage).stat().st_ino == inode, f"{run}/{stage} was replaced"
        assert stage not in rows[run]["stages_run"]
    for name in ("s1", "s2"):
        assert rows[name]["status"] in ("done", "skipped")
        assert list(json.loads((out / name / "manifest.json").read_text())["stages"]) == ["ingest", "detect"]
        assert not (out / name / ".partial").exists()
    assert any(r["status"] == "done" for r in rows.values())
    shutil.rmtree(out)


# --- batch files, clashing names, run's input options ---------------------------------------------------------
@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two rigs' folders each holding a ROS 2 bag called ``run_bag`` (the same 2 s recording, 0.16 m tags)."""
    from sample_data.simulate import SimConfig, simulate, write_bag

    root = tmp_path_factory.mktemp("fleet")
    rec = simulate(SimConfig(seed=4, path="corridor", duration_s=2.0, image_width=320, image_height=240))
    for rig in ("rig_a", "rig_b"):
        write_bag(rec, root / rig / "run_bag", "ros2-sqlite")
    (root / "fleet.csv").write_text("recording,detect.tag_size_m\nrig_a/run_bag,0.16\nrig_b/run_bag,0.2\n")
    return root


def _detections(run: Path) -> dict[tuple[int, int], tuple[float, float]]:
    """Per (frame, tag id): the tag size detect used and the tag's distance from the camera."""
    rows = pq.read_table(run / "detect" / "detections.parquet").to_pylist()
    return {
        (r["frame"], r["tag_id"]): (r["size_m"], float(np.linalg.norm(np.reshape(r["T_camera_tag"], (4, 4))[:3, 3])))
        for r in rows
    }


def test_batch_file_gives_clashing_recordings_their_own_folders_and_tag_sizes(
    fleet: Path, env: dict[str, str], tmp_path: Path
) -> None:
    out = tmp_path / "runs"
    cmd = _cli("batch", "--file", str(fleet / "fleet.csv"), "--out", str(out), "--until", UNTIL, "-j", "2", *SETS)
    first = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300, cwd=env["PYTHONPATH"])
    assert first.returncode == 0, first.stderr
    assert sorted(p.name for p in out.iterdir() if p.is_dir()) == ["rig_a_run_bag", "rig_b_run_bag"]
    sizes = {}
    for run, size in (("rig_a_run_bag", 0.16), ("rig_b_run_bag", 0.2)):
        settings = json.loads((out / run / "settings.json").read_text())
        assert settings["detect"]["tag_size_m"] == size
        assert settings["detect"]["workers"] == 1  # the batch's --set under the entry's own
        sizes[run] = _detections(out / run)
        assert {s for s, _ in sizes[run].values()} == {size}
    a, b = sizes["rig_a_run_bag"], sizes["rig_b_run_bag"]
    assert a.keys() == b.keys() and len(a) > 5  # the same recording, the same tags seen
    for key in a:  # a tag believed 0.2 m wide instead of 0.16 m is seen from 1.25 times as far
        assert b[key][1] / a[key][1] == pytest.approx(0.2 / 0.16, rel=1e-3)
    again = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300, cwd=env["PYTHONPATH"])
    assert again.returncode == 0, again.stderr
    rows = {r["run"]: r["status"] for r in pq.read_table(out / SUMMARY_FILE).to_pylist()}
    assert rows == {"rig_a_run_bag": "skipped", "rig_b_run_bag": "skipped"}  # the same folders: nothing to redo


def test_bad_batch_file_is_one_error_line_per_problem_and_runs_nothing(
    fleet: Path, env: dict[str, str], tmp_path: Path
) -> None:
    bad = tmp_path / "bad.csv"
    rig_a = fleet / "rig_a" / "run_bag"
    bad.write_text(f"recording,name,stride,detect.tag_size_m\n{rig_a},x,0,0.2\n{fleet / 'gone'},x,2,big\n")
    out = tmp_path / "runs"
    cmd = _cli("batch", "--file", str(bad), "--out", str(out), "--until", UNTIL)
    result = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=120, cwd=env["PYTHONPATH"])
    assert result.returncode == 1
    lines = result.stderr.strip().splitlines()
    assert all(
        line.startswith("error: bad.csv line ") or line.startswith("error: duplicate name 'x'") for line in lines
    )
    expected = [
        "line 2 (" + str(rig_a) + "): stride: must be at least 1",
        "line 3 (" + str(fleet / "gone") + "): recording",
        "line 3 (" + str(fleet / "gone") + "): detect.tag_size_m: Input should be a valid number",
        "duplicate name 'x'",
    ]
    assert len(lines) == len(expected), lines
    for line, what in zip(lines, expected, strict=True):
        assert what in line, line
    assert not out.exists() and result.stdout == ""


def test_start_end_stride_on_batch_give_the_ingest_of_run(
    bags: list[Path], env: dict[str, str], tmp_path: Path
) -> None:
    window = ("--start", "0.4", "--end", "1.6", "--stride", "2")
    common = ("--until", "ingest", *window)
    by_run = subprocess.run(
        _cli("run", str(bags[0]), "--out", str(tmp_path / "run"), *common),
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        cwd=env["PYTHONPATH"],
    )
    assert by_run.returncode == 0, by_run.stderr
    by_batch = subprocess.run(
        _cli("batch", str(bags[0]), "--out", str(tmp_path / "batch"), *common),
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        cwd=env["PYTHONPATH"],
    )
    assert by_batch.returncode == 0, by_batch.stderr
    run_dir, batch_dir = tmp_path / "run" / "s1", tmp_path / "batch" / "s1"
    ingest = [json.loads((d / "manifest.json").read_text())["stages"]["ingest"] for d in (run_dir, batch_dir)]
    assert ingest[0]["fingerprint"] == ingest[1]["fingerprint"]  # same code, source and settings
    assert _stable(ingest[0]["summary"]) == _stable(ingest[1]["summary"])
    frames = [pq.read_table(d / "ingest" / "frames.parquet") for d in (run_dir, batch_dir)]
    assert frames[0].equals(frames[1])
    stamps = frames[1].column("stamp_ns").to_pylist()
    start_ns = ingest[1]["summary"]["start_ns"]
    assert 0 < len(stamps) <= 4  # 10 frames in 2 s; every second one of those between 0.4 s and 1.6 s
    assert all(0.4e9 <= s - start_ns <= 1.6e9 for s in stamps)
