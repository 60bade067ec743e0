"""The detect stage: every ingested frame in, every tag out, with its pose and an honest covariance."""

from __future__ import annotations

import logging
import time
from collections import Counter, deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future
from typing import Any

import numpy as np
import pyarrow as pa
import rerun as rr

from pipeline.artifacts import StageInput
from pipeline.context import StageContext
from pipeline.errors import InputError, StageError
from pipeline.recording import colormap, ellipsoids, set_stamp
from pipeline.workers import WorkerPool
from stages.columns import CORNERS, FAMILY, FRAME, STAMP_NS, TAG_ID, TOPIC
from stages.detect.artifacts import (
    ALT_PROBABILITY,
    ALT_T_CAMERA_TAG,
    AMBIGUITY_RATIO,
    AMBIGUOUS,
    CAMERA,
    DECISION_MARGIN,
    DETECTIONS,
    HAMMING,
    POSE_COV,
    POSITION_COV,
    REPROJECTION_PX,
    SIZE_M,
    T_CAMERA_TAG,
)
from stages.detect.backends import TagObservation
from stages.detect.config import DetectConfig, TagSize
from stages.detect.core import (
    DROP_REASONS,
    BatchResult,
    DetectionRow,
    FrameJob,
    FrameProcessor,
    init_worker,
    process_in_worker,
    reposed,
)
from stages.detect.edges import run_shift
from stages.detect.pose import pose_covariance
from stages.frames import RAW_ENCODINGS, frame_blob, readable_encoding
from stages.ingest.artifacts import CAMERA as CAMERA_MODEL
from stages.ingest.artifacts import (
    CAMERAS,
    DATA,
    FORMAT,
    FRAMES,
    HEIGHT,
    STEP,
    TAG_DETECTIONS,
    TAGS,
    WIDTH,
    CameraModel,
    TagsInfo,
)

log = logging.getLogger(__name__)

# apriltag_ros / TagSLAM publish the AprilTag library's corner order; this picks the OpenCV order from it.
_APRILTAG_TO_OPENCV = [1, 0, 3, 2]


def _frame_jobs(ingest: StageInput, batch_frames: int, edge_stride: int = 0) -> Iterator[list[FrameJob]]:
    """The frames in batches; every ``edge_stride``-th (0: none) has its tags' edges measured."""
    start = 0  # the batch's first frame's index in the run
    for batch in FRAMES.batches(ingest, batch_size=batch_frames):
        d = batch.to_pydict()
        yield [
            FrameJob(
                frame=int(d[FRAME][i]),
                stamp_ns=int(d[STAMP_NS][i]),
                camera=str(d[TOPIC][i]),
                format=str(d[FORMAT][i]),
                width=int(d[WIDTH][i]),
                height=int(d[HEIGHT][i]),
                step=int(d[STEP][i] or 0),
                data=d[DATA][i],
                measure_edges=bool(edge_stride) and (start + i) % edge_stride == 0,
            )
            for i in range(batch.num_rows)
        ]
        start += batch.num_rows


def bag_detection_jobs(table: pa.Table, cfg: DetectConfig) -> list[FrameJob]:
    """Frames of detections a bag already holds (``ingest/tag_detections.parquet``), in the OpenCV order."""
    d = table.to_pydict()
    by_frame: dict[tuple[str, int], FrameJob] = {}
    for i in range(table.num_rows):
        key = (str(d[TOPIC][i]), int(d[FRAME][i]))
        job = by_frame.setdefault(
            key, FrameJob(frame=key[1], stamp_ns=int(d[STAMP_NS][i]), camera=key[0], observations=[])
        )
        corners = np.asarray(d[CORNERS][i], float).reshape(4, 2)
        if cfg.bag_corner_order == "apriltag":
            corners = corners[_APRILTAG_TO_OPENCV]
        assert job.observations is not None
        job.observations.append(
            TagObservation(int(d[TAG_ID][i]), str(d[FAMILY][i] or cfg.families[0]), corners, float("nan"), 0)
        )
    return sorted(by_frame.values(), key=lambda j: (j.stamp_ns, j.camera, j.frame))


