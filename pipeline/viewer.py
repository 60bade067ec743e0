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

from pipeline.errors import InputError, PipelineError

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


BLUEPRINT_FILE = "focusmap.rbl"


def viewer_files(run_dir: Path, stages: Sequence[str], show: str | None = None) -> tuple[list[Path], str]:
    """A run's recordings in the order to open them (then its blueprint file), and the stage whose tab shows.

    Every stage's recording carries the run's layout (a tab per stage) with its own tab active, and the
    viewer takes the layout of the first recording it opens: the recording of the stage to show goes
    first. That is ``show``, else the last of ``stages`` (pipeline order) that has a recording.

    Raises:
        InputError: when the run has no recordings, or ``show`` has none.
    """
    have = [name for name in stages if (run_dir / f"{name}.rrd").is_file()]
    others = sorted(p for p in run_dir.glob("*.rrd") if p.stem not in have)  # a stage no longer in the registry
    if not have and not others:
        raise InputError(f"no .rrd recordings in {str(run_dir)!r}; run a stage first")
    if show is not None and show not in have:
        raise InputError(
            f"stage {show!r} has no recording in {str(run_dir)!r}; run it first, or show one of: "
            f"{', '.join(have) or 'none'}"
        )
    first = show or (have[-1] if have else others[0].stem)
    files = [run_dir / f"{first}.rrd", *sorted(run_dir / f"{n}.rrd" for n in have if n != first)]
    files += [p for p in others if p.stem != first]
    if (run_dir / BLUEPRINT_FILE).is_file():
        files.append(run_dir / BLUEPRINT_FILE)
    return files, first


def screenshot(
    files: Sequence[Path], out: Path, at: float = 0.5, timeout_s: float = 120.0, tab: str | None = None
) -> Path:
    """Open ``files`` in a headless viewer, put the cursor at fraction ``at`` of the ``time`` timeline, save a PNG.

    ``tab``: the tab of the layout to show (a stage's name); the picture is taken only once the viewer
    says it is the active one.

    Raises:
        PipelineError: when the viewer cannot start (no graphics driver), does not load the files in time,
            or its layout has no tab ``tab``.
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
        _take_picture(client, files, out, at, timeout_s, tab)
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


def active_tab(client: ViewerClient, tab: str | None = None) -> str | None:
    """The name of the active tab of the viewer's layout, after making ``tab`` the active one when given.

    Reads the layout of the recording on screen (a ``Tabs`` container whose tabs carry the stages' names)
    and writes it back with ``active_tab`` changed. None when the layout has no tabs.

    Raises:
        PipelineError: when ``tab`` is not one of the tabs.
    """
    layout = client.get_blueprint(of="recording").blueprint
    containers = {
        k.lstrip("/"): v.get("ContainerBlueprint", {}) for k, v in layout.items() if "ContainerBlueprint" in v
    }
    tabs = next((c for c in containers.values() if c.get("container_kind") == "Tabs"), None)
    if tabs is None:
        if tab is not None:
            raise PipelineError(f"the run's layout has no tabs; cannot show stage {tab!r}")
        return None
    names = {key: containers.get(key, {}).get("display_name") for key in tabs.get("contents", [])}
    current = names.get(tabs.get("active_tab"))
    if tab is None or current == tab:
        return current
    key = next((k for k, name in names.items() if name == tab), None)
    if key is None:
        raise PipelineError(f"the run's layout has no tab {tab!r}; tabs: {', '.join(str(n) for n in names.values())}")
    tabs["active_tab"] = key
    client.set_blueprint(layout, of="recording")
    return active_tab(client)


def _take_picture(
    client: ViewerClient, files: Sequence[Path], out: Path, at: float, timeout_s: float, tab: str | None = None
) -> None:
    """Open the files, wait until they have loaded, show ``tab``, place the time cursor at ``at``, save the PNG."""
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
    if tab is not None and active_tab(client, tab) != tab:
        raise PipelineError(f"the viewer did not show the tab of stage {tab!r}")
    timeline = next((t for t in recording.timelines if t.name == "time"), None)
    if timeline is not None and timeline.start is not None and timeline.end is not None:
        stamp = timeline.start + at * (timeline.end - timeline.start)
        client.set_time("time", timestamp=stamp * 1e-9, play_state="paused", recording=recording.store_id)
    time.sleep(2.0)  # let the views draw the data at the cursor
    out.parent.mkdir(parents=True, exist_ok=True)
    client.save_screenshot(str(out))
