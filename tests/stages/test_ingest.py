"""Ingest end to end on generated recordings: ROS 1, ROS 2 SQLite, ROS 2 MCAP and a standalone MCAP file."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from pipeline.artifacts import StageInput
from pipeline.config import load_settings
from pipeline.contracts import TableSpec
from pipeline.errors import InputError
from pipeline.run_folder import RunFolder
from pipeline.runner import run_stage
from sample_data.simulate import SimConfig, simulate, write_bag
from stages import REGISTRY
from stages.ingest.artifacts import ARTIFACTS, CAMERA, EXTRINSICS, CameraModel

FORMATS = {"ros1": "bag.bag", "ros2-sqlite": "bag_sqlite", "ros2-mcap": "bag_mcap", "mcap": "bag.mcap"}


@pytest.fixture(scope="module")
def recording():
    return simulate(SimConfig(seed=3, path="corridor", duration_s=4.0, image_format="jpeg"))


@pytest.fixture(scope="module")
def bags(recording, tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("bags")
    return {fmt: write_bag(recording, root / name, fmt) for fmt, name in FORMATS.items()}


def _ingest(bag: Path, tmp: Path, *sets: str) -> RunFolder:
    run = RunFolder.create(tmp / bag.stem, bag)
    run_stage(run, REGISTRY, "ingest", load_settings(REGISTRY.models(), None, list(sets)))
    return run


def _written(recording, kind: str) -> list:
    return [m for m in recording.messages if type(m.payload).__name__ == kind]


@pytest.mark.parametrize("fmt", list(FORMATS))
def test_round_trip_counts_images_odometry_camera(fmt: str, bags, recording, tmp_path: Path) -> None:
    run = _ingest(bags[fmt], tmp_path)
    out = run.stage_dir("ingest")
    summary = json.loads((out / "summary.json").read_text())
    images = _written(recording, "ImageMsg")
    odom = _written(recording, "OdometryMsg")
    scans = _written(recording, "ScanMsg")
    assert (summary["frames"], summary["odometry"], summary["scans"]) == (len(images), len(odom), len(scans))
    frames = pq.read_table(out / "frames.parquet").to_pylist()
    assert [f["frame"] for f in frames] == list(range(len(images)))
    assert frames[0]["format"] == "jpeg" and bytes(frames[0]["data"]) == bytes(images[0].payload.data)
    assert frames[-1]["stamp_ns"] == images[-1].stamp_ns
    table = pq.read_table(out / "odometry.parquet")
    assert table.column("x").to_numpy() == pytest.approx([m.payload.x for m in odom])
    assert np.allclose(table.column("pose_cov").to_pylist()[5], odom[5].payload.pose_covariance)
    camera = json.loads((out / "camera.json").read_text())
    assert camera["K"] == pytest.approx(list(np.asarray(recording.ground_truth["camera"]["K"]).ravel()))
    assert camera["distortion_model"] == "plumb_bob" and len(camera["D"]) == 5
    ext = json.loads((out / "extrinsics.json").read_text())
    gt = recording.ground_truth
    assert np.allclose(ext["sensors"]["camera"]["T_base_sensor"], gt["T_base_camera"], atol=1e-9)
    assert np.allclose(ext["sensors"]["laser"]["T_base_sensor"], gt["T_base_laser"], atol=1e-9)
    assert summary["reader"] == ("mcap" if fmt == "mcap" else "rosbags")


def test_every_artifact_is_declared_and_written_as_declared(bags, tmp_path: Path) -> None:
    out = _ingest(bags["ros1"], tmp_path).stage_dir("ingest")
    written = {p.name for p in out.iterdir()} - {"summary.json"}
    declared = {spec.file: spec for spec in ARTIFACTS.specs}
    assert written <= set(declared)
    assert {f for f, spec in declared.items() if not spec.optional} <= written
    for name in written:
        if isinstance(spec := declared[name], TableSpec):
            assert pq.read_schema(out / name).equals(spec.schema), name
    done = StageInput("ingest", out)
    assert isinstance(CAMERA.read(done), CameraModel) and CAMERA.read(done).width > 0
    mounts = EXTRINSICS.read(done).sensors
    assert set(mounts) == {"camera", "laser"} and not mounts["laser"].assumed


def test_window_and_stride_keep_frame_indices(bags, recording, tmp_path: Path) -> None:
    run = _ingest(bags["ros1"], tmp_path, "ingest.start_s=1.0", "ingest.end_s=3.0", "ingest.frame_stride=2")
    frames = pq.read_table(run.stage_dir("ingest") / "frames.parquet").to_pylist()
    images = _written(recording, "ImageMsg")
    t0 = min(m.stamp_ns for m in recording.messages)
    expect = [i for i, m in enumerate(images) if t0 + 1e9 <= m.stamp_ns <= t0 + 3e9 and i % 2 == 0]
    assert [f["frame"] for f in frames] == expect
    assert all(f["stamp_ns"] == images[f["frame"]].stamp_ns for f in frames)


def test_empty_window_is_an_error(bags, tmp_path: Path) -> None:
    with pytest.raises(InputError, match="widen the time window"):
        _ingest(bags["ros1"], tmp_path, "ingest.start_s=100")
    assert not (tmp_path / "bag" / "ingest").exists()


def test_ingest_rrd_read_back(bags, recording, tmp_path: Path) -> None:
    from rerun.chunk import RrdReader

    run = _ingest(bags["ros1"], tmp_path, "rerun.image_stride=2", "rerun.scan_stride=4")
    rows: dict[str, int] = {}
    for chunk in RrdReader(run.rrd_path("ingest")).stream():
        if not chunk.is_static:
            rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
    n_img = len(_written(recording, "ImageMsg"))
    n_scan = len(_written(recording, "ScanMsg"))
    assert rows["/ingest/camera/image"] == (n_img + 1) // 2
    assert rows["/ingest/world/scan"] == (n_scan + 3) // 4
    assert rows["/ingest/world/odometry/base"] == len(_written(recording, "OdometryMsg"))


def _logged(path: Path, entity: str, column: str) -> list:
    """The values of one component column of an entity's temporal rows in a recording, row by row."""
    from rerun.chunk import RrdReader

    rows: list = []
    for chunk in RrdReader(path).stream():
        if str(chunk.entity_path) == entity and not chunk.is_static:
            batch = chunk.to_record_batch()
            rows.extend(batch.column(batch.schema.get_field_index(column)).to_pylist())
    return rows