def _bounded_map(
    fn: Callable[[list[FrameJob]], BatchResult],
    items: Iterable[list[FrameJob]],
    pool: WorkerPool | None,
    in_flight: int,
) -> Iterator[tuple[list[FrameJob], BatchResult]]:
    """``fn`` over ``items`` in order, at most ``in_flight`` batches queued in the pool at once."""
    if pool is None:
        for item in items:
            yield item, fn(item)
        return
    queue: deque[tuple[list[FrameJob], Future[BatchResult]]] = deque()
    for item in items:
        queue.append((item, pool.submit(process_in_worker, item)))
        if len(queue) >= in_flight:
            done, fut = queue.popleft()
            yield done, fut.result()
    while queue:
        done, fut = queue.popleft()
        yield done, fut.result()


def run(ctx: StageContext, cfg: DetectConfig) -> dict[str, Any]:
    """Detect tags in every ingested frame (or read the bag's detections) and write ``detections.parquet``."""
    start = time.perf_counter()
    ingest = ctx.input("ingest")
    if not ingest.exists(CAMERA_MODEL.file):
        raise InputError(
            f"ingest wrote no {CAMERA_MODEL.file} (no camera_info in the bag); re-run ingest with --camera FILE"
        )
    camera = CAMERA_MODEL.read(ingest)
    cameras = CAMERAS.read(ingest).cameras if ingest.exists(CAMERAS.file) else None
    from_bag = ingest.exists(TAG_DETECTIONS.file)
    tags = TAGS.read(ingest) if ingest.exists(TAGS.file) else None
    if tags is not None:
        cfg = sizes_from_tags(cfg, tags)
    _log_static(ctx.rec, camera)
    batches, total, workers = _batches(ingest, cfg, from_bag)
    found = _detect(ctx, cfg, (camera, cameras), from_bag, batches, total, workers)
    edges = _edge_correction(found, cfg, camera, cameras, from_bag)
    sigma, sigma_source = _corner_sigma(found.rows, cfg)
    table, n_ambiguous, n_dropped_ambiguous = _table(found.rows, sigma, cfg)
    found.rows.clear()  # the table holds them now
    if table.num_rows == 0 and from_bag:
        raise StageError(
            f"no usable tags in the bag's detections ({found.frames} frames, dropped: "
            f"{', '.join(f'{k} {v}' for k, v in found.dropped.items() if v) or 'none'}); check the tag sizes "
            "(detect.tag_size_m) and max_reprojection_px / min_side_px"
        )
    if table.num_rows == 0:
        raise StageError(
            f"no {'/'.join(cfg.families)} tags found in {found.frames} frames ({len(found.corrupt)} corrupt) with "
            f"backend {cfg.backend}; check the families and the tag sizes, or lower min_decision_margin / min_side_px"
        )
    DETECTIONS.write(ctx.output, table)
    _log_tags(ctx.rec, table, ctx.n_sigma)
    seconds = time.perf_counter() - start
    ids = table.column(TAG_ID).to_numpy()
    reproj = table.column(REPROJECTION_PX).to_numpy()
    sizes = {"tag_size_m": cfg.tag_size_m, "tag_sizes": len(cfg.tag_sizes)} if tags is not None else {}
    return {
        "frames": found.frames,
        "detections": table.num_rows,
        "distinct_tags": len(np.unique(ids)),
        "frames_with_tags": len(
            set(zip(table.column(CAMERA).to_pylist(), table.column(FRAME).to_pylist(), strict=True))
        ),
        "detector": "bag" if from_bag else cfg.backend,
        "source": "tag_detections" if from_bag else "images",
        "families": sorted(set(table.column(FAMILY).to_pylist())) if from_bag else list(cfg.families),
        "corrupt_frames": len(found.corrupt),
        "corrupt_frame_ids": [f for f, _ in found.corrupt][:100],
        "dropped": {k: int(found.dropped.get(k, 0)) for k in DROP_REASONS} | {"ambiguous": n_dropped_ambiguous},
        "ambiguous": n_ambiguous,
        "corner_sigma_px": {
            f"{lo:g}-{hi:g}": round(v, 4)
            for lo, hi, v in zip(SIDE_BANDS_PX[:-1], SIDE_BANDS_PX[1:], sigma, strict=True)
        },
        "corner_sigma_source": sigma_source,
        "reprojection_px_median": round(float(np.median(reproj)), 4),
        "detect_seconds": round(seconds, 3),
        "frames_per_second": round(found.frames / seconds, 2) if seconds > 0 else None,
        "workers": workers,
        "edges": edges,
        **({"notes": [edges["note"]]} if "note" in edges else {}),
        **sizes,
    }


