"""Landmark selection (issue 5): mutual-information greedy vs brute force and vs leverage sampling.

    python tests/benchmarks/bench_landmarks.py [--small 200] [--sizes 300x100 1000x300 2000x500] [--budget 30]

1. Near-optimality: greedy (lazy) F(A) divided by the brute-force optimum over many small random
   problems (5 of 15 landmarks), as Beinhofer et al. report it (99.1 % to 100 %).
2. Large problems (T poses x L landmarks, planar range-bearing): greedy vs leverage sampling
   (Mousavi & Motee), quality F(leverage) / F(greedy) and time greedy / leverage, measured side by
   side in one run. Prints ratios; nothing is asserted.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from stages.estimation.landmark_selection import (
    brute_force_mutual_information,
    mutual_information,
    schur_contribution,
    select_landmark_leverage,
    select_mutual_information,
)


def small_problem(rng: np.random.Generator, T: int = 8, L: int = 15):
    """A pose chain with random landmark contributions over 1-3 poses (as the tests use)."""
    n = 3 * T
    info0 = np.zeros((n, n))
    info0[:3, :3] += 1e4 * np.eye(3)
    for t in range(T - 1):
        J = np.hstack([-np.eye(3), np.eye(3)]) * rng.uniform(3, 10)
        idx = np.arange(3 * t, 3 * t + 6)
        info0[np.ix_(idx, idx)] += J.T @ J
    contrib = []
    for _ in range(L):
        poses = rng.choice(T, size=rng.integers(1, 4), replace=False)
        cols = np.concatenate([np.arange(3 * p, 3 * p + 3) for p in sorted(poses)])
        J = rng.normal(size=(2 * len(poses), len(cols))) * rng.uniform(0.5, 5)
        contrib.append((cols, J.T @ J))
    return info0, contrib


def planar_problem(rng: np.random.Generator, T: int, L: int, seen_from: int = 12):
    """A robot driving a random smooth path; each landmark seen (range-bearing) from ``seen_from`` poses."""
    yaw = np.cumsum(rng.normal(0, 0.05, T))
    xy = np.cumsum(np.column_stack([np.cos(yaw), np.sin(yaw)]) * 0.3, axis=0)
    n = 3 * T
    info0 = np.zeros((n, n))
    info0[:3, :3] = 1e6 * np.eye(3)
    odo = np.diag([1 / 0.02**2, 1 / 0.02**2, 1 / 0.01**2])
    for t in range(T - 1):
        J = np.hstack([-np.eye(3), np.eye(3)])
        idx = np.arange(3 * t, 3 * t + 6)
        info0[np.ix_(idx, idx)] += J.T @ odo @ J
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--small", type=int, default=200, help="small random problems for the brute-force ratio")
    parser.add_argument("--sizes", nargs="+", default=["300x100", "1000x300", "2000x500"], help="TxL")
    parser.add_argument("--budget", type=int, default=30)
    parser.add_argument("--draws", type=int, default=20)
    args = parser.parse_args()
    print(f"load average before: {os.getloadavg()}")

    rng = np.random.default_rng(0)
    ratios = [1.0] if not args.small else []
    for _ in range(args.small):
        info0, contrib = small_problem(rng)
        greedy = select_mutual_information(info0, contrib, 5)
        opt, _ = brute_force_mutual_information(info0, contrib, 5)
        ratios.append(mutual_information(info0, contrib, greedy.picks) / opt)
    if args.small:
        r = np.array(ratios)
        print(f"\n## MI greedy / brute force, 5 of 15, {len(r)} random problems")
        print(
            f"mean {r.mean():.4f}, min {r.min():.4f}, share optimal {np.mean(r > 1 - 1e-9):.2f} (bound 1-1/e = 0.632)"
        )

    print(f"\n## Large problems: greedy (lazy) vs leverage ({args.draws} draws, logdet), budget {args.budget}")
    print("| T x L | greedy s | leverage s | time greedy/leverage | F(leverage)/F(greedy) |")
    print("| --- | --- | --- | --- | --- |")
    for size in args.sizes:
        T, L = (int(v) for v in size.split("x"))
        info0, contrib = planar_problem(np.random.default_rng(T + L), T, L)
        t0 = time.perf_counter()
        greedy = select_mutual_information(info0, contrib, args.budget)
        tg = time.perf_counter() - t0
        t0 = time.perf_counter()
        lev = select_landmark_leverage(info0, contrib, args.budget, draws=args.draws, seed=1)
        tl = time.perf_counter() - t0
        fg = mutual_information(info0, contrib, greedy.picks)
        fl = mutual_information(info0, contrib, lev.picks)
        print(f"| {T} x {L} | {tg:.2f} | {tl:.2f} | {tg / tl:.1f}x | {fl / fg:.3f} |")
    print(f"\nload average after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