def test_ingest_rrd_values_are_the_tables(bags, recording, tmp_path: Path) -> None:
    """The scans drawn in ingest.rrd are the table's valid returns placed at the nearest odometry pose (a plain
    per-scan computation here), and the frames drawn are the table's bytes, every stride-th."""
    run = _ingest(bags["ros1"], tmp_path, "rerun.image_stride=3", "rerun.scan_stride=2")
    out = run.stage_dir("ingest")
    scans = pq.read_table(out / "scans.parquet").to_pylist()
    odom = pq.read_table(out / "odometry.parquet").to_pylist()
    frames = pq.read_table(out / "frames.parquet").to_pylist()
    T_base_laser = np.asarray(json.loads((out / "extrinsics.json").read_text())["sensors"]["laser"]["T_base_sensor"])
    stamps = np.array([o["stamp_ns"] for o in odom])
    logged = _logged(run.rrd_path("ingest"), "/ingest/world/scan", "Points3D:positions")
    assert len(logged) == len(scans[::2]) > 5
    for scan, points in zip(scans[::2], logged, strict=True):
        o = odom[min(int(np.searchsorted(stamps, scan["stamp_ns"])), len(odom) - 1)]
        x, y, z, w = (o[k] for k in ("qx", "qy", "qz", "qw"))
        R = np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
            ]
        )
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, (o["x"], o["y"], o["z"])
        r = np.asarray(scan["ranges"], dtype=float)
        a = scan["angle_min"] + scan["angle_increment"] * np.arange(r.size)
        ok = np.isfinite(r) & (r >= scan["range_min"]) & (r <= scan["range_max"])
        local = np.column_stack([r[ok] * np.cos(a[ok]), r[ok] * np.sin(a[ok]), np.zeros(ok.sum()), np.ones(ok.sum())])
        expect = (T @ T_base_laser @ local.T).T[:, :3]
        assert np.allclose(np.asarray(points, dtype=float), expect, atol=1e-5)  # Rerun stores float32
    blobs = _logged(run.rrd_path("ingest"), "/ingest/camera/image", "EncodedImage:blob")
    assert [bytes(b[0]) for b in blobs] == [f["data"] for f in frames[::3]]


