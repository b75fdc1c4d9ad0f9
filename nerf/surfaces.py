"""Fruit surfaces from un-projected pixels: the pixels of each label in one sort, robust centres, sphere fits and
their plausibility (used by the panoptic renders' 3D instance completion, panoptic_fusion and fruit_count)."""
from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares


def unproject(depth_m: np.ndarray, k: np.ndarray, c2w: np.ndarray | None, v: np.ndarray, u: np.ndarray
              ) -> np.ndarray:
    """World points [N, 3] of pixels (row v, column u) with z-depth `depth_m[v, u]` (pixel centres at
    half-integers, OpenCV camera: x right, y down, z forward). k = (fx, fy, cx, cy), c2w [4, 4]; None: the
    points in the camera frame."""
    z = depth_m[v, u].astype(np.float64)
    x = (u + 0.5 - k[2]) / k[0] * z
    y = (v + 0.5 - k[3]) / k[1] * z
    cam = np.stack([x, y, z], 1)                         # [N, 3]
    return cam if c2w is None else cam @ c2w[:3, :3].T + c2w[:3, 3]


def runs_by_key(v: np.ndarray, u: np.ndarray, key: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pixels (v, u) [N] sorted by `key` [N] (stable) and the runs of one key in that order: (v, u, key, starts,
    ends), run j being v[starts[j]:ends[j]] with key key[starts[j]]. The pixels of each label of an image, or of
    each pair of labels packed into one number, in one sort instead of one full-image mask per label."""
    order = np.argsort(key, kind="stable")
    v, u, key = v[order], u[order], key[order]
    if not len(key):
        return v, u, key, np.zeros(0, np.int64), np.zeros(0, np.int64)
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    return v, u, key, starts, np.r_[starts[1:], len(key)]


def robust_centre(points: np.ndarray, k_mad: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """Coordinate-wise median after dropping points whose distance to the median exceeds
    median + k_mad * 1.4826 * MAD of the distances. Returns (centre [3], inlier mask [N])."""
    med = np.median(points, 0)
    d = np.linalg.norm(points - med, axis=1)
    mad = 1.4826 * np.median(np.abs(d - np.median(d)))
    keep = d <= np.median(d) + k_mad * max(mad, 1e-4)
    return np.median(points[keep], 0), keep


def fit_sphere(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares sphere through points [N, 3] (N >= 4): the algebraic (Kasa) solution of
    |p|^2 = 2 c.p + (r^2 - |c|^2), refined by minimising the geometric residuals |p - c| - r with a soft-L1
    loss. Unlike extents, it recovers the full radius from a cap seen from one side. Returns (centre, r)."""
    p = np.asarray(points, np.float64)
    mu = p.mean(0)
    q = p - mu                                            # centred for conditioning
    a = np.c_[2 * q, np.ones(len(q))]
    sol, *_ = np.linalg.lstsq(a, (q ** 2).sum(1), rcond=None)
    c0, r0 = sol[:3], float(np.sqrt(max(sol[3] + sol[:3] @ sol[:3], 1e-12)))
    scale = max(float(np.median(np.linalg.norm(q - c0, axis=1))), 1e-6)

    def resid(x: np.ndarray) -> np.ndarray:
        return np.linalg.norm(q - x[:3], axis=1) - x[3]

    res = least_squares(resid, np.r_[c0, r0], loss="soft_l1", f_scale=0.1 * scale, max_nfev=50)
    return res.x[:3] + mu, abs(float(res.x[3]))


def principal_extents(points: np.ndarray) -> np.ndarray:
    """2.5-97.5 percentile ranges of the points along their principal axes, largest first [3]."""
    q = points - points.mean(0)
    _, vecs = np.linalg.eigh(np.cov(q.T))
    proj = q @ vecs
    ext = np.percentile(proj, 97.5, axis=0) - np.percentile(proj, 2.5, axis=0)
    return np.sort(ext)[::-1]


def plausible_fit(centre: np.ndarray, radius: float, median: np.ndarray, largest_extent: float,
                  max_radius_m: float, max_extent_ratio: float) -> bool:
    """A surface fit (sphere or spheroid: its largest semi-axis as `radius`) describes a fruit: finite, radius
    in (0, max_radius_m], centre within max_radius_m of the points' median (not a nearly flat patch), and
    diameter at most max_extent_ratio x the points' largest extent (not a whole fruit extrapolated from a
    small cap)."""
    return bool(np.all(np.isfinite(centre)) and 0 < radius <= max_radius_m
                and np.linalg.norm(centre - median) <= max_radius_m and 2 * radius <= max_extent_ratio * largest_extent)


def fruit_sphere(points: np.ndarray, max_radius_m: float, max_extent_ratio: float = 2.0, min_points: int = 4
                 ) -> tuple[np.ndarray, float, np.ndarray] | None:
    """(centre [3], radius, median [3]) of a least-squares sphere through the inliers of robust_centre of a
    fruit's seen surface points [N, 3], or None with fewer than min_points (at least 4) inliers or where the
    fit is not plausible_fit."""
    med, keep = robust_centre(points)
    inl = points[keep]
    if len(inl) < max(min_points, 4):
        return None
    c, r = fit_sphere(inl)
    return (c, r, med) if plausible_fit(c, r, med, principal_extents(inl)[0], max_radius_m, max_extent_ratio) else None
