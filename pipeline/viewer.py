"""Pictures of a run's recordings without a screen, through Rerun's headless viewer.

The viewer is spawned headless on a free local port (never the default one, where a viewer left
running would receive the data), the files are opened, and only once everything has loaded is the
time cursor placed and the picture taken. Needs a Vulkan driver (Debian: ``mesa-vulkan-drivers``).
Uses ``rerun.experimental.ViewerClient`` of rerun-sdk 0.41 (pinned in pyproject.toml).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import socket
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from pipeline.errors import PipelineError

if TYPE_CHECKING:
    from rerun.experimental import ViewerClient


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def rerun_executable() -> str:
    """The ``rerun`` binary of this environment (beside the Python that runs focusmap), else on PATH."""
    beside = Path(sys.executable).with_name("rerun")
    if beside.exists():
        return str(beside)
    found = shutil.which("rerun")
    if found is None:
        raise PipelineError("the rerun viewer is not installed; pip install rerun-sdk (a focusmap dependency)")
    return found


def display_problem(env: dict[str, str] | None = None) -> str | None:
    """Why a viewer window cannot open on this machine (Linux without X11 or Wayland), else None."""
    env = dict(os.environ) if env is None else env
    if sys.platform.startswith("linux") and not any(
        env.get(v) for v in ("DISPLAY", "WAYLAND_DISPLAY", "WAYLAND_SOCKET")
    ):
        return "there is no display here (neither DISPLAY nor WAYLAND_DISPLAY is set)"
    return None


def screenshot(files: Sequence[Path], out: Path, at: float = 0.5, timeout_s: float = 120.0) -> Path:
    """Open ``files`` in a headless viewer, put the cursor at fraction ``at`` of the ``time`` timeline, save a PNG.

    Raises:
        PipelineError: when the viewer cannot start (no graphics driver) or does not load the files in time.
    """
    from rerun.experimental import ViewerClient

    os.environ.setdefault("RUST_LOG", "error")  # the viewer's own log lines are not the user's business
    if not os.environ.get("XDG_RUNTIME_DIR"):  # Mesa complains on stderr without one (machines with no session)
        os.environ["XDG_RUNTIME_DIR"] = tempfile.mkdtemp(prefix="focusmap-xdg-")
    try:
        client = ViewerClient.spawn(
            headless=True, port=_free_port(), hide_welcome_screen=True, executable_path=rerun_executable()
        )
    except Exception as err:
        raise PipelineError(
            f"the headless Rerun viewer did not start ({err}); it needs a Vulkan driver (Debian: mesa-vulkan-drivers)"
        ) from None
    try:
        _take_picture(client, files, out, at, timeout_s)
    except PipelineError:
        raise
    except Exception as err:  # the viewer died after it started: on a machine without graphics, it exits at once
        raise PipelineError(
            f"the headless Rerun viewer stopped before the picture was taken ({type(err).__name__}: {err}); "
            "it needs a Vulkan driver (Debian: mesa-vulkan-drivers)"
        ) from None
    finally:
        with contextlib.suppress(Exception):  # the viewer may already be gone
            client.quit()
    return out


def _take_picture(client: ViewerClient, files: Sequence[Path], out: Path, at: float, timeout_s: float) -> None:
    """Open the files, wait until they have loaded, place the time cursor at fraction ``at`` and save the PNG."""
    client.open([str(f) for f in files])
    deadline = time.monotonic() + timeout_s
    while True:
        state = client.get_state()
        if not state.loading and state.recordings and all(r.timelines for r in state.recordings):
            break
        if time.monotonic() > deadline:
            raise PipelineError(f"the viewer did not finish loading {len(files)} files in {timeout_s:.0f} s")
        time.sleep(0.25)
    recording = state.recordings[0]
    client.set_location(recording.location)
    time.sleep(0.5)
    timeline = next((t for t in recording.timelines if t.name == "time"), None)
    if timeline is not None and timeline.start is not None and timeline.end is not None:
        stamp = timeline.start + at * (timeline.end - timeline.start)
        client.set_time("time", timestamp=stamp * 1e-9, play_state="paused", recording=recording.store_id)
    time.sleep(2.0)  # let the views draw the data at the cursor
    out.parent.mkdir(parents=True, exist_ok=True)
    client.save_screenshot(str(out))
