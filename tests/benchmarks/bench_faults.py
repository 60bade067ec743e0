"""The fault matrix of issue #15: seeded faults against ``focusmap`` and how each ended (docs/faults.md).

    python tests/benchmarks/bench_faults.py [--quick] [--out DIR] [--seed 1] [--workers 2]

Inputs are simulated (4 s, 320x240 JPEG at 4 Hz; 12 s for the ``run`` faults), so ``../shared`` is not needed:
ROS 1 plain, bz2 and lz4 with 32 KiB chunks; ROS 2 SQLite; ROS 2 MCAP (32 KiB uncompressed chunks with CRCs)
and plain MCAP (32 KiB zstd chunks with CRCs). Then
- truncation: ``--cuts`` seeded cuts per format, each ingested with and without ``--salvage``;
- byte flips: ``--flips`` seeded bytes per format XORed with a seeded non-zero value, ingested both ways;
- kill -9: ``focusmap run`` killed at ``--kills`` seeded moments spread over a clean run's time; 5 s later no
  process of its session may live; the same command again must give the clean run's results (every table
  column, JSON key and array, less the keys that differ between two clean runs: timings, ids, recordings);
- disk full: ``focusmap run`` with ``--out`` on a tmpfs of each size (skipped where one cannot be mounted);
- bad settings and options: each must be one ``error:`` line (exit 1) and write nothing outside ``--out``.
Outcome classes are described in tests/fixtures/faults.py. ``--quick`` runs a few of each (about a minute).
The table goes to stdout and, with ``--out``, to DIR/faults.md and DIR/faults.json.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict
from pathlib import Path
from typing import Any, TypeVar

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from tests.fixtures import faults  # noqa: E402

T = TypeVar("T")
R = TypeVar("R")
INGEST_OUTCOMES = ("error", "long error", "same", "reported", "silent", "traceback", "crash", "hang")
QUICK_SETTINGS = (
    "run --start inf",
    "run --stride 0",
    "select-landmarks --budget -1",
    "--config binary",
    "--out naming a file",
    "--name ../x",
    "--set detect.tag_size_m=inf",
    "--set optimize.unobserved_sigma_m=inf",
    "--set evaluate.grid_resolution_m=1e-6",
    "--out read-only, new run",
)


def pmap(fn: Callable[[T], R], items: Iterable[T], workers: int) -> list[R]:
    with ThreadPoolExecutor(max_workers=workers) as pool:
        return list(pool.map(fn, items))


def md_table(header: list[str], rows: list[list[Any]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join(" --- " for _ in header) + "|"]
    lines += ["| " + " | ".join(str(c).replace("|", "\\|") for c in row) + " |" for row in rows]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="a few faults of each kind (about a minute)")
    parser.add_argument("--out", type=Path, help="write faults.md and faults.json here")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--workers", type=int, default=2, choices=(1, 2))
    args = parser.parse_args()
    cuts, flips, kills = (1, 1, 1) if args.quick else (20, 20, 10)
    disk_sizes = ["1m"] if args.quick else ["256k", "512k", "1m", "1536k", "2m", "2560k", "3m", "3584k", "4m", "16m"]
    run_seconds = 4.0 if args.quick else 12.0
    t_start = time.perf_counter()
    sections: list[str] = []
    report: dict[str, Any] = {"seed": args.seed, "quick": args.quick}

    with tempfile.TemporaryDirectory(prefix="bench-faults-") as tmp:
        root = Path(tmp)
        recs = faults.make_recordings(root / "rec", seconds=4.0, seed=args.seed)
        run_bag = faults.make_recordings(root / "long", seconds=run_seconds, seed=args.seed, formats=("mcap",))["mcap"]
        stages = faults.run_order()

        # two clean runs one after the other (their dates differ), in one of the workers, beside the ingest faults
        pool = ThreadPoolExecutor(max_workers=args.workers)
        clean_pair = pool.submit(
            lambda: tuple(faults.clean_run(run_bag, root / "run-clean" / name) for name in ("a", "b"))
        )

        # -- truncation and byte flips, through ingest ---------------------------------------------------
        def clean(fmt: str) -> tuple[dict[str, str], int]:
            (root / "clean" / fmt).mkdir(parents=True)
            return faults.clean_ingest(recs[fmt], root / "clean" / fmt)

        cleans = dict(zip(faults.FORMATS, pool.map(clean, faults.FORMATS), strict=True))
        cases = [
            c
            for fmt in faults.FORMATS
            for c in faults.seeded_cases(
                fmt,
                faults.storage_file(recs[fmt]).stat().st_size,
                cuts=cuts,
                flips=flips,
                seed=args.seed,
                salvage_flips=not args.quick,
            )
        ]
        results = list(pool.map(lambda c: faults.run_ingest_case(c, recs[c.fmt], *cleans[c.fmt]), cases))
        rows = []
        for fmt in faults.FORMATS:
            for fault in ("cut", "flip"):
                for salvage in (False, True):
                    got = [r for r in results if (r.case.fmt, r.case.fault, r.case.salvage) == (fmt, fault, salvage)]
                    n = Counter(r.outcome for r in got)
                    kept = [r.kept for r in got if r.kept is not None]
                    rows.append(
                        [
                            fmt + (" (CRC)" if fmt in faults.CHECKSUMMED else ""),
                            "truncation" if fault == "cut" else "byte flip",
                            "yes" if salvage else "no",
                            len(got),
                            *(n[o] for o in INGEST_OUTCOMES),
                            f"{100 * float(np.mean(kept)):.0f} %" if kept else "-",
                        ]
                    )
        header = ["format", "fault", "--salvage", "tried", *INGEST_OUTCOMES, "rows kept (exit 0)"]
        sections.append("### Truncation and byte flips (`focusmap ingest`)\n\n" + md_table(header, rows))
        report["ingest"] = [{**asdict(r.case), "outcome": r.outcome, "kept": r.kept, "line": r.line} for r in results]
        notable = [r for r in results if r.outcome in ("silent", "traceback", "long error", "crash", "hang")]
        lines = [
            f"- {r.case.fmt} {r.case.fault} at byte {r.case.offset}"
            + (f" (xor 0x{r.case.xor:02x})" if r.case.fault == "flip" else "")
            + (" --salvage" if r.case.salvage else "")
            + f": {r.outcome}"
            + (f", {100 * r.kept:.0f} % of rows" if r.kept is not None else "")
            + (f"; last line: `{r.line}`" if r.line else "")
            for r in notable
        ]
        sections.append(
            "Silent reads, tracebacks, crashes and hangs, case by case:\n\n" + "\n".join(lines or ["- none"])
        )

        # -- kill -9 of run, and resume -------------------------------------------------------------------
        (a, secs), (b, _) = clean_pair.result()
        pool.shutdown()
        volatile = faults.volatile_keys(a, b)
        rng = np.random.default_rng([args.seed, 99])
        targets = ["detect"] if args.quick else [stages[k % len(stages)] for k in range(kills)]
        moments = [(t, round(secs[t] * float(rng.uniform(0.05, 0.95)), 3)) for t in targets]

        def kill(moment: tuple[str, float]) -> faults.KillResult:
            work = root / "kill" / f"{moment[0]}-{moment[1]}"
            work.mkdir(parents=True)
            return faults.run_kill_case(run_bag, work, *moment, a, volatile)

        killed = pmap(kill, moments, args.workers)
        rows = [
            [
                f"{k.target} + {k.delay_s:.2f} s",
                k.stage,
                len(k.orphans),
                k.resume,
                k.skipped,
                "yes" if k.identical else f"no ({', '.join(k.diffs[:3])})",
            ]
            for k in killed
        ]
        header = [
            "kill -9 at (stage began + s)",
            "scratch folder at the kill",
            "orphans after 5 s",
            "re-run",
            "stages up to date",
            "identical",
        ]
        sections.append(
            f"### kill -9 of `focusmap run` ({run_seconds:.0f} s recording; the stages of a clean run took "
            f"{sum(secs.values()):.1f} s; "
            f"{len(a)} values compared, {len(volatile)} of them differ between two clean runs and are left out)\n\n"
            + md_table(header, rows)
        )
        report["kill"] = [asdict(k) for k in killed]
        report["volatile"] = sorted(volatile)

        # -- disk full ---------------------------------------------------------------------------------------
        def disk(size: str) -> faults.DiskResult:
            work = root / "disk" / size
            work.mkdir(parents=True)
            return faults.run_disk_case(run_bag, work, size, a, volatile, stages)

        full = pmap(disk, disk_sizes, args.workers)
        rows = [
            [d.size, d.outcome, d.stages_done, "yes" if d.earlier_whole else "NO", f"`{d.line}`" if d.line else ""]
            for d in full
        ]
        header = ["tmpfs size", "outcome", "stages done", "done stages whole", "last line"]
        sections.append("### Disk full (`focusmap run --out` on a small tmpfs)\n\n" + md_table(header, rows))
        report["disk"] = [asdict(d) for d in full]

        # -- bad settings and options -------------------------------------------------------------------------
        g2o = root / "run-clean" / "a" / "r" / "graph" / "graph.g2o"
        settings = faults.setting_cases()
        if args.quick:
            settings = [c for c in settings if c.label in QUICK_SETTINGS]
        judged = pmap(lambda c: faults.run_setting_case(c, recs["mcap"], g2o), settings, args.workers)
        tally = Counter(s.outcome for s in judged)
        failed = [s for s in judged if not s.passed]
        rows = [
            [
                s.case.label,
                s.case.expect,
                s.outcome,
                "ok" if s.passed else "FAIL",
                (f"wrote {s.outside}; " if s.outside else "") + (f"`{s.line}`" if s.line else ""),
            ]
            for s in judged
        ]
        header = ["case", "expected", "outcome", "verdict", "last line"]
        sections.append(
            f"### Bad settings and options ({len(judged)} cases: "
            + ", ".join(f"{v} {k}" for k, v in tally.most_common())
            + f"; {len(failed)} fail)\n\n"
            + md_table(header, rows)
        )
        report["settings"] = [
            {"label": s.case.label, "expect": s.case.expect, "outcome": s.outcome, "passed": s.passed, "line": s.line}
            for s in judged
        ]

    # -- targets ---------------------------------------------------------------------------------------------
    everything = [r.outcome for r in results] + [s.outcome for s in judged] + [d.outcome for d in full]
    everything += [k.resume for k in killed]
    exit0_changed = [r for r in results if r.outcome in ("reported", "silent")]
    crc_silent = sum(r.outcome == "silent" for r in results if r.case.fmt in faults.CHECKSUMMED)
    other = [r for r in exit0_changed if r.case.fmt not in faults.CHECKSUMMED]
    killed_mid = [k for k in killed if k.stage != "finished"]
    targets = [
        ["tracebacks (any `Traceback` / `internal error`)", "0", everything.count("traceback")],
        ["crashes (non-zero exit without an `error:` line)", "0", everything.count("crash")],
        ["`error:` messages running over several lines", "0", everything.count("long error")],
        ["hangs (timeout)", "0", everything.count("hang")],
        ["processes alive 5 s after kill -9", "0", sum(len(k.orphans) for k in killed)],
        ["silent wrong reads, formats with chunk CRCs", "0", crc_silent],
        [
            "damaged reads with exit 0 and changed data, other formats",
            "all reported",
            f"{sum(r.outcome == 'reported' for r in other)} reported, "
            f"{sum(r.outcome == 'silent' for r in other)} silent",
        ],
        [
            "resumed after kill -9 with identical results",
            "100 %",
            f"{sum(k.identical for k in killed_mid)} of {len(killed_mid)}"
            + (
                f" ({len(killed) - len(killed_mid)} runs ended before the kill)"
                if len(killed_mid) < len(killed)
                else ""
            ),
        ],
        [
            "disk full: fits, or one `error: cannot write` line with done stages whole",
            "all",
            f"{sum((d.outcome in ('same', 'error')) and d.earlier_whole for d in full if d.outcome != 'skipped')}"
            f" of {sum(d.outcome != 'skipped' for d in full)}",
        ],
        [
            "bad settings and options: one `error:` line, nothing written outside --out",
            "all",
            f"{len(judged) - len(failed)} of {len(judged)}",
        ],
    ]
    minutes = (time.perf_counter() - t_start) / 60
    head = (
        f"## Targets (seed {args.seed}{', --quick' if args.quick else ''}; "
        f"{len(results)} ingests, {len(killed)} kills, "
        f"{len(full)} disks, {len(judged)} settings; {minutes:.1f} min)\n\n"
        + md_table(["target", "goal", "measured"], targets)
    )
    text = "\n\n".join([head, *sections]) + "\n"
    print(text)
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "faults.md").write_text(text)
        (args.out / "faults.json").write_text(json.dumps(report, indent=1, default=str))


if __name__ == "__main__":
    main()
