"""Ingest's raw field extraction (stages/ingest/fast.py) against the generic decoders it stands in for.

On generated ROS 1, ROS 2 SQLite and standalone MCAP recordings: every parser gives the record the generic
decoding gives, bit for bit; a damaged message (cut, padded, bytes overwritten) is either left to the
generic decoder or read exactly as that decoder reads it (but for the bits of a signalling NaN, which the
mcap library quiets), never read where the decoder would refuse it;
and a type whose layout is not the standard one is not read by a parser at all.
"""

from __future__ import annotations

import dataclasses
import struct
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from pipeline.errors import InputError
from sample_data.simulate import SimConfig, simulate, write_bag
from stages.ingest import convert, fast
from stages.ingest.bags import RawMessage, Recording

Format = Literal["ros1", "ros2-sqlite", "ros2-mcap", "mcap"]
PARSERS: dict[str, tuple[Callable[[bytes, bool, int], Any], Callable[[Any, int], Any]]] = {
    "nav_msgs/msg/Odometry": (fast.odometry, convert.odometry_record),
    "sensor_msgs/msg/LaserScan": (fast.laser_scan, convert.scan_record),
    "sensor_msgs/msg/CompressedImage": (fast.compressed_image, lambda m, t: convert.image_record(m, t, True)),
    "sensor_msgs/msg/Image": (fast.image, lambda m, t: convert.image_record(m, t, False)),
    "sensor_msgs/msg/CameraInfo": (fast.camera_info, lambda m, _t: convert.camera_info_record(m)),
    "tf2_msgs/msg/TFMessage": (fast.tf_message, lambda m, _t: convert.transform_records(m)),
}


def _canon(x: Any, nan_bits: bool = True) -> Any:
    """A comparable form: floats and arrays by their bits (``nan_bits=False``: every NaN alike)."""
    if isinstance(x, np.ndarray):
        if not nan_bits and x.dtype.kind == "f":
            x = np.where(np.isnan(x), np.nan, x).astype(x.dtype)
        return ("array", str(x.dtype), x.shape, x.tobytes())
    if isinstance(x, float):
        return ("float", struct.pack("<d", x))
    if isinstance(x, tuple | list):
        return tuple(_canon(v, nan_bits) for v in x)
    return x


@pytest.fixture(scope="module")
def samples(tmp_path_factory: pytest.TempPathFactory) -> Iterator[list[tuple[str, RawMessage, Any]]]:
    """(format, message, the decoder's type store) for the first messages of every topic of four recordings
    (kept open: a message decodes while its recording is open)."""
    root = tmp_path_factory.mktemp("fast")
    out: list[tuple[str, RawMessage, Any]] = []
    cases: list[tuple[Literal["jpeg", "mono8"], Format]] = [
        ("jpeg", "ros1"),
        ("jpeg", "mcap"),
        ("mono8", "ros1"),
        ("mono8", "ros2-sqlite"),
    ]
    with ExitStack() as stack:
        for image_format, fmt in cases:
            recording = simulate(SimConfig(seed=7, path="corridor", duration_s=1.0, image_format=image_format))
            suffix = {"ros1": ".bag", "mcap": ".mcap"}.get(fmt, "")
            rec = stack.enter_context(Recording(write_bag(recording, root / f"{image_format}_{fmt}{suffix}", fmt)))
            seen: dict[str, int] = {}
            for raw in rec.messages(rec.topics):
                if seen.get(raw.topic, 0) < 2:
                    out.append((fmt, raw, rec.typestore))
                seen[raw.topic] = seen.get(raw.topic, 0) + 1
        assert {raw.type for _, raw, _ in out} == set(PARSERS)
        yield out


def test_every_parser_gives_the_generic_decoding_bit_for_bit(samples) -> None:
    for fmt, raw, _ in samples:
        parse, generic = PARSERS[raw.type]
        quick = parse(raw.data, fmt != "ros1", raw.log_time_ns)
        assert quick is not None, (fmt, raw.type)
        assert _canon(quick) == _canon(generic(raw.decode(), raw.log_time_ns)), (fmt, raw.type)


