"""Read every intact chunk of a damaged ROS 1 bag (``--salvage``), and find where a bag is damaged.

ROS 1 bags (format 2.0) are a sequence of records, ``header_len, header, data_len, data``, with the
messages in chunks (plain, bz2 or lz4), each chunk followed by index records that list its messages
(connection and time), and an index at the end (connections and chunk infos) that a cut file lacks.
The format has no checksums: damage shows only as a chunk that does not decompress (or not to the size
its header states), a record whose header does not parse, or a length that does not lead to the next
record.

The scan walks the records from the start. A damaged chunk is dropped and reported; when the framing is
broken (a damaged header or length), it searches forward for the next record that can only stand outside
a chunk (a chunk, index or chunk-info header whose fields parse) and goes on from there, so every later
whole chunk is still read. A chunk whose length field is damaged is read whole when its data ends where
the next record starts. The messages each chunk's index records (or the end index) list but the scan
could not read are the loss, per connection and in time (:mod:`stages.ingest.losses`).
"""

from __future__ import annotations

import bz2
import mmap
import struct
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from stages.ingest.bags import RawMessage, TopicInfo, _normalise_type
from stages.ingest.losses import ChunkLosses, Lost, salvage_report

_OP_MSG, _OP_BAG, _OP_INDEX, _OP_CHUNK, _OP_CHUNK_INFO, _OP_CONN = 0x02, 0x03, 0x04, 0x05, 0x06, 0x07
_NEEDS: dict[int, dict[str, int | None]] = {  # the fields each kind of record carries, with their size in bytes
    _OP_MSG: {"conn": 4, "time": 8},
    _OP_BAG: {"index_pos": 8, "conn_count": 4, "chunk_count": 4},
    _OP_INDEX: {"ver": 4, "conn": 4, "count": 4},
    _OP_CHUNK: {"compression": None, "size": 4},
    _OP_CHUNK_INFO: {"ver": 4, "chunk_pos": 8, "start_time": 8, "end_time": 8, "count": 4},
    _OP_CONN: {"conn": 4, "topic": None},
}
_OUTER = frozenset(_NEEDS)
_LANDMARKS = frozenset({_OP_INDEX, _OP_CHUNK, _OP_CHUNK_INFO})
"""Records that never stand inside a chunk: the ones a resync searches for between chunks."""
_INNER = frozenset({_OP_MSG, _OP_CONN})
_MAX_HEADER = 1 << 16
_OP_FIELD = b"\x04\x00\x00\x00op="
_FIELDS_BEFORE_OP = 256
"""Most header bytes before the ``op`` field that a resync looks back over."""
_COMPRESSIONS = (b"none", b"bz2", b"lz4")


@dataclass
class _Record:
    op: int
    fields: dict[str, bytes]
    start: int
    data_start: int
    end: int
    """Where the record's length says it ends (may lie past the end of the buffer)."""

    def u32(self, name: str) -> int:
        return int(struct.unpack("<I", self.fields[name])[0])

    def time(self, name: str = "time") -> int:
        sec, nsec = struct.unpack("<II", self.fields[name])
        return int(sec) * 1_000_000_000 + int(nsec)


def _fields(header: bytes | memoryview) -> dict[str, bytes] | None:
    """The ``name=value`` fields of a record header; None unless it is well formed."""
    out: dict[str, bytes] = {}
    pos, size = 0, len(header)
    while pos < size:
        if pos + 4 > size:
            return None
        (n,) = struct.unpack_from("<I", header, pos)
        if n < 2 or pos + 4 + n > size:
            return None
        item = bytes(header[pos + 4 : pos + 4 + n])
        key, eq, value = item.partition(b"=")
        if not eq or not key or not key.replace(b"_", b"a").isalnum() or not key.isascii():
            return None
        out[key.decode("ascii")] = value
        pos += 4 + n
    return out


