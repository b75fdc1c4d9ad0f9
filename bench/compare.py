"""Ours against baselines trained in the same harness, on the same window(s), scored against the synthetic
row's ground truth on the same validation frames (issue 6, item 2; the paper's Tables I-III, on CPU).

Methods (rows):
- detector input: the still-image detector's per-frame panoptic maps (what every NeRF learns from);
- Semantic-NeRF-like: MLP on a Fourier encoding (nerf/baselines.py), semantic head only, fixed poses;
  it has no instance output, so every fruit of one class in a frame is one segment (PQ counts the
  fruits as missed unless a frame holds only one fruit of that class);
- Panoptic-Lifting-like: our field, fixed poses, one shared grid for colour and panoptic, plain assignment;
- ours S / ours L: the paper's presets with the colour step count of this run (L is left out with --quick or
  --no-L: on 2 CPU cores it takes about as long as all the other rows together);
- ours cpu with four pose sources: odometry fixed, COLMAP (from colmap_poses.parquet when it covers the
  window, else COLMAP is run on the window here; skipped with the reason when it registers nothing usable),
  online refinement from the odometry (the paper's), and the pipeline's default: the odometry corrected
  with depth ICP, then refined online (S and L use that too).

Columns of `compare.parquet` (one row per method and window): method, poses (pose source), window, status
('ok' or 'skipped'), note, psnr (dB, mean over the scored validation frames), pq, sq, rq, pq_things,
pq_stuff, miou, id_consistency (share of fruits seen in >= 3 scored frames with one id throughout),
fruits_scored, count_pred / count_gt / count_error_rel (the window's fruit count on the scored frames:
distinct predicted fruit ids against distinct visible ground-truth fruits, bench.ablation.window_count; an
id that flickers counts a fruit twice, so the detector's per-frame ids overcount and the Semantic-NeRF-like
model, with no instance output, counts nothing), fit_min_per_window (colour + panoptic phase, minutes),
render_s_per_image (colour and panoptic in one pass, median seconds), params (colour field + panoptic part
that is used), colour_steps, panoptic_steps, rays_per_step, val_frames, threads, settings (the run's flags).
The row-level count of the whole pipeline (fusion of all windows, fruit_count's 3D rules) is `pag evaluate`'s
count_error_rel. Also `compare.md` (Markdown table, means over windows) and `compare.png`.

    pag bench compare [--seq synth_row] [--window 1 | --all-windows] [--quick] [--no-L | --with-L]
                      [--colour-steps N] [--panoptic-steps N] [--val-frames N]
"""
from __future__ import annotations

import argparse
import copy
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from bench._common import kept_frames, read, run_stage, write_parquet
from bench.ablation import ground_truth, score
from nerf.baselines import PANOPTIC_LIFTING_LIKE, SEMANTIC_ONLY
from nerf.config import NerfConfig, PanopticConfig, preset
from nerf.depth_poses import DepthPoses
from nerf.fit import fit_panoptic_window
from nerf.geometry import pose_matrix
from nerf.panoptic.labels import WindowLabels
from nerf.window import WindowData
from rowmap.window_data import initial_poses, load_labels, load_window

DEPTH_ICP = "depth ICP + online refinement"
"""the pipeline's default pose source: the odometry corrected with depth ICP (nerf/depth_poses.py, 'icp'),
then refined online."""
DEFAULT = dict(colour_steps=300, panoptic_steps=200, val_frames=5)
QUICK = dict(colour_steps=100, panoptic_steps=100, val_frames=3)


def scored_window(w: pd.DataFrame, dets: pd.DataFrame, gt_segments: pd.DataFrame, data_root: Path, n_val: int
                  ) -> tuple[WindowData, WindowLabels, pd.DataFrame, list]:
    """A window's frames, detector labels, rows and per-validation-frame ground truth, with every training
    frame and `n_val` validation frames spread evenly (0 = all): fewer renders."""
    data = load_window(w, data_root)
    keep = kept_frames(data.is_train, n_val or None)
    data, labels = data.take(keep), load_labels(w, dets, data_root).take(keep)
    wk = w.iloc[keep].reset_index(drop=True)
    return data, labels, wk, [ground_truth(wk.iloc[i], gt_segments, data_root) for i in np.flatnonzero(~data.is_train)]


