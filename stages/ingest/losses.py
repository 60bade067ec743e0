"""What a salvage read lost, for every chunked format alike (MCAP and ROS 1): the shared report.

A format's scanner fills a :class:`ChunkLosses` per file (what it read per channel or connection id, the
stretches it could not read as :class:`Lost`, and the totals its index promises where it has one), and
:func:`salvage_report` turns them into the ``salvaged`` section of ``ingest/summary.json`` and of
``focusmap info`` (printed by :func:`stages.ingest.info.salvage_text`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any


@dataclass
class Lost:
    """A stretch of the file that could not be read: a damaged chunk or record, or the part after a cut."""

    offset: int
    reason: str
    start_ns: int | None = None
    end_ns: int | None = None
    counts: dict[int, int] | None = None
    """Messages per channel (connection) id, where an index says so."""
    cut: bool = False
    """The file ends here: what followed is unknown."""


@dataclass
class ChunkLosses:
    """What a salvage read of one file kept and lost, by channel (MCAP) or connection (ROS 1) id."""

    path: Path
    size: int
    lost: list[Lost] = field(default_factory=list)
    counts: dict[int, int] = field(default_factory=dict)
    first_ns: dict[int, int] = field(default_factory=dict)
    last_ns: dict[int, int] = field(default_factory=dict)
    chunks_total: int | None = None
    """Chunks the file's index lists (None without a readable index)."""
    chunks_read: int = 0
    expected: dict[int, int] | None = None
    """Messages per id from the file's index (None without one)."""
    start_ns: int | None = None
    end_ns: int | None = None
    """Message time range from the file's index."""
    problems: list[str] = field(default_factory=list)
    crcs: bool = False
    """Whether any chunk carried a CRC (ROS 1 has none)."""

    @property
    def messages_read(self) -> int:
        return sum(self.counts.values())

    def count(self, cid: int, t: int) -> None:
        """One message read on ``cid`` at log time ``t``."""
        self.counts[cid] = self.counts.get(cid, 0) + 1
        self.first_ns[cid] = min(self.first_ns.get(cid, t), t)
        self.last_ns[cid] = max(self.last_ns.get(cid, t), t)

    def topic_of(self, cid: int) -> str:
        return f"<channel {cid}>"


def salvage_report(scans: Sequence[ChunkLosses]) -> dict[str, Any]:
    """What a salvage read of ``scans`` kept and lost: messages, chunks, the damage, and the loss per topic
    and in time (counts from the summary's statistics or the lost chunks' message indexes where present)."""
    read = sum(s.messages_read for s in scans)
    lost_topics: dict[str, int] = {}
    known = True
    starts: list[int] = []
    ends: list[int] = []
    first_read = [t for s in scans for t in s.first_ns.values()]
    origins = [s.start_ns for s in scans if s.start_ns is not None] + first_read
    for s in scans:
        per_channel: dict[int, int] = {}
        if s.expected is not None:
            for cid, n in s.expected.items():
                per_channel[cid] = n - s.counts.get(cid, 0)
        else:
            for lost in s.lost:
                if lost.counts is None:
                    known = False
                for cid, n in (lost.counts or {}).items():
                    per_channel[cid] = per_channel.get(cid, 0) + n
        for cid, n in per_channel.items():
            if n > 0:
                topic = s.topic_of(cid)
                lost_topics[topic] = lost_topics.get(topic, 0) + n
        for lost in s.lost:
            start = lost.start_ns
            if start is None:  # nothing known of the cut part: it starts after the last message read
                start = max(s.last_ns.values(), default=s.start_ns)
            if start is not None:
                starts.append(start)
            end = s.end_ns if lost.cut else lost.end_ns
            if end is None:
                known = False  # the recording went on past the cut for an unknown time
            if end is not None:
                ends.append(end)
    origin = min(origins + starts) if origins + starts else 0
    lost_report: dict[str, Any] = {
        "messages": sum(lost_topics.values()) if known else None,
        "topics": dict(sorted(lost_topics.items())),
        "start_s": round((min(starts) - origin) * 1e-9, 3) if starts else None,
        "end_s": round((max(ends) - origin) * 1e-9, 3) if ends and known else None,
    }
    problems = [f"{s.path.name}: {p}" for s in scans for p in s.problems]
    totals = [s.chunks_total for s in scans]
    return {
        "messages": read,
        "chunks": sum(s.chunks_read for s in scans),
        "chunks_total": sum(t for t in totals if t is not None) if None not in totals else None,
        "crc_checked": any(s.crcs for s in scans),
        "stopped_at": problems[0] if problems else None,
        "problems": problems,
        "lost": lost_report,
    }
