"""Check every chunk of an MCAP file and, with ``--salvage``, keep every intact one.

A normal read checks each chunk's CRC (where the writer stored one) and the data section's CRC (where
present) and stops with the chunk's offset at the first mismatch. A salvage read drops a damaged chunk,
goes on with the next one, keeps every whole record of a chunk cut by truncation, and says what was lost.

Chunks are found through the summary's chunk indexes when the summary is readable (a damaged chunk header
then cannot hide the chunks after it), else by walking the records from the start (a cut file has no
summary). Records are parsed by the mcap library (``Chunk``, ``breakup_chunk`` with CRC validation,
``SeekingReader.get_summary``); only a cut chunk's header is read by hand, since the library needs whole
records.
"""

from __future__ import annotations

import io
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from mcap.records import Channel, Chunk, DataEnd, Footer, Message, MessageIndex, Schema
from mcap.stream_reader import breakup_chunk

from pipeline.errors import InputError
from stages.ingest.losses import ChunkLosses, Lost, salvage_report

__all__ = ["Block", "Lost", "McapScan", "salvage_report", "scan_mcap"]

_OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK, _OP_MESSAGE_INDEX = 0x03, 0x04, 0x05, 0x06, 0x07
_OP_FOOTER, _OP_DATA_END = 0x02, 0x0F
_PARSED = {_OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK, _OP_MESSAGE_INDEX, _OP_FOOTER, _OP_DATA_END}
_MAGIC = b"\x89MCAP0\r\n"


@dataclass
class Block:
    """Messages that are read together: one intact chunk (re-read by offset) or records kept in memory."""

    start_ns: int
    end_ns: int
    offset: int | None = None
    messages: list[Message] = field(default_factory=list)


@dataclass
class McapScan(ChunkLosses):
    """What one MCAP file holds, checked chunk by chunk (``chunks_total``, ``expected`` and the time range come
    from the summary's chunk indexes and statistics)."""

    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    blocks: list[Block] = field(default_factory=list)

    def topic_of(self, channel_id: int) -> str:
        ch = self.channels.get(channel_id)
        return ch.topic if ch is not None else f"<channel {channel_id}>"

    def type_of(self, channel_id: int) -> str:
        ch = self.channels.get(channel_id)
        sch = self.schemas.get(ch.schema_id) if ch is not None else None
        return sch.name if sch is not None else ""

    # reading ----------------------------------------------------------------------------------------
    def _take(self, records: list[Any], block: Block | None) -> Block:
        """Register the schemas, channels and messages of ``records``; messages go to ``block``."""
        msgs: list[Message] = []
        for r in records:
            if isinstance(r, Schema):
                self.schemas[r.id] = r
            elif isinstance(r, Channel):
                self.channels[r.id] = r
            elif isinstance(r, Message):
                msgs.append(r)
                self.count(r.channel_id, r.log_time)
        if block is None:
            times = [m.log_time for m in msgs] or [0]
            block = Block(min(times), max(times), messages=msgs)
        return block

    def iter_block(self, fh: IO[bytes], block: Block) -> Iterator[Message]:
        """The messages of ``block`` in file order (a chunk is read again from its offset)."""
        if block.offset is None:
            yield from block.messages
            return
        rec = _read_record(fh, block.offset, self.size)
        assert isinstance(rec.record, Chunk)  # it was read intact by the scan
        for r in breakup_chunk(rec.record):
            if isinstance(r, Message):
                yield r


@dataclass
class _Read:
    opcode: int
    length: int
    end: int
    record: Any = None
    content: bytes = b""
    complete: bool = True


def _read_record(fh: IO[bytes], pos: int, size: int) -> _Read:
    """The record at ``pos``, parsed by the mcap library when whole (``complete`` False when cut)."""
    fh.seek(pos)
    head = fh.read(9)
    if len(head) < 9:
        return _Read(-1, 0, pos + len(head), complete=False)
    opcode, length = head[0], struct.unpack_from("<Q", head, 1)[0]
    end = pos + 9 + length
    if end > size:
        return _Read(opcode, length, size, content=fh.read(size - pos - 9), complete=False)
    if opcode not in _PARSED:
        return _Read(opcode, length, end)
    from mcap.stream_reader import StreamReader

    content = fh.read(length)
    reader = StreamReader(io.BytesIO(head + content), skip_magic=True, emit_chunks=True, record_size_limit=None)
    return _Read(opcode, length, end, next(iter(reader.records)))


