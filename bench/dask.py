"""nerf_fit scaling: the same windows fitted by 1 Dask worker and by N workers (one thread each), in one run.

Each window of the sequence is cut into `--split` runs of consecutive frames (default 2) and the first
`--tasks` of them (default 4: 2 per worker, so an idle worker at the end costs little) are fitted with
fewer steps and without the panoptic phase (it scales the same way and would double the cost). The
nerf_fit stage runs as the pipeline runs it (bench._common.run_stage: in a temporary data/ linked to the
sequence's, which stays untouched); wall_s is the stage's run time, cluster start-up included.

    pag bench dask [--seq synth_row] [--steps 100] [--workers 2] [--split 2] [--tasks 4]
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd

from bench._common import bar_plot, read, run_stage, write_parquet


def split_windows(windows: pd.DataFrame, parts: int) -> pd.DataFrame:
    """Each window's frames (by frame id) cut into `parts` runs of consecutive frames, renumbered 0.."""
    out, wid = [], 0
    for _, w in windows.sort_values(["window_id", "frame_id"]).groupby("window_id"):
        for chunk in np.array_split(np.arange(len(w)), parts):
            sub = w.iloc[chunk]
            if len(chunk) and (sub.split == "train").any():
                out.append(sub.assign(window_id=wid))
                wid += 1
    return pd.concat(out, ignore_index=True)


def run(seq: str = "synth_row", steps: int = 100, workers: int = 2, split: int = 2, tasks: int = 4,
        data_root: Path = Path("data"),
        out_dir: Path = Path("data/bench")) -> pd.DataFrame:
    windows = split_windows(read(data_root, seq, "windows"), max(1, split))
    windows = windows[windows.window_id.isin(sorted(windows.window_id.unique())[: tasks or None])]
    n_tasks = int(windows.window_id.nunique())
    rows = []
    for n in (1, workers):
        out, wall = run_stage(seq, data_root, "nerf_fit", tables={"windows": windows}, overrides=[
            f"nerf_fit.model.steps={steps}", "nerf_fit.panoptic.enabled=false", f"nerf_fit.workers={n}",
            "nerf_fit.threads_per_worker=1"])
        m = out["window_metrics"]
        failed = m[m.status != "ok"]
        if len(failed):
            raise RuntimeError(f"windows {failed.window_id.tolist()} failed: {failed.error.iloc[0]}")
        rows.append({"workers": n, "threads_per_worker": 1, "windows": n_tasks, "steps": steps, "wall_s": wall,
                     "task_s_mean": float(m.fit_s.mean())})
    df = pd.DataFrame(rows)
    df["speedup_vs_1"] = df.wall_s.iloc[0] / df.wall_s
    out_dir.mkdir(parents=True, exist_ok=True)
    write_parquet(df, out_dir / "dask.parquet")
    plot(df, out_dir / "dask.png")
    return df


def plot(df: pd.DataFrame, path: Path) -> None:
    bar_plot([f"{int(r.workers)} worker(s)" for r in df.itertuples()], list(df.wall_s), "wall seconds",
             f"nerf_fit scaling: {int(df.windows.iloc[0])} tasks x {int(df.steps.iloc[0])} steps; speedup "
             f"{df.speedup_vs_1.iloc[-1]:.2f}x", path)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="pag bench dask", description=__doc__.split("\n")[0])
    p.add_argument("--seq", default="synth_row")
    p.add_argument("--steps", type=int, default=100)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--split", type=int, default=2, help="cut each window into this many tasks")
    p.add_argument("--tasks", type=int, default=4, help="fit at most this many of them (0 = all)")
    p.add_argument("--data-root", type=Path, default=Path("data"))
    p.add_argument("--out", type=Path, default=Path("data/bench"))
    a = p.parse_args(argv)
    df = run(a.seq, a.steps, a.workers, a.split, a.tasks, a.data_root, a.out)
    print(df.to_string(index=False, float_format=lambda v: f"{v:.2f}"))
    print(f"\ntarget: {a.workers} workers >= 1.6x faster than 1 ({int(df.windows.iloc[0])} tasks; an odd number "
          f"of tasks caps the ideal: 3 -> 1.5x, 5 -> 1.67x)")
    return 0
