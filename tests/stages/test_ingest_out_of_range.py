"""Values no sensor gives (a denormal or non-finite covariance, a NaN pose, a negative laser range): without
--salvage ingest stops with one line naming the topic; with it, those messages are dropped and counted per
topic in summary.json."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline.config import load_settings
from pipeline.errors import InputError
from pipeline.run_folder import RunFolder
from pipeline.runner import run_stage
from sample_data.simulate import SimConfig, simulate, write_bag
from stages import REGISTRY

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def clean(tmp_path_factory: pytest.TempPathFactory) -> Path:
    rec = simulate(SimConfig(seed=3, path="corridor", duration_s=3.0, image_format="jpeg"))
    return write_bag(rec, tmp_path_factory.mktemp("oor") / "clean.bag", "ros1")


def spoil(src: Path, dst: Path, topic: str, index: int, change) -> Path:
    """``src`` written again with message ``index`` of ``topic`` changed by ``change(msg)``."""
    from rosbags.rosbag1 import Reader, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    with Reader(src) as reader, Writer(dst) as writer:
        conns = {
            c.id: writer.add_connection(c.topic, c.msgtype, msgdef=c.msgdef.data, md5sum=c.digest)
            for c in reader.connections
        }
        seen = 0
        for c, t, data in reader.messages():
            if c.topic == topic:
                if seen == index:
                    msg = store.deserialize_ros1(data, c.msgtype)
                    change(msg)
                    data = store.serialize_ros1(msg, c.msgtype)
                seen += 1
            writer.write(conns[c.id], t, data)
    return dst


def _ingest(bag: Path, tmp: Path, *sets: str) -> dict:
    run = RunFolder.create(tmp / "runs" / bag.stem, bag)
    run_stage(run, REGISTRY, "ingest", load_settings(REGISTRY.models(), None, list(sets)))
    return json.loads((run.stage_dir("ingest") / "summary.json").read_text())


def _set(owner, name: str, i: int, value: float) -> None:
    """``owner.name[i] = value`` for a read-only message array."""
    values = getattr(owner, name).copy()
    values[i] = value
    setattr(owner, name, values)


def _denormal(msg) -> None:
    _set(msg.twist, "covariance", 0, 3.28e-307)  # what a cut SQLite bag gave for a twist_cov of 0.0009


def _nan_pose(msg) -> None:
    msg.pose.pose.position.x = math.nan


def _negative_range(msg) -> None:
    _set(msg, "ranges", 3, -2.0)


@pytest.mark.parametrize(
    ("topic", "change", "why"),
    [
        ("/odom", _denormal, "a denormal covariance"),
        ("/odom", _nan_pose, "a non-finite pose or twist"),
        ("/scan", _negative_range, "negative ranges"),
    ],
)
def test_out_of_range_values_stop_or_are_dropped(clean: Path, tmp_path: Path, topic: str, change, why: str) -> None:
    before = _ingest(clean, tmp_path)
    assert before["dropped"] == {}
    bag = spoil(clean, tmp_path / "spoilt.bag", topic, 5, change)
    with pytest.raises(InputError, match=rf"message on {topic} .* has {why}; .*--salvage"):
        _ingest(bag, tmp_path)
    after = _ingest(bag, tmp_path, "ingest.salvage=true")
    assert after["dropped"] == {topic: {why: 1}}
    key = {"/odom": "odometry", "/scan": "scans"}[topic]
    assert after[key] == before[key] - 1


def test_inf_and_nan_ranges_are_legal(clean: Path, tmp_path: Path) -> None:
    def inf_and_nan(msg) -> None:
        _set(msg, "ranges", 0, math.inf)  # REP 117: no return
        _set(msg, "ranges", 1, math.nan)  # REP 117: an erroneous reading

    bag = spoil(clean, tmp_path / "legal.bag", "/scan", 2, inf_and_nan)
    assert _ingest(bag, tmp_path)["dropped"] == {}


def test_cli_warning_line_names_topic_and_count(clean: Path, tmp_path: Path) -> None:
    bag = spoil(clean, tmp_path / "den.bag", "/odom", 7, _denormal)
    cmd = [sys.executable, "-m", "cli.app", "ingest", str(bag), "--out", str(tmp_path / "runs")]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    (line,) = proc.stderr.strip().splitlines()
    assert line.startswith("error: ") and "/odom" in line and "--salvage" in line
    proc = subprocess.run([*cmd, "--salvage"], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert proc.returncode == 0, proc.stderr
    warnings = [ln for ln in proc.stderr.splitlines() if ln.strip().startswith("warning:")]
    assert len(warnings) == 1 and "/odom 1 (1 with a denormal covariance)" in warnings[0]
