"""Benchmark of the detect back-ends: recall, corner RMS, pose NEES and speed, side by side in one run.

Plain script (not a test; wall times are never asserted):

    python tests/benchmarks/bench_detect.py [--duration 40] [--speed-frames 40]

Data: the simulator's office recording (sample_data/simulate.py, in memory, ground-truth corners and
poses), ../shared/data/apriltag-photos (real photos with corner ground truth), ../shared/data/apriltag-multi.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
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
from stages.detect.core import FrameJob, FrameProcessor  # noqa: E402
from stages.detect.render import TagPlacement, look_at_tag, render_frame  # noqa: E402
from stages.detect.stage import _corner_sigma  # noqa: E402

SHARED = ROOT.parent / "shared" / "data"
VARIANTS: dict[str, dict[str, Any]] = {
    "apriltag3 dec1 (default)": {"backend": "apriltag3", "decimation": 1.0},
    "apriltag3 dec2": {"backend": "apriltag3", "decimation": 2.0},
    "opencv subpix": {"backend": "opencv", "opencv_corner_refinement": "subpix"},
    "opencv contour": {"backend": "opencv", "opencv_corner_refinement": "contour"},
}


def simulated(duration: float | None) -> tuple[list[np.ndarray], list[dict[str, Any]], dict[str, Any], float]:
    """Frames, per-frame ground truth, the camera and the tag size of the simulated office run."""
    from sample_data.simulate import SimConfig, decode_image, image_topic, simulate

    cfg = SimConfig(duration_s=duration)
    rec = simulate(cfg)
    topic = image_topic(cfg)
    frames = [decode_image(m.payload) for m in rec.messages if m.topic == topic]
    gt = rec.ground_truth
    return frames, gt["frames"], gt["camera"], float(cfg.tag_size_m)


def rms(values: list[float]) -> float:
    """Root mean square (nan when empty)."""
    return float(np.sqrt(np.mean(np.square(values)))) if values else float("nan")


def bench_sim(frames: list[np.ndarray], truth: list[dict[str, Any]], camera: dict[str, Any], size: float) -> None:
    """Recall, corner RMS and false ids on the simulator, per back-end; NEES per distance band."""
    import gtsam

    print(f"\n## Simulated office recording: {len(frames)} frames (tags fully in view, shortest side >= 15 px)")
    print("| detector | recall | corner RMS px | false ids | NEES/6 (all) | NEES/6 non-ambiguous |")
    print("| --- | --- | --- | --- | --- | --- |")
    bands = [(0, 1), (1, 2), (2, 3), (3, 5), (5, 100)]
    band_rows: dict[str, list[str]] = {}
    for name, kw in VARIANTS.items():
        cfg = DetectConfig(tag_size_m=size, **kw)
        proc = FrameProcessor(cfg, camera)
        rows = []
        n_truth = hits = false = 0
        sq: list[float] = []
        matched = []
        for i, (img, gt) in enumerate(zip(frames, truth, strict=True)):
            assert proc.detector is not None
            from stages.detect.core import detect_image

            found = detect_image(img, proc.detector, proc.camera, cfg, FrameJob(i, 0, "cam"))
            rows += found
            ids = {t["id"]: t for t in gt["visible_tags"]}
            by_id = {r["tag_id"]: r for r in found}
            false += sum(1 for r in found if r["tag_id"] not in ids)
            for tid, t in ids.items():
                c = np.reshape(t["corners_px"], (4, 2))
                if shortest_side_px(c) < 15:
                    continue
                n_truth += 1
                if tid in by_id:
                    hits += 1
                    d = np.reshape(by_id[tid]["corners"], (4, 2)) - c
                    sq += list(np.sum(d**2, axis=1))
            for r in found:
                if r["tag_id"] in ids:
                    matched.append((r, ids[r["tag_id"]]))
        sigmas, _ = _corner_sigma(rows, cfg)
        nees, dist, amb = [], [], []
        for r, t in matched:
            cov = sigmas[0] ** 2 * np.reshape(r["pose_cov_unit"], (6, 6))
            T_est = gtsam.Pose3(np.reshape(r["T_camera_tag"], (4, 4)))
            xi = T_est.localCoordinates(gtsam.Pose3(np.array(t["T_camera_tag"])))
            nees.append(float(xi @ np.linalg.solve(cov, xi)) / 6)
            dist.append(float(np.linalg.norm(np.array(t["T_camera_tag"])[:3, 3])))
            amb.append(r["ambiguity_ratio"] > cfg.max_ambiguity_ratio)
        nees_a, dist_a, amb_a = np.array(nees), np.array(dist), np.array(amb)
        corner = np.sqrt(np.mean(sq)) if sq else float("nan")
        print(
            f"| {name} | {hits}/{n_truth} = {hits / max(n_truth, 1):.3f} | {corner:.3f} "
            f"| {false} | {nees_a.mean():.2f} | {nees_a[~amb_a].mean():.2f} |"
        )
        cells = []
        for lo, hi in bands:
            m = (dist_a >= lo) & (dist_a < hi)
            cells.append(f"{nees_a[m].mean():.2f} (n={m.sum()})" if m.any() else "-")
        band_rows[name] = [*cells, f"{sigmas[0]:.3f}"]
    print("\nNEES/6 of the tag pose against ground truth, per camera-to-tag distance band (pooled corner sigma):")
    print("| detector | " + " | ".join(f"{lo}-{hi} m" for lo, hi in bands) + " | corner sigma px |")
    print("| --- |" + " --- |" * (len(bands) + 1))
    for name, cells in band_rows.items():
        print(f"| {name} | " + " | ".join(cells) + " |")


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


_PROC: FrameProcessor | None = None


def _init(cfg_data: dict[str, Any], camera: dict[str, Any]) -> None:
    global _PROC
    _PROC = FrameProcessor(DetectConfig.model_validate(cfg_data), camera)


def _work(frames: list[np.ndarray]) -> int:
    from stages.detect.core import detect_image

    assert _PROC is not None and _PROC.detector is not None
    return sum(len(detect_image(f, _PROC.detector, _PROC.camera, _PROC.cfg)) for f in frames)


def throughput(cfg: DetectConfig, camera: dict[str, Any], frames: list[np.ndarray], workers: int) -> float:
    """Frames per second of detection + pose, in ``workers`` processes (pool start-up excluded)."""
    batches = [frames[i : i + 4] for i in range(0, len(frames), 4)]
    if workers == 1:
        _init(cfg.model_dump(mode="json"), camera)
        _work(frames[:2])
        t0 = time.perf_counter()
        for b in batches:
            _work(b)
        return len(frames) / (time.perf_counter() - t0)
    with ProcessPoolExecutor(workers, initializer=_init, initargs=(cfg.model_dump(mode="json"), camera)) as pool:
        list(pool.map(_work, [frames[:2]] * workers))
        t0 = time.perf_counter()
        list(pool.map(_work, batches))
        return len(frames) / (time.perf_counter() - t0)


def synthetic_frames(width: int, height: int, n: int) -> tuple[list[np.ndarray], dict[str, Any]]:
    """``n`` rendered frames of 4 tags at 0.8-3 m, size ``width`` x ``height``."""
    f = 0.65 * width
    camera = {
        "width": width,
        "height": height,
        "K": [f, 0, width / 2, 0, f, height / 2, 0, 0, 1],
        "distortion_model": "plumb_bob",
        "D": [-0.06, 0.012, 0.0006, -0.0004, 0.0],
    }
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


def bench_speed(sim_frames: list[np.ndarray], sim_camera: dict[str, Any], n: int) -> None:
    """Frames per second, one process and two, per back-end and frame size; ratios to AT3 dec2 x1."""
    sets: dict[str, tuple[list[np.ndarray], dict[str, Any]]] = {
        f"sim {sim_frames[0].shape[1]}x{sim_frames[0].shape[0]}": (sim_frames[:n], sim_camera),
        "640x480": synthetic_frames(640, 480, n),
        "1280x720": synthetic_frames(1280, 720, n),
    }
    print(f"\n## Speed (frames per second, detection + pose, {n} frames per set; ratio to apriltag3 dec2 x1)")
    print("| detector | " + " | ".join(f"{k} x1 | {k} x2" for k in sets) + " |")
    print("| --- |" + " --- | --- |" * len(sets))
    results: dict[str, list[float]] = {}
    for name, kw in VARIANTS.items():
        cfg = DetectConfig(**kw)
        results[name] = []
        for frames, camera in sets.values():
            results[name] += [throughput(cfg, camera, frames, 1), throughput(cfg, camera, frames, 2)]
    ref = results["apriltag3 dec2"]
    for name, vals in results.items():
        cells = [f"{v:.1f} ({v / ref[2 * (i // 2)]:.2f}x)" for i, v in enumerate(vals)]
        print(f"| {name} | " + " | ".join(cells) + " |")


def main(argv: list[str] | None = None) -> int:
    """Run every part and print markdown tables."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--duration", type=float, default=None, help="simulated seconds (default: whole path)")
    parser.add_argument("--speed-frames", type=int, default=40, help="frames per speed measurement")
    parser.add_argument("--skip", nargs="*", default=[], choices=["sim", "photos", "speed"])
    args = parser.parse_args(argv)
    frames, truth, camera, size = simulated(args.duration)
    timer: Callable[[], float] = time.perf_counter
    t0 = timer()
    if "sim" not in args.skip:
        bench_sim(frames, truth, camera, size)
    if "photos" not in args.skip:
        bench_photos()
    if "speed" not in args.skip:
        bench_speed(frames, camera, args.speed_frames)
    print(f"\n(benchmark took {timer() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
