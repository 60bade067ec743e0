"""Benchmark the selection maths on a Victoria-Park-sized synthetic graph; prints ratios side by side.

/work/venv/bin/python tests/benchmarks/bench_selection.py --budgets 90 1000 --repeats 3

Everything timed in one process, interleaved (floor, greedy, leverage per repeat), medians over the
repeats; ``uptime`` is printed before and after since the machine is shared.
"""

from __future__ import annotations

import argparse
import resource
import subprocess
import sys
import time
import tracemalloc

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from stages.estimation.linear_system import LinearSystem
from stages.estimation.measurement_selection import (
    TrackerOptions,
    _compact_problem,
    _focused_cov,
    default_base,
    focused_entropy,
    select_information,
    select_leverage,
)
from stages.estimation.sparse_cov import SPDSolver, logdet_spd
from tests.fixtures.planar_problems import planar_problem


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


def reference_seconds_per_evaluation(system, cand, focused, n_eval: int = 4) -> float:
    """Alg. 1 as written, one candidate evaluation: factorise ``Λ + A_cᵀA_c`` and read ``Σ_F`` (sparse).

    The dense reference of the tests cannot hold the 21,000-dimensional inverse, so this is its sparse
    equivalent (no dense ``n × n``), timed on ``n_eval`` candidates.
    """
    base = default_base(system, cand)
    prob = _compact_problem(system, base, cand, focused, 100.0)
    fcols = prob.system.columns(prob.focused)
    t = time.perf_counter()
    for c in prob.candidates[:n_eval]:
        info = prob.info0 + prob.system.information([c])
        _, SF = _focused_cov(SPDSolver(info), prob.system.dim, fcols)
        logdet_spd(SF)
    return (time.perf_counter() - t) / n_eval


