"""The whole ``focusmap run`` of the bundled sample against the recording's duration (issue #16's last row).

    python tests/benchmarks/bench_run.py [--rounds 3] [--against OTHER_CHECKOUT] [--out DIR]

Runs README's pipeline command on ``sample_data/office/office.bag`` with ``configs/office.yaml`` into a fresh folder
per round and prints, per round, the wall time, the user + system CPU time of the run and its worker processes, the
peak RSS of its largest process, and wall time / the recording's 115 s. With ``--against`` each round runs the other
checkout's code too, alternating with this one, so that both meet the same load; the ratio of their median wall
times is printed last. The first round of a checkout that never ran compiles its modules; ``--warm`` (default 1)
rounds run first and are not counted. Nothing is asserted: the machine is shared.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from tests.fixtures.memory import command_usage  # noqa: E402

BAG = Path("sample_data/office/office.bag")
CONFIG = Path("configs/office.yaml")
DURATION_S = 114.95
"""The sample's recorded duration (ingest's ``duration_s``)."""


def run_once(checkout: Path, out: Path) -> tuple[float, float, float]:
    """Wall s, CPU s, peak RSS MiB of one whole run of ``checkout``'s code (its own modules first on the path)."""
    env = {**os.environ, "PYTHONPATH": str(checkout)}
    launcher = [sys.executable, "-c", "import sys; from cli.app import main; sys.argv[0] = 'focusmap'; main()"]
    args = ["run", str(BAG), "--out", str(out), "--config", str(CONFIG)]
    return command_usage([*launcher, *args], cwd=checkout, env=env)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--warm", type=int, default=1, help="uncounted rounds first (module compilation)")
    parser.add_argument("--against", type=Path, help="another checkout, run alternately with this one")
    parser.add_argument("--out", type=Path, help="folder for the run folders (default: a temporary one)")
    args = parser.parse_args()
    checkouts = [ROOT] + ([args.against.resolve()] if args.against else [])
    for c in checkouts:
        if not (c / BAG).exists():
            raise SystemExit(f"{c} has no {BAG}: pass the root of a focusmap checkout")
    with tempfile.TemporaryDirectory() as tmp:
        base = args.out or Path(tmp)
        print(f"load average {os.getloadavg()[0]:.2f}; recording {DURATION_S} s")
        print("| round | checkout | wall s | CPU s | peak RSS MiB | wall / duration |")
        print("| --- | --- | --- | --- | --- | --- |")
        walls: dict[Path, list[float]] = {c: [] for c in checkouts}
        for r in range(args.warm + args.rounds):
            for i, c in enumerate(checkouts):
                wall, cpu, rss = run_once(c, base / f"r{r}_{i}")
                label = "warm" if r < args.warm else str(r - args.warm + 1)
                print(f"| {label} | {c} | {wall:.1f} | {cpu:.1f} | {rss:.0f} | {wall / DURATION_S:.3f}x |", flush=True)
                if r >= args.warm:
                    walls[c].append(wall)
        print(f"load average {os.getloadavg()[0]:.2f}")
        for c, w in walls.items():
            print(f"{c}: median wall {statistics.median(w):.1f} s = {statistics.median(w) / DURATION_S:.3f}x")
        if args.against:
            a, b = (statistics.median(walls[c]) for c in checkouts)
            print(f"this checkout / {args.against}: {a / b:.2f}x (medians of {args.rounds} alternating rounds)")


if __name__ == "__main__":
    main()
