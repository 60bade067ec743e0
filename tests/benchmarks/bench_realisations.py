"""Table I over map realisations (issue 14 items 4 and 5): per case the mean collision rate over R redrawn maps with a
bootstrap interval, focus,info's paired difference against every case (sign and Wilcoxon tests), beside the paper's
Table I; and the benchmark's own time.

    python tests/benchmarks/bench_realisations.py RUN [--realisations 30] [--trials 200] [--seed 0] [--jobs 1]
    python tests/benchmarks/bench_realisations.py --generate /tmp/binding [--realisations 30] ...

RUN is a run folder whose graph, select_landmarks and select_measurements stages have run (evaluate's settings
are taken from RUN's selections and the command line). ``--generate DIR`` first simulates the binding regime's
recording into DIR (``sample_data.simulate --seed 21 --pixel-noise 12 --odom-noise-scale 2``) and runs
``focusmap run`` on it with ``configs/office_binding.yaml`` up to optimize. ``--jobs 2`` splits the realisations
over two processes (realisation r is the same whoever runs it). Prints markdown; asserts nothing.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from stages.evaluate.cases import TABLE_I, TABLE_I_LABELS, Case
from stages.evaluate.config import EvaluateConfig
from stages.evaluate.realisations import Study, load_run_inputs, run_realisations, statistics_markdown

ROOT = Path(__file__).resolve().parents[2]
PAPER_TABLE_I = {
    # Mu et al. (RSS 2015) Table I, simulation: observed lms, focused lms, entropy on focused lms (nats?), error on
    # all observed lms, error on focused lms (the paper gives collision probabilities only as a figure, Fig. 5d)
    "optimal": (74, 30, -61.3362, 0.0204, 0.0206),
    "focus_all": (30, 30, -54.7506, 0.0303, 0.0303),
    "focus_info": (30, 30, 7.9911, 0.3872, 0.3872),
    "focus_ds": (30, 26, 66.6130, 2.8026, 2.8026),
    "full_info": (74, 30, 39.9598, 22.3963, 25.5736),
    "full_ds": (44, 19, 100.9545, 2.0227, 2.0456),
}
SIM = ["--seed", "21", "--pixel-noise", "12", "--odom-noise-scale", "2"]


def generate(out: Path) -> Path:
    """Simulate the binding recording into ``out`` and run the pipeline on it up to optimize; the run folder."""
    out.mkdir(parents=True, exist_ok=True)
    bag = out / "binding.bag"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    if not bag.exists():
        cmd = [sys.executable, "-m", "sample_data.simulate", "--out", str(out), "--name", "binding", *SIM]
        subprocess.run(cmd, check=True, env=env)
    config = str(ROOT / "configs" / "office_binding.yaml")
    cmd = ["focusmap", "run", str(bag), "--out", str(out / "runs"), "--config", config, "--until", "optimize"]
    subprocess.run(cmd, check=True, env=env)
    return out / "runs" / "binding"


def _share(args: tuple[str, int, int, int, list[int], dict[str, Any]]) -> Study:
    run, n, trials, seed, indices, overrides = args
    inputs, detections = load_run_inputs(Path(run), EvaluateConfig(**overrides))
    todo = [Case(*c) for c in TABLE_I]
    return run_realisations(inputs, todo, n, trials, seed, detections, indices=indices)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run", nargs="?", type=Path, help="a run folder (graph and both selections done)")
    ap.add_argument("--generate", type=Path, help="simulate the binding recording here and run it first")
    ap.add_argument("--realisations", type=int, default=30)
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--robot-radius", type=float, default=None, help="evaluate.robot_radius_m (default: the run's)")
    args = ap.parse_args(argv)
    if args.generate is None and args.run is None:
        ap.error("give a RUN folder or --generate DIR")
    t_gen = time.perf_counter()
    run = generate(args.generate) if args.generate is not None else args.run
    t_gen = time.perf_counter() - t_gen
    overrides: dict[str, Any] = {"seed": args.seed}
    if args.robot_radius is not None:
        overrides["robot_radius_m"] = args.robot_radius
    t0 = time.perf_counter()
    jobs = max(1, args.jobs)
    shares = [list(range(j, args.realisations, jobs)) for j in range(jobs)]
    work = [(str(run), args.realisations, args.trials, args.seed, s, overrides) for s in shares]
    if jobs == 1:
        parts = [_share(work[0])]
    else:
        with ProcessPoolExecutor(jobs) as pool:
            parts = list(pool.map(_share, work))
    study = Study(parts[0].world, args.realisations, args.trials, args.seed)
    study.rows = sorted((r for p in parts for r in p.rows), key=lambda r: int(r["realisation"]))
    study.failed = [f for p in parts for f in p.failed]
    study.seconds = time.perf_counter() - t0
    load = os.getloadavg()
    print(f"## Table I over map realisations: {run}\n")
    print(
        f"{args.realisations} realisations x {args.trials} trials x {len(TABLE_I)} cases, seed {args.seed}, "
        f"{jobs} process(es), {os.cpu_count()} cores, load average {load[0]:.2f} / {load[1]:.2f} / {load[2]:.2f} "
        f"(1 / 5 / 15 min, the machine is shared); realisations took {study.seconds:.0f} s "
        f"({study.seconds / max(args.realisations, 1):.1f} s each)"
        + (f", generating the recording and its run {t_gen:.0f} s" if args.generate is not None else "")
        + ".\n"
    )
    print("\n".join(statistics_markdown(study, TABLE_I_LABELS, args.seed)))
    print("\n### Mu et al. Table I (simulation), for comparison\n")
    print("| case | observed lms | focused lms | entropy on focused lms | error all (m) | error focused (m) |")
    print("|---|---|---|---|---|---|")
    for case, (obs, foc, ent, err_all, err_foc) in PAPER_TABLE_I.items():
        print(f"| {TABLE_I_LABELS[case]} | {obs} | {foc} | {ent:.4f} | {err_all:.4f} | {err_foc:.4f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