def _partial_chunk(content: bytes) -> tuple[int, int, list[Any]]:
    """Start, end time and the whole records of a chunk cut by truncation (its CRC cannot be checked)."""
    head = struct.Struct("<QQQII")
    start, end, _size, _crc, n = head.unpack_from(content, 0)
    pos = head.size
    compression = content[pos : pos + n].decode()
    data = content[pos + n + 8 :]
    if compression == "zstd":
        import zstandard

        data = zstandard.ZstdDecompressor().decompressobj().decompress(data)
    elif compression == "lz4":
        import lz4.frame

        data = lz4.frame.LZ4FrameDecompressor().decompress(data)
    elif compression:
        raise ValueError(f"unknown compression {compression!r}")
    whole = 0
    while whole + 9 <= len(data):
        (length,) = struct.unpack_from("<Q", data, whole + 1)
        if whole + 9 + length > len(data):
            break
        whole += 9 + length
    chunk = Chunk(
        compression="",
        data=data[:whole],
        message_start_time=start,
        message_end_time=end,
        uncompressed_crc=0,
        uncompressed_size=whole,
    )
    return start, end, breakup_chunk(chunk)


def _damaged(path: Path, offset: int, what: str) -> InputError:
    return InputError(
        f"{str(path)!r} is damaged: the chunk at byte {offset} {what}; copy the file again, "
        "or read every intact chunk with --salvage"
    )


def _crc_text(err: Exception) -> str:
    from mcap.stream_reader import CRCValidationError

    if isinstance(err, CRCValidationError):
        return f"fails its CRC check (stored {err.expected:#010x}, computed {err.actual:#010x})"
    return f"does not decode ({err or type(err).__name__})"


def _summary(fh: IO[bytes]) -> Any:
    from mcap.reader import SeekingReader

    try:
        fh.seek(0)
        return SeekingReader(fh).get_summary()
    except Exception:  # a cut or damaged summary: walk the records instead
        return None


def scan_mcap(path: Path, salvage: bool) -> McapScan:
    """Check and index every chunk of ``path``.

    Raises:
        InputError: without ``salvage``, at the first damaged chunk (naming its offset), a failed data
            section CRC, or a cut; with ``salvage``, only when the file is no MCAP file at all.
    """
    size = path.stat().st_size
    scan = McapScan(path, size)
    with path.open("rb") as fh:
        if fh.read(8) != _MAGIC:
            raise InputError(f"{str(path)!r} does not start with the MCAP magic; it is not an MCAP file")
        summary = _summary(fh)
        if summary is not None and summary.chunk_indexes:
            _scan_indexed(fh, scan, summary, salvage)
        else:
            _scan_linear(fh, scan, salvage)
    return scan


def _lose(scan: McapScan, offset: int, what: str, salvage: bool, lost: Lost | None = None) -> None:
    """Note the damaged chunk at ``offset``; without ``salvage`` stop with its offset."""
    if not salvage:
        raise _damaged(scan.path, offset, what)
    lost = lost or Lost(offset, "")
    lost.reason = f"chunk at byte {offset} {what}"
    scan.lost.append(lost)
    scan.problems.append(lost.reason)


def _check_chunk(scan: McapScan, offset: int, rec: _Read, salvage: bool) -> list[Any] | None:
    """The records of the chunk read at ``offset``; None (and the loss noted) when it is damaged."""
    chunk = rec.record
    if not isinstance(chunk, Chunk):
        _lose(scan, offset, f"is no chunk record (opcode {rec.opcode:#04x})", salvage)
        return None
    scan.crcs = scan.crcs or bool(chunk.uncompressed_crc)
    try:
        return breakup_chunk(chunk, validate_crc=True)
    except Exception as err:
        _lose(scan, offset, _crc_text(err), salvage, Lost(offset, "", chunk.message_start_time, chunk.message_end_time))
        return None


def _scan_indexed(fh: IO[bytes], scan: McapScan, summary: Any, salvage: bool) -> None:
    """Every chunk the summary lists, by offset."""
    scan.schemas.update(summary.schemas)
    scan.channels.update(summary.channels)
    scan.chunks_total = len(summary.chunk_indexes)
    if summary.statistics is not None:
        scan.expected = {int(k): int(v) for k, v in summary.statistics.channel_message_counts.items()}
        if summary.statistics.message_count:
            scan.start_ns = summary.statistics.message_start_time
            scan.end_ns = summary.statistics.message_end_time
    for index in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
        offset = index.chunk_start_offset
        try:
            rec = _read_record(fh, offset, scan.size)
        except Exception:
            rec = _Read(-1, 0, offset, complete=False)
        if not rec.complete or rec.opcode != _OP_CHUNK or rec.end - offset != index.chunk_length:
            what = "has a damaged record header" if offset + index.chunk_length <= scan.size else "is cut"
            _lose(scan, offset, what, salvage, Lost(offset, ""))
            records = None
        else:
            records = _check_chunk(scan, offset, rec, salvage)
        if records is None:
            lost = scan.lost[-1]
            lost.start_ns, lost.end_ns = index.message_start_time, index.message_end_time
            lost.counts = _index_counts(fh, index, scan.size)
            continue
        scan.chunks_read += 1
        scan.blocks.append(scan._take(records, Block(index.message_start_time, index.message_end_time, offset=offset)))
    _check_data_crc(fh, scan, salvage)