def _record_at(buf: Any, pos: int, ops: frozenset[int]) -> _Record | None:
    """The record at ``pos`` when its header is well formed and of a kind in ``ops`` (its data may be cut)."""
    size = len(buf)
    if pos < 0 or pos + 8 > size:
        return None
    (hlen,) = struct.unpack_from("<I", buf, pos)
    if hlen < 6 or hlen > _MAX_HEADER or pos + 8 + hlen > size:
        return None
    fields = _fields(memoryview(buf)[pos + 4 : pos + 4 + hlen])
    if fields is None:
        return None
    op = fields.get("op", b"")
    if len(op) != 1 or op[0] not in ops:
        return None
    for name, width in _NEEDS[op[0]].items():
        value = fields.get(name)
        if value is None or (width is not None and len(value) != width):
            return None
    (dlen,) = struct.unpack_from("<I", buf, pos + 4 + hlen)
    rec = _Record(op[0], fields, pos, pos + 8 + hlen, pos + 8 + hlen + dlen)
    if rec.op == _OP_INDEX and dlen != 12 * rec.u32("count"):
        return None
    if rec.op == _OP_CHUNK_INFO and dlen != 8 * rec.u32("count"):
        return None
    if rec.op == _OP_CHUNK and fields["compression"] not in _COMPRESSIONS:
        return None
    return rec


def _resync(buf: Any, pos: int, ops: frozenset[int], limit: int | None = None) -> int | None:
    """Start of the first whole record of a kind in ``ops`` at or after ``pos`` (before ``limit``)."""
    limit = len(buf) if limit is None else limit
    q = buf.find(_OP_FIELD, pos + 4, limit)
    while q != -1:
        for p in range(max(pos, q - 4 - _FIELDS_BEFORE_OP), q - 3):
            (hlen,) = struct.unpack_from("<I", buf, p)
            if hlen <= q - p - 4 or hlen > _MAX_HEADER:
                continue
            rec = _record_at(buf, p, ops)
            if rec is not None and rec.end <= len(buf):
                return p
        q = buf.find(_OP_FIELD, q + 1, limit)
    return None


def _decompress(compression: bytes, data: bytes, partial_ok: bool = False) -> bytes:
    if compression == b"bz2":
        return bz2.BZ2Decompressor().decompress(data) if partial_ok else bz2.decompress(data)
    if compression == b"lz4":
        import lz4.frame

        if partial_ok:
            return bytes(lz4.frame.LZ4FrameDecompressor().decompress(data))
        return bytes(lz4.frame.decompress(data))
    return bytes(data)


@dataclass
class _Chunk:
    """A chunk met on the way: where it is, what was read of it, what its index records list."""

    offset: int
    read: Counter[tuple[int, int]] = field(default_factory=Counter)
    listed: Counter[tuple[int, int]] | None = None
    lost: Lost | None = None
    before: _Chunk | None = None
    """For a damaged stretch: the chunk before it (the index records after the damage may still be that chunk's)."""

    def missing(self) -> Counter[tuple[int, int]]:
        """Messages the index records list but the scan did not read."""
        if self.listed is None:
            return Counter()
        missing = self.listed - self.read
        return missing - self.before.read if self.before is not None else missing


