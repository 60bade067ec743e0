"""Extrinsics files (TagSLAM camera_poses.yaml, Kalibr camchain, plain 4x4) read as ``T_base_frame``, tag
families of bag detections, and a stereo TagSLAM recording through ingest with ``--extrinsics``.

Conventions checked by hand-computed transforms: TagSLAM's pose is the camera in the rig (maps camera points
into the rig, TagSLAM's ``T_rig_cam``); Kalibr's ``T_cam_imu`` and ``T_cn_cnm1`` map the other way and are
inverted; a plain file holds ``T_base_frame`` as it stands.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from pipeline.errors import InputError
from stages.extrinsics import invert, load_extrinsics_file, rotation_from_rotvec
from stages.tag_families import bag_family


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "extrinsics.yaml"
    path.write_text(text)
    return path


def _rz(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])


def test_rotvec_is_rodrigues() -> None:
    assert np.allclose(rotation_from_rotvec([0, 0, np.pi / 2]), _rz(90))
    R = rotation_from_rotvec([0.3, -0.2, 0.9])
    assert np.allclose(R @ R.T, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)
    # the rotation axis is left alone
    assert np.allclose(R @ np.array([0.3, -0.2, 0.9]), [0.3, -0.2, 0.9])


def test_tagslam_camera_poses_are_camera_in_rig(tmp_path: Path) -> None:
    """cam1 rotated 90 deg about z and 10 cm along x of the rig: its optical centre (camera origin) lands at
    (0.1, 0, 0) in the rig, and its x axis along the rig's y."""
    path = _write(
        tmp_path,
        """
cam0:
  pose:
    position: {x: 0, y: 0, z: 0}
    rotation: {x: 0, y: 0, z: 0}
    R: [1000000, 0, 0, 0, 0, 0,  0, 1000000, 0, 0, 0, 0,  0, 0, 1000000, 0, 0, 0,
        0, 0, 0, 1000000, 0, 0,  0, 0, 0, 0, 1000000, 0,  0, 0, 0, 0, 0, 1000000]
cam1:
  pose:
    position: {x: 0.1, y: 0.0, z: 0.0}
    rotation: {x: 0.0, y: 0.0, z: 1.5707963267948966}
""",
    )
    f = load_extrinsics_file(path)
    assert f.kind == "tagslam camera_poses" and f.base_frame == "rig"
    assert np.allclose(f.mounts["cam0"], np.eye(4))
    T = f.mounts["cam1"]
    assert np.allclose(T @ [0, 0, 0, 1], [0.1, 0, 0, 1])
    assert np.allclose(T[:3, :3] @ [1, 0, 0], [0, 1, 0])
    assert np.allclose(f.information["cam0"], np.eye(6) * 1e12) and "cam1" not in f.information


def test_tagslam_r_is_the_upper_triangular_square_root_information(tmp_path: Path) -> None:
    """TagSLAM writes R as gtsam's square-root information (upper triangular, test_3's cam1): the information is
    RᵀR. An R that is not 36 numbers, or singular, is one line naming the entry."""
    from tests.fixtures.shared_data import need_shared

    f = load_extrinsics_file(need_shared("tagslam-test/test_3/camera_poses.yaml"))
    R = np.array(yaml.safe_load(need_shared("tagslam-test/test_3/camera_poses.yaml").read_text())["cam1"]["pose"]["R"])
    assert np.allclose(f.information["cam1"], R.reshape(6, 6).T @ R.reshape(6, 6))
    for bad, match in (("[1, 0, 0]", "expected 36 numbers"), ("[" + ", ".join(["0"] * 36) + "]", "singular")):
        path = _write(
            tmp_path,
            f"cam0:\n  pose:\n    position: {{x: 0, y: 0, z: 0}}\n    rotation: {{x: 0, y: 0, z: 0}}\n    R: {bad}\n",
        )
        with pytest.raises(InputError, match=f"cam0.pose.R: .*{match}"):
            load_extrinsics_file(path)


