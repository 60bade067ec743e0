"""MCAP salvage and CRC checks on small multi-chunk files: every intact chunk is read, a damaged chunk is
named without --salvage and dropped with it, a cut keeps every whole record before the cut, and the
report says what was lost."""

from __future__ import annotations

import json
import shutil
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from mcap.data_stream import ReadDataStream
from mcap.reader import make_reader
from mcap.records import Chunk, Message
from mcap.stream_reader import breakup_chunk, get_chunk_data_stream
from mcap.writer import CompressionType, Writer

from pipeline.config import load_settings
from pipeline.errors import InputError
from pipeline.run_folder import RunFolder
from pipeline.runner import run_stage
from sample_data.simulate import SimConfig, simulate, write_bag
from stages import REGISTRY
from stages.ingest.bags import Recording

Key = tuple[str, int]  # (topic, log time): one message


def rechunk(src: Path, dst: Path, compression: CompressionType, chunk_size: int = 50_000) -> Path:
    """``src`` written again by the mcap writer with small chunks (and chunk CRCs, the writer's default)."""
    with src.open("rb") as fi, dst.open("wb") as fo:
        reader = make_reader(fi)
        header, summary = reader.get_header(), reader.get_summary()
        assert summary is not None
        writer = Writer(fo, chunk_size=chunk_size, compression=compression)
        writer.start(profile=header.profile, library=header.library)
        sids = {i: writer.register_schema(s.name, s.encoding, s.data) for i, s in summary.schemas.items()}
        cids = {
            i: writer.register_channel(c.topic, c.message_encoding, sids[c.schema_id], c.metadata)
            for i, c in summary.channels.items()
        }
        for meta in reader.iter_metadata():
            writer.add_metadata(meta.name, meta.metadata)
        for _s, channel, m in reader.iter_messages(log_time_order=False):
            writer.add_message(cids[channel.id], m.log_time, m.data, m.publish_time, m.sequence)
        writer.finish()
    return dst


def chunks_of(path: Path) -> list[tuple[int, int, list[tuple[Key, int]]]]:
    """(offset, end, [(message, end of its record in the file)]) of each chunk, from the summary's chunk index.
    Record ends are exact for uncompressed chunks only."""
    out = []
    with path.open("rb") as fh:
        summary = make_reader(fh).get_summary()
        assert summary is not None
        for ci in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
            fh.seek(ci.chunk_start_offset + 9)
            chunk = Chunk.read(ReadDataStream(fh))
            records_at = ci.chunk_start_offset + 9 + 8 + 8 + 8 + 4 + 4 + len(chunk.compression) + 8
            stream, size = get_chunk_data_stream(chunk)
            records = stream.read(size)
            ends, pos = [], 0
            while pos < size:
                pos += 9 + int.from_bytes(records[pos + 1 : pos + 9], "little")
                ends.append(records_at + pos)
            keys = [
                ((summary.channels[r.channel_id].topic, r.log_time), e)
                for r, e in zip(breakup_chunk(chunk), ends, strict=True)
                if isinstance(r, Message)
            ]
            out.append((ci.chunk_start_offset, ci.chunk_start_offset + ci.chunk_length, keys))
    return out


def read_all(path: Path, salvage: bool) -> tuple[Counter[Key], Recording]:
    with Recording(path, salvage=salvage) as rec:
        got = Counter((m.topic, m.log_time_ns) for m in rec.messages(rec.topics))
        counts = {t.name: t.count for t in rec.topics.values() if t.count}
    assert counts == dict(Counter(topic for topic, _ in got.elements()))
    return got, rec


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("mcap")
    rec = simulate(SimConfig(seed=5, path="corridor", duration_s=3.0, image_format="jpeg"))
    plain = write_bag(rec, root / "one_chunk.mcap", "mcap")
    folder = write_bag(rec, root / "ros2", "ros2-mcap")
    (inner,) = folder.glob("*.mcap")
    rechunk(inner, root / "tmp.mcap", CompressionType.ZSTD)
    shutil.move(root / "tmp.mcap", inner)
    return {
        "zstd": rechunk(plain, root / "zstd.mcap", CompressionType.ZSTD),
        "none": rechunk(plain, root / "none.mcap", CompressionType.NONE),
        "ros2": folder,
    }


@pytest.mark.parametrize("name", ["zstd", "none", "ros2"])
def test_intact_file_with_salvage_reads_what_a_normal_read_reads(files: dict[str, Path], name: str) -> None:
    normal, _ = read_all(files[name], salvage=False)
    salvaged, rec = read_all(files[name], salvage=True)
    assert salvaged == normal and sum(normal.values()) > 100
    report = rec.salvaged
    assert report is not None and report["stopped_at"] is None and report["lost"]["messages"] == 0
    assert report["chunks"] == report["chunks_total"] > 5 and report["crc_checked"]


