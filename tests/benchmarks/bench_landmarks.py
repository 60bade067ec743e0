"""Landmark selection (issue 5): mutual-information greedy vs brute force and vs leverage sampling.

    python tests/benchmarks/bench_landmarks.py [--small 200] [--sizes 300x100 1000x300 2000x500] [--budget 30]
        [--draws 5] [--repeats 3] [--baseline REV] [--old-max-n 6000] [--sweep-draws 1 5 20 50 200]

1. Near-optimality: greedy (lazy) F(A) divided by the brute-force optimum over many small random
   problems (5 of 15 landmarks), as Beinhofer et al. report it (99.1 % to 100 %).
2. Large problems (T poses x L landmarks, planar range-bearing): greedy vs leverage sampling
   (Mousavi & Motee), quality F(leverage) / F(greedy) and time greedy / leverage, measured side by
   side in one run. Prints ratios; nothing is asserted.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from stages.estimation.landmark_selection import (
    schur_contribution,
    select_landmark_leverage,
    select_mutual_information,
)
from tests.fixtures.planar_problems import random_mi_problem
from tests.oracles.mutual_information import brute_force_mutual_information, mutual_information


def planar_problem(rng: np.random.Generator, T: int, L: int, seen_from: int = 12):
    """A robot driving a random smooth path; each landmark seen (range-bearing) from ``seen_from`` poses.

    ``info0`` is returned sparse (CSC); the same numbers as the dense matrix this benchmark used to build.
    """
    yaw = np.cumsum(rng.normal(0, 0.05, T))
    xy = np.cumsum(np.column_stack([np.cos(yaw), np.sin(yaw)]) * 0.3, axis=0)
    n = 3 * T
    odo = np.diag([1 / 0.02**2, 1 / 0.02**2, 1 / 0.01**2])
    J = np.hstack([-np.eye(3), np.eye(3)])
    blk = (J.T @ odo @ J).ravel()
    idx = 3 * np.arange(T - 1)[:, None] + np.arange(6)[None, :]  # (T-1, 6)
    rows = np.concatenate([np.arange(3), np.repeat(idx, 6, axis=1).ravel()])
    cols = np.concatenate([np.arange(3), np.tile(idx, (1, 6)).ravel()])
    data = np.concatenate([np.full(3, 1e6), np.tile(blk, T - 1)])
    info0 = sp.csc_matrix((data, (rows, cols)), shape=(n, n))
    contrib = []
    for _ in range(L):
        t0 = int(rng.integers(0, T - seen_from))
        ts = np.arange(t0, t0 + seen_from)
        lm = xy[ts].mean(0) + rng.normal(0, 2.0, 2)
        rows_x, rows_l = [], []
        for k, t in enumerate(ts):
            d = lm - xy[t]
            r2 = float(d @ d)
            r = np.sqrt(r2)
            # range and bearing, whitened (2 cm, 0.01 rad)
            Hx_r = np.array([-d[0] / r, -d[1] / r, 0.0]) / 0.02
            Hx_b = np.array([d[1] / r2, -d[0] / r2, -1.0]) / 0.01
            jx = np.zeros((2, 3 * seen_from))
            jx[0, 3 * k : 3 * k + 3] = Hx_r
            jx[1, 3 * k : 3 * k + 3] = Hx_b
            rows_x.append(jx)
            rows_l.append(np.array([[d[0] / r, d[1] / r], [-d[1] / r2, d[0] / r2]]) / np.array([[0.02], [0.01]]))
        cols = np.concatenate([np.arange(3 * t, 3 * t + 3) for t in ts])
        contrib.append((cols, schur_contribution(np.vstack(rows_x), np.vstack(rows_l))))
    return info0, contrib


def objective(info0, contrib, subset) -> float:
    """``F(A) = ½ log det(Λ₀ + Σ_A Λ_l) − ½ log det Λ₀`` from SuperLU (independent of the selection code)."""

    def logdet(m):
        lu = spla.splu(
            sp.csc_matrix(m), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True}
        )
        return float(np.sum(np.log(np.abs(lu.U.diagonal()))))

    lam = sp.csc_matrix(info0).tolil()
    for l_ in subset:
        cols, B = contrib[l_]
        lam[np.ix_(cols, cols)] = lam[np.ix_(cols, cols)].toarray() + B
    return 0.5 * (logdet(lam) - logdet(info0))


def load_baseline(rev: str):
    """The landmark-selection module as of git revision ``rev`` (``None`` if git cannot give it)."""
    root = Path(__file__).resolve().parents[2]
    try:
        src = subprocess.run(
            ["git", "show", f"{rev}:stages/estimation/landmark_selection.py"],
            cwd=root,
            capture_output=True,
            check=True,
            text=True,
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        return None
    path = Path(tempfile.mkdtemp()) / "baseline_landmark_selection.py"
    path.write_text(src)
    spec = importlib.util.spec_from_file_location("baseline_landmark_selection", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def timed(fn, *args, **kwargs):
    t0 = time.perf_counter()
    out = fn(*args, **kwargs)
    return out, time.perf_counter() - t0


def uniform_best_of(info0, contrib, budget: int, draws: int, seed: int) -> list[int]:
    """Best of ``draws`` uniformly random subsets by F (the paper's uniform-probability baseline)."""
    rng = np.random.default_rng(seed)
    subs = [list(rng.choice(len(contrib), size=budget, replace=False)) for _ in range(draws)]
    return max(subs, key=lambda a: objective(info0, contrib, a))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--small", type=int, default=200, help="small random problems for the brute-force ratio")
    parser.add_argument("--sizes", nargs="+", default=["300x100", "1000x300", "2000x500"], help="TxL")
    parser.add_argument("--budget", type=int, default=30)
    parser.add_argument("--draws", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=3, help="interleaved repeats (medians)")
    parser.add_argument("--baseline", default="731736f", help="git revision of the old (dense-inverse) code")
    parser.add_argument("--old-max-n", type=int, default=6000, help="largest n for which the old code is run")
    parser.add_argument("--sweep-draws", type=int, nargs="*", default=[1, 5, 20, 50, 200], help="p for section 3")
    parser.add_argument("--sweep-sizes", nargs="*", default=None, help="TxL for section 3 (default: --sizes)")
    args = parser.parse_args()
    print(f"load average before: {os.getloadavg()}")

    rng = np.random.default_rng(0)
    ratios = [1.0] if not args.small else []
    for _ in range(args.small):
        info0, contrib = random_mi_problem(rng)
        greedy = select_mutual_information(info0, contrib, 5)
        opt, _ = brute_force_mutual_information(info0, contrib, 5)
        ratios.append(mutual_information(info0, contrib, greedy.picks) / opt)
    if args.small:
        r = np.array(ratios)
        print(f"\n## MI greedy / brute force, 5 of 15, {len(r)} random problems")
        print(
            f"mean {r.mean():.4f}, min {r.min():.4f}, share optimal {np.mean(r > 1 - 1e-9):.2f} (bound 1-1/e = 0.632)"
        )

    baseline = load_baseline(args.baseline)
    warm = planar_problem(np.random.default_rng(0), 60, 20)  # imports and first-call costs out of the timings
    for mod in (m for m in (baseline, sys.modules[select_mutual_information.__module__]) if m is not None):
        mod.select_mutual_information(*warm, 3)
        mod.select_landmark_leverage(*warm, 3, draws=2)
    print(
        f"\n## Large problems: greedy (lazy) vs leverage ({args.draws} draws, logdet), budget {args.budget}, "
        f"medians of {args.repeats} interleaved runs; old = git {args.baseline}"
        + ("" if baseline is not None else " (not available)")
    )
    print(
        "| T x L | n | greedy old s | greedy new s | leverage old s | leverage new s "
        "| greedy/leverage time, old/old | new/new | old greedy/new leverage "
        "| F(leverage)/F(greedy) | same picks old/new |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    problems = {}
    for size in args.sizes:
        T, L = (int(v) for v in size.split("x"))
        info0, contrib = planar_problem(np.random.default_rng(T + L), T, L)
        problems[size] = (info0, contrib)
        n = info0.shape[0]
        old = baseline if baseline is not None and n <= args.old_max_n else None
        times: dict[str, list[float]] = {k: [] for k in ("go", "gn", "lo", "ln")}
        for _ in range(args.repeats):
            if old is not None:
                g_old, t = timed(old.select_mutual_information, info0, contrib, args.budget)
                times["go"].append(t)
            g_new, t = timed(select_mutual_information, info0, contrib, args.budget)
            times["gn"].append(t)
            if old is not None:
                l_old, t = timed(old.select_landmark_leverage, info0, contrib, args.budget, draws=args.draws, seed=1)
                times["lo"].append(t)
            l_new, t = timed(select_landmark_leverage, info0, contrib, args.budget, draws=args.draws, seed=1)
            times["ln"].append(t)
        med = {k: float(np.median(v)) if v else float("nan") for k, v in times.items()}
        fg = objective(info0, contrib, g_new.picks)
        fl = objective(info0, contrib, l_new.picks)
        same = "n/a" if old is None else f"{g_old.picks == g_new.picks}/{l_old.picks == l_new.picks}"
        print(
            f"| {T} x {L} | {n} | {med['go']:.2f} | {med['gn']:.2f} | {med['lo']:.2f} | {med['ln']:.3f} "
            f"| {med['go'] / med['lo']:.1f}x | {med['gn'] / med['ln']:.1f}x | {med['go'] / med['ln']:.0f}x "
            f"| {fl / fg:.3f} | {same} |"
        )

    print(f"\n## Leverage quality vs draws p and measure, budget {args.budget} (F / F(greedy); time in s)")
    print("| T x L | p | logdet | trace | max_eig | uniform best-of-p (by F) | leverage logdet s |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for size in args.sweep_sizes or args.sizes:
        info0, contrib = problems.get(size) or planar_problem(
            np.random.default_rng(sum(int(v) for v in size.split("x"))), *(int(v) for v in size.split("x"))
        )
        fg = objective(info0, contrib, select_mutual_information(info0, contrib, args.budget).picks)
        for p in args.sweep_draws:
            row = []
            for measure in ("logdet", "trace", "max_eig"):
                sel, t = timed(select_landmark_leverage, info0, contrib, args.budget, draws=p, measure=measure, seed=1)
                row.append(objective(info0, contrib, sel.picks) / fg)
                if measure == "logdet":
                    t_logdet = t
            fu = objective(info0, contrib, uniform_best_of(info0, contrib, args.budget, p, seed=1)) / fg
            print(f"| {size} | {p} | {row[0]:.3f} | {row[1]:.3f} | {row[2]:.3f} | {fu:.3f} | {t_logdet:.2f} |")
    print(f"\nload average after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
