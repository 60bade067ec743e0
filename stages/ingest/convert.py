"""ROS messages to plain rows, for ROS 1 and ROS 2 field names alike.

rosbags gives ROS 1 messages their ROS 1 field names (``K``, ``D``) and ROS 2 messages theirs
(``k``, ``d``); the mcap decoder gives ROS 2 names. Every accessor here accepts both.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

import numpy as np

from pipeline.errors import InputError
from stages.columns import FRAME_ID, POSITION, QUATERNION, STAMP_NS
from stages.ingest.artifacts import (
    ANGLE_INCREMENT,
    ANGLE_MAX,
    ANGLE_MIN,
    CHILD_FRAME_ID,
    DATA,
    FORMAT,
    HEIGHT,
    POSE_COV,
    RANGE_MAX,
    RANGE_MIN,
    RANGES,
    SCAN_TIME,
    STEP,
    TIME_INCREMENT,
    TWIST_COV,
    VELOCITY,
    WIDTH,
    CameraModel,
)
from stages.ingest.fast import CameraInfoRecord, ImageRecord, OdometryRecord, ScanRecord, TransformRecord


def get(msg: Any, *names: str, default: Any = None) -> Any:
    """The first of ``names`` that ``msg`` has."""
    for n in names:
        if hasattr(msg, n):
            return getattr(msg, n)
    return default


def stamp_ns(msg: Any, fallback_ns: int) -> int:
    """The header stamp in nanoseconds, or ``fallback_ns`` (the log time) when it is zero."""
    header = get(msg, "header")
    if header is None:
        return fallback_ns
    st = get(header, "stamp")
    sec = int(get(st, "sec", "secs", default=0))
    nsec = int(get(st, "nanosec", "nsecs", default=0))
    value = sec * 1_000_000_000 + nsec
    return value if value > 0 else fallback_ns


def frame_id(msg: Any) -> str:
    """The header's frame id, without a leading slash."""
    header = get(msg, "header")
    return str(get(header, "frame_id", default="") or "").lstrip("/")


def as_bytes(data: Any) -> bytes:
    """Message byte arrays (numpy, list or bytes) as bytes."""
    if isinstance(data, bytes | bytearray | memoryview):
        return bytes(data)
    return np.asarray(data, dtype=np.uint8).tobytes()


def image_row(msg: Any, compressed: bool) -> dict[str, Any]:
    """The stored form of a decoded image (see :func:`image_record_row`)."""
    return image_record_row(image_record(msg, 0, compressed), compressed)


def camera_info_record(msg: Any) -> CameraInfoRecord:
    """The fields of a decoded CameraInfo that the camera model is made of."""
    header = get(msg, "header")
    return CameraInfoRecord(
        frame_id=str(get(header, "frame_id", default="") or ""),
        width=int(msg.width),
        height=int(msg.height),
        distortion_model=str(get(msg, "distortion_model", default="") or ""),
        d=np.asarray(get(msg, "d", "D", default=[]), dtype=float).ravel(),
        k=np.asarray(get(msg, "k", "K"), dtype=float).ravel(),
    )


def camera_from_info(msg: Any, topic: str) -> CameraModel:
    """The camera model (``camera.json``) of a CameraInfo message (see :func:`camera_from_record`)."""
    return camera_from_record(camera_info_record(msg), topic)


def camera_from_record(info: CameraInfoRecord, topic: str) -> CameraModel:
    """The camera model (``camera.json``) of a CameraInfo message's fields.

    Raises:
        InputError: when the message holds no calibration (zero focal length or image size).
    """
    K = [float(v) for v in info.k]
    D = [float(v) for v in info.d]
    width, height = info.width, info.height
    if len(K) != 9 or K[0] <= 0 or K[4] <= 0:
        raise InputError(
            f"CameraInfo on {topic} has zero focal length (K = {K[:1] + K[4:5]}): the camera is not calibrated; "
            "pass a calibration file with --camera FILE"
        )
    if width <= 0 or height <= 0:
        raise InputError(
            f"CameraInfo on {topic} has image size {width}x{height}; pass a calibration with --camera FILE"
        )
    model = info.distortion_model or ("plumb_bob" if D else "none")
    if not any(D):
        model = "none" if not D else model
    return CameraModel(
        width=width,
        height=height,
        K=K,
        distortion_model=model,
        D=D,
        frame_id=info.frame_id.lstrip("/"),
        topic=topic,
        source="camera_info",
    )


