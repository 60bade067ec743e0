"""Benchmark of the detect back-ends: recall, corner RMS, pose NEES and speed, side by side in one run.

Plain script (not a test; wall times are never asserted):

    python tests/benchmarks/bench_detect.py                      # everything, on the committed sample
    python tests/benchmarks/bench_detect.py --skip speed --fit-seeds 1 2   # fit corner_bias_px on other seeds
    python tests/benchmarks/bench_detect.py --skip sim photos --speed-frames 40 --repeats 5
    python tests/benchmarks/bench_detect.py --skip sim photos speed --repeats 5   # pose + covariance share only
    python tests/benchmarks/bench_detect.py --worlds --skip sim photos posecov speed   # recall on generated worlds
    python tests/benchmarks/bench_detect.py --worlds --threshold-survival --skip sim photos posecov speed recall

Data: the committed sample ``sample_data/office/office.bag`` with ``office.ground_truth.json`` (tags
0.16 m), simulator runs of other seeds (``--fit-seeds``, in memory), ../shared/data/apriltag-photos (real
photos with corner ground truth), ../shared/data/apriltag-multi, and rendered 640x480 / 1280x720 frames.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import Counter
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from stages.camera import colmap_camera  # noqa: E402
from stages.detect.backends import make_detector, shortest_side_px  # noqa: E402
from stages.detect.config import DetectConfig  # noqa: E402
from stages.detect.core import DetectionRow, FrameJob, FrameProcessor, detect_image  # noqa: E402
from stages.detect.stage import _corner_sigma  # noqa: E402
from stages.ingest.artifacts import CameraModel  # noqa: E402
from tests.fixtures.tag_render import TagPlacement, look_at_tag, render_frame  # noqa: E402

SHARED = ROOT.parent / "shared" / "data"
DEFAULT = "apriltag3 dec1 adaptive1.2 edge0.6 (default)"
REFERENCE = "apriltag3 dec2 (library defaults)"
VARIANTS: dict[str, dict[str, Any]] = {
    DEFAULT: {},
    "apriltag3 dec1 adaptive1.2 (the default before the edge term)": {
        "edge_white_black_diff": 0,
        "max_white_black_diff": 50,
    },
    "apriltag3 dec1 (library defaults)": {
        "decimation": 1.0,
        "min_white_black_diff": 5,
        "adaptive_white_black_diff": 0,
    },
    "apriltag3 dec1 wb15 (the default until #16)": {
        "adaptive_white_black_diff": 0,
        "max_hamming": 1,
        "min_decision_margin": 10,
    },
    "apriltag3 dec1 adaptive1.5": {"adaptive_white_black_diff": 1.5},
    "apriltag3 dec1.5": {"decimation": 1.5},
    REFERENCE: {"decimation": 2.0, "min_white_black_diff": 5, "adaptive_white_black_diff": 0},
    "apriltag3 dec2 adaptive": {"decimation": 2.0},
    "opencv subpix": {"backend": "opencv", "opencv_corner_refinement": "subpix"},
    "opencv contour": {"backend": "opencv", "opencv_corner_refinement": "contour"},
}
SAMPLE_BAG = ROOT / "sample_data" / "office" / "office.bag"
TAG_SIZE_M = 0.16
BANDS_M = [(0, 1), (1, 2), (2, 3), (3, 5), (5, 100)]


def sample_recording(bag: Path = SAMPLE_BAG) -> tuple[list[np.ndarray], list[dict[str, Any]], CameraModel]:
    """Frames (decoded once), per-frame ground truth and the camera (from camera_info) of a committed bag."""
    import json

    from rosbags.highlevel import AnyReader

    from stages.ingest.convert import camera_from_info

    frames, camera = [], None
    with AnyReader([bag]) as reader:
        conns = [c for c in reader.connections if c.msgtype.endswith(("CompressedImage", "CameraInfo"))]
        for conn, _, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            if conn.msgtype.endswith("CompressedImage"):
                frames.append(cv2.imdecode(np.frombuffer(bytes(msg.data), np.uint8), cv2.IMREAD_GRAYSCALE))
            elif camera is None:
                camera = camera_from_info(msg, conn.topic)
    truth = json.loads(bag.with_name(bag.stem + ".ground_truth.json").read_text())["frames"]
    assert camera is not None and len(truth) == len(frames)
    return frames, truth, camera


def simulated(seed: int) -> tuple[list[np.ndarray], list[dict[str, Any]], CameraModel]:
    """Frames, per-frame ground truth and the camera of a simulated office run of another seed."""
    from sample_data.simulate import SimConfig, decode_image, image_topic, simulate

    cfg = SimConfig(seed=seed)
    rec = simulate(cfg)
    topic = image_topic(cfg)
    frames = [decode_image(m.payload) for m in rec.messages if m.topic == topic]
    return frames, rec.ground_truth["frames"], CameraModel.model_validate(rec.ground_truth["camera"])


def rms(values: list[float]) -> float:
    """Root mean square (nan when empty)."""
    return float(np.sqrt(np.mean(np.square(values)))) if values else float("nan")


# Generated recordings whose rendering differs from the sample's (``sample_data/simulate.py`` options), each
# 150 frames at 2 Hz over the first 75 s of the office path. "held-out" is never looked at while choosing settings.
WORLDS: dict[str, list[str]] = {
    "a: q75, barrel, vignetting, blur": [
        *("--seed", "11", "--jpeg-quality", "75", "--distortion", "-0.28", "0.07", "0", "0", "0"),
        *("--vignetting", "0.6", "--motion-blur", "3"),
    ],
    "b: dark, low contrast, noise 4": [
        *("--seed", "12", "--exposure", "0.35", "--contrast", "0.7", "--pixel-noise", "4"),
    ],
    "c: 1280x960, 0.08 m tags, q80": [
        *("--seed", "13", "--width", "1280", "--height", "960", "--tag-size", "0.08", "--jpeg-quality", "80"),
    ],
    "e: faint (exposure 0.25, contrast 0.5, vignetting 0.5, noise 3)": [
        *("--seed", "15", "--exposure", "0.25", "--contrast", "0.5", "--vignetting", "0.5", "--pixel-noise", "3"),
    ],
    "f: very faint, noisy (exposure 0.2, contrast 0.5, noise 5, q70)": [
        *("--seed", "21", "--exposure", "0.2", "--contrast", "0.5", "--pixel-noise", "5", "--vignetting", "0.4"),
        *("--jpeg-quality", "70"),
    ],
    "d (held-out): 800x600 q60, dim, vignetting, blur": [
        *("--seed", "14", "--width", "800", "--height", "600", "--jpeg-quality", "60", "--exposure", "0.6"),
        *("--vignetting", "0.5", "--motion-blur", "2", "--distortion", "-0.15", "0.03", "0.001", "0", "0"),
        *("--pixel-noise", "2.5"),
    ],
}
WORLD_FRAMES_ARGS = ["--camera-rate", "2", "--duration", "75"]


def generated_worlds(folder: Path) -> dict[str, tuple[list[np.ndarray], list[dict[str, Any]], CameraModel]]:
    """The recordings of :data:`WORLDS`, written by ``sample_data/simulate.py`` into ``folder`` (kept there and
    reused when present), read back like the sample (frames, ground truth, camera from camera_info)."""
    import subprocess

    out = {}
    for name, args in WORLDS.items():
        stem = "world_" + name.split(" ")[0].rstrip(":")
        bag = folder / f"{stem}.bag"
        if not bag.exists():
            cmd = [sys.executable, "-m", "sample_data.simulate", "--out", str(folder), "--name", stem]
            subprocess.run([*cmd, *WORLD_FRAMES_ARGS, *args], check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
        out[name] = sample_recording(bag)
    return out


def library_recall(frames: list[np.ndarray], truth: list[dict[str, Any]], decimation: float = 1.0) -> dict[str, Any]:
    """Recall of the AprilTag 3 library itself (pupil-apriltags, its defaults but ``quad_decimate``, no focusmap
    filter), by id over tags fully in view with shortest side >= 15 px."""
    import pupil_apriltags

    det = pupil_apriltags.Detector(families="tag36h11", quad_decimate=decimation)
    n = hits = false = 0
    for img, gt in zip(frames, truth, strict=True):
        ids = {t["id"]: t for t in gt["visible_tags"]}
        found = {int(d.tag_id) for d in det.detect(np.ascontiguousarray(img))}
        false += len(found - set(ids))
        for tid, t in ids.items():
            if shortest_side_px(np.reshape(t["corners_px"], (4, 2))) >= 15:
                n += 1
                hits += tid in found
    det.tag_detector_ptr = None  # pupil-apriltags 1.0.4 corrupts the heap when it frees a detector
    return {"hits": hits, "n": n, "false": false}


def photo_recall(kw: dict[str, Any] | None) -> tuple[int, int, int]:
    """Tags found on the real photos (their 22 truth tags, matched by centre within 3 px) and on apriltag-multi
    (the ids the AprilTag 3 library finds there at decimation 1), and the detections that match none of those
    (extra); ``kw`` None = the library at decimation 1."""
    import pupil_apriltags

    lib = pupil_apriltags.Detector(families="tag36h11", quad_decimate=1.0)

    def library(img: np.ndarray) -> list[tuple[int, np.ndarray]]:
        return [(int(d.tag_id), np.asarray(d.corners)[[1, 0, 3, 2]] - 0.5) for d in lib.detect(img)]

    def ours(img: np.ndarray) -> list[tuple[int, np.ndarray]]:
        assert det is not None
        cfg = DetectConfig(**(kw or {}))
        return [(r.tag_id, np.reshape(r.corners, (4, 2))) for r in detect_image(img, det, camera, cfg)]

    det = None if kw is None else make_detector(DetectConfig(**kw))
    hits = n = extra = 0
    for path in sorted((SHARED / "apriltag-photos").glob("*.jpg")) + sorted((SHARED / "apriltag-multi").glob("*.png")):
        img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        h, w = img.shape
        camera = colmap_camera(
            CameraModel(width=w, height=h, K=[w, 0, w / 2, 0, w, h / 2, 0, 0, 1], distortion_model="none", D=[])
        )
        found = library(img) if det is None else ours(img)
        if path.suffix == ".jpg":
            truth = []
            for line in path.with_suffix(".txt").read_text().splitlines():
                nums = [float(v) for v in line.replace("(", " ").replace(")", " ").replace(",", " ").split()[1:]]
                truth.append(np.array(nums).reshape(4, 2)[[1, 0, 3, 2]] - 0.5)
            n += len(truth)
            near = [[np.linalg.norm(c.mean(0) - t.mean(0)) < 3 for _, c in found] for t in truth]
            hits += sum(any(m) for m in near)
            extra += sum(not any(m[k] for m in near) for k in range(len(found)))
        else:
            want = {i for i, _ in library(img)}
            got = {i for i, _ in found}
            n += len(want)
            hits += len(want & got)
            extra += len(got - want)
    lib.tag_detector_ptr = None
    return hits, n, extra


def bench_worlds(
    worlds: dict[str, tuple[list[np.ndarray], list[dict[str, Any]], CameraModel]], variants: dict[str, dict[str, Any]]
) -> None:
    """Recall of focusmap's settings (the stage's whole path: detection, filters, pose) and of the AprilTag 3
    library at decimation 1 with its defaults, on every generated world, the sample and the real photos."""
    print(
        "\n## Recall on generated worlds (tags fully in view, shortest side >= 15 px, matched by id; photos: "
        "22 truth tags by centre + the ids the library finds on apriltag-multi)"
    )
    print("| detector | " + " | ".join(worlds) + " | photos |")
    print("| --- |" + " --- |" * (len(worlds) + 1))

    def cell(st: dict[str, Any]) -> str:
        return f"{st['hits']}/{st['n']} = {st['hits'] / max(st['n'], 1):.3f}" + (
            f" ({st['false']} false)" if st["false"] else ""
        )

    cells = [cell(library_recall(f, t)) for f, t, _ in worlds.values()]
    h, n, x = photo_recall(None)
    print(
        "| AprilTag 3 library, dec 1, its defaults | "
        + " | ".join(cells)
        + f" | {h}/{n} = {h / n:.3f}"
        + (f" ({x} extra)" if x else "")
        + " |"
    )
    for name, kw in variants.items():
        if kw.get("backend") == "opencv":
            continue
        cells = []
        for f, t, cam in worlds.values():
            cells.append(cell(run_variant(DetectConfig(tag_size_m=TAG_SIZE_M, **kw), f, t, cam)[2]))
        h, n, x = photo_recall(kw)
        print(f"| {name} | " + " | ".join(cells) + f" | {h}/{n} = {h / n:.3f}" + (f" ({x} extra)" if x else "") + " |")


SURVIVAL_THRESHOLDS = (15, 20, 25, 30, 35, 40, 50, 60, 70, 80, 90, 100, 120, 150)


def bench_threshold_survival(sets: dict[str, list[np.ndarray]]) -> None:
    """What justifies the edge term of the per-frame threshold (``edge_white_black_diff``): for every tag the
    AprilTag 3 library finds at decimation 1 (its defaults), the largest ``min_white_black_diff`` of
    :data:`SURVIVAL_THRESHOLDS` at which it still finds it (matched by id and centre within 3 px), against the
    frame's 95th percentile of tile contrast; and the thresholds the default's rule gives, with and without it."""
    import pupil_apriltags

    from stages.detect.backends import (
        EDGE_QUANTILE,
        _quad_thresh_params,
        frame_white_black_diff,
        tile_contrast_quantiles,
    )

    cfg = DetectConfig()
    lib = pupil_apriltags.Detector(families="tag36h11", quad_decimate=1.0)
    det = pupil_apriltags.Detector(families="tag36h11", quad_decimate=1.0)
    qtp = _quad_thresh_params(det)
    print(
        f"\n## Threshold survival: the largest min_white_black_diff at which the library (dec 1) still finds each of "
        f"its tags, over the frame's {EDGE_QUANTILE:.0%} tile-contrast percentile q"
    )
    print(
        "| set | frames | tags | lowest (survival / q) over frames | threshold without -> with the edge term | raised |"
    )
    print("| --- | --- | --- | --- | --- | --- |")
    for name, frames in sets.items():
        ratios, old, new, tags = [], [], [], 0
        for img in frames:
            img = np.ascontiguousarray(img)
            q = tile_contrast_quantiles(img, (EDGE_QUANTILE,))[0]
            wb = (cfg.min_white_black_diff, cfg.adaptive_white_black_diff)
            old.append(frame_white_black_diff(img, *wb, 0.0, EDGE_QUANTILE, 50))
            new.append(
                frame_white_black_diff(img, *wb, cfg.edge_white_black_diff, EDGE_QUANTILE, cfg.max_white_black_diff)
            )
            alive = {(int(d.tag_id), float(d.center[0]), float(d.center[1])) for d in lib.detect(img)}
            tags += len(alive)
            survived = dict.fromkeys(alive, 0)
            for threshold in SURVIVAL_THRESHOLDS:
                if not alive:
                    break
                qtp.min_white_black_diff = threshold
                got = [(int(d.tag_id), d.center) for d in det.detect(img)]
                for tag in list(alive):
                    if any(i == tag[0] and np.hypot(tag[1] - c[0], tag[2] - c[1]) < 3 for i, c in got):
                        survived[tag] = threshold
                    else:
                        alive.discard(tag)
            if survived:
                ratios.append(min(survived.values()) / max(q, 1))
        print(
            f"| {name} | {len(frames)} | {tags} | {min(ratios):.2f} | {min(old)}-{max(old)} (median "
            f"{np.median(old):.0f}) -> {min(new)}-{max(new)} (median {np.median(new):.0f}) | "
            f"{np.mean(np.array(new) > np.array(old)):.0%} |"
        )
    lib.tag_detector_ptr = det.tag_detector_ptr = None  # pupil-apriltags 1.0.4 corrupts the heap when it frees one


def run_variant(
    cfg: DetectConfig, frames: list[np.ndarray], truth: list[dict[str, Any]], camera: CameraModel
) -> tuple[list[tuple[DetectionRow, dict[str, Any]]], list[DetectionRow], dict[str, Any]]:
    """Rows matched to ground truth, all rows, and recall / corner RMS / false ids of one detector setting."""
    from stages.detect.core import detect_image

    proc = FrameProcessor(cfg, camera)
    assert proc.detector is not None
    rows: list[DetectionRow] = []
    matched = []
    n_truth = hits = false = 0
    sq: list[float] = []
    for i, (img, gt) in enumerate(zip(frames, truth, strict=True)):
        found = detect_image(img, proc.detector, proc.camera, cfg, FrameJob(i, 0, "cam"))
        rows += found
        ids = {t["id"]: t for t in gt["visible_tags"]}
        by_id = {r.tag_id: r for r in found}
        false += sum(1 for r in found if r.tag_id not in ids)
        for tid, t in ids.items():
            c = np.reshape(t["corners_px"], (4, 2))
            if shortest_side_px(c) < 15:
                continue
            n_truth += 1
            if tid in by_id:
                hits += 1
                d = np.reshape(by_id[tid].corners, (4, 2)) - c
                sq += list(np.sum(d**2, axis=1))
        matched += [(r, ids[r.tag_id]) for r in found if r.tag_id in ids]
    stats = {
        "hits": hits,
        "n": n_truth,
        "corner_rms": float(np.sqrt(np.mean(sq))) if sq else float("nan"),
        "false": false,
    }
    return matched, rows, stats


def nees_per_band(
    matched: list[tuple[DetectionRow, dict[str, Any]]], rows: list[DetectionRow], cfg: DetectConfig
) -> tuple[list[str], float, float]:
    """NEES/6 of the reported pose covariance against ground truth, per distance band and overall."""
    import gtsam

    from stages.detect.stage import row_pose_cov

    sigma = _corner_sigma(rows, cfg)[0][0]
    nees, dist = [], []
    for r, t in matched:
        cov, _ = row_pose_cov(r, sigma, cfg)
        xi = gtsam.Pose3(r.pose.T_camera_tag).localCoordinates(gtsam.Pose3(np.array(t["T_camera_tag"])))
        nees.append(float(xi @ np.linalg.solve(cov, xi)) / 6)
        dist.append(float(np.linalg.norm(np.array(t["T_camera_tag"])[:3, 3])))
    nees_a, dist_a = np.array(nees), np.array(dist)
    cells = []
    for lo, hi in BANDS_M:
        m = (dist_a >= lo) & (dist_a < hi)
        cells.append(f"{nees_a[m].mean():.2f} (n={m.sum()})" if m.any() else "-")
    return cells, float(nees_a.mean()), sigma


def radial_bias(matched: list[tuple[DetectionRow, dict[str, Any]]], rows: list[DetectionRow]) -> tuple[float, ...]:
    """Moment fit of ``corner_bias_px``: mean outward corner error per tag vs the white-noise prediction.

    The common outward displacement of a tag's four corners (along their diagonals) has variance
    ``sigma^2 / 4`` under white corner noise; what it has beyond that is ``beta^2``.
    """
    from stages.detect.pose import scale_mode

    sigma2 = sum(r.pose.sse_px2 for r in rows) / (2 * len(rows))
    rb = []
    for r, t in matched:
        g = np.reshape(t["corners_px"], (4, 2))
        e = np.reshape(r.corners, (4, 2)) - g
        rb.append(float(np.sum(e * scale_mode(g).reshape(4, 2), axis=1).mean()))
    mean_sq = float(np.mean(np.square(rb)))
    return float(np.mean(rb)), mean_sq, sigma2 / 4, float(np.sqrt(max(0.0, mean_sq - sigma2 / 4)))


def bench_sim(frames: list[np.ndarray], truth: list[dict[str, Any]], camera: CameraModel, label: str) -> None:
    """Recall, corner RMS and false ids per detector setting; NEES per distance band of the default."""
    print(f"\n## {label}: {len(frames)} frames (recall over tags fully in view, shortest side >= 15 px)")
    print("| detector | recall | corner RMS px | ids not listed as fully visible |")
    print("| --- | --- | --- | --- |")
    default_run = None
    for name, kw in VARIANTS.items():
        cfg = DetectConfig(tag_size_m=TAG_SIZE_M, **kw)
        matched, rows, st = run_variant(cfg, frames, truth, camera)
        if name == DEFAULT:
            default_run = (matched, rows)
        print(
            f"| {name} | {st['hits']}/{st['n']} = {st['hits'] / max(st['n'], 1):.3f} | {st['corner_rms']:.3f} "
            f"| {st['false']} |"
        )
    assert default_run is not None
    matched, rows = default_run
    print(f"\nNEES/6 of the tag pose against ground truth per distance band ({DEFAULT}, tag_size_m={TAG_SIZE_M}):")
    print("| covariance | " + " | ".join(f"{lo}-{hi} m" for lo, hi in BANDS_M) + " | all | corner sigma px |")
    print("| --- |" + " --- |" * (len(BANDS_M) + 2))
    for title, kw in (
        ("default (IPPE two-mode mixture)", {}),
        ("local only (ambiguity_mixture: false)", {"ambiguity_mixture": False}),
        ("mixture + corner_bias_px 0.05", {"corner_bias_px": 0.05}),
    ):
        cfg = DetectConfig(tag_size_m=TAG_SIZE_M, **kw)
        cells, overall, sigma = nees_per_band(matched, rows, cfg)
        print(f"| {title} | " + " | ".join(cells) + f" | {overall:.2f} | {sigma:.3f} |")
    mean_r, mean_sq, white, beta = radial_bias(matched, rows)
    print(
        f"\nCommon outward corner error per tag: mean {mean_r:+.4f} px, mean square {mean_sq:.5f} px^2, "
        f"white-noise prediction sigma^2/4 = {white:.5f} px^2 -> corner_bias_px fit = {beta:.3f}"
    )


def bench_photos() -> None:
    """Recall and corner RMS on the real photos and apriltag-multi."""
    folder = SHARED / "apriltag-photos"
    if not folder.is_dir():
        print(f"\n(skipped photos: {folder} absent)")
        return
    print("\n## Real photos (apriltag-photos; truth = the AprilTag library's file, converted to our convention)")
    print("| detector | " + " | ".join(p.stem for p in sorted(folder.glob("*.jpg"))) + " | apriltag-multi tags (ids) |")
    print("| --- | --- | --- | --- |")
    multi = sorted((SHARED / "apriltag-multi").glob("*.png"))
    for name, kw in VARIANTS.items():
        det = make_detector(DetectConfig(**kw))
        cells = []
        for jpg in sorted(folder.glob("*.jpg")):
            truth = []
            for line in jpg.with_suffix(".txt").read_text().splitlines():
                nums = [float(v) for v in line.replace("(", " ").replace(")", " ").replace(",", " ").split()[1:]]
                truth.append(np.array(nums).reshape(4, 2)[[1, 0, 3, 2]] - 0.5)
            found = det.detect(cv2.imread(str(jpg), cv2.IMREAD_GRAYSCALE))
            errs = []
            for t in truth:
                near = [o for o in found if np.linalg.norm(o.corners.mean(0) - t.mean(0)) < 3]
                if near:
                    errs.append(float(np.sqrt(np.mean(np.sum((near[0].corners - t) ** 2, axis=1)))))
            cells.append(f"{len(errs)}/{len(truth)}, RMS {rms(errs):.3f} px, extra {len(found) - len(errs)}")
        n_multi = []
        for png in multi:
            found = det.detect(cv2.imread(str(png), cv2.IMREAD_GRAYSCALE))
            n_multi.append(f"{len(found)} ({','.join(str(o.tag_id) for o in sorted(found, key=lambda o: o.tag_id))})")
        print(f"| {name} | " + " | ".join(cells) + " | " + "; ".join(n_multi) + " |")


_WORKER: dict[str, Any] = {}


def _init_speed(sets: dict[str, tuple[list[np.ndarray], CameraModel]], pose_batch: int = 1) -> None:
    """Worker initializer: the frames (decoded once, sent once), a processor per (setting, set), and how many
    frames' poses are solved together (:func:`_work`)."""
    _WORKER["sets"] = sets
    _WORKER["procs"] = {}
    _WORKER["pose_batch"] = pose_batch


