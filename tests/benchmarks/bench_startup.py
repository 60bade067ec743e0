"""How long the command line takes to start, against a bare Python start measured side by side.

    python tests/benchmarks/bench_startup.py [--runs 5]

Prints the median wall time of ``focusmap --help``, ``focusmap info <sample bag>`` and ``python -c pass`` over
interleaved runs, and each command's ratio to the bare interpreter (the part of the time that is focusmap's).
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
BAG = ROOT / "sample_data" / "office" / "office.bag"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=5)
    args = parser.parse_args()
    commands = {
        "python -c pass": [sys.executable, "-c", "pass"],
        "focusmap --help": [sys.executable, "-m", "cli.app", "--help"],
        "focusmap info BAG": [sys.executable, "-m", "cli.app", "info", str(BAG)],
    }
    times: dict[str, list[float]] = {k: [] for k in commands}
    for _ in range(args.runs):  # interleaved, so a busy moment hits every command alike
        for name, cmd in commands.items():
            t0 = time.perf_counter()
            subprocess.run(cmd, cwd=ROOT, check=True, capture_output=True)
            times[name].append(time.perf_counter() - t0)
    bare = statistics.median(times["python -c pass"])
    for name, ts in times.items():
        med = statistics.median(ts)
        print(f"{name:<20} median {med:6.3f} s  ({med / bare:4.1f}x a bare Python start)")


if __name__ == "__main__":
    main()
