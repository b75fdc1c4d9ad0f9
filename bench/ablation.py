"""Panoptic ablation on one window: with and without the ID window (repeated-ID rejection), delta grid
vs one shared grid vs two independent grids, and without the slot memory (alone, and together with the
ID window: plain assignment on the predicted probabilities). The colour phase is fitted once; every
variant trains its panoptic phase on its own copy of it, in one process, with the same seed, and is
scored on every validation frame against the sequence's ground truth (the detector input scored on
the same frames for reference).

Output `ablation.parquet`, one row per variant: variant, grid_mode, id_window, memory_prior, val_psnr (dB), pq, sq,
rq, pq_things, pq_stuff, miou, id_consistency, fruits_scored, pq_detector, miou_detector,
params (colour + panoptic), panoptic_params, colour_fit_s, panoptic_fit_s, fit_s (colour + panoptic),
render_s_per_image; and `ablation.png` (PQ, mIoU and ID consistency per variant).

    pag bench ablation [--seq synth_row] [--window 1] [--colour-steps 0 (preset)] [--panoptic-steps 0 (default)]
"""
from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from bench._common import read, stage_defaults, window_rows, write_parquet
from nerf.config import PanopticConfig, preset
from nerf.fit import fit_colour, fit_panoptic_window
from pipeline.classes import VOID
from pipeline.images import read_label
from rowmap.scoring import PanopticScore, thing_instances
from rowmap.window_data import load_labels, load_window

VARIANTS: dict[str, dict] = {
    "delta + ID window (ours)": dict(grid_mode="delta", id_window=True),
    "delta, no ID window": dict(grid_mode="delta", id_window=False),
    "shared grid + ID window": dict(grid_mode="shared", id_window=True),
    "independent grids + ID window": dict(grid_mode="independent", id_window=True),
    "delta + ID window, no slot memory": dict(grid_mode="delta", id_window=True, memory_prior=0.0),
    "delta, plain assignment (no ID window, no slot memory)": dict(grid_mode="delta", id_window=False, memory_prior=0.0),
}


def ground_truth(row: pd.Series, gt_segments: pd.DataFrame, data_root: Path) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth semantic/instance of a frame; segments the depth filter dropped (the far row) are void,
    as the detector's are for training."""
    if not isinstance(row.gt_semantic_path, str):
        raise ValueError(f"frame {row.frame_id} has no ground truth; the ablation needs a synthetic row")
    sem = read_label(data_root / row.gt_semantic_path, "ground-truth semantic")
    inst = read_label(data_root / row.gt_instance_path, "ground-truth instance")
    dropped = gt_segments.loc[(gt_segments.frame_id == row.frame_id) & ~gt_segments.kept, "instance_id"].to_numpy()
    off = (inst > 0) & np.isin(inst, dropped)
    return np.where(off, VOID, sem), np.where(off, 0, inst)


def visible_ids(sem: np.ndarray, inst: np.ndarray, min_px: int) -> set[int]:
    """Thing instance ids covering at least `min_px` pixels of a frame."""
    ids, n = np.unique(thing_instances(sem, inst), return_counts=True)
    return {int(i) for i, c in zip(ids, n) if i > 0 and c >= min_px}


def window_count(preds: list[tuple[np.ndarray, np.ndarray]], gts: list[tuple[np.ndarray, np.ndarray]],
                 min_px: int) -> dict[str, float]:
    """Fruits counted on a window's scored frames: distinct predicted fruit ids (each >= `min_px` pixels in
    at least one frame) against the distinct ground-truth fruits visible (>= `min_px`) in the same frames.
    A fruit whose id changes between frames is counted twice, merged fruits once; per-frame ids (the
    detector input) count every view of a fruit as a new fruit. Example: ids {3} in frame 1 and {3, 7} in
    frame 2 on ground truth {1} and {1, 2} -> count_pred 2, count_gt 2, count_error_rel 0."""
    pred, gt = set(), set()
    for (p_sem, p_inst), (g_sem, g_inst) in zip(preds, gts):
        pred |= visible_ids(p_sem, p_inst, min_px)
        gt |= visible_ids(g_sem, g_inst, min_px)
    err = abs(len(pred) - len(gt)) / len(gt) if gt else float("nan")
    return {"count_pred": float(len(pred)), "count_gt": float(len(gt)), "count_error_rel": err}


