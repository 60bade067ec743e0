"""What ingest draws in ``ingest.rrd``: the odometry path, laser scans in the odometry frame (read back from the
stage's tables), and the camera frames (logged as they are read, :class:`FrameLog`)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import pyarrow as pa
import rerun as rr

from pipeline.artifacts import StageInput
from pipeline.context import StageContext
from pipeline.contracts import Column
from stages.columns import POSITION, QUATERNION, STAMP_NS
from stages.frames import frame_blob
from stages.ingest.artifacts import (
    ANGLE_INCREMENT,
    ANGLE_MIN,
    DATA,
    FORMAT,
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
        drawn = np.arange(0, scans.num_rows, rr_cfg.scan_stride)
        T_world_laser = poses[nearest[drawn]] @ T_base_laser  # per drawn scan
        pieces = []
        for rows in np.array_split(np.arange(drawn.size), -(-drawn.size // 512)):  # 512 scans at a time
            block = drawn[rows]
            limits = {c: v[block] for c, v in meta.items()}
            pieces.append(_scan_points(values, starts[block], lengths[block], limits, T_world_laser[rows]))
        world = np.concatenate([w for w, _ in pieces])
        kept = np.concatenate([k for _, k in pieces])  # points per drawn scan
        first = np.cumsum(kept) - kept
        n = drawn.size
        times = s_stamps[drawn]
        # one call for every logged scan (a scan each at its stamp), as many rows as separate logs would make
        rec.send_columns(
            "/ingest/world/scan",
            indexes=[rr.TimeColumn("time", timestamp=times.astype(np.int64).astype("datetime64[ns]"))],
            columns=[
                *rr.Points3D.columns(positions=world).partition(kept.tolist()),
                *rr.Points3D.columns(colors=np.tile([[255, 120, 60]], (n, 1)), radii=np.full(n, 0.02)),
            ],
        )
        cloud = world[(np.arange(world.shape[0]) - np.repeat(first, kept)) % 2 == 0]  # every other point of each
        # every logged scan at once, in the odometry frame: the walls as odometry (with its drift) sees them
        rec.log(
            "/ingest/world/scan_map",
            rr.Points3D(cloud, colors=[[150, 150, 150]], radii=0.01),
            static=True,
        )

    K = np.asarray(camera.K, dtype=float).reshape(3, 3)
    rec.log("/ingest/camera", rr.Pinhole(image_from_camera=K, resolution=[camera.width, camera.height]), static=True)


def _scan_points(
    values: np.ndarray,
    starts: np.ndarray,
    lengths: np.ndarray,
    meta: Mapping[Column, np.ndarray],
    T_world_laser: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The valid returns of some scans in the world frame (every beam at once), and how many each scan has.

    ``starts``/``lengths``: each scan's beams in ``values``; ``meta``: each scan's angle and range limits;
    ``T_world_laser``: each scan's laser pose.
    """
    owner = np.repeat(np.arange(lengths.size), lengths)  # the scan each beam belongs to
    beam = np.arange(owner.size) - np.repeat(np.cumsum(lengths) - lengths, lengths)  # its index within the scan
    r = values[starts[owner] + beam]
    a = meta[ANGLE_MIN][owner] + meta[ANGLE_INCREMENT][owner] * beam
    ok = np.isfinite(r) & (r >= meta[RANGE_MIN][owner]) & (r <= meta[RANGE_MAX][owner])
    r, a, owner = r[ok], a[ok], owner[ok]
    local = np.column_stack([r * np.cos(a), r * np.sin(a), np.zeros(r.size)])
    R, t = T_world_laser[:, :3, :3], T_world_laser[:, :3, 3]
    world = np.einsum("nij,nj->ni", R[owner], local) + t[owner]
    return world, np.bincount(owner, minlength=lengths.size)


class FrameLog:
    """The camera frames drawn in ``ingest.rrd`` (every ``image_stride``-th), logged as ingest reads them.

    Reading the frames back from ``frames.parquet`` once the stage has written it cost a quarter of the sample's
    ingest; the rows are the same ones the table receives. They go in one call per ``batch`` drawn frames, as
    :func:`stages.frames.frame_blob` encodes them (raw pixels as JPEG).
    """

    def __init__(self, rec: rr.RecordingStream, stride: int, batch: int = 64) -> None:
        self.rec, self.stride, self.batch = rec, max(1, stride), batch
        self.seen = 0
        self.encoded: list[tuple[int, bytes, str]] = []  # stamp, blob, media type

    def add(self, row: dict[str, Any]) -> None:
        """A row of ``frames.parquet`` as it is written."""
        k, self.seen = self.seen, self.seen + 1
        if k % self.stride:
            return
        blob = frame_blob(row[FORMAT], row[WIDTH], row[HEIGHT], row[STEP] or 0, row[DATA])
        if blob is None:
            return
        self.encoded.append((row[STAMP_NS], *blob))
        if len(self.encoded) >= self.batch:
            self.flush()

    def flush(self) -> None:
        if not self.encoded:
            return
        rows, self.encoded = self.encoded, []
        self.rec.send_columns(
            "/ingest/camera/image",
            indexes=[rr.TimeColumn("time", timestamp=np.array([r[0] for r in rows], "datetime64[ns]"))],
            columns=rr.EncodedImage.columns(blob=[r[1] for r in rows], media_type=[r[2] for r in rows]),
        )