def _processor(variant: str, set_name: str) -> FrameProcessor:
    key = (variant, set_name)
    if key not in _WORKER["procs"]:
        _WORKER["procs"][key] = FrameProcessor(DetectConfig(**VARIANTS[variant]), _WORKER["sets"][set_name][1])
    return _WORKER["procs"][key]


def _work(task: tuple[str, str, int, int, bool]) -> int:
    """Detect (and with ``pose``, estimate every pose) in frames ``lo:hi`` of a set; returns the tag count.

    With ``pose`` and ``_WORKER["pose_batch"]`` above 1 the frames' tags are kept and their poses solved together, as
    the detect stage does with a batch of ``detect.batch_frames`` frames (:meth:`FrameProcessor.process`); with 1,
    one frame at a time (``detect_image``, what this benchmark measured before session thirteen)."""
    from collections import Counter

    from stages.detect.core import FrameJob, detect_image, kept_observations, rows_with_poses

    variant, set_name, lo, hi, pose = task
    proc = _processor(variant, set_name)
    assert proc.detector is not None
    frames = _WORKER["sets"][set_name][0][lo:hi]
    if not pose:
        return sum(len(proc.detector.detect(f)) for f in frames)
    if _WORKER.get("pose_batch", 1) <= 1:
        return sum(len(detect_image(f, proc.detector, proc.camera, proc.cfg)) for f in frames)
    dropped: Counter[str] = Counter()
    items = [
        (
            FrameJob(frame=i, stamp_ns=0, camera=""),
            proc.camera,
            kept_observations(proc.detector.detect(f), proc.cfg, dropped, True),
        )
        for i, f in enumerate(frames)
    ]
    return len(rows_with_poses(items, proc.cfg, dropped))