def score(preds: list[tuple[np.ndarray, np.ndarray]], gts: list[tuple[np.ndarray, np.ndarray]]) -> dict[str, float]:
    """PQ, mIoU, ID consistency and the window's fruit count error (window_count) of a window's rendered
    frames, scored as the evaluate stage does."""
    ev = stage_defaults("evaluate")
    min_px = ev.min_visible_px
    ps = PanopticScore(min_px)
    for (p_sem, p_inst), (g_sem, g_inst) in zip(preds, gts):
        ps.update(p_sem, p_inst, g_sem, g_inst, np.unique(g_inst[g_inst > 0]))
    m = ps.metrics(ev.min_frames_id)
    return {k: m[k] for k in ("pq", "sq", "rq", "pq_things", "pq_stuff", "miou", "id_consistency")} | {
        "fruits_scored": int(m["id_consistency_n_fruits"])} | window_count(preds, gts, min_px)


def run(seq: str = "synth_row", window: int = 1, colour_steps: int = 0, panoptic_steps: int = 0, threads: int = 2,
        data_root: Path = Path("data"), out_dir: Path = Path("data/bench")) -> pd.DataFrame:
    torch.set_num_threads(threads)
    w, dets = window_rows(data_root, seq, window)
    gt_segments = read(data_root, seq, "gt_segments")
    data = load_window(w, data_root)
    labels = load_labels(w, dets, data_root)
    val = np.flatnonzero(~data.is_train)
    gts = [ground_truth(w.iloc[i], gt_segments, data_root) for i in val]
    det = score([(labels.semantic[i], labels.instance[i]) for i in val], gts)
    cfg = preset("cpu", **({"steps": colour_steps} if colour_steps else {}))
    t0 = time.perf_counter()
    colour = fit_colour(data, cfg)  # the variants share one colour fit; each trains its panoptic phase on a copy
    colour_s = time.perf_counter() - t0
    base = PanopticConfig(**({"steps": panoptic_steps} if panoptic_steps else {}))
    rows = []
    for name, change in VARIANTS.items():
        fit = fit_panoptic_window(data, labels, cfg, replace(base, **change), colour=colour,
                                  name=f"{seq} window {window}")
        res, pres = fit.colour, fit.panoptic
        preds = [(res.renders[int(i)]["semantic"], res.renders[int(i)]["instance"]) for i in val]
        rows.append({"variant": name, "memory_prior": base.memory_prior, **change,
                     "val_psnr": float(np.mean(list(res.val_psnr.values()))), **score(preds, gts),
                     "pq_detector": det["pq"], "miou_detector": det["miou"],
                     "params": res.params + pres.params, "panoptic_params": pres.params,
                     "colour_fit_s": colour_s, "panoptic_fit_s": pres.fit_s, "fit_s": colour_s + pres.fit_s,
                     "render_s_per_image": res.render_s_per_image, "seq": seq, "window": window})
        print(f"{name}: PQ {rows[-1]['pq']:.3f} mIoU {rows[-1]['miou']:.3f} ID {rows[-1]['id_consistency']:.3f}",
              flush=True)
    df = pd.DataFrame(rows)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_parquet(df, out_dir / "ablation.parquet")
    plot(df, out_dir / "ablation.png")
    return df


def plot(df: pd.DataFrame, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    metrics = ["pq", "miou", "id_consistency"]
    x = np.arange(len(df))
    fig, ax = plt.subplots(figsize=(9, 4))
    for j, m in enumerate(metrics):
        ax.bar(x + (j - 1) * 0.27, df[m] * 100, 0.27, label=m)
    ax.axhline(df.pq_detector.iloc[0] * 100, color="k", ls="--", lw=1, label="detector PQ")
    ax.set_xticks(x, df.variant, rotation=12, fontsize=8)
    ax.set_ylabel("%")
    ax.set_title(f"panoptic ablation, {df.seq.iloc[0]} window {df.window.iloc[0]}")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="pag bench ablation", description=__doc__.split("\n")[0])
    p.add_argument("--seq", default="synth_row")
    p.add_argument("--window", type=int, default=1)
    p.add_argument("--colour-steps", type=int, default=0, help="colour steps (0 = the cpu preset's)")
    p.add_argument("--panoptic-steps", type=int, default=0, help="panoptic steps (0 = the default)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--data-root", type=Path, default=Path("data"))
    p.add_argument("--out", type=Path, default=Path("data/bench"))
    a = p.parse_args(argv)
    df = run(a.seq, a.window, a.colour_steps, a.panoptic_steps, a.threads, a.data_root, a.out)
    cols = ["variant", "val_psnr", "pq", "miou", "id_consistency", "pq_detector", "miou_detector", "params", "fit_s"]
    print(df[cols].to_string(index=False, float_format=lambda v: f"{v:.3f}"))
    return 0
