"""Peak memory of a piece of work, worker processes included.

`PeakMemory` samples the resident set size (RSS) of this process and all its descendants (Dask workers,
process pools) on a background thread and keeps the largest sum seen. Sampling misses peaks shorter than
`interval_s`; the figure is a lower bound of the true peak, close to it for stages that run for seconds.
"""
from __future__ import annotations

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
