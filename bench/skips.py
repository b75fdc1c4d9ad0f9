"""What skipping work a scene does not need saves, each measured on its own, side by side in one run:

- empty space: occupancy-grid skipping on vs off (early termination on in both), rendering validation frames;
- saturated rays: early termination on vs off (occupancy skipping on in both), the same frames;
- windows without any thing detection: the panoptic phase of the window with its fruit detections
  removed, semantic-only (the defaults' share stuff_only_steps / steps of the steps) vs the full phase
  it would otherwise run;
- frames without fruit: the window with every other training frame's fruit detections removed; the
  assignments skipped during its panoptic phase times the measured cost of one frame's assignment (an
  estimate built from measured parts: the skipped work never runs);
- unchanged stages: `pag all` on a tiny synthetic row, run once, then again with nothing changed
  (every stage's manifest matches, nothing reruns).

Render times are medians of interleaved repeats over the same frames; the panoptic phases alternate too.

    pag bench skips [--seq synth_row] [--window 0] [--steps 300] [--frames 2] [--panoptic-steps 150]
"""
from __future__ import annotations

import argparse
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from bench._common import bar_plot, kept_frames, median, window_rows, write_parquet
from nerf.config import PanopticConfig, preset
from nerf.metrics import psnr
from nerf.panoptic.labels import WindowLabels
from nerf.panoptic.train import fit_panoptic
from nerf.trainer import fit_window
from pipeline.classes import THING_IDS
from rowmap.window_data import load_labels, load_window

TINY_ROW = ["synth.n_frames=12", "synth.width=64", "synth.height=40", "synth.n_labelled=2", "synth.supersample=1",
            "synth.workers=1", "windows.half_width=3", "nerf_fit.model.steps=20", "nerf_fit.model.rays_per_step=128",
            "nerf_fit.model.n_levels=4", "nerf_fit.model.log2_capacity=12", "nerf_fit.panoptic.steps=20",
            "nerf_fit.panoptic.rays_per_frame=64", "nerf_fit.panoptic.frames_per_step=2"]


def _render_modes(model, data, repeats: int) -> dict[str, dict[str, float]]:
    base = model.cfg
    modes = {"all skips": base, "no occupancy skipping": replace(base, skip_empty=False),
             "no early termination": replace(base, early_stop_transmittance=0.0)}
    secs: dict[str, list[float]] = {m: [] for m in modes}
    spr: dict[str, list[float]] = {m: [] for m in modes}
    ps: dict[str, list[float]] = {m: [] for m in modes}
    val = np.flatnonzero(~data.is_train)
    for r in range(repeats):
        for i in val:
            for name, cfg in modes.items():
                model.cfg = cfg
                t0 = time.perf_counter()
                out = model.render_image(int(i))
                secs[name].append(time.perf_counter() - t0)
                if r == 0:
                    spr[name].append(float(out["samples_per_ray"]))
                    ps[name].append(psnr(out["rgb"], torch.from_numpy(data.images[i]).float() / 255.0))
    model.cfg = base
    return {m: {"s_per_image": median(secs[m]), "samples_per_ray": float(np.mean(spr[m])),
                "psnr": float(np.mean(ps[m]))} for m in modes}


def _without_things(labels: WindowLabels) -> WindowLabels:
    """The detector input with every fruit detection gone (its pixels become plant, as a miss looks)."""
    thing = np.isin(labels.semantic, THING_IDS)
    return WindowLabels(np.where(thing, 1, labels.semantic).astype(np.uint8), np.zeros_like(labels.instance))


def _manifest_rerun() -> tuple[float, float]:
    from pipeline import cli

    sets = [a for kv in TINY_ROW for a in ("--set", kv)]
    with tempfile.TemporaryDirectory() as tmp:
        times = []
        for _ in range(2):
            t0 = time.perf_counter()
            rc = cli.main(["all", "--seq", "synth_skips", "--data-root", str(Path(tmp) / "data"), "--no-progress",
                           *sets])
            if rc != 0:
                raise RuntimeError(f"`pag all` on the tiny row failed with exit code {rc}")
            times.append(time.perf_counter() - t0)
    return times[0], times[1]


