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