@pytest.mark.parametrize("name", ["none", "zstd"])
def test_a_cut_keeps_every_intact_chunk_and_the_whole_records_of_the_cut_one(
    files: dict[str, Path], name: str, tmp_path: Path
) -> None:
    src = files[name]
    data = src.read_bytes()
    chunks = chunks_of(src)
    all_msgs, _ = read_all(src, salvage=False)
    rng = np.random.default_rng(7)
    cuts = sorted(int(c) for c in rng.integers(chunks[0][0] + 1, chunks[-1][1], size=12))
    for cut in cuts:
        bag = tmp_path / "cut.mcap"
        bag.write_bytes(data[:cut])
        with pytest.raises(InputError, match=r"truncated or damaged.*--salvage"):
            Recording(bag)
        got, rec = read_all(bag, salvage=True)
        whole = Counter(k for start, end, msgs in chunks if end <= cut for k, _ in msgs)
        cut_chunk = Counter(k for start, end, msgs in chunks if start < cut < end for k, _ in msgs)
        if name == "none":  # uncompressed: exactly the records that end before the cut
            whole += Counter(k for start, end, msgs in chunks if start < cut < end for k, e in msgs if e <= cut)
            assert got == whole, cut
        else:
            assert whole <= got <= whole + cut_chunk, cut
        assert got <= all_msgs
        report = rec.salvaged
        assert report is not None and f"cut at byte {cut}" in report["stopped_at"]
        lost = report["lost"]
        assert lost["messages"] is None and lost["end_s"] is None  # the cut took the summary: the rest is unknown
        if got:
            t0 = min(t for _, t in all_msgs)
            assert lost["start_s"] == pytest.approx((max(t for _, t in got) - t0) * 1e-9, abs=1e-3)


def test_a_flipped_byte_in_a_chunk_is_named_and_only_that_chunk_dropped(files: dict[str, Path], tmp_path: Path) -> None:
    src = files["zstd"]
    data = src.read_bytes()
    chunks = chunks_of(src)
    all_msgs, _ = read_all(src, salvage=False)
    t0 = min(t for _, t in all_msgs)
    for start, end, msgs in (chunks[1], chunks[len(chunks) // 2], chunks[-1]):
        flipped = bytearray(data)
        flipped[(start + end) // 2] ^= 0x04
        bag = tmp_path / "flip.mcap"
        bag.write_bytes(bytes(flipped))
        with pytest.raises(InputError, match=rf"'.*flip.mcap' is damaged: the chunk at byte {start} .*--salvage"):
            read_all(bag, salvage=False)
        got, rec = read_all(bag, salvage=True)
        dropped = Counter(k for k, _ in msgs)
        assert got == all_msgs - dropped
        report = rec.salvaged
        assert report is not None and f"chunk at byte {start} " in report["stopped_at"]
        assert report["chunks"] == len(chunks) - 1
        lost = report["lost"]
        assert lost["topics"] == dict(sorted(Counter(topic for topic, _ in dropped.elements()).items()))
        stamps = [t for _, t in dropped]
        assert lost["start_s"] == pytest.approx((min(stamps) - t0) * 1e-9, abs=1e-3)
        assert lost["end_s"] == pytest.approx((max(stamps) - t0) * 1e-9, abs=1e-3)


def test_ingest_of_a_damaged_ros2_mcap_folder_reports_the_loss(files: dict[str, Path], tmp_path: Path) -> None:
    folder = tmp_path / "ros2"
    shutil.copytree(files["ros2"], folder)
    (inner,) = folder.glob("*.mcap")
    start, end, msgs = chunks_of(inner)[3]
    data = bytearray(inner.read_bytes())
    data[(start + end) // 2] ^= 0x01
    inner.write_bytes(bytes(data))
    settings = load_settings(REGISTRY.models(), None, [])
    with pytest.raises(InputError, match=rf"chunk at byte {start} .*--salvage"):
        run_stage(RunFolder.create(tmp_path / "a", folder), REGISTRY, "ingest", settings)
    run = RunFolder.create(tmp_path / "b", folder)
    run_stage(run, REGISTRY, "ingest", load_settings(REGISTRY.models(), None, ["ingest.salvage=true"]))
    summary = json.loads((run.stage_dir("ingest") / "summary.json").read_text())
    lost = summary["salvaged"]["lost"]
    assert lost["messages"] == len(msgs) and summary["reader"] == "mcap"
    images = sum(1 for (topic, _), _e in msgs if topic == "/camera/image_raw/compressed")
    normal, _ = read_all(files["ros2"], salvage=False)
    assert summary["frames"] == sum(n for (t, _), n in normal.items() if t == "/camera/image_raw/compressed") - images