EDGE_MIN_TAGS = 30
"""``corner_shift_px: auto`` needs at least this many measured tags to apply a shift."""
EDGE_MIN_Z = 3.0
"""... and a shift at least this many standard errors from none (a faint, noisy world's 66 tags read 0.039 ± 0.019
px, a shift its map did not have: 2.8 cm off without it, 3.2 cm with it)."""


def _edge_correction(
    found: BatchResult,
    cfg: DetectConfig,
    camera: CameraModel,
    cameras: dict[str, CameraModel] | None,
    from_bag: bool,
) -> dict[str, Any]:
    """``corner_shift_px: auto``: the run's edge shift from the measured tags and, when it reaches
    ``edge_shift_min_px``, the rows' quads moved outwards by it and their poses estimated again (in place). The
    summary's ``edges`` block says what was measured and done."""
    if cfg.corner_shift_px != "auto":
        return {"setting": cfg.corner_shift_px, "applied_px": float(cfg.corner_shift_px)}
    if from_bag:
        return {"setting": "auto", "applied_px": 0.0, "reason": "detections from the bag: no images to measure"}
    shift, se, n = run_shift(np.asarray(found.edge_shifts, dtype=float))
    out: dict[str, Any] = {"setting": "auto", "measured_tags": n}
    if n:
        out |= {"shift_px": round(shift, 4), "shift_se_px": round(se, 4)}
    why = None
    if n < EDGE_MIN_TAGS:
        why = f"{n} tags measured (< {EDGE_MIN_TAGS})"
    elif abs(shift) < cfg.edge_shift_min_px:
        why = f"|{shift:.3f}| px < detect.edge_shift_min_px={cfg.edge_shift_min_px:g}"
    elif abs(shift) < EDGE_MIN_Z * se:
        why = f"|{shift:.3f}| px is within {EDGE_MIN_Z:g} standard errors ({se:.3f} px) of none"
    if why is not None:
        return out | {"applied_px": 0.0, "reason": f"not applied: {why}"}
    processor = FrameProcessor(cfg, camera, with_detector=False, cameras=cameras)
    before = len(found.rows)
    found.rows, dropped = reposed(found.rows, shift, cfg, processor)
    lost = before - len(found.rows)
    found.dropped.update(dropped)
    side = "thinner" if shift > 0 else "thicker"
    cause = "overexposure or blooming" if shift > 0 else "crushed blacks or strong sharpening"
    note = (
        f"detect moved every tag's sides {'out' if shift > 0 else 'in'}wards by {abs(shift):.3f} px "
        f"(detect.corner_shift_px=auto): the black borders of {n} tags read {2 * abs(shift):.2f} px {side} than a "
        f"cell, as {cause} makes them, which would make every range read {'long' if shift > 0 else 'short'}"
        + (f"; {lost} detections no longer fit and were dropped" if lost else "")
    )
    return out | {"applied_px": round(shift, 4), "note": note}


def sizes_from_tags(cfg: DetectConfig, tags: TagsInfo) -> DetectConfig:
    """The settings with the tag sizes of ingest's ``tags.json`` (``--tags``): its default size where
    ``detect.tag_size_m`` is at its default, and the sizes of the tags it lists with a size other than its
    default, for the ids ``detect.tag_sizes`` leaves out (a size set in the settings wins)."""
    default = DetectConfig.model_fields["tag_size_m"].default
    size = tags.default_tag_size_m if tags.default_tag_size_m and cfg.tag_size_m == default else cfg.tag_size_m
    given = {entry.id for entry in cfg.tag_sizes}
    extra = [
        TagSize(id=i, size_m=s)
        for i, s in sorted(tags.tag_sizes_m.items())
        if i not in given and s not in (size, tags.default_tag_size_m)
    ]
    return cfg.model_copy(update={"tag_size_m": size, "tag_sizes": (*cfg.tag_sizes, *extra)})


