"""Growth with the recording's length (issue #16): per stage, time and peak memory on 2, 4, 8, 16 minute recordings.

    python tests/benchmarks/bench_scaling.py --out /tmp/scaling [--minutes 2 4 8 16] [--format ros1]
        [--image-format jpeg] [--stages ingest detect ...]

Each recording is the simulator's corridor there and back, driven lap after lap (``--laps``) until it lasts the
given minutes (640x480 JPEG at 5 Hz, or raw pixels with ``--image-format bgr8``: 0.9 MB a frame; wheel odometry,
a laser). Every stage runs as its own ``focusmap`` command
inside a fresh wrapper process, so the wrapper's ``RUSAGE_CHILDREN`` peak is that stage's (its worker processes
included: the largest single process, not their sum). Printed per stage: the wall time and peak RSS per length,
the growth exponent fitted on log-log (1 = linear), and the RSS at one hour on the line fitted to it (fixed cost
plus a part per minute: with about 250 MiB of imports, the log-log exponent reads linear growth as sub-linear and
extrapolates too low); the whole run's time over the recording's duration; and the peak RSS at an hour both ways.
Nothing is asserted: the machine is shared.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from tests.fixtures.memory import command_usage  # noqa: E402

STAGES = ("ingest", "detect", "graph", "select_landmarks", "select_measurements", "optimize", "evaluate")
SIM_TAG_SIZE_M = 0.16
"""The simulator's tag size (``sample_data/simulate.py``'s ``--tag-size`` default), told to detect."""
LAP_S = 63.6
"""One more lap of the corridor there and back, with the turn before it, s (the first is 57.7 s)."""


def laps_for(minutes: float) -> int:
    """Laps whose recording lasts about ``minutes``."""
    return max(1, round((60.0 * minutes - 57.7) / LAP_S) + 1)


def measured(cmd: list[str]) -> tuple[float, float]:
    """(wall s, peak RSS MiB) of ``cmd`` run in a fresh wrapper process."""
    wall, _, rss = command_usage(cmd)
    return wall, rss


def slope(x: list[float], y: list[float]) -> float:
    """Least-squares slope of log y on log x (NaN with fewer than two points or a non-positive value)."""
    if len(x) < 2 or min(y) <= 0:
        return float("nan")
    return float(np.polyfit(np.log(x), np.log(y), 1)[0])


def affine_at(x: list[float], y: list[float], at: float) -> float:
    """``y`` at ``at`` on the least-squares line ``y = a + b x``: a fixed cost (the imports) plus a part that grows.
    The power law's exponent reads a large fixed cost as sub-linear growth and extrapolates too low; the line does
    not (NaN with fewer than two points)."""
    if len(x) < 2:
        return float("nan")
    b, a = np.polyfit(x, y, 1)
    return float(a + b * at)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True, help="folder for the recordings and run folders")
    parser.add_argument("--minutes", type=float, nargs="+", default=[2.0, 4.0, 8.0, 16.0])
    parser.add_argument("--format", default="ros1", choices=("ros1", "ros2-sqlite", "ros2-mcap", "mcap"))
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument("--image-format", default="jpeg", choices=("jpeg", "png", "mono8", "bgr8"))
    parser.add_argument("--stages", nargs="+", default=list(STAGES), choices=STAGES, help="run these stages only")
    args = parser.parse_args()
    stages = [s for s in STAGES if s in args.stages]
    args.out.mkdir(parents=True, exist_ok=True)
    focusmap = str(Path(sys.executable).with_name("focusmap"))
    rows: dict[float, dict[str, tuple[float, float]]] = {}
    durations: dict[float, float] = {}
    for minutes in args.minutes:
        name = f"m{minutes:g}" + ("" if args.image_format == "jpeg" else f"_{args.image_format}")
        laps = laps_for(minutes)
        bag = args.out / (
            name if args.format.startswith("ros2") else f"{name}.bag" if args.format == "ros1" else f"{name}.mcap"
        )
        if not bag.exists():
            t0 = time.perf_counter()
            subprocess.run(
                [sys.executable, "-m", "sample_data.simulate", "--out", str(args.out), "--name", name, "--format",
                 args.format, "--seed", str(args.seed), "--path", "corridor_return", "--laps", str(laps),
                 "--laser-sweep", "--image-format", args.image_format],
                check=True, cwd=ROOT, stdout=subprocess.DEVNULL,
            )  # fmt: skip
            print(f"simulated {name}: {laps} laps in {time.perf_counter() - t0:.0f} s", flush=True)
        run = args.out / "runs" / name
        rows[minutes] = {}
        for stage in stages:
            cmd = [focusmap, "ingest", str(bag), "--out", str(run.parent), "--name", name, "--force"]
            if stage != "ingest":
                cmd = [focusmap, stage.replace("_", "-"), str(run), "--force"]
            if stage == "detect":  # the simulator's printed size (the default 0.162 m would make the map 1.25 % small)
                cmd += ["--set", f"detect.tag_size_m={SIM_TAG_SIZE_M:g}"]
            rows[minutes][stage] = measured(cmd)
            print(f"{name} {stage:20s} {rows[minutes][stage][0]:8.1f} s {rows[minutes][stage][1]:8.0f} MiB", flush=True)
        durations[minutes] = float(json.loads((run / "ingest" / "summary.json").read_text())["duration_s"])
    mins = sorted(rows)
    dur = [durations[m] for m in mins]
    print("\n| stage | " + " | ".join(f"{durations[m] / 60:.1f} min: s, MiB" for m in mins) + " | time exponent | "
          "RSS exponent | RSS at 1 h, line |")  # fmt: skip
    print("|---|" + "---|" * len(mins) + "---|---|---|")
    for stage in stages:
        t = [rows[m][stage][0] for m in mins]
        r = [rows[m][stage][1] for m in mins]
        cells = " | ".join(f"{a:.1f}, {b:.0f}" for a, b in zip(t, r, strict=True))
        print(f"| {stage} | {cells} | {slope(dur, t):.2f} | {slope(dur, r):.2f} | {affine_at(dur, r, 3600.0):.0f} |")
    total = [sum(rows[m][s][0] for s in stages) for m in mins]
    peak = [max(rows[m][s][1] for s in stages) for m in mins]
    print(f"| whole run | {' | '.join(f'{a:.1f}, {b:.0f}' for a, b in zip(total, peak, strict=True))} | "
          f"{slope(dur, total):.2f} | {slope(dur, peak):.2f} | "
          f"{max(affine_at(dur, [rows[m][s][1] for m in mins], 3600.0) for s in stages):.0f} |")  # fmt: skip
    print("\nwhole run / recording duration: " + ", ".join(f"{t / d:.3f}x" for t, d in zip(total, dur, strict=True)))
    e = slope(dur, peak)
    if math.isfinite(e):
        hour = peak[-1] * (3600.0 / dur[-1]) ** e
        print(f"peak RSS extrapolated to one hour (exponent {e:.2f} from the longest): {hour:.0f} MiB")
    line = {s: affine_at(dur, [rows[m][s][1] for m in mins], 3600.0) for s in stages}
    worst = max(line, key=lambda s: line[s])
    print(f"peak RSS at one hour on each stage's fitted line (fixed + per minute): {line[worst]:.0f} MiB ({worst})")


if __name__ == "__main__":
    main()