def test_kalibr_camchain_is_inverted_and_chained(tmp_path: Path) -> None:
    """Camera-only camchain: base cam0; T_cn_cnm1 maps cam0 points into cam1, so T_cam0_cam1 is its inverse;
    cam2 chains through cam1."""
    T10 = np.eye(4)
    T10[:3, :3] = _rz(30)
    T10[:3, 3] = [-0.12, 0.01, 0.0]
    T21 = np.eye(4)
    T21[:3, :3] = _rz(-10)
    T21[:3, 3] = [0.0, -0.05, 0.02]
    path = _write(
        tmp_path,
        f"""
cam0:
  camera_model: pinhole
  intrinsics: [400, 400, 320, 240]
cam1:
  T_cn_cnm1: {T10.tolist()}
cam2:
  T_cn_cnm1: {T21.tolist()}
""",
    )
    f = load_extrinsics_file(path)
    assert f.kind == "kalibr camchain" and f.base_frame == "cam0"
    assert np.allclose(f.mounts["cam0"], np.eye(4))
    assert np.allclose(f.mounts["cam1"], np.linalg.inv(T10))
    assert np.allclose(f.mounts["cam2"], np.linalg.inv(T21 @ T10))
    # a point 1 m in front of cam1 seen from cam0: T10 maps it back into cam1
    p_cam0 = f.mounts["cam1"] @ [0, 0, 1, 1]
    assert np.allclose(T10 @ p_cam0, [0, 0, 1, 1])


def test_kalibr_imucam_has_the_imu_as_base(tmp_path: Path) -> None:
    T0 = np.eye(4)
    T0[:3, :3] = _rz(90)
    T0[:3, 3] = [0.01, 0.02, 0.03]
    T1 = np.eye(4)
    T1[:3, 3] = [-0.1, 0.0, 0.0]
    path = _write(tmp_path, f"cam0:\n  T_cam_imu: {T0.tolist()}\ncam1:\n  T_cam_imu: {T1.tolist()}\n")
    f = load_extrinsics_file(path)
    assert f.base_frame == "imu"
    assert np.allclose(f.mounts["cam0"], np.linalg.inv(T0))
    assert np.allclose(f.mounts["cam1"], np.linalg.inv(T1))


def test_plain_matrices_are_kept_as_T_base_frame(tmp_path: Path) -> None:
    T = np.eye(4)
    T[:3, :3] = _rz(45)
    T[:3, 3] = [0.2, 0.0, 0.5]
    path = _write(
        tmp_path, f"base_frame: base_link\ncamera_optical: {T.tolist()}\nlaser: {np.eye(4).ravel().tolist()}\n"
    )
    f = load_extrinsics_file(path)
    assert f.kind == "4x4 matrices" and f.base_frame == "base_link"
    assert np.allclose(f.mounts["camera_optical"], T) and np.allclose(f.mounts["laser"], np.eye(4))
    assert np.allclose(invert(T) @ T, np.eye(4))
    assert f.find("nope", "camera_optical") == ("camera_optical", f.mounts["camera_optical"])


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("cam0: [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]\n", "4x4"),
        ("cam0: [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]\n", "not a rotation"),
        ("cam0: {foo: 1}\n", "none of"),
        ("[1, 2]\n", "not a YAML mapping"),
    ],
)
def test_bad_extrinsics_files_give_one_line(tmp_path: Path, text: str, message: str) -> None:
    with pytest.raises(InputError, match=message) as err:
        load_extrinsics_file(_write(tmp_path, text))
    assert "\n" not in str(err.value)


def test_bag_families_map_to_known_names() -> None:
    assert bag_family("mit") == "tag36h11"  # TagSLAM's MIT detector: bits 6, ids up to 586 in test_2
    assert bag_family("") == "tag36h11"
    assert bag_family("36h11") == "tag36h11"
    assert bag_family("tag25h9") == "tag25h9"
    assert bag_family("Standard41h12") == "tagStandard41h12"
    assert bag_family("aruco_4x4") == "aruco_4x4"  # unknown: kept as given


