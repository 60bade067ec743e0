"""The code a stage runs, found statically: a digest of the project modules reachable from its own modules.

A stage's code version must change when, and only when, code it can execute changes. Hashing a whole
package re-runs every stage after any edit; hashing only the stage's own files misses the shared modules
it calls. So the digest covers the root modules (a stage's own sub-package) plus every module of the given
top-level packages that they reach through ``import`` statements, followed transitively. The import graph is
read with :mod:`ast`, without importing anything, and counts every import statement wherever it stands
(also inside functions, so lazy imports are covered), ``from pkg import name`` where ``name`` is a submodule,
and relative imports. Modules of other packages (numpy, gtsam, ...) are left out: their versions are in the
manifest's ``versions``.

A package named by an import contributes its ``__init__.py``; the parent packages of a module do not (their
``__init__`` runs on import, but what it binds is not what the module uses), except when imported by name.
"""

from __future__ import annotations

import ast
import functools
import hashlib
import importlib.util
from collections.abc import Iterable, Mapping
from pathlib import Path


def package_dirs(names: Iterable[str]) -> dict[str, Path]:
    """The source folder of each top-level package, found without importing it."""
    out: dict[str, Path] = {}
    for name in names:
        spec = importlib.util.find_spec(name)
        if spec is None or not spec.submodule_search_locations:
            raise ValueError(f"{name!r} is not an importable package")
        out[name] = Path(next(iter(spec.submodule_search_locations)))
    return out


def module_file(name: str, packages: Mapping[str, Path]) -> Path | None:
    """The source file of module ``name`` (``a.b.c``) inside one of ``packages``, or None when it is not there."""
    top, *rest = name.split(".")
    root = packages.get(top)
    if root is None:
        return None
    base = root.joinpath(*rest)
    if (base / "__init__.py").is_file():
        return base / "__init__.py"
    path = base.with_suffix(".py") if rest else None
    return path if path is not None and path.is_file() else None


def _is_package(path: Path) -> bool:
    return path.name == "__init__.py"


def _import_statements(tree: ast.Module) -> list[ast.Import | ast.ImportFrom]:
    """Every import statement of a module, at any depth (imports are statements: only statement lists are walked)."""
    out: list[ast.Import | ast.ImportFrom] = []
    todo: list[ast.AST] = list(tree.body)
    while todo:
        node = todo.pop()
        if isinstance(node, ast.Import | ast.ImportFrom):
            out.append(node)
            continue
        for attr in ("body", "orelse", "finalbody", "handlers", "cases"):
            children = getattr(node, attr, None)
            if isinstance(children, list):
                todo.extend(c for c in children if isinstance(c, ast.stmt | ast.excepthandler | ast.match_case))
    return out


def imported_modules(name: str, path: Path, packages: Mapping[str, Path]) -> set[str]:
    """The modules of ``packages`` that the source of module ``name`` (at ``path``) imports anywhere in it."""
    tree = ast.parse(path.read_bytes(), filename=str(path))
    package = name if _is_package(path) else name.rpartition(".")[0]
    found: set[str] = set()

    def add(candidate: str) -> bool:
        if module_file(candidate, packages) is not None:
            found.add(candidate)
            return True
        return False

    for node in _import_statements(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                add(alias.name)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split(".")
                anchor = ".".join(parts[: len(parts) - node.level + 1])
                base = f"{anchor}.{node.module}" if node.module else anchor
            else:
                base = node.module or ""
            add(base)
            for alias in node.names:
                if alias.name != "*":
                    add(f"{base}.{alias.name}")
    return found


def package_modules(name: str, packages: Mapping[str, Path]) -> list[str]:
    """``name`` and, when it is a package, every module below it."""
    path = module_file(name, packages)
    if path is None:
        raise ValueError(f"module {name!r} is not in the packages {sorted(packages)}")
    if not _is_package(path):
        return [name]
    out = []
    for f in sorted(path.parent.rglob("*.py")):
        rel = f.relative_to(path.parent).with_suffix("")
        parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
        out.append(".".join((name, *parts)))
    return out


def reachable_modules(roots: Iterable[str], packages: Mapping[str, Path]) -> dict[str, Path]:
    """Every module of ``packages`` reachable by imports from ``roots`` (packages expanded to all their modules)."""
    todo = [m for r in roots for m in package_modules(r, packages)]
    seen: dict[str, Path] = {}
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        path = module_file(name, packages)
        if path is None:
            continue
        seen[name] = path
        todo.extend(imported_modules(name, path, packages) - seen.keys())
    return dict(sorted(seen.items()))


@functools.cache
def _digest(roots: tuple[str, ...], packages: tuple[tuple[str, str], ...]) -> str:
    dirs = {name: Path(p) for name, p in packages}
    digest = hashlib.sha256()
    for name, path in reachable_modules(roots, dirs).items():
        source = path.read_bytes()
        digest.update(f"{name}\0{len(source)}\0".encode())
        digest.update(source)
    return digest.hexdigest()


def code_digest(roots: Iterable[str], packages: Mapping[str, Path]) -> str:
    """SHA-256 over the names and sources of the modules reachable from ``roots`` (cached per process)."""
    return _digest(tuple(sorted(roots)), tuple(sorted((k, str(v)) for k, v in packages.items())))
