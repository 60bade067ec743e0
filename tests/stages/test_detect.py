"""detect: frame decoding, back-ends against rendered ground truth, reference bitmaps, real photos, tag pose
and its covariance (Monte Carlo), calibration files, and the stage on a run folder."""

from __future__ import annotations

import logging
from collections import Counter
from pathlib import Path

import cv2
import numpy as np
import pyarrow.parquet as pq
import pytest

from pipeline.config import load_settings
from pipeline.errors import InputError, StageError
from pipeline.run_folder import RunFolder
from pipeline.runner import run_stage
from stages import REGISTRY
from stages.camera import colmap_camera, load_camera_file
from stages.detect.artifacts import DETECTIONS
from stages.detect.backends import make_detector, shortest_side_px
from stages.detect.config import DetectConfig
from stages.detect.core import detect_image
from stages.detect.pose import estimate_tag_pose
from stages.frames import CorruptFrameError, decode_frame
from tests.fixtures.detect_runs import camera_model as _camera
from tests.fixtures.detect_runs import fake_ingest as _fake_ingest
from tests.fixtures.shared_data import need_shared
from tests.fixtures.tag_render import TagPlacement, corners_of, look_at_tag, render_frame

BACKENDS = ("apriltag3", "opencv")


# --------------------------------------------------------------------------- frames


def test_decode_frame_every_encoding() -> None:
    rng = np.random.default_rng(1)
    gray = rng.integers(0, 256, (6, 5), dtype=np.uint8)
    ok, png = cv2.imencode(".png", gray)
    assert ok
    assert np.array_equal(decode_frame("png", 5, 6, 0, png.tobytes()), gray)
    ok, jpg = cv2.imencode(".jpg", gray, [cv2.IMWRITE_JPEG_QUALITY, 100])
    assert np.abs(decode_frame("jpeg", 5, 6, 0, jpg.tobytes()).astype(int) - gray).max() <= 8
    padded = np.zeros((6, 8), np.uint8)
    padded[:, :5] = gray
    assert np.array_equal(decode_frame("mono8", 5, 6, 8, padded.tobytes()), gray)
    bgr = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
    assert np.array_equal(decode_frame("bgr8", 5, 6, 15, bgr.tobytes()), gray)
    assert np.array_equal(decode_frame("rgb8", 5, 6, 15, bgr[:, :, ::-1].tobytes()), gray)
    mono16 = (gray.astype("<u2") * 4).tobytes()
    assert np.abs(decode_frame("mono16", 5, 6, 10, mono16).astype(int) - (gray * (255 / gray.max()))).max() <= 1


@pytest.mark.parametrize("pattern", ["rggb", "bggr", "gbrg", "grbg"])
def test_decode_frame_bayer_mosaics_give_the_scene_grey(pattern: str) -> None:
    """A colour camera's raw mosaic (ROS names the first row's first two sites) demosaics to the grey of the
    scene; a pattern read the wrong way round swaps red and blue, which this picture's grey tells apart."""
    h, w = 40, 48
    y, x = np.mgrid[0:h, 0:w]
    bgr = np.dstack([40 + 4 * y, np.full((h, w), 120), 30 + 4 * x]).astype(np.uint8)  # blue down, red across
    channel = {"b": 0, "g": 1, "r": 2}
    mosaic = np.empty((h, w), np.uint8)
    for k, c in enumerate(pattern):
        dy, dx = divmod(k, 2)
        mosaic[dy::2, dx::2] = bgr[dy::2, dx::2, channel[c]]
    want = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY).astype(int)[2:-2, 2:-2]
    got = decode_frame(f"bayer_{pattern}8", w, h, w, mosaic.tobytes()).astype(int)[2:-2, 2:-2]
    assert np.abs(got - want).mean() < 2.0
    swapped = bgr[:, :, ::-1]
    assert np.abs(cv2.cvtColor(swapped, cv2.COLOR_BGR2GRAY).astype(int)[2:-2, 2:-2] - want).mean() > 5.0
    deep = (mosaic.astype("<u2") * 256).tobytes()  # 16 bits: scaled by the frame's own range
    got16 = decode_frame(f"BAYER_{pattern.upper()}16", w, h, 2 * w, deep).astype(int)[2:-2, 2:-2]
    assert np.abs(got16 - want * 255 / mosaic.max()).mean() < 2.0


