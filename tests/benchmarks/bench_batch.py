"""Batch throughput with 1 and 2 local workers over the same small recordings, and the speed-up.

    python tests/benchmarks/bench_batch.py [--recordings 8] [--duration 4] [--until detect]
                                           [--set detect.workers=1 ...] [--repeat 1]

Simulates ``--recordings`` short corridor runs (seeds 0..n-1, ROS 1, 640x480), then runs the batch
over them into a fresh output folder with 1 worker and with 2 workers (interleaved when repeated,
so both see the same machine load) and prints recordings per minute and the ratio, all measured in
this one run. By default detect uses one process per recording (``detect.workers=1``) so that the
figure is the batch's own parallelism, not detect's pool. No timing is asserted anywhere.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from pipeline.batch import collect_recordings, plan_tasks, run_batch  # noqa: E402
from pipeline.config import load_settings  # noqa: E402
from sample_data.simulate import SimConfig, simulate, write_bag  # noqa: E402
from stages import REGISTRY  # noqa: E402


def make_recordings(folder: Path, n: int, duration_s: float) -> list[Path]:
    """``n`` simulated corridor runs as ROS 1 bags."""
    paths = []
    for seed in range(n):
        rec = simulate(SimConfig(seed=seed, path="corridor", duration_s=duration_s))
        paths.append(write_bag(rec, folder / f"run{seed}.bag", "ros1"))
    return paths


def batch_seconds(bags: list[Path], out: Path, until: str, sets: list[str], workers: int) -> float:
    """Wall time of one batch over ``bags`` into the empty folder ``out``; every recording must succeed."""
    stages = [s.name for s in REGISTRY.between(None, until)]
    settings = load_settings(REGISTRY.models(), None, sets)
    tasks = plan_tasks(
        collect_recordings([str(b) for b in bags]),
        out,
        stages,
        settings,
        preflight="stages.ingest.bags:detect_format",
    )
    start = time.perf_counter()
    result = run_batch(tasks, workers=workers, progress=False)
    seconds = time.perf_counter() - start
    failed = [o for o in result.outcomes if o.status != "done"]
    if failed:
        raise SystemExit(f"{len(failed)} recordings did not run: {failed[0].run}: {failed[0].reason}")
    return seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--recordings", type=int, default=8, help="How many recordings.")
    parser.add_argument("--duration", type=float, default=4.0, help="Seconds of each simulated run.")
    parser.add_argument("--until", default="detect", help="Last stage to run.")
    parser.add_argument("--set", dest="sets", action="append", default=None, help="SECTION.KEY=VALUE (repeatable).")
    parser.add_argument("--repeat", type=int, default=1, help="Measurements per worker count (median).")
    args = parser.parse_args()
    sets = args.sets if args.sets is not None else ["detect.workers=1"]
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        (root / "bags").mkdir()
        bags = make_recordings(root / "bags", args.recordings, args.duration)
        times: dict[int, list[float]] = {1: [], 2: []}
        for r in range(args.repeat):
            for workers in (1, 2):
                times[workers].append(batch_seconds(bags, root / f"out-{workers}-{r}", args.until, sets, workers))
    print(
        f"batch of {args.recordings} recordings ({args.duration:g} s each, until {args.until}, "
        f"{' '.join(sets) or 'default settings'}), {os.cpu_count()} cores"
    )
    median = {w: statistics.median(t) for w, t in times.items()}
    for workers, seconds in median.items():
        rate = 60.0 * args.recordings / seconds
        print(f"  {workers} worker{'s' if workers > 1 else ' '}: {seconds:6.1f} s  {rate:6.1f} recordings/min")
    print(f"  speed-up 2 vs 1 workers: {median[1] / median[2]:.2f}x")


if __name__ == "__main__":
    main()
