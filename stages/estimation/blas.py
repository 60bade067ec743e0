"""Run the OpenBLAS of numpy and SciPy on one thread inside a block.

The selection loops make thousands of small dense products, eigendecompositions and triangular solves;
OpenBLAS threads them, and on a loaded 2-core machine the threads wait on each other (measured: the
measurement greedy 3x slower, 74 eigh of ~100×100 took 9 s; SciPy's wheel ships its own OpenBLAS, whose
small triangular solves took 1 ms each when threaded).
"""

from __future__ import annotations

import ctypes
import functools
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import ParamSpec, TypeVar

import numpy as np
import scipy.linalg as sla

P = ParamSpec("P")
T = TypeVar("T")


def _openblas_thread_api(libdir: Path) -> tuple[Callable[[], int], Callable[[int], None]] | None:
    """``(get, set)`` for the number of threads of the OpenBLAS in a wheel's ``.libs``, if it can be found."""
    for path in sorted(libdir.glob("libscipy_openblas*.so*")) + sorted(libdir.glob("libopenblas*.so*")):
        try:
            lib = ctypes.CDLL(str(path))
        except OSError:  # pragma: no cover - depends on the environment
            continue
        for prefix, suffix in (("scipy_", "64_"), ("scipy_", ""), ("", "64_"), ("", "")):
            get = getattr(lib, f"{prefix}openblas_get_num_threads{suffix}", None)
            put = getattr(lib, f"{prefix}openblas_set_num_threads{suffix}", None)
            if get is not None and put is not None:
                get.restype = ctypes.c_int
                put.argtypes = [ctypes.c_int]
                return get, put
    return None  # pragma: no cover - depends on the environment


_BLAS_THREADS = [
    api
    for api in (
        _openblas_thread_api(Path(np.__file__).resolve().parent.parent / "numpy.libs"),
        _openblas_thread_api(Path(sla.__file__).resolve().parent.parent.parent / "scipy.libs"),
    )
    if api is not None
]
"""numpy's OpenBLAS and SciPy's (the SciPy wheel ships its own: ``solve_triangular`` goes through it)."""


@contextmanager
def single_threaded_blas() -> Iterator[None]:
    """Run numpy's and SciPy's BLAS on one thread inside the block (restored after)."""
    before = [int(get()) for get, _ in _BLAS_THREADS]
    for _, put in _BLAS_THREADS:
        put(1)
    try:
        yield
    finally:
        for (_, put), b in zip(_BLAS_THREADS, before, strict=True):
            put(b)


def blas_single(fn: Callable[P, T]) -> Callable[P, T]:
    """Decorator: run ``fn`` inside :func:`single_threaded_blas`."""

    @functools.wraps(fn)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> T:
        with single_threaded_blas():
            return fn(*args, **kwargs)

    return wrapper
