"""Import on first use: functions named by an import path, and a package's public names from its submodules.

So that building the stage registry (``focusmap --help``) imports no numerics: a stage refers to its
run function by name, and its package offers its public API without importing it up front.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Mapping, Sequence
from typing import Any


class LazyCallable:
    """A function named by ``"package.module:attribute"``, imported when first called.

    ``__module__`` and ``__name__`` are those of the named function, so code that asks where the
    function lives gets the answer without importing it.
    """

    def __init__(self, spec: str) -> None:
        module, sep, attribute = spec.partition(":")
        if not sep or not module or not attribute:
            raise ValueError(f"expected 'package.module:attribute', got {spec!r}")
        self.spec = spec
        self.__module__ = module
        self.__name__ = self.__qualname__ = attribute
        self._target: Callable[..., Any] | None = None

    @property
    def target(self) -> Callable[..., Any]:
        """The named function (imported on first use)."""
        if self._target is None:
            self._target = getattr(importlib.import_module(self.__module__), self.__name__)
        return self._target

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return self.target(*args, **kwargs)

    def __repr__(self) -> str:
        return f"lazy({self.spec!r})"

    def __reduce__(self) -> tuple[Any, ...]:
        return (LazyCallable, (self.spec,))


def lazy(spec: str) -> Callable[..., Any]:
    """The function named by ``"package.module:attribute"``, imported when first called."""
    return LazyCallable(spec)


def lazy_exports(package: str, exports: Mapping[str, Sequence[str]]) -> Callable[[str], Any]:
    """A module ``__getattr__`` (PEP 562) for ``package``: ``exports`` maps a submodule to the public names it
    defines; each name is imported from its submodule the first time it is asked for, then kept.

    Use as ``__getattr__ = lazy_exports(__name__, {"core": ("solve", ...)})`` in the package's ``__init__``.
    """
    where = {name: f"{package}.{module}" for module, names in exports.items() for name in names}

    def module_getattr(name: str) -> Any:
        module = where.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(module), name)
        setattr(sys.modules[package], name, value)
        return value

    return module_getattr