def fit_and_score(data: WindowData, labels: WindowLabels, gts: list, ncfg: NerfConfig, pcfg: PanopticConfig,
                  depth_poses: DepthPoses = "off", render_scale: float = 1.0, icp_max_depth_m: float = 0.0) -> dict:
    """The window fitted as nerf_fit fits it (nerf/fit.py: depth poses, colour and panoptic phase, one render per
    validation frame at `render_scale` (1 = full size, 0 = nerf_fit's automatic working scale), instance
    completion), then scored; ground truth is taken to the renders' size by nearest pixel."""
    fit = fit_panoptic_window(data, labels, ncfg, pcfg, depth_poses=depth_poses, render_scale=render_scale,
                              icp_max_depth_m=icp_max_depth_m)
    res, pres = fit.colour, fit.panoptic
    preds = [(res.renders[int(i)]["semantic"], res.renders[int(i)]["instance"]) for i in np.flatnonzero(~data.is_train)]
    gts = [gt if gt[0].shape == p[0].shape else tuple(resize_nearest(a, p[0].shape) for a in gt)
           for gt, p in zip(gts, preds)]
    return {"psnr": float(np.mean(list(res.val_psnr.values()))), **score(preds, gts),
            "fit_min_per_window": (res.fit_s + pres.fit_s) / 60, "render_s_per_image": res.render_s_per_image,
            "params": res.params + pres.params, "colour_steps": ncfg.steps, "panoptic_steps": pcfg.steps,
            "rays_per_step": ncfg.rays_for(data.images.shape[1] * data.images.shape[2]),
            "samples_per_ray": float(np.mean([h["samples_per_ray"] for h in res.history]))}