def test_decode_frame_yuv422_is_its_luma() -> None:
    rng = np.random.default_rng(2)
    luma = rng.integers(0, 256, (6, 8), dtype=np.uint8)
    chroma = rng.integers(0, 256, (6, 8), dtype=np.uint8)
    uyvy = np.empty((6, 16), np.uint8)
    uyvy[:, 0::2], uyvy[:, 1::2] = chroma, luma
    yuyv = np.empty((6, 16), np.uint8)
    yuyv[:, 0::2], yuyv[:, 1::2] = luma, chroma
    for fmt, data in (("yuv422", uyvy), ("uyvy", uyvy), ("yuv422_yuy2", yuyv), ("yuyv", yuyv)):
        assert np.array_equal(decode_frame(fmt, 8, 6, 16, data.tobytes()), luma), fmt


@pytest.mark.parametrize(
    ("fmt", "data"), [("jpeg", b"\xff\xd8garbage"), ("png", b""), ("mono8", b"\x00" * 10), ("nv12", b"\x00" * 45)]
)
def test_decode_frame_corrupt_raises(fmt: str, data: bytes) -> None:  # nv12: not an encoding we read
    with pytest.raises(CorruptFrameError):
        decode_frame(fmt, 5, 6, 0, data)


# --------------------------------------------------------------------------- rendered ground truth

SCENES = {
    # name: (lens model, tags as (id, distance m, yaw, pitch, roll, offset), blur px, noise)
    "near-frontal": ("plumb_bob", [(1, 0.6, 0, 0, 5, (-0.12, 0.0)), (2, 0.8, 10, 0, -20, (0.15, 0.05))], 0.0, 2.0),
    "oblique": ("plumb_bob", [(3, 1.0, 55, 0, 0, (-0.2, 0.0)), (4, 1.2, -40, 25, 30, (0.25, -0.1))], 0.6, 2.0),
    "far": ("none", [(5, 2.2, 10, 0, 0, (-0.3, 0.0)), (6, 2.5, -20, 10, 0, (0.35, 0.1))], 0.0, 1.0),
    "blurred": ("plumb_bob", [(7, 0.9, 20, 10, 0, (0.0, 0.0))], 1.5, 3.0),
    "fisheye-edge": ("equidistant", [(8, 0.7, 30, 0, 0, (-0.45, -0.2)), (9, 0.8, -10, -20, 0, (0.5, 0.3))], 0.5, 2.0),
}


def _scene(name: str) -> tuple[object, list[TagPlacement], np.ndarray]:
    model, specs, blur, noise = SCENES[name]
    cam = colmap_camera(_camera(model))
    tags = [TagPlacement(i, "tag36h11", 0.1, look_at_tag(d, y, p, r, off)) for i, d, y, p, r, off in specs]
    img = render_frame(cam, tags, blur_sigma=blur, noise_sigma=noise, rng=np.random.default_rng(7))
    return cam, tags, img


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("scene", list(SCENES))
def test_recall_and_corners_on_rendered_frames(backend: str, scene: str) -> None:
    cam, tags, img = _scene(scene)
    cfg = DetectConfig(backend=backend, decimation=1.0 if scene == "far" else 2.0, tag_size_m=0.1)
    found = {o.tag_id: o for o in make_detector(cfg).detect(img)}
    assert set(found) <= {t.tag_id for t in tags}, "false ids"
    for tag in tags:
        truth = corners_of(cam, tag)
        assert shortest_side_px(truth) >= 15
        assert tag.tag_id in found, f"tag {tag.tag_id} missed"
        rms = float(np.sqrt(np.mean(np.sum((found[tag.tag_id].corners - truth) ** 2, axis=1))))
        # OpenCV's sub-pixel refinement is measurably looser on oblique, blurred tags (docs/detect.md).
        assert rms < (0.35 if backend == "apriltag3" else 1.0), f"corner RMS {rms:.3f} px"


