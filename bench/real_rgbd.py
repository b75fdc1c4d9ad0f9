"""A real RGB-D recording end to end: the model's quality and the poses on images our generator did not make.

    pag bench real_rgbd [--row ../shared/real/sun3d_office] [--frames N] [--set KEY=VALUE ...] [--force]
                        [--data-root data/bench/real_rgbd] [--out data/bench]

The row is a recorded folder in the BUP20-style layout (data/README.md) with `gt/poses.parquet` (the
reference camera poses, e.g. a reconstruction's). It is linked into `<data-root>/raw/<name>` (or, with
--frames N, its first N frames are copied there as an excerpt) and every stage runs through the normal
runner with the defaults, except that the validation frames are rendered at full size
(nerf_fit.render_scale=1) so the PSNR is the full-size one. Reports:
- val PSNR at full size (mean over windows);
- ATE of the odometry and of the refined poses against gt/poses.parquet (rigid alignment), and their ratio;
- ICP's share of the correction: consecutive-frame links ICP set / all links, and the depth limits used
  (window_metrics icp_max_depth_m, far_m);
- how well each set of poses agrees with the depth sensor, an independent referee where the reference poses
  are themselves uncertain: nerf/depth_poses.py depth_disagreement (mean point-to-plane distance between
  frames 4 apart, mm) for the odometry, the refined and the reference poses;
- the fruit count (0 on a scene without fruit);
- time per stage.
A reconstruction is itself only good to about a centimetre (sun3d_office: 1-2 cm), so ATE differences below
that say little.

Writes <out>/real_rgbd.parquet: one row per stage (stage, seconds, peak_rss_mb) with the row's figures
repeated on every line.
"""
from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from bench._common import write_parquet
from bench._pipeline import quality
from pipeline.catalog import dataset
from pipeline.io import read_table
from pipeline.provenance import stage_costs
from pipeline.runner import Runner
from sources.common import StampUnit, stamp_from_name

DEFAULT_ROW = Path(__file__).resolve().parents[2] / "shared" / "real" / "sun3d_office"
"""The shared real row (../shared/real/sun3d_office next to the checkout)."""
FULL_SIZE = ("nerf_fit.render_scale=1",)
"""Settings of the bench beyond the defaults: validation renders (and their PSNR) at full size."""
FIGURES = {
    "psnr_db": (("windows_mean", "psnr"),),
    "ate_odometry_m": (("windows_mean", "ate_odometry_m"),),
    "ate_refined_m": (("windows_mean", "ate_refined_m"),),
    "count_pred": (("row", "count_pred"),),
}
"""Figures read from the row's evaluation table (column -> (scope, metric) candidates)."""


