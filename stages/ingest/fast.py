"""Raw field extraction for the few message types ingest reads in bulk: odometry, laser scans and images.

A generic deserializer builds a Python object per message, field by field; ingest keeps a handful of fields
of four types, whose byte layouts are fixed. Here those fields are read straight from the serialized bytes
(ROS 1 or little-endian CDR) into the records the tables are made of.

Each parser accepts only what the generic deserializers accept too: every field is bounds-checked, strings
must decode as UTF-8 (and in CDR end with their terminator), and the message must end where its last field
ends (CDR: up to 3 bytes of padding after it). Anything else returns None, and the caller decodes the
message the generic way, which then decodes it or raises the error it always raised.

A parser is used for a topic only when the type the generic decoder would use has the standard layout
(:func:`layout` of the decoder's type definitions equals :data:`LAYOUTS`); where the decoder's definitions
are not at hand (the mcap library's), the topic's first message is decoded both ways and compared (see
:class:`stages.ingest.stage._Reading`). A recording whose types differ from the standard ones is read as
before.
"""

from __future__ import annotations

import struct
from typing import Any, NamedTuple

import numpy as np
from rosbags.typesys.base import Nodetype

_U32 = struct.Struct("<I")
_STAMP_ROS1 = struct.Struct("<IiI")  # seq, sec, nsec
_STAMP_CDR = struct.Struct("<iI")  # sec, nanosec
_SCAN_LIMITS = struct.Struct("<7f")
_IMAGE_SIZE = struct.Struct("<II")  # height, width
_IMAGE_STEP = struct.Struct("<BI")  # is_bigendian, step (ROS 1: packed)
_CDR_LE = b"\x00\x01"
_ODOM_DOUBLES = 85
"""Pose (position 3, orientation 4), its covariance (36), twist (linear 3, angular 3), its covariance (36)."""


def _header_layout(ros1: bool) -> list[str]:
    seq = ["header.seq:uint32"] if ros1 else []
    return [*seq, "header.stamp.sec:int32", "header.stamp.nanosec:uint32", "header.frame_id:string"]


def _xyz(path: str, axes: str = "xyz") -> list[str]:
    return [f"{path}.{a}:float64" for a in axes]


def _layouts(ros1: bool) -> dict[str, list[str]]:
    header = _header_layout(ros1)
    scan = ["angle_min", "angle_max", "angle_increment", "time_increment", "scan_time", "range_min", "range_max"]
    return {
        "nav_msgs/msg/Odometry": [
            *header,
            "child_frame_id:string",
            *_xyz("pose.pose.position"),
            *_xyz("pose.pose.orientation", "xyzw"),
            "pose.covariance:float64[36]",
            *_xyz("twist.twist.linear"),
            *_xyz("twist.twist.angular"),
            "twist.covariance:float64[36]",
        ],
        "sensor_msgs/msg/LaserScan": [
            *header,
            *(f"{f}:float32" for f in scan),
            "ranges:float32[]",
            "intensities:float32[]",
        ],
        "sensor_msgs/msg/CompressedImage": [*header, "format:string", "data:uint8[]"],
        "tf2_msgs/msg/TFMessage": [
            "transforms:[]",
            *(f"transforms[].{f}" for f in header),
            "transforms[].child_frame_id:string",
            *_xyz("transforms[].transform.translation"),
            *_xyz("transforms[].transform.rotation", "xyzw"),
        ],
        "sensor_msgs/msg/CameraInfo": [
            *header,
            "height:uint32",
            "width:uint32",
            "distortion_model:string",
            *(f"{m.upper() if ros1 else m}:float64[{n}]" for m, n in (("d", ""), ("k", 9), ("r", 9), ("p", 12))),
            "binning_x:uint32",
            "binning_y:uint32",
            *(f"roi.{f}:uint32" for f in ("x_offset", "y_offset", "height", "width")),
            "roi.do_rectify:bool",
        ],
        "sensor_msgs/msg/Image": [
            *header,
            "height:uint32",
            "width:uint32",
            "encoding:string",
            "is_bigendian:uint8",
            "step:uint32",
            "data:uint8[]",
        ],
    }


LAYOUTS: dict[bool, dict[str, list[str]]] = {True: _layouts(ros1=True), False: _layouts(ros1=False)}
"""By whether the recording is ROS 1: the standard layout (:func:`layout`) of each type the parsers read."""