class Ros1Scan(ChunkLosses):
    """Every readable record of a ROS 1 bag, with what could not be read."""

    def __init__(self, path: Path) -> None:
        super().__init__(path, path.stat().st_size)
        self.conns: dict[int, tuple[str, str]] = {}
        self.definitions: dict[str, str] = {}
        self.msgs: list[tuple[int, int, bytes]] = []  # (time_ns, conn, data)
        self.chunks: list[_Chunk] = []
        self._current: _Chunk | None = None
        self.infos: dict[int, tuple[int, int, dict[int, int]]] = {}  # chunk offset: start, end, counts by conn
        with path.open("rb") as fh, mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as buf:
            self._walk(buf)
        self._account()

    def topic_of(self, cid: int) -> str:
        conn = self.conns.get(cid)
        return conn[0] if conn is not None else f"<connection {cid}>"

    def _problem(self, lost: Lost) -> Lost:
        self.lost.append(lost)
        self.problems.append(lost.reason)
        return lost

    # the walk over the file -----------------------------------------------------------------------------
    def _walk(self, buf: Any) -> None:
        size = len(buf)
        pos = 13
        while pos < size:
            rec = _record_at(buf, pos, _OUTER)
            if rec is None:
                nxt = _resync(buf, pos + 1, _LANDMARKS)
                if nxt is None:
                    self._problem(
                        Lost(pos, f"the record at byte {pos} is cut or damaged and nothing after it reads", cut=True)
                    )
                    return
                lost = self._problem(Lost(pos, f"the record at byte {pos} has a damaged header; skipped to byte {nxt}"))
                # the index records that follow list what the damaged stretch held (a chunk hidden by its header)
                self._current = _Chunk(pos, lost=lost, before=self._current)
                self.chunks.append(self._current)
                self._plain_records(bytes(buf[pos:nxt]), self._current)
                pos = nxt
                continue
            follows = rec.end == size or (rec.end < size and _record_at(buf, rec.end, _OUTER) is not None)
            nxt = None if follows else _resync(buf, rec.data_start, _LANDMARKS)
            ends = sorted({e for e in (rec.end if rec.end <= size else None, nxt) if e is not None})
            if not ends:  # the file ends inside this record
                self._cut(buf, rec)
                return
            used = self._take(buf, rec, ends)
            if used is None:  # a lost chunk: go on where the next record starts
                used = nxt if nxt is not None and (rec.end > size or nxt < rec.end) else min(rec.end, size)
            if used != rec.end:
                self.problems.append(
                    f"the length of the record at byte {rec.start} is damaged (it says the record ends at byte "
                    f"{rec.end}; the next record starts at byte {used})"
                )
            pos = used

    def _take(self, buf: Any, rec: _Record, ends: list[int]) -> int | None:
        """One record whose data ends at one of ``ends``; returns the end used (None: a chunk that is lost)."""
        if rec.op == _OP_CHUNK:
            return self._chunk(buf, rec, ends)
        end = ends[0]  # the length field's end unless the next record starts earlier
        data = bytes(buf[rec.data_start : end])
        if rec.op == _OP_INDEX:
            self._index(rec, data)
        elif rec.op == _OP_CHUNK_INFO:
            self._chunk_info(rec, data)
        elif rec.op == _OP_CONN:
            self._conn(rec, data)
        elif rec.op == _OP_MSG:
            self._message(rec, data, None)
        return end

    def _chunk(self, buf: Any, rec: _Record, ends: list[int]) -> int | None:
        chunk = _Chunk(rec.start)
        self.chunks.append(chunk)
        self._current = chunk
        want = rec.u32("size")
        compression = rec.fields["compression"]
        failure = ""
        for end in ends:
            try:
                inner = _decompress(compression, bytes(buf[rec.data_start : end]))
            except Exception as err:  # bz2, lz4 and memory errors alike: this stretch is no chunk
                failure = failure or f"does not decompress ({compression.decode()}: {err or type(err).__name__})"
                continue
            if len(inner) == want:
                self.chunks_read += 1
                self._inner(inner, chunk)
                return end
            failure = failure or f"decompresses to {len(inner)} bytes, not the {want} its header states"
        chunk.lost = self._problem(Lost(rec.start, f"the chunk at byte {rec.start} {failure}"))
        return None

    def _inner(self, inner: bytes, chunk: _Chunk) -> None:
        """The connection and message records of a decompressed chunk; a damaged one is skipped."""
        pos, size = 0, len(inner)
        skipped = 0
        while pos < size:
            rec = _record_at(inner, pos, _INNER)
            if rec is None or rec.end > size:
                nxt = _resync(inner, pos + 1, _INNER)
                skipped += (nxt if nxt is not None else size) - pos
                if nxt is None:
                    break
                pos = nxt
                continue
            data = inner[rec.data_start : rec.end]
            if rec.op == _OP_CONN:
                self._conn(rec, data)
            else:
                self._message(rec, data, chunk)
            pos = rec.end
        if skipped:
            chunk.lost = self._problem(
                Lost(chunk.offset, f"the chunk at byte {chunk.offset} has {skipped} bytes of damaged records")
            )

    def _plain_records(self, region: bytes, chunk: _Chunk) -> None:
        """The messages of a damaged stretch that is an uncompressed chunk behind a damaged header: kept when whole
        records cover nearly all of it (compressed data cannot look like that)."""
        first = _resync(region, 0, _INNER)
        records: list[_Record] = []
        pos = first if first is not None else len(region)
        while (r := _record_at(region, pos, _INNER)) is not None and r.end <= len(region):
            records.append(r)
            pos = r.end
        if sum(r.end - r.start for r in records) < 0.9 * len(region):
            return
        for r in records:
            if r.op == _OP_CONN:
                self._conn(r, region[r.data_start : r.end])
            else:
                self._message(r, region[r.data_start : r.end], chunk)
        if chunk.lost is not None:
            chunk.lost.reason += f"; {len(records)} whole uncompressed records in it are kept"

    def _cut(self, buf: Any, rec: _Record) -> None:
        """The record the file ends in: of a chunk, every whole message before the cut is kept."""
        lost = self._problem(
            Lost(
                rec.start,
                f"the record at byte {rec.start} runs past the end of the file (the file is cut at byte {len(buf)}, "
                "or the record's length is damaged)",
                cut=True,
            )
        )
        if rec.op != _OP_CHUNK:
            return
        chunk = _Chunk(rec.start, lost=lost)
        self.chunks.append(chunk)
        try:
            inner = _decompress(rec.fields["compression"], bytes(buf[rec.data_start :]), partial_ok=True)
        except Exception:  # the start of the chunk is damaged too
            return
        pos = 0
        while (r := _record_at(inner, pos, _INNER)) is not None and r.end <= len(inner):
            if r.op == _OP_CONN:
                self._conn(r, inner[r.data_start : r.end])
            else:
                self._message(r, inner[r.data_start : r.end], chunk)
            pos = r.end
        if chunk.read:
            lost.start_ns = max(t for _, t in chunk.read)
            lost.reason += f"; its first {sum(chunk.read.values())} messages are whole and kept"

    def _message(self, rec: _Record, data: bytes, chunk: _Chunk | None) -> None:
        conn, t = rec.u32("conn"), rec.time()
        self.msgs.append((t, conn, data))
        if chunk is not None:
            chunk.read[(conn, t)] += 1

    def _conn(self, rec: _Record, data: bytes) -> None:
        fields = _fields(data) or {}
        try:
            typ = fields.get("type", b"").decode()
            topic = rec.fields["topic"].decode()
            definition = fields.get("message_definition", b"").decode()
        except UnicodeDecodeError:
            self.problems.append(f"the connection record at byte {rec.start} is damaged (not text)")
            return
        self.conns.setdefault(rec.u32("conn"), (topic, typ))
        if typ and definition:
            self.definitions.setdefault(_normalise_type(typ), definition)

    def _index(self, rec: _Record, data: bytes) -> None:
        """An index record: the messages of one connection in the chunk before it."""
        chunk = self._current
        if chunk is None:
            return
        listed = chunk.listed if chunk.listed is not None else Counter()
        conn = rec.u32("conn")
        for i in range(rec.u32("count")):
            sec, nsec, _offset = struct.unpack_from("<III", data, 12 * i)
            listed[(conn, sec * 1_000_000_000 + nsec)] += 1
        chunk.listed = listed

    def _chunk_info(self, rec: _Record, data: bytes) -> None:
        (offset,) = struct.unpack("<Q", rec.fields["chunk_pos"])
        counts: dict[int, int] = {}
        for i in range(rec.u32("count")):
            conn, n = struct.unpack_from("<II", data, 8 * i)
            counts[conn] = counts.get(conn, 0) + n
        self.infos[int(offset)] = (rec.time("start_time"), rec.time("end_time"), counts)

    # what was lost -------------------------------------------------------------------------------------
    def _account(self) -> None:
        """Messages read per connection, and per damaged chunk what its index lists but was not read."""
        for t, conn, _ in self.msgs:
            self.count(conn, t)
        if self.infos:
            self.chunks_total = len(self.infos)
            self.expected = {}
            for start, end, counts in self.infos.values():
                for conn, n in counts.items():
                    self.expected[conn] = self.expected.get(conn, 0) + n
                self.start_ns = start if self.start_ns is None else min(self.start_ns, start)
                self.end_ns = end if self.end_ns is None else max(self.end_ns, end)
        for chunk in self.chunks:
            if chunk.lost is None:
                continue
            lost = chunk.lost
            if chunk.listed is not None:
                missing = chunk.missing()
                if not missing:  # every message it lists was read after all: the problem stays, no loss
                    self.lost.remove(lost)
                    continue
                lost.counts = dict(Counter(conn for conn, _ in missing.elements()))
                times = [t for _, t in missing]
                if times and not lost.cut:
                    lost.start_ns, lost.end_ns = min(times), max(times)
            elif chunk.offset in self.infos and not chunk.read:
                lost.start_ns, lost.end_ns, lost.counts = self.infos[chunk.offset]