@pytest.mark.parametrize("compression", ["bz2", "lz4"])
def test_compressed_ros1_chunks(compression: str, recording, tmp_path: Path) -> None:
    bag = write_bag(recording, tmp_path / f"{compression}.bag", "ros1", compression=compression)
    run = _ingest(bag, tmp_path)
    summary = json.loads((run.stage_dir("ingest") / "summary.json").read_text())
    assert summary["frames"] == len(_written(recording, "ImageMsg"))
    assert summary["odometry"] == len(_written(recording, "OdometryMsg"))


def test_several_topics_of_a_type_name_the_setting(recording, tmp_path: Path) -> None:
    """Two image topics: the error lists both and names ingest.image_topic; setting it picks one."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag1 import Writer

    src = write_bag(recording, tmp_path / "src.bag", "ros1")
    dst = tmp_path / "two_cameras.bag"
    with AnyReader([src]) as reader, Writer(dst) as writer:
        conns = {}
        for c in reader.connections:
            conns[c.topic] = writer.add_connection(c.topic, c.msgtype, msgdef=c.msgdef.data, md5sum=c.digest)
            if c.topic == "/camera/image_raw/compressed":
                conns["/left"] = writer.add_connection(
                    "/left/compressed", c.msgtype, msgdef=c.msgdef.data, md5sum=c.digest
                )
        for c, t, data in reader.messages():
            writer.write(conns[c.topic], t, data)
            if c.topic == "/camera/image_raw/compressed":
                writer.write(conns["/left"], t, data)
    with pytest.raises(
        InputError,
        match=r"several camera image topics \['/camera/image_raw/compressed', "
        r"'/left/compressed'\]; pick one with --set ingest.image_topic=",
    ):
        _ingest(dst, tmp_path)
    run = _ingest(dst, tmp_path, "ingest.image_topic=/left/compressed")
    frames = pq.read_table(run.stage_dir("ingest") / "frames.parquet", columns=["topic"]).column(0).to_pylist()
    assert set(frames) == {"/left/compressed"}


def test_salvage_reads_a_truncated_recording_up_to_the_damage(recording, tmp_path: Path) -> None:
    bag = write_bag(recording, tmp_path / "cut.bag", "ros1")
    size = bag.stat().st_size
    with bag.open("r+b") as fh:
        fh.truncate(int(size * 0.7))
    with pytest.raises(InputError, match=r"truncated or damaged.*--salvage"):
        _ingest(bag, tmp_path)
    assert not (tmp_path / "cut" / "ingest").exists()
    run = _ingest(bag, tmp_path, "ingest.salvage=true")
    summary = json.loads((run.stage_dir("ingest") / "summary.json").read_text())
    n_images = len(_written(recording, "ImageMsg"))
    assert 0 < summary["frames"] < n_images
    assert summary["salvaged"]["messages"] > 0 and summary["salvaged"]["stopped_at"]
    frames = pq.read_table(run.stage_dir("ingest") / "frames.parquet").to_pylist()
    images = _written(recording, "ImageMsg")
    assert all(bytes(f["data"]) == bytes(images[f["frame"]].payload.data) for f in frames)


def test_salvage_reads_a_truncated_mcap_file(recording, tmp_path: Path) -> None:
    bag = write_bag(recording, tmp_path / "cut.mcap", "mcap")
    with bag.open("r+b") as fh:
        fh.truncate(int(bag.stat().st_size * 0.6))
    with pytest.raises(InputError, match=r"truncated or damaged.*--salvage"):
        _ingest(bag, tmp_path)
    run = _ingest(bag, tmp_path, "ingest.salvage=true")
    summary = json.loads((run.stage_dir("ingest") / "summary.json").read_text())
    assert summary["reader"] == "mcap" and summary["salvaged"]["stopped_at"]
    assert 0 < summary["frames"] < len(_written(recording, "ImageMsg"))
    assert 0 < summary["odometry"] < len(_written(recording, "OdometryMsg"))


def test_raw_frames_row_groups_and_drawings(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Raw bgr8 frames: frames.parquet keeps their bytes exactly, in row groups bounded by their bytes (readers
    hold a group at a time), and ingest.rrd draws them as JPEG showing the same picture."""
    import cv2

    import stages.ingest.stage as ingest_stage

    rec = simulate(SimConfig(seed=5, path="corridor", duration_s=3.0, image_format="bgr8"))
    bag = write_bag(rec, tmp_path / "raw.bag", "ros1")
    frame_bytes = 640 * 480 * 3
    monkeypatch.setattr(ingest_stage, "FRAME_GROUP_BYTES", 4 * frame_bytes)
    run = _ingest(bag, tmp_path, "rerun.image_stride=2")
    path = run.stage_dir("ingest") / "frames.parquet"
    meta = pq.ParquetFile(path).metadata
    images = _written(rec, "ImageMsg")
    assert meta.num_rows == len(images) > 8
    sizes = [meta.row_group(g).num_rows for g in range(meta.num_row_groups)]
    assert max(sizes) == 4 and sum(sizes) == len(images)
    frames = pq.read_table(path).to_pylist()
    assert all(bytes(f["data"]) == bytes(m.payload.data) for f, m in zip(frames, images, strict=True))
    blobs = _logged(run.rrd_path("ingest"), "/ingest/camera/image", "EncodedImage:blob")
    kinds = _logged(run.rrd_path("ingest"), "/ingest/camera/image", "EncodedImage:media_type")
    assert len(blobs) == (len(images) + 1) // 2 and {k[0] for k in kinds} == {"image/jpeg"}
    for f, blob in zip(frames[::2], blobs, strict=True):
        drawn = cv2.imdecode(np.frombuffer(bytes(blob[0]), np.uint8), cv2.IMREAD_COLOR)
        raw = np.frombuffer(bytes(f["data"]), np.uint8).reshape(480, 640, 3)
        assert len(bytes(blob[0])) < frame_bytes / 5
        assert np.abs(drawn.astype(int) - raw).mean() < 3.0