def odometry_row(msg: Any, stamp: int) -> dict[str, Any]:
    """One odometry sample (a row of ``odometry.parquet``): pose, twist and their covariances (ROS order x y z roll
    pitch yaw)."""
    p = msg.pose.pose.position
    q = msg.pose.pose.orientation
    v = msg.twist.twist.linear
    w = msg.twist.twist.angular
    return {
        STAMP_NS: stamp,
        **{c: float(value) for c, value in zip(POSITION, (p.x, p.y, p.z), strict=True)},
        **{c: float(value) for c, value in zip(QUATERNION, (q.x, q.y, q.z, q.w), strict=True)},
        **{c: float(value) for c, value in zip(VELOCITY, (v.x, v.y, v.z, w.x, w.y, w.z), strict=True)},
        POSE_COV: [float(c) for c in np.asarray(msg.pose.covariance, dtype=float).ravel()],
        TWIST_COV: [float(c) for c in np.asarray(msg.twist.covariance, dtype=float).ravel()],
        FRAME_ID: frame_id(msg),
        CHILD_FRAME_ID: str(get(msg, "child_frame_id", default="")).lstrip("/"),
    }


def scan_row(msg: Any, stamp: int) -> dict[str, Any]:
    """One laser scan (a row of ``scans.parquet``)."""
    return {
        STAMP_NS: stamp,
        FRAME_ID: frame_id(msg),
        ANGLE_MIN: float(msg.angle_min),
        ANGLE_MAX: float(msg.angle_max),
        ANGLE_INCREMENT: float(msg.angle_increment),
        TIME_INCREMENT: float(msg.time_increment),
        SCAN_TIME: float(msg.scan_time),
        RANGE_MIN: float(msg.range_min),
        RANGE_MAX: float(msg.range_max),
        RANGES: np.asarray(msg.ranges, dtype=np.float32),
    }


def quat_to_matrix(x: float, y: float, z: float, w: float) -> np.ndarray:
    """Rotation matrix of a unit quaternion given as x, y, z, w (ROS order)."""
    n = np.sqrt(x * x + y * y + z * z + w * w)
    if n == 0:
        return np.eye(3)
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def transform_records(msg: Any) -> list[TransformRecord]:
    """The transforms of a decoded TFMessage."""
    out = []
    for tf in msg.transforms:
        t = tf.transform.translation
        r = tf.transform.rotation
        parent = str(get(get(tf, "header"), "frame_id", default="") or "")
        values = tuple(float(v) for v in (t.x, t.y, t.z, r.x, r.y, r.z, r.w))
        out.append(TransformRecord(parent, str(tf.child_frame_id), values))
    return out


def transform_edges(msg: Any) -> list[tuple[str, str, np.ndarray]]:
    """(parent, child, T_parent_child) of every transform in a TFMessage."""
    return edges_of(transform_records(msg))


def edges_of(transforms: list[TransformRecord]) -> list[tuple[str, str, np.ndarray]]:
    """(parent, child, T_parent_child) of every transform, frame names without a leading slash."""
    out = []
    for tf in transforms:
        tx, ty, tz, qx, qy, qz, qw = tf.values
        T = np.eye(4)
        T[:3, :3] = quat_to_matrix(qx, qy, qz, qw)
        T[:3, 3] = [tx, ty, tz]
        out.append((tf.parent.lstrip("/"), tf.child.lstrip("/"), T))
    return out


def chain(edges: list[tuple[str, str, np.ndarray]], source: str, target: str) -> np.ndarray | None:
    """T_source_target through the static transform tree (edges used in either direction), or None."""
    if source == target:
        return np.eye(4)
    adj: dict[str, list[tuple[str, np.ndarray]]] = {}
    for parent, child, T in edges:
        adj.setdefault(parent, []).append((child, T))
        adj.setdefault(child, []).append((parent, np.linalg.inv(T)))
    seen = {source}
    queue: deque[tuple[str, np.ndarray]] = deque([(source, np.eye(4))])
    while queue:
        node, T = queue.popleft()
        for nxt, T_step in adj.get(node, []):
            if nxt in seen:
                continue
            T_next = T @ T_step
            if nxt == target:
                return T_next
            seen.add(nxt)
            queue.append((nxt, T_next))
    return None


