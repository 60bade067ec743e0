"""Every bad input: exit code non-zero, one line on stderr starting with 'error:', nothing half-written."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.fixtures.bags import write_minimal_bag

FOCUSMAP = [sys.executable, "-m", "cli.app"]
ROOT = Path(__file__).resolve().parents[2]


def focusmap(*args: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*FOCUSMAP, *map(str, args)], capture_output=True, text=True, cwd=ROOT, timeout=300)


def assert_one_error_line(proc: subprocess.CompletedProcess[str], *needles: str) -> None:
    assert proc.returncode != 0, proc.stdout
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("error: "), lines[0]
    assert "Traceback" not in proc.stderr
    for n in needles:
        assert n in lines[0], lines[0]


def assert_no_stage_output(out: Path) -> None:
    if not out.exists():
        return
    for run in out.iterdir():
        assert not (run / "ingest").exists(), f"half-written ingest in {run}"
        assert not (run / ".partial").exists()
        assert not (run / "ingest.rrd").exists()


def test_missing_file(tmp_path: Path) -> None:
    proc = focusmap("ingest", tmp_path / "nope.bag", "--out", tmp_path / "runs")
    assert_one_error_line(proc, "does not exist")
    assert not (tmp_path / "runs").exists()


def test_zero_byte_file(tmp_path: Path) -> None:
    bag = tmp_path / "empty.bag"
    bag.write_bytes(b"")
    proc = focusmap("ingest", bag, "--out", tmp_path / "runs")
    assert_one_error_line(proc, "empty (0 bytes)")
    assert_no_stage_output(tmp_path / "runs")


def test_text_file_named_bag(tmp_path: Path) -> None:
    bag = tmp_path / "notes.bag"
    bag.write_text("these are not messages\n")
    proc = focusmap("ingest", bag, "--out", tmp_path / "runs")
    assert_one_error_line(proc, "is not a ROS bag or MCAP file")
    assert_no_stage_output(tmp_path / "runs")


def test_bag_with_no_messages(shared_data: Path, tmp_path: Path) -> None:
    proc = focusmap("ingest", shared_data / "rosbag1-fixtures" / "no-messages.bag", "--out", tmp_path / "runs")
    assert_one_error_line(proc, "holds no messages")
    assert_no_stage_output(tmp_path / "runs")


def test_bag_with_no_image_topic(shared_data: Path, tmp_path: Path) -> None:
    proc = focusmap("ingest", shared_data / "rosbag1-fixtures" / "example.bag", "--out", tmp_path / "runs")
    assert_one_error_line(proc, "no camera image topic", "/turtle1/pose (turtlesim/msg/Pose)")
    assert_no_stage_output(tmp_path / "runs")


def test_camera_info_with_zero_focal_length(tmp_path: Path) -> None:
    bag = write_minimal_bag(tmp_path / "uncalibrated.bag", focal=0.0)
    before = bag.read_bytes()
    proc = focusmap("ingest", bag, "--out", tmp_path / "runs")
    assert_one_error_line(proc, "zero focal length", "--camera FILE")
    assert_no_stage_output(tmp_path / "runs")
    assert bag.read_bytes() == before


def test_unknown_set_key(tmp_path: Path) -> None:
    bag = write_minimal_bag(tmp_path / "ok.bag")
    proc = focusmap("ingest", bag, "--out", tmp_path / "runs", "--set", "ingest.frame_strid=2")
    assert_one_error_line(proc, "unknown key ingest.frame_strid", "frame_stride")
    assert not (tmp_path / "runs").exists()


def _truncated_copy(src: Path, dst: Path, keep: float) -> Path:
    shutil.copy(src, dst)
    with dst.open("r+b") as fh:
        fh.truncate(int(dst.stat().st_size * keep))
    return dst


def test_truncated_bag_fails_and_salvage_recovers(shared_data: Path, tmp_path: Path) -> None:
    bag = _truncated_copy(shared_data / "rosbag1-fixtures" / "example.bag", tmp_path / "cut.bag", 0.6)
    proc = focusmap("info", bag)
    assert_one_error_line(proc, "truncated or damaged", "--salvage")
    proc = focusmap("info", bag, "--salvage", "--json")
    assert proc.returncode == 0, proc.stderr
    import json

    data = json.loads(proc.stdout)
    assert 0 < data["messages"] < 8647
    assert data["salvaged"]["messages"] == data["messages"]
    assert data["salvaged"]["stopped_at"]


@pytest.fixture(scope="module")
def minimal_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, subprocess.CompletedProcess[str]]:
    """``focusmap ingest`` of the minimal bag with a calibrated camera, once for the tests that read its run
    folder (they do not change it); returns the run folder and the finished process."""
    tmp = tmp_path_factory.mktemp("minimal")
    bag = write_minimal_bag(tmp / "ok.bag")
    return tmp / "runs" / "ok", focusmap("ingest", bag, "--out", tmp / "runs")


def test_ingest_minimal_bag_works(minimal_run: tuple[Path, subprocess.CompletedProcess[str]]) -> None:
    """The control for the cases above: the same bag with a calibrated camera ingests."""
    run, proc = minimal_run
    assert proc.returncode == 0, proc.stderr
    assert (run / "ingest" / "frames.parquet").is_file()


@pytest.mark.parametrize(
    "args",
    [
        ["--help"],
        ["info", "--help"],
        ["ingest", "--help"],
        ["run", "--help"],
        ["view", "--help"],
        ["show-config", "--help"],
    ],
)
def test_help(args: list[str]) -> None:
    proc = focusmap(*args)
    assert proc.returncode == 0 and "Usage" in proc.stdout


def test_view_opens_every_stage_recording_with_the_run_layout(
    minimal_run: tuple[Path, subprocess.CompletedProcess[str]],
) -> None:
    run, ingested = minimal_run
    assert ingested.returncode == 0, ingested.stderr
    proc = focusmap("view", run, "--print")
    assert proc.returncode == 0, proc.stderr
    args = proc.stdout.split()
    assert args[0].endswith("rerun")
    assert args[1:] == [str(run / "ingest.rrd"), str(run / "focusmap.rbl")]
    proc = focusmap("view", run.parent / "nothing")
    assert_one_error_line(proc, "does not exist")


def test_view_without_a_display_is_one_error_line(minimal_run: tuple[Path, subprocess.CompletedProcess[str]]) -> None:
    """No X11 or Wayland display: one line saying so and what to do instead, before any viewer starts."""
    import os

    run, ingested = minimal_run
    assert ingested.returncode == 0, ingested.stderr
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY", "WAYLAND_SOCKET")}
    proc = subprocess.run([*FOCUSMAP, "view", str(run)], capture_output=True, text=True, cwd=ROOT, timeout=60, env=env)
    if not sys.platform.startswith("linux"):
        pytest.skip("the display check is for Linux")
    assert_one_error_line(proc, "no display", "--screenshot")


def test_view_screenshot_from_a_headless_viewer(
    headless_viewer: None, minimal_run: tuple[Path, subprocess.CompletedProcess[str]], tmp_path: Path
) -> None:
    """A picture of the run without a screen; skipped (with the viewer's message) where the machine has no
    Vulkan driver, found by the ``headless_viewer`` probe. Where the viewer can draw, a failure here is focusmap's."""
    from pipeline.viewer import screenshot

    run, ingested = minimal_run
    assert ingested.returncode == 0, ingested.stderr
    out = tmp_path / "view.png"
    screenshot([run / "ingest.rrd"], out, timeout_s=60)
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size > 10_000


def test_view_opens_the_recording_of_the_stage_to_show_first(tmp_path: Path) -> None:
    """The viewer takes the layout of the first recording it opens (each has its own stage's tab active)."""
    from pipeline.errors import InputError
    from pipeline.viewer import viewer_files

    stages = ["ingest", "detect", "graph"]
    for name in ("ingest.rrd", "detect.rrd", "focusmap.rbl"):
        (tmp_path / name).write_bytes(b"x")
    files, tab = viewer_files(tmp_path, stages)  # default: the last stage that ran
    assert (tab, [f.name for f in files]) == ("detect", ["detect.rrd", "ingest.rrd", "focusmap.rbl"])
    files, tab = viewer_files(tmp_path, stages, "ingest")
    assert (tab, [f.name for f in files]) == ("ingest", ["ingest.rrd", "detect.rrd", "focusmap.rbl"])
    with pytest.raises(InputError, match=r"stage 'graph' has no recording .* one of: ingest, detect"):
        viewer_files(tmp_path, stages, "graph")


def test_view_screenshot_shows_the_tab_asked_for(headless_viewer: None, tmp_path: Path) -> None:
    """``--stage`` picks the tab of the picture; skipped where the machine has no Vulkan driver."""
    from pipeline.errors import PipelineError
    from pipeline.viewer import screenshot
    from sample_data.simulate import SimConfig, simulate, write_bag

    rec = simulate(SimConfig(seed=1, path="corridor", duration_s=2.0, image_width=320, image_height=240))
    bag = write_bag(rec, tmp_path / "short.bag", "ros1")
    made = focusmap("run", bag, "--out", tmp_path / "runs", "--until", "detect", "--set", "detect.workers=1")
    assert made.returncode == 0, made.stderr
    copy = tmp_path / "runs" / "short"
    files = sorted(copy.glob("*.rrd"))  # detect.rrd first: its layout has the detect tab active
    out = tmp_path / "ingest.png"
    screenshot(files, out, timeout_s=60, tab="ingest")  # raises unless the viewer says the ingest tab shows
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(PipelineError, match="no tab 'nope'"):
        screenshot(files, tmp_path / "nope.png", timeout_s=60, tab="nope")
    proc = focusmap("view", copy, "--screenshot", tmp_path / "cli.png", "--stage", "ingest")
    assert proc.returncode == 0 and proc.stdout.strip() == f"picture: {tmp_path / 'cli.png'}", proc.stderr


def test_view_screenshot_without_graphics_is_one_error_line(
    viewer_problem: str | None, minimal_run: tuple[Path, subprocess.CompletedProcess[str]], tmp_path: Path
) -> None:
    """Where the viewer cannot draw, ``view --screenshot`` says so and what to install, with no internal error and
    no picture (the viewer's own panic text may come before focusmap's line: it is the viewer's stderr)."""
    if viewer_problem is None:
        pytest.skip("this machine's headless viewer can draw; the no-graphics path is not reachable here")
    run, ingested = minimal_run
    assert ingested.returncode == 0, ingested.stderr
    out = tmp_path / "view.png"
    proc = focusmap("view", run, "--screenshot", out)
    assert proc.returncode == 1, proc.stderr
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("error: the headless Rerun viewer") and "Vulkan driver" in last, proc.stderr
    assert "internal error" not in proc.stderr and "Traceback" not in proc.stderr
    assert not out.exists()
