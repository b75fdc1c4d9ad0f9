"""Initial camera poses of a window corrected with the depth sensor.

Wheel odometry is often a few percent long or short (wheel radius, slip) and drifts in yaw, and the pose
refinement does not undo that: stretching or bending every pose of a window at once is a direction that
per-frame corrections trained from colour do not find (a window keeps the stretch it starts with through
refinement). The depth sensor measures it directly. Two corrections, `depth_initial_poses(mode)`:

- 'scale' (odometry_scale): for frame pairs a few frames apart, point-to-plane ICP (Open3D) aligns the two
  depth clouds starting from the odometry's relative pose; the window's positions are stretched about
  their mean by the median ratio of ICP to odometry translations,
      t_i' = c + s (t_i - c),   c = mean_i t_i,   s = median over pairs of |t_icp| / |t_odometry|.
- 'icp' (icp_trajectory): every consecutive pair's relative pose from ICP, chained, then placed onto the
  odometry by one rigid transform (the window stays in the odometry's frame, its shape comes from depth);
  a link keeps the odometry's relative pose where ICP does not converge or jumps. The pose errors before and
  after (ATE, rotation) are in the evaluation table (`ate_odometry_m`, `ate_refined_m`).

Either way the online refinement then trains from colour only, as before.

ICP runs in Open3D where it imports; elsewhere (a GPU machine without Open3D's wheels, or PAG_ICP=numpy) in
numpy/scipy with the same steps and settings (voxel means, PCA normals, point-to-plane Gauss-Newton).
"""
from __future__ import annotations

import functools
import os
from dataclasses import dataclass
from typing import Literal

import numpy as np

from nerf.geometry import align_similarity, rotation_angle_deg, similarity_matrix
from nerf.surfaces import unproject
from nerf.window import round_up, valid_depth_sample

NEAR_PERCENTILE = 5.0
"""ICP's depth limit is derived from this percentile of the window's valid depth (its nearest surfaces)."""
NEAR_REACH = 2.5
"""... times this reach: a structured-light or stereo sensor's depth noise grows with depth squared, so points
beyond 2.5x the nearest surfaces carry over 6x their noise."""
REFERENCE_DEPTH_M = 1.5
"""ICP's voxel size and inlier distance (VOXEL_M, MAX_DIST_M) are set for a depth limit of this many metres and
grow in proportion to the limit (point spacing and depth noise both grow with depth)."""
VOXEL_M = 0.004
MAX_DIST_M = 0.01


def icp_depth_limit_m(depths: np.ndarray, far_m: float = 0.0) -> float:
    """ICP's depth limit for a window's depth frames [N, H, W] (metres, 0 = none): NEAR_REACH x the
    NEAR_PERCENTILE of the valid depth, rounded up to 0.5 m, at most far_m (if > 0); REFERENCE_DEPTH_M without
    valid depth. Example: a glasshouse row whose near row starts at 0.48 m -> 1.5 m; an office whose nearest
    surfaces lie at 1.5-1.7 m -> 4.0-4.5 m."""
    v = valid_depth_sample(depths)
    if v.size == 0:
        return REFERENCE_DEPTH_M
    limit = round_up(NEAR_REACH * float(np.percentile(v, NEAR_PERCENTILE)))
    return min(limit, far_m) if far_m > 0 else limit


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


IcpBackend = Literal["open3d", "numpy"]


@functools.cache
def icp_backend() -> IcpBackend:
    """'numpy' when PAG_ICP=numpy or Open3D does not import, else 'open3d' (decided once per process)."""
    if os.environ.get("PAG_ICP") == "numpy":
        return "numpy"
    try:
        import open3d  # noqa: F401
    except (ImportError, OSError):                                          # OSError: its shared libraries do not load
        return "numpy"
    return "open3d"


@dataclass(frozen=True)
class Cloud:
    """A depth cloud of the numpy ICP (camera frame, metres)."""
    points: np.ndarray
    """[n, 3] voxel means."""
    normals: np.ndarray
    """[n, 3] unit normals, facing the camera."""


def depth_cloud(depth_m: np.ndarray, k: np.ndarray, max_depth_m: float, voxel_m: float):
    """Point cloud (camera frame, with normals) of the pixels with depth in (0, max_depth_m], thinned to the
    mean point of each voxel of voxel_m, normals from the neighbours within 5 voxel_m (at most 30): an
    Open3D PointCloud or, with the numpy backend (icp_backend), a Cloud."""
    v, u = np.nonzero((depth_m > 0) & (depth_m <= max_depth_m) & np.isfinite(depth_m))
    pts = unproject(depth_m, k, None, v, u)
    if icp_backend() == "numpy":
        return numpy_cloud(pts, voxel_m)
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)).voxel_down_sample(voxel_m)
    if len(pc.points) < 3:
        return pc
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel_m, max_nn=30))
    return pc