class Ros1Salvage:
    """Everything readable in a damaged ROS 1 bag: topics, messages, and the report of what was lost."""

    def __init__(self, path: Path) -> None:
        from rosbags.typesys import Stores, get_typestore
        from rosbags.typesys.msg import get_types_from_msg

        self.scan = scan = Ros1Scan(path)
        store = get_typestore(Stores.EMPTY)
        for name, definition in scan.definitions.items():
            try:
                store.register(get_types_from_msg(definition, name))
            except Exception:  # an exotic or damaged definition: its messages stay undecodable, others still read
                continue
        self.typestore = store
        self.conns = scan.conns
        self.msgs = sorted(scan.msgs, key=lambda m: m[0])
        self.topics: dict[str, TopicInfo] = {}
        for topic, typ in scan.conns.values():
            self.topics.setdefault(topic, TopicInfo(topic, _normalise_type(typ)))
        for t, conn, _ in self.msgs:
            if conn not in self.conns:
                continue
            info = self.topics[self.conns[conn][0]]
            info.count += 1
            info.first_ns = t if info.first_ns is None else min(info.first_ns, t)
            info.last_ns = t if info.last_ns is None else max(info.last_ns, t)
        orphans = sum(1 for _, conn, _ in self.msgs if conn not in self.conns)
        if orphans:
            scan.problems.append(f"{orphans} messages name a connection whose record is lost; they are dropped")
        self.report = salvage_report([scan])

    def messages(self, topics: set[str]) -> Iterator[RawMessage]:
        """Recovered messages on ``topics`` in time order."""
        for t, conn, data in self.msgs:
            topic, typ = self.conns.get(conn, ("", ""))
            if topic in topics:
                yield RawMessage(topic, _normalise_type(typ), t, data, self._decode)

    def _decode(self, data: bytes, typ: str) -> Any:
        return self.typestore.deserialize_ros1(data, typ)


def first_damage(path: Path) -> str | None:
    """Where a ROS 1 bag is damaged (the first problem a scan meets), or None when every record reads."""
    try:
        scan = Ros1Scan(path)
    except Exception:  # the scan itself should not fail; if it does, the caller's own message stands
        return None
    return scan.problems[0] if scan.problems else None