def _tagslam_bag(tmp_path: Path, name: str) -> Path:
    import bz2

    from tests.fixtures.shared_data import need_shared

    src = need_shared(f"tagslam-test/{name}/tag_detections.bag.bz2")
    bag = tmp_path / "tag_detections.bag"
    bag.write_bytes(bz2.decompress(src.read_bytes()))
    return bag


def test_stereo_tagslam_recording_uses_each_cameras_calibration(tmp_path: Path) -> None:
    """test_2's stereo recording (family ``mit``) with test_3's camera_poses.yaml (both cameras placed): both
    detection topics are read, each with its own cameras.yaml entry and mount, and the graph uses both."""
    from pipeline.config import load_settings
    from pipeline.registry import Registry
    from pipeline.run_folder import RunFolder
    from pipeline.runner import run_stage
    from stages import detect, graph, ingest
    from tests.fixtures.shared_data import need_shared

    bag = _tagslam_bag(tmp_path, "test_2")
    folder = need_shared("tagslam-test")
    registry = Registry([ingest.STAGE, detect.STAGE, graph.STAGE])
    sets = [
        f"ingest.camera_file={folder / 'test_2' / 'cameras.yaml'}",
        f"ingest.extrinsics_file={folder / 'test_3' / 'camera_poses.yaml'}",
        "ingest.start_s=29",
        "ingest.end_s=37",
        "detect.tag_size_m=0.16",
        "graph.model=3d",
    ]
    run = RunFolder.create(tmp_path / "run", bag)
    settings = load_settings(registry.models(), None, sets)
    summary: dict[str, Any] = run_stage(run, registry, "ingest", settings).summary
    assert summary["camera_topics"] == ["/stereo/left/tags", "/stereo/right/tags"]
    assert summary["warnings"] == []
    out = run.stage_dir("ingest")
    ext = json.loads((out / "extrinsics.json").read_text())
    cams = json.loads((out / "cameras.json").read_text())["cameras"]
    assert ext["base_frame"] == "rig" and ext["file"].endswith("test_3/camera_poses.yaml")
    right = ext["sensors"]["/stereo/right/tags"]
    assert right["frame_id"] == "cam1" and right["source"].endswith("cam1") and not right["assumed"]
    R = rotation_from_rotvec([2.18315889, 0.00184602, 2.25060271])
    assert np.allclose(np.asarray(right["T_base_sensor"])[:3, :3], R)
    assert np.allclose(np.asarray(right["T_base_sensor"])[:3, 3], [0.08058282, 0.00047375, -0.07335839])
    assert cams["/stereo/right/tags"]["K"][0] == pytest.approx(471.126)  # cam1's, not cam0's 470.338
    assert cams["/stereo/left/tags"]["K"][0] == pytest.approx(470.338)
    det: dict[str, Any] = run_stage(run, registry, "detect", settings).summary
    assert det["families"] == ["tag36h11"] and det["detections"] > 0
    g: dict[str, Any] = run_stage(run, registry, "graph", settings).summary
    assert set(g["extrinsics"]) == {"/stereo/left/tags", "/stereo/right/tags"}
    assert "dropped_camera_without_extrinsics" not in g


