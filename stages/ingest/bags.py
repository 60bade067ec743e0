"""Open any recording focusmap reads, behind one small interface.

Formats: ROS 1 ``.bag`` (uncompressed, bz2 or lz4 chunks), ROS 2 bag folders with SQLite (``.db3``)
or MCAP storage (split recordings included), a single ROS 2 ``.db3`` file, and a standalone ``.mcap``
file with ROS 2 (CDR) messages. rosbags reads what it can; the mcap library reads MCAP files that
rosbags cannot (no ``metadata.yaml``, a standalone file, damaged indexes).

Message counts always come from the files themselves (the ROS 1 index, the MCAP statistics or the
records, SQLite's ``messages`` table), never from a ``metadata.yaml`` that may disagree.
"""

from __future__ import annotations

import sqlite3
import tempfile
from collections.abc import Iterable, Iterator
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from pipeline.errors import InputError

ROS1_MAGIC = b"#ROSBAG V2.0\n"
MCAP_MAGIC = b"\x89MCAP0\r\n"
SQLITE_MAGIC = b"SQLite format 3\x00"


@dataclass
class TopicInfo:
    """One topic of a recording."""

    name: str
    type: str
    count: int = 0
    first_ns: int | None = None
    last_ns: int | None = None

    @property
    def rate_hz(self) -> float:
        """Mean message rate over the topic's own span."""
        if self.count < 2 or self.first_ns is None or self.last_ns is None or self.last_ns <= self.first_ns:
            return 0.0
        return (self.count - 1) / ((self.last_ns - self.first_ns) * 1e-9)


@dataclass
class RawMessage:
    """A message as stored: topic, type, log time and serialized bytes (deserialize on demand)."""

    topic: str
    type: str
    log_time_ns: int
    data: bytes
    _decode: Any = field(repr=False, default=None)

    def decode(self) -> Any:
        """The deserialized message (attribute access, ROS field names of the bag's ROS version)."""
        try:
            return self._decode(self.data, self.type)
        except Exception as err:  # library errors vary by reader
            raise InputError(f"cannot decode a {self.type} message on {self.topic}: {err}") from None


def _normalise_type(name: str) -> str:
    """``pkg/Type`` and ``pkg/msg/Type`` both become ``pkg/msg/Type``."""
    parts = name.split("/")
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    return name


def detect_format(path: Path) -> str:
    """Which kind of recording ``path`` is: ``ros1``, ``ros2`` (folder), ``ros2-db3`` or ``mcap``.

    Raises:
        InputError: for a missing path, an empty file, or a file that is no recording.
    """
    if not path.exists():
        raise InputError(
            f"{str(path)!r} does not exist; pass the path of a .bag file, a ROS 2 bag folder or a .mcap file"
        )
    if path.is_dir():
        if (path / "metadata.yaml").is_file():
            return "ros2"
        if any(path.glob("*.db3")) or any(path.glob("*.mcap")):
            return "ros2"
        raise InputError(f"{str(path)!r} is a folder without metadata.yaml, .db3 or .mcap files; it is not a ROS 2 bag")
    size = path.stat().st_size
    if size == 0:
        raise InputError(f"{str(path)!r} is empty (0 bytes); the recording was not written, copy it again")
    with path.open("rb") as fh:
        head = fh.read(16)
    if head.startswith(ROS1_MAGIC[:9]):
        return "ros1"
    if head.startswith(MCAP_MAGIC):
        return "mcap"
    if head.startswith(SQLITE_MAGIC):
        return "ros2-db3"
    raise InputError(
        f"{str(path)!r} is not a ROS bag or MCAP file (it starts with {head[:12]!r}); "
        "pass a ROS 1 .bag, a ROS 2 bag folder, a .db3 or a .mcap file"
    )


