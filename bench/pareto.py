"""Cost against quality over the model knobs (issue 6, item 3): each point fits one window of the row (colour
phase with online poses, then the panoptic phase) with one setting of levels, log2 table capacity, colour
steps and rays per step, and is scored on the same validation frames against ground truth. The Pareto
fronts (least fit time for the quality) of fit time vs PSNR and fit time vs PQ are plotted, with the
presets (their knobs, at this run's step count where the preset's own is longer) marked. Samples per ray
move with the marching step (`step_factor` x the preset's cone_angle); image scale (`image_scale`) fits,
renders and scores the window at a lower resolution (colour by area averaging, depth, labels and the
ground truth by nearest pixel, intrinsics scaled), so its PSNR and PQ are those of the smaller images.

Output `pareto.parquet`, one row per point: point, preset ('cpu', 'S', 'L' or '' for other settings),
n_levels, log2_capacity, image_scale, cone_angle, samples_per_ray (training), colour_steps, rays_per_step, panoptic_steps, params, fit_min_per_window
(colour + panoptic, minutes), render_s_per_image (median, colour + panoptic in one pass), psnr (dB), pq,
miou, id_consistency, count_pred / count_gt / count_error_rel (the window's fruit count on the scored frames,
bench.ablation.window_count), front_psnr / front_pq (on the front of fit time vs that metric), val_frames,
settings; and `pareto.png`.

`--stage` fits every point as the nerf_fit stage does (its model settings and step counts, depth-ICP initial
poses, renders at its working scale, scored there against the ground truth taken to that size) with every
validation frame, and its points (STAGE_POINTS) are variants of those settings: fewer steps, a longer
marching step, earlier termination, other learning rates (grid / decoders) and a smaller table. It writes
`pareto_stage.parquet` and `pareto_stage.png`: at 1280x720 (`--seq synth_bup20 --window 0`) this is the scale
bench the step budget is chosen on.

`--fronts LABEL=PARQUET ...` fits nothing: it puts the points of earlier runs (the same window, e.g. the old and
the new code) in one figure, each run with its front of whole minutes per window (fits plus validation renders)
against PSNR and against PQ, into `pareto_fronts.parquet` and `pareto_fronts.png`.

    pag bench pareto [--seq synth_row] [--window 1] [--quick | --long | --stage] [--val-frames N]
    pag bench pareto --fronts old=OLD/pareto_stage.parquet new=NEW/pareto_stage.parquet [--out DIR]
"""
from __future__ import annotations

import argparse
from dataclasses import replace
from itertools import cycle
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import torch

from bench._common import read, window_rows, write_parquet
from bench.compare import fit_and_score, scored_window
from nerf.config import PanopticConfig, preset
from nerf.panoptic.labels import WindowLabels
from nerf.window import WindowData

# (name, preset the point starts from, changes); steps are scaled by the run mode
POINTS: list[tuple[str, str, dict]] = [
    ("cpu preset", "cpu", {}),
    ("S preset", "S", {}),
    ("6 levels, 2^14", "cpu", dict(n_levels=6, log2_capacity=14)),
    ("cpu, half steps", "cpu", dict(steps_factor=0.5)),
    ("cpu, 512 rays", "cpu", dict(rays_per_step=512)),
    ("14 levels, 2^17", "cpu", dict(n_levels=14, log2_capacity=17)),
    ("cpu, double steps", "cpu", dict(steps_factor=2.0)),
    ("cpu, 2x marching step", "cpu", dict(step_factor=2.0)),
    ("cpu, half image scale", "cpu", dict(image_scale=0.5)),
]
LONG_POINTS = POINTS + [
    ("16 levels, 2^18, 2048 rays", "cpu", dict(n_levels=16, log2_capacity=18, rays_per_step=2048)),
    ("L preset", "L", {}),
]
STAGE_POINTS = [
    ("nerf_fit settings", "", {}),
    ("2/3 of the steps", "", dict(steps_factor=2 / 3)),
    ("1/2 of the steps", "", dict(steps_factor=0.5)),
    ("1.5x marching step", "", dict(step_factor=1.5)),
    ("early stop at T < 1e-2", "", dict(train_early_stop=0.01)),
    ("decoders' rate 2e-2", "", dict(lr_mlp=2e-2)),
    ("rates 3e-2 / 2e-2", "", dict(lr_grid=3e-2, lr_mlp=2e-2)),
    ("2^18 table, rates 3e-2 / 2e-2", "", dict(log2_capacity=18, lr_grid=3e-2, lr_mlp=2e-2)),
    ("decoders 64 wide", "", dict(hidden=64)),
]
"""--stage: nerf_fit's own settings (model, steps, ICP poses, working-scale renders) and cheaper variants."""
MODES = {"quick": dict(colour_steps=100, panoptic_steps=80, val_frames=3),
         "default": dict(colour_steps=200, panoptic_steps=150, val_frames=3),
         "long": dict(colour_steps=600, panoptic_steps=400, val_frames=6),
         "stage": dict(colour_steps=0, panoptic_steps=0, val_frames=0)}


