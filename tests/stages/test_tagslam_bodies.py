"""TagSLAM bodies end to end, on recordings written on the fly (:mod:`tests.fixtures.tag_detection_bags`): a rig
with one or two cameras moves past a wall of static tags (ids 0 to 9) while a wand with tags 40 and 41 moves about
in front of it.

- the wand's tags (``is_static: false`` in tagslam.yaml) are no landmarks: the graph leaves their detections out
  and one note names the body, its tags and how many detections;
- a static camera rig (TagSLAM's aviary: fixed cameras watching the wand) stops ``focusmap run`` with one line
  before a run folder is made;
- a camera_poses.yaml sits in the rig body cameras.yaml names, whatever it is called, and a camera's entry is
  found by its cameras.yaml name even when the camera has a frame id of its own.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

from tests.fixtures.tag_detection_bags import (
    TAG_SIZE_M,
    WAND_TAGS,
    camera_poses_yaml,
    cameras_yaml,
    write_tag_detection_bag,
)

ROOT = Path(__file__).resolve().parents[2]

TAGSLAM_YAML = f"""
default_body: wall
bodies:
 - wall:
     is_static: true
     type: simple
     default_tag_size: {TAG_SIZE_M}
 - wand:
     is_static: false
     type: simple
     default_tag_size: {TAG_SIZE_M}
     tags:
       - id: 40
       - id: 41
 - rig:
     is_static: RIG_STATIC
     type: simple
"""


def _tags_file(folder: Path, rig_static: bool = False) -> Path:
    path = folder / ("aviary.yaml" if rig_static else "tagslam.yaml")
    path.write_text(TAGSLAM_YAML.replace("RIG_STATIC", "true" if rig_static else "false"))
    return path


def _focusmap(*args: str | Path) -> subprocess.CompletedProcess[str]:
    cmd = [sys.executable, "-m", "cli.app", *map(str, args)]
    return subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=600)


def _T(rotvec: list[float], t: list[float]) -> np.ndarray:
    from stages.extrinsics import rotation_from_rotvec

    T = np.eye(4)
    T[:3, :3] = rotation_from_rotvec(rotvec)
    T[:3, 3] = t
    return T


def test_the_tags_of_a_moving_wand_are_no_landmarks(tmp_path: Path) -> None:
    """With the tags file the wand's tags are left out of the graph (one note line says which and how many) and
    only the wall's are landmarks; without it they were landmarks too (the wand is in view throughout)."""
    bag, counts = write_tag_detection_bag(tmp_path / "wand.bag", {"cam0": np.eye(4)})
    cameras = cameras_yaml(tmp_path / "cameras.yaml", ["cam0"])
    assert all(counts[t] >= 20 for t in WAND_TAGS)
    common = ("run", bag, "--until", "graph", "--camera", cameras, "--set", "graph.model=3d")

    proc = _focusmap(*common, "--out", tmp_path / "with", "--tags", _tags_file(tmp_path))
    assert proc.returncode == 0, proc.stderr[-2000:]
    graph = tmp_path / "with" / "wand" / "graph"
    summary = json.loads((graph / "summary.json").read_text())
    left_out = counts[40] + counts[41]
    assert summary["dropped_moving_body_tags"] == {"wand": {"tags": [40, 41], "detections": left_out}}
    assert sorted(pq.read_table(graph / "landmarks.parquet").column("tag_id").to_pylist()) == list(range(10))
    notes = [line for line in proc.stderr.splitlines() if "moving body" in line]
    assert len(notes) == 1, proc.stderr
    assert notes[0].strip().startswith(f"note: {left_out} detections of tags 40, 41 left out")
    assert "'wand'" in notes[0] and "is_static: false" in notes[0]
    assert summary["health"]["ok"], summary["health"]["warnings"]
    ingest = json.loads((tmp_path / "with" / "wand" / "ingest" / "tags.json").read_text())
    assert ingest["moving_tags"] == {"wand": [40, 41]}

    proc = _focusmap(*common, "--out", tmp_path / "without")
    assert proc.returncode == 0, proc.stderr[-2000:]
    landmarks = pq.read_table(tmp_path / "without" / "wand" / "graph" / "landmarks.parquet").column("tag_id")
    assert {40, 41} <= set(landmarks.to_pylist())  # the wand seen as if it stood still: what the tags file prevents