class Recording:
    """An open recording: its topics with real counts, and its messages in log-time order."""

    def __init__(self, path: Path, salvage: bool = False) -> None:
        self.path = path
        self.salvage = salvage
        self.format = detect_format(path)
        self.reader = "rosbags"
        self.storage = ""
        self.salvaged: dict[str, Any] | None = None
        self._stack = ExitStack()
        self._impl: _Impl
        try:
            self._impl = self._open()
        except InputError:
            self._stack.close()
            raise

    def _open(self) -> _Impl:
        if self.format == "ros1":
            self.storage = "ros1"
            return _Ros1(self)
        if self.format == "mcap":
            self.storage = "mcap"
            self.reader = "mcap"
            return _Mcap(self, [self.path])
        if self.format == "ros2-db3":
            self.storage = "sqlite3"
            self.reader = "sqlite3"
            return _Sqlite(self, [self.path], sqlite_check([self.path], self.salvage))
        files, storage = _ros2_files(self.path)
        self.storage = storage
        if storage == "sqlite3":
            problems = sqlite_check(files, self.salvage)
            if problems:  # --salvage: read the rows that still read, row by row
                self.reader = "sqlite3"
                return _Sqlite(self, files, problems)
        if storage == "mcap":
            if self.salvage:  # chunk by chunk, dropping the damaged ones
                self.reader = "mcap"
                return _Mcap(self, files)
            try:
                impl: _Impl = _Rosbags2(self)
            except InputError:
                self.reader = "mcap"
                return _Mcap(self, files)
            return impl
        try:
            return _Rosbags2(self)
        except InputError:
            self.reader = "sqlite3"
            return _Sqlite(self, files, [])

    # public API -----------------------------------------------------------------------------------
    @property
    def topics(self) -> dict[str, TopicInfo]:
        """Topics by name, with the counts read from the file."""
        return self._impl.topics

    @property
    def start_ns(self) -> int:
        """Log time of the first message (0 for an empty recording)."""
        firsts = [t.first_ns for t in self.topics.values() if t.first_ns is not None and t.count]
        return min(firsts) if firsts else 0

    @property
    def end_ns(self) -> int:
        """Log time of the last message."""
        lasts = [t.last_ns for t in self.topics.values() if t.last_ns is not None and t.count]
        return max(lasts) if lasts else 0

    @property
    def message_count(self) -> int:
        """Messages in the recording."""
        return sum(t.count for t in self.topics.values())

    def topics_of_type(self, *types: str) -> list[str]:
        """Names of the topics whose type is one of ``types`` (``pkg/msg/Type``)."""
        wanted = {_normalise_type(t) for t in types}
        return sorted(name for name, t in self.topics.items() if t.type in wanted)

    def messages(self, topics: Iterable[str]) -> Iterator[RawMessage]:
        """Messages on ``topics`` in log-time order."""
        return self._impl.messages(set(topics))

    @property
    def typestore(self) -> Any | None:
        """The rosbags type store :meth:`RawMessage.decode` decodes with (None: another library decodes)."""
        return self._impl.typestore()

    def close(self) -> None:
        """Release the files."""
        self._stack.close()

    def __enter__(self) -> Recording:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class _Impl:
    topics: dict[str, TopicInfo]

    def typestore(self) -> Any | None:
        return None

    def messages(self, topics: set[str]) -> Iterator[RawMessage]:
        raise NotImplementedError


def _ros2_files(path: Path) -> tuple[list[Path], str]:
    meta = path / "metadata.yaml"
    files: list[Path] = []
    storage = ""
    if meta.is_file():
        try:
            info = (yaml.safe_load(meta.read_text()) or {}).get("rosbag2_bagfile_information", {})
        except yaml.YAMLError:
            info = {}
        storage = str(info.get("storage_identifier", ""))
        files = [path / f for f in info.get("relative_file_paths", []) if (path / f).is_file()]
    if not files:
        files = sorted(path.glob("*.db3")) or sorted(path.glob("*.mcap"))
    if not files:
        raise InputError(f"ROS 2 bag {str(path)!r} lists no storage files that exist; the folder is incomplete")
    if not storage:
        storage = "mcap" if files[0].suffix == ".mcap" else "sqlite3"
    return files, storage


def _truncation_hint(path: Path, err: Exception) -> InputError:
    return InputError(
        f"{str(path)!r} cannot be read, it looks truncated or damaged ({err}); copy it again, "
        "or read what is intact with --salvage"
    )


def _ros1_damage(path: Path, err: Exception) -> InputError:
    """The error for a ROS 1 bag rosbags cannot read: where the bag is damaged, when a scan finds it."""
    from stages.ingest.salvage import first_damage

    where = first_damage(path)
    if where is None:
        return _truncation_hint(path, err)
    return InputError(
        f"{str(path)!r} cannot be read, it looks truncated or damaged ({where}); copy it again, "
        "or read every intact chunk with --salvage"
    )


