"""A window's data for a NeRF fit, read from the pipeline's tables: its frames (images, depth, intrinsics,
initial poses) as nerf's WindowData, its detector labels as WindowLabels, and the choice of initial poses.
Used by nerf_fit and by the benchmarks, so both fit exactly what the pipeline fits.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from nerf.geometry import pose_matrix
from pipeline.classes import VOID
from pipeline.images import read_depth_m, read_label, read_rgb


def load_window(frames: pd.DataFrame, data_root: Path):
    """The window's frames (rows of frames.parquet, in order; `split` says train/val) as nerf.window.WindowData:
    images, depth in metres, intrinsics, odometry (or given initial) poses."""
    from nerf.window import WindowData

    imgs = np.stack([read_rgb(data_root / p) for p in frames["rgb_path"]])
    deps = np.stack([read_depth_m(data_root / p, s) for p, s in zip(frames["depth_path"], frames["depth_scale_m"])])
    k = frames[["fx", "fy", "cx", "cy"]].to_numpy(np.float64)
    poses = pose_matrix(frames[["tx", "ty", "tz", "qx", "qy", "qz", "qw"]].to_numpy(np.float64))
    return WindowData(imgs, deps, k, poses, (frames["split"] == "train").to_numpy(), frames["frame_id"].to_numpy())


def load_labels(frames: pd.DataFrame, dets: pd.DataFrame | None, data_root: Path):
    """The detector's panoptic input of a window's frames (nerf/panoptic/labels.WindowLabels): segments the
    depth filter dropped become void, thing segments carry their score, stuff 1."""
    from nerf.panoptic.labels import WindowLabels

    h, w = int(frames["height"].iloc[0]), int(frames["width"].iloc[0])
    n = len(frames)
    # filled frame by frame: lists of frames stacked at the end would hold the window's labels twice
    sems, insts = np.empty((n, h, w), np.uint8), np.empty((n, h, w), np.int16)
    scores: list[np.ndarray] = []
    for j, (fid, sp, ip) in enumerate(zip(frames["frame_id"], frames["det_semantic_path"], frames["det_instance_path"])):
        if not isinstance(sp, str) or not isinstance(ip, str):  # no detector output for this frame: all void
            sems[j], insts[j] = VOID, 0
            scores.append(np.ones(1, np.float32))
            continue
        sem = read_label(data_root / sp, "detector semantic").astype(np.uint8)
        inst = read_label(data_root / ip, "detector instance")
        if sem.shape != (h, w) or inst.shape != (h, w):
            raise ValueError(f"frame {fid}: detector PNGs {sp} / {ip} are {sem.shape} / {inst.shape}, "
                             f"the images are {(h, w)}")
        fd = dets[dets.frame_id == fid] if dets is not None else None
        score = np.ones(int(max(inst.max(), fd.segment_id.max() if fd is not None and len(fd) else 0)) + 1,
                        np.float32)
        if fd is not None:
            keep = np.ones(len(score), bool)
            keep[fd.segment_id.to_numpy()] = fd.kept.to_numpy()
            score[fd.segment_id.to_numpy()] = fd.score.to_numpy()
            drop = (inst > 0) & ~keep[inst]
            sem[drop] = VOID
            inst[drop] = 0
        if len(score) - 1 > np.iinfo(insts.dtype).max:  # ids past int16's range (a 16-bit PNG's upper half)
            insts = insts.astype(np.int32)
        sems[j], insts[j] = sem, inst
        scores.append(score)
    table = np.ones((n, max(len(s) for s in scores)), np.float32)
    for j, s in enumerate(scores):
        table[j, :len(s)] = s
    return WindowLabels(sems, insts, table)


def initial_poses(w: pd.DataFrame, wid: int, colmap: pd.DataFrame | None, source: str) -> pd.DataFrame:
    """The window's rows (windows merged with frames) with the initial pose columns taken from `source`
    and a `pose_source` column per frame ('odometry' or 'colmap', as colmap_poses.parquet says)."""
    w = w.copy()
    w["pose_source"] = "odometry"
    if source == "odometry":
        return w
    if colmap is None or colmap.empty:
        raise ValueError("nerf_fit.pose_source=colmap, but colmap_poses.parquet is "
                         f"{'missing' if colmap is None else 'empty'}; run `pag colmap_poses --set "
                         "colmap_poses.enabled=true` first (or `pag all` with that setting)")
    cols = ["tx", "ty", "tz", "qx", "qy", "qz", "qw"]
    c = colmap[colmap.window_id == wid].set_index("frame_id")
    missing = sorted(set(w["frame_id"]) - set(c.index))
    if missing:
        raise ValueError(f"nerf_fit.pose_source=colmap: colmap_poses.parquet has no pose for window {wid}, frames "
                         f"{missing[:10]}; it is older than windows.parquet: rerun `pag colmap_poses`")
    c = c.loc[w["frame_id"]]
    w[cols] = c[cols].to_numpy()
    w["pose_source"] = c["source"].to_numpy()
    return w


def window_detections(dets: pd.DataFrame | None, w: pd.DataFrame) -> dict | None:
    """The detections_filtered rows of the window's frames as columns (what a fit task carries), or None."""
    if dets is None or dets.empty:
        return None
    return dets[dets.frame_id.isin(w.frame_id)][["frame_id", "segment_id", "score", "kept"]].to_dict("list")
