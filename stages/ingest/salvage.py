"""Read a damaged ROS 1 bag up to the damage (``--salvage``).

A truncated ROS 1 bag loses its index, which is written last, so indexed readers refuse it. The
records themselves are self-delimiting (ROS bag format 2.0: ``header_len, header, data_len, data``),
so a sequential scan recovers every chunk that is whole. Connection records carry the message
definitions, so messages still deserialize.
"""

from __future__ import annotations

import bz2
import struct
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from stages.ingest.bags import RawMessage, TopicInfo, _normalise_type

_OP_MSG, _OP_CHUNK, _OP_CONN = 0x02, 0x05, 0x07


def _fields(header: bytes) -> dict[str, bytes]:
    out: dict[str, bytes] = {}
    pos = 0
    while pos + 4 <= len(header):
        (n,) = struct.unpack_from("<I", header, pos)
        pos += 4
        item = header[pos : pos + n]
        pos += n
        key, _, value = item.partition(b"=")
        out[key.decode()] = value
    return out


def _records(buf: bytes, pos: int = 0) -> Iterator[tuple[dict[str, bytes], bytes, int]]:
    """(header fields, data, end position) of each whole record; stops at the first incomplete one."""
    size = len(buf)
    while pos + 4 <= size:
        (hlen,) = struct.unpack_from("<I", buf, pos)
        if pos + 4 + hlen + 4 > size:
            return
        header = buf[pos + 4 : pos + 4 + hlen]
        (dlen,) = struct.unpack_from("<I", buf, pos + 4 + hlen)
        start = pos + 8 + hlen
        if start + dlen > size:
            return
        yield _fields(header), buf[start : start + dlen], start + dlen
        pos = start + dlen


def _partial_record(buf: bytes, pos: int) -> tuple[dict[str, bytes], bytes] | None:
    """Header and available data of the record cut off at the end of ``buf``."""
    if pos + 4 > len(buf):
        return None
    (hlen,) = struct.unpack_from("<I", buf, pos)
    if pos + 8 + hlen > len(buf):
        return None
    return _fields(buf[pos + 4 : pos + 4 + hlen]), buf[pos + 8 + hlen :]


def _decompress(hdr: dict[str, bytes], data: bytes, partial_ok: bool = False) -> bytes:
    comp = hdr.get("compression", b"none").decode()
    if comp == "bz2":
        return bz2.BZ2Decompressor().decompress(data) if partial_ok else bz2.decompress(data)
    if comp == "lz4":
        import lz4.frame

        if partial_ok:
            return lz4.frame.LZ4FrameDecompressor().decompress(data)
        return lz4.frame.decompress(data)
    return data


class Ros1Salvage:
    """Everything readable in a damaged ROS 1 bag."""

    def __init__(self, path: Path) -> None:
        from rosbags.typesys import Stores, get_typestore
        from rosbags.typesys.msg import get_types_from_msg

        buf = path.read_bytes()
        self.conns: dict[int, tuple[str, str]] = {}
        self.msgs: list[tuple[int, int, bytes]] = []  # (time_ns, conn, data)
        types: dict[str, Any] = {}
        chunks = bad_chunks = 0
        end = 13
        stopped: str | None = None
        for hdr, data, rec_end in _records(buf, 13):
            op = hdr.get("op", b"\x00")[0]
            if op == _OP_CHUNK:
                try:
                    inner = _decompress(hdr, data)
                except Exception as err:
                    bad_chunks += 1
                    stopped = f"chunk at byte {rec_end - len(data)} does not decompress: {err}"
                    break
                chunks += 1
                for ihdr, idata, _ in _records(inner):
                    self._take(ihdr, idata, types)
            else:
                self._take(hdr, data, types)
            end = rec_end
        if stopped is None and end < len(buf):
            stopped = f"incomplete record at byte {end} of {len(buf)}"
            partial = _partial_record(buf, end)
            if partial is not None and partial[0].get("op", b"\x00")[0] == _OP_CHUNK:
                # the cut chunk: keep every whole message before the cut
                try:
                    inner = _decompress(partial[0], partial[1], partial_ok=True)
                except Exception:
                    inner = b""
                for ihdr, idata, _ in _records(inner):
                    self._take(ihdr, idata, types)
        store = get_typestore(Stores.EMPTY)
        for name, definition in types.items():
            try:
                store.register(get_types_from_msg(definition, name))
            except Exception:  # an exotic definition: its messages stay undecodable, others still read
                continue
        self.typestore = store
        self.msgs.sort(key=lambda m: m[0])
        self.topics: dict[str, TopicInfo] = {}
        for conn_id, (topic, typ) in self.conns.items():
            self.topics.setdefault(topic, TopicInfo(topic, _normalise_type(typ)))
            del conn_id
        for t, conn, _ in self.msgs:
            topic = self.conns[conn][0]
            info = self.topics[topic]
            info.count += 1
            info.first_ns = t if info.first_ns is None else min(info.first_ns, t)
            info.last_ns = t if info.last_ns is None else max(info.last_ns, t)
        self.report = {
            "messages": len(self.msgs),
            "bytes_read": end,
            "bytes_total": len(buf),
            "chunks": chunks,
            "stopped_at": stopped,
        }

    def _take(self, hdr: dict[str, bytes], data: bytes, types: dict[str, Any]) -> None:
        op = hdr.get("op", b"\x00")[0]
        if op == _OP_CONN:
            conn = struct.unpack("<I", hdr["conn"])[0]
            fields = _fields(data)
            typ = fields.get("type", b"").decode()
            self.conns[conn] = (hdr.get("topic", fields.get("topic", b"")).decode(), typ)
            if typ and "message_definition" in fields:
                types.setdefault(_normalise_type(typ), fields["message_definition"].decode())
        elif op == _OP_MSG:
            conn = struct.unpack("<I", hdr["conn"])[0]
            sec, nsec = struct.unpack("<II", hdr["time"])
            self.msgs.append((sec * 1_000_000_000 + nsec, conn, data))

    def messages(self, topics: set[str]) -> Iterator[RawMessage]:
        """Recovered messages on ``topics`` in time order."""
        for t, conn, data in self.msgs:
            topic, typ = self.conns.get(conn, ("", ""))
            if topic in topics:
                yield RawMessage(topic, _normalise_type(typ), t, data, self._decode)

    def _decode(self, data: bytes, typ: str) -> Any:
        return self.typestore.deserialize_ros1(data, typ)
