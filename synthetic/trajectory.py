"""Ground-truth robot trajectory along the row and the drifting odometry a real robot would report."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

# Camera optical frame (x right, y down, z forward) looking at the plants (+y), seen from base_link.
R_BASE_CAMERA = np.stack([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]], 1)


def camera_extrinsic(height_m: float, lateral_m: float = 0.1) -> np.ndarray:
    """T_robot_camera: camera-to-robot 4x4 for a camera on a mast looking left (+y)."""
    t = np.eye(4)
    t[:3, :3] = R_BASE_CAMERA
    t[:3, 3] = [0.0, lateral_m, height_m]
    return t


def se2_to_se3(x: np.ndarray, y: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """[K] planar poses -> [K, 4, 4] base-to-world."""
    out = np.tile(np.eye(4), (len(x), 1, 1))
    c, s = np.cos(yaw), np.sin(yaw)
    out[:, 0, 0], out[:, 0, 1], out[:, 1, 0], out[:, 1, 1] = c, -s, s, c
    out[:, 0, 3], out[:, 1, 3] = x, y
    return out


@dataclass(frozen=True)
class Trajectories:
    stamps_ns: np.ndarray
    """[K] odometry sample times."""
    gt_base: np.ndarray
    """[K, 4, 4] true base-to-world."""
    odom_base: np.ndarray
    """[K, 4, 4] odometry base-to-world (drifting)."""


def make_trajectories(t0_ns: int, duration_s: float, rate_hz: float, speed_m_per_s: float, x0_m: float,
                      drift_m_per_m: float, yaw_drift_deg_per_m: float, noise_m: float,
                      rng: np.random.Generator) -> Trajectories:
    """Straight drive along +x with a slight lateral and heading wobble; odometry integrates the true
    increments with a scale error (drift_m_per_m), a heading error growing with distance
    (yaw_drift_deg_per_m) and a random walk (noise_m per sqrt(m)); equal to the truth at t0."""
    n = int(np.ceil(duration_s * rate_hz)) + 1
    stamps = t0_ns + np.round(np.arange(n) * 1e9 / rate_hz).astype(np.int64)
    t = (stamps - t0_ns) / 1e9
    phase = rng.uniform(0, 2 * np.pi, 2)
    x = x0_m + speed_m_per_s * t
    y = 0.008 * np.sin(2 * np.pi * t / 7.0 + phase[0])
    yaw = np.radians(0.6) * np.sin(2 * np.pi * t / 5.0 + phase[1])
    gt = se2_to_se3(x, y, yaw)
    # odometry: integrate body-frame increments with errors
    dx_w, dy_w = np.diff(x), np.diff(y)
    dyaw = np.diff(yaw)
    c, s = np.cos(yaw[:-1]), np.sin(yaw[:-1])
    fwd, lat = c * dx_w + s * dy_w, -s * dx_w + c * dy_w
    step = np.hypot(fwd, lat)
    sign = rng.choice([-1.0, 1.0], 2)
    fwd_o = fwd * (1 + sign[0] * drift_m_per_m)
    yaw_err = sign[1] * np.radians(yaw_drift_deg_per_m) * step + rng.normal(0, np.radians(0.02), len(step)) * np.sqrt(step / 0.01)
    yaw_o = np.concatenate([[yaw[0]], yaw[0] + np.cumsum(dyaw + yaw_err)])
    co, so = np.cos(yaw_o[:-1]), np.sin(yaw_o[:-1])
    walk = rng.normal(0, noise_m, (len(step), 2)) * np.sqrt(step / 1.0)[:, None]
    xo = np.concatenate([[x[0]], x[0] + np.cumsum(co * fwd_o - so * lat + walk[:, 0])])
    yo = np.concatenate([[y[0]], y[0] + np.cumsum(so * fwd_o + co * lat + walk[:, 1])])
    return Trajectories(stamps, gt, se2_to_se3(xo, yo, yaw_o))


def interpolate(stamps_ns: np.ndarray, poses: np.ndarray, at_ns: np.ndarray) -> np.ndarray:
    """Poses [K, 4, 4] sampled at stamps -> [M, 4, 4] at `at_ns` (linear + slerp)."""
    from scipy.spatial.transform import Slerp

    t = (stamps_ns - stamps_ns[0]) / 1e9
    q = (at_ns - stamps_ns[0]) / 1e9
    rot = Slerp(t, Rotation.from_matrix(poses[:, :3, :3]))(q).as_matrix()
    out = np.tile(np.eye(4), (len(q), 1, 1))
    out[:, :3, :3] = rot
    for i in range(3):
        out[:, i, 3] = np.interp(q, t, poses[:, i, 3])
    return out


def to_txyzq(poses: np.ndarray) -> np.ndarray:
    """[K, 4, 4] -> [K, 7] tx, ty, tz, qx, qy, qz, qw (scalar last, qw >= 0)."""
    q = Rotation.from_matrix(poses[:, :3, :3]).as_quat()
    q[q[:, 3] < 0] *= -1
    return np.concatenate([poses[:, :3, 3], q], 1)
