"""Damaged ROS 2 SQLite bags: a cut file is one error naming the damage (SQLite itself reads a file cut by a
few bytes silently wrong), and --salvage reads every row that still reads."""

from __future__ import annotations

import shutil
from collections import Counter
from pathlib import Path

import pytest

from pipeline.errors import InputError
from sample_data.simulate import SimConfig, simulate, write_bag
from stages.ingest.bags import Recording


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    rec = simulate(SimConfig(seed=3, path="corridor", duration_s=4.0, image_format="jpeg"))
    return write_bag(rec, tmp_path_factory.mktemp("sqlite") / "bag", "ros2-sqlite")


def read_all(path: Path, salvage: bool) -> tuple[Counter[tuple[str, int]], dict | None]:
    with Recording(path, salvage=salvage) as rec:
        got = Counter((m.topic, m.log_time_ns) for m in rec.messages(rec.topics))
        assert {t.name: t.count for t in rec.topics.values() if t.count} == dict(Counter(t for t, _ in got))
    return got, rec.salvaged


@pytest.mark.parametrize("cut", [1, 100, 4096, 100_000, 300_000])
def test_a_cut_database_is_named_and_salvage_reads_the_rows_that_read(folder: Path, tmp_path: Path, cut: int) -> None:
    everything, _ = read_all(folder, salvage=False)
    bag = shutil.copytree(folder, tmp_path / "bag")
    (db,) = bag.glob("*.db3")
    with db.open("r+b") as fh:
        fh.truncate(db.stat().st_size - cut)
    with pytest.raises(InputError, match=r"is damaged: the file is cut: .*--salvage"):
        read_all(bag, salvage=False)
    got, report = read_all(bag, salvage=True)
    assert got & everything == got  # nothing invented
    assert report is not None and "the file is cut" in report["stopped_at"]
    if cut <= 100:  # the last page is short by less than a page: every row still reads
        assert got == everything
    else:
        assert 0 < sum(got.values()) < sum(everything.values())
