"""What ingest draws in ``ingest.rrd``: the odometry path, laser scans in the odometry frame, camera frames."""

from __future__ import annotations

from typing import Any

import numpy as np
import pyarrow as pa
import rerun as rr

from pipeline.artifacts import StageInput
from pipeline.context import StageContext
from pipeline.recording import set_stamp
from stages.columns import POSITION, QUATERNION, STAMP_NS
from stages.ingest.artifacts import (
    ANGLE_INCREMENT,
    ANGLE_MIN,
    DATA,
    FORMAT,
    FRAMES,
    HEIGHT,
    ODOMETRY,
    RANGE_MAX,
    RANGE_MIN,
    RANGES,
    SCANS,
    STEP,
    WIDTH,
    CameraModel,
    Extrinsics,
)


def _rotation_matrices(quats: np.ndarray) -> np.ndarray:
    """The rotation matrices of unit quaternions (x, y, z, w), with the arithmetic of scipy's
    ``Rotation.from_quat(quats).as_matrix()`` (normalised once more, then the same products), so the same bits,
    without the 0.27 s scipy's import adds to an ingest run on its own."""
    q = quats / np.sqrt((quats * quats).sum(axis=1))[:, None]
    x, y, z, w = q.T
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    rows = [
        x2 - y2 - z2 + w2,
        2 * (xy - zw),
        2 * (xz + yw),
        2 * (xy + zw),
        -x2 + y2 - z2 + w2,
        2 * (yz - xw),
        2 * (xz - yw),
        2 * (yz + xw),
        -x2 - y2 + z2 + w2,
    ]
    return np.stack(rows, axis=-1).reshape(-1, 3, 3)


def _pose_matrices(odom: pa.Table) -> tuple[np.ndarray, np.ndarray]:
    """4x4 odometry poses and their unit quaternions (x, y, z, w, as ROS and Rerun order them), vectorised."""
    quats = np.column_stack([odom.column(c).to_numpy() for c in QUATERNION])
    quats[np.linalg.norm(quats, axis=1) == 0] = [0.0, 0.0, 0.0, 1.0]
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    T = np.tile(np.eye(4), (odom.num_rows, 1, 1))
    T[:, :3, :3] = _rotation_matrices(quats)
    T[:, :3, 3] = np.column_stack([odom.column(c).to_numpy() for c in POSITION])
    return T, quats