def run(seq: str = "synth_row", window: int = 0, steps: int = 300, frames: int = 2, panoptic_steps: int = 150,
        repeats: int = 2, threads: int = 2, data_root: Path = Path("data"),
        out_dir: Path = Path("data/bench")) -> pd.DataFrame:
    torch.set_num_threads(threads)
    w, dets = window_rows(data_root, seq, window)
    full = load_window(w, data_root)
    res = fit_window(full, preset("cpu", steps=steps), render_val=False)
    model = res.model
    rows = []
    r = _render_modes(model, full.take(kept_frames(full.is_train, frames)), repeats)
    on = r["all skips"]
    for name, what in (("no occupancy skipping", "empty space (occupancy grid)"),
                       ("no early termination", "saturated rays (early termination)")):
        off = r[name]
        rows.append({"skip": what, "measure": "render s per image", "with_skip": on["s_per_image"],
                     "without_skip": off["s_per_image"], "samples_per_ray_with": on["samples_per_ray"],
                     "samples_per_ray_without": off["samples_per_ray"], "psnr_change_db": on["psnr"] - off["psnr"]})
    labels = load_labels(w, dets[dets.frame_id.isin(w.frame_id)], data_root)
    # the semantic-only phase keeps the defaults' share of steps (stuff_only_steps / steps)
    default = PanopticConfig()
    pcfg = PanopticConfig(steps=panoptic_steps,
                          stuff_only_steps=max(1, round(panoptic_steps * default.stuff_only_steps / default.steps)))
    bare = _without_things(labels)
    t_skip, t_full = [], []
    for _ in range(repeats):
        a = fit_panoptic(model, bare, full.is_train, full.depths, pcfg)
        b = fit_panoptic(model, bare, full.is_train, full.depths, replace(pcfg, stuff_only_steps=panoptic_steps))
        t_skip.append(a.fit_s)
        t_full.append(b.fit_s)
    rows.append({"skip": "window without thing detections (semantic-only phase)", "measure": "panoptic phase s",
                 "with_skip": median(t_skip), "without_skip": median(t_full)})
    # every other training frame without its fruit detections, so that frames without fruit occur
    half = WindowLabels(labels.semantic.copy(), labels.instance.copy(), labels.scores)
    drop = np.flatnonzero(full.is_train)[::2]
    half.semantic[drop], half.instance[drop] = bare.semantic[drop], bare.instance[drop]  # (stuff scores 1)
    ph = fit_panoptic(model, half, full.is_train, full.depths, pcfg)
    per_frame = ph.assign_s / max(ph.frames_assigned, 1)
    rows.append({"skip": "frames without fruit (no assignment)", "measure": "assignment s in the panoptic phase",
                 "with_skip": ph.assign_s, "without_skip": ph.assign_s + ph.frames_without_things * per_frame,
                 "frames_skipped": ph.frames_without_things, "frames_assigned": ph.frames_assigned})
    first, second = _manifest_rerun()
    rows.append({"skip": "unchanged stages (manifest)", "measure": "pag all s (tiny synthetic row)",
                 "with_skip": second, "without_skip": first})
    df = pd.DataFrame(rows)
    df["saving"] = 1 - df.with_skip / df.without_skip
    df["speedup"] = df.without_skip / df.with_skip
    df["seq"], df["window"], df["threads"] = seq, window, threads
    out_dir.mkdir(parents=True, exist_ok=True)
    write_parquet(df, out_dir / "skips.parquet")
    bar_plot([s.split(" (")[0][:22] for s in df.skip], list(df.speedup), "speedup from the skip (x)",
             f"work skipped, {seq} window {window}", out_dir / "skips.png")
    return df


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="pag bench skips", description=__doc__.split("\n")[0])
    p.add_argument("--seq", default="synth_row")
    p.add_argument("--window", type=int, default=0)
    p.add_argument("--steps", type=int, default=300, help="colour steps of the window fit")
    p.add_argument("--frames", type=int, default=2, help="validation frames rendered per mode")
    p.add_argument("--panoptic-steps", type=int, default=150)
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--data-root", type=Path, default=Path("data"))
    p.add_argument("--out", type=Path, default=Path("data/bench"))
    a = p.parse_args(argv)
    df = run(a.seq, a.window, a.steps, a.frames, a.panoptic_steps, a.repeats, a.threads, a.data_root, a.out)
    show = df[["skip", "measure", "with_skip", "without_skip", "speedup", "saving"]]
    print(show.to_string(index=False, float_format=lambda v: f"{v:.3g}"))
    return 0