def downscale(data: WindowData, labels: WindowLabels, gts: list, scale: float
              ) -> tuple[WindowData, WindowLabels, list]:
    """The window, its detector labels and ground truth at `scale` x the resolution (1 = unchanged)."""
    if scale == 1.0:
        return data, labels, gts
    n, h, w = data.images.shape[:3]
    size = (max(1, int(round(w * scale))), max(1, int(round(h * scale))))
    sx, sy = size[0] / w, size[1] / h
    near = lambda a: cv2.resize(a, size, interpolation=cv2.INTER_NEAREST)  # noqa: E731
    k = data.intrinsics * np.array([sx, sy, sx, sy])
    small = WindowData(np.stack([cv2.resize(im, size, interpolation=cv2.INTER_AREA) for im in data.images]),
                       np.stack([near(d) for d in data.depths]), k, data.poses_c2w, data.is_train, data.frame_ids)
    lab = WindowLabels(np.stack([near(a) for a in labels.semantic]),
                       np.stack([near(a) for a in labels.instance]), labels.scores)
    return small, lab, [(near(gs), near(gi)) for gs, gi in gts]


def with_fronts(df: pd.DataFrame, cost: str) -> pd.DataFrame:
    """df with front_psnr / front_pq: whether each point is on the front of column `cost` against PSNR / PQ."""
    return df.assign(front_psnr=pareto_front(df[cost].to_numpy(), df.psnr.to_numpy()),
                     front_pq=pareto_front(df[cost].to_numpy(), df.pq.to_numpy()))


def pareto_front(cost: np.ndarray, quality: np.ndarray) -> np.ndarray:
    """Points no other point dominates (cost <= and quality >=, one of them strictly). NaN quality is never
    on the front. Example: cost (1, 2, 3), quality (10, 9, 12) -> (True, False, True)."""
    ok = np.isfinite(quality)
    front = np.zeros(len(cost), bool)
    for i in np.flatnonzero(ok):
        dom = ok & (cost <= cost[i]) & (quality >= quality[i]) & ((cost < cost[i]) | (quality > quality[i]))
        front[i] = not dom.any()
    return front