def log_ingest(ctx: StageContext, camera: CameraModel, extrinsics: Extrinsics) -> None:
    """Log the ingested data (read back from the stage's output) to the stage's recording."""
    rec = ctx.rec
    written = StageInput("ingest", ctx.output.path)
    rr_cfg = ctx.settings.rerun
    rec.log("/ingest/world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)

    odom = ODOMETRY.read(written, columns=[STAMP_NS, *POSITION, *QUATERNION])
    poses, quats = _pose_matrices(odom) if odom.num_rows else (np.zeros((0, 4, 4)), np.zeros((0, 4)))
    stamps = odom.column(STAMP_NS).to_numpy() if odom.num_rows else np.zeros(0, dtype=np.int64)
    if len(poses):
        rec.log("/ingest/world/odometry/path", rr.LineStrips3D([poses[:, :3, 3]], colors=[[90, 160, 255]]), static=True)
        rec.send_columns(
            "/ingest/world/odometry/base",
            indexes=[rr.TimeColumn("time", timestamp=stamps.astype("datetime64[ns]"))],
            columns=rr.Transform3D.columns(translation=poses[:, :3, 3], quaternion=quats),
        )
        rec.log("/ingest/world/odometry/base", rr.TransformAxes3D(0.3), static=True)

    scans = SCANS.read(written)
    if scans.num_rows and len(poses):
        laser = extrinsics.sensors.get("laser")
        T_base_laser = np.asarray(laser.T_base_sensor) if laser is not None else np.eye(4)
        s_stamps = scans.column(STAMP_NS).to_numpy()
        meta = {c: scans.column(c).to_numpy() for c in (ANGLE_MIN, ANGLE_INCREMENT, RANGE_MIN, RANGE_MAX)}
        ranges: Any = scans.column(RANGES).combine_chunks()  # a ListArray
        lengths = ranges.value_lengths().to_numpy(zero_copy_only=False)
        ends = np.cumsum(lengths)
        starts = ends - lengths
        with np.errstate(invalid="ignore"):  # signalling NaNs from damaged bytes are NaN ranges
            values = ranges.flatten().to_numpy(zero_copy_only=False).astype(float)
        nearest = np.clip(np.searchsorted(stamps, s_stamps), 0, len(stamps) - 1)  # the odometry pose of each scan
        cloud, logged, times = [], [], []
        for i in range(0, scans.num_rows, rr_cfg.scan_stride):
            r = values[starts[i] : ends[i]]
            a = meta[ANGLE_MIN][i] + meta[ANGLE_INCREMENT][i] * np.arange(len(r))
            ok = np.isfinite(r) & (r >= meta[RANGE_MIN][i]) & (r <= meta[RANGE_MAX][i])
            pts = np.column_stack([r[ok] * np.cos(a[ok]), r[ok] * np.sin(a[ok]), np.zeros(ok.sum()), np.ones(ok.sum())])
            world = (poses[nearest[i]] @ T_base_laser @ pts.T).T[:, :3]
            logged.append(world)
            times.append(s_stamps[i])
            cloud.append(world[::2])
        # one call for every logged scan (a scan each at its stamp), as many rows as separate logs would make
        n = len(logged)
        rec.send_columns(
            "/ingest/world/scan",
            indexes=[rr.TimeColumn("time", timestamp=np.asarray(times, dtype=np.int64).astype("datetime64[ns]"))],
            columns=[
                *rr.Points3D.columns(positions=np.concatenate(logged)).partition([len(w) for w in logged]),
                *rr.Points3D.columns(colors=np.tile([[255, 120, 60]], (n, 1)), radii=np.full(n, 0.02)),
            ],
        )
        # every logged scan at once, in the odometry frame: the walls as odometry (with its drift) sees them
        rec.log(
            "/ingest/world/scan_map",
            rr.Points3D(np.concatenate(cloud), colors=[[150, 150, 150]], radii=0.01),
            static=True,
        )

    K = np.asarray(camera.K, dtype=float).reshape(3, 3)
    rec.log("/ingest/camera", rr.Pinhole(image_from_camera=K, resolution=[camera.width, camera.height]), static=True)
    k = 0
    pool = pa.default_memory_pool()
    for batch in FRAMES.batches(written, batch_size=64):
        pool.release_unused()  # Arrow's allocator would keep every read batch's memory: 140 MiB at 16 minutes
        # only the frames drawn leave Arrow (each batch's bytes are read and decompressed anyway)
        drawn = [i for i in range(batch.num_rows) if (k + i) % rr_cfg.image_stride == 0]
        k += batch.num_rows
        encoded: list[dict[str, Any]] = []
        for row in batch.take(drawn).to_pylist():
            if row[FORMAT] in ("jpeg", "png"):
                encoded.append(row)
                continue
            set_stamp(rec, row[STAMP_NS])
            rec.log("/ingest/camera/image", image_archetype(row))
        if encoded:  # JPEG/PNG frames: a row each, as image_archetype's, in one call per batch
            rec.send_columns(
                "/ingest/camera/image",
                indexes=[rr.TimeColumn("time", timestamp=np.array([r[STAMP_NS] for r in encoded], "datetime64[ns]"))],
                columns=rr.EncodedImage.columns(
                    blob=[r[DATA] for r in encoded], media_type=[_MEDIA_TYPES[r[FORMAT]] for r in encoded]
                ),
            )


_MEDIA_TYPES = {"jpeg": "image/jpeg", "png": "image/png"}


def image_archetype(row: dict[str, Any]) -> Any:
    """A Rerun image for a frames.parquet row: compressed bytes as they are, raw pixels with their layout."""
    fmt = row[FORMAT]
    if fmt in ("jpeg", "png"):
        return rr.EncodedImage(contents=row[DATA], media_type=_MEDIA_TYPES[fmt])
    h, w, step = row[HEIGHT], row[WIDTH], row[STEP]
    buf = np.frombuffer(row[DATA], dtype=np.uint8)
    if fmt in ("mono8", "8UC1"):
        return rr.Image(buf.reshape(h, step)[:, :w], color_model="L")
    if fmt in ("mono16", "16UC1"):
        return rr.Image(buf.view(np.uint16).reshape(h, step // 2)[:, :w], color_model="L")
    if fmt in ("bgr8", "rgb8"):
        img = buf.reshape(h, step)[:, : w * 3].reshape(h, w, 3)
        return rr.Image(img, color_model="BGR" if fmt == "bgr8" else "RGB")
    return rr.TextLog(f"frame in encoding {fmt!r} not drawn")
