"""Peak memory of a piece of work, worker processes included.

`PeakMemory` samples the resident set size (RSS) of this process and all its descendants (Dask workers,
process pools) on a background thread and keeps the largest sum seen. Sampling misses peaks shorter than
`interval_s`; the figure is a lower bound of the true peak, close to it for stages that run for seconds.
`reset_own_peak` / `own_peak_mb` read one process's exact peak over a piece of work from the kernel's
high-water mark (Linux), e.g. a Dask worker's over one window's fit.
"""
from __future__ import annotations

import math
import os
import threading
from types import TracebackType

import psutil


def tree_rss_bytes(pid: int | None = None) -> int:
    """RSS of process `pid` (default: this one) plus every live descendant, in bytes."""
    try:
        root = psutil.Process(pid or os.getpid())
        procs = [root, *root.children(recursive=True)]
    except psutil.Error:
        return 0
    total = 0
    for p in procs:
        try:
            total += p.memory_info().rss
        except psutil.Error:  # exited between listing and reading
            continue
    return total


def reset_own_peak() -> bool:
    """Reset this process's resident-memory high-water mark (Linux: /proc/self/clear_refs), so own_peak_mb
    then reads the peak from now on. False where the system cannot (own_peak_mb is then nan)."""
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return True
    except OSError:
        return False


def own_peak_mb() -> float:
    """This process's peak resident memory (MiB) since reset_own_peak (the kernel's VmHWM); nan where unknown."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except (OSError, ValueError, IndexError):
        pass
    return math.nan


class PeakMemory:
    """Context manager: `with PeakMemory() as m: ...; m.peak_mb` = the largest process-tree RSS seen (MiB)."""

    def __init__(self, interval_s: float = 0.2):
        if interval_s <= 0:
            raise ValueError(f"interval_s must be > 0, got {interval_s}")
        self.interval_s = interval_s
        self.peak_bytes = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def sample(self) -> None:
        self.peak_bytes = max(self.peak_bytes, tree_rss_bytes())

    def _loop(self) -> None:
        while not self._stop.wait(self.interval_s):
            self.sample()

    def start(self) -> PeakMemory:
        self.sample()
        self._thread = threading.Thread(target=self._loop, name="pag-peak-memory", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        self.sample()

    def __enter__(self) -> PeakMemory:
        return self.start()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()

    @property
    def peak_mb(self) -> float:
        return self.peak_bytes / 2**20
