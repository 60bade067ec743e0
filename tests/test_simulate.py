"""Tests of the deterministic recording simulator in ``sample_data/simulate.py``."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from sample_data.simulate import (
    CAMERA_INFO_TOPIC,
    ODOM_TOPIC,
    SCAN_TOPIC,
    TF_STATIC_TOPIC,
    CameraModel,
    ImageMsg,
    OdometryMsg,
    Recording,
    ScanMsg,
    SimConfig,
    build_trajectory,
    build_world,
    decode_image,
    distance_to_walls,
    ground_truth_path,
    main,
    planar_T,
    simulate,
    tag_corners_tag_frame,
    write_bag,
)


def _payloads(rec: Recording, kind: type) -> list:
    return [m.payload for m in rec.messages if isinstance(m.payload, kind)]


@pytest.fixture(scope="module")
def office_rec() -> Recording:
    """Six seconds of the office path, lossless images so the detector sees the rendering."""
    return simulate(SimConfig(seed=1, duration_s=6.0, image_format="png"))


@pytest.fixture(scope="module")
def small_rec() -> Recording:
    """A tiny recording for the writers."""
    return simulate(SimConfig(seed=2, duration_s=1.5, image_width=160, image_height=120))


def test_world_has_enough_tags_with_contiguous_ids() -> None:
    world = build_world(SimConfig(first_tag_id=10))
    ids = [t.id for t in world.tags]
    assert len(ids) >= 50
    assert ids == list(range(10, 10 + len(ids)))
    corridor = [t for t in world.tags if t.T_world_tag[0, 3] > 8.0]
    assert len(corridor) >= 10
    for tag in world.tags:  # tag z points away from its wall, into free space
        T = tag.T_world_tag
        assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3))
        assert np.isclose(np.linalg.det(T[:3, :3]), 1.0)
        assert np.allclose(T[:3, 1], [0, 0, 1])
        assert np.allclose(T[:3, 2], np.append(world.wall_normals()[tag.wall], 0.0))
    sized = build_world(SimConfig(tag_size_overrides=((3, 0.24),))).tags
    assert [t.size_m for t in sized[2:5]] == [0.16, 0.24, 0.16]


def test_same_seed_same_messages_other_seed_other_noise() -> None:
    cfg = SimConfig(seed=5, duration_s=1.0, image_width=160, image_height=120)
    a, b = simulate(cfg), simulate(cfg)
    assert [m.topic for m in a.messages] == [m.topic for m in b.messages]
    for ma, mb in zip(a.messages, b.messages, strict=True):
        assert ma.stamp_ns == mb.stamp_ns
        pa, pb = ma.payload, mb.payload
        if isinstance(pa, ScanMsg):
            assert np.array_equal(pa.ranges, pb.ranges)
            continue
        assert pa == pb
    assert json.dumps(a.ground_truth) == json.dumps(b.ground_truth)
    c = simulate(SimConfig(seed=6, duration_s=1.0, image_width=160, image_height=120))
    assert _payloads(c, OdometryMsg)[-1].x != _payloads(a, OdometryMsg)[-1].x
    assert _payloads(c, ImageMsg)[0].data != _payloads(a, ImageMsg)[0].data


def test_messages_in_time_order_with_header_stamps(office_rec: Recording) -> None:
    stamps = [m.stamp_ns for m in office_rec.messages]
    assert stamps == sorted(stamps)
    assert stamps[0] == SimConfig().start_time_ns
    assert office_rec.messages[0].topic == TF_STATIC_TOPIC
    for m in office_rec.messages:
        header = m.payload.transforms[0].header if m.topic == TF_STATIC_TOPIC else m.payload.header
        assert header.stamp_ns == m.stamp_ns
    counts = office_rec.counts()
    assert counts[CAMERA_INFO_TOPIC] == counts["/camera/image_raw/compressed"] == 30
    assert counts[ODOM_TOPIC] == 121
    assert counts[SCAN_TOPIC] == 60


@pytest.mark.parametrize("path", ["office", "corridor"])
def test_path_keeps_clear_of_walls(path: str) -> None:
    cfg = SimConfig(path=path)
    traj = build_trajectory(cfg)
    t = np.arange(0.0, traj.duration_s, 0.01)
    x, y, _, v, w = traj.sample(t)
    assert distance_to_walls(np.stack([x, y], axis=1), build_world(cfg).walls).min() > 0.25
    assert v.max() <= cfg.max_speed_mps + 1e-9
    assert np.abs(w).max() <= cfg.max_yaw_rate_radps + 1e-6
    assert x.max() > 15.0  # reaches the far end of the corridor
    if path == "office":
        assert 60.0 < traj.duration_s < 150.0
        assert x.min() < 2.0 and y.max() > 4.5  # wanders the room first


def test_laser_ranges_are_ray_cast_distances(office_rec: Recording) -> None:
    gt = office_rec.ground_truth
    walls = np.array(gt["world"]["walls"])
    poses = {p["stamp_ns"]: p for p in gt["poses"]}
    T_base_laser = np.array(gt["T_base_laser"])
    sigma = gt["noise"]["laser_range_sigma_m"]
    residuals = []
    for scan in _payloads(office_rec, ScanMsg)[::10]:
        p = poses[scan.header.stamp_ns]
        T = planar_T(p["x"], p["y"], p["yaw"]) @ T_base_laser
        yaw = math.atan2(T[1, 0], T[0, 0])
        for i, r in enumerate(scan.ranges):
            a = yaw + scan.angle_min + i * scan.angle_increment
            o, d = T[:2, 3], np.array([math.cos(a), math.sin(a)])
            best = math.inf
            for x0, y0, x1, y1 in walls:  # plain ray / segment intersection
                e = np.array([x1 - x0, y1 - y0])
                den = d[0] * e[1] - d[1] * e[0]
                if abs(den) < 1e-12:
                    continue
                ao = np.array([x0, y0]) - o
                t = (ao[0] * e[1] - ao[1] * e[0]) / den
                s = (ao[0] * d[1] - ao[1] * d[0]) / den
                if t > 0 and 0 <= s <= 1:
                    best = min(best, t)
            if best > scan.range_max:
                assert math.isinf(r)
            else:
                residuals.append(float(r) - best)
    res = np.array(residuals)
    assert len(res) > 500
    assert np.abs(res).max() < 6 * sigma
    assert 0.5 * sigma < res.std() < 1.5 * sigma


def test_odometry_drifts_but_stays_bounded() -> None:
    rec = simulate(SimConfig(seed=3, duration_s=12.0, image_width=160, image_height=120))
    gt = rec.ground_truth
    T_world_odom = np.array(gt["T_world_odom"])
    poses = {p["stamp_ns"]: p for p in gt["poses"]}
    odom = _payloads(rec, OdometryMsg)
    assert odom[0].x == odom[0].y == odom[0].yaw == 0.0
    assert odom[0].header.frame_id == "odom" and odom[0].child_frame_id == "base_link"
    errors = []
    for o in odom:
        p = poses[o.header.stamp_ns]
        est = T_world_odom @ planar_T(o.x, o.y, o.yaw)
        errors.append(math.hypot(est[0, 3] - p["x"], est[1, 3] - p["y"]))
    assert 1e-4 < errors[-1] < 0.5
    assert max(errors) < 0.5
    cov = np.array(odom[-1].pose_covariance).reshape(6, 6)
    assert np.allclose(cov, cov.T)
    assert np.all(np.linalg.eigvalsh(cov[np.ix_([0, 1, 5], [0, 1, 5])]) > 0)
    first_cov = np.array(odom[10].pose_covariance).reshape(6, 6)
    assert cov[0, 0] + cov[1, 1] > first_cov[0, 0] + first_cov[1, 1]  # uncertainty grows
    assert errors[-1] < 6 * math.sqrt(cov[0, 0] + cov[1, 1])  # and the drift fits it
    twist_cov = np.array(odom[-1].twist_covariance).reshape(6, 6)
    assert twist_cov[0, 0] == pytest.approx(gt["noise"]["odom_v_sigma_mps"] ** 2)
    assert twist_cov[5, 5] == pytest.approx(gt["noise"]["odom_yaw_rate_sigma_radps"] ** 2)


def test_ground_truth_corners_reproject_from_T_camera_tag(office_rec: Recording) -> None:
    gt = office_rec.ground_truth
    K = np.array(gt["camera"]["K"]).reshape(3, 3)
    D = np.array(gt["camera"]["D"])
    sizes = {t["id"]: t["size_m"] for t in gt["tags"]}
    tags = {t.id: t for t in build_world(SimConfig()).tags}
    T_base_cam = np.array(gt["T_base_camera"])
    poses = {p["stamp_ns"]: p for p in gt["poses"]}
    n = 0
    for frame in gt["frames"]:
        p = poses[frame["stamp_ns"]]
        T_world_cam = planar_T(p["x"], p["y"], p["yaw"]) @ T_base_cam
        for vis in frame["visible_tags"]:
            T = np.array(vis["T_camera_tag"])
            rvec, _ = cv2.Rodrigues(T[:3, :3])
            px, _ = cv2.projectPoints(tag_corners_tag_frame(sizes[vis["id"]]), rvec, T[:3, 3], K, D)
            assert np.abs(px.reshape(-1) - np.array(vis["corners_px"])).max() < 0.01
            # T_camera_tag agrees with the world poses of the camera and the tag
            T_expected = np.linalg.inv(T_world_cam) @ tags[vis["id"]].T_world_tag
            assert np.allclose(T, T_expected, atol=1e-6)
            n += 1
    assert n > 50
    # quaternion_xyzw of the tags matches their rotation
    q = np.array(gt["tags"][0]["quat_xyzw"])
    R = tags[gt["tags"][0]["id"]].T_world_tag[:3, :3]
    x, y, z, w = q
    R_q = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    assert np.allclose(R, R_q, atol=1e-9)


def test_detector_finds_tags_where_ground_truth_says(office_rec: Recording) -> None:
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    params.cornerRefinementWinSize = 5
    params.relativeCornerRefinmentWinSize = 0.5
    detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11), params)
    world_ids = {t["id"] for t in office_rec.ground_truth["tags"]}
    images = _payloads(office_rec, ImageMsg)
    w, h = office_rec.config.image_width, office_rec.config.image_height
    sq_errors, per_tag_rms, expected, found_expected = [], [], 0, 0
    for img_msg, frame in zip(images, office_rec.ground_truth["frames"], strict=True):
        corners, ids, _ = detector.detectMarkers(decode_image(img_msg))
        found = {} if ids is None else {int(i): c.reshape(4, 2) for i, c in zip(ids.ravel(), corners, strict=True)}
        assert set(found) <= world_ids  # no invented ids
        gt = {v["id"]: np.array(v["corners_px"]).reshape(4, 2) for v in frame["visible_tags"]}
        for tag_id, c in gt.items():
            side = np.linalg.norm(np.roll(c, -1, axis=0) - c, axis=1).min()
            if side < 20:
                continue
            if tag_id in found:  # a detection of a big listed tag is where the truth says
                err = ((found[tag_id] - c) ** 2).sum(axis=1)
                per_tag_rms.append(math.sqrt(err.mean()))
                sq_errors.extend(err)
            margin = 0.3 * side  # the detector needs the quiet border inside the image
            inside = (c[:, 0] > margin).all() and (c[:, 0] < w - 1 - margin).all()
            inside = inside and (c[:, 1] > margin).all() and (c[:, 1] < h - 1 - margin).all()
            if inside:  # every big, well-inside tag is detected
                expected += 1
                found_expected += tag_id in found
    assert expected >= 40
    assert found_expected == expected
    assert math.sqrt(np.mean(sq_errors)) < 0.5
    assert max(per_tag_rms) < 1.0


def test_image_formats_decode_to_the_same_picture() -> None:
    base = SimConfig(seed=4, duration_s=0.5, image_width=160, image_height=120)
    images = {}
    for fmt in ("png", "mono8", "bgr8", "jpeg", "bayer_rggb8", "yuv422"):
        rec = simulate(SimConfig(**{**base.__dict__, "image_format": fmt}))
        msg = _payloads(rec, ImageMsg)[0]
        assert msg.encoding == fmt
        images[fmt] = decode_image(msg).astype(int)
        topic = next(m.topic for m in rec.messages if isinstance(m.payload, ImageMsg))
        assert topic == ("/camera/image_raw/compressed" if fmt in ("png", "jpeg") else "/camera/image_raw")
    assert images["png"].shape == (120, 160)
    assert np.array_equal(images["png"], images["mono8"])
    assert np.array_equal(images["png"], images["bgr8"])
    assert np.array_equal(images["png"], images["bayer_rggb8"])  # the grey scene's mosaic
    assert np.array_equal(images["png"], images["yuv422"])
    assert np.abs(images["png"] - images["jpeg"]).mean() < 3.0


def test_camera_model_inverse_distortion() -> None:
    cam = CameraModel.from_config(SimConfig())
    xd, yd = np.meshgrid(np.linspace(-0.8, 0.8, 9), np.linspace(-0.6, 0.6, 7))
    xu, yu = cam.undistort_normalized(xd, yd)
    xr, yr = cam.distort_normalized(xu, yu)
    assert np.abs(xr - xd).max() < 1e-10 and np.abs(yr - yd).max() < 1e-10
    pts = np.stack([xu.ravel(), yu.ravel(), np.ones(xu.size)], axis=1)
    px, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), cam.K, cam.D)
    expected = np.stack([xd.ravel() * cam.K[0, 0] + cam.K[0, 2], yd.ravel() * cam.K[1, 1] + cam.K[1, 2]], axis=1)
    assert np.abs(px.reshape(-1, 2) - expected).max() < 1e-8


def _read_counts(path: Path) -> tuple[dict[str, int], dict[str, object]]:
    from rosbags.highlevel import AnyReader

    counts: dict[str, int] = {}
    first: dict[str, object] = {}
    with AnyReader([path]) as reader:
        for conn, stamp, raw in reader.messages():
            counts[conn.topic] = counts.get(conn.topic, 0) + 1
            if conn.topic not in first:
                msg = reader.deserialize(raw, conn.msgtype)
                header = msg.transforms[0].header if conn.topic == TF_STATIC_TOPIC else msg.header
                assert stamp == header.stamp.sec * 10**9 + header.stamp.nanosec  # bag time = header stamp
                first[conn.topic] = msg
    return counts, first


@pytest.mark.parametrize(
    ("fmt", "name", "compression"),
    [
        ("ros1", "run.bag", None),
        ("ros1", "run.bag", "lz4"),
        ("ros1", "run.bag", "bz2"),
        ("ros2-sqlite", "run", None),
        ("ros2-mcap", "run", None),
        ("mcap", "run.mcap", None),
    ],
)
def test_writers_round_trip(small_rec: Recording, tmp_path: Path, fmt: str, name: str, compression: str | None) -> None:
    out = write_bag(small_rec, tmp_path / name, fmt, compression)  # type: ignore[arg-type]
    assert out.exists()
    gt_file = ground_truth_path(out)
    assert gt_file == tmp_path / "run.ground_truth.json"
    assert json.loads(gt_file.read_text()) == json.loads(json.dumps(small_rec.ground_truth))
    counts, first = _read_counts(out)
    assert counts == small_rec.counts()
    info = first[CAMERA_INFO_TOPIC]
    d = info.D if fmt == "ros1" else info.d
    assert info.distortion_model == "plumb_bob"
    assert np.allclose(d, small_rec.ground_truth["camera"]["D"])
    img = first["/camera/image_raw/compressed"]
    assert img.format == "jpeg"
    assert cv2.imdecode(img.data, cv2.IMREAD_GRAYSCALE).shape == (120, 160)
    tf = first[TF_STATIC_TOPIC]
    assert [t.child_frame_id for t in tf.transforms] == ["camera", "laser"]
    scan = first[SCAN_TOPIC]
    assert scan.header.frame_id == "laser" and len(scan.ranges) == 360
    with pytest.raises(FileExistsError):
        write_bag(small_rec, out, fmt, compression)  # type: ignore[arg-type]


def test_standalone_mcap_reads_with_mcap_ros2(small_rec: Recording, tmp_path: Path) -> None:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    out = write_bag(small_rec, tmp_path / "run.mcap", "mcap")
    counts: dict[str, int] = {}
    with out.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, message, ros_msg in reader.iter_decoded_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
            if channel.topic == ODOM_TOPIC:
                assert ros_msg.child_frame_id == "base_link"
                assert message.log_time == ros_msg.header.stamp.sec * 10**9 + ros_msg.header.stamp.nanosec
    assert counts == small_rec.counts()


def test_ros2_tf_static_is_transient_local(small_rec: Recording, tmp_path: Path) -> None:
    out = write_bag(small_rec, tmp_path / "run", "ros2-sqlite")
    meta = (out / "metadata.yaml").read_text()
    assert "durability: transient_local" in meta


def test_cli_writes_bag_and_refuses_to_overwrite(tmp_path: Path) -> None:
    args = ["--out", str(tmp_path), "--name", "cli", "--duration", "0.5", "--width", "160", "--height", "120"]
    assert main(args) == 0
    assert (tmp_path / "cli.bag").exists() and (tmp_path / "cli.ground_truth.json").exists()
    assert main(args) == 1
    assert main([*args, "--force"]) == 0


def test_cli_noise_options_reach_the_recording(tmp_path: Path) -> None:
    args = ["--out", str(tmp_path), "--duration", "0.5", "--width", "160", "--height", "120"]
    assert main([*args, "--name", "noisy", "--pixel-noise", "12", "--odom-noise-scale", "2"]) == 0
    noise = json.loads((tmp_path / "noisy.ground_truth.json").read_text())["noise"]
    assert noise["pixel_noise_sigma"] == 12.0
    assert noise["odom_v_sigma_mps"] == pytest.approx(2 * SimConfig.odom_v_sigma_mps)
    assert noise["odom_yaw_rate_sigma_radps"] == pytest.approx(2 * SimConfig.odom_yaw_rate_sigma_radps)
    assert main([*args, "--name", "bad", "--odom-noise-scale", "-1"]) == 1
    assert not (tmp_path / "bad.bag").exists()


def test_bad_options_are_refused(small_rec: Recording, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="image_format"):
        simulate(SimConfig(image_format="tiff"))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"\*\.bag"):
        write_bag(small_rec, tmp_path / "x.mcap", "ros1")
    with pytest.raises(ValueError, match="compression"):
        write_bag(small_rec, tmp_path / "x", "ros2-sqlite", "lz4")


SAMPLE = Path(__file__).resolve().parents[1] / "sample_data" / "office" / "office.bag"


@pytest.mark.skipif(not SAMPLE.exists(), reason="committed sample not present")
def test_committed_sample_matches_its_ground_truth() -> None:
    from rosbags.highlevel import AnyReader

    gt = json.loads(ground_truth_path(SAMPLE).read_text())
    with AnyReader([SAMPLE]) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
        image_stamps = [stamp for conn, stamp, _ in reader.messages() if conn.topic == "/camera/image_raw/compressed"]
    assert counts == {
        "/camera/image_raw/compressed": 575,
        "/camera/camera_info": 575,
        "/odom": 2300,
        "/scan": 1150,
        "/tf_static": 1,
    }
    assert image_stamps == [f["stamp_ns"] for f in gt["frames"]]
    assert gt["seed"] == 0 and len(gt["tags"]) == 76
    assert SAMPLE.stat().st_size + ground_truth_path(SAMPLE).stat().st_size < 20_000_000


def _frames(rec: Recording) -> list[np.ndarray]:
    return [decode_image(m.payload) for m in rec.messages if isinstance(m.payload, ImageMsg)]


def _look(**kw: object) -> Recording:
    """Two seconds of the office, lossless and noiseless so that the rendering options show alone."""
    return simulate(
        SimConfig(seed=4, duration_s=2.0, image_format="png", pixel_noise_sigma=0.0, **kw)  # type: ignore[arg-type]
    )


def test_exposure_contrast_and_vignetting_change_the_picture_as_stated() -> None:
    base = np.stack(_frames(_look())).astype(float)
    dark = np.stack(_frames(_look(exposure_gain=0.5))).astype(float)
    flat = np.stack(_frames(_look(contrast=0.5))).astype(float)
    vign = np.stack(_frames(_look(vignetting=0.6))).astype(float)
    assert dark.mean() == pytest.approx(0.5 * base.mean(), rel=0.01)
    assert flat.std() == pytest.approx(0.5 * base.std(), rel=0.02)
    assert flat.mean() == pytest.approx(128 + 0.5 * (base.mean() - 128), rel=0.01)
    # Vignetting: the centre keeps its light, the corners lose about 60 %.
    h, w = base.shape[1:]
    centre = (slice(None), slice(h // 2 - 10, h // 2 + 10), slice(w // 2 - 10, w // 2 + 10))
    corner = (slice(None), slice(0, 8), slice(0, 8))
    assert vign[centre].mean() == pytest.approx(base[centre].mean(), rel=0.01)
    assert vign[corner].mean() / base[corner].mean() == pytest.approx(0.4, abs=0.05)


def _edge_width(img: np.ndarray) -> float:
    """Mean width (px) of the strong horizontal edges: summed |d/dx| over the peak |d/dx| along each edge."""
    g = np.abs(np.diff(img.astype(float), axis=1))
    rows = [r for r in g if r.max() > 15]
    return float(np.mean([r[max(0, r.argmax() - 10) : r.argmax() + 11].sum() / r.max() for r in rows]))


def test_motion_blur_widens_edges_and_keeps_the_ground_truth() -> None:
    sharp, blurred = _look(), _look(motion_blur_px=6.0)
    assert sharp.ground_truth["frames"] == blurred.ground_truth["frames"]
    assert blurred.ground_truth["config"]["motion_blur_px"] == 6.0
    assert "motion_blur_px" not in sharp.ground_truth["config"]  # neutral values stay out (sample unchanged)
    w_sharp = np.median([_edge_width(f) for f in _frames(sharp)])
    w_blur = np.median([_edge_width(f) for f in _frames(blurred)])
    assert w_blur > w_sharp + 3.0
    # The blur is centred: the tags' centres found by the detector do not move (a one-sided kernel moves them by 3 px).
    det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11))
    errs = []
    for img, frame in zip(_frames(blurred), blurred.ground_truth["frames"], strict=True):
        corners, ids, _ = det.detectMarkers(img)
        gt = {v["id"]: np.array(v["corners_px"]).reshape(4, 2) for v in frame["visible_tags"]}
        for c, i in zip(corners, [] if ids is None else ids.ravel(), strict=True):
            if int(i) in gt:
                errs.append(c.reshape(4, 2).mean(axis=0) - gt[int(i)].mean(axis=0))
    assert len(errs) >= 10 and np.abs(np.mean(errs, axis=0)).max() < 0.3


def test_cli_rendering_options_reach_the_recording(tmp_path: Path) -> None:
    args = ["--out", str(tmp_path), "--duration", "1.0", "--width", "320", "--height", "240", "--name", "look"]
    extra = ["--jpeg-quality", "60", "--distortion", "-0.28", "0.07", "0", "0", "0", "--exposure", "0.4"]
    extra += ["--contrast", "0.8", "--vignetting", "0.5", "--motion-blur", "3", "--tag-size", "0.1"]
    assert main([*args, *extra]) == 0
    gt = json.loads((tmp_path / "look.ground_truth.json").read_text())
    cfg = gt["config"]
    assert (cfg["jpeg_quality"], cfg["exposure_gain"], cfg["contrast"]) == (60, 0.4, 0.8)
    assert (cfg["vignetting"], cfg["motion_blur_px"], cfg["tag_size_m"]) == (0.5, 3.0, 0.1)
    assert gt["camera"]["D"] == [-0.28, 0.07, 0.0, 0.0, 0.0]
    assert {t["size_m"] for t in gt["tags"]} == {0.1}
    # The ground truth's corners are the projection of the 0.1 m tags through the distorted camera.
    cam = CameraModel(320, 240, np.array(gt["camera"]["K"]).reshape(3, 3), np.array(gt["camera"]["D"]))
    seen = [v for f in gt["frames"] for v in f["visible_tags"]]
    assert seen
    for v in seen:
        T = np.array(v["T_camera_tag"])
        pc = tag_corners_tag_frame(0.1) @ T[:3, :3].T + T[:3, 3]
        xd, yd = cam.distort_normalized(pc[:, 0] / pc[:, 2], pc[:, 1] / pc[:, 2])
        px = np.stack([xd * cam.K[0, 0] + cam.K[0, 2], yd * cam.K[1, 1] + cam.K[1, 2]], axis=1)
        assert np.abs(px.ravel() - np.array(v["corners_px"])).max() < 0.01
    assert main([*args, "--name", "bad", "--vignetting", "1.5"]) == 1
    assert main([*args, "--name", "bad", "--jpeg-quality", "0"]) == 1


def test_cli_rig_options_reach_the_bag_and_the_world(tmp_path: Path) -> None:
    """A camera looking left from 0.9 m, behind the axle: the bag's /tf_static says so, and the tags hang at its
    height (so the camera still sees them)."""
    args = ["--out", str(tmp_path), "--duration", "1.0", "--width", "160", "--height", "120", "--name", "rig"]
    rig = ["--camera-yaw", "90", "--camera-xyz", "-0.2", "0.1", "0.9", "--laser-xyz", "0.25", "0", "0.3"]
    assert main([*args, *rig]) == 0
    gt = json.loads((tmp_path / "rig.ground_truth.json").read_text())
    _, first = _read_counts(tmp_path / "rig.bag")
    tf = {t.child_frame_id: t.transform for t in first[TF_STATIC_TOPIC].transforms}
    cam, laser = tf["camera"], tf["laser"]
    assert (cam.translation.x, cam.translation.y, cam.translation.z) == pytest.approx((-0.2, 0.1, 0.9))
    assert (laser.translation.x, laser.translation.y, laser.translation.z) == pytest.approx((0.25, 0.0, 0.3))
    q = cam.rotation
    R = np.array(gt["T_base_camera"])[:3, :3]
    assert np.allclose(R[:, 2], [0.0, 1.0, 0.0], atol=1e-9)  # the optical axis points along the base's +y (left)
    w = math.sqrt(max(0.0, 1 + R[0, 0] + R[1, 1] + R[2, 2])) / 2  # the message's quaternion is the same rotation
    assert abs(abs(q.w) - w) < 1e-6
    assert all(abs(t["position"][2] - 0.9) <= 0.06 + 1e-9 for t in gt["tags"])
    assert main([*args, "--name", "bad", "--camera-xyz", "0", "0", "3"]) == 1
    assert not (tmp_path / "bad.bag").exists()