_TINY = 1e-300
"""Below this (and not zero), a covariance entry is a denormal: a damaged number, not a variance."""
_BYTES_PER_PIXEL = {"mono8": 1, "8UC1": 1, "mono16": 2, "16UC1": 2, "bgr8": 3, "rgb8": 3, "bgra8": 4, "rgba8": 4}


def _bad_covariance(values: list[float]) -> str | None:
    a = np.asarray(values, dtype=float)
    if not np.isfinite(a).all():
        return "a non-finite covariance"
    if ((a != 0) & (np.abs(a) < _TINY)).any():
        return "a denormal covariance"
    return None


def odometry_problem(row: dict[str, Any]) -> str | None:
    """Why an odometry row holds values no odometry gives (None when it is fine): a non-finite pose or twist, a
    non-finite or denormal covariance (exactly 0 is fine)."""
    if not np.isfinite([row[c] for c in (*POSITION, *QUATERNION, *VELOCITY)]).all():
        return "a non-finite pose or twist"
    return _bad_covariance(row[POSE_COV]) or _bad_covariance(row[TWIST_COV])


def scan_problem(row: dict[str, Any]) -> str | None:
    """Why a laser scan holds impossible values (None when it is fine). Following REP 117, +inf (no return),
    -inf (too close) and NaN (an erroneous reading) are legal ranges, and so is a range outside
    [range_min, range_max] (to be discarded by the reader); a negative finite range, non-finite limits or angles,
    or range_min > range_max are not."""
    limits = [row[c] for c in (ANGLE_MIN, ANGLE_MAX, ANGLE_INCREMENT, RANGE_MIN, RANGE_MAX)]
    if not np.isfinite(limits).all():
        return "non-finite angles or range limits"
    if row[RANGE_MIN] > row[RANGE_MAX]:
        return "range_min > range_max"
    with np.errstate(invalid="ignore"):  # a damaged float32 may be a signalling NaN: still a NaN range
        r = np.asarray(row[RANGES], dtype=float)
    if (np.isfinite(r) & (r < 0)).any():
        return "negative ranges"
    return None


def image_problem(row: dict[str, Any]) -> str | None:
    """Why a raw image's size does not match its data (None when it does, and for compressed images)."""
    if row[FORMAT] in ("jpeg", "png") or not row[HEIGHT]:
        return None
    h, w, step, n = row[HEIGHT], row[WIDTH], row[STEP], len(row[DATA])
    bpp = _BYTES_PER_PIXEL.get(row[FORMAT])
    if h < 0 or w <= 0 or step * h != n or (bpp is not None and step < w * bpp):
        return f"an image size that does not match its data ({w}x{h}, step {step}, {n} bytes)"
    return None


# records: the form the table writers take, made from a decoded message here or from the bytes (fast.py) --------
def odometry_record(msg: Any, fallback_ns: int) -> OdometryRecord:
    """The record of a decoded odometry message (the same values :func:`odometry_row` gives).

    Raises:
        InputError: a covariance that is not 6x6 (a message type that is not nav_msgs/Odometry).
    """
    row = odometry_row(msg, stamp_ns(msg, fallback_ns))
    if len(row[POSE_COV]) != 36 or len(row[TWIST_COV]) != 36:
        raise InputError(
            f"an odometry message has covariances of {len(row[POSE_COV])} and {len(row[TWIST_COV])} values, not 36"
        )
    values = np.array(
        [
            *(row[c] for c in (*POSITION, *QUATERNION)),
            *row[POSE_COV],
            *(row[c] for c in VELOCITY),
            *row[TWIST_COV],
        ],
        dtype=np.float64,
    )
    return OdometryRecord(row[STAMP_NS], row[FRAME_ID], row[CHILD_FRAME_ID], values)


def odometry_record_row(rec: OdometryRecord) -> dict[str, Any]:
    """The ``odometry.parquet`` row of a record."""
    v = [float(x) for x in rec.values]
    return {
        STAMP_NS: rec.stamp_ns,
        **dict(zip((*POSITION, *QUATERNION), v[0:7], strict=True)),
        POSE_COV: v[7:43],
        **dict(zip(VELOCITY, v[43:49], strict=True)),
        TWIST_COV: v[49:85],
        FRAME_ID: rec.frame_id,
        CHILD_FRAME_ID: rec.child_frame_id,
    }