def numpy_cloud(pts: np.ndarray, voxel_m: float, max_nn: int = 30) -> Cloud:
    """Cloud of points [N, 3] (camera frame): the mean point of each voxel of voxel_m (on Open3D's grid: cubes
    from half a voxel below the points' minimum), normals from the PCA of each mean's nearest max_nn
    neighbours (itself included) within 5 voxel_m (the covariance's least eigenvector; the optical axis with
    fewer than 3, as in Open3D), turned to face the camera at the origin."""
    from scipy.spatial import cKDTree

    if len(pts) == 0:
        return Cloud(np.zeros((0, 3)), np.zeros((0, 3)))
    cell = np.floor((pts - (pts.min(0) - voxel_m / 2)) / voxel_m).astype(np.int64)
    dims = cell.max(0) + 1
    _, inv, count = np.unique((cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2], return_inverse=True,
                              return_counts=True)
    inv = inv.reshape(-1)
    pts = np.stack([np.bincount(inv, pts[:, a], len(count)) for a in range(3)], 1) / count[:, None]   # [n, 3]
    n = len(pts)
    dist, idx = cKDTree(pts).query(pts, k=min(max_nn, n), distance_upper_bound=5 * voxel_m, workers=-1)
    dist, idx = dist.reshape(n, -1), idx.reshape(n, -1)
    found = np.isfinite(dist)                                              # [n, k]
    cnt = found.sum(1)
    # a missing neighbour is the point itself (offset 0): it adds nothing to the sums below
    rel = pts[np.where(found, idx, np.arange(n)[:, None])] - pts[:, None]  # [n, k, 3] offsets to the neighbours
    mean = rel.sum(1) / cnt[:, None]                                       # [n, 3]
    cov = np.matmul(rel.transpose(0, 2, 1), rel) / cnt[:, None, None] - mean[:, :, None] * mean[:, None, :]
    normals = np.linalg.eigh(cov)[1][:, :, 0]                              # least eigenvalue's eigenvector
    normals[cnt < 3] = [0.0, 0.0, 1.0]                                     # too few to fit a plane: the optical axis
    normals *= np.where(np.einsum("ij,ij->i", normals, pts) > 0, -1.0, 1.0)[:, None]
    return Cloud(pts, normals)


def register(src, dst, init: np.ndarray, max_dist_m: float, min_points: int = 100) -> tuple[np.ndarray, float] | None:
    """Point-to-plane ICP of cloud `src` onto `dst` (depth_cloud) from `init` [4, 4]: (transform, fitness),
    or None when either cloud has fewer than `min_points` points. Clouds of the numpy backend (Cloud) go to
    numpy_icp, the others to Open3D."""
    if len(src.points) < min_points or len(dst.points) < min_points:
        return None
    if isinstance(src, Cloud):
        return numpy_icp(src, dst, init, max_dist_m)
    import open3d as o3d

    reg = o3d.pipelines.registration.registration_icp(
        src, dst, max_dist_m, init, o3d.pipelines.registration.TransformationEstimationPointToPlane())
    return np.asarray(reg.transformation), float(reg.fitness)


def numpy_icp(src: Cloud, dst: Cloud, init: np.ndarray, max_dist_m: float, max_iterations: int = 30,
              min_step: float = 1e-6) -> tuple[np.ndarray, float]:
    """Point-to-plane ICP (as Open3D's registration_icp) of `src` onto `dst` from `init` [4, 4]: (transform,
    fitness). Each iteration pairs each moved src point p with its nearest dst point q within max_dist_m
    (normal n) and takes the Gauss-Newton step (w, t) of the linearised residuals
        r = (p - q) . n + w . (p x n) + t . n,     [p x n, n] (w, t) = -(p - q) . n  in least squares,
    applied as exp([w]x), t; it stops after max_iterations or when |w| (rad) and |t| (m) fall below min_step.
    fitness: the fraction of src points paired at the end."""
    from scipy.spatial import cKDTree
    from scipy.spatial.transform import Rotation

    tree = cKDTree(dst.points)
    t_total = np.array(init, dtype=np.float64)
    for _ in range(max_iterations):
        p = src.points @ t_total[:3, :3].T + t_total[:3, 3]
        dist, j = tree.query(p, distance_upper_bound=max_dist_m, workers=-1)
        ok = np.isfinite(dist)
        if ok.sum() < 6:
            break
        p, q, n = p[ok], dst.points[j[ok]], dst.normals[j[ok]]
        jac = np.concatenate([np.cross(p, n), n], 1)                      # [m, 6]
        res = np.einsum("ij,ij->i", p - q, n)
        # least squares: directions the scene leaves free (a plane's in-plane motion) get no step
        step = np.linalg.lstsq(jac.T @ jac, -jac.T @ res, rcond=None)[0]
        update = np.eye(4)
        update[:3, :3], update[:3, 3] = Rotation.from_rotvec(step[:3]).as_matrix(), step[3:]
        t_total = update @ t_total
        if np.linalg.norm(step[:3]) < min_step and np.linalg.norm(step[3:]) < min_step:
            break
    p = src.points @ t_total[:3, :3].T + t_total[:3, 3]
    dist, _ = tree.query(p, distance_upper_bound=max_dist_m, workers=-1)
    return t_total, float(np.isfinite(dist).mean())


