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


def test_the_kernels_cached_blocks_are_freed_between_phases():
    import torch

    from nerf import _ext
    from nerf.encoding import PermutoEncoding

    ext = _ext.load_permuto_ext("cpu")
    if ext is None:
        pytest.skip("no C++ toolchain here: the fused kernel is unavailable")
    enc = PermutoEncoding(n_levels=8, n_features=2, log2_capacity=12, coarsest_scale=1.0, finest_scale=0.01,
                          backend="fused")
    out = enc(torch.rand(40_000, 3) * 2 - 1)      # 2.6 MB of features: a pooled block
    del out                                        # its block goes back to the pool, kept for the next step
    assert ext.cached_bytes() >= 40_000 * 16 * 4
    release_freed()
    assert ext.cached_bytes() == 0