def _rss_mib() -> float:
    """Peak resident set of this process (``VmHWM``; ``ru_maxrss`` would include the parent's peak at fork)."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except OSError:  # pragma: no cover - not Linux
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def memory_probe(K: int) -> None:
    """Peak RSS of the greedy alone: build the benchmark graph, run ``select_information`` once."""
    pp = planar_problem(7000, 150, 10000, seed=0, extent=200, sensor_range=30)
    system = LinearSystem.from_gtsam(pp.graph, pp.values)
    focused = system.variables_of_kind("landmark")[:30]
    cand = [f for f in pp.measurement_factors if set(focused) & set(system.factors[f].variables)]
    before = _rss_mib()
    select_information(system, cand, focused, K)
    print(
        f"peak RSS (fresh process): {before:.0f} MiB after building the graph, {_rss_mib():.0f} MiB after greedy K={K}"
    )


def uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True, check=False).stdout.strip()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--poses", type=int, default=7000)
    ap.add_argument("--landmarks", type=int, default=150)
    ap.add_argument("--measurements", type=int, default=10000)
    ap.add_argument("--focused", type=int, default=30)
    ap.add_argument("--budgets", type=int, nargs="+", default=[90, 1000])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--draws", type=int, default=5, help="leverage draws")
    ap.add_argument("--flat-steps", type=int, default=100, help="greedy steps for the per-step timing")
    ap.add_argument(
        "--tracker",
        choices=["auto", "window", "capacitance"],
        default=None,
        help="tracker for the totals (default: TrackerOptions' default)",
    )
    ap.add_argument("--memory-probe", type=int, default=0, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.memory_probe:
        memory_probe(args.memory_probe)
        return
    print(f"uptime before: {uptime()}")
    totals = TrackerOptions() if args.tracker is None else TrackerOptions(tracker=args.tracker)
    print(f"tracker for the totals: {totals.tracker}")
    pp = planar_problem(args.poses, args.landmarks, args.measurements, seed=0, extent=200, sensor_range=30)
    system = LinearSystem.from_gtsam(pp.graph, pp.values)
    lms = system.variables_of_kind("landmark")
    focused = lms[: args.focused]
    fs = set(focused)
    cand = [f for f in pp.measurement_factors if fs & set(system.factors[f].variables)]
    print(
        f"graph: {args.poses} poses, {len(lms)} landmarks (all observed: {len(lms) == args.landmarks}), "
        f"{len(pp.measurement_factors)} measurements; {len(cand)} candidates on {len(focused)} focused landmarks"
    )
    t_floor: list[float] = []
    t_greedy: dict[int, list[float]] = {K: [] for K in args.budgets}
    t_lev: dict[int, list[float]] = {K: [] for K in args.budgets}
    sel: dict[int, object] = {}
    lev: dict[int, object] = {}
    for _ in range(args.repeats):
        t_floor.append(floor_seconds(pp))
        for K in args.budgets:
            t = time.perf_counter()
            sel[K] = select_information(system, cand, focused, K, options=totals)
            t_greedy[K].append(time.perf_counter() - t)
            t = time.perf_counter()
            lev[K] = select_leverage(system, cand, focused, K, draws=args.draws)
            t_lev[K].append(time.perf_counter() - t)
    floor = float(np.median(t_floor))
    print(f"floor (LM optimise + all marginals): {floor:.2f} s (runs {', '.join(f'{x:.2f}' for x in t_floor)})")
    t_eval = reference_seconds_per_evaluation(system, cand, focused)
    N = len(cand)
    for K in args.budgets:
        tg, tl = float(np.median(t_greedy[K])), float(np.median(t_lev[K]))
        s, lv = sel[K], lev[K]
        t_ref = t_eval * sum(N - k for k in range(K))  # every remaining candidate at every step
        fresh = focused_entropy(system, default_base(system, cand) + s.picks, focused)
        print(
            f"K={K}: greedy {tg:.2f} s = {tg / floor:.1f}x floor (runs {', '.join(f'{x:.2f}' for x in t_greedy[K])}; "
            f"loop {1e3 * s.stats['loop_s'] / K:.2f} ms/step, {s.stats['refactorisations']:.0f} refactorisations) | "
            f"reference (extrapolated, {1e3 * t_eval:.0f} ms per candidate evaluation) {t_ref:.0f} s = "
            f"{t_ref / tg:.0f}x greedy | leverage ({args.draws} draws) {tl:.2f} s = {tl / tg:.2f}x greedy\n"
            f"      focused entropy {s.entropy_before:.1f} -> greedy {s.entropy_after:.1f} nats, "
            f"leverage {lv.entropy_after:.1f} nats (greedy removes "
            f"{(s.entropy_before - s.entropy_after) / max(s.entropy_before - lv.entropy_after, 1e-12):.2f}x "
            f"the entropy leverage removes); greedy's bookkept entropy vs a fresh factorisation: "
            f"{s.entropy_after - fresh:+.4f} nats"
        )
    # time per step as the candidates grow: all landmarks focused, the first n measurements as candidates
    # (graph and focus fixed, only the candidate set grows). Trackers: the sequential window on the
    # Schur-reduced system (grows with the candidates' rows), the capacitance form on the whole compact
    # graph (fixed-size solves), and the default (``auto``: whichever the size of the candidates' rows picks)
    steps = args.flat_steps
    sizes = (1000, args.measurements)
    variants = ("window", "capacitance", "auto")
    per_step: dict[tuple[str, int], list[float]] = {(v, nc): [] for v in variants for nc in sizes}
    info: dict[tuple[str, int], list[dict[str, float]]] = {key: [] for key in per_step}
    for _ in range(args.repeats):
        for variant, nc in per_step:
            s = select_information(
                system, pp.measurement_factors[:nc], lms, steps, options=TrackerOptions(tracker=variant)
            )
            per_step[(variant, nc)].append(1e3 * s.stats["loop_s"] / steps)
            info[(variant, nc)].append(s.stats)

    def med(variant: str, nc: int, key: str) -> float:
        return float(np.median([1e3 * st[key] / steps for st in info[(variant, nc)]]))

    for variant in variants:
        a, b = (float(np.median(per_step[(variant, nc)])) for nc in sizes)
        ua, ub = (med(variant, nc, "update_s") + med(variant, nc, "gain_s") for nc in sizes)
        fa, fb = (med(variant, nc, "factor_s") for nc in sizes)
        ia, ib = info[(variant, sizes[0])][-1], info[(variant, sizes[1])][-1]
        print(
            f"all landmarks focused, {steps} steps, tracker {variant}: {a:.2f} ms/step with {sizes[0]:,} candidates "
            f"({ia['tracked_rows']:.0f} candidate rows, capacitance {ia['capacitance']:.0f}), {b:.2f} ms/step with "
            f"{sizes[1]:,} ({ib['tracked_rows']:.0f} rows, capacitance {ib['capacitance']:.0f}) = {b / a:.2f}x; "
            f"O(N) part (per-candidate updates + gain evaluation) {ua:.2f} vs {ub:.2f} ms/step; the rest "
            f"{a - ua:.2f} vs {b - ub:.2f} ({(b - ub) / (a - ua):.2f}x), of which factorisations {fa:.2f} vs {fb:.2f}"
        )
    # memory: the greedy alone in a fresh process (peak RSS after building the graph and after the
    # greedy), and the Python/numpy allocations during one greedy (tracemalloc)
    K = max(args.budgets)
    probe = subprocess.run(
        [sys.executable, __file__, "--memory-probe", str(K)], capture_output=True, text=True, check=False
    )
    print(probe.stdout.strip() or probe.stderr.strip())
    tracemalloc.start()
    select_information(system, cand, focused, K, options=totals)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    print(f"peak numpy/Python allocations in greedy K={K}: {peak / 2**20:.0f} MiB")
    print(f"this process's peak RSS (GTSAM marginals, leverage, ...): {_rss_mib():.0f} MiB")
    print(f"uptime after: {uptime()}")


if __name__ == "__main__":
    main()