def odometry_scale(depths: np.ndarray, intrinsics: np.ndarray, c2w: np.ndarray, gap: int = 8, stride: int = 4,
                   max_depth_m: float = REFERENCE_DEPTH_M, voxel_m: float = VOXEL_M, max_dist_m: float = MAX_DIST_M,
                   min_fitness: float = 0.5, min_baseline_m: float = 0.03, min_pairs: int = 5,
                   max_spread: float = 0.02, max_change: float = 0.2) -> ScaleEstimate:
    """Scale of a window's odometry from depth frames [N, H, W] (metres, 0 = none), intrinsics [N, 4]
    (fx fy cx cy) and odometry camera-to-world poses [N, 4, 4] (frames in time order). Pairs (i, i + gap)
    every `stride` frames vote when ICP (inlier distance max_dist_m) converges with fitness >= min_fitness
    and the odometry moved >= min_baseline_m between them. Returns scale 1 with a note when fewer than
    min_pairs vote, when their ratios disagree (MAD > max_spread) or when the scale is off by more than
    max_change: a scene ICP cannot lock on (moving leaves, no depth) must not stretch the trajectory."""
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
        reg = register(clouds[i], clouds[j], init, max_dist_m)
        if reg is None:
            continue
        t = reg[0][:3, 3]
        if reg[1] >= min_fitness and np.all(np.isfinite(t)):
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