def resize_nearest(a: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Label image `a` [H, W] at (h, w) = `shape`, each pixel taking the label at its centre (any dtype)."""
    rows = ((np.arange(shape[0]) + 0.5) * a.shape[0] / shape[0]).astype(int)
    cols = ((np.arange(shape[1]) + 0.5) * a.shape[1] / shape[1]).astype(int)
    return a[rows[:, None], cols[None, :]]


def methods(colour_steps: int, with_l: bool) -> list[tuple[str, str, dict, dict]]:
    """(method, pose source, NerfConfig preset + changes, PanopticConfig changes)."""
    out = [
        ("Semantic-NeRF-like", "odometry fixed", dict(preset="cpu", field_kind="mlp_pe", refine_poses=False),
         SEMANTIC_ONLY),
        ("Panoptic-Lifting-like", "odometry fixed", dict(preset="cpu", refine_poses=False), PANOPTIC_LIFTING_LIKE),
        ("ours S", DEPTH_ICP, dict(preset="S"), {}),
    ]
    if with_l:
        out.append(("ours L", DEPTH_ICP, dict(preset="L"), {}))
    out += [
        ("ours cpu", "odometry fixed", dict(preset="cpu", refine_poses=False), {}),
        ("ours cpu", "COLMAP", dict(preset="cpu", refine_poses=False), {}),
        ("ours cpu", "online refinement", dict(preset="cpu"), {}),
        ("ours cpu", DEPTH_ICP, dict(preset="cpu"), {}),
    ]
    return out


def colmap_window(seq: str, data_root: Path, windows: pd.DataFrame, kept: pd.DataFrame, wid: int
                  ) -> tuple[pd.DataFrame | None, str]:
    """The `kept` rows of window `wid` with COLMAP initial poses, or None and why not. Poses come from the
    sequence's colmap_poses table when it covers the window; otherwise the bench runs the colmap_poses stage
    (default settings) on that window alone, in a temporary data/ (about 7 s per window of 41 frames on 2 cores)."""
    try:
        colmap = read(data_root, seq, "colmap_poses")
    except FileNotFoundError:
        colmap = None
    note = ""
    if colmap is None or not (colmap.window_id == wid).any():
        out, _ = run_stage(seq, data_root, "colmap_poses", ["colmap_poses.enabled=true"],
                           tables={"windows": windows[windows.window_id == wid]})
        colmap = out["colmap_poses"]
        c = colmap[colmap.window_id == wid]
        note = f"COLMAP run by the bench: {int(c.registered.sum())} of {len(c)} frames take its poses"
    c = colmap[colmap.window_id == wid]
    if not (c["source"] == "colmap").any():
        return None, f"COLMAP registered no usable frame in window {wid}"
    try:
        return initial_poses(kept, wid, colmap, "colmap"), note
    except ValueError as err:
        return None, str(err)


def run(seq: str = "synth_row", windows_sel: list[int] | None = None, colour_steps: int = DEFAULT["colour_steps"],
        panoptic_steps: int = DEFAULT["panoptic_steps"], val_frames: int = DEFAULT["val_frames"], with_l: bool = False,
        threads: int = 2, settings: str = "", data_root: Path = Path("data"),
        out_dir: Path = Path("data/bench")) -> pd.DataFrame:
    torch.set_num_threads(threads)
    frames, windows = read(data_root, seq, "frames"), read(data_root, seq, "windows")
    dets, gt_segments = read(data_root, seq, "detections_filtered"), read(data_root, seq, "gt_segments")
    all_ids = sorted(int(i) for i in windows.window_id.unique())
    for wid in windows_sel or all_ids:
        if wid not in all_ids:
            raise ValueError(f"window {wid} not in {seq}; windows: {all_ids}")
    rows = []
    base_p = PanopticConfig(steps=panoptic_steps)
    for wid in windows_sel or all_ids:
        w = windows[windows.window_id == wid].merge(frames, on="frame_id")
        data, labels, wk, gts = scored_window(w, dets, gt_segments, data_root, val_frames)
        val = np.flatnonzero(~data.is_train)
        common = {"window": wid, "val_frames": len(val), "threads": threads, "settings": settings, "seq": seq}
        det = score([(labels.semantic[i], labels.instance[i]) for i in val], gts)
        rows.append({"method": "detector input", "poses": "-", "status": "ok", "note": "", **det, **common})
        print(f"window {wid}: detector PQ {det['pq']:.3f} mIoU {det['miou']:.3f}", flush=True)
        for name, poses, ncfg_kw, pcfg_kw in methods(colour_steps, with_l):
            kw = dict(ncfg_kw)
            ncfg = preset(kw.pop("preset"), **kw, steps=colour_steps, seed=wid)
            d = data
            if poses == "COLMAP":
                cw, why = colmap_window(seq, data_root, windows, wk, wid)
                if cw is None:
                    rows.append({"method": name, "poses": poses, "status": "skipped", "note": why, **common})
                    print(f"window {wid}: {name} / {poses}: skipped ({why})", flush=True)
                    continue
                d = copy.copy(data)
                d.poses_c2w = pose_matrix(cw[["tx", "ty", "tz", "qx", "qy", "qz", "qw"]].to_numpy(np.float64))
            # DEPTH_ICP: ICP on the kept frames (every training frame, a few validation ones)
            r = fit_and_score(d, labels, gts, ncfg, replace(base_p, **pcfg_kw), "icp" if poses == DEPTH_ICP else "off")
            rows.append({"method": name, "poses": poses, "status": "ok", "note": why if poses == "COLMAP" else "",
                         **r, **common})
            print(f"window {wid}: {name} / {poses}: PSNR {r['psnr']:.2f} PQ {r['pq']:.3f} mIoU {r['miou']:.3f} "
                  f"ID {r['id_consistency']:.2f} count {r['count_pred']:.0f}/{r['count_gt']:.0f} fit {r['fit_min_per_window']:.1f} min "
                  f"render {r['render_s_per_image']:.1f} s", flush=True)
    df = pd.DataFrame(rows)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_parquet(df, out_dir / "compare.parquet")
    (out_dir / "compare.md").write_text(markdown(df))
    plot(df, out_dir / "compare.png")
    return df


COLUMNS = [("psnr", "PSNR dB", "{:.2f}"), ("pq", "PQ %", "{:.1%}"), ("miou", "mIoU %", "{:.1%}"),
           ("id_consistency", "ID consistency", "{:.2f}"), ("count_error_rel", "count error %", "{:.1%}"),
           ("fit_min_per_window", "fit min/window", "{:.2f}"),
           ("render_s_per_image", "render s/image", "{:.2f}"), ("params", "parameters", "{:,.0f}")]


def summary(df: pd.DataFrame) -> pd.DataFrame:
    """Means over windows per (method, pose source), in the order of the rows."""
    keys = ["method", "poses"]
    order = df[keys].drop_duplicates()
    num = [c for c, _, _ in COLUMNS if c in df]
    agg = df[df.status == "ok"].groupby(keys, sort=False)[num].mean().reset_index()
    notes = df.groupby(keys, sort=False).agg(status=("status", "first"), note=("note", "first")).reset_index()
    return order.merge(agg, on=keys, how="left").merge(notes, on=keys, how="left")


def markdown(df: pd.DataFrame) -> str:
    s = summary(df)
    head = ["method", "poses"] + [h for _, h, _ in COLUMNS]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in s.itertuples(index=False):
        cells = [r.method, r.poses]
        for c, _, fmt in COLUMNS:
            v = getattr(r, c, float("nan"))
            cells.append(fmt.format(v) if isinstance(v, (int, float)) and np.isfinite(v) else "-")
        if r.status == "skipped":
            cells = [r.method, r.poses, f"skipped: {r.note}"] + [""] * (len(head) - 3)
        lines.append("| " + " | ".join(cells) + " |")
    ok = df[df.status == "ok"]
    first = df.iloc[0]
    foot = (f"\n{df.seq.iloc[0]}, window(s) {sorted(int(v) for v in df.window.unique())}, {int(first.val_frames)} validation frames per "
            f"window scored against ground truth; colour steps {int(ok.colour_steps.dropna().iloc[0]) if 'colour_steps' in ok else '-'}, "
            f"panoptic steps {int(ok.panoptic_steps.dropna().iloc[0]) if 'panoptic_steps' in ok else '-'} for every NeRF; "
            f"{int(first.threads)} CPU threads; settings: {first.settings or 'default'}. Count error: distinct predicted "
            "fruit ids vs distinct visible ground-truth fruits on the scored frames (the whole pipeline's row-level "
            "count is in `pag evaluate`).\n")
    return "\n".join(lines) + "\n" + foot


def plot(df: pd.DataFrame, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = summary(df)
    s = s[s.status == "ok"].reset_index(drop=True)
    labels = [f"{m}\n{p}" if p != "-" else m for m, p in zip(s.method, s.poses)]
    x = np.arange(len(s))
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(13, 4.2))
    for j, (m, name) in enumerate([("pq", "PQ"), ("miou", "mIoU"), ("id_consistency", "ID consistency")]):
        a1.bar(x + (j - 1) * 0.27, s[m].fillna(0) * 100, 0.27, label=name)
    a1.set_xticks(x, labels, fontsize=7, rotation=20)
    a1.set_ylabel("%")
    a1.legend(fontsize=8)
    a1.set_title("panoptic quality vs ground truth", fontsize=10)
    nerf = s[s.method != "detector input"].reset_index(drop=True)
    xx = np.arange(len(nerf))
    a2.bar(xx, nerf.psnr, color="#48c")
    for i, r in nerf.iterrows():
        a2.text(i, r.psnr, f"{r.fit_min_per_window:.1f} min\n{r.render_s_per_image:.1f} s/img", ha="center",
                va="bottom", fontsize=7)
    a2.set_xticks(xx, [f"{m}\n{p}" for m, p in zip(nerf.method, nerf.poses)], fontsize=7, rotation=20)
    a2.set_ylabel("val PSNR (dB)")
    a2.set_ylim(0, max(nerf.psnr.max() * 1.2, 1) if len(nerf) else 1)
    a2.set_title("PSNR (labels: fit minutes, render seconds per image)", fontsize=10)
    fig.suptitle(f"{df.seq.iloc[0]}: {df.settings.iloc[0] or 'default settings'}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="pag bench compare", description=__doc__.split("\n")[0])
    p.add_argument("--seq", default="synth_row")
    p.add_argument("--window", type=int, default=1)
    p.add_argument("--all-windows", action="store_true", help="every window of the sequence (slow)")
    p.add_argument("--quick", action="store_true",
                   help=f"fewer steps and frames: {QUICK} instead of {DEFAULT} (the other flags still override)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--with-L", dest="with_l", action="store_true", default=None,
                   help="the L preset row also in --quick mode")
    g.add_argument("--no-L", dest="with_l", action="store_false", help="leave out the L preset row (slow on CPU)")
    p.add_argument("--colour-steps", type=int, default=0, help="colour steps of every NeRF (0 = the mode's)")
    p.add_argument("--panoptic-steps", type=int, default=0, help="panoptic steps (0 = the mode's)")
    p.add_argument("--val-frames", type=int, default=-1, help="validation frames scored per window (0 = all)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--data-root", type=Path, default=Path("data"))
    p.add_argument("--out", type=Path, default=Path("data/bench"))
    a = p.parse_args(argv)
    mode = dict(QUICK if a.quick else DEFAULT)
    with_l = (not a.quick) if a.with_l is None else a.with_l
    if a.colour_steps:
        mode["colour_steps"] = a.colour_steps
    if a.panoptic_steps:
        mode["panoptic_steps"] = a.panoptic_steps
    if a.val_frames >= 0:
        mode["val_frames"] = a.val_frames
    settings = (f"{'quick' if a.quick else 'default'}: colour_steps={mode['colour_steps']} "
                f"panoptic_steps={mode['panoptic_steps']} val_frames={mode['val_frames'] or 'all'}"
                f"{' with L' if with_l else ' without L'}")
    print(f"pag bench compare, {settings}", flush=True)
    df = run(a.seq, None if a.all_windows else [a.window], mode["colour_steps"], mode["panoptic_steps"],
             mode["val_frames"], with_l, a.threads, settings, a.data_root, a.out)
    print(markdown(df))
    print(f"wrote {a.out / 'compare.parquet'}, compare.md, compare.png")
    return 0
