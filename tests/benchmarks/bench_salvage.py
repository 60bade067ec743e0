"""MCAP salvage: messages recovered per cut and per flipped byte on one generated multi-chunk file.

    python tests/benchmarks/bench_salvage.py [--seconds 8] [--cuts 12] [--flips 6] [--seed 1]

Simulates a recording, writes it as MCAP with small zstd chunks (chunk CRCs on), then
- cuts the file at ``--cuts`` seeded offsets and reads each with ``--salvage``: "whole chunks" are the
  messages of the chunks that end before the cut (from the intact file's chunk index), "read" what the
  salvage read recovered;
- flips one byte inside ``--flips`` seeded chunks: "normal read" is whether a read without --salvage
  stops with an error, "read" what a salvage read recovers, "expected" every message of the other chunks.
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=8.0)
    parser.add_argument("--cuts", type=int, default=12)
    parser.add_argument("--flips", type=int, default=6)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--chunk-size", type=int, default=100_000)
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


if __name__ == "__main__":
    main()