def test_shortest_side_is_the_smallest_side_length_to_the_bit() -> None:
    # the detections' side_px (and the min_side_px cut) must not move by a rounding when the formula is rewritten
    rng = np.random.default_rng(0)
    for _ in range(2000):
        quad = rng.normal(size=(4, 2)) * rng.uniform(1, 500) + rng.uniform(0, 1000, size=2)
        sides = [float(np.hypot(*(quad[i] - quad[(i + 1) % 4]))) for i in range(4)]
        assert shortest_side_px(quad) == pytest.approx(min(sides), rel=1e-15)
        assert shortest_side_px(quad) == float(np.min(np.linalg.norm(quad - np.roll(quad, -1, axis=0), axis=1)))
    assert shortest_side_px(np.array([[0, 0], [30, 0], [30, 20], [0, 20]])) == 20.0


def test_frame_without_tags_gives_no_rows() -> None:
    cfg = DetectConfig()
    cam = colmap_camera(_camera())
    img = render_frame(cam, [], noise_sigma=3.0)
    assert detect_image(img, make_detector(cfg), cam, cfg) == []


# --------------------------------------------------------------------------- reference bitmaps and real photos


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize(("family", "count"), [("tag36h11", 587), ("tag25h9", 35), ("tag16h5", 30)])
def test_every_reference_bitmap_decodes_to_its_id(backend: str, family: str, count: int) -> None:
    mosaic = cv2.imread(str(need_shared("tag-bitmaps") / f"{family}-mosaic.png"), cv2.IMREAD_UNCHANGED)
    gray = np.where(mosaic[:, :, 3] > 0, mosaic[:, :, 0], 255).astype(np.uint8)
    pitch = {"tag36h11": 11, "tag25h9": 10, "tag16h5": 9}[family]  # tag with white border + 1 px separator
    per_row = (gray.shape[1] + 1) // pitch
    scale = 6
    big = cv2.resize(
        np.pad(gray, pitch, constant_values=255), None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST
    )
    cfg = DetectConfig(backend=backend, families=(family,), decimation=1.0, max_hamming=0)
    seen: dict[int, int] = {}
    for obs in make_detector(cfg).detect(big):
        cx, cy = obs.corners.mean(axis=0) / scale - pitch
        seen[obs.tag_id] = int(cy // pitch) * per_row + int(cx // pitch)
    assert sorted(seen) == list(range(count))
    assert all(slot == tag_id for tag_id, slot in seen.items())


def _photo_truth(txt: Path) -> list[np.ndarray]:
    out = []
    for line in txt.read_text().splitlines():
        nums = [float(v) for v in line.replace("(", " ").replace(")", " ").replace(",", " ").split()[1:]]
        # The file is the AprilTag library's output: its corner order, and pixel centres at +0.5.
        out.append(np.array(nums).reshape(4, 2)[[1, 0, 3, 2]] - 0.5)
    return out


def test_real_photos_every_tag_found() -> None:
    folder = need_shared("apriltag-photos")
    detector = make_detector(DetectConfig(backend="apriltag3"))
    for jpg in sorted(folder.glob("*.jpg")):
        truth = _photo_truth(jpg.with_suffix(".txt"))
        found = detector.detect(cv2.imread(str(jpg), cv2.IMREAD_GRAYSCALE))
        assert len(found) == len(truth), jpg.name
        sq = []
        for t in truth:
            best = min(found, key=lambda o: float(np.linalg.norm(o.corners.mean(0) - t.mean(0))))
            sq.append(np.mean(np.sum((best.corners - t) ** 2, axis=1)))
        # Measured 0.34 and 0.60 px RMS against the upstream files (docs/detect.md), not their 0.14 px.
        assert np.sqrt(np.mean(sq)) < 0.7, jpg.name


# --------------------------------------------------------------------------- pose and covariance


def test_pose_exact_corners_and_both_ippe_solutions() -> None:
    cam = colmap_camera(_camera("plumb_bob"))
    T = look_at_tag(0.9, 35, 15, 10, (0.1, -0.05))
    pose = estimate_tag_pose(corners_of(cam, TagPlacement(0, "tag36h11", 0.12, T)), 0.12, cam)
    assert pose is not None
    assert np.allclose(pose.T_camera_tag, T, atol=1e-6)
    assert pose.alt_T_camera_tag is not None and pose.ambiguity_ratio < 1e-6
    assert pose.reprojection_px < 1e-6
    # Small and frontal: both planar solutions fit noisy corners about as well.
    far = TagPlacement(0, "tag36h11", 0.05, look_at_tag(3.0))
    noisy = corners_of(cam, far) + np.random.default_rng(3).normal(0, 0.5, (4, 2))
    ambiguous = estimate_tag_pose(noisy, 0.05, cam)
    assert ambiguous is not None and ambiguous.ambiguity_ratio > 0.05


@pytest.mark.parametrize("model", ["plumb_bob", "equidistant"])
def test_covariance_matches_monte_carlo_spread(model: str) -> None:
    import gtsam

    cam = colmap_camera(_camera(model))
    T_true = look_at_tag(0.8, 40, -20, 10, (0.1, 0.05))
    truth = corners_of(cam, TagPlacement(0, "tag36h11", 0.15, T_true))
    sigma = 0.4
    rng = np.random.default_rng(11)
    errors = []
    cov = None
    for _ in range(300):
        pose = estimate_tag_pose(truth + rng.normal(0, sigma, (4, 2)), 0.15, cam)
        assert pose is not None
        errors.append(gtsam.Pose3(pose.T_camera_tag).localCoordinates(gtsam.Pose3(T_true)))
        cov = sigma**2 * pose.cov_unit if cov is None else cov
    errors_arr = np.array(errors)
    sample = np.cov(errors_arr.T)
    # Per-axis spread within 25 %, and the NEES (per degree of freedom) near 1.
    ratio = np.sqrt(np.diag(sample) / np.diag(cov))
    assert np.all((ratio > 0.75) & (ratio < 1.3)), ratio
    nees = np.mean([e @ np.linalg.solve(cov, e) for e in errors_arr]) / 6
    assert 0.75 < nees < 1.35, nees


def test_position_cov_is_the_translation_block_in_the_camera_frame() -> None:
    cam = colmap_camera(_camera())
    T = look_at_tag(1.0, 30, 0, 0)
    pose = estimate_tag_pose(corners_of(cam, TagPlacement(0, "tag36h11", 0.1, T)), 0.1, cam)
    assert pose is not None
    R = pose.T_camera_tag[:3, :3]
    assert np.allclose(pose.position_cov_unit, R @ pose.cov_unit[3:, 3:] @ R.T)
    # Depth is the least certain direction of a tag's centre.
    assert np.argmax(np.diag(pose.position_cov_unit)) == 2


# --------------------------------------------------------------------------- calibration files


def test_kalibr_cameras_yaml_both_lens_models() -> None:
    folder = need_shared("tagslam-test")
    fish = load_camera_file(folder / "test_1" / "cameras.yaml")
    assert fish.distortion_model == "equidistant" and fish.width == 1280 and len(fish.D) == 4
    assert colmap_camera(fish).model_name == "OPENCV_FISHEYE"
    radtan = load_camera_file(folder / "test_10" / "cameras.yaml")
    assert radtan.distortion_model == "plumb_bob" and len(radtan.D) == 5
    assert colmap_camera(radtan).model_name == "FULL_OPENCV"
    second = load_camera_file(folder / "test_21" / "cameras.yaml", topic="/t265/fisheye2/tags")
    assert second.K[0] == pytest.approx(286.80)


def test_camera_info_yaml(tmp_path: Path) -> None:
    path = tmp_path / "cam.yaml"
    path.write_text(
        "image_width: 640\nimage_height: 480\ncamera_name: front\n"
        "camera_matrix: {rows: 3, cols: 3, data: [400, 0, 320, 0, 401, 240, 0, 0, 1]}\n"
        "distortion_model: plumb_bob\n"
        "distortion_coefficients: {rows: 1, cols: 5, data: [-0.1, 0.01, 0.001, 0.0, 0.0]}\n"
    )
    cam = load_camera_file(path)
    assert cam.K[4] == 401 and cam.distortion_model == "plumb_bob" and cam.frame_id == "front"
    assert colmap_camera(cam).model_name == "OPENCV"


def test_a_calibration_that_is_no_camera_names_the_file(tmp_path: Path) -> None:
    path = tmp_path / "cameras.yaml"
    path.write_text("cam0:\n  intrinsics: [400, 401, 320, 240]\n  resolution: [0, 480]\n  distortion_model: none\n")
    with pytest.raises(InputError, match=r"cameras\.yaml' cam0: width: .*greater than 0"):
        load_camera_file(path)


# --------------------------------------------------------------------------- the stage on a run folder


def _rendered_run(tmp_path: Path) -> tuple[RunFolder, list[TagPlacement]]:
    """Four rendered frames (the third without tags) and a corrupt one."""
    camera = _camera()
    cam = colmap_camera(camera)
    tags = [
        TagPlacement(4, "tag36h11", 0.1, look_at_tag(0.7, 20, 0, 0, (-0.1, 0))),
        TagPlacement(9, "tag36h11", 0.1, look_at_tag(0.9, -25, 10, 0, (0.15, 0.05))),
    ]
    jobs = []
    for k in range(4):
        img = render_frame(cam, tags if k != 2 else [], noise_sigma=2.0, rng=np.random.default_rng(k))
        jobs.append(("png", cv2.imencode(".png", img)[1].tobytes()))
    jobs.append(("jpeg", b"\xff\xd8 not a jpeg"))
    return _fake_ingest(tmp_path, jobs, camera, 640, 480), tags


_SETTINGS = ["detect.tag_size_m=0.1", "detect.workers=2", "detect.batch_frames=2"]


def test_stage_writes_detections_skips_corrupt_and_empty_frames(tmp_path: Path) -> None:
    run, tags = _rendered_run(tmp_path)
    settings = load_settings(REGISTRY.models(), None, _SETTINGS)
    result = run_stage(run, REGISTRY, "detect", settings)
    summary = result.summary
    assert summary["frames"] == 5 and summary["corrupt_frames"] == 1 and summary["corrupt_frame_ids"] == [4]
    table = pq.read_table(run.stage_dir("detect") / "detections.parquet")
    assert table.num_rows == 6 and summary["detections"] == 6 and summary["distinct_tags"] == 2
    assert 2 not in table.column("frame").to_pylist()
    assert table.schema.equals(DETECTIONS.schema)
    rows = table.to_pylist()
    truth = {t.tag_id: t for t in tags}
    for r in rows:
        T = np.reshape(r["T_camera_tag"], (4, 4))
        assert np.linalg.norm(T[:3, 3] - truth[r["tag_id"]].T_camera_tag[:3, 3]) < 0.01
        cov = np.reshape(r["pose_cov"], (6, 6))
        assert np.all(np.linalg.eigvalsh(cov) > 0)
    assert (run.path / "detect.rrd").exists()


def test_frames_detect_cannot_decode_one_line_each(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """Frames in an encoding detect does not read: with other frames, one warning names it; alone, one error
    before any pixel is read, and no detections are written. Damaged frames: one warning per reason."""
    camera = _camera()
    img = render_frame(colmap_camera(camera), [], noise_sigma=2.0, rng=np.random.default_rng(0))
    good = ("png", cv2.imencode(".png", img)[1].tobytes())
    jobs = [good, good, *[("nv12", bytes(640 * 720))] * 3, *[("jpeg", b"\xff\xd8 cut")] * 7]
    run = _fake_ingest(tmp_path / "mixed", jobs, camera, 640, 480)
    settings = load_settings(REGISTRY.models(), None, [*_SETTINGS, "detect.workers=1"])
    with caplog.at_level(logging.WARNING), pytest.raises(StageError, match="no tag36h11 tags found"):
        run_stage(run, REGISTRY, "detect", settings)
    lines = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert [m for m in lines if "'nv12' (3 frames) skipped: detect does not decode" in m] != []
    damaged = [m for m in lines if "do not decode" in m and "jpeg" in m]
    assert len(damaged) == 1 and "(7 in all)" in damaged[0]
    only = _fake_ingest(tmp_path / "only", [("nv12", bytes(640 * 720))] * 3, camera, 640, 480)
    with pytest.raises(InputError, match=r"^the camera frames are in encoding 'nv12' \(3 frames\), which detect"):
        run_stage(only, REGISTRY, "detect", settings)
    assert not (only.stage_dir("detect") / "detections.parquet").exists()


def test_detections_made_into_arrow_in_chunks_equal_the_table_made_at_once(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The stage turns its rows into Arrow TABLE_CHUNK at a time (memory on long recordings): 6 rows in chunks of 4
    give the same table as in one."""
    from stages.detect import stage as detect_stage

    whole, _ = _rendered_run(tmp_path / "whole")
    run_stage(whole, REGISTRY, "detect", load_settings(REGISTRY.models(), None, _SETTINGS))
    monkeypatch.setattr(detect_stage, "TABLE_CHUNK", 4)
    chunked, _ = _rendered_run(tmp_path / "chunked")
    run_stage(chunked, REGISTRY, "detect", load_settings(REGISTRY.models(), None, _SETTINGS))
    a = pq.read_table(whole.stage_dir("detect") / "detections.parquet")
    b = pq.read_table(chunked.stage_dir("detect") / "detections.parquet")
    assert a.num_rows == 6 and a.equals(b)


def test_stage_reads_detections_the_bag_holds(tmp_path: Path) -> None:
    import bz2

    from rosbags.highlevel import AnyReader

    folder = need_shared("tagslam-test") / "test_1"
    bag = tmp_path / "tag_detections.bag"
    bag.write_bytes(bz2.decompress((folder / "tag_detections.bag.bz2").read_bytes()))
    per_msg: Counter[int] = Counter()
    with AnyReader([bag]) as reader:
        conns = [c for c in reader.connections if c.msgtype.endswith("ApriltagArrayStamped")]
        for i, (conn, _, raw) in enumerate(reader.messages(connections=conns)):
            per_msg[i] = len(reader.deserialize(raw, conn.msgtype).apriltags)
    run = RunFolder.create(tmp_path / "run", bag)
    settings = load_settings(
        REGISTRY.models(), None, [f"ingest.camera_file={folder / 'cameras.yaml'}", "detect.tag_size_m=0.225"]
    )
    run_stage(run, REGISTRY, "ingest", settings)
    summary = run_stage(run, REGISTRY, "detect", settings).summary
    assert summary["source"] == "tag_detections"
    assert summary["detections"] == sum(per_msg.values())
    assert summary["frames_with_tags"] == sum(1 for v in per_msg.values() if v)
    table = pq.read_table(run.stage_dir("detect") / "detections.parquet")
    # The corner order read from the bag fits a tag facing the camera to a fraction of a pixel.
    assert np.median(table.column("reprojection_px").to_numpy()) < 0.3
    R = np.reshape(table.column("T_camera_tag")[0].as_py(), (4, 4))[:3, :3]
    assert R[2, 2] < 0
