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
        lines.append(f"salvaged:  {salvage_text(data['salvaged'])}")
    if data["topics"]:
        w_name = max(len(t["name"]) for t in data["topics"])
        w_type = max(len(t["type"]) for t in data["topics"])
        lines.append("topics:")
        for t in data["topics"]:
            lines.append(f"  {t['name']:<{w_name}}  {t['type']:<{w_type}}  {t['count']:>8}  {t['rate_hz']:>9.2f} Hz")
    else:
        lines.append("topics:    none")
    return "\n".join(lines)


def salvage_text(report: dict[str, Any]) -> str:
    """One line for a salvage report: what was read, what was lost (time range, messages per topic), why."""
    if "lost" not in report:  # a report without a loss estimate (ROS 1): its fields as they are
        return str(report)
    parts = [f"read {report['messages']} messages"]
    if report.get("chunks_total") is not None:
        parts[0] += f" ({report['chunks']} of {report['chunks_total']} chunks)"
    lost = report["lost"]
    if not report.get("problems"):
        return parts[0] + "; nothing lost"
    if lost["messages"] == 0:  # damage that cost no message (a length field read around)
        return "; ".join([parts[0], "nothing lost", *report["problems"]])
    count = f"{lost['messages']} messages" if lost["messages"] is not None else "an unknown number of messages"
    start = f"{lost['start_s']:.3f} s" if lost["start_s"] is not None else "?"
    end = f"{lost['end_s']:.3f} s" if lost["end_s"] is not None else "the unknown end"
    text = f"lost {count} from {start} to {end}"
    if lost["topics"]:
        text += " (" + ", ".join(f"{t} {n}" for t, n in lost["topics"].items()) + ")"
    parts.append(text)
    parts.extend(report["problems"])
    return "; ".join(parts)
