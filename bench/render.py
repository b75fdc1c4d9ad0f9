"""Empty-space skipping and early termination on vs off, on one window of a sequence: one model is fitted
(with skipping, the default), then the same validation frames are rendered with occupancy skipping and
early termination and with dense marching through the window's bounds (no grid, no early stop). Reports
samples per ray, render time and PSNR per mode; plus the time per training step of each mode, measured
on a few extra steps, interleaved.

    pag bench render [--seq synth_row] [--window 0] [--steps 300] [--frames 3] [--threads 2]
"""
from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from bench._common import bar_plot, kept_frames, window_rows, write_parquet
from nerf.config import preset
from nerf.metrics import psnr
from nerf.trainer import fit_window
from rowmap.window_data import load_window


def run(seq: str = "synth_row", window: int = 0, steps: int = 300, frames: int = 3, threads: int = 2,
        data_root: Path = Path("data"), out_dir: Path = Path("data/bench")) -> pd.DataFrame:
    torch.set_num_threads(threads)
    w, _ = window_rows(data_root, seq, window)
    data = load_window(w, data_root)
    data = data.take(kept_frames(data.is_train, frames))
    cfg = preset("cpu", steps=steps)
    res = fit_window(data, cfg)
    model = res.model
    # time per training step of each mode: a few more steps from scratch, interleaved (median of 3 short fits)
    step_s: dict[bool, list[float]] = {True: [], False: []}
    tiny = data.take(kept_frames(data.is_train, 0))  # train frames only: no renders at the end
    for _ in range(3):
        for skip in (True, False):
            r = fit_window(tiny, replace(cfg, steps=12, skip_empty=skip,
                                         early_stop_transmittance=cfg.early_stop_transmittance if skip else 0.0))
            step_s[skip].append(r.fit_s / 12)
    rows = []
    for skip in (True, False):
        model.cfg = replace(cfg, skip_empty=skip, early_stop_transmittance=cfg.early_stop_transmittance if skip else 0.0)
        spr, secs, ps = [], [], []
        for i in np.flatnonzero(~data.is_train):
            t0 = time.perf_counter()
            out = model.render_image(int(i))
            secs.append(time.perf_counter() - t0)
            spr.append(out["samples_per_ray"])
            ps.append(psnr(out["rgb"], torch.from_numpy(data.images[i]).float() / 255.0))
        rows.append({"skip_empty": skip, "fit_steps": steps, "train_s_per_step": float(np.median(step_s[skip])),
                     "render_samples_per_ray": float(np.mean(spr)), "render_s_per_image": float(np.median(secs)),
                     "val_psnr": float(np.mean(ps)), "frames": len(ps), "threads": threads, "seq": seq,
                     "window": window})
    model.cfg = cfg
    df = pd.DataFrame(rows)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_parquet(df, out_dir / "render.parquet")
    bar_plot(["render spr (skip)", "render spr (dense)", "render s/img (skip)", "render s/img (dense)"],
             [df.render_samples_per_ray[0], df.render_samples_per_ray[1], df.render_s_per_image[0],
              df.render_s_per_image[1]], "samples per ray / seconds",
             f"occupancy skipping, {seq} window {window}: PSNR {df.val_psnr[0]:.2f} vs {df.val_psnr[1]:.2f} dB",
             out_dir / "render.png")
    return df


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="pag bench render", description=__doc__.split("\n")[0])
    p.add_argument("--seq", default="synth_row")
    p.add_argument("--window", type=int, default=0)
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--frames", type=int, default=3, help="validation frames rendered per mode")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--data-root", type=Path, default=Path("data"))
    p.add_argument("--out", type=Path, default=Path("data/bench"))
    a = p.parse_args(argv)
    df = run(a.seq, a.window, a.steps, a.frames, a.threads, a.data_root, a.out)
    print(df.to_string(index=False, float_format=lambda v: f"{v:.3f}"))
    on, off = df.iloc[0], df.iloc[1]
    print(f"\nrender samples per ray: {off.render_samples_per_ray / on.render_samples_per_ray:.1f}x fewer with skipping "
          f"(target >= 3x); render time {off.render_s_per_image / on.render_s_per_image:.1f}x; "
          f"train time per step {off.train_s_per_step / on.train_s_per_step:.1f}x; "
          f"PSNR change {on.val_psnr - off.val_psnr:+.2f} dB (target >= -0.3 dB)")
    return 0
