"""Streaming writers of ingest's tables: rows are gathered as columns and written in row groups.

Odometry and scans arrive as records of arrays (:mod:`stages.ingest.fast`); they go into Arrow arrays
whole (no Python row per message). The Parquet files keep zstd compression; dictionary encoding is used
for the text columns only (on ranges, covariances and image bytes it costs time and makes files larger).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, Generic, TypeVar, cast

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from pipeline.artifacts import StageOutput
from pipeline.contracts import TableSpec
from stages.columns import FRAME_ID, POSITION, QUATERNION, STAMP_NS
from stages.ingest.artifacts import (
    ANGLE_INCREMENT,
    ANGLE_MAX,
    ANGLE_MIN,
    CHILD_FRAME_ID,
    ODOMETRY,
    POSE_COV,
    RANGE_MAX,
    RANGE_MIN,
    RANGES,
    SCAN_TIME,
    SCANS,
    TIME_INCREMENT,
    TWIST_COV,
    VELOCITY,
)
from stages.ingest.fast import OdometryBatch, OdometryRecord, ScanBatch, ScanRecord

_ODOMETRY_SLICES: tuple[tuple[str, int], ...] = (
    *((c, i) for i, c in enumerate(POSITION)),
    *((c, 3 + i) for i, c in enumerate(QUATERNION)),
    *((c, 43 + i) for i, c in enumerate(VELOCITY)),
)
"""Scalar odometry columns and their index in :attr:`OdometryRecord.values` (covariances: 7:43 and 49:85)."""
T = TypeVar("T")

_SCAN_LIMITS = (ANGLE_MIN, ANGLE_MAX, ANGLE_INCREMENT, TIME_INCREMENT, SCAN_TIME, RANGE_MIN, RANGE_MAX)
"""The columns of :attr:`ScanRecord.limits`, in its order."""


def parquet_writer(spec: TableSpec, path: Path, stored: tuple[str, ...] = ()) -> pq.ParquetWriter:
    """A streaming writer of ``spec``'s schema: zstd, dictionaries for the text columns only.

    ``stored``: top-level columns written without compression (JPEG or PNG bytes, which zstd cannot shrink:
    3 % smaller files for 3 times the time to write and read them).
    """
    text: Any = [str(c) for c in spec.columns if pa.types.is_string(c.type)] or False  # a list: those columns
    compression: Any = "zstd"
    if stored:  # by column (only top-level columns can be named: keep it to tables of plain columns)
        assert all(not pa.types.is_nested(c.type) for c in spec.columns), spec.file
        compression = {n: "none" if n in stored else "zstd" for n in spec.names}
    return pq.ParquetWriter(path, spec.schema, compression=compression, use_dictionary=text)


class TableWriter(Generic[T]):
    """Items (rows, or records) of a declared table, written in row groups of ``batch`` items.

    ``weight`` and ``max_bytes``: a row group also ends once its items' weights (e.g. an image's bytes) reach
    ``max_bytes``. Readers hold a whole row group at a time, so raw camera frames (0.9 MB each at 640x480 bgr8)
    would otherwise make row groups of hundreds of megabytes.
    """

    def __init__(
        self,
        out: StageOutput,
        spec: TableSpec,
        batch: int,
        table: Callable[[list[T]], pa.Table] | None = None,
        stored: tuple[str, ...] = (),
        weight: Callable[[T], int] | None = None,
        max_bytes: int = 0,
    ) -> None:
        self.spec, self.batch = spec, batch
        self.weight, self.max_bytes = weight, max_bytes
        self.items: list[T] = []
        self.bytes = 0
        self.count = 0
        self.writer = parquet_writer(spec, out.file(spec.file), stored)
        self._table: Callable[[list[T]], pa.Table] = table or spec.table  # type: ignore[assignment]

    def add_table(self, table: pa.Table) -> None:
        """Rows already in a table of the declared schema, after the items added before them."""
        self.flush()
        self.writer.write_table(table)
        self.count += table.num_rows

    def add(self, item: T) -> None:
        self.items.append(item)
        self.count += 1
        if self.weight is not None:
            self.bytes += self.weight(item)
        if len(self.items) >= self.batch or (self.max_bytes and self.bytes >= self.max_bytes):
            self.flush()

    def flush(self) -> None:
        if self.items:
            self.writer.write_table(self._table(self.items))
            self.items, self.bytes = [], 0

    def close(self) -> None:
        self.flush()
        self.writer.close()


def _fixed_lists(values: np.ndarray, size: int) -> pa.Array:
    return pa.FixedSizeListArray.from_arrays(pa.array(np.ascontiguousarray(values).ravel()), size)


def odometry_table(records: list[OdometryRecord]) -> pa.Table:
    """The rows of ``odometry.parquet`` for ``records``."""
    return odometry_columns(
        np.array([r.stamp_ns for r in records], dtype=np.int64),
        np.stack([r.values for r in records]),
        [r.frame_id for r in records],
        [r.child_frame_id for r in records],
    )


def odometry_batch_table(batch: OdometryBatch) -> pa.Table:
    """The rows of ``odometry.parquet`` for a batch of messages of one layout."""
    n = len(batch.stamps_ns)
    return odometry_columns(batch.stamps_ns, batch.values, [batch.frame_id] * n, [batch.child_frame_id] * n)


def odometry_columns(stamps: np.ndarray, v: np.ndarray, frames: list[str], children: list[str]) -> pa.Table:
    """The rows of ``odometry.parquet``: stamps (ns), values (n, 85) as :attr:`OdometryRecord.values`, frame ids."""
    columns: dict[str, Any] = {STAMP_NS: stamps.astype(np.int64, copy=False)}
    columns.update({c: v[:, i] for c, i in _ODOMETRY_SLICES})
    columns[POSE_COV] = _fixed_lists(v[:, 7:43], 36)
    columns[TWIST_COV] = _fixed_lists(v[:, 49:85], 36)
    columns[FRAME_ID] = frames
    columns[CHILD_FRAME_ID] = children
    return ODOMETRY.table(columns)


def scan_table(records: list[ScanRecord]) -> pa.Table:
    """The rows of ``scans.parquet`` for ``records``."""
    limits = np.array([r.limits for r in records], dtype=np.float64).reshape(len(records), len(_SCAN_LIMITS))
    offsets = np.zeros(len(records) + 1, dtype=np.int32)
    np.cumsum([len(r.ranges) for r in records], out=offsets[1:])
    values = np.concatenate([r.ranges for r in records]).astype(np.float32, copy=False)
    return scan_columns([r.stamp_ns for r in records], [r.frame_id for r in records], limits, offsets, values)


def scan_batch_table(batch: ScanBatch) -> pa.Table:
    """The rows of ``scans.parquet`` for a batch of scans of one layout."""
    n, beams = batch.ranges.shape
    offsets = np.arange(n + 1, dtype=np.int32) * beams
    return scan_columns(batch.stamps_ns, [batch.frame_id] * n, batch.limits, offsets, batch.ranges.ravel())


def scan_columns(
    stamps: Any, frames: list[str], limits: np.ndarray, offsets: np.ndarray, values: np.ndarray
) -> pa.Table:
    """The rows of ``scans.parquet``: stamps (ns), frame ids, limits (n, 7), and every scan's ranges as list
    offsets into ``values`` (float32)."""
    columns: dict[str, Any] = {
        STAMP_NS: np.asarray(stamps, dtype=np.int64),
        FRAME_ID: frames,
        **{c: limits[:, i] for i, c in enumerate(_SCAN_LIMITS)},
        RANGES: pa.ListArray.from_arrays(cast(Any, pa.array(offsets)), cast(Any, pa.array(values))),
    }
    return SCANS.table(columns)
