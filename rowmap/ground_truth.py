"""Ground truth and a row's map in one frame: true poses keyed by frame, fruit centres moved into the ground
truth's world frame, and one-to-one fruit matching (used by evaluate and the season scores)."""
from __future__ import annotations

import numpy as np
import pandas as pd
from scipy.optimize import linear_sum_assignment

from nerf.geometry import pose_matrix
from sources.common import pair_nearest


def gt_poses_by_frame(gt_poses: pd.DataFrame, frames: pd.DataFrame) -> pd.DataFrame:
    """gt/poses.parquet keyed by the ingested frames' frame_id: each frame takes the ground-truth pose whose
    stamp_ns is nearest its own, within half the median frame period (0 for a single frame). frame_id in the
    file numbers the recorder's frames, which ingest renumbers after any skipped frame, so the stamp is the
    only key both share. Frames without such a pose are left out; the file's frame_id is dropped."""
    stamps = np.sort(frames.stamp_ns.to_numpy(np.int64))
    tol_ns = int(np.median(np.diff(stamps)) // 2) if len(stamps) > 1 else 0
    gt = gt_poses.drop(columns=["frame_id"], errors="ignore").sort_values("stamp_ns", kind="stable")
    j = pair_nearest(frames.stamp_ns.to_numpy(np.int64), gt.stamp_ns.to_numpy(np.int64), tol_ns)
    ok = j >= 0
    out = gt.iloc[j[ok]].drop(columns=["stamp_ns"]).reset_index(drop=True)
    out.insert(0, "frame_id", frames.frame_id.to_numpy()[ok])
    return out


def match_fruits(pred: np.ndarray, gt: np.ndarray, max_m: float) -> list[tuple[int, int, float]]:
    """One-to-one matches (pred index, gt index, distance) of centres [P, 3] and [G, 3] minimising the total
    distance (Hungarian), pairs farther than max_m excluded."""
    if len(pred) == 0 or len(gt) == 0:
        return []
    d = np.linalg.norm(pred[:, None] - gt[None], axis=2)
    r, c = linear_sum_assignment(np.where(d <= max_m, d, 1e3 + d))  # large finite cost outside the gate
    return [(int(i), int(j), float(d[i, j])) for i, j in zip(r, c) if d[i, j] <= max_m]


def to_ground_truth_frame(fruits: pd.DataFrame, frames: pd.DataFrame, gt_poses: pd.DataFrame | None,
                          map_poses: pd.DataFrame | None = None) -> np.ndarray:
    """Fruit centres [F, 3] moved from the map's world frame into the ground truth's, each through the camera
    of one frame that saw it (the frame nearest the middle of first_frame_id..last_frame_id):
    p_gt = T_gt(f) T_map(f)^-1 p, with T_map the pose the map placed frame f with (`map_poses`:
    panoptic_frames' row-frame poses; else the odometry pose in `frames`). The row map drifts with the
    odometry (centimetres over a row); this local alignment scores each fruit where the robot thought it was
    when it saw it, as a tape measure from the camera would. Without ground-truth poses the centres are
    returned unchanged."""
    xyz = fruits[["x_m", "y_m", "z_m"]].to_numpy(np.float64)
    if gt_poses is None or len(fruits) == 0:
        return xyz
    cols = ["tx", "ty", "tz", "qx", "qy", "qz", "qw"]
    placed = frames[["frame_id", *cols]].reset_index(drop=True)
    if map_poses is not None and len(map_poses) and set(cols) <= set(map_poses.columns):
        placed = map_poses[["frame_id", *cols]].reset_index(drop=True)
    both = placed.merge(gt_poses[["frame_id", *cols]], on="frame_id", suffixes=("_odo", "_gt"))
    if both.empty:
        return xyz
    fids = both.frame_id.to_numpy()
    t_odo = pose_matrix(both[[f"{c}_odo" for c in cols]].to_numpy(np.float64))
    t_gt = pose_matrix(both[[f"{c}_gt" for c in cols]].to_numpy(np.float64))
    mid = (fruits.first_frame_id.to_numpy(np.float64) + fruits.last_frame_id.to_numpy(np.float64)) / 2
    ref = np.abs(fids[None, :] - mid[:, None]).argmin(1)
    rel = t_gt[ref] @ np.linalg.inv(t_odo[ref])                                          # [F, 4, 4]
    return np.einsum("fij,fj->fi", rel[:, :3, :3], xyz) + rel[:, :3, 3]
