"""Builds and loads the fused C++ kernels (torch cpp_extension, JIT with ninja), once per process.

Any failure (no compiler, build error) gives one warning and `None`, and callers fall back to the
pure-torch reference. PAG_NO_EXT=1 forces that fallback.
"""
from __future__ import annotations

import os
import warnings
from pathlib import Path
from types import ModuleType

_CACHE: dict[str, ModuleType | None] = {}
_SRC = Path(__file__).parent / "csrc"
BUILD_DIR = Path(os.environ.get("PAG_EXT_BUILD_DIR", Path(__file__).resolve().parents[1] / ".cache" / "torch_extensions"))


def load_permuto_ext(device_type: str = "cpu") -> ModuleType | None:
    """The CPU kernels module, or None (with one warning) when it cannot be built."""
    if os.environ.get("PAG_NO_EXT") == "1":
        return None
    if device_type != "cpu":
        return None  # CUDA devices use the torch reference (the CPU kernel is CPU-only)
    if "cpu" in _CACHE:
        return _CACHE["cpu"]
    try:
        from torch.utils.cpp_extension import load

        BUILD_DIR.mkdir(parents=True, exist_ok=True)
        mod = load(name="pag_permuto_cpu", sources=[str(_SRC / "permuto_cpu.cpp")],
                   extra_cflags=["-O3", "-fopenmp", "-std=c++17"], extra_ldflags=["-fopenmp"],
                   build_directory=str(BUILD_DIR), verbose=False)
    except Exception as err:  # no compiler, no ninja, build error: fall back, say so once
        warnings.warn(f"fused permutohedral kernel unavailable ({type(err).__name__}: {str(err)[:300]}); "
                      f"using the pure-torch reference (slower)", RuntimeWarning, stacklevel=2)
        mod = None
    _CACHE["cpu"] = mod
    return mod