def test_camera_without_extrinsics_is_calibrated_from_the_tags_it_shares(tmp_path: Path) -> None:
    """test_2's own camera_poses.yaml places only cam0: the graph estimates the right camera's mount from the tags
    both cameras see (TagSLAM does the same), within 1 cm and 0.5° of the mount test_3's camera_poses.yaml gives for
    the same rig, and writes it as a camera_poses.yaml that --extrinsics reads back. With
    ``graph.rig_calibration=false`` the camera is left out instead, as before."""
    from pipeline.config import load_settings
    from pipeline.registry import Registry
    from pipeline.run_folder import RunFolder
    from pipeline.runner import run_stage
    from stages import detect, graph, ingest
    from stages.extrinsics import load_extrinsics_file
    from stages.graph import remarks as graph_remarks
    from stages.graph.rig import GIVEN_PRIOR, camera_poses_yaml
    from stages.ingest import remarks
    from tests.fixtures.shared_data import need_shared

    bag = _tagslam_bag(tmp_path, "test_2")
    folder = need_shared("tagslam-test/test_2")
    registry = Registry([ingest.STAGE, detect.STAGE, graph.STAGE])
    sets = [
        f"ingest.camera_file={folder / 'cameras.yaml'}",
        f"ingest.extrinsics_file={folder / 'camera_poses.yaml'}",
        "detect.tag_size_m=0.16",
        "graph.model=3d",
    ]
    run = RunFolder.create(tmp_path / "run", bag)
    settings = load_settings(registry.models(), None, sets)
    summary: dict[str, Any] = run_stage(run, registry, "ingest", settings).summary
    assert summary["warnings"] == []
    (note,) = [n for n in summary["notes"] if "'cam1'" in n]
    assert "estimates its mount" in note and ("note", note) in remarks(summary)
    run_stage(run, registry, "detect", settings)
    g: dict[str, Any] = run_stage(run, registry, "graph", settings).summary
    assert "dropped_camera_without_extrinsics" not in g
    assert set(g["extrinsics"]) == {"/stereo/left/tags", "/stereo/right/tags"}
    cam = g["rig_calibration"]["cameras"]["/stereo/right/tags"]
    assert cam["frame_id"] == "cam1" and cam["placed_from"] == "/stereo/left/tags"
    T = np.asarray(cam["T_base_camera"])
    truth = load_extrinsics_file(need_shared("tagslam-test/test_3/camera_poses.yaml")).mounts["cam1"]
    angle = np.degrees(np.arccos(np.clip((np.trace(T[:3, :3].T @ truth[:3, :3]) - 1) / 2, -1, 1)))
    assert np.linalg.norm(T[:3, 3] - truth[:3, 3]) < 0.01 and angle < 0.5
    assert 0 < max(cam["sigma_translation_m"]) < 0.01
    assert any(kind == "note" and "camera cam1" in text for kind, text in graph_remarks(g))
    from rerun.chunk import RrdReader

    paths = {c.entity_path for c in RrdReader(run.rrd_path("graph")).stream()}
    assert {"/graph/pose/cameras", "/graph/pose/cameras_given"} <= paths  # the mounts under the moving rig
    written = load_extrinsics_file(run.stage_dir("graph") / "camera_poses.yaml")
    assert set(written.mounts) == {"cam0", "cam1"}
    assert np.allclose(written.mounts["cam1"], T, atol=1e-6) and np.allclose(written.mounts["cam0"], np.eye(4))
    off = load_settings(registry.models(), None, [*sets, "graph.rig_calibration=false"])
    g = run_stage(run, registry, "graph", off).summary
    assert list(g["dropped_camera_without_extrinsics"]) == ["/stereo/right/tags"]
    assert set(g["extrinsics"]) == {"/stereo/left/tags"} and "rig_calibration" not in g
    assert not (run.stage_dir("graph") / "camera_poses.yaml").exists()
    # cam1 given 5 cm off with a loose R (σ 0.1 m, 0.1 rad): estimated with it as its prior, back within 1 cm
    loose = tmp_path / "camera_poses_loose.yaml"
    off_by = truth.copy()
    off_by[:3, 3] += [0.05, 0.0, 0.0]
    loose.write_text(camera_poses_yaml({"cam0": (np.eye(4), None), "cam1": (off_by, np.eye(6) * 0.01)}, "rig"))
    sets_loose = [s for s in sets if not s.startswith("ingest.extrinsics_file")]
    settings_loose = load_settings(registry.models(), None, [*sets_loose, f"ingest.extrinsics_file={loose}"])
    for stage in ("ingest", "detect"):
        run_stage(run, registry, stage, settings_loose)
    g = run_stage(run, registry, "graph", settings_loose).summary
    cam = g["rig_calibration"]["cameras"]["/stereo/right/tags"]
    assert cam["placed_from"] == GIVEN_PRIOR
    T = np.asarray(cam["T_base_camera"])
    assert np.linalg.norm(T[:3, 3] - truth[:3, 3]) < 0.01
    assert any(kind == "note" and "looser than 1 mm" in text for kind, text in graph_remarks(g))