def layout(typestore: Any, typename: str, prefix: str = "") -> list[str]:
    """The fields of ``typename`` in a rosbags type store, flattened in order: ``path:type`` (``type[n]`` for an
    array, ``type[]`` for a sequence, ``type[<=n]`` for a bounded one)."""
    out: list[str] = []
    for name, (kind, rest) in typestore.fielddefs[typename][1]:
        path = prefix + name
        if kind == Nodetype.NAME:
            out += layout(typestore, rest, path + ".")
        elif kind == Nodetype.BASE:
            out.append(f"{path}:{rest[0]}" + (f"<={rest[1]}" if rest[1] else ""))
        else:
            (sub_kind, sub), n = rest
            size = str(n) if kind == Nodetype.ARRAY else (f"<={n}" if n else "")
            if sub_kind == Nodetype.NAME:  # a list of messages: its length, then the fields of one
                out.append(f"{path}:[{size}]")
                out += layout(typestore, sub, f"{path}[].")
            else:
                out.append(f"{path}:{sub[0]}[{size}]")
    return out


def standard(typestore: Any, typename: str, ros1: bool) -> bool | None:
    """Whether ``typename`` has its standard layout in ``typestore`` (None: no type store, or a type no parser
    reads)."""
    want = LAYOUTS[ros1].get(typename)
    if typestore is None or want is None:
        return None
    try:
        return layout(typestore, typename) == want
    except (KeyError, TypeError, ValueError):
        return False


class OdometryRecord(NamedTuple):
    stamp_ns: int
    frame_id: str
    child_frame_id: str
    values: np.ndarray
    """float64 [x y z, qx qy qz qw, pose covariance 36, vx vy vz wx wy wz, twist covariance 36]."""


class ScanRecord(NamedTuple):
    stamp_ns: int
    frame_id: str
    limits: tuple[float, ...]
    """angle_min, angle_max, angle_increment, time_increment, scan_time, range_min, range_max."""
    ranges: np.ndarray
    """float32, as recorded."""


class ImageRecord(NamedTuple):
    stamp_ns: int
    frame_id: str
    format: str
    """CompressedImage: the format field as recorded; Image: the encoding."""
    width: int
    height: int
    step: int
    data: bytes


class _LayoutError(Exception):
    """The bytes are not what the parser reads: leave the message to the generic decoder."""


def _stamp(sec: int, nsec: int, fallback_ns: int) -> int:
    value = sec * 1_000_000_000 + nsec
    return value if value > 0 else fallback_ns


def _string(buf: bytes, pos: int, cdr: bool) -> tuple[str, int]:
    """A length-prefixed string at ``pos`` (aligned already) and the position after it."""
    if pos + 4 > len(buf):
        raise _LayoutError
    (n,) = _U32.unpack_from(buf, pos)
    end = pos + 4 + n
    if end > len(buf):
        raise _LayoutError
    if cdr:
        if n < 1 or buf[end - 1] != 0:
            raise _LayoutError
        raw = buf[pos + 4 : end - 1]
    else:
        raw = buf[pos + 4 : end]
    try:
        return bytes(raw).decode(), end
    except UnicodeDecodeError:
        raise _LayoutError from None