def _tasks(variant: str, set_name: str, n: int, pose: bool) -> list[tuple[str, str, int, int, bool]]:
    """The set's frames in tasks of ``pose_batch`` frames (4 when poses are solved per frame)."""
    batch = _WORKER["pose_batch"] if _WORKER.get("pose_batch", 1) > 1 else 4
    return [(variant, set_name, i, min(i + batch, n), pose) for i in range(0, n, batch)]


_CPU: dict[tuple[str, str, bool], list[float]] = {}


def _fps(pool: ProcessPoolExecutor | None, variant: str, set_name: str, n: int, pose: bool) -> float:
    """Frames per second (wall); in this process also records the CPU time per frame in ``_CPU``."""
    tasks = _tasks(variant, set_name, n, pose)
    t0, c0 = time.perf_counter(), time.process_time()
    if pool is None:
        for t in tasks:
            _work(t)
        _CPU.setdefault((variant, set_name, pose), []).append((time.process_time() - c0) / n)
    else:
        list(pool.map(_work, tasks))
    return n / (time.perf_counter() - t0)


def synthetic_frames(width: int, height: int, n: int) -> tuple[list[np.ndarray], CameraModel]:
    """``n`` rendered frames of 4 tags at 0.8-3 m, size ``width`` x ``height`` (flat background, noise 2)."""
    f = 0.65 * width
    camera = CameraModel(
        width=width,
        height=height,
        K=[f, 0, width / 2, 0, f, height / 2, 0, 0, 1],
        distortion_model="plumb_bob",
        D=[-0.06, 0.012, 0.0006, -0.0004, 0.0],
    )
    cam = colmap_camera(camera)
    rng = np.random.default_rng(0)
    frames = []
    for _ in range(n):
        tags = [
            TagPlacement(
                int(rng.integers(0, 500)),
                "tag36h11",
                0.16,
                look_at_tag(
                    rng.uniform(0.8, 3.0),
                    rng.uniform(-40, 40),
                    rng.uniform(-20, 20),
                    0,
                    ((k % 2 - 0.5) * 0.6, (k // 2 - 0.5) * 0.4),
                ),
            )
            for k in range(4)
        ]
        frames.append(render_frame(cam, tags, noise_sigma=2.0, rng=rng))
    return frames, camera


def photo_frames(n: int) -> tuple[list[np.ndarray], CameraModel] | None:
    """The real photos and apriltag-multi images (cycled to ``n`` frames; a nominal camera for the pose)."""
    paths = sorted((SHARED / "apriltag-photos").glob("*.jpg")) + sorted((SHARED / "apriltag-multi").glob("*.png"))
    imgs = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in paths]
    if not imgs:
        return None
    # Different sizes: crop every image to the smallest one so that one camera fits all.
    h = min(i.shape[0] for i in imgs)
    w = min(i.shape[1] for i in imgs)
    imgs = [np.ascontiguousarray(i[:h, :w]) for i in imgs]
    camera = CameraModel(width=w, height=h, K=[w, 0, w / 2, 0, w, h / 2, 0, 0, 1], distortion_model="none", D=[])
    return [imgs[k % len(imgs)] for k in range(n)], camera


def bench_speed(
    sim_frames: list[np.ndarray],
    sim_camera: CameraModel,
    n: int,
    repeats: int,
    extra: dict[str, tuple[list[np.ndarray], CameraModel]] | None = None,
    pose_batch: int = 1,
) -> None:
    """Frames per second, one process and two, per setting and frame set, interleaved; ratios to the reference.

    ``pose_batch``: frames whose poses are solved together, in tasks of that many frames (the detect stage's
    ``detect.batch_frames``, 16 by default; ``n`` a multiple of twice it keeps the two workers' shares equal), or 1:
    one frame at a time, in tasks of 4 frames.

    Frames are decoded once and sent to the workers once (the initializer); pool start-up and the first
    detector construction are excluded (one warm-up pass). Each (setting, set, processes) cell is measured
    ``repeats`` times, the cells interleaved round-robin, and the median is reported.
    """
    import os

    step = max(1, len(sim_frames) // n)
    sets: dict[str, tuple[list[np.ndarray], CameraModel]] = {
        f"sample {sim_frames[0].shape[1]}x{sim_frames[0].shape[0]}": (sim_frames[::step][:n], sim_camera),
        "640x480": synthetic_frames(640, 480, n),
        "1280x720": synthetic_frames(1280, 720, n),
    }
    for name, (frames, cam) in (extra or {}).items():  # the generated worlds (--worlds), spread over each
        sets[f"world {name}"] = (frames[:: max(1, len(frames) // n)][:n], cam)
    photos = photo_frames(n)
    if photos is not None:
        sets[f"photos {photos[0][0].shape[1]}x{photos[0][0].shape[0]}"] = photos
    load_before = os.getloadavg()
    _init_speed(sets, pose_batch)
    results: dict[tuple[str, str, int, bool], list[float]] = {}
    t_start = time.perf_counter()
    with ProcessPoolExecutor(2, initializer=_init_speed, initargs=(sets, pose_batch)) as pool:
        for variant in VARIANTS:  # warm-up: build every detector in both workers and here
            for set_name in sets:
                list(pool.map(_work, [(variant, set_name, 0, 1, True)] * 4))
                _work((variant, set_name, 0, 1, True))
        for _ in range(repeats):
            for set_name, (frames, _) in sets.items():
                for variant in VARIANTS:
                    for workers, pose in ((1, True), (2, True), (1, False)):
                        fps = _fps(pool if workers == 2 else None, variant, set_name, len(frames), pose)
                        results.setdefault((variant, set_name, workers, pose), []).append(fps)
    load_after = os.getloadavg()
    print(
        f"\n## Speed: frames per second (median of {repeats} interleaved repeats, {n} frames per set, poses solved "
        f"{'one frame at a time' if pose_batch <= 1 else f'{pose_batch} frames at a time'}), "
        f"ratio to {REFERENCE} in one process"
    )
    print(
        f"Load average (1, 5, 15 min) before {', '.join(f'{v:.2f}' for v in load_before)}, after "
        f"{', '.join(f'{v:.2f}' for v in load_after)} on {os.cpu_count()} cores; {time.perf_counter() - t_start:.0f} s."
    )
    for pose in (True, False):
        what = "detection + pose" if pose else "detection only, one process"
        cols = [(s, w) for s in sets for w in ((1, 2) if pose else (1,))]
        print(f"\n{what}:")
        print("| detector | " + " | ".join(f"{s} x{w}" for s, w in cols) + " |")
        print("| --- |" + " --- |" * len(cols))
        for variant in VARIANTS:
            cells = []
            for s, w in cols:
                med = float(np.median(results[(variant, s, w, pose)]))
                ref = float(np.median(results[(REFERENCE, s, 1, pose)]))
                cells.append(f"{med:.1f} ({med / ref:.2f}x)")
            print(f"| {variant} | " + " | ".join(cells) + " |")
    print(
        "\nCPU time per frame, one process, detection + pose (ms; ratio = the reference's CPU time / this; less "
        "sensitive to other jobs than the wall times above; two processes on two free cores give about twice it):"
    )
    print("| detector | " + " | ".join(sets) + " |")
    print("| --- |" + " --- |" * len(sets))
    for variant in VARIANTS:
        cells = []
        for s in sets:
            med = float(np.median(_CPU[(variant, s, True)]))
            ref = float(np.median(_CPU[(REFERENCE, s, True)]))
            cells.append(f"{1e3 * med:.2f} ({ref / med:.2f}x)")
        print(f"| {variant} | " + " | ".join(cells) + " |")
    spread = {
        s: max(float(np.ptp(v) / np.median(v)) for (var, s2, w, p), v in results.items() if s2 == s and var == DEFAULT)
        for s in sets
    }
    print(
        "\nLargest (max - min) / median over the repeats of the default's cells: "
        + ", ".join(f"{s} {v:.0%}" for s, v in spread.items())
    )


def bench_posecov(frames: list[np.ndarray], camera: CameraModel, n: int, repeats: int, batches: Sequence[int]) -> None:
    """Share of pose + covariance in the detect stage, one process: detection alone, detection + the former pose path
    (pycolmap per IPPE solution, :mod:`tests.oracles.tag_pose_colmap`), and detection + the batched solver per
    frame and per chunk of ``batch`` frames (the stage's ``batch_frames``), on the same frames, interleaved."""
    import os

    import stages.detect.core as core
    from tests.oracles.tag_pose_colmap import estimate_tag_pose_colmap

    def colmap_poses(corners: list[Any], sizes: list[float], cam: Any) -> list[Any]:
        return [estimate_tag_pose_colmap(c, s, cam) for c, s in zip(corners, sizes, strict=True)]

    step = max(1, len(frames) // n)
    frames = frames[::step][:n]
    cfg = DetectConfig(tag_size_m=TAG_SIZE_M)
    proc = FrameProcessor(cfg, camera)
    det = proc.detector
    assert det is not None

    def run(mode: str) -> int:
        if mode == "detection alone":
            return sum(len(det.detect(f)) for f in frames)
        chunk = int(mode.split(" in ")[1].split("-")[0]) if mode.endswith("chunks") else 1
        dropped: Any = Counter()
        rows = 0
        for lo in range(0, len(frames), chunk):
            items = [
                (FrameJob(lo + k, 0, "cam"), proc.camera, core.kept_observations(det.detect(f), cfg, dropped, True))
                for k, f in enumerate(frames[lo : lo + chunk])
            ]
            rows += len(core.rows_with_poses(items, cfg, dropped))
        return rows

    modes = [
        "detection alone",
        "+ pose, former (pycolmap)",
        "+ pose, batched per frame",
        *[f"+ pose, batched in {b}-frame chunks" for b in batches],
    ]
    times: dict[str, list[float]] = {m: [] for m in modes}
    cpu: dict[str, list[float]] = {m: [] for m in modes}
    batched = core.estimate_tag_poses
    load_before = os.getloadavg()
    for r in range(repeats + 1):  # the first round warms up
        for m in modes:
            core.estimate_tag_poses = colmap_poses if "former" in m else batched  # type: ignore[assignment]
            try:
                t0, c0 = time.perf_counter(), time.process_time()
                count = run(m)
                dt, dc = time.perf_counter() - t0, time.process_time() - c0
            finally:
                core.estimate_tag_poses = batched  # type: ignore[assignment]
            if r:
                times[m].append(dt)
                cpu[m].append(dc)
        if r == 0:
            tags = count
    load_after = os.getloadavg()
    print(
        f"\n## Pose + covariance share of detect: {len(frames)} sample frames ({tags} tags kept), one process, "
        f"median of {repeats} interleaved repeats"
    )
    print(f"Load average before {load_before[0]:.2f}, after {load_after[0]:.2f} on {os.cpu_count()} cores.")
    print("| path | fps | ms per frame | pose + covariance ms per frame | share of the stage | pose time vs former |")
    print("| --- | --- | --- | --- | --- | --- |")
    med = {m: float(np.median(v)) for m, v in times.items()}
    base = med[modes[0]]
    former = med[modes[1]] - base
    for m in modes:
        pose = med[m] - base
        cells = [f"{len(frames) / med[m]:.1f}", f"{1e3 * med[m] / len(frames):.2f}"]
        if m == modes[0]:
            cells += ["-", "-", "-"]
        else:
            cells += [f"{1e3 * pose / len(frames):.2f}", f"{pose / med[m]:.0%}", f"{pose / former:.2f}x"]
        print(f"| {m} | " + " | ".join(cells) + " |")
    # the share from CPU time, paired by round (each round runs every path once, back to back): another job on the
    # machine moves the wall-time medians apart by several points; the paired CPU shares move far less
    alone = np.asarray(cpu[modes[0]])
    print("\nShare of the stage from CPU time, per round (median, and the rounds' range):")
    print("| path | share, median | range |")
    print("| --- | --- | --- |")
    for m in modes[1:]:
        share = 1.0 - alone / np.asarray(cpu[m])
        print(f"| {m} | {float(np.median(share)):.0%} | {float(share.min()):.0%}–{float(share.max()):.0%} |")


def _exact_tag_image(tag_id: int, H: np.ndarray, width: int = 320, height: int = 240, ss: int = 8) -> np.ndarray:
    """Grey image of a tag36h11 marker (one white cell of quiet border) through the homography ``H`` (bitmap
    cells 0..10 -> pixels, pixel centres at integers), by exact point sampling at ``ss`` x ``ss`` per pixel and
    area averaging: no bitmap resampling, no bilinear warp (unlike the simulator)."""
    dic = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    m = cv2.copyMakeBorder(
        cv2.aruco.generateImageMarker(dic, tag_id, 8, borderBits=1), 1, 1, 1, 1, cv2.BORDER_CONSTANT, value=255
    )
    off = (np.arange(ss) + 0.5) / ss - 0.5
    u2, v2 = np.meshgrid(np.arange(width * ss), np.arange(height * ss))
    U, V = u2 // ss + off[u2 % ss], v2 // ss + off[v2 % ss]
    Hi = np.linalg.inv(H)
    Z = Hi[2, 0] * U + Hi[2, 1] * V + Hi[2, 2]
    x = (Hi[0, 0] * U + Hi[0, 1] * V + Hi[0, 2]) / Z
    y = (Hi[1, 0] * U + Hi[1, 1] * V + Hi[1, 2]) / Z
    inside = (x >= 0) & (x < 10) & (y >= 0) & (y < 10)
    val = np.full(x.shape, 200.0)
    xi, yi = np.clip(np.floor(x).astype(int), 0, 9), np.clip(np.floor(y).astype(int), 0, 9)
    val[inside] = np.where(m[yi[inside], xi[inside]] > 0, 200.0, 40.0)
    return val.reshape(height, ss, width, ss).mean(axis=(1, 3))


def bench_corner_scale(per_size: int = 12, seed: int = 1) -> None:
    """Is the outward corner offset (a scale error of the quad) the detector's or the simulator's?

    Tags drawn exactly (no bitmap warp), random in-plane angle, sub-pixel position and a small projective
    tilt, with and without a Gaussian blur, pixel noise 1.5; the default detector's corners against the exact
    corners: mean displacement outwards along the diagonals, px and % of the half-diagonal, by side length.
    """
    det = make_detector(DetectConfig())
    rng = np.random.default_rng(seed)
    sides = [16, 20, 25, 32, 40, 55, 70, 90]
    res = []
    for side in sides:
        for k in range(per_size):
            ang = rng.uniform(0, 2 * np.pi)
            c = np.array([160.0, 120.0]) + rng.uniform(-3, 3, 2)
            tilt = rng.uniform(-0.15, 0.15, 2)
            s = side / 8.0
            A = np.array([[s * np.cos(ang), -s * np.sin(ang), 0], [s * np.sin(ang), s * np.cos(ang), 0], [0, 0, 1]])
            H = (
                np.array([[1, 0, c[0]], [0, 1, c[1]], [0, 0, 1]])
                @ A
                @ np.array([[1, 0, -5], [0, 1, -5], [tilt[0] / side / 2, tilt[1] / side / 2, 1]])
            )
            img = _exact_tag_image(1 + k, H)
            P = np.array([[1, 1, 1], [9, 1, 1], [9, 9, 1], [1, 9, 1]], float) @ H.T
            P = P[:, :2] / P[:, 2:]
            for blur in (0.0, 0.7):
                im = cv2.GaussianBlur(img, (0, 0), blur) if blur else img
                im = np.clip(np.rint(im + rng.normal(0, 1.5, im.shape)), 0, 255).astype(np.uint8)
                obs = det.detect(im)
                if not obs:
                    continue
                cd = np.asarray(obs[0].corners, float).reshape(4, 2)
                Pt = P[[int(np.argmin(np.linalg.norm(P - q, axis=1))) for q in cd]]
                rad = Pt - Pt.mean(0)
                r = np.linalg.norm(rad, axis=1)
                out = float(((cd - Pt) * rad / r[:, None]).sum(1).mean())
                res.append((side, blur, out, out / r.mean()))
    R = np.array(res)
    print("\nCorner scale on exactly drawn tags (default detector; outward along the diagonals):")
    print("| side (px) | no blur: px | % of half-diagonal | blur 0.7 px: px | % of half-diagonal |")
    print("| --- | --- | --- | --- | --- |")
    for side in sides:
        cells = []
        for blur in (0.0, 0.7):
            m = (R[:, 0] == side) & (R[:, 1] == blur)
            cells += [f"{R[m, 2].mean():+.4f}", f"{100 * R[m, 3].mean():+.3f}"]
        print(f"| {side} | " + " | ".join(cells) + " |")


def main(argv: list[str] | None = None) -> int:
    """Run every part and print markdown tables."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--bag", type=Path, default=SAMPLE_BAG, help="recording with <stem>.ground_truth.json beside")
    parser.add_argument("--fit-seeds", type=int, nargs="*", default=[], help="also run simulator seeds (fitting)")
    parser.add_argument("--speed-frames", type=int, default=40, help="frames per speed set")
    parser.add_argument(
        "--speed-batch",
        type=int,
        default=1,
        help="frames whose tags' poses are solved together in the speed table, in tasks of that many (the detect "
        "stage's detect.batch_frames is 16: --speed-batch 16 --speed-frames 64 measures the stage's way); 1 (the "
        "default): one frame at a time, as this table always was",
    )
    parser.add_argument("--repeats", type=int, default=3, help="interleaved repeats per speed cell (median)")
    parser.add_argument("--skip", nargs="*", default=[], choices=["sim", "photos", "speed", "posecov", "recall"])
    parser.add_argument("--posecov-frames", type=int, default=200, help="sample frames for the pose + covariance share")
    parser.add_argument(
        "--posecov-batches", type=int, nargs="*", default=[], help="chunk sizes to compare (default: batch_frames)"
    )
    parser.add_argument("--corner-scale", action="store_true", help="also the exact-render corner scale check")
    parser.add_argument(
        "--worlds", action="store_true", help="recall against AprilTag 3 on generated worlds (WORLDS), sample, photos"
    )
    parser.add_argument("--worlds-dir", type=Path, default=None, help="keep / reuse the generated worlds here")
    parser.add_argument(
        "--threshold-survival",
        action="store_true",
        help="per tag, the largest quad threshold the library keeps it at (generated worlds, sample, photos)",
    )
    parser.add_argument(
        "--variants", nargs="*", default=None, help="only the settings whose name contains one of these words"
    )
    args = parser.parse_args(argv)
    if args.variants:
        for name in list(VARIANTS):
            if name not in (DEFAULT, REFERENCE) and not any(w in name for w in args.variants):
                del VARIANTS[name]
    t0 = time.perf_counter()
    frames, truth, camera = sample_recording(args.bag)
    worlds: dict[str, tuple[list[np.ndarray], list[dict[str, Any]], CameraModel]] = {}
    if args.worlds:
        import tempfile

        with tempfile.TemporaryDirectory() as tmp:
            folder = args.worlds_dir or Path(tmp)
            folder.mkdir(parents=True, exist_ok=True)
            worlds = generated_worlds(folder)
        if args.threshold_survival:
            photos = sorted((SHARED / "apriltag-photos").glob("*.jpg")) + sorted(
                (SHARED / "apriltag-multi").glob("*.png")
            )
            bench_threshold_survival(
                {
                    **{name.split(":")[0]: f for name, (f, _, _) in worlds.items()},
                    f"sample {args.bag.name} (every 2nd frame)": frames[::2],
                    "photos": [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in photos],
                }
            )
        if "recall" not in args.skip:
            bench_worlds({**worlds, f"sample {args.bag.name}": (frames, truth, camera)}, VARIANTS)
    if "sim" not in args.skip:
        bench_sim(frames, truth, camera, f"Sample recording {args.bag.name}")
    for seed in args.fit_seeds:
        f, t, c = simulated(seed)
        bench_sim(f, t, c, f"Simulator seed {seed} (fitting data, not the sample)")
    if "photos" not in args.skip:
        bench_photos()
    if args.corner_scale:
        bench_corner_scale()
    if "posecov" not in args.skip:
        batches = args.posecov_batches or [DetectConfig().batch_frames]
        bench_posecov(frames, camera, args.posecov_frames, args.repeats, batches)
    if "speed" not in args.skip:
        extra = {name.split(":")[0]: (f, c) for name, (f, _, c) in worlds.items()}
        bench_speed(frames, camera, args.speed_frames, args.repeats, extra, args.speed_batch)
    print(f"\n(benchmark took {time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
