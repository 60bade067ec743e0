"""release_freed_memory gives a fragmented heap's free pages back to the system."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from pipeline.memory import _malloc_trim, release_freed_memory


def _rss_mib() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096 / 2**20


@pytest.mark.skipif(not sys.platform.startswith("linux") or _malloc_trim() is None, reason="needs glibc's malloc_trim")
def test_a_fragmented_heap_shrinks_after_release() -> None:
    # 160 MB of 8 KB blocks (below glibc's mmap threshold: they live in the heap), every 64th kept: the free runs
    # between the kept blocks cannot be returned by the heap's own top trim, only by malloc_trim
    blocks = [np.ones(1024) for _ in range(20_000)]
    kept = blocks[::64]
    del blocks
    held = _rss_mib()
    release_freed_memory()
    after = _rss_mib()
    assert held - after > 80, f"RSS {held:.0f} -> {after:.0f} MiB"
    assert all(float(k.sum()) == 1024.0 for k in kept)  # the live blocks are untouched
