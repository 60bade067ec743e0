"""Measurement selection on GTSAM's real Victoria Park (6,969 poses, 151 landmarks), timed against its import.

/work/venv/bin/python tests/benchmarks/bench_victoria.py [--budgets 90 1000] [--repeats 2]

The reference is what a user pays anyway: ``focusmap import-graph victoria_park.txt`` (GTSAM's reader, one
Levenberg-Marquardt optimise and the marginals of every variable). Against it, ``select-measurements`` with every
landmark focused (``focus=all``, Mu et al.'s Alg. 1) at each budget, on the same run folder, in one process and
interleaved per repeat (medians); ``uptime`` before and after, since the machine is shared. Issue #17's target:
selection within 5x of import + optimise + marginals.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

import gtsam

from pipeline.config import load_settings
from pipeline.runner import run_stage
from stages import REGISTRY
from stages.graph.imports import import_run


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--budgets", type=int, nargs="+", default=[90, 1000])
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args()
    print(subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip())
    source = Path(gtsam.findExampleDataFile("victoria_park.txt"))
    times: dict[str, list[float]] = {"import": [], **{f"K={k}": [] for k in args.budgets}}
    summary: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for rep in range(args.repeats):
            out = Path(tmp) / f"rep{rep}"
            t0 = time.perf_counter()
            run = import_run(source, out)
            res = run_stage(run, REGISTRY, "graph", load_settings(REGISTRY.models(), None, []))
            times["import"].append(time.perf_counter() - t0)
            summary["import"] = res.summary
            for k in args.budgets:
                settings = load_settings(
                    REGISTRY.models(), None, ["select_measurements.focus=all", f"select_measurements.budget={k}"]
                )
                t0 = time.perf_counter()
                res = run_stage(run, REGISTRY, "select_measurements", settings, force=True)
                times[f"K={k}"].append(time.perf_counter() - t0)
                summary[f"K={k}"] = res.summary
    base = statistics.median(times["import"])
    g = summary["import"]
    print(
        f"victoria_park.txt: poses={g['poses']} landmarks={g['landmarks']} factors={g['factors']} "
        f"final_error={g['final_error']:.6g}"
    )
    print(f"{'work':<12} {'median s':>9} {'x import':>9}  detail")
    print(f"{'import':<12} {base:9.2f} {1.0:9.2f}  read + LM optimise + marginals (graph stage)")
    for k in args.budgets:
        s = summary[f"K={k}"]
        med = statistics.median(times[f"K={k}"])
        detail = (
            f"candidates={s['candidates']} selected={s['selected']} "
            f"entropy {s['entropy_before']:.1f} -> {s['entropy_after']:.1f} nats"
        )
        print(f"{f'K={k}':<12} {med:9.2f} {med / base:9.2f}  {detail}")
    print(subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip())


if __name__ == "__main__":
    main()
