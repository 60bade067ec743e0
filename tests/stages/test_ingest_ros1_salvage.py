"""ROS 1 salvage on real multi-chunk bags (plain, bz2, lz4) damaged on purpose: every intact chunk is read, a
damaged chunk or header is skipped and the scan goes on, a damaged length is read around, and the report says
what was lost per topic and in time. Without --salvage, the damage is one error naming its byte offset."""

from __future__ import annotations

import json
import struct
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest

from pipeline.errors import InputError
from sample_data.simulate import SimConfig, simulate, write_bag
from stages.ingest.bags import Recording
from tests.fixtures.bags import rewrite_ros1, ros1_chunks

Key = tuple[str, int]  # (topic, log time): one message
ROOT = Path(__file__).resolve().parents[2]
FORMATS = ("plain", "bz2", "lz4")


@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("ros1")
    src = write_bag(
        simulate(SimConfig(seed=3, path="corridor", duration_s=4.0, image_format="jpeg")), root / "s.bag", "ros1"
    )
    return {c: rewrite_ros1(src, root / f"{c}.bag", None if c == "plain" else c) for c in FORMATS}


def read_all(path: Path, salvage: bool) -> tuple[Counter[Key], dict | None]:
    with Recording(path, salvage=salvage) as rec:
        got = Counter((m.topic, m.log_time_ns) for m in rec.messages(rec.topics))
        counts = {t.name: t.count for t in rec.topics.values() if t.count}
    assert counts == dict(Counter(topic for topic, _ in got.elements()))  # the topic counts are what was read
    return got, rec.salvaged


def damaged(src: Path, dst: Path, at: int, mask: int) -> Path:
    data = bytearray(src.read_bytes())
    data[at] ^= mask
    dst.write_bytes(bytes(data))
    return dst


def per_topic(keys: list[Key]) -> dict[str, int]:
    return dict(sorted(Counter(t for t, _ in keys).items()))


@pytest.mark.parametrize("fmt", FORMATS)
def test_intact_bag_with_salvage_reads_what_a_normal_read_reads(bags: dict[str, Path], fmt: str) -> None:
    normal, _ = read_all(bags[fmt], salvage=False)
    salvaged, report = read_all(bags[fmt], salvage=True)
    assert salvaged == normal and sum(normal.values()) > 100
    assert report is not None and report["chunks"] == report["chunks_total"] == len(ros1_chunks(bags[fmt])) > 4
    assert report["problems"] == [] and report["lost"]["messages"] == 0


@pytest.mark.parametrize(("fmt", "damage"), [*((f, "header") for f in FORMATS), ("bz2", "data")])
def test_a_damaged_chunk_is_named_and_only_it_dropped(
    bags: dict[str, Path], fmt: str, damage: str, tmp_path: Path
) -> None:
    """A flipped byte in a chunk's header (every format) or in its bz2 data: the chunks after it are read. (A flip
    inside plain or lz4 chunk data reads silently: ROS 1 carries no checksum.)"""
    src = bags[fmt]
    chunks = ros1_chunks(src)
    everything, _ = read_all(src, salvage=False)
    start, end, keys = chunks[2]
    at = start + 6 if damage == "header" else (start + end) // 2  # header: a byte of the first field's length
    bag = damaged(src, tmp_path / "flip.bag", at, 0x20)
    with pytest.raises(InputError, match=rf"truncated or damaged \(the (chunk|record) at byte {start} .*--salvage"):
        read_all(bag, salvage=False)
    got, report = read_all(bag, salvage=True)
    assert report is not None and report["chunks"] == len(chunks) - 1
    assert f"at byte {start}" in report["stopped_at"]
    if fmt == "plain":  # an uncompressed chunk behind a damaged header: its whole records are still read
        assert got == everything and report["lost"]["messages"] == 0
        return
    assert got == everything - Counter(keys)
    lost = report["lost"]
    assert lost["messages"] == len(keys) and lost["topics"] == per_topic(keys)
    t0 = min(t for _, t in everything)
    assert lost["start_s"] == round((min(t for _, t in keys) - t0) * 1e-9, 3)
    assert lost["end_s"] == round((max(t for _, t in keys) - t0) * 1e-9, 3)


