"""Builds and loads the fused encoding kernels (torch.utils.cpp_extension, JIT with ninja) once per
process and device type: nerf/csrc/permuto_cpu.cpp (C++17 + OpenMP) for "cpu", and
nerf/csrc/permuto_cuda.cpp + permuto_cuda_kernels.cu for "cuda" (only when torch sees a GPU and a
working nvcc). Build products go to .cache/torch_extensions/ (or $PAG_EXT_BUILD_DIR).

Any failure (no compiler, no nvcc, build error) gives exactly one warning per device type and
`None`; callers then fall back to the pure-torch reference. PAG_NO_EXT=1 forces that fallback.
"""
from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import warnings
from pathlib import Path
from types import ModuleType

import torch

_CACHE: dict[str, ModuleType | None] = {}
_SRC = Path(__file__).parent / "csrc"
BUILD_DIR = Path(os.environ.get("PAG_EXT_BUILD_DIR",
                                Path(__file__).resolve().parents[1] / ".cache" / "torch_extensions"))
# Portable flags only: the .so may be reused on another CPU, so no -march=native. Contraction into
# FMAs is off so the kernel's lattice arithmetic matches the torch reference bit for bit.
CPU_FLAGS = ["-O3", "-fopenmp", "-ffp-contract=off"]


def _nvcc_problem() -> str | None:
    """Why the CUDA kernels cannot be built here, or None."""
    if not torch.cuda.is_available():
        return "torch sees no CUDA device"
    if torch.version.cuda is None:
        return "this torch build has no CUDA support"
    from torch.utils.cpp_extension import CUDA_HOME

    nvcc = Path(CUDA_HOME) / "bin" / "nvcc" if CUDA_HOME else shutil.which("nvcc")
    if not nvcc or not Path(nvcc).exists():
        return "nvcc not found (set CUDA_HOME)"
    try:
        done = subprocess.run([str(nvcc), "--version"], capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.SubprocessError) as err:
        return f"nvcc does not run: {err}"
    if done.returncode != 0 or "release" not in done.stdout:
        return f"nvcc at {nvcc} is not a working CUDA compiler"
    return None


def _sources_tag() -> str:
    """Hash of every file in csrc/ (headers included), passed as a define so that any change
    triggers a rebuild (torch's JIT versioning hashes only the listed sources)."""
    h = hashlib.sha1()
    for f in sorted(_SRC.iterdir()):
        h.update(f.name.encode() + f.read_bytes())
    return h.hexdigest()[:12]


def _build(device_type: str) -> ModuleType:
    from torch.utils.cpp_extension import load

    BUILD_DIR.mkdir(parents=True, exist_ok=True)
    tag = f"-DPAG_SOURCES={_sources_tag()}"
    if device_type == "cpu":
        return load(name="pag_permuto_cpu", sources=[str(_SRC / "permuto_cpu.cpp")], extra_cflags=CPU_FLAGS + [tag],
                    extra_ldflags=["-fopenmp"], build_directory=str(BUILD_DIR), verbose=False)
    problem = _nvcc_problem()
    if problem:
        raise RuntimeError(problem)
    return load(name="pag_permuto_cuda", sources=[str(_SRC / "permuto_cuda.cpp"), str(_SRC / "permuto_cuda_kernels.cu")],
                extra_cflags=["-O3", tag], extra_cuda_cflags=["-O3", tag],
                build_directory=str(BUILD_DIR), verbose=False)


def load_permuto_ext(device_type: str = "cpu") -> ModuleType | None:
    """The kernels module for "cpu" or "cuda", or None (after one warning) when it cannot be built."""
    if os.environ.get("PAG_NO_EXT") == "1":
        return None
    if device_type not in ("cpu", "cuda"):
        return None  # other devices (mps, ...) use the torch reference
    if device_type in _CACHE:
        return _CACHE[device_type]
    try:
        mod = _build(device_type)
    except Exception as err:  # no compiler, no nvcc, build error: fall back, say so once
        reason = " ".join(f"{type(err).__name__}: {err}".split())[:400]
        warnings.warn(f"fused permutohedral kernel unavailable on {device_type} ({reason}); using the pure-torch "
                      f"reference (slower)", RuntimeWarning, stacklevel=3)
        mod = None
    _CACHE[device_type] = mod
    return mod


def release_cached() -> int:
    """Free what the loaded CPU kernels keep for reuse (the output pool's blocks, this thread's scratch);
    returns the bytes freed (0 when the kernels are not loaded)."""
    mod = _CACHE.get("cpu")
    return int(mod.release_cached()) if mod is not None else 0
