"""A quick seeded subset of the fault matrix (tests/benchmarks/bench_faults.py, docs/faults.md), kept by CI.

Per format one cut read with and without ``--salvage`` and one flipped byte; one kill -9 of ``focusmap run``
while detect's workers run; a few bad settings. The recordings are simulated, so ``../shared`` is not needed.
The disk-full faults are tests/cli/test_full_disk.py's.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.fixtures import faults

SEED = 1
SETTINGS = (
    "run --start 1e300",
    "--config a YAML list",
    "--out naming a file",
    "--name ../../x",
    "--name absolute path",
    "--set optimize.unobserved_sigma_m=inf",
    "--set evaluate.grid_resolution_m=1e-6",
)
BROKEN = ("traceback", "crash", "hang")


@pytest.fixture(scope="module")
def recordings(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    return faults.make_recordings(tmp_path_factory.mktemp("recordings"), seconds=4.0, seed=SEED)


@pytest.mark.parametrize("fmt", faults.FORMATS)
def test_cut_and_flipped_recordings_end_cleanly(fmt: str, recordings: dict[str, Path], tmp_path: Path) -> None:
    bag = recordings[fmt]
    clean = faults.clean_ingest(bag, tmp_path, inprocess=True)
    size = faults.storage_file(bag).stat().st_size
    cases = faults.seeded_cases(fmt, size, cuts=1, flips=1, seed=SEED)
    got = {(c.fault, c.salvage): faults.run_ingest_case(c, bag, *clean, inprocess=True).outcome for c in cases}
    assert not [k for k, v in got.items() if v in BROKEN], got
    # a cut file read normally: one error line, never a partial read with exit 0
    assert got["cut", False] in ("error", "same"), got
    # with --salvage: what was read is said, or the read stops with an error line
    assert got["cut", True] in ("error", "reported", "same"), got
    if fmt in faults.CHECKSUMMED:
        assert got["flip", False] in ("error", "same"), got
        assert got["flip", True] in ("error", "reported", "same"), got


def test_kill_9_during_detect_leaves_no_process_and_resumes_to_the_same_results(
    recordings: dict[str, Path], tmp_path: Path
) -> None:
    bag = recordings["mcap"]
    until = ("--until", "graph", "--set", "detect.workers=2")
    a, seconds = faults.clean_run(bag, tmp_path / "a", until)
    b, _ = faults.clean_run(bag, tmp_path / "b", until)
    volatile = faults.volatile_keys(a, b)
    assert any(k.startswith("detect/detections.parquet:") for k in a.keys() - volatile)

    (tmp_path / "kill").mkdir()
    killed = faults.run_kill_case(bag, tmp_path / "kill", "detect", seconds["detect"] / 2, a, volatile, until)

    assert killed.orphans == []
    assert killed.stage != "finished", "the run ended before the kill; nothing was tested"
    assert killed.identical, (killed.resume, killed.diffs)
    assert killed.skipped >= 1  # ingest, finished before the kill, was kept


@pytest.mark.parametrize("label", SETTINGS)
def test_bad_setting_is_one_error_line_and_writes_nothing_outside_out(
    label: str, recordings: dict[str, Path], tmp_path: Path
) -> None:
    (case,) = [c for c in faults.setting_cases() if c.label == label]
    result = faults.run_setting_case(case, recordings["mcap"], tmp_path / "missing.g2o")
    assert result.passed, (result.outcome, result.line, result.outside)
