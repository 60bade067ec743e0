"""Where a stage's memory peaks: run one focusmap command in this process and sample its resident size.

    python tests/benchmarks/rss_profile.py OUT.txt evaluate RUN --force

A thread reads ``/proc/self/statm`` every 5 ms; per 2 s window it keeps the highest RSS and the main thread's stack
at that moment (the frames outside Python and its libraries). OUT.txt gets the windows' maxima in time order, then
the highest local maxima with their stacks; the overall peak goes to stderr. It sees this process only: a stage's
worker processes (evaluate's navigation worker, detect's pool) are not counted, which is what ``bench_scaling.py``
measures. Linux only. The sampling costs a few per cent of one core.
"""

from __future__ import annotations

import os
import sys
import sysconfig
import threading
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from tests.fixtures.memory import resident_mib  # noqa: E402

WINDOW_S = 2.0
PERIOD_S = 0.005
STACK_DEPTH = 7
SHOWN_PEAKS = 12


@dataclass
class Window:
    start_s: float
    peak_mib: float = 0.0
    stack: list[str] = field(default_factory=list)


_PATHS = sysconfig.get_paths()
LIBRARY_PREFIXES = (*{_PATHS[k] for k in ("stdlib", "platstdlib", "purelib", "platlib")}, "<frozen")
"""Frames from these files are Python's or the installed libraries', not the caller's code."""


def project_stack(thread_id: int) -> list[str]:
    """The thread's innermost :data:`STACK_DEPTH` frames outside Python and its libraries, as ``path:line function``
    (paths relative to the project)."""
    frame = sys._current_frames().get(thread_id)
    if frame is None:
        return []
    ours = [fs for fs in traceback.extract_stack(frame) if not fs.filename.startswith(LIBRARY_PREFIXES)]
    del frame
    root = f"{ROOT}{os.sep}"
    return [f"{fs.filename.removeprefix(root)}:{fs.lineno} {fs.name}" for fs in ours][-STACK_DEPTH:]


class Sampler(threading.Thread):
    def __init__(self, watched: int) -> None:
        super().__init__(daemon=True)
        self.watched = watched
        self.windows: list[Window] = []
        self.stopped = threading.Event()

    def run(self) -> None:
        t0 = time.monotonic()
        cur = Window(0.0)
        while not self.stopped.is_set():
            t = time.monotonic() - t0
            if t - cur.start_s >= WINDOW_S:
                self.windows.append(cur)
                cur = Window(t)
            r = resident_mib()
            if r > cur.peak_mib:
                cur.peak_mib, cur.stack = r, project_stack(self.watched)
            time.sleep(PERIOD_S)
        self.windows.append(cur)


def local_maxima(windows: list[Window], reach: int = 3) -> list[Window]:
    """Windows at least as high as every window within ``reach`` of them, highest first."""
    out = [
        w
        for i, w in enumerate(windows)
        if w.peak_mib >= max(x.peak_mib for x in windows[max(0, i - reach) : i + reach + 1])
    ]
    return sorted(out, key=lambda w: -w.peak_mib)


def report(windows: list[Window]) -> str:
    lines = ["windows (s: MiB): " + " ".join(f"{w.start_s:.0f}:{w.peak_mib:.0f}" for w in windows), ""]
    for w in local_maxima(windows)[:SHOWN_PEAKS]:
        lines.append(f"PEAK {w.start_s:7.1f} s {w.peak_mib:7.0f} MiB")
        lines.extend(f"    {s}" for s in w.stack)
    return "\n".join(lines) + "\n"


def main() -> None:
    if len(sys.argv) < 3 or not sys.platform.startswith("linux"):
        raise SystemExit(__doc__)
    out, args = Path(sys.argv[1]), sys.argv[2:]
    from cli.app import main as focusmap

    sampler = Sampler(threading.get_ident())
    sampler.start()
    sys.argv = ["focusmap", *args]
    code: int | str | None = 0
    try:
        focusmap()
    except SystemExit as done:
        code = done.code
    finally:
        sampler.stopped.set()
        sampler.join()
        out.write_text(report(sampler.windows))
        print(f"peak {max(w.peak_mib for w in sampler.windows):.0f} MiB; windows and stacks in {out}", file=sys.stderr)
    sys.exit(code)


if __name__ == "__main__":
    main()