def excerpt(row: Path, dest: Path, n_frames: int, stamp_unit: StampUnit = "auto") -> Path:
    """Copy the first `n_frames` frames of the recorded row folder `row` (by the stamps of rgb/'s names, read
    as ingest reads them) into `dest`: their colour, depth and detector images, the odometry rows up to one
    row past the last frame, params.yaml, the detector scores, the gt/ tables' rows of those frames and
    README.txt. Returns dest."""
    row, dest = Path(row), Path(dest)
    colour = sorted((stamp_from_name(p.stem, stamp_unit), p) for p in (row / "rgb").iterdir()
                    if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
    if len(colour) < n_frames:
        raise ValueError(f"{row / 'rgb'} has {len(colour)} colour frames, fewer than the {n_frames} asked for")
    stems = {p.stem for _, p in colour[:n_frames]}
    last_ns = colour[n_frames - 1][0]
    for sub in ("rgb", "depth", "pred_seg/semantic", "pred_seg/instance", "seg"):
        if not (row / sub).is_dir():
            continue
        (dest / sub).mkdir(parents=True, exist_ok=True)
        for p in (row / sub).iterdir():
            if p.stem in stems:
                shutil.copyfile(p, dest / sub / p.name)
    for name in ("params.yaml", "README.txt"):
        if (row / name).is_file():
            shutil.copyfile(row / name, dest / name)
    odom = pd.read_csv(row / "odometry.csv", dtype={"timestamp": str})
    odom_ns = np.array([stamp_from_name(t.strip(), stamp_unit) for t in odom.timestamp], np.int64)
    odom = odom.iloc[np.argsort(odom_ns, kind="stable")]
    odom.iloc[:int(np.searchsorted(np.sort(odom_ns), last_ns, side="right")) + 1].to_csv(dest / "odometry.csv",
                                                                                          index=False)
    scores = row / "pred_seg" / "scores.csv"
    if scores.is_file():
        shutil.copyfile(scores, dest / "pred_seg" / "scores.csv")
    if (row / "gt").is_dir():
        (dest / "gt").mkdir(parents=True, exist_ok=True)
        for p in (row / "gt").glob("*.parquet"):
            t = pd.read_parquet(p)
            if "frame_id" in t:
                t = t[t.frame_id < n_frames]
            t.to_parquet(dest / "gt" / p.name, index=False)
    return dest


def place_row(row: Path, data_root: Path, n_frames: int = 0) -> str:
    """The row under data_root/raw/: a link to it, or with n_frames a copy of its first frames. Returns the
    sequence name (the row folder's name, with `_<n>f` for an excerpt)."""
    row = Path(row).resolve()
    if not (row / "rgb").is_dir():
        raise FileNotFoundError(f"{row} is not a recorded row folder (no rgb/); give one with --row "
                                f"(data/README.md describes the layout)")
    seq = f"{row.name}_{n_frames}f" if n_frames else row.name
    target = Path(data_root) / "raw" / seq
    target.parent.mkdir(parents=True, exist_ok=True)
    if n_frames:
        if not target.is_dir():
            excerpt(row, target, n_frames)
    elif not target.exists():
        target.symlink_to(row, target_is_directory=True)
    return seq


def icp_figures(data_root: Path, seq: str) -> dict[str, float]:
    """ICP's share of the consecutive-frame links and the depth limits the windows used (window_metrics)."""
    m = read_table(dataset("window_metrics").path(data_root, seq), "window_metrics")
    ok = m[m.status == "ok"]
    links = float((ok.n_train + ok.n_val - 1).sum())
    icp = ok.depth_pose_votes[ok.depth_poses == "icp"].sum()
    return {"icp_link_share": float(icp) / links if links else float("nan"),
            "icp_max_depth_m": float(ok.icp_max_depth_m.median()), "far_m": float(ok.far_m.median()),
            "windows": float(len(ok)), "samples_per_ray": float(ok.samples_per_ray.mean()),
            "render_s_per_image": float(ok.render_s_per_image.median()), "fit_s": float(ok.fit_s.mean())}


AGREEMENT_GAP = 4
"""Frames apart of the depth-agreement pairs the bench reports."""


def depth_agreement(data_root: Path, seq: str, gap: int = AGREEMENT_GAP) -> dict[str, float]:
    """Mean over windows of depth_disagreement (mm) of the odometry, refined and reference (gt/poses.parquet,
    matched by stamp) poses of each window's frames, with the window's own ICP depth limit and reach."""
    from nerf.depth_poses import MAX_DIST_M, REFERENCE_DEPTH_M, VOXEL_M, depth_cloud, depth_disagreement
    from nerf.geometry import pose_matrix
    from rowmap.ground_truth import gt_poses_by_frame
    from rowmap.window_data import load_window

    data_root = Path(data_root)
    frames = read_table(dataset("frames").path(data_root, seq), "frames")
    poses = read_table(dataset("window_poses").path(data_root, seq), "window_poses")
    metrics = read_table(dataset("window_metrics").path(data_root, seq), "window_metrics")
    gt_path = data_root / "raw" / seq / "gt" / "poses.parquet"
    gt = pd.read_parquet(gt_path) if gt_path.is_file() else None
    cols = ["tx", "ty", "tz", "qx", "qy", "qz", "qw"]
    out: dict[str, list[float]] = {"odometry": [], "refined": [], "reference": []}
    for wid, wp in poses.groupby("window_id"):
        wp = wp.sort_values("frame_id")
        fr = frames.set_index("frame_id").loc[wp.frame_id].reset_index()
        if len(fr) <= gap:
            continue
        data = load_window(fr.assign(split="train"), data_root)
        m = metrics[metrics.window_id == wid].iloc[0]
        limit = float(m.icp_max_depth_m) if np.isfinite(m.icp_max_depth_m) else REFERENCE_DEPTH_M
        grow = limit / REFERENCE_DEPTH_M
        clouds = [depth_cloud(d, k, limit, VOXEL_M * grow) for d, k in zip(data.depths, data.intrinsics)]
        sets = {"odometry": pose_matrix(fr[cols].to_numpy()), "refined": pose_matrix(wp[cols].to_numpy())}
        if gt is not None and "stamp_ns" in gt:
            ref = gt_poses_by_frame(gt, fr)  # matched as evaluate matches them; used only if every frame has one
            if len(ref) == len(fr):
                sets["reference"] = pose_matrix(ref.set_index("frame_id").loc[fr.frame_id, cols].to_numpy())
        for name, c2w in sets.items():
            out[name].append(1e3 * depth_disagreement(clouds, c2w, MAX_DIST_M * grow, gap, stride=1))
    return {f"depth_disagreement_{k}_mm": float(np.mean(v)) if v else float("nan") for k, v in out.items()}


def run(row: Path, data_root: Path, n_frames: int = 0, overrides: tuple[str, ...] = (), force: bool = False,
        show_progress: bool = True) -> pd.DataFrame:
    """Run every stage on the row and return the bench table (one line per stage, figures repeated)."""
    seq = place_row(row, data_root, n_frames)
    runner = Runner(seq, data_root=data_root, overrides=[*FULL_SIZE, *overrides], show_progress=show_progress)
    runner.run(force=force)
    stages = stage_costs(data_root, seq, [s.name for s in runner.active()])
    figures = {**quality(data_root, seq, FIGURES), **icp_figures(data_root, seq), **depth_agreement(data_root, seq)}
    figures["ate_ratio"] = figures["ate_refined_m"] / figures["ate_odometry_m"]
    df = stages[["stage", "seconds", "peak_rss_mb"]].copy()
    df = pd.concat([df, pd.DataFrame([{"stage": "total", "seconds": df.seconds.sum(),
                                       "peak_rss_mb": df.peak_rss_mb.max()}])], ignore_index=True)
    df.insert(0, "seq", seq)
    for k, v in figures.items():
        df[k] = v
    return df


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="pag bench real_rgbd", description=__doc__.split("\n")[0])
    p.add_argument("--row", type=Path, default=DEFAULT_ROW, help=f"recorded row folder (default {DEFAULT_ROW})")
    p.add_argument("--frames", type=int, default=0, help="use an excerpt of the row's first N frames (0 = all)")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                   help="further settings")
    p.add_argument("--force", action="store_true", help="rerun every stage")
    p.add_argument("--data-root", type=Path, default=Path("data/bench/real_rgbd"))
    p.add_argument("--out", type=Path, default=Path("data/bench"))
    a = p.parse_args(argv)
    df = run(a.row, a.data_root, a.frames, tuple(a.sets), a.force)
    write_parquet(df, a.out / "real_rgbd.parquet")
    print(df[["stage", "seconds", "peak_rss_mb"]].to_string(index=False, float_format=lambda v: f"{v:.1f}"))
    print(df.drop(columns=["stage", "seconds", "peak_rss_mb"]).iloc[0].to_string())
    print("the reference poses of a reconstruction are good to about 1-2 cm: ATE differences below that say little")
    print(f"wrote {a.out / 'real_rgbd.parquet'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