def odometry_values_fine(values: np.ndarray) -> np.ndarray:
    """Per row of odometry values (:attr:`OdometryRecord.values`, one row or many), whether
    :func:`odometry_problem` has nothing to say: every value finite, and none denormal."""
    a = np.abs(values)
    return ((a < np.inf) & ((a >= _TINY) | (a == 0))).all(axis=-1)


def odometry_record_problem(rec: OdometryRecord) -> str | None:
    """:func:`odometry_problem` of a record: a vectorised pass for the messages that are fine, the reason for
    the others."""
    return None if odometry_values_fine(rec.values) else odometry_problem(odometry_record_row(rec))


_SCAN_LIMIT_COLUMNS = (ANGLE_MIN, ANGLE_MAX, ANGLE_INCREMENT, TIME_INCREMENT, SCAN_TIME, RANGE_MIN, RANGE_MAX)


def scan_record(msg: Any, fallback_ns: int) -> ScanRecord:
    """The record of a decoded laser scan (the same values :func:`scan_row` gives)."""
    row = scan_row(msg, stamp_ns(msg, fallback_ns))
    return ScanRecord(row[STAMP_NS], row[FRAME_ID], tuple(row[c] for c in _SCAN_LIMIT_COLUMNS), row[RANGES])


def scan_record_row(rec: ScanRecord) -> dict[str, Any]:
    """The ``scans.parquet`` row of a record."""
    return {
        STAMP_NS: rec.stamp_ns,
        FRAME_ID: rec.frame_id,
        **dict(zip(_SCAN_LIMIT_COLUMNS, (float(x) for x in rec.limits), strict=True)),
        RANGES: rec.ranges,
    }


def scan_values_fine(limits: np.ndarray, ranges: np.ndarray) -> np.ndarray:
    """Per scan of many (limits (n, 7) as :attr:`ScanRecord.limits`, ranges (n, beams)), whether
    :func:`scan_problem` has nothing to say; a scan with a NaN range is left to it."""
    amin, amax, ainc, _, _, rmin, rmax = limits.T
    finite = np.isfinite(np.column_stack([amin, amax, ainc, rmin, rmax])).all(axis=1)
    return finite & (rmin <= rmax) & (ranges >= 0).all(axis=1)


def scan_record_problem(rec: ScanRecord) -> str | None:
    """:func:`scan_problem` of a record: a quick pass for the scans that are fine, the reason for the others."""
    amin, amax, ainc, _, _, rmin, rmax = rec.limits
    r = rec.ranges
    if (
        all(math.isfinite(x) for x in (amin, amax, ainc, rmin, rmax))
        and rmin <= rmax
        and (r.size == 0 or bool(r.min() >= 0))  # NaN or any negative range (-inf too): the full check
    ):
        return None
    return scan_problem(scan_record_row(rec))


def image_record(msg: Any, fallback_ns: int, compressed: bool) -> ImageRecord:
    """The record of a decoded CompressedImage (``format`` is its format field) or Image (its encoding)."""
    stamp, fid = stamp_ns(msg, fallback_ns), frame_id(msg)
    if compressed:
        return ImageRecord(stamp, fid, str(get(msg, "format", default="")), 0, 0, 0, as_bytes(msg.data))
    return ImageRecord(
        stamp, fid, str(msg.encoding), int(msg.width), int(msg.height), int(msg.step), as_bytes(msg.data)
    )


def image_record_row(rec: ImageRecord, compressed: bool) -> dict[str, Any]:
    """The stored form of an image (the image columns of ``frames.parquet``): compressed bytes as they are, raw
    pixels with their encoding."""
    if compressed:
        fmt = rec.format.lower()
        kind = "png" if "png" in fmt else "jpeg" if ("jpeg" in fmt or "jpg" in fmt) else fmt or "jpeg"
        return {FORMAT: kind, WIDTH: 0, HEIGHT: 0, STEP: 0, DATA: rec.data}
    return {FORMAT: rec.format, WIDTH: rec.width, HEIGHT: rec.height, STEP: rec.step, DATA: rec.data}
