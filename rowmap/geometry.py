"""Fruit geometry across windows: the row frame the windows are brought into, the centre of a fruit from
its seen surface, groups of pixels whose 3D points lie apart, an even subsample of points, and the depth that
places fused pixels in 3D."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from nerf.geometry import align_similarity, pose_matrix, similarity_matrix
from nerf.surfaces import robust_centre
from pipeline.images import ImageError, read_depth_m

POSE_COLS = ("tx", "ty", "tz", "qx", "qy", "qz", "qw")
"""camera-to-world pose columns of the pose tables (position in m, rotation quaternion)."""


def window_alignments(window_poses: pd.DataFrame) -> dict[int, np.ndarray]:
    """Per window, the transform [4, 4] from its own (refined) frame into the row frame: the first window's
    frame, each later window joined to the nearest earlier one it shares frames with. The join is the rigid
    transform between the shared frames' poses (as already aligned): the chordal mean rotation of their
    orientations (which pin the roll about the row that a straight, nearly collinear track of positions
    leaves free) and the mean position offset. A window sharing no frame keeps the previous one's transform."""
    poses = {int(w): dict(zip(g.frame_id.astype(int), pose_matrix(g[list(POSE_COLS)].to_numpy(np.float64))))
             for w, g in window_poses.groupby("window_id")}
    out: dict[int, np.ndarray] = {}
    done: list[int] = []
    for wid in sorted(poses):
        t = out[done[-1]] if done else np.eye(4)
        for prev in reversed(done):
            shared = sorted(set(poses[wid]) & set(poses[prev]))
            if shared:
                src = np.stack([poses[wid][f] for f in shared])
                dst = out[prev] @ np.stack([poses[prev][f] for f in shared])
                s, r, tr = align_similarity(src[:, :3, 3], dst[:, :3, 3], src[:, :3, :3], dst[:, :3, :3],
                                            with_scale=False, position_weight=0.0, orientation_weight=1.0)
                t = similarity_matrix(s, r, tr)
                break
        out[wid] = t
        done.append(wid)
    return out


def sphere_behind(points: np.ndarray, eye: np.ndarray, radius: float, min_points: int = 4) -> np.ndarray | None:
    """Centre [3] of the least-squares sphere of the given radius through the inliers of robust_centre of a
    fruit's seen surface points [N, 3], started `radius` behind their median as seen from `eye` [3] (the mean
    camera centre of the views that saw them). A free fit to a shallow or partial cap finds a sphere far
    wider than the fruit (not plausible_fit); a sphere of the fruit's size still places the centre behind the
    seen part, where the cap's curvature says it is, instead of on the side that faced the camera. None with
    fewer than min_points (at least 4) inliers, a non-positive radius, or where the fit ends nearer the eye
    than the median."""
    med, keep = robust_centre(points)
    inl = np.asarray(points[keep], np.float64)
    ray = med - np.asarray(eye, np.float64)
    if len(inl) < max(min_points, 4) or not radius > 0 or not np.linalg.norm(ray) > 0:
        return None
    ray /= np.linalg.norm(ray)

    def resid(c: np.ndarray) -> np.ndarray:
        return np.linalg.norm(inl - c, axis=1) - radius

    c = least_squares(resid, med + radius * ray, loss="soft_l1", f_scale=0.1 * radius, max_nfev=50).x
    return c if np.all(np.isfinite(c)) and (c - med) @ ray > 0 else None


def subsample(n: int, cap: int) -> np.ndarray:
    """Evenly spaced indices of at most `cap` of n items (deterministic). Example: subsample(5, 3) -> [0, 2, 4]."""
    return np.arange(n) if n <= cap else np.round(np.linspace(0, n - 1, cap)).astype(np.int64)


def pixel_groups(v: np.ndarray, u: np.ndarray, points: np.ndarray, gap_m: float, min_size: int,
                 max_groups: int) -> np.ndarray:
    """Labels [N] of the groups that pixels (v, u) [N] with 3D points [N, 3] form when image neighbours (left,
    right, up, down) are linked if their points lie closer than gap_m: a depth jump or an image gap
    separates groups. Largest group 0, then by size; groups of fewer than min_size pixels join group 0,
    and so do groups past the first max_groups. gap_m <= 0 or fewer than 2 * min_size pixels: all zeros."""
    n = len(v)
    if gap_m <= 0 or n < 2 * min_size:
        return np.zeros(n, np.int64)
    index = np.full((int(v.max()) + 2, int(u.max()) + 2), -1, np.int64)
    index[v, u] = np.arange(n)
    pairs = []
    for dv, du in ((0, 1), (1, 0)):
        j = index[v + dv, u + du]
        i = np.flatnonzero(j >= 0)
        j = j[i]
        near = np.linalg.norm(points[i] - points[j], axis=1) < gap_m
        pairs.append((i[near], j[near]))
    i = np.concatenate([p[0] for p in pairs])
    j = np.concatenate([p[1] for p in pairs])
    k, lab = connected_components(coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n)), directed=False)
    if k == 1:
        return np.zeros(n, np.int64)
    rank = np.empty(k, np.int64)
    rank[np.argsort(-np.bincount(lab, minlength=k), kind="stable")] = np.arange(k)
    lab = rank[lab]
    keep = (np.bincount(lab, minlength=k) >= min_size) & (np.arange(k) < max_groups)
    keep[0] = True
    return np.where(keep[lab], np.cumsum(keep)[lab] - 1, 0)


def with_sensor_depth(rendered: np.ndarray, sensor_path: Path, scale_m: float) -> np.ndarray:
    """[H, W] metres: the recorded depth image at `sensor_path` (units of `scale_m` metres; ingest aligns it
    to colour, so it matches the render's size) where it has a valid pixel, the `rendered` depth elsewhere."""
    sensor = read_depth_m(sensor_path, scale_m)
    if sensor.shape != rendered.shape:
        raise ImageError(f"depth image {sensor_path} is {sensor.shape[1]}x{sensor.shape[0]} but the render is "
                         f"{rendered.shape[1]}x{rendered.shape[0]}; rerun the pipeline from ingest")
    return np.where(sensor > 0, sensor, rendered)
