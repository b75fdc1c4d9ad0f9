"""The odometry's scale along a window, measured with the depth sensor.

Wheel odometry is often a few percent long or short (wheel radius, slip), and the pose refinement cannot
correct that: stretching every pose of a window at once is a direction that per-frame corrections
trained from colour do not find (the default synthetic row kept its 3 % stretch through refinement). The
depth sensor measures it directly. For frame pairs a few frames apart, point-to-plane ICP (Open3D) aligns
the two depth clouds starting from the odometry's relative pose; the ratio of the ICP translation to the
odometry translation is that stretch over the pair. The window's scale is the median ratio over pairs
whose ICP converged, and the window's initial poses are stretched by it about their mean position:

    t_i' = c + s (t_i - c),   c = mean_i t_i,   s = median over pairs of |t_icp| / |t_odometry|

Rotations are left to the refinement. Default row, window 1: median ratio 0.967 against 0.967 from
the ground truth.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ScaleEstimate:
    scale: float
    """the stretch applied to the window's translations (1 = none)."""
    pairs: int
    """frame pairs whose ICP converged and that voted."""
    spread: float
    """median absolute deviation of the pairs' ratios."""
    note: str
    """why no scale was applied, or ''."""


def depth_cloud(depth_m: np.ndarray, k: np.ndarray, max_depth_m: float, voxel_m: float):
    """Open3D point cloud (camera frame, with normals) of the pixels with depth in (0, max_depth_m]."""
    import open3d as o3d

    v, u = np.nonzero((depth_m > 0) & (depth_m <= max_depth_m) & np.isfinite(depth_m))
    z = depth_m[v, u].astype(np.float64)
    pts = np.stack([(u + 0.5 - k[2]) / k[0] * z, (v + 0.5 - k[3]) / k[1] * z, z], 1)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)).voxel_down_sample(voxel_m)
    if len(pc.points) < 3:
        return pc
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel_m, max_nn=30))
    return pc


def odometry_scale(depths: np.ndarray, intrinsics: np.ndarray, c2w: np.ndarray, gap: int = 8, stride: int = 4,
                   max_depth_m: float = 1.5, voxel_m: float = 0.004, max_dist_m: float = 0.01,
                   min_fitness: float = 0.5, min_baseline_m: float = 0.03, min_pairs: int = 5,
                   max_spread: float = 0.02, max_change: float = 0.2) -> ScaleEstimate:
    """Scale of a window's odometry from depth frames [N, H, W] (metres, 0 = none), intrinsics [N, 4]
    (fx fy cx cy) and odometry camera-to-world poses [N, 4, 4] (frames in time order). Pairs (i, i + gap)
    every `stride` frames vote when ICP (inlier distance max_dist_m) converges with fitness >= min_fitness
    and the odometry moved >= min_baseline_m between them. Returns scale 1 with a note when fewer than
    min_pairs vote, when their ratios disagree (MAD > max_spread) or when the scale is off by more than
    max_change: a scene ICP cannot lock on (moving leaves, no depth) must not stretch the trajectory."""
    import open3d as o3d

    n = len(depths)
    ratios, clouds = [], {}
    for i in range(0, max(n - gap, 0), stride):
        j = i + gap
        init = np.linalg.inv(c2w[j]) @ c2w[i]                 # camera i -> camera j, from the odometry
        base = float(np.linalg.norm(init[:3, 3]))
        if base < min_baseline_m:
            continue
        for f in (i, j):
            if f not in clouds:
                clouds[f] = depth_cloud(depths[f], intrinsics[f], max_depth_m, voxel_m)
        if len(clouds[i].points) < 100 or len(clouds[j].points) < 100:
            continue
        reg = o3d.pipelines.registration.registration_icp(
            clouds[i], clouds[j], max_dist_m, init, o3d.pipelines.registration.TransformationEstimationPointToPlane())
        t = np.asarray(reg.transformation)[:3, 3]
        if reg.fitness >= min_fitness and np.all(np.isfinite(t)):
            ratios.append(float(np.linalg.norm(t)) / base)
    if len(ratios) < min_pairs:
        return ScaleEstimate(1.0, len(ratios), float("nan"), f"{len(ratios)} of the needed {min_pairs} frame pairs "
                                                              "registered")
    r = np.array(ratios)
    s, spread = float(np.median(r)), float(np.median(np.abs(r - np.median(r))))
    if spread > max_spread:
        return ScaleEstimate(1.0, len(r), spread, f"pair ratios disagree (MAD {spread:.3f} > {max_spread})")
    if abs(s - 1.0) > max_change:
        return ScaleEstimate(1.0, len(r), spread, f"scale {s:.3f} is off by more than {max_change:.0%}")
    return ScaleEstimate(s, len(r), spread, "")


def stretch(c2w: np.ndarray, scale: float) -> np.ndarray:
    """Poses [N, 4, 4] with their positions stretched by `scale` about their mean (rotations unchanged)."""
    out = c2w.copy()
    c = c2w[:, :3, 3].mean(0)
    out[:, :3, 3] = c + scale * (c2w[:, :3, 3] - c)
    return out