def place_onto(poses: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """The rigid transform [4, 4] that best places trajectory `poses` [N, 4, 4] onto `ref`: the rotation is
    the chordal mean of ref_i R_i^T over the frames (orientations, not positions: a nearly straight track
    leaves the roll about it free in a fit of positions), then the mean positions coincide."""
    s, r, t = align_similarity(poses[:, :3, 3], ref[:, :3, 3], poses[:, :3, :3], ref[:, :3, :3], with_scale=False,
                               position_weight=0.0, orientation_weight=1.0)
    return similarity_matrix(s, r, t)


def icp_trajectory(depths: np.ndarray, intrinsics: np.ndarray, c2w: np.ndarray,
                   max_depth_m: float = REFERENCE_DEPTH_M, voxel_m: float = VOXEL_M, max_dist_m: float = MAX_DIST_M,
                   min_fitness: float = 0.5,
                   max_link_change_m: float = 0.01, max_link_change_deg: float = 1.0) -> tuple[np.ndarray, int, str]:
    """A window's camera poses [N, 4, 4] from its depth frames: each consecutive pair's relative pose by
    point-to-plane ICP started from the odometry's, chained from the first frame, then placed onto the
    odometry by one rigid transform (place_onto: mean orientation and mean position; the window stays in the
    odometry's frame, only its shape comes from depth). A link keeps the odometry's relative pose
    when ICP does not converge (fitness < min_fitness) or moves it by more than max_link_change_m /
    max_link_change_deg (a wrong lock). The chain is kept only where the depth of frames AGREEMENT_GAP apart
    agrees better with it than with the odometry (depth_disagreement); else the odometry is returned with 0
    links. Returns (poses, links from ICP, note)."""
    n = len(depths)
    clouds = [depth_cloud(d, k, max_depth_m, voxel_m) for d, k in zip(depths, intrinsics)]
    out = [c2w[0].copy()]
    good = 0
    for i in range(n - 1):
        init = np.linalg.inv(c2w[i + 1]) @ c2w[i]               # camera i -> camera i + 1, from the odometry
        rel = init
        reg = register(clouds[i], clouds[i + 1], init, max_dist_m)
        if reg is not None and reg[1] >= min_fitness and np.all(np.isfinite(reg[0])):
            t = reg[0]
            change = np.linalg.inv(init) @ t
            if (np.linalg.norm(change[:3, 3]) <= max_link_change_m
                    and rotation_angle_deg(init[:3, :3], t[:3, :3]) <= max_link_change_deg):
                rel, good = t, good + 1
        out.append(out[-1] @ np.linalg.inv(rel))
    poses = np.stack(out)
    placed = place_onto(poses, c2w) @ poses
    note = "" if good == n - 1 else f"{n - 1 - good} of {n - 1} links kept the odometry's relative pose"
    if good and n > 2:
        # chained links add up their errors: keep the chain only where it makes frames several links apart agree
        # better than the odometry does (a noisy far-range sensor's links can be worse than a good odometry's)
        gap = min(AGREEMENT_GAP, n - 1)
        icp_m, odo_m = (depth_disagreement(clouds, p, max_dist_m, gap) for p in (placed, c2w))
        if not icp_m < odo_m:
            return c2w, 0, (f"ICP's trajectory disagrees more with the depth than the odometry's ({1e3 * icp_m:.2f} "
                            f"against {1e3 * odo_m:.2f} mm, frames {gap} apart): odometry kept")
    return placed, good, note


AGREEMENT_GAP = 8
"""Frames apart of the pairs whose depth agreement decides between the ICP chain and the odometry."""


def depth_disagreement(clouds: list, c2w: np.ndarray, max_dist_m: float, gap: int, stride: int = 2) -> float:
    """How far the depth clouds (depth_cloud: camera frames, with normals) of frames `gap` apart lie from each
    other's surfaces when placed with poses c2w [N, 4, 4]: the mean over pairs (i, i + gap), every `stride`
    frames, and over frame i's points of the point-to-plane distance |(p - q) . n_q| from frame i's points p to
    their nearest point q of frame j, each capped at 3 x max_dist_m (also where q is farther than that: a surface
    frame j does not see). Point-to-plane, as ICP measures, so two samplings of one surface agree. Metres; lower =
    the poses agree better with the depth."""
    from scipy.spatial import cKDTree

    cap = 3 * max_dist_m
    out = []
    for i in range(0, len(c2w) - gap, stride):
        j = i + gap
        dst, dst_normals = np.asarray(clouds[j].points), np.asarray(clouds[j].normals)
        if len(clouds[i].points) == 0 or len(dst) == 0 or len(dst_normals) != len(dst):
            continue
        rel = np.linalg.inv(c2w[j]) @ c2w[i]
        src = np.asarray(clouds[i].points) @ rel[:3, :3].T + rel[:3, 3]
        near, idx = cKDTree(dst).query(src, distance_upper_bound=cap)
        found = np.isfinite(near)
        dist = np.full(len(src), cap)
        normals = dst_normals[idx[found]]
        dist[found] = np.minimum(np.abs(np.einsum("ij,ij->i", src[found] - dst[idx[found]], normals)), cap)
        out.append(float(dist.mean()))
    return float(np.mean(out)) if out else float("inf")


DepthPoses = Literal["off", "scale", "icp"]


def depth_initial_poses(mode: DepthPoses, depths: np.ndarray, intrinsics: np.ndarray, c2w: np.ndarray,
                        max_depth_m: float = 0.0) -> tuple[np.ndarray, dict]:
    """A window's initial poses [N, 4, 4] (frames in time order) corrected by `mode`, and what was done:
    {'depth_poses': mode, 'odometry_scale': scale or NaN, 'depth_pose_votes': ICP pairs or links used,
    'depth_pose_note': why less was done ('' if nothing to say), 'icp_max_depth_m': the depth limit used (NaN
    with mode 'off')}. ICP takes the points up to `max_depth_m` (0 = icp_depth_limit_m of the depths), with a
    voxel size and inlier distance grown in proportion to that limit (VOXEL_M, MAX_DIST_M at
    REFERENCE_DEPTH_M)."""
    if mode == "off":
        return c2w, {"depth_poses": mode, "odometry_scale": float("nan"), "depth_pose_votes": 0, "depth_pose_note": "",
                     "icp_max_depth_m": float("nan")}
    limit = max_depth_m if max_depth_m > 0 else icp_depth_limit_m(depths)
    grow = limit / REFERENCE_DEPTH_M
    reach = dict(max_depth_m=limit, voxel_m=VOXEL_M * grow, max_dist_m=MAX_DIST_M * grow)
    if mode == "scale":
        est = odometry_scale(depths, intrinsics, c2w, **reach)
        return stretch(c2w, est.scale), {"depth_poses": mode, "odometry_scale": est.scale,
                                         "depth_pose_votes": est.pairs, "depth_pose_note": est.note,
                                         "icp_max_depth_m": limit}
    if mode == "icp":
        poses, links, note = icp_trajectory(depths, intrinsics, c2w, **reach)
        return poses, {"depth_poses": mode, "odometry_scale": float("nan"), "depth_pose_votes": links,
                       "depth_pose_note": note, "icp_max_depth_m": limit}
    raise ValueError(f"unknown depth_poses mode {mode!r}; modes: ['off', 'scale', 'icp']")
