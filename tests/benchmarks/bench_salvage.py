"""Salvage: messages recovered per cut and per flipped byte on generated multi-chunk files (MCAP, ROS 1).

    python tests/benchmarks/bench_salvage.py [--seconds 8] [--cuts 12] [--flips 6] [--seed 1] [--ros1-before REV]

Simulates a recording, writes it as MCAP with small zstd chunks (chunk CRCs on), then
- cuts the file at ``--cuts`` seeded offsets and reads each with ``--salvage``: "whole chunks" are the
  messages of the chunks that end before the cut (from the intact file's chunk index), "read" what the
  salvage read recovered;
- flips one byte inside ``--flips`` seeded chunks: "normal read" is whether a read without --salvage
  stops with an error, "read" what a salvage read recovers, "expected" every message of the other chunks.

ROS 1 (plain, bz2, lz4; the same recording with ~64 kB chunks): per cut, and per damage to chunk k (a flipped
byte in its header, in its data, in its length field), the messages of the intact chunks ("expected"), what
the salvage read recovers now ("after") and what the scan of git revision ``--ros1-before`` recovered
("before", run side by side on the same file; "exc" where it raised). ROS 1 has no checksums: a flip inside
plain or lz4 chunk data reads silently, and a plain chunk behind a damaged header keeps its whole records, so
"after" can exceed "expected" there.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
from mcap.reader import make_reader  # noqa: E402
from mcap.writer import CompressionType, Writer  # noqa: E402

from pipeline.errors import InputError  # noqa: E402
from sample_data.simulate import SimConfig, simulate, write_bag  # noqa: E402
from stages.ingest.bags import Recording  # noqa: E402
from tests.fixtures.bags import rewrite_ros1, ros1_chunks  # noqa: E402


def rechunk(src: Path, dst: Path, chunk_size: int) -> None:
    with src.open("rb") as fi, dst.open("wb") as fo:
        reader = make_reader(fi)
        header, summary = reader.get_header(), reader.get_summary()
        assert summary is not None
        writer = Writer(fo, chunk_size=chunk_size, compression=CompressionType.ZSTD)
        writer.start(profile=header.profile, library=header.library)
        sids = {i: writer.register_schema(s.name, s.encoding, s.data) for i, s in summary.schemas.items()}
        cids = {
            i: writer.register_channel(c.topic, c.message_encoding, sids[c.schema_id], c.metadata)
            for i, c in summary.channels.items()
        }
        for _s, channel, m in reader.iter_messages(log_time_order=False):
            writer.add_message(cids[channel.id], m.log_time, m.data, m.publish_time, m.sequence)
        writer.finish()


def salvage_read(path: Path) -> tuple[int, str]:
    try:
        with Recording(path, salvage=True) as rec:
            n = sum(1 for _ in rec.messages(rec.topics))
            report = rec.salvaged or {}
    except InputError as err:
        return 0, f"error: {err}"[:60]
    lost = report.get("lost")
    if lost is None:
        return n, "-"
    count = "?" if lost["messages"] is None else str(lost["messages"])
    end = "end?" if lost["end_s"] is None else f"{lost['end_s']:.2f} s"
    start = "?" if lost["start_s"] is None else f"{lost['start_s']:.2f} s"
    return n, f"{count} msgs, {start} .. {end}"


def old_ros1_salvage(rev: str) -> type | None:
    """``Ros1Salvage`` as it was at git revision ``rev`` (None when git cannot show it)."""
    import importlib.util
    import subprocess

    try:
        text = subprocess.run(
            ["git", "show", f"{rev}:stages/ingest/salvage.py"], capture_output=True, text=True, check=True, cwd=ROOT
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        return None
    path = Path(tempfile.mkdtemp()) / "old_salvage.py"
    path.write_text(text)
    spec = importlib.util.spec_from_file_location("old_salvage", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.Ros1Salvage


def ros1_section(src: Path, root: Path, rng: np.random.Generator, cuts: int, before_rev: str) -> None:
    old = old_ros1_salvage(before_rev)

    def before(path: Path) -> str:
        if old is None:
            return "-"
        try:
            return str(len(old(path).msgs))
        except Exception as err:
            return f"exc {type(err).__name__}"

    def after(path: Path) -> tuple[int, str]:
        return salvage_read(path)

    print()
    print(f"ROS 1, before = revision {before_rev}")
    print(f"{'format':>6} {'damage':>16} {'expected':>9} {'before':>22} {'after':>6}  reported lost")
    for fmt in ("plain", "bz2", "lz4"):
        bag = rewrite_ros1(src, root / f"{fmt}.bag", None if fmt == "plain" else fmt)
        data = bag.read_bytes()
        chunks = ros1_chunks(bag)
        total = sum(len(k) for *_, k in chunks)
        damaged = root / "damaged.bag"
        for cut in sorted(int(c) for c in rng.integers(chunks[0][0] + 1, len(data), size=cuts)):
            damaged.write_bytes(data[:cut])
            whole = sum(len(k) for _s, e, k in chunks if e <= cut)
            n, lost = after(damaged)
            print(f"{fmt:>6} {f'cut {100 * cut / len(data):.0f}%':>16} {whole:>9} {before(damaged):>22} {n:>6}  {lost}")
        k = len(chunks) // 2
        start, end, keys = chunks[k]
        (hlen,) = np.frombuffer(data[start : start + 4], dtype="<u4")
        for what, at, mask in (
            ("header", start + 6, 0x20),
            ("data", (start + end) // 2, 0x10),
            ("length", start + 4 + int(hlen) + 2, 0x01),
        ):
            flipped = bytearray(data)
            flipped[at] ^= mask
            damaged.write_bytes(bytes(flipped))
            expected = total if what == "length" else total - len(keys)
            n, lost = after(damaged)
            label = f"{what} chunk {k}/{len(chunks)}"
            print(f"{fmt:>6} {label:>16} {expected:>9} {before(damaged):>22} {n:>6}  {lost}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=8.0)
    parser.add_argument("--cuts", type=int, default=12)
    parser.add_argument("--flips", type=int, default=6)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--chunk-size", type=int, default=100_000)
    parser.add_argument("--ros1-before", default="2be492d", help="git revision whose ROS 1 salvage to compare")
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        rec = simulate(SimConfig(seed=args.seed, path="corridor", duration_s=args.seconds, image_format="jpeg"))
        src = root / "src.mcap"
        write_bag(rec, src, "mcap")
        bag = root / "chunked.mcap"
        rechunk(src, bag, args.chunk_size)
        data = bag.read_bytes()
        with bag.open("rb") as fh:
            reader = make_reader(fh)
            summary = reader.get_summary()
            assert summary is not None
            index = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
            # messages per chunk: the message counts of its message index records
            per_chunk = []
            for ci in index:
                n = 0
                for off in ci.message_index_offsets.values():
                    fh.seek(off + 1 + 8 + 2)
                    n += int.from_bytes(fh.read(4), "little") // 16
                per_chunk.append(n)
        total = sum(per_chunk)
        print(f"file: {len(data)} bytes, {len(index)} chunks, {total} messages, {args.seconds:.0f} s")
        print()
        print(f"{'cut at byte':>12} {'% file':>7} {'whole chunks':>12} {'expected':>9} {'read':>6}  reported lost")
        cuts = sorted(int(c) for c in rng.integers(index[0].chunk_start_offset + 1, len(data), size=args.cuts))
        cut_file = root / "cut.mcap"
        for cut in cuts:
            cut_file.write_bytes(data[:cut])
            whole = [
                n for ci, n in zip(index, per_chunk, strict=True) if ci.chunk_start_offset + ci.chunk_length <= cut
            ]
            n, lost = salvage_read(cut_file)
            print(f"{cut:>12} {100 * cut / len(data):>6.1f}% {len(whole):>12} {sum(whole):>9} {n:>6}  {lost}")
        print()
        print(f"{'flip in chunk':>13} {'normal read':>12} {'expected':>9} {'read':>6}  reported lost")
        flip_file = root / "flip.mcap"
        for k in sorted(rng.choice(len(index), size=min(args.flips, len(index)), replace=False)):
            ci = index[k]
            flipped = bytearray(data)
            flipped[ci.chunk_start_offset + ci.chunk_length // 2] ^= 0x10
            flip_file.write_bytes(bytes(flipped))
            try:
                with Recording(flip_file) as plain:
                    sum(1 for _ in plain.messages(plain.topics))
                normal = "silent"
            except InputError:
                normal = "error"
            n, lost = salvage_read(flip_file)
            print(f"{int(k):>13} {normal:>12} {total - per_chunk[k]:>9} {n:>6}  {lost}")
        ros1 = root / "src.bag"
        write_bag(rec, ros1, "ros1")
        ros1_section(ros1, root, rng, max(args.cuts // 2, 1), args.ros1_before)


if __name__ == "__main__":
    main()
