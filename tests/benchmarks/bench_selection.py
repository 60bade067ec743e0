"""Benchmark the selection maths on a Victoria-Park-sized synthetic graph; prints ratios side by side.

/work/venv/bin/python tests/benchmarks/bench_selection.py --budgets 90 1000
"""

from __future__ import annotations

import argparse
import resource
import time

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from stages.estimation.linear_system import LinearSystem
from stages.estimation.measurement_selection import select_information, select_leverage
from stages.estimation.synthetic import planar_problem


def floor_seconds(pp) -> float:
    """One GTSAM LM optimise from a perturbed start plus marginals of every variable."""
    rng = np.random.default_rng(0)
    init = gtsam.Values()
    for i, (x, y, th) in enumerate(pp.poses):
        init.insert(X(i), gtsam.Pose2(x + rng.normal(0, 0.05), y + rng.normal(0, 0.05), th + rng.normal(0, 0.005)))
    for k, (x, y) in enumerate(pp.landmarks):
        if pp.values.exists(L(k)):
            init.insert(L(k), gtsam.Point2(x + rng.normal(0, 0.1), y + rng.normal(0, 0.1)))
    t = time.perf_counter()
    res = gtsam.LevenbergMarquardtOptimizer(pp.graph, init, gtsam.LevenbergMarquardtParams()).optimize()
    m = gtsam.Marginals(pp.graph, res)
    key_vector = res.keys()  # a gtsam KeyVector
    for key in key_vector:
        m.marginalCovariance(key)
    return time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--poses", type=int, default=7000)
    ap.add_argument("--landmarks", type=int, default=150)
    ap.add_argument("--measurements", type=int, default=10000)
    ap.add_argument("--focused", type=int, default=30)
    ap.add_argument("--budgets", type=int, nargs="+", default=[90, 1000])
    args = ap.parse_args()
    pp = planar_problem(args.poses, args.landmarks, args.measurements, seed=0, extent=200, sensor_range=30)
    system = LinearSystem.from_gtsam(pp.graph, pp.values)
    lms = system.variables_of_kind("landmark")
    focused = lms[: args.focused]
    fs = set(focused)
    cand = [f for f in pp.measurement_factors if fs & set(system.factors[f].variables)]
    floor = floor_seconds(pp)
    print(
        f"graph: {args.poses} poses, {len(lms)} landmarks, {len(pp.measurement_factors)} measurements; "
        f"{len(cand)} candidates on {len(focused)} focused landmarks"
    )
    print(f"floor (LM optimise + all marginals): {floor:.2f} s")
    for K in args.budgets:
        t = time.perf_counter()
        sel = select_information(system, cand, focused, K)
        tg = time.perf_counter() - t
        t = time.perf_counter()
        lev = select_leverage(system, cand, focused, K, draws=5)
        tl = time.perf_counter() - t
        print(
            f"K={K}: greedy {tg:.2f} s = {tg / floor:.1f}x floor ({1e3 * sel.stats['loop_s'] / K:.2f} ms/step); "
            f"entropy {sel.entropy_before:.1f} -> {sel.entropy_after:.1f} nats | leverage {tl:.2f} s, "
            f"entropy -> {lev.entropy_after:.1f} nats"
        )
    for n_cand in (1000, 10000):
        c = pp.measurement_factors[:n_cand]
        sel = select_information(system, c, lms, 30)
        print(f"{len(c)} candidates (all landmarks focused): {1e3 * sel.stats['loop_s'] / 30:.2f} ms/step")
    print(f"peak RSS: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB")


if __name__ == "__main__":
    main()