class _Ros1(_Impl):
    """ROS 1 bags through rosbags (index) or, with --salvage, a scan of the records that skips the damage."""

    def __init__(self, rec: Recording) -> None:
        from rosbags.highlevel import AnyReader

        self.rec = rec
        self.reader: Any = None
        if rec.salvage:
            from stages.ingest.salvage import Ros1Salvage

            self.salvage = Ros1Salvage(rec.path)
            rec.salvaged = self.salvage.report
            rec.reader = "salvage"
            self.topics = self.salvage.topics
            return
        try:
            reader = AnyReader([rec.path])
            rec._stack.enter_context(reader)
        except Exception as err:  # rosbags' errors vary with the damage
            raise _ros1_damage(rec.path, err) from None
        self.reader = reader
        self.topics = {}
        for conn in reader.connections:
            info = self.topics.setdefault(conn.topic, TopicInfo(conn.topic, _normalise_type(conn.msgtype)))
            info.count += conn.msgcount
        # first/last stamps per topic from the bag's index (no pass over the messages)
        for conn in reader.connections:
            index = getattr(conn.owner, "indexes", {}).get(conn.id) or []
            if not index:
                continue
            info = self.topics[conn.topic]
            first, last = min(i.time for i in index), max(i.time for i in index)
            info.first_ns = first if info.first_ns is None else min(info.first_ns, first)
            info.last_ns = last if info.last_ns is None else max(info.last_ns, last)

    def typestore(self) -> Any | None:
        return self.reader.typestore if self.reader is not None else self.salvage.typestore

    def _iter(self, topics: set[str] | None) -> Iterator[RawMessage]:
        reader = self.reader
        conns = [c for c in reader.connections if topics is None or c.topic in topics]
        if not conns:
            return
        for conn, stamp, data in reader.messages(connections=conns):
            yield RawMessage(conn.topic, _normalise_type(conn.msgtype), stamp, data, reader.deserialize)

    def messages(self, topics: set[str]) -> Iterator[RawMessage]:
        if self.reader is None:
            yield from self.salvage.messages(topics)
            return
        try:
            yield from self._iter(topics)
        except InputError:
            raise
        except Exception as err:
            raise _ros1_damage(self.rec.path, err) from None


class _Rosbags2(_Impl):
    """ROS 2 bag folders through rosbags."""

    def __init__(self, rec: Recording) -> None:
        from rosbags.highlevel import AnyReader, AnyReaderError
        from rosbags.typesys import Stores, get_typestore

        self.rec = rec
        try:
            reader = AnyReader([rec.path], default_typestore=get_typestore(Stores.LATEST))
            rec._stack.enter_context(reader)
        except (AnyReaderError, Exception) as err:
            raise InputError(f"rosbags cannot read {str(rec.path)!r}: {err}") from None
        self.reader = reader
        self.topics = {}
        for conn in reader.connections:
            self.topics.setdefault(conn.topic, TopicInfo(conn.topic, _normalise_type(conn.msgtype)))
        files, _ = _ros2_files(rec.path)
        # real counts from the storage files, not metadata.yaml
        counts = _sqlite_counts(files) if rec.storage == "sqlite3" else _mcap_counts(files)
        for name, (n, first, last) in counts.items():
            if name in self.topics:
                info = self.topics[name]
                info.count, info.first_ns, info.last_ns = n, first, last

    def typestore(self) -> Any | None:
        return self.reader.typestore

    def messages(self, topics: set[str]) -> Iterator[RawMessage]:
        reader = self.reader
        conns = [c for c in reader.connections if c.topic in topics]
        if not conns:
            return
        try:
            for conn, stamp, data in reader.messages(connections=conns):
                yield RawMessage(conn.topic, _normalise_type(conn.msgtype), stamp, data, reader.deserialize)
        except InputError:
            raise
        except Exception as err:
            raise _truncation_hint(self.rec.path, err) from None


def _sqlite_connect(f: Path) -> sqlite3.Connection:
    return sqlite3.connect(f"file:{f}?mode=ro&immutable=1", uri=True)


def _sqlite_damaged(f: Path, what: str) -> InputError:
    return InputError(f"{str(f)!r} is damaged: {what}; copy it again, or read the rows that are intact with --salvage")