def test_a_static_camera_rig_stops_before_any_run_folder(tmp_path: Path) -> None:
    """TagSLAM's aviary: the rig body the cameras sit on is static. `run` and `ingest` stop with one line that says
    why, exit non-zero and make no run folder (the bag is not read)."""
    bag, _ = write_tag_detection_bag(tmp_path / "aviary.bag", {"cam0": np.eye(4)}, frames=3)
    cameras = cameras_yaml(tmp_path / "cameras.yaml", ["cam0"], rig_body="rig")
    tags = _tags_file(tmp_path, rig_static=True)
    for command in ("run", "ingest"):
        proc = _focusmap(command, bag, "--out", tmp_path / "runs", "--camera", cameras, "--tags", tags)
        assert proc.returncode != 0, proc.stdout
        lines = proc.stderr.strip().splitlines()
        assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
        assert lines[0].startswith(
            "error: aviary.yaml makes the camera rig 'rig' (carrying cam0) static (is_static: true): "
            "focusmap maps static tags from a moving camera"
        ), lines[0]
        assert not (tmp_path / "runs").exists()


def test_a_rig_body_of_another_name_is_the_base_of_camera_poses(tmp_path: Path) -> None:
    """cameras.yaml puts both cameras on a rig body called 'quad'; camera_poses.yaml places cam0 (whose frame id is
    its own, 'left_optical'), /tf_static places cam1 from 'quad'. Both mounts are found, from the 'quad' frame."""
    from pipeline.config import load_settings
    from pipeline.registry import Registry
    from pipeline.run_folder import RunFolder
    from pipeline.runner import run_stage
    from stages import ingest

    mounts = {"cam0": _T([0.0, 0.05, 0.0], [-0.1, 0.0, 0.0]), "cam1": _T([0.0, -0.05, 0.0], [0.1, 0.0, 0.0])}
    bag, _ = write_tag_detection_bag(
        tmp_path / "quad.bag", mounts, frames=5, tf_static=[("quad", "cam1", mounts["cam1"])]
    )
    cameras = cameras_yaml(tmp_path / "cameras.yaml", ["cam0", "cam1"], "quad", frame_ids={"cam0": "left_optical"})
    poses = camera_poses_yaml(tmp_path / "camera_poses.yaml", {"cam0": mounts["cam0"]})
    registry = Registry([ingest.STAGE])
    sets = [
        f"ingest.camera_file={cameras}",
        f"ingest.extrinsics_file={poses}",
        f"ingest.tags_file={_tags_file(tmp_path)}",
    ]
    run = RunFolder.create(tmp_path / "run", bag)
    summary = run_stage(run, registry, "ingest", load_settings(registry.models(), None, sets)).summary
    assert summary["warnings"] == []
    ext = json.loads((run.stage_dir("ingest") / "extrinsics.json").read_text())
    assert ext["base_frame"] == "quad"
    cam0, cam1 = ext["sensors"]["camera"], ext["sensors"]["/cam1/tags"]
    assert cam0["frame_id"] == "left_optical" and not cam0["assumed"]
    assert cam0["source"] == "camera_poses.yaml (tagslam camera_poses) cam0"
    np.testing.assert_allclose(cam0["T_base_sensor"], mounts["cam0"], atol=1e-12)
    assert cam1["source"] == "/tf_static" and not cam1["assumed"]
    np.testing.assert_allclose(cam1["T_base_sensor"], mounts["cam1"], atol=1e-9)
