"""Shared benchmark helpers: interleaved repeats with medians, atomic table output, plots."""
from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.io import atomic_write_bytes


def interleaved_medians(variants: dict[str, Callable[[], None]], repeats: int, warmup: int = 1) -> dict[str, list[float]]:
    """Time every variant once per round, `repeats` rounds, so machine noise hits all variants alike."""
    for _ in range(warmup):
        for fn in variants.values():
            fn()
    times: dict[str, list[float]] = {k: [] for k in variants}
    for _ in range(repeats):
        for name, fn in variants.items():
            t0 = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t0)
    return times


def median(xs: list[float]) -> float:
    return float(statistics.median(xs))


def write_parquet(df: pd.DataFrame, path: Path) -> None:
    """Write a bench table atomically, with the commit that measured it in the file's metadata
    (`pag.commit`, read by `pag bench results`)."""
    import io

    import pyarrow as pa
    import pyarrow.parquet as pq

    from pipeline.provenance import code_version

    table = pa.Table.from_pandas(df, preserve_index=False)
    meta = dict(table.schema.metadata or {})
    meta[b"pag.commit"] = code_version().encode()
    buf = io.BytesIO()
    pq.write_table(table.replace_schema_metadata(meta), buf)
    atomic_write_bytes(path, buf.getvalue())


def bar_plot(labels: list[str], values: list[float], ylabel: str, title: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.5))
    ax.bar(labels, values, color=["#c44", "#4a4", "#888", "#48c", "#aaa"][: len(labels)])
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=10)
    for i, v in enumerate(values):
        ax.text(i, v, f"{v:.3g}", ha="center", va="bottom", fontsize=8)
    plt.xticks(rotation=15, fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def kept_frames(is_train: np.ndarray, n_val: int | None) -> np.ndarray:
    """Indices of every training frame and of `n_val` validation frames spread evenly over the window
    (None = all of them, 0 = none), in frame order: fewer renders in a benchmark."""
    val = np.flatnonzero(~is_train)
    if n_val is not None and n_val < len(val):
        val = val[np.linspace(0, len(val) - 1, n_val).round().astype(int)] if n_val > 0 else val[:0]
    return np.sort(np.concatenate([np.flatnonzero(is_train), val]))


def window_rows(data_root: Path, seq: str, window: int) -> tuple[pd.DataFrame, pd.DataFrame]:
    """A window's rows of windows.parquet joined with frames.parquet (in frame order), and the sequence's
    detections_filtered table; a clear error if the sequence has no such window."""
    from pipeline.io import read_table

    interim = data_root / "interim" / seq
    frames = read_table(interim / "frames.parquet", "frames")
    windows = read_table(interim / "windows.parquet", "windows")
    w = windows[windows.window_id == window].merge(frames, on="frame_id").sort_values("frame_id")
    if w.empty:
        raise ValueError(f"window {window} not in {seq}; windows: {sorted(windows.window_id.unique())}")
    return w.reset_index(drop=True), read_table(interim / "detections_filtered.parquet", "detections")