def _damaged(data: bytes, rng: np.random.Generator) -> list[bytes]:
    n = len(data)
    cuts = [data[:k] for k in sorted({0, 1, 3, 4, 5, 11, 12, 16, n // 2, n - 4, n - 1}) if 0 <= k < n]
    pads = [data + b"\0" * k for k in (1, 3, 4, 8)]
    hits = []
    for pos in rng.integers(0, n, size=40):
        b = bytearray(data)
        b[pos] = 0xFF if b[pos] != 0xFF else 0x7F
        hits.append(bytes(b))
    return cuts + pads + hits


def test_a_damaged_message_is_left_to_the_decoder_or_read_as_it_reads_it(samples) -> None:
    rng = np.random.default_rng(1)
    read = left = 0
    for fmt, raw, _ in samples:
        parse, generic = PARSERS[raw.type]
        for data in _damaged(raw.data, rng):
            quick = parse(data, fmt != "ros1", raw.log_time_ns)
            if quick is None:
                left += 1
                continue
            read += 1
            try:
                decoded = dataclasses.replace(raw, data=data).decode()
            except InputError as err:
                pytest.fail(f"{fmt} {raw.type}: read from {len(data)} bytes the decoder refuses ({err})")
            # the mcap library reads float32 through Python floats, which quiets a signalling NaN (a damaged
            # range); the parsers keep a NaN's bits as recorded, as rosbags does
            nan_bits = fmt != "mcap"
            assert _canon(quick, nan_bits) == _canon(generic(decoded, raw.log_time_ns), nan_bits), (fmt, raw.type)
    assert read and left  # both outcomes met: the damage reached the fields read and the checks


def test_only_types_of_the_standard_layout_are_read_by_a_parser(samples) -> None:
    for fmt, raw, store in samples:
        if store is not None:  # the mcap library decodes the standalone file: checked on its first message
            assert fast.standard(store, raw.type, ros1=fmt == "ros1") is True, (fmt, raw.type)
            assert fast.standard(store, raw.type, ros1=fmt != "ros1") is False, (fmt, raw.type)
    latest = get_typestore(Stores.LATEST)
    consts, fields = latest.fielddefs["nav_msgs/msg/Odometry"]
    for changed in (fields[:-1], [*fields, ("extra", fields[1][1])], [fields[1], fields[0], *fields[2:]]):
        store = get_typestore(Stores.EMPTY)
        store.register({**latest.fielddefs, "nav_msgs/msg/Odometry": (consts, changed)})
        assert fast.standard(store, "nav_msgs/msg/Odometry", ros1=False) is False
    assert fast.standard(latest, "std_msgs/msg/String", ros1=False) is None  # no parser: the decoder reads it
    assert fast.standard(None, "nav_msgs/msg/Odometry", ros1=False) is None


def _odometry_after_ingest(bag: Path, out: Path) -> Any:
    import pyarrow.parquet as pq

    from pipeline.config import load_settings
    from pipeline.run_folder import RunFolder
    from pipeline.runner import run_stage
    from stages import REGISTRY

    run = RunFolder.create(out, bag)
    run_stage(run, REGISTRY, "ingest", load_settings(REGISTRY.models()), force=True)
    return pq.read_table(run.stage_dir("ingest") / "odometry.parquet")


@pytest.mark.parametrize("fmt", ["ros1", "mcap"])
def test_a_parser_is_not_trusted_where_the_layout_is_not_known_to_be_standard(
    fmt: Format, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An odometry parser that reads wrong values: with the type store's layout not the standard one (ROS 1),
    or without a type store and a first message that disagrees (MCAP), ingest reads the generic way."""
    recording = simulate(SimConfig(seed=7, path="corridor", duration_s=1.0, image_format="jpeg"))
    bag = write_bag(recording, tmp_path / ("bag.bag" if fmt == "ros1" else "bag.mcap"), fmt)
    expected = _odometry_after_ingest(bag, tmp_path / "a")
    right = fast.odometry

    def wrong(buf: bytes, cdr: bool, fallback_ns: int) -> fast.OdometryRecord | None:
        rec = right(buf, cdr, fallback_ns)
        return None if rec is None else rec._replace(values=rec.values + 1.0)

    right_batch = fast.odometry_batch

    def wrong_batch(bufs: list[bytes], cdr: bool, fallback_ns: np.ndarray) -> fast.OdometryBatch | None:
        batch = right_batch(bufs, cdr, fallback_ns)
        return None if batch is None else batch._replace(values=batch.values + 1.0)

    monkeypatch.setattr(fast, "odometry", wrong)
    monkeypatch.setattr(fast, "odometry_batch", wrong_batch)
    if fmt == "ros1":  # the trusted path: the parser is used as long as the layout is the standard one
        assert not _odometry_after_ingest(bag, tmp_path / "b").equals(expected)
        layouts = {**fast.LAYOUTS[True], "nav_msgs/msg/Odometry": [*fast.LAYOUTS[True]["nav_msgs/msg/Odometry"], "x"]}
        monkeypatch.setitem(fast.LAYOUTS, True, layouts)
    assert _odometry_after_ingest(bag, tmp_path / "c").equals(expected)


BATCHES: dict[str, tuple[Callable[[list[bytes], bool, np.ndarray], Any], Callable[[bytes, bool, int], Any]]] = {
    "nav_msgs/msg/Odometry": (fast.odometry_batch, fast.odometry),
    "sensor_msgs/msg/LaserScan": (fast.scan_batch, fast.laser_scan),
}


@pytest.mark.parametrize("fmt", ["ros1", "ros2-sqlite", "mcap"])
def test_a_batch_reads_every_message_as_its_parser_does_or_declines(fmt: Format, tmp_path: Path) -> None:
    """Every odometry and scan message of a recording read as one batch gives, row by row, the record the
    one-message parser gives (stamps, frame ids, values bit for bit); a batch whose messages differ in length or
    in the bytes that place the fields (a frame id) is declined, to be read one message at a time."""
    recording = simulate(SimConfig(seed=5, path="corridor", duration_s=2.0, image_format="jpeg"))
    suffix = {"ros1": ".bag", "mcap": ".mcap"}.get(fmt, "")
    cdr = fmt != "ros1"
    with Recording(write_bag(recording, tmp_path / f"b{suffix}", fmt)) as rec:
        by_type: dict[str, list[RawMessage]] = {}
        for raw in rec.messages(rec.topics):
            if raw.type in BATCHES:
                by_type.setdefault(raw.type, []).append(raw)
    assert set(by_type) == set(BATCHES)
    for typename, raws in by_type.items():
        batch_of, one = BATCHES[typename]
        data = [r.data for r in raws]
        stamps = np.array([r.log_time_ns for r in raws], dtype=np.int64)
        batch = batch_of(data, cdr, stamps)
        assert batch is not None and len(batch.stamps_ns) == len(raws) > 10, typename
        for i, raw in enumerate(raws):
            record = one(raw.data, cdr, raw.log_time_ns)
            assert batch.stamps_ns[i] == record.stamp_ns and batch.frame_id == record.frame_id
            if typename == "nav_msgs/msg/Odometry":
                assert batch.child_frame_id == record.child_frame_id
                assert batch.values[i].tobytes() == record.values.tobytes()
            else:
                assert _canon(tuple(float(x) for x in batch.limits[i])) == _canon(record.limits)
                assert batch.ranges[i].tobytes() == record.ranges.tobytes()
        # a zero stamp falls back to the log time, as in the one-message parser
        zeroed = bytearray(data[0])
        zeroed[4:12] = bytes(8)
        assert batch_of([bytes(zeroed), *data[1:]], cdr, stamps).stamps_ns[0] == stamps[0]
        # the frame id's last letter changed in one message: same length, other field bytes: declined
        frame = batch.frame_id.encode()
        at = data[3].index(frame) + len(frame) - 1
        renamed = bytearray(data[3])
        renamed[at] = ord("Q")
        assert batch_of([*data[:3], bytes(renamed), *data[4:]], cdr, stamps) is None
        assert batch_of([*data[:3], data[3] + bytes(4), *data[4:]], cdr, stamps) is None  # another length
        assert batch_of([data[0][:-8], *data[1:]], cdr, stamps) is None  # the first one cut: not its layout
