"""release_freed_memory gives a fragmented heap's free pages back to the system; after map_large_blocks a freed large
array is given back at once."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from pipeline.memory import _libc, release_freed_memory
from tests.fixtures.memory import resident_mib


@pytest.mark.skipif(
    not sys.platform.startswith("linux") or _libc("malloc_trim") is None, reason="needs glibc's malloc_trim"
)
@pytest.mark.parametrize("collect", [True, False])
def test_a_fragmented_heap_shrinks_after_release(collect: bool) -> None:
    # 160 MB of 8 KB blocks (below glibc's mmap threshold: they live in the heap), every 64th kept: the free runs
    # between the kept blocks cannot be returned by the heap's own top trim, only by malloc_trim
    blocks = [np.ones(1024) for _ in range(20_000)]
    kept = blocks[::64]
    del blocks
    held = resident_mib()
    release_freed_memory(collect=collect)  # the freed blocks had no cycles: the trim alone gives them back
    after = resident_mib()
    assert held - after > 80, f"RSS {held:.0f} -> {after:.0f} MiB"
    assert all(float(k.sum()) == 1024.0 for k in kept)  # the live blocks are untouched


_FREED_AT_ONCE = """
import numpy as np
from pipeline.memory import map_large_blocks
def rss():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096 / 2**20
if MAP:
    map_large_blocks()
big = np.ones(2**21)  # 16 MB, mapped and freed: glibc's own threshold then rises to 16 MB
del big
a = [np.ones(2**20) for _ in range(8)]  # 8 MB arrays: on the heap below that threshold, mapped above ours
kept = a[1::2]  # every other one stays: the freed ones are not at the heap's top, which glibc trims itself
before = rss()
del a[::2]
print(before - rss())
"""


@pytest.mark.skipif(not sys.platform.startswith("linux") or _libc("mallopt") is None, reason="needs glibc's mallopt")
def test_large_arrays_are_given_back_when_freed_after_map_large_blocks() -> None:
    def freed(map_them: bool) -> float:
        code = f"MAP = {map_them}\n" + _FREED_AT_ONCE
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
        return float(out)

    assert freed(True) > 28  # the 32 MB of arrays left with them
    assert freed(False) < 4  # glibc's default keeps them
