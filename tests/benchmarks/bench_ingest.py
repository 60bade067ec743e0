"""Ingest throughput as a ratio to the raw read speed of the same file, measured side by side.

    python tests/benchmarks/bench_ingest.py [BAG] [--repeat 3]

"raw read" iterates every message of the bag with rosbags without deserialising (the floor any
reader pays); "ingest" is the full stage (decode, tables, recording) into a temporary run folder.
Prints the medians and the ratio; no timing is asserted anywhere. The CPU-time ratio (this process's CPU
seconds, every thread) beside it moves less when other work shares the machine's cores.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from pipeline.config import load_settings  # noqa: E402
from pipeline.run_folder import RunFolder  # noqa: E402
from pipeline.runner import run_stage  # noqa: E402
from stages import REGISTRY  # noqa: E402
from stages.ingest.bags import Recording  # noqa: E402


def raw_read(bag: Path) -> tuple[float, float, int, int]:
    """(wall seconds, CPU seconds, messages, payload bytes) of one pass over every message."""
    start, cpu = time.perf_counter(), time.process_time()
    n = size = 0
    with Recording(bag) as rec:
        for msg in rec.messages(rec.topics):
            n += 1
            size += len(msg.data)
    return time.perf_counter() - start, time.process_time() - cpu, n, size


def ingest(bag: Path) -> tuple[float, float]:
    """(wall seconds, CPU seconds) of the ingest stage into a temporary run folder."""
    with tempfile.TemporaryDirectory() as tmp:
        run = RunFolder.create(Path(tmp) / "r", bag)
        start, cpu = time.perf_counter(), time.process_time()
        run_stage(run, REGISTRY, "ingest", load_settings(REGISTRY.models()), force=True)
        return time.perf_counter() - start, time.process_time() - cpu


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("bag", nargs="?", type=Path, default=ROOT / "sample_data" / "office" / "office.bag")
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    raws, ings, raw_cpus, ing_cpus = [], [], [], []
    n = size = 0
    for _ in range(args.repeat):  # interleaved, so both see the same machine load
        t, c, n, size = raw_read(args.bag)
        raws.append(t)
        raw_cpus.append(c)
        t, c = ingest(args.bag)
        ings.append(t)
        ing_cpus.append(c)
    raw, ing = statistics.median(raws), statistics.median(ings)
    raw_cpu, ing_cpu = statistics.median(raw_cpus), statistics.median(ing_cpus)
    mb = size / 1e6
    print(f"bag: {args.bag} ({n} messages, {mb:.1f} MB of payload)")
    print(f"raw read : {raw:7.3f} s  {n / raw:9.0f} msg/s  {mb / raw:7.1f} MB/s")
    print(f"ingest   : {ing:7.3f} s  {n / ing:9.0f} msg/s  {mb / ing:7.1f} MB/s")
    print(f"ingest / raw read time ratio: {ing / raw:.2f}x")
    print(f"ingest / raw read CPU-time ratio: {ing_cpu / raw_cpu:.2f}x ({ing_cpu:.3f} / {raw_cpu:.3f} s)")


if __name__ == "__main__":
    main()