def run(seq: str = "synth_row", window: int = 1, mode: str = "default", val_frames: int = -1, threads: int = 2,
        data_root: Path = Path("data"), out_dir: Path = Path("data/bench")) -> pd.DataFrame:
    """Fit and score every point of `mode` on the window. Mode 'stage' fits as the nerf_fit stage does (its
    model settings and steps, ICP-corrected poses, renders at its working scale) and scores at that scale."""
    torch.set_num_threads(threads)
    m = dict(MODES[mode])
    if val_frames >= 0:
        m["val_frames"] = val_frames
    fit_kw, points = {}, LONG_POINTS if mode == "long" else POINTS
    if mode == "stage":
        from pipeline import dag

        stage = dag.load_stage("nerf_fit").module     # through the DAG, as stage_defaults does: no stage import
        scfg = stage.Config()
        base_n, pcfg, points = stage.model_config(scfg), scfg.panoptic, STAGE_POINTS
        m.update(colour_steps=base_n.steps, panoptic_steps=pcfg.steps)
        fit_kw = dict(depth_poses=scfg.depth_poses, render_scale=scfg.render_scale,
                      icp_max_depth_m=scfg.icp_max_depth_m)
    else:
        pcfg = PanopticConfig(steps=m["panoptic_steps"])
    settings = f"{mode}: base colour_steps={m['colour_steps']} panoptic_steps={m['panoptic_steps']} val_frames={m['val_frames']}"
    print(f"pag bench pareto, {settings}", flush=True)
    w, dets = window_rows(data_root, seq, window)
    gt_segments = read(data_root, seq, "gt_segments")
    data, labels, _, gts = scored_window(w, dets, gt_segments, data_root, m["val_frames"])
    rows = []
    for name, pre, change in points:
        change = dict(change)
        steps = max(1, int(round(m["colour_steps"] * change.pop("steps_factor", 1.0))))
        scale = change.pop("image_scale", 1.0)
        step_factor = change.pop("step_factor", 1.0)
        ncfg = replace(base_n, steps=steps, seed=window, **change) if mode == "stage" else \
            preset(pre, steps=steps, seed=window, **change)
        ncfg = replace(ncfg, cone_angle=ncfg.cone_angle * step_factor)
        r = fit_and_score(*downscale(data, labels, gts, scale), ncfg, pcfg, **fit_kw)
        rows.append({"point": name, "preset": pre if not change and name.endswith("preset") else "",
                     "n_levels": ncfg.n_levels, "log2_capacity": ncfg.log2_capacity, "image_scale": scale,
                     "cone_angle": ncfg.cone_angle, **r,
                     "val_frames": int((~data.is_train).sum()), "settings": settings, "seq": seq, "window": window})
        print(f"{name}: fit {r['fit_min_per_window']:.2f} min, render {r['render_s_per_image']:.1f} s, "
              f"PSNR {r['psnr']:.2f}, PQ {r['pq']:.3f}, count {r['count_pred']:.0f}/{r['count_gt']:.0f}", flush=True)
    df = with_fronts(pd.DataFrame(rows), "fit_min_per_window")
    out_dir.mkdir(parents=True, exist_ok=True)
    name = "pareto_stage" if mode == "stage" else "pareto"
    write_parquet(df, out_dir / f"{name}.parquet")
    plot(df, out_dir / f"{name}.png")
    return df


def metric_figure(path: Path, title: str, xlabel: str, draw) -> None:
    """One panel for val PSNR and one for PQ, each filled by draw(ax, metric), saved to `path`."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    for ax, metric, label in ((axes[0], "psnr", "val PSNR (dB)"), (axes[1], "pq", "PQ")):
        draw(ax, metric)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(label)
        ax.legend(fontsize=7, loc="lower right")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot(df: pd.DataFrame, path: Path) -> None:
    def draw(ax, metric: str) -> None:
        front = df[df[f"front_{metric}"]].sort_values("fit_min_per_window")
        ax.plot(front.fit_min_per_window, front[metric], "-", color="#c44", lw=1.5, label="Pareto front", zorder=1)
        ax.scatter(df.fit_min_per_window, df[metric], c="#48c", s=30, zorder=2, label="points")
        pre = df[df.preset != ""]
        ax.scatter(pre.fit_min_per_window, pre[metric], marker="*", s=220, c="#fa0", edgecolors="k", zorder=3,
                   label="presets")
        for r in df.itertuples(index=False):
            ax.annotate(f"{r.point}\n{r.render_s_per_image:.1f} s/img", (r.fit_min_per_window, getattr(r, metric)),
                        fontsize=6.5, xytext=(4, 3), textcoords="offset points")

    metric_figure(path, f"{df.seq.iloc[0]} window {df.window.iloc[0]}, {df.settings.iloc[0]}",
                  "fit time per window (min, colour + panoptic)", draw)


def window_minutes(df: pd.DataFrame) -> np.ndarray:
    """A point's whole cost per window (minutes): colour and panoptic fits plus its validation renders."""
    return (df.fit_min_per_window + df.render_s_per_image * df.val_frames / 60.0).to_numpy(np.float64)


