"""The pose refinement's shift penalty on one window: refined poses against the reference poses, per weight.

    pag bench pose_prior [--seq sun3d_office] [--data-root data/bench/real_rgbd] [--window 0]
                         [--penalties 0,1,10] [--depth-poses STAGE|icp|scale|off] [--seed 0] [--threads 2]

Fits the window's colour phase (nerf/fit.py `fit_colour`, nerf_fit's model settings and ICP correction)
once per `pose_shift_penalty` weight, and once with pose refinement off, all with the same seed, and scores
the final camera positions against the row's gt/poses.parquet (matched by stamp) as `evaluate` does (ATE
after a rigid alignment), on all of the window's frames and on its training and validation frames apart.
The sequence must have been ingested and windowed (`pag windows --seq SEQ`; `pag bench real_rgbd` does it
for the shared office row). `--depth-poses off` starts from the odometry, so the colour refinement alone
must correct its drift: the case where a penalty could hold back a correction the images ask for.

Output `pose_prior.parquet`, one row per variant: variant, pose_shift_penalty, shift_weight (the weight per m^2
the fit gave it: the penalty over the window's parallax spread squared), refine_poses, ate_m,
ate_train_m, ate_val_m, ate_initial_m (the poses the fit started from), ate_odometry_m, shift_train_mm and
shift_val_mm (mean distance the refinement moved the cameras), train_psnr (dB, last steps), fit_s, seed.
"""
from __future__ import annotations

import argparse
import sys
import time
import typing
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from bench._common import window_rows, write_parquet
from nerf.fit import fit_colour
from nerf.depth_poses import DepthPoses
from nerf.metrics import ate_rmse
from rowmap.ground_truth import gt_poses_by_frame
from rowmap.window_data import load_window

POSITION = ["tx", "ty", "tz"]


def reference_positions(data_root: Path, seq: str, frames: pd.DataFrame) -> np.ndarray:
    """[N, 3] camera positions of gt/poses.parquet for `frames` (frame_id, stamp_ns), matched by stamp as
    evaluate matches them (rowmap/ground_truth.py gt_poses_by_frame); an error naming frames without one."""
    path = Path(data_root) / "raw" / seq / "gt" / "poses.parquet"
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found: the bench scores poses against a row's reference poses")
    gt = gt_poses_by_frame(pd.read_parquet(path), frames).set_index("frame_id")
    missing = frames.loc[~frames.frame_id.isin(gt.index), "stamp_ns"].tolist()
    if missing:
        raise ValueError(f"{path} has no pose at {len(missing)} frame stamps, e.g. {missing[:3]}")
    return gt.loc[frames.frame_id, POSITION].to_numpy(np.float64)


def run(seq: str, data_root: Path, window: int = 0, penalties: tuple[float, ...] = (0.0, 1.0, 10.0),
        depth_poses: str = "stage", threads: int = 2, model: dict | None = None, seed: int = 0) -> pd.DataFrame:
    """Fit window `window` of `seq` (ingested and windowed under data_root) once per penalty and once without
    refinement, all with nerf_fit's seed for the window plus `seed`; one table row per fit. `model`: further
    NerfConfig settings over nerf_fit's (tests shorten the fit with it)."""
    from pipeline import dag

    torch.set_num_threads(threads)
    stage = dag.load_stage("nerf_fit").module           # through the DAG: the stage's own settings, no stage import
    scfg = stage.Config()
    base = replace(stage.model_config(scfg), seed=scfg.seed + window + seed, **(model or {}))
    how = scfg.depth_poses if depth_poses == "stage" else depth_poses
    w, _ = window_rows(data_root, seq, window)
    data = load_window(w, data_root)
    ref = reference_positions(data_root, seq, w[["frame_id", "stamp_ns"]])
    odo = w[POSITION].to_numpy(np.float64)
    train = data.is_train
    variants = [(f"shift penalty {p:g}", replace(base, pose_shift_penalty=p)) for p in penalties]
    variants.append(("no pose refinement", replace(base, refine_poses=False)))
    rows = []
    for name, cfg in variants:
        t0 = time.perf_counter()
        colour = fit_colour(data, cfg, how, icp_max_depth_m=scfg.icp_max_depth_m, name=f"window {window}")
        fitted, start = colour.result.poses_c2w[:, :3, 3], colour.data.poses_c2w[:, :3, 3]
        shift = 1e3 * np.linalg.norm(fitted - start, axis=1)
        rows.append({"variant": name, "pose_shift_penalty": cfg.pose_shift_penalty,
                     "shift_weight": colour.result.shift_weight, "refine_poses": cfg.refine_poses,
                     "ate_m": ate_rmse(fitted, ref), "ate_train_m": ate_rmse(fitted[train], ref[train]),
                     "ate_val_m": ate_rmse(fitted[~train], ref[~train]), "ate_initial_m": ate_rmse(start, ref),
                     "ate_odometry_m": ate_rmse(odo, ref), "shift_train_mm": float(shift[train].mean()),
                     "shift_val_mm": float(shift[~train].mean()) if (~train).any() else float("nan"),
                     "train_psnr": colour.result.train_psnr, "fit_s": time.perf_counter() - t0,
                     "seq": seq, "window": window, "depth_poses": how, "seed": cfg.seed})
        r = rows[-1]
        print(f"{name} (weight {r['shift_weight']:.3g} per m^2): ATE {1e3 * r['ate_m']:.2f} mm (train "
              f"{1e3 * r['ate_train_m']:.2f}, val {1e3 * r['ate_val_m']:.2f}; odometry {1e3 * r['ate_odometry_m']:.2f}), moved {r['shift_train_mm']:.1f}"
              f" / {r['shift_val_mm']:.1f} mm, train PSNR {r['train_psnr']:.2f} dB, {r['fit_s']:.0f} s", flush=True)
    return pd.DataFrame(rows)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="pag bench pose_prior", description=__doc__.split("\n")[0])
    p.add_argument("--seq", default="sun3d_office")
    p.add_argument("--data-root", type=Path, default=Path("data/bench/real_rgbd"))
    p.add_argument("--window", type=int, default=0)
    p.add_argument("--penalties", default="0,1,10",
                   help="comma-separated pose_shift_penalty weights (per m^2 at a parallax spread of 1/m)")
    p.add_argument("--depth-poses", default="stage", choices=["stage", *typing.get_args(DepthPoses)],
                   help="initial pose correction (stage = nerf_fit's default)")
    p.add_argument("--seed", type=int, default=0, help="added to the fits' seed (nerf_fit's seed + window)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--out", type=Path, default=Path("data/bench"))
    a = p.parse_args(argv)
    penalties = tuple(float(x) for x in a.penalties.split(",") if x.strip())
    df = run(a.seq, a.data_root, a.window, penalties, a.depth_poses, a.threads, seed=a.seed)
    how = "" if a.depth_poses == "stage" else f"_{a.depth_poses}"
    name = f"pose_prior{how}{f'_seed{a.seed}' if a.seed else ''}.parquet"
    write_parquet(df, a.out / name)
    print(f"wrote {a.out / name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
