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


def read(data_root: Path, seq: str, name: str) -> pd.DataFrame:
    """Table `name` of sequence `seq` from the catalog (validated against its schema); a clear error naming the
    stage to run when it does not exist."""
    from pipeline import dag
    from pipeline.catalog import dataset
    from pipeline.io import read_table

    ds = dataset(name)
    path = ds.path(data_root, seq)
    if not path.is_file():
        producer = dag.producers(dag.build()).get(name, "")
        how = f"run `pag {producer} --seq {seq}` (or `pag all --seq {seq}`) first" if producer else "see data/README.md"
        raise FileNotFoundError(f"{name} table of {seq!r} not found at {path}; {how}")
    return read_table(path, ds.schema)


def window_rows(data_root: Path, seq: str, window: int) -> tuple[pd.DataFrame, pd.DataFrame]:
    """A window's rows of the windows table joined with the frames table (in frame order), and the sequence's
    detections_filtered table; a clear error if the sequence has no such window."""
    frames = read(data_root, seq, "frames")
    windows = read(data_root, seq, "windows")
    w = windows[windows.window_id == window].merge(frames, on="frame_id").sort_values("frame_id")
    if w.empty:
        raise ValueError(f"window {window} not in {seq}; windows: {sorted(windows.window_id.unique())}")
    return w.reset_index(drop=True), read(data_root, seq, "detections_filtered")


def stage_defaults(name: str):
    """The default config of pipeline stage `name` (what `pag <name>` runs without --set)."""
    from pipeline import dag

    return dag.load_stage(name).config_class()


def run_stage(seq: str, data_root: Path, stage: str, overrides: list[str] | tuple[str, ...] = (),
              tables: dict[str, pd.DataFrame] | None = None) -> tuple[dict[str, pd.DataFrame], float]:
    """Run pipeline stage `stage` through the runner on sequence `seq` without touching its data (run_stages).
    Returns the stage's output tables and the seconds the stage ran."""
    out, results = run_stages(seq, data_root, [stage], overrides, tables)
    return out, results[0].seconds


def run_stages(seq: str, data_root: Path, stages: list[str], overrides: list[str] | tuple[str, ...] = (),
               tables: dict[str, pd.DataFrame] | None = None, config: dict | None = None):
    """Run pipeline stages `stages` (in DAG order, each on the outputs of the ones before) through the runner on
    sequence `seq` without touching its data: in a temporary data/ whose datasets link to those under
    `data_root`, except the stages' outputs and `tables` (name -> DataFrame) written in place of the stored ones.
    `config` ({section: {key: value}}) is the run's config file, `overrides` go over it (section.key=value).
    Returns the stages' output tables and the runner's StageResult per stage."""
    import tempfile

    import yaml

    from pipeline import dag
    from pipeline.catalog import DATASETS
    from pipeline.io import read_table, write_table
    from pipeline.runner import Runner

    tables = tables or {}
    outputs = [o for name in stages for o in dag.load_stage(name).outputs]
    with tempfile.TemporaryDirectory(prefix="pag_bench_") as tmp:
        root = Path(tmp) / "data"
        for name, ds in DATASETS.items():
            src, dst = ds.path(data_root, seq), ds.path(root, seq)
            if name in tables:
                write_table(tables[name], dst, ds.schema)
            elif src.exists() and name not in outputs:
                dst.parent.mkdir(parents=True, exist_ok=True)
                dst.symlink_to(src.resolve(), target_is_directory=src.is_dir())
        config_file = None
        if config:
            config_file = Path(tmp) / "config.yaml"
            config_file.write_text(yaml.safe_dump(config, sort_keys=False))
        results = Runner(seq, data_root=root, config_file=config_file, overrides=list(overrides),
                         show_progress=False).run(stages, force=True)
        out = {o: read_table(DATASETS[o].path(root, seq), DATASETS[o].schema)
               for o in outputs if DATASETS[o].kind == "table"}
    return out, results
