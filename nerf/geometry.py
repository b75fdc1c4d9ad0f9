"""Small rigid-body helpers (numpy and torch)."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def pose_matrix(txyzq: np.ndarray) -> np.ndarray:
    """[..., 7] tx ty tz qx qy qz qw -> [..., 4, 4]."""
    v = np.asarray(txyzq, np.float64)
    out = np.tile(np.eye(4), v.shape[:-1] + (1, 1))
    out[..., :3, :3] = Rotation.from_quat(v[..., 3:].reshape(-1, 4)).as_matrix().reshape(v.shape[:-1] + (3, 3))
    out[..., :3, 3] = v[..., :3]
    return out


def pose_txyzq(p: np.ndarray) -> np.ndarray:
    q = Rotation.from_matrix(p[..., :3, :3].reshape(-1, 3, 3)).as_quat()
    q[q[:, 3] < 0] *= -1
    return np.concatenate([p[..., :3, 3].reshape(-1, 3), q], 1)


def rotation_angle_deg(r_a: np.ndarray, r_b: np.ndarray) -> np.ndarray:
    """Geodesic angle between rotation matrices [..., 3, 3]."""
    rel = np.einsum("...ji,...jk->...ik", r_a, r_b)
    c = np.clip((np.trace(rel, axis1=-2, axis2=-1) - 1) / 2, -1, 1)
    return np.degrees(np.arccos(c))


def align_similarity(src: np.ndarray, dst: np.ndarray, src_rot: np.ndarray | None = None,
                     dst_rot: np.ndarray | None = None, *, with_scale: bool = True, position_weight: float = 1.0,
                     orientation_weight: float = 1.0) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) with dst_i ~ s R src_i + t and, where rotations are given, dst_rot_i ~ R src_rot_i.
    Points src, dst [N, 3]; rotations [N, 3, 3]. The one aligner of the project (trajectory errors, COLMAP
    poses onto odometry, windows onto each other, depth-derived tracks onto odometry).

    R maximises tr(R^T M) (Umeyama 1991, with orientations added), where
        M = position_weight * H / (sigma_s sigma_d) + orientation_weight * mean_i dst_rot_i src_rot_i^T,
        H = mean_i (dst_i - mu_d)(src_i - mu_s)^T,  sigma = RMS distance to the centroid,
    so both terms are unitless. Camera centres along a straight row are nearly collinear and leave the
    rotation about that line free; the orientation term pins it (orientation_weight alone gives the chordal
    mean rotation). With M = U D V^T:
        R = U diag(1, 1, det(U V^T)) V^T,  s = sum_i (dst_i - mu_d) . R (src_i - mu_s) / sum_i |src_i - mu_s|^2
    (s = 1 without with_scale), t = mean_i (dst_i - s R src_i). Rotations count only where both are given.
    Example: src = dst gives s = 1, R = I, t = 0.

    Raises ValueError for mismatched shapes, fewer than 2 points, and (with_scale) coincident points or a
    non-positive scale: the scale is undetermined then."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    need = 2 if with_scale or position_weight > 0 else 1   # one pose fixes a rotation, not a scale
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < need:
        raise ValueError(f"align_similarity needs two [N >= {need}, 3] point sets, got {src.shape} and {dst.shape}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    m = np.zeros((3, 3))
    if position_weight > 0:
        sig = np.sqrt((xs ** 2).sum(1).mean() * (xd ** 2).sum(1).mean())
        m = m + position_weight * (xd.T @ xs / len(src)) / (sig if sig > 0 else 1.0)
    if src_rot is not None and dst_rot is not None and orientation_weight > 0:
        if np.shape(src_rot) != (len(src), 3, 3) or np.shape(dst_rot) != (len(src), 3, 3):
            raise ValueError(f"align_similarity: rotations must be [{len(src)}, 3, 3], got {np.shape(src_rot)} "
                             f"and {np.shape(dst_rot)}")
        m = m + orientation_weight * np.einsum("nij,nkj->ik", dst_rot, src_rot) / len(src)
    u, _, vt = np.linalg.svd(m)
    r = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt)) or 1.0]) @ vt
    s = 1.0
    if with_scale:
        var = float((xs ** 2).sum())
        if not var > 0 or not (xd ** 2).sum() > 0:
            raise ValueError("align_similarity: the points coincide, so the scale is undetermined")
        s = float((xd * (xs @ r.T)).sum() / var)
        if not s > 0:
            raise ValueError(f"align_similarity: non-positive scale {s} (the point sets do not correspond)")
    return s, r, (dst - s * src @ r.T).mean(0)


def similarity_matrix(s: float, r: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The [4, 4] matrix of x -> s R x + t."""
    out = np.eye(4)
    out[:3, :3] = s * np.asarray(r)
    out[:3, 3] = t
    return out


def apply_similarity(s: float, r: np.ndarray, t: np.ndarray, c2w: np.ndarray) -> np.ndarray:
    """Camera-to-world poses [N, 4, 4] moved by x -> s R x + t: rotation R c2w_R, centre s R c + t (the
    camera keeps its own unit scale, unlike similarity_matrix(s, r, t) @ c2w)."""
    out = np.array(c2w, np.float64, copy=True)
    out[:, :3, :3] = r @ c2w[:, :3, :3]
    out[:, :3, 3] = s * c2w[:, :3, 3] @ r.T + t
    return out