def _align(pos: int, n: int) -> int:
    """``pos`` in a CDR body (after the 4-byte encapsulation header) moved up to a multiple of ``n``."""
    return 4 + (-(-(pos - 4) // n) * n)


def _start(buf: bytes, cdr: bool) -> int:
    """Where the message's fields start: after CDR's encapsulation header (little-endian CDR only)."""
    if not cdr:
        return 0
    if len(buf) < 4 or buf[:2] != _CDR_LE:
        raise _LayoutError
    return 4


def _header_at(buf: bytes, pos: int, cdr: bool) -> tuple[int, int, str, int]:
    """(sec, nanosec, frame id as recorded, position after) of a std_msgs/Header at ``pos``."""
    if cdr:
        pos = _align(pos, 4)
        if pos + 8 > len(buf):
            raise _LayoutError
        sec, nsec = _STAMP_CDR.unpack_from(buf, pos)
        frame, pos = _string(buf, pos + 8, cdr)
    else:
        if pos + 12 > len(buf):
            raise _LayoutError
        _, sec, nsec = _STAMP_ROS1.unpack_from(buf, pos)
        frame, pos = _string(buf, pos + 12, cdr)
    return sec, nsec, frame, pos


def _header(buf: bytes, cdr: bool, fallback_ns: int) -> tuple[int, str, int]:
    """(stamp in ns, frame id without a leading slash, position after the header) of a message's header."""
    sec, nsec, frame, pos = _header_at(buf, _start(buf, cdr), cdr)
    return _stamp(sec, nsec, fallback_ns), frame.lstrip("/"), pos


def _ends(buf: bytes, pos: int, cdr: bool) -> None:
    """The message ends at ``pos`` (CDR: up to 3 bytes of padding follow)."""
    if pos > len(buf) or len(buf) - pos > (3 if cdr else 0):
        raise _LayoutError


def _sequence(buf: bytes, pos: int, cdr: bool, itemsize: int) -> tuple[int, int]:
    """(item count, position of the first item) of a sequence at ``pos``; its items fit in the buffer."""
    if cdr:
        pos = _align(pos, 4)
    if pos + 4 > len(buf):
        raise _LayoutError
    (n,) = _U32.unpack_from(buf, pos)
    pos += 4
    if pos + n * itemsize > len(buf):
        raise _LayoutError
    return n, pos


def _stamp_at(cdr: bool) -> int:
    """Where a message's header stamp starts: after ROS 1's seq, or after CDR's encapsulation header."""
    return 4


def _odometry_layout(buf: bytes, cdr: bool) -> tuple[str, str, int]:
    """(frame id, child frame id, position of the 85 doubles) of a nav_msgs/Odometry; raises ``_LayoutError``."""
    _, _, frame, pos = _header_at(buf, _start(buf, cdr), cdr)
    if cdr:
        pos = _align(pos, 4)
    child, pos = _string(buf, pos, cdr)
    if cdr:
        pos = _align(pos, 8)
    _ends(buf, pos + 8 * _ODOM_DOUBLES, cdr)
    return frame, child, pos


def odometry(buf: bytes, cdr: bool, fallback_ns: int) -> OdometryRecord | None:
    """A nav_msgs/Odometry message's record, or None when the generic decoder is to read it."""
    try:
        frame, child, pos = _odometry_layout(buf, cdr)
    except _LayoutError:
        return None
    sec, nsec = _STAMP_CDR.unpack_from(buf, _stamp_at(cdr))
    values = np.frombuffer(buf, dtype="<f8", count=_ODOM_DOUBLES, offset=pos).astype(np.float64)
    return OdometryRecord(_stamp(sec, nsec, fallback_ns), frame.lstrip("/"), child.lstrip("/"), values)


def _scan_layout(buf: bytes, cdr: bool) -> tuple[str, int, int, int, int]:
    """(frame id, position of the limits, number of ranges, position of the first range, position of the first
    intensity) of a sensor_msgs/LaserScan; raises ``_LayoutError``."""
    _, _, frame, pos = _header_at(buf, _start(buf, cdr), cdr)
    if cdr:
        pos = _align(pos, 4)
    if pos + _SCAN_LIMITS.size > len(buf):
        raise _LayoutError
    n, start = _sequence(buf, pos + _SCAN_LIMITS.size, cdr, 4)
    m, at = _sequence(buf, start + 4 * n, cdr, 4)  # intensities: read past, not kept
    _ends(buf, at + 4 * m, cdr)
    return frame, pos, n, start, at


def laser_scan(buf: bytes, cdr: bool, fallback_ns: int) -> ScanRecord | None:
    """A sensor_msgs/LaserScan message's record, or None when the generic decoder is to read it."""
    try:
        frame, limits_at, n, start, _ = _scan_layout(buf, cdr)
    except _LayoutError:
        return None
    sec, nsec = _STAMP_CDR.unpack_from(buf, _stamp_at(cdr))
    limits = _SCAN_LIMITS.unpack_from(buf, limits_at)
    ranges = np.frombuffer(buf, dtype="<f4", count=n, offset=start).astype(np.float32)
    return ScanRecord(_stamp(sec, nsec, fallback_ns), frame.lstrip("/"), limits, ranges)


class OdometryBatch(NamedTuple):
    """Many nav_msgs/Odometry messages of one layout, as columns."""

    stamps_ns: np.ndarray
    frame_id: str
    child_frame_id: str
    values: np.ndarray
    """float64 (n, 85), each row as :attr:`OdometryRecord.values`."""


class ScanBatch(NamedTuple):
    """Many sensor_msgs/LaserScan messages of one layout, as columns."""

    stamps_ns: np.ndarray
    frame_id: str
    limits: np.ndarray
    """float64 (n, 7), each row as :attr:`ScanRecord.limits`."""
    ranges: np.ndarray
    """float32 (n, beams), as recorded."""


def _rows(bufs: list[bytes], same: list[tuple[int, int]]) -> np.ndarray | None:
    """The messages as the rows of one byte matrix, when they are all as long as the first and equal to it on
    the byte ranges ``same`` (the fields that place every other field: string and sequence lengths, the
    strings, the padding); else None."""
    size = len(bufs[0])
    if any(len(b) != size for b in bufs):
        return None
    rows = np.frombuffer(b"".join(bufs), dtype=np.uint8).reshape(len(bufs), size)
    for a, b in same:
        if a < b and not (rows[:, a:b] == rows[0, a:b]).all():
            return None
    return rows


def _column(rows: np.ndarray, at: int, count: int, dtype: str) -> np.ndarray:
    """``count`` values of ``dtype`` at byte ``at`` of every row, as an (n, count) array."""
    width = np.dtype(dtype).itemsize * count
    return np.ascontiguousarray(rows[:, at : at + width]).view(dtype).reshape(len(rows), count)


def _stamps(rows: np.ndarray, cdr: bool, fallback_ns: np.ndarray) -> np.ndarray:
    """Every row's header stamp in ns, each as :func:`_stamp` gives it."""
    at = _stamp_at(cdr)
    sec = _column(rows, at, 1, "<i4")[:, 0].astype(np.int64)
    nsec = _column(rows, at + 4, 1, "<u4")[:, 0].astype(np.int64)
    value = sec * 1_000_000_000 + nsec
    return np.where(value > 0, value, fallback_ns)


def _constant(cdr: bool) -> list[tuple[int, int]]:
    """The leading bytes every message of a batch shares: CDR's encapsulation header (ROS 1's seq varies)."""
    return [(0, 4)] if cdr else []


def odometry_batch(bufs: list[bytes], cdr: bool, fallback_ns: np.ndarray) -> OdometryBatch | None:
    """Many nav_msgs/Odometry messages at once, each read as :func:`odometry` reads it, when they share the first
    one's layout (its length, frame ids and padding); None when they do not (read them one at a time)."""
    try:
        frame, child, pos = _odometry_layout(bufs[0], cdr)
    except _LayoutError:
        return None
    rows = _rows(bufs, [*_constant(cdr), (_stamp_at(cdr) + 8, pos)])
    if rows is None:
        return None
    values = _column(rows, pos, _ODOM_DOUBLES, "<f8").astype(np.float64)
    return OdometryBatch(_stamps(rows, cdr, fallback_ns), frame.lstrip("/"), child.lstrip("/"), values)


def scan_batch(bufs: list[bytes], cdr: bool, fallback_ns: np.ndarray) -> ScanBatch | None:
    """Many sensor_msgs/LaserScan messages at once, each read as :func:`laser_scan` reads it, when they share the
    first one's layout (its length, frame id, numbers of ranges and intensities); None when they do not."""
    try:
        frame, limits_at, n, start, at = _scan_layout(bufs[0], cdr)
    except _LayoutError:
        return None
    # the bytes that place the fields: the frame id, the ranges' count, the intensities' count (their values and
    # CDR's padding after them may differ)
    same = [
        *_constant(cdr),
        (_stamp_at(cdr) + 8, limits_at),
        (limits_at + _SCAN_LIMITS.size, start),
        (start + 4 * n, at),
    ]
    rows = _rows(bufs, same)
    if rows is None:
        return None
    limits = _column(rows, limits_at, 7, "<f4").astype(np.float64)
    ranges = _column(rows, start, n, "<f4").astype(np.float32)
    return ScanBatch(_stamps(rows, cdr, fallback_ns), frame.lstrip("/"), limits, ranges)


def compressed_image(buf: bytes, cdr: bool, fallback_ns: int) -> ImageRecord | None:
    """A sensor_msgs/CompressedImage message's record, or None when the generic decoder is to read it."""
    try:
        stamp, frame, pos = _header(buf, cdr, fallback_ns)
        if cdr:
            pos = _align(pos, 4)
        fmt, pos = _string(buf, pos, cdr)
        n, start = _sequence(buf, pos, cdr, 1)
        _ends(buf, start + n, cdr)
    except _LayoutError:
        return None
    return ImageRecord(stamp, frame, fmt, 0, 0, 0, bytes(buf[start : start + n]))


def image(buf: bytes, cdr: bool, fallback_ns: int) -> ImageRecord | None:
    """A sensor_msgs/Image message's record, or None when the generic decoder is to read it."""
    try:
        stamp, frame, pos = _header(buf, cdr, fallback_ns)
        if cdr:
            pos = _align(pos, 4)
        if pos + 8 > len(buf):
            raise _LayoutError
        height, width = _IMAGE_SIZE.unpack_from(buf, pos)
        encoding, pos = _string(buf, pos + 8, cdr)
        if cdr:  # is_bigendian (1 byte), then step aligned to 4
            if pos + 1 > len(buf):
                raise _LayoutError
            pos = _align(pos + 1, 4)
            if pos + 4 > len(buf):
                raise _LayoutError
            (step,) = _U32.unpack_from(buf, pos)
            pos += 4
        else:
            if pos + _IMAGE_STEP.size > len(buf):
                raise _LayoutError
            _, step = _IMAGE_STEP.unpack_from(buf, pos)
            pos += _IMAGE_STEP.size
        n, start = _sequence(buf, pos, cdr, 1)
        _ends(buf, start + n, cdr)
    except _LayoutError:
        return None
    return ImageRecord(stamp, frame, encoding, width, height, step, bytes(buf[start : start + n]))


class TransformRecord(NamedTuple):
    parent: str
    """The header's frame id, as recorded."""
    child: str
    values: tuple[float, ...]
    """tx, ty, tz, qx, qy, qz, qw."""


_TRANSFORM = struct.Struct("<7d")


def tf_message(buf: bytes, cdr: bool, fallback_ns: int) -> list[TransformRecord] | None:
    """The transforms of a tf2_msgs/TFMessage, or None when the generic decoder is to read it."""
    del fallback_ns  # the transforms' stamps are not kept
    try:
        n, pos = _sequence(buf, _start(buf, cdr), cdr, 1 if cdr else 0)
        out = []
        for _ in range(n):
            _, _, parent, pos = _header_at(buf, pos, cdr)
            if cdr:
                pos = _align(pos, 4)
            child, pos = _string(buf, pos, cdr)
            if cdr:
                pos = _align(pos, 8)
            if pos + _TRANSFORM.size > len(buf):
                raise _LayoutError
            out.append(TransformRecord(parent, child, _TRANSFORM.unpack_from(buf, pos)))
            pos += _TRANSFORM.size
        _ends(buf, pos, cdr)
    except _LayoutError:
        return None
    return out


class CameraInfoRecord(NamedTuple):
    """The fields of a CameraInfo that ingest keeps, by the names :func:`stages.ingest.convert.camera_from_info`
    reads (ROS 2's)."""

    frame_id: str
    """As recorded."""
    width: int
    height: int
    distortion_model: str
    d: np.ndarray
    k: np.ndarray


def camera_info(buf: bytes, cdr: bool, fallback_ns: int) -> CameraInfoRecord | None:
    """A sensor_msgs/CameraInfo message's calibration, or None when the generic decoder is to read it (also for an
    empty distortion vector, after which decoders differ on CDR's alignment)."""
    del fallback_ns
    try:
        _, _, frame, pos = _header_at(buf, _start(buf, cdr), cdr)
        if cdr:
            pos = _align(pos, 4)
        if pos + 8 > len(buf):
            raise _LayoutError
        height, width = _IMAGE_SIZE.unpack_from(buf, pos)
        model, pos = _string(buf, pos + 8, cdr)
        n, pos = _sequence(buf, pos, cdr, 8)
        if n == 0:
            raise _LayoutError
        if cdr:
            pos = _align(pos, 8)
        d_at, pos = pos, pos + 8 * n
        if cdr:
            pos = _align(pos, 8)
        k_at, pos = pos, pos + 8 * (9 + 9 + 12)  # K, R, P
        if cdr:
            pos = _align(pos, 4)
        pos += 4 * 6 + 1  # binning x and y, the region of interest (4 x uint32, bool)
        _ends(buf, pos, cdr)
    except _LayoutError:
        return None
    d = np.frombuffer(buf, dtype="<f8", count=n, offset=d_at).astype(np.float64)
    k = np.frombuffer(buf, dtype="<f8", count=9, offset=k_at).astype(np.float64)
    return CameraInfoRecord(frame, width, height, model, d, k)
