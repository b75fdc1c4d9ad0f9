"""Empty-space skipping and early termination on vs off: samples per ray, time per training step,
render time and PSNR, on one window of a sequence, trained twice in one process with the same seed.

    pag bench render [--seq synth_row] [--window 0] [--steps 150] [--threads 2]
"""
from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from bench._common import bar_plot, write_parquet
from nerf.config import preset
from nerf.trainer import fit_window
from pipeline.io import read_table
from stages.nerf_fit import load_window


def run(seq: str = "synth_row", window: int = 0, steps: int = 150, threads: int = 2, data_root: Path = Path("data"),
        out_dir: Path = Path("data/bench")) -> pd.DataFrame:
    torch.set_num_threads(threads)
    frames = read_table(data_root / "interim" / seq / "frames.parquet", "frames")
    windows = read_table(data_root / "interim" / seq / "windows.parquet", "windows")
    w = windows[windows.window_id == window].merge(frames, on="frame_id")
    if w.empty:
        raise ValueError(f"window {window} not in {seq}; windows: {sorted(windows.window_id.unique())}")
    data = load_window(w, data_root)
    base = preset("cpu", steps=steps, refine_poses=False)
    rows = []
    for skip in (True, False):
        cfg = replace(base, skip_empty=skip)
        t0 = time.perf_counter()
        res = fit_window(data, cfg)
        rows.append({"skip_empty": skip, "steps": steps, "s_per_step": res.fit_s / steps,
                     "train_samples_per_ray": float(np.mean([h["samples_per_ray"] for h in res.history])),
                     "render_samples_per_ray": res.samples_per_ray, "render_s_per_image": res.render_s_per_image,
                     "val_psnr": float(np.mean(list(res.val_psnr.values()))), "wall_s": time.perf_counter() - t0,
                     "threads": threads, "seq": seq, "window": window})
    df = pd.DataFrame(rows)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_parquet(df, out_dir / "render.parquet")
    bar_plot(["train spr (skip)", "train spr (dense)", "render spr (skip)", "render spr (dense)"],
             [df.train_samples_per_ray[0], df.train_samples_per_ray[1], df.render_samples_per_ray[0],
              df.render_samples_per_ray[1]], "samples per ray", f"occupancy skipping, {seq} window {window}",
             out_dir / "render.png")
    return df


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="pag bench render", description=__doc__.split("\n")[0])
    p.add_argument("--seq", default="synth_row")
    p.add_argument("--window", type=int, default=0)
    p.add_argument("--steps", type=int, default=150)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--data-root", type=Path, default=Path("data"))
    p.add_argument("--out", type=Path, default=Path("data/bench"))
    a = p.parse_args(argv)
    df = run(a.seq, a.window, a.steps, a.threads, a.data_root, a.out)
    print(df.to_string(index=False, float_format=lambda v: f"{v:.3f}"))
    on, off = df.iloc[0], df.iloc[1]
    print(f"\nrender samples per ray: {off.render_samples_per_ray / on.render_samples_per_ray:.1f}x fewer with skipping "
          f"(target >= 3x); train: {off.train_samples_per_ray / on.train_samples_per_ray:.1f}x; "
          f"time per step {off.s_per_step / on.s_per_step:.1f}x; PSNR change {on.val_psnr - off.val_psnr:+.2f} dB "
          f"(target >= -0.3 dB)")
    return 0
