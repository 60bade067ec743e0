"""The Table I comparison over several recordings (simulator seeds): per-run tables and a cross-run summary.

```
python -m stages.evaluate.seeds RUNS/office_s1 RUNS/office_s2 ...     # run folders (their evaluate/cases.parquet)
python -m stages.evaluate.seeds a.parquet b.parquet ...               # or cases.parquet files (copies)
```

Prints markdown: one table per run, then per case the mean ± sd over the runs of every column, then how often
``focus_info`` is better (lower) than each other case, per column. Runs are named by their folder (or file stem).
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq

from pipeline.errors import StageError

COLUMNS: tuple[tuple[str, str, str], ...] = (
    ("observed_landmarks", "observed", "{:.0f}"),
    ("focused_landmarks", "focused", "{:.0f}"),
    ("focused_entropy", "entropy (nats)", "{:.1f}"),
    ("error_all_m", "error all (m)", "{:.4f}"),
    ("focused_error_m", "focused error (m)", "{:.4f}"),
    ("focused_error_aligned_m", "focused aligned (m)", "{:.4f}"),
    ("oracle_focused_error_aligned_m", "oracle aligned (m)", "{:.4f}"),
    ("focused_nees", "focused NEES", "{:.2f}"),
    ("max_collision_probability", "max P", "{:.1e}"),
    ("collision_rate", "collision rate", "{:.3f}"),
    ("selection_s", "selection (s)", "{:.2f}"),
)
"""(column, header, format) of the tables."""

COMPARE = (
    "focused_entropy",
    "focused_error_m",
    "focused_error_aligned_m",
    "oracle_focused_error_aligned_m",
    "max_collision_probability",
    "collision_rate",
)
"""Columns on which focus_info is compared with every other case (lower is better)."""


def load(path: Path) -> tuple[str, dict[str, dict[str, Any]]]:
    """(run name, case name → row) from a run folder or a cases.parquet file."""
    file = path if path.suffix == ".parquet" else path / "evaluate" / "cases.parquet"
    # a copied RUN/evaluate/cases.parquet is named by its folder
    stem = path.parent.name if path.stem == "cases" else path.stem
    name = stem if path.suffix == ".parquet" else path.name
    if not file.is_file():
        raise StageError(
            f"{file} does not exist; pass run folders whose evaluate stage has run, or their cases.parquet"
        )
    t = pq.read_table(file).to_pylist()
    return name, {r["case"]: r for r in t}


def _f(v: Any, fmt: str) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    return fmt.format(v)


def run_table(rows: dict[str, dict[str, Any]]) -> list[str]:
    """Markdown table of one run."""
    head = "| case | " + " | ".join(h for _, h, _ in COLUMNS) + " |"
    out = [head, "|" + "---|" * (len(COLUMNS) + 1)]
    for name, r in rows.items():
        out.append(f"| {r.get('label', name)} | " + " | ".join(_f(r.get(c), f) for c, _, f in COLUMNS) + " |")
    return out


def summary_table(runs: Sequence[tuple[str, dict[str, dict[str, Any]]]]) -> list[str]:
    """Per case, mean ± sd over the runs of every column (n = runs that have the case)."""
    cases: list[str] = []
    for _, rows in runs:
        cases += [c for c in rows if c not in cases]
    head = "| case | n | " + " | ".join(h for _, h, _ in COLUMNS) + " |"
    out = [head, "|" + "---|" * (len(COLUMNS) + 2)]
    for case in cases:
        have = [rows[case] for _, rows in runs if case in rows]
        cells = []
        for c, _, f in COLUMNS:
            v = np.array([float(r[c]) for r in have if r.get(c) is not None], dtype=float)
            v = v[np.isfinite(v)]
            if not len(v):
                cells.append("–")
                continue
            sd = float(v.std(ddof=1)) if len(v) > 1 else float("nan")
            cells.append(f"{_f(float(v.mean()), f)} ± {_f(sd, f)}")
        label = have[0].get("label", case)
        out.append(f"| {label} | {len(have)} | " + " | ".join(cells) + " |")
    return out


def wins_table(runs: Sequence[tuple[str, dict[str, dict[str, Any]]]], ref: str = "focus_info") -> list[str]:
    """How often ``ref`` is lower than each other case, per column: ``wins/runs`` (ties counted apart)."""
    others: list[str] = []
    for _, rows in runs:
        others += [c for c in rows if c != ref and c not in others]
    head = f"| {ref} lower than | " + " | ".join(COMPARE) + " |"
    out = [head, "|" + "---|" * (len(COMPARE) + 1)]
    for o in others:
        cells = []
        for c in COMPARE:
            wins = ties = n = 0
            for _, rows in runs:
                if ref not in rows or o not in rows:
                    continue
                a, b = rows[ref].get(c), rows[o].get(c)
                if a is None or b is None or not (math.isfinite(a) and math.isfinite(b)):
                    continue
                n += 1
                wins += a < b
                ties += a == b
            cells.append(f"{wins}/{n}" + (f" ({ties} tie)" if ties else ""))
        out.append(f"| {o} | " + " | ".join(cells) + " |")
    return out


def report(paths: Sequence[Path]) -> str:
    """The markdown of per-run tables, the summary and the win counts."""
    runs = [load(p) for p in paths]
    lines: list[str] = []
    for name, rows in runs:
        lines += [f"#### {name}", "", *run_table(rows), ""]
    lines += [f"#### mean ± sd over {len(runs)} runs", "", *summary_table(runs), ""]
    lines += ["#### how often focus,info is lower", "", *wins_table(runs), ""]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """CLI: print the markdown."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("paths", nargs="+", type=Path, help="run folders or cases.parquet files")
    args = ap.parse_args(argv)
    try:
        print(report(args.paths))
    except StageError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
