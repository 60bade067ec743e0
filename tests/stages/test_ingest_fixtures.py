"""info and ingest on real recordings from other projects (../shared/data)."""

from __future__ import annotations

import sqlite3
from collections import Counter
from pathlib import Path

import pytest

from pipeline.errors import InputError
from stages.ingest.bags import Recording
from stages.ingest.info import bag_info

GOOD = [
    "rosbag1-fixtures/example.bag",
    "rosbag1-fixtures/example-bz2.bag",
    "rosbag1-fixtures/example-unsorted-chunks.bag",
    "rosbag1-fixtures/no-messages.bag",
    "rosbag2-fixtures/sqlite3_cdr_test",
    "rosbag2-fixtures/sqlite3_wbag_split",
    "rosbag2-fixtures/mcap_cdr_test",
    "rosbag2-fixtures/mcap_wbag_split",
    "rosbag2-fixtures/empty_bag",
    "rosbag2-fixtures/mcap_cdr_test/cdr_test_0.mcap",
    "rosbag2-fixtures/sqlite3_cdr_test/cdr_test_0.db3",
]


def _counts_by_reading_records(path: Path) -> Counter[str]:
    """Per-topic counts from the records themselves, independently of any index or summary."""
    counts: Counter[str] = Counter()
    if path.suffix == ".bag":
        from rosbags.rosbag1 import Reader

        with Reader(path) as r:
            for conn, _t, _d in r.messages():
                counts[conn.topic] += 1
        return counts
    files = [path] if path.is_file() else sorted(path.glob("*.db3")) + sorted(path.glob("*.mcap"))
    for f in files:
        if f.suffix == ".db3":
            con = sqlite3.connect(f)
            for (name,) in con.execute("SELECT t.name FROM messages m JOIN topics t ON t.id = m.topic_id"):
                counts[name] += 1
            con.close()
        else:
            from mcap.records import Channel, Message
            from mcap.stream_reader import StreamReader

            channels = {}
            with f.open("rb") as fh:
                for rec in StreamReader(fh).records:
                    if isinstance(rec, Channel):
                        channels[rec.id] = rec.topic
                    elif isinstance(rec, Message):
                        counts[channels[rec.channel_id]] += 1
    return counts


@pytest.mark.parametrize("rel", GOOD)
def test_info_counts_equal_the_records(shared_data: Path, rel: str) -> None:
    path = shared_data / rel
    data = bag_info(path)
    got = {t["name"]: t["count"] for t in data["topics"] if t["count"]}
    assert got == dict(_counts_by_reading_records(path))
    assert data["messages"] == sum(got.values())


def test_info_fields_and_rates(shared_data: Path) -> None:
    data = bag_info(shared_data / "rosbag1-fixtures" / "example.bag")
    assert data["format"] == "ros1" and data["duration_s"] == pytest.approx(21.700086, abs=1e-5)
    pose = next(t for t in data["topics"] if t["name"] == "/turtle1/pose")
    assert pose["type"] == "turtlesim/msg/Pose" and pose["count"] == 1344
    assert pose["rate_hz"] == pytest.approx(62.5, rel=0.01)
    split = bag_info(shared_data / "rosbag2-fixtures" / "mcap_wbag_split")
    assert split["format"] == "ros2-mcap" and len(split["topics"]) == 8 and split["messages"] == 6074


@pytest.mark.parametrize("rel", ["rosbag1-fixtures/empty-file.bag", "rosbag1-fixtures/asci-file.txt"])
def test_broken_fixtures_fail_with_a_reason(shared_data: Path, rel: str) -> None:
    with pytest.raises(InputError, match=r"empty|not a ROS bag"):
        Recording(shared_data / rel)


def test_messages_come_in_time_order(shared_data: Path) -> None:
    with Recording(shared_data / "rosbag1-fixtures" / "example-unsorted-chunks.bag") as rec:
        stamps = [m.log_time_ns for m in rec.messages(rec.topics)]
    assert stamps == sorted(stamps) and len(stamps) == 3
