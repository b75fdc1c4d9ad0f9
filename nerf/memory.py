"""Freed memory handed back to the system between the phases of a fit (and between a run's stages)."""
from __future__ import annotations

import ctypes
import ctypes.util
import functools
import gc
import sys


@functools.cache
def _malloc_trim():
    """glibc's malloc_trim, or None where the C library has none (macOS, musl)."""
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return None


def release_freed() -> bool:
    """Collect garbage, free the encoding kernels' cached blocks (nerf/_ext.py, when loaded: up to 1 GiB kept
    for reuse across steps, of sizes the next phase or window may never ask for) and return the C heap's
    free pages to the system (glibc malloc_trim). Arrays under
    glibc's mmap threshold (which rises to 32 MB once such blocks are freed) are carved from the heap, and
    their pages stay resident after they are freed; the next phase's large arrays are mapped afresh beside
    them, so a phase's peak would carry the last phase's garbage. True where the heap could be trimmed."""
    gc.collect()
    ext = sys.modules.get("nerf._ext")  # (never imported here: the runner calls this without torch)
    if ext is not None:
        ext.release_cached()
    trim = _malloc_trim()
    if trim is None:
        return False
    trim(0)
    return True
