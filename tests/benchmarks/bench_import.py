"""Which GTSAM example datasets and SE-Sync benchmark graphs import-graph reads, and its optimum against GTSAM's.

For every ``.txt`` / ``.graph`` / ``.g2o`` file of GTSAM's ``examples/Data`` (the copy the gtsam wheel ships,
``gtsam.findExampleDataFile``) and of ``../shared/data/se-sync-graphs`` and ``slam-graphs``: import it through the
graph stage (``focusmap import-graph``: read, optimise, marginals, write), or print the ``error:`` line it gives.
For each imported graph, GTSAM's own Levenberg-Marquardt optimises the same reader output (GTSAM's reader's graph
and values, with the same prior on the first pose); the table compares the final errors. Nothing is asserted::

    /work/venv/bin/python tests/benchmarks/bench_import.py [--skip-larger-than 30000] [--work /tmp/fm_import]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))


def gtsam_final_error(path: Path) -> float:
    """GTSAM's LM on GTSAM's reader output for ``path`` (the reader import-graph picks), with its first-pose prior."""
    import gtsam

    from stages.graph.datasets import read_with_gtsam, scan_file
    from stages.graph.g2o import read_graph_file

    scan = scan_file(path)
    graph, _ = read_with_gtsam(path, scan)
    problem = read_graph_file(path)  # the initial values of poses GTSAM's 3D reader leaves out, and the prior
    initial = gtsam.Values()
    for key in problem.var_types:
        sym = gtsam.Symbol(key)
        gkey = sym.index() if chr(sym.chr()) == "x" else key
        problem.kind(key).insert(initial, gkey, problem.kind(key).read(problem.initial, key))
    prior = problem.rows[0]
    pose0 = gtsam.Symbol(prior.keys[0]).index()
    noise = gtsam.noiseModel.Gaussian.Covariance(prior.covariance)
    kind = problem.graph_model.pose
    if kind.name == "Pose2":
        graph.add(gtsam.PriorFactorPose2(pose0, kind.from_vector(prior.measurement), noise))
    else:
        graph.add(gtsam.PriorFactorPose3(pose0, kind.from_vector(prior.measurement), noise))
    params = gtsam.LevenbergMarquardtParams()
    return float(graph.error(gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()))


def main() -> None:
    import gtsam

    from pipeline.errors import PipelineError
    from tests.fixtures.graphs import import_graph

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=None, help="folder for the run folders (default: a temporary one)")
    ap.add_argument("--skip-larger-than", type=int, default=10**9, help="skip files with more lines than this")
    args = ap.parse_args()
    data = Path(gtsam.findExampleDataFile("victoria_park.txt")).parent
    groups = {"gtsam examples/Data": data, "SE-Sync": ROOT.parent / "shared/data/se-sync-graphs"}
    work = args.work or Path(tempfile.mkdtemp(prefix="fm_import_"))
    print("| set | file | poses | landmarks | factors | ours: final error | GTSAM LM: final error | import s |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    counts: dict[str, list[int]] = {}
    for group, folder in groups.items():
        files = sorted(p for ext in ("*.txt", "*.graph", "*.g2o") for p in folder.glob(ext))
        for path in files:
            n = sum(1 for _ in path.open())
            if n > args.skip_larger_than:
                print(f"| {group} | {path.name} | skipped: {n} lines |")
                continue
            tally = counts.setdefault(group, [0, 0])
            t = time.perf_counter()
            try:
                run = import_graph(path, work, f"{path.stem}_{group.split()[0]}")
            except PipelineError as err:
                tally[1] += 1
                print(f"| {group} | {path.name} | error: {err} |")
                continue
            seconds = time.perf_counter() - t
            tally[0] += 1
            s = json.loads((run / "graph" / "summary.json").read_text())
            ref = gtsam_final_error(path)
            print(
                f"| {group} | {path.name} | {s['poses']} | {s['landmarks']} | {s['factors']} | "
                f"{s['final_error']:.6g} | {ref:.6g} | {seconds:.2f} |"
            )
    for group, (ok, bad) in counts.items():
        print(f"{group}: {ok} imported, {bad} refused with an error: line")


if __name__ == "__main__":
    main()