def _sqlite_torn(f: Path) -> str | None:
    """Whether the file is shorter than its header says (a cut copy), or not whole pages."""
    with f.open("rb") as fh:
        head = fh.read(100)
    size = f.stat().st_size
    page = int.from_bytes(head[16:18], "big") if len(head) == 100 else 0
    page = 65536 if page == 1 else page
    if not page:
        return f"its header is cut ({size} bytes)"
    pages = int.from_bytes(head[28:32], "big")
    valid = head[24:28] == head[92:96]  # the header's page count is kept up to date
    if size % page or (valid and pages * page > size):
        return f"the file is cut: it is {size} bytes, its header says {pages} pages of {page} bytes"
    return None


def _sqlite_readable(f: Path, tmp: Path) -> Path:
    """``f``, or a copy padded with zero bytes to the size its header states (SQLite refuses a shorter file;
    the rows on the pages that are there still read)."""
    if _sqlite_torn(f) is None:
        return f
    with f.open("rb") as fh:
        head = fh.read(100)
    page = int.from_bytes(head[16:18], "big") if len(head) == 100 else 4096
    page = 65536 if page == 1 else page or 4096
    want = max(int.from_bytes(head[28:32], "big") * page, -(-f.stat().st_size // page) * page)
    copy = tmp / f.name
    with f.open("rb") as src, copy.open("wb") as dst:
        while block := src.read(1 << 20):
            dst.write(block)
        dst.truncate(want)
    return copy


def sqlite_check(files: list[Path], salvage: bool) -> list[str]:
    """SQLite's own consistency check (``PRAGMA quick_check``) of each storage file: the problems found.

    Raises:
        InputError: without ``salvage``, for the first file with a problem (a torn or inconsistent database).
    """
    problems: list[str] = []
    for f in files:
        torn = _sqlite_torn(f)
        if torn is not None:
            if not salvage:
                raise _sqlite_damaged(f, torn)
            problems.append(f"{f.name}: {torn}")
            continue
        con = _sqlite_connect(f)
        try:
            found = [str(r[0]) for r in con.execute("PRAGMA quick_check(20)") if r[0] != "ok"]
        except sqlite3.DatabaseError as err:
            found = [str(err)]
        finally:
            con.close()
        if not found:
            continue
        what = f"SQLite's quick_check finds {len(found)}{'+' if len(found) == 20 else ''} problems (first: {found[0]})"
        if not salvage:
            raise _sqlite_damaged(f, what)
        problems.append(f"{f.name}: {what}")
    return problems


def _sqlite_counts(files: list[Path]) -> dict[str, tuple[int, int | None, int | None]]:
    out: dict[str, list[Any]] = {}
    for f in files:
        con = _sqlite_connect(f)
        try:
            rows = con.execute(
                "SELECT t.name, COUNT(m.id), MIN(m.timestamp), MAX(m.timestamp) "
                "FROM topics t LEFT JOIN messages m ON m.topic_id = t.id GROUP BY t.id"
            ).fetchall()
        except sqlite3.DatabaseError as err:
            raise InputError(f"{str(f)!r} is not a readable ROS 2 SQLite bag ({err}); copy it again") from None
        finally:
            con.close()
        for name, n, first, last in rows:
            acc = out.setdefault(name, [0, None, None])
            acc[0] += n
            if first is not None:
                acc[1] = first if acc[1] is None else min(acc[1], first)
                acc[2] = last if acc[2] is None else max(acc[2], last)
    return {k: (v[0], v[1], v[2]) for k, v in out.items()}


def _mcap_counts(files: list[Path]) -> dict[str, tuple[int, int | None, int | None]]:
    """Per-topic counts and spans of MCAP files, every chunk's CRC checked on the way."""
    from stages.ingest.mcap_scan import scan_mcap

    out: dict[str, list[Any]] = {}
    for f in files:
        scan = scan_mcap(f, salvage=False)
        for cid, ch in scan.channels.items():
            acc = out.setdefault(ch.topic, [0, None, None])
            if cid not in scan.counts:
                continue
            acc[0] += scan.counts[cid]
            first, last = scan.first_ns[cid], scan.last_ns[cid]
            acc[1] = first if acc[1] is None else min(acc[1], first)
            acc[2] = last if acc[2] is None else max(acc[2], last)
    return {k: (v[0], v[1], v[2]) for k, v in out.items()}


class _Mcap(_Impl):
    """MCAP files (standalone, or a ROS 2 folder rosbags cannot read or is salvaged) through the mcap library.

    Every chunk is checked (:mod:`stages.ingest.mcap_scan`); with --salvage, damaged chunks are dropped,
    the whole records of a cut chunk kept, and ``rec.salvaged`` says what was lost.
    """

    def __init__(self, rec: Recording, files: list[Path]) -> None:
        from stages.ingest.mcap_scan import salvage_report, scan_mcap

        self.rec = rec
        self.files = files
        self.topics = {}
        try:
            self.scans = [scan_mcap(f, rec.salvage) for f in files]
        except InputError:
            raise
        except Exception as err:  # library errors vary
            raise _truncation_hint(rec.path, err) from None
        for scan in self.scans:
            for cid, ch in scan.channels.items():
                info = self.topics.setdefault(ch.topic, TopicInfo(ch.topic, _normalise_type(scan.type_of(cid))))
                if not info.type:
                    info.type = _normalise_type(scan.type_of(cid))
                if cid not in scan.counts:
                    continue
                info.count += scan.counts[cid]
                first, last = scan.first_ns[cid], scan.last_ns[cid]
                info.first_ns = first if info.first_ns is None else min(info.first_ns, first)
                info.last_ns = last if info.last_ns is None else max(info.last_ns, last)
        if rec.salvage:
            rec.salvaged = salvage_report(self.scans)

    def messages(self, topics: set[str]) -> Iterator[RawMessage]:
        from mcap.reader import make_reader
        from mcap_ros2.decoder import DecoderFactory

        factory = DecoderFactory()
        decoders: dict[tuple[Path, int], Any] = {}  # channel ids are per file

        def raw(f: Path, schema: Any, channel: Any, message: Any) -> RawMessage:
            dec = decoders.get((f, channel.id))
            if dec is None:
                dec = factory.decoder_for(channel.message_encoding, schema)
                if dec is None:
                    raise InputError(f"no decoder for {channel.message_encoding} messages on {channel.topic}")
                decoders[(f, channel.id)] = dec
            return RawMessage(
                channel.topic, _normalise_type(schema.name), message.log_time, message.data, lambda d, _t: dec(d)
            )

        for f, scan in zip(self.files, self.scans, strict=True):
            with f.open("rb") as fh:
                if self.rec.salvage:
                    for message in _salvaged_messages(fh, scan, topics):
                        channel = scan.channels[message.channel_id]
                        yield raw(f, scan.schemas.get(channel.schema_id), channel, message)
                    continue
                try:
                    for schema, channel, message in make_reader(fh, validate_crcs=True).iter_messages(
                        topics=list(topics), log_time_order=True
                    ):
                        yield raw(f, schema, channel, message)
                except InputError:
                    raise
                except Exception as err:
                    raise _truncation_hint(self.rec.path, err) from None


def _salvaged_messages(fh: Any, scan: Any, topics: set[str]) -> Iterator[Any]:
    """The intact messages of ``scan`` on ``topics`` in log-time order (ties in file order).

    Chunks whose time ranges overlap are merged in memory; the others are read one at a time.
    """
    wanted = {cid for cid, ch in scan.channels.items() if ch.topic in topics}
    group: list[Any] = []
    group_end = -1

    def flush() -> Iterator[Any]:
        msgs = [m for block in group for m in scan.iter_block(fh, block) if m.channel_id in wanted]
        msgs.sort(key=lambda m: m.log_time)
        yield from msgs

    for block in sorted(scan.blocks, key=lambda b: b.start_ns):
        if group and block.start_ns > group_end:
            yield from flush()
            group = []
        group.append(block)
        group_end = max(group_end, block.end_ns) if len(group) > 1 else block.end_ns
    if group:
        yield from flush()


class _Sqlite(_Impl):
    """ROS 2 SQLite storage files read directly (a lone .db3, a folder rosbags cannot open, or a damaged one with
    --salvage: then every row that still reads is read at once, and ``rec.salvaged`` says what was lost)."""

    _QUERY = "SELECT m.timestamp, t.name, t.type, m.data FROM messages m JOIN topics t ON m.topic_id = t.id"

    def __init__(self, rec: Recording, files: list[Path], problems: list[str]) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.rec = rec
        self.files = files
        self.store = get_typestore(Stores.LATEST)
        self.topics = {}
        self.rows: list[tuple[int, str, str, bytes]] | None = None
        for f in files:
            con = _sqlite_connect(f)
            try:
                for name, typ in con.execute("SELECT name, type FROM topics"):
                    self.topics.setdefault(name, TopicInfo(name, _normalise_type(typ)))
            except sqlite3.DatabaseError as err:
                if not problems:
                    raise InputError(f"{str(f)!r} is not a readable ROS 2 SQLite bag ({err}); copy it again") from None
                problems.append(f"{f.name}: its topics table does not read ({err})")
            finally:
                con.close()
        if problems:
            self._salvage(problems)
            return
        for name, (n, first, last) in _sqlite_counts(files).items():
            info = self.topics[name]
            info.count, info.first_ns, info.last_ns = n, first, last

    def _salvage(self, problems: list[str]) -> None:
        """Every row that reads; the topic counts are what was read, the loss what the tables' counts say."""
        try:
            listed: dict[str, int] | None = {k: v[0] for k, v in _sqlite_counts(self.files).items()}
        except InputError:
            listed = None
        self.rows = []
        with tempfile.TemporaryDirectory() as tmp:
            for f in self.files:
                before = len(self.rows)
                con = _sqlite_connect(_sqlite_readable(f, Path(tmp)))
                try:
                    skipped = self._read_rows(con, sum(listed.values()) if listed else 0)
                finally:
                    con.close()
                if skipped:
                    problems.append(f"{f.name}: {skipped} row ids do not read; {len(self.rows) - before} rows read")
        self.rows.sort(key=lambda r: r[0])
        for stamp, name, typ, _ in self.rows:
            info = self.topics.setdefault(name, TopicInfo(name, _normalise_type(typ)))
            info.count += 1
            info.first_ns = stamp if info.first_ns is None else min(info.first_ns, stamp)
            info.last_ns = stamp if info.last_ns is None else max(info.last_ns, stamp)
        lost = {n: c - self.topics[n].count for n, c in (listed or {}).items() if n in self.topics}
        lost = {n: c for n, c in sorted(lost.items()) if c > 0}
        self.rec.salvaged = {
            "messages": len(self.rows),
            "chunks": None,
            "chunks_total": None,
            "crc_checked": False,
            "stopped_at": problems[0],
            "problems": problems,
            "lost": {
                "messages": sum(lost.values()) if listed is not None else None,
                "topics": lost,
                "start_s": None,
                "end_s": None,
            },
        }

    def _read_rows(self, con: sqlite3.Connection, expected: int) -> int:
        """Every message row that reads, in id order: a scan that, at a damaged page, looks the ids up one by one
        until one reads again. Returns the ids that did not read."""
        assert self.rows is not None
        last, skipped, misses = 0, 0, 0
        q = f"{self._QUERY} WHERE m.id > ? ORDER BY m.id"
        one = f"{self._QUERY.replace('SELECT ', 'SELECT m.id, ')} WHERE m.id = ?"
        try:
            top = int(con.execute("SELECT max(id) FROM messages").fetchone()[0] or 0)
        except sqlite3.DatabaseError:
            top = 0
        top = max(top, expected, last + 1)
        while True:
            try:
                for row in con.execute(f"SELECT m.id, {q[len('SELECT ') :]}", (last,)):
                    last = row[0]
                    self.rows.append(row[1:])
                return skipped
            except sqlite3.DatabaseError:
                pass
            # the scan met a damaged page: find the next id that reads
            while True:
                last += 1
                if last > top + misses:
                    return skipped
                try:
                    found = con.execute(one, (last,)).fetchall()
                except sqlite3.DatabaseError:
                    found = []
                if found:
                    self.rows.append(found[0][1:])
                    break
                skipped += 1
                misses = min(misses + 1, 4096)

    def typestore(self) -> Any | None:
        return self.store

    def _decode(self, data: bytes, typ: str) -> Any:
        return self.store.deserialize_cdr(data, typ)

    def messages(self, topics: set[str]) -> Iterator[RawMessage]:
        if self.rows is not None:
            rows = [r for r in self.rows if r[1] in topics]
        else:
            rows = []
            for f in self.files:
                con = _sqlite_connect(f)
                try:
                    q = f"{self._QUERY} WHERE t.name IN ({','.join('?' * len(topics))}) ORDER BY m.timestamp"
                    rows.extend(con.execute(q, sorted(topics)).fetchall())
                except sqlite3.DatabaseError as err:
                    raise _sqlite_damaged(f, f"its messages do not read ({err})") from None
                finally:
                    con.close()
            rows.sort(key=lambda r: r[0])
        for stamp, name, typ, data in rows:
            yield RawMessage(name, _normalise_type(typ), stamp, bytes(data), self._decode)