def fronts(runs: dict[str, pd.DataFrame]) -> pd.DataFrame:
    """The points of several runs of the bench (label -> its parquet), each with its whole window minutes
    (window_minutes) and whether it is on its own run's front of those minutes against PSNR and against PQ."""
    return pd.concat([with_fronts(df.assign(code=label, window_min=window_minutes(df)), "window_min")
                      for label, df in runs.items()], ignore_index=True)


def plot_fronts(df: pd.DataFrame, path: Path) -> None:
    """Each run's points and Pareto front (fronts()) in one figure per metric: where a front moved."""
    def draw(ax, metric: str) -> None:
        for colour, (code, run_df) in zip(cycle(["#999", "#c44", "#48c", "#4a4"]), df.groupby("code", sort=False)):
            front = run_df[run_df[f"front_{metric}"]].sort_values("window_min")
            ax.plot(front.window_min, front[metric], "-", color=colour, lw=1.5, label=f"{code}: front")
            ax.scatter(run_df.window_min, run_df[metric], c=colour, s=28)
            for r in run_df.itertuples(index=False):
                ax.annotate(r.point, (r.window_min, getattr(r, metric)), fontsize=6, color=colour, xytext=(4, 3),
                            textcoords="offset points")

    metric_figure(path, f"{df.seq.iloc[0]} window {df.window.iloc[0]}: Pareto fronts",
                  "minutes per window (colour + panoptic fit + validation renders)", draw)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="pag bench pareto", description=__doc__.split("\n")[0])
    p.add_argument("--seq", default="synth_row")
    p.add_argument("--window", type=int, default=1)
    g = p.add_mutually_exclusive_group()
    g.add_argument("--quick", action="store_true", help=f"fewer steps: {MODES['quick']}")
    g.add_argument("--long", action="store_true", help=f"more steps and points (incl. L): {MODES['long']}")
    g.add_argument("--stage", action="store_true", help="nerf_fit's own settings and steps, ICP poses and "
                   "working-scale renders, every validation frame; points: cheaper variants of them")
    p.add_argument("--val-frames", type=int, default=-1, help="validation frames scored (-1 = the mode's, 0 = all)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--data-root", type=Path, default=Path("data"))
    p.add_argument("--out", type=Path, default=Path("data/bench"))
    p.add_argument("--fronts", nargs="+", default=[], metavar="LABEL=PARQUET",
                   help="no fits: plot the fronts of earlier runs (e.g. old=old/pareto_stage.parquet) together")
    a = p.parse_args(argv)
    if a.fronts:
        runs = {}
        for item in a.fronts:
            label, sep, path = item.partition("=")
            if not sep or not label:
                p.error(f"--fronts takes LABEL=PARQUET, got {item!r}")
            if not Path(path).is_file():
                p.error(f"--fronts {label}: no file {path} (a pareto or pareto_stage parquet of an earlier run)")
            runs[label] = pd.read_parquet(path)
        df = fronts(runs)
        a.out.mkdir(parents=True, exist_ok=True)
        write_parquet(df, a.out / "pareto_fronts.parquet")
        plot_fronts(df, a.out / "pareto_fronts.png")
        cols = ["code", "point", "window_min", "fit_min_per_window", "render_s_per_image", "psnr", "pq",
                "count_pred", "count_gt", "front_psnr", "front_pq"]
        print(df[cols].to_string(index=False, float_format=lambda v: f"{v:.3f}"))
        return 0
    mode = "quick" if a.quick else "long" if a.long else "stage" if a.stage else "default"
    df = run(a.seq, a.window, mode, a.val_frames, a.threads, a.data_root, a.out)
    cols = ["point", "n_levels", "log2_capacity", "colour_steps", "rays_per_step", "image_scale", "cone_angle",
            "samples_per_ray", "params", "fit_min_per_window",
            "render_s_per_image", "psnr", "pq", "miou", "count_error_rel", "front_psnr", "front_pq"]
    print(df[cols].to_string(index=False, float_format=lambda v: f"{v:.3f}"))
    return 0
