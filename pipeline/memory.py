"""Give memory that was freed back to the operating system between the large steps of a long stage.

A stage that works through an hour's recording in steps (evaluate's cases) frees hundreds of MB after each step, but
the allocators keep it: glibc's heap cannot shrink below a live block and keeps freed chunks for reuse, pyarrow's
pool keeps its pages. The process's resident size then only grows, although what is live does not (measured on an
hour's evaluate: about 300 MB held after the first case). :func:`release_freed_memory` asks both to give back what
they hold unused; it changes no result and costs a few milliseconds.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import gc

import pyarrow as pa


@functools.cache
def _libc(name: str) -> ctypes._CFuncPtr | None:  # type: ignore[name-defined]
    """glibc's function ``name`` (``malloc_trim``, ``mallopt``); None elsewhere (musl, macOS, Windows)."""
    lib = ctypes.util.find_library("c")
    if lib is None:
        return None
    try:
        return getattr(ctypes.CDLL(lib), name)
    except (OSError, AttributeError):
        return None


M_MMAP_THRESHOLD = -3
LARGE_BLOCK_BYTES = 1 << 20


def map_large_blocks(threshold: int = LARGE_BLOCK_BYTES) -> None:
    """Have glibc give every allocation of ``threshold`` bytes or more its own mapping, unmapped when it is freed.

    By default glibc raises that threshold to the size of the largest block freed so far (up to 32 MB), so that the
    numpy arrays of a long stage land on the heap, where what they leave free stays resident until
    :func:`release_freed_memory`. Changes no result."""
    fn = _libc("mallopt")
    if fn is not None:
        fn(M_MMAP_THRESHOLD, threshold)


def freeze_live_objects() -> None:
    """Have the cyclic garbage collector ignore, from now on, every object alive now.

    Called once a stage's libraries are imported: their modules, classes and functions (~140,000 objects after
    evaluate's imports) then stop being traversed by every full collection, which cost 66 ms each on the sample,
    whether :func:`release_freed_memory` asked for it or Python did. The caller collects first, so nothing already
    garbage is kept; what stays frozen are objects alive for the process's lifetime. Changes no result."""
    gc.freeze()


def release_freed_memory(collect: bool = True) -> None:
    """Collect garbage (unless ``collect`` is False: what was just freed had no cycles), then return the freed memory
    of glibc's heap and pyarrow's pool to the system."""
    if collect:
        gc.collect()
    trim = _libc("malloc_trim")
    if trim is not None:
        trim(0)
    pa.default_memory_pool().release_unused()