def _index_counts(fh: IO[bytes], index: Any, size: int) -> dict[int, int] | None:
    """Messages per channel of a chunk, from its message index records."""
    counts: dict[int, int] = {}
    try:
        for cid, off in index.message_index_offsets.items():
            rec = _read_record(fh, off, size)
            if not isinstance(rec.record, MessageIndex):
                return None
            counts[int(cid)] = len(rec.record.records)
    except Exception:
        return None
    return counts


def _check_data_crc(fh: IO[bytes], scan: McapScan, salvage: bool) -> None:
    """The data section's CRC (written by few writers), when every chunk passed its own check."""
    if scan.lost:
        return
    try:
        footer_start = scan.size - 8 - (1 + 8 + 8 + 8 + 4)
        footer = _read_record(fh, footer_start, scan.size).record
        if not isinstance(footer, Footer) or not footer.summary_start:
            return
        data_end = _read_record(fh, footer.summary_start - 13, scan.size).record
    except Exception:
        return
    if not isinstance(data_end, DataEnd) or not data_end.data_section_crc:
        return
    fh.seek(0)
    crc, left = 0, footer.summary_start - 13
    while left > 0:
        block = fh.read(min(left, 1 << 20))
        if not block:
            break
        crc = zlib.crc32(block, crc)
        left -= len(block)
    if crc != data_end.data_section_crc:
        what = f"data section fails its CRC check (stored {data_end.data_section_crc:#010x}, computed {crc:#010x})"
        if not salvage:
            raise InputError(
                f"{str(scan.path)!r} is damaged: the {what} outside any chunk; copy the file again, "
                "or read what is intact with --salvage"
            )
        scan.problems.append(f"the {what}; every chunk passed its own check")


def _scan_linear(fh: IO[bytes], scan: McapScan, salvage: bool) -> None:
    """Walk the records from the start (no readable summary: a cut file, or a writer without one)."""
    pos = 8
    loose: list[Any] = []
    last_lost: Lost | None = None
    while pos < scan.size:
        try:
            rec = _read_record(fh, pos, scan.size)
        except Exception as err:
            what = f"record at byte {pos} does not parse ({err or type(err).__name__})"
            if not salvage:
                raise InputError(
                    f"{str(scan.path)!r} cannot be read, it looks truncated or damaged ({what}); copy it again, "
                    "or read what is intact with --salvage"
                ) from None
            scan.lost.append(Lost(pos, what))
            scan.problems.append(what)
            break
        if not rec.complete:
            what = (
                f"the record at byte {pos} runs past the end of the file (the file is cut at byte {scan.size}, "
                "or the record's length is damaged)"
            )
            if not salvage:
                raise InputError(
                    f"{str(scan.path)!r} cannot be read, it looks truncated or damaged ({what}); copy it again, "
                    "or read what is intact with --salvage"
                )
            lost = Lost(pos, what, cut=True)
            if rec.opcode == _OP_CHUNK:
                try:
                    start, end, partial = _partial_chunk(rec.content)
                    lost.start_ns, lost.end_ns = start, end
                    block = scan._take(partial, None)
                    if block.messages:
                        scan.blocks.append(block)
                        lost.start_ns = block.end_ns
                        lost.reason += f"; its first {len(block.messages)} messages are whole and kept"
                except Exception:
                    pass
            scan.lost.append(lost)
            scan.problems.append(lost.reason)
            break
        if rec.opcode == _OP_CHUNK:
            records = _check_chunk(scan, pos, rec, salvage)
            last_lost = None
            if records is None:
                last_lost = scan.lost[-1]
            else:
                chunk = rec.record
                scan.chunks_read += 1
                scan.blocks.append(
                    scan._take(records, Block(chunk.message_start_time, chunk.message_end_time, offset=pos))
                )
        elif rec.opcode == _OP_MESSAGE_INDEX and last_lost is not None and isinstance(rec.record, MessageIndex):
            counts = last_lost.counts if last_lost.counts is not None else {}
            counts[rec.record.channel_id] = len(rec.record.records)
            last_lost.counts = counts
        elif rec.opcode in (_OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE):
            loose.append(rec.record)
        elif rec.opcode in (_OP_DATA_END, _OP_FOOTER):
            break
        pos = rec.end
    block = scan._take(loose, None)
    if block.messages:
        scan.blocks.append(block)
