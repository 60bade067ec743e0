"""``focusmap info``: what a recording holds, like ``ros2 bag info``, with counts read from the file."""

from __future__ import annotations

import datetime as dt
from pathlib import Path
from typing import Any

from stages.ingest.bags import Recording


def bag_info(path: Path, salvage: bool = False) -> dict[str, Any]:
    """Path, format, start, duration and per-topic name, type, count and rate."""
    with Recording(path, salvage=salvage) as rec:
        topics = [
            {"name": t.name, "type": t.type, "count": t.count, "rate_hz": round(t.rate_hz, 3)}
            for t in sorted(rec.topics.values(), key=lambda t: t.name)
        ]
        data: dict[str, Any] = {
            "path": str(path),
            "format": rec.format if rec.format != "ros2" else f"ros2-{rec.storage}",
            "reader": rec.reader,
            "start_ns": rec.start_ns,
            "duration_s": round((rec.end_ns - rec.start_ns) * 1e-9, 9),
            "messages": rec.message_count,
            "topics": topics,
        }
        if rec.salvaged is not None:
            data["salvaged"] = rec.salvaged
    return data


def format_info(data: dict[str, Any]) -> str:
    """The info as an aligned text table."""
    start = dt.datetime.fromtimestamp(data["start_ns"] * 1e-9, tz=dt.UTC).isoformat() if data["start_ns"] else "-"
    lines = [
        f"path:      {data['path']}",
        f"format:    {data['format']} (read with {data['reader']})",
        f"start:     {start} ({data['start_ns']} ns)",
        f"duration:  {data['duration_s']:.3f} s",
        f"messages:  {data['messages']}",
    ]
    if "salvaged" in data:
        lines.append(f"salvaged:  {data['salvaged']}")
    if data["topics"]:
        w_name = max(len(t["name"]) for t in data["topics"])
        w_type = max(len(t["type"]) for t in data["topics"])
        lines.append("topics:")
        for t in data["topics"]:
            lines.append(f"  {t['name']:<{w_name}}  {t['type']:<{w_type}}  {t['count']:>8}  {t['rate_hz']:>9.2f} Hz")
    else:
        lines.append("topics:    none")
    return "\n".join(lines)