def _check_encodings(ingest: StageInput) -> None:
    """Stop before reading any pixels when no frame is in an encoding :func:`decode_frame` reads; warn once per
    encoding it does not read when others remain.

    Raises:
        InputError: every frame is in such an encoding.
    """
    counts = Counter(FRAMES.read(ingest, columns=[FORMAT]).column(FORMAT).to_pylist())
    unread = {f: n for f, n in counts.items() if not readable_encoding(str(f))}
    if not unread:
        return
    listed = ", ".join(f"{f!r} ({n} frames)" for f, n in sorted(unread.items()))
    known = "jpeg, png and the raw encodings " + ", ".join(RAW_ENCODINGS)
    if len(unread) == len(counts):
        raise InputError(
            f"the camera frames are in encoding {listed}, which detect does not decode (it reads {known}); "
            "republish the images in one of those, or record the tag detections instead"
        )
    log.warning("%s skipped: detect does not decode that encoding (it reads %s)", listed, known)


def _batches(ingest: StageInput, cfg: DetectConfig, from_bag: bool) -> tuple[Iterable[list[FrameJob]], int, int]:
    """The work in batches (the bag's detections, or the frames), how many batches, and how many workers."""
    if from_bag:
        jobs = bag_detection_jobs(TAG_DETECTIONS.read(ingest), cfg)
        return [jobs[i : i + 256] for i in range(0, len(jobs), 256)], (len(jobs) + 255) // 256, 1
    total_frames = FRAMES.num_rows(ingest)
    if total_frames == 0:
        raise InputError(f"no frames in {ingest.file(FRAMES.file)}; check the camera topic given to ingest")
    _check_encodings(ingest)
    total = (total_frames + cfg.batch_frames - 1) // cfg.batch_frames
    stride = max(1, -(-total_frames // cfg.edge_frames)) if cfg.corner_shift_px == "auto" else 0
    return _frame_jobs(ingest, cfg.batch_frames, stride), total, cfg.workers


def _detect(
    ctx: StageContext,
    cfg: DetectConfig,
    rig: tuple[CameraModel, dict[str, CameraModel] | None],
    from_bag: bool,
    batches: Iterable[list[FrameJob]],
    total: int,
    workers: int,
) -> BatchResult:
    """Process the batches (in ``workers`` processes when more than one), logging the frames as they come.

    ``rig``: the camera, and of a rig with several, each camera by its topic.
    """
    camera, cameras = rig
    pool = None
    if workers > 1:
        # Its workers die with this process and leave Ctrl-C to it (pipeline.workers).
        pool = WorkerPool(
            workers, initializer=init_worker, initargs=(cfg.model_dump(mode="json"), camera, not from_bag, cameras)
        )
        fn = process_in_worker
    else:
        fn = FrameProcessor(cfg, camera, with_detector=not from_bag, cameras=cameras).process
    found = BatchResult()  # the sum over every batch
    try:
        stream = _bounded_map(fn, batches, pool, 2 * workers)
        for jobs_done, result in ctx.progress(stream, "detect", total=total):
            found.frames += result.frames
            found.rows += result.rows
            found.corrupt += result.corrupt
            found.dropped.update(result.dropped)
            found.edge_shifts += result.edge_shifts
            _log_frames(ctx.rec, jobs_done, result, ctx.settings.rerun.image_stride)
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)
    by_reason: dict[str, list[int]] = {}
    for frame, why in found.corrupt:
        by_reason.setdefault(why, []).append(frame)
    for why, frames in by_reason.items():  # one line per reason, not per frame
        shown = ", ".join(str(f) for f in frames[:5]) + (f", … ({len(frames)} in all)" if len(frames) > 5 else "")
        log.warning("%s %s skipped: %s", "frame" if len(frames) == 1 else "frames", shown, why)
    return found


# Corner noise can be pooled per band of the tag's shortest side in the image (px). Per-band pools
# (0, 15, 25, 40, 70, inf) were measured worse than one pool on the simulator (docs/detect.md): the
# residuals of mid-size tags understate their correlated corner errors. So one band.
SIDE_BANDS_PX = (0.0, float("inf"))
_MIN_PER_BAND = 20


def _band_of(side_px: float) -> int:
    return int(np.searchsorted(SIDE_BANDS_PX, side_px, side="right") - 1)


def _corner_sigma(rows: list[DetectionRow], cfg: DetectConfig) -> tuple[list[float], str]:
    """Corner noise per side band: from the settings, or pooled over the reprojection residuals.

    A tag's four corners give 8 residuals for 6 pose parameters, so 2 degrees of freedom. Residuals are
    pooled per band of the tag's shortest side (``SIDE_BANDS_PX``); a band with fewer than 20 tags uses
    the pool of every tag. Estimates are floored at ``min_corner_sigma_px``.
    """
    n_bands = len(SIDE_BANDS_PX) - 1
    if cfg.corner_sigma_px is not None:
        return [float(cfg.corner_sigma_px)] * n_bands, "settings"
    if not rows:
        return [cfg.min_corner_sigma_px] * n_bands, "floor"
    sse = np.zeros(n_bands)
    count = np.zeros(n_bands)
    for r in rows:
        b = _band_of(r.side_px)
        sse[b] += r.pose.sse_px2
        count[b] += 1
    overall = np.sqrt(sse.sum() / (2.0 * count.sum()))
    per_band = np.where(count >= _MIN_PER_BAND, np.sqrt(sse / (2.0 * np.maximum(count, 1))), overall)
    return [float(v) for v in np.maximum(per_band, cfg.min_corner_sigma_px)], "residuals"


def row_pose_cov(r: DetectionRow, sigma_px: float, cfg: DetectConfig) -> tuple[np.ndarray, float]:
    """The 6x6 pose covariance of one detection row for corner noise ``sigma_px`` and the probability that
    the other planar solution is the true one (see ``stages.detect.pose.pose_covariance``)."""
    pose = r.pose
    alt = None
    if pose.alt_cov_unit is not None:
        assert pose.alt_scale_dir is not None and pose.alt_offset is not None
        alt = (pose.alt_cov_unit, pose.alt_scale_dir, pose.alt_offset, float(pose.alt_sse_px2))
    return pose_covariance(
        pose.cov_unit, pose.scale_dir, sigma_px, cfg.corner_bias_px, float(pose.sse_px2), alt, cfg.ambiguity_mixture
    )


TABLE_CHUNK = 4096
"""Detections turned into Arrow at a time: as Python rows (lists of floats in dicts) an hour's 70,000 took ~300 MB."""


def _table(rows: list[DetectionRow], sigmas: list[float], cfg: DetectConfig) -> tuple[pa.Table, int, int]:
    """``detections.parquet``: the rows with their covariances for the corner noise of their band, the ambiguous
    ones flagged (or dropped); how many were ambiguous and how many of those were dropped."""
    out: list[dict[str, Any]] = []
    parts: list[pa.Table] = []  # the rows as Arrow every TABLE_CHUNK: their Python lists and dicts freed as we go
    n_ambiguous = n_dropped = 0
    for r in rows:
        if len(out) == TABLE_CHUNK:
            parts.append(DETECTIONS.table(out))
            out = []
        var = sigmas[_band_of(r.side_px)] ** 2
        ambiguous = bool(r.ambiguity_ratio > cfg.max_ambiguity_ratio)
        n_ambiguous += ambiguous
        if ambiguous and cfg.ambiguous == "drop":
            n_dropped += 1
            continue
        cov, p_alt = row_pose_cov(r, float(np.sqrt(var)), cfg)
        R = r.pose.T_camera_tag[:3, :3]
        out.append(
            {
                FRAME: r.frame,
                STAMP_NS: r.stamp_ns,
                CAMERA: r.camera,
                TAG_ID: r.tag_id,
                FAMILY: r.family,
                CORNERS: r.corners,
                SIZE_M: r.size_m,
                T_CAMERA_TAG: r.T_camera_tag,
                ALT_T_CAMERA_TAG: r.alt_T_camera_tag,
                POSE_COV: cov.ravel().tolist(),
                POSITION_COV: (R @ cov[3:, 3:] @ R.T).ravel().tolist(),
                REPROJECTION_PX: r.reprojection_px,
                AMBIGUITY_RATIO: r.ambiguity_ratio,
                ALT_PROBABILITY: p_alt,
                AMBIGUOUS: ambiguous,
                DECISION_MARGIN: r.decision_margin,
                HAMMING: r.hamming,
            }
        )
    if n_ambiguous:
        log.info(
            "%d ambiguous detections (ratio > %.2f) %s",
            n_ambiguous,
            cfg.max_ambiguity_ratio,
            "dropped" if cfg.ambiguous == "drop" else "kept, flagged",
        )
    if out or not parts:
        parts.append(DETECTIONS.table(out))
    return pa.concat_tables(parts), n_ambiguous, n_dropped


def _log_static(rec: rr.RecordingStream, camera: CameraModel) -> None:
    K = np.asarray(camera.K, float).reshape(3, 3)
    rec.log(
        "/detect/camera",
        rr.Pinhole(image_from_camera=K, resolution=[camera.width, camera.height], camera_xyz=rr.ViewCoordinates.RDF),
        static=True,
    )


def _log_frames(rec: rr.RecordingStream, jobs: list[FrameJob], result: BatchResult, stride: int) -> None:
    by_frame: dict[tuple[str, int], list[DetectionRow]] = {}
    for r in result.rows:
        by_frame.setdefault((r.camera, r.frame), []).append(r)
    for job in jobs:
        rows = by_frame.get((job.camera, job.frame), [])
        set_stamp(rec, job.stamp_ns)
        rec.log("/detect/stats/detections", rr.Scalars([float(len(rows))]))
        if rows:
            rec.log("/detect/stats/reprojection_px", rr.Scalars([float(np.mean([r.reprojection_px for r in rows]))]))
        if job.frame % stride:
            continue
        blob = None if job.data is None else frame_blob(job.format, job.width, job.height, job.step, job.data)
        if blob is not None:
            rec.log("/detect/camera/image", rr.EncodedImage(contents=blob[0], media_type=blob[1]))
        strips = [np.vstack([np.reshape(r.corners, (4, 2)), np.reshape(r.corners, (4, 2))[:1]]) for r in rows]
        ids = np.array([r.tag_id for r in rows])
        rec.log(
            "/detect/camera/image/tags",
            rr.LineStrips2D(
                strips,
                labels=[str(i) for i in ids],
                colors=colormap(ids % 16, 0, 15) if len(ids) else None,
                radii=rr.Radius.ui_points(2.0),
            ),
        )


def _log_tags(rec: rr.RecordingStream, table: pa.Table, n_sigma: float) -> None:
    """Tag axes and n-sigma position ellipsoids in the camera frame, per frame."""
    d = table.select([STAMP_NS, TAG_ID, SIZE_M, T_CAMERA_TAG, POSITION_COV, AMBIGUOUS]).to_pydict()
    by_stamp: dict[int, list[int]] = {}
    for i, s in enumerate(d[STAMP_NS]):
        by_stamp.setdefault(int(s), []).append(i)
    axis_colors = np.array([[230, 40, 40], [40, 200, 40], [40, 90, 230]], np.uint8)
    for stamp, idx in by_stamp.items():
        set_stamp(rec, stamp)
        origins, vectors, colors = [], [], []
        centers, covs, labels = [], [], []
        for i in idx:
            T = np.reshape(d[T_CAMERA_TAG][i], (4, 4))
            for k in range(3):
                origins.append(T[:3, 3])
                vectors.append(T[:3, k] * d[SIZE_M][i] * 0.75)
                colors.append(axis_colors[k])
            centers.append(T[:3, 3])
            covs.append(np.reshape(d[POSITION_COV][i], (3, 3)))
            labels.append(f"{d[TAG_ID][i]}{' (ambiguous)' if d[AMBIGUOUS][i] else ''}")
        rec.log("/detect/camera/tags/axes", rr.Arrows3D(origins=origins, vectors=vectors, colors=colors))
        rec.log("/detect/camera/tags/position_cov", ellipsoids(np.array(centers), covs, n_sigma, labels=labels))
