"""The longest functions of the shipped packages (``pipeline``, ``stages``, ``cli``), longest first.

    python tests/benchmarks/code_shape.py [--top 15] [--root DIR]

Length is ``end_lineno - lineno + 1`` of the ``def`` (docstring included), read with ``ast``.
"""

from __future__ import annotations

import argparse
import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def function_lengths(root: Path) -> list[tuple[int, str]]:
    """(lines, "path:line name") of every function and method under the shipped packages of ``root``."""
    rows = []
    for package in ("pipeline", "stages", "cli"):
        for path in sorted((root / package).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and node.end_lineno is not None:
                    where = f"{path.relative_to(root)}:{node.lineno} {node.name}"
                    rows.append((node.end_lineno - node.lineno + 1, where))
    return sorted(rows, reverse=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--top", type=int, default=15)
    parser.add_argument("--root", type=Path, default=ROOT, help="a checkout of focusmap (default: this one)")
    args = parser.parse_args()
    for lines, where in function_lengths(args.root)[: args.top]:
        print(f"{lines:5d}  {where}")


if __name__ == "__main__":
    main()