@pytest.mark.parametrize("fmt", ["yuv422", "bayer_rggb8"])
def test_yuv_and_bayer_frames_read_back_as_the_scene(fmt: str, tmp_path: Path) -> None:
    """A colour camera's raw YUV 4:2:2 or Bayer frames, through a ROS 2 bag and ingest, decode to the grey the
    simulator rendered: exactly (the luma), or within demosaicking's blur."""
    from sample_data.simulate import decode_image
    from stages.frames import decode_frame

    rec = simulate(SimConfig(seed=6, path="corridor", duration_s=1.0, image_format=fmt))  # type: ignore[arg-type]
    run = _ingest(write_bag(rec, tmp_path / fmt, "ros2-sqlite"), tmp_path)
    frames = pq.read_table(run.stage_dir("ingest") / "frames.parquet").to_pylist()
    images = _written(rec, "ImageMsg")
    assert len(frames) == len(images) > 2
    for f, m in zip(frames, images, strict=True):
        assert f["format"] == fmt
        got = decode_frame(f["format"], f["width"], f["height"], f["step"], f["data"]).astype(int)
        want = decode_image(m.payload).astype(int)
        if fmt == "yuv422":
            assert np.array_equal(got, want)
        else:
            assert np.abs(got - want)[2:-2, 2:-2].mean() < 2.0