@pytest.mark.parametrize("fmt", FORMATS)
def test_a_damaged_chunk_length_is_read_around(bags: dict[str, Path], fmt: str, tmp_path: Path) -> None:
    """A flipped length field breaks the framing: the scan finds the next record, and the chunk still reads whole."""
    src = bags[fmt]
    everything, _ = read_all(src, salvage=False)
    start, _end, _keys = ros1_chunks(src)[3]
    (hlen,) = struct.unpack_from("<I", src.read_bytes(), start)
    bag = damaged(src, tmp_path / "len.bag", start + 4 + hlen + 2, 0x01)  # the data length's third byte
    with pytest.raises(InputError, match=rf"the length of the record at byte {start} is damaged.*--salvage"):
        read_all(bag, salvage=False)
    got, report = read_all(bag, salvage=True)
    assert got == everything
    assert report is not None and report["lost"]["messages"] == 0 and f"byte {start}" in report["problems"][0]


@pytest.mark.parametrize("fmt", FORMATS)
def test_a_cut_keeps_every_chunk_before_it(bags: dict[str, Path], fmt: str, tmp_path: Path) -> None:
    src = bags[fmt]
    data = src.read_bytes()
    chunks = ros1_chunks(src)
    everything, _ = read_all(src, salvage=False)
    for cut in (chunks[1][1] + 40, (chunks[4][0] + chunks[4][1]) // 2, len(data) - 100):
        bag = tmp_path / f"cut{cut}.bag"
        bag.write_bytes(data[:cut])
        with pytest.raises(InputError, match=r"truncated or damaged.*--salvage"):
            read_all(bag, salvage=False)
        got, report = read_all(bag, salvage=True)
        whole = Counter(k for _s, e, keys in chunks if e <= cut for k in keys)
        assert got - whole == (got - whole) & everything  # nothing invented
        assert got & whole == whole  # every whole chunk
        assert report is not None and report["stopped_at"]
        if cut < chunks[-1][1]:
            assert sum(got.values()) < sum(everything.values())
            assert report["lost"]["start_s"] is not None


def test_the_shared_example_bag_as_lz4_chunks(shared_data: Path, tmp_path: Path) -> None:
    """A real recording (rosbag's example bag, 8647 messages) rewritten with lz4 chunks and one chunk damaged."""
    bag = rewrite_ros1(shared_data / "rosbag1-fixtures" / "example.bag", tmp_path / "lz4.bag", "lz4", 200_000)
    chunks = ros1_chunks(bag)
    everything, _ = read_all(bag, salvage=False)
    start, _end, keys = chunks[len(chunks) // 2]
    flipped = damaged(bag, tmp_path / "flip.bag", start + 6, 0x20)
    got, report = read_all(flipped, salvage=True)
    assert len(chunks) > 3 and got == everything - Counter(keys)
    assert report is not None and report["lost"]["topics"] == per_topic(keys)


def focusmap(*args: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "cli.app", *map(str, args)], capture_output=True, text=True, cwd=ROOT, timeout=300
    )


def test_cli_damaged_lz4_bag_one_error_line_or_salvaged(bags: dict[str, Path], tmp_path: Path) -> None:
    start, _end, keys = ros1_chunks(bags["lz4"])[1]
    bag = damaged(bags["lz4"], tmp_path / "bad.bag", start + 6, 0x20)
    proc = focusmap("ingest", bag, "--out", tmp_path / "runs")
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert (
        len(lines) == 1 and lines[0].startswith("error: ") and f"byte {start}" in lines[0] and "--salvage" in lines[0]
    )
    assert not (tmp_path / "runs" / "bad" / "ingest").exists()
    proc = focusmap("ingest", bag, "--out", tmp_path / "runs", "--salvage")
    assert proc.returncode == 0, proc.stderr
    assert f"salvaged: read {sum(len(k) for *_, k in ros1_chunks(bags['lz4'])) - len(keys)} messages" in proc.stdout
    assert f"lost {len(keys)} messages" in proc.stdout
    summary = json.loads((tmp_path / "runs" / "bad" / "ingest" / "summary.json").read_text())
    assert summary["salvaged"]["lost"]["topics"] == per_topic(keys)
