"""Freed memory handed back between a fit's phases (nerf/memory.py)."""
import numpy as np
import psutil
import pytest

from nerf.memory import release_freed


def test_freed_heap_pages_are_returned_to_the_system():
    rss = lambda: psutil.Process().memory_info().rss  # noqa: E731
    blocks, pins = [], []
    for _ in range(3000):  # 64 KB blocks come from the heap; a small block kept after each holds the heap open
        blocks.append(np.ones(8192))
        pins.append(np.ones(128))
    held = rss()
    del blocks
    if not release_freed():
        pytest.skip("this C library has no malloc_trim")
    assert held - rss() > 100 * 2**20   # most of the 190 MB freed is no longer resident
    assert len(pins) == 3000
